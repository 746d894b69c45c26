"""The `normals` stage of `reconstruct`: hull two-bounce maps -> NNet (+ cost volume) -> latent
optimization, with per-view outputs for people and for the next stage.

Writes OUT/normals/view_XX.npz (n1, n2 camera frame float32 (H,W,3); mask, tir bool (H,W);
render_error float32 (H,W), the per-pixel squared error of the re-rendering, mean over RGB) and
OUT/normals/view_XX.png (input | hull normals | predicted normals | re-rendered image).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh

from ..capture.images import write_image
from ..fileio import write_atomic
from ..viz import normal_map_rgb, tonemap
from .inputs import NormalInputs, prepare_inputs
from .latent import LatentOptConfig, optimize_latent
from .model import NormalNet, build_cost_volume, network_inputs
from .render_layer import comparable, prediction_error_maps
from .train import load_weights

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"
TRAINED_VIEWS = (5, 10, 20)


@dataclass
class NormalStageConfig:
    """weights: a weights.safetensors path, or "" for the shipped weights of the view count
    nearest `views` (0: the capture's view count). latent: the post-processing (iterations 0 = off)."""

    weights: str = ""
    views: int = 0
    latent: LatentOptConfig = field(default_factory=LatentOptConfig)


def shipped_weights(num_views: int, net: str = "normals") -> tuple[Path | None, int]:
    """The packaged weights of `net` ("normals" or "points") for the trained view count nearest
    `num_views` (None if none ship)."""
    available = [v for v in TRAINED_VIEWS if (WEIGHTS_DIR / f"{net}_{v:02d}views.safetensors").exists()]
    if not available:
        return None, 0
    best = min(available, key=lambda v: (abs(v - num_views), -v))
    return WEIGHTS_DIR / f"{net}_{best:02d}views.safetensors", best


def predict_normals(net: NormalNet, x: NormalInputs, latent: LatentOptConfig | None, ior: float):
    """(n1, n2) (V,H,W,3) camera frame from the network, optionally latent-optimized."""
    cfg = net.cfg
    vh_err = x.vh_error if cfg.use_error_map else None
    inputs = network_inputs(x.image, x.mask, x.vh_n1, x.vh_n2, vh_err, x.vh_tir)
    cv = build_cost_volume(x.envmap, x.image, x.mask, x.vh_n1, x.vh_n2, x.cameras, cfg.theta_deg,
                           cfg.cost_volume_k, ior) if cfg.use_cost_volume else None
    if latent is not None and latent.iterations_n2 + latent.iterations_both > 0:
        n1, n2, _ = optimize_latent(net, inputs, cv, x.envmap, x.image, x.mask, x.cameras, latent)
    else:
        with torch.no_grad():
            n1, n2 = net(inputs, cv)
    return n1.detach().permute(0, 2, 3, 1), n2.detach().permute(0, 2, 3, 1)


@dataclass
class NormalStageResult:
    """report: figures for report.json. cameras: the views at the network's resolution; n1
    (V,H,W,3) camera frame; error (V,H,W) per-pixel squared re-rendering error (0 off the mask);
    tir, mask (V,H,W) bool: what feature mapping reads."""

    report: dict
    cameras: object
    n1: torch.Tensor
    error: torch.Tensor
    tir: torch.Tensor
    mask: torch.Tensor


def run_normal_stage(images: np.ndarray, masks: np.ndarray, envmap: np.ndarray, cameras, hull: trimesh.Trimesh,
                     ior: float, out_dir: Path, config: NormalStageConfig, weights_path: Path,
                     device: str = "cpu") -> NormalStageResult:
    """The networks and the rendering layer run on `device`; the result is on the CPU."""
    net = load_weights(weights_path).to(device)
    meta = json.loads(weights_path.with_suffix(".json").read_text())
    x = prepare_inputs(torch.from_numpy(images), torch.from_numpy(masks), torch.from_numpy(envmap), cameras, hull,
                       net.cfg.width, net.cfg.height, int(meta.get("envmap_height", 128)), ior, device=device)
    n1, n2 = predict_normals(net, x, config.latent, ior)
    err_vh, _, _ = prediction_error_maps(x.envmap, x.vh_n1, x.vh_n2, x.cameras, x.image, x.mask, ior)
    err_pred, tir, pred_render = prediction_error_maps(x.envmap, n1, n2, x.cameras, x.image, x.mask, ior)
    n1, n2, m, tir, err_vh, err_pred = (t.cpu() for t in (n1, n2, x.mask, tir, err_vh, err_pred))
    image, vh_n1, rendered = x.image.cpu(), x.vh_n1.cpu(), pred_render.image.cpu()
    folder = out_dir / "normals"
    folder.mkdir(parents=True, exist_ok=True)
    for v in range(len(m)):
        arrays = dict(n1=n1[v].numpy(), n2=n2[v].numpy(), mask=m[v].numpy(), tir=tir[v].numpy(),
                      render_error=err_pred[v].numpy())
        write_atomic(folder / f"view_{v:02d}.npz", lambda p, a=arrays: np.savez_compressed(p, **a))
        panels = [tonemap(image[v].numpy()), normal_map_rgb(vh_n1[v].numpy(), m[v].numpy()),
                  normal_map_rgb(n1[v].numpy(), m[v].numpy()),
                  # the re-rendering inside the mask, the photo around it (off the mask there are no normals)
                  tonemap(torch.where(m[v, ..., None], comparable(rendered[v]), image[v]).numpy())]
        gap = np.ones((panels[0].shape[0], 3, 3), np.float32)
        write_image(folder / f"view_{v:02d}.png", np.concatenate([panels[0], gap, panels[1], gap, panels[2], gap,
                                                                  panels[3]], axis=1), encoding="linear")
    count = max(int(m.sum()), 1)
    report = {"weights": str(weights_path), "network_size": [net.cfg.width, net.cfg.height],
              "render_error_vh": float(err_vh[m].sum()) / count, "render_error": float(err_pred[m].sum()) / count,
              "latent_iterations": [config.latent.iterations_n2, config.latent.iterations_both]}
    return NormalStageResult(report, x.cameras.to("cpu"), n1, err_pred, tir, m)
