"""The differentiable two-bounce normals against the renderer's own maps (`trace_two_bounce`, the
reference every table is built on) and against finite differences; the re-rendering comparison
against the renderer itself (a mesh re-rendered against its own rendering scores only the Monte
Carlo noise; a shrunken copy scores far worse)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch
import trimesh

from lookingglass.data.rigs import paper_rig
from lookingglass.physics.constants import IOR_GLASS
from lookingglass.physics.environment import EnvironmentMap
from lookingglass.render.compare import photos_at, rerender
from lookingglass.render.differentiable import mesh_two_bounce
from lookingglass.render.testshapes import radial_blob
from lookingglass.render.tracer import RenderConfig, render_views, trace_two_bounce


def _blob():
    return radial_blob(seed=1, subdivisions=4, amplitude=0.3)


def test_normals_match_the_renderers_two_bounce_maps():
    mesh = _blob()
    cams = paper_rig(5, rng=0, width=64, height=48)
    ref = trace_two_bounce(mesh, cams)
    ours = mesh_two_bounce(torch.as_tensor(mesh.vertices, dtype=torch.float32),
                           torch.as_tensor(mesh.faces, dtype=torch.long), cams)
    first = ref.mask
    # the renderer interpolates trimesh's vertex normals, ours the area-weighted ones: on a
    # 5k-face blob they differ by a fraction of a degree, a wrong hit by tens of degrees
    cos1 = (ours.normal1[first] * ref.normal1[first]).sum(-1)
    assert float(torch.quantile(cos1, 0.01)) > np.cos(np.radians(1.0))
    both = ref.hit2 & ours.valid
    assert int(both.sum()) > 0.99 * int(ref.hit2.sum())  # the same second hits, bar grazing pixels
    cos2 = (ours.normal2[both] * ref.normal2[both]).sum(-1)
    assert float(torch.quantile(cos2, 0.01)) > np.cos(np.radians(1.5))


def test_gradients_match_finite_differences():
    mesh = _blob()
    cams = paper_rig(5, rng=1, width=24, height=18).to(dtype=torch.float64)
    faces = torch.as_tensor(mesh.faces, dtype=torch.long)
    x0 = torch.as_tensor(mesh.vertices, dtype=torch.float64)
    weights = torch.randn(5, 18, 24, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def loss(x):
        tb = mesh_two_bounce(x, faces, cams)
        return ((tb.normal1 + 0.5 * tb.normal2) * weights).sum()

    x = x0.clone().requires_grad_(True)
    loss(x).backward()
    grad = x.grad
    # the vertices with the largest gradients; central differences small enough not to change
    # which triangles the rays meet
    for i in torch.argsort(grad.norm(dim=1), descending=True)[:5].tolist():
        for k in range(3):
            e = torch.zeros_like(x0)
            e[i, k] = 1e-6
            fd = (loss(x0 + e) - loss(x0 - e)) / 2e-6
            assert abs(float(fd) - float(grad[i, k])) <= 1e-3 * max(1.0, abs(float(fd)))


def test_rerender_scores_the_shape():
    mesh = _blob()
    cams = paper_rig(5, rng=2, width=80, height=60)
    h = 32
    u = torch.linspace(0, 1, 2 * h)
    v = torch.linspace(0, 1, h)[:, None]
    env = torch.stack([0.2 + u.expand(h, -1), 0.2 + v.expand(-1, 2 * h), 0.5 + 0.4 * torch.sin(12 * u) * v], -1)
    photos = render_views(mesh, EnvironmentMap(env), cams, RenderConfig(samples_per_axis=3, seed=5)).image
    capture = SimpleNamespace(images=photos.numpy(), masks=trace_two_bounce(mesh, cams).mask.numpy(),
                              envmap=env.numpy(), cameras=cams, ior=IOR_GLASS)
    same = rerender(mesh, capture, width=80)
    smaller = trimesh.Trimesh(mesh.vertices * 0.9, mesh.faces, process=False)
    assert same.error.shape == (5,)
    assert same.mean_error < 0.03  # sampling noise only (3x3 samples per pixel against the default 1)
    prepared = photos_at(capture, 80)  # several meshes against the same photos: prepared once
    assert rerender(smaller, capture, prepared=prepared).mean_error > 3 * same.mean_error
    assert np.array_equal(rerender(mesh, capture, prepared=prepared).error, same.error)


def test_gradients_are_bitwise_repeatable_on_two_threads():
    """The refine stage's descents sum these gradients onto shared vertices; summed in a varying
    order (indexing's backward across threads) their 1e-7 differences grew to 0.2% of a mesh's CD
    over 16 steps. A 20k-face mesh: enough gathered rows for torch to split the sums over threads."""
    mesh = radial_blob(seed=1, subdivisions=5, amplitude=0.3)
    cams = paper_rig(5, rng=2, width=64, height=48)
    faces = torch.as_tensor(mesh.faces, dtype=torch.long)
    weights = torch.randn(5, 48, 64, 3, generator=torch.Generator().manual_seed(0))

    def gradient():
        x = torch.as_tensor(mesh.vertices, dtype=torch.float32).requires_grad_(True)
        tb = mesh_two_bounce(x, faces, cams)
        ((tb.normal1 + 0.5 * tb.normal2) * weights).sum().backward()
        return x.grad

    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        first = gradient()
        assert float(first.abs().sum()) > 0
        assert all(torch.equal(first, gradient()) for _ in range(10))
    finally:
        torch.set_num_threads(old)
