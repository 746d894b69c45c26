"""Mitsuba 3 (scalar_rgb) as the independent reference for the tests.

Scenes are built from this project's Cameras and arrays, but rays, envmap sampling and light
transport are Mitsuba's own. Keep images small: scalar_rgb renders on one core.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
mi.set_variant("scalar_rgb")


def sensor_dict(cameras, view: int, spp: int, rfilter: str = "box") -> dict:
    """Mitsuba `perspective` sensor equal to view `view` of `cameras` (fov_axis x, look_at)."""
    origin = cameras.origin[view].double().tolist()
    target = (cameras.origin[view] + cameras.forward[view]).double().tolist()
    up = cameras.up[view].double().tolist()
    return {
        "type": "perspective",
        "fov_axis": "x",
        "fov": float(cameras.fov_x_deg[view]),
        "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=target, up=up),
        "film": {"type": "hdrfilm", "width": cameras.width, "height": cameras.height,
                 "rfilter": {"type": rfilter}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp},
    }


def write_envmap(env: np.ndarray, folder: Path) -> str:
    path = str(Path(folder) / "env.exr")
    mi.Bitmap(np.ascontiguousarray(env, dtype=np.float32)).write(path)
    return path


def write_mesh(mesh, folder: Path, name: str = "mesh.ply") -> str:
    """PLY with the mesh's own vertex normals, so Mitsuba shades with the same smooth normals."""
    path = str(Path(folder) / name)
    m = mi.Mesh(name, vertex_count=len(mesh.vertices), face_count=len(mesh.faces), has_vertex_normals=True)
    params = mi.traverse(m)
    params["vertex_positions"] = np.asarray(mesh.vertices, dtype=np.float32).ravel().tolist()
    params["faces"] = np.asarray(mesh.faces, dtype=np.uint32).ravel().tolist()
    params["vertex_normals"] = np.asarray(mesh.vertex_normals, dtype=np.float32).ravel().tolist()
    params.update()
    m.write_ply(path)
    return path


def render(scene_dict: dict, cameras, spp: int, seed: int = 0, rfilter: str = "box") -> np.ndarray:
    """Render every view; returns (V, H, W, 3) float32."""
    out = []
    for v in range(cameras.num_views):
        scene = mi.load_dict({**scene_dict, "sensor": sensor_dict(cameras, v, spp, rfilter)})
        img = mi.render(scene, seed=seed + v)
        out.append(np.array(img, dtype=np.float32)[..., :3])
    return np.stack(out)


def render_environment(env: np.ndarray, cameras, spp: int = 64) -> np.ndarray:
    """The bare environment seen by each camera (box-filtered pixels)."""
    with tempfile.TemporaryDirectory() as tmp:
        scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 1},
                 "env": {"type": "envmap", "filename": write_envmap(env, Path(tmp))}}
        return render(scene, cameras, spp)


def render_coverage(mesh, cameras, spp: int = 64) -> np.ndarray:
    """Fraction of each pixel covered by `mesh` (V, H, W): the mesh glows with radiance 1
    against a black background, rendered with a box filter."""
    with tempfile.TemporaryDirectory() as tmp:
        scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 1},
                 "shape": {"type": "ply", "filename": write_mesh(mesh, Path(tmp)),
                           "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}},
                           "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}}}
        return render(scene, cameras, spp)[..., 0]


def render_glass(mesh, env: np.ndarray, cameras, ior: float, ext_ior: float, spp: int,
                 max_depth: int = 16, seed: int = 0) -> np.ndarray:
    """A smooth dielectric mesh under the environment, Mitsuba's `path` integrator."""
    with tempfile.TemporaryDirectory() as tmp:
        scene = {"type": "scene", "integrator": {"type": "path", "max_depth": max_depth, "rr_depth": 1000},
                 "env": {"type": "envmap", "filename": write_envmap(env, Path(tmp))},
                 "shape": {"type": "ply", "filename": write_mesh(mesh, Path(tmp)),
                           "bsdf": {"type": "dielectric", "int_ior": ior, "ext_ior": ext_ior}}}
        return render(scene, cameras, spp, seed=seed)
