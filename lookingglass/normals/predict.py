"""Normal maps from the network, and their re-rendering: the one prediction path.

`reconstruct`, `eval-normals`, `eval-shapes` and the point network's training features all call
`predict_normals`; `render_normals` scores any normals (the hull's, the ground truth's) the same
way, so every row of every table is measured by the same rendering layer.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from ..physics.camera import Cameras
from .consensus import view_consensus
from .inputs import NormalInputs, mirror_vector_maps, network_tensors
from .latent import LatentOptConfig, optimize_latent
from .model import NormalNet
from .render_layer import comparable, prediction_error_maps


@dataclass
class NormalMaps:
    """Per-view normals at the network's resolution and how well they explain the photos.

    cameras: the views at H x W, the inputs' frame. n1, n2 (V,H,W,3) camera-frame normals at the
    first and second hit; error (V,H,W) per-pixel squared re-rendering error (mean over RGB, 0 off
    the mask); tir, mask (V,H,W) bool; rendered (V,H,W,3) the re-rendering clipped like the photo
    (None where the normals were not rendered, e.g. ground truth handed to feature mapping);
    predicted_gain (V,H,W,2) the network's estimate of how much closer to the truth its N1 and N2
    are than the hull's, degrees (None without a gain head)."""

    cameras: Cameras
    n1: Tensor
    n2: Tensor
    error: Tensor
    tir: Tensor
    mask: Tensor
    rendered: Tensor | None = None
    predicted_gain: Tensor | None = None

    def to(self, device) -> NormalMaps:
        moved = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        moved = {k: (v.to(device) if v is not None else None) for k, v in moved.items()}
        return NormalMaps(**moved)

    def render_error(self) -> float:
        """Mean squared re-rendering error over the masks' pixels and channels."""
        return float(self.error[self.mask].sum()) / max(int(self.mask.sum()), 1)


def render_normals(x: NormalInputs, n1: Tensor, n2: Tensor) -> NormalMaps:
    """Render normals n1, n2 (V,H,W,3) camera frame under the inputs' environment and compare
    with the inputs' photos."""
    with torch.no_grad():
        error, tir, out = prediction_error_maps(x.envmap, n1, n2, x.cameras, x.image, x.mask, x.ior)
    return NormalMaps(x.cameras, n1, n2, error, tir, x.mask, comparable(out.image))


def network_normals(net: NormalNet, x: NormalInputs, latent: LatentOptConfig | None = None,
                    mirror_average: bool = False) -> tuple[Tensor, Tensor, Tensor | None]:
    """(n1, n2) (V,H,W,3) camera frame from NNet, latent-optimized when `latent` has steps, and
    the gain head's predicted gains over the hull's normals (V,H,W,2) degrees (None when the net
    has no head). With `mirror_average`, the mean of the net's answers for the capture and for its
    mirror image (`NormalInputs.mirrored`, mapped back)."""
    if mirror_average:
        n1, n2, gain = network_normals(net, x, latent)
        m1, m2, mgain = network_normals(net, x.mirrored(), latent)
        n1 = torch.nn.functional.normalize(n1 + mirror_vector_maps(m1), dim=-1)
        n2 = torch.nn.functional.normalize(n2 + mirror_vector_maps(m2), dim=-1)
        return n1, n2, None if gain is None else (gain + mgain.flip(2)) / 2
    inputs, cost_volume = network_tensors(x, net.cfg)
    if latent is not None and latent.iterations_n2 + latent.iterations_both > 0:
        n1, n2, _, gain = optimize_latent(net, inputs, cost_volume, x.envmap, x.image, x.mask, x.cameras, latent,
                                           x.ior)
    else:
        with torch.no_grad():
            n1, n2, gain = net(inputs, cost_volume, with_gain=True)
    gain = None if gain is None else gain.detach().permute(0, 2, 3, 1)
    return n1.detach().permute(0, 2, 3, 1), n2.detach().permute(0, 2, 3, 1), gain


def predict_normals(net: NormalNet, x: NormalInputs, latent: LatentOptConfig | None = None,
                    consensus_px: float = 0.0, mirror_average: bool = False) -> NormalMaps:
    """NNet's normals for the inputs (latent-optimized when `latent` has steps), made to agree
    across views where `consensus_px` > 0 and the inputs carry the fed mesh's hits
    (normals/consensus.py), re-rendered."""
    n1, n2, gain = network_normals(net, x, latent, mirror_average)
    if consensus_px > 0 and x.vh_p1 is not None:
        n1, n2 = view_consensus(n1, n2, x.cameras, x.vh_p1, x.vh_p2, x.vh_n1, x.vh_hit & x.mask,
                                x.vh_valid & x.mask, consensus_px)
    return dataclasses.replace(render_normals(x, n1, n2), predicted_gain=gain)
