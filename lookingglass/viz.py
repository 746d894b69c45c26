"""Pictures for people: tone-mapped photos and normal maps side by side."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .capture.images import linear_to_srgb, write_image


def tonemap(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Linear (H, W, 3) -> display [0, 1] sRGB, exposure set so the mean (inside `mask`) is 0.5."""
    ref = image[mask] if mask is not None and mask.any() else image
    return linear_to_srgb(image * (0.5 / max(float(ref.mean()), 1e-8)))


def normal_map_rgb(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Camera-frame unit normals (H, W, 3) -> colours (n + 1) / 2 inside `mask`, white outside."""
    rgb = (np.asarray(normals) + 1) / 2
    return np.where(mask[..., None], rgb, 1.0).astype(np.float32)


def silhouette_overlay(mask: np.ndarray, cast: np.ndarray) -> np.ndarray:
    """(H, W, 3) display colours comparing a mask with a mesh's ray-cast silhouette (both (H, W)
    bool): the silhouette grey where the mask agrees, blue where the mask is left uncovered,
    orange where the silhouette spills outside the mask; the mask's outline red on top."""
    import cv2

    rgb = np.ones(mask.shape + (3,), np.float32)
    rgb[cast & mask] = (0.62, 0.62, 0.62)
    rgb[mask & ~cast] = (0.25, 0.45, 1.0)
    rgb[cast & ~mask] = (1.0, 0.6, 0.1)
    m = mask.astype(np.uint8)
    outline = (m - cv2.erode(m, np.ones((3, 3), np.uint8))) > 0
    rgb[outline] = (0.9, 0.05, 0.05)
    return rgb


def _crop_box(mask: np.ndarray) -> tuple[slice, slice]:
    ys, xs = np.nonzero(mask)
    if not len(ys):
        return slice(None), slice(None)
    half = int(0.6 * max(ys.max() - ys.min(), xs.max() - xs.min())) + 4
    cy, cx = (ys.min() + ys.max()) // 2, (xs.min() + xs.max()) // 2
    return slice(max(cy - half, 0), cy + half), slice(max(cx - half, 0), cx + half)


def silhouette_sheet(path: str | Path, images: np.ndarray, masks: np.ndarray, casts: np.ndarray,
                     views: list[int], rerendering=None) -> Path:
    """Write a PNG with one row per view in `views`: the photo, then `silhouette_overlay` of its
    mask and the cast silhouette, then (given a `render.compare.Rerendering`) the mesh re-rendered
    as glass with its re-rendering error written on it, cropped around the mask. images
    (V, H, W, 3) linear; masks, casts (V, H, W) bool. The PNG holds display values."""
    rows = []
    for v in views:
        ys, xs = _crop_box(masks[v])
        panels = [tonemap(images[v], masks[v])[ys, xs], silhouette_overlay(masks[v], casts[v])[ys, xs]]
        if rerendering is not None:
            panels.append(_rerender_panel(rerendering, v, masks.shape[2], masks.shape[1])[ys, xs])
        gap = np.ones((panels[0].shape[0], 4, 3), np.float32)
        rows.append(np.concatenate([p for panel in panels for p in (panel, gap)][:-1], axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0)), constant_values=1.0) for r in rows]
    return write_image(path, np.concatenate(rows, axis=0), encoding="linear")


def _rerender_panel(rerendering, v: int, width: int, height: int) -> np.ndarray:
    """View v's re-rendering at width x height in display values, exposed like `tonemap` exposes
    the photo (its mean inside the mask to 0.5), with "error 0.123" written in its corner."""
    photo, mask = rerendering.photos[v], rerendering.masks[v]
    ref = photo[mask] if mask.any() else photo
    panel = linear_to_srgb(rerendering.renders[v] * (0.5 / max(float(ref.mean()), 1e-8)))
    panel = np.ascontiguousarray(np.round(255 * cv2.resize(panel, (width, height), interpolation=cv2.INTER_LINEAR))
                                 .clip(0, 255).astype(np.uint8))  # putText draws on 8-bit images only
    # the label at the mask's top-left, where the crop keeps it
    ys, xs = np.nonzero(cv2.resize(mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST))
    x0, y0 = (int(xs.min()), int(ys.min())) if len(ys) else (2, 2)
    scale = max(0.3, height / 900)
    cv2.putText(panel, f"error {rerendering.error[v]:.3f}", (max(x0 - 10, 2), max(y0 - 4, 12)),
                cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 50), 1, cv2.LINE_AA)
    return panel.astype(np.float32) / 255
