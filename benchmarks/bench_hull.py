"""Visual hull speed and quality: `python benchmarks/bench_hull.py [--repeats 5] [--shapes 5]`.

Speed: a synthetic capture of the paper's size (a procedural shape, `lookingglass.data.shapes`,
seen by the 10-view rig of DESIGN.md, 480x360 masks from Embree) carved at 128^3 with the default
`HullConfig`; median seconds per sub-step over `--repeats` runs after one warm-up, against the
target of 2 s for the whole `carve_visual_hull` on the 2-core reference machine. Run with 1 and 2
torch threads (the default picks half the cores, 1 here).

Quality: on `--shapes` procedural shapes and a sphere (10-view rig), DESIGN.md's shape metrics
(`lookingglass.metrics.shape_metrics`, 20 000 samples, GT unit-sphere scale) for binary carving
(the paper's release) and for the continuous distance field, without and with LS3 Loop
subdivision at several iteration counts; plus the worst ground-truth surface point outside the
hull, in voxels. And the normal error of the hull of a sphere seen from 60 views, where the hull
is nearly the sphere, so the error is the surface's own (discretization), not the hull's shape.

Writes docs/benchmarks_hull.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import numpy as np  # noqa: E402
import torch  # noqa: E402
import trimesh  # noqa: E402

from lookingglass.data.rigs import PAPER_FOV_X_DEG, PAPER_IMAGE_SIZE, paper_rig  # noqa: E402
from lookingglass.data.shapes import random_shape  # noqa: E402
from lookingglass.hull import HullConfig, carve_visual_hull  # noqa: E402
from lookingglass.metrics import shape_metrics  # noqa: E402
from lookingglass.render.raycast import object_masks  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 2.0
STEPS = ["masks", "box", "carve", "coverage", "marching_cubes", "components", "recarve", "subdivision", "finish"]


def timing(masks, cams, repeats: int, threads: int) -> dict:
    cfg = HullConfig(num_threads=threads)
    carve_visual_hull(masks, cams, cfg)  # warm-up (imports, allocator)
    runs = [carve_visual_hull(masks, cams, cfg) for _ in range(repeats)]
    med = {k: float(np.median([r.timings.get(k, 0.0) for r in runs])) for k in STEPS + ["total"]}  # recarve: rare
    tot = [r.timings["total"] for r in runs]
    return dict(median=med, min=min(tot), max=max(tot), hull=runs[-1])


def outside_voxels(hull, gt: trimesh.Trimesh) -> float:
    pts = trimesh.sample.sample_surface_even(gt, 4000, seed=0)[0]
    out = ~hull.mesh.contains(pts)
    if not out.any():
        return 0.0
    return float(trimesh.proximity.closest_point(hull.mesh, pts[out])[1].max() / hull.voxel_size)


VARIANTS = [  # (label, HullConfig overrides)
    ("binary field, MC", dict(field="binary", subdivision_iterations=0)),
    ("binary field, MC + LS3 x5", dict(field="binary")),
    ("distance field, MC", dict(subdivision_iterations=0)),
    ("distance field, MC + LS3 x1", dict(subdivision_iterations=1)),
    ("distance field, MC + LS3 x3", dict(subdivision_iterations=3)),
    ("distance field, MC + LS3 x5 (default)", dict()),
    ("distance field, MC + LS3 x10", dict(subdivision_iterations=10)),
    ("distance field, MC + LS3 x20", dict(subdivision_iterations=20)),
    ("distance field, MC + LS3 x1, all edges split (threshold 0)",
     dict(subdivision_iterations=1, subdivision_threshold=0.0)),
]


def quality(n_shapes: int) -> list[dict]:
    R = trimesh.transformations.rotation_matrix
    box = trimesh.creation.box((1.2, 0.8, 0.6))
    box.apply_transform(R(0.5, [1, 1, 0]) @ R(0.3, [0, 0, 1]))
    objects = [("sphere", trimesh.creation.icosphere(6, 1.0)), ("box", box)]
    objects += [(f"shape {s}", random_shape(s)) for s in range(n_shapes)]
    captures = []
    for i, (name, gt) in enumerate(objects):
        cams = paper_rig(10, rng=100 + i)
        captures.append((name, gt, cams, object_masks(gt, cams)))
    rows = []
    for label, over in VARIANTS:
        per = []
        for name, gt, cams, masks in captures:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # few-view hulls may drop phantom pieces
                hv = carve_visual_hull(masks, cams, HullConfig(**over))
            m = shape_metrics(hv.mesh, gt)
            per.append(dict(name=name, out=outside_voxels(hv, gt), sub=hv.timings["subdivision"],
                            faces=len(hv.mesh.faces), **m))
        mean = lambda k, sel=per: float(np.mean([p[k] for p in sel]))  # noqa: E731
        shapes_only = [p for p in per if p["name"].startswith("shape")]
        rows.append(dict(label=label, sphere=per[0], box=per[1], cd=mean("cd", shapes_only),
                         cdn_mean=mean("cdn_mean", shapes_only), cdn_med=mean("cdn_med", shapes_only),
                         out=max(p["out"] for p in per), sub=mean("sub"), faces=mean("faces")))
        print(f"  {label:58s} shapes: CD {rows[-1]['cd']:6.2f}  CDN-mean {rows[-1]['cdn_mean']:5.2f}  "
              f"CDN-med {rows[-1]['cdn_med']:5.2f} | sphere CDN-mean {per[0]['cdn_mean']:5.2f} | "
              f"box CDN-mean {per[1]['cdn_mean']:5.2f}, outside {per[1]['out']:.2f} vox | "
              f"worst GT point outside {rows[-1]['out']:.2f} vox | LS3 {rows[-1]['sub']:.3f} s", flush=True)
    return rows


def sphere_many_views(views: int = 60) -> dict:
    """Radial normal error (area-weighted mean angle between face normal and radius) of the hull
    of a unit sphere seen from `views` views spread over the sphere."""
    rng = np.random.default_rng(7)
    i = np.arange(views) + 0.5
    y = 0.9 * (1 - 2 * i / views)
    r = np.sqrt(1 - y ** 2)
    phi = i * np.pi * (3 - np.sqrt(5))
    dirs = np.stack([r * np.sin(phi), y, r * np.cos(phi)], 1)
    up = np.array([0.0, 1.0, 0.0]) + rng.uniform(-0.1, 0.1, (views, 3))
    from lookingglass.physics.camera import Cameras

    cams = Cameras.look_at(3 * dirs, np.zeros((views, 3)), up, PAPER_FOV_X_DEG, *PAPER_IMAGE_SIZE)
    gt = trimesh.creation.icosphere(6, 1.0)
    masks = object_masks(gt, cams)
    out = {}
    for label, it in (("MC", 0), ("MC + LS3 x5", 5)):
        hv = carve_visual_hull(masks, cams, HullConfig(subdivision_iterations=it))
        c = hv.mesh.triangles_center
        cos = np.clip((hv.mesh.face_normals * c / np.linalg.norm(c, axis=1, keepdims=True)).sum(1), -1, 1)
        out[label] = dict(radial=float(np.degrees(np.average(np.arccos(cos), weights=hv.mesh.area_faces))),
                          cdn_mean=shape_metrics(hv.mesh, gt)["cdn_mean"],
                          radius_err_vox=float(np.abs(np.linalg.norm(hv.mesh.vertices, axis=1) - 1).max()
                                               / hv.voxel_size))
        print(f"  sphere, {views} views, {label:12s}: radial normal error {out[label]['radial']:.2f} deg, "
              f"CDN-mean {out[label]['cdn_mean']:.2f} deg, max radius error {out[label]['radius_err_vox']:.2f} vox")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per thread setting")
    ap.add_argument("--shapes", type=int, default=5, help="procedural shapes in the quality table")
    ap.add_argument("--no-write", action="store_true", help="do not write docs/benchmarks_hull.md")
    args = ap.parse_args()

    load0 = os.getloadavg()[0]
    gt = random_shape(0)
    cams = paper_rig(10, rng=0)
    masks = object_masks(gt, cams)
    print(f"capture: procedural shape seed 0 ({len(gt.faces)} faces), 10 views, {cams.width}x{cams.height}, "
          f"mask pixels per view {int(masks.sum((1, 2)).mean())}")
    speed = {}
    for threads in (1, 2):
        r = timing(masks, cams, args.repeats, threads)
        speed[threads] = r
        hv = r["hull"]
        print(f"threads {threads}: " + "  ".join(f"{k} {r['median'][k]:.3f}" for k in STEPS)
              + f"  | total median {r['median']['total']:.3f} s (min {r['min']:.3f}, max {r['max']:.3f}),"
              f" {r['median']['total'] / TARGET_S:.2f} x the {TARGET_S:.0f} s target")
    hv = speed[1]["hull"]
    print(f"grid {hv.grid_shape} (resolution {HullConfig().resolution} on the longest side), voxel "
          f"{hv.voxel_size:.4f} = 1/{2 * hv.scale / hv.voxel_size:.0f} of the hull's diameter; "
          f"mesh {len(hv.mesh.vertices)} vertices, {len(hv.mesh.faces)} faces")
    load1 = os.getloadavg()[0]
    print(f"load average (1 min) before/after timing: {load0:.2f} / {load1:.2f} on {os.cpu_count()} cores")

    print("quality, 10-view rig:")
    rows = quality(args.shapes)
    sph = sphere_many_views()

    if not args.no_write:
        write_doc(args, gt, cams, speed, rows, sph, (load0, load1))
    return 0 if speed[1]["median"]["total"] <= TARGET_S else 1


def write_doc(args, gt, cams, speed, rows, sph, loads) -> None:
    hv = speed[1]["hull"]
    cfg = HullConfig()
    lines = [
        "## Visual hull (`benchmarks/bench_hull.py`)",
        "",
        f"Command: `.venv/bin/python benchmarks/bench_hull.py --repeats {args.repeats} --shapes {args.shapes}` "
        f"({time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores, torch "
        f"{torch.__version__}; 1-minute load average {loads[0]:.1f} before and {loads[1]:.1f} after the "
        "timed runs: other jobs shared the machine).",
        "",
        f"**Speed.** `carve_visual_hull` on 10 views of {cams.width}x{cams.height} masks of a procedural shape "
        f"(paper rig, seed 0), default `HullConfig` (resolution {cfg.resolution}: grid {hv.grid_shape}, "
        f"{cfg.subdivision_iterations} LS3 Loop iterations at {100 * cfg.subdivision_threshold:g}% of the "
        f"diagonal), median seconds of {args.repeats} runs after a warm-up. Target: 2 s for the whole call.",
        "",
        "| sub-step | 1 thread (default here) | 2 threads |",
        "|---|---|---|",
    ]
    for k in STEPS + ["total"]:
        a, b = speed[1]["median"][k], speed[2]["median"][k]
        name = f"**{k}**" if k == "total" else k
        lines.append(f"| {name} | {a:.3f} | {b:.3f} |")
    lines += [
        f"| ratio to the 2 s target | **{speed[1]['median']['total'] / TARGET_S:.2f}** | "
        f"{speed[2]['median']['total'] / TARGET_S:.2f} |",
        f"| total min / max over runs | {speed[1]['min']:.3f} / {speed[1]['max']:.3f} | "
        f"{speed[2]['min']:.3f} / {speed[2]['max']:.3f} |",
        "",
        "Sub-steps: masks = per-view signed distance transforms (scipy's exact Euclidean one since session 53, bit-identical between calls where OpenCV's varied); box = triangulated centre and "
        "coarse carving until the box is stable (32^3 rounds, then one 64^3); carve = the fine "
        f"{cfg.resolution}^3 field (10 views, projection as one small matrix product per view, bilinear "
        "`grid_sample`, min over views, chunks of 2^20 voxels); coverage = mask-consistency check; "
        "marching_cubes = skimage Lewiner; components = largest piece (where others are dropped, their and its "
        "ray casts through the mask pixels: ~0.2-0.5 s at 480x360, 10 views); recarve = only where the dropped "
        "pieces cover mask pixels the largest leaves uncovered, the same box at twice the resolution (the demo's "
        "240x180 capture: ~2.5 s at 256^3); subdivision = pymeshlab LS3 Loop; "
        "finish = watertight/orientation checks and normalization.",
        "",
        "Threads: the default (`HullConfig.num_threads=0`) uses half the cores, 1 here. On an idle 2-core "
        "machine 2 torch threads gain ~15-20%; with other jobs running, every parallel op waits at a "
        "barrier for a thread the OS has descheduled, and 2 threads can be several times slower (one "
        "earlier run at load 2-3: 2.18 s median and 4.23 s max with 2 threads vs 0.81 s with 1). This "
        f"run, load {loads[0]:.1f}-{loads[1]:.1f}: 2 threads {speed[2]['median']['total']:.2f} s median "
        f"(max {speed[2]['max']:.2f}), 1 thread {speed[1]['median']['total']:.2f} s (max {speed[1]['max']:.2f}).",
        "",
        f"**Quality.** 10-view paper rig, 480x360. Mean over {args.shapes} procedural shapes (seeds "
        f"0-{args.shapes - 1}) of DESIGN.md's metrics (20 000 samples, GT unit-sphere scale; CD x1e4); the "
        "CDN-mean of a unit sphere and of a rotated box (1.2 x 0.8 x 0.6); the worst GT surface point "
        "outside the hull, in voxels, for the box and over all objects; the LS3 time.",
        "",
        "| hull surface | CD | CDN-mean (deg) | CDN-med (deg) | sphere CDN-mean | box CDN-mean "
        "| box GT outside (vox) | all GT outside (vox) | LS3 (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['label']} | {r['cd']:.2f} | {r['cdn_mean']:.2f} | {r['cdn_med']:.2f} | "
                     f"{r['sphere']['cdn_mean']:.2f} | {r['box']['cdn_mean']:.2f} | {r['box']['out']:.2f} | "
                     f"{r['out']:.2f} | {r['sub']:.3f} |")
    mc, ls = sph["MC"], sph["MC + LS3 x5"]
    by = {r["label"]: r for r in rows}
    b_mc, b_ls = by["binary field, MC"], by["binary field, MC + LS3 x5"]
    d_mc, d_ls = by["distance field, MC"], by["distance field, MC + LS3 x5 (default)"]
    lines += [
        "",
        f"Sphere seen from 60 views (its hull is nearly the sphere, so this is the surface's own error): "
        f"area-weighted angle between face normals and the radius {mc['radial']:.2f} deg with plain marching "
        f"cubes, {ls['radial']:.2f} deg with LS3 x5 (CDN-mean {mc['cdn_mean']:.2f} -> {ls['cdn_mean']:.2f} deg); "
        f"max radius error {ls['radius_err_vox']:.2f} voxel.",
        "",
        f"Reading: the binary carve reproduces DESIGN.md's figures (plain marching cubes "
        f"{b_mc['cdn_mean']:.1f} deg CDN-mean here vs 24.6 there; with LS3 {b_ls['cdn_mean']:.1f} vs 17.3). "
        f"Carving the views' signed distances instead gets {d_mc['cdn_mean']:.1f} deg before any smoothing "
        f"and {d_ls['cdn_mean']:.1f} deg with the default LS3; CD does not change (it is set by the hull's "
        "shape, not its surface). LS3 Loop at 1% of the diagonal splits no edge of a 128^3 marching-cubes "
        "mesh (its edges are at most sqrt(2) voxels, ~0.7% of the mesh's diagonal): it acts as a "
        "volume-preserving smoother, each repetition lowering the normal error a little more. 5 "
        "repetitions are the default: most of the gain for 0.1-0.2 s, vertices move under one voxel, and "
        "the box's sharp edges stay well within a voxel of the hull (the box column: 10-20 repetitions "
        "start pulling them inside the object). Splitting all edges (threshold 0) quadruples the faces "
        "and smooths less per repetition.",
        "",
    ]
    out = ROOT / "docs" / "benchmarks_hull.md"
    out.write_text("\n".join(lines))
    print(f"wrote {out.relative_to(ROOT)}")


if __name__ == "__main__":
    sys.exit(main())
