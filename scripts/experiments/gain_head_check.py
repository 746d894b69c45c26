"""How well a normal net's gain head tells where its normals beat the hull's, on a validation set.

Usage: .venv/bin/python scripts/experiments/gain_head_check.py DATA WEIGHTS [threshold_deg] [--shapes a,b]
Per scene, over the masked pixels where the hull's two-bounce path exists: the share the head trusts (both
predicted gains > threshold), the true gain (hull's angle error minus the prediction's, degrees; mean of both
hits) on the trusted pixels and on the rest, the precision (trusted pixels whose true gain is > 0 at both
hits) and the recall (pixels with a positive true gain at both hits that are trusted). Runs the normal stage as
`reconstruct` does (default latent steps).
"""
import argparse
import json
import warnings
from pathlib import Path

import torch

from lookingglass.capture.scene import load_capture
from lookingglass.config import PipelineConfig
from lookingglass.hull import carve_visual_hull
from lookingglass.metrics import load_mesh
from lookingglass.normals.stage import run_normal_stage
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.weights import load_normal_net

angle = lambda a, b: torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))  # noqa: E731


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("data")
    parser.add_argument("weights")
    parser.add_argument("threshold", nargs="?", type=float, default=1.0)
    parser.add_argument("--shapes", default="")
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    data = Path(args.data)
    names = args.shapes.split(",") if args.shapes else list(json.loads((data / "index.json").read_text())["shapes"])
    cfg = PipelineConfig()
    weights = load_normal_net(args.weights)
    for name in names:
        cap = load_capture(data / name / "scene")
        hull = carve_visual_hull(cap.masks, cap.cameras, cfg.hull)
        stage = run_normal_stage(cap, hull, weights, cfg.normals)
        x, maps = stage.inputs, stage.maps
        truth = trace_two_bounce(load_mesh(data / name / "ground_truth.ply"), x.cameras, ior=cap.ior)
        valid = x.mask & x.vh_valid & truth.mask & truth.valid & ~maps.tir
        g1 = angle(x.vh_n1, truth.normal1) - angle(maps.n1, truth.normal1)
        g2 = angle(x.vh_n2, truth.normal2) - angle(maps.n2, truth.normal2)
        trusted = valid & (maps.predicted_gain > args.threshold).all(-1)
        good = valid & (g1 > 0) & (g2 > 0)
        g = (g1 + g2) / 2
        rest = valid & ~trusted
        print(f"{name:15s} trusted {float(trusted.sum() / valid.sum()):.3f} | gain trusted {float(g[trusted].mean()):+6.2f} "
              f"rest {float(g[rest].mean()):+6.2f} | precision {float((trusted & good).sum() / trusted.sum().clamp(min=1)):.2f} "
              f"recall {float((trusted & good).sum() / good.sum().clamp(min=1)):.2f} | good share "
              f"{float(good.sum() / valid.sum()):.2f}", flush=True)


if __name__ == "__main__":
    main()
