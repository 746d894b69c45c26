"""N1 and N2 medians of the hull's normals and of one or more normal nets' predictions on a validation set
(docs/results.md, issue 27): per scene, and the means with their ratio to the hull's.

Usage, after `lookingglass validate --data data/val480 --out runs/val480` (which leaves each scene's hull):
    .venv/bin/python scripts/experiments/val_normals.py data/val480 runs/val480 A.safetensors,B.safetensors [latent]
The nets see what `reconstruct` feeds them (`NormalInputs.from_capture`); without `latent`, no latent
optimization (its default steps with it).
"""
import json, sys
import numpy as np, torch
from pathlib import Path
from lookingglass.capture.scene import load_capture
from lookingglass.metrics import load_mesh, normal_angle_errors
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.predict import network_normals
from lookingglass.normals.latent import LatentOptConfig
from lookingglass.weights import load_normal_net, DEFAULT_ENVMAP_HEIGHT as DEH
root, out = Path(sys.argv[1]), Path(sys.argv[2])
wlist = sys.argv[3].split(",")
latent = LatentOptConfig() if len(sys.argv) > 4 else None
nets = [load_normal_net(w) for w in wlist]
rows = {}
for name in sorted(json.loads((root/"index.json").read_text())["shapes"]):
    cap = load_capture(root/name/"scene"); gt = load_mesh(root/name/"ground_truth.ply"); hull = load_mesh(out/name/"visual_hull.ply")
    net0 = nets[0].net
    W, H = net0.cfg.width, net0.cfg.height
    x = NormalInputs.from_capture(cap.images, cap.masks, cap.envmap, cap.cameras, cap.ior, hull, W, H, DEH)
    cams = cap.cameras.with_resolution(W, H)
    truth = trace_two_bounce(gt, cams, ior=cap.ior)
    m = x.mask & truth.mask; two = m & truth.valid
    row = {"hull": (normal_angle_errors(x.vh_n1, truth.normal1, m)["median"], normal_angle_errors(x.vh_n2, truth.normal2, two)["median"])}
    for w, nw in zip(wlist, nets):
        n1, n2 = network_normals(nw.net, x, latent)
        row[Path(w).parent.name or w] = (normal_angle_errors(n1, truth.normal1, m)["median"], normal_angle_errors(n2, truth.normal2, two)["median"])
    rows[name] = row
    print(name, {k: (round(a, 2), round(b, 2)) for k, (a, b) in row.items()}, flush=True)
keys = list(next(iter(rows.values())))
h1 = np.mean([r["hull"][0] for r in rows.values()]); h2 = np.mean([r["hull"][1] for r in rows.values()])
for k in keys:
    a = np.mean([r[k][0] for r in rows.values()]); b = np.mean([r[k][1] for r in rows.values()])
    print(f"MEAN {k}: N1 {a:.2f} ({a/h1:.3f}x)  N2 {b:.2f} ({b/h2:.3f}x)")
