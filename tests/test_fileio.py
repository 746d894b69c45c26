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


# ---- staged_dir: a command's whole output folder -----------------------------------------------
from lookingglass.errors import Interrupted, LookingGlassError  # noqa: E402
from lookingglass.fileio import staged_dir  # noqa: E402


def test_staged_dir_appears_finished_with_the_usual_modes(tmp_path):
    out = tmp_path / "new" / "deeper" / "out"
    with umask(0o022), staged_dir(out) as work:
        assert work.parent == out.parent and work.name.startswith(".out.partial-") and not out.exists()
        (work / "sub").mkdir()
        write_json(work / "sub" / "a.json", {})
    assert sorted(p.name for p in out.parent.iterdir()) == ["out"]
    assert mode(out) == 0o755 and mode(out / "sub") == 0o755 and mode(out / "sub" / "a.json") == 0o644


def test_staged_dir_force_replaces_whole_and_failure_keeps_the_old(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(LookingGlassError, match="not empty"):
        with staged_dir(out):
            pass
    with pytest.raises(RuntimeError):
        with staged_dir(out, force=True) as work:
            (work / "new.txt").write_text("new")
            raise RuntimeError("a stage failed")
    assert [p.name for p in tmp_path.iterdir()] == ["out"] and (out / "old.txt").read_text() == "old"
    with staged_dir(out, force=True) as work:
        (work / "new.txt").write_text("new")
    assert [p.name for p in out.iterdir()] == ["new.txt"] and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_staged_dir_interrupted_says_so_and_removes_what_it_made(tmp_path):
    out = tmp_path / "made" / "out"
    with pytest.raises(Interrupted) as info:
        with staged_dir(out, doing="reconstruct of scene") as work:
            (work / "mesh.ply").write_text("partial")
            raise KeyboardInterrupt
    assert str(info.value) == f"interrupted: reconstruct of scene; no partial result was left ({out} was not created)"
    assert list(tmp_path.iterdir()) == []  # the parent made for it is gone too


def test_check_output_dir_refuses_before_any_work(tmp_path):
    from lookingglass.fileio import check_output_dir

    (tmp_path / "file").write_text("x")
    for out, said in [(tmp_path / "file", "not a folder"), (tmp_path / "file" / "o", "is not a folder"),
                      (tmp_path, "replace the input")]:
        with pytest.raises(LookingGlassError, match=said):
            check_output_dir(out, True, inputs=[tmp_path / "scene"])
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        with pytest.raises(LookingGlassError, match="not writable"):
            check_output_dir(locked / "o", False)


def test_staged_dir_says_read_or_write_by_where_the_error_was(tmp_path):
    """A permission error on an input (a photo the user may not open) is "cannot read"; one inside
    the folder being written is "cannot write". (Made here: as root no file is unreadable.)"""
    import errno

    with pytest.raises(LookingGlassError, match=r"in\.exr: cannot read \(Permission denied\)"):
        with staged_dir(tmp_path / "out"):
            raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "in.exr"))
    with pytest.raises(LookingGlassError, match=r"cannot write \(No space left on device\)"):
        with staged_dir(tmp_path / "out") as work:
            raise OSError(errno.ENOSPC, "No space left on device", str(work / "mesh.ply"))
    assert not (tmp_path / "out").exists()


def test_an_image_without_read_permission_names_it(tmp_path, monkeypatch):
    from lookingglass.capture import images

    path = tmp_path / "a.png"
    images.write_mask(path, __import__("numpy").ones((4, 4), bool))
    monkeypatch.setattr(images.os, "access", lambda p, mode: False)  # as root every file is readable
    with pytest.raises(LookingGlassError, match=r"a\.png: cannot read \(permission denied\)"):
        images.read_mask(path)
