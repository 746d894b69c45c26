"""PNet training losses (paper Sec. 3.2, "Point cloud refinement"), batched (B, N, 3) torch.

All three compare the refined points p = p̃ + δp̃ and normals N of PNet with the ground truth,
weighted by λ1 = 200 (points) and λ2 = 5 (normals), the paper's values for all experiments:

  nearest   L_P^nearest = Σ λ1 ||p - p̂||² + λ2 ||N - N̂||²                    (paper Eq. 2)
            p̂, N̂: the ground-truth surface point nearest to the *hull point* p̃, and its
            normal. The target is fixed per hull point; it does not follow the prediction.
  view      L_P^view = Σ λ1 ||p - p̂_v*||² + λ2 ||N - N̂_v*||²                  (paper Eq. 3)
            p̂_v*, N̂_v* = T_v*(S_v*(p̃, P̂¹_v*)), T_v*(S_v*(p̃, N̂¹_v*)): the ground-truth
            first-hit point and normal that the view v* chosen by feature mapping sees at p̃'s
            pixel, i.e. the first ground-truth surface point on the ray from v*'s camera centre
            through p̃ (`view_targets` casts exactly that ray); (p̂, N̂) where no view was chosen
            (the paper's v* = 0).
  chamfer   L_P^CD = Σ_p λ1/2 ||p - G(p,{q})|| + λ2/2 ||N - G_n(p,{q})||
                   + Σ_q λ1/2 ||q - G(q,{p})|| + λ2/2 ||N_q - G_n(q,{p})||       (paper Eq. 4)
            {q}, N_q: points sampled evenly on the ground-truth surface with their normals;
            G / G_n: the nearest point of the other set / that point's normal.

How we read the paper where it is loose:
- Eq. 2 and 3 square their norms; Eq. 4 as printed does not. Our Chamfer squares by default
  (`squared=True`): it matches Eq. 2-3, the squared Chamfer distance the paper reports (CD) and the
  authors' released training code; `squared=False` gives the printed, unsquared form.
- The paper sums over points. `reduction="mean"` (default) averages each sum over its points
  instead (for Eq. 4 each side over its own set, so sets of different sizes weigh equally), which
  keeps the loss independent of the point count; `reduction="sum"` is the printed sums. Both are
  then averaged over the batch. Adam, the paper's optimizer, is nearly invariant to that constant
  factor. With "mean" and squared=True, `PointLoss.point` of the Chamfer loss is exactly the CD
  metric of DESIGN.md ("Metrics"), ½(mean d(gt→pred)² + mean d(pred→gt)²).
- Nearest neighbours are searched in the ground-truth samples {q} (the caller makes them dense
  enough to stand for the surface), under no_grad; the distances are then recomputed from the
  gathered points, so gradients reach p and N (for Chamfer, also through the q -> p side).

Every loss returns a `PointLoss(total, point, normal)`: total = λ1 point + λ2 normal, point and
normal the unweighted, reduced terms (for logging). All share one call signature, so
`LOSSES[name](pred_points, pred_normals, gt_points, gt_normals, **targets)` works for any name
(targets: hull_points, view_points, view_normals, view_valid; options: lambda_point,
lambda_normal, reduction, squared); a loss ignores the ones it does not use, and a misspelt
keyword raises TypeError.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
import torch
import trimesh
from torch import Tensor

from ..render.raycast import RayCaster
from .model import gather_points, knn

__all__ = [
    "LAMBDA_POINT",
    "LAMBDA_NORMAL",
    "PointLoss",
    "nearest_targets",
    "view_targets",
    "nearest_l2_loss",
    "view_dependent_l2_loss",
    "chamfer_loss",
    "unseen_weights",
    "LOSSES",
]

LAMBDA_POINT = 200.0  # λ1
LAMBDA_NORMAL = 5.0  # λ2
REDUCTIONS = ("mean", "sum")


class PointLoss(NamedTuple):
    """total: λ1 point + λ2 normal (scalar, differentiable). point / normal: the reduced
    unweighted point and normal terms (scalars, differentiable)."""

    total: Tensor
    point: Tensor
    normal: Tensor


def _reduce(per_point: Tensor, reduction: str) -> Tensor:
    """(B, N) -> scalar: mean over points ("mean") or sum over points ("sum"), then batch mean."""
    if reduction == "mean":
        return per_point.mean()
    if reduction == "sum":
        return per_point.sum(-1).mean()
    raise ValueError(f"unknown reduction {reduction!r}; use one of {REDUCTIONS}")


def _check(pred_points: Tensor, pred_normals: Tensor, gt_points: Tensor, gt_normals: Tensor) -> None:
    if pred_points.dim() != 3 or pred_points.shape[-1] != 3 or pred_normals.shape != pred_points.shape:
        raise ValueError(f"predictions must be (B, N, 3) points and normals, got {tuple(pred_points.shape)} "
                         f"and {tuple(pred_normals.shape)}")
    if gt_points.dim() != 3 or gt_points.shape[-1] != 3 or gt_normals.shape != gt_points.shape \
            or gt_points.shape[0] != pred_points.shape[0]:
        raise ValueError(f"ground truth must be (B, M, 3) points and normals with B = {pred_points.shape[0]}, "
                         f"got {tuple(gt_points.shape)} and {tuple(gt_normals.shape)}")


def _sq_norm(x: Tensor) -> Tensor:
    return x.square().sum(-1)


def _norm(x: Tensor, squared: bool) -> Tensor:
    """||x||² or ||x|| over the last axis; the plain norm has a zero (not NaN) gradient at 0."""
    s = _sq_norm(x)
    if squared:
        return s
    positive = s > 0
    return torch.where(positive, s.clamp_min(1e-30).sqrt(), torch.zeros_like(s))


def nearest_targets(query: Tensor, gt_points: Tensor, gt_normals: Tensor) -> tuple[Tensor, Tensor]:
    """The ground-truth sample nearest to each query point, and its normal.

    query: (B, N, 3). gt_points, gt_normals: (B, M, 3), same frame. Returns (B, N, 3), (B, N, 3)
    (no gradient: they are targets).
    """
    idx = knn(query, gt_points, 1)[..., 0]
    return gather_points(gt_points.detach(), idx), gather_points(gt_normals.detach(), idx)


def _paired(pred_points: Tensor, pred_normals: Tensor, target_points: Tensor, target_normals: Tensor,
            lambda_point: float, lambda_normal: float, reduction: str) -> PointLoss:
    point = _reduce(_sq_norm(pred_points - target_points), reduction)
    normal = _reduce(_sq_norm(pred_normals - target_normals), reduction)
    return PointLoss(lambda_point * point + lambda_normal * normal, point, normal)


def nearest_l2_loss(pred_points: Tensor, pred_normals: Tensor, gt_points: Tensor, gt_normals: Tensor, *,
                    hull_points: Tensor | None = None, lambda_point: float = LAMBDA_POINT,
                    lambda_normal: float = LAMBDA_NORMAL, reduction: str = "mean",
                    view_points: Tensor | None = None, view_normals: Tensor | None = None,
                    view_valid: Tensor | None = None, squared: bool = True) -> PointLoss:
    """L_P^nearest, paper Eq. 2: Σ λ1 ||p - p̂||² + λ2 ||N - N̂||².

    pred_points, pred_normals: (B, N, 3) p = p̃ + δp̃ and N. gt_points, gt_normals: (B, M, 3)
    ground-truth surface samples {q} and their unit normals. hull_points: (B, N, 3) the hull
    points p̃; the paper's p̂ is the ground truth nearest to p̃. Without hull_points the query
    is the (detached) prediction p itself, which makes this the p -> q half of Chamfer.
    view_points, view_normals, view_valid, squared: unused (the shared LOSSES signature).
    """
    _check(pred_points, pred_normals, gt_points, gt_normals)
    query = pred_points if hull_points is None else hull_points
    target_p, target_n = nearest_targets(query, gt_points, gt_normals)
    return _paired(pred_points, pred_normals, target_p, target_n, lambda_point, lambda_normal, reduction)


def view_dependent_l2_loss(pred_points: Tensor, pred_normals: Tensor, gt_points: Tensor, gt_normals: Tensor, *,
                           view_points: Tensor, view_normals: Tensor, view_valid: Tensor | None = None,
                           hull_points: Tensor | None = None, lambda_point: float = LAMBDA_POINT,
                           lambda_normal: float = LAMBDA_NORMAL, reduction: str = "mean",
                           squared: bool = True) -> PointLoss:
    """L_P^view, paper Eq. 3: Σ λ1 ||p - p̂_v*||² + λ2 ||N - N̂_v*||².

    view_points, view_normals: (B, N, 3) the per-point targets p̂_v*, N̂_v* precomputed by the
    caller (`view_targets`: ground truth seen through p̃ by its chosen view v*), world frame.
    view_valid: (B, N) bool, False where no view was chosen or its ray missed the ground truth;
    there the target falls back to Eq. 2's nearest point (to hull_points, see
    `nearest_l2_loss`). None: all valid. Other arguments as `nearest_l2_loss`; squared: unused.
    """
    _check(pred_points, pred_normals, gt_points, gt_normals)
    if view_points.shape != pred_points.shape or view_normals.shape != pred_points.shape:
        raise ValueError(f"view targets must be {tuple(pred_points.shape)}, got {tuple(view_points.shape)} "
                         f"and {tuple(view_normals.shape)}")
    target_p, target_n = view_points.detach(), view_normals.detach()
    if view_valid is not None and not bool(view_valid.all()):
        query = pred_points if hull_points is None else hull_points
        near_p, near_n = nearest_targets(query, gt_points, gt_normals)
        ok = view_valid.to(torch.bool).unsqueeze(-1)
        target_p, target_n = torch.where(ok, target_p, near_p), torch.where(ok, target_n, near_n)
    return _paired(pred_points, pred_normals, target_p, target_n, lambda_point, lambda_normal, reduction)


def unseen_weights(gt_points: Tensor, hull_points: Tensor, weight: float, distance: float) -> Tensor:
    """Per ground-truth sample weights (B, M) that stress the surface no silhouette shows.

    A sample q whose nearest hull point (of `hull_points`, (B, N, 3), the hull's own samples) is
    farther than `distance` lies in a concavity the hull spans (a slot's walls and floor); its weight
    ramps from 1 at `distance` to 1 + `weight` at twice that. The nearest of N hull samples stands for
    the hull's surface: it overestimates the distance by up to half their spacing (~0.02 for 4096
    samples in the hull-normalized frame), hence train-points' default start of 0.05, not 0. The
    training step recomputes these each time (one k-d tree query, milliseconds) rather than cache them.
    """
    idx = knn(gt_points, hull_points, 1)[..., 0]
    d = (gt_points.detach() - gather_points(hull_points.detach(), idx)).norm(dim=-1)
    return 1.0 + weight * ((d - distance) / distance).clamp(0.0, 1.0)


def _weighted(per_point: Tensor, weights: Tensor | None, reduction: str) -> Tensor:
    """`_reduce` of per_point (B, M) with per-point weights (B, M) (None: plain). "mean" divides by the
    weights' sum, so a shape without weighted points has exactly the unweighted loss."""
    if weights is None:
        return _reduce(per_point, reduction)
    if reduction == "mean":
        return ((per_point * weights).sum(-1) / weights.sum(-1)).mean()
    return _reduce(per_point * weights, reduction)


def chamfer_loss(pred_points: Tensor, pred_normals: Tensor, gt_points: Tensor, gt_normals: Tensor, *,
                 lambda_point: float = LAMBDA_POINT, lambda_normal: float = LAMBDA_NORMAL,
                 reduction: str = "mean", squared: bool = True, hull_points: Tensor | None = None,
                 view_points: Tensor | None = None, view_normals: Tensor | None = None,
                 view_valid: Tensor | None = None, gt_weights: Tensor | None = None) -> PointLoss:
    """L_P^CD, paper Eq. 4: both directions between the prediction {p, N} and the ground truth
    {q, N_q}, each with λ1/2 on the distance to the nearest point of the other set and λ2/2 on
    the difference to that point's normal.

    pred_points, pred_normals: (B, N, 3). gt_points, gt_normals: (B, M, 3) evenly sampled
    ground-truth surface points and unit normals. squared: square the norms (default; see the
    module docstring). `point` = ½(d(p→q) + d(q→p)), `normal` likewise, each reduced per side.
    gt_weights: (B, M) optional weights of the q→p side's samples (`unseen_weights`), a weighted
    mean under "mean"; None: the paper's loss.
    hull_points, view_points, view_normals, view_valid: unused (the shared LOSSES signature).
    """
    _check(pred_points, pred_normals, gt_points, gt_normals)
    to_gt = knn(pred_points, gt_points, 1)[..., 0]  # G(p, {q}), (B, N)
    to_pred = knn(gt_points, pred_points, 1)[..., 0]  # G(q, {p}), (B, M)
    q, nq = gt_points.detach(), gt_normals.detach()
    p_fwd = _reduce(_norm(pred_points - gather_points(q, to_gt), squared), reduction)
    n_fwd = _reduce(_norm(pred_normals - gather_points(nq, to_gt), squared), reduction)
    p_bwd = _weighted(_norm(q - gather_points(pred_points, to_pred), squared), gt_weights, reduction)
    n_bwd = _weighted(_norm(nq - gather_points(pred_normals, to_pred), squared), gt_weights, reduction)
    point, normal = 0.5 * (p_fwd + p_bwd), 0.5 * (n_fwd + n_bwd)
    return PointLoss(lambda_point * point + lambda_normal * normal, point, normal)


LOSSES: dict[str, Callable[..., PointLoss]] = {
    "nearest": nearest_l2_loss,
    "view": view_dependent_l2_loss,
    "chamfer": chamfer_loss,
}


def view_targets(hull_points, chosen_view, camera_origins, gt_mesh: trimesh.Trimesh | RayCaster
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """The view-dependent targets p̂_v*, N̂_v* of Eq. 3 for one shape, by ray casting.

    The paper fetches view v*'s ground-truth first-hit point and normal maps (P̂¹, N̂¹, moved to
    world by T_v*) bilinearly at p̃'s projection; that is the first ground-truth surface hit on
    the ray from v*'s camera centre through p̃, which we cast exactly (Embree) instead of
    interpolating between pixels. N̂ is the hit's smooth (vertex-interpolated) outward normal.

    hull_points: (N, 3) p̃. chosen_view: (N,) int, the view feature mapping chose
    (features.map_features(...)["chosen_view"]), -1 for none. camera_origins: (V, 3) camera
    centres (Cameras.origin). gt_mesh: the ground-truth mesh (or a RayCaster on it). All in the
    same world frame; numpy or torch.
    Returns points (N, 3) float32, normals (N, 3) float32 and valid (N,) bool (a view was chosen
    and its ray hit the ground truth); invalid rows are zero. Tensors on the CPU; add a batch axis
    and move them to the prediction's device for `view_dependent_l2_loss`.
    """
    as_np = lambda a: (a.detach().cpu().numpy() if isinstance(a, Tensor) else np.asarray(a))  # noqa: E731
    p = as_np(hull_points).astype(np.float64).reshape(-1, 3)
    view = as_np(chosen_view).astype(np.int64).reshape(-1)
    origins = as_np(camera_origins).astype(np.float64).reshape(-1, 3)
    if len(view) != len(p):
        raise ValueError(f"chosen_view has {len(view)} entries for {len(p)} points")
    if (view >= len(origins)).any():
        raise ValueError(f"chosen_view refers to view {int(view.max())} of {len(origins)}")
    caster = gt_mesh if isinstance(gt_mesh, RayCaster) else RayCaster(gt_mesh)
    points = np.zeros((len(p), 3), np.float32)
    normals = np.zeros((len(p), 3), np.float32)
    valid = np.zeros(len(p), bool)
    rows = np.nonzero(view >= 0)[0]
    if len(rows):
        o = origins[view[rows]]
        d = p[rows] - o
        d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
        hits = caster.intersect(o, d)
        points[rows] = hits.point
        normals[rows] = hits.normal
        valid[rows] = hits.hit
    return torch.from_numpy(points), torch.from_numpy(normals), torch.from_numpy(valid)
