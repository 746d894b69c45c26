"""Atomic output files (lookingglass.fileio): they get the usual mode, as open() would give them."""

from __future__ import annotations

import contextlib
import json
import os
import stat

import pytest

from lookingglass import fileio
from lookingglass.fileio import atomic_path, usual_mode, write_json


@contextlib.contextmanager
def umask(mask: int):
    """The process's umask set to `mask` for the block (tests run in one thread)."""
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask, expected", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_write_json_gives_the_usual_mode(tmp_path, mask, expected):
    """mkstemp makes its files 0o600; the output must instead get 0o666 less the umask."""
    path = tmp_path / "sub" / "data.json"
    with umask(mask):
        write_json(path, {"a": 1})
    assert mode(path) == expected
    assert json.loads(path.read_text()) == {"a": 1}
    assert [p.name for p in path.parent.iterdir()] == ["data.json"]  # no temporary file left


def test_atomic_path_mode_also_when_the_writer_replaces_the_file(tmp_path):
    path = tmp_path / "out.txt"
    with umask(0o022), atomic_path(path) as tmp:
        tmp.unlink()  # writers may delete and re-create the file
        fd = os.open(tmp, os.O_CREAT | os.O_WRONLY, 0o600)
        os.close(fd)
    assert mode(path) == 0o644


def test_umask_read_without_proc(monkeypatch):
    """Where /proc/self/status is missing, the umask is read by setting it back: same answer, and
    the umask left as it was."""
    def no_proc(*args, **kwargs):
        raise OSError("no /proc here")

    with umask(0o027):
        assert fileio._umask() == 0o027
        monkeypatch.setattr(fileio, "open", no_proc, raising=False)
        assert fileio._umask() == 0o027
        assert usual_mode() == 0o640 and usual_mode(directory=True) == 0o750
        assert os.umask(0o027) == 0o027  # unchanged
