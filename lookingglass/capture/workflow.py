"""`lookingglass capture`: from a folder of photos, one of mirror-ball photos and the object's masks to a
reconstructed mesh, stage by stage in one work folder; a rerun resumes after the last finished stage
(each stage's output is written atomically, so one that exists is finished):

    WORK/sfm/       structure from motion on all photos together (`run_sfm`; kept database)
    WORK/envmap.hdr the ball's environment map, model frame (`envmap_from_ball`)
    WORK/scene/     the scene folder (`import_colmap`)
    WORK/result/    `reconstruct`'s output (default preset, up to config.stop_after)
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

from ..errors import LookingGlassError
from ..fileio import within
from ..physics.constants import IOR_GLASS, check_ior
from .config import CaptureConfig


def run_capture(photos: str | os.PathLike, ball: str | os.PathLike, masks: str | os.PathLike,
                out: str | os.PathLike, config: CaptureConfig = CaptureConfig(), circles=None, ior: float = IOR_GLASS,
                size=None, envmap_size=(1024, 512), reporter=None) -> Path:
    """Run (or resume) the real-capture path into the work folder `out`; returns the mesh's path."""
    from ..pipeline import reconstruct
    from ..presets import preset
    from ..progress import Reporter
    from .ball import envmap_from_ball
    from .colmap import import_colmap
    from .sfm import SFM_FILE, run_sfm

    ior = check_ior(ior, "--ior")  # before any stage: the import stage would refuse it only after sfm
    reporter = reporter or Reporter(quiet=True)
    photos, ball, masks, out = (Path(p) for p in (photos, ball, masks, out))
    for p in (photos, ball, masks):
        if not p.is_dir():
            raise LookingGlassError("folder not found" if not p.exists() else "not a folder", p)
    if photos.resolve() == ball.resolve():
        raise LookingGlassError("--photos and --ball must be different folders", ball)
    if out.exists() and not out.is_dir():
        raise LookingGlassError("the work folder exists and is not a folder", out)
    for p in (photos, ball, masks):  # sfm/ and the rest are written into out: not among the inputs
        if within(out, p):
            raise LookingGlassError(f"the work folder must lie outside the input folder {p}", out)
    out.mkdir(parents=True, exist_ok=True)
    sfm_dir, env, scene, result = out / "sfm", out / "envmap.hdr", out / "scene", out / "result"
    if (sfm_dir / SFM_FILE).is_file() and (sfm_dir / "model").is_dir():
        reporter.info(f"sfm: {sfm_dir} is finished, skipped")
    else:
        run_sfm([photos, ball], sfm_dir, masks, config.sfm, reporter)
    if env.is_file():
        reporter.info(f"envmap-from-ball: {env} is finished, skipped")
    else:
        with reporter.stage("envmap", "environment map from the mirror ball"):
            envmap_from_ball(sfm_dir, ball, env, circles=circles, size=envmap_size, config=config.ball, force=True)
    if (scene / "scene.json").is_file():
        reporter.info(f"import-colmap: {scene} is finished, skipped")
    else:
        with reporter.stage("import", "scene folder from the COLMAP model"):
            import_colmap(sfm_dir, photos, masks, env, scene, ior=ior, size=size)
    if (result / "mesh.ply").is_file():
        reporter.info(f"reconstruct: {result} is finished, skipped")
    else:
        shutil.rmtree(result, ignore_errors=True)
        pipeline = dataclasses.replace(preset().pipeline, stop_after=config.stop_after)
        reconstruct(scene, result, pipeline, force=True, reporter=reporter)
    return result / "mesh.ply"
