"""The refine stage's settings compared on a validation set, from the PNet surfaces a `validate` run left
(OUT/<name>/surface.ply): per scene and in the mean, CD / CDN-mean / Metro against the ground truth, the worst
view's silhouette IoU, whether `reconstruct`'s keep check keeps the refined mesh, and the stage's seconds.

Usage, after `lookingglass validate --data DATA --out RUNS`:
    .venv/bin/python scripts/experiments/refine_val_variants.py DATA RUNS \\
        "default" "iterations=12" "iterations=24,silhouette_views=0" [--shapes duck,key] [--normals W|shipped|none]
        [--second-pass-latent none|config]
Each variant is "default" or comma-separated RefineConfig fields (key=value) over the defaults. The refine
stage's normal term runs as in `reconstruct`: the normal net (--normals: a weights.safetensors, by default the
shipped one for the view count; "none": no normal term) run again on the mesh the silhouette iterations leave.
"""
import argparse
import dataclasses
import json
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from lookingglass.capture.scene import load_capture
from lookingglass.config import PipelineConfig
from lookingglass.configio import config_from_dict
from lookingglass.hull import carve_visual_hull
from lookingglass.metrics import load_mesh, shape_metrics
from lookingglass.normals.stage import SECOND_PASS, run_normal_stage
from lookingglass.refine import RefineConfig, refine_surface
from lookingglass.weights import load_normal_net, shipped_weights


def variant(text: str) -> RefineConfig:
    """RefineConfig from "default" or "key=value,key=value" (fields over the defaults; values as JSON)."""
    if text == "default":
        return RefineConfig()
    values = {key: json.loads(value) for key, value in (item.split("=") for item in text.split(","))}
    return config_from_dict(RefineConfig, values, f"variant {text!r}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("data")
    parser.add_argument("runs")
    parser.add_argument("variants", nargs="+")
    parser.add_argument("--shapes", default="")
    parser.add_argument("--normals", default="shipped", help="the normal net of the normal term's second pass "
                        "(shipped: the capture's view count's; none: no normal term)")
    parser.add_argument("--second-pass-latent", choices=["none", "config"], default="none",
                        help="the second pass's latent optimization: none (as reconstruct) or the normal stage's")
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    data, runs = Path(args.data), Path(args.runs)
    names = args.shapes.split(",") if args.shapes else list(json.loads((data / "index.json").read_text())["shapes"])
    config = PipelineConfig()
    hull_config = config.hull
    rows = {v: [] for v in args.variants}
    for name in names:
        capture = load_capture(data / name / "scene")
        gt = load_mesh(data / name / "ground_truth.ply")
        hull = carve_visual_hull(capture.masks, capture.cameras.to(dtype=torch.float32), hull_config)
        surface = load_mesh(runs / name / "surface.ply")
        stage = None
        if args.normals != "none":  # as reconstruct: the net run again on the mesh the silhouettes leave
            path = shipped_weights(capture.num_views)[0] if args.normals == "shipped" else args.normals
            net = load_normal_net(path)
            # as `second_pass`: without the views' consensus
            passed = SECOND_PASS if args.second_pass_latent == "none" else dataclasses.replace(
                SECOND_PASS, latent=config.normals.latent)
            stage = lambda mesh, c=capture, n=net, p=passed: run_normal_stage(c, mesh, n, p)  # noqa: E731
        h, s = shape_metrics(hull.mesh, gt), shape_metrics(surface, gt)
        print(f"{name:15s} hull    CD {h['cd']:6.2f} CDN {h['cdn_mean']:6.2f} metro {h['metro']:6.2f} | "
              f"surface CD {s['cd']:6.2f} CDN {s['cdn_mean']:6.2f} vol {surface.volume / gt.volume:.3f}", flush=True)
        for v in args.variants:
            t = time.perf_counter()
            result = refine_surface(surface, hull, capture.masks, capture.cameras, variant(v), capture=capture,
                                    normals=stage)
            seconds = time.perf_counter() - t
            m = shape_metrics(result.refined, gt)
            kept = result.report["kept"] == "refined"
            iou = min(result.report["silhouette_iou_after"])
            rr = result.report.get("rerender_error", [np.nan, np.nan])[1]
            term = result.report.get("normal_term", {})
            term_text = "term " + ("-" if "kept" not in term else "kept" if term["kept"] else "dropped")
            rows[v].append((h["cd"], h["cdn_mean"], m["cd"], m["cdn_mean"], m["metro"], iou, kept, seconds, rr))
            print(f"{name:15s} {v:40s} CD {m['cd']:6.2f} CDN {m['cdn_mean']:6.2f} metro {m['metro']:6.2f} "
                  f"vol {result.refined.volume / gt.volume:.3f} IoU {iou:.4f} trusted {result.report.get('normal_term', {}).get('trusted_share', 0):.3f} bias {result.report['terms_after'].get('silhouette_bias_px', np.nan):+.3f}px rr {rr:.4f} {term_text} {'kept' if kept else 'REJECTED ' + result.report.get('kept_why', '')} "
                  f"{seconds:.1f}s carve {result.report.get('hull_carve', {}).get('kept', '-')} "
                  f"rounds {len(result.report.get('silhouette_rounds', [None]))} passes "
                  + " ".join(f"{q['kept'][0]}{'T' if q.get('normal_term_kept') else 't'}" for q in result.report.get("passes", [])),
                  flush=True)
    # ratios of the means, as docs/results.md and issue 25's bars use them
    print("\nmeans: CD/hull CDN/hull CD CDN Metro | worst IoU | kept | seconds | rerender")
    for v, r in rows.items():
        a = np.array([x[:6] + (float(x[6]), x[7], x[8]) for x in r])
        print(f"{v:40s} {a[:, 2].mean() / a[:, 0].mean():.3f} {a[:, 3].mean() / a[:, 1].mean():.3f} {a[:, 2].mean():6.2f} {a[:, 3].mean():6.2f} "
              f"{a[:, 4].mean():6.2f} | {a[:, 5].min():.4f} | {int(a[:, 6].sum())}/{len(a)} | {a[:, 7].mean():.1f} | "
              f"{a[:, 8].mean():.4f}")


if __name__ == "__main__":
    main()
