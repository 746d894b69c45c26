"""Training of the normal network: what one step computes (`NormalInputs.from_sample` ->
`network_tensors` -> the net -> `normal_loss`, the inference path's own inputs); its config,
`TrainConfig`, is lookingglass.normals.config's (no torch there: the command line reads it before
torch loads), the named presets lookingglass.presets'. The loop itself (Adam, the paper's step schedule,
checkpoints and exact resume, progress, metrics.jsonl, DistributedDataParallel under torchrun)
is lookingglass.training's.

RUN_DIR holds: config.json (the resolved TrainConfig), checkpoint.pt, metrics.jsonl (one line
per epoch: epoch, step, lr, loss, loss_hull, seconds, processes), and at the end
weights.safetensors + weights.json (the network config), the files `reconstruct` loads.
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

from .. import training
from ..progress import Reporter
from ..weights import DEFAULT_ENVMAP_HEIGHT
from .config import NORMAL_LOSSES, VARIANTS, TrainConfig  # noqa: F401 (re-exported)
from .inputs import NormalInputs, mirror_vector_maps, network_tensors
from .model import HULL_N1_CHANNELS, HULL_N2_CHANNELS, NormalNet


# ---- one scene -> network tensors ---------------------------------------------------------------
def select_views(sample: dict, count: int, generator: torch.Generator) -> dict:
    """`count` random views of a scene sample (per-view keys sliced; the envmap kept)."""
    V = sample["mask"].shape[0]
    if not count or count >= V:
        return sample
    pick = torch.randperm(V, generator=generator)[:count].sort().values
    return {k: (v[pick] if isinstance(v, Tensor) and v.dim() > 0 and v.shape[0] == V and k != "envmap" else v)
            for k, v in sample.items()}


def normal_targets(sample: dict, device: str = "cpu") -> dict:
    """The ground truth of one dataset scene the loss reads: n1, n2 (V,3,H,W), mask and n2_valid
    (V,H,W) bool (N2 is supervised where the true path has exactly two interfaces)."""
    mask = sample["mask"].to(device).bool()
    return dict(n1=sample["n1"].to(device).float(), n2=sample["n2"].to(device).float(), mask=mask,
                n2_valid=sample["valid"].to(device).bool() & mask)


def mirror_targets(t: dict) -> dict:
    """`normal_targets` of the scene's mirror image (`NormalInputs.mirrored`'s world): the maps'
    columns reversed, the camera-frame normals' x negated."""
    vectors = lambda n: mirror_vector_maps(n.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)  # noqa: E731 (V,3,H,W)
    return dict(n1=vectors(t["n1"]), n2=vectors(t["n2"]), mask=t["mask"].flip(2), n2_valid=t["n2_valid"].flip(2))


# Charbonnier width of the angle loss, in chord length (|n - t| = 2 sin(angle / 2)): ~1.1 degrees.
ANGLE_LOSS_EPS = 0.02


def pixel_loss(n: Tensor, t: Tensor, kind: str = "l2") -> Tensor:
    """Per-pixel loss of unit normals n, t (B,3,H,W) -> (B,1,H,W). l2: |n - t|^2 ~ angle^2, which
    spends the net on the pixels the hull has badly wrong (the paper's); angle: sqrt(|n - t|^2 +
    eps^2) - eps ~ the angle, so adding 3 degrees where the hull is within 2 costs as much as
    removing 3 from a 20-degree error (issue 27: the net must not make a good hull worse)."""
    sq = ((n - t) ** 2).sum(1, keepdim=True)
    if kind == "l2":
        return sq
    return (sq + ANGLE_LOSS_EPS ** 2).sqrt() - ANGLE_LOSS_EPS


def normal_loss(n1: Tensor, n2: Tensor, t: dict, kind: str = "l2", hull: tuple[Tensor, Tensor] | None = None,
                hinge: float = 0.0) -> Tensor:
    """L_N: the per-pixel loss (`pixel_loss`; the paper's squared L2) of N1 over the mask plus N2
    over pixels with a valid GT N2. With `hull` (the hull's N1, N2 the net was fed) and `hinge` > 0,
    each pixel also adds hinge * max(0, its loss - the hull's): a pixel the net makes worse than
    its input weighs 1 + hinge times (where the hull has no second hit its N2 is zero, a large loss,
    so the hinge leaves those pixels alone)."""
    hull1, hull2 = hull if hull is not None else (None, None)
    total = 0.0
    for n, h, target, valid in ((n1, hull1, t["n1"], t["mask"]), (n2, hull2, t["n2"], t["n2_valid"])):
        m = valid.unsqueeze(1).float()
        per_pixel = pixel_loss(n, target, kind)
        if hinge and h is not None:
            with torch.no_grad():
                per_hull = pixel_loss(h, target, kind)
            per_pixel = per_pixel + hinge * (per_pixel - per_hull).clamp(min=0)
        total = total + (per_pixel * m).sum() / m.sum().clamp(min=1)
    return total


# A pixel whose true path has no second interface has no usable N2: following the predicted N2
# there gains this much (a loss: its N2 must not be followed).
NO_N2_GAIN_DEG = -10.0


def angle_deg(n: Tensor, t: Tensor) -> Tensor:
    """Angle (degrees) between unit normals n, t (B,3,H,W) -> (B,H,W)."""
    return torch.rad2deg(torch.acos((n * t).sum(1).clamp(-1, 1)))


def gain_head_loss(gain: Tensor, n1: Tensor, n2: Tensor, hull1: Tensor, hull2: Tensor, t: dict,
                   quantile: float) -> Tensor:
    """The pinball loss of the predicted gains `gain` (B,2,H,W, degrees) against the true ones,
    the hull's angle error minus the prediction's at each hit (hull1, hull2 (B,3,H,W) the hull's
    normals, zero where its path does not exist: those pixels do not count), so `gain` learns
    their `quantile`; where the true path has no second interface the N2 gain is NO_N2_GAIN_DEG."""
    with torch.no_grad():
        g1 = angle_deg(hull1, t["n1"]) - angle_deg(n1, t["n1"])
        g2 = torch.where(t["n2_valid"], angle_deg(hull2, t["n2"]) - angle_deg(n2, t["n2"]),
                         torch.full_like(g1, NO_N2_GAIN_DEG))
        hull_exists = (hull1.norm(dim=1) > 0.5) & (hull2.norm(dim=1) > 0.5)
    m = (t["mask"] & hull_exists).float()
    total = 0.0
    for k, g in enumerate((g1, g2)):
        r = g - gain[:, k]
        total = total + ((torch.maximum(quantile * r, (quantile - 1) * r) * m).sum() / m.sum().clamp(min=1))
    return total


# ---- the loop -----------------------------------------------------------------------------------
def train_normals(dataset, run_dir: str | os.PathLike, config: TrainConfig, device: str = "cpu",
                  reporter: Reporter | None = None, max_steps: int | None = None) -> dict:
    """Train on `dataset` (a torch Dataset of scenes); resumes from RUN_DIR/checkpoint.pt.

    The loop, files and torchrun behaviour are lookingglass.training's: under torchrun each
    process takes its share of the scenes per epoch and DDP averages the gradients. One step is
    one scene (`views_per_step` random views of it). metrics.jsonl logs, beside the net's loss,
    `loss_hull`: the same loss for the hull's own normals, what the net must beat. Returns the
    last epoch's metrics.
    """
    session = training.TrainingSession(run_dir, config, device, reporter)
    # the rendering layer's map size; inference resizes a capture's map to it
    envmap_height = int(dataset.config.envmap_height) if hasattr(dataset, "config") else DEFAULT_ENVMAP_HEIGHT
    device = session.device  # under torchrun on GPUs: this process's own

    def step(model: torch.nn.Module, index: int, global_step: int) -> tuple[Tensor, dict[str, float]]:
        draws = torch.Generator().manual_seed(config.seed * 1_000_003 + global_step)
        sample = select_views(dataset[index], config.views_per_step, draws)
        x, t = NormalInputs.from_sample(sample, config.ior, device), normal_targets(sample, device)
        if config.mirror_augment and bool(torch.rand((), generator=draws) < 0.5):
            x, t = x.mirrored(), mirror_targets(t)
        inputs, cost_volume = network_tensors(x, config.net)
        if config.gain_head_only:
            n1, n2, gain = model(inputs, cost_volume, with_gain=True)
            return gain_head_loss(gain, n1, n2, inputs[:, HULL_N1_CHANNELS], inputs[:, HULL_N2_CHANNELS], t,
                                  config.gain_quantile), {
                "loss_normals": float(normal_loss(n1, n2, t, config.loss))}
        n1, n2 = model(inputs, cost_volume)
        hull = (inputs[:, HULL_N1_CHANNELS], inputs[:, HULL_N2_CHANNELS])
        with torch.no_grad():
            loss_hull = float(normal_loss(*hull, t, config.loss))
        return normal_loss(n1, n2, t, config.loss, hull, config.hull_hinge), {"loss_hull": loss_hull}

    def make_net() -> NormalNet:
        net = NormalNet(config.net)
        only = "gain_head." if config.gain_head_only else "detail_head." if config.detail_head_only else None
        if only:  # Adam skips what needs no gradient; the rest stays as --init gave it
            for name, p in net.named_parameters():
                p.requires_grad_(name.startswith(only))
        elif config.net.gain_head:  # no loss reads it here (and DDP refuses weights without a gradient): kept as
            for name, p in net.named_parameters():  # --init gave it, to be retrained with --gain-head-only
                p.requires_grad_(not name.startswith("gain_head."))
        return net

    return session.fit(make_net, len(dataset), step,
                       weights_extra=lambda steps: {"kind": "normals", "steps": steps,
                                                    "views": config.net.num_views,
                                                    "envmap_height": envmap_height},
                       labels={"loss_normals": "normals"} if config.gain_head_only else {"loss_hull": "hull normals"},
                       max_steps=max_steps)
