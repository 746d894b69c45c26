"""Independent work items (scenes) spread over spawned worker processes, shared by `generate`
and the evaluations."""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any

_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _init_worker(initializer: Callable[..., None] | None, initargs: tuple) -> None:
    import signal
    import warnings

    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the parent stops the pool, quietly
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")  # callers record what matters in their results
    if initializer is not None:
        initializer(*initargs)


def map_in_processes(func: Callable[[Any], Any], tasks: Iterable, workers: int,
                     initializer: Callable[..., None] | None = None, initargs: tuple = ()) -> Iterator[Any]:
    """Yield func(task) for every task, in the order they finish, from `workers` spawned processes
    with one torch / BLAS / OpenMP thread each; `initializer(*initargs)` runs once per process
    (e.g. to load networks). func and initializer must be module-level (picklable).

    Spawn, not fork: forking after torch or OpenMP started can hang. The thread variables are
    set before the children import anything and restored when the generator ends or is closed."""
    saved = {v: os.environ.get(v) for v in _THREAD_VARIABLES}
    os.environ.update({v: "1" for v in saved})
    try:
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(workers, initializer=_init_worker, initargs=(initializer, initargs)) as pool:
            yield from pool.imap_unordered(func, tasks, chunksize=1)
    finally:
        for v, old in saved.items():
            if old is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = old


def worker_count(workers: int | None, tasks: int) -> int:
    """workers None or 0: one per CPU core; never more than there are tasks (at least 1)."""
    workers = workers or os.cpu_count() or 1
    return max(1, min(workers, tasks))
