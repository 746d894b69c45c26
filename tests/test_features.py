"""Feature mapping onto hull points (lookingglass.points.features), checked on a unit sphere.

The "predicted" first-hit normals are the exact ones of the unit sphere (ray-sphere intersection
per pixel centre), so every error left is the mapping's own: projection, pixel convention,
bilinear fetch, visibility and view selection. The hull is an icosphere inscribed in the sphere
(subdivision 4: facets within 2.6 deg of radial, at most 0.0011 inside the sphere).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from lookingglass.data.rigs import paper_rig
from lookingglass.physics.camera import Cameras
from lookingglass.points.features import (FEATURE_COLUMNS, NUM_FEATURES, SILHOUETTE_OFFSETS, UNSEEN_COS,
                                          UNSEEN_ERROR, UNSEEN_TIR, map_features, sample_hull_points,
                                          select_nearest, select_rendering_error, silhouette_counts)

W, H = 64, 48


def sphere_hits(origins: torch.Tensor, dirs: torch.Tensor, centre=(0.0, 0.0, 0.0), radius: float = 1.0):
    """First hit of rays (..., 3) with a sphere: (hit (...) bool, unit outward normal (..., 3),
    zero on misses), world frame."""
    c = origins.new_tensor(centre)
    oc = origins - c
    b = (oc * dirs).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - radius ** 2)
    hit = disc > 0
    t = -b - disc.clamp_min(0).sqrt()
    normal = (oc + t[..., None] * dirs) / radius
    return hit, torch.where(hit[..., None], normal, torch.zeros_like(normal))


def sphere_maps(cams: Cameras):
    """Analytic first-hit normals of the unit sphere in camera frame (V, H, W, 3), its mask
    (V, H, W), and the world normals (V, H, W, 3)."""
    origins, dirs = cams.pixel_rays()
    mask, n_world = sphere_hits(origins, dirs)
    return cams.world_to_camera(n_world), mask, n_world


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a, b = a.double(), b.double()
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b, dim=-1).norm(dim=-1), (a * b).sum(-1)))


@pytest.fixture(scope="module")
def scene():
    cams = paper_rig(10, deterministic=True, width=W, height=H, dtype=torch.float64)
    hull = trimesh.creation.icosphere(subdivisions=4)
    pts, nrm = sample_hull_points(hull, 2000, seed=0)
    n1_cam, mask, n_world = sphere_maps(cams)
    zeros = torch.zeros(mask.shape, dtype=torch.float64)
    return dict(cams=cams, hull=hull, pts=pts, nrm=nrm, n1=n1_cam, mask=mask, n_world=n_world,
                err=zeros, tir=torch.zeros_like(mask))


def run(scene, strategy, **over):
    s = {**scene, **over}
    return map_features(s["pts"], s["nrm"], s["hull"], s["cams"], s["n1"], s["err"], s["tir"], s["mask"],
                        strategy=strategy)


def tap_bound_deg(cams: Cameras, pts: np.ndarray, n_world: torch.Tensor, mask: torch.Tensor):
    """Per view and point: the exact normal at the sphere hit of the ray camera -> point (V, N, 3),
    and the largest angle (V, N) between it and the GT normals of the up-to-four in-mask pixel
    centres that bilinear interpolation at the point's projection reads.

    A mask-weighted, re-normalized bilinear fetch is a non-negative combination of those four
    normals, so it lies in their cone: its angle to the exact normal cannot exceed this bound.
    """
    p = torch.from_numpy(pts).double()
    V = cams.num_views
    d = torch.nn.functional.normalize(p[None] - cams.origin[:, None], dim=-1)
    _, gt = sphere_hits(cams.origin[:, None].expand_as(d), d)
    xy, _ = cams.project(p)
    c0 = torch.floor(xy[..., 0] - 0.5).long()
    r0 = torch.floor(xy[..., 1] - 0.5).long()
    bound = torch.zeros(V, len(pts), dtype=torch.float64)
    vi = torch.arange(V)[:, None]
    for dc in (0, 1):
        for dr in (0, 1):
            c, r = c0 + dc, r0 + dr
            ok = (c >= 0) & (c < W) & (r >= 0) & (r < H)
            cc, rr = c.clamp(0, W - 1), r.clamp(0, H - 1)
            ok &= mask[vi, rr, cc]
            ang = angle_deg(n_world[vi, rr, cc], gt)
            bound = torch.where(ok, torch.maximum(bound, ang), bound)
    return gt, bound


# ---------------------------------------------------------------------------------------------
def test_sample_hull_points_count_surface_and_spacing():
    hull = trimesh.creation.icosphere(subdivisions=4)
    for count in (1, 500, 3000):
        pts, nrm = sample_hull_points(hull, count, seed=3)
        assert pts.shape == (count, 3) and nrm.shape == (count, 3)
        assert pts.dtype == np.float32 and nrm.dtype == np.float32
    # on the surface: within float32 rounding of the (radius <= 1) facets
    _, dist, _ = trimesh.proximity.closest_point(hull, pts)
    assert dist.max() < 1e-6
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-6)
    radial = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    assert ((nrm * radial).sum(1) > np.cos(np.radians(3.0))).all()  # face normals, facets <= 2.64 deg
    # deterministic per seed, different across seeds
    again, _ = sample_hull_points(hull, 3000, seed=3)
    other, _ = sample_hull_points(hull, 3000, seed=4)
    np.testing.assert_array_equal(pts, again)
    assert not np.allclose(pts, other)
    # Poisson-disk spacing: no two points closer than the rejection radius sqrt(A / 3N) (0.037
    # here); area-uniform random samples of this size come ~10x closer
    nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
    assert nn.min() >= 0.99 * np.sqrt(hull.area / (3 * 3000))


def test_sample_hull_points_pads_to_exact_count(monkeypatch):
    # force rejection sampling to come up short every time: the rest is padded area-uniformly
    real = trimesh.sample.sample_surface_even
    calls = []

    def short(mesh, count, radius=None, seed=None):
        calls.append(radius)
        pts, faces = real(mesh, count, radius=radius, seed=seed)
        return pts[: count // 2], faces[: count // 2]

    monkeypatch.setattr(trimesh.sample, "sample_surface_even", short)
    tri = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]])
    pts, nrm = sample_hull_points(tri, 1000, seed=0)
    assert pts.shape == (1000, 3) and len(calls) == 5
    assert calls[-1] < calls[0]  # the rejection radius was shrunk between tries
    np.testing.assert_allclose(nrm, np.tile([0, 0, 1], (1000, 1)), atol=1e-7)
    assert np.abs(pts[:, 2]).max() == 0 and (pts[:, :2] >= -1e-7).all() and (pts[:, :2].sum(1) <= 1 + 1e-6).all()
    assert len(np.unique(pts, axis=0)) == 1000
    again, _ = sample_hull_points(tri, 1000, seed=0)
    np.testing.assert_array_equal(pts, again)


@pytest.mark.parametrize("strategy", ["NE", "RE", "AV"])
def test_mapped_normals_match_the_sphere(scene, strategy):
    out = run(scene, strategy)
    cams, pts = scene["cams"], scene["pts"]
    gt, bound = tap_bound_deg(cams, pts, scene["n_world"], scene["mask"])
    vis = out["view_visible"]
    # per view: the fetched normal lies in the cone of its four bilinear taps (1e-4 deg: the
    # float32 output rounds a unit vector by ~1e-7 rad)
    per_view = angle_deg(out["view_normal"], gt)
    assert (per_view[vis] <= bound[vis] + 1e-4).all()
    # the merged normal: the chosen view's bound (NE, RE) or the worst visible view's (AV)
    seen = out["seen"]
    N = len(pts)
    if strategy == "AV":
        worst = torch.where(vis, bound, torch.zeros_like(bound)).amax(0)
        assert (out["chosen_view"] == -1).all()
    else:
        ch = out["chosen_view"]
        assert (ch[seen] >= 0).all() and vis[ch[seen], torch.arange(N)[seen]].all()
        worst = bound[ch.clamp_min(0), torch.arange(N)]
        # NE/RE normal *is* the chosen view's fetch, compared to that view's exact normal
        err = angle_deg(out["normal"], gt[ch.clamp_min(0), torch.arange(N)])
        assert (err[seen] <= worst[seen] + 1e-4).all()
    # nearly every point of the sphere is seen by the rig (only the bottom cap is missed)
    assert seen.float().mean() > 0.95
    # against the radial normal: away from the silhouette (view cosine >= 0.5) the fetch is
    # bilinear on a smooth field, second order in the pixel footprint. The normal turns by
    # alpha * d / R ~ 0.0193 rad/px * 2.2 / 1 ~ 2.4 deg per pixel at 64x48; require a tenth
    # of that on average (measured: NE 0.02 deg, RE 0.02, AV includes grazing views).
    radial = torch.nn.functional.normalize(torch.from_numpy(pts).double(), dim=-1)
    ang = angle_deg(out["normal"], radial)
    frontal = seen & (out["cos"] >= 0.5)
    # NE takes the most frontal view; RE (all errors equal here) the first visible one
    assert frontal.sum() > (0.5 if strategy == "NE" else 0.3) * N
    if strategy in ("NE", "RE"):
        assert ang[frontal].mean() < 0.24
        assert ang[frontal].max() < 1.0
    else:
        assert ang[frontal].mean() < 2.4


def test_far_side_is_occluded_and_front_is_visible():
    cams = Cameras.look_at([[0.0, 0.0, 3.0]], [[0.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]], 63.4, W, H,
                           dtype=torch.float64)
    hull = trimesh.creation.icosphere(subdivisions=4)
    pts, nrm = sample_hull_points(hull, 3000, seed=1)
    n1, mask, _ = sphere_maps(cams)
    out = map_features(pts, nrm, hull, cams, n1, torch.zeros(mask.shape), torch.zeros_like(mask), mask, "NE")
    vis = out["view_visible"][0].numpy()
    # nearest pixel inside the mask, independently of the module
    xy, depth = cams.project(torch.from_numpy(pts).double())
    col = xy[0, :, 0].floor().long().clamp(0, W - 1)
    row = xy[0, :, 1].floor().long().clamp(0, H - 1)
    in_mask = mask[0, row, col].numpy() & (depth[0] > 0).numpy()
    # on the unit sphere a point is visible from distance 3 iff radial . (to camera) > 1/3
    c = pts[:, 2] / np.linalg.norm(pts, axis=1)
    back = c < 0.25  # margin: the 1%-of-diagonal depth slack (0.035) admits points just past the limb
    assert (back & in_mask).sum() > 1000  # they project onto the object: only the depth test hides them
    assert not vis[back].any()
    front = c > 0.45
    np.testing.assert_array_equal(vis[front], in_mask[front])
    assert in_mask[front].mean() > 0.95
    assert (out["seen"].numpy() == vis).all()


def test_another_object_occludes():
    # a small sphere in front of a big one, camera on +z: the big sphere's facing cap behind the
    # small one is in the mask and faces the camera but is hidden
    cams = Cameras.look_at([[0.0, 0.0, 3.0]], [[0.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]], 63.4, W, H,
                           dtype=torch.float64)
    big = trimesh.creation.icosphere(subdivisions=4, radius=0.6)
    big.apply_translation([0, 0, -0.4])
    small = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    small.apply_translation([0, 0, 0.8])
    hull = trimesh.util.concatenate([big, small])
    pts, nrm = sample_hull_points(big, 2000, seed=2)
    mask = torch.ones(1, H, W, dtype=torch.bool)
    n1 = torch.zeros(1, H, W, 3, dtype=torch.float64)
    n1[..., 2] = 1.0
    out = map_features(pts, nrm, hull, cams, n1, torch.zeros(1, H, W), torch.zeros_like(mask), mask, "NE")
    vis = out["view_visible"][0].numpy()
    o = np.array([0.0, 0.0, 3.0])
    to_cam = (o - pts) / np.linalg.norm(o - pts, axis=1, keepdims=True)
    faces_cam = (nrm * to_cam).sum(1) > 0.3
    # does the segment point -> camera pass through the small sphere (centre (0,0,0.8), r 0.3)?
    rel = pts - np.array([0, 0, 0.8])
    b = (rel * to_cam).sum(1)
    disc = b * b - ((rel * rel).sum(1) - 0.3 ** 2)  # > 0: the line meets the small sphere
    behind_small = (disc > 0.01) & (b < 0)
    clear = disc < -0.01  # margins: the small sphere is a faceted icosphere
    assert (faces_cam & behind_small).sum() > 20
    assert not vis[faces_cam & behind_small].any()
    assert vis[faces_cam & clear].all()


def test_ne_picks_the_most_frontal_visible_view(scene):
    out = run(scene, "NE")
    cams, pts, nrm = scene["cams"], scene["pts"], scene["nrm"]
    to_cam = cams.origin.numpy()[:, None] - pts[None]
    to_cam /= np.linalg.norm(to_cam, axis=-1, keepdims=True)
    cos = (to_cam * nrm[None]).sum(-1)  # (V, N), independent of the module
    np.testing.assert_allclose(out["view_cos"].numpy(), cos, atol=1e-6)
    vis = out["view_visible"].numpy()
    seen = out["seen"].numpy()
    best = np.where(vis, cos, -np.inf).max(0)
    ch = out["chosen_view"].numpy()
    np.testing.assert_allclose(cos[ch[seen], np.nonzero(seen)[0]], best[seen], atol=1e-9)
    np.testing.assert_allclose(out["cos"].numpy()[seen], best[seen], atol=1e-6)
    # the most frontal view of a point well inside every silhouette is one that sees it clearly:
    # its cosine beats every view with cosine > 0.45 (those see the point whenever it is in the mask)
    clear = (cos > 0.45) & vis
    assert (best[clear.any(0)] >= np.where(clear, cos, -np.inf).max(0)[clear.any(0)] - 1e-9).all()


def test_re_prefers_low_error_and_avoids_tir(scene):
    V = scene["cams"].num_views
    # constant error per view: view 0 high, the others distinct and low
    levels = torch.tensor([1.0] + [0.01 * (v + 1) for v in range(1, V)], dtype=torch.float64)
    err = levels[:, None, None].expand(V, H, W).clone()
    out = run(scene, "RE", err=err)
    vis = out["view_visible"]
    # a mask-weighted fetch of a constant map returns the constant exactly
    np.testing.assert_allclose(out["view_error"][vis].numpy(), levels[:, None].expand(V, vis.shape[1])[vis].numpy(),
                               rtol=1e-6)
    expect = torch.where(vis, levels[:, None], torch.full_like(vis, np.inf, dtype=torch.float64)).argmin(0)
    seen = out["seen"]
    assert (out["chosen_view"][seen] == expect[seen]).all()
    multi = vis[0] & (vis.sum(0) >= 2)
    assert multi.sum() > 50 and (out["chosen_view"][multi] != 0).all()
    np.testing.assert_allclose(out["error"][seen].numpy(), levels[expect[seen]].numpy(), rtol=1e-6)

    # TIR everywhere in the best view (view 1): it loses to any TIR-free visible view even though
    # its error is the lowest
    tir = torch.zeros(V, H, W, dtype=torch.bool)
    tir[1] = True
    out2 = run(scene, "RE", err=err, tir=tir)
    vis1_and_other = vis[1] & ((vis & ~torch.nn.functional.one_hot(torch.tensor(1), V).bool()[:, None]).sum(0) > 0)
    assert vis1_and_other.sum() > 50
    assert (out2["chosen_view"][vis1_and_other] != 1).all()
    assert (out2["tir"][vis1_and_other] == 0).all()
    only1 = vis[1] & (vis.sum(0) == 1) & (out["view_cos"][1] > 0)
    assert (out2["chosen_view"][only1] == 1).all() and (out2["tir"][only1] == 1).all()

    # TIR in every view: Algorithm 1 falls back to the largest view cosine, i.e. NE, except that
    # it takes no view at all when that cosine is <= 0 (the walk starts at C = 0)
    out3 = run(scene, "RE", err=err, tir=torch.ones(V, H, W, dtype=torch.bool))
    ne = run(scene, "NE")
    expect = torch.where(ne["cos"] > 0, ne["chosen_view"], torch.full_like(ne["chosen_view"], -1))
    assert (out3["chosen_view"] == expect).all()
    assert (ne["seen"] & (ne["cos"] <= 0)).sum() > 0  # the edge case occurs here


def algorithm1_literal(visible, error, tir, cos):
    """Supplement Algorithm 1 transcribed line by line (loops), returning the chosen view
    (0-based, -1 for none)."""
    V, N = visible.shape
    chosen = []
    for i in range(N):
        p_tir, p_err, p_v, p_c = 1, 2.0, -1, 0.0
        for v in range(V):
            update = False
            if visible[v, i]:
                if tir[v, i]:
                    if p_tir == 1 and cos[v, i] > p_c:
                        update = True
                else:
                    if p_tir == 1:
                        update = True
                    elif error[v, i] < p_err:
                        update = True
            if update:
                p_tir, p_err, p_c, p_v = int(tir[v, i]), float(error[v, i]), float(cos[v, i]), v
        chosen.append(p_v)
    return np.array(chosen)


def test_re_selection_equals_algorithm1_literal():
    g = torch.Generator().manual_seed(0)
    V, N = 7, 3000
    visible = torch.rand(V, N, generator=g) < 0.5
    tir = torch.rand(V, N, generator=g) < 0.4
    # coarse levels make ties common, so the first-on-ties rule is exercised; errors above the
    # initial 2 and non-positive cosines exercise the edge cases
    error = torch.randint(0, 6, (V, N), generator=g).double() * 0.5
    cos = torch.randint(-2, 5, (V, N), generator=g).double() / 4
    got = select_rendering_error(visible, error, tir, cos).numpy()
    np.testing.assert_array_equal(got, algorithm1_literal(visible.numpy(), error.numpy(), tir.numpy(), cos.numpy()))
    ne = select_nearest(visible, cos).numpy()
    ref = np.where(visible.any(0).numpy(), np.where(visible.numpy(), cos.numpy(), -np.inf).argmax(0), -1)
    np.testing.assert_array_equal(ne, ref)


def test_av_is_the_normalized_mean_of_visible_views(scene):
    tir = torch.zeros(scene["cams"].num_views, H, W, dtype=torch.bool)
    tir[2] = True
    err = torch.arange(scene["cams"].num_views, dtype=torch.float64)[:, None, None].expand(-1, H, W).clone()
    out = run(scene, "AV", err=err, tir=tir)
    vis = out["view_visible"].double()
    seen = out["seen"]
    mean = torch.nn.functional.normalize((vis[..., None] * out["view_normal"].double()).sum(0), dim=-1)
    np.testing.assert_allclose(out["normal"][seen].numpy(), mean[seen].numpy(), atol=1e-6)
    cnt = vis.sum(0).clamp_min(1)
    mean_of = lambda per_view: ((vis * per_view).sum(0) / cnt)[seen].numpy()  # noqa: E731
    np.testing.assert_allclose(out["error"][seen].numpy(), mean_of(torch.arange(vis.shape[0])[:, None]), rtol=1e-6)
    np.testing.assert_allclose(out["tir"][seen].numpy(), mean_of(tir[:, :1, 0].double()), rtol=1e-6)
    np.testing.assert_allclose(out["cos"][seen].numpy(), mean_of(out["view_cos"].double()), atol=1e-6)


def test_unseen_points_keep_hull_normal_and_feature_layout():
    cams = Cameras.look_at([[0.0, 0.0, 3.0]], [[0.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]], 63.4, W, H,
                           dtype=torch.float32)
    hull = trimesh.creation.icosphere(subdivisions=3)
    pts, nrm = sample_hull_points(hull, 800, seed=5)
    n1, mask, _ = sphere_maps(cams.to(dtype=torch.float64))
    for strategy in ("AV", "NE", "RE"):
        out = map_features(torch.from_numpy(pts), torch.from_numpy(nrm), hull, cams, n1.float(),
                           torch.full(mask.shape, 0.3), torch.zeros_like(mask), mask, strategy)
        f = out["features"]
        assert f.shape == (800, NUM_FEATURES) and f.dtype == torch.float32
        np.testing.assert_allclose(f[:, FEATURE_COLUMNS["point"]].numpy(), pts, atol=1e-7)
        np.testing.assert_allclose(f[:, FEATURE_COLUMNS["hull_normal"]].numpy(), nrm, atol=1e-6)
        for key in ("normal", "error", "tir", "cos"):
            col = f[:, FEATURE_COLUMNS[key]]
            np.testing.assert_array_equal(col.numpy(), out[key].reshape(len(pts), -1).numpy())
        cones = silhouette_counts(pts, nrm, cams, mask).float()
        np.testing.assert_array_equal(f[:, FEATURE_COLUMNS["silhouette"]].numpy(), cones.numpy())
        unseen = ~out["seen"]
        assert unseen.sum() > 300  # the far hemisphere
        np.testing.assert_allclose(out["normal"][unseen].numpy(), nrm[unseen.numpy()], atol=1e-6)
        assert (out["error"][unseen] == UNSEEN_ERROR).all() and (out["tir"][unseen] == UNSEEN_TIR).all()
        assert (out["cos"][unseen] == UNSEEN_COS).all() and (out["chosen_view"][unseen] == -1).all()
        assert (out["visible_count"][unseen] == 0).all()
        assert torch.allclose(out["error"][~unseen], torch.tensor(0.3), atol=1e-6)


def test_silhouette_counts_match_the_cones_of_the_sphere(scene):
    """Pushed out by eps, a point of the unit sphere leaves view v's silhouette exactly when the
    ray from v's camera through it makes a larger angle with the centre than the sphere's
    silhouette cone. Where that angle is over 1.5 pixels from the cone's, all bilinear taps of the
    mask (within sqrt(2) pixels) agree, so view v adds exactly 0 or 1; a closer view adds
    something in [0, 1]. The count must lie between those bounds for every point (at 512 x 384,
    where the largest eps moves a rim point ~6 pixels, the bounds are tight)."""
    cams = scene["cams"].with_resolution(512, 384)
    _, mask, _ = sphere_maps(cams)
    g = torch.Generator().manual_seed(4)
    u = torch.nn.functional.normalize(torch.randn(3000, 3, generator=g, dtype=torch.float64), dim=-1)
    counts = silhouette_counts(u, u, cams, mask)
    assert counts.shape == (3000, len(SILHOUETTE_OFFSETS))
    pixel_angle = float(2 * cams.tan_half_fov_x.max() / cams.width)  # the largest, at the image centre
    dist = cams.origin.norm(dim=-1)[:, None]  # (V, 1)
    half_angle = torch.asin(1 / dist)  # the cone's
    to_centre = -cams.origin[:, None] / dist[..., None]
    for k, eps in enumerate(SILHOUETTE_OFFSETS):
        ray = torch.nn.functional.normalize((1 + eps) * u[None] - cams.origin[:, None], dim=-1)  # (V, N, 3)
        beyond = torch.acos((ray * to_centre).sum(-1).clamp(-1, 1)) - half_angle
        near = beyond.abs() <= 1.5 * pixel_angle
        lower = (beyond > 0).logical_and(~near).sum(0).double()
        upper = lower + near.sum(0)
        assert ((counts[:, k] >= lower - 1e-9) & (counts[:, k] <= upper + 1e-9)).all(), eps
    # Tight and informative at the largest offset: most points clearly leave two views or more.
    assert (upper - lower).mean() < 0.7 and (lower >= 2).float().mean() > 0.6
    # Farther out, no fewer cones are left.
    assert (counts[:, 1:] >= counts[:, :-1] - 1e-9).all()


def test_rejects_bad_input(scene):
    with pytest.raises(ValueError, match="strategy"):
        run(scene, "XX")
    with pytest.raises(ValueError, match="n1_cam"):
        run(scene, "NE", n1=scene["n1"][:, :-1])


def test_surface_of_exact_normals_is_the_sphere(scene):
    """Mapping + Poisson (points.stage) on exact normals gives the unit sphere back: within two
    depth-8 voxels (Poisson's isosurface sits within a voxel of exact oriented points; the hull's
    facets are up to 0.0011 inside the sphere), the capture frame restored."""
    from lookingglass.points.stage import SurfaceConfig, surface_from_normals

    centre, scale = np.array([0.3, -0.2, 0.1]), 2.0  # capture frame = unit frame x 2 + centre
    from lookingglass.hull import VisualHull
    from lookingglass.normals.predict import NormalMaps

    hull = scene["hull"].copy()
    hull.vertices = np.asarray(hull.vertices) * scale + centre
    cams = scene["cams"].transformed(torch.as_tensor(-centre / scale), 1.0 / scale)
    maps = NormalMaps(cams, scene["n1"], scene["n1"], scene["err"], scene["tir"], scene["mask"])
    mesh, oriented = surface_from_normals(VisualHull.from_mesh(hull, centre, scale), maps, SurfaceConfig(points=4000))
    assert mesh.is_watertight and len(oriented.points) == 4000 and oriented.seen.mean() > 0.95  # the rig misses a polar cap
    radius = np.linalg.norm((np.asarray(mesh.vertices) - centre) / scale, axis=1)
    voxel = 1.1 * 2 / 2 ** 8
    assert np.abs(radius - 1).max() < 2 * voxel, np.abs(radius - 1).max()


def test_point_net_runs_on_several_clouds_of_its_trained_size(scene):
    """With PNet, the hull gets ceil(points / num_points) independent even clouds of PNet's size
    (seeds seed, seed + 1, ...), refined in one batch; an untrained residual PNet moves nothing."""
    from lookingglass.points.model import PointNet, PointNetConfig
    from lookingglass.points.stage import SurfaceConfig, map_normals_to_hull

    torch.manual_seed(0)
    net = PointNet(PointNetConfig(num_points=256, centres=(64, 16, 8, 4), radii=(0.3, 0.6, 1.0, 1.6),
                                  neighbours=(8, 8, 8, 4), sa_mlps=((8, 8), (16, 16), (16, 16), (32, 32)),
                                  fp_mlps=((16,), (16,), (8,), (8, 8)), gn_group_size=4, residual=True)).eval()
    out = map_normals_to_hull(scene["hull"], scene["cams"], scene["n1"], scene["err"], scene["tir"], scene["mask"],
                              SurfaceConfig(points=600, seed=5), net)
    assert out.points.shape == (768, 3) and out.normals.shape == (768, 3)  # 3 clouds of 256
    expected = np.concatenate([sample_hull_points(scene["hull"], 256, 5 + k)[0] for k in range(3)])
    np.testing.assert_allclose(out.points, expected, atol=1e-6)


def test_smoothing_over_neighbours_keeps_a_smooth_field_and_cancels_noise(scene):
    from lookingglass.points.stage import smooth_over_neighbours

    pts = scene["pts"].astype(np.float64)  # 2000 even points on the unit sphere
    smooth = 0.05 * pts[:, :1] * np.ones((1, 3))  # varies over the shape's scale
    noise = np.random.default_rng(0).normal(0, 0.01, pts.shape)
    (out,) = smooth_over_neighbours(pts, [smooth + noise], 16)
    # a linear field is kept up to its curvature over a neighbourhood (radius ~0.1: < 5e-3 here);
    # independent noise shrinks by ~sqrt(16) = 4
    assert np.abs(smooth_over_neighbours(pts, [smooth], 16)[0] - smooth).max() < 5e-3
    assert np.std(out - smooth) < 0.01 / 3
    assert smooth_over_neighbours(pts, [noise], 1)[0] is not noise  # a copy, never the input
