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
5. Consistent winding, outward orientation (positive volume), and a final check: a result that is
   empty, not watertight or of non-positive volume raises LookingGlassError.

Frames: any; points, normals and hull share one frame (normally the normalized unit-sphere frame).
"""

from __future__ import annotations

import os

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from .errors import LookingGlassError

__all__ = ["poisson_surface", "DEFAULT_TRIM_FRACTION"]

DEFAULT_TRIM_FRACTION = 0.05  # trim_distance default: this fraction of the hull's (or points') bbox diagonal
MIN_COMPONENT_AREA = 1e-3  # components smaller than this fraction of the largest one's area are dropped
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
    # Marching cubes leaves vertices a hair apart where the surface passes near a grid corner.
    # Merged here (1e-6 of the box diagonal) and the pinches that makes split, so no later rounding
    # (the move back to the capture's frame, a PLY reader merging equal positions) can pinch the
    # written mesh into a non-manifold one.
    ms.meshing_merge_close_vertices(threshold=pymeshlab.PercentageValue(1e-4))
    repair_pinches(ms)
    m = ms.current_mesh()  # the filter adds the surface as a new, current layer
    # process=True merges Poisson's duplicated vertices, so shared edges are recognized
    return trimesh.Trimesh(vertices=m.vertex_matrix(), faces=m.face_matrix(), process=True)


def repair_pinches(ms) -> None:
    """Split the current mesh of pymeshlab MeshSet `ms` where two sheets touch along an edge or at
    a vertex (marching cubes makes these where a surface is one cell thin), and close what opens."""
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_null_faces()
    ms.meshing_repair_non_manifold_edges(method="Split Vertices")
    ms.meshing_repair_non_manifold_vertices()
    ms.meshing_close_holes()
    ms.meshing_remove_unreferenced_vertices()


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
    """Watertight, outward-oriented mesh from oriented points by screened Poisson.

    points: (N, 3) positions; normals: (N, 3) outward normals (need not be unit), same frame;
    numpy or torch. Rows with non-finite values or zero normals are dropped.
    depth: octree depth; the voxel is about 1.1 x (bounding-box size) / 2^depth (MeshLab's
    default box scale 1.1). hull: the visual hull, to drop components outside its
    neighbourhood. trim_distance: distance beyond which a component counts as far from the data;
    default DEFAULT_TRIM_FRACTION (5%) of the hull's bounding-box diagonal (of the points' without
    a hull). smooth_iterations: Taubin smoothing steps (0 = none). threads: Poisson threads (0 =
    half the cores). samples_per_node, point_weight: MeshLab's screened-Poisson parameters.

    Returns a trimesh.Trimesh, watertight with consistent outward winding. Its
    metadata["poisson"] holds: depth, points_used, points_dropped, components, components_dropped,
    far_faces, trim_distance. Raises LookingGlassError when too few valid points are given or the
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
    # object (a bar, a handle) the pieces are real surface. Crumbs below MIN_COMPONENT_AREA of the
    # largest are dropped.
    largest = max(part.area for part in near)
    near = [part for part in near if part.area >= MIN_COMPONENT_AREA * largest]
    mesh = near[0] if len(near) == 1 else trimesh.util.concatenate(near)

    # ---- report (not trim) faces far from every point: trimming would open holes ---------------
    far_faces = int((tree.query(mesh.triangles_center, k=1)[0] > trim_distance).sum())

    if smooth_iterations > 0:
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=int(smooth_iterations))

    mesh.fix_normals(multibody=True)  # consistent winding, each body flipped if its volume is negative
    if not mesh.is_watertight or not mesh.is_winding_consistent:
        raise LookingGlassError("Poisson surface is not watertight (open or non-manifold edges); "
                                "try a lower depth or denser points")
    if not mesh.volume > 0:
        raise LookingGlassError("Poisson surface encloses no volume")
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
