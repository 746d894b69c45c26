"""The refine stage's settings compared on test-split scenes (docs/history.md, 2026-11-25: the silhouette weight at
128x96): per scene, the PNet surface and the refined mesh of each variant, CD / CDN-mean against the ground truth
and the worst view's silhouette IoU; "kept" says whether `reconstruct`'s keep check would keep it.

Usage: .venv/bin/python scripts/experiments/refine_variants.py DATA 1,2,3,4,5,6 [VARIANT ...]
(DATA/test a split made by `lookingglass generate --split test`; the shipped weights for its view count.) A VARIANT is
"default" or comma-separated RefineConfig fields over the defaults ("iterations=12,fair_weight=25";
"normal_iterations=0": without the normal term, which otherwise runs as in `reconstruct`); without any, the
silhouette weights of the 2026-11-25 measurement.
"""
import dataclasses
import json
import sys
import warnings
from pathlib import Path

import torch

from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.metrics import shape_metrics
from lookingglass.normals.stage import run_normal_stage
from lookingglass.pipeline import refine_stage
from lookingglass.points.stage import SurfaceConfig, surface_from_normals
from lookingglass.refine import RefineConfig, silhouette_iou
from lookingglass.weights import load_normal_net, load_point_net, shipped_weights

VARIANTS = {"weight 1": dict(silhouette_weight=1.0, silhouette_width=0),
            "weight 0.25": dict(silhouette_weight=0.25, silhouette_width=0),
            "weight 0.07": dict(silhouette_weight=0.07, silhouette_width=0),
            "weight 0": dict(silhouette_weight=0.0), "default": {}}

if len(sys.argv) > 3:
    sys.path.insert(0, str(Path(__file__).parent))
    from refine_val_variants import variant

    VARIANTS = {v: dataclasses.asdict(variant(v)) for v in sys.argv[3:]}
warnings.simplefilter("ignore")
torch.set_num_threads(1)
views = json.loads((Path(sys.argv[1]) / "test" / "config.json").read_text())["views"]
ds = TransparentSceneDataset(sys.argv[1], "test", views=views)
normal_net, point_net = load_normal_net(shipped_weights(views)[0]), load_point_net(shipped_weights(views, "points")[0])
for i in map(int, sys.argv[2].split(",")):
    capture, hull, truth = ds.capture(i), ds.hull(i), ds.meshes(i)[0]
    normals = run_normal_stage(capture, hull.mesh, normal_net, None)
    mesh, _ = surface_from_normals(hull, normals.maps, SurfaceConfig(), point_net)
    m = shape_metrics(mesh, truth)
    print(i, "surface", round(m["cd"], 2), round(m["cdn_mean"], 2),
          round(float(silhouette_iou(mesh, capture.cameras, capture.masks).min()), 3), flush=True)
    for name, settings in VARIANTS.items():
        result = refine_stage(capture, hull, mesh, normal_net, RefineConfig(**settings))
        m = shape_metrics(result.refined, truth)
        term = result.report.get("normal_term", {})
        print(i, name, "kept" if result.report["kept"] == "refined" else "rejected", round(m["cd"], 2),
              round(m["cdn_mean"], 2), round(min(result.report["silhouette_iou_after"]), 3),
              "term", term.get("trusted_share"), term.get("kept"),
              "rerender", result.report.get("rerender_error"), "iou_mean", result.report["silhouette_iou_mean"],
              result.report.get("kept_why", ""), "seconds", result.report["seconds"],
              "passes", [(p["kept"], p["worst_iou"], p["rounds"], p["seconds"]) for p in result.report.get("passes", [])],
              flush=True)
        for r in result.report.get("silhouette_rounds", []):
            print("   round", r["kept"], r["worst_iou"], "carved", r.get("carved"), r["seconds"], flush=True)
        print("   carve", result.report.get("hull_carve"), flush=True)
