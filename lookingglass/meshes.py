"""Mesh helpers shared by the hull, the surface and the shape generator: plain functions.

Arrays: vertices (N, 3) float64, faces (M, 3) int64 indexing into them (pymeshlab wants int32
and gets it converted here). Functions that need trimesh's caches (watertightness, winding) take a
`trimesh.Trimesh`; `repair_pinches` and `merged_and_repaired` take a pymeshlab MeshSet, whose
current mesh they change in place (callers build those surfaces inside MeshLab).

Orientation convention: a closed mesh is outward-oriented when its signed volume is positive
(faces wound counter-clockwise seen from outside, normals by the right-hand rule point out); in a
mesh of several bodies, one inside another is a cavity and wound inward (`wind_cavities_inward`).
"""

from __future__ import annotations

import numpy as np
import trimesh

from .errors import LookingGlassError

__all__ = [
    "TAUBIN_LAMBDA",
    "TAUBIN_MU",
    "MIN_COMPONENT_AREA",
    "signed_volume",
    "body_volumes",
    "orient_outward",
    "require_closed_and_oriented",
    "check_glass_mesh",
    "face_components",
    "largest_component",
    "without_crumbs",
    "wind_cavities_inward",
    "taubin_smooth",
    "subdivide_ls3_loop",
    "repair_pinches",
    "merged_and_repaired",
    "manifold_mesh",
]

# Taubin's lambda/mu (Taubin 1995): a shrinking step by lambda, then an inflating one by mu with
# |mu| slightly above lambda, so low frequencies (the shape) keep their size and ripples shrink.
TAUBIN_LAMBDA = 0.5
TAUBIN_MU = -0.53
MIN_COMPONENT_AREA = 1e-3  # pieces smaller than this fraction of the largest one's area are crumbs (`without_crumbs`)


# ---------------------------------------------------------------------------------------------
# Volume and orientation
# ---------------------------------------------------------------------------------------------

def _six_tetra_volumes(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(M,) a . (b x c) per face (a, b, c): six times the signed volume of the tetrahedron
    (origin, a, b, c). Summed over a closed mesh, six times its volume (divergence theorem); the
    division by 6 is left to the end, so a mesh with exact coordinates gets an exact volume."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c))


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed triangle mesh; positive when its faces wind outward.

    vertices (N, 3) float64, faces (M, 3) int.
    """
    return float(_six_tetra_volumes(vertices, faces).sum()) / 6.0


def body_volumes(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(B,) signed volume of each body (connected component with faces) of a closed mesh: negative
    for a body wound inward (a cavity, `wind_cavities_inward`). vertices (N, 3), faces (M, 3) int."""
    count, face_label = face_components(faces, len(vertices))
    faces_per_label, volumes = _label_faces_and_volumes(vertices, faces, count, face_label)
    return volumes[faces_per_label > 0]


def _label_faces_and_volumes(vertices: np.ndarray, faces: np.ndarray, count: int,
                             face_label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(count,) faces and signed volume per label of `face_components` (0 faces: an unreferenced vertex)."""
    faces_per_label = np.bincount(face_label, minlength=count)
    return faces_per_label, np.bincount(face_label, weights=_six_tetra_volumes(vertices, faces), minlength=count) / 6.0


def orient_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """`faces` (M, 3) wound outward: reversed (a new array) when the signed volume is negative.

    For one closed, consistently wound body (one sign decides for all faces). vertices (N, 3).
    """
    if signed_volume(vertices, faces) < 0:
        return faces[:, ::-1].copy()
    return faces


def require_closed_and_oriented(mesh: trimesh.Trimesh, what: str, hint: str = "") -> None:
    """Raise LookingGlassError unless `mesh` has finite vertices, is watertight with consistent
    winding, and encloses a positive volume (outward normals).

    what: the mesh in the message ("Poisson surface"); hint: appended to the message of a broken
    (non-finite or open) mesh, e.g. what to try instead.
    """
    if not np.isfinite(mesh.vertices).all():
        raise LookingGlassError(f"{what} has non-finite vertex positions{hint}")
    if not mesh.is_watertight or not mesh.is_winding_consistent:
        raise LookingGlassError(f"{what} is not watertight (open or non-manifold edges){hint}")
    if not mesh.volume > 0:
        raise LookingGlassError(f"{what} encloses no volume")


def check_glass_mesh(mesh: trimesh.Trimesh, path) -> None:
    """Raise LookingGlassError naming the file `path` unless `mesh` is a solid a renderer can trace
    as glass: closed (watertight, consistently wound), wound outward (positive volume) and free of
    self-intersections (where sheets cross, inside and outside are undefined)."""
    if not mesh.is_watertight or not mesh.is_winding_consistent:
        open_edges = int(len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)))
        what = f"{open_edges} boundary edges" if open_edges else "non-manifold edges or inconsistent winding"
        raise LookingGlassError(f"mesh is not closed ({what}): a glass object must be a watertight surface", path)
    if not mesh.volume > 0:
        raise LookingGlassError("mesh is oriented inward (its faces' normals point into the object, negative "
                                "volume): flip its faces", path)
    ms = _meshset(mesh.vertices, mesh.faces)
    ms.compute_selection_by_self_intersections_per_face()
    crossing = int(ms.current_mesh().selected_face_number())
    if crossing:
        raise LookingGlassError(f"mesh intersects itself ({crossing} faces cross others): inside and outside are "
                                "undefined there; repair it (e.g. a boolean union of its parts)", path)


# ---------------------------------------------------------------------------------------------
# Components
# ---------------------------------------------------------------------------------------------

def face_components(faces: np.ndarray, num_vertices: int) -> tuple[int, np.ndarray]:
    """Connected components of a triangle mesh, faces joined through shared vertices.

    faces (M, 3) int; num_vertices: N. Returns (count, face_label (M,) int in [0, count)).
    Unreferenced vertices are components of their own, so labels of faces may skip values.
    """
    import scipy.sparse
    import scipy.sparse.csgraph

    # Vertex graph through two edges of each face (a-b, b-c): enough to connect a triangle.
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = scipy.sparse.coo_matrix((np.ones(len(rows), np.int8), (rows, cols)),
                                    shape=(num_vertices, num_vertices))
    count, vertex_label = scipy.sparse.csgraph.connected_components(graph, directed=False)
    return int(count), vertex_label[faces[:, 0]]


def largest_component(vertices: np.ndarray, faces: np.ndarray,
                      min_volume: float = 0.0) -> tuple[np.ndarray, np.ndarray, int]:
    """Keep the connected component with the most faces (the first one on ties).

    vertices (N, 3), faces (M, 3) int64, components joined through shared vertices. Returns the
    kept vertices (K, 3) (unreferenced ones dropped, order kept) and faces (F, 3) int64 indexing
    them, and the number of dropped pieces that enclose more than `min_volume` (by |signed
    volume|, meaningful for closed pieces): callers warn about those, smaller ones are specks.
    """
    count, face_label = face_components(faces, len(vertices))
    dropped = 0
    if count > 1:
        faces_per_label, piece_volume = _label_faces_and_volumes(vertices, faces, count, face_label)
        keep_label = int(np.argmax(faces_per_label))
        big = (faces_per_label > 0) & (np.abs(piece_volume) > min_volume)
        big[keep_label] = False
        dropped = int(big.sum())
        faces = faces[face_label == keep_label]
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    new_index = np.cumsum(used) - 1  # old vertex index -> index among the used ones
    return vertices[used], new_index[faces], dropped


def without_crumbs(parts: list[trimesh.Trimesh], min_area_fraction: float) -> trimesh.Trimesh:
    """The parts (non-empty list, e.g. `mesh.split(only_watertight=False)`) whose area is at least
    `min_area_fraction` of the largest one's, as one mesh (the part itself when one is left).

    Unlike `largest_component` every real piece is kept: for surfaces that may legitimately come
    in several pieces (Poisson cutting a thin bar), where only marching-cubes crumbs are noise.
    """
    largest = max(part.area for part in parts)
    kept = [part for part in parts if part.area >= min_area_fraction * largest]
    return kept[0] if len(kept) == 1 else trimesh.util.concatenate(kept)


def wind_cavities_inward(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """`mesh` (closed, each body wound outward, e.g. after `fix_normals(multibody=True)`) with every
    body that lies inside an odd number of the others wound inward: a cavity in the glass, not a
    second solid. Screened Poisson makes such bodies where PNet's points trace a tunnel or pocket the
    masks cannot see (test scene 33: its pieces lie on the object's hidden tunnel; wound outward they
    cost CDN-mean 2.2 degrees, and rays would enter the glass twice). Returns `mesh` itself when no
    body is turned, else a new mesh (bodies in their order)."""
    if mesh.body_count < 2:
        return mesh
    bodies = mesh.split(only_watertight=False)
    # a host encloses more volume and its box holds the body's (area need not grow: a wrinkled
    # pocket may have more of it than the smooth shell around it)
    volumes = [abs(float(body.volume)) for body in bodies]

    def encloses(j: int, i: int) -> bool:
        outer, inner = bodies[j], bodies[i]
        if not (volumes[j] > volumes[i] and outer.is_watertight and (inner.bounds[0] >= outer.bounds[0]).all()
                and (inner.bounds[1] <= outer.bounds[1]).all()):
            return False
        # bodies do not touch (they are components), so one point decides; the majority of up to 16
        # vertices in case one sits on the other's surface
        probe = np.asarray(inner.vertices)[:: max(1, len(inner.vertices) // 16)][:16]
        return bool(outer.contains(probe).mean() > 0.5)

    turned = [i for i, body in enumerate(bodies)
              if body.volume > 0 and sum(encloses(j, i) for j in range(len(bodies)) if j != i) % 2]
    for i in turned:
        bodies[i].invert()
    return trimesh.util.concatenate(bodies) if turned else mesh


# ---------------------------------------------------------------------------------------------
# Smoothing and subdivision
# ---------------------------------------------------------------------------------------------

def taubin_smooth(vertices: np.ndarray, faces: np.ndarray, passes: int) -> np.ndarray:
    """Taubin smoothing with uniform (umbrella) weights: `passes` alternating passes, a lambda
    (TAUBIN_LAMBDA) pass first, then a mu (TAUBIN_MU) one, ... (trimesh's count: 2 passes make one
    lambda/mu step). Moves vertices only, so the topology (watertightness) is kept.

    vertices (N, 3) float64, every vertex used by a face (trimesh sizes its Laplacian by the
    largest index used); faces (M, 3) int. Returns new vertices (N, 3) float64.
    """
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), faces, process=False, validate=False)
    trimesh.smoothing.filter_taubin(mesh, lamb=TAUBIN_LAMBDA, nu=-TAUBIN_MU, iterations=int(passes))
    return np.asarray(mesh.vertices, np.float64)


def subdivide_ls3_loop(vertices: np.ndarray, faces: np.ndarray, iterations: int,
                       threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """MeshLab LS3 Loop subdivision (Boye et al. 2010), via pymeshlab.

    vertices (N, 3) float64, faces (M, 3) int, closed and outward. threshold: fraction of the
    bounding-box diagonal; edges longer than it are split, `iterations` times. Returns vertices
    (K, 3) float64 and faces (F, 3) int64.
    """
    import pymeshlab

    ms = _meshset(vertices, faces)

    def subdivide() -> None:
        ms.meshing_surface_subdivision_ls3_loop(
            loopweight="Loop", iterations=int(iterations), threshold=pymeshlab.PercentageValue(100.0 * threshold))

    def finite() -> bool:
        return bool(np.isfinite(ms.current_mesh().vertex_matrix()).all())

    try:
        subdivide()
        if finite():
            m = ms.current_mesh()
            return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
    except pymeshlab.PyMeshLabException:
        pass
    # Marching cubes can pinch two sheets of the surface along an edge or at a vertex where the
    # surface is one voxel thin; LS3 needs a 2-manifold (it raises, or returns NaN positions).
    # Split the pinches, close what opens, and subdivide again.
    ms = _meshset(vertices, faces)
    repair_pinches(ms)
    repaired = ms.current_mesh()
    repaired_v, repaired_f = repaired.vertex_matrix().copy(), repaired.face_matrix().astype(np.int64)
    try:
        subdivide()
        ms.meshing_remove_unreferenced_vertices()
        if finite():
            m = ms.current_mesh()
            return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
    except pymeshlab.PyMeshLabException:
        pass
    # LS3 can still fail on a repaired surface; smooth it without subdividing instead (Taubin: no
    # shrinkage), rather than hand on a broken surface.
    return taubin_smooth(repaired_v.astype(np.float64), repaired_f, 4 * int(iterations)), repaired_f


# ---------------------------------------------------------------------------------------------
# Manifold repair (pymeshlab)
# ---------------------------------------------------------------------------------------------

def _meshset(vertices: np.ndarray, faces: np.ndarray):
    """A pymeshlab MeshSet holding the mesh (vertices (N, 3), faces (M, 3))."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(vertices, np.float64),
                               face_matrix=np.ascontiguousarray(faces, np.int32)))
    return ms


def repair_pinches(ms) -> None:
    """Split the current mesh of pymeshlab MeshSet `ms` where two sheets touch along an edge or at
    a vertex (marching cubes makes these where a surface is one cell thin), and close what opens."""
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_null_faces()
    ms.meshing_repair_non_manifold_edges(method="Split Vertices")
    ms.meshing_repair_non_manifold_vertices()
    ms.meshing_close_holes()
    ms.meshing_remove_unreferenced_vertices()


def merged_and_repaired(ms) -> trimesh.Trimesh:
    """The current mesh of pymeshlab MeshSet `ms`, a marching-cubes surface, as a manifold trimesh."""
    import pymeshlab

    # Marching cubes leaves vertices a hair apart where the surface passes near a grid corner.
    # Merged here (1e-6 of the box diagonal) and the pinches that makes split, so no later rounding
    # (the move back to the capture's frame, a PLY reader merging equal positions) can pinch the
    # written mesh into a non-manifold one.
    ms.meshing_merge_close_vertices(threshold=pymeshlab.PercentageValue(1e-4))
    repair_pinches(ms)
    m = ms.current_mesh()  # filters that generate a surface (Poisson) add it as the current layer
    # process=True merges duplicated vertices, so shared edges are recognized
    return trimesh.Trimesh(vertices=m.vertex_matrix(), faces=m.face_matrix(), process=True)


def manifold_mesh(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    """A marching-cubes surface (vertices (N, 3), faces (M, 3)) merged and repaired into a
    manifold trimesh (see `merged_and_repaired`)."""
    return merged_and_repaired(_meshset(vertices, faces))
