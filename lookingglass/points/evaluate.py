"""The paper's Table 2/3 on a test split: shape metrics of the visual hull and of the surfaces
made from normal predictions (points on the hull + feature mapping + Poisson).

Rows: `vh` (the hull itself); `vh+gt-normals` (the hull's points with the ground-truth first-hit
normals mapped by the chosen strategy: what mapping + Poisson can reach with perfect normals);
per strategy, `normals-<RE|NE|AV>` with the network's normals (the normal stage as `normals`
configures it); `pnet-<strategy>` when point-network weights are given (its training strategy); and
`refined` when a refine config is given: that surface through `reconstruct`'s refine stage (the mesh
it keeps). Metrics are DESIGN.md's (CD x1e4, Metro x1e3, CDN-mean/med in degrees), on the ground
truth's unit-sphere scale; with the refine row, `vh`, the pnet row and `refined` also carry the
re-rendering error against the photos (`render.compare.rerender`) and the worst view's silhouette
IoU with the masks; `refined` also which mesh the stage kept, its weighted mean IoU before and after,
and why it refused the refined mesh where it did. Per-scene values are kept so the worst scenes can be read.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from ..config import NormalStageConfig
from ..errors import LookingGlassError
from ..hull import VisualHull
from ..metrics import shape_metrics
from ..normals.predict import NormalMaps
from ..normals.stage import run_normal_stage
from ..parallel import map_scenes
from ..pipeline import refine_stage
from ..progress import Reporter
from ..refine import RefineConfig, silhouette_iou
from ..render.compare import rerender
from ..weights import load_normal_net, load_point_net
from .stage import SurfaceConfig, surface_from_normals

METRICS = ("cd", "cdn_mean", "cdn_med", "metro")
# Scored beside METRICS on the rows that show the photos' side (the refine row's evaluation).
PHOTO_METRICS = ("rerender", "iou_min")


def evaluate_shapes(dataset, weights: Path | None, strategies: tuple[str, ...] = ("RE",),
                    normals: NormalStageConfig | None = None, surface: SurfaceConfig | None = None,
                    max_scenes: int = 0, reporter: Reporter | None = None,
                    point_weights: Path | None = None, done: list[dict] | None = None,
                    on_scene: Callable[[dict], None] | None = None, device: str = "cpu",
                    workers: int = 1, refine: RefineConfig | None = None, ior: float | None = None) -> dict:
    """Returns {"rows": {name: {metric: mean}}, "scenes": [{"index", name: {metric}}...]}.

    done: scene records of an earlier, interrupted run with the same settings (their scenes are
    not redone); on_scene: called with the partial result after every scene (to save it).
    workers: scenes evaluated at once, each in its own process with one thread (0: one per core;
    CPU only). The records do not depend on it beyond float rounding.

    dataset: a TransparentSceneDataset (test split, not augmented). Surfaces are made in each
    scene's hull-normalized frame (PNet's, from meta.json) and scored against the GT in its own
    unit-sphere frame. The networks and the rendering layer run on `device`; feature mapping and
    Poisson on the CPU. ior: the IoR every stage assumes for every scene (the paper's "var. IoR"
    rows hold 1.4723); None: each scene's own. The ground truth is the scene's own either way."""
    reporter = reporter or Reporter(quiet=True)
    n = len(dataset) if not max_scenes else min(max_scenes, len(dataset))
    scenes = [record for record in (done or []) if record["index"] < n]
    finished = {record["index"] for record in scenes}
    todo = [i for i in range(n) if i not in finished]
    args = (dataset, weights, point_weights, tuple(strategies), normals or NormalStageConfig(),
            surface or SurfaceConfig(), refine, ior)
    records = map_scenes(_ShapeEvaluation, args, todo, workers, device)
    for record in reporter.track(records, total=len(todo), description="test scenes"):
        scenes.append(record)
        if on_scene is not None:
            on_scene(summarize(scenes))
    return summarize(scenes)


class _ShapeEvaluation:
    """What every scene's evaluation needs: the dataset, the networks (loaded once) and settings."""

    def __init__(self, dataset, weights: Path | None, point_weights: Path | None, strategies: tuple[str, ...],
                 normals: NormalStageConfig, surface: SurfaceConfig, refine: RefineConfig | None = None,
                 ior: float | None = None, device: str = "cpu"):
        self.dataset, self.strategies, self.normals, self.surface, self.device = (dataset, strategies, normals,
                                                                                 surface, device)
        self.refine, self.ior = refine, ior
        self.weights = load_normal_net(weights) if weights is not None else None
        self.point_net = load_point_net(point_weights) if point_weights is not None else None
        if self.weights is not None:
            self.weights.net.to(device)
        if self.point_net is not None:
            self.point_net.net.to(device)

    def scene(self, i: int) -> dict:
        """{"index": i, row: metrics} for test scene i, on `reconstruct`'s path: the scene as a
        capture, its stored hull, `run_normal_stage`, `surface_from_normals`."""
        capture, hull = self.dataset.capture(i, self.ior), self.dataset.hull(i)
        gt = self.dataset.meshes(i)[0]
        sample = self.dataset[i]
        record = {"index": i, "vh": self._scored(hull.mesh, gt, capture)}
        # Ground-truth first-hit normals at the dataset's resolution: what mapping + Poisson reach
        # with perfect normals (their own rendering error is the layer's residual, taken as 0).
        mask = sample["mask"].bool()
        V, H, W = mask.shape
        truth = NormalMaps(capture.cameras.with_resolution(W, H), sample["n1"].permute(0, 2, 3, 1).float(),
                           sample["n2"].permute(0, 2, 3, 1).float(), torch.zeros(mask.shape), sample["tir"].bool() & mask,
                           mask)
        record["vh+gt-normals"] = _surface_metrics(hull, gt, truth, self._surface(self.strategies[0]), None)[1]
        if self.weights is not None:
            normals = run_normal_stage(capture, hull.mesh, self.weights, self.normals, self.device)
            maps = normals.maps
            for strategy in self.strategies:
                record[f"normals-{strategy}"] = _surface_metrics(hull, gt, maps, self._surface(strategy), None)[1]
            if self.point_net is not None:  # PNet maps with the strategy it was trained on
                mesh, record[f"pnet-{self.point_net.strategy}"] = _surface_metrics(
                    hull, gt, maps, self.surface, self.point_net, lambda m, g: self._scored(m, g, capture))
                if mesh is not None and self.refine is not None:  # as reconstruct's refine stage, on that surface
                    refined = refine_stage(capture, hull, mesh, self.weights, self.refine, self.device)
                    record["refined"] = {**self._scored(refined.mesh, gt, capture), "kept": refined.report["kept"],
                                         "iou_mean_input_refined": refined.report["silhouette_iou_mean"],
                                         # the penalty rounds run and the one returned, and what they cost
                                         "rounds": len(refined.report.get("silhouette_rounds", [None])),
                                         "round": refined.report.get("silhouette_round", 0),
                                         # what each pass kept (`passes`): "refined" twice where the second
                                         # pass's mesh was kept
                                         "passes": [p["kept"] for p in refined.report["passes"]],
                                         # and whether each kept its normal term's steps (None: the term did not run)
                                         "normal_term_kept": [p.get("normal_term_kept") for p in refined.report["passes"]],
                                         "seconds": refined.report["seconds"],
                                         # whether the input was cut to the hull first (its input carve)
                                         "input_carved": bool(refined.report.get("input_carve", {}).get("kept")),
                                         **({"kept_why": refined.report["kept_why"]}
                                            if "kept_why" in refined.report else {})}
        return record

    def _scored(self, mesh, gt, capture) -> dict:
        """Shape metrics against the ground truth; with the refine row, also against the photos."""
        metrics = shape_metrics(mesh, gt)
        if self.refine is not None:
            metrics["rerender"] = rerender(mesh, capture, threads=1).mean_error
            metrics["iou_min"] = float(silhouette_iou(mesh, capture.cameras, capture.masks).min())
        return metrics

    def _surface(self, strategy: str) -> SurfaceConfig:
        return dataclasses.replace(self.surface, strategy=strategy)


def summarize(scenes: list[dict]) -> dict:
    """{"rows": means of every row's metrics over the scenes it did not fail on, "scenes": ...}."""
    scenes = sorted(scenes, key=lambda record: record["index"])
    names = list(dict.fromkeys(k for s in scenes for k in s if k != "index"))
    rows = {}
    for name in names:
        ok = [s[name] for s in scenes if name in s and "error" not in s[name]]
        rows[name] = {m: float(np.mean([s[m] for s in ok])) if ok else float("nan") for m in METRICS}
        rows[name].update({m: float(np.mean([s[m] for s in ok])) for m in PHOTO_METRICS
                           if ok and all(m in s for s in ok)})
        rows[name]["failed"] = len(scenes) - len(ok)
    return {"rows": rows, "scenes": scenes}


def _surface_metrics(hull: VisualHull, gt, maps: NormalMaps, cfg: SurfaceConfig, point_net, score=shape_metrics,
                     ) -> tuple[object, dict]:
    """(`surface_from_normals`' mesh, `score(mesh, gt)`), or (None, {"error": ...}) when it failed: a
    failed Poisson is recorded, not hidden."""
    try:
        mesh = surface_from_normals(hull, maps, cfg, point_net)[0]
    except LookingGlassError as exc:
        return None, {"error": str(exc)}
    return mesh, score(mesh, gt)


def markdown_table(rows: dict) -> str:
    """Table 2/3 as markdown; with the re-rendering error and worst silhouette IoU columns when any row has
    them ("-" in the rows that do not)."""
    photo = any(m in r for r in rows.values() for m in PHOTO_METRICS)
    extra = " re-rendering error | worst view's silhouette IoU |" if photo else ""
    lines = ["| | CD (×1e4) | CDN-mean (°) | CDN-med (°) | Metro (×1e3) |" + extra + " failed |",
             "|---|---|---|---|---|" + ("---|---|" if photo else "") + "---|"]
    for name, r in rows.items():
        cells = f" {r['cd']:.2f} | {r['cdn_mean']:.2f} | {r['cdn_med']:.2f} | {r['metro']:.2f} |"
        if photo:
            cells += "".join(f" {r[m]:.4f} |" if m in r else " - |" for m in PHOTO_METRICS)
        lines.append(f"| {name} |{cells} {r['failed']} |")
    return "\n".join(lines)
