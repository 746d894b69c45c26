"""A validation set of shapes unlike the procedural training shapes, rendered like users' captures.

The training shapes are smooth unions of random primitives carved at 128x96. Users bring scanned
figurines and manufactured parts photographed at full resolution, where the visual hull is
already good. This set stands in for them: each shape is built here (no download), by name, from
one of four families, and rendered at 480x360 from the paper's 10-view rig under the natural maps
kept out of training, with 16 samples per pixel.

Families:
  cad     flat faces and sharp edges (CSG of boxes, prisms and cylinders)
  handle  a body with a thin handle (genus 1, a slit the hull cannot see into)
  thin    thin plates and rods beside a body
  blob    smooth figurine-like solids (few concavities: the hull is nearly right)

The shapes are built with the helpers of families.py (CSG, smooth blobs, `finish`: edges at most
`EDGE`), which also draws random members of the same families for training data; the ten here are
fixed, named shapes that no training seed makes.

Layout of OUT (resumable: a finished scene is skipped):
  OUT/index.json                 {"shapes": {name: family}, "views", "size", "samples_per_axis"}
  OUT/<name>/scene/              a scene folder (scene.json, images/*.exr, masks/*.png, envmap.hdr)
  OUT/<name>/ground_truth.ply    the shape, world frame (unit sphere)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from ..errors import LookingGlassError
from ..physics.constants import IOR_GLASS
from ..fileio import write_atomic, write_json
from ..progress import Reporter
from .families import EDGE, blob, boolean, cylinder, finish, moved

__all__ = ["EDGE", "SHAPES", "generate_validation_set", "validation_shape"]


def bracket() -> trimesh.Trimesh:
    """An L-bracket with a bolt hole through its foot: flat faces, a concave corner, genus 1."""
    foot = trimesh.creation.box((1.6, 0.3, 1.0))
    wall = moved(trimesh.creation.box((0.3, 1.2, 1.0)), (-0.65, 0.45, 0))
    return boolean("difference", [boolean("union", [foot, wall]), cylinder(0.18, 1.0, (0, 1, 0), offset=(0.35, 0, 0))])


def nut() -> trimesh.Trimesh:
    """A hexagonal nut: six flat sides, sharp rims, a round hole (genus 1)."""
    prism = trimesh.creation.cylinder(1.0, 0.7, sections=6)
    return boolean("difference", [prism, cylinder(0.42, 1.0)])


def chamfered_cube() -> trimesh.Trimesh:
    """A cube with its twelve edges chamfered (the cube cut by three boxes turned 45 degrees)."""
    parts = [trimesh.creation.box((1.0, 1.0, 1.0))]
    for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
        parts.append(moved(trimesh.creation.box((1.25, 1.25, 1.25)), axis=axis, angle=np.pi / 4))
    return boolean("intersection", parts)


def stepped_shaft() -> trimesh.Trimesh:
    """A turned part: a wide disc on a narrower shaft, a concave step between them."""
    return boolean("union", [cylinder(0.8, 0.4, offset=(0, 0, -0.3)), cylinder(0.4, 1.4, offset=(0, 0, 0.2))])


def mug() -> trimesh.Trimesh:
    """A solid cylinder with a thin ring handle on its side (genus 1)."""
    body = cylinder(0.55, 1.3, (0, 1, 0))
    handle = moved(trimesh.creation.torus(0.38, 0.09, major_sections=96, minor_sections=24), (0.6, 0, 0),
                    axis=(1, 0, 0), angle=np.pi / 2)
    return boolean("union", [body, handle])


def key() -> trimesh.Trimesh:
    """A key: a ring bow and a long thin blade with teeth."""
    bow = moved(trimesh.creation.torus(0.35, 0.1, major_sections=96, minor_sections=24), (-0.75, 0, 0))
    blade = moved(trimesh.creation.box((1.3, 0.16, 0.12)), (0.2, 0, 0))
    teeth = [moved(trimesh.creation.box((0.1, 0.18, 0.12)), (0.3 + 0.2 * k, -0.14, 0)) for k in range(3)]
    return boolean("union", [bow, blade, *teeth])


def finned_body() -> trimesh.Trimesh:
    """A capsule with two thin fins (plates 0.06 thick) standing off it."""
    body = trimesh.creation.capsule(1.0, 0.35, count=[48, 48])
    fins = [moved(trimesh.creation.box((0.06, 0.9, 0.9)), (0, 0.4 * s, 0), axis=(0, 0, 1), angle=s * 0.5)
            for s in (-1, 1)]
    return boolean("union", [body, *fins])


def seated_figure() -> trimesh.Trimesh:
    """A sitting animal: body, head, two ears, a tail."""
    return blob([((0, -0.2, 0), (0.55, 0.5, 0.45)), ((0, 0.45, 0.1), (0.33, 0.3, 0.3)),
                  ((-0.18, 0.75, 0.05), (0.09, 0.16, 0.07)), ((0.18, 0.75, 0.05), (0.09, 0.16, 0.07)),
                  ((0, -0.55, -0.45), (0.12, 0.1, 0.3))])


def pebble() -> trimesh.Trimesh:
    """A flattened, slightly lopsided pebble: convex, the hull's easiest case."""
    return blob([((0, 0, 0), (0.9, 0.45, 0.65)), ((0.3, 0.05, 0.1), (0.5, 0.4, 0.45))], blend=0.3)


def duck() -> trimesh.Trimesh:
    """A bath duck: a body, a head on a neck, a flat beak."""
    return blob([((0, -0.25, 0), (0.7, 0.4, 0.5)), ((0.3, 0.35, 0), (0.3, 0.3, 0.28)),
                  ((0.62, 0.3, 0), (0.2, 0.06, 0.12)), ((-0.6, -0.05, 0), (0.2, 0.18, 0.2))])


SHAPES: dict[str, tuple[str, Callable[[], trimesh.Trimesh]]] = {
    "bracket": ("cad", bracket), "nut": ("cad", nut), "chamfered_cube": ("cad", chamfered_cube),
    "stepped_shaft": ("cad", stepped_shaft), "mug": ("handle", mug), "key": ("handle", key),
    "finned_body": ("thin", finned_body), "seated_figure": ("blob", seated_figure), "pebble": ("blob", pebble),
    "duck": ("blob", duck),
}


def validation_shape(name: str, seed: int = 0) -> trimesh.Trimesh:
    """Shape `name` in the unit sphere (max |p| = 1), turned by a seeded random rotation (so no
    face lines up with the rig), watertight, outward, edges at most EDGE long."""
    if name not in SHAPES:
        raise LookingGlassError(f"unknown validation shape {name!r} (choose from {', '.join(SHAPES)})")
    draw = np.random.default_rng([seed, list(SHAPES).index(name)]).random(3)  # each shape its own rotation
    return finish(SHAPES[name][1](), draw, f"validation shape {name}")


def generate_validation_set(out, names: list[str] | None = None, views: int = 10, size=(480, 360),
                            samples_per_axis: int = 4, seed: int = 0, envmap_folder=None,
                            reporter: Reporter | None = None, ior_range: tuple[float, float] | None = None) -> Path:
    """Render the validation shapes (all, or `names`) into OUT (see the module docstring);
    finished scenes are kept. Returns OUT/index.json. ior_range: each shape's glass gets its own
    IoR drawn uniformly from (LO, HI) (seeded per shape; a set to judge an IoR estimate on), else
    IOR_GLASS."""
    from ..capture.images import read_envmap
    from ..render.tracer import RenderConfig
    from .dataset import DatasetConfig
    from .envmaps import default_envmap_folder
    from .rigs import paper_rig
    from .synthetic import render_capture

    out, reporter = Path(out), reporter or Reporter(quiet=True)
    names = list(SHAPES) if names is None else names
    folder = Path(envmap_folder) if envmap_folder is not None else default_envmap_folder()
    test_envmaps = DatasetConfig().test_envmaps  # the natural maps no training scene was lit by
    for name in reporter.track(names, description="validation scenes"):
        if name not in SHAPES:
            raise LookingGlassError(f"unknown validation shape {name!r} (choose from {', '.join(SHAPES)})")
        k = list(SHAPES).index(name)  # a shape's rig and map do not depend on which others are made
        scene_dir = out / name
        if (scene_dir / "ground_truth.ply").exists() and (scene_dir / "scene" / "scene.json").exists():
            continue
        mesh = validation_shape(name, seed)
        env = read_envmap(folder / test_envmaps[k % len(test_envmaps)])
        cameras = paper_rig(views, seed + k, width=size[0], height=size[1])
        ior = IOR_GLASS if ior_range is None else float(np.random.default_rng([seed, k, 1]).uniform(*ior_range))
        render_capture(mesh, env, cameras, scene_dir / "scene", RenderConfig(ior=ior, samples_per_axis=samples_per_axis,
                                                                            seed=seed + k), overwrite=True)
        write_atomic(scene_dir / "ground_truth.ply", lambda p, m=mesh: m.export(p, file_type="ply"))
    settings = {"views": views, "size": list(size), "samples_per_axis": samples_per_axis, "seed": seed}
    if ior_range is not None:  # absent otherwise, so sets made before the option stay valid
        settings["ior_range"] = [float(v) for v in ior_range]
    index_path = out / "index.json"
    earlier = json.loads(index_path.read_text()) if index_path.exists() else {}
    if earlier and {k: earlier.get(k) for k in [*settings, "ior_range"]} != {"ior_range": None, **settings}:
        raise LookingGlassError("the folder holds validation scenes made with other settings; pick another --out",
                                index_path)
    shapes = {**earlier.get("shapes", {}), **{n: SHAPES[n][0] for n in names}}
    return write_json(index_path, {"shapes": shapes, **settings})
