"""Speed and variety of the procedural shapes: `python benchmarks/bench_shapes.py [--n 50] [--start 0]`.

Prints seconds per shape (generation only), face counts, and variety statistics: genus (from the
Euler characteristic), sphericity and volume / convex-hull volume, plus validity counts
(watertight, one body, self-intersecting faces).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "2")

import numpy as np  # noqa: E402

from lookingglass.data.shapes import ShapeConfig, random_shape, self_intersecting_faces, shape_stats  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=50, help="number of shapes")
    ap.add_argument("--start", type=int, default=0, help="first seed")
    args = ap.parse_args()
    config = ShapeConfig()
    times, stats, bad = [], [], []
    for seed in range(args.start, args.start + args.n):
        t0 = time.perf_counter()
        mesh = random_shape(seed, config)
        times.append(time.perf_counter() - t0)
        s = shape_stats(mesh)
        s["watertight"] = bool(mesh.is_watertight)
        s["bodies"] = int(mesh.body_count)
        s["self_intersections"] = len(self_intersecting_faces(mesh.vertices, mesh.faces))
        s["max_norm_err"] = float(abs(np.linalg.norm(mesh.vertices, axis=1).max() - 1))
        stats.append(s)
        if not s["watertight"] or s["bodies"] != 1 or s["self_intersections"]:
            bad.append((seed, s))
    t = np.array(times)
    col = lambda k: np.array([s[k] for s in stats], dtype=float)  # noqa: E731
    faces, genus = col("faces"), col("genus").astype(int)
    print(f"shapes: {args.n} (seeds {args.start}..{args.start + args.n - 1}), config {config}")
    print(f"seconds/shape: mean {t.mean():.3f}  median {np.median(t):.3f}  max {t.max():.3f}  (threads: "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}, cpus {os.cpu_count()})")
    print(f"faces: mean {faces.mean():.0f}  min {faces.min():.0f}  max {faces.max():.0f}")
    values, counts = np.unique(genus, return_counts=True)
    print("genus: " + ", ".join(f"{v}: {c}" for v, c in zip(values, counts)))
    for k in ("sphericity", "convexity"):
        x = col(k)
        print(f"{k}: min {x.min():.3f}  p10 {np.percentile(x, 10):.3f}  median {np.median(x):.3f}  "
              f"p90 {np.percentile(x, 90):.3f}  max {x.max():.3f}")
    print(f"max | |p| - 1 |: {col('max_norm_err').max():.2e}")
    print(f"invalid (not watertight / not one body / self-intersecting): {len(bad)}")
    for seed, s in bad:
        print(f"  seed {seed}: {s}")


if __name__ == "__main__":
    main()
