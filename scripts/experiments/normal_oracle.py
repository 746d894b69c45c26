"""The refine stage's normal term with the ground truth's normals as the target (an oracle): can the descent
carry good normals into the mesh? (docs/results.md, "The normal term")

Usage, after `lookingglass validate --data data/val480 --out runs/val480`:
    .venv/bin/python scripts/experiments/normal_oracle.py data/val480 runs/val480 duck 8,32
Per scene and step count: CD, CDN-mean of the refined mesh, its re-rendering error, the loss per step.
"""
import sys, json, dataclasses, warnings, types
import numpy as np, torch
from pathlib import Path
from lookingglass.capture.scene import load_capture
from lookingglass.metrics import load_mesh, shape_metrics
from lookingglass.hull import carve_visual_hull
from lookingglass.config import PipelineConfig
from lookingglass.refine import refine_surface
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.predict import NormalMaps
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.weights import DEFAULT_ENVMAP_HEIGHT as DEH
warnings.simplefilter("ignore")
root, out = Path(sys.argv[1]), Path(sys.argv[2])
its = [int(i) for i in sys.argv[4].split(",")]
cfg = PipelineConfig()
for name in sys.argv[3].split(","):
    cap = load_capture(root/name/"scene"); gt = load_mesh(root/name/"ground_truth.ply")
    hull = carve_visual_hull(cap.masks, cap.cameras, cfg.hull)
    x = NormalInputs.from_capture(cap.images, cap.masks, cap.envmap, cap.cameras, cap.ior, hull.mesh, 128, 96, DEH)
    t = trace_two_bounce(gt, x.cameras, ior=cap.ior)
    # the true normals, vouched for everywhere (a gain far above the trust bar; the term's guard against
    # the photos still applies)
    maps = NormalMaps(x.cameras, t.normal1, t.normal2, torch.zeros(x.mask.shape), torch.zeros_like(x.mask), x.mask,
                      predicted_gain=torch.full((*x.mask.shape, 2), 90.0))
    stage = types.SimpleNamespace(inputs=x, maps=maps)
    surf = load_mesh(out/name/"surface.ply")
    for n in its:
        rc = dataclasses.replace(cfg.refine, normal_iterations=n)
        r = refine_surface(surf, hull, cap.masks, cap.cameras, rc, capture=cap, normals=stage)
        m = shape_metrics(r.refined, gt)
        print(name, n, {"CD": round(m["cd"], 2), "CDNm": round(m["cdn_mean"], 2), "rr": r.report.get("rerender_error"), "term": r.report.get("normal_term"), "iou": min(r.report["silhouette_iou_after"]), "kept": r.report["kept"]}, flush=True)
