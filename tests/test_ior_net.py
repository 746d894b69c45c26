"""The learned IoR estimate's parts (lookingglass/ior_net.py): its inputs carry the IoR, its head's
distribution is read within the user's range, and views that see nothing do not count."""

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
