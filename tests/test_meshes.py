"""Mesh helpers (lookingglass.meshes): volumes, orientation, components, smoothing, checks."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from lookingglass.errors import LookingGlassError
from lookingglass.meshes import (body_volumes, largest_component, orient_outward, require_closed_and_oriented,
                                 signed_volume, taubin_smooth, wind_cavities_inward, without_crumbs)


def unit_cube() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(1.0, 1.0, 1.0))  # corners at +-0.5, outward


def test_signed_volume_of_a_unit_cube_is_exactly_one():
    cube = unit_cube()
    # corners at +-0.5: every a . (b x c) is a multiple of 1/8, their sum 6, exact in binary
    assert signed_volume(cube.vertices, cube.faces) == 1.0
    assert signed_volume(cube.vertices, cube.faces[:, ::-1]) == -1.0
    moved = cube.vertices + [10.0, -3.0, 7.0]  # the origin of the tetrahedra cancels out
    assert signed_volume(moved, cube.faces) == pytest.approx(1.0, abs=1e-12)


def test_signed_volume_of_a_sphere_within_the_tessellation_error():
    """An icosphere of radius r lies between the sphere through its vertices and the sphere
    touching its nearest face plane (radius r_in): 4/3 pi r_in^3 <= V <= 4/3 pi r^3. At 2562
    vertices, r = 2, the polyhedron is 0.22% smaller than the sphere."""
    r = 2.0
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=r)
    volume = signed_volume(sphere.vertices, sphere.faces)
    r_in = np.abs(np.einsum("ij,ij->i", sphere.face_normals, sphere.triangles_center)).min()
    assert 4 / 3 * np.pi * r_in ** 3 <= volume < 4 / 3 * np.pi * r ** 3
    assert volume == pytest.approx(4 / 3 * np.pi * r ** 3, rel=3e-3)
    assert volume == pytest.approx(sphere.volume, rel=1e-12)  # trimesh's integral agrees


def test_orient_outward_flips_an_inverted_mesh_only():
    cube = unit_cube()
    inverted = cube.faces[:, ::-1]
    fixed = orient_outward(cube.vertices, inverted)
    np.testing.assert_array_equal(fixed, cube.faces)
    assert signed_volume(cube.vertices, fixed) == 1.0
    assert orient_outward(cube.vertices, cube.faces) is cube.faces  # already outward: untouched


def cube_and_speck(speck_size: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """A unit cube (12 faces) and, 5 away, a small cube of edge `speck_size` (12 faces too)
    listed first, so the kept component is not simply the first one."""
    cube, speck = unit_cube(), trimesh.creation.box(extents=(speck_size,) * 3)
    speck.apply_translation([5.0, 0.0, 0.0])
    # the big cube gets more faces (subdivided once: 48), so "most faces" picks it
    cube = cube.subdivide()
    mesh = trimesh.util.concatenate([speck, cube])
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)


def test_largest_component_drops_a_stray_speck():
    vertices, faces = cube_and_speck()
    kept_v, kept_f, dropped = largest_component(vertices, faces)
    assert len(kept_f) == 48 and len(kept_v) == 26  # the subdivided cube: 8 corners, 12 edges, 6 faces
    assert kept_v.max() == 0.5 and kept_v.min() == -0.5  # nothing of the speck at x = 5
    assert signed_volume(kept_v, kept_f) == pytest.approx(1.0, abs=1e-12)
    assert dropped == 1  # the speck encloses 1e-6 > the default min_volume 0
    # a speck under min_volume is dropped without being counted (callers warn only about real pieces)
    assert largest_component(vertices, faces, min_volume=1e-5)[2] == 0
    # one component: the mesh comes back whole (vertex order kept)
    v1, f1, d1 = largest_component(kept_v, kept_f)
    np.testing.assert_array_equal(v1, kept_v)
    np.testing.assert_array_equal(f1, kept_f)
    assert d1 == 0


def test_largest_component_drops_unreferenced_vertices():
    cube = unit_cube()
    vertices = np.concatenate([[[9.0, 9.0, 9.0]], cube.vertices])  # an unused vertex in front
    kept_v, kept_f, dropped = largest_component(vertices, cube.faces + 1)
    np.testing.assert_array_equal(kept_v, cube.vertices)
    np.testing.assert_array_equal(kept_f, cube.faces)
    assert dropped == 0


def test_without_crumbs_keeps_every_real_piece():
    """Relative area: a piece of 1/4 of the largest one's area stays, one of 1e-4 goes."""
    big = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    second = trimesh.creation.icosphere(subdivisions=2, radius=0.5).apply_translation([3, 0, 0])
    crumb = trimesh.creation.icosphere(subdivisions=2, radius=0.01).apply_translation([-3, 0, 0])
    kept = without_crumbs([crumb, big, second], 1e-3)
    assert len(kept.faces) == len(big.faces) + len(second.faces)
    assert kept.area == pytest.approx(big.area + second.area)
    assert without_crumbs([crumb, big], 1e-3) is big  # one piece left: that piece itself


def test_wind_cavities_inward_by_nesting_depth():
    """A body inside one other is a cavity (wound inward), inside two an island in it (outward), a
    body beside the others stays as it is; a one-body mesh comes back unchanged."""
    spheres = [trimesh.creation.icosphere(subdivisions=2, radius=r) for r in (1.0, 0.6, 0.3)]
    beside = trimesh.creation.icosphere(subdivisions=2, radius=0.5).apply_translation([3, 0, 0])
    mesh = trimesh.util.concatenate(spheres + [beside])
    wound = wind_cavities_inward(mesh)
    volumes = sorted(round(body.volume, 6) for body in wound.split(only_watertight=False))
    expected = sorted(round(v, 6) for v in (spheres[0].volume, -spheres[1].volume, spheres[2].volume, beside.volume))
    assert volumes == expected
    assert wound.is_watertight and wound.is_winding_consistent
    assert sorted(np.round(body_volumes(wound.vertices, wound.faces), 6)) == expected
    assert wind_cavities_inward(spheres[0]) is spheres[0]
    # a wrinkled pocket may have more area than the smooth shell around it: volume decides
    pocket = trimesh.creation.icosphere(subdivisions=5)
    pocket.vertices *= (0.62 + 0.28 * np.prod(np.sin(16 * pocket.vertices), axis=1))[:, None]  # star-shaped, r < 0.9
    assert pocket.area > spheres[0].area
    wound = wind_cavities_inward(trimesh.util.concatenate([spheres[0], pocket]))
    assert sorted(np.round(body_volumes(wound.vertices, wound.faces), 6)) == [round(-pocket.volume, 6),
                                                                              round(spheres[0].volume, 6)]


def test_taubin_smooth_removes_noise_without_shrinking():
    """A unit icosphere with 2% radial noise: 10 passes halve the radial scatter (0.020 -> 0.009)
    and keep the mean radius within 0.1% (plain Laplacian smoothing shrinks it by 1.5%)."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    rng = np.random.default_rng(0)
    noisy = sphere.vertices * (1 + rng.normal(0, 0.02, (len(sphere.vertices), 1)))
    smooth = taubin_smooth(noisy, sphere.faces, 10)
    r_noisy, r_smooth = np.linalg.norm(noisy, axis=1), np.linalg.norm(smooth, axis=1)
    assert r_smooth.std() < 0.5 * r_noisy.std()
    assert abs(r_smooth.mean() - 1.0) < 1e-3
    assert smooth.shape == noisy.shape and smooth.dtype == np.float64
    np.testing.assert_array_equal(taubin_smooth(noisy, sphere.faces, 0), noisy)
    assert noisy is not smooth and not np.array_equal(noisy, smooth)  # a new array; the input kept


def test_require_closed_and_oriented():
    require_closed_and_oriented(unit_cube(), "cube")  # closed, outward: no error
    inverted = unit_cube()
    inverted.invert()
    with pytest.raises(LookingGlassError, match="cube encloses no volume"):
        require_closed_and_oriented(inverted, "cube")
    cube = unit_cube()
    open_box = trimesh.Trimesh(cube.vertices, cube.faces[1:], process=False)
    with pytest.raises(LookingGlassError, match="box is not watertight.*; try again"):
        require_closed_and_oriented(open_box, "box", "; try again")
    broken = unit_cube()
    broken.vertices[0] = np.nan
    with pytest.raises(LookingGlassError, match="non-finite"):
        require_closed_and_oriented(broken, "cube")
