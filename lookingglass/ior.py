"""The object's index of refraction estimated from the photos (`reconstruct --ior auto`, issue 22).

The reconstructed mesh is re-rendered as glass (`render.compare.rerender`, the re-rendering check's
renderer and photo normalization) at candidate IoRs IOR_STEP apart over the range asked for: the cost is the
mean over the pixels inside both the mask and the mesh's silhouette of min(|render - photo|,
ERROR_CLIP) per channel; the estimate is the minimum of the parabola through the lowest candidate and
its neighbours, its uncertainty the bootstrap standard deviation over views.

The estimate is only as good as the shape rendered: a shape that refracts wrongly matches the photos
best where it refracts least, so errors in the mesh bias the estimate LOW (measured: with the true
shape it is within 0.01; with the final mesh of 480x360 captures within 0.02 where the curve is deep,
0.07-0.17 low where it is flat; with a 128x96 capture's hull at the range's end; docs/results.md,
"Estimating the IoR"). So the pipeline estimates it last, from the kept (refined) mesh, and calls the
estimate reliable only where the cost curve is deep enough (max / min >= MIN_CONTRAST), its minimum
inside the range and the photos at least RELIABLE_MIN_WIDTH wide. The stages before assume IOR_GLASS (the networks' training IoR): a wrong IoR moves
the final mesh by ~1% in CD (docs/results.md, the variable-IoR tables), so they are not run again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import trimesh

from .errors import LookingGlassError
from .physics.constants import IOR_GLASS
from .render.compare import photos_at, rerender

IOR_STEP = 0.025  # candidate spacing: the parabola then resolves ~0.005
ERROR_CLIP = 0.05  # per-channel difference beyond which a pixel counts as unexplained (normalized photos)
ESTIMATE_WIDTH = 120  # render width: 240 px measured no better on the validation set, at twice the time
BOOTSTRAP = 200
# The cost curve's highest value over its lowest. Where the mesh explains too little of the photos for
# the IoR to change much (validation set: bracket, mug, finned body 1.02), the minimum is not the IoR.
MIN_CONTRAST = 1.05
# Photos narrower than this: the flag is not to be trusted. At 128x96 (the variable-IoR test split) the estimate
# is 0.09 off in the median with curves as deep as those of good 480x360 meshes; widths between are unmeasured.
RELIABLE_MIN_WIDTH = 480


@dataclass
class IorEstimate:
    """value: the estimate; uncertainty: its bootstrap standard deviation over views (it does not
    cover a biased shape); candidates (K,) and cost (K,) the curve minimized; at_bound: the minimum
    is at an end of the range; contrast: the curve's max over its min; seconds: time taken;
    photo_width: the capture's width in pixels."""

    value: float
    uncertainty: float
    candidates: np.ndarray
    cost: np.ndarray
    at_bound: bool
    contrast: float
    seconds: float
    photo_width: int

    @property
    def reliable(self) -> bool:
        """The minimum is inside the range, the curve deep enough (MIN_CONTRAST) to mean it, and the
        photos as wide as those it was validated on (RELIABLE_MIN_WIDTH)."""
        return not self.at_bound and self.contrast >= MIN_CONTRAST and self.photo_width >= RELIABLE_MIN_WIDTH

    def report(self) -> dict:
        return {"value": round(self.value, 4), "uncertainty": round(self.uncertainty, 4),
                "reliable": self.reliable, "contrast": round(self.contrast, 4), "photo_width": self.photo_width,
                "range": [float(self.candidates[0]), float(self.candidates[-1])], "at_bound": self.at_bound,
                "candidates": [round(float(c), 4) for c in self.candidates],
                "cost": [round(float(c), 5) for c in self.cost], "seconds": round(self.seconds, 2)}


def assumed_ior(ior_range: tuple[float, float]) -> float:
    """The IoR the stages assume before the estimate: the networks' training IoR, moved into the range."""
    return float(np.clip(IOR_GLASS, *ior_range))


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
    """The IoR in `ior_range` at which `mesh` (closed, outward, the capture's frame) rendered as
    glass best explains `capture`'s photos (module docstring). capture: a loaded `Capture`."""
    start = time.perf_counter()
    candidates = candidate_iors(ior_range)
    sums = np.zeros((len(candidates), capture.num_views))  # per candidate and view: clipped differences
    prepared = photos_at(capture, width)  # the same photos for every candidate
    for k, ior in enumerate(candidates):
        shown = rerender(mesh, capture, width, samples_per_axis=1, device=device, seed=seed, ior=float(ior),
                         prepared=prepared)
        region = shown.masks & shown.silhouettes  # the silhouette is the mesh's: the same at any IoR
        clipped = np.minimum(np.abs(shown.renders - shown.photos), ERROR_CLIP).mean(axis=-1)
        sums[k] = (clipped * region).sum(axis=(1, 2))
    counts = region.sum(axis=(1, 2)).astype(np.float64)
    if counts.sum() == 0:
        raise LookingGlassError("the mesh's silhouette meets no mask: nothing to estimate the IoR from",
                                getattr(capture, "root", None))
    cost = sums.sum(axis=1) / counts.sum()
    value = parabola_minimum(cost, candidates)
    draws = np.random.default_rng(seed).integers(0, capture.num_views, size=(BOOTSTRAP, capture.num_views))
    boot = [parabola_minimum(sums[:, d].sum(axis=1) / max(counts[d].sum(), 1), candidates) for d in draws]
    i = int(np.argmin(cost))
    return IorEstimate(value, float(np.std(boot)), candidates, cost, i in (0, len(cost) - 1),
                       float(cost.max() / max(cost.min(), 1e-12)), time.perf_counter() - start,
                       int(capture.masks.shape[2]))
