"""The normal network's inputs, built in one place from a capture or from a dataset sample.

`NormalInputs.from_capture` is what `reconstruct` and both evaluations run: the photos are
normalized, resized to the network's resolution, and the hull's two-bounce normals are traced at
that resolution. `NormalInputs.from_sample` serves training from the maps `generate` stored (the
same normalization, the same hull tracing, done once at generation). Everything downstream —
`network_tensors`, `predict_normals` (normals/predict.py) — takes a `NormalInputs`, whichever way
it was made.

Normalization (DESIGN.md): the HDR images are scaled so their mean over all views is
`target_mean` (0.5; training draws it from U[0.4, 0.6]) and clipped to [0, 1]; the environment
map gets the same factor. Images are resized to the network's resolution (area filter), masks by
area coverage >= 1/2, and the environment map to H_E x 2H_E.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch
import trimesh
from torch import Tensor

from ..capture.images import exposure_factor, resize_images, resize_masks
from ..errors import LookingGlassError
from ..physics.camera import Cameras
from ..physics.environment import EnvironmentMap
from ..physics.optics import IOR_GLASS
from ..render.tracer import trace_two_bounce
from .model import NormalNetConfig, build_cost_volume, network_inputs
from .render_layer import error_map, render_layer


@dataclass
class NormalInputs:
    """Everything NNet and the rendering layer need for V views at the network's resolution.

    image (V,H,W,3) normalized and clipped; mask (V,H,W) bool; envmap scaled by the same factor;
    cameras: the views at H x W, capture (or dataset world) frame; vh_n1, vh_n2 (V,H,W,3)
    camera-frame normals of the hull's first and second hits; vh_valid (V,H,W) the hull's
    two-bounce path exists; factor: the exposure factor applied to the original radiance; ior:
    the object's index of refraction; vh_p1, vh_p2 (V,H,W,3) world-frame first and second hits and
    vh_hit (V,H,W) where the first exists (from a capture; what the views' consensus,
    normals/consensus.py, matches the views by; None from a dataset sample)."""

    image: Tensor
    mask: Tensor
    envmap: EnvironmentMap
    cameras: Cameras
    vh_n1: Tensor
    vh_n2: Tensor
    vh_valid: Tensor
    factor: float
    ior: float = IOR_GLASS
    vh_p1: Tensor | None = None
    vh_p2: Tensor | None = None
    vh_hit: Tensor | None = None

    @classmethod
    def from_capture(cls, images, masks, envmap, cameras: Cameras, ior: float, hull: trimesh.Trimesh,
                     width: int, height: int, envmap_height: int, target_mean: float = 0.5,
                     device: str | torch.device = "cpu") -> NormalInputs:
        """images (V,H0,W0,3) linear radiance; masks (V,H0,W0) bool; envmap (He,2He,3) linear in
        the images' units (numpy or torch); cameras at H0 x W0 and `hull` in the same frame. The
        result lives on `device` (the hull's rays are cast on the CPU either way)."""
        images, masks, envmap = (torch.as_tensor(a).to(device) for a in (images, masks, envmap))
        try:
            factor = exposure_factor(images, target_mean)
        except ValueError as exc:  # all-black photos: the user's input, not a bug
            raise LookingGlassError(str(exc)) from None
        image = resize_images(images.float() * factor, width, height).clamp(0, 1)
        mask = resize_masks(masks.bool(), width, height)
        cams = cameras.with_resolution(width, height).to(device)
        env = EnvironmentMap(envmap.float() * factor).resized(envmap_height)
        tb = trace_two_bounce(hull, cams, ior=ior, device=device)
        return cls(image, mask, env, cams, tb.normal1, tb.normal2, tb.valid, factor, ior, tb.point1, tb.point2,
                   tb.mask)

    @classmethod
    def from_sample(cls, sample: dict, ior: float, device: str | torch.device = "cpu") -> NormalInputs:
        """A dataset item (data/torch_dataset.py keys: normalized image, the hull's stored
        two-bounce maps, the scaled environment map, look-at cameras)."""
        s = {k: (v.to(device) if isinstance(v, Tensor) else v) for k, v in sample.items()}
        mask = s["mask"].bool()
        V, H, W = mask.shape
        cams = Cameras.look_at(s["origin"].cpu(), s["target"].cpu(), s["up"].cpu(), s["fov_x_deg"].cpu(), W, H,
                               device=device)
        channels_last = {k: s[k].permute(0, 2, 3, 1).float() for k in ("image", "vh_n1", "vh_n2")}
        return cls(channels_last["image"], mask, EnvironmentMap(s["envmap"].permute(1, 2, 0).float()), cams,
                   channels_last["vh_n1"], channels_last["vh_n2"], s["vh_valid"].bool(), float(s["factor"]), ior)

    def mirrored(self) -> NormalInputs:
        """The same capture in the world mirrored in the plane x = 0, every image flipped left to
        right (`Cameras.mirrored`): what the views would see of the mirror-image object under the
        mirror-image light. Exact, no tracing: the hull's hits and normals are mirrored as they are."""
        mirror = lambda t: None if t is None else t.flip(2)  # noqa: E731  (V, H, W, ...): W reversed
        vector = lambda t: None if t is None else mirror_vector_maps(t)  # noqa: E731
        return NormalInputs(mirror(self.image), mirror(self.mask), self.envmap.mirrored(), self.cameras.mirrored(),
                            vector(self.vh_n1), vector(self.vh_n2), mirror(self.vh_valid), self.factor, self.ior,
                            vector(self.vh_p1), vector(self.vh_p2), mirror(self.vh_hit))

    @property
    def num_views(self) -> int:
        return int(self.mask.shape[0])

    @cached_property
    def hull_error(self) -> tuple[Tensor, Tensor]:
        """Ĩer (V,H,W,3) and M̃tr (V,H,W) (paper Eq. 4-5): the hull's normals rendered by the
        layer, compared with the photo."""
        out = render_layer(self.envmap, self.vh_n1, self.vh_n2, self.cameras, ior=self.ior)
        return error_map(self.image, out.image, self.mask), out.tir & self.mask


def mirror_vector_maps(maps: Tensor) -> Tensor:
    """(V, H, W, 3) camera-frame vectors or world points per pixel, in the mirrored world of
    `NormalInputs.mirrored` (and back: it is its own inverse): columns reversed, x negated."""
    return maps.flip(2) * maps.new_tensor([-1.0, 1.0, 1.0])


def network_tensors(x: NormalInputs, cfg: NormalNetConfig) -> tuple[Tensor, Tensor | None]:
    """NNet's input channels (V, C, H, W) and cost volume (V, K², 8, H, W) or None, per the
    config's switches (the paper's ablations)."""
    vh_error, vh_tir = x.hull_error if cfg.use_error_map else (None, None)
    inputs = network_inputs(x.image, x.mask, x.vh_n1, x.vh_n2, vh_error, vh_tir)
    cost_volume = build_cost_volume(x.envmap, x.image, x.mask, x.vh_n1, x.vh_n2, x.cameras, cfg.theta_deg,
                                    cfg.cost_volume_k, x.ior) if cfg.use_cost_volume else None
    return inputs, cost_volume
