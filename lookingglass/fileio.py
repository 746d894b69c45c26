"""Atomic file writing: an interrupted run never leaves a half-written file that looks finished.

`write_atomic` / `atomic_path` do it for one file, `staged_dir` for a command's whole output
folder (written into a temporary folder beside it and renamed into place when finished).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from .errors import Interrupted, LookingGlassError


_UMASK_LOCK = threading.Lock()


def _umask() -> int:
    """The process's umask, read without changing it where the system allows.

    Linux (4.7+) reports it in /proc/self/status: a plain read, safe with threads. Elsewhere it can
    only be read by setting it and setting it back; the lock keeps two of our own threads from
    interleaving (which could leave the wrong umask behind), but a file another thread creates in
    that instant gets the temporary umask 0o077: private rather than too open.
    """
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        old = os.umask(0o077)
        os.umask(old)
    return old


def usual_mode(directory: bool = False) -> int:
    """The mode open() / mkdir() give a new file / folder: 0o666 / 0o777 less the umask.

    For files and folders made by `tempfile` (mode 0o600 / 0o700, private) that become outputs.
    """
    return (0o777 if directory else 0o666) & ~_umask()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it onto `path` only if the block succeeds.

    The temporary name keeps the suffix of `path` so writers that pick a format by extension
    (OpenCV, trimesh) still work. The file gets the usual mode (`usual_mode`), not mkstemp's 0o600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # after the writer, in case it replaced the file rather than writing into it
        os.chmod(tmp_path, usual_mode())
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def resolved_path(path: str | os.PathLike) -> Path:
    """`path` made absolute with its symbolic links followed; a LookingGlassError naming it for a
    link loop (Path.resolve raises RuntimeError or OSError there)."""
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError) as exc:
        raise LookingGlassError(f"cannot follow the path ({exc}): a loop of symbolic links?", path) from None


def within(path: str | os.PathLike, folder: str | os.PathLike) -> bool:
    """Whether `path` is `folder` or lies inside it, symbolic links followed (neither need exist)."""
    inner, outer = resolved_path(path), resolved_path(folder)
    return inner == outer or outer in inner.parents


def check_output_dir(out: str | os.PathLike, force: bool, inputs: Iterable[str | os.PathLike] = ()) -> None:
    """Refuse, before any work starts, an output folder that a run could not write or must not
    replace (LookingGlassError naming it): a path that exists and is not a folder; a non-empty
    folder without `force`; a folder that is, or holds, one of `inputs` (files or folders: replacing
    it would delete the input); a folder (or, when it does not exist yet, its nearest existing
    parent) that is not a folder or that this process may not write. Missing parents are fine:
    `staged_dir` makes them."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise LookingGlassError("output path exists and is not a folder", out)
    resolved = resolved_path(out)
    for p in inputs:
        if within(p, out):
            raise LookingGlassError(f"output folder would replace the input {p}", out)
    if out.is_dir():
        if any(out.iterdir()) and not force:
            raise LookingGlassError("output folder is not empty (use --force to replace it)", out)
        if not os.access(out, os.W_OK | os.X_OK):
            raise LookingGlassError("output folder is not writable", out)
    parent = resolved.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise LookingGlassError(f"cannot create the output folder: {parent} is not a folder", out)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise LookingGlassError(f"cannot create the output folder: {parent} is not writable", out)


# errors of writing (a full disk, a folder made read-only meanwhile...): said in one line, not a traceback
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS, errno.EIO}


@contextlib.contextmanager
def staged_dir(out: str | os.PathLike, force: bool = False, doing: str = "",
               inputs: Iterable[str | os.PathLike] = ()) -> Iterator[Path]:
    """Yield a fresh, empty temporary folder beside `out` to write a command's whole output into;
    when the block finishes, rename it onto `out` (with `force`, a non-empty `out` is replaced whole
    at that moment, never mixed with the new files).

    Checked first with `check_output_dir(out, force, inputs)`. When the block fails or is
    interrupted, the temporary folder (and any missing parent folder made for it) is removed and
    `out` is as it was: no partial result is left. A Ctrl-C comes out as `Interrupted`, saying
    `doing` (what was running, e.g. "reconstruct") and that nothing was left; a failed write (disk
    full, permissions) as a one-line LookingGlassError. The folder gets the usual mode, not
    mkdtemp's private 0o700.
    """
    out = Path(out)
    check_output_dir(out, force, inputs)
    existed = out.exists()
    parent = Path(os.path.abspath(out)).parent
    made = []  # parent folders this call creates, deepest first
    p = parent
    while not p.exists() and p != p.parent:
        made.append(p)
        p = p.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=parent))
        os.chmod(tmp, usual_mode(directory=True))
    except OSError as exc:
        _remove_empty(made)
        raise LookingGlassError(f"cannot create the output folder ({exc.strerror})", out) from None
    backup = None
    try:
        yield tmp
        backup = _move_into_place(tmp, out, force)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty(made)
        if isinstance(exc, KeyboardInterrupt):
            inner = exc.doing if isinstance(exc, Interrupted) else ""
            state = f"{out} is unchanged" if existed else f"{out} was not created"
            raise Interrupted(", ".join(s for s in (doing, inner) if s),
                              f"no partial result was left ({state})") from None
        if isinstance(exc, OSError) and not isinstance(exc, LookingGlassError) and exc.errno in _WRITE_ERRNOS:
            where = exc.filename or out
            # a file outside the output being written was being read (an input the run may not open)
            writing = not exc.filename or Path(os.path.abspath(exc.filename)).is_relative_to(tmp.absolute()) \
                or Path(os.path.abspath(exc.filename)) == Path(os.path.abspath(out))
            raise LookingGlassError(f"cannot {'write' if writing else 'read'} ({exc.strerror}); no partial result was "
                                    "left", where) from None
        raise
    if backup is not None:  # the old folder, replaced: out is finished whatever happens here
        shutil.rmtree(backup, ignore_errors=True)


def _move_into_place(tmp: Path, out: Path, force: bool) -> Path | None:
    """Rename the finished folder `tmp` onto `out`. A non-empty `out` (refused unless force) is
    first renamed to a hidden backup beside it, put back if the second rename fails; returns that
    backup folder (for the caller to delete), or None."""
    if not (out.exists() or out.is_symlink()):
        os.replace(tmp, out)
        return None
    if out.is_dir() and not out.is_symlink() and not any(out.iterdir()):
        os.replace(tmp, out)  # rename(2) replaces an empty folder
        return None
    if not force:  # something was written there while this run worked
        raise LookingGlassError("output folder is not empty (use --force to replace it)", out)
    backup = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=tmp.parent))
    os.replace(out, backup / out.name)
    try:
        os.replace(tmp, out)
    except BaseException:
        os.replace(backup / out.name, out)
        shutil.rmtree(backup, ignore_errors=True)
        raise
    return backup


def _remove_empty(folders: list[Path]) -> None:
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            break


def write_atomic(path: str | os.PathLike, writer: Callable[[Path], Any]) -> Path:
    """Call `writer(tmp_path)` and move the result onto `path` atomically."""
    with atomic_path(path) as tmp:
        writer(tmp)
    return Path(path)


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes (provenance of weights), read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_json(path: str | os.PathLike, what: str = "JSON file") -> Any:
    """The JSON in `path`; a file that cannot be read or parsed is a LookingGlassError naming it
    (`what` says what the file is meant to be)."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise LookingGlassError(f"cannot read the {what} ({exc})", path) from None


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write `data` as indented JSON, atomically."""
    text = json.dumps(data, indent=2, sort_keys=False, default=_json_default) + "\n"
    return write_atomic(path, lambda p: p.write_text(text))


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")
