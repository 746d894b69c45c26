"""The mirror image of a capture (`Cameras.mirrored`, `EnvironmentMap.mirrored`,
`NormalInputs.mirrored`) and the normal stage's mirror average.

Mirroring the world in the plane x = 0 and flipping every image left to right is a symmetry of
the physics: the mirrored object under the mirrored light, seen by the mirrored cameras, looks like
the flipped photos. So the mirrored inputs, made by flipping arrays, must equal the inputs traced
afresh from the mirrored hull, and the rendering layer must score them the same, pixel for pixel.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from lookingglass.data.rigs import paper_rig
from lookingglass.normals.inputs import NormalInputs, mirror_vector_maps
from lookingglass.normals.predict import network_normals
from lookingglass.physics.environment import EnvironmentMap
from lookingglass.physics.optics import IOR_GLASS
from lookingglass.render.tracer import RenderConfig, render_views, trace_two_bounce
from lookingglass.weights import load_normal_net, shipped_weights

W, H = 128, 96
MIRROR = np.diag([-1.0, 1.0, 1.0, 1.0])


def _lopsided() -> trimesh.Trimesh:
    """A shape with no mirror symmetry: a box and a sphere off to one side, turned about an oblique axis."""
    box = trimesh.creation.box(extents=(1.0, 0.7, 0.5))
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.45)
    ball.apply_translation((0.45, 0.3, 0.1))
    mesh = trimesh.boolean.union([box, ball], engine="manifold")
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.6, (0.3, 1.0, 0.5)))
    return mesh


@pytest.fixture(scope="module")
def scene():
    mesh = _lopsided()
    cameras = paper_rig(10, rng=0, width=W, height=H)
    u = torch.linspace(0, 1, 64)
    v = torch.linspace(0, 1, 32)[:, None]
    env = torch.stack([0.2 + u.expand(32, -1), 0.2 + v.expand(-1, 64), 0.5 + 0.4 * torch.sin(9 * u) * v], -1)
    photos = render_views(mesh, EnvironmentMap(env), cameras, RenderConfig(samples_per_axis=1, jitter=False)).image
    masks = trace_two_bounce(mesh, cameras).mask
    x = NormalInputs.from_capture(photos.numpy(), masks.numpy(), env.numpy(), cameras, IOR_GLASS, mesh, W, H, 32)
    return mesh, x


def test_mirrored_cameras_see_the_mirrored_world_in_flipped_images():
    cameras = paper_rig(10, rng=3, width=W, height=H, dtype=torch.float64)
    mirrored = cameras.mirrored()
    points = torch.rand(50, 3, dtype=torch.float64) - 0.5
    flip = points.new_tensor([-1.0, 1.0, 1.0])
    xy, depth = cameras.project(points)
    xy_m, depth_m = mirrored.project(points * flip)
    torch.testing.assert_close(xy_m[..., 0], W - xy[..., 0])
    torch.testing.assert_close(xy_m[..., 1], xy[..., 1])
    torch.testing.assert_close(depth_m, depth)
    # a camera-frame vector's x changes sign; the frames stay right-handed
    vectors = torch.randn(10, 7, 3, dtype=torch.float64)
    torch.testing.assert_close(mirrored.world_to_camera(vectors * flip), cameras.world_to_camera(vectors) * flip)
    torch.testing.assert_close(torch.linalg.det(mirrored.basis), torch.linalg.det(cameras.basis))


def test_mirrored_environment_is_the_light_from_mirrored_directions():
    env = EnvironmentMap(torch.rand(16, 32, 3, dtype=torch.float64))
    directions = torch.nn.functional.normalize(torch.randn(200, 3, dtype=torch.float64), dim=-1)
    flip = directions.new_tensor([-1.0, 1.0, 1.0])
    torch.testing.assert_close(env.mirrored().lookup(directions * flip), env.lookup(directions))


def test_mirrored_inputs_equal_the_mirrored_hull_traced_afresh(scene):
    mesh, x = scene
    m = x.mirrored()
    mirrored_mesh = mesh.copy()
    mirrored_mesh.apply_transform(MIRROR)  # trimesh reverses the faces: still outward
    assert mirrored_mesh.volume == pytest.approx(mesh.volume, rel=1e-9)
    traced = trace_two_bounce(mirrored_mesh, m.cameras, ior=IOR_GLASS)
    # a ray along an edge of the box may hit or miss by rounding: a handful of pixels of ~70 000
    assert int((traced.mask != m.vh_hit).sum()) <= 5 and int((traced.valid != m.vh_valid).sum()) <= 20
    both = traced.mask & m.vh_hit
    assert int(both.sum()) > 5000
    torch.testing.assert_close(traced.normal1[both], m.vh_n1[both], atol=1e-5, rtol=0)
    torch.testing.assert_close(traced.point1[both], m.vh_p1[both], atol=1e-4, rtol=0)  # float32 hits
    second = traced.valid & m.vh_valid
    torch.testing.assert_close(traced.normal2[second], m.vh_n2[second], atol=1e-4, rtol=0)
    # the rendering layer under the mirrored light scores the mirrored hull as the original, pixel for pixel
    error, tir = x.hull_error
    error_m, tir_m = m.hull_error
    torch.testing.assert_close(error_m, error.flip(2), atol=1e-4, rtol=0)
    assert torch.equal(tir_m, tir.flip(2))
    # mirrored twice: the inputs themselves
    twice = m.mirrored()
    for name in ("image", "mask", "vh_n1", "vh_n2", "vh_valid", "vh_p1", "vh_hit"):
        assert torch.equal(getattr(twice, name), getattr(x, name)), name


def test_the_mirror_average_answers_the_mirror_image_with_the_mirror_image(scene):
    """The net itself is not mirror-symmetric (its two answers differ by degrees), but the average is:
    fed the mirrored capture it returns the mirror image of what it returns for the capture. A wrong
    mapping back (x not negated, the columns not reversed) breaks this."""
    _, x = scene
    net = load_normal_net(shipped_weights(10)[0]).net
    n1, n2, gain = network_normals(net, x, None, mirror_average=True)
    m1, m2, mgain = network_normals(net, x.mirrored(), None, mirror_average=True)
    flip = n1.new_tensor([-1.0, 1.0, 1.0])
    mask = x.mask
    torch.testing.assert_close(m1.flip(2)[mask] * flip, n1[mask], atol=2e-4, rtol=0)
    torch.testing.assert_close(m2.flip(2)[mask] * flip, n2[mask], atol=2e-4, rtol=0)
    torch.testing.assert_close(mgain.flip(2)[mask], gain[mask], atol=2e-3, rtol=0)
    # and the single answers do differ: the average is not a no-op
    own = network_normals(net, x, None)[0]
    mirrored_own = network_normals(net, x.mirrored(), None)[0].flip(2) * flip
    apart = torch.rad2deg(torch.acos((own * mirrored_own).sum(-1).clamp(-1, 1)))[mask]
    assert float(apart.median()) > 0.3


def test_mirrored_targets_are_the_mirror_worlds_truth(scene):
    """`train-normals --mirror-augment` trains on the mirror image of a scene: its targets (the
    dataset's (V,3,H,W) layout) must be the true normals of the mirrored object seen by the mirrored
    cameras, and the loss of the hull's normals must not change (angles are kept)."""
    from lookingglass.normals.train import mirror_targets, normal_loss

    mesh, x = scene
    truth = trace_two_bounce(mesh, x.cameras, ior=IOR_GLASS)
    channels_first = lambda n: n.permute(0, 3, 1, 2)  # noqa: E731
    t = dict(n1=channels_first(truth.normal1), n2=channels_first(truth.normal2), mask=truth.mask,
             n2_valid=truth.valid & truth.mask)
    m = mirror_targets(t)
    mirrored_mesh = mesh.copy()
    mirrored_mesh.apply_transform(MIRROR)
    traced = trace_two_bounce(mirrored_mesh, x.cameras.mirrored(), ior=IOR_GLASS)
    assert int((traced.mask != m["mask"]).sum()) <= 5 and int((traced.valid != m["n2_valid"]).sum()) <= 20
    both = traced.mask & m["mask"]
    torch.testing.assert_close(channels_first(traced.normal1).permute(0, 2, 3, 1)[both],
                               m["n1"].permute(0, 2, 3, 1)[both], atol=1e-5, rtol=0)
    second = traced.valid & m["n2_valid"]
    torch.testing.assert_close(traced.normal2[second], m["n2"].permute(0, 2, 3, 1)[second], atol=1e-4, rtol=0)
    convex = trace_two_bounce(mesh.convex_hull, x.cameras, ior=IOR_GLASS)  # a hull that is not the truth
    hull = (channels_first(convex.normal1), channels_first(convex.normal2))
    mirrored_hull = tuple(channels_first(mirror_vector_maps(n)) for n in (convex.normal1, convex.normal2))
    for kind in ("l2", "angle"):
        before = float(normal_loss(*hull, t, kind))
        assert before > 0.01
        assert float(normal_loss(*mirrored_hull, m, kind)) == pytest.approx(before, rel=1e-5)


def test_mirror_augment_mirrors_some_steps_reproducibly(tmp_path, monkeypatch):
    """About half the steps train on the mirror image, the same steps in every run of a seed."""
    from lookingglass.data.dataset import DatasetConfig, generate_dataset
    from lookingglass.data.torch_dataset import TransparentSceneDataset
    from lookingglass.normals.model import cpu_config
    from lookingglass.normals.train import TrainConfig, train_normals

    generate_dataset(tmp_path / "data", 4, views=5, split="train", seed=0,
                     config=DatasetConfig(width=64, height=48, envmap_height=32, samples_per_axis=1), workers=1)
    ds = TransparentSceneDataset(tmp_path / "data", "train")
    calls = []
    original = NormalInputs.mirrored
    monkeypatch.setattr(NormalInputs, "mirrored", lambda self: calls.append(1) or original(self))
    net = cpu_config(width=64, height=48, num_views=5, enc_channels=(8, 16, 32), fnet_channels=8)
    counts = []
    for run in ("a", "b"):
        calls.clear()
        train_normals(ds, tmp_path / run, TrainConfig(net=net, epochs=2, lr=1e-3, mirror_augment=True))
        counts.append(len(calls))
    assert 0 < counts[0] < 8 and counts[0] == counts[1]  # 8 steps
    a = load_normal_net(tmp_path / "a" / "weights.safetensors").net.state_dict()
    b = load_normal_net(tmp_path / "b" / "weights.safetensors").net.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
