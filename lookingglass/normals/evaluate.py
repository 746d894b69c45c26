"""The paper's Table 1 on a test split: N1/N2 angle errors and render error for the visual hull
and each trained variant (basic, wr, wr+cv), plus wr+cv with latent optimization (wr+cv+op) and
with the views' consensus (wr+cv+mv, normals/consensus.py: what `reconstruct`'s normal stage
outputs), and the ground-truth normals' render error (row gt, a reference: what the two-bounce
rendering layer misses even with the true normals).

Statistics pool every pixel of every view of every scene: N1 over the object mask, N2 over the
pixels whose true path has exactly two interfaces (the dataset's `valid`), render error over the
mask (mean squared difference of the rendering layer's image, clipped to [0, 1] like the
normalized input, and that input, x 1e-2
in the table, as the paper reports it). Each row is scored at the size it is made (the nets' own;
the hull's and the truth's rows at the first net's): a split rendered at another size, as a
capture's 480x360, has its truth traced from the ground-truth mesh there.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..config import VIEW_CONSENSUS_PX
from ..metrics import normal_angles
from ..parallel import map_scenes
from ..progress import Reporter
from ..render.tracer import trace_two_bounce
from ..weights import DEFAULT_ENVMAP_HEIGHT, load_normal_net
from .inputs import NormalInputs
from .latent import LatentOptConfig
from .predict import NormalMaps, predict_normals, render_normals
from .train import normal_targets


def _angles(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    """Angles in degrees between (V,H,W,3) normal maps over mask (V,H,W) (a missing normal, zero,
    scores 90 degrees: the hull's N2 where its path ends and the truth's goes on)."""
    mask = mask.bool().to(a.device)
    return normal_angles(a[mask].double().cpu(), b.to(a.device)[mask].double().cpu())


@dataclass
class NormalErrors:
    """Pools the angle errors and squared render error of one row of Table 1 over scenes."""

    n1: list = field(default_factory=list)
    n2: list = field(default_factory=list)
    sq_err: float = 0.0
    count: int = 0
    seconds: float = 0.0

    def add(self, maps: NormalMaps, truth: dict, seconds: float = 0.0) -> None:
        """One scene's maps (`predict_normals` / `render_normals`) against its ground truth
        (`normal_targets`: n1, n2 (V,3,H,W), mask, n2_valid (V,H,W))."""
        self.n1.append(_angles(maps.n1, truth["n1"].permute(0, 2, 3, 1), truth["mask"]))
        self.n2.append(_angles(maps.n2, truth["n2"].permute(0, 2, 3, 1), truth["n2_valid"]))
        self.sq_err += 3 * float(maps.error[maps.mask].sum())  # error is the mean over RGB
        self.count += 3 * int(maps.mask.sum())
        self.seconds += seconds

    def merge(self, other: NormalErrors) -> None:
        """Pool another scene's (or worker's) errors into these."""
        self.n1 += other.n1
        self.n2 += other.n2
        self.sq_err += other.sq_err
        self.count += other.count
        self.seconds += other.seconds

    def summary(self) -> dict:
        n1, n2 = np.concatenate(self.n1), np.concatenate(self.n2)
        return {"n1_median": float(np.median(n1)), "n1_mean": float(n1.mean()), "n2_median": float(np.median(n2)),
                "n2_mean": float(n2.mean()), "render_error": self.sq_err / max(self.count, 1)}


@dataclass
class NormalTable:
    """Table 1: rows pooled over every pixel of every scene ({row: NormalErrors.summary() and
    seconds_per_scene}, in the table's order), and each scene's own ({"index", "ior": the scene's
    true IoR, "rows": {row: summary}}, by index) for plots against a scene property."""

    rows: dict[str, dict]
    scenes: list[dict]


def evaluate_normals(dataset, weights: dict[str, Path], latent: LatentOptConfig | None = None,
                     max_scenes: int = 0, reporter: Reporter | None = None, device: str = "cpu",
                     workers: int = 1, ior: float | None = None,
                     consensus_px: float = VIEW_CONSENSUS_PX, mirror_average: bool = True) -> NormalTable:
    """Table 1. weights maps a variant name (basic, wr, wr+cv) to its weights file; `wr+cv+op` is
    added when wr+cv is given and `latent` is not None, `wr+cv+mv` when wr+cv is given and
    consensus_px > 0 (the consensus of wr+cv's normals, averaged with the mirror image's where
    `mirror_average`, without latent optimization: `reconstruct`'s normal stage). Runs on
    `device`. workers: scenes evaluated at once, each in its own process with one thread (0: one
    per core; CPU only); the pooled statistics do not depend on it beyond float rounding. ior: the
    IoR the inputs, the rendering layer and the latent optimization assume for every scene (the
    paper's "var. IoR" rows hold 1.4723 while the photos have others); None: each scene's own. The
    ground truth is the scene's own either way."""
    reporter = reporter or Reporter(quiet=True)
    n = len(dataset) if not max_scenes else min(max_scenes, len(dataset))
    per_scene = map_scenes(_NormalEvaluation, (dataset, dict(weights), latent, ior, consensus_px, mirror_average),
                           list(range(n)), workers, device)
    rows: dict[str, NormalErrors] = {}
    scenes = []
    for index, scene_rows in reporter.track(per_scene, total=n, description="test scenes"):
        for name, errors in scene_rows.items():
            rows.setdefault(name, NormalErrors()).merge(errors)
        scenes.append({"index": index, "ior": float(dataset.meta(index)["ior"]),
                       "rows": {name: errors.summary() for name, errors in scene_rows.items()}})
    order = ["vh", *weights, "wr+cv+op", "wr+cv+mv", "gt"]  # the row order, whatever order the scenes finished in
    return NormalTable({name: {**rows[name].summary(), "seconds_per_scene": rows[name].seconds / max(n, 1)}
                        for name in order if name in rows}, sorted(scenes, key=lambda s: s["index"]))


class _NormalEvaluation:
    """What every scene's evaluation needs: the dataset, the networks (loaded once) and settings."""

    def __init__(self, dataset, weights: dict[str, Path], latent: LatentOptConfig | None, ior: float | None = None,
                 consensus_px: float = 0.0, mirror_average: bool = False, device: str = "cpu"):
        self.dataset, self.latent, self.ior, self.device = dataset, latent, ior, device
        self.consensus_px, self.mirror_average = consensus_px, mirror_average
        self.nets = {name: load_normal_net(path) for name, path in weights.items()}
        for w in self.nets.values():
            w.net.to(device)

    def scene(self, i: int) -> tuple[int, dict[str, NormalErrors]]:
        """i and every row's errors on test scene i, on `reconstruct`'s path: the inputs are made
        from the scene as a capture and its hull (`NormalInputs.from_capture`)."""
        capture, hull = self.dataset.capture(i, self.ior), self.dataset.hull(i)
        stored = normal_targets(self.dataset[i], self.device)
        truths = {tuple(stored["mask"].shape[1:]): stored}

        def truth_at(width: int, height: int) -> dict:
            """The ground truth at a net's size: the stored maps where the dataset was rendered at
            it, else traced from the ground-truth mesh (a split rendered at a capture's 480x360, the
            nets at 128x96), so every row is scored at the size it was made."""
            if (height, width) not in truths:
                meta = self.dataset.meta(i)
                truths[(height, width)] = traced_targets(self.dataset.meshes(i)[0],
                                                         capture.cameras.with_resolution(width, height),
                                                         float(meta["ior"]), float(meta["ext_ior"]), self.device)
            return truths[(height, width)]

        made: dict[tuple, NormalInputs] = {}  # nets of one size and map height share their inputs

        def inputs(width: int, height: int, envmap_height: int) -> NormalInputs:
            key = (width, height, envmap_height)
            if key not in made:
                made[key] = NormalInputs.from_capture(capture.images, capture.masks, capture.envmap, capture.cameras,
                                                      capture.ior, hull.mesh, width, height, envmap_height,
                                                      device=self.device)
            return made[key]

        rows: dict[str, NormalErrors] = {}
        for name, w in self.nets.items():
            x = inputs(w.net.cfg.width, w.net.cfg.height, w.envmap_height)
            runs = [(name, None, 0.0, False)]
            runs += [("wr+cv+op", self.latent, 0.0, False)] if name == "wr+cv" and self.latent else []
            if name == "wr+cv" and self.consensus_px > 0:
                runs += [("wr+cv+mv", None, self.consensus_px, self.mirror_average)]
            for row, latent, consensus_px, mirror_average in runs:
                start = time.perf_counter()
                maps = predict_normals(w.net, x, latent, consensus_px, mirror_average)
                rows.setdefault(row, NormalErrors()).add(maps, truth_at(w.net.cfg.width, w.net.cfg.height),
                                                         time.perf_counter() - start)
        # the hull's and the truth's rows where the (first) net is scored, so their ratios compare
        # like with like; without nets at the dataset's size
        first = next(iter(self.nets.values()), None)
        H, W = (first.net.cfg.height, first.net.cfg.width) if first else stored["mask"].shape[1:]
        truth = truth_at(W, H)
        x = inputs(W, H, first.envmap_height if first else DEFAULT_ENVMAP_HEIGHT)
        rows["vh"] = NormalErrors()
        rows["vh"].add(render_normals(x, x.vh_n1, x.vh_n2), truth)
        # The ground truth's own render error, a reference: the two-bounce layer cannot render the
        # pixels whose light takes more interfaces or none after the first (angle errors 0 here).
        rows["gt"] = NormalErrors()
        rows["gt"].add(render_normals(x, truth["n1"].permute(0, 2, 3, 1), truth["n2"].permute(0, 2, 3, 1)), truth)
        return i, rows


def traced_targets(mesh, cameras, ior: float, ext_ior: float, device: str = "cpu") -> dict:
    """`normal_targets`' dict for `mesh` (the ground truth, world frame) seen by `cameras`, traced at
    the pixel centres as the dataset's own maps are (`trace_two_bounce`)."""
    tb = trace_two_bounce(mesh, cameras, ior, ext_ior, threads=1)
    mask = tb.mask.to(device)
    return dict(n1=tb.normal1.permute(0, 3, 1, 2).to(device), n2=tb.normal2.permute(0, 3, 1, 2).to(device),
                mask=mask, n2_valid=tb.valid.to(device) & mask)


def markdown_table(results: dict[str, dict]) -> str:
    lines = ["| | N1 median (°) | N1 mean (°) | N2 median (°) | N2 mean (°) | render error (×1e-2) |",
             "|---|---|---|---|---|---|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['n1_median']:.2f} | {r['n1_mean']:.2f} | {r['n2_median']:.2f} | "
                     f"{r['n2_mean']:.2f} | {100 * r['render_error']:.2f} |")
    return "\n".join(lines)
