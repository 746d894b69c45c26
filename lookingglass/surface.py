"""Surface from oriented points: screened Poisson reconstruction (pipeline step 6, DESIGN.md).

The point net's output (points p = p~ + dp with normals N) becomes a watertight mesh by MeshLab's
screened Poisson reconstruction (Kazhdan & Hoppe 2013, via pymeshlab
`generate_surface_reconstruction_screened_poisson`), then:

1. The Poisson isosurface is split into connected components. A component is dropped when it is
   far from the data: the median distance of its vertices to the nearest input point exceeds
   `trim_distance`, or (with a `hull`) the median of its vertices lies more than `trim_distance`
   outside the hull. Poisson's spurious blobs are such components.
2. The remaining components are kept (Poisson may cut a thin part of the object into pieces;
   they are real surface), apart from crumbs under MIN_COMPONENT_AREA of the largest one's area.
3. No face-level trimming. The isosurface of Poisson's indicator function is closed by
   construction; deleting faces that are far from the points (MeshLab's usual density trim)
   would open holes and break watertightness, which the pipeline's output must have. Faces
   farther than `trim_distance` from every input point are only counted
   (`mesh.metadata["poisson"]["far_faces"]`): many of them mean the points left a region
   unsampled and Poisson bridged it.
4. Optional Taubin smoothing (lambda/mu, no shrinkage; moves vertices only, so watertightness
   is kept).
5. Consistent winding, each body outward but a body inside another inward (a cavity:
   `meshes.wind_cavities_inward`), and a final check: a result that is empty, not watertight or of
   non-positive volume raises LookingGlassError.

Frames: any; points, normals and hull share one frame (normally the normalized unit-sphere frame).
"""

from __future__ import annotations

import os

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from .errors import LookingGlassError
from .meshes import (MIN_COMPONENT_AREA, manifold_mesh, merged_and_repaired, require_closed_and_oriented, taubin_smooth,
                     wind_cavities_inward, without_crumbs)

__all__ = ["poisson_surface", "close_narrow_tunnels", "DEFAULT_TRIM_FRACTION"]

DEFAULT_TRIM_FRACTION = 0.05  # trim_distance default: this fraction of the hull's (or points') bbox diagonal
_MIN_POINTS = 16  # Poisson on fewer oriented points gives nothing meaningful


def _numpy64(a, name: str) -> np.ndarray:
    if hasattr(a, "detach"):  # torch tensor, any device
        a = a.detach().cpu().numpy()
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    return a


def _threads(n: int) -> int:
    """n > 0: n; otherwise half the cores, at least 1 (see lookingglass.threads: on a busy 2-core
    machine two OpenMP threads made Poisson ~8x slower than one)."""
    return int(n) if n > 0 else max(1, (os.cpu_count() or 2) // 2)


def _run_poisson(points: np.ndarray, normals: np.ndarray, depth: int, threads: int,
                 samples_per_node: float, point_weight: float) -> trimesh.Trimesh:
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(points),
                               v_normals_matrix=np.ascontiguousarray(normals)))
    try:
        ms.generate_surface_reconstruction_screened_poisson(
            depth=int(depth), samplespernode=float(samples_per_node), pointweight=float(point_weight),
            threads=_threads(threads))
    except pymeshlab.PyMeshLabException as exc:
        raise LookingGlassError(f"Poisson surface reconstruction failed: {exc}") from exc
    return merged_and_repaired(ms)


def _outside_hull_median(hull: trimesh.Trimesh, vertices: np.ndarray, probes: int = 256) -> float:
    """Median over (a deterministic subset of) `vertices` of their distance outside `hull`
    (positive outside, negative inside; trimesh's signed distance is positive inside)."""
    step = max(1, len(vertices) // probes)
    sd = trimesh.proximity.signed_distance(hull, vertices[::step])
    return float(np.median(-sd))


def poisson_surface(points, normals, depth: int = 8, hull: trimesh.Trimesh | None = None,
                    trim_distance: float | None = None, smooth_iterations: int = 0,
                    threads: int = 0, samples_per_node: float = 1.5,
                    point_weight: float = 4.0) -> trimesh.Trimesh:
    """Watertight, outward-oriented mesh (cavities wound inward) from oriented points by screened Poisson.

    points: (N, 3) positions; normals: (N, 3) outward normals (need not be unit), same frame;
    numpy or torch. Rows with non-finite values or zero normals are dropped.
    depth: octree depth; the voxel is about 1.1 x (bounding-box size) / 2^depth (MeshLab's
    default box scale 1.1). hull: the visual hull, to drop components outside its
    neighbourhood. trim_distance: distance beyond which a component counts as far from the data;
    default DEFAULT_TRIM_FRACTION (5%) of the hull's bounding-box diagonal (of the points' without
    a hull). smooth_iterations: Taubin smoothing steps (0 = none). threads: Poisson threads (0 =
    half the cores). samples_per_node, point_weight: MeshLab's screened-Poisson parameters.

    Returns a trimesh.Trimesh, watertight with consistent outward winding (a body inside another
    inward: a cavity). Its metadata["poisson"] holds: depth, points_used, points_dropped,
    components, components_dropped, far_faces, trim_distance. Raises LookingGlassError when too few valid points are given or the
    result is empty or not watertight.
    """
    p = _numpy64(points, "points")
    n = _numpy64(normals, "normals")
    if p.shape != n.shape:
        raise ValueError(f"points {p.shape} and normals {n.shape} differ in shape")
    length = np.linalg.norm(n, axis=1)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(n).all(axis=1) & (length > 1e-12)
    if ok.sum() < _MIN_POINTS:
        raise LookingGlassError(f"Poisson surface reconstruction needs at least {_MIN_POINTS} points with "
                                f"finite positions and non-zero normals, got {int(ok.sum())}")
    p, n = p[ok], n[ok] / length[ok, None]

    if trim_distance is None:
        box = hull.bounds if hull is not None else np.stack([p.min(axis=0), p.max(axis=0)])
        trim_distance = DEFAULT_TRIM_FRACTION * float(np.linalg.norm(box[1] - box[0]))
    trim_distance = float(trim_distance)

    mesh = _run_poisson(p, n, depth, threads, samples_per_node, point_weight)
    if len(mesh.faces) == 0:
        raise LookingGlassError("Poisson surface reconstruction produced an empty mesh "
                                f"from {len(p)} points (are the normals consistent?)")

    # ---- components: drop the ones far from the data and the crumbs, keep the rest ------------
    tree = cKDTree(p)
    parts = mesh.split(only_watertight=False)
    near = []
    for part in parts:  # a handful of components, not points
        far_from_points = np.median(tree.query(part.vertices, k=1)[0]) > trim_distance
        outside_hull = hull is not None and _outside_hull_median(hull, np.asarray(part.vertices)) > trim_distance
        if not (far_from_points or outside_hull):
            near.append(part)
    if not near:
        raise LookingGlassError("Poisson surface reconstruction produced no surface near the input points "
                                f"(all {len(parts)} components farther than {trim_distance:.4g})")
    # Every near component is kept, not only the largest: where Poisson cuts a thin part of the
    # object (a bar, a handle) the pieces are real surface.
    mesh = without_crumbs(near, MIN_COMPONENT_AREA)

    # ---- report (not trim) faces far from every point: trimming would open holes ---------------
    far_faces = int((tree.query(mesh.triangles_center, k=1)[0] > trim_distance).sum())

    if smooth_iterations > 0:
        mesh.vertices = taubin_smooth(mesh.vertices, mesh.faces, int(smooth_iterations))

    mesh.fix_normals(multibody=True)  # consistent winding, each body outward
    mesh = wind_cavities_inward(mesh)  # but a body inside another is a cavity
    require_closed_and_oriented(mesh, "Poisson surface", "; try a lower depth or denser points")
    mesh.metadata["poisson"] = {
        "depth": int(depth),
        "points_used": int(len(p)),
        "points_dropped": int((~ok).sum()),
        "components": len(parts),
        "components_dropped": len(parts) - len(near),
        "far_faces": far_faces,
        "trim_distance": trim_distance,
    }
    return mesh


SAMPLES_PER_CELL = 8  # surface samples a grid cell's area of surface gets in signed_distance_grid


def _ball(radius: int) -> np.ndarray:
    g = np.mgrid[-radius:radius + 1, -radius:radius + 1, -radius:radius + 1]
    return (g ** 2).sum(axis=0) <= radius * radius  # the grid nodes within `radius` steps of the centre


def signed_distance_grid(mesh: trimesh.Trimesh, pitch: float, margin: int, samples: int = 0,
                         seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance to closed `mesh` (negative inside) on a grid of spacing `pitch` over its
    bounds plus `margin` steps, clamped to +-2 steps, and the grid's first node. Near the surface
    (the nodes of the cells that hold one of `samples` surface samples, and their neighbours) it
    is the distance to the tangent plane of the nearest sample, exact to well under a step (at
    least SAMPLES_PER_CELL samples a cell's area of surface, more if `samples` asks); away
    from it, +-2 steps by the side of the surface that the walls around the node face: each
    region the band cuts off takes the majority sign of the band nodes next to it. (Not "enclosed
    by the band means inside": a pocket of outside space behind a neck narrower than the band, as
    in a slit handle, would be filled.)"""
    lo = mesh.bounds[0] - margin * pitch
    shape = np.ceil((mesh.bounds[1] + margin * pitch - lo) / pitch).astype(int) + 1
    # enough samples that every cell the surface crosses holds one and the band separates inside
    # from outside (a floor of 1 000 000 until session 72 gave the same closings within the
    # sampling noise, CD 0.6-1.1 x 1e-4 between them, in 1.2-1.7 x the time)
    samples = max(int(samples), int(SAMPLES_PER_CELL * mesh.area / pitch ** 2))
    points, face_index = trimesh.sample.sample_surface(mesh, samples, seed=seed)
    normals = mesh.face_normals[face_index]
    # band: grid nodes of the cells that hold a sample, and their neighbours; only these get a distance
    cell = np.floor((points - lo) / pitch).astype(int)
    band = np.zeros(shape, bool)
    for corner in np.ndindex(2, 2, 2):
        i = cell + corner
        band[i[:, 0], i[:, 1], i[:, 2]] = True
    band = ndimage.binary_dilation(band)
    nodes = np.argwhere(band)
    x = lo + nodes * pitch
    _, nearest = cKDTree(points).query(x)
    signed = np.einsum("ij,ij->i", x - points[nearest], normals[nearest])
    field = np.zeros(shape, np.float32)
    field[band] = np.clip(signed, -2.0 * pitch, 2.0 * pitch)
    free = ~band
    region, count = ndimage.label(free)  # 0 on the band
    side = np.sign(field).astype(np.int8)  # +-1 on the band, 0 off it (not yet assigned)
    votes = np.zeros(count + 1)
    for axis in range(3):  # each region's 6-neighbours on the band vote with their side
        for a, b in ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None))):
            src, dst = [slice(None)] * 3, [slice(None)] * 3
            src[axis], dst[axis] = a, b
            r, v = region[tuple(src)], side[tuple(dst)]
            pair = (r > 0) & (v != 0)
            votes += np.bincount(r[pair], weights=v[pair], minlength=count + 1)
    inside_region = votes < 0
    # what touches the grid's border is outside whatever the votes say (the grid has a margin)
    for axis in range(3):
        inside_region[np.moveaxis(region, axis, 0)[[0, -1]].ravel()] = False
    field[free] = np.where(inside_region[region[free]], -2.0 * pitch, 2.0 * pitch)
    return field, lo


def close_narrow_tunnels(mesh: trimesh.Trimesh, pitch: float, radius: int, samples: int = 0,
                         seed: int = 0) -> trimesh.Trimesh:
    """`mesh` (closed) with every tunnel, slit and crevice narrower than about 2 * radius * pitch
    filled in: a morphological closing of its solid by a ball of `radius` grid steps, on a grid of
    spacing `pitch`, re-meshed by marching cubes. Elsewhere the surface is kept to a small fraction
    of `pitch`: the grid holds the signed distance to the tangent plane of the nearest of `samples`
    surface samples (at least SAMPLES_PER_CELL a grid cell's area of surface), not a 0/1 occupancy.

    Why: where PNet's displacement pushes two facing sheets of points through each other, screened
    Poisson opens tunnels narrower than the point spacing. They change the genus (wrong topology)
    but hardly the Chamfer distance; a real hole through the object (a handle) is much wider and
    survives. Closing can also bridge a groove over a wider channel and so add a handle: callers
    compare the genus before and after. The result is watertight and outward-oriented (the fill
    below closes every pocket, Poisson's cavities too, so it has none); metadata["closing"] says how
    much solid the closing added (in grid cells)."""
    # a margin wider than the ball: the closing's dilation must not reach the grid's border
    field, lo = signed_distance_grid(mesh, pitch, margin=int(radius) + 3, samples=samples, seed=seed)
    inside = field < 0
    # Closing can seal a pocket behind a narrow neck; it is filled too: on PNet's surfaces these
    # are the space between sheets pushed through each other, which the tunnels lead into.
    added = ndimage.binary_fill_holes(ndimage.binary_closing(inside, structure=_ball(int(radius)))) & ~inside
    field[added] = -0.5 * pitch  # the plugs: inside, half a step from their boundary
    vertices, faces, _, _ = marching_cubes(field, 0.0, spacing=(pitch, pitch, pitch))
    closed = manifold_mesh(vertices + lo, faces)
    parts = closed.split(only_watertight=False)
    if not parts:
        raise LookingGlassError("closing the narrow tunnels left no surface")
    closed = without_crumbs(parts, MIN_COMPONENT_AREA)
    closed.fix_normals(multibody=True)  # consistent winding, each body outward (the fill left no cavity)
    require_closed_and_oriented(closed, "the surface with its narrow tunnels closed")
    closed.metadata["closing"] = {"pitch": float(pitch), "radius": int(radius), "cells_added": int(added.sum())}
    return closed
