"""The learned IoR estimate's parts (lookingglass/ior_net.py): its inputs carry the IoR, its head's
distribution is read within the user's range, and views that see nothing do not count."""

import json

import numpy as np
import pytest
import torch
import trimesh

from lookingglass.data.envmaps import procedural_envmap
from lookingglass.data.rigs import paper_rig
from lookingglass.ior_net import IorNet, IorNetConfig, ior_net_inputs, posterior_estimate, soft_labels
from lookingglass.normals.inputs import NormalInputs
from lookingglass.render.tracer import RenderConfig, render_views
from lookingglass.physics.environment import EnvironmentMap


@pytest.mark.parametrize("true_ior", [1.4, 1.6])
def test_the_error_channels_are_lowest_at_the_true_ior(true_ior):
    """A glass ellipsoid rendered by the project's path tracer at IoR 1.4 or 1.6, fed with its own
    shape as the 'hull': the rendering layer at the true IoR explains the photos best, so the mean
    error channel over the pixels it explains (two-bounce, no TIR) is lowest at the candidate equal
    to the truth (candidates 0.05 apart; measured 0.067 at 1.4 against 0.074 / 0.077 beside it)."""
    env = procedural_envmap(np.random.default_rng(1), 64)
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    mesh.apply_scale([0.8, 0.6, 0.5])
    cams = paper_rig(5, 0, width=64, height=48)
    shown = render_views(mesh, EnvironmentMap(torch.as_tensor(env).float()), cams,
                         RenderConfig(ior=true_ior, samples_per_axis=2))
    images, masks = shown.image.numpy(), shown.mask.numpy()
    x = NormalInputs.from_capture(images, masks, env, cams, 1.4723, mesh, 64, 48, 32)
    cfg = IorNetConfig()
    views = ior_net_inputs(x, mesh, cfg.candidates)
    assert views.shape == (5, cfg.in_channels, 48, 64) and torch.isfinite(views).all()
    errors = [views[:, 11 + 2 * k].sum() / views[:, 12 + 2 * k].sum() for k in range(len(cfg.candidates))]
    best = cfg.candidates[int(np.argmin(errors))]
    assert best == pytest.approx(true_ior), [round(float(e), 4) for e in errors]
    # and the curve is not flat: 0.2 away from the truth explains clearly less
    far = cfg.candidates.index(round(3.0 - true_ior, 4) if true_ior == 1.4 else 1.4)
    assert errors[far] > 1.2 * min(errors)


def test_the_posterior_is_read_within_the_users_range():
    """Flat logits: the mean is the middle of the bins kept and the spread a uniform's over them
    ((b - a) / sqrt(12), to the bins' discreteness); a range outside the bins keeps the nearest
    bin; the Gaussian targets are normalized and peak at the truth."""
    cfg = IorNetConfig()
    centres = cfg.bin_centres()
    flat = torch.zeros(1, cfg.bins)
    mean, std = posterior_estimate(flat, centres)
    assert float(mean) == pytest.approx(1.5, abs=1e-6)
    assert float(std) == pytest.approx(0.4 / np.sqrt(12) * np.sqrt(cfg.bins * (cfg.bins + 1)) / (cfg.bins - 1) *
                                       np.sqrt((cfg.bins - 1) / (cfg.bins + 1)), rel=0.02)
    mean, _ = posterior_estimate(flat, centres, (1.55, 1.7))
    assert float(mean) == pytest.approx(1.625, abs=1e-6)
    mean, std = posterior_estimate(flat, centres, (2.0, 2.5))
    assert float(mean) == pytest.approx(1.7) and float(std) == pytest.approx(0.0, abs=1e-6)
    labels = soft_labels(torch.tensor([1.43, 1.61]), centres)
    assert torch.allclose(labels.sum(-1), torch.ones(2))
    assert centres[labels.argmax(-1)].tolist() == pytest.approx([1.43, 1.61])


def test_views_that_see_nothing_do_not_count():
    """The scene's feature is the mean over the views whose mask is not empty: adding an empty view
    (anything in its channels) leaves the logits as they were."""
    torch.manual_seed(0)
    cfg = IorNetConfig()
    net = IorNet(cfg).eval()
    views = torch.rand(1, 3, cfg.in_channels, 48, 64)
    masks = torch.zeros(1, 3, 48, 64, dtype=torch.bool)
    masks[:, :, 10:30, 20:40] = True
    with torch.no_grad():
        base = net(views, masks)
        extra = torch.cat([views, torch.rand(1, 1, cfg.in_channels, 48, 64)], 1)
        padded = net(extra, torch.cat([masks, torch.zeros(1, 1, 48, 64, dtype=torch.bool)], 1))
    assert torch.allclose(base, padded, atol=1e-5)


@pytest.fixture(scope="module")
def varied(tmp_path_factory):
    """4 scenes of 5 views at 64x48, each its own IoR in [1.3, 1.7]."""
    from lookingglass.data.dataset import DatasetConfig, generate_dataset

    root = tmp_path_factory.mktemp("ior_data")
    cfg = DatasetConfig(width=64, height=48, envmap_height=32, samples_per_axis=1, ior_range=(1.3, 1.7))
    generate_dataset(root / "data", 4, views=5, split="train", seed=0, config=cfg, workers=1)
    return root / "data"


def test_training_caches_inputs_resumes_exactly_and_ships_weights(varied, tmp_path):
    """train-ior's loop: one cached input file a scene (the true IoR in it), finite losses logged
    per epoch, weights that load back as the IoR net and read a capture within the range asked
    for; interrupted after 5 steps and resumed, the run ends with the uninterrupted run's weights."""
    from safetensors.torch import load_file

    from lookingglass.data.torch_dataset import TransparentSceneDataset
    from lookingglass.ior_net import IorTrainConfig, learned_ior, load_ior_net, train_ior_net

    ds = TransparentSceneDataset(varied, "train")
    config = IorTrainConfig(epochs=2, checkpoint_every=2)
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    train_ior_net(ds, whole, config)
    cached = sorted((whole / "features").glob("scene_*.npz"))
    assert len(cached) == 4
    with np.load(cached[0]) as z:
        assert z["views"].shape == (5, config.net.in_channels, 96, 128) and z["views"].dtype == np.float16
        assert float(z["ior"]) == pytest.approx(ds.meta(0)["ior"]) and 1.3 <= float(z["ior"]) <= 1.7
    logged = [json.loads(line) for line in (whole / "metrics.jsonl").read_text().splitlines()]
    assert [m["epoch"] for m in logged] == [1, 2] and all(np.isfinite(m["loss"]) for m in logged)
    train_ior_net(ds, parts, config, max_steps=5)
    train_ior_net(ds, parts, config)
    a, b = load_file(str(whole / "weights.safetensors")), load_file(str(parts / "weights.safetensors"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    net = load_ior_net(whole / "weights.safetensors")
    found = learned_ior(ds.capture(0), ds.hull(0).mesh, net, (1.5, 1.6))
    assert 1.5 <= found.value <= 1.6 and found.uncertainty >= 0 and not found.beyond_trained_range
    assert learned_ior(ds.capture(0), ds.hull(0).mesh, net, (1.2, 1.6)).beyond_trained_range


def test_training_refuses_scenes_of_one_ior(tmp_path):
    """A dataset whose scenes all share one IoR cannot teach the net anything: refused, naming the
    folder and the `generate` option that makes the right data, before any work."""
    from types import SimpleNamespace

    from lookingglass.errors import LookingGlassError
    from lookingglass.ior_net import IorTrainConfig, train_ior_net

    fixed = SimpleNamespace(config=SimpleNamespace(ior_range=(1.4723, 1.4723)), split_dir=tmp_path / "data" / "train")
    with pytest.raises(LookingGlassError, match="--ior-range") as err:
        train_ior_net(fixed, tmp_path / "run", IorTrainConfig())
    assert "train" in str(err.value) and not (tmp_path / "run").exists()
