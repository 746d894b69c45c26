"""Where the normal net is worse than the hull (docs/history.md, session 51): per validation scene, N1 median
angle errors of the hull and of the net (no latent optimization) binned by how sharply the hull's own normals turn at
the pixel (the largest angle between its hull normal and its 8 neighbours', at the net's 128x96).

Usage, after `lookingglass validate --data data/val480 --out RUN` (or `reconstruct --stop-after visual_hull`
per scene), which leaves each scene's visual_hull.ply:
    .venv/bin/python scripts/experiments/normal_creases.py data/val480 RUN WEIGHTS chamfered_cube,key,nut,pebble
"""
import sys
from pathlib import Path

import torch

from lookingglass.capture.scene import load_capture
from lookingglass.metrics import load_mesh
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.predict import network_normals
from lookingglass.normals.train import angle_deg as angle_channels_first
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.weights import load_normal_net

BINS = ((0, 2), (2, 5), (5, 10), (10, 20), (20, 180))


def angle_deg(a, b):
    """Degrees between unit normals (..., H, W, 3), channels last as the stage's maps are."""
    return angle_channels_first(a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2))


def crease_deg(normals):
    """(V, H, W) the largest angle between each pixel's normal and its 8 neighbours' (edges replicated)."""
    V, H, W, _ = normals.shape
    padded = torch.nn.functional.pad(normals.permute(0, 3, 1, 2), (1, 1, 1, 1), mode="replicate").permute(0, 2, 3, 1)
    out = torch.zeros(V, H, W)
    for dy in range(3):
        for dx in range(3):
            out = torch.maximum(out, angle_deg(normals, padded[:, dy:dy + H, dx:dx + W]))
    return out


root, run, weights = Path(sys.argv[1]), Path(sys.argv[2]), load_normal_net(sys.argv[3])
W, H = weights.net.cfg.width, weights.net.cfg.height
for name in sys.argv[4].split(","):
    cap, truth_mesh = load_capture(root / name / "scene"), load_mesh(root / name / "ground_truth.ply")
    x = NormalInputs.from_capture(cap.images, cap.masks, cap.envmap, cap.cameras, cap.ior,
                                  load_mesh(run / name / "visual_hull.ply"), W, H, weights.envmap_height)
    truth = trace_two_bounce(truth_mesh, cap.cameras.with_resolution(W, H), ior=cap.ior)
    n1 = network_normals(weights.net, x, None)[0]  # (V, H, W, 3)
    m = x.mask & truth.mask & x.vh_valid
    hull_err, net_err, crease = angle_deg(x.vh_n1, truth.normal1)[m], angle_deg(n1, truth.normal1)[m], crease_deg(x.vh_n1)[m]
    print(name, "pixels", int(m.sum()))
    for lo, hi in BINS:
        k = (crease >= lo) & (crease < hi)
        if k.any():
            print(f"  crease {lo:>3}-{hi:<3} share {float(k.float().mean()):.2f} hull {float(hull_err[k].median()):.2f} "
                  f"net {float(net_err[k].median()):.2f}")
