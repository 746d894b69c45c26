import os
import shutil
import sys
from pathlib import Path

import pytest

from lookingglass.parallel import THREAD_VARIABLES  # starts no thread pool

sys.path.insert(0, str(Path(__file__).parent))  # tests/mitsuba_ref.py and friends
# One thread a pytest-xdist worker (`pytest -n 2`: a worker a core), else both cores; set before
# any test module imports torch (or numpy's OpenBLAS), and inherited by the CLI subprocesses the
# tests start. A worker overrides what it inherits: the controller, which imports this file first
# and is no worker, would otherwise hand both workers 2 threads each, and 4 threads spinning on 2
# cores made some tests 10x slower than alone (the suite took 16-22 min instead of ~8).
for variable in THREAD_VARIABLES:
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ[variable] = "1"
    else:
        os.environ.setdefault(variable, "2")

SHARED = Path(__file__).resolve().parents[2] / "shared"  # ../shared beside the repository


@pytest.fixture(autouse=True)
def seeded_generators():
    """Every test draws the same numbers from torch's and numpy's global generators whichever tests ran
    before it in its worker (pytest-xdist deals tests out differently from run to run)."""
    import numpy as np
    import torch

    torch.manual_seed(0)
    np.random.seed(0)


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
    defaults, run once for the whole test run: the pytest-xdist workers share it through a file
    lock (each worker running its own made the two runs contend for the cores; alone it takes
    ~80 s, ~95 s in the suite).
    tests/test_cli.py and tests/test_report.py read it; a test that changes anything in it works on
    a copy."""
    from filelock import FileLock

    from cli_helpers import render_torus_scene, run

    # the workers' base temp dirs share a parent; without xdist it is this run's own
    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = shared.parent
    root = shared / "torus"
    with FileLock(str(shared / "torus.lock")):
        if not (root / "done").exists():
            if root.exists():  # a run that failed part-way: start again
                shutil.rmtree(root)
            root.mkdir()
            render_torus_scene(root)
            run("reconstruct", root / "scene", "--out", root / "out", "--quiet", timeout=1200)
            (root / "done").touch()
    return root
