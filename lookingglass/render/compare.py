"""A mesh re-rendered as glass from a capture's cameras and compared with its photos.

This is the check that a reconstruction explains the observations: the project's renderer
(`render_views`, the one that made the training data) renders the mesh under the capture's
environment map from every camera, at a reduced size, and the result is compared with the photos
shrunk the same way. Both are normalized as the normal network's inputs are (one exposure factor
bringing the photos' mean to 0.5, then clipped to [0, 1]), so the error reads the same for any
capture's units: the mean absolute difference per channel over the pixels where either the mask
or the mesh's silhouette is (a shape that misses part of the object, or covers background, pays
for those pixels too).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from ..capture.images import exposure_factor, resize_images, resize_masks
from ..config import RERENDER_SAMPLES, RERENDER_WIDTH  # noqa: F401 (re-exported)
from ..physics.environment import EnvironmentMap
from .tracer import RenderConfig, render_views



@dataclass
class Rerendering:
    """photos, renders (V, h, w, 3) float32 normalized and clipped to [0, 1] (the mesh traced only in
    masks | silhouettes, the environment seen straight elsewhere: `render_views`' region); masks,
    silhouettes (V, h, w) bool (the capture's masks shrunk, the mesh's pixel-centre silhouette);
    error (V,) the mean absolute difference per channel over masks | silhouettes."""

    photos: np.ndarray
    renders: np.ndarray
    masks: np.ndarray
    silhouettes: np.ndarray
    error: np.ndarray

    @property
    def mean_error(self) -> float:
        return float(np.mean(self.error))


def photos_at(capture, width: int) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The capture's photos at `width` x (width * H / W) (no wider than they are), normalized (the
    exposure factor that brings their mean to 0.5, then clipped to [0, 1]), its masks at that size,
    and the factor (the environment map takes the same)."""
    V, H, W = capture.masks.shape
    width = min(int(width), W)
    height = max(1, round(width * H / W))
    photos = torch.as_tensor(capture.images).float()
    factor = exposure_factor(photos)
    return (resize_images(photos * factor, width, height).clamp(0, 1),
            resize_masks(torch.as_tensor(capture.masks).bool(), width, height), factor)


def rerender(mesh: trimesh.Trimesh, capture, width: int = RERENDER_WIDTH, samples_per_axis: int = RERENDER_SAMPLES,
             threads: int | None = None, device: str = "cpu", seed: int = 0, ior: float | None = None,
             prepared: tuple[torch.Tensor, torch.Tensor, float] | None = None) -> Rerendering:
    """Render `mesh` (closed, outward, the capture's frame) under `capture`'s environment map from
    its cameras at `width` x (width * H / W) pixels and compare with the photos. capture: anything
    with images (V,H,W,3) linear, masks (V,H,W), envmap, cameras and ior (a loaded `Capture`);
    `ior`, when given, is rendered instead of the capture's (the IoR estimate's candidates).
    prepared: `photos_at(capture, width)` when the caller renders several meshes or IoRs against
    the same photos (it is then not recomputed; `width` is read from it)."""
    photos, masks, factor = photos_at(capture, width) if prepared is None else prepared
    height, width = masks.shape[1:]
    cams = capture.cameras.with_resolution(width, height)
    envmap = EnvironmentMap(torch.as_tensor(capture.envmap).float())
    config = RenderConfig(ior=capture.ior if ior is None else ior, samples_per_axis=samples_per_axis, threads=threads, device=device,
                          seed=seed)
    result = render_views(mesh, envmap, cams, config, region=masks)  # the error reads masks | silhouettes only
    renders = (result.image.cpu() * factor).clamp(0, 1)
    silhouettes = result.mask.cpu()
    region = (masks | silhouettes).unsqueeze(-1).float()
    diff = (renders - photos).abs() * region
    error = diff.sum(dim=(1, 2, 3)) / (3 * region.sum(dim=(1, 2, 3))).clamp(min=1)
    return Rerendering(photos.numpy(), renders.numpy(), masks.numpy(), silhouettes.numpy(), error.numpy())
