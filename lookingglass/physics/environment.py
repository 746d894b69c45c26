"""Distant environment lighting: an equirectangular radiance map and its lookup, in torch.

Convention (DESIGN.md, = Mitsuba 3 `envmap` with identity to_world): direction d = (x, y, z)
maps to u = atan2(x, -z) / (2 pi) mod 1, v = acos(y) / pi; the map is H x 2H, row 0 looks up
(+y) and u grows towards +x from -z. Lookups are bilinear and wrap around the u seam. Exactly as
Mitsuba 3 samples its bitmap (checked texel for texel in tests/test_environment.py): columns are
texel-centred (x = u W - 1/2) while rows span the poles (y = v (H - 1), row 0 at +y, row H-1 at -y).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def direction_to_uv(directions: Tensor) -> tuple[Tensor, Tensor]:
    """Unit directions (..., 3) -> (u, v) each (...,), u in [0, 1), v in [0, 1]."""
    x, y, z = directions.unbind(-1)
    u = torch.remainder(torch.atan2(x, -z) / (2 * math.pi), 1.0)
    y = y.clamp(-1.0, 1.0)
    # acos' is infinite at +-1 (a ray straight up or down): take the value at y and the gradient
    # just inside, so the value stays exact and gradients stay finite.
    y_inside = y.clamp(-1.0 + 1e-6, 1.0 - 1e-6)
    v = (torch.acos(y_inside) + (torch.acos(y) - torch.acos(y_inside)).detach()) / math.pi
    return u, v


def uv_to_direction(u: Tensor, v: Tensor) -> Tensor:
    """Inverse of `direction_to_uv`: (u, v) each (...,) -> unit directions (..., 3)."""
    phi, theta = 2 * math.pi * u, math.pi * v
    s = torch.sin(theta)
    return torch.stack([s * torch.sin(phi), torch.cos(theta), -s * torch.cos(phi)], dim=-1)


class EnvironmentMap:
    """An equirectangular radiance map, linear units, (H, W, 3) float with W = 2H."""

    def __init__(self, radiance: Tensor):
        if radiance.dim() != 3 or radiance.shape[-1] != 3:
            raise ValueError(f"environment map must be (H, W, 3), got {tuple(radiance.shape)}")
        # Contiguous once here: lookups flatten the map, and a permuted (C, H, W) view would be
        # copied (slowly, strided) on every lookup.
        self.radiance = radiance.contiguous()

    @property
    def height(self) -> int:
        return self.radiance.shape[0]

    @property
    def width(self) -> int:
        return self.radiance.shape[1]

    def to(self, device=None, dtype=None) -> "EnvironmentMap":
        kw = {k: v for k, v in dict(device=device, dtype=dtype).items() if v is not None}
        return EnvironmentMap(self.radiance.to(**kw))

    def scaled(self, factor: float) -> "EnvironmentMap":
        return EnvironmentMap(self.radiance * factor)

    def resized(self, height: int) -> "EnvironmentMap":
        """Area-averaged (downsizing) or bilinear (upsizing) copy with the given height (width 2H)."""
        img = self.radiance.permute(2, 0, 1)[None]
        mode = "area" if height < self.height else "bilinear"
        kw = {} if mode == "area" else dict(align_corners=False)
        out = torch.nn.functional.interpolate(img, size=(height, 2 * height), mode=mode, **kw)
        return EnvironmentMap(out[0].permute(1, 2, 0).contiguous())

    def mirrored(self) -> "EnvironmentMap":
        """The light of the world mirrored in the plane x = 0: E'(x, y, z) = E(-x, y, z). u -> 1 - u,
        and with texel-centred columns that is the columns reversed, exactly."""
        return EnvironmentMap(self.radiance.flip(1))

    def lookup(self, directions: Tensor) -> Tensor:
        """Radiance arriving from unit directions (..., 3) (the direction light travels *from*,
        i.e. where the ray escapes to). Bilinear, differentiable in the directions.
        Returns (..., 3) in the map's dtype."""
        u, v = direction_to_uv(directions)
        return self.lookup_uv(u, v)

    def lookup_uv(self, u: Tensor, v: Tensor) -> Tensor:
        """Bilinear lookup at texture coordinates u (wrapping), v (clamped): (...,) -> (..., 3)."""
        H, W = self.height, self.width
        x = u * W - 0.5  # columns: texel centres at (i + 1/2) / W
        y = (v * (H - 1)).clamp(0.0, H - 1.0)  # rows: first and last row on the poles (Mitsuba)
        x0f, y0f = torch.floor(x), torch.floor(y)
        wx, wy = (x - x0f).unsqueeze(-1), (y - y0f).unsqueeze(-1)
        x0 = torch.remainder(x0f.long(), W)
        x1 = torch.remainder(x0 + 1, W)
        y0 = y0f.long().clamp(0, H - 1)
        y1 = (y0 + 1).clamp(max=H - 1)
        flat = self.radiance.reshape(-1, 3)
        # index_select gathers rows ~3x faster than advanced indexing (a hot spot of the renderer).
        g = lambda yy, xx: flat.index_select(0, (yy * W + xx).reshape(-1)).reshape(*yy.shape, 3)  # noqa: E731
        top = g(y0, x0) * (1 - wx) + g(y0, x1) * wx
        bottom = g(y1, x0) * (1 - wx) + g(y1, x1) * wx
        return top * (1 - wy) + bottom * wy


def texel_directions(height: int, dtype=torch.float64, device="cpu") -> Tensor:
    """The direction of every texel of an H x 2H map, where `EnvironmentMap.lookup_uv` reads it
    exactly: column c at u = (c + 1/2) / W (texel-centred), row r at v = r / (H - 1) (rows span the
    poles). Returns unit directions (H, 2H, 3). A map whose texel (r, c) holds the radiance from
    direction [r, c] is looked up consistently by `EnvironmentMap.lookup` (writing and reading one
    convention)."""
    H, W = int(height), 2 * int(height)
    u = (torch.arange(W, dtype=dtype, device=device) + 0.5) / W
    v = torch.arange(H, dtype=dtype, device=device) / max(H - 1, 1)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return uv_to_direction(uu, vv)


def rotate_envmap(radiance: Tensor, rotation: Tensor) -> Tensor:
    """The map of the same light in a rotated world frame: world' = rotation @ world, so the new map
    holds E'(d') = E(rotation^T d'). radiance: (H, 2H, 3); rotation: (3, 3) orthonormal. Bilinear
    (`EnvironmentMap.lookup`), same size and dtype."""
    env = EnvironmentMap(radiance)
    dirs = texel_directions(env.height, dtype=torch.float64, device=radiance.device)
    old = dirs @ rotation.to(dirs)  # rows: (R^T d')^T = d'^T R
    return env.lookup(old.to(radiance.dtype))
