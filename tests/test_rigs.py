"""The paper's camera rigs: layout, jitter ranges, look-at geometry, determinism."""

import math

import numpy as np
import pytest
import torch

from lookingglass.data.rigs import paper_rig, paper_rig_params, rig_layout


def _angles(origin):
    r = np.linalg.norm(origin, axis=1)
    polar = np.degrees(np.arccos(origin[:, 1] / r))
    azimuth = np.degrees(np.arctan2(origin[:, 0], origin[:, 2])) % 360  # from +z towards +x
    return polar, azimuth


def _wrap(a):
    return (a + 180) % 360 - 180


@pytest.mark.parametrize("views", [5, 10, 20])
def test_layout_and_jitter_ranges(views):
    polar0, azimuth0, jp, ja = rig_layout(views)
    for seed in range(20):
        p = paper_rig_params(views, seed)
        assert p["origin"].shape == (views, 3)
        np.testing.assert_allclose(np.linalg.norm(p["origin"], axis=1), 3.0, atol=1e-12)
        dist_to_target = np.linalg.norm(p["origin"] - p["target"], axis=1)
        assert (np.abs(dist_to_target - 3.0) <= 0.05 * math.sqrt(3) + 1e-9).all()
        assert (np.abs(p["target"]) <= 0.05).all()
        polar, azimuth = _angles(p["origin"])
        np.testing.assert_allclose(polar, p["polar_deg"], atol=1e-9)
        np.testing.assert_allclose(_wrap(azimuth - p["azimuth_deg"]), 0, atol=1e-9)
        assert (np.abs(polar - polar0) <= jp + 1e-9).all()
        assert (np.abs(_wrap(azimuth - azimuth0)) <= ja + 1e-9).all()
        forward = p["target"] - p["origin"]
        forward /= np.linalg.norm(forward, axis=1, keepdims=True)
        np.testing.assert_allclose((p["up"] * forward).sum(1), 0, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(p["up"], axis=1), 1, atol=1e-12)
        # the true up is +y (jittered by at most 0.1 per axis) made orthogonal: it rolls away from the
        # unjittered one by at most atan(0.1 sqrt 3 / (cos 50 - 0.1 sqrt 3)) ~ 20 deg (steepest view)
        y_perp = np.array([0.0, 1.0, 0.0]) - forward[:, 1:2] * forward
        y_perp /= np.linalg.norm(y_perp, axis=1, keepdims=True)
        tilt = np.degrees(np.arccos(np.clip((p["up"] * y_perp).sum(1), -1, 1)))
        assert (tilt < 20.0).all(), tilt.max()


def test_paper_10_view_rig_nominal_angles():
    polar, azimuth, jp, ja = rig_layout(10)
    assert sorted(set(polar)) == [50.0, 100.0] and (jp, ja) == (10.0, 20.0)
    assert sorted(set(azimuth)) == [0.0, 72.0, 144.0, 216.0, 288.0]
    p = paper_rig_params(10, deterministic=True)
    np.testing.assert_allclose(p["origin"][0], [0, 3 * math.cos(math.radians(50)), 3 * math.sin(math.radians(50))])


def test_rigs_are_nested():
    """Deterministic rigs: the 5-view cameras are among the 10-view ones, those among the 20."""
    o5, o10, o20 = (paper_rig_params(v, deterministic=True)["origin"] for v in (5, 10, 20))
    for small, big in ((o5, o10), (o10, o20)):
        d = np.linalg.norm(small[:, None] - big[None], axis=-1)
        assert (d.min(axis=1) < 1e-12).all()


@pytest.mark.parametrize("views", [5, 10, 20])
def test_cameras_look_at_target_and_frame_the_unit_sphere(views):
    p = paper_rig_params(views, 123)
    cams = paper_rig(views, 123, dtype=torch.float64)
    assert len(cams) == views and (cams.width, cams.height) == (480, 360)
    torch.testing.assert_close(cams.fov_x_deg, torch.full((views,), 63.4, dtype=torch.float64))
    torch.testing.assert_close(cams.origin, torch.tensor(p["origin"]))
    torch.testing.assert_close(cams.up, torch.tensor(p["up"]))
    xy, depth = cams.project(torch.tensor(p["target"])[:, None, :].expand(-1, 1, -1).clone())
    torch.testing.assert_close(xy[:, 0], torch.tensor([[240.0, 180.0]], dtype=torch.float64).expand(views, -1))
    up_dot_forward = (cams.up * cams.forward).sum(-1)
    torch.testing.assert_close(up_dot_forward, torch.zeros(views, dtype=torch.float64))
    # every point of the unit sphere projects inside the image, in front of the camera
    rng = np.random.default_rng(0)
    s = rng.normal(size=(2000, 3))
    s /= np.linalg.norm(s, axis=1, keepdims=True)
    xy, depth = cams.project(torch.tensor(s))
    assert (depth > 0).all()
    assert (xy[..., 0] > 0).all() and (xy[..., 0] < 480).all() and (xy[..., 1] > 0).all() and (xy[..., 1] < 360).all()


def test_deterministic_per_seed():
    a = paper_rig(10, np.random.default_rng(5))
    b = paper_rig(10, 5)
    torch.testing.assert_close(a.origin, b.origin, rtol=0, atol=0)
    torch.testing.assert_close(a.basis, b.basis, rtol=0, atol=0)
    c = paper_rig(10, 6)
    assert not torch.equal(a.origin, c.origin)
    d = paper_rig(10, deterministic=True)
    np.testing.assert_allclose(_angles(d.origin.double().numpy())[0], rig_layout(10)[0], atol=1e-4)


def test_errors():
    with pytest.raises(ValueError):
        paper_rig(7, 0)
    with pytest.raises(ValueError):
        paper_rig(10)  # jitter needs a generator
