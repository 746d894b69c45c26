"""How much the refine stage's penalty rounds move when its input surface is rounded to float32 (as OUT/surface.ply
stores it, and as refine_val_variants.py reads it back): the normal and surface stages rerun in one process
(`stage_meshes`, `reconstruct`'s calls), the saved surface's distance to them, then the refine stage from the surface in
float64 (what `validate` refines) and rounded to float32; each round's worst view (docs/history.md, session 70).

Usage: OMP_NUM_THREADS=1 .venv/bin/python scripts/experiments/surface_rounding_rounds.py DATA RUNS SHAPE
(after `lookingglass validate --data DATA --out RUNS`; e.g. data/val128 runs/val128_s70b stepped_shaft)
"""
import sys
import warnings
from pathlib import Path

import numpy as np
import torch
import trimesh

from lookingglass.capture.scene import load_capture
from lookingglass.config import PipelineConfig
from lookingglass.hull import carve_visual_hull
from lookingglass.metrics import load_mesh
from lookingglass.pipeline import refine_stage, stage_meshes
from lookingglass.weights import load_normal_net, load_point_net, shipped_weights


def main() -> None:
    data, runs, shape = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
    warnings.simplefilter("ignore")
    torch.set_num_threads(1)
    capture = load_capture(data / shape / "scene")
    config = PipelineConfig(device="cpu")
    hull = carve_visual_hull(capture.masks, capture.cameras.to(dtype=torch.float32), config.hull)
    weights = load_normal_net(shipped_weights(capture.num_views)[0])
    points = load_point_net(shipped_weights(capture.num_views, "points")[0])
    surface = stage_meshes(capture, hull, weights, points, config, refine=False).surface
    saved = load_mesh(runs / shape / "surface.ply")
    if len(saved.vertices) == len(surface.vertices):
        print(f"saved surface.ply against the stages' surface: max |dv| {np.abs(saved.vertices - surface.vertices).max():.2e}")
    else:
        print("saved surface.ply has other vertices than the stages' surface (another run's)")
    rounded = trimesh.Trimesh(surface.vertices.astype(np.float32).astype(np.float64), surface.faces, process=False)
    for label, mesh in (("float64", surface), ("float32", rounded)):
        report = refine_stage(capture, hull, mesh, weights, config.refine, "cpu").report
        rounds = [(r["worst_iou"], r["kept"]) for r in report.get("silhouette_rounds", [])]
        print(f"{label}: rounds {rounds or 'one'}, ended {report.get('silhouette_rounds_ended', '-')}", flush=True)


if __name__ == "__main__":
    main()
