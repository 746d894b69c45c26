"""The scene folder's own checks, made before any file in it is read (DESIGN.md's scene folder
format). Nothing here imports torch or an image library, so the command line refuses a wrong path
before it loads the pipeline."""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import LookingGlassError
from ..fileio import check_output_dir, resolved_path

SCENE_FILE = "scene.json"


def scene_file_in(folder: str | os.PathLike) -> Path:
    """FOLDER/scene.json. Raises LookingGlassError naming `folder` where it is a loop of symbolic
    links, is missing, is not a folder, or holds no scene.json."""
    root = Path(folder)
    resolved_path(root)  # a loop of links "exists" as nothing: say what it is
    if not root.exists():
        raise LookingGlassError("scene folder not found", root)
    if not root.is_dir():
        raise LookingGlassError("not a folder (expected a scene folder holding scene.json)", root)
    scene_path = root / SCENE_FILE
    if not scene_path.exists():
        raise LookingGlassError(f"no {SCENE_FILE} in the scene folder", root)
    return scene_path


def check_output_folder(scene_dir: str | os.PathLike, out: str | os.PathLike, force: bool) -> None:
    """Refuse an output folder a reconstruction of `scene_dir` must not write (LookingGlassError naming
    it): the scene folder itself, one that holds it, and what `fileio.check_output_dir` refuses (not
    empty without `force`, not writable). The files scene.json names are checked once it is read."""
    if resolved_path(scene_dir) == resolved_path(out):
        raise LookingGlassError("output folder must differ from the scene folder", out)
    check_output_dir(out, force, inputs=[scene_dir])
