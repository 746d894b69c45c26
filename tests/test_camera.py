"""The camera model against Mitsuba 3's perspective sensor and against itself."""

import numpy as np
import pytest
import torch
import trimesh

from lookingglass.physics.camera import Cameras, fov_y_deg
from lookingglass.render.raycast import object_masks

mitsuba_ref = pytest.importorskip("mitsuba_ref")
mi = mitsuba_ref.mi


def _cameras(width=64, height=48, dtype=torch.float64):
    origin = [[0.3, 1.5, 2.5], [-2.8, 0.5, 0.4], [0.2, -2.0, -2.1]]
    target = [[0.0, 0.02, 0.0], [0.05, 0.0, 0.0], [0.0, 0.0, 0.03]]
    up = [[0.0, 1.0, 0.0], [0.1, 1.0, 0.0], [0.0, 0.6, -0.8]]
    return Cameras.look_at(origin, target, up, [63.4, 50.0, 70.0], width, height, dtype=dtype)


def test_rays_match_mitsuba_sensor():
    cams = _cameras()
    rng = np.random.default_rng(0)
    for v in range(cams.num_views):
        sensor = mi.load_dict(mitsuba_ref.sensor_dict(cams, v, spp=1))
        xy = rng.random((50, 2)) * [cams.width, cams.height]
        ref = np.array([np.array(sensor.sample_ray(0.0, 0.5, mi.Point2f(x / cams.width, y / cams.height),
                                                   mi.Point2f(0.5, 0.5))[0].d) for x, y in xy])
        ours = cams.select(v).directions_at(torch.tensor(xy[None, :, 0]), torch.tensor(xy[None, :, 1]))[0]
        # Mitsuba works in float32: agreement to ~1e-6 rad.
        np.testing.assert_allclose(ours.numpy(), ref, atol=2e-6)


def test_project_inverts_rays():
    cams = _cameras()
    origins, dirs = cams.pixel_rays()
    depth_along = torch.linspace(0.5, 4.0, cams.height * cams.width, dtype=torch.float64).view(cams.height, cams.width)
    points = origins + dirs * depth_along[None, ..., None]
    xy, depth = cams.project(points.reshape(cams.num_views, -1, 3))
    x, y = cams.pixel_grid()
    torch.testing.assert_close(xy[..., 0], x.reshape(1, -1).expand(cams.num_views, -1))
    torch.testing.assert_close(xy[..., 1], y.reshape(1, -1).expand(cams.num_views, -1))
    # Depth is along the forward axis: distance times cos(angle to forward).
    cos = (dirs * cams.forward[:, None, None, :]).sum(-1)
    torch.testing.assert_close(depth, (depth_along * cos).reshape(cams.num_views, -1))


def test_pixel_pitch_is_a_pixel_at_unit_depth():
    """Two points one pixel apart (x and x + 1) at forward depth d lie pitch x d apart: the size the
    hull's fields, the refine stage's rims and the views' consensus give a pixel in the world."""
    cams = _cameras()
    y = torch.full((cams.num_views, 1), 20.5, dtype=torch.float64)
    x0 = torch.full_like(y, 30.0)
    for depth in (0.7, 3.0):
        ends = []
        for x in (x0, x0 + 1):
            d = cams.directions_at(x, y)[:, 0]  # (V, 3)
            ends.append(cams.origin + d * (depth / (d * cams.forward).sum(-1, keepdim=True)))
        torch.testing.assert_close((ends[1] - ends[0]).norm(dim=-1), cams.pixel_pitch * depth)


def test_camera_frame_convention():
    cams = _cameras()
    towards_camera = cams.world_to_camera(-cams.forward[:, None, :])
    torch.testing.assert_close(towards_camera, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(3, 1, 3))
    v = torch.randn(3, 10, 3, dtype=torch.float64)
    torch.testing.assert_close(cams.camera_to_world(cams.world_to_camera(v)), v)
    # Image up in the camera frame is +y, right is +x.
    torch.testing.assert_close(cams.world_to_camera(cams.up[:, None]), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand(3, 1, 3))
    assert fov_y_deg(90.0, 200, 100) == pytest.approx(2 * np.degrees(np.arctan(0.5)))


def test_resolution_and_normalization_keep_geometry():
    cams = _cameras()
    p = torch.tensor([[0.1, 0.2, -0.1], [0.3, -0.2, 0.05]], dtype=torch.float64)
    xy, depth = cams.project(p)
    half = cams.with_resolution(32, 24)
    xy_half, _ = half.project(p)
    torch.testing.assert_close(xy_half, xy / 2)
    center, scale = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64), 4.0
    moved = cams.transformed(center, scale)
    xy_moved, depth_moved = moved.project((p - center) / scale)
    torch.testing.assert_close(xy_moved, xy)
    torch.testing.assert_close(depth_moved, depth / scale)
    with pytest.raises(ValueError):
        cams.with_resolution(64, 64)
    with pytest.raises(ValueError):
        Cameras.look_at([0, 0, 3], [0, 0, 0], [0, 0, 1], 60, 8, 8)


def test_mesh_mask_matches_mitsuba():
    """The project's mask of a mesh vs Mitsuba's (coverage >= 1/2 with a box filter): IoU >= 0.99.

    Both estimate the same box-filtered coverage; pixels disagree only where coverage is near
    1/2 (silhouette edge), so the IoU deficit is bounded by a fraction of the boundary pixels.
    """
    mesh = trimesh.creation.capsule(height=1.0, radius=0.4)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.7, [1, 0.3, 0.2]))
    mesh.apply_translation([0.1, -0.05, 0.0])
    cams = _cameras(80, 60)
    ref = mitsuba_ref.render_coverage(mesh, cams, spp=256) >= 0.5
    ours = object_masks(mesh, cams, samples_per_axis=8)
    iou = (ref & ours).sum() / (ref | ours).sum()
    assert ref.sum() > 500
    assert iou >= 0.99, iou
