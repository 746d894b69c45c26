"""The rendering layer against the path tracer (two-interface paths) and its gradients."""

import numpy as np
import torch
import trimesh

from lookingglass.data.envmaps import procedural_envmap
from lookingglass.data.rigs import paper_rig
from lookingglass.normals.render_layer import error_map, render_layer
from lookingglass.physics.camera import Cameras
from lookingglass.physics.environment import EnvironmentMap
from lookingglass.render.tracer import RenderConfig, render_views


def _scene():
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.9)
    mesh.vertices[:, 1] *= 0.7  # an ellipsoid: N2 is not simply the mirror of N1
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces)
    env = EnvironmentMap(torch.tensor(procedural_envmap(np.random.default_rng(3), 64)))
    cams = paper_rig(5, 0, width=64, height=48)
    return mesh, env, cams


def test_reproduces_tracer_on_two_interface_paths():
    """With the tracer limited to 2 interfaces, pixel-centre rays and no pruning, both compute the
    same light paths from the same smooth normals: agreement to float32 rounding wherever the
    tracer's two-bounce model is valid."""
    mesh, env, cams = _scene()
    cfg = RenderConfig(max_depth=2, samples_per_axis=1, jitter=False, prune_threshold=0.0, prune_rest=False)
    res = render_views(mesh, env, cams, cfg)
    tb = res.two_bounce
    out = render_layer(env, tb.normal1, tb.normal2, cams)
    valid = tb.valid
    assert valid.sum() > 1000
    diff = (out.image - res.image).abs()[valid]
    rel = diff.mean() / res.image[valid].mean()
    assert rel < 2e-3, rel
    # The layer's TIR mask matches the tracer's TIR at the second hit.
    hit = tb.mask & tb.hit2
    agree = (out.tir[hit] == tb.tir[hit]).float().mean()
    assert agree > 0.995, agree
    # Error map is zero outside the mask and equals |I - clip(render)| inside.
    em = error_map(res.image, out.image, tb.mask)
    assert (em[~tb.mask] == 0).all()
    torch.testing.assert_close(em[valid], (res.image - out.image.clamp(0, 1)).abs()[valid])


def test_gradients_reach_both_normals():
    mesh, env, cams = _scene()
    tb = render_views(mesh, env, cams, RenderConfig(max_depth=2, samples_per_axis=1, jitter=False)).two_bounce
    n1 = tb.normal1.double().clone().requires_grad_(True)
    n2 = tb.normal2.double().clone().requires_grad_(True)
    env64 = EnvironmentMap(env.radiance.double())
    out = render_layer(env64, n1, n2, cams.to(dtype=torch.float64))
    loss = (out.image * tb.valid.unsqueeze(-1)).sum()
    loss.backward()
    assert n1.grad[tb.valid].abs().sum() > 0 and n2.grad[tb.valid].abs().sum() > 0
    # Finite-difference check on a few pixels (gradcheck on a small slice).
    idx = torch.nonzero(tb.valid[0])[:4]  # pixels of view 0, rendered with view 0's camera
    v, y, x = 0, idx[:, 0], idx[:, 1]
    sub = cams.to(dtype=torch.float64)
    dirs = sub.pixel_rays()[1][v, y, x].reshape(1, 4, 1, 3)

    def f(a, b):
        return render_layer(env64, a, b, sub.select([0]), view_dirs=dirs).image

    a = tb.normal1.double()[v, y, x].reshape(1, 4, 1, 3).requires_grad_(True)
    b = tb.normal2.double()[v, y, x].reshape(1, 4, 1, 3).requires_grad_(True)
    assert torch.autograd.gradcheck(f, (a, b), eps=1e-6, atol=1e-4)


def test_gradients_stay_finite_through_tir_and_the_poles():
    """Latent optimization back-propagates through every pixel, TIR and grazing ones included:
    one NaN gradient poisons the shared latent code (it once turned every predicted normal to NaN)."""
    cams = Cameras.look_at([[0, 0, 3.0]], [[0, 0, 0]], [[0, 1, 0]], 40.0, 16, 12)
    env = EnvironmentMap(torch.rand(8, 16, 3, generator=torch.Generator().manual_seed(0)))
    g = torch.Generator().manual_seed(1)
    n1 = torch.nn.functional.normalize(torch.randn(1, 12, 16, 3, generator=g) * 0.6 + torch.tensor([0, 0, 1.0]), dim=-1)
    n2 = torch.nn.functional.normalize(torch.randn(1, 12, 16, 3, generator=g), dim=-1)  # many TIR exits
    n1, n2 = n1.requires_grad_(), n2.requires_grad_()
    out = render_layer(env, n1, n2, cams)
    assert out.tir.any() and (~out.tir).any()
    out.image.sum().backward()
    assert torch.isfinite(n1.grad).all() and torch.isfinite(n2.grad).all()
    # Directions exactly at the poles: the value is the pole row, the gradient finite.
    d = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], requires_grad=True)
    value = env.lookup(d)
    torch.testing.assert_close(value.detach(), torch.stack([env.radiance[0].mean(0), env.radiance[-1].mean(0)]),
                               atol=0.5, rtol=0)  # bilinear at the pole row: a blend of that row
    value.sum().backward()
    assert torch.isfinite(d.grad).all()
