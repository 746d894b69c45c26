"""The paper's differentiable rendering layer: (E, N1, N2, camera) -> I^r, I^t, M^tr.

Light paths of at most two interfaces: the camera ray either reflects once at the first hit
(Fresnel F1) or refracts in at N1 and out at N2 (transmittance (1 - F1)(1 - F2)); both exits read
the environment. Built on the shared optics and camera modules, batched over views, and
differentiable in the normals (and the environment).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..physics.camera import Cameras
from ..physics.environment import EnvironmentMap
from ..physics.optics import IOR_AIR, IOR_GLASS, interface


@dataclass
class LayerOutput:
    """reflected, transmitted: (V, H, W, 3) radiance I^r, I^t; tir: (V, H, W) bool M^tr, True
    where the refracted path cannot leave after the second interface (TIR at N2, or N2 facing
    away from the refracted ray); image = reflected + transmitted."""

    reflected: Tensor
    transmitted: Tensor
    tir: Tensor

    @property
    def image(self) -> Tensor:
        return self.reflected + self.transmitted


def render_layer(envmap: EnvironmentMap, normal1: Tensor, normal2: Tensor, cameras: Cameras,
                 ior: float = IOR_GLASS, ext_ior: float = IOR_AIR,
                 view_dirs: Tensor | None = None) -> LayerOutput:
    """Render V views from per-pixel normals.

    normal1, normal2: (V, H, W, 3) camera-frame unit normals at the first and second hit
    (outward, x = right, y = up, z = towards the camera, as the networks predict them).
    cameras: the V views, at the normals' resolution (pixel-centre rays), or pass `view_dirs`
    (V, H, W, 3) world ray directions directly (e.g. cached). Returns `LayerOutput`.
    """
    d = cameras.pixel_rays()[1].to(normal1) if view_dirs is None else view_dirs
    n1 = cameras.camera_to_world(torch.nn.functional.normalize(normal1, dim=-1))
    n2 = cameras.camera_to_world(torch.nn.functional.normalize(normal2, dim=-1))
    refl_dir, t1, f1, tir1 = interface(d, n1, ext_ior / ior)
    # Leaving the glass through the second interface: the normal facing the ray is -n2.
    # A refracted ray that does not point out through N2 cannot leave there either.
    leaves = (t1 * n2).sum(-1) > 0
    _, t2, f2, tir2 = interface(t1, n2, ior / ext_ior)
    tir = tir1 | tir2 | ~leaves
    reflected = f1.unsqueeze(-1) * envmap.lookup(refl_dir)
    transmittance = ((1 - f1) * (1 - f2)).unsqueeze(-1)
    safe_t2 = torch.where(tir.unsqueeze(-1), d, t2)  # any unit vector: the term is masked out
    transmitted = torch.where(tir.unsqueeze(-1), torch.zeros_like(reflected), transmittance * envmap.lookup(safe_t2))
    return LayerOutput(reflected, transmitted, tir)


def comparable(rendered: Tensor) -> Tensor:
    """A rendering clipped to [0, 1] like the normalized input photos, so the two compare: a
    bright source seen through a wrong normal then costs at most 1 per channel."""
    return rendered.clamp(0.0, 1.0)


def error_map(image: Tensor, rendered: Tensor, mask: Tensor) -> Tensor:
    """The paper's Ĩ^er = |I - (Ĩ^r + Ĩ^t)| ⊙ M: (V, H, W, 3) images (`image` normalized and
    clipped, `rendered` clipped here), (V, H, W) mask."""
    return (image - comparable(rendered)).abs() * mask.unsqueeze(-1).to(image.dtype)
