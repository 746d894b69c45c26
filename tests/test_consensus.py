"""The views' consensus of predicted normals (lookingglass/normals/consensus.py) on a sphere.

A unit sphere seen by the paper's 10-view rig at 128x96: every surface point is seen by several
views, and the back of one view's object (its second hit) is the front of another's. The
consensus averages the votes of the views that see the same point, so
- exact normals stay exact up to the sphere's turn across the matching tolerance (one pixel
  footprint at depth 3 is ~0.029, i.e. ~1.7 degrees of the unit sphere);
- independent per-view errors shrink (a mean of k independent deviations);
- a poor N2 is mended by the N1 of the views that see its point head-on.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from lookingglass.data.rigs import paper_rig
from lookingglass.metrics import normal_angles
from lookingglass.normals.consensus import view_consensus
from lookingglass.render.tracer import trace_two_bounce

W, H = 128, 96


def _radial_sphere() -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=5)
    sphere.vertex_normals = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    return sphere


@pytest.fixture(scope="module")
def seen():
    cams = paper_rig(10, rng=0, width=W, height=H)
    tb = trace_two_bounce(_radial_sphere(), cams, ior=1.5)
    return cams, tb


def _noisy(normals: torch.Tensor, degrees: float, seed: int) -> torch.Tensor:
    """Each normal turned by exactly `degrees` about a random perpendicular axis."""
    g = torch.Generator().manual_seed(seed)
    axis = torch.linalg.cross(normals, torch.randn(normals.shape, generator=g), dim=-1)
    axis = torch.nn.functional.normalize(axis, dim=-1)
    a = math.radians(degrees)
    return normals * math.cos(a) + torch.linalg.cross(axis, normals, dim=-1) * math.sin(a)


def _errors(pred: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    return normal_angles(pred[mask], truth[mask])


def _consensus(cams, tb, n1, n2, tolerance_px=1.0):
    return view_consensus(n1, n2, cams, tb.point1, tb.point2, tb.normal1, tb.mask, tb.valid, tolerance_px)


def test_exact_normals_stay_exact_within_the_matching_blur(seen):
    cams, tb = seen
    n1, n2 = _consensus(cams, tb, tb.normal1, tb.normal2)
    e1, e2 = _errors(n1, tb.normal1, tb.mask), _errors(n2, tb.normal2, tb.valid)
    # the votes lie within one footprint (~0.029 at depth 3 through 63.4 deg over 128 px): the sphere's
    # normal turns by at most ~1.7 degrees across it, and the weighted mean by less
    footprint = 2 * 3.0 * math.tan(math.radians(63.4 / 2)) / W
    blur = math.degrees(footprint)  # unit radius: the angle is the arc
    assert np.median(e1) < 0.3 * blur and e1.max() < blur
    assert np.median(e2) < 0.3 * blur and e2.max() < blur


def test_independent_errors_shrink_and_a_poor_n2_is_mended(seen):
    cams, tb = seen
    n1 = _noisy(tb.normal1, 10.0, seed=1)
    n2 = _noisy(tb.normal2, 30.0, seed=2)
    f1, f2 = _consensus(cams, tb, n1, n2)
    e1, e2 = _errors(f1, tb.normal1, tb.mask), _errors(f2, tb.normal2, tb.valid)
    # several views see most points: the mean of k independent 10-degree turns is ~10 / sqrt(k)
    # (6.0 here: ~2.7 views a point); two views would give 7.1
    assert np.median(e1) < 7.0
    # N2's points are other views' first hits, whose votes (10 degrees off) pull its own 30 (weighing
    # OWN_N2_WEIGHT = 3 head-on votes) to ~20
    assert np.median(e2) < 22.5
    # pixels no view votes for (the hull misses them: off the object) keep their prediction
    off = ~tb.mask
    assert torch.equal(f1[off], n1[off]) and torch.equal(f2[~tb.valid], n2[~tb.valid])


def test_without_a_tolerance_only_each_views_own_votes_count(seen):
    cams, tb = seen
    n1 = _noisy(tb.normal1, 10.0, seed=3)
    f1, f2 = _consensus(cams, tb, n1, tb.normal2, tolerance_px=1e-6)
    # no other view's hit lies within 1e-6 footprints, a view's own pixel does (distance 0): unchanged
    assert torch.allclose(f1[tb.mask], n1[tb.mask], atol=1e-5)
    assert torch.allclose(f2[tb.valid], tb.normal2[tb.valid], atol=1e-5)
