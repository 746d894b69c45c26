"""COLMAP models (from `lookingglass sfm`, the COLMAP GUI or any pycolmap run) and their conversion
into a scene folder (`lookingglass import-colmap`).

A COLMAP model (text or binary; pycolmap reads both) gives each registered photo a camera
(intrinsics with lens distortion, COLMAP's pixel convention: the image's top-left corner at (0, 0),
pixel centres at +0.5, as ours) and a pose cam_from_world = (R, t): x_cam = R x_world + t, the
camera looking along +z with y down. In our look-at convention (lookingglass/physics/camera.py)
that camera has right r = R[0], true up u = -R[1], forward f = R[2] and origin -R^T t.

The scene folder's camera is an ideal pinhole (principal point at the image centre, square pixels,
fov_x), so each photo and mask is undistorted onto such a camera with OpenCV (`cv2.remap`; the map
comes from the model's own `Camera.img_from_cam`, so every COLMAP camera model is handled by
COLMAP's own equations), then resized.

The scene's world frame: the object (the point the views' mask centroids triangulate to) at the
origin, y up (the mean of the cameras' up vectors, or the user's up vector, given in the model's
frame), the first camera in the y-z plane on the +z side; no scaling. The environment map (in the
model's frame, e.g. from `envmap-from-ball`) is rotated by the same transform, so it lines up with
the object with no manual rotation. The transform is written to import.json beside scene.json.
"""

from __future__ import annotations

import math
import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from ..errors import LookingGlassError, LookingGlassWarning
from ..fileio import staged_dir, write_json
from ..physics.camera import Cameras
from ..physics.constants import IOR_GLASS, check_ior
from ..physics.environment import rotate_envmap
from .images import HDR_SUFFIXES, check_image_size, read_envmap, read_image, read_mask
from .paper_import import (PHOTO_SUFFIXES, _check_aspect, _check_envmap_and_out, _list_files,
                           _masks_by_stem, _photos_for, natural_key)
from .scene import SceneSpec, ViewSpec, check_staged_scene, save_scene, triangulate_mask_centroids

IMPORT_FILE = "import.json"
_MODEL_SUBFOLDERS = (".", "model", "sparse/0", "sparse", "0")


# ---------------------------------------------------------------------------------------------
# reading a model
# ---------------------------------------------------------------------------------------------
@dataclass
class ColmapView:
    """One registered photo of a COLMAP model.

    name: its image name in the model (may hold folders: "ball/IMG_1.jpg"). camera: its
    pycolmap.Camera (intrinsics, distortion, size). rotation (3, 3), translation (3,) float64:
    cam_from_world, COLMAP's convention (see the module docstring).
    """

    name: str
    camera: object
    rotation: np.ndarray
    translation: np.ndarray

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    @property
    def origin(self) -> np.ndarray:
        """Camera centre (3,), model's world frame."""
        return -self.rotation.T @ self.translation

    @property
    def basis(self) -> np.ndarray:
        """Rows (right, true up, forward) (3, 3) in the model's world frame (our look-at basis)."""
        return self.rotation * np.array([1.0, -1.0, 1.0])[:, None]


@dataclass
class ColmapModel:
    """The registered photos of a COLMAP model, in the natural order of their names; path: the
    folder holding the model's files."""

    path: Path
    views: list[ColmapView]

    def view_for(self, photo: Path) -> ColmapView:
        """The model's view of the photo file `photo`: same file name, else the same stem; among
        several (photos in different folders of the model), the one in a folder of photo's folder's
        name. Raises LookingGlassError naming the photo when the model does not hold it."""
        for same in (lambda v: Path(v.name).name == photo.name, lambda v: v.stem == photo.stem):
            found = [v for v in self.views if same(v)]
            if len(found) > 1:
                found = [v for v in found if Path(v.name).parent.name == photo.parent.name] or found
            if len(found) == 1:
                return found[0]
            if len(found) > 1:
                raise LookingGlassError(f"several photos of the COLMAP model {self.path} match this photo: "
                                        + ", ".join(v.name for v in found), photo)
        raise LookingGlassError(f"photo is not in the COLMAP model {self.path} (not registered, or from "
                                f"another shoot; the model holds {len(self.views)} photos)", photo)


def find_model_dir(path: str | os.PathLike) -> Path:
    """The folder holding a COLMAP model's files (cameras, images, points3D as .bin or .txt): `path`
    itself, or its model/, sparse/0/, sparse/ or 0/ (the layouts of `lookingglass sfm` and of
    COLMAP's GUI)."""
    path = Path(path)
    if not path.exists():
        raise LookingGlassError("COLMAP model folder not found", path)
    if not path.is_dir():
        raise LookingGlassError("not a folder (expected a COLMAP model folder holding cameras.bin/.txt and "
                                "images.bin/.txt)", path)
    for sub in _MODEL_SUBFOLDERS:
        folder = path / sub
        if all((folder / f"{name}.bin").is_file() or (folder / f"{name}.txt").is_file()
               for name in ("cameras", "images")):
            return folder.resolve() if sub != "." else path
    raise LookingGlassError("no COLMAP model here (cameras.bin/.txt and images.bin/.txt, also looked in "
                            + ", ".join(s + "/" for s in _MODEL_SUBFOLDERS[1:]) + ")", path)


def read_model(path: str | os.PathLike) -> ColmapModel:
    """Read a COLMAP model (text or binary) with pycolmap; see `find_model_dir` for where it may
    lie. Only registered photos (with a pose) are kept. Raises LookingGlassError naming the folder
    for a missing, unreadable or empty model."""
    import pycolmap

    folder = find_model_dir(path)
    for name in ("points3D",):  # pycolmap refuses a model without it; an empty one is fine
        if not ((folder / f"{name}.bin").is_file() or (folder / f"{name}.txt").is_file()):
            raise LookingGlassError(f"COLMAP model lacks {name}.bin/.txt (an empty {name}.txt will do)", folder)
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as exc:  # pycolmap raises ValueError / RuntimeError with the C++ message
        raise LookingGlassError(f"cannot read the COLMAP model ({str(exc).strip().splitlines()[-1]})",
                                folder) from None
    views = []
    for image in rec.images.values():
        if not image.has_pose:
            continue
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        views.append(ColmapView(image.name, rec.cameras[image.camera_id],
                                np.asarray(pose.rotation.matrix(), np.float64),
                                np.asarray(pose.translation, np.float64)))
    if not views:
        raise LookingGlassError("the COLMAP model has no registered photo", folder)
    views.sort(key=lambda v: natural_key(v.name))
    return ColmapModel(folder, views)


# ---------------------------------------------------------------------------------------------
# undistortion onto the scene folder's pinhole camera
# ---------------------------------------------------------------------------------------------
def pinhole_focal(camera) -> float:
    """Focal length (pixels, at the camera's own size) of the ideal pinhole a photo is undistorted
    onto: the model's mean focal length (fx and fy differ only for PINHOLE/OPENCV models)."""
    return float(camera.mean_focal_length())


def undistort_map(camera, focal: float) -> np.ndarray:
    """cv2.remap's map (H, W, 2) float32 from the ideal pinhole (focal `focal`, principal point at
    the image centre, the camera's own size) to the model's distorted photo: output pixel centre
    (c + 1/2, r + 1/2) -> source pixel (OpenCV's convention: integer = pixel centre)."""
    W, H = int(camera.width), int(camera.height)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    rays = np.stack([(xs - W / 2) / focal, (ys - H / 2) / focal, np.ones_like(xs)], axis=-1).reshape(-1, 3)
    src = np.asarray(camera.img_from_cam(rays), np.float64)  # (N, 2), COLMAP pixel coordinates
    return (src - 0.5).reshape(H, W, 2).astype(np.float32)


def undistort(image: np.ndarray, camera, focal: float, linear_mask: bool = False) -> np.ndarray:
    """Photo (H, W, C) float or mask (H, W) bool of `camera`, resampled (bilinear) onto the ideal
    pinhole of `undistort_map`; a mask is resampled as coverage and thresholded at 1/2. Pixels
    whose source lies outside the photo are 0."""
    maps = undistort_map(camera, focal)
    src = image.astype(np.float32) if image.dtype != np.float32 else image
    out = cv2.remap(src, maps[..., 0], maps[..., 1], interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out >= 0.5 if image.dtype == bool and not linear_mask else out


def model_cameras(views: list[ColmapView], width: int, height: int, dtype=torch.float64) -> Cameras:
    """Our pinhole `Cameras` of the views undistorted and resized to width x height, model frame."""
    origin = np.stack([v.origin for v in views])
    basis = np.stack([v.basis for v in views])
    fov = [math.degrees(2 * math.atan(v.camera.width / (2 * pinhole_focal(v.camera)))) for v in views]
    return Cameras.look_at(origin, origin + basis[:, 2], basis[:, 1], fov, width, height, dtype=dtype)


# ---------------------------------------------------------------------------------------------
# the scene's world frame
# ---------------------------------------------------------------------------------------------
def scene_frame(cameras: Cameras, masks: np.ndarray, up=None, where: str | os.PathLike = "") -> tuple[np.ndarray, np.ndarray]:
    """The rigid transform p_scene = rotation @ (p_model - centre) that puts the object at the origin
    and `up` (model frame; default: the cameras' mean up vector) along +y, the first camera on the
    +z side. cameras: model frame; masks (V, H, W) bool. Returns rotation (3, 3), centre (3,)
    float64. Raises LookingGlassError (naming `where`) when the views do not converge."""
    found = triangulate_mask_centroids(cameras, masks)
    if found is None or found[1] < 1e-3:
        raise LookingGlassError("the views' lines of sight through their masks do not meet (fewer than two views, "
                                "or all parallel): no object centre", where)
    centre = found[0]
    cams = cameras.to(dtype=torch.float64)
    y = cams.up.numpy().mean(axis=0) if up is None else np.asarray(up, np.float64)
    y = y / np.linalg.norm(y)
    z = cams.origin.numpy()[0] - centre
    z = z - (z @ y) * y
    if np.linalg.norm(z) < 1e-9 * max(1.0, float(np.linalg.norm(centre))):
        z = np.cross(y, [1.0, 0, 0]) if abs(y[0]) < 0.9 else np.cross(y, [0, 0, 1.0])
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    return np.stack([x, y, z]), centre


# ---------------------------------------------------------------------------------------------
# import-colmap
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Source:
    """One view to import: its mask's stem, photo and mask files and the model's view of it."""

    stem: str
    photo: Path
    mask: Path
    view: ColmapView


def _load_view(src: _Source, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The view's photo (H, W, 3) float32 linear and mask (H, W) bool, undistorted and resized to
    `size` (W, H). Raises LookingGlassError naming the file at fault."""
    cam = src.view.camera
    img = read_image(src.photo, "srgb")
    mask = read_mask(src.mask)
    (hi, wi), (hm, wm) = img.shape[:2], mask.shape
    if (wi, hi) != (cam.width, cam.height):
        raise LookingGlassError(f"photo is {wi}x{hi} but its camera in the COLMAP model ({src.view.name}) is "
                                f"{cam.width}x{cam.height}: a photo of another size or camera", src.photo)
    if (hi, wi) != (hm, wm):
        hint = " (rotated: check the photo's EXIF orientation)" if (hi, wi) == (wm, hm) else ""
        raise LookingGlassError(f"mask is {wm}x{hm} but its photo {src.photo.name} is {wi}x{hi}{hint}", src.mask)
    if not mask.any():
        raise LookingGlassError("mask is empty (no object pixel)", src.mask)
    focal = pinhole_focal(cam)
    img = undistort(img, cam, focal)
    cover = undistort(mask.astype(np.float32), cam, focal)
    W, H = size
    if (wi, hi) != (W, H):
        _check_aspect(wi, hi, W, H, src.photo)
        img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
        cover = cv2.resize(cover, (W, H), interpolation=cv2.INTER_AREA)
    mask = cover >= 0.5
    if not mask.any():
        raise LookingGlassError(f"mask is empty after undistorting and resizing to {W}x{H}", src.mask)
    return np.maximum(img, 0), mask


def _sources(model: ColmapModel, images: Path, masks: Path) -> tuple[list[_Source], list[str]]:
    """The masked photos (natural order of the mask stems) with their model views, and the names of
    the photos skipped for want of a mask."""
    photo_files = _list_files(images, PHOTO_SUFFIXES + tuple(HDR_SUFFIXES), "image")
    mask_files = _masks_by_stem(masks)
    stems = sorted(mask_files, key=natural_key)
    photos = _photos_for(stems, mask_files, photo_files, images)
    masked = {p.stem.lower() for p in photos}
    skipped = sorted((p.name for s, ps in photo_files.items() if s.lower() not in masked for p in ps),
                     key=natural_key)
    return [_Source(s, p, mask_files[s][0], model.view_for(p)) for s, p in zip(stems, photos)], skipped


def import_colmap(model: str | os.PathLike, images: str | os.PathLike, masks: str | os.PathLike,
                  envmap: str | os.PathLike, out: str | os.PathLike, ior: float = IOR_GLASS,
                  size: tuple[int, int] | None = None, up=None, force: bool = False) -> Path:
    """Convert a COLMAP model, its photos, the object's masks and an environment map (in the model's
    frame) into the scene folder `out`; returns `out`.

    model: a COLMAP model folder (`find_model_dir`). images: folder of photos; photos without a
    mask are skipped with a warning naming them. masks: folder of masks matched to photos by file
    stem (plain grey, or a PNG's alpha channel). envmap: equirectangular map, model frame, written
    rotated into the scene's frame (`scene_frame`) as envmap.hdr. size: (W, H) of the scene's
    images (default: the first view's camera size; the aspect ratio must be kept). up: (3,) up
    direction in the model's frame (default: the cameras' mean up).

    Output: images/<stem>.png (8-bit sRGB; .exr for HDR photos), masks/<stem>.png, envmap.hdr,
    scene.json and import.json (the transform, the views' model names, the skipped photos); written
    into a temporary folder, checked by loading it back (`check_staged_scene`) and only then renamed
    onto `out`. Raises LookingGlassError naming the file at fault; inputs are only read.
    """
    model, images, masks, envmap, out = (Path(p) for p in (model, images, masks, envmap, out))
    ior = check_ior(ior, "--ior")
    if size is not None:
        size = check_image_size(size, "--size")
    if up is not None:
        up = np.asarray(up, np.float64)
        if up.shape != (3,) or not np.isfinite(up).all() or np.linalg.norm(up) < 1e-12:
            raise LookingGlassError(f"--up must be three finite numbers, not all zero, got {up.tolist()}")
    _check_envmap_and_out(envmap, out, [model, images, masks, envmap], force)
    colmap = read_model(model)
    sources, skipped = _sources(colmap, images, masks)
    if skipped:
        warnings.warn(LookingGlassWarning(f"{images}: {len(skipped)} photo{'s' if len(skipped) > 1 else ''} without a "
                                          f"mask skipped: {', '.join(skipped)}"), stacklevel=2)
    env = read_envmap(envmap)
    first = sources[0].view.camera
    size = size or (int(first.width), int(first.height))
    with ThreadPoolExecutor(max(1, min(4, len(sources), os.cpu_count() or 1))) as pool:
        loaded = list(pool.map(lambda s: _load_view(s, size), sources))
    photos = np.stack([img for img, _ in loaded])
    object_masks = np.stack([m for _, m in loaded])
    del loaded

    cams = model_cameras([s.view for s in sources], *size)
    rotation, centre = scene_frame(cams, object_masks, up, colmap.path)
    R = torch.from_numpy(rotation)
    origin = (cams.origin - torch.from_numpy(centre)) @ R.T
    basis = cams.basis @ R.T  # rows r, u, f in the scene frame
    fov = cams.fov_x_deg
    hdr = [s.photo.suffix.lower() in HDR_SUFFIXES for s in sources]
    views = [ViewSpec(image=f"images/{s.stem}{'.exr' if h else '.png'}", mask=f"masks/{s.stem}.png",
                      origin=tuple(origin[i].tolist()), target=tuple((origin[i] + basis[i, 2]).tolist()),
                      up=tuple(basis[i, 1].tolist()), fov_x_deg=float(fov[i]))
             for i, (s, h) in enumerate(zip(sources, hdr))]
    spec = SceneSpec(ior=float(ior), envmap="envmap.hdr", envmap_scale=1.0, image_encoding="srgb", views=views)
    env_scene = rotate_envmap(torch.from_numpy(env), R).numpy()
    record = {"model": str(colmap.path), "world_from_model": {
                  "rotation": rotation.tolist(), "centre": centre.tolist(),
                  "meaning": "p_scene = rotation @ (p_model - centre); directions d_scene = rotation @ d_model"},
              "up_model": rotation[1].tolist(), "up_from": "cameras" if up is None else "--up",
              "views": [{"stem": s.stem, "photo": str(s.photo), "mask": str(s.mask), "model_image": s.view.name}
                        for s in sources],
              "skipped_photos": skipped}
    inputs = [model, images, masks, envmap]
    with staged_dir(out, force, doing=f"import-colmap into {out}", inputs=inputs) as tmp:
        write_json(tmp / IMPORT_FILE, record)
        save_scene(tmp, spec, images=photos, masks=object_masks, envmap=env_scene)
        caught = check_staged_scene(tmp, out, colmap.path)
    for w in caught:
        warnings.warn(w, stacklevel=2)
    return out


__all__ = ["ColmapModel", "ColmapView", "find_model_dir", "read_model", "undistort_map", "undistort",
           "model_cameras", "scene_frame", "import_colmap", "IMPORT_FILE"]
