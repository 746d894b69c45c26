"""Multi-view consensus of the normal net's per-view normals (the `normals` stage's last step).

The net predicts each view's N1 and N2 on its own, yet a point of the surface has one normal, and
most points are seen by several views: the second interface of one view is the first interface of
another, seen head-on. So every pixel's normal is replaced by a weighted mean of the predictions
at the same point of the fed mesh (the hull):

- N1 at a pixel whose fed-mesh first hit is P: the N1 of every view whose own first hit at P's
  pixel lies within `tolerance_px` pixel footprints of P (the view sees P itself, not something in
  front of it), this view's included;
- N2 at a pixel whose fed-mesh second hit is P2: this view's own N2 (weight `OWN_N2_WEIGHT`) and the
  N1 of every view that sees P2 the same way.

Each N1 vote weighs the cosine between its view's direction and the fed mesh's normal there (a
face seen head-on is predicted better than one seen edge-on). On the validation set at 10 views
(docs/results.md, "The views' consensus"), the predicted N1 median goes from 0.83 x the hull's to
0.75 x and N2 from 0.73 x to 0.70 x. The refine stage's second pass runs without it (normals/stage.py).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..physics.camera import Cameras

# a view's own N2 weighs as three head-on N1 votes of other views: where the hull is coarse its second hit
# lies off the object's, and other views' N1 there describe another point (the 128x96 test split's N2 median:
# own 7.79, weight 1 8.37, 3 7.89 degrees; val480 0.733 / 0.693 / 0.698 x the hull's; docs/history.md, session 91)
OWN_N2_WEIGHT = 3.0


def _votes(cameras: Cameras, point1: Tensor, seen1: Tensor, query: Tensor, query_ok: Tensor,
           tolerance_px: float) -> list[tuple[Tensor, Tensor, Tensor]]:
    """For each view j: (y, x, sees) where (y, x) (V,H,W) is the pixel of view j that `query`
    (V,H,W,3 world points) falls in, and `sees` (V,H,W) that view j's first hit there is the query
    point (within `tolerance_px` pixel footprints at its depth)."""
    V, H, W = seen1.shape
    flat = query.reshape(-1, 3)
    ok = query_ok.reshape(-1)
    pitch = cameras.pixel_pitch
    out = []
    for j in range(V):  # one view at a time: V x (V H W) points, not V^2 H W at once
        xy, depth = cameras.select([j]).project(flat)
        x, y, depth = xy[0, :, 0].floor().long(), xy[0, :, 1].floor().long(), depth[0]
        inside = (x >= 0) & (x < W) & (y >= 0) & (y < H) & (depth > 0)
        xc, yc = x.clamp(0, W - 1), y.clamp(0, H - 1)
        near = (point1[j][yc, xc] - flat).norm(dim=-1) < tolerance_px * pitch[j] * depth.abs()
        sees = inside & ok & seen1[j][yc, xc] & near
        out.append((yc.reshape(V, H, W), xc.reshape(V, H, W), sees.reshape(V, H, W)))
    return out


def view_consensus(n1: Tensor, n2: Tensor, cameras: Cameras, point1: Tensor, point2: Tensor, normal1: Tensor,
                   seen1: Tensor, seen2: Tensor, tolerance_px: float = 1.0) -> tuple[Tensor, Tensor]:
    """n1, n2 (V,H,W,3): predicted camera-frame normals. cameras: the V views at H x W. point1,
    point2 (V,H,W,3): the fed mesh's first and second hits (world frame); normal1 its camera-frame
    normal at the first; seen1, seen2 (V,H,W) bool: where the first hit (and the prediction) exists,
    where the two-bounce path does. Returns the consensus (n1, n2), camera frame; pixels without a
    vote keep their prediction."""
    dtype = n1.dtype
    cams = cameras.to(device=n1.device, dtype=torch.float32)
    p1, p2 = point1.float(), point2.float()
    n1w = cams.camera_to_world(n1.float())
    facing = normal1[..., 2].float().clamp(min=0) * seen1  # camera frame: z faces the camera

    def mean_of(query, query_ok, own, own_weight):
        total = own * (own_weight * query_ok)[..., None]
        for j, (y, x, sees) in enumerate(_votes(cams, p1, seen1, query, query_ok, tolerance_px)):
            weight = facing[j][y, x] * sees
            total = total + n1w[j][y, x] * weight[..., None]
        norm = total.norm(dim=-1, keepdim=True)
        return torch.where(norm > 1e-6, total / norm.clamp(min=1e-12), own)

    # N1: the own view's vote is among the V (a view's first hit is its own pixel's)
    fused1 = cams.world_to_camera(mean_of(p1, seen1, n1w, torch.zeros_like(facing))).to(dtype)
    own2 = torch.full_like(facing, OWN_N2_WEIGHT)
    fused2 = cams.world_to_camera(mean_of(p2, seen2, cams.camera_to_world(n2.float()), own2))
    return torch.where(seen1[..., None], fused1, n1), torch.where(seen2[..., None], fused2.to(dtype), n2)
