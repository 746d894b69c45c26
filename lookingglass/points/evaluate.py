"""The paper's Table 2/3 on a test split: shape metrics of the visual hull and of the surfaces
made from normal predictions (points on the hull + feature mapping + Poisson).

Rows: `vh` (the hull itself); `vh+gt-normals` (the hull's points with the ground-truth first-hit
normals mapped by the chosen strategy: what mapping + Poisson can reach with perfect normals);
and, per strategy, `normals-<RE|NE|AV>` with the network's normals (latent-optimized when
`latent` is given). Metrics are DESIGN.md's (CD x1e4, Metro x1e3, CDN-mean/med in degrees), on
the ground truth's unit-sphere scale; per-scene values are kept so the worst scenes can be read.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from ..errors import LookingGlassError
from ..metrics import shape_metrics
from ..normals.latent import LatentOptConfig, optimize_latent
from ..normals.render_layer import comparable, render_layer
from ..normals.train import load_weights, scene_tensors
from ..progress import Reporter
from ..surface import poisson_surface
from .stage import SurfaceConfig, map_normals_to_hull

METRICS = ("cd", "cdn_mean", "cdn_med", "metro")


def evaluate_shapes(dataset, weights: Path | None, strategies: tuple[str, ...] = ("RE",),
                    latent: LatentOptConfig | None = None, surface: SurfaceConfig | None = None,
                    max_scenes: int = 0, reporter: Reporter | None = None) -> dict:
    """Returns {"rows": {name: {metric: mean}}, "scenes": [{"index", name: {metric}}...]}.

    dataset: a TransparentSceneDataset (test split, not augmented). The dataset's meshes are in
    its world frame, the GT already unit-sphere normalized, so Poisson runs there directly."""
    reporter = reporter or Reporter(quiet=True)
    surface = surface or SurfaceConfig()
    net = load_weights(weights) if weights is not None else None
    n = len(dataset) if not max_scenes else min(max_scenes, len(dataset))
    scenes = []
    for i in reporter.track(range(n), description="test scenes"):
        sample = dataset[i]
        gt, hull = dataset.meshes(i)
        t = scene_tensors(sample, net.cfg if net is not None else _plain_config(), 1.4723)
        cams, mask = t["cameras"], t["mask"]
        record = {"index": i, "vh": shape_metrics(hull, gt)}
        maps = {"vh+gt-normals": (t["n1"], None)}
        if net is not None:
            if latent is not None:
                n1, n2, _ = optimize_latent(net, t["inputs"], t["cost_volume"], t["envmap"], t["image"], mask, cams,
                                            latent)
            else:
                with torch.no_grad():
                    n1, n2 = net(t["inputs"], t["cost_volume"])
            maps["normals"] = (n1.detach(), n2.detach())
        for name, (n1, n2) in maps.items():
            n1_hw = n1.permute(0, 2, 3, 1)
            if n2 is None:  # GT: its own rendering error is the renderer's residual, take it as 0
                error, tir = torch.zeros(mask.shape), sample["tir"].bool() & mask
            else:
                out = render_layer(t["envmap"], n1_hw, n2.permute(0, 2, 3, 1), cams)
                error = ((comparable(out.image) - t["image"]) ** 2).mean(-1) * mask
                tir = out.tir & mask
            for strategy in (strategies if name == "normals" else strategies[:1]):
                cfg = dataclasses.replace(surface, strategy=strategy)
                oriented = map_normals_to_hull(hull, cams, n1_hw, error, tir, mask, cfg)
                row = f"normals-{strategy}" if name == "normals" else name
                try:
                    mesh = poisson_surface(oriented.points, oriented.normals, depth=cfg.depth, hull=hull)
                    record[row] = shape_metrics(mesh, gt)
                except LookingGlassError as exc:  # counted, not hidden: the row's mean says how many failed
                    record[row] = {"error": str(exc)}
        scenes.append(record)
    names = [k for k in scenes[0] if k != "index"] if scenes else []
    rows = {}
    for name in names:
        ok = [s[name] for s in scenes if "error" not in s[name]]
        rows[name] = {m: float(np.mean([s[m] for s in ok])) if ok else float("nan") for m in METRICS}
        rows[name]["failed"] = len(scenes) - len(ok)
    return {"rows": rows, "scenes": scenes}


def _plain_config():
    from ..normals.model import NormalNetConfig

    return NormalNetConfig(use_error_map=False, use_cost_volume=False)


def markdown_table(rows: dict) -> str:
    lines = ["| | CD (×1e4) | CDN-mean (°) | CDN-med (°) | Metro (×1e3) | failed |", "|---|---|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['cd']:.2f} | {r['cdn_mean']:.2f} | {r['cdn_med']:.2f} | {r['metro']:.2f} | "
                     f"{r['failed']} |")
    return "\n".join(lines)
