"""Small procedural test shapes for the renderer's validation and benchmarks.

Not the dataset's shape generator (lookingglass.data.shapes): these only need to be closed,
single-surface (no inner faces), outward-oriented and, for `radial_blob`, non-convex, so that
light paths get interesting.
"""

from __future__ import annotations

import numpy as np
import trimesh


def radial_blob(seed: int = 0, subdivisions: int = 5, bumps: int = 12, amplitude: float = 0.45,
                width: float = 0.5) -> trimesh.Trimesh:
    """An icosphere pushed in and out along its radii by a sum of smooth Gaussian bumps.

    r(u) = 1 + sum_k a_k exp((u . c_k - 1) / width^2), a_k ~ U[-amplitude, amplitude], c_k
    random unit vectors: star-shaped about the origin, so it stays watertight and free of
    self-intersections, while the dents make it non-convex (rays re-enter, reflections hit the
    object again). Scaled so max |p| = 1 (DESIGN.md's unit-sphere normalization).
    Faces: 20 * 4^subdivisions (subdivisions=5: 20480).
    """
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    u = np.asarray(sphere.vertices)
    u = u / np.linalg.norm(u, axis=1, keepdims=True)
    centres = rng.normal(size=(bumps, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    a = rng.uniform(-amplitude, amplitude, size=bumps)
    r = 1.0 + (a[None] * np.exp((u @ centres.T - 1.0) / width ** 2)).sum(1)
    r = np.maximum(r, 0.2)  # keep the radius positive: the shape stays star-shaped
    v = u * r[:, None]
    v /= np.linalg.norm(v, axis=1).max()
    return trimesh.Trimesh(v, sphere.faces, process=False)
