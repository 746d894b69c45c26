import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # tests/mitsuba_ref.py and friends
# one torch thread a pytest-xdist worker (`pytest -n 2`: a worker a core), else both cores; set
# before any test module imports torch, and inherited by the CLI subprocesses the tests start
os.environ.setdefault("OMP_NUM_THREADS", "1" if os.environ.get("PYTEST_XDIST_WORKER") else "2")

SHARED = Path(__file__).resolve().parents[2] / "shared"  # ../shared beside the repository


@pytest.fixture(scope="session")
def shared_envmaps() -> list[Path]:
    maps = sorted((SHARED / "envmaps").glob("*.hdr"))
    if not maps:
        pytest.skip("../shared/envmaps not found")
    return maps


@pytest.fixture(scope="session")
def torus_run(tmp_path_factory) -> Path:
    """ROOT with gt.ply, env.hdr and scene/ (`cli_helpers.render_torus_scene`: a 10-view 120x90
    capture of a tilted torus) and out/: `lookingglass reconstruct scene --out out` with the
    defaults, run once for the session (tests/test_cli.py and tests/test_report.py read it; a test
    that changes anything in it works on a copy)."""
    from cli_helpers import render_torus_scene, run

    root = tmp_path_factory.mktemp("torus")
    render_torus_scene(root)
    run("reconstruct", root / "scene", "--out", root / "out", "--quiet")
    return root
