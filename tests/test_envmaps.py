"""Environment map pool: augmentation in the project's convention, procedural maps, reproducibility."""

import json
import math

import numpy as np
import pytest
import torch

from lookingglass.data.envmaps import (EnvmapAugmentation, EnvmapSampler, augment_envmap, envmap_from_description,
                                       load_natural_envmap, mirror_envmap, procedural_envmap, rotate_envmap,
                                       texel_directions)
from lookingglass.errors import LookingGlassError
from lookingglass.physics.environment import EnvironmentMap, direction_to_uv


def _dirs(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return torch.tensor(d / np.linalg.norm(d, axis=1, keepdims=True))


def _rot_y(deg):
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=torch.float64)


def _lookup(env, d):
    return EnvironmentMap(torch.tensor(env, dtype=torch.float64)).lookup(d)


def test_rotation_moves_radiance_of_d_to_Ry_d_exactly_for_whole_texels():
    env = np.random.default_rng(0).random((16, 32, 3)).astype(np.float32)
    d = _dirs(500)
    for k in (1, 5, 31):
        angle = k * 360.0 / 32
        out = rotate_envmap(env, angle)
        torch.testing.assert_close(_lookup(out, d @ _rot_y(angle).T), _lookup(env, d), atol=1e-12, rtol=1e-6)


def test_rotation_by_fractional_texels_is_the_rotated_map_up_to_interpolation():
    """A smooth map (band-limited in u) rotated by a non-integer number of texels: the only error is
    the extra linear interpolation, O((texel * frequency)^2)."""
    d = texel_directions(64)
    u, v = (t.numpy() for t in direction_to_uv(torch.tensor(d)))
    env = np.stack([1.5 + np.sin(2 * np.pi * u + 3 * v), 1.5 + np.cos(4 * np.pi * u), 1.0 + v], -1).astype(np.float32)
    angle = 37.3
    out = rotate_envmap(env, angle)
    q = _dirs(1000, 1)
    err = (_lookup(out, q @ _rot_y(angle).T) - _lookup(env, q)).abs().max().item()
    assert err < 2e-3, err


def test_mirror_maps_x_to_minus_x():
    env = np.random.default_rng(1).random((16, 32, 3)).astype(np.float32)
    d = _dirs(500)
    flip = d * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(_lookup(mirror_envmap(env), flip), _lookup(env, d), atol=1e-12, rtol=1e-6)


def test_exposure_and_white_balance_scale_the_mean_exactly():
    env = np.random.default_rng(2).random((32, 64, 3)).astype(np.float32) * 3
    rng = np.random.default_rng(3)
    for _ in range(5):
        aug = EnvmapAugmentation.sample(rng, width=64)
        out = aug.apply(env)
        gains = aug.exposure * np.array(aug.white_balance)
        np.testing.assert_allclose(out.reshape(-1, 3).mean(0, dtype=np.float64),
                                   env.reshape(-1, 3).mean(0, dtype=np.float64) * gains, rtol=1e-6)
        assert abs(np.array([0.2126, 0.7152, 0.0722]) @ np.array(aug.white_balance) - 1) < 1e-12
        assert 0.5 <= aug.exposure <= 2.0 and all(0.8 < g < 1.25 for g in aug.white_balance)
        assert float(aug.rotation_deg / 360 * 64).is_integer()
    assert out.dtype == np.float32 and out.shape == env.shape
    assert augment_envmap(env, np.random.default_rng(4)).shape == env.shape


def test_procedural_maps_are_hdr_and_textured():
    for seed in range(6):
        env = procedural_envmap(np.random.default_rng(seed), 64)
        assert env.shape == (64, 128, 3) and env.dtype == np.float32
        assert np.isfinite(env).all() and (env >= 0).all()
        lum = env @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
        assert lum.max() / np.median(lum) >= 20, seed  # a bright source: HDR
        # texture: mean absolute difference of neighbouring texels (bright sources clipped out)
        c = np.minimum(lum, 4 * np.median(lum))
        grad = np.abs(np.diff(c, axis=1)).mean() + np.abs(np.diff(c, axis=0)).mean()
        assert grad / c.mean() > 0.02, (seed, grad / c.mean())
    a = procedural_envmap(np.random.default_rng(9), 32)
    np.testing.assert_array_equal(a, procedural_envmap(np.random.default_rng(9), 32))
    assert not np.array_equal(a, procedural_envmap(np.random.default_rng(10), 32))


def test_texel_directions_match_the_lookup_convention():
    env = np.random.default_rng(5).random((8, 16, 3)).astype(np.float32)
    d = torch.tensor(texel_directions(8).reshape(-1, 3))
    looked = _lookup(env, d).numpy().reshape(8, 16, 3)
    np.testing.assert_allclose(looked[1:-1], env[1:-1], atol=1e-6)  # (pole rows are one direction each)


def test_sampler_is_deterministic_and_descriptions_round_trip(shared_envmaps, tmp_path):
    folder = shared_envmaps[0].parent
    sampler = EnvmapSampler(folder, height=32, p_procedural=0.5, seed=11)
    sources = set()
    for i in range(12):
        env, desc = sampler[i]
        sources.add(desc["source"])
        assert env.shape == (32, 64, 3) and env.dtype == np.float32
        desc = json.loads(json.dumps(desc))  # what a scene records
        np.testing.assert_array_equal(envmap_from_description(desc, folder, 32), env)
        env2, desc2 = EnvmapSampler(folder, height=32, p_procedural=0.5, seed=11).sample(i)
        assert desc2 == desc
        np.testing.assert_array_equal(env2, env)
    assert sources == {"natural", "procedural"}
    first = [d for _, d in zip(range(3), sampler)]
    assert [d for _, d in first] == [sampler.description(i) for i in range(3)]
    assert EnvmapSampler(folder, 32, seed=12).description(0) != sampler.description(0) or \
        EnvmapSampler(folder, 32, seed=12).description(1) != sampler.description(1)


def test_natural_maps_resized_and_cached(shared_envmaps):
    a = load_natural_envmap(shared_envmaps[0], 64)
    assert a.shape == (64, 128, 3) and not a.flags.writeable
    assert load_natural_envmap(shared_envmaps[0], 64) is a
    # area resize keeps the mean radiance
    full = load_natural_envmap(shared_envmaps[0], 512)
    np.testing.assert_allclose(a.mean((0, 1), dtype=np.float64), full.mean((0, 1), dtype=np.float64), rtol=1e-6)


def test_sampler_names_and_errors(shared_envmaps, tmp_path):
    folder = shared_envmaps[0].parent
    name = shared_envmaps[0].stem
    s = EnvmapSampler(folder, 16, p_procedural=0.0, names=[name])
    assert all(s.description(i)["name"] == shared_envmaps[0].name for i in range(5))
    with pytest.raises(LookingGlassError):
        EnvmapSampler(folder, 16, names=["no_such_map"])
    with pytest.raises(LookingGlassError):
        EnvmapSampler(tmp_path, 16, p_procedural=0.5)
    only_procedural = EnvmapSampler(tmp_path, 16, p_procedural=1.0)
    assert only_procedural.description(0)["source"] == "procedural"
    with pytest.raises(LookingGlassError):
        envmap_from_description({"source": "natural", "name": "missing.hdr"}, folder, 16)
    with pytest.raises(LookingGlassError):
        envmap_from_description({"source": "sketch"}, folder, 16)
