"""How many latent-optimization steps pay: `python benchmarks/latent_sweep.py --weights W [--scenes 5]`.

For the first test scenes of a dataset, runs the network and then latent optimization with
(k, k) steps (N2 with N1 held, then both) for several k, and prints the N1/N2 median angle error,
render error and seconds per scene for each k: the knee of this curve sets
`LatentOptConfig`'s defaults (docs/history.md keeps the tables).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.normals.evaluate import NormalErrors
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.latent import LatentOptConfig
from lookingglass.normals.predict import predict_normals
from lookingglass.normals.train import normal_targets
from lookingglass.weights import load_normal_net


def schedule(entry: str, lrs: list[float]) -> tuple[tuple[int, int], list[float]]:
    """'10' -> ((10, 10), lrs); '30+0' -> ((30, 0), lrs); '25+15@0.05' -> ((25, 15), [0.05])."""
    steps, _, rate = entry.partition("@")
    n2, plus, both = steps.partition("+")
    return (int(n2), int(both) if plus else int(n2)), ([float(rate)] if rate else lrs)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", default="data")
    parser.add_argument("--weights", required=True)
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--steps", default="0,10,25,50,100",
                        help="comma-separated schedules: K (K + K steps), N2+BOTH, or either with @RATE")
    parser.add_argument("--lrs", default=str(LatentOptConfig.lr), help="comma-separated Adam rates to sweep too")
    parser.add_argument("--data-views", type=int, default=10)
    args = parser.parse_args()
    lrs = [float(x) for x in args.lrs.split(",")]
    ks = []  # (steps of each phase, Adam rate); no rate sweep without steps
    for entry in args.steps.split(","):
        phases, entry_lrs = schedule(entry, lrs)
        ks += [(phases, lr) for lr in (entry_lrs if sum(phases) else entry_lrs[:1])]
    ds = TransparentSceneDataset(args.data, "test", views=args.data_views)
    weights = load_normal_net(args.weights)
    net = weights.net
    rows = {key: NormalErrors() for key in ks}
    for i in range(min(args.scenes, len(ds))):
        capture, hull = ds.capture(i), ds.hull(i)  # reconstruct's own inputs
        x = NormalInputs.from_capture(capture.images, capture.masks, capture.envmap, capture.cameras, capture.ior,
                                      hull.mesh, net.cfg.width, net.cfg.height, weights.envmap_height)
        truth = normal_targets(ds[i])
        for k, lr in ks:
            start = time.perf_counter()
            maps = predict_normals(net, x, LatentOptConfig(*k, lr=lr) if sum(k) else None)
            rows[k, lr].add(maps, truth, time.perf_counter() - start)
        print(f"scene {i + 1}/{min(args.scenes, len(ds))}", flush=True)
    print(f"\nLatent-optimization sweep: {args.weights}, first {args.scenes} test scenes of {args.data}, "
          f"{args.data_views} views\n")
    print("| steps (N2 + both) | Adam rate | N1 median (°) | N2 median (°) | render error (×1e-2) | seconds / scene |")
    print("|---|---|---|---|---|---|")
    for (k, lr), row in rows.items():
        s = row.summary()
        print(f"| {k[0]} + {k[1]} | {lr if sum(k) else '-'} | {s['n1_median']:.2f} | {s['n2_median']:.2f} | {100 * s['render_error']:.3f} | "
              f"{row.seconds / max(1, min(args.scenes, len(ds))):.1f} |")
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    raise SystemExit(main())
