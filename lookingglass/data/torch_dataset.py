"""A torch `Dataset` over the scenes `lookingglass generate` writes (see `data/dataset.py`).

Normalization (DESIGN.md, "Image units"): the stored images are linear HDR radiance. Per scene,
one factor k = target_mean / mean(images) is computed over *all* pixels of *all* the scene's views
and all three channels (not only the mask: the background matters to the network as much as the
object, and at inference `normals.inputs.NormalInputs.from_capture` uses the same rule through the same
function, `exposure_factor`). The image becomes clip(k * image, 0, 1); the environment map gets
the same k and is *not* clipped (it stays HDR: the rendering layer must see the sun as bright as
it is). target_mean is 0.5; with augment=True it is drawn from U[0.4, 0.6] per item.

Augmentation: that exposure draw and, with `photo_noise` > 0, phone-photo degradation with that
chance per item: the normalized image is encoded to sRGB, gets Gaussian sensor noise (sigma up to
`PHOTO_NOISE_SIGMA` of full scale) and 8-bit quantization, and is decoded again, as a JPEG or PNG
photo reaches `reconstruct` (capture/images.py decodes with the same sRGB curve). Flipping one image
alone would need a mirrored world per view (one environment map cannot be mirrored consistently for every camera of
a rig); mirroring the whole world, every camera and the map with it, is exact and is the trainer's
(`train-normals --mirror-augment`, `NormalInputs.mirrored`). Rotating world + environment about +y leaves every
camera-frame quantity unchanged.
The random state of item i is numpy default_rng([seed, i, n]) with n the number of times this
Dataset object has served item i, so a run is reproducible for a seed (with DataLoader workers,
each worker counts its own draws).

Every item is a dict of tensors (V views, H x W, He x 2He environment):
    image            (V, 3, H, W) float32  normalized and clipped to [0, 1]
    mask             (V, H, W)    bool     object mask
    n1, n2           (V, 3, H, W) float32  GT normals at the first / second hit, camera frame
    valid            (V, H, W)    bool     the GT two-bounce path is valid (N2 supervised there)
    tir              (V, H, W)    bool     total internal reflection at the second hit
    vh_mask          (V, H, W)    bool     the visual hull covers the pixel centre
    vh_n1, vh_n2     (V, 3, H, W) float32  the hull's two-bounce normals (Ñ1, Ñ2), camera frame
    vh_valid, vh_tir (V, H, W)    bool
    envmap           (3, He, 2He) float32  the environment map times the same factor
    origin, target, up (V, 3)     float32  look-at cameras, world frame
    fov_x_deg        (V,)         float32
    factor           ()           float32  the factor applied to the stored radiance
    target_mean      ()           float32  the mean the factor aimed at
    index            ()           int64    the item index
"""

from __future__ import annotations

import functools
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from ..errors import LookingGlassError
from .dataset import (SPLITS, DatasetConfig, is_finished, load_maps, load_scene_mesh, load_scene_meta,
                      rig_subset)

_IMAGE_KEYS = ("image", "n1", "n2", "vh_n1", "vh_n2")  # (V, H, W, 3) -> (V, 3, H, W)


@functools.lru_cache(maxsize=32)
def _cached_envmap(desc_json: str, folder: str | None, height: int) -> np.ndarray:
    from .envmaps import envmap_from_description

    env = envmap_from_description(json.loads(desc_json), folder, height)
    env.setflags(write=False)
    return env


def scene_envmap(meta: dict, folder=None) -> np.ndarray:
    """The scene's environment map (He, 2He, 3) float32, unnormalized, regenerated from its
    description at the height it was rendered with; cached (the last 32 maps per process).
    The array is read-only and shared."""
    desc = json.dumps(meta["envmap"], sort_keys=True)
    return _cached_envmap(desc, None if folder is None else str(folder), int(meta["envmap_height"]))


PHOTO_NOISE_SIGMA = 0.01  # sensor noise, a fraction of the 8-bit range (2.5 levels at most)


def as_8bit_photo(image: torch.Tensor, sigma: float, rng: np.random.Generator) -> torch.Tensor:
    """`image` (linear, [0, 1]) as an 8-bit sRGB photo with Gaussian sensor noise `sigma` (of full
    scale, added in sRGB) would decode: linear, quantized to the 256 levels' images."""
    from ..capture.images import linear_to_srgb, srgb_to_linear

    encoded = linear_to_srgb(image.numpy()) + rng.normal(0.0, sigma, image.shape).astype(np.float32)
    levels = np.clip(np.round(encoded * 255.0), 0, 255) / 255.0
    return torch.from_numpy(srgb_to_linear(levels))


class TransparentSceneDataset(Dataset):
    """The finished scenes of ROOT/SPLIT, in index order.

    root: the folder given to `lookingglass generate --out`. split: "train" or "test".
    views: None for every stored view, or 5 / 10 / 20 to serve that paper rig out of a larger
        stored one (the rigs are nested; note the hull maps still come from all stored views,
        so they are better than a hull carved from the subset alone).
    augment: draw the normalization's target mean from `mean_range` (else `target_mean`), and
        degrade a `photo_noise` fraction of the items like 8-bit photos.
    seed: seed of the augmentation draws. envmap_folder: where the natural maps are
        (default `envmaps.default_envmap_folder()`).
    """

    def __init__(self, root, split: str = "train", views: int | None = None, augment: bool = False,
                 seed: int = 0, target_mean: float = 0.5, mean_range: tuple[float, float] = (0.4, 0.6),
                 envmap_folder=None, photo_noise: float = 0.0):
        if split not in SPLITS:
            raise LookingGlassError(f"split must be train or test, got {split!r}")
        self.split_dir = Path(root) / split
        cfg_path = self.split_dir / "config.json"
        if not cfg_path.is_file():
            raise LookingGlassError("no dataset here (config.json missing); make one with `lookingglass generate`",
                                    self.split_dir)
        saved = json.loads(cfg_path.read_text())
        self.config = DatasetConfig.from_dict(saved["config"])
        self.stored_views = int(saved["views"])
        self.view_index = None if views is None or views == self.stored_views else rig_subset(self.stored_views, views)
        self.views = self.stored_views if views is None else int(views)
        folders = sorted(p for p in self.split_dir.glob("scene_*") if p.is_dir())
        finished = [is_finished(p) for p in folders]
        self.scene_dirs = [p for p, done in zip(folders, finished) if done]
        if not self.scene_dirs:
            raise LookingGlassError("no finished scenes (scene_*/meta.json)", self.split_dir)
        unfinished = [p.name for p, done in zip(folders, finished) if not done]
        if unfinished:  # a table or a training run over what is left would be a silent partial result
            raise LookingGlassError(
                f"{len(unfinished)} scene(s) unfinished or damaged ({', '.join(unfinished[:3])}"
                f"{', ...' if len(unfinished) > 3 else ''}: meta.json unreadable or a data file missing); re-run "
                "`lookingglass generate` with the same options to finish them", self.split_dir)
        self.augment, self.seed = bool(augment), int(seed)
        self.target_mean, self.mean_range = float(target_mean), tuple(float(m) for m in mean_range)
        self.photo_noise = float(photo_noise)
        self.envmap_folder = envmap_folder
        self._draws: dict[int, int] = defaultdict(int)

    def __len__(self) -> int:
        return len(self.scene_dirs)

    def meta(self, index: int) -> dict:
        return load_scene_meta(self.scene_dirs[index])

    def meshes(self, index: int):
        """(ground truth, visual hull) of scene `index` as trimesh.Trimesh, world frame."""
        d = self.scene_dirs[index]
        return load_scene_mesh(d, "mesh"), load_scene_mesh(d, "hull")

    def capture(self, index: int, ior: float | None = None):
        """Scene `index` as a `Capture`, what `load_capture` gives for its scene folder: the stored
        linear images (not normalized), masks, environment map (unscaled), cameras and IoR (the
        scene's own, meta.json's; `ior`, when given, instead: one an evaluation holds for every
        scene, `Capture.with_ior`); the views this dataset serves. `save_scene(folder, c.spec,
        c.images, c.masks, c.envmap)` writes it as a scene folder `reconstruct` reads (EXR images
        and map: exact)."""
        from ..capture.scene import Capture, SceneSpec, ViewSpec
        from .dataset import scene_cameras

        scene_dir, meta = self.scene_dirs[index], self.meta(index)
        sel = slice(None) if self.view_index is None else self.view_index
        maps = load_maps(scene_dir)
        cameras = scene_cameras(meta).select(sel)
        # the rig's own look-at numbers (not re-derived from the float32 cameras), so a scene folder
        # written from this capture gives back the very cameras the scene was rendered and carved with
        rig = {k: np.asarray(meta["cameras"][k], np.float64)[sel].tolist() for k in ("origin", "target", "up",
                                                                                      "fov_x_deg")}
        views = [ViewSpec(image=f"images/{v:02d}.exr", mask=f"masks/{v:02d}.png", origin=tuple(rig["origin"][v]),
                          target=tuple(rig["target"][v]), up=tuple(rig["up"][v]), fov_x_deg=rig["fov_x_deg"][v])
                 for v in range(cameras.num_views)]
        spec = SceneSpec(ior=float(meta["ior"]), envmap="envmap.exr", image_encoding="linear", views=views)
        capture = Capture(root=scene_dir, spec=spec, images=maps["image"][sel].astype(np.float32),
                          masks=maps["mask"][sel].astype(bool), envmap=np.array(scene_envmap(meta, self.envmap_folder)),
                          cameras=cameras, ior=float(meta["ior"]))
        return capture if ior is None else capture.with_ior(ior)

    def hull(self, index: int):
        """Scene `index`'s stored visual hull as a `VisualHull` with the normalization `generate`
        recorded (carved from every stored view; world frame)."""
        from ..hull import VisualHull

        frame = self.meta(index)["hull"]
        return VisualHull.from_mesh(load_scene_mesh(self.scene_dirs[index], "hull"), frame["center"], frame["scale"],
                                    frame.get("voxel_size", float("nan")), frame.get("view_coverage", ()))

    def _draws_for(self, index: int) -> tuple[float, float]:
        """(target mean, photo-noise sigma; 0 = a clean image) of this serving of item `index`."""
        if not self.augment:
            return self.target_mean, 0.0
        rng = np.random.default_rng([self.seed, int(index), self._draws[index]])
        self._draws[index] += 1
        target = float(rng.uniform(*self.mean_range))
        noisy = rng.random() < self.photo_noise
        return target, float(rng.uniform(0.0, PHOTO_NOISE_SIGMA)) if noisy else 0.0

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        from ..capture.images import exposure_factor

        if not -len(self) <= index < len(self):
            raise IndexError(f"scene {index} out of range ({len(self)} scenes)")
        index = index % len(self)
        scene_dir = self.scene_dirs[index]
        maps, meta = load_maps(scene_dir), load_scene_meta(scene_dir)
        sel = slice(None) if self.view_index is None else self.view_index
        maps = {k: v[sel] for k, v in maps.items()}
        target, sigma = self._draws_for(index)
        image = torch.from_numpy(maps["image"].astype(np.float32))
        try:
            factor = exposure_factor(image, target)
        except ValueError as exc:
            raise LookingGlassError(str(exc), scene_dir) from None
        env = torch.from_numpy(scene_envmap(meta, self.envmap_folder).astype(np.float32))
        out: dict[str, torch.Tensor] = {}
        for key, value in maps.items():
            t = torch.from_numpy(np.ascontiguousarray(value))
            if key in _IMAGE_KEYS:
                t = t.float().permute(0, 3, 1, 2).contiguous()
            out[key] = t
        out["image"] = (out["image"] * factor).clamp_(0.0, 1.0)
        if sigma > 0:
            out["image"] = as_8bit_photo(out["image"], sigma, np.random.default_rng([self.seed, index, 1 << 20,
                                                                                     self._draws[index]]))
        out["envmap"] = (env * factor).permute(2, 0, 1).contiguous()
        cams = meta["cameras"]
        for key in ("origin", "target", "up", "fov_x_deg"):
            out[key] = torch.tensor(np.asarray(cams[key])[sel], dtype=torch.float32)
        out["factor"] = torch.tensor(factor, dtype=torch.float32)
        out["target_mean"] = torch.tensor(target, dtype=torch.float32)
        out["index"] = torch.tensor(index, dtype=torch.int64)
        return out


__all__ = ["TransparentSceneDataset", "scene_envmap"]
