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


@dataclass
class FirstInterface:
    """The part of the layer that depends on N1 alone: world view directions `d` and refracted
    directions `t1` (V, H, W, 3), Fresnel reflectance `f1` and TIR `tir1` (V, H, W), and the
    reflected radiance (V, H, W, 3). The cost volume reuses one of these for K choices of N2."""

    d: Tensor
    t1: Tensor
    f1: Tensor
    tir1: Tensor
    reflected: Tensor


def first_interface(envmap: EnvironmentMap, normal1: Tensor, cameras: Cameras, ior: float = IOR_GLASS,
                    ext_ior: float = IOR_AIR, view_dirs: Tensor | None = None) -> FirstInterface:
    """Reflect and refract the camera rays at N1 (V, H, W, 3), camera frame."""
    d = cameras.pixel_rays()[1].to(normal1) if view_dirs is None else view_dirs
    n1 = cameras.camera_to_world(torch.nn.functional.normalize(normal1, dim=-1))
    refl_dir, t1, f1, tir1 = interface(d, n1, ext_ior / ior)
    return FirstInterface(d, t1, f1, tir1, f1.unsqueeze(-1) * envmap.lookup(refl_dir))


def second_interface(envmap: EnvironmentMap, first: FirstInterface, normal2: Tensor, cameras: Cameras,
                     ior: float = IOR_GLASS, ext_ior: float = IOR_AIR) -> LayerOutput:
    """Leave the glass at N2 (V, H, W, 3), camera frame, after `first`."""
    n2 = cameras.camera_to_world(torch.nn.functional.normalize(normal2, dim=-1))
    # Leaving the glass through the second interface: the normal facing the ray is -n2.
    # A refracted ray that does not point out through N2 cannot leave there either.
    leaves = (first.t1 * n2).sum(-1) > 0
    _, t2, f2, tir2 = interface(first.t1, n2, ior / ext_ior)
    tir = first.tir1 | tir2 | ~leaves
    transmittance = ((1 - first.f1) * (1 - f2)).unsqueeze(-1)
    safe_t2 = torch.where(tir.unsqueeze(-1), first.d, t2)  # any unit vector: the term is masked out
    transmitted = torch.where(tir.unsqueeze(-1), torch.zeros_like(first.reflected),
                              transmittance * envmap.lookup(safe_t2))
    return LayerOutput(first.reflected, transmitted, tir)


def render_layer(envmap: EnvironmentMap, normal1: Tensor, normal2: Tensor, cameras: Cameras,
                 ior: float = IOR_GLASS, ext_ior: float = IOR_AIR,
                 view_dirs: Tensor | None = None) -> LayerOutput:
    """Render V views from per-pixel normals.

    normal1, normal2: (V, H, W, 3) camera-frame unit normals at the first and second hit
    (outward, x = right, y = up, z = towards the camera, as the networks predict them).
    cameras: the V views, at the normals' resolution (pixel-centre rays), or pass `view_dirs`
    (V, H, W, 3) world ray directions directly (e.g. cached). Returns `LayerOutput`.
    """
    first = first_interface(envmap, normal1, cameras, ior, ext_ior, view_dirs)
    return second_interface(envmap, first, normal2, cameras, ior, ext_ior)


def comparable(rendered: Tensor) -> Tensor:
    """A rendering clipped to [0, 1] like the normalized input photos, so the two compare: a
    bright source seen through a wrong normal then costs at most 1 per channel."""
    return rendered.clamp(0.0, 1.0)


def error_map(image: Tensor, rendered: Tensor, mask: Tensor) -> Tensor:
    """The paper's Ĩ^er = |I - (Ĩ^r + Ĩ^t)| ⊙ M: (V, H, W, 3) images (`image` normalized and
    clipped, `rendered` clipped here), (V, H, W) mask."""
    return (image - comparable(rendered)).abs() * mask.unsqueeze(-1).to(image.dtype)


def prediction_error_maps(envmap: EnvironmentMap, normal1: Tensor, normal2: Tensor, cameras: Cameras, image: Tensor,
                          mask: Tensor, ior: float = IOR_GLASS) -> tuple[Tensor, Tensor, LayerOutput]:
    """What feature mapping reads from a prediction: the per-pixel squared re-rendering error
    (V, H, W), mean over RGB of (I - clip(I^r + I^t))², 0 off the mask; the TIR mask (V, H, W)
    inside the mask; and the layer's output. normal1/2 (V, H, W, 3) camera frame; image
    (V, H, W, 3) normalized; mask (V, H, W) bool."""
    out = render_layer(envmap, normal1, normal2, cameras, ior=ior)
    error = ((comparable(out.image) - image) ** 2).mean(-1) * mask
    return error, out.tir & mask, out
