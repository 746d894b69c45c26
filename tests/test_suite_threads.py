"""The test suite's own thread budget (tests/conftest.py): under `pytest -n 2` each worker runs one
thread of torch, OpenMP and BLAS, not the two the controller process sets for itself. With two each,
4 threads spun on the 2 cores and the suite took twice as long (some tests 10x their time alone)."""

import os

import pytest
import torch

from lookingglass.parallel import THREAD_VARIABLES


def test_a_pytest_worker_runs_one_thread():
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        pytest.skip("not a pytest-xdist worker (pytest -n 0)")
    assert {v: os.environ.get(v) for v in THREAD_VARIABLES} == {v: "1" for v in THREAD_VARIABLES}
    assert torch.get_num_threads() == 1
