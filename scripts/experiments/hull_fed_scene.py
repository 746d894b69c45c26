"""One validation scene as the normal-term experiments start from it: the capture, its ground truth,
the hull carved with the pipeline's settings, the shipped normal net's stage fed that hull (latent
optimization as `reconstruct`'s), the true two-bounce normals at the net's pixels, and a run's
PNet surface (RUNS/<name>/surface.ply)."""
from pathlib import Path
from types import SimpleNamespace

from lookingglass.capture.scene import load_capture
from lookingglass.config import PipelineConfig
from lookingglass.hull import carve_visual_hull
from lookingglass.metrics import load_mesh
from lookingglass.normals.stage import run_normal_stage
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.weights import load_normal_net, shipped_weights


def hull_fed_scene(data: Path, runs: Path, name: str, cfg: PipelineConfig) -> SimpleNamespace:
    cap = load_capture(data / name / "scene")
    hull = carve_visual_hull(cap.masks, cap.cameras, cfg.hull)
    gt = load_mesh(data / name / "ground_truth.ply")
    stage = run_normal_stage(cap, hull.mesh, load_normal_net(shipped_weights(cap.num_views)[0]), cfg.normals)
    return SimpleNamespace(cap=cap, gt=gt, hull=hull, stage=stage, x=stage.inputs, maps=stage.maps,
                           truth=trace_two_bounce(gt, stage.inputs.cameras, ior=cap.ior),
                           surf=load_mesh(runs / name / "surface.ply"))
