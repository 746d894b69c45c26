"""Dataset generation speed and size: `python benchmarks/bench_dataset.py [--scenes 8] [--quick]`.

1. Throughput of `generate_dataset` (what `lookingglass generate` runs) for 10-view training
   scenes at the cpu preset (128 x 96 images, E 256 x 128, 4 spp, 128^3 visual hull included),
   with 1 and with 2 worker processes, wall clock including the workers' start-up; target >= 6
   scenes per minute on the 2-core machine.
2. Seconds per part of a scene (shape, envmap, render incl. GT two-bounce, of which two-bounce,
   hull, hull two-bounce, write): means of the scenes' own timings (meta.json) in the 1-worker
   run (one core, uncontended) and in the 2-worker run (both cores busy).
3. Seconds per 10-view 480 x 360 scene, image + two-bounce maps (`render_views`, default
   RenderConfig: 4 spp, both cores), for procedural shapes under the dataset's environment maps at
   512 x 256; target <= 10 s.
4. The paper preset (256 x 192, E 512 x 256, 9 spp): seconds per scene, one worker.
5. Dataset size per scene (KB, per file) and the time to read one item with
   `TransparentSceneDataset` (normalization and environment map included).

Writes docs/benchmarks_dataset.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from lookingglass.data.dataset import SCENE_FILES, DatasetConfig, generate_dataset, load_scene_meta, scene_seeds
from lookingglass.data.envmaps import EnvmapSampler
from lookingglass.data.rigs import paper_rig
from lookingglass.data.shapes import random_shape
from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.physics.environment import EnvironmentMap
from lookingglass.presets import preset
from lookingglass.render.tracer import RenderConfig, render_views

ROOT = Path(__file__).resolve().parents[1]
TARGET_SCENES_PER_MIN = 6.0
TARGET_480_S = 10.0
PARTS = ["shape", "envmap", "render", "render_two_bounce", "hull", "hull_two_bounce", "write"]


def run_generate(root: Path, scenes: int, workers: int, config: DatasetConfig, views: int = 10) -> dict:
    summary = generate_dataset(root, scenes, views=views, split="train", seed=0, config=config, workers=workers)
    assert len(summary["made"]) == scenes
    metas = [load_scene_meta(Path(summary["split_dir"]) / f"scene_{i:05d}") for i in range(scenes)]
    sizes = {f: float(np.mean([(Path(summary["split_dir"]) / f"scene_{i:05d}" / f).stat().st_size
                               for i in range(scenes)])) / 1024 for f in SCENE_FILES}
    per_scene = [sum(m["timings"][p] for p in PARTS if p != "render_two_bounce") for m in metas]
    return dict(summary=summary, scenes_per_min=60 * scenes / summary["seconds"], sizes=sizes,
                parts={p: float(np.mean([m["timings"][p] for m in metas])) for p in PARTS},
                per_scene=per_scene, attempts=sum(m["attempt"] for m in metas),
                hull_faces=float(np.mean([m["hull"]["faces"] for m in metas])))


def render_480(n: int) -> list[dict]:
    rows = []
    sampler = EnvmapSampler(height=256, seed=123)
    for i in range(n):
        seeds = scene_seeds(0, "train", 1000 + i)
        mesh = random_shape(seeds["shape"])
        env, desc = sampler.sample(i)
        cams = paper_rig(10, seeds["rig"], width=480, height=360)
        envmap = EnvironmentMap(torch.from_numpy(np.ascontiguousarray(env)))
        runs = [render_views(mesh, envmap, cams, RenderConfig(seed=i)) for _ in range(3)]
        best = min(runs, key=lambda r: r.stats.seconds)
        rows.append(dict(faces=len(mesh.faces), env=desc.get("name", "procedural"), seconds=best.stats.seconds,
                         all=[r.stats.seconds for r in runs], two_bounce=best.stats.seconds_two_bounce,
                         object=float(best.mask.float().mean()), rays=best.stats.rays_cast))
    return rows


def read_speed(root: Path) -> dict:
    ds = TransparentSceneDataset(root, "train", augment=True)
    cold = []
    for i in range(len(ds)):
        t = time.perf_counter()
        ds[i]
        cold.append(time.perf_counter() - t)
    warm = []
    for i in range(len(ds)):
        t = time.perf_counter()
        ds[i]
        warm.append(time.perf_counter() - t)
    return dict(cold=float(np.mean(cold)), warm=float(np.mean(warm)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=8,
                    help="scenes of the 1-worker run (the 2-worker run makes twice as many)")
    ap.add_argument("--quick", action="store_true", help="fewer scenes everywhere (a smoke run)")
    args = ap.parse_args()
    n1 = 2 if args.quick else args.scenes
    warnings.simplefilter("ignore")
    load0 = os.getloadavg()[0]
    cpu = preset("cpu").dataset
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print(f"cpu preset, 1 worker, {n1} scenes ...", flush=True)
        one = run_generate(tmp / "w1", n1, 1, cpu)
        print(f"  {one['scenes_per_min']:.1f} scenes/min", flush=True)
        print(f"cpu preset, 2 workers, {2 * n1} scenes ...", flush=True)
        two = run_generate(tmp / "w2", 2 * n1, 2, cpu)
        print(f"  {two['scenes_per_min']:.1f} scenes/min", flush=True)
        reading = read_speed(tmp / "w1")
        n_paper = 1 if args.quick else 2
        print(f"paper preset, 1 worker, {n_paper} scenes ...", flush=True)
        paper = run_generate(tmp / "paper", n_paper, 1, preset("paper").dataset)
        print(f"  {60 / paper['scenes_per_min']:.1f} s/scene", flush=True)
    print("480 x 360 renders ...", flush=True)
    big = render_480(1 if args.quick else 3)
    load1 = os.getloadavg()[0]
    write_doc(args, one, two, paper, big, reading, (load0, load1))
    best = two["scenes_per_min"]
    worst480 = max(r["seconds"] for r in big)
    print(f"scenes/min (2 workers): {best:.1f} = {best / TARGET_SCENES_PER_MIN:.1f}x "
          f"the target of {TARGET_SCENES_PER_MIN:g}")
    print(f"480x360 10-view scene: {worst480:.2f} s (worst) = {worst480 / TARGET_480_S:.2f} "
          f"of the {TARGET_480_S:g} s budget")
    return 0


def write_doc(args, one, two, paper, big, reading, loads) -> None:
    cpu_cfg = preset("cpu").dataset
    fmt = lambda x: f"{x:.3f}"  # noqa: E731
    lines = [
        "# Dataset generation benchmark (lookingglass.data.dataset)",
        "",
        f"Command: `python benchmarks/bench_dataset.py{' --quick' if args.quick else ''}` (writes this file).",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}; "
        f"load average {loads[0]:.2f} before / {loads[1]:.2f} after the run ({time.strftime('%Y-%m-%d')}). "
        "Every scene is made with one torch and one Embree thread; parallelism is one process per worker.",
        "",
        "## Training scenes per minute (10 views, cpu preset, visual hull included)",
        "",
        f"cpu preset: {cpu_cfg.width} x {cpu_cfg.height} images, E {2 * cpu_cfg.envmap_height} x "
        f"{cpu_cfg.envmap_height}, {cpu_cfg.samples_per_axis ** 2} spp, hull {cpu_cfg.hull.resolution}^3 + LS3 x"
        f"{cpu_cfg.hull.subdivision_iterations}. Wall clock of `generate_dataset` (= `lookingglass generate`), "
        "workers' start-up included.",
        "",
        "| workers | scenes | seconds | scenes / min | vs target (>= 6 / min) |",
        "|---|---|---|---|---|",
    ]
    for w, r in ((1, one), (2, two)):
        n = len(r["summary"]["made"])
        lines.append(f"| {w} | {n} | {r['summary']['seconds']:.1f} | **{r['scenes_per_min']:.1f}** | "
                     f"{r['scenes_per_min'] / TARGET_SCENES_PER_MIN:.1f}x |")
    lines += [
        "",
        "## Seconds per part of a scene (mean over the scenes)",
        "",
        "| part | 1 worker (one core, uncontended) | 2 workers (both cores busy) | paper preset, 1 worker |",
        "|---|---|---|---|",
    ]
    names = {"render": "render (image + GT two-bounce)", "render_two_bounce": "  of which GT two-bounce maps",
             "hull": "visual hull (carve + MC + LS3)", "hull_two_bounce": "hull two-bounce maps",
             "write": "write (npz, ply, json)"}
    for p in PARTS:
        lines.append(f"| {names.get(p, p)} | {fmt(one['parts'][p])} | {fmt(two['parts'][p])} | {fmt(paper['parts'][p])} |")
    tot = lambda r: sum(v for k, v in r["parts"].items() if k != "render_two_bounce")  # noqa: E731
    lines.append(f"| **total** | **{tot(one):.2f}** | **{tot(two):.2f}** | **{tot(paper):.2f}** |")
    lines += [
        "",
        f"Mean hull size {one['hull_faces']:.0f} faces. Redrawn scenes (degenerate shape or hull): "
        f"{one['attempts'] + two['attempts']}. Paper preset: 256 x 192, E 512 x 256, 9 spp; "
        f"{60 / paper['scenes_per_min']:.1f} s per scene wall clock with one worker "
        f"({paper['scenes_per_min']:.1f} scenes / min; two workers roughly double that).",
        "",
        "## Seconds per 10-view 480 x 360 scene (image + two-bounce maps)",
        "",
        "`render_views` with the default RenderConfig (4 spp, both cores), procedural shapes under the "
        "pool's environment maps at 512 x 256; best of 3 runs.",
        "",
        "| shape faces | environment | seconds | runs | of which two-bounce | object pixels | rays cast | vs target (<= 10 s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in big:
        lines.append(f"| {r['faces']:,} | {r['env']} | **{r['seconds']:.2f}** | {[round(s, 2) for s in r['all']]} | "
                     f"{r['two_bounce']:.2f} | {100 * r['object']:.0f} % | {r['rays'] / 1e6:.1f} M | "
                     f"{r['seconds'] / TARGET_480_S:.2f} |")
    lines += [
        "",
        "## Size on disk and reading",
        "",
        "| file | cpu preset KB / scene | paper preset KB / scene |",
        "|---|---|---|",
    ]
    for f in SCENE_FILES:
        lines.append(f"| {f} | {one['sizes'][f]:.0f} | {paper['sizes'][f]:.0f} |")
    lines.append(f"| **total** | **{sum(one['sizes'].values()):.0f}** | **{sum(paper['sizes'].values()):.0f}** |")
    lines += [
        "",
        "maps.npz holds the float16 images and normal maps and the boolean masks (np.savez_compressed); "
        "hull.npz the hull's float32 vertices and int32 faces; mesh.ply the ground truth (binary PLY).",
        "",
        f"`TransparentSceneDataset[i]` (cpu preset, 10 views, normalization + environment map): "
        f"{1000 * reading['cold']:.0f} ms for a scene's first read (environment map regenerated), "
        f"{1000 * reading['warm']:.0f} ms once its map is cached.",
        "",
    ]
    (ROOT / "docs" / "benchmarks_dataset.md").write_text("\n".join(lines))


if __name__ == "__main__":
    sys.exit(main())
