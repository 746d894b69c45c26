"""What the command-line tests share: running `lookingglass` in a subprocess, and a small rendered
capture to run it on."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import trimesh

from lookingglass.capture.images import write_image
from lookingglass.capture.scene import load_capture
from lookingglass.data.envmaps import procedural_envmap
from lookingglass.render.tracer import trace_two_bounce

CLI = [sys.executable, "-m", "lookingglass.cli"]


def run(*args, ok=True, timeout=600, **kwargs):
    """`lookingglass ARGS` in a subprocess; with ok, assert it exits 0 (stderr in the message).
    timeout guards against a hang only: a 2-core machine running the other pytest worker beside it
    takes 3-4x a quiet run's time."""
    proc = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout, **kwargs)
    if ok:
        assert proc.returncode == 0, proc.stderr
    return proc


def run_here(*args, cwd=None, env=None, timeout=120) -> subprocess.CompletedProcess:
    """`lookingglass ARGS` in this process, through `cli.main` as the console script runs it, for commands
    that refuse their input before any work: the same exit status and stderr as `run` in ~0.1 s, where
    a new process spends ~3.5 s importing (tests/test_bad_input.py keeps the real-process check). An
    exception main() lets through is written to stderr as the traceback a process would print, exit
    status 1, and so is a call that runs past `timeout` seconds (a hang, as `run`'s timeout guards). cwd and
    env (os.environ's entries to set) hold only for the call; so do the interrupt hook main() installs and
    torch's thread count."""
    import contextlib
    import io
    import os
    import signal
    import traceback

    import torch

    from lookingglass import cli

    out, err = io.StringIO(), io.StringIO()
    argv = ["lookingglass", *map(str, args)]
    old_argv, old_hook, old_threads, old_cwd, old_env = (sys.argv, sys.unraisablehook, torch.get_num_threads(),
                                                         os.getcwd(), dict(os.environ))
    sys.argv = argv
    os.environ.update(env or {})
    code = 0

    def hung(signum, frame):
        raise TimeoutError(f"{' '.join(argv)} ran past {timeout} s")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(timeout)
    try:
        if cwd is not None:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                cli.main()
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except Exception:  # a process would print it and exit 1
                traceback.print_exc(file=err)
                code = 1
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
        sys.argv, sys.unraisablehook = old_argv, old_hook
        torch.set_num_threads(old_threads)
        os.chdir(old_cwd)
        os.environ.clear()
        os.environ.update(old_env)
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())


def render_torus_scene(root: Path) -> Path:
    """ROOT/gt.ply (a tilted torus), ROOT/env.hdr (procedural) and ROOT/scene, its 10-view 120x90
    rendering by `lookingglass render`; returns ROOT."""
    mesh = trimesh.creation.torus(major_radius=0.6, minor_radius=0.25)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.6, [1, 0, 0.3]))
    mesh.export(root / "gt.ply")
    write_image(root / "env.hdr", procedural_envmap(np.random.default_rng(0), 64))
    run("render", root / "gt.ply", "--envmap", root / "env.hdr", "--rig", 10, "--size", 120, 90, "--out", root / "scene")
    return root


def normal_errors(scene, gt_path, out, views: int) -> tuple[dict, dict]:
    """The normals stage of `out`/report.json and the median angle errors (N1, N2) in degrees of
    the predicted normals ("pred") and of the hull's ("hull") against the ground truth traced at
    the network's resolution, over pixels both see."""
    report = json.loads((out / "report.json").read_text())
    stage = next(s for s in report["stages"] if s["name"] == "normals")
    maps = [np.load(out / "normals" / f"view_{v:02d}.npz") for v in range(views)]
    assert (out / "normals" / f"view_{views - 1:02d}.png").exists()
    n1, n2, mask = (np.stack([v[k] for v in maps]) for k in ("n1", "n2", "mask"))
    width, height = stage["network_size"]
    cams = load_capture(scene).cameras.with_resolution(width, height)
    gt = trace_two_bounce(trimesh.load(gt_path, force="mesh"), cams)
    hull = trace_two_bounce(trimesh.load(out / "visual_hull.ply", force="mesh"), cams)

    def median_angle(a, b, m):
        a, b = a[m], b[m]  # off the masks the normals are zero
        cos = np.clip((a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1), -1, 1)
        return float(np.degrees(np.median(np.arccos(cos))))

    m1 = mask & gt.mask.numpy() & hull.mask.numpy()
    m2 = m1 & gt.valid.numpy() & hull.hit2.numpy()
    return stage, {name: (median_angle(a1, gt.normal1.numpy(), m1), median_angle(a2, gt.normal2.numpy(), m2))
                   for name, (a1, a2) in {"pred": (n1, n2), "hull": (hull.normal1.numpy(), hull.normal2.numpy())}.items()}
