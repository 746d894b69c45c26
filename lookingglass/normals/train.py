"""Training of the normal network: Adam, the paper's step schedule, checkpoints and resume,
progress, a metrics log, and DistributedDataParallel under torchrun (gloo on CPU, nccl on GPU).

RUN_DIR holds: config.json (the resolved TrainConfig), checkpoint.pt (model + optimizer + step,
written atomically every `checkpoint_every` steps and loaded with weights_only=True),
metrics.jsonl (one line per epoch), and at the end weights.safetensors + weights.json (the
network config), the files `reconstruct` loads.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.distributed as dist
from safetensors.torch import load_file, save_file
from torch import Tensor

from ..configio import config_from_dict
from ..errors import LookingGlassError
from ..fileio import write_atomic, write_json
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


# The paper's ablations (Table 1): (use_error_map, use_cost_volume).
VARIANTS = {"basic": (False, False), "wr": (True, False), "wr+cv": (True, True)}


def train_preset(name: str, views: int = 10) -> TrainConfig:
    if name not in PRESETS:
        raise LookingGlassError(f"unknown preset '{name}' (choose from {', '.join(PRESETS)})")
    net = PRESETS[name](num_views=views)
    if name == "cpu":
        # The CPU budget (~75 minutes on 2 cores, ~2.5 s a step): 2 epochs over ~700 scenes,
        # 4 random views a step (more scenes per second than all 10), a higher rate halved once.
        return TrainConfig(net=net, epochs=2, lr=4e-4, lr_halve_epochs=1, views_per_step=4)
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


# ---- checkpoints --------------------------------------------------------------------------------
def save_checkpoint(path: Path, net: torch.nn.Module, opt: torch.optim.Optimizer, step: int, epoch: int) -> None:
    state = {"model": net.state_dict(), "optim": opt.state_dict(), "step": step, "epoch": epoch}
    write_atomic(path, lambda tmp: torch.save(state, tmp))


def load_checkpoint(path: Path) -> dict:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a checkpoint is ours, but the user may hand us anything
        raise LookingGlassError(f"cannot read checkpoint ({exc})", path) from None


def save_weights(run_dir: Path, net: NormalNet, extra: dict | None = None) -> Path:
    """The shipped form: safetensors weights + the network config as JSON."""
    state = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    write_atomic(run_dir / "weights.safetensors", lambda tmp: save_file(state, str(tmp)))
    write_json(run_dir / "weights.json", {"net": dataclasses.asdict(net.cfg), **(extra or {})})
    return run_dir / "weights.safetensors"


def load_weights(path: str | os.PathLike) -> NormalNet:
    """Load weights.safetensors and its weights.json beside it (never unpickles)."""
    path = Path(path)
    meta_path = path.with_suffix(".json")
    if not path.exists():
        raise LookingGlassError("weights file not found", path)
    if not meta_path.exists():
        raise LookingGlassError("network config not found beside the weights", meta_path)
    meta = json.loads(meta_path.read_text())
    cfg = config_from_dict(NormalNetConfig, meta["net"], where=str(meta_path))
    net = NormalNet(cfg)
    try:
        net.load_state_dict(load_file(str(path)))
    except Exception as exc:
        raise LookingGlassError(f"weights do not fit the network config ({exc})", path) from None
    return net.eval()


# ---- the loop -----------------------------------------------------------------------------------
def _dist_info() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def train_normals(dataset, run_dir: str | os.PathLike, config: TrainConfig, device: str = "cpu",
                  reporter: Reporter | None = None, max_steps: int | None = None) -> dict:
    """Train on `dataset` (a torch Dataset of scenes); resumes from RUN_DIR/checkpoint.pt.

    Under torchrun (WORLD_SIZE set) each process takes its share of the scenes per epoch
    (DistributedSampler) and gradients are averaged by DDP. Returns the last epoch's metrics.
    """
    run_dir = Path(run_dir)
    ddp = "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1
    if ddp and not dist.is_initialized():
        dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
    rank, world = _dist_info()
    reporter = reporter or Reporter(quiet=rank != 0)
    if rank != 0:
        reporter = Reporter(quiet=True)
    run_dir.mkdir(parents=True, exist_ok=True)
    cfg_path = run_dir / "config.json"
    cfg_dict = dataclasses.asdict(config)
    if cfg_path.exists():
        saved = json.loads(cfg_path.read_text())
        if saved != json.loads(json.dumps(cfg_dict)):
            raise LookingGlassError("run folder holds a different config; use a new --out or the same settings",
                                    cfg_path)
    elif rank == 0:
        write_json(cfg_path, cfg_dict)

    torch.manual_seed(config.seed)
    net = NormalNet(config.net).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=config.lr)
    step, start_epoch = 0, 0
    ckpt_path = run_dir / "checkpoint.pt"
    if ckpt_path.exists():
        ckpt = load_checkpoint(ckpt_path)
        net.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optim"])
        step, start_epoch = int(ckpt["step"]), int(ckpt["epoch"])
        reporter.info(f"resuming from step {step} (epoch {start_epoch + 1})")
    model = torch.nn.parallel.DistributedDataParallel(net) if ddp else net

    n = len(dataset) if not config.max_scenes else min(config.max_scenes, len(dataset))
    steps_per_epoch = math.ceil(n / world)
    metrics: dict = {}
    for epoch in range(start_epoch, config.epochs):
        lr = config.lr * 0.5 ** (epoch // config.lr_halve_epochs)
        for g in opt.param_groups:
            g["lr"] = lr
        order = torch.randperm(n, generator=torch.Generator().manual_seed(config.seed + epoch)).tolist()
        mine = order[rank::world][:steps_per_epoch]
        done_in_epoch = step - epoch * steps_per_epoch
        losses, hull_losses, start = [], [], time.perf_counter()
        for i in reporter.track(mine[done_in_epoch:], description=f"epoch {epoch + 1}/{config.epochs}"):
            sample = select_views(dataset[i], config.views_per_step,
                                  torch.Generator().manual_seed(config.seed * 1_000_003 + step))
            t = scene_tensors(sample, config.net, config.ior, device)
            n1, n2 = model(t["inputs"], t["cost_volume"])
            loss = normal_loss(n1, n2, t)
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
            with torch.no_grad():  # the same loss for the hull's own normals: what the net must beat
                hull_n1, hull_n2 = t["inputs"][:, HULL_N1_CHANNELS], t["inputs"][:, HULL_N2_CHANNELS]
                hull_losses.append(float(normal_loss(hull_n1, hull_n2, t)))
            step += 1
            if step % config.checkpoint_every == 0 and rank == 0:
                save_checkpoint(ckpt_path, net, opt, step, epoch)
            if max_steps is not None and step >= max_steps:
                break
        metrics = {"epoch": epoch + 1, "step": step, "lr": lr, "loss": sum(losses) / max(len(losses), 1),
                   "loss_hull": sum(hull_losses) / max(len(hull_losses), 1),
                   "seconds": round(time.perf_counter() - start, 2), "processes": world}
        if rank == 0:
            with open(run_dir / "metrics.jsonl", "a") as f:
                f.write(json.dumps(metrics) + "\n")
            save_checkpoint(ckpt_path, net, opt, step, epoch + 1 if len(losses) == len(mine[done_in_epoch:]) else epoch)
            reporter.info(f"epoch {epoch + 1}: loss {metrics['loss']:.4f}, hull normals {metrics['loss_hull']:.4f} "
                          f"(lr {lr:.1e}, {metrics['seconds']} s)")
        if max_steps is not None and step >= max_steps:
            break
    if rank == 0:
        save_weights(run_dir, net, {"steps": step, "views": config.net.num_views})
    if ddp:
        dist.barrier()
    return metrics
