"""lookingglass.parallel: results from worker processes, and a failing task or initializer raised in
the caller at once, the other workers killed rather than waited for (multiprocessing.Pool's terminate
could deadlock there, which hung an evaluation in CI)."""

import multiprocessing
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


def sleep_after_the_first(x: int) -> int:
    if x > 0:
        time.sleep(SLOW)
    return x


def die_on_two(x: int) -> int:
    if x == 2:
        os._exit(9)  # as if killed (out of memory) or crashed: no exception to send back
    return x


def refuse_to_start() -> None:
    raise LookingGlassError("network config not found beside the weights", "w.json")


def no_workers_left(timeout: float = 10.0) -> bool:
    """Whether every child process has ended (active_children reaps the killed ones) within timeout."""
    deadline = time.monotonic() + timeout
    while multiprocessing.active_children() and time.monotonic() < deadline:
        time.sleep(0.05)
    return not multiprocessing.active_children()


def test_every_result_comes_back_and_the_thread_settings_are_restored(monkeypatch):
    monkeypatch.setenv(THREAD_VARIABLES[0], "3")
    monkeypatch.delenv(THREAD_VARIABLES[1], raising=False)
    before = {v: os.environ.get(v) for v in THREAD_VARIABLES}
    assert sorted(map_in_processes(square, range(25), 2)) == [x * x for x in range(25)]
    assert {v: os.environ.get(v) for v in THREAD_VARIABLES} == before


def test_a_failing_task_is_raised_and_the_other_workers_killed():
    start = time.monotonic()
    with pytest.raises(LookingGlassError, match="scene_0003: task three failed"):
        list(map_in_processes(fail_on_three, range(10), 2))
    assert no_workers_left() and time.monotonic() - start < SLOW / 2  # the sleeping workers were killed


def test_a_failing_initializer_is_raised_once():
    with pytest.raises(LookingGlassError, match="w.json: network config not found"):
        list(map_in_processes(square, range(6), 2, refuse_to_start))
    assert no_workers_left()


def test_a_caller_that_stops_early_leaves_no_worker_behind():
    start = time.monotonic()
    results = map_in_processes(sleep_after_the_first, range(40), 2)
    assert next(results) == 0
    results.close()  # the other worker is asleep in its task: killed, not joined
    assert no_workers_left() and time.monotonic() - start < SLOW / 2


def test_a_worker_that_dies_is_a_clear_error_not_a_hang():
    with pytest.raises(LookingGlassError, match="worker process stopped abruptly .* --workers 1"):
        list(map_in_processes(die_on_two, range(6), 2))
    assert no_workers_left()


def _make_mesh(holder: list) -> None:
    import weakref

    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2)  # its helpers point back at it: a reference cycle
    holder.append(weakref.ref(mesh))


def test_run_and_collect_frees_a_scenes_meshes_at_once():
    """A trimesh.Trimesh is a reference cycle: without a full collection it outlives the scene that
    made it (with automatic collections off, as they effectively are in a process holding many
    long-lived objects), and a long loop of scenes grows until it is killed."""
    import gc

    from lookingglass.parallel import run_and_collect

    was_enabled = gc.isenabled()
    gc.disable()
    try:
        plain, collected = [], []
        _make_mesh(plain)
        assert plain[0]() is not None  # the premise: the cycle survives its scene
        run_and_collect(_make_mesh, collected)
        assert collected[0]() is None and plain[0]() is None
    finally:
        if was_enabled:
            gc.enable()
        gc.collect()
