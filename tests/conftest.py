import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # tests/mitsuba_ref.py and friends
os.environ.setdefault("OMP_NUM_THREADS", "2")

SHARED = Path(__file__).resolve().parents[2] / "shared"  # ../shared beside the repository


@pytest.fixture(scope="session")
def shared_envmaps() -> list[Path]:
    maps = sorted((SHARED / "envmaps").glob("*.hdr"))
    if not maps:
        pytest.skip("../shared/envmaps not found")
    return maps
