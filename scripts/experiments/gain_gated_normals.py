"""N1 / N2 medians on a validation set when the normal stage's output takes the network's normal only where
its gain head predicts it closer to the truth than the hull's by more than a threshold, the hull's elsewhere
(issue 27: "never worse than the input"). Per scene and in the mean, against the hull's and the raw net's.

Usage, after `lookingglass validate --data DATA --out RUNS` (which leaves each scene's hull):
    .venv/bin/python scripts/experiments/gain_gated_normals.py DATA RUNS [WEIGHTS] [latent]
"""
import json
import sys
from pathlib import Path

import numpy as np
import torch

from lookingglass.capture.scene import load_capture
from lookingglass.metrics import load_mesh, normal_angle_errors
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.latent import LatentOptConfig
from lookingglass.normals.predict import network_normals
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.weights import load_normal_net, shipped_weights

root, out = Path(sys.argv[1]), Path(sys.argv[2])
names = sorted(json.loads((root / "index.json").read_text())["shapes"])
first = load_capture(root / names[0] / "scene")
weights = load_normal_net(sys.argv[3] if len(sys.argv) > 3 and sys.argv[3] != "shipped"
                          else shipped_weights(first.num_views)[0])
latent = LatentOptConfig() if "latent" in sys.argv[3:] else None
W, H = weights.net.cfg.width, weights.net.cfg.height
thresholds = [-2.0, -1.0, 0.0, 1.0, 2.0]
labels = ["hull", "net"] + [f"gate>{t:g}" for t in thresholds] + ["gate-both>0", "gate-both>1"]
rows = {}
for name in names:
    cap = load_capture(root / name / "scene")
    gt = load_mesh(root / name / "ground_truth.ply")
    hull = load_mesh(out / name / "visual_hull.ply")
    x = NormalInputs.from_capture(cap.images, cap.masks, cap.envmap, cap.cameras, cap.ior, hull, W, H,
                                  weights.envmap_height)
    truth = trace_two_bounce(gt, cap.cameras.with_resolution(W, H), ior=cap.ior)
    m = x.mask & truth.mask
    two = m & truth.valid
    n1, n2, gain = network_normals(weights.net, x, latent)
    h1, h2 = x.vh_n1.to(n1.dtype), x.vh_n2.to(n1.dtype)
    outs = {"hull": (h1, h2), "net": (n1, n2)}
    for t in thresholds:  # each hit on its own
        outs[f"gate>{t:g}"] = (torch.where((gain[..., :1] > t), n1, h1), torch.where((gain[..., 1:] > t), n2, h2))
    for t in (0.0, 1.0):  # both hits together (as the refine stage's trust)
        both = (gain > t).all(-1, keepdim=True)
        outs[f"gate-both>{t:g}"] = (torch.where(both, n1, h1), torch.where(both, n2, h2))
    row = {k: (normal_angle_errors(a, truth.normal1, m)["median"], normal_angle_errors(b, truth.normal2, two)["median"])
           for k, (a, b) in outs.items()}
    rows[name] = row
    print(f"{name:15s} " + " ".join(f"{k} {a:.2f}/{b:.2f}" for k, (a, b) in row.items()), flush=True)
print()
for k in labels:
    a = np.mean([r[k][0] for r in rows.values()])
    b = np.mean([r[k][1] for r in rows.values()])
    ha = np.mean([r["hull"][0] for r in rows.values()])
    hb = np.mean([r["hull"][1] for r in rows.values()])
    print(f"MEAN {k:14s} N1 {a:.2f} ({a / ha:.3f}x)  N2 {b:.2f} ({b / hb:.3f}x)")
