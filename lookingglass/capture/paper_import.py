"""Convert the paper's real-capture layout into a scene folder (DESIGN.md format).

The paper's release describes a real capture with:

- a camera file `cam*.txt`: the view count on the first line, then per view three lines:
  origin, target, up (3 floats each, whitespace or comma separated; blank lines and lines
  starting with '#' are skipped);
- a folder of photos (JPEG from a phone, possibly holding more photos than masks);
- a folder of masks, matched to photos by file stem, binary or in the PNG alpha channel;
- an environment map and the factor bringing it into the photos' units, and fov_x.

The camera file lists the masked views in the *sorted order of the mask names*. We sort with a
natural key (digit runs compare as numbers, letters case-insensitively): "2" < "10". For the
release's own names (fixed-width timestamps such as LRM_20191113_010451) this is the same as
plain sorting; for unpadded numbers (im_1 ... im_12, as the release numbers its processed
views in camera order) only the natural order is right.
"""

from __future__ import annotations

import os
import re
import shutil
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import LookingGlassError
from ..physics.constants import PAPER_CAPTURE_FOV_X_DEG as PAPER_FOV_X_DEG
from ..fileio import check_output_dir, staged_dir
from .images import (HDR_SUFFIXES, check_image_size, read_envmap, read_image, read_mask, read_raw, write_image,
                     write_mask)
from .scene import SCENE_FILE, SceneSpec, ViewSpec, check_staged_scene, save_scene

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")
MASK_SUFFIXES = (".png", ".jpg", ".jpeg")
ENVMAP_SUFFIXES = (".hdr", ".exr", ".png", ".jpg", ".jpeg")
MAX_ASPECT_ERROR_PX = 0.5


def natural_key(name: str) -> tuple:
    """Sort key: digit runs compare as integers, text case-insensitively ("im_2" < "im_10")."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts) + ((2, 0, name),)


def read_paper_cameras(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a `cam*.txt` file of the paper's release.

    Returns origin, target, up: each (V, 3) float64, world frame of the capture. Raises
    LookingGlassError naming the file and the (1-based) line for anything unparsable, and when
    the number of views differs from the count on the first line.
    """
    path = Path(path)
    if not path.is_file():
        raise LookingGlassError("camera file not found" if not path.exists() else "not a file", path)
    try:
        lines = path.read_text(encoding="utf-8", errors="strict").splitlines()
    except (UnicodeDecodeError, OSError) as exc:
        raise LookingGlassError(f"cannot read camera file as text ({exc})", path) from None
    rows = [(n, line.strip()) for n, line in enumerate(lines, 1)]
    rows = [(n, s) for n, s in rows if s and not s.startswith("#")]
    if not rows:
        raise LookingGlassError("camera file is empty (expected the view count on the first line)", path)
    n0, head = rows[0]
    try:
        count = int(head.split()[0]) if len(head.split()) == 1 else None
    except ValueError:
        count = None
    if count is None or count <= 0:
        raise LookingGlassError(f"line {n0}: expected the number of views (a positive integer), got '{head}'", path)
    vectors, numbers = [], []
    for n, s in rows[1:]:
        tokens = s.replace(",", " ").split()
        try:
            vec = [float(t) for t in tokens]
        except ValueError:
            vec = None
        if vec is None or len(vec) != 3 or not all(np.isfinite(vec)):
            raise LookingGlassError(f"line {n}: expected 3 numbers (origin, target or up of a view), got '{s}'", path)
        vectors.append(vec)
        numbers.append(n)
    if len(vectors) != 3 * count:
        whole, rest = divmod(len(vectors), 3)
        got = f"{whole} views" + (f" and {rest} extra line{'s' if rest > 1 else ''}" if rest else "")
        raise LookingGlassError(f"line {n0} says {count} views but the file holds {got} "
                                "(3 lines per view: origin, target, up)", path)
    arr = np.asarray(vectors, dtype=np.float64).reshape(count, 3, 3)
    _check_paper_cameras(arr, np.asarray(numbers).reshape(count, 3), path)
    return arr[:, 0], arr[:, 1], arr[:, 2]


def _check_paper_cameras(arr: np.ndarray, lines: np.ndarray, path: Path) -> None:
    """Refuse degenerate cameras, naming the camera file and the line: arr (V, 3 [origin, target,
    up], 3); lines (V, 3) their 1-based line numbers. The same tests as scene.json's cameras."""
    for i, ((o, t, up), (n_o, n_t, n_up)) in enumerate(zip(arr, lines)):
        scale = max(1.0, float(np.linalg.norm(o)), float(np.linalg.norm(t)))
        dist = float(np.linalg.norm(t - o))
        if dist <= 1e-9 * scale:
            raise LookingGlassError(f"line {n_t}: degenerate camera {i + 1}, its target equals its origin (line {n_o})",
                                    path)
        up_len = float(np.linalg.norm(up))
        if up_len <= 1e-12:
            raise LookingGlassError(f"line {n_up}: degenerate camera {i + 1}, its up vector is zero", path)
        if np.linalg.norm(np.cross((t - o) / dist, up / up_len)) < 1e-6:
            raise LookingGlassError(f"line {n_up}: degenerate camera {i + 1}, its up vector is parallel to its viewing "
                                    f"direction (lines {n_o}-{n_t}: origin, target)", path)


def _find_camera_file(cams: Path) -> Path:
    if cams.is_dir():
        found = sorted(cams.glob("cam*.txt"), key=lambda p: natural_key(p.name))
        if len(found) != 1:
            what = "no cam*.txt" if not found else f"{len(found)} camera files ({', '.join(p.name for p in found)})"
            raise LookingGlassError(f"{what} in this folder: pass the camera file itself", cams)
        return found[0]
    return cams


def _list_files(folder: Path, suffixes: tuple[str, ...], what: str) -> dict[str, list[Path]]:
    """stem -> files with that stem and one of `suffixes` (case-insensitive), hidden files skipped."""
    if not folder.exists():
        raise LookingGlassError(f"{what} folder not found", folder)
    if not folder.is_dir():
        raise LookingGlassError(f"not a folder (expected the {what} folder)", folder)
    out: dict[str, list[Path]] = {}
    for p in folder.iterdir():
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in suffixes:
            out.setdefault(p.stem, []).append(p)
    return out


def _check_aspect(w_in: int, h_in: int, w_out: int, h_out: int, path: Path) -> None:
    """Resizing keeps fov_x; the vertical field then follows from the aspect ratio. Allow the
    resulting misalignment at the top/bottom edge up to MAX_ASPECT_ERROR_PX output pixels
    (2048x1534 -> 480x360, the paper's own conversion, is off by 0.23 px)."""
    err = 0.5 * h_out * abs(1.0 - (h_out * w_in) / (w_out * h_in))
    if err > MAX_ASPECT_ERROR_PX:
        h_fit = max(1, round(w_out * h_in / w_in))
        raise LookingGlassError(
            f"resizing {w_in}x{h_in} to {w_out}x{h_out} changes the aspect ratio (the image edges would be "
            f"{err:.1f} px off the camera model, which keeps fov_x); use {w_out}x{h_fit} or crop the photos "
            "and masks first", path)


@dataclass(frozen=True)
class _PaperView:
    """One masked view of the paper's layout: the mask's file stem, its photo and mask files, and
    its look-at camera (world frame of the capture)."""

    stem: str
    photo: Path
    mask: Path
    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]


def _checked_size(envmap_scale: float, fov_x_deg: float, size) -> tuple[int, int] | None:
    """Check the numeric options of `import_paper`; returns `size` as (W, H) ints (or None)."""
    if not (np.isfinite(envmap_scale) and envmap_scale > 0):
        raise LookingGlassError(f"envmap scale must be a positive number, got {envmap_scale}")
    if not (np.isfinite(fov_x_deg) and 0 < fov_x_deg < 180):
        raise LookingGlassError(f"fov_x must be in (0, 180) degrees, got {fov_x_deg}")
    return None if size is None else check_image_size(size)


def _check_envmap_and_out(envmap: Path, out: Path, inputs: list[Path], force: bool) -> None:
    """The envmap must be a file of a known type; `out` must not replace an input and, unless
    force, must be missing or an empty folder."""
    if not envmap.is_file():
        raise LookingGlassError("environment map not found" if not envmap.exists() else "not a file", envmap)
    if envmap.suffix.lower() not in ENVMAP_SUFFIXES:
        raise LookingGlassError(f"unsupported environment map type '{envmap.suffix}' (use .hdr, .exr, .png or .jpg)",
                                envmap)
    check_output_dir(out, force, inputs)


def _photos_for(stems: list[str], mask_files: dict[str, list[Path]], photo_files: dict[str, list[Path]],
                images: Path) -> list[Path]:
    """The photo of each mask stem (files by stem, as `_list_files`, of the masks and of the photos
    in folder `images`): the same stem, else the same stem in another case. Raises
    LookingGlassError for a stem with no photo or several."""
    lower: dict[str, list[Path]] = {}
    for stem, paths in photo_files.items():
        lower.setdefault(stem.lower(), []).extend(paths)
    photos: list[Path] = []
    unmatched = []
    for stem in stems:
        cands = photo_files.get(stem) or lower.get(stem.lower(), [])
        if not cands:
            unmatched.append(stem)
        elif len(cands) > 1:
            raise LookingGlassError(f"several photos match the mask stem '{stem}': "
                                    f"{', '.join(p.name for p in sorted(cands))}", images)
        else:
            photos.append(cands[0])
    if unmatched:
        shown = ", ".join(mask_files[s][0].name for s in unmatched[:5]) + (" ..." if len(unmatched) > 5 else "")
        raise LookingGlassError(f"no photo in {images} for mask{'s' if len(unmatched) > 1 else ''} {shown} "
                                "(photos are matched to masks by file stem)", mask_files[unmatched[0]][0])
    return photos


def _masks_by_stem(masks: Path) -> dict[str, list[Path]]:
    """The mask files of folder `masks` by stem (as `_list_files`); LookingGlassError for a folder
    without masks or two masks with one stem."""
    mask_files = _list_files(masks, MASK_SUFFIXES, "mask")
    for stem, paths in mask_files.items():
        if len(paths) > 1:
            names = ", ".join(p.name for p in sorted(paths))
            raise LookingGlassError(f"several masks share the stem '{stem}': {names}", masks)
    if not mask_files:
        raise LookingGlassError(f"no masks ({'/'.join(MASK_SUFFIXES)}) in this folder", masks)
    return mask_files


def _paper_views(cams: Path, images: Path, masks: Path) -> list[_PaperView]:
    """The masked views, in the natural order of the mask stems, paired with the camera file's
    views (in that order) and with their photos. Raises LookingGlassError naming the file at fault."""
    cam_file = _find_camera_file(cams)
    origin, target, up = read_paper_cameras(cam_file)
    mask_files = _masks_by_stem(masks)
    photo_files = _list_files(images, PHOTO_SUFFIXES, "image")
    stems = sorted(mask_files, key=natural_key)
    if len(stems) != len(origin):
        raise LookingGlassError(f"{len(stems)} masks in {masks} but the camera file lists {len(origin)} views "
                                "(it must list exactly the masked views)", cam_file)
    photos = _photos_for(stems, mask_files, photo_files, images)
    return [_PaperView(stem, photo, mask_files[stem][0], *(tuple(map(float, a[i])) for a in (origin, target, up)))
            for i, (stem, photo) in enumerate(zip(stems, photos))]


def _convert_view(view: _PaperView, folder: Path, size: tuple[int, int] | None, target_wh: tuple[int, int],
                  first_photo: str, fov_x_deg: float) -> ViewSpec:
    """Write the view's photo and mask into the scene folder `folder` at `target_wh` (W, H),
    resized when `size` asks for it; returns its entry of scene.json."""
    photo, mask_path = view.photo, view.mask
    is_hdr = photo.suffix.lower() in HDR_SUFFIXES
    img = read_image(photo, "srgb")  # (H, W, 3) linear
    mask = read_mask(mask_path)      # (H, W) bool
    (hi, wi), (hm, wm) = img.shape[:2], mask.shape
    if (hi, wi) != (hm, wm):
        hint = " (rotated: check the photo's EXIF orientation)" if (hi, wi) == (wm, hm) else ""
        raise LookingGlassError(f"mask is {wm}x{hm} but its photo {photo.name} is {wi}x{hi}{hint}", mask_path)
    if not mask.any():
        raise LookingGlassError("mask is empty (no object pixel)", mask_path)
    W, H = target_wh
    if (wi, hi) != (W, H):
        if size is None:
            raise LookingGlassError(f"photo is {wi}x{hi} but {first_photo} is {W}x{H}; pass a size to "
                                    "resize all views to one size", photo)
        _check_aspect(wi, hi, W, H, photo)
        img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
        mask = cv2.resize(mask.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA) >= 0.5
        if not mask.any():
            raise LookingGlassError(f"mask is empty after resizing to {W}x{H}", mask_path)
    image_rel = f"images/{view.stem}{'.exr' if is_hdr else '.png'}"
    mask_rel = f"masks/{view.stem}.png"
    write_image(folder / image_rel, img, encoding="srgb")
    write_mask(folder / mask_rel, mask)
    return ViewSpec(image=image_rel, mask=mask_rel, origin=view.origin, target=view.target, up=view.up,
                    fov_x_deg=float(fov_x_deg))


def _write_scene(folder: Path, views: list[_PaperView], envmap: Path, envmap_scale: float,
                 size: tuple[int, int] | None, fov_x_deg: float) -> None:
    """Write the scene folder: the views (in parallel, one per thread), the envmap, scene.json."""
    first = read_raw(views[0].photo)[0].shape
    target_wh = size or (first[1], first[0])
    with ThreadPoolExecutor(max(1, min(8, len(views), os.cpu_count() or 1))) as pool:
        specs = list(pool.map(lambda view: _convert_view(view, folder, size, target_wh, views[0].photo.name,
                                                         fov_x_deg), views))
    env_rel = f"envmap{envmap.suffix.lower()}"
    shutil.copyfile(envmap, folder / env_rel)
    save_scene(folder, SceneSpec(envmap=env_rel, envmap_scale=float(envmap_scale), image_encoding="srgb",
                                 views=specs))


def import_paper(cams: Path, images: Path, masks: Path, envmap: Path, out: Path, envmap_scale: float = 1.0,
                 fov_x_deg: float = PAPER_FOV_X_DEG, size: tuple[int, int] | None = None,
                 force: bool = False) -> Path:
    """Convert the paper's real-capture layout into the scene folder `out`; returns `out`.

    cams: the camera file `cam*.txt` (or a folder holding exactly one). images: folder of
    photos (.png/.jpg/.jpeg, any case; extra photos without masks are ignored). masks: folder of
    masks (binary, or in the PNG alpha channel), matched to photos by file stem; the camera
    file's views follow the masks' natural sort order (see the module docstring).
    envmap: .hdr/.exr or 8-bit equirectangular map, copied unchanged to out/envmap<suffix>,
    with envmap_scale recorded in scene.json. fov_x_deg: horizontal field of view of the photos.
    size: (W, H) to resize photos (cv2.INTER_AREA on linear radiance) and masks (area average,
    object where >= 0.5); fov_x is unchanged, so the aspect ratio must be kept (to within half
    an output pixel at the image edges; otherwise an error, no cropping).

    Output: images/<stem>.png (8-bit sRGB; .exr for HDR photos), masks/<stem>.png, envmap,
    scene.json; written into a temporary folder beside `out`, loaded back with `load_capture`
    (so every scene-folder check applies), then renamed onto `out`. Refuses a non-empty `out`
    unless force. Inputs are only read.
    """
    cams, images, masks, envmap, out = (Path(p) for p in (cams, images, masks, envmap, out))
    size = _checked_size(envmap_scale, fov_x_deg, size)
    _check_envmap_and_out(envmap, out, [cams, images, masks, envmap], force)
    views = _paper_views(cams, images, masks)
    read_envmap(envmap, envmap_scale)  # NaN/inf, shape and sign checks, naming the file

    cam_file = _find_camera_file(cams)
    with staged_dir(out, force, doing=f"import-paper into {out}", inputs=[cams, images, masks, envmap]) as tmp:
        _write_scene(tmp, views, envmap, envmap_scale, size, fov_x_deg)
        caught = check_staged_scene(tmp, out, cam_file)  # the cameras come from the camera file
    for w in caught:
        warnings.warn(w, stacklevel=2)
    return out


__all__ = ["import_paper", "read_paper_cameras", "natural_key", "PAPER_FOV_X_DEG", "SCENE_FILE"]
