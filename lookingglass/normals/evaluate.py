"""The paper's Table 1 on a test split: N1/N2 angle errors and render error for the visual hull
and each trained variant (basic, wr, wr+cv), plus wr+cv with latent optimization (wr+cv+op), and
the ground-truth normals' render error (row gt, a reference: what the two-bounce rendering layer
misses even with the true normals).

Statistics pool every pixel of every view of every scene: N1 over the object mask, N2 over the
pixels whose true path has exactly two interfaces (the dataset's `valid`), render error over the
mask (mean squared difference of the rendering layer's image, clipped to [0, 1] like the
normalized input, and that input, x 1e-2
in the table, as the paper reports it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..parallel import map_scenes
from ..progress import Reporter
from .latent import LatentOptConfig, optimize_latent
from .render_layer import comparable, render_layer
from .train import load_weights, scene_tensors


def _angles(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    """Angles in degrees between (V,3,H,W) normal maps over mask (V,H,W)."""
    a = torch.nn.functional.normalize(a.permute(0, 2, 3, 1)[mask], dim=-1)
    b = torch.nn.functional.normalize(b.permute(0, 2, 3, 1)[mask], dim=-1)
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b, dim=-1).norm(dim=-1), (a * b).sum(-1))).cpu().numpy()


@dataclass
class NormalErrors:
    """Pools the angle errors and squared render error of one row of Table 1 over scenes."""

    n1: list = field(default_factory=list)
    n2: list = field(default_factory=list)
    sq_err: float = 0.0
    count: int = 0
    seconds: float = 0.0

    def add(self, n1, n2, t, seconds=0.0):
        self.n1.append(_angles(n1, t["n1"], t["mask"]))
        self.n2.append(_angles(n2, t["n2"], t["n2_valid"]))
        out = render_layer(t["envmap"], n1.permute(0, 2, 3, 1), n2.permute(0, 2, 3, 1), t["cameras"])
        m = t["mask"]
        self.sq_err += float(((comparable(out.image) - t["image"])[m] ** 2).sum())
        self.count += int(m.sum()) * 3
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


def evaluate_normals(dataset, weights: dict[str, Path], latent: LatentOptConfig | None = None,
                     max_scenes: int = 0, reporter: Reporter | None = None, device: str = "cpu",
                     workers: int = 1) -> dict[str, dict]:
    """Rows of Table 1. weights maps a variant name (basic, wr, wr+cv) to its weights file;
    `wr+cv+op` is added when wr+cv is given and `latent` is not None. Runs on `device`.
    workers: scenes evaluated at once, each in its own process with one thread (0: one per core;
    CPU only); the pooled statistics do not depend on it beyond float rounding."""
    reporter = reporter or Reporter(quiet=True)
    n = len(dataset) if not max_scenes else min(max_scenes, len(dataset))
    per_scene = map_scenes(_NormalEvaluation, (dataset, dict(weights), latent), list(range(n)), workers, device)
    rows: dict[str, NormalErrors] = {}
    for scene_rows in reporter.track(per_scene, total=n, description="test scenes"):
        for name, errors in scene_rows.items():
            rows.setdefault(name, NormalErrors()).merge(errors)
    order = ["vh", *weights, "wr+cv+op", "gt"]  # the table's row order, whatever order the scenes finished in
    return {name: {**rows[name].summary(), "seconds_per_scene": rows[name].seconds / max(n, 1)}
            for name in order if name in rows}


class _NormalEvaluation:
    """What every scene's evaluation needs: the dataset, the networks (loaded once) and settings."""

    def __init__(self, dataset, weights: dict[str, Path], latent: LatentOptConfig | None, device: str = "cpu"):
        self.dataset, self.latent, self.device = dataset, latent, device
        self.nets = {name: load_weights(path).to(device) for name, path in weights.items()}

    def scene(self, i: int) -> dict[str, NormalErrors]:
        """Every row's errors on test scene i."""
        device, sample = self.device, self.dataset[i]
        rows = {"vh": NormalErrors()}
        base = None
        for name, net in self.nets.items():
            t = scene_tensors(sample, net.cfg, 1.4723, device)
            base = base or t
            start = time.perf_counter()
            with torch.no_grad():
                n1, n2 = net(t["inputs"], t["cost_volume"])
            rows.setdefault(name, NormalErrors()).add(n1, n2, t, time.perf_counter() - start)
            if name == "wr+cv" and self.latent is not None:
                start = time.perf_counter()
                o1, o2, _ = optimize_latent(net, t["inputs"], t["cost_volume"], t["envmap"], t["image"], t["mask"],
                                            t["cameras"], self.latent)
                rows.setdefault("wr+cv+op", NormalErrors()).add(o1.detach(), o2.detach(), t,
                                                                time.perf_counter() - start)
        if base is None:
            from .model import NormalNetConfig

            base = scene_tensors(sample, NormalNetConfig(use_error_map=False, use_cost_volume=False), 1.4723, device)
        vh1 = sample["vh_n1"].to(device).float() * base["mask"].unsqueeze(1)
        rows["vh"].add(vh1, sample["vh_n2"].to(device).float(), base)
        # The ground truth's own render error, a reference: the two-bounce layer cannot render the
        # pixels whose light takes more interfaces or none after the first (angle errors 0 here).
        rows["gt"] = NormalErrors()
        rows["gt"].add(base["n1"], base["n2"], base)
        return rows


def markdown_table(results: dict[str, dict]) -> str:
    lines = ["| | N1 median (°) | N1 mean (°) | N2 median (°) | N2 mean (°) | render error (×1e-2) |",
             "|---|---|---|---|---|---|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['n1_median']:.2f} | {r['n1_mean']:.2f} | {r['n2_median']:.2f} | "
                     f"{r['n2_mean']:.2f} | {100 * r['render_error']:.2f} |")
    return "\n".join(lines)
