"""Independent work items (scenes) spread over spawned worker processes, shared by `generate`
and the evaluations."""

from __future__ import annotations

import gc
import itertools
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from .errors import LookingGlassError

# what sizes the thread pools of torch, OpenMP and the BLAS libraries (tests/conftest.py sets them too)
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _init_worker(initializer: Callable[..., None] | None, initargs: tuple) -> None:
    import signal
    import warnings

    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the parent stops the pool, quietly
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")  # callers record what matters in their results
    if initializer is not None:
        try:
            initializer(*initargs)
        except Exception as error:  # noqa: BLE001 - re-raised by every task, so it reaches the caller
            # Raised here, it would break the pool with a bare BrokenProcessPool (multiprocessing.Pool:
            # respawn the worker forever); kept, every task re-raises it with its message.
            global _INIT_ERROR
            _INIT_ERROR = error


_INIT_ERROR: Exception | None = None  # what this worker's initializer raised


def _run_task(func: Callable[[Any], Any], task: Any) -> Any:
    if _INIT_ERROR is not None:
        raise _INIT_ERROR
    return run_and_collect(func, task)


def run_and_collect(func: Callable[[Any], Any], task: Any) -> Any:
    """func(task) (one scene's work), then a full garbage collection. Every trimesh.Trimesh is a
    reference cycle (its ray, proximity and visual helpers point back at it) that keeps its arrays,
    caches and Embree scene alive until a full collection, and in a process that holds many
    long-lived objects Python runs those rarely: a loop over scenes grew ~30 MB a scene without
    one (train-points' features, `generate`: killed for memory after a few hundred scenes), and
    held ~0.5 GB with it."""
    try:
        return func(task)
    finally:
        gc.collect()


def map_in_processes(func: Callable[[Any], Any], tasks: Iterable, workers: int,
                     initializer: Callable[..., None] | None = None, initargs: tuple = ()) -> Iterator[Any]:
    """Yield func(task) for every task, in the order they finish, from `workers` spawned processes
    with one torch / BLAS / OpenMP thread each; `initializer(*initargs)` runs once per process
    (e.g. to load networks). func and initializer must be module-level (picklable). A task's error
    is raised here; the other workers are then killed, not waited for.

    Spawn, not fork: forking after torch or OpenMP started can hang. concurrent.futures, not
    multiprocessing.Pool: Pool.terminate() can deadlock when a task fails (CPython issues 96995,
    78178), which hung an evaluation in CI. At most two tasks per worker are queued, so a long
    task list costs no memory. The thread variables are set before the children import anything
    and restored when the generator ends or is closed."""
    saved = {v: os.environ.get(v) for v in THREAD_VARIABLES}
    os.environ.update({v: "1" for v in saved})
    executor = None
    finished = False
    try:
        executor = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                       initializer=_init_worker, initargs=(initializer, initargs))
        todo = iter(tasks)
        running: set = set()
        try:
            while True:
                for task in itertools.islice(todo, max(0, 2 * workers - len(running))):
                    running.add(executor.submit(_run_task, func, task))
                if not running:
                    break
                done, running = wait(running, return_when=FIRST_COMPLETED)
                for future in done:
                    yield future.result()
        except BrokenProcessPool:  # killed (out of memory?) or crashed: not a task's own error
            raise LookingGlassError("a worker process stopped abruptly (killed, out of memory or crashed); rerun "
                                    "with --workers 1 to see why") from None
        finished = True
    finally:
        if executor is not None and finished:
            executor.shutdown(wait=True)
        elif executor is not None:  # an error, Ctrl-C or a caller that stopped early: stop the workers now
            processes = list((getattr(executor, "_processes", None) or {}).values())
            executor.shutdown(wait=False, cancel_futures=True)
            for process in processes:  # Python 3.14 has executor.terminate_workers() for this
                process.kill()
        for v, old in saved.items():
            if old is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = old


def map_scenes(evaluation_class: Callable[..., Any], args: tuple, indices: list[int], workers: int,
               device: str = "cpu") -> Iterator[Any]:
    """Yield evaluation_class(*args, device=device).scene(i) for every scene index: in this process
    in order when one worker is asked for (or `device` is not the CPU), else from `workers` spawned
    processes (see worker_count; 0: one per core) that each build the object once, in the order the
    scenes finish. evaluation_class must be module-level (picklable). The object is built here
    first either way, so bad inputs (weights without their config...) fail once, in this process,
    before any worker starts."""
    workers = 1 if device != "cpu" else worker_count(workers, len(indices))
    evaluation = evaluation_class(*args, device=device)
    if workers == 1:
        return (run_and_collect(evaluation.scene, i) for i in indices)
    del evaluation
    return map_in_processes(_scene_in_worker, indices, workers, _start_scene_worker, (evaluation_class, args))


_WORKER_EVALUATION: Any = None  # the object map_scenes built in this worker process


def _start_scene_worker(evaluation_class: Callable[..., Any], args: tuple) -> None:
    global _WORKER_EVALUATION
    _WORKER_EVALUATION = evaluation_class(*args)


def _scene_in_worker(i: int) -> Any:
    return _WORKER_EVALUATION.scene(i)


def worker_count(workers: int | None, tasks: int) -> int:
    """workers None or 0: one per CPU core; never more than there are tasks (at least 1)."""
    workers = workers or os.cpu_count() or 1
    return max(1, min(workers, tasks))
