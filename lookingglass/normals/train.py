"""Training of the normal network: what one step computes (`scene_tensors`, `normal_loss`) and
the presets. The loop itself (Adam, the paper's step schedule, checkpoints and exact resume,
progress, metrics.jsonl, DistributedDataParallel under torchrun) is lookingglass.training's.

RUN_DIR holds: config.json (the resolved TrainConfig), checkpoint.pt, metrics.jsonl (one line
per epoch: epoch, step, lr, loss, loss_hull, seconds, processes), and at the end
weights.safetensors + weights.json (the network config), the files `reconstruct` loads.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from .. import training
from ..errors import LookingGlassError
from ..physics.camera import Cameras
from ..physics.environment import EnvironmentMap
from ..progress import Reporter
from .inputs import hull_error_maps
from .model import (HULL_N1_CHANNELS, HULL_N2_CHANNELS, PRESETS, NormalNet, NormalNetConfig, build_cost_volume,
                    network_inputs)


@dataclass
class TrainConfig:
    """lr halves every `lr_halve_epochs` (the paper: 1e-4, halved every 2 of 10 epochs)."""

    net: NormalNetConfig = field(default_factory=NormalNetConfig)
    epochs: int = 10
    lr: float = 1e-4
    lr_halve_epochs: int = 2
    checkpoint_every: int = 50
    seed: int = 0
    ior: float = 1.4723
    augment: bool = True
    max_scenes: int = 0  # 0: all
    views_per_step: int = 0  # 0: every view of the scene; k: k random views (views are independent images)
    init: str = ""  # weights to fine-tune from ("" : random start)


# The paper's ablations (Table 1): (use_error_map, use_cost_volume).
VARIANTS = {"basic": (False, False), "wr": (True, False), "wr+cv": (True, True)}


def train_preset(name: str, views: int = 10) -> TrainConfig:
    if name not in PRESETS:
        raise LookingGlassError(f"unknown preset '{name}' (choose from {', '.join(PRESETS)})")
    net = PRESETS[name](num_views=views)
    if name == "cpu":
        # 8 epochs over ~600 scenes, 4 random views a step (more scenes per second than all 10), a
        # higher rate halved every 3 epochs: ~80 minutes under torchrun on 2 cores (~10 min an
        # epoch). The earlier 2 epochs, halved after 1, stopped while the loss still fell: the same
        # data for 8 epochs took the test N1 median from 0.88 to 0.73 x the hull's (docs/history.md).
        return TrainConfig(net=net, epochs=8, lr=4e-4, lr_halve_epochs=3, views_per_step=4)
    return TrainConfig(net=net)


# ---- one scene -> network tensors ---------------------------------------------------------------
def select_views(sample: dict, count: int, generator: torch.Generator) -> dict:
    """`count` random views of a scene sample (per-view keys sliced; the envmap kept)."""
    V = sample["mask"].shape[0]
    if not count or count >= V:
        return sample
    pick = torch.randperm(V, generator=generator)[:count].sort().values
    return {k: (v[pick] if isinstance(v, Tensor) and v.dim() > 0 and v.shape[0] == V and k != "envmap" else v)
            for k, v in sample.items()}


def scene_tensors(sample: dict, cfg: NormalNetConfig, ior: float, device: str = "cpu") -> dict:
    """Network inputs and targets of one dataset scene (see data/torch_dataset.py for the keys):
    returns inputs (V,C,H,W), cost_volume (V,K²,8,H,W) or None, gt n1/n2 (V,3,H,W), masks, and
    the rendering context (envmap, cameras, image (V,H,W,3), mask (V,H,W))."""
    s = {k: (v.to(device) if isinstance(v, Tensor) else v) for k, v in sample.items()}
    image = s["image"].permute(0, 2, 3, 1).float()
    mask = s["mask"].bool()
    V, H, W = mask.shape
    cams = Cameras.look_at(s["origin"].cpu(), s["target"].cpu(), s["up"].cpu(), s["fov_x_deg"].cpu(), W, H,
                           device=device)
    env = EnvironmentMap(s["envmap"].permute(1, 2, 0).float())
    vh_n1, vh_n2 = s["vh_n1"].permute(0, 2, 3, 1).float(), s["vh_n2"].permute(0, 2, 3, 1).float()
    vh_error = vh_tir = None
    if cfg.use_error_map:
        vh_error, vh_tir = hull_error_maps(env, image, mask, vh_n1, vh_n2, cams, ior)
    cost_volume = None
    if cfg.use_cost_volume:
        cost_volume = build_cost_volume(env, image, mask, vh_n1, vh_n2, cams, cfg.theta_deg, cfg.cost_volume_k, ior)
    return dict(inputs=network_inputs(image, mask, vh_n1, vh_n2, vh_error, vh_tir), cost_volume=cost_volume,
                n1=s["n1"].float(), n2=s["n2"].float(), mask=mask, n2_valid=s["valid"].bool() & mask,
                image=image, envmap=env, cameras=cams)


def normal_loss(n1: Tensor, n2: Tensor, t: dict) -> Tensor:
    """The paper's L_N: squared L2 of N1 over the mask plus N2 over pixels with a valid GT N2."""
    m1 = t["mask"].unsqueeze(1).float()
    m2 = t["n2_valid"].unsqueeze(1).float()
    l1 = (((n1 - t["n1"]) ** 2) * m1).sum() / m1.sum().clamp(min=1)
    l2 = (((n2 - t["n2"]) ** 2) * m2).sum() / m2.sum().clamp(min=1)
    return l1 + l2


# The loop's checkpoint helpers, importable from here as before.
save_checkpoint, load_checkpoint = training.save_checkpoint, training.load_checkpoint


# ---- weights -------------------------------------------------------------------------------------
def save_weights(run_dir: Path, net: NormalNet, extra: dict | None = None) -> Path:
    """The shipped form: safetensors weights + the network config as JSON."""
    return training.save_weights(run_dir, net, {"kind": "normals", **(extra or {})})


def load_weights(path: str | os.PathLike) -> NormalNet:
    """Load weights.safetensors and its weights.json beside it (never unpickles)."""
    net, _ = training.load_weights(path, NormalNetConfig, NormalNet, kind="normals")
    return net  # type: ignore[return-value]


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
    device = session.device  # under torchrun on GPUs: this process's own

    def step(model: torch.nn.Module, index: int, global_step: int) -> tuple[Tensor, dict[str, float]]:
        sample = select_views(dataset[index], config.views_per_step,
                              torch.Generator().manual_seed(config.seed * 1_000_003 + global_step))
        t = scene_tensors(sample, config.net, config.ior, device)
        n1, n2 = model(t["inputs"], t["cost_volume"])
        with torch.no_grad():
            hull_n1, hull_n2 = t["inputs"][:, HULL_N1_CHANNELS], t["inputs"][:, HULL_N2_CHANNELS]
            loss_hull = float(normal_loss(hull_n1, hull_n2, t))
        return normal_loss(n1, n2, t), {"loss_hull": loss_hull}

    return session.fit(lambda: NormalNet(config.net), len(dataset), step,
                       weights_extra=lambda steps: {"kind": "normals", "steps": steps,
                                                    "views": config.net.num_views},
                       labels={"loss_hull": "hull normals"}, max_steps=max_steps)
