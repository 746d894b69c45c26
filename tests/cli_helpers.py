"""What the command-line tests share: running `lookingglass` in a subprocess, and a small rendered
capture to run it on."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import trimesh

from lookingglass.capture.images import write_image
from lookingglass.data.envmaps import procedural_envmap

CLI = [sys.executable, "-m", "lookingglass.cli"]


def run(*args, ok=True, **kwargs):
    """`lookingglass ARGS` in a subprocess; with ok, assert it exits 0 (stderr in the message)."""
    proc = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=300, **kwargs)
    if ok:
        assert proc.returncode == 0, proc.stderr
    return proc


def render_torus_scene(root: Path) -> Path:
    """ROOT/gt.ply (a tilted torus), ROOT/env.hdr (procedural) and ROOT/scene, its 10-view 120x90
    rendering by `lookingglass render`; returns ROOT."""
    mesh = trimesh.creation.torus(major_radius=0.6, minor_radius=0.25)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.6, [1, 0, 0.3]))
    mesh.export(root / "gt.ply")
    write_image(root / "env.hdr", procedural_envmap(np.random.default_rng(0), 64))
    run("render", root / "gt.ply", "--envmap", root / "env.hdr", "--rig", 10, "--size", 120, 90, "--out", root / "scene")
    return root
