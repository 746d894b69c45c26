"""A learned IoR estimate (`reconstruct --ior auto`, issue 22): the photos against the visual hull
rendered as glass at candidate IoRs, read by a small network.

The photometric search in `ior.py` renders the *final* mesh at each candidate and keeps the best
match; where that mesh is off (CAD parts at 480x360, any 128x96 capture) a wrong shape matches best
where it refracts least and the estimate runs low. Here the comparison is learned instead: per view,
the normalized photo, the mask, the hull's two-bounce normals and, for each candidate IoR, the
per-pixel difference between the photo and the hull re-traced and rendered at that IoR by the
paper's rendering layer (`normals/render_layer.py`); a convolutional encoder pools each view over
its mask, the views are averaged, and a head gives a distribution over IoR bins. Trained on scenes
of known IoR whose hulls are carved as `reconstruct` carves them, it learns how a hull's errors bias
the match. The inputs are built from `NormalInputs`, the normal stage's own inputs, so training and
`reconstruct` run the same code.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import trimesh
from torch import Tensor, nn
from torch.nn import functional as F

from .normals.inputs import NormalInputs
from .normals.render_layer import error_map, render_layer
from .render.raycast import RayCaster
from .render.tracer import trace_two_bounce


@dataclass
class IorNetConfig:
    """candidates: the IoRs the hull is rendered at (input channels); bins: the output
    distribution's IoRs (its range is the range the net was trained on); widths: the encoder's
    channels, each layer halving the resolution."""

    candidates: list[float] = field(default_factory=lambda: [round(float(c), 4) for c in np.linspace(1.3, 1.7, 9)])
    bin_range: tuple[float, float] = (1.3, 1.7)
    bins: int = 41
    widths: list[int] = field(default_factory=lambda: [32, 64, 128, 128])

    @property
    def in_channels(self) -> int:
        return 11 + 2 * len(self.candidates)  # image 3, mask 1, N1 3, N2 3, valid 1; per candidate error, valid

    def bin_centres(self) -> Tensor:
        return torch.linspace(*self.bin_range, self.bins)

    def to_dict(self) -> dict:
        return asdict(self)


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
    """Views (B, V, C, H, W) and masks (B, V, H, W) -> logits (B, bins) over `cfg.bin_centres()`."""

    def __init__(self, cfg: IorNetConfig):
        super().__init__()
        self.cfg = cfg
        layers, c = [], cfg.in_channels
        for w in cfg.widths:
            layers += [nn.Conv2d(c, w, 3, stride=2, padding=1), nn.GroupNorm(8, w), nn.ReLU(inplace=True),
                       nn.Conv2d(w, w, 3, padding=1), nn.ReLU(inplace=True)]
            c = w
        self.encoder = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Linear(2 * c, 128), nn.ReLU(inplace=True), nn.Linear(128, cfg.bins))

    def forward(self, views: Tensor, masks: Tensor) -> Tensor:
        B, V = views.shape[:2]
        f = self.encoder(views.flatten(0, 1))  # (B*V, c, h, w)
        m = F.adaptive_avg_pool2d(masks.flatten(0, 1).unsqueeze(1).float(), f.shape[-2:])
        per_view = (f * m).sum((2, 3)) / m.sum((2, 3)).clamp(min=1e-6)  # masked mean over the view
        per_view = per_view.view(B, V, -1)
        weight = (m.view(B, V, -1).sum(-1) > 0).float().unsqueeze(-1)  # views that see the object
        mean = (per_view * weight).sum(1) / weight.sum(1).clamp(min=1)
        spread = ((per_view - mean.unsqueeze(1)).abs() * weight).sum(1) / weight.sum(1).clamp(min=1)
        return self.head(torch.cat([mean, spread], dim=-1))


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
