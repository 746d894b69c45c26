"""Shape families beyond the procedural unions: CAD-like solids, handles, thin parts, smooth blobs.

Users bring manufactured parts (flat faces, sharp edges, holes) and figurines (smooth, few
concavities, where the visual hull is nearly right). The procedural generator (shapes.py) makes
neither, so the networks never saw a good hull on a flat-faced part. This module builds both:

  cad     CSG of boxes, prisms and cylinders: unions (steps, L shapes), through-holes, notches,
          chamfers (intersections with turned boxes)
  handle  a body with a thin ring handle, or a key-like ring and blade (genus 1)
  thin    a body with thin plates or rods standing off it
  blob    a smooth union of a few ellipsoids (figurine-like)

`random_family_shape(family, seed)` draws one at random (training data: `generate` with
`--families`); the validation set (validation.py) builds ten named ones from the same helpers.

Sharp edges: the renderer shades with smooth vertex normals (render/tracer.py), so CSG meshes are
subdivided to edges of at most `EDGE` (unit-sphere frame) first; a crease is then rounded over one
small triangle, like the bevel of a real part, and its faces stay flat.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh

from ..errors import LookingGlassError
from .shapes import normalize_to_unit_sphere

EDGE = 0.03  # longest edge of a rendered CSG mesh, unit-sphere frame
FAMILIES = ("procedural", "cad", "handle", "thin", "blob")


def boolean(op: str, meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Union, difference or intersection of closed meshes (manifold3d: exact, watertight)."""
    fn = {"union": trimesh.boolean.union, "difference": trimesh.boolean.difference,
          "intersection": trimesh.boolean.intersection}[op]
    return fn(meshes, engine="manifold")


def moved(mesh: trimesh.Trimesh, offset=(0, 0, 0), axis=None, angle=0.0) -> trimesh.Trimesh:
    """A copy rotated by `angle` (radians) about `axis`, then moved by `offset`."""
    mesh = mesh.copy()
    if axis is not None:
        mesh.apply_transform(trimesh.transformations.rotation_matrix(angle, axis))
    mesh.apply_translation(offset)
    return mesh


def cylinder(radius: float, height: float, axis=(0, 0, 1), sections: int = 96, offset=(0, 0, 0)):
    """A cylinder (a prism when `sections` is small) along unit vector `axis`, centred at `offset`."""
    cyl = trimesh.creation.cylinder(radius, height, sections=sections)
    axis = np.asarray(axis, float)
    if not np.allclose(axis, (0, 0, 1)):
        cyl.apply_transform(trimesh.geometry.align_vectors((0, 0, 1), axis))
    return moved(cyl, offset)


def blob(ellipsoids: list[tuple[tuple, tuple]], blend: float = 0.12, resolution: int = 144) -> trimesh.Trimesh:
    """A smooth union (polynomial smooth minimum, width `blend`) of ellipsoids ((centre), (radii)),
    meshed by marching cubes on a grid over [-1.3, 1.3]^3 (the ellipsoids must lie inside it)."""
    from skimage.measure import marching_cubes

    axis = np.linspace(-1.3, 1.3, resolution)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    field = None
    for centre, radii in ellipsoids:
        q = np.sqrt(sum(((c - o) / r) ** 2 for c, o, r in zip((x, y, z), centre, radii)))
        d = (q - 1) * min(radii)  # a distance bound, good enough for a smooth union
        if field is None:
            field = d
        else:
            h = np.clip(0.5 + 0.5 * (d - field) / blend, 0, 1)
            field = d * (1 - h) + field * h - blend * h * (1 - h)
    step = axis[1] - axis[0]
    verts, faces, _, _ = marching_cubes(field, 0.0, spacing=(step,) * 3, allow_degenerate=False)
    mesh = trimesh.Trimesh(verts - 1.3, faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    trimesh.smoothing.filter_taubin(mesh, iterations=10)
    return mesh


def finish(mesh: trimesh.Trimesh, rotation_draw, what: str, max_edge: float = EDGE) -> trimesh.Trimesh:
    """`mesh` turned by the random rotation of `rotation_draw` (3 numbers in [0, 1): no face lines
    up with the rig), in the unit sphere, edges at most `max_edge` long. Raises when it is not one
    closed, outward surface (a CSG failure)."""
    mesh = mesh.copy()
    mesh.apply_transform(trimesh.transformations.random_rotation_matrix(np.asarray(rotation_draw, float)))
    mesh = normalize_to_unit_sphere(mesh)
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge)
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    if not mesh.is_watertight or mesh.volume <= 0 or mesh.body_count != 1:
        raise LookingGlassError(f"{what} is not one closed, outward surface (a CSG failure)")
    return mesh


# ---------------------------------------------------------------------------------------------
# random members of each family (construction frame: about [-1, 1]^3; finish() rescales)
# ---------------------------------------------------------------------------------------------
def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _random_axis(rng: np.random.Generator) -> tuple:
    return ((1, 0, 0), (0, 1, 0), (0, 0, 1))[int(rng.integers(3))]


def _cad_base(rng: np.random.Generator) -> trimesh.Trimesh:
    kind = rng.choice(["box", "prism", "cylinder"], p=[0.5, 0.25, 0.25])
    if kind == "box":
        return trimesh.creation.box(rng.uniform(0.5, 1.6, 3))
    sections = int(rng.choice([5, 6, 8])) if kind == "prism" else 96
    return cylinder(_u(rng, 0.4, 0.85), _u(rng, 0.3, 1.5), sections=sections)


def random_cad(rng: np.random.Generator) -> trimesh.Trimesh:
    """A base block, prism or cylinder, then 1-3 of: a block or disc added (a step, an L), a round
    through-hole, a box notch, chamfered edges."""
    mesh = _cad_base(rng)
    ext = mesh.extents
    for _ in range(int(rng.integers(1, 4))):
        op = rng.choice(["add", "hole", "notch", "chamfer"], p=[0.35, 0.3, 0.2, 0.15])
        lo, hi = mesh.bounds
        if op == "add":
            size = rng.uniform(0.25, 0.9, 3) * ext.max()
            corner = rng.uniform(lo, hi)  # centred on a point of the bounding box: overlaps the body
            part = (trimesh.creation.box(size) if rng.random() < 0.6
                    else cylinder(size[0] / 2, size[2], axis=_random_axis(rng)))
            mesh = boolean("union", [mesh, moved(part, corner)])
        elif op == "hole":
            axis = _random_axis(rng)
            a = int(np.argmax(axis))
            radius = _u(rng, 0.08, 0.3) * np.delete(ext, a).min()
            centre = (lo + hi) / 2 + rng.uniform(-0.25, 0.25, 3) * ext
            mesh = boolean("difference", [mesh, cylinder(radius, ext[a] * 3, axis=axis, offset=centre)])
        elif op == "notch":
            size = rng.uniform(0.2, 0.5, 3) * ext
            corner = np.where(rng.random(3) < 0.5, lo, hi)
            mesh = boolean("difference", [mesh, moved(trimesh.creation.box(size * 2), corner)])
        else:
            k = _u(rng, 0.75, 0.95)
            cutter = moved(trimesh.creation.box(ext * [k, k, 10] * np.sqrt(2)), (lo + hi) / 2, axis=(0, 0, 1),
                           angle=np.pi / 4)
            mesh = boolean("intersection", [mesh, cutter])
        ext = mesh.extents
    return mesh


def random_handle(rng: np.random.Generator) -> trimesh.Trimesh:
    """A cylinder, box or ellipsoid body with a thin ring handle on its side (a mug, a jug), or a
    key: a ring bow and a blade with teeth."""
    minor = _u(rng, 0.05, 0.11)
    if rng.random() < 0.3:
        major = _u(rng, 0.25, 0.4)
        bow = moved(trimesh.creation.torus(major, minor, major_sections=64, minor_sections=16), (-0.75, 0, 0))
        width, thick = _u(rng, 0.12, 0.22), _u(rng, 0.08, 0.14)
        length = _u(rng, 0.9, 1.5)
        blade = moved(trimesh.creation.box((length, width, thick)), (-0.75 + major + length / 2 - 0.05, 0, 0))
        teeth = [moved(trimesh.creation.box((0.09, width, thick)),
                       (-0.75 + major + length * _u(rng, 0.4, 0.95), -width * 0.8, 0))
                 for _ in range(int(rng.integers(0, 4)))]
        return boolean("union", [bow, blade, *teeth])
    radius, height = _u(rng, 0.4, 0.65), _u(rng, 0.9, 1.5)
    kind = rng.choice(["cylinder", "box", "ellipsoid"])
    if kind == "cylinder":
        body = cylinder(radius, height, (0, 1, 0))
    elif kind == "box":
        body = trimesh.creation.box((2 * radius, height, 2 * radius * _u(rng, 0.6, 1.0)))
    else:
        body = trimesh.creation.icosphere(4)
        body.apply_scale((radius, height / 2, radius))
    major = _u(rng, 0.25, 0.45)
    handle = moved(trimesh.creation.torus(major, minor, major_sections=64, minor_sections=16),
                   (radius + major * _u(rng, 0.35, 0.7), _u(rng, -0.2, 0.2) * height, 0), axis=(1, 0, 0),
                   angle=np.pi / 2)
    return boolean("union", [body, handle])


def random_thin(rng: np.random.Generator) -> trimesh.Trimesh:
    """A capsule, box or ellipsoid body with 1-3 thin plates (fins) or rods standing off it."""
    kind = rng.choice(["capsule", "box", "ellipsoid"])
    if kind == "capsule":
        body = trimesh.creation.capsule(_u(rng, 0.6, 1.2), _u(rng, 0.25, 0.45), count=[32, 32])
    elif kind == "box":
        body = trimesh.creation.box(rng.uniform(0.4, 1.0, 3))
    else:
        body = trimesh.creation.icosphere(4)
        body.apply_scale(rng.uniform(0.3, 0.6, 3))
    parts = [body]
    for _ in range(int(rng.integers(1, 4))):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        thickness = _u(rng, 0.04, 0.08)
        if rng.random() < 0.6:
            plate = trimesh.creation.box((thickness, _u(rng, 0.5, 1.0), _u(rng, 0.5, 1.0)))
            plate.apply_transform(trimesh.geometry.align_vectors((0, 1, 0), direction))
            parts.append(moved(plate, direction * _u(rng, 0.25, 0.45)))
        else:
            length = _u(rng, 0.6, 1.1)
            parts.append(cylinder(thickness, length, axis=direction, sections=24, offset=direction * length / 2))
    return boolean("union", parts)


def random_blob(rng: np.random.Generator) -> trimesh.Trimesh:
    """A smooth union of a body ellipsoid and 0-5 smaller ones on its surface (head, ears, feet):
    figurine-like, few concavities."""
    body_radii = rng.uniform(0.4, 0.75, 3)
    parts = [((0.0, 0.0, 0.0), tuple(body_radii))]
    for _ in range(int(rng.integers(0, 6))):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        radii = rng.uniform(0.08, 0.4, 3)
        centre = direction * body_radii * _u(rng, 0.8, 1.1)
        parts.append((tuple(np.clip(centre, -0.8, 0.8)), tuple(radii)))
    return blob(parts, blend=_u(rng, 0.06, 0.3), resolution=112)


RANDOM: dict[str, Callable[[np.random.Generator], trimesh.Trimesh]] = {
    "cad": random_cad, "handle": random_handle, "thin": random_thin, "blob": random_blob}


def random_family_shape(family: str, seed: int, max_edge: float = EDGE, max_tries: int = 20) -> trimesh.Trimesh:
    """A random member of `family` (one of RANDOM) in the unit sphere, randomly turned, edges at
    most `max_edge`: a function of (family, seed). A failed draw (a CSG that falls apart) is redrawn
    from the same generator."""
    if family not in RANDOM:
        raise LookingGlassError(f"unknown shape family {family!r} (choose from {', '.join(RANDOM)})")
    rng = np.random.default_rng(seed)
    for _ in range(max_tries):
        try:
            return finish(RANDOM[family](rng), rng.random(3), f"a {family} shape", max_edge)
        except (LookingGlassError, ValueError):
            continue
    raise LookingGlassError(f"no valid {family} shape for seed {seed} after {max_tries} draws")
