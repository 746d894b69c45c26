"""Tests of lookingglass.metrics against analytic figures.

Sampling model used for the tolerances. Each mesh gets N independent area-uniform samples. For
two concentric spheres of radii 1 and 1 + eps, the squared distance between points in directions
u, v is eps^2 + (1 + eps) * theta^2 + O(theta^4) with theta = angle(u, v), so the nearest point
in 3-D is the nearest in angle, and for N uniform points on the sphere (4 pi sr) E[theta_nn^2] =
4 pi / (pi N) = 4 / N. Hence

    CD    = (eps^2 + 4 (1 + eps) / N) * 1e4             (N = 20 000: eps^2 * 1e4 + 2.0 (1 + eps))
    Metro = (eps^2 + (1 + eps) * max theta_nn^2) * 1e3  with max theta_nn^2 ~ 4 (ln 2N + G) / N,

G a Gumbel variable (mean 0.58, P(G > 7) ~ 1e-3). The mean nearest-neighbour spacing is
sqrt(4 pi / N) = 0.025 for N = 20 000. Measured over 20 seeds for the CD floor (eps = 0):
2.004 +- 0.017, so a tolerance of 0.1 on CD is about 6 sigma; at N = 200 000 the floor is 0.2 and
we check eps^2 directly.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch
import trimesh

from lookingglass.errors import LookingGlassError
from lookingglass.metrics import (
    evaluate_mesh_files,
    normal_angle_errors,
    normalization_transform,
    render_error,
    sample_surface,
    shape_metrics,
)

N = 20000
CD_FLOOR = 4.0 / N * 1e4  # perfect unit sphere, see module docstring: 2.0
CD_TOL = 0.1  # ~6 sigma of the sampling noise (sigma 0.017 measured)


@pytest.fixture(scope="module")
def sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=5)  # 20 480 faces, radius 1


def scaled(mesh: trimesh.Trimesh, s: float, offset=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    m = mesh.copy()
    m.apply_scale(s)
    m.apply_translation(offset)
    return m


def metro_bounds(eps: float, n: int = N) -> tuple[float, float]:
    """Range (x 1e3) Metro must fall in for concentric spheres 1, 1 + eps (see module doc)."""
    r_min = 0.999  # facet centres of the icosphere lie just inside the unit sphere
    lo = (eps * r_min) ** 2 * 1e3
    hi = (eps ** 2 + (1 + eps) * 4.0 * (math.log(2 * n) + 7.0) / n) * 1e3
    return lo, hi


# ---------------------------------------------------------------------------------------------
# sampling
# ---------------------------------------------------------------------------------------------
def test_sample_surface_shapes_normals_and_determinism(sphere):
    p, n = sample_surface(sphere, 1000, seed=3)
    assert p.shape == (1000, 3) and n.shape == (1000, 3)
    assert p.dtype == np.float64 and n.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    # points on the icosphere: radius within the facet sag, outward face normals ~ radial
    r = np.linalg.norm(p, axis=1)
    assert r.max() <= 1.0 + 1e-12 and r.min() > 0.999
    assert np.degrees(np.arccos(np.clip((n * p / r[:, None]).sum(1), -1, 1))).max() < 1.5
    p2, n2 = sample_surface(sphere, 1000, seed=3)
    np.testing.assert_array_equal(p, p2)
    np.testing.assert_array_equal(n, n2)
    p3, _ = sample_surface(sphere, 1000, seed=4)
    assert not np.array_equal(p, p3)


def test_sample_surface_is_area_uniform():
    # a box 1 x 1 x 4: the four long sides hold 16 of the 18 area units
    box = trimesh.creation.box(extents=(1.0, 1.0, 4.0))
    p, n = sample_surface(box, 36000, seed=0)
    frac_caps = np.mean(np.abs(n[:, 2]) > 0.5)
    assert abs(frac_caps - 2.0 / 18.0) < 0.01  # binomial sigma 0.0017
    np.testing.assert_allclose(np.abs(p[np.abs(n[:, 2]) > 0.5, 2]), 2.0, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# shape metrics
# ---------------------------------------------------------------------------------------------
def test_identical_mesh_is_at_the_sampling_floor(sphere):
    m = shape_metrics(sphere, sphere)
    assert set(m) == {"cd", "metro", "cdn_mean", "cdn_med", "samples"}
    assert all(type(m[k]) is float for k in ("cd", "metro", "cdn_mean", "cdn_med"))
    assert m["samples"] == N
    assert abs(m["cd"] - CD_FLOOR) < CD_TOL
    lo, hi = metro_bounds(0.0)
    assert lo <= m["metro"] <= hi
    # CDN of a faceted sphere against itself: neighbours lie on the same or a nearby facet, so the
    # angle is bounded by the icosphere's largest dihedral (facet) angle, 1.44 deg here.
    facet = float(np.degrees(sphere.face_adjacency_angles.max()))
    assert 0.0 <= m["cdn_med"] <= m["cdn_mean"] + 0.2
    assert m["cdn_mean"] < facet
    # a smoother sphere (subdivision 6) halves the facet angle and lowers CDN
    fine = trimesh.creation.icosphere(subdivisions=6)
    assert shape_metrics(fine, fine)["cdn_mean"] < m["cdn_mean"]


@pytest.mark.parametrize("eps", [0.02, 0.05, 0.1])
def test_concentric_spheres(sphere, eps):
    m = shape_metrics(scaled(sphere, 1 + eps), sphere)
    expected_cd = (eps ** 2 + 4 * (1 + eps) / N) * 1e4  # eps^2 * 1e4 plus the sampling floor
    # facet sag: samples lie at radius r <= 1 (E[r^2] = 1 - 3.6e-4 at subdivision 5), so the gap
    # is eps * r, biasing CD low by ~4e-4 relative; allow 1e-3 relative on top of the noise.
    assert abs(m["cd"] - expected_cd) < CD_TOL + 1e-3 * eps ** 2 * 1e4, (m, expected_cd)
    lo, hi = metro_bounds(eps)
    assert lo <= m["metro"] <= hi, (m, lo, hi)
    # same facet structure on both spheres: normals agree as for identical meshes
    assert m["cdn_mean"] < float(np.degrees(sphere.face_adjacency_angles.max()))


def test_concentric_spheres_dense_sampling_recovers_eps_squared(sphere):
    eps, n = 0.05, 200_000
    m = shape_metrics(scaled(sphere, 1 + eps), sphere, samples=n)
    assert m["samples"] == n
    floor = 4 * (1 + eps) / n * 1e4  # 0.21
    assert abs(m["cd"] - eps ** 2 * 1e4 - floor) < 0.03
    lo, hi = metro_bounds(eps, n)
    assert lo <= m["metro"] <= hi
    assert hi - eps ** 2 * 1e3 < 0.5  # i.e. Metro = eps^2 * 1e3 to within 0.5


def test_shifted_sphere(sphere):
    # two unit spheres offset by delta: the gap along the normal is |delta . n|, whose square
    # averages delta^2 / 3 over the sphere. Dense sampling keeps the floor at 0.2.
    delta, n = 0.05, 200_000
    m = shape_metrics(scaled(sphere, 1.0, (delta, 0.0, 0.0)), sphere, samples=n)
    expected = (delta ** 2 / 3 + 4.0 / n) * 1e4
    assert abs(m["cd"] - expected) < 0.05, (m, expected)
    lo, hi = metro_bounds(delta, n)
    assert lo <= m["metro"] <= hi


def test_rotated_sphere_is_at_the_sampling_floor(sphere):
    rot = trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 3.0])
    turned = sphere.copy()
    turned.apply_transform(rot)
    m = shape_metrics(turned, sphere)
    assert abs(m["cd"] - CD_FLOOR) < CD_TOL
    assert m["metro"] <= metro_bounds(0.0)[1]
    # facets no longer line up, but nearby normals still differ by about a facet angle
    assert m["cdn_mean"] < 1.5 * float(np.degrees(sphere.face_adjacency_angles.max()))


def test_inside_out_prediction_is_not_flipped(sphere):
    inverted = sphere.copy()
    inverted.invert()
    m = shape_metrics(inverted, sphere)
    assert abs(m["cd"] - CD_FLOOR) < CD_TOL  # same surface
    assert m["cdn_mean"] > 178.0 and m["cdn_med"] > 178.0


def test_normalize_gt_is_scale_and_translation_invariant(sphere):
    pred = scaled(sphere, 1.05)
    base = shape_metrics(pred, sphere)
    for s, off in [(10.0, (0.0, 0.0, 0.0)), (10.0, (3.0, -7.0, 1.5)), (0.01, (0.2, 0.1, 0.0))]:
        m = shape_metrics(scaled(pred, s, off), scaled(sphere, s, off), normalize="gt")
        for k in ("cd", "metro", "cdn_mean", "cdn_med"):
            assert m[k] == pytest.approx(base[k], rel=1e-6, abs=1e-9), (k, s, off)
    # without normalization a 10x larger pair gives 100x the squared distances
    big = shape_metrics(scaled(pred, 10.0), scaled(sphere, 10.0), normalize=None)
    assert big["cd"] == pytest.approx(100 * base["cd"], rel=1e-6)
    assert big["cdn_mean"] == pytest.approx(base["cdn_mean"], rel=1e-6)


def test_normalization_transform_is_gt_bbox_centre_and_max_radius():
    box = trimesh.creation.box(extents=(2.0, 4.0, 6.0))
    box.apply_translation((1.0, 2.0, 3.0))
    centre, scale = normalization_transform(box)
    np.testing.assert_allclose(centre, [1.0, 2.0, 3.0], atol=1e-12)
    assert scale == pytest.approx(math.sqrt(1 + 4 + 9))
    # normalized already: normalize=None and "gt" agree
    s = trimesh.creation.icosphere(subdivisions=4)
    a = shape_metrics(scaled(s, 1.1), s, samples=2000, normalize=None)
    b = shape_metrics(scaled(s, 1.1), s, samples=2000, normalize="gt")
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-9)
    with pytest.raises(ValueError, match="normalize"):
        shape_metrics(s, s, normalize="pred")


def test_determinism_per_seed(sphere):
    pred = scaled(sphere, 1.03)
    a = shape_metrics(pred, sphere, seed=7)
    b = shape_metrics(pred, sphere, seed=7)
    c = shape_metrics(pred, sphere, seed=8)
    assert a == b
    assert a["cd"] != c["cd"]
    assert abs(a["cd"] - c["cd"]) < 2 * CD_TOL


def test_shape_metrics_is_fast(sphere):
    pred = scaled(sphere, 1.02)
    shape_metrics(pred, sphere)  # warm-up
    t0 = time.perf_counter()
    shape_metrics(pred, sphere)
    assert time.perf_counter() - t0 < 1.0


def test_shape_metrics_rejects_bad_meshes(sphere):
    empty = trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64))
    with pytest.raises(ValueError, match="no faces"):
        shape_metrics(empty, sphere)
    flat = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [2, 0, 0]], faces=[[0, 1, 2]],
                           process=False)
    with pytest.raises(ValueError, match="zero surface area"):
        shape_metrics(sphere, flat)
    with pytest.raises(TypeError):
        shape_metrics(np.zeros((10, 3)), sphere)


# ---------------------------------------------------------------------------------------------
# normal maps and render error
# ---------------------------------------------------------------------------------------------
def rotate_by(normals: np.ndarray, angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Each normal rotated by exactly `angle_deg` about a random axis perpendicular to it."""
    k = np.cross(normals, rng.normal(size=normals.shape))
    k /= np.linalg.norm(k, axis=-1, keepdims=True)
    a = math.radians(angle_deg)
    return normals * math.cos(a) + np.cross(k, normals) * math.sin(a)


@pytest.mark.parametrize("angle", [1e-6, 0.5, 7.5, 45.0, 90.0, 135.0, 179.9])
def test_normal_angle_of_known_rotation(angle):
    rng = np.random.default_rng(0)
    gt = rng.normal(size=(24, 32, 3))
    gt /= np.linalg.norm(gt, axis=-1, keepdims=True)
    pred = rotate_by(gt, angle, rng)
    mask = np.ones((24, 32), bool)
    e = normal_angle_errors(pred, gt, mask)
    assert set(e) == {"mean", "median"} and all(type(v) is float for v in e.values())
    # exact to rounding, also for tiny angles (atan2, not arccos, of the dot product)
    assert e["mean"] == pytest.approx(angle, rel=1e-8, abs=1e-11)
    assert e["median"] == pytest.approx(angle, rel=1e-8, abs=1e-11)


def test_normal_angle_mask_lengths_torch_and_channels_first():
    rng = np.random.default_rng(1)
    gt = rng.normal(size=(2, 16, 20, 3))
    gt /= np.linalg.norm(gt, axis=-1, keepdims=True)
    pred = rotate_by(gt, 10.0, rng)
    mask = np.zeros((2, 16, 20), bool)
    mask[:, 4:12, 5:15] = True
    pred[~mask] = rng.normal(size=(int((~mask).sum()), 3))  # garbage outside the mask is ignored
    pred *= rng.uniform(0.2, 5.0, size=(2, 16, 20, 1))  # lengths do not matter
    # the masked-in quarter at 20 deg: mean 12.5, median still 10
    pred_b = pred.copy()
    pred_b[:, 4:6, 5:15] = rotate_by(gt[:, 4:6, 5:15], 20.0, rng)
    e = normal_angle_errors(pred_b, gt, mask)
    assert e["mean"] == pytest.approx(12.5, rel=1e-9)
    assert e["median"] == pytest.approx(10.0, rel=1e-9)
    # torch tensors (float32), a float mask with a singleton channel, channels-first layout
    t_pred = torch.from_numpy(pred).float().permute(0, 3, 1, 2)
    t_gt = torch.from_numpy(gt).float().permute(0, 3, 1, 2)
    t_mask = torch.from_numpy(mask).float()
    e2 = normal_angle_errors(t_pred, t_gt, t_mask, channel_axis=1)
    assert e2["mean"] == pytest.approx(10.0, abs=1e-3)
    e3 = normal_angle_errors(torch.from_numpy(pred), torch.from_numpy(gt), t_mask[..., None])
    assert e3["median"] == pytest.approx(10.0, rel=1e-9)


def test_a_missing_normal_scores_90_degrees():
    """A mesh that misses a pixel the truth covers leaves a zero normal there: it must count as a
    90-degree error, not as exact (atan2(0, 0) is 0). Zero against zero (neither has a hit) is 0."""
    gt = np.tile([0.0, 0.0, 1.0], (4, 4, 1))
    pred = gt.copy()
    pred[0, :] = 0.0  # a quarter of the pixels missed
    e = normal_angle_errors(pred, gt, np.ones((4, 4), bool))
    assert e["mean"] == pytest.approx(22.5)
    assert normal_angle_errors(gt, pred, np.ones((4, 4), bool))["mean"] == pytest.approx(22.5)
    assert normal_angle_errors(pred[:1], gt[:1] * 0, np.ones((1, 4), bool))["mean"] == 0.0
    # Table 1's pooled angles (normals/evaluate.py) go through the same function
    from lookingglass.normals.evaluate import _angles
    pooled = _angles(torch.from_numpy(pred).float(), torch.from_numpy(gt).float(), torch.ones(4, 4, dtype=torch.bool))
    assert np.sort(pooled)[-4:].tolist() == [90.0] * 4 and pooled.mean() == pytest.approx(22.5)


def test_normal_angle_errors_reject_bad_input():
    n = np.tile([0.0, 0.0, 1.0], (4, 4, 1))
    with pytest.raises(ValueError, match="mask is empty"):
        normal_angle_errors(n, n, np.zeros((4, 4), bool))
    with pytest.raises(ValueError, match="3 channels"):
        normal_angle_errors(n[..., :2], n[..., :2], np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="differ in shape"):
        normal_angle_errors(n, n[:3], np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="does not match"):
        normal_angle_errors(n, n, np.ones((5, 4), bool))


def test_render_error_of_known_arrays():
    image = np.zeros((2, 3, 3))
    rendered = np.zeros((2, 3, 3))
    rendered[0, 0] = [0.1, 0.2, 0.3]  # in mask: squares 0.01 + 0.04 + 0.09 = 0.14
    rendered[1, 2] = [1.0, 0.0, 0.0]  # in mask: 1.0
    rendered[0, 1] = [9.0, 9.0, 9.0]  # outside the mask: ignored
    mask = np.array([[1, 0, 0], [0, 1, 1]], dtype=np.uint8)
    # 3 masked pixels x 3 channels = 9 terms
    assert render_error(rendered, image, mask) == pytest.approx((0.14 + 1.0) / 9, rel=1e-12)
    assert type(render_error(rendered, image, mask)) is float
    t = render_error(torch.from_numpy(rendered).permute(2, 0, 1), torch.from_numpy(image)
                     .permute(2, 0, 1), torch.from_numpy(mask.astype(bool)), channel_axis=0)
    assert t == pytest.approx((0.14 + 1.0) / 9, rel=1e-12)
    assert render_error(image, image, mask) == 0.0
    with pytest.raises(ValueError, match="mask is empty"):
        render_error(rendered, image, np.zeros((2, 3)))


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------
def test_evaluate_mesh_files_matches_shape_metrics(tmp_path, sphere):
    pred = scaled(sphere, 1.05, (0.3, 0.0, 0.0))
    pred_path, gt_path = tmp_path / "pred.ply", tmp_path / "gt.obj"
    pred.export(pred_path)
    sphere.export(gt_path)
    m = evaluate_mesh_files(pred_path, gt_path, samples=5000, seed=2)
    ref = shape_metrics(pred, sphere, samples=5000, seed=2)
    for k in ("cd", "metro", "cdn_mean", "cdn_med"):
        assert m[k] == pytest.approx(ref[k], rel=1e-5), k
    assert m["samples"] == 5000


def test_evaluate_mesh_files_errors_name_the_file(tmp_path, sphere):
    good = tmp_path / "good.ply"
    sphere.export(good)

    missing = tmp_path / "nope.ply"
    with pytest.raises(LookingGlassError, match="not found") as info:
        evaluate_mesh_files(missing, good)
    assert info.value.path == str(missing) and str(missing) in str(info.value)

    garbage_ply = tmp_path / "garbage.ply"
    garbage_ply.write_bytes(b"this is not a mesh\x00\x01\x02")
    with pytest.raises(LookingGlassError, match="cannot read mesh") as info:
        evaluate_mesh_files(good, garbage_ply)
    assert info.value.path == str(garbage_ply)

    garbage_obj = tmp_path / "garbage.obj"  # trimesh reads this as an empty mesh
    garbage_obj.write_text("hello world\nnot an obj\n")
    with pytest.raises(LookingGlassError, match="no faces") as info:
        evaluate_mesh_files(garbage_obj, good)
    assert info.value.path == str(garbage_obj)

    points = tmp_path / "points.xyz"  # a point cloud, not a surface
    points.write_text("0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(LookingGlassError):
        evaluate_mesh_files(points, good)

    with pytest.raises(LookingGlassError, match="not a file"):
        evaluate_mesh_files(tmp_path, good)
