"""Normal-stage inference speed: `python benchmarks/bench_normals.py [--repeats 3]`.

A synthetic 10-view 480x360 capture (procedural shape, procedural environment, the paper's rig)
is rendered once; then, as `reconstruct` does: the visual hull, the network inputs (resize,
normalization, the hull's two-bounce maps, error maps), NNet + cost volume, and latent
optimization with the default iterations. Uses the shipped 10-view weights when present (else a
freshly initialized cpu-preset network: the time is the same). Targets on this 2-core machine:
network + cost volume <= 5 s, latent optimization <= 20 s. Writes docs/benchmarks_normals.md.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from lookingglass.data.envmaps import procedural_envmap
from lookingglass.data.rigs import paper_rig
from lookingglass.data.shapes import random_shape
from lookingglass.hull import carve_visual_hull
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.latent import LatentOptConfig
from lookingglass.normals.model import NormalNet, cpu_config
from lookingglass.normals.predict import predict_normals
from lookingglass.physics.environment import EnvironmentMap
from lookingglass.physics.optics import IOR_GLASS
from lookingglass.weights import DEFAULT_ENVMAP_HEIGHT, load_normal_net, shipped_weights
from lookingglass.render.tracer import render_views

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    shape = random_shape(0)
    cams = paper_rig(10, 0, width=480, height=360)
    env = procedural_envmap(np.random.default_rng(0), 256)
    res = render_views(shape, EnvironmentMap(torch.from_numpy(env)), cams)
    hull = carve_visual_hull(res.mask.numpy(), cams).mesh
    path, _ = shipped_weights(10)
    weights = load_normal_net(path) if path else None
    net = weights.net if weights else NormalNet(cpu_config()).eval()
    envmap_height = weights.envmap_height if weights else DEFAULT_ENVMAP_HEIGHT
    source = str(path.relative_to(ROOT)) if path else "untrained cpu-preset network"
    latent = LatentOptConfig()
    t_prep, t_net, t_lat = [], [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        x = NormalInputs.from_capture(res.image, res.mask, env, cams, IOR_GLASS, hull, net.cfg.width, net.cfg.height,
                                      envmap_height)
        _ = x.hull_error  # the error maps are part of making the inputs
        t1 = time.perf_counter()
        predict_normals(net, x, None)
        t2 = time.perf_counter()
        predict_normals(net, x, latent)
        t3 = time.perf_counter()
        t_prep.append(t1 - t0)
        t_net.append(t2 - t1)
        t_lat.append((t3 - t2) - (t2 - t1))  # the optimization beyond one forward pass
    med = statistics.median
    rows = [("inputs (resize, hull two-bounce maps, error maps)", med(t_prep), None),
            ("network + cost volume", med(t_net), 5.0),
            (f"latent optimization ({latent.iterations_n2} + {latent.iterations_both} steps)", med(t_lat), 20.0)]
    for name, sec, target in rows:
        ratio = f"{sec / target:.2f} of the {target:.0f} s target" if target else ""
        print(f"{name:55s} {sec:7.2f} s  {ratio}")
    lines = ["## Normal stage inference (`benchmarks/bench_normals.py`)", "",
             f"Command: `.venv/bin/python benchmarks/bench_normals.py --repeats {args.repeats}` "
             f"({time.strftime('%Y-%m-%d')}, {platform.machine()}, torch {torch.__version__}, "
             f"{torch.get_num_threads()} threads). 10 views of 480x360, network at "
             f"{net.cfg.width}x{net.cfg.height} ({source}); median of {args.repeats} runs.", "",
             "| step | seconds | ratio to target |", "|---|---|---|"]
    for name, sec, target in rows:
        lines.append(f"| {name} | {sec:.2f} | {f'{sec / target:.2f} (target {target:.0f} s)' if target else ''} |")
    (ROOT / "docs" / "benchmarks_normals.md").write_text("\n".join(lines) + "\n")
    print("wrote docs/benchmarks_normals.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
