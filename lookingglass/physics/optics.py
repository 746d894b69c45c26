"""Smooth dielectric interfaces: reflection, Snell refraction, unpolarized Fresnel, TIR.

The one implementation used by the renderer, the rendering layer and the tests. All functions
take batched torch tensors (..., 3) and are differentiable.

Convention: `d` is the unit direction the light travels along (towards the surface); `n` is a unit
normal on the side the ray comes from (dot(d, n) < 0). `eta = n_incident / n_transmitted`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .constants import IOR_AIR, IOR_GLASS  # noqa: F401 (re-exported)


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1, keepdim=True)


def face_forward(n: Tensor, d: Tensor) -> Tensor:
    """Flip normals n (..., 3) so they face against the ray direction d (dot(d, n) <= 0)."""
    return torch.where(_dot(d, n) > 0, -n, n)


def reflect(d: Tensor, n: Tensor) -> Tensor:
    """Mirror direction of d about n: d - 2 (d.n) n. (..., 3) -> (..., 3)."""
    return d - 2 * _dot(d, n) * n


def refract(d: Tensor, n: Tensor, eta: float | Tensor) -> tuple[Tensor, Tensor]:
    """Snell refraction of d through a surface with normal n facing the incident side.

    eta: n_incident / n_transmitted, scalar or (...,). Returns the transmitted unit direction
    (..., 3) (zeros where there is none) and a bool mask (...,) that is True under total internal
    reflection.
    """
    eta = torch.as_tensor(eta, dtype=d.dtype, device=d.device)
    if eta.dim() > 0:
        eta = eta.unsqueeze(-1)
    cos_i = -_dot(d, n)
    sin2_t = eta * eta * (1 - cos_i * cos_i).clamp(min=0)
    tir = sin2_t >= 1
    cos_t = torch.sqrt((1 - sin2_t).clamp(min=1e-12))
    t = eta * d + (eta * cos_i - cos_t) * n
    t = torch.where(tir, torch.zeros_like(t), t)
    return t, tir.squeeze(-1)


def fresnel_dielectric(cos_i: Tensor, eta: float | Tensor) -> Tensor:
    """Unpolarized Fresnel reflectance of a smooth dielectric interface.

    cos_i: (...,) cosine between the incident ray and the normal on its side (>= 0).
    eta: n_incident / n_transmitted. Returns F (...,) in [0, 1]; 1 under total internal reflection.
    F = ((eta cos_i - cos_t)/(eta cos_i + cos_t))^2 / 2 + ((cos_i - eta cos_t)/(cos_i + eta cos_t))^2 / 2,
    the paper's Eq. (rendering layer) with l^i.N = cos_i, l^t.N = cos_t.
    """
    eta = torch.as_tensor(eta, dtype=cos_i.dtype, device=cos_i.device)
    cos_i = cos_i.clamp(0.0, 1.0)
    sin2_t = eta * eta * (1 - cos_i * cos_i)
    # clamp above 0: sqrt'(0) is infinite, and inf x (clamp's zero gradient) = NaN would poison
    # every gradient through a TIR or grazing pixel (cos_t changes by 1e-6 at most)
    cos_t = torch.sqrt((1 - sin2_t).clamp(min=1e-12))
    r_s = (eta * cos_i - cos_t) / (eta * cos_i + cos_t).clamp(min=1e-12)
    r_p = (cos_i - eta * cos_t) / (cos_i + eta * cos_t).clamp(min=1e-12)
    f = 0.5 * (r_s * r_s + r_p * r_p)
    return torch.where(sin2_t >= 1, torch.ones_like(f), f.clamp(0.0, 1.0))


def interface(d: Tensor, n: Tensor, eta: float | Tensor):
    """One smooth dielectric interface hit by rays d with normals n (either orientation).

    Returns (reflected dir, transmitted dir, Fresnel reflectance F (...,), tir mask (...,)).
    The transmitted weight is 1 - F; under TIR F = 1 and the transmitted dir is zero.
    """
    n = face_forward(n, d)
    cos_i = (-_dot(d, n)).squeeze(-1)
    t, tir = refract(d, n, eta)
    f = fresnel_dielectric(cos_i, eta)
    return reflect(d, n), t, f, tir
