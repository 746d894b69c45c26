"""The `normals` stage: hull two-bounce maps -> NNet (+ cost volume) -> latent optimization.

`run_normal_stage` is what `reconstruct` and `eval-shapes` run on a capture and its hull, and
`second_pass` what their refine stage runs on its own mesh;
`write_normal_views` writes its per-view files (called by the pipeline, which owns the output
folder):
OUT/normals/view_XX.npz (n1, n2 camera frame float32 (H,W,3); mask, tir bool (H,W);
render_error float32 (H,W), the per-pixel squared error of the re-rendering, mean over RGB) and
OUT/normals/view_XX.png (input | hull normals | predicted normals | re-rendered image).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import trimesh

from ..capture.images import write_image
# LatentOptConfig and NormalStageConfig are re-exported here; their home is lookingglass.config
from ..config import LatentOptConfig, NormalStageConfig  # noqa: F401
from ..fileio import write_atomic
from ..viz import normal_map_rgb, tonemap
from ..weights import NormalWeights
from .inputs import NormalInputs
from .predict import NormalMaps, predict_normals, render_normals

# the refine stage's second pass: no latent steps, no consensus, no mirror average (see `second_pass`)
SECOND_PASS = NormalStageConfig(consensus_px=0.0, mirror_average=False)


@dataclass
class NormalStageResult:
    """inputs: what the network saw; maps: its (latent-optimized) normals and their re-rendering;
    hull_maps: the hull's own normals rendered the same way (the baseline); report: figures for
    report.json."""

    inputs: NormalInputs
    maps: NormalMaps
    hull_maps: NormalMaps
    report: dict


def run_normal_stage(capture, mesh: trimesh.Trimesh, weights: NormalWeights, config: NormalStageConfig | None = None,
                     device: str = "cpu") -> NormalStageResult:
    """capture: anything with images (V,H,W,3) linear, masks (V,H,W), envmap (He,2He,3), cameras
    and ior (a loaded `Capture`, or a dataset scene's `capture(i)`); mesh in the same frame, the one
    whose two-bounce normals the network corrects: the visual hull's, or the refine stage's own
    mesh in its second pass. config: the latent optimization, the views' consensus and the mirror
    average (its `weights` and `views` are the caller's to resolve; None: the defaults). The
    networks and the rendering layer run on `device`."""
    config = config or NormalStageConfig()
    net = weights.net.to(device)
    x = NormalInputs.from_capture(capture.images, capture.masks, capture.envmap, capture.cameras, capture.ior,
                                  mesh, net.cfg.width, net.cfg.height, weights.envmap_height, device=device)
    latent = config.latent
    maps = predict_normals(net, x, latent, config.consensus_px, config.mirror_average)
    hull_maps = render_normals(x, x.vh_n1, x.vh_n2)
    report = {"weights": str(weights.path), "network_size": [net.cfg.width, net.cfg.height],
              "render_error_vh": hull_maps.render_error(), "render_error": maps.render_error(),
              "latent_iterations": [latent.iterations_n2, latent.iterations_both],
              "consensus_px": config.consensus_px, "mirror_average": config.mirror_average}
    return NormalStageResult(x, maps, hull_maps, report)


def second_pass(capture, weights: NormalWeights,
                device: str = "cpu") -> Callable[[trimesh.Trimesh], NormalStageResult | None]:
    """The refine stage's normal term's source: the normal stage on a mesh the refine stage hands
    it, without latent optimization (on val480 it changes the refined mesh by under 1%, CD 5.04 vs
    5.05, and costs ~6 s; docs/history.md, session 43) and without the views' consensus (with it the
    refined CAD meshes came out rounder: val480 CD 3.71 -> 3.92, docs/history.md, session 91) or the
    mirror average (from the same surfaces CD 3.71 -> 3.70, Metro 9.54 -> 10.07, ~2.5 s a scene more;
    session 92). None, without running the net, when the net has no gain head (the term cannot tell
    where to trust it)."""
    if not weights.net.cfg.gain_head:
        return lambda mesh: None
    return lambda mesh: run_normal_stage(capture, mesh, weights, SECOND_PASS, device)


def write_normal_views(folder: Path, result: NormalStageResult) -> None:
    """OUT/normals/view_XX.npz and .png for every view (see the module docstring)."""
    maps, x = result.maps.to("cpu"), result.inputs
    image, vh_n1, m = x.image.cpu(), x.vh_n1.cpu(), maps.mask
    folder.mkdir(parents=True, exist_ok=True)
    for v in range(len(m)):
        arrays = dict(n1=maps.n1[v].numpy(), n2=maps.n2[v].numpy(), mask=m[v].numpy(), tir=maps.tir[v].numpy(),
                      render_error=maps.error[v].numpy())
        write_atomic(folder / f"view_{v:02d}.npz", lambda p, a=arrays: np.savez_compressed(p, **a))
        panels = [tonemap(image[v].numpy()), normal_map_rgb(vh_n1[v].numpy(), m[v].numpy()),
                  normal_map_rgb(maps.n1[v].numpy(), m[v].numpy()),
                  # the re-rendering inside the mask, the photo around it (off the mask there are no normals)
                  tonemap(torch.where(m[v, ..., None], maps.rendered[v], image[v]).numpy())]
        gap = np.ones((panels[0].shape[0], 3, 3), np.float32)
        strip = np.concatenate([panels[0], gap, panels[1], gap, panels[2], gap, panels[3]], axis=1)
        write_image(folder / f"view_{v:02d}.png", strip, encoding="linear")
