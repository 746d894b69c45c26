"""Latent optimization lowers the masked rendering error with the network frozen."""

import pytest
import torch

from lookingglass.normals.latent import LatentOptConfig, adam_step, optimize_latent
from lookingglass.normals.model import NormalNet, cpu_config, network_inputs
from lookingglass.normals.render_layer import render_layer
from lookingglass.physics.camera import Cameras
from lookingglass.physics.environment import EnvironmentMap


@pytest.mark.parametrize("residual", [False, True])
def test_latent_optimization_lowers_render_error_and_keeps_weights(residual):
    torch.manual_seed(0)
    cams = Cameras.look_at([[0, 0, 3.0], [3.0, 0, 0]], [[0, 0, 0]] * 2, [[0, 1, 0]] * 2, 30.0, 32, 24)
    env = EnvironmentMap(torch.rand(16, 32, 3))
    yy, xx = torch.meshgrid(torch.linspace(-0.5, 0.5, 24), torch.linspace(-0.5, 0.5, 32), indexing="ij")
    n1 = torch.nn.functional.normalize(torch.stack([xx, -yy, torch.ones_like(xx)], -1), dim=-1).expand(2, -1, -1, -1)
    n2 = -n1
    image = render_layer(env, n1, n2, cams).image
    mask = torch.ones(2, 24, 32, dtype=torch.bool)
    net = NormalNet(cpu_config(width=32, height=24, use_cost_volume=False, residual=residual))
    if residual:  # a trained residual net has a non-zero last layer (it starts at zero)
        torch.nn.init.normal_(net.decoder[-1].weight, std=0.05)
    before = [p.clone() for p in net.parameters()]
    # The hull's normals (the residual net's base) are off the truth by a smooth tilt.
    tilt = torch.tensor([0.25, -0.15, 0.0])
    hull1 = torch.nn.functional.normalize(n1 + tilt, dim=-1)
    hull2 = torch.nn.functional.normalize(n2 + tilt, dim=-1)
    x = network_inputs(image, mask, hull1, hull2, torch.zeros_like(image), torch.zeros_like(mask))
    _, _, history, _ = optimize_latent(net, x, None, env, image, mask, cams,
                                    LatentOptConfig(iterations_n2=20, iterations_both=80, lr=2e-2))
    # An untrained decoder spans few shapes; a trained one moves further (docs/history.md).
    assert history[-1] < 0.85 * history[0], history[::10]
    assert all(torch.equal(a, b) for a, b in zip(before, net.parameters()))


def test_adam_step_matches_torch_adam():
    """The latent's own Adam update is torch.optim.Adam's, step for step (on a quadratic with a
    gradient that changes every step, so both moments and the bias corrections matter)."""
    gen = torch.Generator().manual_seed(0)
    target = torch.randn(4, 8, generator=gen)
    ours = torch.randn(4, 8, generator=gen).requires_grad_(True)
    ref = ours.detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([ref], lr=5e-2)
    moments = (torch.zeros_like(ours), torch.zeros_like(ours))
    start = float(((ours.detach() - target) ** 4).sum())
    for t in range(1, 31):
        ((ours - target) ** 4).sum().backward()
        adam_step(ours, moments, t, 5e-2)
        opt.zero_grad()
        ((ref - target) ** 4).sum().backward()
        opt.step()
        torch.testing.assert_close(ours, ref, rtol=1e-5, atol=1e-6)
    assert ours.grad is None
    assert float(((ours.detach() - target) ** 4).sum()) < 0.5 * start
