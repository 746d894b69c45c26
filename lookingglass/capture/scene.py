"""The scene folder: `scene.json` plus images, masks and an environment map (DESIGN.md).

Two layers:

- `SceneSpec` / `ViewSpec`: the typed contents of `scene.json` (paths are relative strings naming
  files inside the folder, cameras are look-at parameters in the capture's own world frame).
  `SceneSpec.from_json` checks types and ranges and never touches the image files.
- `Capture`: everything loaded into memory and checked against each other by `load_capture`:
  images (V, H, W, 3) float32 linear, masks (V, H, W) bool, the environment map (He, 2He, 3)
  float32 linear times `envmap_scale`, and `Cameras` (float32).

Problems the user must fix raise `LookingGlassError` naming the file and the problem. Odd but
usable input (unknown keys, duplicated cameras, a mask covering the whole image)
is reported as text by the parsers and emitted by `load_capture` as Python warnings of category
`LookingGlassWarning` (also kept in `Capture.warnings`). Nothing in the scene folder is ever
modified by loading. `save_scene` writes a folder in this format (scene.json last, atomically).
"""

from __future__ import annotations

import difflib
import json
import math
import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..errors import LookingGlassError, LookingGlassWarning
from ..fileio import write_json
from ..physics.camera import Cameras
from ..physics.constants import IOR_GLASS as DEFAULT_IOR, check_ior
from .folder import SCENE_FILE, scene_file_in  # noqa: F401 (SCENE_FILE re-exported)
from .images import read_envmap, read_image, read_mask, write_image, write_mask

IMAGE_ENCODINGS = ("srgb", "linear")

_TOP_KEYS = ("ior", "envmap", "envmap_scale", "image_encoding", "views")
_VIEW_KEYS = ("image", "mask", "origin", "target", "up", "fov_x_deg")

Vec3 = tuple[float, float, float]


def _workers(n: int) -> int:
    return max(1, min(8, n, os.cpu_count() or 1))


# ---------------------------------------------------------------------------------------------
# scene.json <-> typed spec
# ---------------------------------------------------------------------------------------------
@dataclass
class ViewSpec:
    """One view of scene.json.

    image, mask: paths relative to the scene folder. origin, target, up: look-at camera in the
    capture's world frame (up need not be orthogonal to the viewing direction). fov_x_deg:
    horizontal field of view in degrees, in (0, 180).
    """

    image: str
    mask: str
    origin: Vec3
    target: Vec3
    up: Vec3
    fov_x_deg: float

    def to_json_dict(self) -> dict:
        return {"image": self.image, "mask": self.mask, "origin": [float(v) for v in self.origin],
                "target": [float(v) for v in self.target], "up": [float(v) for v in self.up],
                "fov_x_deg": float(self.fov_x_deg)}


@dataclass(kw_only=True)
class SceneSpec:
    """The contents of scene.json (DESIGN.md, "The scene folder the command line reads").

    ior: index of refraction of the object (> 0; 1.4723 glass by default). envmap: path of the
    equirectangular environment map, relative to the folder. envmap_scale: factor bringing the
    envmap into the images' linear units. image_encoding: "srgb" or "linear", for 8-bit images.
    views: at least one.
    """

    ior: float = DEFAULT_IOR
    envmap: str
    envmap_scale: float = 1.0
    image_encoding: str = "srgb"
    views: list[ViewSpec] = field(default_factory=list)

    # ---- reading --------------------------------------------------------------------------
    @classmethod
    def from_json(cls, path: str | os.PathLike) -> tuple["SceneSpec", list[str]]:
        """Parse and check a scene.json file.

        Returns (spec, warnings): warnings are messages about odd but usable content (unknown
        keys, duplicated cameras, ...), each starting with the file's path; they are returned,
        not emitted (`load_capture` emits them). Raises LookingGlassError naming the file for a
        missing/unreadable file, malformed JSON (with line and column) and invalid fields.
        """
        path = Path(path)
        if not path.is_file():
            raise LookingGlassError("scene file not found" if not path.exists() else "not a file", path)
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise LookingGlassError(f"not UTF-8 text ({exc.reason} at byte {exc.start})", path) from None
        except OSError as exc:
            raise LookingGlassError(f"cannot read ({exc.strerror})", path) from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise LookingGlassError(f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}", path) from None
        return cls.from_dict(data, source=path)

    @classmethod
    def from_dict(cls, data: Any, source: str | os.PathLike = SCENE_FILE) -> tuple["SceneSpec", list[str]]:
        """Check a parsed scene.json object; `source` names it in messages. See `from_json`."""
        src = str(source)
        notes: list[str] = []

        def fail(message: str) -> LookingGlassError:
            return LookingGlassError(message, src)

        if not isinstance(data, dict):
            raise fail(f"the top level must be a JSON object, got {_json_type(data)}")
        unknown_top = _unknown_keys(data, _TOP_KEYS)
        notes += [f"{src}: unknown key '{k}'{_did_you_mean(k, _TOP_KEYS)} (ignored)" for k in unknown_top]

        ior = check_ior(_number(data.get("ior", DEFAULT_IOR), "ior", fail), "ior", fail)
        if "envmap" not in data:
            raise fail("missing required key 'envmap' (path of the environment map)"
                       + _unknown_hint(unknown_top))
        envmap = _path_string(data["envmap"], "envmap", fail)
        envmap_scale = _number(data.get("envmap_scale", 1.0), "envmap_scale", fail)
        if envmap_scale <= 0:
            raise fail(f"envmap_scale must be > 0, got {envmap_scale}")
        encoding = data.get("image_encoding", "srgb")
        if encoding not in IMAGE_ENCODINGS:
            raise fail(f"image_encoding must be 'srgb' or 'linear', got {json.dumps(encoding)}")
        if "views" not in data:
            raise fail("missing required key 'views'" + _unknown_hint(unknown_top))
        raw_views = data["views"]
        if not isinstance(raw_views, list):
            raise fail(f"'views' must be a list of view objects, got {_json_type(raw_views)}")
        if not raw_views:
            raise fail("'views' is empty: a capture needs at least one view")

        views = []
        for i, rv in enumerate(raw_views):
            where = f"views[{i}]"
            if not isinstance(rv, dict):
                raise fail(f"{where} must be a JSON object, got {_json_type(rv)}")
            unknown = _unknown_keys(rv, _VIEW_KEYS)
            notes += [f"{src}: unknown key '{k}' in {where}{_did_you_mean(k, _VIEW_KEYS)} (ignored)" for k in unknown]
            missing = [k for k in _VIEW_KEYS if k not in rv]
            if missing:
                raise fail(f"{where} is missing required key{'s' if len(missing) > 1 else ''} "
                           + ", ".join(f"'{k}'" for k in missing) + _unknown_hint(unknown))
            fov = _number(rv["fov_x_deg"], f"{where}.fov_x_deg", fail)
            if not 0 < fov < 180:
                raise fail(f"{where}.fov_x_deg must be in (0, 180) degrees, got {fov}")
            views.append(ViewSpec(image=_path_string(rv["image"], f"{where}.image", fail),
                                  mask=_path_string(rv["mask"], f"{where}.mask", fail),
                                  origin=_vec3(rv["origin"], f"{where}.origin", fail),
                                  target=_vec3(rv["target"], f"{where}.target", fail),
                                  up=_vec3(rv["up"], f"{where}.up", fail), fov_x_deg=fov))
        spec = cls(ior=ior, envmap=envmap, envmap_scale=envmap_scale, image_encoding=encoding, views=views)
        notes += spec._check_cameras(src)
        return spec, notes

    def _check_cameras(self, src: str) -> list[str]:
        """Raise for degenerate cameras; return warnings for duplicated cameras or image files."""
        o = np.array([v.origin for v in self.views], dtype=np.float64)  # (V, 3)
        t = np.array([v.target for v in self.views], dtype=np.float64)
        up = np.array([v.up for v in self.views], dtype=np.float64)
        fov = np.array([v.fov_x_deg for v in self.views], dtype=np.float64)
        fwd = t - o
        dist = np.linalg.norm(fwd, axis=1)
        scale = np.maximum(1.0, np.maximum(np.linalg.norm(o, axis=1), np.linalg.norm(t, axis=1)))
        up_len = np.linalg.norm(up, axis=1)
        for i, v in enumerate(self.views):
            if dist[i] <= 1e-9 * scale[i]:
                raise LookingGlassError(f"views[{i}] ({v.image}): degenerate camera, origin equals target", src)
            if up_len[i] <= 1e-12:
                raise LookingGlassError(f"views[{i}] ({v.image}): degenerate camera, up is the zero vector", src)
        f = fwd / dist[:, None]
        side = np.cross(f, up / up_len[:, None])
        sin = np.linalg.norm(side, axis=1)
        for i in np.flatnonzero(sin < 1e-6):
            v = self.views[i]
            raise LookingGlassError(f"views[{i}] ({v.image}): degenerate camera, up {list(v.up)} is parallel to "
                                    "the viewing direction (target - origin)", src)
        r = side / sin[:, None]
        u = np.cross(r, f)
        # Pairwise identical cameras (same origin, forward, true up, fov), vectorized over (V, V).
        tol = 1e-7 * scale.max()
        same = ((np.linalg.norm(o[:, None] - o[None], axis=-1) <= tol)
                & (np.einsum("ik,jk->ij", f, f) > 1 - 1e-12)
                & (np.einsum("ik,jk->ij", u, u) > 1 - 1e-12)
                & (np.abs(fov[:, None] - fov[None]) <= 1e-9 * fov.max()))
        notes = [f"{src}: views[{i}] ({self.views[i].image}) and views[{j}] ({self.views[j].image}) have "
                 "identical cameras" for i, j in zip(*np.nonzero(np.triu(same, 1)))]
        seen: dict[str, int] = {}
        for i, v in enumerate(self.views):
            key = os.path.normpath(v.image)
            if key in seen:
                notes.append(f"{src}: views[{seen[key]}] and views[{i}] use the same image file {v.image}")
            seen.setdefault(key, i)
        return notes

    # ---- writing --------------------------------------------------------------------------
    def to_json_dict(self) -> dict:
        """The scene.json object (plain Python types, keys in the documented order)."""
        return {"ior": float(self.ior), "envmap": self.envmap, "envmap_scale": float(self.envmap_scale),
                "image_encoding": self.image_encoding, "views": [v.to_json_dict() for v in self.views]}

    def cameras(self, width: int, height: int, dtype: torch.dtype = torch.float32) -> Cameras:
        """The views' cameras for images of width x height pixels (world frame of the capture)."""
        try:
            return Cameras.look_at([v.origin for v in self.views], [v.target for v in self.views],
                                   [v.up for v in self.views], [v.fov_x_deg for v in self.views],
                                   width, height, dtype=dtype)
        except ValueError as exc:  # _check_cameras catches these first; kept as a safety net
            raise LookingGlassError(str(exc)) from None


def _json_type(x: Any) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null",
            int: "a number", float: "a number"}.get(type(x), type(x).__name__)


def _unknown_keys(obj: dict, known: Sequence[str]) -> list[str]:
    return [k for k in obj if k not in known]


def _did_you_mean(key: str, known: Sequence[str]) -> str:
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.5)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _unknown_hint(unknown: list[str]) -> str:
    if not unknown:
        return ""
    return f" (found unknown key{'s' if len(unknown) > 1 else ''} {', '.join(repr(k) for k in unknown)})"


def _number(x: Any, name: str, fail) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise fail(f"{name} must be a number, got {_json_type(x)} {json.dumps(x)}")
    if not math.isfinite(x):
        raise fail(f"{name} must be finite, got {x}")
    return float(x)


def _vec3(x: Any, name: str, fail) -> Vec3:
    ok = (isinstance(x, list) and len(x) == 3
          and all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in x))
    if not ok:
        raise fail(f"{name} must be a list of 3 finite numbers, got {json.dumps(x)}")
    return (float(x[0]), float(x[1]), float(x[2]))


def _path_string(x: Any, name: str, fail) -> str:
    """A file path of scene.json: a non-empty string naming a file inside the scene folder (not
    absolute, no '..' leading out of it), so that the folder holds the whole capture."""
    if not isinstance(x, str) or not x.strip():
        raise fail(f"{name} must be a non-empty file path string, got {json.dumps(x)}")
    norm = os.path.normpath(x.replace("\\", "/"))
    if os.path.isabs(x) or x.startswith(("/", "\\")) or (x[:1].isalpha() and x[1:3] in (":/", ":\\")) \
            or norm == ".." or norm.startswith("../"):
        raise fail(f"{name} must be a path inside the scene folder, got {json.dumps(x)} (paths are relative to the "
                   "folder; copy or link the file into it)")
    return x


# ---------------------------------------------------------------------------------------------
# The loaded capture
# ---------------------------------------------------------------------------------------------
@dataclass
class Capture:
    """A scene folder loaded into memory and checked.

    root: the scene folder. spec: its scene.json.
    images: (V, H, W, 3) float32 linear radiance (8-bit sRGB files linearized).
    masks: (V, H, W) bool, True on the object.
    envmap: (He, 2 He, 3) float32 linear, already multiplied by spec.envmap_scale
      (equirectangular, DESIGN.md convention).
    cameras: `Cameras` (float32, CPU) for W x H images, world frame of the capture.
    ior: index of refraction. warnings: the messages emitted while loading.
    """

    root: Path
    spec: SceneSpec
    images: np.ndarray
    masks: np.ndarray
    envmap: np.ndarray
    cameras: Cameras
    ior: float
    warnings: list[str] = field(default_factory=list)

    @property
    def num_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def image_paths(self) -> list[Path]:
        return [self.root / v.image for v in self.spec.views]

    @property
    def mask_paths(self) -> list[Path]:
        return [self.root / v.mask for v in self.spec.views]

    @property
    def mask_names(self) -> list[str]:
        """The masks' files as scene.json names them (relative to the folder), for messages about a view."""
        return [v.mask for v in self.spec.views]

    @property
    def envmap_path(self) -> Path:
        return self.root / self.spec.envmap

    def with_ior(self, ior: float) -> Capture:
        """This capture with another index of refraction for every stage that reads `ior` (one the
        user knows better, `reconstruct --ior`, or one an evaluation holds); `spec` keeps scene.json's.
        Raises LookingGlassError for an IoR out of [IOR_MIN, IOR_MAX]."""
        return replace(self, ior=check_ior(ior))


def load_capture(folder: str | os.PathLike) -> Capture:
    """Load and check the scene folder `folder` (DESIGN.md format).

    Raises LookingGlassError naming the file and the problem for: a missing folder or scene.json,
    malformed JSON or invalid fields (see `SceneSpec.from_json`), missing or unreadable image,
    mask or envmap files, NaN/inf values, image sizes differing between views, a mask whose size
    differs from its image, an empty mask, and cameras that do not see the object (see
    `check_object_in_front`). Emits `LookingGlassWarning`s for odd but usable input.
    Files are only read, never modified.
    """
    root = Path(folder)
    scene_path = scene_file_in(root)
    spec, notes = SceneSpec.from_json(scene_path)
    for message in notes:  # now, so that they accompany any error below
        warnings.warn(LookingGlassWarning(message), stacklevel=2)
    emitted = len(notes)
    views = spec.views
    V = len(views)

    # Every referenced file first, so that all missing ones are listed at once.
    refs = [(root / spec.envmap, "envmap")]
    for i, v in enumerate(views):
        refs += [(root / v.image, f"views[{i}].image"), (root / v.mask, f"views[{i}].mask")]
    missing = [(p, what) for p, what in refs if not p.is_file()]
    if missing:
        p, what = missing[0]
        more = f"; also missing: {', '.join(str(q) for q, _ in missing[1:6])}" if len(missing) > 1 else ""
        more += " ..." if len(missing) > 6 else ""
        state = "not a file" if p.exists() else "file not found"
        raise LookingGlassError(f"{state} ({what} in {scene_path}){more}", p)

    with ThreadPoolExecutor(_workers(2 * V + 1)) as pool:
        env_job = pool.submit(read_envmap, root / spec.envmap, spec.envmap_scale)
        img_jobs = [pool.submit(read_image, root / v.image, spec.image_encoding) for v in views]
        mask_jobs = [pool.submit(read_mask, root / v.mask) for v in views]
        images = [j.result() for j in img_jobs]  # re-raises the first failing view's error
        masks = [j.result() for j in mask_jobs]
        envmap = env_job.result()

    h, w = images[0].shape[:2]
    for i, v in enumerate(views):
        if images[i].shape[:2] != (h, w):
            hi, wi = images[i].shape[:2]
            raise LookingGlassError(f"image is {wi}x{hi} but views[0] ({views[0].image}) is {w}x{h}; "
                                    "all views must share one image size", root / v.image)
    for i, v in enumerate(views):
        if masks[i].shape != (h, w):
            hm, wm = masks[i].shape
            raise LookingGlassError(f"mask is {wm}x{hm} but its image {v.image} is {w}x{h}", root / v.mask)
    images_a = np.stack(images)  # (V, H, W, 3) float32
    masks_a = np.stack(masks)    # (V, H, W) bool
    del images, masks
    counts = masks_a.reshape(V, -1).sum(axis=1)
    for i in np.flatnonzero(counts == 0):
        raise LookingGlassError(f"mask is empty (no pixel > 127) for views[{i}] ({views[i].image})",
                                root / views[i].mask)
    for i in np.flatnonzero(counts == h * w):
        notes.append(f"{root / views[i].mask}: mask covers the whole image (object fills the frame?)")

    cams64 = spec.cameras(w, h, dtype=torch.float64)
    check_object_in_front(cams64, masks_a, [v.image for v in views], scene_path)

    for message in notes[emitted:]:
        warnings.warn(LookingGlassWarning(message), stacklevel=2)
    return Capture(root=root, spec=spec, images=images_a, masks=masks_a, envmap=envmap,
                   cameras=cams64.to(dtype=torch.float32), ior=spec.ior, warnings=notes)


def triangulate_mask_centroids(cameras: Cameras, masks: np.ndarray, iterations: int = 10,
                               scale: float = 0.05) -> tuple[np.ndarray, float] | None:
    """Robust least-squares point nearest to the lines through each camera and its mask centroid.

    cameras: V views; masks: (V, H, W) bool, non-empty. Lines, not half-rays, so a camera facing
    away still "passes" through the object and is caught by its depth. Weights are re-estimated
    `iterations` times with a Cauchy loss on the angular residual (scale in radians), so one
    wrong camera barely moves the point. Returns (point (3,) float64 in the world frame,
    conditioning in [0, 1]: the smallest eigenvalue of the normalized normal matrix, ~0 when all
    lines are parallel), or None for fewer than two views.
    """
    V, H, W = masks.shape
    if V < 2:
        return None
    m = masks.astype(np.float64)
    counts = m.sum(axis=(1, 2))
    cx = m.sum(axis=1) @ (np.arange(W) + 0.5) / counts  # (V,) continuous pixel coordinates
    cy = m.sum(axis=2) @ (np.arange(H) + 0.5) / counts
    cams = cameras.to(dtype=torch.float64)
    d = cams.directions_at(torch.from_numpy(cx)[:, None], torch.from_numpy(cy)[:, None])[:, 0].numpy()  # (V, 3)
    o = cams.origin.numpy()  # (V, 3)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (V, 3, 3): I - d d^T
    w = np.ones(V)
    p = np.zeros(3)
    cond = 0.0
    for _ in range(iterations):
        A = np.einsum("v,vij->ij", w, proj)
        b = np.einsum("v,vij,vj->i", w, proj, o)
        evals = np.linalg.eigvalsh(A / w.sum())
        cond = float(evals[0])
        if cond < 1e-9:
            return p, cond
        p = np.linalg.solve(A, b)
        rel = p[None] - o
        dist = np.linalg.norm(rel, axis=1)
        resid = np.linalg.norm(np.einsum("vij,vj->vi", proj, rel), axis=1) / np.maximum(dist, 1e-12)  # sin(angle)
        w = 1.0 / (1.0 + (resid / scale) ** 2)
    return p, cond


def check_object_in_front(cameras: Cameras, masks: np.ndarray, names: Sequence[str],
                          source: str | os.PathLike = SCENE_FILE, min_conditioning: float = 1e-3,
                          margin: float = 0.5) -> np.ndarray | None:
    """Raise LookingGlassError if some camera cannot be looking at the object.

    The object centre is triangulated from the mask centroids (`triangulate_mask_centroids`).
    A view fails when that point is behind its camera (depth <= 0) or projects further than
    `margin` x the image size outside its image. names: (V,) image file names for the message.
    Skipped (returns None) for one view or when the lines are nearly parallel (conditioning
    below `min_conditioning`: two lines less than ~4 degrees apart). Returns the point (3,) otherwise.
    """
    res = triangulate_mask_centroids(cameras, masks)
    if res is None or res[1] < min_conditioning:
        return None
    p, _ = res
    cams = cameras.to(dtype=torch.float64)
    xy, depth = cams.project(torch.from_numpy(p)[None])
    xy, depth = xy[:, 0].numpy(), depth[:, 0].numpy()  # (V, 2), (V,)
    W, H = cams.width, cams.height
    outside = ((xy[:, 0] < -margin * W) | (xy[:, 0] > (1 + margin) * W)
               | (xy[:, 1] < -margin * H) | (xy[:, 1] > (1 + margin) * H))
    problems = []
    for i in range(len(depth)):
        if depth[i] <= 0:
            problems.append(f"views[{i}] ({names[i]}): the object is behind this camera (depth {depth[i]:.3g}); "
                            "the camera looks away from it")
        elif outside[i]:
            problems.append(f"views[{i}] ({names[i]}): the object projects to pixel ({xy[i, 0]:.0f}, {xy[i, 1]:.0f}), "
                            f"far outside the {W}x{H} image")
    if problems:
        centre = ", ".join(f"{c:.3g}" for c in p)
        raise LookingGlassError(
            f"camera{'s' if len(problems) > 1 else ''} not looking at the object: " + "; ".join(problems)
            + f" (object centre triangulated from all views' mask centroids: ({centre})); check origin, target "
            "and up", source)
    return p


def check_staged_scene(tmp: Path, out: Path, cameras_from: str | os.PathLike) -> list[Warning]:
    """Load the scene folder an importer has just written into the temporary folder `tmp` (to be
    renamed onto `out`), so every scene-folder check applies (e.g. cameras that do not see the
    object). Its messages name the user's files rather than the temporary folder: `out` for `tmp`,
    and `cameras_from` (the file or model the cameras came from) for tmp/scene.json. Raises that
    LookingGlassError; returns the warnings it emitted (to re-emit once `out` is in place)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            load_capture(tmp)
        except LookingGlassError as exc:
            message = str(exc)
            if exc.path == str(tmp / SCENE_FILE):
                message = f"{cameras_from}: {message[len(exc.path) + 2:]}"
            raise LookingGlassError(message.replace(str(tmp), str(out))) from None
    return [type(w.message)(str(w.message).replace(str(tmp), str(out))) for w in caught]


# ---------------------------------------------------------------------------------------------
# Writing a scene folder
# ---------------------------------------------------------------------------------------------
def save_scene(folder: str | os.PathLike, spec: SceneSpec, images: np.ndarray | None = None,
               masks: np.ndarray | None = None, envmap: np.ndarray | None = None,
               overwrite: bool = False) -> Path:
    """Write a scene folder: the given arrays to the paths named in `spec`, then scene.json.

    images: (V, H, W, 3) float linear radiance (same meaning as `Capture.images`); written as
      8-bit PNG/JPG encoded per spec.image_encoding ("srgb" or clipped "linear"), or as linear
      float when the view's image path ends in .exr/.hdr.
    masks: (V, H, W) bool, written as 8-bit PNG (0/255).
    envmap: (He, 2He, 3) float linear, *including* envmap_scale (same meaning as
      `Capture.envmap`): the file receives envmap / spec.envmap_scale, so save -> load returns it.
    Every file is written atomically and scene.json last. Refuses (LookingGlassError) to replace
    an existing scene.json or any file it would write unless overwrite. Returns scene.json's path.
    """
    root = Path(folder)
    spec, _ = SceneSpec.from_dict(spec.to_json_dict(), source=root / SCENE_FILE)  # same checks as loading
    V = len(spec.views)
    if images is not None:
        images = np.asarray(images)
        if images.ndim != 4 or images.shape[0] != V or images.shape[-1] != 3:
            raise LookingGlassError(f"images must be (V={V}, H, W, 3), got {images.shape}")
        if not np.isfinite(images).all():
            raise LookingGlassError("images contain NaN or infinite values")
    if masks is not None:
        masks = np.asarray(masks).astype(bool, copy=False)
        if masks.ndim != 3 or masks.shape[0] != V:
            raise LookingGlassError(f"masks must be (V={V}, H, W), got {masks.shape}")
        if images is not None and masks.shape[1:] != images.shape[1:3]:
            raise LookingGlassError(f"masks are {masks.shape[1:]} (H, W) but images are {images.shape[1:3]}")
    if envmap is not None:
        envmap = np.asarray(envmap, dtype=np.float32)
        if envmap.ndim != 3 or envmap.shape[1] != 2 * envmap.shape[0] or envmap.shape[2] != 3:
            raise LookingGlassError(f"envmap must be (He, 2 He, 3), got {envmap.shape}")
        if not np.isfinite(envmap).all():
            raise LookingGlassError("envmap contains NaN or infinite values")

    jobs: list[tuple[Path, Any]] = []
    if images is not None:
        for v, img in zip(spec.views, images):
            jobs.append((root / v.image, lambda p, a=img: write_image(p, a, encoding=spec.image_encoding)))
    if masks is not None:
        for v, m in zip(spec.views, masks):
            jobs.append((root / v.mask, lambda p, a=m: write_mask(p, a)))
    if envmap is not None:
        env_file = envmap / np.float32(spec.envmap_scale)
        jobs.append((root / spec.envmap, lambda p, a=env_file: write_image(p, a, encoding="srgb")))
    targets = [root / SCENE_FILE] + [p for p, _ in jobs]
    seen: set[Path] = set()
    for p in targets:
        if p in seen:
            raise LookingGlassError("two arrays would be written to the same file", p)
        seen.add(p)
    if not overwrite:
        existing = [p for p in targets if p.exists()]
        if existing:
            raise LookingGlassError("already exists (pass overwrite=True to replace it)", existing[0])
    root.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(_workers(len(jobs))) as pool:
        for fut in [pool.submit(fn, p) for p, fn in jobs]:
            fut.result()
    return write_json(root / SCENE_FILE, spec.to_json_dict())


__all__ = ["SCENE_FILE", "DEFAULT_IOR", "ViewSpec", "SceneSpec", "Capture", "load_capture", "save_scene",
           "triangulate_mask_centroids", "check_object_in_front", "check_staged_scene"]
