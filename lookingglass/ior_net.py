"""A learned IoR estimate (`reconstruct --ior auto`, issue 22): the photos against a mesh of the object
rendered as glass at candidate IoRs, read by a small network.

The photometric search in `ior.py` renders the *final* mesh at each candidate and keeps the best
match; where that mesh is off (CAD parts at 480x360, any 128x96 capture) a wrong shape matches best
where it refracts least and the estimate runs low. Here the comparison is learned instead: per view,
the normalized photo, the mask, the mesh's two-bounce normals and, for each candidate IoR, the
per-pixel difference between the photo and the mesh re-traced and rendered at that IoR by the
paper's rendering layer (`normals/render_layer.py`) where that layer explains the pixel. The net
reads the cost curve those give over the candidates (plain, and weighted by a per-pixel trust it
learns) beside features pooled over each view's mask, and gives a distribution over IoR bins: its
mean is the estimate, its spread the uncertainty. Trained on scenes of known IoR with their visual
hulls carved as `reconstruct` carves them, it learns how a mesh's errors bend the curve; `reconstruct`
feeds it the mesh it kept (the refined one by default), which is closer to the object than the hull,
and the closer the mesh the better the reading. The inputs are built from `NormalInputs`, the normal
stage's own inputs, by `scene_inputs`, which both `reconstruct` and the training cache call.

Measured (docs/results.md, "Glass of unknown IoR"): on the variable-IoR test split (128x96) the
median error is 0.025 reading the refined mesh (0.044 reading the hull; the search on the refined
mesh 0.091); on 480x360 captures the search is better where its checks pass, so `reconstruct` takes
the net's value only where they do not (0.015 so; the search alone 0.025, the net alone 0.030).
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from torch import Tensor, nn
from torch.nn import functional as F

from .errors import LookingGlassError
from .fileio import write_atomic
from .ior_net_config import IorNetConfig, IorTrainConfig  # noqa: F401 (re-exported)
from .normals.inputs import NormalInputs
from .normals.render_layer import error_map, render_layer
from .physics.constants import IOR_GLASS
from .progress import Reporter
from .render.raycast import RayCaster
from .render.tracer import trace_two_bounce


def ior_net_inputs(x: NormalInputs, hull: trimesh.Trimesh, candidates: list[float]) -> Tensor:
    """(V, C, H, W) float32: x's photo, mask, hull normals (traced at x.ior) and, for each candidate
    IoR, the mean over RGB of |photo - the hull traced and rendered at that IoR|, then where that is
    meaningful: inside the mask, on a two-bounce path that leaves the glass (the layer renders
    neither TIR nor longer paths, and counting them biases the match low: with the true shape the
    lowest error is at the lowest IoR; without them it is at the truth, tests/test_ior_net.py)."""
    mask = x.mask.unsqueeze(-1).float()
    channels = [x.image * mask, mask, x.vh_n1 * mask, x.vh_n2 * x.vh_valid.unsqueeze(-1), x.vh_valid.unsqueeze(-1).float()]
    caster = RayCaster(hull)
    for ior in candidates:
        tb = trace_two_bounce(hull, x.cameras, ior=float(ior), device=x.image.device, caster=caster)
        out = render_layer(x.envmap, tb.normal1, tb.normal2, x.cameras, ior=float(ior))
        explained = (tb.valid & ~out.tir & x.mask).unsqueeze(-1)
        channels += [error_map(x.image, out.image, x.mask).mean(-1, keepdim=True) * explained, explained.float()]
    return torch.cat(channels, dim=-1).permute(0, 3, 1, 2).contiguous()


class IorNet(nn.Module):
    """Views (B, V, C, H, W) and masks (B, V, H, W) -> logits (B, bins) over `cfg.bin_centres()`.

    Two readings of the same inputs. The cost curve: for each candidate, the error summed over every
    view's explained pixels over their count (what a search would minimize), given to the head as its
    shape (each value over the curve's mean, minus 1), its level and each candidate's explained
    share, once over all pixels and once weighted by a learned per-pixel trust (where the hull's
    error curve is worth reading); the head learns how a hull's errors bend it. And the pixels: averaged over 2 x 2,
    mixed per pixel, two strided 3 x 3 convolutions, pooled over each view's mask, then the mean and
    mean spread over the views that see the object. Small on purpose: ~40 M multiply-adds a
    128 x 96 view, trained on a laptop CPU in minutes."""

    def __init__(self, cfg: IorNetConfig):
        super().__init__()
        self.cfg = cfg
        k = len(cfg.candidates)
        w1, w2, w3 = cfg.widths
        self.pixel = nn.Sequential(nn.Conv2d(cfg.in_channels, w1, 1), nn.ReLU(inplace=True), nn.Conv2d(w1, w1, 1),
                                   nn.ReLU(inplace=True))
        self.context = nn.Sequential(nn.Conv2d(w1, w2, 3, stride=2, padding=1), nn.GroupNorm(8, w2),
                                     nn.ReLU(inplace=True), nn.Conv2d(w2, w3, 3, stride=2, padding=1),
                                     nn.GroupNorm(8, w3), nn.ReLU(inplace=True))
        self.trust = nn.Conv2d(w1, 1, 1)  # per pixel: how much its error curve says about the IoR
        self.head = nn.Sequential(nn.Linear(2 * (w1 + w3) + 3 * k + 2, 128), nn.ReLU(inplace=True),
                                  nn.Linear(128, 128), nn.ReLU(inplace=True), nn.Linear(128, cfg.bins))

    @staticmethod
    def cost_curve(views: Tensor, weight: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The curve over the candidates (B, K) of the weighted error over the weighted explained
        pixels, its shape (each value over the mean, minus 1, x 10), its log level (B, 1) and the
        explained share of the weight (B, K). views (B, V, C, H, W); weight (B, V, 1, H, W)."""
        error = (views[:, :, 11::2] * weight).sum((1, 3, 4))  # (B, K)
        explained = (views[:, :, 12::2] * weight).sum((1, 3, 4))
        curve = error / explained.clamp(min=1e-6)
        level = curve.mean(-1, keepdim=True).clamp(min=1e-6)
        share = explained / weight.sum((1, 2, 3, 4)).unsqueeze(-1).clamp(min=1e-6)
        return 10 * (curve / level - 1), torch.log(level), share

    def forward(self, views: Tensor, masks: Tensor) -> Tensor:
        B, V = views.shape[:2]
        x = F.avg_pool2d(views.flatten(0, 1), 2)
        m = F.avg_pool2d(masks.flatten(0, 1).unsqueeze(1).float(), 2)
        per_pixel = self.pixel(x)
        around = self.context(per_pixel)
        m_low = F.adaptive_avg_pool2d(m, around.shape[-2:])
        pooled = torch.cat([(per_pixel * m).sum((2, 3)) / m.sum((2, 3)).clamp(min=1e-6),
                            (around * m_low).sum((2, 3)) / m_low.sum((2, 3)).clamp(min=1e-6)], dim=-1)
        per_view = pooled.view(B, V, -1)
        weight = (m.view(B, V, -1).sum(-1) > 0).float().unsqueeze(-1)  # views that see the object
        mean = (per_view * weight).sum(1) / weight.sum(1).clamp(min=1)
        spread = ((per_view - mean.unsqueeze(1)).abs() * weight).sum(1) / weight.sum(1).clamp(min=1)
        low = x.view(B, V, *x.shape[1:])
        plain_shape, plain_level, share = self.cost_curve(low, m.view(B, V, 1, *m.shape[-2:]))
        trust = torch.sigmoid(self.trust(per_pixel)) * m  # (B*V, 1, h, w)
        trusted_shape, trusted_level, _ = self.cost_curve(low, trust.view(B, V, 1, *m.shape[-2:]))
        return self.head(torch.cat([mean, spread, plain_shape, plain_level, share, trusted_shape, trusted_level],
                                   dim=-1))


def posterior_estimate(logits: Tensor, centres: Tensor, ior_range: tuple[float, float] | None = None
                       ) -> tuple[Tensor, Tensor]:
    """(mean, standard deviation) of the softmax over the bins, restricted to `ior_range` where
    given (the user's range; at least the nearest bin is kept)."""
    logits = logits.clone()
    if ior_range is not None:
        outside = (centres < ior_range[0] - 1e-9) | (centres > ior_range[1] + 1e-9)
        if outside.all():
            outside = torch.ones_like(outside)
            outside[torch.argmin((centres - float(np.clip(np.mean(ior_range), centres[0], centres[-1]))).abs())] = False
        logits[..., outside] = -torch.inf
    p = torch.softmax(logits, dim=-1)
    mean = (p * centres).sum(-1)
    std = (p * (centres - mean.unsqueeze(-1)) ** 2).sum(-1).sqrt()
    return mean, std


def soft_labels(ior: Tensor, centres: Tensor, sigma: float = 0.01) -> Tensor:
    """(B, bins) Gaussian targets around each true IoR (B,), normalized."""
    w = torch.exp(-0.5 * ((centres.unsqueeze(0) - ior.unsqueeze(-1)) / sigma) ** 2)
    return w / w.sum(-1, keepdim=True)


# ---- training ---------------------------------------------------------------------------------------
# The networks' image size: the normal net's (the capture is resized to it) and its map height.
IOR_NET_WIDTH, IOR_NET_HEIGHT, IOR_NET_ENVMAP_HEIGHT = 128, 96, 128
# Half the training scenes are seen as 8-bit sRGB photos with sensor noise up to this sigma (of full
# scale, in sRGB: ~5 levels), as from a phone.
PHOTO_NOISE_MAX = 0.02


def scene_inputs(images, masks, envmap, cameras, mesh: trimesh.Trimesh, cfg: IorNetConfig,
                 device: str = "cpu") -> tuple[Tensor, Tensor]:
    """The net's inputs (V, C, H, W) and masks (V, H, W) for one capture (linear images, the
    capture's masks, map and cameras) and a mesh of its object: what `reconstruct` (its kept mesh)
    and the training cache (the visual hull) both compute. The mesh is traced at IOR_GLASS for its
    normals, as the normal stage does."""
    x = NormalInputs.from_capture(images, masks, envmap, cameras, IOR_GLASS, mesh, IOR_NET_WIDTH, IOR_NET_HEIGHT,
                                  IOR_NET_ENVMAP_HEIGHT, device=device)
    return ior_net_inputs(x, mesh, cfg.candidates), x.mask


def cache_path(run_dir: Path, dataset, index: int) -> Path:
    return run_dir / "features" / f"{dataset.scene_dirs[index].name}.npz"


def prepare_cache(dataset, run_dir: Path, config: IorTrainConfig, reporter: Reporter, rank: int = 0,
                  world: int = 1) -> int:
    """Each scene's inputs in RUN_DIR/features/scene_NNNNN.npz (float16 views, mask, true IoR), made
    once (resumable: finished files are kept); a scene is drawn as a noisy 8-bit photo with
    probability `photo_noise` (seeded by its number). Returns how many were made."""
    from .capture.images import exposure_factor
    from .data.torch_dataset import as_8bit_photo

    count = min(config.max_scenes, len(dataset)) if config.max_scenes else len(dataset)
    todo = [i for i in range(rank, count, world) if not cache_path(run_dir, dataset, i).exists()]
    cache_path(run_dir, dataset, 0).parent.mkdir(parents=True, exist_ok=True)
    for i in reporter.track(todo, description="IoR net inputs"):
        capture = dataset.capture(i)
        images = capture.images
        rng = np.random.default_rng([_scene_number(dataset, i), 17])  # the scene's own: any partial listing
        if rng.random() < config.photo_noise:
            linear = torch.as_tensor(images)
            factor = exposure_factor(linear, 0.5)
            photo = as_8bit_photo((linear * factor).clamp(0, 1), float(rng.uniform(0, PHOTO_NOISE_MAX)), rng)
            images = (photo / factor).numpy()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            views, mask = scene_inputs(images, capture.masks, capture.envmap, capture.cameras,
                                       dataset.hull(i).mesh, config.net)
        arrays = {"views": views.numpy().astype(np.float16), "mask": mask.numpy(), "ior": capture.ior}
        write_atomic(cache_path(run_dir, dataset, i), lambda tmp: _save_npz(tmp, arrays))
    return len(todo)


def _scene_number(dataset, index: int) -> int:
    return int(dataset.scene_dirs[index].name.rsplit("_", 1)[-1])


def _save_npz(path: Path, arrays: dict) -> None:
    with open(path, "wb") as f:  # a file object: np.savez would add ".npz" to a temporary name
        np.savez(f, **arrays)


def train_ior_net(dataset, run_dir: str | os.PathLike, config: IorTrainConfig, device: str = "cpu",
                  reporter: Reporter | None = None, max_steps: int | None = None) -> dict:
    """Cache every scene's inputs, then train the IoR net on them (resumes from RUN_DIR/checkpoint.pt;
    runs under torchrun for DDP). dataset: scenes of known, varied IoR (`generate --ior-range`).
    Returns the last epoch's metrics; RUN_DIR/weights.safetensors is the result."""
    from . import training

    run_dir = Path(run_dir)
    lo, hi = dataset.config.ior_range
    if not lo < hi:
        raise LookingGlassError(f"every scene here has IoR {lo}: the IoR net learns from scenes of varied IoR "
                                "(make them with `generate --ior-range 1.3 1.7`)", dataset.split_dir)
    session = training.TrainingSession(run_dir, config, device, reporter)
    made = prepare_cache(dataset, run_dir, config, session.reporter, session.rank, session.world)
    if made:
        session.reporter.info(f"IoR net inputs: made {made}")
    session.barrier()
    device = session.device
    centres = config.net.bin_centres().to(device)
    lo, hi = config.net.bin_range

    def step(model: nn.Module, index: int, global_step: int) -> tuple[Tensor, dict[str, float]]:
        path = cache_path(run_dir, dataset, index)
        try:
            arrays = np.load(path)
            views, mask, ior = arrays["views"], arrays["mask"], float(arrays["ior"])
        except Exception as exc:  # a truncated or foreign file in the cache
            raise LookingGlassError(f"cannot read cached IoR-net inputs ({exc}); delete the file", path) from None
        if not lo <= ior <= hi:
            raise LookingGlassError(f"scene IoR {ior} is outside the net's range {lo}-{hi}", path)
        g = torch.Generator().manual_seed(config.seed * 1_000_003 + global_step)
        most = min(config.max_views, len(mask))  # scenes of fewer views than asked show all they have
        count = int(torch.randint(min(config.min_views, most), most + 1, (1,), generator=g))
        chosen = torch.randperm(len(mask), generator=g)[:count]
        v = torch.from_numpy(views)[chosen].float().unsqueeze(0).to(device)
        m = torch.from_numpy(mask)[chosen].unsqueeze(0).to(device)
        logits = model(v, m)
        target = soft_labels(torch.tensor([ior], device=device), centres, config.label_sigma)
        loss = -(target * torch.log_softmax(logits, -1)).sum(-1).mean()
        estimate = posterior_estimate(logits.detach(), centres)[0]
        return loss, {"abs_error": float((estimate - ior).abs())}

    def weights_extra(steps: int) -> dict:
        return {"kind": "ior", "steps": steps, "image_size": [IOR_NET_WIDTH, IOR_NET_HEIGHT],
                "envmap_height": IOR_NET_ENVMAP_HEIGHT}

    return session.fit(lambda: IorNet(config.net), len(dataset), step, weights_extra=weights_extra,
                       labels={"abs_error": "|error|"}, max_steps=max_steps)


# ---- inference --------------------------------------------------------------------------------------
# The net's spread (its distribution's standard deviation) up to which its value is called reliable.
LEARNED_RELIABLE_STD = 0.03


@dataclass
class LearnedIor:
    """The net's reading of one capture: value and uncertainty (the mean and standard deviation of
    its distribution over its bins, restricted to the range asked for), the range its bins span,
    whether the range asked for reaches beyond it (its estimate then cannot say so), and the seconds
    it took."""

    value: float
    uncertainty: float
    trained_range: tuple[float, float]
    beyond_trained_range: bool
    seconds: float

    def report(self) -> dict:
        return {"value": round(self.value, 4), "uncertainty": round(self.uncertainty, 4),
                "trained_range": [round(r, 4) for r in self.trained_range],
                "beyond_trained_range": self.beyond_trained_range, "seconds": round(self.seconds, 2)}


def load_ior_net(path: str | os.PathLike) -> IorNet:
    """The IoR net from its weights file (eval mode, CPU); refuses other networks' weights."""
    from .weights import load_weights

    net, _ = load_weights(path, IorNetConfig, IorNet, kind="ior")
    return net


def learned_ior(capture, mesh: trimesh.Trimesh, net: IorNet, ior_range: tuple[float, float],
                device: str = "cpu") -> LearnedIor:
    """The IoR net's estimate for `capture` (linear photos, masks, map, cameras) and a mesh of its
    object (`reconstruct`'s kept mesh; the closer to the object, the better: docs/results.md), read
    within `ior_range`."""
    start = time.perf_counter()
    with torch.no_grad():
        views, mask = scene_inputs(capture.images, capture.masks, capture.envmap, capture.cameras, mesh, net.cfg,
                                   device=device)
        net = net.to(device)
        logits = net(views.unsqueeze(0), mask.unsqueeze(0)).cpu()
    mean, std = posterior_estimate(logits, net.cfg.bin_centres(), ior_range)
    lo, hi = (float(b) for b in net.cfg.bin_range)
    beyond = ior_range[0] < lo - 1e-9 or ior_range[1] > hi + 1e-9
    return LearnedIor(float(mean), float(std), (lo, hi), beyond, time.perf_counter() - start)
