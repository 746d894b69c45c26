"""Synthetic captures: render a glass mesh into a scene folder (DESIGN.md format).

Backs `lookingglass render` and `lookingglass demo`, and gives tests a capture with known ground
truth. Images are written as linear EXR so no radiance is clipped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh

from ..capture.scene import SceneSpec, ViewSpec, save_scene
from ..physics.camera import Cameras
from ..physics.environment import EnvironmentMap
from ..render.tracer import RenderConfig, render_views


def render_capture(mesh: trimesh.Trimesh, envmap: np.ndarray, cameras: Cameras, out: str | Path,
                   config: RenderConfig | None = None, overwrite: bool = False) -> Path:
    """Render `mesh` (world frame) under `envmap` ((He, 2He, 3) linear) from `cameras` and write
    the scene folder `out` (images/NN.exr, masks/NN.png, envmap.hdr, scene.json). Returns out."""
    config = config or RenderConfig()
    result = render_views(mesh, EnvironmentMap(torch.as_tensor(envmap, dtype=torch.float32)), cameras, config)
    params = cameras.to(dtype=torch.float64).look_at_params()
    views = [ViewSpec(image=f"images/{i:02d}.exr", mask=f"masks/{i:02d}.png", origin=tuple(params["origin"][i]),
                      target=tuple(params["target"][i]), up=tuple(params["up"][i]),
                      fov_x_deg=float(params["fov_x_deg"][i]))
             for i in range(cameras.num_views)]
    spec = SceneSpec(ior=config.ior, envmap="envmap.hdr", envmap_scale=1.0, image_encoding="linear", views=views)
    save_scene(out, spec, images=result.image.cpu().numpy(), masks=result.mask.cpu().numpy(),
               envmap=np.asarray(envmap, dtype=np.float32), overwrite=overwrite)
    return Path(out)
