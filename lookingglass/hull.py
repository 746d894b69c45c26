"""Visual hull: carve the masks into a smooth, watertight mesh (pipeline step 1, DESIGN.md).

Frames. Everything a caller passes in or gets back is in the *capture frame* (the frame of the
cameras, with the object at any position and scale). The hull also fixes the *normalized frame*
that every later stage works in: p_n = (p - center) / scale maps the hull into the unit sphere
(max |p_n| = 1, DESIGN.md "Shapes are normalized to the unit sphere").

Method.
1. Per view, a signed distance (pixels) to the silhouette boundary: positive inside the mask,
   negative outside, zero on the pixel edges between object and background (DESIGN.md: carving a
   continuous field instead of a binary one gives sub-voxel surfaces). Out of the image counts as
   outside, so an object cut off by the border still gives a bounded hull (with a warning).
2. The carving box is found from the data: a centre triangulated from the rays through the mask
   centroids, a generous cube around it sized from the silhouettes' angular extents, then coarse
   carving -> box of the occupied voxels -> repeat until the box stops shrinking.
3. The fine carve at `resolution` voxels along the box's longest side: each voxel centre is
   projected into every view, the pixel field is sampled bilinearly and converted to world units
   (pixel footprint at the voxel's depth), and views are combined by a minimum (inside all cones).
4. Marching cubes at level 0, largest component, LS3 Loop subdivision (MeshLab, as the paper's
   release does) for smooth normals, then a watertightness / orientation check.
   A visual hull often has pieces apart from the object's: regions every mask allows but hidden
   behind the object in every view, which no mask pixel needs; they are dropped quietly. Where
   instead the dropped pieces cover mask pixels the largest one leaves uncovered, a part of the
   object thinner than a voxel came apart (a rod or a handle: the demo's shape at 128 voxels), and
   the box is carved again at twice the resolution (up to `max_resolution`).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
import trimesh
from scipy import ndimage

from .config import HullConfig  # noqa: F401 (re-exported; its home is lookingglass.config)
from .errors import LookingGlassError
from .meshes import largest_component, orient_outward, require_closed_and_oriented, taubin_smooth
from .meshes import subdivide_ls3_loop as _ls3_loop  # the name hull's tests import
from .threads import torch_threads
from .physics.camera import Cameras

ProgressFn = Callable[[str, float], None]


@dataclass
class VisualHull:
    """A carved visual hull.

    mesh: watertight, outward-oriented triangle mesh, capture frame.
    center: (3,) float64 and scale: float, capture frame: (p - center) / scale maps the hull into the
        unit sphere with max |p| = 1 (the normalization every later stage uses).
    bbox: (2, 3) float64, the carving box [min, max] in the capture frame.
    voxel_size: edge of one fine voxel, capture-frame units.
    grid_shape: (nx, ny, nz) voxel samples of the fine carve.
    view_coverage: (V,) fraction of each view's mask that the hull's projection covers (~1 when the
        masks and cameras agree).
    timings: seconds per sub-step ("masks", "box", "carve", "coverage", "marching_cubes",
        "components", "recarve" where the hull came apart and was carved again finer,
        "subdivision", "finish") and "total".
    """

    mesh: trimesh.Trimesh
    center: np.ndarray
    scale: float
    bbox: np.ndarray
    voxel_size: float
    grid_shape: tuple[int, int, int]
    view_coverage: np.ndarray
    timings: dict[str, float] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh, center=None, scale: float | None = None,
                  voxel_size: float = float("nan"), view_coverage=()) -> "VisualHull":
        """A hull carved earlier (e.g. stored by `generate`), with its normalization when known
        (else computed as `carve_visual_hull` does: the bounding box's centre, the farthest vertex)."""
        vertices = np.asarray(mesh.vertices, np.float64)
        if center is None or scale is None:
            center, scale = hull_normalization(vertices)
        return cls(mesh=mesh, center=np.asarray(center, np.float64), scale=float(scale),
                   bbox=np.stack([vertices.min(axis=0), vertices.max(axis=0)]), voxel_size=float(voxel_size),
                   grid_shape=(0, 0, 0), view_coverage=np.asarray(view_coverage, np.float64))

    def mesh_normalized(self) -> trimesh.Trimesh:
        """A copy of the hull in the normalized frame (inside the unit sphere, max |p| = 1)."""
        m = self.mesh.copy()
        m.vertices = (np.asarray(self.mesh.vertices) - self.center) / self.scale
        return m

    def normalize_points(self, points: np.ndarray) -> np.ndarray:
        """Capture frame -> normalized frame. points: (..., 3)."""
        return (np.asarray(points, dtype=np.float64) - self.center) / self.scale

    def denormalize_points(self, points: np.ndarray) -> np.ndarray:
        """Normalized frame -> capture frame. points: (..., 3)."""
        return np.asarray(points, dtype=np.float64) * self.scale + self.center

    def cameras_normalized(self, cameras: Cameras) -> Cameras:
        """The capture's cameras expressed in the normalized frame."""
        return cameras.transformed(torch.as_tensor(self.center), self.scale)


def hull_normalization(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """(center (3,), scale) with (p - center) / scale inside the unit sphere, max |p| = 1: the
    bounding box's centre and the distance to the farthest vertex. vertices: (N, 3)."""
    center = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    return center, float(np.linalg.norm(vertices - center, axis=1).max())


# ---------------------------------------------------------------------------------------------
# Per-view silhouette fields
# ---------------------------------------------------------------------------------------------

# The field images get this many pixels of background around the image, so that sampling beyond
# the image border (grid_sample padding_mode="border" replicates the edge) reads "outside".
_PAD = 2


def _as_bool_masks(masks) -> np.ndarray:
    if isinstance(masks, torch.Tensor):
        masks = masks.detach().cpu().numpy()
    masks = np.asarray(masks)
    if masks.ndim != 3:
        raise LookingGlassError(f"masks must have shape (views, height, width), got {masks.shape}")
    return masks.astype(bool, copy=False)


def silhouette_fields(masks: np.ndarray, blur_px: float = 0.0) -> np.ndarray:
    """Signed distance (pixels) of every pixel centre to its view's silhouette boundary.

    masks: (V, H, W) bool. Returns (V, H + 2*_PAD, W + 2*_PAD) float32, the image padded with
    background: positive inside the mask, negative outside. The boundary is put on the pixel edges
    (distances shifted by half a pixel), so bilinear sampling crosses zero exactly between an object
    pixel centre (+0.5) and a background pixel centre (-0.5). blur_px > 0: the field blurred by a
    Gaussian of that sigma (pixels), which irons out the mask's pixel staircase: on the true boundary
    of discs 10-30 px across the field reads 0.22 px off in rms unblurred, 0.15 at 0.7 px
    (tests/test_hull.py).
    """
    import cv2

    V, H, W = masks.shape
    out = np.empty((V, H + 2 * _PAD, W + 2 * _PAD), np.float32)
    for v in range(V):  # per image; ~5 ms each at 480x360
        m = np.zeros((H + 2 * _PAD, W + 2 * _PAD), bool)
        m[_PAD:_PAD + H, _PAD:_PAD + W] = masks[v]
        # The exact Euclidean distance from each pixel centre to the nearest centre of the other kind.
        # scipy's, not OpenCV's DIST_MASK_PRECISE: that one differs by ~1e-5 px from call to call on the
        # same mask, and the refine stage's iterations grew that into different meshes run to run.
        d_in = ndimage.distance_transform_edt(m)
        d_out = ndimage.distance_transform_edt(~m)
        out[v] = np.where(m, d_in - 0.5, 0.5 - d_out)
        if blur_px > 0:
            out[v] = cv2.GaussianBlur(out[v], (0, 0), blur_px)
    return out


def sample_silhouette_fields(fields, xy):
    """Bilinear samples (V, N) of `silhouette_fields` output (a torch tensor (V, H + 2P, W + 2P)) at
    pixel coordinates xy (V, N, 2) of the unpadded image (x right, y down, pixel centres at +0.5);
    differentiable in xy. Beyond the padding the border replicates: outside."""
    V, Hp, Wp = fields.shape
    gx = (xy[..., 0] + _PAD) / Wp * 2 - 1  # align_corners=False: pixel k's centre is at k + 0.5
    gy = (xy[..., 1] + _PAD) / Hp * 2 - 1
    grid = torch.stack([gx, gy], dim=-1).unsqueeze(1)  # (V, 1, N, 2)
    return torch.nn.functional.grid_sample(fields.unsqueeze(1), grid, mode="bilinear", padding_mode="border",
                                           align_corners=False)[:, 0, 0]


# ---------------------------------------------------------------------------------------------
# Carving
# ---------------------------------------------------------------------------------------------

class _Carver:
    """Evaluates the combined silhouette field on regular grids.

    The field at a capture-frame point p is min over views of s_v(p) = (bilinear pixel field at
    p's projection) x (p's depth) x (pixel pitch at unit depth): the view's signed distance to the
    silhouette in world units (approximately the distance to that view's silhouette cone), so the
    min over views is comparable across views at different distances and marching cubes
    interpolates it linearly in space. Behind a camera counts as far outside.
    """

    def __init__(self, fields: np.ndarray, cameras: Cameras, device: str, chunk_voxels: int):
        self.device = torch.device(device)
        self.V = cameras.num_views
        W, H = cameras.width, cameras.height
        self.cams64 = cameras.to(dtype=torch.float64, device="cpu")
        tx = self.cams64.tan_half_fov_x
        ty = tx * (H / W)
        # Pixel pitch at unit depth (square pixels), folded into the fields so that field x depth
        # is in world units.
        pitch = self.cams64.pixel_pitch.to(torch.float32)
        f = torch.from_numpy(fields) * pitch[:, None, None]
        self.fields = f.to(self.device).unsqueeze(1).contiguous()  # (V, 1, Hp, Wp)
        self.chunk = int(chunk_voxels)
        # Rows of the projection (before the divide by depth) giving grid_sample coordinates of the
        # padded image directly: g_x = x_ndc * W / (W + 2 pad), g_y = -y_ndc * H / (H + 2 pad)
        # (grid y runs down the image), and the depth along forward.
        sx = (1.0 / tx) * (W / (W + 2 * _PAD))
        sy = -(1.0 / ty) * (H / (H + 2 * _PAD))
        B = self.cams64.basis  # (V, 3, 3) rows right, up, forward
        self.rows = torch.stack([B[:, 0] * sx[:, None], B[:, 1] * sy[:, None], B[:, 2]], dim=1)  # (V,3,3)

    def carve(self, lo: np.ndarray, h: float, shape: tuple[int, int, int],
              far: float) -> torch.Tensor:
        """Field at the grid points lo + (i, j, k) * h, i < shape[0] etc. (capture frame).

        Returns (nx, ny, nz) float32 on the device, world units, positive inside the hull.
        `far` is the value given to points behind a camera (large negative magnitude).
        """
        nx, ny, nz = shape
        dev = self.device
        # Projection of grid index (i, j, k, 1): rows (V, 3, 3) times h plus a translation computed
        # in float64 from lo - origin, so float32 keeps full precision at any capture position.
        lo64 = torch.as_tensor(lo, dtype=torch.float64)
        trans = torch.einsum("vjk,vk->vj", self.rows, lo64 - self.cams64.origin)  # (V, 3)
        P = torch.cat([self.rows * h, trans[:, :, None]], dim=2)  # (V, 3, 4), float64
        P_t = P.transpose(1, 2).to(torch.float32).to(dev).contiguous()  # (V, 4, 3)
        jj, kk = torch.meshgrid(torch.arange(ny, dtype=torch.float32, device=dev),
                                torch.arange(nz, dtype=torch.float32, device=dev), indexing="ij")
        plane = torch.stack([jj.flatten(), kk.flatten()], dim=1)  # (ny*nz, 2)
        out = torch.empty((nx, ny * nz), dtype=torch.float32, device=dev)
        slab = max(1, self.chunk // (ny * nz))  # x-slabs per chunk
        for i0 in range(0, nx, slab):
            i1 = min(nx, i0 + slab)
            m = (i1 - i0) * ny * nz
            X = torch.empty((i1 - i0, ny * nz, 4), dtype=torch.float32, device=dev)  # (i, j, k, 1)
            X[..., 0] = torch.arange(i0, i1, dtype=torch.float32, device=dev)[:, None]
            X[..., 1:3] = plane
            X[..., 3] = 1.0
            X = X.view(m, 4)
            # Depth is affine in the indices, so its minimum over the chunk is at a corner: when all
            # corners are in front of every camera (the usual case) the per-voxel test is skipped.
            corners = torch.tensor([[i, j, k, 1.0] for i in (i0, i1 - 1) for j in (0, ny - 1)
                                    for k in (0, nz - 1)], dtype=torch.float64)
            min_depth = torch.einsum("ck,vk->vc", corners, P[:, 2]).min(dim=1).values  # (V,)
            acc = out[i0:i1].view(m)
            grid = torch.empty((1, 1, m, 2), dtype=torch.float32, device=dev)
            for v in range(self.V):  # loop over views only; each view is a few vectorized passes
                proj = X @ P_t[v]  # (m, 3): scaled x, scaled y, depth
                depth = proj[:, 2]
                torch.div(proj[:, :2], depth[:, None], out=grid.view(m, 2))
                s = torch.nn.functional.grid_sample(
                    self.fields[v:v + 1], grid, mode="bilinear", padding_mode="border",
                    align_corners=False).view(m)
                s.mul_(depth)
                if min_depth[v] <= 0:
                    s = torch.where(depth > 0, s, torch.full_like(s, far))
                if v == 0:
                    acc.copy_(s)
                else:
                    torch.minimum(acc, s, out=acc)
        return out.view(nx, ny, nz)


def _triangulate_center(masks: np.ndarray, cameras: Cameras) -> np.ndarray:
    """Least-squares point closest to the rays through each mask's centroid. Returns (3,) float64.

    Minimizes sum_v |(I - d_v d_v^T)(p - o_v)|^2, i.e. solves sum_v P_v p = sum_v P_v o_v.
    """
    V, H, W = masks.shape
    rows = np.arange(H, dtype=np.float64) + 0.5
    cols = np.arange(W, dtype=np.float64) + 0.5
    area = masks.sum(axis=(1, 2)).astype(np.float64)
    cy = (masks.sum(axis=2) * rows).sum(axis=1) / area
    cx = (masks.sum(axis=1) * cols).sum(axis=1) / area
    cams = cameras.to(dtype=torch.float64, device="cpu")
    d = cams.directions_at(torch.from_numpy(cx), torch.from_numpy(cy)).numpy()  # (V, 3)
    o = cams.origin.numpy()
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (V, 3, 3) projectors off each ray
    A = P.sum(axis=0)
    b = np.einsum("vij,vj->i", P, o)
    # A is singular only when all centroid rays are parallel (views from one direction): lstsq
    # then returns the least-norm point of the solution line, and the box search that follows
    # reports the unbounded hull.
    return np.linalg.lstsq(A, b, rcond=1e-9)[0]


def _initial_half_size(masks: np.ndarray, cameras: Cameras, center: np.ndarray) -> float:
    """A generous half-size of a cube around `center` that holds the hull.

    Per view, the silhouette's angular radius alpha around the direction to `center` bounds the
    object's extent across that view to about dist * tan(alpha); twice the largest such bound is
    a cube that (for views from different directions) holds the whole hull. The box search grows
    the cube if the hull still reaches its faces.
    """
    cams = cameras.to(dtype=torch.float64, device="cpu")
    xy, depth = cams.project(torch.from_numpy(center)[None])  # (V, 1, 2)
    dist = np.linalg.norm(cams.origin.numpy() - center, axis=1)
    sizes = []
    for v in range(masks.shape[0]):
        ys, xs = np.nonzero(masks[v])
        # Only the silhouette's extreme pixels matter: its bounding-box corners bound every angle.
        corners_x = np.array([xs.min(), xs.max() + 1, xs.min(), xs.max() + 1], np.float64)
        corners_y = np.array([ys.min(), ys.min(), ys.max() + 1, ys.max() + 1], np.float64)
        dirs = cams.select(v).directions_at(torch.from_numpy(corners_x)[None],
                                            torch.from_numpy(corners_y)[None])[0].numpy()
        to_c = (center - cams.origin[v].numpy()) / max(dist[v], 1e-12)
        cos_a = np.clip(dirs @ to_c, -1.0, 1.0).min()
        if depth[v, 0] <= 0 or cos_a <= 0.05:  # centre behind the view or a near-180 deg spread
            sizes.append(dist[v])
        else:
            sizes.append(dist[v] * math.tan(math.acos(cos_a)))
    return 2.0 * float(max(sizes))


def _occupied_bounds(field: torch.Tensor, threshold: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Index bounds [imin, imax] (each (3,) int) of grid points with field > threshold, or None."""
    occ = field > threshold
    if not bool(occ.any()):
        return None
    lo, hi = [], []
    for axis in range(3):
        others = tuple(a for a in range(3) if a != axis)
        idx = torch.nonzero(occ.any(dim=others[1]).any(dim=others[0])).flatten()
        lo.append(int(idx[0]))
        hi.append(int(idx[-1]))
    return np.array(lo), np.array(hi)


def _grid_for_box(lo: np.ndarray, hi: np.ndarray, resolution: int) -> tuple[np.ndarray, float, tuple]:
    """Regular grid over [lo, hi] with `resolution` voxels along the longest side.

    Returns (origin (3,), voxel size h, shape): sample points are origin + index * h; the grid is
    centred on the box and covers it.
    """
    ext = hi - lo
    h = float(ext.max()) / resolution
    n = np.ceil(ext / h - 1e-6).astype(int) + 1
    origin = (lo + hi) / 2 - (n - 1) * h / 2
    return origin, h, tuple(int(x) for x in n)


def _find_box(carver: _Carver, masks: np.ndarray, cameras: Cameras,
              config: HullConfig) -> tuple[np.ndarray, np.ndarray]:
    """Tight box [lo, hi] (each (3,), capture frame) holding the hull, found by coarse carving.

    A round carves a grid over the current box; the new box is the occupied grid points' bounds
    plus one coarse voxel. A grid point counts as occupied when the field there exceeds minus one
    voxel: a voxel cell that touches the hull has its centre within sqrt(3)/2 voxels of it, and the
    field is roughly a distance, so the test keeps every cell the hull touches. Where the occupied
    region reaches the box's face the hull may continue beyond, so that side is pushed out by the
    box's size. Rounds at half `coarse_resolution` repeat until no side moves by more than a
    quarter voxel; one last round at `coarse_resolution` tightens the box to ~1/64 of its size.
    """
    center = _triangulate_center(masks, cameras)
    half = _initial_half_size(masks, cameras, center)
    lo, hi = center - half, center + half
    cam_dist = float(np.linalg.norm(cameras.origin.double().cpu().numpy() - center, axis=1).max())

    def one_round(lo: np.ndarray, hi: np.ndarray, res: int):
        origin, h, shape = _grid_for_box(lo, hi, res)
        field = carver.carve(origin, h, shape, far=-float(np.linalg.norm(hi - lo)))
        bounds = _occupied_bounds(field, -h)
        if bounds is None:
            raise LookingGlassError(
                "the visual hull is empty: no point lies inside every view's mask. The masks do not "
                "agree with the cameras (wrong camera poses, masks in a different order than the "
                "cameras, or a mask of another object)")
        imin, imax = bounds
        touch_lo, touch_hi = imin == 0, imax == np.array(shape) - 1
        new_lo = np.where(touch_lo, lo - (hi - lo), origin + (imin - 1) * h)
        new_hi = np.where(touch_hi, hi + (hi - lo), origin + (imax + 1) * h)
        touched = bool(np.any(touch_lo | touch_hi))
        if touched and float((new_hi - new_lo).max()) > 100 * cam_dist:
            raise LookingGlassError(
                "the visual hull is unbounded: the silhouettes do not close it off. Views from "
                "several directions are needed, and each mask must lie inside its image")
        moved = max(float(np.abs(new_lo - lo).max()), float(np.abs(new_hi - hi).max()))
        return new_lo, new_hi, touched, moved <= 0.25 * h

    for _ in range(config.box_iterations):
        lo, hi, touched, small_move = one_round(lo, hi, max(8, config.coarse_resolution // 2))
        if not touched and small_move:
            break
    else:
        if touched:
            raise LookingGlassError(
                "could not bound the visual hull: it keeps reaching the search box. Check that the "
                "views look at the object from several directions")
    # A touch in the final round only grows that side; the fine carve checks its faces again.
    lo, hi, _, _ = one_round(lo, hi, config.coarse_resolution)
    return lo, hi


def _view_coverage(volume: torch.Tensor, origin: np.ndarray, h: float, masks: np.ndarray,
                   cameras: Cameras) -> np.ndarray:
    """Fraction of each view's mask that the hull's projection covers. Returns (V,) float64.

    With consistent masks and cameras every mask pixel's ray meets the hull, so this is ~1; a view
    whose silhouette the hull explains only in part points at a wrong pose, a mask of another
    view, or a mask that disagrees with the others. Cheap approximation: the occupied voxels of
    the fine grid at stride 2 are projected and splatted into blocks of f x f pixels, f about the
    projected stride, and the splat is dilated by one block (a voxel's centre projects within a
    block of every pixel its cell covers).
    """
    import cv2

    occ = torch.nonzero(volume[::2, ::2, ::2] > 0).cpu().to(torch.float64) * (2 * h)
    pts = occ + torch.as_tensor(origin, dtype=torch.float64)  # (N, 3), capture frame
    cams = cameras.to(dtype=torch.float64, device="cpu")
    V, H, W = masks.shape
    centre = pts.mean(dim=0, keepdim=True)
    _, depth_c = cams.project(centre)  # (V, 1)
    pitch = cams.pixel_pitch * depth_c[:, 0].clamp_min(1e-12)  # world size of a pixel
    xy, depth = cams.project(pts)  # (V, N, 2), (V, N)
    cover = np.ones(V)
    for v in range(V):
        f = int(max(1, math.ceil(2 * h / float(pitch[v]))))
        hb, wb = -(-H // f), -(-W // f)
        blocks = np.zeros((hb * f, wb * f), bool)
        blocks[:H, :W] = masks[v]
        m_small = blocks.reshape(hb, f, wb, f).any(axis=(1, 3))
        ok = depth[v] > 0
        c = torch.floor(xy[v, ok] / f).long().numpy()
        inside = (c[:, 0] >= 0) & (c[:, 0] < wb) & (c[:, 1] >= 0) & (c[:, 1] < hb)
        splat = np.zeros((hb, wb), np.uint8)
        splat[c[inside, 1], c[inside, 0]] = 1
        splat = cv2.dilate(splat, np.ones((3, 3), np.uint8)) > 0
        cover[v] = (m_small & splat).sum() / max(1, m_small.sum())
    return cover


# ---------------------------------------------------------------------------------------------
# Steps of carve_visual_hull
# ---------------------------------------------------------------------------------------------
# Warnings raised in these steps use stacklevel=3: they point at the caller of carve_visual_hull.

class _StepClock:
    """Seconds per sub-step of carve_visual_hull, each reported to the optional progress callback."""

    def __init__(self, progress: ProgressFn | None):
        self.progress = progress
        self.start = self.last = time.perf_counter()
        self.timings: dict[str, float] = {}

    def __call__(self, name: str, fraction: float) -> None:
        """Sub-step `name` ended; `fraction` of the whole work is done."""
        now = time.perf_counter()
        self.timings[name] = now - self.last
        self.last = now
        if self.progress is not None:
            self.progress(name, fraction)

    def with_total(self) -> dict[str, float]:
        """The timings so far plus "total", the seconds since the clock was made."""
        self.timings["total"] = time.perf_counter() - self.start
        return self.timings


def _views(indices, names=None) -> str:
    """"view(s) [1, 3]", or with the views' mask files "view(s) 1 (masks/01.png), 3 (masks/03.png)"."""
    indices = [int(v) for v in indices]
    if names is None:
        return f"view(s) {indices}"
    return "view(s) " + ", ".join(f"{v} ({names[v]})" for v in indices)


def _checked_inputs(masks, cameras: Cameras, config: HullConfig, names=None) -> np.ndarray:
    """The masks as (V, H, W) bool after checking them against the cameras.

    Raises LookingGlassError for masks that do not fit the cameras or an empty mask (the config
    checked its own ranges); warns when a mask touches its image border (the hull is clipped there).
    """
    masks = _as_bool_masks(masks)
    V, H, W = masks.shape
    if V != cameras.num_views:
        raise LookingGlassError(f"{V} masks for {cameras.num_views} cameras")
    if (W, H) != (cameras.width, cameras.height):
        raise LookingGlassError(
            f"masks are {W}x{H} pixels but the cameras are {cameras.width}x{cameras.height}")
    if V < 2:
        raise LookingGlassError("a visual hull needs at least 2 views")
    areas = masks.sum(axis=(1, 2))
    if np.any(areas == 0):
        raise LookingGlassError(f"the mask of {_views(np.flatnonzero(areas == 0), names)} is empty")
    border = masks[:, 0, :].any(1) | masks[:, -1, :].any(1) | masks[:, :, 0].any(1) | masks[:, :, -1].any(1)
    if np.any(border):
        warnings.warn(
            f"the mask of {_views(np.flatnonzero(border), names)} touches the image border: the "
            "object is cut off there, and the hull is clipped to the image (outside counts as "
            "background)", stacklevel=3)
    return masks


def _carve_fine(carver: _Carver, lo: np.ndarray, hi: np.ndarray, config: HullConfig):
    """The fine carve over the box [lo, hi] (capture frame) at `config.resolution`.

    The coarse search is conservative, but if the hull still reaches the grid's faces, that side
    is grown and the grid carved again (up to 3 times) rather than the hull clipped flat.
    Returns (field (nx, ny, nz) float32 on the carver's device, positive inside; lo, hi: the box
    finally carved; origin (3,), voxel size h, shape: the grid, as `_grid_for_box`). With
    `config.field == "binary"` the field is +-h/2 occupancy.
    """
    origin, h, shape = _grid_for_box(lo, hi, config.resolution)
    far = -float(np.linalg.norm(hi - lo))
    vol = carver.carve(origin, h, shape, far=far)
    for _ in range(3):
        touch = np.array([[float(vol[0].max()) > 0, float(vol[-1].max()) > 0],
                          [float(vol[:, 0].max()) > 0, float(vol[:, -1].max()) > 0],
                          [float(vol[:, :, 0].max()) > 0, float(vol[:, :, -1].max()) > 0]])
        if not touch.any():
            break
        grow = 0.1 * float((hi - lo).max())
        lo = lo - grow * touch[:, 0]
        hi = hi + grow * touch[:, 1]
        origin, h, shape = _grid_for_box(lo, hi, config.resolution)
        vol = carver.carve(origin, h, shape, far=far)
    if config.field == "binary":
        vol = torch.where(vol > 0, 0.5 * h, -0.5 * h)
    return vol, lo, hi, origin, h, shape


def _checked_coverage(vol: torch.Tensor, origin: np.ndarray, h: float, masks: np.ndarray,
                      cameras: Cameras, config: HullConfig, names=None) -> np.ndarray:
    """Each view's mask coverage by the carved hull ((V,) float64, see `_view_coverage`).

    Raises LookingGlassError when the hull is empty or covers less than `min_view_coverage` of a
    view's mask; warns below `warn_view_coverage`.
    """
    if not bool((vol > 0).any()):
        raise LookingGlassError(
            "the visual hull is empty at the carving resolution: the masks do not agree with "
            "the cameras (or the object is thinner than a voxel)")
    coverage = _view_coverage(vol, origin, h, masks, cameras)
    bad = np.flatnonzero(coverage < config.min_view_coverage)
    if len(bad):
        raise LookingGlassError(
            f"the masks do not agree with the cameras: the visual hull covers only "
            f"{', '.join(f'{100 * coverage[v]:.0f}%' for v in bad)} of the mask of "
            f"{_views(bad, names)} (a wrong camera pose, masks in another order than the cameras, or "
            f"a mask of another object)")
    low = np.flatnonzero(coverage < config.warn_view_coverage)
    if len(low):
        warnings.warn(
            f"the visual hull covers only {', '.join(f'{100 * coverage[v]:.0f}%' for v in low)} "
            f"of the mask of {_views(low, names)}: some masks or camera poses are off",
            stacklevel=4)  # called from _carve_surface
    return coverage


def _marching_cubes(volume: np.ndarray, origin: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Outward-oriented zero set of the carved field `volume` (nx, ny, nz), grid origin + index * h.

    Returns vertices (N, 3) float64 in the capture frame and faces (M, 3) int64; closed (the grid
    gets a layer of "outside"). Changes `volume` (samples exactly at zero).
    """
    from skimage.measure import marching_cubes

    # Samples exactly at the level make zero-area triangles; nudge them off it (far below the
    # float32 resolution of the surface position).
    volume[volume == 0] = -1e-7 * h
    # One layer of "outside" around the grid guarantees a closed surface.
    volume = np.pad(volume, 1, mode="constant", constant_values=-h)
    verts, faces, _, _ = marching_cubes(volume, level=0.0, spacing=(h, h, h), allow_degenerate=True)
    verts = verts.astype(np.float64) + (origin - h)  # undo the padding layer; capture frame
    # Orient outward before subdivision (LS3 fits with the normals): rather than rely on
    # skimage's winding convention, flip when the signed volume is negative.
    return verts, orient_outward(verts, faces.astype(np.int64))


def _largest_piece(verts: np.ndarray, faces: np.ndarray, h: float, masks: np.ndarray,
                   cameras: Cameras) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """The hull's largest piece (vertices (K, 3), faces (F, 3)), the number of pieces larger than a
    voxel (h^3) dropped besides it (specks where the field grazes zero at one sample are not
    counted), and per view the share of the mask that the dropped pieces cover and the largest one
    does not ((V,); zeros when none was dropped): ~0 for the regions every mask allows but no
    mask pixel needs, the share of a part of the object that came apart otherwise."""
    kept_verts, kept_faces, dropped = largest_component(verts, faces, min_volume=h ** 3)
    lost = np.zeros(len(masks))
    if dropped:
        from .render.raycast import RayCaster

        # the mask pixels' rays only, and of those the whole hull's hits against the largest piece
        origins, directions = (r.numpy()[masks] for r in cameras.to(dtype=torch.float64, device="cpu").pixel_rays())
        uncovered = RayCaster.of(verts, faces).hit_mask(origins, directions)
        uncovered[uncovered] = ~RayCaster.of(kept_verts, kept_faces).hit_mask(origins[uncovered],
                                                                              directions[uncovered])
        view = np.broadcast_to(np.arange(len(masks))[:, None, None], masks.shape)[masks]
        lost = np.bincount(view[uncovered], minlength=len(masks)) / np.maximum(1, masks.sum(axis=(1, 2)))
    return kept_verts, kept_faces, dropped, lost


@dataclass
class _Carved:
    """One fine carve's box [lo, hi], grid (origin, voxel size h, shape), the views' mask coverage,
    and its surface's largest piece with what `_largest_piece` says of the pieces dropped."""

    lo: np.ndarray
    hi: np.ndarray
    origin: np.ndarray
    h: float
    shape: tuple
    coverage: np.ndarray
    verts: np.ndarray
    faces: np.ndarray
    dropped: int
    lost: np.ndarray


def _carve_surface(carver: _Carver, lo: np.ndarray, hi: np.ndarray, config: HullConfig, masks: np.ndarray,
                   cameras: Cameras, view_names=None, step: "_StepClock | None" = None) -> _Carved:
    """The fine carve over [lo, hi] at `config.resolution`, its coverage, marching cubes and largest
    piece. With `step` (the first carve) the coverage is checked (`_checked_coverage`: errors and
    warnings) and each sub-step timed; without (the finer second carve of the same box) it is only
    measured."""
    checked = step is not None
    step = step or (lambda name, fraction: None)
    vol, lo, hi, origin, h, shape = _carve_fine(carver, lo, hi, config)
    step("carve", 0.6)
    coverage = (_checked_coverage(vol, origin, h, masks, cameras, config, view_names) if checked
                else _view_coverage(vol, origin, h, masks, cameras))
    step("coverage", 0.65)
    verts, faces = _marching_cubes(vol.cpu().numpy(), origin, h)
    step("marching_cubes", 0.7)
    verts, faces, dropped, lost = _largest_piece(verts, faces, h, masks, cameras)
    step("components", 0.75)
    return _Carved(lo, hi, origin, h, shape, coverage, verts, faces, dropped, lost)


def _smoothed(verts: np.ndarray, faces: np.ndarray, config: HullConfig) -> tuple[np.ndarray, np.ndarray]:
    """Optional Taubin smoothing, then LS3 Loop subdivision, as `config` asks."""
    if config.smoothing_iterations > 0:
        # the config counts lambda/mu steps, taubin_smooth single passes
        verts = taubin_smooth(verts, faces, 2 * config.smoothing_iterations)
    if config.subdivision_iterations > 0:
        verts, faces = _ls3_loop(verts, faces, config.subdivision_iterations,
                                 config.subdivision_threshold)
    return verts, faces


# ---------------------------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------------------------

def carve_visual_hull(masks, cameras: Cameras, config: HullConfig = HullConfig(),
                      progress: ProgressFn | None = None, view_names=None) -> VisualHull:
    """Carve the visual hull of V silhouettes.

    masks: (V, H, W) bool, numpy or torch (object = True); H, W = the cameras' image size.
    cameras: the V views, capture frame (any position and scale of the object).
    config: see `HullConfig`.
    progress: optional callback progress(sub_step, fraction_done) for a progress bar; called after
        each sub-step with its name (the keys of `VisualHull.timings`).
    view_names: optional (V,) names of the views' mask files, for the messages about a view.
    Returns a `VisualHull` in the capture frame. Raises `LookingGlassError` when the inputs do not
    match, a mask is empty, the hull is empty or unbounded, or the hull explains less than
    `config.min_view_coverage` of some view's mask (masks and cameras disagree). Warns
    (warnings.warn) when a mask touches its image border (the object is cut off there: the hull is
    clipped to the image), when a view's coverage is below `config.warn_view_coverage`, when the
    hull came apart at `config.resolution` and was carved again finer, and when pieces of the hull
    that cover mask pixels the largest one does not are dropped (`recarve_lost_share`).
    """
    step = _StepClock(progress)
    masks = _checked_inputs(masks, cameras, config, view_names)

    with torch_threads(config.num_threads), torch.inference_mode():
        carver = _Carver(silhouette_fields(masks), cameras, config.device, config.chunk_voxels)
        step("masks", 0.05)

        lo, hi = _find_box(carver, masks, cameras, config)
        pad = config.padding * float((hi - lo).max())
        step("box", 0.1)

        carved = _carve_surface(carver, lo - pad, hi + pad, config, masks, cameras, view_names, step)
        finer = min(2 * config.resolution, config.max_resolution)
        if carved.lost.max() > config.recarve_lost_share and finer > config.resolution:
            # a part thinner than a voxel came apart: the same box (no new search) at a finer grid
            fine = _carve_surface(carver, carved.lo, carved.hi, dataclasses.replace(config, resolution=finer),
                                  masks, cameras)
            worst = int(np.argmax(carved.lost))
            warnings.warn(f"the visual hull came apart at {config.resolution} voxels (a part thinner than a voxel: "
                          f"the pieces besides the largest cover {100 * carved.lost[worst]:.1f}% of the mask of "
                          f"{_views([worst], view_names)}); carved again at {finer} voxels, where they cover "
                          f"{100 * fine.lost[worst]:.1f}%", stacklevel=2)
            if fine.lost.max() < carved.lost.max():
                carved = fine
            step("recarve", 0.8)
    verts, faces, dropped, lost = carved.verts, carved.faces, carved.dropped, carved.lost
    if lost.max() > config.recarve_lost_share:
        worst = np.flatnonzero(lost > config.recarve_lost_share)
        warnings.warn(f"the visual hull has {dropped + 1} separate pieces; kept the largest, dropped {dropped}, "
                      f"which cover {', '.join(f'{100 * lost[v]:.1f}%' for v in worst)} of the mask of "
                      f"{_views(worst, view_names)} that the largest leaves uncovered (parts thinner than a "
                      f"voxel, stray mask pixels or an inconsistent view?)", stacklevel=2)
    verts, faces = _smoothed(verts, faces, config)
    step("subdivision", 0.95)

    # Marching cubes and MeshLab both return shared vertices, so no merging (process=False keeps
    # the topology exactly as built; merging coincident vertices could pinch it).
    # Vertices rounded to float32 (the precision PLY files, the renderer and `generate`'s stored
    # hulls keep; ~1e-7 of the box, far below a voxel), so a hull read back is the hull carved.
    verts = verts.astype(np.float32).astype(np.float64)
    mesh = trimesh.Trimesh(verts, orient_outward(verts, faces), process=False, validate=False)
    require_closed_and_oriented(mesh, "the carved hull",
                                " (an internal error: please report it, with the masks and cameras)")
    center, scale = hull_normalization(np.asarray(mesh.vertices))
    step("finish", 1.0)
    return VisualHull(mesh=mesh, center=center, scale=scale, bbox=np.stack([carved.lo, carved.hi]),
                      voxel_size=carved.h, grid_shape=carved.shape, view_coverage=carved.coverage,
                      timings=step.with_total())
