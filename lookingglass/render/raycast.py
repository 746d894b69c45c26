"""Ray casting against a triangle mesh with Embree (embreex, the backend trimesh uses).

One scene per mesh; batched first-hit queries return distance, triangle, barycentrics, the hit
point and the interpolated (smooth) normal. Everything is numpy float32/float64 (Embree is
single precision); callers convert to torch where they need gradients.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh


@dataclass
class Hits:
    """First hits of N rays. hit: (N,) bool; t: (N,) distance (inf on a miss); face: (N,) int
    (-1 on a miss); bary: (N, 3) barycentric weights of the face's vertices; point: (N, 3);
    normal: (N, 3) unit smooth (vertex-interpolated) normal, outward; face_normal: (N, 3) unit
    geometric normal, outward. Rows of misses are zero apart from t and face."""

    hit: np.ndarray
    t: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    face_normal: np.ndarray


# embreex copies the arrays it is given into Embree's buffers one element at a time through Python
# indexing: a numpy scalar made for every coordinate, and a row view for every face. Python objects
# that index cheaply give Embree the same float32 triangles in ~1/4 of the time (17 800 vertices,
# 35 000 faces: 64 -> 15 ms; the refine stage builds ~200 scenes of one face set). The faces' tuples
# take ~9 ms to make and ~180 bytes a face, so the last few face sets' are kept, up to a bound; a
# larger mesh (a fine hull's marching cubes) is handed over as plain arrays, as is every mesh where
# an embreex that reads its arrays another way refuses the objects.
_FACE_TUPLES: list[tuple[np.ndarray, np.ndarray]] = []
_FACE_TUPLES_KEPT = 3
_FACE_TUPLES_MAX_FACES = 400_000  # kept in all (~70 MB); also the largest mesh built from Python objects
_FACE_TUPLES_LOCK = threading.Lock()
_OBJECTS_REFUSED = False  # set once this embreex has refused them


def _face_tuples(faces: np.ndarray) -> np.ndarray:
    """(F,) object array of each face's three int vertex indices as a tuple (embreex reads
    `indices[i][k]`), kept for the last few face sets."""
    faces = np.asarray(faces, dtype=np.int32)
    with _FACE_TUPLES_LOCK:
        for known, tuples in _FACE_TUPLES:
            if known.shape == faces.shape and np.array_equal(known, faces):
                return tuples
    tuples = np.empty(len(faces), dtype=object)
    tuples[:] = list(zip(*faces.T.tolist()))
    with _FACE_TUPLES_LOCK:
        _FACE_TUPLES.insert(0, (faces.copy(), tuples))
        while len(_FACE_TUPLES) > _FACE_TUPLES_KEPT or sum(len(f) for f, _ in _FACE_TUPLES) > _FACE_TUPLES_MAX_FACES:
            _FACE_TUPLES.pop()
    return tuples


def _embree_scene(vertices: np.ndarray, faces: np.ndarray) -> rtcore_scene.EmbreeScene:
    """An Embree scene of the indexed triangles (shared vertices, not a triangle soup: the same float32
    triangles in ~0.55 x the time), from Python objects where they pay (above)."""
    global _OBJECTS_REFUSED
    v32, f32 = vertices.astype(np.float32), faces.astype(np.int32)
    if not _OBJECTS_REFUSED and 0 < len(f32) <= _FACE_TUPLES_MAX_FACES:
        scene = rtcore_scene.EmbreeScene()
        try:
            TriangleMesh(scene, v32.astype(object), _face_tuples(f32))
            return scene
        except (TypeError, ValueError):
            _OBJECTS_REFUSED = True
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, v32, f32)
    return scene


def _extents(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """trimesh's `extents` (the box of the vertices the faces use), without its cache's hashing of the
    arrays (~5 ms a scene: 1.1 s of the refine stage's ~200); zeros for a mesh without faces."""
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.reshape(-1)] = True
    if not used.any():
        return np.zeros(3)
    kept = vertices[used]
    return np.ptp(np.array([kept.min(axis=0), kept.max(axis=0)]), axis=0)


class RayCaster:
    """Embree scene of one mesh (any frame). Build once, query many times."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.mesh = mesh
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        self._scene = _embree_scene(self.vertices, self.faces)
        # Secondary rays start this far along their direction so they don't re-hit their origin.
        self.epsilon = 1e-5 * float(np.linalg.norm(_extents(self.vertices, self.faces)))

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray) -> "RayCaster":
        """The scene of a mesh given as arrays (kept as given: no merging or reordering)."""
        return cls(trimesh.Trimesh(vertices, faces, process=False))

    # computed on first use: a third of the build's time, and the refine stage's differentiable
    # casts (intersect_raw, dozens of fresh scenes a run) never read them
    @cached_property
    def vertex_normals(self) -> np.ndarray:
        return np.asarray(self.mesh.vertex_normals, dtype=np.float64)

    @cached_property
    def face_normals(self) -> np.ndarray:
        return np.asarray(self.mesh.face_normals, dtype=np.float64)

    def intersect(self, origins: np.ndarray, directions: np.ndarray, offset: bool = False) -> Hits:
        """First hit of each ray. origins, directions: (N, 3); directions need not be unit but
        `t` is then in units of |direction|. With offset=True the origins are moved by
        `epsilon` along the (unit) direction first and t is measured from the moved origin."""
        o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float32).reshape(-1, 3)
        if offset:
            o = (o + self.epsilon * d).astype(np.float32)
        n = len(o)
        if n == 0 or len(self.faces) == 0:  # no rays, or nothing to hit
            z = np.zeros((n, 3))
            return Hits(np.zeros(n, bool), np.full(n, np.inf), np.full(n, -1, np.int64), z, z, z, z)
        res = self._scene.run(o, d, output=1)
        face = res["primID"].astype(np.int64)
        hit = res["geomID"] != -1
        face = np.where(hit, face, -1)
        t = np.where(hit, res["tfar"].astype(np.float64), np.inf)
        u = res["u"].astype(np.float64)
        v = res["v"].astype(np.float64)
        bary = np.stack([1 - u - v, u, v], axis=-1) * hit[:, None]
        fi = np.where(hit, face, 0)
        tri = self.faces[fi]  # (N, 3)
        point = np.einsum("nk,nkj->nj", bary, self.vertices[tri])
        normal = np.einsum("nk,nkj->nj", bary, self.vertex_normals[tri])
        normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
        face_normal = self.face_normals[fi] * hit[:, None]
        return Hits(hit, t, face, bary, point, normal * hit[:, None], face_normal)

    def intersect_raw(self, origins: np.ndarray, directions: np.ndarray, offset: bool = False,
                      threads: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """First hits with no post-processing, for the renderer's hot loop (`intersect` spends
        ~4x Embree's own time building float64 points and normals).

        origins, directions: (N, 3), converted to float32 exactly as in `intersect`; offset as
        there. The batch is split over `threads` threads (Embree releases the GIL).
        Returns t (N,) float32 (inf on a miss), face (N,) int64 (-1 on a miss) and the
        barycentric weights u, v (N,) float32 of the face's 2nd and 3rd vertices.
        """
        o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float32).reshape(-1, 3)
        if offset:
            o = (o + self.epsilon * d).astype(np.float32)
        n = len(o)
        t = np.full(n, np.inf, np.float32)
        face = np.full(n, -1, np.int64)
        u = np.zeros(n, np.float32)
        v = np.zeros(n, np.float32)

        def run(sl: slice) -> None:
            res = self._scene.run(o[sl], d[sl], output=1)
            hit = res["geomID"] != -1
            t[sl] = np.where(hit, res["tfar"], np.inf)
            face[sl] = np.where(hit, res["primID"], -1)
            u[sl], v[sl] = res["u"], res["v"]

        parts = max(1, min(int(threads), n // 65536))
        bounds = np.linspace(0, n, parts + 1).astype(int)
        slices = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
        if parts == 1:
            run(slices[0])
        else:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(parts) as pool:
                list(pool.map(run, slices))
        return t, face, u, v

    def hit_mask(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(N,) bool: does each ray hit the mesh at all."""
        o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
        d = np.ascontiguousarray(directions, dtype=np.float32).reshape(-1, 3)
        if len(o) == 0:
            return np.zeros(0, bool)
        return self._scene.run(o, d) != -1


def object_masks(mesh: trimesh.Trimesh, cameras, samples_per_axis: int = 1) -> np.ndarray:
    """Binary silhouettes of `mesh` seen by `cameras` (lookingglass.physics.camera.Cameras).

    With samples_per_axis = s > 1 each pixel is tested at s x s sub-pixel positions and counts as
    object when at least half of them hit (a box-filtered coverage thresholded at 0.5).
    Returns (V, H, W) bool.
    """
    import torch

    caster = RayCaster(mesh)
    cams = cameras.to(dtype=torch.float64, device="cpu")
    s = int(samples_per_axis)
    coverage = np.zeros((cams.num_views, cams.height, cams.width))
    for i in range(s):
        for j in range(s):
            origins, dirs = cams.pixel_rays(subpixel=((j + 0.5) / s, (i + 0.5) / s))
            hit = caster.hit_mask(origins.reshape(-1, 3).numpy(), dirs.reshape(-1, 3).numpy())
            coverage += hit.reshape(coverage.shape)
    return coverage / (s * s) >= 0.5
