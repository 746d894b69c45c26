"""Feature mapping: per-view normal-net predictions onto points of the visual hull (pipeline step 4).

Paper Sec. 3.2 ("Feature mapping") and supplement Algorithm 1. Points p are sampled evenly on the
visual hull (VH). For each view v a point is projected into the image (S_v: bilinear fetch),
tested for visibility (V_v), and the view's first-hit normal N1 (camera frame -> world, T_v), its
rendering error I_er, its total-internal-reflection mask M_tr and the view cosine C_v are fetched.
The views are then merged per point by one of three strategies:

- "AV": mean over the visible views (N1 re-normalized; I_er, M_tr and C averaged).
- "NE": the visible view with the largest C_v (nearest, i.e. most frontal, view).
- "RE": Algorithm 1 (rendering-error view selection), vectorized; see `select_rendering_error`.

Frames. `points`, `hull_normals`, the hull mesh and the cameras share one world frame (normally
the normalized frame of lookingglass.hull). N1 maps are in each view's camera frame (x = right,
y = up, z = towards the camera, DESIGN.md "Conventions"); every normal returned here is world.

Pixel convention (lookingglass.physics.camera): pixel (col, row) covers [col, col+1) x
[row, row+1), centre (col + 0.5, row + 0.5). With `align_corners=False`, grid_sample's -1 / +1
are the outer edges of the first / last pixel, so grid = 2 xy / (W, H) - 1 samples exactly there.

Choices the paper leaves open:
- C_v is the cosine between the hull normal and the unit direction from the point to the camera
  centre (> 0 when the hull faces the camera).
- Visibility V_v = in front of the camera, inside the image, inside the object mask (nearest
  pixel) and not occluded by the hull: the ray from the camera centre to the point (Embree, via
  lookingglass.render.raycast.RayCaster) must not hit the hull more than `occlusion_tolerance`
  x (hull bounding-box diagonal) before the point.
- Bilinear fetches are mask-weighted (normalized convolution): values of the up to four
  neighbouring pixel centres are averaged with the bilinear weights times the mask, so background
  pixels (whose normals and errors are meaningless) never leak into a point's feature. A visible
  point's own pixel is in the mask and carries bilinear weight >= 1/4, so the sum of weights is
  never zero there.
- M_tr is fetched the same way and binarized at 0.5: Algorithm 1 tests "S_v(p, M_tr) = 1", which
  a bilinear fetch of a binary map only meets exactly away from TIR borders.
- Points no view sees keep the hull normal and Algorithm 1's initial values (I_er = 2, M_tr = 1,
  C = 0) under every strategy, and are flagged `seen = False`.

Ours, not the paper's: silhouette-cone counts (columns "silhouette"). Every hull point lies on
the cone of at least one view's silhouette; where it also lies near the cones of other views, the
hull is tight there (measured on our test split: hull points that leave the silhouette in >= 2
views when pushed out by 0.02 lie about half as far from the true surface as those that leave it
in one; docs/history.md, "What limits the shape"). Per offset eps of SILHOUETTE_OFFSETS the column
counts the views in which p + eps * (hull normal) falls outside the object mask, with the mask read
bilinearly (so the count moves smoothly with the point) and a projection behind the camera or off
the image counting as outside. Nets trained on the paper's 12 columns read only those (PNet takes
the first `in_features` columns).
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from torch import Tensor

from ..config import STRATEGIES  # noqa: F401 (re-exported; its home is lookingglass.config)
from ..physics.camera import Cameras
from ..render.raycast import RayCaster
from .config import FEATURE_COLUMNS, NUM_FEATURES, PAPER_FEATURES, SILHOUETTE_OFFSETS  # noqa: F401 (re-exported)

__all__ = [
    "STRATEGIES",
    "FEATURE_COLUMNS",
    "NUM_FEATURES",
    "PAPER_FEATURES",
    "UNSEEN_ERROR",
    "UNSEEN_TIR",
    "UNSEEN_COS",
    "SILHOUETTE_OFFSETS",
    "sample_hull_points",
    "map_features",
    "silhouette_counts",
    "select_nearest",
    "select_rendering_error",
]


# Algorithm 1's initial values, kept by points that no (usable) view sees.
UNSEEN_ERROR = 2.0
UNSEEN_TIR = 1.0
UNSEEN_COS = 0.0


# ---------------------------------------------------------------------------------------------
# Sampling the hull
# ---------------------------------------------------------------------------------------------
def sample_hull_points(mesh: trimesh.Trimesh, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Exactly `count` roughly evenly spaced points on `mesh` with the normals of their faces.

    Poisson-disk style (trimesh.sample.sample_surface_even: 3x oversampling, then rejection of
    pairs closer than r = sqrt(area / (3 count))). When rejection leaves fewer than `count`, r is
    shrunk (x0.8, up to 4 times) and, as a last resort, the rest is padded with area-uniform
    samples. Deterministic for a given seed.

    mesh: closed, outward-oriented triangle mesh (world frame). count: N >= 1. seed: int.
    Returns points (N, 3) float32 and unit outward face normals (N, 3) float32.
    """
    count = int(count)
    if count < 1:
        raise ValueError(f"point count must be positive, got {count}")
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise ValueError("cannot sample points on a mesh with no surface area")
    even_seed, pad_seed = np.random.SeedSequence(int(seed)).spawn(2)
    radius = float(np.sqrt(mesh.area / (3 * count)))
    logger = logging.getLogger("trimesh")
    level = logger.level
    logger.setLevel(logging.ERROR)  # sample_surface_even warns on every short draw; we handle it
    try:
        for _ in range(5):
            points, faces = trimesh.sample.sample_surface_even(
                mesh, count, radius=radius, seed=np.random.default_rng(even_seed))
            if len(points) >= count:
                break
            radius *= 0.8
    finally:
        logger.setLevel(level)
    points, faces = np.asarray(points)[:count], np.asarray(faces)[:count]
    if len(points) < count:
        extra, extra_faces = trimesh.sample.sample_surface(mesh, count - len(points), seed=pad_seed)
        points = np.concatenate([points, extra])
        faces = np.concatenate([faces, extra_faces])
    normals = np.asarray(mesh.face_normals)[faces]
    return points.astype(np.float32), normals.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# View selection (pure functions over per-view samples)
# ---------------------------------------------------------------------------------------------
def select_nearest(visible: Tensor, cos: Tensor) -> Tensor:
    """NE strategy: per point, the visible view with the largest view cosine (first one on ties).

    visible: (V, N) bool. cos: (V, N) float. Returns (N,) int64 view index, -1 where no view sees
    the point.
    """
    key = cos.masked_fill(~visible, float("-inf"))
    return torch.where(visible.any(0), key.argmax(0), torch.full_like(key[0], -1, dtype=torch.long))


def select_rendering_error(visible: Tensor, error: Tensor, tir: Tensor, cos: Tensor) -> Tensor:
    """RE strategy: supplement Algorithm 1, vectorized over points and views.

    Algorithm 1 walks the views v = 1..V in order, starting each point at (M_tr = 1, I_er = 2,
    C = 0, no view), and, for a view that sees the point, takes it when
      - the view has TIR there:     the current choice has TIR too and C_v > current C; or
      - the view has no TIR there:  the current choice has TIR (always true until the first
                                    TIR-free view), or I_er,v < current I_er.
    Once a TIR-free view is taken the state has M_tr = 0 and no TIR view can replace it. So the
    walk ends on
      1. the TIR-free visible view of lowest error, if there is one (first such view on ties:
         later views replace only on a strictly lower error), else
      2. the visible TIR view of largest C_v, among those with C_v > 0 (first on ties), else
      3. nothing: the point keeps the hull normal and the initial values.
    Note 1. takes the first TIR-free view even when its error exceeds the initial 2, as the walk
    does. Non-finite errors of TIR-free views rank last (a NaN never wins a "<" comparison).

    visible, tir: (V, N) bool. error, cos: (V, N) float.
    Returns (N,) int64 view index, -1 in case 3.
    """
    clear = visible & ~tir
    big = torch.finfo(error.dtype).max
    err_key = torch.where(clear, torch.nan_to_num(error, nan=big, posinf=big, neginf=-big),
                          torch.full_like(error, float("inf")))
    by_error = err_key.argmin(0)  # torch returns the first index among equal minima
    tir_ok = visible & tir & (cos > 0)
    by_cos = cos.masked_fill(~tir_ok, float("-inf")).argmax(0)
    none = torch.full_like(by_error, -1)
    return torch.where(clear.any(0), by_error, torch.where(tir_ok.any(0), by_cos, none))


# ---------------------------------------------------------------------------------------------
# Mapping
# ---------------------------------------------------------------------------------------------
def _as_cpu64(x) -> Tensor:
    return torch.as_tensor(np.asarray(x) if not isinstance(x, Tensor) else x).detach().to(
        device="cpu", dtype=torch.float64)


def _as_cpu_bool(x) -> Tensor:
    t = torch.as_tensor(np.asarray(x) if not isinstance(x, Tensor) else x).detach().cpu()
    return t if t.dtype == torch.bool else t > 0.5


def _fetch(maps: Tensor, xy: Tensor, width: int, height: int) -> Tensor:
    """Bilinear fetch with the pixel-centre convention.

    maps: (V, C, H, W). xy: (V, N, 2) continuous image coordinates (non-finite allowed: zeros).
    Returns (V, N, C); outside the image the taps read zero (padding_mode="zeros").
    """
    scale = xy.new_tensor([2.0 / width, 2.0 / height])
    grid = torch.nan_to_num(xy * scale - 1, nan=-3.0, posinf=3.0, neginf=-3.0).clamp(-3, 3)
    out = F.grid_sample(maps, grid[:, None], mode="bilinear", padding_mode="zeros", align_corners=False)
    return out[:, :, 0].permute(0, 2, 1)


def _unoccluded(caster: RayCaster, origins: Tensor, points: Tensor, candidates: Tensor,
                tolerance: float) -> Tensor:
    """(V, N) bool: the first hull hit on the ray camera -> point is not closer than
    |point - camera| - tolerance. Only `candidates` (V, N) are cast (one Embree batch);
    everything else is False. A miss counts as unoccluded (nothing lies in front of the point).
    origins: (V, 3); points: (N, 3); world frame."""
    out = torch.zeros_like(candidates)
    v, n = candidates.nonzero(as_tuple=True)
    if len(v) == 0:
        return out
    o = origins[v]
    d = points[n] - o
    dist = d.norm(dim=-1)
    d = d / dist.clamp_min(1e-12)[:, None]
    t, _, _, _ = caster.intersect_raw(o.numpy(), d.numpy())
    out[v, n] = torch.from_numpy(t.astype(np.float64)) >= dist - tolerance
    return out


def silhouette_counts(points, hull_normals, cameras: Cameras, mask,
                      offsets: tuple[float, ...] = SILHOUETTE_OFFSETS) -> Tensor:
    """Per point and offset eps, the number of views whose object mask does not hold
    p + eps * n (see the module docstring): sum over views of 1 - (bilinear mask value there),
    1 for projections behind the camera or off the image.

    points, hull_normals: (N, 3) world, the normals unit and outward. cameras: V views at the
    mask's W x H. mask: (V, H, W) bool or numbers > 0.5. offsets: K world distances.
    Returns (N, K) float64 on the CPU, each in [0, V].
    """
    p = _as_cpu64(points).reshape(-1, 3)
    n = F.normalize(_as_cpu64(hull_normals).reshape(-1, 3), dim=-1)
    cams = cameras.to(device="cpu", dtype=torch.float64)
    m = _as_cpu_bool(mask).to(torch.float64)[:, None]  # (V, 1, H, W)
    columns = []
    for eps in offsets:
        xy, depth = cams.project(p + float(eps) * n)
        held = _fetch(m, xy, cams.width, cams.height)[..., 0] * (depth > 0)  # (V, N); off-image taps read 0
        columns.append((1.0 - held).sum(0))
    return torch.stack(columns, dim=1) if columns else p.new_zeros((p.shape[0], 0))


class _ViewSamples(NamedTuple):
    """What each view says about each point: (V, N, ...) float64 / bool, world frame."""

    visible: Tensor  # (V, N) bool, V_v(p)
    normal: Tensor   # (V, N, 3) N1 (meaningless where not visible)
    error: Tensor    # (V, N)
    tir: Tensor      # (V, N) bool
    cos: Tensor      # (V, N) view cosine C_v


class _Merged(NamedTuple):
    """The per-point result of merging the views: (N, ...) float64, world frame."""

    normal: Tensor  # (N, 3)
    error: Tensor   # (N,)
    tir: Tensor     # (N,)
    cos: Tensor     # (N,)
    chosen: Tensor  # (N,) int64 view index, -1 for none (and for AV)


def _checked_inputs(points, hull_normals, cameras: Cameras, n1_cam, error, tir, mask):
    """The inputs of `map_features` as CPU tensors, checked against each other.

    Returns p (N, 3) and unit hull normals hn (N, 3) float64, the cameras in float64 on the CPU,
    n1 (V, H, W, 3) and error (V, H, W) float64, tir and mask (V, H, W) bool. Raises ValueError
    on a shape mismatch.
    """
    p = _as_cpu64(points).reshape(-1, 3)
    hn = F.normalize(_as_cpu64(hull_normals).reshape(-1, 3), dim=-1)
    if hn.shape != p.shape:
        raise ValueError(f"hull_normals {tuple(hn.shape)} do not match points {tuple(p.shape)}")
    cams = cameras.to(device="cpu", dtype=torch.float64)
    V, H, W = cams.num_views, cams.height, cams.width
    n1 = _as_cpu64(n1_cam)
    err = _as_cpu64(error)
    tir_map = _as_cpu_bool(tir)
    obj = _as_cpu_bool(mask)
    for name, arr, shape in (("n1_cam", n1, (V, H, W, 3)), ("error", err, (V, H, W)),
                             ("tir", tir_map, (V, H, W)), ("mask", obj, (V, H, W))):
        if tuple(arr.shape) != shape:
            raise ValueError(f"{name} has shape {tuple(arr.shape)}, expected {shape} "
                             f"(V views at the cameras' {W}x{H})")
    return p, hn, cams, n1, err, tir_map, obj


def _visibility(p: Tensor, cams: Cameras, obj: Tensor, hull_mesh: trimesh.Trimesh | RayCaster,
                occlusion_tolerance: float) -> tuple[Tensor, Tensor]:
    """V_v(p): in front of the camera, inside the image, inside the mask (nearest pixel) and not
    occluded by the hull. p: (N, 3); obj: (V, H, W) bool. Returns the projections xy (V, N, 2) and
    visible (V, N) bool."""
    V, H, W = obj.shape
    xy, depth = cams.project(p)  # (V, N, 2), (V, N)
    x, y = xy[..., 0], xy[..., 1]
    inside = (depth > 0) & (x >= 0) & (x < W) & (y >= 0) & (y < H)  # NaN compares False
    col = torch.nan_to_num(x, nan=0.0).floor().clamp(0, W - 1).long()
    row = torch.nan_to_num(y, nan=0.0).floor().clamp(0, H - 1).long()
    in_mask = obj[torch.arange(V)[:, None], row, col] & inside
    # the occlusion test casts rays only for the points that passed the cheap tests
    if isinstance(hull_mesh, RayCaster):
        caster, extents = hull_mesh, hull_mesh.mesh.extents
    else:
        caster, extents = RayCaster(hull_mesh), hull_mesh.extents
    tolerance = float(occlusion_tolerance) * float(np.linalg.norm(extents))
    return xy, _unoccluded(caster, cams.origin, p, in_mask, tolerance)


def _view_samples(p: Tensor, hn: Tensor, cams: Cameras, xy: Tensor, visible: Tensor, n1: Tensor,
                  err: Tensor, tir_map: Tensor, obj: Tensor) -> _ViewSamples:
    """Per view and point: N1 (world), error and TIR fetched mask-weighted bilinear at the
    projections xy (V, N, 2), and the view cosine; see `_checked_inputs` for the maps' shapes."""
    W, H = cams.width, cams.height
    m = obj.to(torch.float64)
    n1_world = cams.camera_to_world(n1)  # (V, H, W, 3)
    # one fetch for all maps: the mask-weighted values and, last, the weights (the mask) themselves
    stack = torch.cat([n1_world * m[..., None], (torch.nan_to_num(err) * m)[..., None],
                       (tir_map.to(torch.float64) * m)[..., None], m[..., None]], dim=-1)
    taps = _fetch(stack.permute(0, 3, 1, 2).contiguous(), xy, W, H)  # (V, N, 6)
    weight = taps[..., 5].clamp_min(1e-12)
    to_cam = F.normalize(cams.origin[:, None, :] - p[None], dim=-1)
    return _ViewSamples(
        visible=visible,
        normal=F.normalize(taps[..., 0:3], dim=-1),  # the weight's scale drops out
        error=taps[..., 3] / weight,
        tir=taps[..., 4] / weight > 0.5,
        cos=(to_cam * hn[None]).sum(-1))


def _merge_average(views: _ViewSamples, hn: Tensor) -> _Merged:
    """AV: the mean over the visible views (N1 re-normalized); unseen points keep the hull normal
    and the UNSEEN_* values."""
    count = views.visible.sum(0)
    seen = count > 0
    w = views.visible.to(torch.float64)
    denom = count.clamp_min(1).to(torch.float64)
    total = (w[..., None] * views.normal).sum(0)
    ok = seen & (total.norm(dim=-1) > 1e-9)  # opposite normals could cancel exactly
    return _Merged(
        normal=torch.where(ok[:, None], F.normalize(total, dim=-1), hn),
        error=torch.where(seen, (w * views.error).sum(0) / denom, torch.full_like(denom, UNSEEN_ERROR)),
        tir=torch.where(seen, (w * views.tir).sum(0) / denom, torch.full_like(denom, UNSEEN_TIR)),
        cos=torch.where(seen, (w * views.cos).sum(0) / denom, torch.full_like(denom, UNSEEN_COS)),
        chosen=torch.full((len(hn),), -1, dtype=torch.long))


def _merge_chosen(views: _ViewSamples, hn: Tensor, chosen: Tensor) -> _Merged:
    """NE / RE: the values of the chosen view (N,) per point; points with none (-1) keep the hull
    normal and the UNSEEN_* values."""
    N = len(hn)
    has = chosen >= 0
    idx = chosen.clamp_min(0)
    pick = lambda a: a[idx, torch.arange(N)]  # noqa: E731 - (V, N, ...) -> (N, ...)
    unseen = lambda value: torch.full((N,), value, dtype=torch.float64)  # noqa: E731
    return _Merged(
        normal=torch.where(has[:, None], pick(views.normal), hn),
        error=torch.where(has, pick(views.error), unseen(UNSEEN_ERROR)),
        tir=torch.where(has, pick(views.tir).to(torch.float64), unseen(UNSEEN_TIR)),
        cos=torch.where(has, pick(views.cos), unseen(UNSEEN_COS)),
        chosen=chosen)


def map_features(points, hull_normals, hull_mesh: trimesh.Trimesh | RayCaster, cameras: Cameras,
                 n1_cam, error, tir, mask, strategy: str = "RE",
                 occlusion_tolerance: float = 0.01) -> dict[str, Tensor]:
    """Map per-view N1 / rendering error / TIR predictions onto hull points (paper Sec. 3.2).

    points: (N, 3) world points on the hull. hull_normals: (N, 3) their unit outward hull normals,
    world. hull_mesh: the hull (world frame; or a RayCaster built on it) for the occlusion test.
    cameras: V views at the resolution W x H of the maps. n1_cam: (V, H, W, 3) predicted first-hit
    normals, camera frame (x = right, y = up, z = towards the camera). error: (V, H, W) per-pixel
    rendering error. tir: (V, H, W) total-internal-reflection mask (bool, or numbers > 0.5).
    mask: (V, H, W) object mask (bool, or numbers > 0.5). Arrays may be numpy or torch.
    strategy: "AV", "NE" or "RE" (see the module docstring). occlusion_tolerance: the depth-test
    slack as a fraction of the hull's bounding-box diagonal.

    Returns a dict of tensors on the device of `points` (CPU for numpy); floats are float32:
      normal (N, 3)        world unit normal: the merged / chosen N1, the hull normal if unseen
      error (N,)           rendering error of the chosen view (AV: mean), UNSEEN_ERROR if unseen
      tir (N,)             TIR of the chosen view, 0/1 (AV: fraction of visible views), 1 if unseen
      cos (N,)             view cosine of the chosen view (AV: mean), 0 if unseen
      visible_count (N,)   int64, number of views that see the point
      chosen_view (N,)     int64, the view taken (NE, RE); -1 for AV, for unseen points, and for
                           RE points whose only visible views have TIR and C_v <= 0
      seen (N,)            bool, visible_count > 0
      features (N, NUM_FEATURES) [point, hull normal, normal, error, tir, cos, silhouette counts];
                           see FEATURE_COLUMNS
      view_visible (V, N)  bool, V_v(p)
      view_normal (V, N, 3) world N1 fetched from each view (meaningless where not visible)
      view_error (V, N), view_tir (V, N) bool, view_cos (V, N): the per-view fetches
    """
    strategy = str(strategy).upper()
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown feature-mapping strategy {strategy!r}; use one of {STRATEGIES}")
    device = points.device if isinstance(points, Tensor) else torch.device("cpu")
    p, hn, cams, n1, err, tir_map, obj = _checked_inputs(points, hull_normals, cameras, n1_cam, error, tir, mask)
    xy, visible = _visibility(p, cams, obj, hull_mesh, occlusion_tolerance)
    views = _view_samples(p, hn, cams, xy, visible, n1, err, tir_map, obj)
    if strategy == "AV":
        merged = _merge_average(views, hn)
    elif strategy == "NE":
        merged = _merge_chosen(views, hn, select_nearest(visible, views.cos))
    else:
        merged = _merge_chosen(views, hn, select_rendering_error(visible, views.error, views.tir, views.cos))

    count = visible.sum(0)
    cones = silhouette_counts(p, hn, cams, obj)
    features = torch.cat([p, hn, merged.normal, merged.error[:, None], merged.tir[:, None], merged.cos[:, None],
                          cones], dim=1)
    f32 = lambda a: a.to(device=device, dtype=torch.float32)  # noqa: E731
    return {
        "normal": f32(merged.normal),
        "error": f32(merged.error),
        "tir": f32(merged.tir),
        "cos": f32(merged.cos),
        "visible_count": count.to(device),
        "chosen_view": merged.chosen.to(device),
        "seen": (count > 0).to(device),
        "features": f32(features),
        "view_visible": visible.to(device),
        "view_normal": f32(views.normal),
        "view_error": f32(views.error),
        "view_tir": views.tir.to(device),
        "view_cos": f32(views.cos),
    }
