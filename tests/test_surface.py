"""Screened Poisson surfaces from exact oriented points (lookingglass.surface).

Tolerances. At depth 8 MeshLab's octree spans 1.1 x the points' bounding box in 2^8 cells, so a
voxel is h = 1.1 x 2 / 256 = 0.0086 for the unit sphere and the torus below (both 2 wide).
Poisson's isosurface is extracted per voxel, so exact points and normals should give vertices
well within one voxel of the true surface (measured: max 0.0011, mean 0.0002).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from lookingglass.errors import LookingGlassError
from lookingglass.hull import VisualHull
from lookingglass.metrics import shape_metrics
from lookingglass.normals.predict import NormalMaps
from lookingglass.surface import poisson_surface

VOXEL = 1.1 * 2.0 / 2 ** 8  # depth 8, 2-wide bounding box


def sphere_points(n: int, seed: int, radius: float = 1.0, centre=(0.0, 0.0, 0.0)):
    """n area-uniform points on a sphere and their outward unit normals."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(centre) + radius * d, d


def torus_points(n: int, seed: int, major: float = 0.7, minor: float = 0.3):
    """n area-uniform points on a torus around z (area element (R + r cos v) du dv, by rejection)
    and their outward unit normals."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(0, 2 * np.pi, 4 * n)
    v = rng.uniform(0, 2 * np.pi, 4 * n)
    keep = rng.uniform(0, major + minor, 4 * n) < major + minor * np.cos(v)
    u, v = u[keep][:n], v[keep][:n]
    ring = np.stack([np.cos(u), np.sin(u), np.zeros_like(u)], axis=1)
    normal = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    return major * ring + minor * normal, normal


@pytest.fixture(scope="module")
def sphere_surface():
    p, n = sphere_points(8000, seed=0)
    return poisson_surface(p, n, depth=8)


def test_sphere_is_watertight_and_within_a_voxel(sphere_surface):
    m = sphere_surface
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert m.euler_number == 2  # one closed genus-0 surface
    err = np.abs(np.linalg.norm(m.vertices, axis=1) - 1.0)
    assert err.max() < VOXEL
    assert err.mean() < VOXEL / 8
    assert abs(m.volume / (4 / 3 * np.pi) - 1) < 3 * VOXEL  # volume: ~3 x (radial error)
    meta = m.metadata["poisson"]
    assert meta["components"] == 1 and meta["far_faces"] == 0 and meta["points_used"] == 8000


def test_sphere_chamfer_is_at_the_metric_sampling_floor(sphere_surface):
    gt = trimesh.creation.icosphere(subdivisions=6)  # within 3e-4 of the true sphere
    metrics = shape_metrics(sphere_surface, gt)
    # lookingglass.metrics: a perfect unit sphere scores CD 2.00 +- 0.02 at 20k samples; the
    # surface's own error (~2e-4) adds ~1e-7 x 1e4, nothing at this precision
    assert 1.9 < metrics["cd"] < 2.1, metrics
    assert metrics["cdn_mean"] < 2.0, metrics  # nearest-sample normal noise, not surface error


def test_torus_is_watertight_genus_one_and_within_a_voxel():
    R, r = 0.7, 0.3
    p, n = torus_points(8000, seed=1, major=R, minor=r)
    m = poisson_surface(torch.from_numpy(p), torch.from_numpy(n), depth=8)  # torch input too
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert m.euler_number == 0  # genus 1: the hole was not closed
    V = np.asarray(m.vertices)
    dist = np.abs(np.hypot(np.hypot(V[:, 0], V[:, 1]) - R, V[:, 2]) - r)
    assert dist.max() < VOXEL
    assert dist.mean() < VOXEL / 8
    assert abs(m.volume / (2 * np.pi ** 2 * R * r * r) - 1) < 0.01


def test_far_component_outside_the_hull_is_dropped_near_ones_kept():
    # the real object: a sphere of radius 0.5; a bigger spurious blob of points at x = 2.5, outside
    # the hull, would win "largest component" without the hull test
    p1, n1 = sphere_points(3000, seed=2, radius=0.5)
    p2, n2 = sphere_points(3000, seed=3, radius=0.7, centre=(2.5, 0.0, 0.0))
    hull = trimesh.creation.icosphere(subdivisions=3, radius=0.6)
    pts, nrm = np.concatenate([p1, p2]), np.concatenate([n1, n2])
    m = poisson_surface(pts, nrm, depth=7, hull=hull)
    assert m.is_watertight and m.metadata["poisson"]["components"] == 2
    assert m.metadata["poisson"]["components_dropped"] == 1
    voxel = 1.1 * 3.7 / 2 ** 7  # the box spans both spheres
    assert np.abs(np.linalg.norm(m.vertices, axis=1) - 0.5).max() < voxel
    # without a hull both are near the data, and both are kept (a thin part that Poisson cut off
    # is real surface): two bodies, each a closed sphere within a voxel
    m2 = poisson_surface(pts, nrm, depth=7)
    assert m2.is_watertight and m2.body_count == 2 and m2.metadata["poisson"]["components_dropped"] == 0
    volume = 4 / 3 * np.pi * (0.5 ** 3 + 0.7 ** 3)
    assert abs(m2.volume / volume - 1) < 3 * voxel / 0.5  # volume error ~ 3 x relative radius error


def test_a_cavity_stays_a_cavity():
    """A hollow ball (outer radius 1, an air pocket of radius 0.5 whose points' normals face into it):
    two bodies, the pocket wound inward, so the solid's volume is 4/3 pi (1 - 0.5^3); wound outward
    like a second solid (trimesh's multibody fix alone) it would be 4/3 pi (1 + 0.5^3)."""
    p1, n1 = sphere_points(6000, seed=4)
    p2, n2 = sphere_points(3000, seed=5, radius=0.5)
    m = poisson_surface(np.concatenate([p1, p2]), np.concatenate([n1, -n2]), depth=8)
    assert m.is_watertight and m.body_count == 2
    volume = 4 / 3 * np.pi * (1 - 0.5 ** 3)
    assert abs(m.volume / volume - 1) < 3 * VOXEL / 0.5, m.volume  # 3 x the pocket's relative radius error
    inner = min(m.split(only_watertight=False), key=lambda body: body.area)
    assert inner.volume < 0 and np.abs(np.linalg.norm(inner.vertices, axis=1) - 0.5).max() < VOXEL


def test_inward_normals_smoothing_and_invalid_rows():
    p, n = sphere_points(2000, seed=4)
    p[:5] = np.nan  # dropped, and counted
    m = poisson_surface(p, -n, depth=6, smooth_iterations=5)
    # Poisson of inward normals is the same surface inside out: the result is re-oriented
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert m.metadata["poisson"]["points_dropped"] == 5
    # Taubin smoothing does not shrink: still within a depth-6 voxel of the sphere
    assert np.abs(np.linalg.norm(m.vertices, axis=1) - 1).max() < 1.1 * 2 / 2 ** 6


def test_errors():
    p, n = sphere_points(10, seed=5)
    with pytest.raises(LookingGlassError, match="at least"):
        poisson_surface(p, n)
    with pytest.raises(ValueError, match="shape"):
        poisson_surface(p[:, :2], n[:, :2])


def test_genus_counts_handles_over_bodies():
    from lookingglass.points.stage import genus

    sphere = trimesh.creation.icosphere(subdivisions=2)
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    far_torus = torus.copy()
    far_torus.apply_translation([5, 0, 0])
    assert genus(sphere) == 0 and genus(torus) == 1
    assert genus(trimesh.util.concatenate([torus, far_torus])) == 2
    assert genus(trimesh.util.concatenate([sphere, far_torus])) == 1


# ---- close_narrow_tunnels ----------------------------------------------------------------------
# A 1 x 1 x 0.6 box drilled along z by a cylinder, meshed finely (0.01) from its exact signed
# distance. The closing below uses a grid step PITCH = 0.02 and a ball of 2 steps: a tunnel of
# diameter 0.04 (narrower than the ball's 0.08) must be filled, one of 0.3 must stay open.
PITCH = 0.02


def carved_box(carve, half_height: float = 0.3) -> trimesh.Trimesh:
    """The box (1 x 1 x 2 half_height) minus the solid where carve(x, y, z) < 0 (a signed distance,
    negative inside the cut), meshed by marching cubes at 0.01 from the exact distance."""
    from skimage.measure import marching_cubes

    step = 0.01
    axis = np.arange(-0.6, 0.6, step) + 0.0037  # no node exactly on a face: no degenerate triangles
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    q = np.abs(np.stack([x, y, z])) - np.array([0.5, 0.5, half_height])[:, None, None, None]
    box = np.linalg.norm(np.maximum(q, 0), axis=0) + np.minimum(q.max(axis=0), 0)
    vertices, faces, _, _ = marching_cubes(np.maximum(box, -carve(x, y, z)), 0.0, spacing=(step,) * 3)
    mesh = trimesh.Trimesh(vertices + axis[0], faces)
    mesh.fix_normals()
    return mesh


def drilled_box(tunnel_radius: float, half_height: float = 0.3) -> trimesh.Trimesh:
    return carved_box(lambda x, y, z: np.hypot(x, y) - tunnel_radius, half_height)  # minus a cylinder along z


@pytest.mark.parametrize("tunnel_radius, genus_after", [(0.02, 0), (0.15, 1)])
def test_closing_fills_narrow_tunnels_and_keeps_wide_ones(tunnel_radius, genus_after):
    from lookingglass.points.stage import genus
    from lookingglass.surface import close_narrow_tunnels

    drilled = drilled_box(tunnel_radius)
    assert drilled.is_watertight and genus(drilled) == 1
    closed = close_narrow_tunnels(drilled, PITCH, radius=2)
    assert closed.is_watertight and closed.is_winding_consistent and closed.volume > 0
    assert genus(closed) == genus_after
    # Where nothing was filled the surface stays put: every vertex of the result lies on the
    # drilled box to a fraction of the grid step (the filled tunnel's plug lies inside the tunnel,
    # within its radius of the wall).
    distance = np.abs(trimesh.proximity.signed_distance(drilled, closed.vertices))
    plug = np.hypot(closed.vertices[:, 0], closed.vertices[:, 1]) < tunnel_radius
    assert np.median(distance[~plug]) < 0.05 * PITCH and distance[~plug].max() < 0.5 * PITCH
    if genus_after == 0:
        assert plug.any() and distance[plug].max() <= tunnel_radius + PITCH
        # the whole tunnel is filled (0.6 long): the volume is the undrilled box's, re-meshed alike
        # (marching cubes shaves the box's edges by about a grid step's triangle, the same in both),
        # but for the plug's two ends, each of which may sink by up to a step over the mouth
        solid = close_narrow_tunnels(drilled_box(0.0), PITCH, radius=2)
        tunnel = np.pi * tunnel_radius ** 2 * 0.6
        mouths = 2 * np.pi * (tunnel_radius + PITCH) ** 2 * PITCH
        assert mouths < 0.3 * tunnel and abs(closed.volume - solid.volume) < mouths
    else:
        assert closed.metadata["closing"]["cells_added"] == 0


def test_closing_keeps_a_sphere_to_a_fraction_of_the_grid_step():
    """The grid holds distances to tangent planes of dense samples, not occupancy: the re-meshed
    sphere's radius error is a small fraction of the step (occupancy would give ~ a quarter step)."""
    from lookingglass.surface import close_narrow_tunnels

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    closed = close_narrow_tunnels(sphere, PITCH, radius=2)
    error = np.abs(np.linalg.norm(closed.vertices, axis=1) - 0.5)
    assert error.mean() < 0.02 * PITCH and error.max() < 0.1 * PITCH
    assert closed.metadata["closing"]["cells_added"] == 0


def test_signed_distance_grid_keeps_a_pocket_behind_a_narrow_neck_outside():
    """A chamber inside a box, open to the outside only by a slit narrower than the grid's
    near-surface band: the band cuts the chamber off, but its walls face into it, so it stays
    outside (the rule "cut off by the band means inside" would fill it, as it filled a slit
    handle's hole on a test scene). Re-meshing without closing (radius 0: the grid alone) keeps
    the volume. (A closing by a ball wider than the slit seals it and fills the chamber, by design.)"""
    from lookingglass.surface import close_narrow_tunnels, signed_distance_grid

    def chamber_and_slit(x, y, z):
        chamber = np.sqrt(x ** 2 + y ** 2 + z ** 2) - 0.2
        slit = np.maximum(np.maximum(np.abs(x) - 0.0125, np.abs(y) - 0.1), -z)  # 0.025 wide, chamber to top
        return np.minimum(chamber, slit)

    mesh = carved_box(chamber_and_slit)
    assert mesh.is_watertight and mesh.volume > 0

    field, lo = signed_distance_grid(mesh, PITCH, margin=3)

    def at(point):
        i = np.round((np.asarray(point) - lo) / PITCH).astype(int)
        return field[tuple(i)]

    assert at((0, 0, -0.1)) > 0  # in the chamber, below the slit, farther than the band from any wall
    assert at((0.3, 0.3, 0.0)) < 0 and at((0.3, 0.3, 0.34)) > 0  # in the solid; above the box

    remeshed = close_narrow_tunnels(mesh, PITCH, radius=0)
    chamber_volume = 4 / 3 * np.pi * 0.2 ** 3
    assert abs(remeshed.volume - mesh.volume) < 0.1 * chamber_volume


def surface_stage_on(monkeypatch, poisson: trimesh.Trimesh, center: np.ndarray, scale: float) -> trimesh.Trimesh:
    """The mesh surface_from_normals makes when screened Poisson returns `poisson` (in the hull's
    frame): feature mapping and Poisson are stubbed out, the rest of the stage runs."""
    from lookingglass.points import stage

    points = np.zeros((4, 3), np.float32)

    class Unmoved:  # the cameras only need moving to the CPU and into the hull's frame
        def transformed(self, center, scale):
            return self

        def to(self, device):
            return self

    monkeypatch.setattr(stage, "map_normals_to_hull",
                        lambda *args, **kwargs: stage.OrientedPoints(points, points, np.ones(4, bool), points))
    monkeypatch.setattr(stage, "_poisson", lambda *args: poisson.copy())
    sphere = trimesh.creation.icosphere()
    hull = VisualHull.from_mesh(trimesh.Trimesh(sphere.vertices * scale + center, sphere.faces), center, scale)
    empty = torch.zeros(0)
    maps = NormalMaps(Unmoved(), empty, empty, empty, empty, empty)
    mesh, _ = stage.surface_from_normals(hull, maps, stage.SurfaceConfig())
    return mesh


@pytest.mark.parametrize("tunnel_radius, closed", [(0.01, True), (0.15, False), (None, False)])
def test_surface_stage_fills_poissons_narrow_tunnels(monkeypatch, tunnel_radius, closed):
    """surface_from_normals closes a Poisson surface's tunnels narrower than the closing ball
    (SurfaceConfig.close_radius Poisson voxels, 0.0086 each at depth 8: 0.034 wide at 2), keeps a
    wide one, and hands a genus-0 surface through untouched (a drilled plate 0.06 thick, such as
    sheets pushed through each other leave, stands in for Poisson's surface; None: undrilled)."""
    from lookingglass.points import stage

    poisson = drilled_box(0.0 if tunnel_radius is None else tunnel_radius, half_height=0.03)
    poisson.metadata["poisson"] = {"depth": 8}  # Poisson's own report, kept on the closed surface too
    center, scale = np.array([1.0, 2.0, 3.0]), 2.0
    mesh = surface_stage_on(monkeypatch, poisson, center, scale)
    assert stage.genus(mesh) == (0 if closed or tunnel_radius is None else 1)
    assert ("closing" in mesh.metadata) == (tunnel_radius is not None)
    assert mesh.metadata["poisson"] == {"depth": 8}
    if tunnel_radius is None:  # untouched, moved back into the capture's frame
        np.testing.assert_allclose(mesh.vertices, poisson.vertices * scale + center)
    else:
        assert mesh.metadata["closing"]["genus_before"] == 1
        assert mesh.metadata["closing"]["genus_after"] == stage.genus(mesh)
        assert mesh.metadata["closing"]["applied"] == closed
        if closed:  # the plug buried the tunnel's wall, at most half the plate's thickness deep
            assert mesh.metadata["closing"]["buried_voxels"] <= 0.03 / stage.poisson_voxel(8) + 1
        if not closed:  # the kept surface is Poisson's, moved back into the capture's frame
            np.testing.assert_allclose(mesh.vertices, poisson.vertices * scale + center)
        np.testing.assert_allclose(mesh.bounds, poisson.bounds * scale + center, atol=0.01 * scale)
    with pytest.raises(ValueError, match="close_radius"):
        stage.SurfaceConfig(close_radius=-1)


def test_surface_stage_keeps_a_narrow_tunnel_that_leads_into_a_cavity(monkeypatch):
    """A slit narrower than the closing ball through a box, widening into a chamber of radius 0.2
    inside it (genus 1): closing the slit would seal the chamber and fill it, burying its wall up to
    0.3 (35 Poisson voxels) deep, far past stage.MAX_BURIED_BALLS ball radii. The tunnel leads somewhere
    real (test scene 25, a genus-2 shape, lost a handle and its cavity so: CD 12 -> 42), so the
    stage keeps Poisson's surface and says how deep the closing would have buried it."""
    from lookingglass.points import stage

    def chamber_and_through_slit(x, y, z):
        chamber = np.sqrt(x ** 2 + y ** 2 + z ** 2) - 0.2
        slit = np.maximum(np.abs(x) - 0.0125, np.abs(y) - 0.1)  # 0.025 wide, top to bottom
        return np.minimum(chamber, slit)

    poisson = carved_box(chamber_and_through_slit)
    assert poisson.is_watertight and stage.genus(poisson) == 1
    mesh = surface_stage_on(monkeypatch, poisson, np.zeros(3), 1.0)
    np.testing.assert_allclose(mesh.vertices, poisson.vertices)
    closing = mesh.metadata["closing"]
    assert not closing["applied"] and closing["genus_before"] == closing["genus_after"] == 1
    # the chamber's equator lies 0.3 from the box's top and bottom faces, the closed surface there
    depth = 0.3 / stage.poisson_voxel(8)
    assert 0.9 * depth < closing["buried_voxels"] < 1.1 * depth
    assert closing["buried_voxels"] > stage.MAX_BURIED_BALLS * stage.SurfaceConfig().close_radius


def test_surface_stage_keeps_poissons_surface_when_closing_fails(monkeypatch):
    """The closing is a clean-up: if it fails, Poisson's surface stands and the report says why."""
    from lookingglass.points import stage

    poisson = trimesh.creation.torus(major_radius=0.6, minor_radius=0.2)

    def failing_closing(*args, **kwargs):
        raise LookingGlassError("closing the narrow tunnels left no surface")

    monkeypatch.setattr(stage, "close_narrow_tunnels", failing_closing)
    mesh = surface_stage_on(monkeypatch, poisson, np.zeros(3), 1.0)
    np.testing.assert_allclose(mesh.vertices, poisson.vertices)
    assert mesh.metadata["closing"] == {"genus_before": 1, "genus_after": 1, "applied": False,
                                        "error": "closing the narrow tunnels left no surface"}
