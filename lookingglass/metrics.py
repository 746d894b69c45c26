"""Evaluation metrics, defined exactly as in DESIGN.md "Metrics" so numbers compare with the paper.

Shape metrics (paper Tables 2 and 3), on the unit-sphere scale, from `samples` points drawn
area-uniformly on each mesh with the normals of the faces they lie on. With d(a -> B) the distance
from a point a to its nearest sample in B:

- ``cd``     = 1/2 (mean_gt d(gt -> pred)^2 + mean_pred d(pred -> gt)^2), reported x 1e4.
- ``metro``  = max over both directions of d^2, reported x 1e3.
- ``cdn_mean`` / ``cdn_med`` = 1/2 (mean / median over gt points of the angle between a point's
  normal and its nearest pred sample's normal + the same from pred to gt), in degrees. Normals
  are *not* flipped to agree: an inside-out mesh scores about 180 degrees.

"Unit-sphere scale": both meshes are mapped by the one similarity transform that normalizes the
ground truth, p -> (p - c) / s, with c the centre of the GT's axis-aligned bounding box and
s = max |v - c| over the GT's vertices that faces use (so the GT then has max |p| = 1, DESIGN's
normalization). The centre does not change any metric (the same translation is applied to both
meshes); it only fixes s. The bounding-box centre is cheap, exact, independent of how finely the
surface is tessellated (a vertex mean is not), and gives a radius within a few percent of the
minimal enclosing sphere's. ``normalize=None`` uses the meshes as given (already normalized).

Sampling noise floor. The two meshes are sampled independently (seeds spawned from one
`numpy.random.SeedSequence(seed)`), as two independent scans would be, so even a perfect
prediction scores above zero: for N samples on a surface of area A, a point's squared distance
to the nearest of N uniform samples averages A / (pi N). For the unit sphere (A = 4 pi) and
N = 20 000 that is 4 / N = 2.0e-4, i.e. **CD = 2.0 (x 1e4) for a perfect reconstruction of a unit
sphere** (measured over 20 seeds: 2.004 +- 0.017), and Metro, a maximum over 2N such
squared distances, about 4 (ln 2N + 0.58) / N = 2.2 (x 1e3; measured 2.30 +- 0.31). Shapes of
smaller area have a lower floor. Keep this in mind when reading values near the paper's
(full method, 10 views: CD 2.00, Metro 5.98).

Normal-map metrics (paper Table 1): per-pixel angle between predicted and true normals, mean and
median over a mask, in degrees; and the render error, the mean squared difference between the
re-rendered and the input image over the masked pixels and channels.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from .errors import LookingGlassError

__all__ = [
    "DEFAULT_SAMPLES",
    "sample_surface",
    "normalization_transform",
    "shape_metrics",
    "normal_angle_errors",
    "normal_angles",
    "render_error",
    "evaluate_mesh_files",
]

DEFAULT_SAMPLES = 20000
MAX_SAMPLES = 10_000_000  # per surface; the nearest-neighbour searches grow with it (10 M: minutes, GiBs)
CD_UNIT = 1e4  # CD is reported x 1e4
METRO_UNIT = 1e3  # Metro is reported x 1e3


# ---------------------------------------------------------------------------------------------
# Shape metrics
# ---------------------------------------------------------------------------------------------
def sample_surface(mesh: trimesh.Trimesh, count: int = DEFAULT_SAMPLES,
                   seed: int | np.random.SeedSequence | np.random.Generator = 0
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform samples on `mesh` with the unit normals of the faces they lie on.

    mesh: a trimesh.Trimesh with at least one face of positive area. count: N. seed: anything
    `numpy.random.default_rng` accepts; the same seed gives the same samples.
    Returns points (N, 3) float64 and normals (N, 3) float64 (face normals, from the winding,
    not flipped).
    """
    if count < 1:
        raise ValueError(f"sample count must be positive, got {count}")
    _check_mesh(mesh, "mesh")
    points, face_index = trimesh.sample.sample_surface(mesh, int(count), seed=seed)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)[face_index]
    return np.asarray(points, dtype=np.float64), normals


def normalization_transform(gt: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """(centre (3,), scale) with p -> (p - centre) / scale mapping `gt` into the unit sphere.

    centre: the midpoint of the axis-aligned bounding box of the vertices that faces use;
    scale: the largest distance from the centre to such a vertex (so max |p| = 1 afterwards).
    """
    _check_mesh(gt, "gt")
    verts = np.asarray(gt.vertices, dtype=np.float64)[np.unique(np.asarray(gt.faces))]
    centre = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
    scale = float(np.sqrt(((verts - centre) ** 2).sum(axis=1).max()))
    if not np.isfinite(scale) or scale <= 0.0:
        raise ValueError("ground-truth mesh has zero extent; cannot normalize it")
    return centre, scale


def shape_metrics(pred: trimesh.Trimesh, gt: trimesh.Trimesh, samples: int = DEFAULT_SAMPLES,
                  seed: int = 0, normalize: str | None = "gt") -> dict[str, Any]:
    """CD (x 1e4), Metro (x 1e3), CDN-mean and CDN-med (degrees) between two meshes.

    pred, gt: trimesh.Trimesh (any position and scale when normalize="gt"). samples: points drawn
    on *each* mesh (the paper uses 20 000). seed: the GT and the prediction are sampled with two
    independent streams spawned from SeedSequence(seed); the same seed gives the same numbers.
    normalize: "gt" maps both meshes by the transform that puts the GT in the unit sphere (see
    `normalization_transform`); None takes them as already normalized.

    Returns {"cd", "metro", "cdn_mean", "cdn_med"} as Python floats and "samples" (int). See the
    module docstring for the definitions and the sampling noise floor (CD about 2.0 for a perfect
    unit sphere at 20 000 samples).
    """
    _check_mesh(pred, "pred")
    _check_mesh(gt, "gt")
    if normalize == "gt":
        centre, scale = normalization_transform(gt)
        gt = _transformed(gt, centre, scale)
        pred = _transformed(pred, centre, scale)
    elif normalize is not None:
        raise ValueError(f'normalize must be "gt" or None, got {normalize!r}')

    gt_seed, pred_seed = np.random.SeedSequence(seed).spawn(2)
    p_gt, n_gt = sample_surface(gt, samples, seed=gt_seed)
    p_pr, n_pr = sample_surface(pred, samples, seed=pred_seed)

    d_gt, i_gt = cKDTree(p_pr).query(p_gt, k=1, workers=-1)  # gt -> pred
    d_pr, i_pr = cKDTree(p_gt).query(p_pr, k=1, workers=-1)  # pred -> gt
    a_gt = _angles_deg(n_gt, n_pr[i_gt])
    a_pr = _angles_deg(n_pr, n_gt[i_pr])

    d2_gt, d2_pr = d_gt ** 2, d_pr ** 2
    return {
        "cd": float(0.5 * (d2_gt.mean() + d2_pr.mean()) * CD_UNIT),
        "metro": float(max(d2_gt.max(), d2_pr.max()) * METRO_UNIT),
        "cdn_mean": float(0.5 * (a_gt.mean() + a_pr.mean())),
        "cdn_med": float(0.5 * (np.median(a_gt) + np.median(a_pr))),
        "samples": int(samples),
    }


def _transformed(mesh: trimesh.Trimesh, centre: np.ndarray, scale: float) -> trimesh.Trimesh:
    """A copy of `mesh` with vertices (v - centre) / scale (same faces, no processing)."""
    verts = (np.asarray(mesh.vertices, dtype=np.float64) - centre) / scale
    return trimesh.Trimesh(vertices=verts, faces=np.asarray(mesh.faces), process=False)


def _check_mesh(mesh: Any, name: str) -> None:
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"{name} must be a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError(f"{name} mesh has no faces")
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        raise ValueError(f"{name} mesh has non-finite vertex coordinates")
    if not mesh.area > 0.0:
        raise ValueError(f"{name} mesh has zero surface area")


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between rows of a and b, (..., 3) each, via atan2(|a x b|, a . b).

    atan2 needs no clamping and stays accurate near 0 and 180 degrees, where arccos(dot) loses
    digits. Inputs need not be unit length (the angle does not depend on length); a zero vector
    gives 90 degrees against anything non-zero, 0 against zero.
    """
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = (a * b).sum(axis=-1)
    angles = np.degrees(np.arctan2(cross, dot))
    # atan2(0, 0) is 0: without this a missing normal (a mesh that misses the pixel) would score as exact
    zero_a, zero_b = ~np.any(a != 0, axis=-1), ~np.any(b != 0, axis=-1)
    return np.where(zero_a ^ zero_b, 90.0, angles)


# ---------------------------------------------------------------------------------------------
# Normal-map and image metrics
# ---------------------------------------------------------------------------------------------
def _to_numpy(x: Any) -> np.ndarray:
    """numpy float64 / bool view of a numpy array, a torch tensor (any device, grad or not)
    or a nested sequence."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # torch.Tensor without importing torch
        x = x.detach().cpu().numpy()
    x = np.asarray(x)
    return x if x.dtype == bool else x.astype(np.float64, copy=False)


def _channels_last(x: np.ndarray, channel_axis: int, name: str) -> np.ndarray:
    x = np.moveaxis(x, channel_axis, -1)
    if x.shape[-1] != 3:
        raise ValueError(f"{name} must have 3 channels on axis {channel_axis}, got shape "
                         f"{tuple(np.moveaxis(x, -1, channel_axis).shape)}")
    return x


def _mask_bool(mask: Any, shape: tuple[int, ...]) -> np.ndarray:
    """Boolean mask of `shape` (the image shape without channels). Accepts bool, or numbers with
    inside = value > 0.5; a trailing singleton channel is dropped; broadcasting is allowed."""
    m = _to_numpy(mask)
    if m.dtype != bool:
        m = m > 0.5
    if m.ndim == len(shape) + 1 and m.shape[-1] == 1:
        m = m[..., 0]
    try:
        m = np.broadcast_to(m, shape)
    except ValueError:
        raise ValueError(f"mask of shape {m.shape} does not match images of shape {shape}") from None
    if not m.any():
        raise ValueError("mask is empty: no pixels to evaluate the metric over")
    return m


def normal_angles(pred: Any, gt: Any) -> np.ndarray:
    """Angles in degrees between rows of (..., 3) normals (numpy or torch; any length, a zero
    vector scoring 90 degrees against a non-zero one): what every normal-error table pools."""
    return _angles_deg(_to_numpy(pred), _to_numpy(gt))


def normal_angle_errors(pred: Any, gt: Any, mask: Any, channel_axis: int = -1) -> dict[str, float]:
    """Mean and median angle (degrees) between predicted and true normals over a mask.

    pred, gt: (..., 3) normal maps (numpy or torch; channels on `channel_axis`, last by default),
    e.g. (H, W, 3) or (V, H, W, 3); they are normalized here, so length does not matter (a zero
    vector scores 90 degrees). mask: (...) bool, or numbers with inside = value > 0.5 (a trailing
    singleton channel is accepted). The angle is atan2(|a x b|, a . b), which equals
    arccos(clamp(a . b, -1, 1)) for unit vectors but is exact near 0 and 180 degrees.
    Returns {"mean": float, "median": float}. Raises ValueError for an empty mask.
    """
    p = _channels_last(_to_numpy(pred), channel_axis, "pred")
    g = _channels_last(_to_numpy(gt), channel_axis, "gt")
    if p.shape != g.shape:
        raise ValueError(f"pred and gt normal maps differ in shape: {p.shape} vs {g.shape}")
    m = _mask_bool(mask, p.shape[:-1])
    ang = _angles_deg(p[m], g[m])  # (M,)
    return {"mean": float(ang.mean()), "median": float(np.median(ang))}


def render_error(rendered: Any, image: Any, mask: Any, channel_axis: int = -1) -> float:
    """Mean squared difference between a re-rendered and the input image inside a mask.

    rendered, image: (..., 3) images (numpy or torch, same units; channels on `channel_axis`).
    mask: (...) bool or numbers (inside = value > 0.5). The mean runs over all masked pixels *and*
    the 3 channels: sum_{masked pixels, c} (rendered - image)^2 / (3 * number of masked pixels).
    Raises ValueError for an empty mask.
    """
    r = _channels_last(_to_numpy(rendered), channel_axis, "rendered")
    i = _channels_last(_to_numpy(image), channel_axis, "image")
    if r.shape != i.shape:
        raise ValueError(f"rendered and input images differ in shape: {r.shape} vs {i.shape}")
    m = _mask_bool(mask, r.shape[:-1])
    return float(((r[m] - i[m]) ** 2).mean())


# ---------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------
def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Load a mesh file as one trimesh.Trimesh (scenes are concatenated).

    Raises LookingGlassError naming the file when it is missing, cannot be read as a mesh, has
    no faces, has non-finite coordinates or zero surface area.
    """
    path = Path(path)
    if not path.exists():
        raise LookingGlassError("mesh file not found", path)
    if not path.is_file():
        raise LookingGlassError("not a file (expected a mesh such as .ply, .obj, .off, .stl)", path)
    try:
        # unprocessed first: trimesh's processing drops the faces of a NaN vertex without a word
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise LookingGlassError(f"cannot read mesh ({type(exc).__name__}: {exc})", path) from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise LookingGlassError(f"file holds no triangle mesh (got {type(mesh).__name__})", path)
    if len(mesh.faces) == 0:
        raise LookingGlassError("mesh is empty (no faces); is this a mesh file in a supported format?",
                                path)
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        raise LookingGlassError("mesh has non-finite vertex coordinates", path)
    mesh.process()  # what trimesh.load does by default: merge duplicate vertices
    if not mesh.area > 0.0:
        raise LookingGlassError("mesh has zero surface area (all faces degenerate)", path)
    return mesh


def evaluate_mesh_files(pred_path: str | os.PathLike, gt_path: str | os.PathLike,
                        samples: int = DEFAULT_SAMPLES, seed: int = 0) -> dict[str, Any]:
    """Shape metrics of a predicted mesh file against a ground-truth mesh file.

    Both are loaded with `load_mesh` (LookingGlassError naming the file on any problem) and
    compared by `shape_metrics(pred, gt, samples, seed, normalize="gt")`. Returns its dict:
    cd (x 1e4), metro (x 1e3), cdn_mean, cdn_med (degrees), samples.
    """
    pred = load_mesh(pred_path)
    gt = load_mesh(gt_path)
    return shape_metrics(pred, gt, samples=samples, seed=seed, normalize="gt")
