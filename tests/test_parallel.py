"""lookingglass.parallel: results from worker processes, and a failing task or initializer raised in
the caller at once, without waiting for the other workers (multiprocessing.Pool's terminate could
deadlock there, which hung an evaluation in CI)."""

import os
import time

import pytest

from lookingglass.errors import LookingGlassError
from lookingglass.parallel import THREAD_VARIABLES, map_in_processes

SLOW = 60.0  # seconds a task sleeps that the caller must not wait for


def square(x: int) -> int:
    return x * x


def fail_on_three(x: int) -> int:
    if x == 3:
        raise LookingGlassError("task three failed", "scene_0003")
    if x > 3:
        time.sleep(SLOW)
    return x


def die_on_two(x: int) -> int:
    if x == 2:
        os._exit(9)  # as if killed (out of memory) or crashed: no exception to send back
    return x


def refuse_to_start() -> None:
    raise LookingGlassError("network config not found beside the weights", "w.json")


def test_every_result_comes_back_and_the_thread_settings_are_restored():
    before = {v: os.environ.get(v) for v in THREAD_VARIABLES}
    assert sorted(map_in_processes(square, range(25), 2)) == [x * x for x in range(25)]
    assert {v: os.environ.get(v) for v in THREAD_VARIABLES} == before


def test_a_failing_task_is_raised_without_waiting_for_the_others():
    start = time.monotonic()
    with pytest.raises(LookingGlassError, match="scene_0003: task three failed"):
        list(map_in_processes(fail_on_three, range(10), 2))
    assert time.monotonic() - start < SLOW / 2  # the sleeping workers were killed, not joined


def test_a_failing_initializer_is_raised_once():
    with pytest.raises(LookingGlassError, match="w.json: network config not found"):
        list(map_in_processes(square, range(6), 2, refuse_to_start))


def test_a_caller_that_stops_early_leaves_no_worker_behind():
    import multiprocessing

    results = map_in_processes(square, range(40), 2)
    assert next(results) in {x * x for x in range(40)}
    results.close()
    deadline = time.monotonic() + 10
    while multiprocessing.active_children() and time.monotonic() < deadline:  # reaps the killed ones
        time.sleep(0.05)
    assert multiprocessing.active_children() == []


def test_a_worker_that_dies_is_a_clear_error_not_a_hang():
    with pytest.raises(LookingGlassError, match="worker process stopped abruptly .* --workers 1"):
        list(map_in_processes(die_on_two, range(6), 2))
