"""From a capture (or a dataset scene) to the normal network's inputs, in one place.

Normalization (DESIGN.md): the HDR images are scaled so their mean over all views is
`target_mean` (0.5; training draws it from U[0.4, 0.6]) and clipped to [0, 1]; the environment
map gets the same factor. Images are resized to the network's resolution (area filter), masks by
area coverage >= 1/2, and the environment map to H_E x 2H_E.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from torch import Tensor

from ..physics.camera import Cameras
from ..physics.environment import EnvironmentMap
from ..render.tracer import trace_two_bounce
from .render_layer import error_map, render_layer


def exposure_factor(images: Tensor, target_mean: float = 0.5) -> float:
    """Factor that brings the mean of `images` (any shape, linear) to `target_mean`."""
    mean = float(images.double().mean())
    if not np.isfinite(mean) or mean <= 0:
        raise ValueError("images are black (mean radiance 0): nothing to normalize")
    return target_mean / mean


def resize_images(images: Tensor, width: int, height: int) -> Tensor:
    """(V, H, W, C) float -> (V, height, width, C), area-averaged when shrinking."""
    if images.shape[1:3] == (height, width):
        return images
    x = images.permute(0, 3, 1, 2)
    shrink = height <= images.shape[1] and width <= images.shape[2]
    x = F.interpolate(x, size=(height, width), mode="area") if shrink else \
        F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)
    return x.permute(0, 2, 3, 1).contiguous()


def resize_masks(masks: Tensor, width: int, height: int) -> Tensor:
    """(V, H, W) bool -> (V, height, width) bool by area coverage >= 1/2."""
    return resize_images(masks.unsqueeze(-1).float(), width, height)[..., 0] >= 0.5


@dataclass
class NormalInputs:
    """Everything NNet and the rendering layer need for V views at the network's resolution.

    image (V,H,W,3) normalized and clipped; mask (V,H,W); envmap scaled by the same factor;
    cameras at H x W; vh_n1, vh_n2 (V,H,W,3) camera-frame hull normals; vh_valid (V,H,W) the
    hull's two-bounce validity; vh_error (V,H,W,3) Ĩer; vh_tir (V,H,W) M̃tr; factor: the
    exposure factor applied to the original radiance."""

    image: Tensor
    mask: Tensor
    envmap: EnvironmentMap
    cameras: Cameras
    vh_n1: Tensor
    vh_n2: Tensor
    vh_valid: Tensor
    vh_error: Tensor
    vh_tir: Tensor
    factor: float


def hull_error_maps(envmap: EnvironmentMap, image: Tensor, mask: Tensor, vh_n1: Tensor, vh_n2: Tensor,
                    cameras: Cameras, ior: float) -> tuple[Tensor, Tensor]:
    """Ĩer and M̃tr (paper Eq. 4-5): render the hull's normals with the layer, compare with I."""
    out = render_layer(envmap, vh_n1, vh_n2, cameras, ior=ior)
    return error_map(image, out.image, mask), out.tir & mask


def prepare_inputs(images: Tensor, masks: Tensor, envmap: Tensor, cameras: Cameras, hull: trimesh.Trimesh,
                   width: int, height: int, envmap_height: int, ior: float, target_mean: float = 0.5,
                   device: str | torch.device = "cpu") -> NormalInputs:
    """images (V,H0,W0,3) linear; masks (V,H0,W0) bool; envmap (He,2He,3) linear in the images'
    units; cameras at H0 x W0 and `hull` in the same (world) frame. The result lives on `device`
    (the hull's rays are cast on the CPU either way)."""
    images, masks, envmap = images.to(device), masks.to(device), envmap.to(device)
    factor = exposure_factor(images, target_mean)
    image = resize_images(images.float() * factor, width, height).clamp(0, 1)
    mask = resize_masks(masks, width, height)
    cams = cameras.with_resolution(width, height).to(device)
    env = EnvironmentMap(envmap.float() * factor).resized(envmap_height)
    tb = trace_two_bounce(hull, cams, ior=ior, device=device)
    vh_error, vh_tir = hull_error_maps(env, image, mask, tb.normal1, tb.normal2, cams, ior)
    return NormalInputs(image, mask, env, cams, tb.normal1, tb.normal2, tb.valid, vh_error, vh_tir, factor)
