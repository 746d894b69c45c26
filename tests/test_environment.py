"""Environment lookup against Mitsuba 3's envmap emitter."""

import math

import cv2
import numpy as np
import pytest
import torch

from lookingglass.capture.images import read_envmap
from lookingglass.physics.camera import Cameras
from lookingglass.physics.environment import EnvironmentMap, direction_to_uv, uv_to_direction

mitsuba_ref = pytest.importorskip("mitsuba_ref")
mi = mitsuba_ref.mi


def _random_dirs(n, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_uv_convention():
    d = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]],
                     dtype=torch.float64)
    u, v = direction_to_uv(d)
    torch.testing.assert_close(u[:3], torch.tensor([0.0, 0.25, 0.5], dtype=torch.float64))
    torch.testing.assert_close(v, torch.tensor([0.5, 0.5, 0.5, 0.0, 1.0], dtype=torch.float64))
    dirs = torch.tensor(_random_dirs(1000))
    torch.testing.assert_close(uv_to_direction(*direction_to_uv(dirs)), dirs)


def test_lookup_matches_mitsuba_emitter_texel_for_texel(tmp_path):
    """Bilinear lookup equals Mitsuba's envmap eval up to float32 rounding, near the seam and poles too.

    (Exactly at a pole the map itself is ambiguous — all of row 0 is one direction — so those two
    directions are left out.)"""
    rng = np.random.default_rng(1)
    env = (rng.random((8, 16, 3)) + 0.1).astype(np.float32)
    emitter = mi.load_dict({"type": "envmap", "filename": mitsuba_ref.write_envmap(env, tmp_path)})
    dirs = np.concatenate([_random_dirs(300), [[0.01, 1, 0.02], [-0.02, -1, 0.01], [1e-4, 0.3, -1], [-1e-4, 0.3, -1]]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ref = []
    for d in dirs:
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-d))
        ref.append(np.array(emitter.eval(si)))
    ours = EnvironmentMap(torch.tensor(env, dtype=torch.float64)).lookup(torch.tensor(dirs)).numpy()
    np.testing.assert_allclose(ours, np.array(ref), atol=1e-5)


def test_environment_along_camera_rays_matches_mitsuba_render(shared_envmaps):
    """A render of the bare environment: our per-pixel box-filtered lookups vs Mitsuba's.

    Both average the same radiance over each pixel; the tolerance is Mitsuba's Monte Carlo noise at
    256 spp (about 1/sqrt(256) of the per-pixel radiance variation) plus our 8x8 quadrature error.
    """
    env = cv2.resize(read_envmap(shared_envmaps[0]), (256, 128), interpolation=cv2.INTER_AREA)
    cams = Cameras.look_at([[0.3, 1.5, 2.5], [-2.8, -0.5, 0.4]], [[0, 0, 0], [0, 0.3, 0]], [[0, 1, 0], [0, 1, 0]],
                           63.4, 64, 48, dtype=torch.float64)
    ref = mitsuba_ref.render_environment(env, cams, spp=256)
    em = EnvironmentMap(torch.tensor(env, dtype=torch.float64))
    s = 8
    ours = sum(em.lookup(cams.pixel_rays(((j + 0.5) / s, (i + 0.5) / s))[1]) for i in range(s) for j in range(s)) / s**2
    rel = np.abs(ours.numpy() - ref).mean() / ref.mean()
    assert rel < 0.01, rel
    # A wrong convention (e.g. u mirrored) is far off: the test has teeth.
    mirrored = EnvironmentMap(torch.tensor(env[:, ::-1].copy(), dtype=torch.float64))
    bad = mirrored.lookup(cams.pixel_rays()[1]).numpy()
    assert np.abs(bad - ref).mean() / ref.mean() > 5 * rel


def test_lookup_is_differentiable_and_resizes():
    env = EnvironmentMap(torch.rand(16, 32, 3, dtype=torch.float64))
    d = torch.nn.functional.normalize(torch.tensor(_random_dirs(8, seed=2)), dim=-1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: env.lookup(torch.nn.functional.normalize(x, dim=-1)), (d,))
    small = env.resized(8)
    assert small.radiance.shape == (8, 16, 3)
    assert small.radiance.mean().item() == pytest.approx(env.radiance.mean().item(), rel=1e-12)
    assert math.isclose(env.scaled(2.0).radiance.sum().item(), 2 * env.radiance.sum().item())
