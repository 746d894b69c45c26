"""Torch intra-op thread settings for a block of work, shared by the hull and the renderer."""

from __future__ import annotations

import contextlib
import os
from typing import Iterator

import torch


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with n torch intra-op threads, then restore the previous setting.

    n > 0: exactly n; n = 0: half the machine's cores (at least 1, at most torch's current
    setting); n < 0: leave torch's setting alone. Why half: on the 2-core machine with other jobs
    running, 2 threads made the carve 5x slower than 1 (every op waits at a barrier for a thread
    the OS has descheduled), while on an idle machine 2 threads gained only ~20%.
    """
    if n == 0:
        n = max(1, min(torch.get_num_threads(), (os.cpu_count() or 2) // 2))
    if n < 0:
        yield
        return
    with _torch_setting(torch.get_num_threads, torch.set_num_threads, n):
        yield


@contextlib.contextmanager
def _torch_setting(get, put, value) -> Iterator[None]:
    """Run the block with a torch setting (read by `get`, written by `put`) at `value`, then restore it."""
    old = get()
    if value == old:
        yield
        return
    put(value)
    try:
        yield
    finally:
        put(old)
