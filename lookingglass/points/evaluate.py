"""The paper's Table 2/3 on a test split: shape metrics of the visual hull and of the surfaces
made from normal predictions (points on the hull + feature mapping + Poisson).

Rows: `vh` (the hull itself); `vh+gt-normals` (the hull's points with the ground-truth first-hit
normals mapped by the chosen strategy: what mapping + Poisson can reach with perfect normals);
per strategy, `normals-<RE|NE|AV>` with the network's normals (latent-optimized when `latent` is
given); and `pnet-<strategy>` when point-network weights are given (its training strategy). Metrics are DESIGN.md's (CD x1e4, Metro x1e3, CDN-mean/med in degrees), on
the ground truth's unit-sphere scale; per-scene values are kept so the worst scenes can be read.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from ..errors import LookingGlassError
from ..metrics import shape_metrics
from ..normals.latent import LatentOptConfig, optimize_latent
from ..normals.render_layer import prediction_error_maps
from ..normals.train import load_weights, scene_tensors
from ..parallel import map_scenes
from ..progress import Reporter
from .stage import SurfaceConfig, surface_from_normals
from .train import load_point_weights

METRICS = ("cd", "cdn_mean", "cdn_med", "metro")


def evaluate_shapes(dataset, weights: Path | None, strategies: tuple[str, ...] = ("RE",),
                    latent: LatentOptConfig | None = None, surface: SurfaceConfig | None = None,
                    max_scenes: int = 0, reporter: Reporter | None = None,
                    point_weights: Path | None = None, done: list[dict] | None = None,
                    on_scene: Callable[[dict], None] | None = None, device: str = "cpu",
                    workers: int = 1) -> dict:
    """Returns {"rows": {name: {metric: mean}}, "scenes": [{"index", name: {metric}}...]}.

    done: scene records of an earlier, interrupted run with the same settings (their scenes are
    not redone); on_scene: called with the partial result after every scene (to save it).
    workers: scenes evaluated at once, each in its own process with one thread (0: one per core;
    CPU only). The records do not depend on it beyond float rounding.

    dataset: a TransparentSceneDataset (test split, not augmented). Surfaces are made in each
    scene's hull-normalized frame (PNet's, from meta.json) and scored against the GT in its own
    unit-sphere frame. The networks and the rendering layer run on `device`; feature mapping and
    Poisson on the CPU."""
    reporter = reporter or Reporter(quiet=True)
    n = len(dataset) if not max_scenes else min(max_scenes, len(dataset))
    scenes = [record for record in (done or []) if record["index"] < n]
    finished = {record["index"] for record in scenes}
    todo = [i for i in range(n) if i not in finished]
    args = (dataset, weights, point_weights, tuple(strategies), latent, surface or SurfaceConfig())
    records = map_scenes(_ShapeEvaluation, args, todo, workers, device)
    for record in reporter.track(records, total=len(todo), description="test scenes"):
        scenes.append(record)
        if on_scene is not None:
            on_scene(summarize(scenes))
    return summarize(scenes)


class _ShapeEvaluation:
    """What every scene's evaluation needs: the dataset, the networks (loaded once) and settings."""

    def __init__(self, dataset, weights: Path | None, point_weights: Path | None, strategies: tuple[str, ...],
                 latent: LatentOptConfig | None, surface: SurfaceConfig, device: str = "cpu"):
        self.dataset, self.strategies, self.latent, self.surface, self.device = (dataset, strategies, latent,
                                                                                 surface, device)
        self.net = load_weights(weights).to(device) if weights is not None else None
        self.point_net = load_point_weights(point_weights).to(device) if point_weights is not None else None
        self.point_strategy = "RE"
        if point_weights is not None:  # PNet is evaluated with the mapping it was trained on
            self.point_strategy = json.loads(Path(point_weights).with_suffix(".json").read_text()).get("strategy",
                                                                                                      "RE")

    def scene(self, i: int) -> dict:
        """{"index": i, row: metrics} for test scene i."""
        dataset, device, net, surface = self.dataset, self.device, self.net, self.surface
        sample = dataset[i]
        gt, hull = dataset.meshes(i)
        t = scene_tensors(sample, net.cfg if net is not None else _plain_config(), 1.4723, device)
        cams, mask = t["cameras"], t["mask"]
        cams_cpu = cams.to("cpu")  # feature mapping and Poisson run on the CPU
        frame = dataset.meta(i)["hull"]  # read once: every row's surface is made in this frame
        record = {"index": i, "vh": shape_metrics(hull, gt)}
        maps = {"vh+gt-normals": (t["n1"], None)}
        if net is not None:
            if self.latent is not None:
                n1, n2, _ = optimize_latent(net, t["inputs"], t["cost_volume"], t["envmap"], t["image"], mask, cams,
                                            self.latent)
            else:
                with torch.no_grad():
                    n1, n2 = net(t["inputs"], t["cost_volume"])
            maps["normals"] = (n1.detach(), n2.detach())
        for name, (n1, n2) in maps.items():
            n1_hw = n1.permute(0, 2, 3, 1)
            if n2 is None:  # GT: its own rendering error is the renderer's residual, take it as 0
                error, tir = torch.zeros(mask.shape, device=mask.device), sample["tir"].to(device).bool() & mask
            else:
                error, tir, _ = prediction_error_maps(t["envmap"], n1_hw, n2.permute(0, 2, 3, 1), cams, t["image"],
                                                      mask)
            runs = ([(f"normals-{s}", s, None) for s in self.strategies] if name == "normals"
                    else [(name, self.strategies[0], None)])
            if name == "normals" and self.point_net is not None:
                runs.append((f"pnet-{self.point_strategy}", self.point_strategy, self.point_net))
            maps_cpu = [x.cpu() for x in (n1_hw, error, tir, mask)]
            for row, strategy, pnet in runs:
                record[row] = _surface_metrics(hull, gt, frame, cams_cpu, *maps_cpu,
                                               dataclasses.replace(surface, strategy=strategy), pnet)
        return record


def summarize(scenes: list[dict]) -> dict:
    """{"rows": means of every row's metrics over the scenes it did not fail on, "scenes": ...}."""
    scenes = sorted(scenes, key=lambda record: record["index"])
    names = [k for k in scenes[0] if k != "index"] if scenes else []
    rows = {}
    for name in names:
        ok = [s[name] for s in scenes if "error" not in s[name]]
        rows[name] = {m: float(np.mean([s[m] for s in ok])) if ok else float("nan") for m in METRICS}
        rows[name]["failed"] = len(scenes) - len(ok)
    return {"rows": rows, "scenes": scenes}


def _surface_metrics(hull, gt, frame: dict, cams, n1_hw, error, tir, mask, cfg: SurfaceConfig, point_net) -> dict:
    """Shape metrics of the surface made from the maps, in the hull-normalized frame (PNet's;
    `frame` is the scene meta's "hull" entry), measured in the ground truth's frame; a failed
    Poisson is recorded, not hidden."""
    center, scale = np.asarray(frame["center"], np.float64), float(frame["scale"])
    try:
        mesh, _ = surface_from_normals(hull, center, scale, cams, n1_hw, error, tir, mask, cfg, point_net)
        return shape_metrics(mesh, gt)
    except LookingGlassError as exc:
        return {"error": str(exc)}


def _plain_config():
    from ..normals.model import NormalNetConfig

    return NormalNetConfig(use_error_map=False, use_cost_volume=False)


def markdown_table(rows: dict) -> str:
    lines = ["| | CD (×1e4) | CDN-mean (°) | CDN-med (°) | Metro (×1e3) | failed |", "|---|---|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['cd']:.2f} | {r['cdn_mean']:.2f} | {r['cdn_med']:.2f} | {r['metro']:.2f} | "
                     f"{r['failed']} |")
    return "\n".join(lines)
