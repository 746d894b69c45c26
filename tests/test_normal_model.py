"""NNet / FNet / cost volume: shapes, the paper's switches, the cone sampling geometry."""

import math

import pytest
import torch

from lookingglass.normals.model import (NormalNet, build_cost_volume, cpu_config, network_inputs, paper_config,
                                        sample_cone, unit_channels)
from lookingglass.physics.camera import Cameras
from lookingglass.physics.environment import EnvironmentMap


def test_sample_cone_angles_and_frame():
    g = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=-1)
    cone = sample_cone(n, 15.0, 4)
    assert cone.shape == (4, 500, 3)
    torch.testing.assert_close(cone.norm(dim=-1), torch.ones(4, 500, dtype=torch.float64))
    angles = torch.rad2deg(torch.acos((cone * n).sum(-1).clamp(-1, 1)))
    torch.testing.assert_close(angles[0], torch.zeros(500, dtype=torch.float64), atol=1e-5, rtol=0)
    torch.testing.assert_close(angles[1:], torch.full((3, 500), 15.0, dtype=torch.float64))
    # phi = 0, 120, 240 degrees: the three tilted samples are 120 degrees apart around Ñ.
    tilt = cone[1:] - (cone[1:] * n).sum(-1, keepdim=True) * n
    tilt = torch.nn.functional.normalize(tilt, dim=-1)
    cos01 = (tilt[0] * tilt[1]).sum(-1)
    torch.testing.assert_close(cos01, torch.full((500,), math.cos(math.radians(120)), dtype=torch.float64))
    # phi = 0 tilts towards X = Y x Z, which is perpendicular to the image up vector.
    assert (tilt[0][:, 1].abs() < 1e-9).all()


@pytest.mark.parametrize("error_map, cost_volume, channels", [(False, False, 13), (True, False, 15), (True, True, 15)])
def test_switches_and_shapes(error_map, cost_volume, channels):
    cfg = cpu_config(width=64, height=48, use_error_map=error_map, use_cost_volume=cost_volume)
    net = NormalNet(cfg)
    assert cfg.in_channels == channels
    x = torch.randn(2, channels, 48, 64)
    cv = torch.randn(2, 16, 8, 48, 64) if cost_volume else None
    n1, n2 = net(x, cv)
    assert n1.shape == n2.shape == (2, 3, 48, 64)
    torch.testing.assert_close(n1.norm(dim=1), torch.ones(2, 48, 64), atol=1e-5, rtol=0)
    (n1.sum() + n2.sum()).backward()
    if cost_volume:
        w = net.pooling_weights()
        assert (w > 0).all() and w.sum().item() == pytest.approx(1.0)
        assert net.pool_logits.grad is not None


def test_paper_widths():
    net = NormalNet(paper_config())
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert (convs[0].in_channels, convs[0].out_channels, convs[0].kernel_size, convs[0].stride) == (15, 64, (4, 4), (2, 2))
    fnet = [m for m in net.fnet.modules() if isinstance(m, torch.nn.Conv2d)]
    assert (fnet[0].in_channels, fnet[0].out_channels) == (8, 64)
    enc2_first = [m for m in net.enc2.modules() if isinstance(m, torch.nn.Conv2d)][0]
    assert (enc2_first.in_channels, enc2_first.out_channels) == (128, 256)  # 64 + 64 from the cost volume
    assert net.decoder[-1].out_channels == 6


def test_cost_volume_zero_error_at_truth():
    """At the pair (θ=0, θ=0), i.e. the hull normals themselves, the error equals the layer's own."""
    cams = Cameras.look_at([[0, 0, 3.0]], [[0, 0, 0]], [[0, 1, 0]], 40.0, 16, 12)
    env = EnvironmentMap(torch.rand(8, 16, 3))
    n = torch.nn.functional.normalize(torch.randn(1, 12, 16, 3) * 0.2 + torch.tensor([0, 0, 1.0]), dim=-1)
    from lookingglass.normals.render_layer import render_layer

    image = render_layer(env, n, -n, cams).image
    mask = torch.ones(1, 12, 16, dtype=torch.bool)
    cv = build_cost_volume(env, image, mask, n, -n, cams, 15.0)
    assert cv.shape == (1, 16, 8, 12, 16)
    assert cv[0, 0, 6].abs().max() < 1e-6  # pair (0, 0): rendered from the same normals
    assert cv[0, 5, 6].abs().mean() > 1e-3  # a tilted pair renders differently
    x = network_inputs(image, mask, n, -n, cv[:, 0, 6:7].permute(0, 2, 3, 1).expand(-1, -1, -1, 3), mask)
    assert x.shape == (1, 15, 12, 16)


def test_cost_volume_pairs_match_the_layer():
    """The cost volume shares the first interface across N2 choices: every pair must still equal
    a full rendering-layer pass on that pair of normals."""
    from lookingglass.normals.render_layer import error_map, render_layer

    g = torch.Generator().manual_seed(3)
    cams = Cameras.look_at([[0.3, 0.2, 3.0], [-2.0, 1.0, 2.0]], [[0, 0, 0]] * 2, [[0, 1, 0]] * 2, 50.0, 16, 12)
    env = EnvironmentMap(torch.rand(16, 32, 3, generator=g))
    n1 = torch.nn.functional.normalize(torch.randn(2, 12, 16, 3, generator=g) * 0.3 + torch.tensor([0, 0, 1.0]), dim=-1)
    n2 = torch.nn.functional.normalize(torch.randn(2, 12, 16, 3, generator=g) * 0.3 - torch.tensor([0, 0, 1.0]), dim=-1)
    image = torch.rand(2, 12, 16, 3, generator=g)
    mask = torch.rand(2, 12, 16, generator=g) > 0.3
    cv = build_cost_volume(env, image, mask, n1, n2, cams, 15.0)
    n1s, n2s = sample_cone(n1, 15.0), sample_cone(n2, 15.0)
    for a, b in [(0, 3), (2, 1), (3, 3)]:
        out = render_layer(env, n1s[a], n2s[b], cams)
        expected = error_map(image, out.image, mask).mean(-1)
        torch.testing.assert_close(cv[:, 4 * a + b, 6], expected, atol=1e-6, rtol=0)
        torch.testing.assert_close(cv[:, 4 * a + b, 7], (out.tir & mask).float())


def test_residual_net_starts_at_the_hull_normals():
    """The residual switch (ours): an untrained net returns Ñ1, Ñ2 exactly, and still learns."""
    cfg = cpu_config(width=64, height=48)
    assert cfg.residual
    net = NormalNet(cfg)
    g = torch.Generator().manual_seed(0)
    vh1 = torch.nn.functional.normalize(torch.randn(2, 48, 64, 3, generator=g), dim=-1)
    vh2 = torch.nn.functional.normalize(torch.randn(2, 48, 64, 3, generator=g), dim=-1)
    mask = torch.ones(2, 48, 64, dtype=torch.bool)
    x = network_inputs(torch.rand(2, 48, 64, 3, generator=g), mask, vh1, vh2, torch.rand(2, 48, 64, 3), mask)
    n1, n2 = net(x, torch.randn(2, 16, 8, 48, 64, generator=g))
    torch.testing.assert_close(n1, vh1.permute(0, 3, 1, 2), atol=1e-6, rtol=0)
    torch.testing.assert_close(n2, vh2.permute(0, 3, 1, 2), atol=1e-6, rtol=0)
    (n1[:, 0].sum() + n2[:, 2].sum()).backward()
    assert net.decoder[-1].weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="hull normals"):
        net.decode(net.encode(x, torch.zeros(2, 16, 8, 48, 64)))


def test_unit_channels_is_normalize_with_its_gradient():
    """The decoder's fast channel normalization must be F.normalize(dim=1) in value and gradient,
    including a zero vector (a finite gradient there, upstream / eps, not NaN)."""
    x = torch.randn(2, 3, 5, 7, dtype=torch.float64)
    x[0, :, 0, 0] = 0.0
    x.requires_grad_(True)
    ours, ref = unit_channels(x), torch.nn.functional.normalize(x, dim=1, eps=1e-6)
    assert torch.allclose(ours, ref, atol=1e-12)
    weights = torch.randn_like(ours)
    (g_ours,) = torch.autograd.grad((ours * weights).sum(), x)
    (g_ref,) = torch.autograd.grad((ref * weights).sum(), x)
    assert torch.isfinite(g_ours).all()
    assert torch.allclose(g_ours, g_ref, atol=1e-8)


def test_gain_head_is_an_extra_output():
    """A net with a gain head decodes the same normals as its weights without the head (which
    load into it, the head fresh) and adds per-pixel gains for n1 and n2 (degrees)."""
    torch.manual_seed(0)
    plain = NormalNet(cpu_config(width=64, height=48, enc_channels=(16, 32, 64), use_cost_volume=False)).eval()
    headed = NormalNet(cpu_config(width=64, height=48, enc_channels=(16, 32, 64), use_cost_volume=False,
                            gain_head=True)).eval()
    headed.load_state_dict(headed.widen_initial_state(plain.state_dict(), {}))
    x = torch.randn(2, 15, 48, 64)
    with torch.no_grad():
        n1, n2 = plain(x)
        h1, h2 = headed(x)
        e1, e2, gain = headed(x, with_gain=True)
        assert plain(x, with_gain=True)[2] is None
    for a, b in ((n1, h1), (n2, h2), (n1, e1), (n2, e2)):
        torch.testing.assert_close(a, b)
    assert gain.shape == (2, 2, 48, 64) and bool(torch.isfinite(gain).all()) and float(gain.std()) > 0


def test_detail_head_starts_as_the_plain_net_and_reads_the_inputs():
    """Weights without the detail head load into a net with one (its last layer zero): the same
    normals; once that layer is nonzero the output depends on the full-resolution inputs beyond
    what the decoder saw, and a pixel's correction moves with the hull normal at that pixel."""
    torch.manual_seed(0)
    small = dict(width=64, height=48, enc_channels=(16, 32, 64), use_cost_volume=False)
    plain = NormalNet(cpu_config(**small)).eval()
    torch.nn.init.normal_(plain.decoder[-1].weight, std=0.1)  # a residual net starts at the hull's normals
    detailed = NormalNet(cpu_config(**small, detail_head=True)).eval()
    detailed.load_state_dict(detailed.widen_initial_state(plain.state_dict(), {}))
    x = torch.randn(2, 15, 48, 64)
    with torch.no_grad():
        for a, b in zip(plain(x), detailed(x)):
            torch.testing.assert_close(a, b)
        torch.nn.init.normal_(detailed.detail_head[-1].weight, std=0.1)
        moved = detailed(x)[0]
        assert float((moved - plain(x)[0]).abs().max()) > 1e-3
        # the same latent decoded beside other inputs: only the detail head sees the difference
        latent = detailed.encode(x)
        y = x.clone()
        y[:, 0:3, 20, 30] += 1.0  # one pixel's photo
        a, b = detailed.decode(latent, x)[0], detailed.decode(latent, y)[0]
    changed = (a - b).abs().amax(1) > 1e-6
    assert bool(changed[:, 20, 30].all()) and int(changed.sum()) <= 2 * 25  # within its 5x5 reach


def test_detail_head_training_needs_the_head_and_weights():
    from lookingglass.errors import ConfigError
    from lookingglass.normals.train import TrainConfig

    with pytest.raises(ConfigError, match="detail head"):
        TrainConfig(net=cpu_config(), detail_head_only=True, init="w.safetensors")
    with pytest.raises(ConfigError, match="detail head"):
        TrainConfig(net=cpu_config(detail_head=True), detail_head_only=True)
