"""The IoR net (lookingglass/ior_net.py) on a variable-IoR split, fed the visual hull, the mesh
`reconstruct` keeps (its normal stage, PNet surface and refine stage, every stage told 1.4723 as
`--ior auto` runs them; as `eval-shapes --latent-iterations 0` runs them, without the latent
optimization), or the ground truth: how much of its error is the mesh it reads (issue 22). The search
on such meshes: ior_auto_split.py.

    .venv/bin/python scripts/experiments/ior_net_meshes.py data/data10_varior 60 hull,refined,gt

after `lookingglass generate --out data/data10_varior --scenes 60 --views 10 --split test --ior-range 1.3 1.7
--ior-per-shape 5`. ~15 s a scene for `refined` on 2 cores, ~1 s for the others.
"""

from __future__ import annotations

import sys
import warnings

import numpy as np
import torch

from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.ior_net import learned_ior, load_ior_net
from lookingglass.config import PipelineConfig
from lookingglass.normals.latent import LatentOptConfig
from lookingglass.normals.stage import NormalStageConfig
from lookingglass.physics.constants import IOR_GLASS
from lookingglass.pipeline import stage_meshes
from lookingglass.weights import shipped_weights, load_normal_net, load_point_net


def main(argv: list[str]) -> int:
    dataset, count, which = TransparentSceneDataset(argv[0], "test"), int(argv[1]), argv[2].split(",")
    views = dataset.capture(0).num_views
    net = load_ior_net(shipped_weights(views, "ior")[0])
    normal_net = load_normal_net(shipped_weights(views, "normals")[0])
    point_net = load_point_net(shipped_weights(views, "points")[0])
    # as eval-shapes' Table 2/3: without the latent optimization
    config = PipelineConfig(device="cpu", normals=NormalStageConfig(latent=LatentOptConfig(0, 0)))
    errors, spreads = {w: [] for w in which}, {w: [] for w in which}
    for i in range(min(count, len(dataset))):
        truth, capture, hull = dataset.capture(i).ior, dataset.capture(i, IOR_GLASS), dataset.hull(i)
        row = []
        for what in which:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if what == "hull":
                    mesh = hull.mesh
                elif what == "gt":
                    mesh = dataset.meshes(i)[0]
                else:  # reconstruct's stages, as eval-shapes --latent-iterations 0 runs them
                    mesh = stage_meshes(capture, hull, normal_net, point_net, config).refined.mesh
                found = learned_ior(capture, mesh, net, (1.3, 1.7))
            errors[what].append(found.value - truth)
            spreads[what].append(found.uncertainty)
            row.append(f"{what} {found.value:.4f} +- {found.uncertainty:.4f} ({found.value - truth:+.4f})")
        print(i, f"true {truth:.4f}", " | ".join(row), flush=True)
    for what in which:
        e, s = np.array(errors[what]), np.array(spreads[what])
        print(f"{what}: median |error| {np.median(np.abs(e)):.4f}, within 0.03 {(np.abs(e) <= 0.03).sum()}/{len(e)}, "
              f"mean error {e.mean():+.4f}, within 1 / 2 sd {(np.abs(e) <= s).mean():.2f} / "
              f"{(np.abs(e) <= 2 * s).mean():.2f}, sd <= 0.03 on {(s <= 0.03).sum()}")
    return 0


if __name__ == "__main__":
    torch.set_num_threads(1)
    sys.exit(main(sys.argv[1:]))
