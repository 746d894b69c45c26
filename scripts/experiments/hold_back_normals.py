"""Would the rendering error tell where to trust the predicted N1 over the hull's? (docs/results.md, issue 27)

Usage, after `lookingglass validate --data data/val480 --out runs/val480`:
    .venv/bin/python scripts/experiments/hold_back_normals.py data/val480 runs/val480
Per scene and in the mean: N1 median of the hull, the prediction, the prediction gated per pixel by the
rendering errors (gateK: prediction where its K x K box-filtered error is lower) and blended (softK:
weight e_hull / (e_hull + e_pred)).
"""
import json
import sys

import numpy as np
import torch
import torch.nn.functional as F
from pathlib import Path
from lookingglass.capture.scene import load_capture
from lookingglass.metrics import load_mesh, normal_angle_errors
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.predict import render_normals
from lookingglass.weights import DEFAULT_ENVMAP_HEIGHT as DEH  # noqa: E402
torch.set_grad_enabled(False)
root, out = Path(sys.argv[1]), Path(sys.argv[2])
res = {}
for name in sorted(json.loads((root/"index.json").read_text())["shapes"]):
    cap = load_capture(root/name/"scene"); gt = load_mesh(root/name/"ground_truth.ply"); hull = load_mesh(out/name/"visual_hull.ply")
    maps = [np.load(p) for p in sorted((out/name/"normals").glob("view_*.npz"))]
    n1p = torch.as_tensor(np.stack([m["n1"] for m in maps])); n2p = torch.as_tensor(np.stack([m["n2"] for m in maps]))
    errp = torch.as_tensor(np.stack([m["render_error"] for m in maps])); mask = torch.as_tensor(np.stack([m["mask"] for m in maps]))
    H, W = mask.shape[1:]
    x = NormalInputs.from_capture(cap.images, cap.masks, cap.envmap, cap.cameras, cap.ior, hull, W, H, DEH)
    hm = render_normals(x, x.vh_n1, x.vh_n2)
    errh = hm.error
    cams = cap.cameras.with_resolution(W, H)
    truth = trace_two_bounce(gt, cams, ior=cap.ior)
    m = mask & truth.mask
    def blur(e, k):
        return F.avg_pool2d(e[:, None], k, 1, k//2, count_include_pad=False)[:, 0] if k > 1 else e
    row = {"hull": normal_angle_errors(x.vh_n1, truth.normal1, m)["median"], "pred": normal_angle_errors(n1p, truth.normal1, m)["median"]}
    for k in (1, 5, 9):
        eh, ep = blur(errh, k), blur(errp, k)
        pick = (ep < eh)[..., None]
        row[f"gate{k}"] = normal_angle_errors(torch.where(pick, n1p, x.vh_n1), truth.normal1, m)["median"]
        w = (eh / (eh + ep + 1e-6))[..., None]   # soft
        nb = torch.nn.functional.normalize(w * n1p + (1 - w) * x.vh_n1, dim=-1)
        row[f"soft{k}"] = normal_angle_errors(nb, truth.normal1, m)["median"]
    res[name] = row; print(name, {k: round(v, 2) for k, v in row.items()}, flush=True)
keys = list(next(iter(res.values())))
print("MEAN", {k: round(float(np.mean([r[k] for r in res.values()])), 2) for k in keys})
