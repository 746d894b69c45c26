"""The glass renderer (lookingglass.render.tracer) against Mitsuba 3, analytic optics and itself.

Runtime on the 2-core dev machine: ~40 s in all, ~33 s of it the two Mitsuba image comparisons
(marked `slow`; Mitsuba's scalar_rgb renders are kept to one 48 x 36 view); the rest ~5 s.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
import trimesh

from lookingglass.capture.images import read_envmap
from lookingglass.physics.camera import Cameras
from lookingglass.physics.environment import EnvironmentMap
from lookingglass.physics.optics import IOR_AIR, IOR_GLASS
from lookingglass.render.raycast import RayCaster, object_masks
from lookingglass.render.testshapes import radial_blob
from lookingglass.render.tracer import RenderConfig, render_views, trace_two_bounce

IOR, EXT_IOR = IOR_GLASS, IOR_AIR

# The shared map with the lowest dynamic range (max/mean 9.6 at 256 x 128; the others reach
# 20-18000): Mitsuba's variance, not ours, limits how tightly we can compare, and it grows with
# the contrast of what the glass shows. Both renderers read the very same array.
ENV_NAME = "potsdamer_platz_1k.hdr"


@pytest.fixture(scope="module")
def env_small(shared_envmaps) -> np.ndarray:
    path = next(p for p in shared_envmaps if p.name == ENV_NAME)
    env = cv2.resize(read_envmap(path), (256, 128), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(env, dtype=np.float32)


def _one_view(width: int, height: int) -> Cameras:
    return Cameras.look_at([[1.2, 1.4, 2.4]], [[0.02, -0.03, 0.01]], [[0.0, 1.0, 0.0]], 63.4, width, height)


def _views(width: int, height: int) -> Cameras:
    origin = [[1.2, 1.4, 2.4], [-2.6, 0.4, -1.3], [0.3, -2.2, 2.0]]
    target = [[0.02, -0.03, 0.01], [0.0, 0.05, 0.0], [-0.03, 0.0, 0.02]]
    up = [[0.0, 1.0, 0.0], [0.1, 1.0, 0.05], [0.0, 0.7, 0.7]]
    return Cameras.look_at(origin, target, up, 63.4, width, height)


def _sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=5)  # radius 1, 20480 faces


def _torus() -> trimesh.Trimesh:
    return trimesh.creation.torus(0.7, 0.3, major_sections=128, minor_sections=64)


def _rel_mae(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """mean |a - b| / mean b over the masked pixels and all channels."""
    return float(np.abs(a[mask] - b[mask]).mean() / b[mask].mean())


# ---------------------------------------------------------------------------------------------
# full light transport vs Mitsuba 3
# ---------------------------------------------------------------------------------------------
@pytest.mark.slow  # ~8 s per shape on an idle 2-core machine (~25 s loaded), almost all Mitsuba
@pytest.mark.parametrize("shape", ["sphere", "blob"])
def test_image_matches_mitsuba(shape, env_small):
    """Inside the mask, our deterministic-branching image equals Mitsuba's `path` render of the
    same smooth dielectric, to a relative MAE of 3 %.

    Why 3 % and how it splits: Mitsuba samples one Fresnel branch per bounce and its pixels on
    a uniform random grid, so even its 2 x 4096-spp reference is noisy. Its own noise is
    measured from two renders with different seeds: their relative MAE e_pair is ~3.1 %
    (sphere) and ~2.7 % (blob) at 48 x 36 with this map (4.4 % and 3.8 % at 2048 spp), so
    each is ~e_pair/sqrt 2 from the truth and their average, our reference, ~e_pair/2 ~ 1.5 %.
    Our 24 x 24 stratified samples with deterministic Fresnel branching are nearly converged
    (pruning bias ~1e-4), so our error vs the reference should sit at that noise floor, and
    does (printed). We assert (1) relMAE <= 3 % (the brief's target; ~2x the noise floor),
    (2) our excess over the floor, sqrt(err^2 - (e_pair/2)^2), <= 1 %, and (3) the mean over
    the mask, where the noise averages out, agrees to 0.5 % (measured <= 0.1 %): a Fresnel,
    depth or energy error would show there. Mitsuba's seeds are fixed: no flakiness.
    Max depth: 24 interfaces for us = Mitsuba's max_depth 25 (it counts the emitter vertex).
    """
    mitsuba_ref = pytest.importorskip("mitsuba_ref")
    mesh = _sphere() if shape == "sphere" else radial_blob(0)
    cams = _one_view(48, 36)
    depth = 24
    spp = 4096
    a = mitsuba_ref.render_glass(mesh, env_small, cams, IOR, EXT_IOR, spp, max_depth=depth + 1, seed=0)
    b = mitsuba_ref.render_glass(mesh, env_small, cams, IOR, EXT_IOR, spp, max_depth=depth + 1, seed=1)
    ref = 0.5 * (a + b)
    env = EnvironmentMap(torch.from_numpy(env_small))
    ours = render_views(mesh, env, cams, RenderConfig(samples_per_axis=24, max_depth=depth))
    img, mask = ours.image.numpy(), ours.mask.numpy()

    e_pair = _rel_mae(a, b, mask)
    err = _rel_mae(img, ref, mask)
    excess = math.sqrt(max(err ** 2 - (e_pair / 2) ** 2, 0.0))
    bias = float(img[mask].mean() / ref[mask].mean() - 1)
    print(f"\n{shape}: relMAE vs Mitsuba {err:.4f}, Mitsuba seed-vs-seed {e_pair:.4f} "
          f"(reference noise ~{e_pair / 2:.4f}), excess {excess:.4f}, mean bias {bias:+.4f}, "
          f"pruned {ours.stats.pruned_energy:.1e}, truncated {ours.stats.truncated_energy:.1e}")
    assert err <= 0.03
    assert excess <= 0.01
    assert abs(bias) <= 0.005

    # Pixels well away from the object (its mask dilated by 2 px) show the box-filtered
    # environment; only anti-aliasing noise remains there.
    near = cv2.dilate(mask[0].astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)[None]
    bg = ~near
    assert _rel_mae(img, ref, bg) <= 0.01


@pytest.mark.slow  # ~5 s
def test_max_depth_semantics_match_mitsuba(env_small):
    """Our max_depth counts interfaces, Mitsuba's path vertices: ours D = Mitsuba D + 1. At D = 2
    the blob loses ~5 % of its energy to truncation, so a mismatch of one would show far above
    the 1 % tolerance on the masked mean (noise in the mean is ~0.1 % at 512 spp)."""
    mitsuba_ref = pytest.importorskip("mitsuba_ref")
    mesh = radial_blob(0)
    cams = _one_view(48, 36)
    ref = mitsuba_ref.render_glass(mesh, env_small, cams, IOR, EXT_IOR, 512, max_depth=3, seed=3)
    ours = render_views(mesh, EnvironmentMap(torch.from_numpy(env_small)), cams,
                        RenderConfig(samples_per_axis=12, max_depth=2))
    mask = ours.mask.numpy()
    assert ours.stats.truncated_energy > 0.01  # the check has teeth
    bias = ours.image.numpy()[mask].mean() / ref[mask].mean() - 1
    assert abs(bias) <= 0.01, bias


# ---------------------------------------------------------------------------------------------
# energy
# ---------------------------------------------------------------------------------------------
def test_white_environment_sphere_renders_one():
    """Clear glass conserves energy: under a constant unit environment every pixel is 1.

    Losses can only come from pruning (given back by the rest term, exact for a constant map)
    and from paths still bouncing after max_depth interfaces. On a sphere the latter are grazing
    silhouette samples: the interpolated normal there can face away from a ray that hits a
    front-facing triangle, so the ray counts as leaving the glass, is totally reflected into the
    sphere at a grazing angle and circles in a whispering-gallery TIR loop (Mitsuba, deciding
    the side by the same shading normal, loses them too). We allow that on silhouette pixels
    only: at most 1 % of the object's pixels off by > 1e-3, and the background exact away from
    the silhouette."""
    white = EnvironmentMap(torch.ones(32, 64, 3))
    res = render_views(_sphere(), white, _views(64, 48), RenderConfig())
    img, mask = res.image, res.mask
    near = torch.from_numpy(np.stack([cv2.dilate(m.numpy().astype(np.uint8), np.ones((3, 3), np.uint8))
                                      for m in mask]).astype(bool))
    assert float((img[~near] - 1).abs().max()) <= 1e-6
    inside = img[mask]
    assert float(inside.max()) <= 1 + 1e-5
    assert abs(float(inside.mean()) - 1) <= 1e-4
    assert float((inside < 1 - 1e-3).any(-1).float().mean()) <= 0.01
    # Without the rest term the pruning loss shows, and it is small.
    res = render_views(_sphere(), white, _views(64, 48), RenderConfig(prune_rest=False))
    assert abs(float(res.image[res.mask].mean()) - 1) <= 1e-3


@pytest.mark.parametrize("shape", ["blob", "torus"])
def test_energy_bookkeeping(shape):
    """Under a unit environment the image mean is exactly 1 minus the truncated energy (all
    pixels, rest term on): every unit of sample throughput either escapes, is pruned (rest term)
    or is truncated, whatever the shape."""
    mesh = radial_blob(1) if shape == "blob" else _torus()
    white = EnvironmentMap(torch.ones(16, 32, 3))
    res = render_views(mesh, white, _views(40, 30), RenderConfig(max_depth=16))
    assert res.stats.truncated_energy > 0
    np.testing.assert_allclose(float(res.image.double().mean()), 1 - res.stats.truncated_energy, atol=2e-6)


# ---------------------------------------------------------------------------------------------
# two-bounce maps
# ---------------------------------------------------------------------------------------------
def _analytic_sphere(o: np.ndarray, d: np.ndarray, eta: float):
    """Two-bounce path through the unit sphere at the origin for rays (N, 3) (float64).

    Returns hit (N,), p1, n1, p2, n2, exit direction (N, 3). Snell in vector form,
    t = eta d + (eta c - sqrt(1 - eta^2 (1 - c^2))) n with c = -d.n, written out here rather than
    taken from physics.optics so the check is independent."""
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - 1)
    hit = disc > 0
    t = -b - np.sqrt(np.maximum(disc, 0))  # misses get garbage rows, masked out by the caller
    p1 = o + t[:, None] * d
    n1 = p1 / np.linalg.norm(p1, axis=-1, keepdims=True)

    def snell(v, n, e):
        c = -(v * n).sum(-1, keepdims=True)
        return e * v + (e * c - np.sqrt(np.maximum(1 - e * e * (1 - c * c), 0))) * n

    t1 = snell(d, n1, eta)
    p2 = p1 - 2 * (p1 * t1).sum(-1, keepdims=True) * t1  # the chord of the unit sphere
    n2 = p2 / np.linalg.norm(p2, axis=-1, keepdims=True)
    t2 = snell(t1, -n2, 1 / eta)
    return hit, p1, n1, p2, n2, t2


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle in degrees, via atan2 in float64 (acos of a float32 dot bottoms out at 0.02 deg)."""
    a, b = a.double(), b.double()
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1)))


def test_two_bounce_sphere_matches_analytic():
    """N1, N2, P1, P2 and the exit ray of an icosphere agree with the analytic sphere.

    The icosphere gets exactly radial vertex normals (trimesh's area-weighted ones are off by up
    to 0.075 deg at subdivision 5, an error of the mesh, not of the tracer); the interpolated
    normal at a point p of a face is then exactly p/|p|. What remains is the facet error:
    subdivision 5 has edges of ~0.035-0.041, so faces lie up to ~2e-4 inside the unit sphere,
    moving P1 by ~2e-4 / cos(incidence) along the ray and tilting N1 by ~2e-4 tan(incidence)
    rad. Within an impact parameter of 0.95 (incidence <= 72 deg): N1 within 0.05 deg; the error
    carried across the chord: N2 within 0.1 deg, exit ray within 0.2 deg; medians 5x smaller."""
    cams = _views(96, 72).to(dtype=torch.float64)
    ico = _sphere()
    radial = ico.vertices / np.linalg.norm(ico.vertices, axis=1, keepdims=True)
    sphere = trimesh.Trimesh(ico.vertices, ico.faces, vertex_normals=radial, process=False)
    assert np.allclose(sphere.vertex_normals, radial)
    two = trace_two_bounce(sphere, cams, IOR, EXT_IOR)
    o, d = cams.pixel_rays()
    o, d = o.reshape(-1, 3).numpy(), d.reshape(-1, 3).numpy()
    impact = np.linalg.norm(np.cross(o, d), axis=-1)
    _, p1, n1, p2, n2, t2 = _analytic_sphere(o, d, EXT_IOR / IOR)
    core = torch.from_numpy((impact < 0.95).reshape(two.mask.shape))
    shape = (*two.mask.shape, 3)
    as_cam = lambda v: cams.world_to_camera(torch.from_numpy(v.reshape(shape)))  # noqa: E731

    assert bool(two.mask[core].all())
    assert not bool(two.mask[torch.from_numpy((impact > 1.0).reshape(two.mask.shape))].any())
    e1 = _angle_deg(two.normal1, as_cam(n1))[core]
    e2 = _angle_deg(two.normal2, as_cam(n2))[core]
    ex = _angle_deg(two.exit_dir.double(), torch.from_numpy(t2.reshape(shape)))[core]
    print(f"\nN1 err max {e1.max():.4f} med {e1.median():.4f} deg; N2 max {e2.max():.4f} "
          f"med {e2.median():.4f}; exit max {ex.max():.4f}")
    assert float(e1.max()) < 0.08 and float(e1.median()) < 0.02
    assert float(e2.max()) < 0.1 and float(e2.median()) < 0.02
    assert float(ex.max()) < 0.2 and float(ex.median()) < 0.04
    dp1 = (two.point1.double() - torch.from_numpy(p1.reshape(shape))).norm(dim=-1)[core]
    dp2 = (two.point2.double() - torch.from_numpy(p2.reshape(shape))).norm(dim=-1)[core]
    assert float(dp1.max()) < 1e-3 and float(dp2.max()) < 3e-3
    # Depth along the forward axis, as Cameras.project measures it.
    _, z1 = cams.project(two.point1.double().reshape(cams.num_views, -1, 3))
    assert torch.allclose(two.depth1.double()[two.mask], z1.view(two.mask.shape)[two.mask], atol=1e-5)
    # Camera frame: normals at P1 face the camera (z > 0), and the outward N2 looks away.
    assert bool((two.normal1[core][:, 2] > 0).all())
    # A convex shape without TIR: every core pixel is a valid two-bounce pixel.
    assert bool(two.valid[core].all()) and not bool(two.tir.any())


def test_two_bounce_torus_flags():
    """On a torus, exit rays that hit the object again and TIR at P2 are flagged invalid."""
    mesh = _torus()
    cams = _views(80, 60)
    two = trace_two_bounce(mesh, cams, IOR, EXT_IOR)
    assert not bool((two.valid & ~two.mask).any())
    assert not bool((two.tir & ~two.hit2).any())
    assert not bool((two.valid & two.tir).any())
    # Re-check re-entry with the independent RayCaster.intersect.
    caster = RayCaster(mesh)
    sel = two.hit2 & ~two.tir & (two.exit_dir.norm(dim=-1) > 0)
    again = caster.intersect(two.point2[sel].numpy(), two.exit_dir[sel].numpy(), offset=True).hit
    assert np.array_equal(two.valid[sel].numpy(), ~again)
    assert again.sum() > 20 and int(two.tir.sum()) > 20  # the torus exercises both flags
    # Outward normals: compare with the torus's analytic outward normal (axis z, R = 0.7).
    for n_cam, p, where in ((two.normal1, two.point1, two.mask), (two.normal2, two.point2, two.hit2)):
        n, p = cams.camera_to_world(n_cam)[where], p[where]
        ring = torch.nn.functional.normalize(p * p.new_tensor([1.0, 1.0, 0.0]), dim=-1) * 0.7
        out = torch.nn.functional.normalize(p - ring, dim=-1)
        assert float((n * out).sum(-1).min()) > 0.99


def test_mask_matches_object_masks():
    for mesh in (radial_blob(2), _torus()):
        cams = _views(80, 60)
        two = trace_two_bounce(mesh, cams, IOR, EXT_IOR)
        assert np.array_equal(two.mask.numpy(), object_masks(mesh, cams))


def test_render_views_reuses_two_bounce():
    mesh = radial_blob(3)
    cams = _views(40, 30)
    env = EnvironmentMap(torch.rand(16, 32, 3))
    res = render_views(mesh, env, cams, RenderConfig(samples_per_axis=1))
    two = trace_two_bounce(mesh, cams, IOR, EXT_IOR)
    for name in ("mask", "normal1", "normal2", "point1", "point2", "depth1", "depth2", "tir"):
        assert torch.equal(getattr(res, name), getattr(two, name)), name
    assert torch.equal(res.two_bounce_valid, two.valid)
    assert res.image.shape == (3, 30, 40, 3) and res.image.dtype == torch.float32


def test_deterministic_per_seed():
    mesh = radial_blob(4)
    cams = _views(40, 30)
    env = EnvironmentMap(torch.rand(16, 32, 3))
    a = render_views(mesh, env, cams, RenderConfig(seed=7)).image
    b = render_views(mesh, env, cams, RenderConfig(seed=7)).image
    c = render_views(mesh, env, cams, RenderConfig(seed=8)).image
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    assert float((a - c).abs().mean() / a.mean()) < 0.1


@pytest.mark.parametrize("spp, chunk_rays", [(1, 1 << 20), (2, 1 << 20), (2, 3000)])
def test_region_traces_its_pixels_as_the_whole_image_does(spp, chunk_rays):
    """render_views(region=R) traces only the samples of R and of the silhouette, each along the
    path the whole image's render takes (the same image there: bit for bit where the samples fit
    one wavefront, to float rounding where later blocks join it), and the others see the
    environment along their camera ray: fewer rays, the same comparison with photos (which reads
    masks | silhouettes only, render/compare.py)."""
    mesh = radial_blob(6)
    cams = _views(40, 30)
    env = EnvironmentMap(torch.rand(16, 32, 3))
    config = RenderConfig(samples_per_axis=spp, threads=2, chunk_rays=chunk_rays)
    whole = render_views(mesh, env, cams, config)
    region = torch.zeros(3, 30, 40, dtype=torch.bool)
    region[:, 5:12, 8:30] = True  # a block of background and of the object
    part = render_views(mesh, env, cams, config, region=region)
    traced = region | whole.mask
    if chunk_rays >= 3 * 30 * 40 * spp * spp:
        assert torch.equal(part.image[traced], whole.image[traced])
    else:  # the wavefront is refilled: a pixel's contributions may be summed in another order
        assert torch.allclose(part.image[traced], whole.image[traced], rtol=1e-5, atol=1e-6)
        assert not torch.allclose(part.image[traced], whole.image[traced] * 1.01, rtol=1e-5, atol=1e-6)
    assert part.stats.rays_cast < 0.8 * whole.stats.rays_cast
    # outside it, where the mesh is far from every sample (not a neighbour of a silhouette pixel),
    # the image is the environment in the pixel's direction, as the whole render has it there
    near = torch.nn.functional.max_pool2d(whole.mask.float()[:, None], 3, 1, 1)[:, 0].bool()
    far = ~traced & ~near
    assert far.sum() > 1000 and torch.allclose(part.image[far], whole.image[far], rtol=1e-6, atol=1e-6)


def test_thread_count_changes_only_rounding():
    """Samples are fixed by (seed, view, index), not by which worker draws them."""
    mesh = radial_blob(5)
    cams = _views(40, 30)
    env = EnvironmentMap(torch.rand(16, 32, 3))
    one = render_views(mesh, env, cams, RenderConfig(threads=1, chunk_rays=20000)).image
    two = render_views(mesh, env, cams, RenderConfig(threads=2)).image
    assert torch.allclose(one, two, rtol=1e-5, atol=1e-6)


def test_config_validation():
    with pytest.raises(ValueError):
        RenderConfig(max_depth=0)
    with pytest.raises(ValueError):
        RenderConfig(samples_per_axis=0)
    with pytest.raises(ValueError):
        RenderConfig(prune_threshold=1.5)
    assert RenderConfig(samples_per_axis=3).samples_per_pixel == 9
    assert RenderConfig().max_depth >= 8
    inverted = _sphere()
    inverted.invert()
    with pytest.raises(ValueError, match="inward"):
        trace_two_bounce(inverted, _views(8, 6))


def test_ray_caster_reuses_a_face_set_only_when_it_is_the_same(monkeypatch):
    """Scenes built from the same vertices and different faces of one shape (the kept face tuples
    must not stand in for another set), against the exact answer: a ray along -z through (0.1, 0.3)
    hits the triangle in z = 0 at t = 1 (weights 0.6, 0.1, 0.3 of vertices 0, 1, 2, in the faces' order)
    and misses the one in z = 0.5 that lies beside it. Then the same with the kept sets bounded, and
    with a mesh too large for them (built from plain arrays)."""
    from lookingglass.render import raycast

    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 0.5], [3, 2, 0.5], [2, 3, 0.5]], float)
    origin, direction = np.array([[0.1, 0.3, 1.0]]), np.array([[0.0, 0.0, -1.0]])
    cases = [([[0, 1, 2]], [0.6, 0.1, 0.3]), ([[3, 4, 5]], None), ([[0, 1, 2]], [0.6, 0.1, 0.3]),
             ([[2, 1, 0]], [0.3, 0.1, 0.6]), ([[1, 2, 0]], [0.1, 0.3, 0.6])]
    for kept, largest in [(3, 400_000), (1, 400_000), (3, 0)]:
        monkeypatch.setattr(raycast, "_FACE_TUPLES_KEPT", kept)
        monkeypatch.setattr(raycast, "_FACE_TUPLES_MAX_FACES", largest)
        raycast._FACE_TUPLES.clear()
        for faces, bary in cases:
            hits = RayCaster.of(vertices, np.array(faces)).intersect(origin, direction)
            assert bool(hits.hit[0]) == (bary is not None)
            if bary is not None:
                assert hits.t[0] == pytest.approx(1.0, abs=1e-6)
                np.testing.assert_allclose(hits.bary[0], bary, atol=1e-6)
                np.testing.assert_allclose(hits.point[0], [0.1, 0.3, 0.0], atol=1e-6)
        assert len(raycast._FACE_TUPLES) == (0 if largest == 0 else min(kept, 4))
