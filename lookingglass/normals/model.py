"""NNet (encoder-decoder for N1, N2), FNet and the cost volume (paper Sec. 3.1, supplement).

One implementation; the paper's ablations are switches of `NormalNetConfig`:
  basic:  use_error_map=False, use_cost_volume=False  (I, I*M, M, Ñ1, Ñ2: 13 channels)
  wr:     use_error_map=True,  use_cost_volume=False  (+ Ĩer, M̃tr: 15 channels)
  wr+cv:  use_error_map=True,  use_cost_volume=True   (+ FNet features pooled over K x K pairs)
All normal maps are camera-frame (x right, y up, z towards the camera), tensors (B, C, H, W).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from ..physics.camera import Cameras
from ..physics.environment import EnvironmentMap
from ..physics.optics import IOR_AIR, IOR_GLASS
from .config import COST_VOLUME_THETA_DEG, NormalNetConfig, cpu_config, paper_config  # noqa: F401 (re-exported)
from .render_layer import error_map, first_interface, second_interface

# The gain head's output is GAIN_HEAD_SCALE_DEG * x (degrees): a unit step of its last layer is a
# few degrees, about the gains at stake.
GAIN_HEAD_SCALE_DEG = 5.0


def _conv(cin: int, cout: int, k: int, stride: int, groups: int) -> nn.Sequential:
    # 3x3 stride 1 and 4x4 stride 2 both take padding 1: same size, or exactly half.
    conv = nn.Conv2d(cin, cout, k, stride, padding=1, bias=False)
    return nn.Sequential(conv, nn.GroupNorm(min(groups, cout), cout), nn.ReLU(inplace=True))


class FNet(nn.Module):
    """Features of one (Ñ1_k, Ñ2_k') pair: 8 channels (two normals, error, TIR mask) -> /2 resolution."""

    def __init__(self, cfg: NormalNetConfig):
        super().__init__()
        c = cfg.fnet_channels
        self.net = nn.Sequential(_conv(8, c, 4, 2, cfg.groups), _conv(c, c, 3, 1, cfg.groups))

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class NormalNet(nn.Module):
    """NNet with optional cost volume. forward(inputs, cost_volume=None) -> (n1, n2) unit normals."""

    def __init__(self, cfg: NormalNetConfig):
        super().__init__()
        self.cfg = cfg
        c1, c2, c3 = cfg.enc_channels
        g = cfg.groups
        self.enc1 = nn.Sequential(_conv(cfg.in_channels, c1, 4, 2, g), _conv(c1, c1, 3, 1, g))
        extra = cfg.fnet_channels if cfg.use_cost_volume else 0
        self.enc2 = nn.Sequential(_conv(c1 + extra, c2, 4, 2, g), _conv(c2, c2, 3, 1, g),
                                  _conv(c2, c3, 4, 2, g), _conv(c3, c3, 3, 1, g))
        up = lambda: nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False)  # noqa: E731
        self.decoder = nn.Sequential(
            _conv(c3, c3, 3, 1, g), _conv(c3, c2, 3, 1, g), up(),
            _conv(c2, c2, 3, 1, g), _conv(c2, c1 * 2, 3, 1, g), up(),
            _conv(c1 * 2, c1 * 2, 3, 1, g), _conv(c1 * 2, c1, 3, 1, g), up(),
            nn.Conv2d(c1, 6, 3, 1, 1))
        if cfg.residual:
            nn.init.zeros_(self.decoder[-1].weight)
            nn.init.zeros_(self.decoder[-1].bias)
        if cfg.gain_head:  # reads the decoder's last features, both normals, the hull's, and how far apart they are
            self.gain_head = nn.Sequential(_conv(c1 + 14, c1, 3, 1, g), nn.Conv2d(c1, 2, 3, 1, 1))
            nn.init.zeros_(self.gain_head[-1].bias)
        if cfg.detail_head:
            # per pixel and local (no normalization over the image): a 5 x 5 reach
            self.detail_head = nn.Sequential(nn.Conv2d(cfg.in_channels + 6, c1, 3, 1, 1), nn.ReLU(inplace=True),
                                             nn.Conv2d(c1, c1, 1), nn.ReLU(inplace=True), nn.Conv2d(c1, 6, 3, 1, 1))
            nn.init.zeros_(self.detail_head[-1].weight)
            nn.init.zeros_(self.detail_head[-1].bias)
        if cfg.use_cost_volume:
            self.fnet = FNet(cfg)
            k2 = cfg.cost_volume_k ** 2
            self.pool_logits = nn.Parameter(torch.zeros(k2))  # softmax: positive weights summing to 1

    def pooling_weights(self) -> Tensor:
        return torch.softmax(self.pool_logits, dim=0)

    def encode(self, inputs: Tensor, cost_volume: Tensor | None = None) -> Tensor:
        """inputs (B, in_channels, H, W); cost_volume (B, K*K, 8, H, W) or None -> latent (B, c3, H/8, W/8)."""
        x = self.enc1(inputs)
        if self.cfg.use_cost_volume:
            if cost_volume is None:
                raise ValueError("this network was built with a cost volume; pass one")
            B, K2 = cost_volume.shape[:2]
            feats = self.fnet(cost_volume.flatten(0, 1)).unflatten(0, (B, K2))
            x = torch.cat([x, (feats * self.pooling_weights().view(1, K2, 1, 1, 1)).sum(1)], dim=1)
        return self.enc2(x)

    def decode(self, latent: Tensor, inputs: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """latent -> unit (n1, n2), each (B, 3, H, W). A residual net adds its output to the hull
        normals, read from `inputs` (the tensor `encode` was given)."""
        return self.decode_with_gain(latent, inputs, with_gain=False)[:2]

    def decode_with_gain(self, latent: Tensor, inputs: Tensor | None = None,
                          with_gain: bool = True) -> tuple[Tensor, Tensor, Tensor | None]:
        """`decode`, and with a gain head (and `with_gain`) the predicted gains of n1 and n2 over
        the hull's normals (B, 2, H, W): the hull's angle error minus the prediction's, degrees;
        else None."""
        features = self.decoder[:-1](latent)
        out = torch.tanh(self.decoder[-1](features))
        needs_inputs = self.cfg.residual or (with_gain and self.cfg.gain_head) or self.cfg.detail_head
        if needs_inputs and inputs is None:
            raise ValueError("this network decodes from its inputs (the hull normals, the detail head's channels); "
                             "pass the inputs")
        if self.cfg.detail_head:
            out = out + self.detail_head(torch.cat([out, inputs], 1))
        n1, n2 = out[:, :3], out[:, 3:]
        if self.cfg.residual:
            n1, n2 = n1 + inputs[:, HULL_N1_CHANNELS], n2 + inputs[:, HULL_N2_CHANNELS]
        n1, n2 = unit_channels(n1), unit_channels(n2)
        if not (with_gain and self.cfg.gain_head):
            return n1, n2, None
        hull1, hull2 = inputs[:, HULL_N1_CHANNELS], inputs[:, HULL_N2_CHANNELS]
        # the cosines between prediction and hull, which a 3x3 convolution would only approximate
        agreement = torch.cat([(n1 * hull1).sum(1, keepdim=True), (n2 * hull2).sum(1, keepdim=True)], 1)
        head_in = torch.cat([features, n1, n2, hull1, hull2, agreement], 1)
        return n1, n2, GAIN_HEAD_SCALE_DEG * self.gain_head(head_in)

    def forward(self, inputs: Tensor, cost_volume: Tensor | None = None,
                with_gain: bool = False) -> tuple[Tensor, ...]:
        """(n1, n2); with `with_gain`, (n1, n2, gain) (`decode_with_gain`; DDP needs the
        training step's outputs to come from forward)."""
        decoded = self.decode_with_gain(self.encode(inputs, cost_volume), inputs, with_gain)
        return decoded if with_gain else decoded[:2]

    def widen_initial_state(self, state: dict[str, Tensor], saved_config: dict) -> dict[str, Tensor]:
        """--init weights saved without the gain head (or the detail head) start its training: the
        head keeps its fresh initialization, every other weight is loaded."""
        own = self.state_dict()
        return {**{k: v for k, v in own.items() if k.startswith(("gain_head.", "detail_head."))}, **state}


def unit_channels(x: Tensor, eps: float = 1e-6) -> Tensor:
    """x / max(|x|, eps) over dim 1 of (B, C, H, W): F.normalize(x, dim=1), whose norm over the
    channel dim takes ~20 ms for 10 views at 128x96 on this CPU (torch 2.13) against < 1 ms for
    this sum of squares; it runs twice per latent-optimization step. The clamp comes before the
    root so a zero vector gets a finite gradient (upstream / eps, not NaN), as with F.normalize."""
    return x * x.square().sum(1, keepdim=True).clamp_min(eps * eps).rsqrt()


# ---- inputs -------------------------------------------------------------------------------------
def to_channels(x: Tensor) -> Tensor:
    """(V, H, W, C) -> (V, C, H, W)."""
    return x.permute(0, 3, 1, 2)


# Where `network_inputs` puts the (masked) hull normals Ñ1, Ñ2.
HULL_N1_CHANNELS, HULL_N2_CHANNELS = slice(7, 10), slice(10, 13)


def network_inputs(image: Tensor, mask: Tensor, vh_n1: Tensor, vh_n2: Tensor, vh_error: Tensor | None,
                   vh_tir: Tensor | None) -> Tensor:
    """Stack the paper's input channels. image (V,H,W,3) normalized; mask (V,H,W) bool; vh_n1/2
    (V,H,W,3) camera frame; vh_error (V,H,W,3) Ĩer or None (basic); vh_tir (V,H,W) bool.
    Returns (V, 13 or 15, H, W)."""
    m = mask.unsqueeze(-1).to(image.dtype)
    parts = [image, image * m, m, vh_n1 * m, vh_n2 * m]
    if vh_error is not None:
        parts += [vh_error.mean(-1, keepdim=True), vh_tir.unsqueeze(-1).to(image.dtype) * m]
    return to_channels(torch.cat(parts, dim=-1))


def sample_cone(normals: Tensor, theta_deg: float, k: int = 4) -> Tensor:
    """The cost volume's K normals around each normal (..., 3): theta = 0, t, t, ... and phi evenly
    spread from 0 in the local frame Z = Ñ, Y = normalize(U - (U.Ñ)Ñ) with U = image up (0, 1, 0)
    in camera coordinates, X = Y x Z. Returns (K, ..., 3)."""
    z = torch.nn.functional.normalize(normals, dim=-1)
    up = torch.zeros_like(z)
    up[..., 1] = 1.0
    y = up - (up * z).sum(-1, keepdim=True) * z
    # Where Ñ is (anti)parallel to the image up vector, fall back to the image's right vector.
    right = torch.zeros_like(z)
    right[..., 0] = 1.0
    degenerate = y.norm(dim=-1, keepdim=True) < 1e-6
    y = torch.where(degenerate, right - (right * z).sum(-1, keepdim=True) * z, y)
    y = torch.nn.functional.normalize(y, dim=-1)
    x = torch.linalg.cross(y, z, dim=-1)
    t = math.radians(theta_deg)
    thetas = [0.0] + [t] * (k - 1)
    phis = [0.0] + [2 * math.pi * i / (k - 1) for i in range(k - 1)]
    out = [x * math.cos(p) * math.sin(th) + y * math.sin(p) * math.sin(th) + z * math.cos(th)
           for th, p in zip(thetas, phis)]
    return torch.stack(out)


def build_cost_volume(envmap: EnvironmentMap, image: Tensor, mask: Tensor, vh_n1: Tensor, vh_n2: Tensor,
                      cameras: Cameras, theta_deg: float, k: int = 4, ior: float = IOR_GLASS,
                      ext_ior: float = IOR_AIR) -> Tensor:
    """For every pair (Ñ1_k, Ñ2_k') render an error map and TIR mask with the rendering layer.

    image (V,H,W,3) in the environment's units; mask (V,H,W); vh_n1/2 (V,H,W,3) camera frame;
    cameras at the same resolution. Returns (V, K*K, 8, H, W): Ñ1_k, Ñ2_k', mean |error|, M̃tr."""
    n1s, n2s = sample_cone(vh_n1, theta_deg, k), sample_cone(vh_n2, theta_deg, k)
    dirs = cameras.pixel_rays()[1].to(image)
    m = mask.unsqueeze(-1).to(image.dtype)
    pairs = []
    for a in range(k):
        first = first_interface(envmap, n1s[a], cameras, ior, ext_ior, view_dirs=dirs)  # shared by K N2s
        for b in range(k):
            out = second_interface(envmap, first, n2s[b], cameras, ior, ext_ior)
            err = error_map(image, out.image, mask).mean(-1, keepdim=True)
            tir = out.tir.unsqueeze(-1).to(image.dtype) * m
            pairs.append(torch.cat([n1s[a] * m, n2s[b] * m, err, tir], dim=-1))
    return torch.stack(pairs, dim=1).permute(0, 1, 4, 2, 3)
