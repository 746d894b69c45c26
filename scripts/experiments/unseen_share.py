"""How much of a test split's Chamfer distance lies where no mask sees (docs/results.md, "What the figures do not
show"; session 72): the ground truth's surface farther than 0.05 from the hull's surface (the ground truth scaled
into the unit sphere, as `shape_metrics` scales it), the walls and floors of slots and holes no silhouette shows.

Usage:
    .venv/bin/python scripts/experiments/unseen_share.py DATA                  # the stored hulls only (~1 min)
    .venv/bin/python scripts/experiments/unseen_share.py DATA --stages 0,2,4   # also the PNet surface and the
                                                                              # refined mesh of these scenes
    ... --stages 0,2,4 --point-weights W.safetensors --no-refine              # another PNet's surface only
Per scene (with --stages) one JSON line {"index", "hull": [CD, unseen part], "surface": [...], "refined": [...]}; then
the means. The CD here is `shape_metrics`' (x 1e4, 20 000 samples a mesh) with its own sampling seeds, so it differs
from eval-shapes' by the sampling noise; the split into the two parts is exact within it. Run two processes on
disjoint scene lists to use both cores.
"""
import argparse
import json
import warnings
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.metrics import CD_UNIT, DEFAULT_SAMPLES, normalization_transform, sample_surface

UNSEEN = 0.05  # distance (the ground truth in the unit sphere) from the hull's surface beyond which no silhouette constrains the object


def normalized_samples(mesh, centre, scale, seed: int) -> np.ndarray:
    """`shape_metrics`' samples of `mesh` in the ground truth's unit-sphere frame."""
    moved = mesh.copy()
    moved.vertices = (np.asarray(mesh.vertices) - centre) / scale
    return sample_surface(moved, DEFAULT_SAMPLES, seed=np.random.SeedSequence(seed))[0]


def parts(points: np.ndarray, truth_points: np.ndarray, unseen: np.ndarray) -> list[float]:
    """[CD, the part of it from the unseen ground-truth samples] of a mesh's samples against the ground truth's."""
    to_mesh = cKDTree(points).query(truth_points)[0] ** 2
    to_truth = cKDTree(truth_points).query(points)[0] ** 2
    return [float(0.5 * (to_mesh.mean() + to_truth.mean()) * CD_UNIT),
            float(0.5 * to_mesh[unseen].sum() / len(to_mesh) * CD_UNIT)]


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("data")
    parser.add_argument("--stages", default="", help="scene indices to run through the normal stage, PNet and the "
                                                     "refine stage as eval-shapes does (default: hulls only, all)")
    parser.add_argument("--point-weights", default="", help="PNet weights (default: the shipped ones)")
    parser.add_argument("--no-refine", action="store_true", help="with --stages: the PNet surface only")
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    torch.set_num_threads(1)
    views = json.loads((Path(args.data) / "test" / "config.json").read_text())["views"]
    ds = TransparentSceneDataset(args.data, "test", views=views)
    indices = [int(i) for i in args.stages.split(",")] if args.stages else range(len(ds))
    if args.stages:
        from lookingglass.normals.stage import run_normal_stage
        from lookingglass.pipeline import refine_stage
        from lookingglass.points.stage import SurfaceConfig, surface_from_normals
        from lookingglass.refine import RefineConfig
        from lookingglass.weights import load_normal_net, load_point_net, shipped_weights
        normal_net = load_normal_net(shipped_weights(views)[0])
        point_net = load_point_net(args.point_weights or shipped_weights(views, "points")[0])
    rows = []
    for i in indices:
        truth, hull = ds.meshes(i)[0], ds.hull(i)
        centre, scale = normalization_transform(truth)
        truth_points = normalized_samples(truth, centre, scale, seed=1)
        hull_points = normalized_samples(hull.mesh, centre, scale, seed=3)
        unseen = cKDTree(hull_points).query(truth_points)[0] > UNSEEN
        row = {"index": i, "hull": parts(hull_points, truth_points, unseen)}
        if args.stages:
            capture = ds.capture(i)
            normals = run_normal_stage(capture, hull.mesh, normal_net, None)
            surface, _ = surface_from_normals(hull, normals.maps, SurfaceConfig(), point_net)
            meshes = [("surface", surface)]
            if not args.no_refine:
                meshes.append(("refined", refine_stage(capture, hull, surface, normal_net, RefineConfig()).refined))
            for name, mesh in meshes:
                row[name] = parts(normalized_samples(mesh, centre, scale, seed=3), truth_points, unseen)
            print(json.dumps(row), flush=True)
        rows.append(row)
    for name in [k for k in rows[0] if k != "index"]:
        cd, part = (float(np.mean([r[name][j] for r in rows])) for j in (0, 1))
        print(f"{name:8s} CD {cd:6.2f} = unseen {part:6.2f} + elsewhere {cd - part:6.2f} ({len(rows)} scenes)")
    hull_cd = float(np.mean([r["hull"][0] for r in rows]))
    print(f"0.45 x the hull's CD: {0.45 * hull_cd:.2f}; unseen share of the hull's: "
          f"{np.mean([r['hull'][1] for r in rows]) / hull_cd:.3f}; scenes where it is most of it: "
          f"{sum(r['hull'][1] > 0.5 * r['hull'][0] for r in rows)}")


if __name__ == "__main__":
    main()
