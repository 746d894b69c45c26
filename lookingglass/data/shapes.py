"""Random procedural shapes for synthetic training data, normalized to the unit sphere.

In the spirit of the paper's dataset (Li et al. 2018, Xu et al. 2018): random combinations of
1-5 primitives -- ellipsoids, rounded boxes, cylinders, capsules, tori (handles), thin plates and
rods (thin parts) -- with random sizes and rotations, fused by a smooth union of their signed
distance fields, optionally carved by a smooth subtraction (dents, grooves, through-holes), and
perturbed by smooth low-frequency noise. The field is sampled on a grid fitted to the shape and
meshed by marching cubes. The paper fuses 75 depth maps with Poisson reconstruction to get rid of
inner surfaces where primitives intersect; here the union is taken in the distance field, which has
no inner surfaces to begin with, and enclosed cavities and detached pieces are removed on the
voxel grid, so the result is ONE closed outer surface.

Frame: world coordinates, y up, arbitrary orientation (the primitives are randomly rotated).
The returned mesh is centred at its bounding-box centre and scaled so max |p| = 1 (DESIGN.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymeshlab
import trimesh
from scipy import ndimage
from scipy.sparse import coo_matrix
from skimage import measure

from ..meshes import TAUBIN_LAMBDA, TAUBIN_MU, largest_component, orient_outward
from .shape_config import CARVE_KINDS, KINDS, ShapeConfig  # noqa: F401 (re-exported)


@dataclass
class Primitive:
    """One SDF primitive. world = center + rotation @ local; local = (world - center) @ rotation.

    kind: one of KINDS (carving primitives use "ellipsoid" and "capsule").
    params: kind-specific sizes in the local frame (see `_primitive_sdf`).
    half_extents: (3,) local-frame half sizes of its bounding box (used for the grid and placement).
    """

    kind: str
    center: np.ndarray
    rotation: np.ndarray
    params: dict
    half_extents: np.ndarray
    blend: float

    def world_half_box(self) -> np.ndarray:
        """(3,) half size of the world axis-aligned bounding box."""
        return np.abs(self.rotation) @ self.half_extents


# ---------------------------------------------------------------------------------------------
# signed distance functions (local frame, on broadcast coordinate arrays, float32)
# ---------------------------------------------------------------------------------------------

def _matmul3(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """a (..., 3) @ m (3, K) by broadcasting. numpy's @ calls BLAS, whose rounding can depend on
    the number of threads; this keeps every shape bit-identical for its seed on any setting."""
    return a[..., 0:1] * m[0] + a[..., 1:2] * m[1] + a[..., 2:3] * m[2]


def _length(*xs: np.ndarray) -> np.ndarray:
    return np.sqrt(sum(x * x for x in xs))


def _primitive_sdf(kind: str, x: np.ndarray, y: np.ndarray, z: np.ndarray, p: dict) -> np.ndarray:
    """Signed distance (negative inside) of a primitive at local coordinates x, y, z (same shape).

    Exact for box, cylinder, capsule and torus; the ellipsoid uses the usual first-order bound
    k0 (k0 - 1) / k1, which is exact on the surface and good near it (all marching cubes needs).
    Axis of cylinders, capsules and tori: local y.
    """
    if kind == "ellipsoid":
        r = p["radii"]
        k0 = _length(x / r[0], y / r[1], z / r[2])
        k1 = _length(x / r[0] ** 2, y / r[1] ** 2, z / r[2] ** 2)
        # at the very centre k0 = k1 = 0: the depth there is the smallest radius
        return np.where(k1 > 1e-9, k0 * (k0 - 1.0) / np.maximum(k1, 1e-9), -float(np.min(r)))
    if kind in ("box", "plate"):
        b, rr = p["half"], p["rounding"]
        qx, qy, qz = np.abs(x) - (b[0] - rr), np.abs(y) - (b[1] - rr), np.abs(z) - (b[2] - rr)
        outside = _length(np.maximum(qx, 0), np.maximum(qy, 0), np.maximum(qz, 0))
        inside = np.minimum(np.maximum(np.maximum(qx, qy), qz), 0)
        return outside + inside - rr
    if kind == "cylinder":
        rho, h, rr = p["radius"], p["half_height"], p["rounding"]
        dx = _length(x, z) - (rho - rr)
        dy = np.abs(y) - (h - rr)
        return np.minimum(np.maximum(dx, dy), 0) + _length(np.maximum(dx, 0), np.maximum(dy, 0)) - rr
    if kind in ("capsule", "rod"):
        qy = np.maximum(np.abs(y) - p["half_length"], 0)
        return _length(x, qy, z) - p["radius"]
    if kind == "torus":
        q = _length(x, z) - p["major"]
        return _length(q, y) - p["minor"]
    raise ValueError(f"unknown primitive kind '{kind}'")


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (smooth union) with blend radius k; equals min where |a-b| >= k,
    and never exceeds min(a, b) by more than k/4 below it."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - (h * h) * (k * 0.25)


# ---------------------------------------------------------------------------------------------
# sampling the primitives
# ---------------------------------------------------------------------------------------------

def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation (3, 3) from a normalized Gaussian quaternion."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _sample_params(kind: str, rng: np.random.Generator, size: tuple[float, float],
                   thin: tuple[float, float]) -> tuple[dict, np.ndarray]:
    """Random sizes for a primitive kind: (params, local half extents (3,))."""
    lo, hi = size
    u = lambda a=lo, b=hi: float(rng.uniform(a, b))  # noqa: E731
    if kind == "ellipsoid":
        r = np.array([u(), u(), u()])
        return {"radii": r}, r
    if kind == "box":
        b = np.array([u(), u(), u()])
        return {"half": b, "rounding": u(0.05, 0.5) * b.min()}, b
    if kind == "plate":
        t = u(*thin)
        b = np.array([u(), t, u()])
        return {"half": b, "rounding": 0.95 * t}, b
    if kind == "cylinder":
        rho, h = u(lo, 0.8 * hi), u()
        return {"radius": rho, "half_height": h, "rounding": u(0.02, 0.4) * min(rho, h)}, np.array([rho, h, rho])
    if kind == "capsule":
        rho, h = u(0.5 * lo, 0.6 * hi), u()
        return {"radius": rho, "half_length": h}, np.array([rho, h + rho, rho])
    if kind == "rod":
        rho, h = u(*thin), u(0.5 * hi, 1.1 * hi)
        return {"radius": rho, "half_length": h}, np.array([rho, h + rho, rho])
    if kind == "torus":
        major = u(max(lo, 0.25), hi)
        minor = u(0.12, 0.35) * major
        minor = max(minor, thin[0])
        return {"major": major, "minor": minor}, np.array([major + minor, minor, major + minor])
    raise ValueError(f"unknown primitive kind '{kind}'")


def _surface_point(prim: Primitive, rng: np.random.Generator, depth: tuple[float, float]) -> np.ndarray:
    """A point near the primitive's surface: on the ellipsoid inscribed in its local bounding box,
    scaled by U(depth) towards the centre (depth < 1 lands inside, > 1 outside). World frame (3,)."""
    local = _random_unit(rng) * prim.half_extents * rng.uniform(*depth)
    return prim.center + prim.rotation @ local


def sample_primitives(rng: np.random.Generator, config: ShapeConfig = ShapeConfig()
                      ) -> tuple[list[Primitive], list[Primitive]]:
    """Draw the additive primitives and the carving (subtracted) ones.

    The first primitive (the body) sits near the origin; each later one is attached at a point near
    the surface of a random earlier one, so parts overlap rather than float. Carvers are placed near
    the body's surface (dents, grooves) or through a part's centre along a random axis (holes).
    """
    kinds = list(config.kind_weights)
    w = np.array([config.kind_weights[k] for k in kinds], dtype=float)
    w /= w.sum()
    n = int(rng.integers(config.num_primitives[0], config.num_primitives[1] + 1))
    adds: list[Primitive] = []
    for i in range(n):
        kind = kinds[int(rng.choice(len(kinds), p=w))]
        size = config.first_size if i == 0 else config.part_size
        params, half = _sample_params(kind, rng, size, config.thin_half_thickness)
        if i == 0:
            center = rng.uniform(-0.05, 0.05, 3)
        else:
            center = _surface_point(adds[int(rng.integers(len(adds)))], rng, (0.5, 1.0))
        adds.append(Primitive(kind, center, _random_rotation(rng), params, half, float(rng.uniform(*config.blend))))

    carves: list[Primitive] = []
    if rng.random() < config.p_carve:
        for _ in range(int(rng.integers(1, config.max_carves + 1))):
            style = CARVE_KINDS[int(rng.integers(len(CARVE_KINDS)))]
            target = adds[int(rng.integers(len(adds)))]
            scale = float(np.min(target.half_extents[target.half_extents > 0.1], initial=0.3))
            rot = _random_rotation(rng)
            if style == "dent":  # a spherical/ellipsoidal scoop into the surface
                kind, (params, half) = "ellipsoid", _sample_params("ellipsoid", rng, (0.3 * scale, 0.8 * scale), (0, 0))
                center = _surface_point(target, rng, (1.0, 1.25))
            elif style == "groove":  # a capsule grazing the surface
                rho = float(rng.uniform(0.1, 0.3)) * scale
                h = float(rng.uniform(0.5, 1.2)) * scale
                kind, params, half = "capsule", {"radius": rho, "half_length": h}, np.array([rho, h + rho, rho])
                center = _surface_point(target, rng, (0.95, 1.1))
            else:  # "hole": a capsule through the part, longer than the part is wide
                rho = float(rng.uniform(0.12, 0.35)) * scale
                h = float(np.linalg.norm(target.half_extents)) * 1.5
                kind, params, half = "capsule", {"radius": rho, "half_length": h}, np.array([rho, h + rho, rho])
                center = target.center + target.rotation @ (rng.uniform(-0.3, 0.3, 3) * target.half_extents)
            carves.append(Primitive(kind, center, rot, params, half, float(rng.uniform(*config.blend))))
    return adds, carves


# ---------------------------------------------------------------------------------------------
# the distance field on a grid
# ---------------------------------------------------------------------------------------------

@dataclass
class _Noise:
    """n(p) = sum_t a_t sin(w_t . p + phi_t); |n| <= bound everywhere."""

    amplitude: np.ndarray  # (T,)
    freq: np.ndarray  # (T, 3)
    phase: np.ndarray  # (T,)

    @property
    def bound(self) -> float:
        return float(np.abs(self.amplitude).sum())

    def on_grid(self, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> np.ndarray:
        """Noise on the grid xs x ys x zs, (nx, ny, nz) float32.

        Separable: sin(w.p + phi) = Im(e^{i phi} e^{i wx x} e^{i wy y} e^{i wz z}), so the sum over
        terms is one complex matrix product instead of T sines per voxel."""
        out = np.zeros((len(xs), len(ys), len(zs)), dtype=np.float32)
        for a, w, phase in zip(self.amplitude, self.freq, self.phase):
            ex = a * np.exp(1j * (w[0] * xs + phase))
            yz = np.exp(1j * w[1] * ys)[:, None] * np.exp(1j * w[2] * zs)[None, :]
            # Im(ex yz) = Re(ex) Im(yz) + Im(ex) Re(yz): two real outer products. (Deliberately not a
            # BLAS matrix product: its rounding depends on the thread count, and the shapes must
            # be identical for a seed on any machine setting.)
            out += ex.real.astype(np.float32)[:, None, None] * yz.imag.astype(np.float32)[None]
            out += ex.imag.astype(np.float32)[:, None, None] * yz.real.astype(np.float32)[None]
        return out

    def at(self, points: np.ndarray) -> np.ndarray:
        """Noise at world points (N, 3) -> (N,) float64."""
        return (np.sin(_matmul3(points, self.freq.T) + self.phase) * self.amplitude).sum(axis=-1)


def _sample_noise(rng: np.random.Generator, config: ShapeConfig) -> _Noise:
    t = config.noise_terms
    std = rng.uniform(*config.noise_amplitude)
    f = rng.uniform(*config.noise_frequency)
    # amplitude sqrt(2/T) * std per term: the sum of T random-phase sines has standard deviation std
    return _Noise(np.full(t, std * math.sqrt(2.0 / t)), rng.normal(size=(t, 3)) * f, rng.uniform(0, 2 * math.pi, t))


def _axis_slice(axis: np.ndarray, lo: float, hi: float) -> slice:
    return slice(int(np.searchsorted(axis, lo, "left")), int(np.searchsorted(axis, hi, "right")))


def sdf_grid(adds: list[Primitive], carves: list[Primitive], noise: _Noise, resolution: int
             ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The fused signed distance field sampled on a cubic-voxel grid fitted to the shape.

    Returns the field (nx, ny, nz) float32 (negative inside) and the grid axes (xs, ys, zs), world.
    Each primitive is evaluated only inside its own bounding box grown by a margin m > 1.25 k +
    noise bound: outside it, its distance exceeds m, where the smooth union (and subtraction) either
    equals the running field exactly or keeps its sign -- so the zero set is the same as evaluating
    everywhere, at a fraction of the cost.
    """
    lo = np.min([p.center - p.world_half_box() for p in adds], axis=0)
    hi = np.max([p.center + p.world_half_box() for p in adds], axis=0)
    h = float((hi - lo).max()) / (resolution - 1)
    pad = noise.bound + 3 * h
    lo, hi = lo - pad, hi + pad
    axes = tuple(np.arange(lo[i], hi[i] + h, h, dtype=np.float64) for i in range(3))
    xs, ys, zs = axes
    field_ = np.full((len(xs), len(ys), len(zs)), 1e3, dtype=np.float32)

    def evaluate(prim: Primitive) -> tuple[tuple[slice, slice, slice], np.ndarray] | None:
        m = 1.5 * prim.blend + noise.bound + 2 * h
        half = prim.world_half_box() + m
        sl = tuple(_axis_slice(axes[i], prim.center[i] - half[i], prim.center[i] + half[i]) for i in range(3))
        if any(s.stop <= s.start for s in sl):
            return None
        # local = (world - center) @ R, built by broadcasting the three 1D axes (no (N, 3) array)
        d = [(axes[i][sl[i]] - prim.center[i]).astype(np.float32) for i in range(3)]
        dx, dy, dz = d[0][:, None, None], d[1][None, :, None], d[2][None, None, :]
        R = prim.rotation.astype(np.float32)
        local = [dx * R[0, k] + dy * R[1, k] + dz * R[2, k] for k in range(3)]
        return sl, _primitive_sdf(prim.kind, *local, prim.params).astype(np.float32)

    for prim in adds:
        out = evaluate(prim)
        if out is not None:
            sl, d = out
            field_[sl] = _smin(field_[sl], d, prim.blend)
    for prim in carves:  # smooth subtraction: max(f, -d) smoothed = -smin(-f, d)
        out = evaluate(prim)
        if out is not None:
            sl, d = out
            field_[sl] = -_smin(-field_[sl], d, prim.blend)
    field_ += noise.on_grid(xs, ys, zs)
    return field_, axes


def sdf_points(adds: list[Primitive], carves: list[Primitive], noise: _Noise, points: np.ndarray) -> np.ndarray:
    """The same fused field as `sdf_grid` (near its zero set), at world points (N, 3) -> (N,) float64.

    Every primitive is evaluated at every point (no bounding-box culling); used to project mesh
    vertices onto the exact zero set and by tests."""
    points = np.asarray(points, dtype=np.float64)
    out = np.full(len(points), 1e3)
    for i, prim in enumerate(adds + carves):
        local = _matmul3(points - prim.center, prim.rotation)
        d = _primitive_sdf(prim.kind, local[:, 0], local[:, 1], local[:, 2], prim.params)
        out = _smin(out, d, prim.blend) if i < len(adds) else -_smin(-out, d, prim.blend)
    return out + noise.at(points)


def _keep_single_solid(field_: np.ndarray, h: float) -> np.ndarray | None:
    """Keep the largest 26-connected inside region and fill its enclosed cavities.

    Voxels of other pieces are pushed outside (+h/2), cavity voxels inside (-h/2). With
    26-connectivity no discarded voxel is a neighbour of a kept one, so marching cubes sees exactly
    the original values around the kept surface and the outer zero set is unchanged. Returns None
    when nothing is inside. The border layer is forced outside, so the surface is closed."""
    inside = field_ < 0
    _set_border(inside, False)
    labels, n = ndimage.label(inside, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return None
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    keep = labels == int(sizes.argmax())
    # cavities: outside voxels (6-connected, the dual of 26) not connected to the border
    outside, _ = ndimage.label(~keep)
    solid = outside != outside[0, 0, 0]
    out = np.where(solid, np.minimum(field_, -0.5 * h), np.maximum(field_, 0.5 * h)).astype(np.float32)
    out[keep] = field_[keep]  # the kept region's own values are untouched
    _set_border(out, h)
    return out


def _set_border(a: np.ndarray, value) -> None:
    a[0, :, :] = a[-1, :, :] = a[:, 0, :] = a[:, -1, :] = a[:, :, 0] = a[:, :, -1] = value


def _marching_cubes(solid: np.ndarray, axes) -> tuple[np.ndarray, np.ndarray]:
    """Zero set of a cleaned field: vertices (V, 3) float64 world, faces (F, 3) int64."""
    xs, ys, zs = axes
    h = float(xs[1] - xs[0])
    verts, faces, _, _ = measure.marching_cubes(solid, 0.0, spacing=(h, h, h), allow_degenerate=False)
    return verts.astype(np.float64) + np.array([xs[0], ys[0], zs[0]]), faces.astype(np.int64)


def _choose_resolution(adds, carves, noise, config: ShapeConfig) -> int | None:
    """Grid resolution giving about config.target_faces faces, from a coarse pre-pass.

    Marching-cubes face count scales with (surface area) / h^2, i.e. with resolution^2 for a fixed
    shape, so one coarse count predicts it. None if the coarse pass finds nothing inside."""
    rc = config.coarse_resolution
    coarse, axes = sdf_grid(adds, carves, noise, rc)
    solid = _keep_single_solid(coarse, float(axes[0][1] - axes[0][0]))
    if solid is None:
        return None
    _, faces = _marching_cubes(solid, axes)
    if len(faces) == 0:
        return None
    r = rc * math.sqrt(config.target_faces / len(faces))
    return int(np.clip(round(r), *config.resolution))


def _project_to_zero_set(vertices: np.ndarray, field_at, h: float, iterations: int) -> np.ndarray:
    """Newton steps p <- p - f(p) grad f / |grad f|^2 onto the exact zero set of the field.

    Marching cubes interpolates the field linearly along grid edges, which leaves vertices off the
    surface by up to ~10% of a voxel and tilts facets by ~10 degrees on average; projecting onto
    the analytic field brings facet normals to ~1 degree of the field's gradient. Gradients by
    central differences; steps are clamped to h/2 so creases (where the gradient jumps) stay put."""
    v = vertices.copy()
    eps = 1e-4 * h
    offsets = np.eye(3) * eps
    for _ in range(iterations):
        f = field_at(v)
        g = np.stack([field_at(v + offsets[i]) - field_at(v - offsets[i]) for i in range(3)], axis=1) / (2 * eps)
        step = (f / np.maximum((g * g).sum(axis=1), 1e-12))[:, None] * g
        length = np.linalg.norm(step, axis=1, keepdims=True)
        v -= step * np.minimum(1.0, 0.5 * h / np.maximum(length, 1e-300))
    return v


def self_intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Indices of faces that intersect another face of the mesh (pymeshlab's exact test)."""
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=faces.astype(np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    return np.flatnonzero(ms.current_mesh().face_selection_array())


def _undo_self_intersections(verts: np.ndarray, safe: np.ndarray, faces: np.ndarray,
                             rounds: int = 3) -> np.ndarray | None:
    """Put the vertices around self-intersecting faces back to their `safe` positions.

    Smoothing and projection move vertices by up to ~h/2; where two sheets of the surface are
    closer than that (narrow gaps between parts, sharp creases) a few faces (~1 shape in 40) can
    pass through each other. Marching cubes itself does not self-intersect, so reverting the
    vertices of the offending faces and a ring around them, growing the ring each round, removes
    them; if that fails, all vertices are reverted. None if even `safe` self-intersects (possible
    only after simplification): the caller redraws the shape."""
    bad = self_intersecting_faces(verts, faces)
    if len(bad) == 0:
        return verts
    n = len(verts)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    adjacency = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adjacency = adjacency + adjacency.T
    verts = verts.copy()
    for ring in range(1, rounds + 1):
        mask = np.zeros(n, dtype=bool)
        mask[faces[bad].ravel()] = True
        for _ in range(ring):
            mask |= adjacency @ mask > 0
        verts[mask] = safe[mask]
        bad = self_intersecting_faces(verts, faces)
        if len(bad) == 0:
            return verts
    return safe.copy() if len(self_intersecting_faces(safe, faces)) == 0 else None


def _mesh_field(field_: np.ndarray, axes, field_at, config: ShapeConfig) -> trimesh.Trimesh | None:
    """Clean the field to one solid, mesh it, simplify if needed, smooth, project onto the exact
    zero set of `field_at` (world points (N, 3) -> (N,)). None if degenerate."""
    h = float(axes[0][1] - axes[0][0])
    solid = _keep_single_solid(field_, h)
    if solid is None:
        return None
    verts, faces, _ = largest_component(*_marching_cubes(solid, axes))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts, face_matrix=faces.astype(np.int32)))
    if len(faces) > config.max_faces:
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=config.target_faces, preservetopology=True,
                                                    preservenormal=True, qualitythr=0.5, autoclean=True)
    safe = ms.current_mesh().vertex_matrix().astype(np.float64)  # marching cubes: no self-intersections
    if config.taubin_steps > 0:  # evens out the marching-cubes triangle pattern before projecting
        # MeshLab's Taubin, not meshes.taubin_smooth: the mesh is already in MeshLab here, and the
        # two differ in rounding (~1e-9), which would change every shape a seed stands for.
        ms.apply_coord_taubin_smoothing(lambda_=TAUBIN_LAMBDA, mu=TAUBIN_MU, stepsmoothnum=config.taubin_steps)
    m = ms.current_mesh()
    verts, faces = m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
    if config.projection_steps > 0:
        verts = _project_to_zero_set(verts, field_at, h, config.projection_steps)
    verts = _undo_self_intersections(verts, safe, faces)
    if verts is None:
        return None
    # outward normals: the marching-cubes winding depends on the field's sign convention
    mesh = trimesh.Trimesh(verts, orient_outward(verts, faces), process=False)
    if len(mesh.faces) < config.min_faces or not mesh.is_watertight:
        return None
    return mesh


def normalize_to_unit_sphere(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Centre at the bounding-box centre and scale so the farthest vertex is at distance 1 (in place)."""
    v = mesh.vertices - (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
    v /= np.sqrt((v * v).sum(axis=1)).max()
    mesh.vertices = v
    return mesh


def random_shape(seed: int, config: ShapeConfig = ShapeConfig()) -> trimesh.Trimesh:
    """A random closed shape: one watertight outer surface, outward normals, unit-sphere normalized.

    seed: any int; the same seed and config give identical vertices and faces.
    Returns a trimesh.Trimesh in world coordinates (float64 vertices (V, 3), int64 faces (F, 3)),
    centred at its bounding-box centre with max |p| = 1.
    A degenerate draw (empty, too small, broken) is redrawn from the same generator, so the result
    is still a function of the seed.
    """
    rng = np.random.default_rng(seed)
    for _ in range(config.max_tries):
        adds, carves = sample_primitives(rng, config)
        noise = _sample_noise(rng, config)
        resolution = _choose_resolution(adds, carves, noise, config)
        if resolution is None:
            continue
        field_at = lambda p: sdf_points(adds, carves, noise, p)  # noqa: E731
        mesh = _mesh_field(*sdf_grid(adds, carves, noise, resolution), field_at, config)
        if mesh is not None and mesh.body_count == 1:
            return normalize_to_unit_sphere(mesh)
    raise RuntimeError(f"no valid shape for seed {seed} after {config.max_tries} draws")


def shape_stats(mesh: trimesh.Trimesh) -> dict:
    """Descriptive statistics of a closed mesh, for variety checks and benchmarks.

    genus from the Euler characteristic (V - E + F = 2 - 2g); sphericity = pi^(1/3) (6V)^(2/3) / A
    (1 for a ball, lower for flat or thin shapes); convexity = volume / convex-hull volume (1 when
    convex, lower with concavities and handles).
    """
    edges = mesh.edges_unique
    chi = len(mesh.vertices) - len(edges) + len(mesh.faces)
    vol, area = float(mesh.volume), float(mesh.area)
    return {
        "faces": int(len(mesh.faces)),
        "genus": int(round((2 - chi) / 2)),
        "volume": vol,
        "sphericity": float(math.pi ** (1 / 3) * (6 * vol) ** (2 / 3) / area),
        "convexity": float(vol / mesh.convex_hull.volume),
    }
