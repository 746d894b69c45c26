"""PNet (lookingglass.points.model) and its losses (lookingglass.points.losses).

Index helpers against brute-force numpy references, the paper's three switches, output ranges,
gradient flow, the losses against hand-written sums, and a short overfit run.
"""

import itertools
import math

import numpy as np
import pytest
import torch
import trimesh

from lookingglass.points import model as pm
from lookingglass.presets import preset
from lookingglass.points.features import FEATURE_COLUMNS, NUM_FEATURES, PAPER_FEATURES
from lookingglass.points.config import POINT_LOSSES
from lookingglass.points.losses import (LOSSES, chamfer_loss, nearest_l2_loss, unseen_weights,
                                        view_dependent_l2_loss, view_targets)
from lookingglass.points.model import (PointNet, PointNetConfig, ball_members, ball_query, cpu_config,
                                       farthest_point_sample, group, interpolate, paper_config,
                                       parameter_count, three_nn)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """One intra-op thread: these nets run many tiny ops, and on a busy 2-core machine a second
    spinning OpenMP thread makes them 10-20x slower (measured), not faster."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def tiny_config(**kw) -> PointNetConfig:
    """Four levels, a few channels: fast enough to build and run many times in a test."""
    base = dict(centres=(64, 16, 8, 4), radii=(0.3, 0.6, 1.0, 1.6), neighbours=(8, 8, 8, 4),
                sa_mlps=((8, 8), (16, 16), (16, 16), (32, 32)), fp_mlps=((16,), (16,), (8,), (8, 8)),
                gn_group_size=4)
    base.update(kw)
    return PointNetConfig(**base)


def sphere_features(n: int, radius: float = 1.1, seed: int = 0, noise: float = 0.0) -> torch.Tensor:
    """(1, n, 12) features of points on a sphere: radial hull normal, radial mapped normal
    (optionally perturbed), error 0, no TIR, cosine 1."""
    g = torch.Generator().manual_seed(seed)
    u = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    f = torch.zeros(1, n, NUM_FEATURES)
    f[0, :, FEATURE_COLUMNS["point"]] = radius * u
    f[0, :, FEATURE_COLUMNS["hull_normal"]] = u
    mapped = u + noise * torch.randn(n, 3, generator=g)
    f[0, :, FEATURE_COLUMNS["normal"]] = torch.nn.functional.normalize(mapped, dim=-1)
    f[0, :, FEATURE_COLUMNS["cos"]] = 1.0
    return f


# ---------------------------------------------------------------------------------------------
# Index helpers
# ---------------------------------------------------------------------------------------------
def min_pairwise(x: np.ndarray) -> float:
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    return float(d[~np.eye(len(x), dtype=bool)].min())


def test_farthest_point_sample_matches_reference_and_spreads():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, size=(2, 600, 3))
    idx = farthest_point_sample(torch.from_numpy(xyz), 64).numpy()
    assert idx.shape == (2, 64) and (idx[:, 0] == 0).all()
    for b in range(2):
        assert len(set(idx[b].tolist())) == 64
        # Reference: the textbook loop, one point at a time.
        ref, dist = [0], np.linalg.norm(xyz[b] - xyz[b, 0], axis=-1)
        for _ in range(63):
            ref.append(int(dist.argmax()))
            dist = np.minimum(dist, np.linalg.norm(xyz[b] - xyz[b, ref[-1]], axis=-1))
        assert idx[b].tolist() == ref
        # FPS is a 2-approximation of the max-min spacing; random subsets do far worse.
        fps_gap = min_pairwise(xyz[b, idx[b]])
        for seed in range(5):
            subset = np.random.default_rng(seed).choice(600, 64, replace=False)
            assert fps_gap >= min_pairwise(xyz[b, subset])
    with pytest.raises(ValueError):
        farthest_point_sample(torch.zeros(1, 5, 3), 6)


@pytest.mark.parametrize("chunk", [pm.CHUNK_ELEMENTS, 50])
def test_ball_query_matches_brute_force(monkeypatch, chunk):
    monkeypatch.setattr(pm, "CHUNK_ELEMENTS", chunk)  # 50: one centre per chunk
    rng = np.random.default_rng(1)
    xyz = rng.uniform(-1, 1, size=(2, 300, 3))
    centres = np.concatenate([xyz[:, :20], rng.uniform(-1, 1, size=(2, 5, 3))], axis=1)
    centres[1, -1] = [5.0, 5.0, 5.0]  # an empty ball
    radius, k = 0.45, 12
    idx = ball_query(torch.from_numpy(xyz), torch.from_numpy(centres), radius, k).numpy()
    assert idx.shape == (2, 25, k)
    member = ball_members(torch.from_numpy(idx)).numpy()
    for b in range(2):
        for m in range(25):
            d = np.linalg.norm(xyz[b] - centres[b, m], axis=-1)
            inside = np.nonzero(d <= radius)[0]
            if len(inside) == 0:  # the nearest point stands in for the empty ball
                assert (b, m) == (1, 24)
                assert (idx[b, m] == d.argmin()).all() and member[b, m].sum() == 1
                continue
            first = inside[:k]
            expect = np.concatenate([first, np.full(k - len(first), first[0])])
            assert idx[b, m].tolist() == expect.tolist()
            assert (d[idx[b, m]] <= radius).all()
            assert member[b, m].tolist() == [True] * len(first) + [False] * (k - len(first))


@pytest.mark.parametrize("k", [1, 3])
def test_knn_both_paths_match_brute_force(monkeypatch, k):
    monkeypatch.setattr(pm, "CHUNK_ELEMENTS", 2000)  # several chunks on the dense path
    g = torch.Generator().manual_seed(3)
    ref = torch.randn(2, 150, 3, generator=g, dtype=torch.float64)
    query = torch.randn(2, 90, 3, generator=g, dtype=torch.float64)
    want = torch.cdist(query, ref, compute_mode="donot_use_mm_for_euclid_dist").topk(k, largest=False).indices
    assert torch.equal(pm.knn(query, ref, k), want)  # CPU: k-d tree
    assert torch.equal(pm._knn_dense(query, ref, k), want)  # other devices: distance matrices


def test_group_gathers_balls():
    pts = torch.arange(2 * 5 * 2, dtype=torch.float64).reshape(2, 5, 2)
    idx = torch.tensor([[[0, 4], [2, 2]], [[1, 3], [4, 0]]])
    out = group(pts, idx)
    assert out.shape == (2, 2, 2, 2)
    for b, m, j in itertools.product(range(2), range(2), range(2)):
        assert torch.equal(out[b, m, j], pts[b, idx[b, m, j]])


def test_three_nn_interpolation():
    g = torch.Generator().manual_seed(2)
    ref = torch.rand(2, 200, 3, generator=g, dtype=torch.float64)
    A = torch.randn(3, 4, generator=g, dtype=torch.float64)
    c = torch.randn(4, generator=g, dtype=torch.float64)
    values = ref @ A + c  # a linear function sampled at the ref points
    # Queried at (a shuffle of) the sample points themselves, interpolation returns the samples.
    perm = torch.randperm(200, generator=g)
    idx, w = three_nn(ref[:, perm], ref)
    torch.testing.assert_close(interpolate(values, idx, w), values[:, perm], rtol=0, atol=1e-6)
    # Anywhere: the three nearest (brute force) and convex weights favouring the nearest.
    query = torch.rand(2, 50, 3, generator=g, dtype=torch.float64)
    idx, w = three_nn(query, ref)
    d = torch.cdist(query, ref, compute_mode="donot_use_mm_for_euclid_dist")
    assert torch.equal(idx, d.topk(3, largest=False).indices)
    torch.testing.assert_close(w.sum(-1), torch.ones(2, 50, dtype=torch.float64))
    assert (w[..., 0] >= w[..., 1]).all() and (w[..., 1] >= w[..., 2]).all()
    # Fewer than three reference points: use what there is.
    idx, w = three_nn(query, ref[:, :2])
    assert idx.shape == (2, 50, 2)


# ---------------------------------------------------------------------------------------------
# The network
# ---------------------------------------------------------------------------------------------
SWITCHES = list(itertools.product([True, False], repeat=3))


@pytest.mark.parametrize("avg, diff, skip", SWITCHES)
def test_shapes_ranges_and_switches(avg, diff, skip):
    torch.manual_seed(0)
    net = PointNet(tiny_config(average_pooling=avg, normal_difference=diff, normal_skip=skip))
    x = torch.cat([sphere_features(300, seed=1, noise=0.3), sphere_features(300, seed=2, noise=0.3)])
    offset, normal = net(x)
    assert offset.shape == normal.shape == (2, 300, 3)
    assert offset.abs().max() <= 0.25
    torch.testing.assert_close(normal.norm(dim=-1), torch.ones(2, 300), atol=1e-5, rtol=0)
    points, _ = net.refine(x)
    torch.testing.assert_close(points, x[..., :3] + offset)
    # The switches' channels: normal difference adds 3 inputs to every SA MLP, the normal skip
    # adds 6 (normal and its difference to the interpolated one) to every FP MLP.
    sa_in = [level.mlp[0].in_features for level in net.sa]
    fp_in = [level.mlp[0].in_features for level in net.fp]
    assert sa_in == [c + 3 + 3 * diff for c in (NUM_FEATURES, 8, 16, 16)]
    assert fp_in == [c + 6 * skip for c in (32 + 16, 16 + 16, 16 + 8, 8 + NUM_FEATURES)]


def test_each_switch_changes_the_network():
    x = sphere_features(300, seed=3, noise=0.3)
    base = tiny_config()
    torch.manual_seed(0)
    ref = PointNet(base)
    out = ref(x)
    for name in ("normal_difference", "normal_skip"):
        other = PointNet(tiny_config(**{name: False}))
        assert parameter_count(other) < parameter_count(ref), name
    # Pooling has no parameters: same weights, different outputs.
    maxpool = PointNet(tiny_config(average_pooling=False))
    maxpool.load_state_dict(ref.state_dict())
    out_max = maxpool(x)
    assert not torch.allclose(out[0], out_max[0]) and not torch.allclose(out[1], out_max[1])


def test_gradients_reach_every_parameter():
    torch.manual_seed(0)
    net = PointNet(tiny_config())
    x = sphere_features(300, seed=4, noise=0.3)
    offset, normal = net(x)
    gt = sphere_features(200, radius=1.0, seed=5)
    loss = chamfer_loss(x[..., :3] + offset, normal, gt[..., :3], gt[..., 6:9]).total
    loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_residual_starts_at_the_hull():
    net = PointNet(tiny_config(residual=True))
    x = sphere_features(300, seed=6, noise=0.3)
    offset, normal = net(x)
    assert offset.abs().max() == 0
    torch.testing.assert_close(normal, x[..., FEATURE_COLUMNS["normal"]], atol=1e-6, rtol=0)


def test_widened_net_is_the_same_function_and_reads_the_new_columns():
    """widen_initial_state: a net for the paper's 12 columns, widened to NUM_FEATURES, computes
    the same function (new input weights zero) and the narrow net ignores extra columns; once the
    new weights move, the silhouette columns change the output."""
    torch.manual_seed(3)
    narrow = PointNet(tiny_config(in_features=PAPER_FEATURES)).eval()
    wide = PointNet(tiny_config()).eval()
    wide.load_state_dict(wide.widen_initial_state(narrow.state_dict(), {"in_features": PAPER_FEATURES}))
    x = sphere_features(300, seed=8, noise=0.2)
    x[..., FEATURE_COLUMNS["silhouette"]] = torch.rand(1, 300, NUM_FEATURES - PAPER_FEATURES) * 5
    with torch.no_grad():
        for a, b in zip(narrow(x), wide(x)):  # float32: wider matmuls sum in another order
            torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
        wide.sa[0].mlp[0].weight[:, -1] = 0.5
        assert (wide(x)[0] - narrow(x)[0]).abs().max() > 1e-3
    with pytest.raises(ValueError, match="narrow"):
        narrow.widen_initial_state(wide.state_dict(), {"in_features": NUM_FEATURES})


def test_presets():
    paper, cpu = paper_config(), cpu_config()
    assert preset("paper").point_training.net.centres == (1024, 256, 64, 16)
    assert paper.radii == (0.1, 0.2, 0.4, 0.8) and paper.neighbours == (64, 32, 32, 32)
    assert paper.sa_mlps == ((64, 64), (128, 128), (256, 256), (512, 512))
    assert paper.offset_scale == 0.25 and paper.in_features == NUM_FEATURES
    assert paper.average_pooling and paper.normal_difference and paper.normal_skip and not paper.residual
    net = PointNet(paper)
    assert [level.mlp[0].in_features for level in net.sa] == [6 + NUM_FEATURES, 70, 134, 262]
    # The paper's input (12 columns, 18 inputs to the first MLP) reads the first 12 columns only.
    paper_input = PointNet(paper_config(in_features=PAPER_FEATURES))
    assert paper_input.sa[0].mlp[0].in_features == 18
    assert [level.mlp[-3].out_features for level in net.sa] == [64, 128, 256, 512]
    assert net.head.in_features == 64 and net.head.out_features == 6
    assert cpu.num_points == 4096 and cpu.centres == (512, 128, 32, 8) and cpu.residual
    assert parameter_count(PointNet(cpu)) < parameter_count(net)
    with pytest.raises(ValueError):
        PointNetConfig(radii=(0.1, 0.2))
    with pytest.raises(ValueError):
        net(torch.zeros(1, 10, 5))


# ---------------------------------------------------------------------------------------------
# Losses
# ---------------------------------------------------------------------------------------------
def _nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a[:, None] - b[None], axis=-1).argmin(1)


def _random_cloud(g, b, n):
    p = torch.randn(b, n, 3, generator=g, dtype=torch.float64)
    return p, torch.nn.functional.normalize(torch.randn(b, n, 3, generator=g, dtype=torch.float64), dim=-1)


@pytest.mark.parametrize("squared, reduction", [(True, "mean"), (False, "mean"), (True, "sum"), (False, "sum")])
def test_chamfer_brute_force(squared, reduction):
    g = torch.Generator().manual_seed(7)
    p, n = _random_cloud(g, 2, 7)
    q, nq = _random_cloud(g, 2, 5)
    out = chamfer_loss(p, n, q, nq, squared=squared, reduction=reduction)
    P, N, Q, NQ = (t.numpy() for t in (p, n, q, nq))
    norm = (lambda v: (v ** 2).sum(-1)) if squared else (lambda v: np.linalg.norm(v, axis=-1))
    red = np.mean if reduction == "mean" else np.sum
    totals = []
    for b in range(2):
        f, r = _nearest(P[b], Q[b]), _nearest(Q[b], P[b])
        point = 0.5 * (red(norm(P[b] - Q[b, f])) + red(norm(Q[b] - P[b, r])))
        normal = 0.5 * (red(norm(N[b] - NQ[b, f])) + red(norm(NQ[b] - N[b, r])))
        totals.append((200 * point + 5 * normal, point, normal))
    expect = np.mean(totals, axis=0)
    for got, want in zip(out, expect):
        assert got.item() == pytest.approx(want, rel=1e-10)


def test_unseen_weights_ramp_with_the_distance_to_the_hull():
    """Hull samples on the plane z = 0; ground truth at depths 0 (on the hull), 0.05 (the ramp's
    start), 0.075 (half way), 0.1 and 0.3 (full weight) below it."""
    xy = torch.stack(torch.meshgrid(torch.linspace(-1, 1, 41, dtype=torch.float64),
                                    torch.linspace(-1, 1, 41, dtype=torch.float64), indexing="ij"), -1).reshape(-1, 2)
    hull = torch.cat([xy, torch.zeros(len(xy), 1, dtype=torch.float64)], -1)[None]
    depth = torch.tensor([0.0, 0.05, 0.075, 0.1, 0.3], dtype=torch.float64)
    gt = torch.stack([torch.full_like(depth, 0.2), torch.full_like(depth, -0.4), -depth], -1)[None]  # on grid nodes
    w = unseen_weights(gt, hull, 8.0, 0.05)
    np.testing.assert_allclose(w[0].numpy(), [1.0, 1.0, 5.0, 9.0, 9.0], atol=1e-12)


def test_chamfer_gt_weights_are_a_weighted_mean_of_the_q_side():
    g = torch.Generator().manual_seed(17)
    p, n = _random_cloud(g, 2, 7)
    q, nq = _random_cloud(g, 2, 5)
    plain = chamfer_loss(p, n, q, nq)
    ones = chamfer_loss(p, n, q, nq, gt_weights=torch.ones(2, 5, dtype=torch.float64))
    for a, b in zip(plain, ones):  # all weights equal: the paper's loss exactly
        assert a.item() == pytest.approx(b.item(), rel=1e-12)
    w = 1 + torch.rand(2, 5, generator=g, dtype=torch.float64) * 4
    out = chamfer_loss(p, n, q, nq, gt_weights=w)
    P, N, Q, NQ, W = (t.numpy() for t in (p, n, q, nq, w))
    points, normals = [], []
    for b in range(2):
        f, r = _nearest(P[b], Q[b]), _nearest(Q[b], P[b])
        wm = lambda v: (W[b] * v).sum() / W[b].sum()  # noqa: E731
        points.append(0.5 * (((P[b] - Q[b, f]) ** 2).sum(-1).mean() + wm(((Q[b] - P[b, r]) ** 2).sum(-1))))
        normals.append(0.5 * (((N[b] - NQ[b, f]) ** 2).sum(-1).mean() + wm(((NQ[b] - N[b, r]) ** 2).sum(-1))))
    assert out.point.item() == pytest.approx(np.mean(points), rel=1e-10)
    assert out.normal.item() == pytest.approx(np.mean(normals), rel=1e-10)


def test_chamfer_zero_on_identical_sets_and_gradients():
    g = torch.Generator().manual_seed(8)
    p, n = _random_cloud(g, 1, 50)
    perm = torch.randperm(50, generator=g)
    for squared in (True, False):
        pp = p.clone().requires_grad_(True)
        same = chamfer_loss(pp, n, p[:, perm].clone(), n[:, perm].clone(), squared=squared)
        assert same.total.item() == 0 and same.point.item() == 0 and same.normal.item() == 0
        same.total.backward()  # the plain norm's gradient at 0 must not be NaN
        assert torch.isfinite(pp.grad).all() and pp.grad.abs().max() == 0


def test_nearest_l2_brute_force_uses_the_hull_points():
    g = torch.Generator().manual_seed(9)
    p, n = _random_cloud(g, 2, 9)
    hull = p + 0.3 * torch.randn(2, 9, 3, generator=g, dtype=torch.float64)
    q, nq = _random_cloud(g, 2, 20)
    out = nearest_l2_loss(p, n, q, nq, hull_points=hull)
    P, N, H, Q, NQ = (t.numpy() for t in (p, n, hull, q, nq))
    per = []
    for b in range(2):
        i = _nearest(H[b], Q[b])  # the paper's p̂: nearest to the hull point p̃
        per.append([((P[b] - Q[b, i]) ** 2).sum(-1).mean(), ((N[b] - NQ[b, i]) ** 2).sum(-1).mean()])
    point, normal = np.mean(per, axis=0)
    assert out.point.item() == pytest.approx(point, rel=1e-10)
    assert out.normal.item() == pytest.approx(normal, rel=1e-10)
    assert out.total.item() == pytest.approx(200 * point + 5 * normal, rel=1e-10)
    # Without hull points the prediction itself is the query: the p -> q half of Chamfer.
    half = nearest_l2_loss(p, n, q, nq)
    i = [_nearest(P[b], Q[b]) for b in range(2)]
    want = np.mean([((P[b] - Q[b, i[b]]) ** 2).sum(-1).mean() for b in range(2)])
    assert half.point.item() == pytest.approx(want, rel=1e-10)
    assert tuple(LOSSES) == POINT_LOSSES == ("nearest", "view", "chamfer")  # the config checks --loss against POINT_LOSSES
    # One signature for all: every loss takes every target keyword, and rejects misspelt ones.
    targets = dict(hull_points=hull, view_points=p, view_normals=n, view_valid=None)
    for name, fn in LOSSES.items():
        assert torch.isfinite(fn(p, n, q, nq, **targets).total), name
        with pytest.raises(TypeError):
            fn(p, n, q, nq, hull_point=hull)


def test_view_dependent_targets_and_fallback():
    g = torch.Generator().manual_seed(10)
    p, n = _random_cloud(g, 1, 6)
    q, nq = _random_cloud(g, 1, 30)
    hull = p + 0.1
    vp, vn = _random_cloud(g, 1, 6)
    valid = torch.tensor([[True, False, True, True, False, True]])
    out = LOSSES["view"](p, n, q, nq, view_points=vp, view_normals=vn, view_valid=valid, hull_points=hull)
    near = _nearest(hull[0].numpy(), q[0].numpy())
    tp = torch.where(valid[0, :, None], vp[0], q[0, near])
    tn = torch.where(valid[0, :, None], vn[0], nq[0, near])
    assert out.point.item() == pytest.approx(((p[0] - tp) ** 2).sum(-1).mean().item(), rel=1e-10)
    assert out.normal.item() == pytest.approx(((n[0] - tn) ** 2).sum(-1).mean().item(), rel=1e-10)
    all_valid = view_dependent_l2_loss(p, n, q, nq, view_points=vp, view_normals=vn)
    assert all_valid.point.item() == pytest.approx(((p - vp) ** 2).sum(-1).mean().item(), rel=1e-10)


def test_view_targets_on_a_sphere():
    gt = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    rng = np.random.default_rng(11)
    u = rng.normal(size=(40, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    hull = 1.1 * u
    origins = np.array([[0.0, 0.0, 3.0], [3.0, 0.0, 0.0]])
    chosen = np.where(u[:, 2] > 0.2, 0, np.where(u[:, 0] > 0.2, 1, -1))
    points, normals, valid = view_targets(hull, chosen, origins, gt)
    # Analytic first hit of the ray o + t d on the unit sphere.
    for i in range(40):
        if chosen[i] < 0:
            assert not valid[i]
            continue
        o = origins[chosen[i]]
        d = (hull[i] - o) / np.linalg.norm(hull[i] - o)
        b = o @ d
        disc = b * b - (o @ o - 1.0)
        if abs(disc) < 1e-3:  # grazing: either answer is right
            continue
        assert bool(valid[i]) == (disc > 0)  # a hull point on the silhouette may miss the truth
        if disc < 0:
            continue
        hit = o + (-b - math.sqrt(disc)) * d
        np.testing.assert_allclose(points[i].numpy(), hit, atol=2e-3)  # faceted sphere
        np.testing.assert_allclose(normals[i].numpy(), hit, atol=2e-3)


# ---------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------
def test_overfit_one_sphere():
    """Hull: sphere of radius 1.1 with noisy mapped normals; truth: the unit sphere sampled in
    the same directions (a perfect answer has zero loss). The cpu preset, shrunk, starts at the
    hull (residual) and must cut the Chamfer loss 10x in 100 Adam steps (it reaches ~40x), the
    point term most of all: the offsets really move the points inwards."""
    torch.manual_seed(0)
    cfg = cpu_config(centres=(128, 32, 8, 4), neighbours=(16, 8, 8, 4),
                     sa_mlps=((16, 16), (32, 32), (32, 32), (64, 64)), fp_mlps=((32,), (32,), (16,), (16, 16)))
    net = PointNet(cfg)
    x = sphere_features(512, radius=1.1, seed=12, noise=0.2)
    u = x[..., FEATURE_COLUMNS["hull_normal"]]
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    history = []
    for _ in range(100):
        opt.zero_grad()
        points, normals = net.refine(x)
        loss = chamfer_loss(points, normals, u, u)
        loss.total.backward()
        opt.step()
        history.append(loss)
    first, last = history[0], history[-1]
    assert first.point.item() == pytest.approx(0.01, rel=1e-4)  # the hull is 0.1 off everywhere
    assert last.total.item() * 10 <= first.total.item(), (first.total.item(), last.total.item())
    assert last.point.item() * 20 <= first.point.item(), (first.point.item(), last.point.item())
