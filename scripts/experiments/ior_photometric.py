"""An experiment, not shipped (issue 22, `--ior auto`): the IoR estimated from the photos by rendering a mesh
(the visual hull) as glass at candidate IoRs and keeping the one whose render matches the photos best.

The estimator: candidates IOR_STEP apart over the range; the project's renderer (`render_views`) at 120 px wide,
1 spp; photos normalized as the re-rendering check does (`render.compare.photos_at`); cost = mean over the pixels
inside mask and silhouette of min(|render - photo|, ERROR_CLIP) per channel; parabola through the minimum;
uncertainty = bootstrap over views. ~1 s a candidate for 10 views here, 17 candidates.

Why it is not shipped: it is only as good as the shape rendered, and a wrong shape biases it LOW (its render
matches a photo best where it refracts least, whatever the statistic). Measured 2026-11-25:
- the true mesh: within 0.01 (val480 duck 1.473, bracket 1.474, key 1.471; an ellipsoid at 1.6: 1.600 +- 0.01);
- the hull, val480 (480x360, 10 views, true 1.4723): duck -0.016, key -0.005, nut -0.032, pebble -0.015, mug -0.114,
  bracket -0.172 (the final mesh instead: -0.002, -0.006, -0.019, -0.016, -0.083, -0.154);
- the hull of a convex ellipsoid (10 views, true 1.6): 480x360 -0.025, 240x180 -0.05 to -0.07, 120x90 -0.08 to -0.14;
- the hull on the 128x96 variable-IoR test split: 1.300, the range's end, on scenes 0-2 (true 1.671, 1.691, 1.474);
  the normal net's predicted normals through the render layer give the same;
- statistics tried, all biased the same way: mean, median, 25th percentile, clipped at 0.02/0.05/0.10, inlier share,
  per-pixel votes, normalized cross-correlation of the images and of their gradients.
The curve's contrast (max / min cost) flags the worst cases (mug, bracket: 1.02; good hulls 1.04-1.13) but not the
bias of a fair hull (the 120x90 ellipsoid: 1.10, 0.08 low). What it would take: the shape and the IoR optimized
together (the refine stage's photometric term with the IoR as a variable), or networks trained on a range of IoRs.

Usage, on a variable-IoR split (`lookingglass generate --split test --ior-range 1.3 1.7 --ior-per-shape 5`):
    .venv/bin/python scripts/experiments/ior_photometric.py DATA [FIRST LAST] [--json OUT.json]
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.hull import HullConfig, carve_visual_hull
from lookingglass.physics.environment import EnvironmentMap
from lookingglass.render.compare import photos_at
from lookingglass.render.tracer import RenderConfig, render_views

IOR_STEP = 0.025  # candidate spacing: the parabola then resolves ~0.005
ERROR_CLIP = 0.05  # per-channel difference beyond which a pixel counts as unexplained (normalized photos)
ESTIMATE_WIDTH = 120  # render width: a quarter of a 480x360 capture, ~0.3 s for 10 views a candidate
BOOTSTRAP = 200
# The cost curve's highest value over its lowest: where the hull explains too little of the photos
# for the IoR to change much (bracket, mug: 1.02), the minimum is not the object's IoR.
MIN_CONTRAST = 1.05


@dataclass
class IorEstimate:
    """value: the estimate; uncertainty: its bootstrap standard deviation over views (it does not
    cover the hull's bias); candidates (K,) and cost (K,) the curve it minimizes; at_bound: the
    minimum is at an end of the range; contrast: the curve's max over its min."""

    value: float
    uncertainty: float
    candidates: np.ndarray
    cost: np.ndarray
    at_bound: bool
    contrast: float
    seconds: float

    @property
    def reliable(self) -> bool:
        """The minimum is inside the range and the curve deep enough (MIN_CONTRAST) to mean it."""
        return not self.at_bound and self.contrast >= MIN_CONTRAST

    def report(self) -> dict:
        return {"value": round(self.value, 4), "uncertainty": round(self.uncertainty, 4),
                "reliable": self.reliable, "contrast": round(self.contrast, 4),
                "range": [float(self.candidates[0]), float(self.candidates[-1])], "at_bound": self.at_bound,
                "candidates": [round(float(c), 4) for c in self.candidates],
                "cost": [round(float(c), 5) for c in self.cost], "seconds": round(self.seconds, 2)}


def candidate_iors(ior_range: tuple[float, float], step: float = IOR_STEP) -> np.ndarray:
    """IoRs from LO to HI (both included) about `step` apart, at least 5."""
    lo, hi = ior_range
    count = max(5, int(round((hi - lo) / step)) + 1)
    return np.linspace(lo, hi, count)


def parabola_minimum(cost: np.ndarray, candidates: np.ndarray) -> float:
    """The abscissa of the minimum of the parabola through the lowest cost and its neighbours
    (the lowest candidate itself at an end of the range or where the curve is not convex)."""
    i = int(np.argmin(cost))
    if i == 0 or i == len(cost) - 1:
        return float(candidates[i])
    a, b, c = cost[i - 1], cost[i], cost[i + 1]
    curvature = a - 2 * b + c
    offset = 0.5 * (a - c) / curvature if curvature > 0 else 0.0
    return float(candidates[i] + np.clip(offset, -1, 1) * (candidates[i + 1] - candidates[i]))


def estimate_ior(mesh: trimesh.Trimesh, capture, ior_range: tuple[float, float], width: int = ESTIMATE_WIDTH,
                 device: str = "cpu", seed: int = 0) -> IorEstimate:
    """The IoR in `ior_range` at which `mesh` (closed, the capture's frame; the visual hull) rendered
    as glass best explains `capture`'s photos (module docstring). capture: a loaded `Capture`."""
    start = time.perf_counter()
    photos, masks, factor = photos_at(capture, width)
    height, width = masks.shape[1:]
    cams = capture.cameras.with_resolution(width, height)
    envmap = EnvironmentMap(torch.as_tensor(capture.envmap).float())
    candidates = candidate_iors(ior_range)
    # per candidate and view: the sum of clipped differences and the pixel count it is over
    sums = np.zeros((len(candidates), capture.num_views))
    counts = np.zeros(capture.num_views)
    for k, ior in enumerate(candidates):
        result = render_views(mesh, envmap, cams, RenderConfig(ior=float(ior), samples_per_axis=1, seed=seed,
                                                               device=device))
        renders = (result.image.cpu() * factor).clamp(0, 1)
        region = (masks & result.mask.cpu()).float()
        clipped = (renders - photos).abs().clamp(max=ERROR_CLIP).mean(dim=-1)
        sums[k] = (clipped * region).sum(dim=(1, 2)).numpy()
        counts = region.sum(dim=(1, 2)).numpy()  # the same at every candidate: the silhouette is the mesh's
    if counts.sum() == 0:
        raise ValueError("the mesh's silhouette meets no mask: nothing to estimate the IoR from")
    cost = sums.sum(axis=1) / counts.sum()
    value = parabola_minimum(cost, candidates)
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, capture.num_views, size=(BOOTSTRAP, capture.num_views))
    boot = [parabola_minimum(sums[:, d].sum(axis=1) / max(counts[d].sum(), 1), candidates) for d in draws]
    i = int(np.argmin(cost))
    return IorEstimate(value, float(np.std(boot)), candidates, cost, i in (0, len(cost) - 1),
                       float(cost.max() / max(cost.min(), 1e-12)), time.perf_counter() - start)


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    out = sys.argv[sys.argv.index("--json") + 1] if "--json" in sys.argv else None
    if out in args:
        args.remove(out)
    ds = TransparentSceneDataset(args[0], "test", views=10)
    first, last = (int(args[1]), int(args[2])) if len(args) > 2 else (0, len(ds))
    rows = []
    for i in range(first, min(last, len(ds))):
        cap = ds.capture(i)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            hull = carve_visual_hull(cap.masks, cap.cameras, HullConfig())
        est = estimate_ior(hull.mesh, cap, (1.3, 1.7))
        rows.append({"scene": i, "true": cap.ior, "estimate": est.value, "uncertainty": est.uncertainty,
                     "at_bound": est.at_bound, "seconds": est.seconds})
        err = np.abs([r["estimate"] - r["true"] for r in rows])
        print(f"{i} true {cap.ior:.4f} est {est.value:.4f} +- {est.uncertainty:.4f} ({est.seconds:.1f} s)  "
              f"median |err| so far {np.median(err):.4f} over {len(rows)}", flush=True)
    err = np.abs([r["estimate"] - r["true"] for r in rows])
    summary = {"scenes": len(rows), "median_abs_error": float(np.median(err)), "mean_abs_error": float(err.mean()),
               "within_0.03": float((err <= 0.03).mean()),
               "within_2_sigma": float(np.mean([abs(r["estimate"] - r["true"]) <= 2 * r["uncertainty"] for r in rows]))}
    print(json.dumps(summary))
    if out:
        json.dump({"summary": summary, "rows": rows}, open(out, "w"), indent=1)
