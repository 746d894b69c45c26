"""PNet: the paper's modified PointNet++ for point-cloud refinement (Sec. 3.2, supplement).

PNet({p̃}, {f}) -> ({δp̃}, {N}): per visual-hull point an offset, p = p̃ + δp̃, and a unit normal.
One implementation; the supplement's ablation (its table "standard, - maxPooling, - normal Diff.,
- normal Skip.") is three switches of `PointNetConfig`:
  average_pooling    True: ball features are averaged over the ball's real members (the paper's
                     change, "to favor smooth results"); False: standard PointNet++ max pooling.
  normal_difference  True: each neighbour's grouping feature gets its normal minus the centre's
                     normal, next to the usual relative position.
  normal_skip        True: every feature-propagation skip link gets the level's normals and their
                     difference to the normals interpolated from the coarser level.
  standard PointNet++ = all three False.

Input. `forward(features)` takes (B, N, C) world-frame features in the column layout of
lookingglass.points.features.FEATURE_COLUMNS: xyz at 0:3 (the hull point p̃), the hull normal at
3:6, the mapped (predicted) normal N1 at 6:9, then rendering error, TIR and view cosine (the
paper's 12 columns), then our silhouette-cone counts. The net reads the first `in_features`
columns (PAPER_FEATURES = 12: the paper's input; NUM_FEATURES: with the counts), so nets made for
fewer columns run on today's features. xyz drives sampling and grouping; the mapped normal is
"the normal" of the three switches; all read columns are the level-0 point features. Points are
expected at the unit-sphere scale of the normalized frame (the radii 0.1 ... 0.8 are in its units).

Layout. Tensors are channels-last, (B, N, C); a per-point MLP layer is Linear (no bias) ->
GroupNorm (channels per group `gn_group_size`; statistics per shape over all points and
neighbours) -> ReLU. Index work (farthest point sampling, ball query, 3-NN) runs without
gradients: the hull points are inputs, never learned.

Choices the paper leaves open (ours):
- Relative neighbour positions are divided by the ball radius, so each level sees them in [-1, 1].
- Average pooling averages over the ball's distinct members only; the duplicates that pad a ball
  to k entries would otherwise over-weight its first member. (Max pooling is unaffected by them.)
- Feature-propagation widths (coarse to fine) (512, 256), (256, 128), (128, 64), (64,), then a
  linear head to 6 = offset (3) + normal (3); 3-NN interpolation with inverse squared distance
  weights (as PointNet++).
- Fine-tuning onto more input columns (`widen_initial_state`): the new columns' input weights
  start at zero, so the widened net starts as the function it was trained to be.
- `residual` (cpu preset): the last layer is zero-initialized and the normal is
  normalize(mapped normal + raw), so an untrained net returns the hull points and the mapped
  normals and training spends its steps on corrections (as NormalNetConfig.residual).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import Tensor, nn

from .config import FEATURE_COLUMNS, PointNetConfig, cpu_config, paper_config

__all__ = [
    "PointNetConfig",
    "paper_config",
    "cpu_config",
    "PointNet",
    "farthest_point_sample",
    "ball_query",
    "ball_members",
    "gather_points",
    "group",
    "three_nn",
    "interpolate",
    "knn",
    "parameter_count",
]

XYZ_COLUMNS = FEATURE_COLUMNS["point"]
NORMAL_COLUMNS = FEATURE_COLUMNS["normal"]

# Distance matrices are built in chunks of about this many entries (x 4 bytes, plus the sort
# keys of a ball query), so 20 000 points x 1024 centres never materializes at once.
CHUNK_ELEMENTS = 1 << 22


# ---------------------------------------------------------------------------------------------
# Index helpers (vectorized over batch and points; no gradients)
# ---------------------------------------------------------------------------------------------
def _chunk_rows(rows: int, cols: int, batch: int) -> int:
    return max(1, min(rows, CHUNK_ELEMENTS // max(1, cols * batch)))


@torch.no_grad()
def farthest_point_sample(xyz: Tensor, m: int) -> Tensor:
    """Farthest point sampling, deterministic: starts at index 0 of every cloud.

    Each step takes the point farthest (Euclidean) from all points taken so far; ties go to the
    lowest index. The loop runs over the m picks; each pick is vectorized over B and N.
    xyz: (B, N, 3). m: 1 <= m <= N. Returns (B, m) int64 indices, distinct when the cloud has at
    least m distinct points.
    """
    B, N, _ = xyz.shape
    m = int(m)
    if not 1 <= m <= N:
        raise ValueError(f"cannot sample {m} of {N} points")
    x = xyz.detach()
    out = torch.empty(B, m, dtype=torch.long, device=x.device)
    nearest = torch.full((B, N), float("inf"), dtype=x.dtype, device=x.device)
    far = torch.zeros(B, dtype=torch.long, device=x.device)
    rows = torch.arange(B, device=x.device)
    diff = torch.empty_like(x)
    d = torch.empty_like(nearest)
    for i in range(m):
        out[:, i] = far
        # In-place ops into preallocated buffers: this loop is the sampler's whole cost.
        torch.sub(x, x[rows, far].unsqueeze(1), out=diff)
        torch.sum(diff.square_(), dim=-1, out=d)
        torch.minimum(nearest, d, out=nearest)
        far = nearest.argmax(dim=-1)
    return out


def _sq_dist(a: Tensor, b: Tensor, b_sq: Tensor | None = None, row_term: bool = True) -> Tensor:
    """(B, n, 3), (B, m, 3) -> (B, n, m) squared distances |a|² + |b|² - 2 a·b (one batched
    matmul, as torch.cdist's matmul mode, without its square root: ~2x faster than cdist here;
    accurate to ~1e-7 x |x|², ample for neighbour selection). b_sq: precomputed |b|² (B, 1, m).
    row_term=False leaves out |a|², which changes no row's ordering (for nearest-neighbour
    searches)."""
    if b_sq is None:
        b_sq = b.square().sum(-1).unsqueeze(1)
    d = torch.baddbmm(b_sq, a, b.transpose(1, 2), alpha=-2.0)
    if row_term:
        d = d.add_(a.square().sum(-1, keepdim=True)).clamp_min_(0.0)
    return d


@torch.no_grad()
def ball_query(xyz: Tensor, centres: Tensor, radius: float, k: int) -> Tensor:
    """PointNet++ ball query: per centre the first k points (in index order) within `radius`.

    A ball with fewer than k members is padded with its first member. A ball with no member at
    all (possible only for centres that are not cloud points) gets the nearest point instead.
    xyz: (B, N, 3). centres: (B, M, 3), same frame. Returns (B, M, k) int64 indices into N.
    Built from chunked distance matrices and a top-k over "index if inside, else N" keys.
    """
    B, N, _ = xyz.shape
    M = centres.shape[1]
    k = int(k)
    kk = min(k, N)
    r2 = float(radius) ** 2
    x, c = xyz.detach(), centres.detach()
    order = torch.arange(N, device=x.device, dtype=torch.float32)  # exact up to 2^24 points
    out = torch.empty(B, M, k, dtype=torch.long, device=x.device)
    x_sq = x.square().sum(-1).unsqueeze(1)
    step = _chunk_rows(M, N, B)
    for s in range(0, M, step):
        d2 = _sq_dist(c[:, s:s + step], x, x_sq)  # (B, m, N)
        key = torch.where(d2 <= r2, order, float(N))
        first = key.topk(kk, dim=-1, largest=False, sorted=True).values.long()  # (B, m, kk)
        found = first < N
        # Empty ball: fall back to the nearest point, so every entry is a real index.
        lead = torch.where(found[..., 0], first[..., 0], d2.argmin(dim=-1))
        idx = torch.where(found, first, lead.unsqueeze(-1))
        if kk < k:
            idx = torch.cat([idx, lead.unsqueeze(-1).expand(-1, -1, k - kk)], dim=-1)
        out[:, s:s + step] = idx
    return out


def ball_members(idx: Tensor) -> Tensor:
    """(B, M, k) ball-query indices -> (B, M, k) bool: True for a ball's distinct members, False
    for the padding. Members come in increasing index order and padding repeats the first one,
    so an entry is padding exactly when it is not the first and equals the first."""
    member = idx != idx[..., :1]
    member[..., 0] = True
    return member


def gather_points(points: Tensor, idx: Tensor) -> Tensor:
    """points (B, N, C), idx (B, M) int64 -> (B, M, C)."""
    return torch.gather(points, 1, idx.unsqueeze(-1).expand(-1, -1, points.shape[-1]))


def group(points: Tensor, idx: Tensor) -> Tensor:
    """points (B, N, C), idx (B, M, k) int64 -> (B, M, k, C): the points of each ball
    (differentiable in `points`)."""
    B, M, k = idx.shape
    return gather_points(points, idx.reshape(B, M * k)).reshape(B, M, k, points.shape[-1])


@torch.no_grad()
def knn(query: Tensor, ref: Tensor, k: int) -> Tensor:
    """The k nearest `ref` points of every `query` point, nearest first.

    query: (B, N, 3). ref: (B, M, 3), 1 <= k <= M. Returns (B, N, k) int64 indices into M.
    On the CPU a k-d tree per cloud (scipy; exact, float64): 20 000 x 20 000 takes ~0.03 s there
    against ~1.2 s for the chunked distance matrix, which is what runs on other devices
    (chunks of `_sq_dist` over the query points, then top-k).
    """
    B, N, _ = query.shape
    M = ref.shape[1]
    if not 1 <= k <= M:
        raise ValueError(f"cannot take {k} nearest of {M} points")
    q, r = query.detach(), ref.detach()
    if q.device.type == "cpu":
        out = np.empty((B, N, k), dtype=np.int64)
        for b in range(B):  # a loop over shapes, not points
            tree = cKDTree(r[b].double().numpy())
            out[b] = tree.query(q[b].double().numpy(), k=k)[1].reshape(N, k)
        return torch.from_numpy(out)
    return _knn_dense(q, r, k)


def _knn_dense(q: Tensor, r: Tensor, k: int) -> Tensor:
    """`knn` by chunked distance matrices (any device; the path GPUs take)."""
    B, N, _ = q.shape
    M = r.shape[1]
    out = torch.empty(B, N, k, dtype=torch.long, device=q.device)
    r_sq = r.square().sum(-1).unsqueeze(1)
    step = _chunk_rows(N, M, B)
    for s in range(0, N, step):
        d = _sq_dist(q[:, s:s + step], r, r_sq, row_term=False)
        out[:, s:s + step] = d.argmin(-1, keepdim=True) if k == 1 else d.topk(k, -1, largest=False).indices
    return out


@torch.no_grad()
def three_nn(query: Tensor, ref: Tensor) -> tuple[Tensor, Tensor]:
    """Three nearest `ref` points of every `query` point and their interpolation weights.

    Weights are inverse squared distances normalized to sum to 1 (PointNet++); squared distances
    are recomputed exactly from the gathered points and floored at 1e-10, so a query that sits on
    a ref point takes (to ~1e-8) that point's value.
    query: (B, N, 3). ref: (B, M, 3). Returns idx (B, N, t) int64 and weights (B, N, t), t = min(3, M).
    """
    t = min(3, ref.shape[1])
    idx = knn(query, ref, t)
    near = group(ref.detach(), idx)  # (B, N, t, 3)
    d2 = (query.detach().unsqueeze(2) - near).square().sum(-1).clamp_min(1e-10)
    w = 1.0 / d2
    return idx, w / w.sum(-1, keepdim=True)


def interpolate(values: Tensor, idx: Tensor, weights: Tensor) -> Tensor:
    """values (B, M, C) at ref points, idx / weights (B, N, t) from `three_nn` -> (B, N, C)."""
    return (group(values, idx) * weights.unsqueeze(-1)).sum(2)


# ---------------------------------------------------------------------------------------------
# Layers
# ---------------------------------------------------------------------------------------------
class GroupNormLast(nn.Module):
    """GroupNorm for channels-last tensors (B, ..., C): statistics per sample and group over all
    leading positions, then a per-channel affine (as nn.GroupNorm on (B, C, ...))."""

    def __init__(self, groups: int, channels: int, eps: float = 1e-5):
        super().__init__()
        if channels % groups:
            raise ValueError(f"{channels} channels do not split into {groups} groups")
        self.groups, self.eps = groups, eps
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, x: Tensor) -> Tensor:
        B, C = x.shape[0], x.shape[-1]
        y = x.reshape(B, -1, self.groups, C // self.groups)
        var, mean = torch.var_mean(y, dim=(1, 3), unbiased=False, keepdim=True)
        y = (y - mean) * torch.rsqrt(var + self.eps)
        return y.reshape(x.shape) * self.weight + self.bias


def _mlp(cin: int, widths: tuple[int, ...], group_size: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for cout in widths:
        groups = max(1, cout // group_size)
        while cout % groups:  # widths that are not multiples of the group size
            groups -= 1
        # No bias: GroupNorm's shift makes it redundant.
        layers += [nn.Linear(cin, cout, bias=False), GroupNormLast(groups, cout), nn.ReLU(inplace=True)]
        cin = cout
    return nn.Sequential(*layers)


class SetAbstraction(nn.Module):
    """One PointNet++ set-abstraction level: FPS centres, ball grouping, shared MLP, pooling.

    Per neighbour j of centre c the MLP sees [(x_j - x_c) / radius, (n_j - n_c) if
    normal_difference, f_j]; the ball is pooled by (masked) average or max.
    """

    def __init__(self, centres: int, radius: float, neighbours: int, in_channels: int,
                 widths: tuple[int, ...], *, average_pooling: bool, normal_difference: bool,
                 group_size: int):
        super().__init__()
        self.centres, self.radius, self.neighbours = centres, radius, neighbours
        self.average_pooling, self.normal_difference = average_pooling, normal_difference
        self.mlp = _mlp(in_channels + 3 + (3 if normal_difference else 0), widths, group_size)
        self.out_channels = widths[-1]

    def forward(self, xyz: Tensor, normals: Tensor, feats: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """xyz (B, N, 3), normals (B, N, 3) unit, feats (B, N, C) ->
        centres' xyz (B, M, 3), their normals (B, M, 3), pooled features (B, M, out_channels)."""
        m = min(self.centres, xyz.shape[1])
        centre_idx = farthest_point_sample(xyz, m)
        new_xyz, new_normals = gather_points(xyz, centre_idx), gather_points(normals, centre_idx)
        idx = ball_query(xyz, new_xyz, self.radius, self.neighbours)  # (B, M, k)
        parts = [(group(xyz, idx) - new_xyz.unsqueeze(2)) / self.radius]
        if self.normal_difference:
            parts.append(group(normals, idx) - new_normals.unsqueeze(2))
        parts.append(group(feats, idx))
        h = self.mlp(torch.cat(parts, dim=-1))  # (B, M, k, C')
        if self.average_pooling:
            member = ball_members(idx).unsqueeze(-1).to(h.dtype)
            pooled = (h * member).sum(2) / member.sum(2)
        else:
            pooled = h.amax(2)  # padding repeats a member, so it never changes the max
        return new_xyz, new_normals, pooled


class FeaturePropagation(nn.Module):
    """One PointNet++ feature-propagation level: 3-NN interpolation from the coarse level, skip
    link from the fine level ([interpolated, skip, (n, n - interpolated n) if normal_skip]), MLP."""

    def __init__(self, coarse_channels: int, skip_channels: int, widths: tuple[int, ...], *,
                 normal_skip: bool, group_size: int):
        super().__init__()
        self.normal_skip = normal_skip
        self.mlp = _mlp(coarse_channels + skip_channels + (6 if normal_skip else 0), widths, group_size)
        self.out_channels = widths[-1]

    def forward(self, xyz: Tensor, normals: Tensor, skip: Tensor, coarse_xyz: Tensor,
                coarse_normals: Tensor, coarse_feats: Tensor) -> Tensor:
        """Fine level xyz / normals (B, N, 3), skip (B, N, Cs); coarse level xyz / normals
        (B, M, 3), feats (B, M, Cc). Returns (B, N, out_channels)."""
        idx, w = three_nn(xyz, coarse_xyz)
        parts = [interpolate(coarse_feats, idx, w), skip]
        if self.normal_skip:
            parts += [normals, normals - interpolate(coarse_normals, idx, w)]
        return self.mlp(torch.cat(parts, dim=-1))


# ---------------------------------------------------------------------------------------------
# The network
# ---------------------------------------------------------------------------------------------
class PointNet(nn.Module):
    """PNet. forward(features (B, N, in_features)) -> (offset (B, N, 3), normal (B, N, 3)).

    offset = offset_scale * tanh(.) (world units, |component| <= offset_scale); normal is unit,
    world frame. See the module docstring for the feature columns.
    """

    def __init__(self, cfg: PointNetConfig):
        super().__init__()
        self.cfg = cfg
        self.sa = nn.ModuleList()
        channels = [cfg.in_features]
        for m, r, k, widths in zip(cfg.centres, cfg.radii, cfg.neighbours, cfg.sa_mlps):
            level = SetAbstraction(m, r, k, channels[-1], widths, average_pooling=cfg.average_pooling,
                                   normal_difference=cfg.normal_difference, group_size=cfg.gn_group_size)
            self.sa.append(level)
            channels.append(level.out_channels)
        self.fp = nn.ModuleList()
        coarse = channels[-1]
        for i, widths in enumerate(cfg.fp_mlps):
            skip = channels[cfg.levels - 1 - i]
            level = FeaturePropagation(coarse, skip, widths, normal_skip=cfg.normal_skip,
                                       group_size=cfg.gn_group_size)
            self.fp.append(level)
            coarse = level.out_channels
        self.head = nn.Linear(coarse, 6)
        if cfg.residual:
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)

    def forward(self, features: Tensor) -> tuple[Tensor, Tensor]:
        if features.dim() != 3 or features.shape[-1] < self.cfg.in_features:
            raise ValueError(f"expected features (B, N, >= {self.cfg.in_features}), got {tuple(features.shape)}")
        features = features[..., :self.cfg.in_features]
        xyz = features[..., XYZ_COLUMNS].contiguous()
        normals = F.normalize(features[..., NORMAL_COLUMNS], dim=-1, eps=1e-6)
        levels = [(xyz, normals, features)]
        for sa in self.sa:
            levels.append(sa(*levels[-1]))
        feats = levels[-1][2]
        for i, fp in enumerate(self.fp):
            fine_xyz, fine_normals, skip = levels[self.cfg.levels - 1 - i]
            coarse_xyz, coarse_normals, _ = levels[self.cfg.levels - i]
            feats = fp(fine_xyz, fine_normals, skip, coarse_xyz, coarse_normals, feats)
        out = self.head(feats)
        offset = self.cfg.offset_scale * torch.tanh(out[..., :3])
        raw = out[..., 3:]
        if self.cfg.residual:
            raw = normals + torch.tanh(raw)
        return offset, F.normalize(raw, dim=-1, eps=1e-6)

    def widen_initial_state(self, state: dict[str, Tensor], saved_config: dict) -> dict[str, Tensor]:
        """`state` of a net like this one but made with `saved_config` (its weights.json "net")
        for in_features <= cfg.in_features input columns, with zero input weights added for the
        new columns. The level-0 features enter two layers: the first SA MLP, where they are the
        last inputs, and the last FP MLP, where they are the skip link, before the normals when
        normal_skip is on."""
        saved_in_features = int(saved_config.get("in_features", self.cfg.in_features))
        extra = self.cfg.in_features - saved_in_features
        if extra < 0:
            raise ValueError(f"cannot narrow {saved_in_features} input columns to {self.cfg.in_features}")
        if extra == 0:
            return state
        state = dict(state)
        tail = 6 if self.cfg.normal_skip else 0
        for key, after in (("sa.0.mlp.0.weight", 0), (f"fp.{len(self.fp) - 1}.mlp.0.weight", tail)):
            w = state[key]
            at = w.shape[1] - after
            state[key] = torch.cat([w[:, :at], w.new_zeros(w.shape[0], extra), w[:, at:]], dim=1)
        return state

    def refine(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """The refined cloud: points p = p̃ + δp̃ (B, N, 3) and unit normals (B, N, 3), world."""
        offset, normal = self(features)
        return features[..., XYZ_COLUMNS] + offset, normal


def parameter_count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
