"""Does smoothing the normal net's predicted N1/N2 maps within the mask lower their error (issue 27, the CAD
family's N1 at 0.94 x the hull's)? Per scene: N1 / N2 medians of the hull, the net, and the net's maps smoothed
by a masked Gaussian of a few sigmas (pixels at the net's size), renormalized.

Usage, after `lookingglass validate --data data/val480 --out RUN`:
    .venv/bin/python scripts/experiments/smoothed_normals.py data/val480 RUN [W.safetensors]
"""
import json
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from lookingglass.capture.scene import load_capture
from lookingglass.metrics import load_mesh, normal_angle_errors
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.predict import network_normals
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.weights import load_normal_net, shipped_weights

SIGMAS = (0.5, 0.75, 1.0, 1.5)


def smooth(n, mask, sigma):
    """n (V,H,W,3), mask (V,H,W): the masked Gaussian mean, renormalized (pixels outside keep n)."""
    r = max(1, int(3 * sigma))
    k = torch.exp(-torch.arange(-r, r + 1, dtype=torch.float32) ** 2 / (2 * sigma ** 2))
    k2 = (k[:, None] * k[None, :]) / k.sum() ** 2
    w = mask.float()[:, None]
    x = n.permute(0, 3, 1, 2) * w
    num = F.conv2d(x, k2.expand(3, 1, -1, -1).contiguous(), padding=r, groups=3)
    den = F.conv2d(w, k2[None, None], padding=r)
    out = (num / den.clamp_min(1e-6)).permute(0, 2, 3, 1)
    return torch.where(mask[..., None], F.normalize(out, dim=-1), n)


root, run = Path(sys.argv[1]), Path(sys.argv[2])
weights = load_normal_net(sys.argv[3] if len(sys.argv) > 3 else shipped_weights(10)[0])
index = json.loads((root / "index.json").read_text())
rows = {}
for name in sorted(index["shapes"]):
    cap = load_capture(root / name / "scene")
    gt = load_mesh(root / name / "ground_truth.ply")
    hull = load_mesh(run / name / "visual_hull.ply")
    W, H = weights.net.cfg.width, weights.net.cfg.height
    x = NormalInputs.from_capture(cap.images, cap.masks, cap.envmap, cap.cameras, cap.ior, hull, W, H,
                                  weights.envmap_height)
    truth = trace_two_bounce(gt, cap.cameras.with_resolution(W, H), ior=cap.ior)
    m = x.mask & truth.mask
    two = m & truth.valid
    n1, n2, _ = network_normals(weights.net, x, None)
    med = lambda a, b, k: normal_angle_errors(a, b, k)["median"]  # noqa: E731
    row = {"hull": (med(x.vh_n1, truth.normal1, m), med(x.vh_n2, truth.normal2, two)),
           "net": (med(n1, truth.normal1, m), med(n2, truth.normal2, two))}
    for s in SIGMAS:
        row[f"net s{s}"] = (med(smooth(n1, x.mask, s), truth.normal1, m), med(smooth(n2, x.mask, s), truth.normal2, two))
        row[f"hull s{s}"] = (med(smooth(x.vh_n1, x.mask, s), truth.normal1, m),
                             med(smooth(x.vh_n2, x.mask, s), truth.normal2, two))
    rows[name] = row
    print(name, " ".join(f"{k} {a:.2f}/{b:.2f}" for k, (a, b) in row.items()), flush=True)
families = {"cad": ("bracket", "nut", "chamfered_cube", "stepped_shaft")}
for label in rows[next(iter(rows))]:
    for fam, names in [("all", tuple(rows)), *families.items()]:
        h = np.mean([[rows[n]["hull"][0], rows[n]["hull"][1]] for n in names], 0)
        v = np.mean([[rows[n][label][0], rows[n][label][1]] for n in names], 0)
        print(f"MEAN {fam:4s} {label:10s} N1 {v[0]:.2f} ({v[0] / h[0]:.3f}x)  N2 {v[1]:.2f} ({v[1] / h[1]:.3f}x)")
