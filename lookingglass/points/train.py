"""Training of the point network (PNet, paper Sec. 3.2): feature preparation and the loss of one
step. The loop (Adam, the step schedule, checkpoints and exact resume, metrics.jsonl, progress,
DDP under torchrun) is lookingglass.training's, shared with the normal net.

Two phases, both resumable:

1. Feature preparation, once per training scene, cached as RUN_DIR/features/<scene>.npz
   (written atomically; a scene whose file exists is skipped, so an interrupted run picks up
   where it stopped). Per scene: `reconstruct`'s normal stage with its defaults (`run_normal_stage`
   with `TRAINING_FEATURES`: the mirror average and the views' consensus, *no latent optimization*,
   the scene as a capture with its stored hull, as the evaluations run it) gives N1, N2 for every
   view, their per-pixel rendering error and TIR mask; `cfg.net.num_points` points are sampled on
   the visual hull and `map_features` maps the predictions onto them with the config's strategy;
   then the ground-truth targets the loss needs. Under torchrun each process prepares every
   world-th scene. RUN_DIR/features/source.json records the normal weights' SHA-256 and the normal
   stage's settings: a cache made with others is refused, not mixed.
2. Training: one scene per step, PNet(features) -> offset, normal; p = p̃ + offset; the loss
   LOSSES[config.loss] with the paper's λ1 = 200, λ2 = 5.

Frame. Everything is in the scene's *hull-normalized frame*, p_n = (p - c) / s with the hull's
centre c and scale s (max |p_n| = 1 over the hull; the "hull" entry of the scene's meta.json,
the numbers `carve_visual_hull` returned), because that is the frame the pipeline maps features
in at inference (points/stage.py). Ground truth and cameras are moved into it too.

Cached arrays (float32 unless noted; N = cfg.net.num_points, world = hull-normalized frame):
  features         (N, NUM_FEATURES)  features.FEATURE_COLUMNS: p̃, hull normal, mapped N1, error, TIR,
                   cos, silhouette-cone counts (the net reads its first in_features)
  gt_points, gt_normals        (N, 3)  chamfer: even samples of the GT surface, face normals
  nearest_points, nearest_normals (N, 3)  nearest, view: the exact closest GT surface point to
                                       each p̃ and the smooth normal there
  view_points, view_normals    (N, 3)  view: the GT first hit on the ray from the chosen view's
                                       camera through p̃ (`losses.view_targets`)
  view_valid       (N,) bool   view: a view was chosen and its ray hit the GT

RUN_DIR also holds config.json, checkpoint.pt, metrics.jsonl (epoch, step, lr, loss,
loss_point, loss_normal, loss_input, seconds, processes; loss_input is the loss of the untouched
input, hull points with the mapped normals: what the net must beat) and, at the end,
weights.safetensors + weights.json (the PointNetConfig, the loss and the strategy).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from torch import Tensor

from .. import training
from ..errors import LookingGlassError
from ..fileio import sha256_file, write_atomic
from ..hull import VisualHull
from ..config import NormalStageConfig
from ..normals.stage import run_normal_stage
from ..parallel import run_and_collect
from ..progress import Reporter
from ..threads import torch_threads
from ..weights import NormalWeights, load_normal_net
from .config import PointTrainConfig
from .features import FEATURE_COLUMNS, NUM_FEATURES, map_features, sample_hull_points
from .losses import LOSSES, PointLoss, unseen_weights, view_targets
from .model import PointNet

__all__ = [
    "PointTrainConfig",
    "TARGET_KEYS",
    "scene_point_data",
    "prepare_features",
    "feature_path",
    "load_scene_arrays",
    "point_loss",
    "train_points",
]

# The cached target arrays each loss reads (beside "features").
TARGET_KEYS: dict[str, tuple[str, ...]] = {
    "chamfer": ("gt_points", "gt_normals"),
    "nearest": ("nearest_points", "nearest_normals"),
    "view": ("nearest_points", "nearest_normals", "view_points", "view_normals", "view_valid"),
}
FEATURE_DIR = "features"
# The normal stage that makes the features: `reconstruct`'s default, so PNet learns from what it is
# fed (the shipped point nets, trained before session 92, learned from each view's own prediction).
TRAINING_FEATURES = NormalStageConfig()


# ---- one scene -> cached arrays ---------------------------------------------------------------------
def _closest_points(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The closest surface point of `mesh` to each of `points` (N, 3) and the smooth
    (vertex-interpolated, as RayCaster's hits) unit normal there: (N, 3), (N, 3) float32."""
    closest, _, face = trimesh.proximity.closest_point(mesh, points)
    tri = np.asarray(mesh.faces)[face]  # (N, 3) vertex ids
    bary = trimesh.triangles.points_to_barycentric(np.asarray(mesh.vertices)[tri], closest)
    normal = np.einsum("nk,nkj->nj", bary, np.asarray(mesh.vertex_normals)[tri])
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    return closest.astype(np.float32), normal.astype(np.float32)


def scene_point_data(normal_weights: NormalWeights, capture, gt_mesh: trimesh.Trimesh, hull: VisualHull,
                     config: PointTrainConfig, seed: int, device: str = "cpu") -> dict[str, np.ndarray]:
    """PNet's input features and the loss's targets for one training scene.

    normal_weights: the trained normal net (eval mode), run as `reconstruct`'s normal stage
    (`TRAINING_FEATURES`). capture: the scene as a capture (`dataset.capture(i, config.ior)`);
    gt_mesh: the ground truth, dataset world frame; hull: the scene's visual hull with its
    normalization (`dataset.hull(i)`). seed: point sampling.
    Returns float32 numpy arrays (bool for view_valid) in the hull-normalized frame: "features"
    (N, NUM_FEATURES) and TARGET_KEYS[config.loss] (see the module docstring).
    """
    maps = run_normal_stage(capture, hull.mesh, normal_weights, TRAINING_FEATURES, device).maps.to("cpu")
    unit_hull = hull.mesh_normalized()
    gt = trimesh.Trimesh(hull.normalize_points(gt_mesh.vertices), np.asarray(gt_mesh.faces), process=False,
                         validate=False)
    cams = hull.cameras_normalized(maps.cameras)
    points, hull_normals = sample_hull_points(unit_hull, config.net.num_points, seed)
    mapped = map_features(points, hull_normals, unit_hull, cams, maps.n1, maps.error, maps.tir, maps.mask,
                          config.strategy)
    out = {"features": mapped["features"].numpy().astype(np.float32)}
    if config.loss == "chamfer":
        out["gt_points"], out["gt_normals"] = sample_hull_points(gt, config.net.num_points, seed + 1)
    else:
        out["nearest_points"], out["nearest_normals"] = _closest_points(gt, points)
    if config.loss == "view":
        vp, vn, valid = view_targets(points, mapped["chosen_view"], cams.origin, gt)
        out["view_points"], out["view_normals"], out["view_valid"] = vp.numpy(), vn.numpy(), valid.numpy()
    return out


# ---- the cache ----------------------------------------------------------------------------------------
def _scene_name(dataset, index: int) -> str:
    """The scene's folder name when the dataset has folders (stable when more scenes finish
    later), else its index."""
    dirs = getattr(dataset, "scene_dirs", None)
    return Path(dirs[index]).name if dirs is not None else f"scene_{index:05d}"


def feature_path(run_dir: str | os.PathLike, dataset, index: int) -> Path:
    """RUN_DIR/features/<scene>.npz of dataset item `index`."""
    return Path(run_dir) / FEATURE_DIR / f"{_scene_name(dataset, index)}.npz"


def load_scene_arrays(path: Path, loss: str) -> dict[str, np.ndarray]:
    """The cached "features" and TARGET_KEYS[loss] arrays of one scene (no pickles)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in ("features", *TARGET_KEYS[loss])}
    except (OSError, ValueError, KeyError) as exc:
        raise LookingGlassError(f"cannot read cached point features ({exc}); delete the file to remake it",
                                path) from None


def _check_source(run_dir: Path, normals: Path, views: int, rank: int) -> str:
    """Record (or compare) the normal weights and normal stage the cache is made from; returns the
    weights' SHA-256."""
    digest = sha256_file(normals)
    source = {"normals_sha256": digest, "views": views, "feature_columns": NUM_FEATURES,
              "consensus_px": TRAINING_FEATURES.consensus_px, "mirror_average": TRAINING_FEATURES.mirror_average}
    training.record_or_compare(run_dir / FEATURE_DIR / "source.json", source, rank,
                               "the cached point features were made with other normal weights, views, "
                               "feature columns or normal stage",
                               "use a new --out or the same --normals (a cache from before the silhouette "
                               "columns or session 92's normal stage must be remade: delete RUN_DIR/features)")
    return digest


def prepare_features(dataset, run_dir: str | os.PathLike, config: PointTrainConfig, normal_weights: NormalWeights,
                     device: str = "cpu", reporter: Reporter | None = None, rank: int = 0,
                     world: int = 1) -> dict:
    """Make the missing RUN_DIR/features/<scene>.npz of the first `config.max_scenes` items
    (all for 0); process `rank` of `world` makes the items i with i % world == rank.
    dataset: scenes with `capture(i, ior)`, `meshes(i)` -> (gt, hull), `hull(i)`, views and
    resolution matching `normal_weights.net.cfg`.
    Returns {"made": [indices], "skipped": count, "seconds": float} for this process."""
    reporter = reporter or Reporter(quiet=True)
    n = len(dataset) if not config.max_scenes else min(config.max_scenes, len(dataset))
    mine = [i for i in range(n) if i % world == rank]
    todo = [i for i in mine if not feature_path(run_dir, dataset, i).exists()]
    start = time.perf_counter()
    cfg = normal_weights.net.cfg

    def make(i: int) -> None:
        capture = dataset.capture(i, config.ior)
        V, H, W = capture.masks.shape
        if (V, H, W) != (cfg.num_views, cfg.height, cfg.width):
            raise LookingGlassError(f"scene {_scene_name(dataset, i)} has {V} views of {W}x{H}, the normal net takes "
                                    f"{cfg.num_views} of {cfg.width}x{cfg.height}")
        arrays = scene_point_data(normal_weights, capture, dataset.meshes(i)[0], dataset.hull(i), config,
                                  seed=config.seed * 1_000_003 + i, device=device)
        write_atomic(feature_path(run_dir, dataset, i), lambda tmp: np.savez(tmp, **arrays))

    for i in reporter.track(todo, description="point features"):
        run_and_collect(make, i)
    return {"made": todo, "skipped": len(mine) - len(todo), "seconds": round(time.perf_counter() - start, 2)}


# ---- the loss of one step ---------------------------------------------------------------------------
def point_loss(name: str, points: Tensor, normals: Tensor, targets: dict[str, Tensor],
               gt_weights: Tensor | None = None) -> PointLoss:
    """LOSSES[name] on predictions points, normals (B, N, 3) and the cached targets (B, ., 3).
    gt_weights: the Chamfer loss's per-sample weights (`losses.unseen_weights`), None for none.

    For "nearest" (and "view"'s fallback) the targets are the exact closest GT points to the
    hull points, precomputed; they are passed as both the GT set and the query of the loss's
    nearest search, which then returns each row's own target (Eq. 2 with exact targets, instead
    of the nearest of a finite GT sample set).
    """
    loss = LOSSES[name]
    if name == "chamfer":
        return loss(points, normals, targets["gt_points"], targets["gt_normals"], gt_weights=gt_weights)
    near_p, near_n = targets["nearest_points"], targets["nearest_normals"]
    if name == "nearest":
        return loss(points, normals, near_p, near_n, hull_points=near_p)
    return loss(points, normals, near_p, near_n, hull_points=near_p, view_points=targets["view_points"],
                view_normals=targets["view_normals"], view_valid=targets["view_valid"])


# ---- training ---------------------------------------------------------------------------------------
def train_points(dataset, run_dir: str | os.PathLike, config: PointTrainConfig, normals: str | os.PathLike,
                 device: str = "cpu", reporter: Reporter | None = None, max_steps: int | None = None,
                 threads: int = 1) -> dict:
    """Prepare (or reuse) the feature cache, then train PNet; resumes from RUN_DIR/checkpoint.pt.

    dataset: training scenes (TransparentSceneDataset, not augmented: the features are made
    once, at the exposure inference uses), with the views and resolution of the normal net.
    normals: the normal net's weights.safetensors. threads: torch intra-op threads on the CPU
    (1 by default: PNet is many small ops, and on a busy 2-core machine 2 threads measured ~10x
    slower than 1; 0: half the cores; < 0: leave torch's setting). Returns the last epoch's
    metrics (see the module docstring).
    """
    normals = Path(normals)
    run_dir = Path(run_dir)
    session = training.TrainingSession(run_dir, config, device, reporter)  # refuses another config first
    device = session.device  # under torchrun on GPUs: this process's own
    with torch_threads(threads if not device.startswith("cuda") else -1):
        normal_weights = load_normal_net(normals)
        normal_weights.net.to(device)
        digest = _check_source(run_dir, normals, normal_weights.net.cfg.num_views, session.rank)
        summary = prepare_features(dataset, run_dir, config, normal_weights, device, session.reporter, session.rank,
                                   session.world)
        if summary["made"]:
            session.reporter.info(f"point features: made {len(summary['made'])}, reused {summary['skipped']} "
                                  f"({summary['seconds']:.1f} s)")
        del normal_weights
        session.barrier()
        keys = ("features", *TARGET_KEYS[config.loss])
        xyz, mapped_normal = FEATURE_COLUMNS["point"], FEATURE_COLUMNS["normal"]

        def step(model: torch.nn.Module, index: int, global_step: int) -> tuple[Tensor, dict[str, float]]:
            arrays = load_scene_arrays(feature_path(run_dir, dataset, index), config.loss)
            batch = {k: torch.from_numpy(arrays[k]).unsqueeze(0).to(device) for k in keys}
            features = batch["features"]  # (1, N, NUM_FEATURES)
            offset, normal = model(features)
            weights = None
            if config.unseen_weight > 0:
                weights = unseen_weights(batch["gt_points"], features[..., xyz], config.unseen_weight,
                                         config.unseen_distance)
            loss = point_loss(config.loss, features[..., xyz] + offset, normal, batch, weights)
            with torch.no_grad():  # the input itself: hull points with the mapped normals
                base = point_loss(config.loss, features[..., xyz], F.normalize(features[..., mapped_normal], dim=-1),
                                  batch, weights)
            return loss.total, {"loss_point": float(loss.point.detach()), "loss_normal": float(loss.normal.detach()),
                                "loss_input": float(base.total)}

        def weights_extra(steps: int) -> dict:
            extra = {"kind": "points", "steps": steps, "loss": config.loss, "strategy": config.strategy,
                     "normals_sha256": digest}
            if config.unseen_weight > 0:
                extra.update(unseen_weight=config.unseen_weight, unseen_distance=config.unseen_distance)
            return extra

        return session.fit(lambda: PointNet(config.net), len(dataset), step, weights_extra=weights_extra,
                           labels={"loss_point": "points", "loss_normal": "normals", "loss_input": "input"},
                           max_steps=max_steps)
