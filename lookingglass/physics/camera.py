"""The camera model: pixel -> ray and point -> pixel, batched over views, in torch.

Conventions (DESIGN.md, = Mitsuba 3 `perspective` with fov_axis='x' and look_at):
  forward f = normalize(target - origin), right r = normalize(f x up), true up u = r x f.
  Continuous image coordinates (x_px, y_px): pixel (col, row) covers [col, col+1) x [row, row+1),
  so its centre is (col + 0.5, row + 0.5). NDC x = 2 x_px / W - 1, y = 1 - 2 y_px / H, and the ray
  is normalize(f + x tan(fov_x/2) r + y tan(fov_x/2) (H/W) u).
  Camera frame (for network normals): x = r, y = u, z = -f (towards the camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


def look_at_basis(origin: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """Rows (r, u, f) of the camera basis in world coordinates.

    origin, target, up: (..., 3) float. Returns (..., 3, 3): [..., 0, :] = right, [..., 1, :] = true
    up, [..., 2, :] = forward.
    """
    f = torch.nn.functional.normalize(target - origin, dim=-1)
    r = torch.nn.functional.normalize(torch.linalg.cross(f, up, dim=-1), dim=-1)
    u = torch.linalg.cross(r, f, dim=-1)
    return torch.stack([r, u, f], dim=-2)


@dataclass
class Cameras:
    """V pinhole cameras sharing one image size.

    origin: (V, 3) float, world. basis: (V, 3, 3) rows (right, up, forward), world.
    tan_half_fov_x: (V,) float. width, height: image size in pixels.
    """

    origin: Tensor
    basis: Tensor
    tan_half_fov_x: Tensor
    width: int
    height: int

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def look_at(cls, origin, target, up, fov_x_deg, width: int, height: int,
                dtype=torch.float32, device="cpu") -> "Cameras":
        """Cameras from look-at parameters. origin/target/up: (V, 3); fov_x_deg: (V,) or scalar."""
        as_t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731 - basis in double
        origin, target, up = as_t(origin).reshape(-1, 3), as_t(target).reshape(-1, 3), as_t(up).reshape(-1, 3)
        fov = as_t(fov_x_deg).reshape(-1).expand(origin.shape[0])
        forward = target - origin
        side = torch.linalg.cross(forward, up, dim=-1).norm(dim=-1)
        bad = (forward.norm(dim=-1) < 1e-12) | (side < 1e-9 * forward.norm(dim=-1) * up.norm(dim=-1)) | (up.norm(dim=-1) < 1e-12)
        if bad.any():
            raise ValueError(f"degenerate camera {bad.nonzero()[0].item()}: origin == target, zero up vector, "
                             "or up parallel to the viewing direction")
        basis = look_at_basis(origin, target, up)
        tan_half = torch.tan(torch.deg2rad(fov) / 2)
        to = dict(dtype=dtype, device=device)
        return cls(origin.to(**to), basis.to(**to), tan_half.to(**to), int(width), int(height))

    @property
    def num_views(self) -> int:
        return self.origin.shape[0]

    def __len__(self) -> int:
        return self.num_views

    @property
    def fov_x_deg(self) -> Tensor:
        return torch.rad2deg(2 * torch.atan(self.tan_half_fov_x))

    @property
    def pixel_pitch(self) -> Tensor:
        """(V,) a pixel's width per unit depth (square pixels): times a depth, its size in the world."""
        return 2 * self.tan_half_fov_x / self.width

    @property
    def right(self) -> Tensor:
        return self.basis[:, 0]

    @property
    def up(self) -> Tensor:
        return self.basis[:, 1]

    @property
    def forward(self) -> Tensor:
        return self.basis[:, 2]

    def to(self, device=None, dtype=None) -> "Cameras":
        kw = {k: v for k, v in dict(device=device, dtype=dtype).items() if v is not None}
        return Cameras(self.origin.to(**kw), self.basis.to(**kw), self.tan_half_fov_x.to(**kw),
                       self.width, self.height)

    def select(self, index) -> "Cameras":
        """A subset of the views (index: int, slice, list or bool/long tensor)."""
        if isinstance(index, int):
            index = [index]
        return Cameras(self.origin[index], self.basis[index], self.tan_half_fov_x[index],
                       self.width, self.height)

    def with_resolution(self, width: int, height: int) -> "Cameras":
        """The same cameras rendering a resized image; fov_x is kept, so the aspect must match."""
        if abs(width / height - self.width / self.height) > 0.02 * self.width / self.height:
            raise ValueError(f"resizing {self.width}x{self.height} to {width}x{height} changes the aspect ratio")
        return Cameras(self.origin, self.basis, self.tan_half_fov_x, int(width), int(height))

    def transformed(self, center: Tensor, scale: float) -> "Cameras":
        """Cameras in the frame p' = (p - center) / scale (a similarity: directions are unchanged)."""
        center = torch.as_tensor(center, dtype=self.origin.dtype, device=self.origin.device)
        return Cameras((self.origin - center) / scale, self.basis, self.tan_half_fov_x, self.width, self.height)

    def mirrored(self) -> "Cameras":
        """The cameras of the world mirrored in the plane x = 0, each image flipped left to right, so
        the views stay right-handed: pixel (x, y) of a mirrored view sees the mirror image of what
        pixel (W - x, y) of the original sees, and a camera-frame vector (x, y, z) becomes (-x, y, z)."""
        flip = self.origin.new_tensor([-1.0, 1.0, 1.0])
        basis = self.basis * flip  # every row's world x mirrored
        basis = torch.stack([-basis[:, 0], basis[:, 1], basis[:, 2]], dim=1)  # the image's right flipped
        return Cameras(self.origin * flip, basis, self.tan_half_fov_x, self.width, self.height)

    def look_at_params(self) -> dict:
        """origin, target (one unit ahead), up and fov_x_deg as nested lists, for scene.json."""
        return dict(origin=self.origin.tolist(), target=(self.origin + self.forward).tolist(),
                    up=self.up.tolist(), fov_x_deg=self.fov_x_deg.tolist())

    # ---- pixel -> ray ---------------------------------------------------------------------
    def _half_extent(self) -> tuple[Tensor, Tensor]:
        tx = self.tan_half_fov_x
        return tx, tx * (self.height / self.width)

    def directions_at(self, x_px: Tensor, y_px: Tensor) -> Tensor:
        """Unit world ray directions through continuous image points.

        x_px, y_px: (V, ...) float, continuous image coordinates (pixel centres at +0.5).
        Returns (V, ..., 3).
        """
        tx, ty = self._half_extent()
        extra = (1,) * (x_px.dim() - 1)
        sx = ((2 * x_px / self.width - 1) * tx.view(-1, *extra)).unsqueeze(-1)
        sy = ((1 - 2 * y_px / self.height) * ty.view(-1, *extra)).unsqueeze(-1)
        v = lambda a: a.view(a.shape[0], *extra, 3)  # noqa: E731
        d = v(self.forward) + sx * v(self.right) + sy * v(self.up)
        return torch.nn.functional.normalize(d, dim=-1)

    def pixel_grid(self, subpixel: tuple[float, float] = (0.5, 0.5)) -> tuple[Tensor, Tensor]:
        """Continuous coordinates of every pixel: x_px, y_px each (H, W); default at the centres."""
        dev, dt = self.origin.device, self.origin.dtype
        ys = torch.arange(self.height, device=dev, dtype=dt) + subpixel[1]
        xs = torch.arange(self.width, device=dev, dtype=dt) + subpixel[0]
        y, x = torch.meshgrid(ys, xs, indexing="ij")
        return x, y

    def pixel_rays(self, subpixel: tuple[float, float] = (0.5, 0.5)) -> tuple[Tensor, Tensor]:
        """Rays through every pixel of every view.

        Returns origins (V, H, W, 3) and unit directions (V, H, W, 3), world frame.
        """
        x, y = self.pixel_grid(subpixel)
        V = self.num_views
        d = self.directions_at(x.expand(V, -1, -1), y.expand(V, -1, -1))
        return self.origin.view(V, 1, 1, 3).expand_as(d), d

    # ---- point -> pixel -------------------------------------------------------------------
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points into every view.

        points: (N, 3) (shared by all views) or (V, N, 3). Returns xy (V, N, 2) continuous image
        coordinates (x_px, y_px) and depth (V, N) along the forward axis (> 0 in front).
        Points at or behind the camera get non-finite or meaningless xy: mask them by depth.
        """
        if points.dim() == 2:
            points = points.unsqueeze(0)
        rel = points - self.origin[:, None, :]
        cam = torch.einsum("vnk,vjk->vnj", rel, self.basis)  # (V, N, 3): along r, u, f
        depth = cam[..., 2]
        tx, ty = self._half_extent()
        safe = torch.where(depth.abs() > 1e-12, depth, torch.full_like(depth, 1e-12))
        sx = cam[..., 0] / (safe * tx[:, None])
        sy = cam[..., 1] / (safe * ty[:, None])
        x_px = (sx + 1) * (self.width / 2)
        y_px = (1 - sy) * (self.height / 2)
        return torch.stack([x_px, y_px], dim=-1), depth

    # ---- frames ---------------------------------------------------------------------------
    def world_to_camera(self, vectors: Tensor) -> Tensor:
        """World vectors (V, ..., 3) -> camera frame (x = right, y = up, z = -forward)."""
        shape = vectors.shape
        flat = vectors.reshape(shape[0], -1, 3)
        cam = torch.einsum("vnk,vjk->vnj", flat, self.basis)
        cam = cam * cam.new_tensor([1.0, 1.0, -1.0])
        return cam.reshape(shape)

    def camera_to_world(self, vectors: Tensor) -> Tensor:
        """Camera-frame vectors (V, ..., 3) -> world frame."""
        shape = vectors.shape
        flat = vectors.reshape(shape[0], -1, 3) * vectors.new_tensor([1.0, 1.0, -1.0])
        world = torch.einsum("vnj,vjk->vnk", flat, self.basis)
        return world.reshape(shape)


def fov_y_deg(fov_x_deg: float, width: int, height: int) -> float:
    """Vertical field of view of an image with horizontal fov `fov_x_deg`."""
    return math.degrees(2 * math.atan(math.tan(math.radians(fov_x_deg) / 2) * height / width))
