"""Pictures for people: tone-mapped photos and normal maps side by side."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from .capture.images import linear_to_srgb, write_image
from .physics.camera import Cameras
from .render.tracer import trace_two_bounce


def tonemap(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Linear (H, W, 3) -> display [0, 1] sRGB, exposure set so the mean (inside `mask`) is 0.5."""
    ref = image[mask] if mask is not None and mask.any() else image
    return linear_to_srgb(image * (0.5 / max(float(ref.mean()), 1e-8)))


def normal_map_rgb(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Camera-frame unit normals (H, W, 3) -> colours (n + 1) / 2 inside `mask`, white outside."""
    rgb = (np.asarray(normals) + 1) / 2
    return np.where(mask[..., None], rgb, 1.0).astype(np.float32)


def overview(path: str | Path, image: np.ndarray, mask: np.ndarray, cameras: Cameras,
             meshes: dict[str, trimesh.Trimesh]) -> Path:
    """Write a PNG row for one view: the photo, its mask, then the first-hit normals of each mesh
    seen by `cameras` (one view), cropped around the mask; the PNG holds display values."""
    panels = [tonemap(image, mask), np.repeat(mask[..., None].astype(np.float32), 3, axis=-1)]
    for mesh in meshes.values():
        tb = trace_two_bounce(mesh, cameras)
        panels.append(normal_map_rgb(tb.normal1[0].numpy(), tb.mask[0].numpy()))
    ys, xs = np.nonzero(mask)
    if len(ys):  # crop to the object with a margin, so it is not a speck in the frame
        half = int(0.75 * max(ys.max() - ys.min(), xs.max() - xs.min())) + 4
        cy, cx = (ys.min() + ys.max()) // 2, (xs.min() + xs.max()) // 2
        y0, x0 = max(cy - half, 0), max(cx - half, 0)
        panels = [p[y0:cy + half, x0:cx + half] for p in panels]
    gap = np.ones((panels[0].shape[0], 4, 3), np.float32)
    row = np.concatenate([x for p in panels for x in (p, gap)][:-1], axis=1)
    return write_image(path, row, encoding="linear")
