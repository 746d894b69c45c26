"""The learned IoR estimate (lookingglass/ior_net.py) on a split of known IoRs: cache its inputs, score a net
(trained by `lookingglass train-ior`), or score the plain cost curve's minimum.

    python scripts/experiments/ior_net_experiment.py cache DATA SPLIT CACHE [--noise P]
    python scripts/experiments/ior_net_experiment.py baseline CACHE     # the cost curve's minimum, no network
    python scripts/experiments/ior_net_experiment.py score CACHE_TEST WEIGHTS
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.ior_net import IorNet, IorNetConfig, IorTrainConfig, posterior_estimate, prepare_cache
from lookingglass.progress import Reporter


def opt(argv, name, default):
    return type(default)(argv[argv.index(name) + 1]) if name in argv else default


def cache(argv):
    """`train-ior`'s own cache (lookingglass.ior_net.prepare_cache) of any split, in OUT/features."""
    data, split, out = argv[0], argv[1], Path(argv[2])
    ds = TransparentSceneDataset(data, split)
    made = prepare_cache(ds, out, IorTrainConfig(photo_noise=opt(argv, "--noise", 0.0)), Reporter())
    print(f"made {made} of {len(ds)}")


def load(cache_dir):
    folder = Path(cache_dir) / "features" if (Path(cache_dir) / "features").is_dir() else Path(cache_dir)
    files = sorted(folder.glob("scene_*.npz"))
    views, masks, iors = [], [], []
    for f in files:
        d = np.load(f)
        views.append(torch.from_numpy(d["views"]))
        masks.append(torch.from_numpy(d["mask"]))
        iors.append(float(d["ior"]))
    return torch.stack(views), torch.stack(masks), torch.tensor(iors)


def score(argv):
    views, masks, iors = load(argv[0])
    cfg = IorNetConfig()
    net = IorNet(cfg)
    from safetensors.torch import load_file
    net.load_state_dict(load_file(argv[1]))
    net.eval()
    with torch.no_grad():
        est, std = [], []
        subsets, nviews = opt(argv, "--subsets", 0), opt(argv, "--views", 6)
        g = torch.Generator().manual_seed(0)
        for i in range(len(iors)):
            if subsets:  # the mean of the distributions over random view subsets
                probs = 0
                for _ in range(subsets):
                    sel = torch.randperm(views.shape[1], generator=g)[:nviews]
                    probs = probs + torch.softmax(net(views[i:i + 1, sel].float(), masks[i:i + 1, sel]), -1)
                logits = torch.log(probs / subsets)
            else:
                logits = net(views[i:i + 1].float(), masks[i:i + 1])
            mean, sd = posterior_estimate(logits, cfg.bin_centres())
            est.append(float(mean))
            std.append(float(sd))
    est, std = np.array(est), np.array(std)
    err = est - iors.numpy()
    for i in range(len(err)):
        print(f"{i} true {iors[i]:.4f} est {est[i]:.4f} +- {std[i]:.4f} err {err[i]:+.4f}")
    print(f"median |err| {np.median(np.abs(err)):.4f}, mean err {err.mean():+.4f}, within 0.03: "
          f"{(np.abs(err) <= 0.03).sum()}/{len(err)}, mean std {std.mean():.4f}")


def baseline(argv):
    """No network: the candidate whose error over the explained pixels is lowest (parabola)."""
    from lookingglass.ior import parabola_minimum
    views, masks, iors = load(argv[0])
    cand = np.array(IorNetConfig().candidates)
    err = views[:, :, 11::2].float().sum((1, 3, 4)) / views[:, :, 12::2].float().sum((1, 3, 4)).clamp(min=1)
    est = np.array([parabola_minimum(e.numpy(), cand) for e in err])
    d = est - iors.numpy()
    print(f"baseline: median |err| {np.median(np.abs(d)):.4f}, mean err {d.mean():+.4f}, within 0.03: "
          f"{(np.abs(d) <= 0.03).sum()}/{len(d)}")


if __name__ == "__main__":
    {"cache": cache, "score": score, "baseline": baseline}[sys.argv[1]](sys.argv[2:])
