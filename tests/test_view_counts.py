"""Captures of any view count from 3 to 30 reconstruct with the shipped weights of the nearest
trained count, and report.json says which (issue 22)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import trimesh

from lookingglass.config import PipelineConfig
from lookingglass.data.rigs import paper_rig
from lookingglass.data.synthetic import render_capture
from lookingglass.hull import HullConfig
from lookingglass.normals.latent import LatentOptConfig
from lookingglass.normals.stage import NormalStageConfig
from lookingglass.pipeline import reconstruct
from lookingglass.render.tracer import RenderConfig
from lookingglass.weights import shipped_weights

from cli_helpers import normal_errors, procedural_envmap

pytestmark = pytest.mark.skipif(shipped_weights(10)[0] is None, reason="no normal-network weights ship in this build")


@pytest.fixture(scope="module")
def views_30(tmp_path_factory):
    """A 30-view 120x90 capture of a squashed, tilted ellipsoid: the paper's 20-view rig and its
    10-view rig with another jitter, rendered into ROOT/rig20 and ROOT/rig10 (ROOT/gt.ply the
    truth); returns ROOT."""
    root = tmp_path_factory.mktemp("views")
    gt = trimesh.creation.icosphere(subdivisions=4)
    gt.apply_scale([0.9, 0.6, 0.75])
    gt.apply_transform(trimesh.transformations.rotation_matrix(0.5, [1, 0.2, 0]))
    gt.export(root / "gt.ply")
    env = procedural_envmap(np.random.default_rng(1), 64)
    for n, seed in ((20, 0), (10, 1)):
        render_capture(gt, env, paper_rig(n, seed, width=120, height=90), root / f"rig{n}", RenderConfig(seed=seed))
    return root


def _subset(root, views: list[int], name: str):
    """ROOT/NAME: a scene folder of the views (indices into rig20's views, then rig10's) copied."""
    folders = [root / "rig20", root / "rig10"]
    specs = [(folder, view) for folder in folders for view in json.loads((folder / "scene.json").read_text())["views"]]
    scene = json.loads((folders[0] / "scene.json").read_text())
    out = root / name
    (out / "images").mkdir(parents=True)
    (out / "masks").mkdir()
    shutil.copy(folders[0] / scene["envmap"], out / scene["envmap"])
    scene["views"] = []
    for k, i in enumerate(views):
        folder, view = specs[i]
        image, mask = f"images/{k:02d}.exr", f"masks/{k:02d}.png"
        shutil.copy(folder / view["image"], out / image)
        shutil.copy(folder / view["mask"], out / mask)
        scene["views"].append({**view, "image": image, "mask": mask})
    (out / "scene.json").write_text(json.dumps(scene))
    return out


@pytest.mark.parametrize("count", [4, 7, 13, 25])
def test_any_view_count_reconstructs_with_the_nearest_weights(views_30, tmp_path, count):
    """4 and 7 views take the 5-view weights, 13 the 10-view ones and 25 the 20-view ones (the nearest
    that ship); the note says so; the network's normals beat the hull's (N1 median
    angle against the ground truth's first-hit normals). (The stages after the normals take any count:
    tests/test_cli.py runs them at 5 and 10.)"""
    root = views_30
    # spread the views over both rigs so that every subset sees the object from all around
    chosen = sorted(set(np.linspace(0, 29, count).round().astype(int)))
    assert len(chosen) == count
    scene = _subset(root, chosen, f"v{count}")
    # the network's own normals: the latent optimization's steps cost ~0.1 s per view each
    config = PipelineConfig(stop_after="normals", device="cpu", hull=HullConfig(resolution=64),
                            normals=NormalStageConfig(latent=LatentOptConfig(iterations_n2=0, iterations_both=0)))
    report = reconstruct(scene, tmp_path / "out", config)
    stage = next(s for s in report["stages"] if s["name"] == "normals")
    expected = shipped_weights(count)[1]
    assert stage["trained_views"] == expected and report["num_views"] == count
    assert stage["note"] == f"{count} views: using the weights trained for {expected}"

    _, err = normal_errors(scene, root / "gt.ply", tmp_path / "out", count)
    assert err["pred"][0] < err["hull"][0], err
