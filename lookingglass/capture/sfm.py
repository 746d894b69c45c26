"""Camera poses by structure from motion with pycolmap (`lookingglass sfm`).

Every photo (of the object and of the mirror ball, shot at the same spot) goes into one COLMAP
reconstruction with one shared camera (`SfmConfig.camera_model`, SIMPLE_RADIAL by default), CPU
SIFT, exhaustive matching and incremental mapping. The output folder OUT holds:

- database.db: COLMAP's database (features, matches), kept so that a rerun skips the finished
  steps: extraction and matching are skipped when their stamp (.features.json / .matches.json: the
  photo names and settings they ran with) matches this run's;
- masks/: COLMAP's feature masks made from the object masks (`--masks`; black = no feature), dilated
  by `mask_dilation`: the object refracts the background, so features seen through it lie;
- images/: links to the photos when they come from several folders (model names "folder/file");
- model/: the COLMAP model (binary), written into a temporary folder and renamed into place;
- sfm.json: the registered and unregistered photos, the optical-axis check, the settings.

Photos that do not register are listed (warning and sfm.json), never dropped silently; views whose
optical axes miss the point all axes meet by more than `max_axis_miss_deg` are reported by name.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from ..errors import LookingGlassError
from ..fileio import check_output_dir, staged_dir, within, write_atomic, write_json
from .colmap import read_model
from .config import SfmConfig
from .images import HDR_SUFFIXES, read_image, read_mask, write_image
from .paper_import import PHOTO_SUFFIXES, _list_files, _masks_by_stem, natural_key

SFM_FILE = "sfm.json"


def _photos(image_dirs: list[Path]) -> tuple[Path | None, list[str], dict[str, Path]]:
    """(image_path for COLMAP or None when the photos need a folder of links, image names, name ->
    photo file). One folder of 8-bit photos: names are file names, read in place; several folders:
    'folder/file' (folders named after the given folders, made unique). An HDR photo (.exr/.hdr) is
    named <stem>.png: COLMAP reads a tone-mapped 8-bit copy of it (`_link_photos`)."""
    if not image_dirs:
        raise LookingGlassError("no photo folder given")
    files: dict[str, Path] = {}
    labels: list[str] = []
    for folder in image_dirs:
        found = _list_files(folder, PHOTO_SUFFIXES + tuple(HDR_SUFFIXES), "photo")
        paths = sorted((p for ps in found.values() for p in ps), key=lambda p: natural_key(p.name))
        if not paths:
            raise LookingGlassError(f"no photos ({'/'.join(PHOTO_SUFFIXES + tuple(sorted(HDR_SUFFIXES)))}) in this "
                                    "folder", folder)
        label = folder.resolve().name or "photos"
        while label in labels:
            label += "_"
        labels.append(label)
        for p in paths:
            name = f"{p.stem}.png" if p.suffix.lower() in HDR_SUFFIXES else p.name
            files[name if len(image_dirs) == 1 else f"{label}/{name}"] = p
    in_place = len(image_dirs) == 1 and all(p.name == n for n, p in files.items())
    return image_dirs[0] if in_place else None, sorted(files, key=natural_key), files


def _link_photos(files: dict[str, Path], root: Path) -> None:
    """root/<name> for every photo: a link to it, or for an HDR photo an 8-bit sRGB copy scaled to its
    99th percentile."""
    for name, path in files.items():
        link = root / name
        link.parent.mkdir(parents=True, exist_ok=True)
        if link.is_symlink() or link.exists():
            link.unlink()
        if path.suffix.lower() in HDR_SUFFIXES:
            img = read_image(path)
            write_image(link, img / max(float(np.percentile(img, 99)), 1e-6))
            continue
        try:
            link.symlink_to(path.resolve())
        except OSError:
            shutil.copyfile(path, link)


def _check_sizes(files: dict[str, Path]) -> tuple[int, int]:
    """All photos share one size (one shared camera); returns it (W, H)."""
    size, first = None, None
    for path in files.values():
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | (cv2.IMREAD_ANYDEPTH if path.suffix.lower() == ".hdr" else 0))
        if img is None and path.suffix.lower() == ".exr":
            img = read_image(path)[..., 0]
        if img is None:
            raise LookingGlassError("cannot read image (corrupt or not an image)", path)
        if size is None:
            size, first = img.shape, path
        elif img.shape != size:
            raise LookingGlassError(f"photo is {img.shape[1]}x{img.shape[0]} but {first.name} is {size[1]}x{size[0]}: "
                                    "one shoot, one camera (all photos must share one size)", path)
    return size[1], size[0]


def _stamp_ok(path: Path, stamp: dict) -> bool:
    try:
        return json.loads(path.read_text()) == stamp
    except (OSError, ValueError):
        return False


def _feature_masks(files: dict[str, Path], masks: Path, out: Path, dilation: float, size: tuple[int, int]) -> int:
    """COLMAP masks out/masks/<name>.png (0 where no feature: the object's mask, dilated), one for
    every photo (COLMAP skips a photo whose mask is missing: those without an object mask get an
    all-white one); returns how many photos have an object mask."""
    mask_files = _masks_by_stem(masks)
    count = 0
    for name, photo in files.items():
        found = mask_files.get(photo.stem)
        pixels = np.full((size[1], size[0]), 255, np.uint8)
        if found:
            m = read_mask(found[0])
            if m.shape != pixels.shape:
                raise LookingGlassError(f"mask is {m.shape[1]}x{m.shape[0]} but its photo {photo.name} is "
                                        f"{size[0]}x{size[1]}", found[0])
            r = max(1, int(round(dilation * math.hypot(*size))))
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            pixels[cv2.dilate(m.astype(np.uint8), kernel) > 0] = 0
            count += 1
        target = out / "masks" / f"{name}.png"
        target.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(target, lambda p, a=pixels: cv2.imwrite(str(p), a))
    return count


def axis_misses(origins: np.ndarray, forwards: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The point nearest all optical axes (least squares) and each axis's angle to it (degrees).
    origins, forwards: (V, 3), forwards unit."""
    proj = np.eye(3)[None] - forwards[:, :, None] * forwards[:, None, :]
    point = np.linalg.lstsq(proj.sum(0), np.einsum("vij,vj->i", proj, origins), rcond=None)[0]
    to = point - origins
    cos = (to * forwards).sum(1) / np.maximum(np.linalg.norm(to, axis=1), 1e-12)
    return point, np.degrees(np.arccos(np.clip(cos, -1, 1)))


def run_sfm(image_dirs: list[str | os.PathLike], out: str | os.PathLike, masks: str | os.PathLike | None = None,
            config: SfmConfig = SfmConfig(), reporter=None) -> dict:
    """Structure from motion on every photo of `image_dirs` into the folder `out` (see the module
    docstring); returns the sfm.json record. Re-running on the same folder skips the finished
    steps. Raises LookingGlassError for photos of different sizes, too few registered photos, etc."""
    import pycolmap

    from ..progress import Reporter

    reporter = reporter or Reporter(quiet=True)
    pycolmap.logging.minloglevel = 3  # no COLMAP log lines: the stages show progress, errors are ours
    dirs = [Path(d) for d in image_dirs]
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise LookingGlassError("output path exists and is not a folder", out)
    for d in dirs:
        if within(d, out):
            raise LookingGlassError(f"output folder would replace the input {d}", out)
        if within(out, d):  # database.db and model/ among the photos
            raise LookingGlassError(f"output folder is inside the photo folder {d}; put it elsewhere", out)
    root, names, files = _photos(dirs)
    W, H = _check_sizes(files)
    check_output_dir(out / "model", True)
    out.mkdir(parents=True, exist_ok=True)
    if root is None:  # several folders or HDR photos: links and copies under one image path
        root = out / "images"
        _link_photos(files, root)
    db = out / "database.db"
    settings = asdict(config)
    feature_stamp = {"names": names, "size": [W, H], "masks": str(masks) if masks else None,
                     **{k: settings[k] for k in ("camera_model", "max_image_size", "max_num_features",
                                                 "mask_dilation")}}
    if not _stamp_ok(out / ".features.json", feature_stamp):
        for stale in (db, out / ".features.json", out / ".matches.json"):
            stale.unlink(missing_ok=True)
        with reporter.stage("features", f"SIFT features of {len(names)} photos (CPU)"):
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = config.camera_model
            if masks is not None:
                shutil.rmtree(out / "masks", ignore_errors=True)
                if _feature_masks(files, Path(masks), out, config.mask_dilation, (W, H)):
                    reader.mask_path = str(out / "masks")
            extraction = pycolmap.FeatureExtractionOptions()
            extraction.max_image_size = config.max_image_size
            extraction.sift.max_num_features = config.max_num_features
            extraction.num_threads = max(1, min(4, os.cpu_count() or 1))
            pycolmap.extract_features(str(db), str(root), image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                      reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        write_json(out / ".features.json", feature_stamp)
    else:
        reporter.info("features: already extracted (database.db), skipped")
    if not _stamp_ok(out / ".matches.json", feature_stamp):
        with reporter.stage("matching", f"exhaustive matching of {len(names)} photos"):
            # RANSAC's verification draws from an unseeded generator unless told: a seed makes the two-view
            # geometries, and with them the poses, the same run after run
            verification = pycolmap.TwoViewGeometryOptions()
            verification.ransac.random_seed = config.seed
            pycolmap.match_exhaustive(str(db), verification_options=verification, device=pycolmap.Device.cpu)
        write_json(out / ".matches.json", feature_stamp)
    else:
        reporter.info("matching: already done (database.db), skipped")

    with reporter.stage("mapping", "incremental mapping"):
        options = pycolmap.IncrementalPipelineOptions()
        options.random_seed = config.seed
        options.num_threads = max(1, min(4, os.cpu_count() or 1))
        options.min_model_size = min(options.min_model_size, config.min_registered)
        scratch = out / ".mapping"
        shutil.rmtree(scratch, ignore_errors=True)
        scratch.mkdir()
        models = pycolmap.incremental_mapping(str(db), str(root), str(scratch), options=options)
        shutil.rmtree(scratch, ignore_errors=True)
    if not models:
        raise LookingGlassError(f"structure from motion found no model: the {len(names)} photos share too few "
                                "features (more overlap, more texture around the object)", out)
    best = max(models.values(), key=lambda r: r.num_reg_images())
    registered = sorted((best.image(i).name for i in best.reg_image_ids()), key=natural_key)
    unregistered = [n for n in names if n not in set(registered)]
    if len(registered) < config.min_registered:
        raise LookingGlassError(f"only {len(registered)} of {len(names)} photos registered (at least "
                                f"{config.min_registered} needed); not registered: {', '.join(unregistered[:10])}",
                                out)
    with staged_dir(out / "model", force=True, doing=f"sfm into {out}") as tmp:
        best.write(str(tmp))
    model = read_model(out / "model")
    object_names = None
    if masks is not None:
        stems = set(_masks_by_stem(Path(masks)))
        object_names = [v.name for v in model.views if v.stem in stems]
    checked = [v for v in model.views if object_names is None or v.name in object_names]
    flagged = []
    if len(checked) >= 2:
        point, miss = axis_misses(np.stack([v.origin for v in checked]), np.stack([v.basis[2] for v in checked]))
        flagged = [{"photo": v.name, "axis_miss_deg": float(m)} for v, m in zip(checked, miss)
                   if m > config.max_axis_miss_deg]
    record = {"photos": len(names), "registered": registered, "unregistered": unregistered,
              "camera": {"model": model.views[0].camera.model_name,
                         "params": np.asarray(model.views[0].camera.params).tolist(), "size": [W, H]},
              "axis_check": {"views": [v.name for v in checked], "flagged": flagged,
                             "limit_deg": config.max_axis_miss_deg},
              "config": settings}
    write_json(out / SFM_FILE, record)
    if unregistered:
        reporter.warn(f"{len(unregistered)} photo{'s' if len(unregistered) > 1 else ''} not registered: "
                      + ", ".join(unregistered))
    for f in flagged:
        reporter.warn(f"{f['photo']}: its optical axis misses the point the views look at by "
                      f"{f['axis_miss_deg']:.1f} degrees: a pose that does not fit the shoot?")
    return record


__all__ = ["run_sfm", "axis_misses", "SFM_FILE"]
