"""Progress on the terminal (rich, to stderr) and per-stage timing, silenced by --quiet."""

from __future__ import annotations

import contextlib
import resource
import sys
import time
from typing import Iterable, Iterator, TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from .errors import Interrupted

T = TypeVar("T")


# A Ctrl-C that arrived while a C library was calling back into Python (ctypes callbacks, e.g. the
# rtree index trimesh builds in the surface stage) is printed and dropped by the interpreter as
# "unraisable"; the hook notes it instead, and the running stage or loop raises it (`raise_pending_interrupt`).
_interrupt_pending = False


def _note_unraisable_interrupt(unraisable) -> None:
    """sys.unraisablehook: remember a swallowed KeyboardInterrupt quietly; anything else as usual."""
    global _interrupt_pending
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        _interrupt_pending = True
        return
    sys.__unraisablehook__(unraisable)


def install_interrupt_hook() -> None:
    """Make a Ctrl-C that a C callback swallowed stop the command at the end of its stage (the CLI
    installs it; a library user's interpreter is left alone)."""
    sys.unraisablehook = _note_unraisable_interrupt


def raise_pending_interrupt() -> None:
    """Raise the KeyboardInterrupt a C callback swallowed, if one did (once)."""
    global _interrupt_pending
    if _interrupt_pending:
        _interrupt_pending = False
        raise KeyboardInterrupt


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far, in MiB (Linux reports ru_maxrss in KiB)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024.0 if sys.platform != "darwin" else rss / 2**20


def _stoppable(items: Iterable[T]) -> Iterator[T]:
    for item in items:
        raise_pending_interrupt()
        yield item


class Reporter:
    """Times named stages and shows progress; `quiet=True` prints nothing (for scripts)."""

    def __init__(self, quiet: bool = False):
        self.quiet = quiet
        self.console = Console(stderr=True, quiet=quiet)
        self.stages: list[dict] = []

    def info(self, message: str) -> None:
        self.console.print(message)

    def warn(self, message: str) -> None:
        self.console.print(f"[yellow]warning:[/yellow] {message}")

    @contextlib.contextmanager
    def stage(self, name: str, description: str | None = None) -> Iterator[dict]:
        """Time a pipeline stage. The yielded dict collects the stage's figures for the report.
        A Ctrl-C in the stage comes out as `Interrupted`, naming the stage."""
        record: dict = {"name": name}
        start = time.perf_counter()
        try:
            with self.console.status(f"{description or name} ..."):
                yield record
                raise_pending_interrupt()
        except KeyboardInterrupt as exc:
            if isinstance(exc, Interrupted):
                raise
            raise Interrupted(f"in the {name} stage") from None
        record["seconds"] = round(time.perf_counter() - start, 3)
        record["peak_memory_mb"] = round(peak_memory_mb(), 1)
        self.stages.append(record)
        self.console.print(f"[green]✓[/green] {description or name} [dim]({record['seconds']:.2f} s)[/dim]")

    def track(self, items: Iterable[T], total: int | None = None, description: str = "") -> Iterator[T]:
        """Iterate with a progress bar (with counts and ETA); a swallowed Ctrl-C
        (`raise_pending_interrupt`) stops the loop at the next item."""
        if total is None and not self.quiet:
            total = len(items)  # type: ignore[arg-type]
        items = _stoppable(items)
        if self.quiet:
            yield from items
            return
        if not self.console.is_terminal:  # a log file or a batch job: plain lines, not a live bar
            yield from self._track_lines(items, total, description)
            return
        columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                   TimeElapsedColumn(), TimeRemainingColumn())
        with Progress(*columns, console=self.console, transient=False) as bar:
            task = bar.add_task(description, total=total)
            for item in items:
                yield item
                bar.advance(task)

    def _track_lines(self, items: Iterable[T], total: int, description: str,
                     every_seconds: float = 30.0) -> Iterator[T]:
        """One line at every 10% and at least every `every_seconds`, with elapsed time and ETA."""
        start = last = time.perf_counter()
        step = max(1, total // 10)
        for done, item in enumerate(items, 1):
            yield item
            now = time.perf_counter()
            if done == total or done % step == 0 or now - last >= every_seconds:
                last = now
                eta = (now - start) / done * (total - done)
                self.console.print(f"{description}: {done}/{total} ({now - start:.0f} s, ~{eta:.0f} s left)")
