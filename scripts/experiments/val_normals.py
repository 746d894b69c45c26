"""N1 and N2 medians of the hull's normals and of one or more normal nets' predictions on a validation set
(docs/results.md, issue 27): per scene, and the means with their ratio to the hull's.

Usage, after `lookingglass validate --data data/val480 --out runs/val480` (which leaves each scene's hull):
    .venv/bin/python scripts/experiments/val_normals.py data/val480 runs/val480 A.safetensors,B.safetensors [latent] [input=mesh.ply]
The nets see what `reconstruct` feeds them (`NormalInputs.from_capture`) at their own image size and map height;
"W@256x192" runs net W at another size. Each net's figures are beside the hull's at the same size (the hull's
N1 median depends on the pixel grid it is sampled on). Without `latent`, no latent optimization.
"""
import json, sys
import numpy as np
from pathlib import Path
from lookingglass.capture.scene import load_capture
from lookingglass.metrics import load_mesh, normal_angle_errors
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.predict import network_normals
from lookingglass.normals.latent import LatentOptConfig
from lookingglass.weights import load_normal_net


def parse(spec: str):
    path, _, size = spec.partition("@")
    weights = load_normal_net(path)
    W, H = (int(v) for v in size.split("x")) if size else (weights.net.cfg.width, weights.net.cfg.height)
    return spec if size else (Path(path).parent.name or path), weights, W, H


root, out = Path(sys.argv[1]), Path(sys.argv[2])
nets = [parse(s) for s in sys.argv[3].split(",")]
latent = LatentOptConfig() if len(sys.argv) > 4 and sys.argv[4] == "latent" else None
# the mesh the nets are fed in place of the hull: "mesh.ply" asks how the net treats the refined mesh
INPUT_MESH = next((a.split("=", 1)[1] for a in sys.argv[4:] if a.startswith("input=")), "visual_hull.ply")
rows = {}
for name in sorted(json.loads((root / "index.json").read_text())["shapes"]):
    cap = load_capture(root / name / "scene"); gt = load_mesh(root / name / "ground_truth.ply")
    hull = load_mesh(out / name / INPUT_MESH)
    row, cache = {}, {}
    for label, nw, W, H in nets:
        key = (W, H, nw.envmap_height)
        if key not in cache:
            x = NormalInputs.from_capture(cap.images, cap.masks, cap.envmap, cap.cameras, cap.ior, hull, W, H,
                                          nw.envmap_height)
            truth = trace_two_bounce(gt, cap.cameras.with_resolution(W, H), ior=cap.ior)
            m = x.mask & truth.mask; two = m & truth.valid
            hull_err = (normal_angle_errors(x.vh_n1, truth.normal1, m)["median"],
                        normal_angle_errors(x.vh_n2, truth.normal2, two)["median"])
            cache[key] = (x, truth, m, two, hull_err)
        x, truth, m, two, hull_err = cache[key]
        n1, n2, _ = network_normals(nw.net, x, latent)
        row[label] = (hull_err, (normal_angle_errors(n1, truth.normal1, m)["median"],
                                 normal_angle_errors(n2, truth.normal2, two)["median"]))
    rows[name] = row
    print(name, {k: f"hull {h[0]:.2f}/{h[1]:.2f} net {p[0]:.2f}/{p[1]:.2f}" for k, (h, p) in row.items()}, flush=True)
families = json.loads((root / "index.json").read_text())["shapes"]
for label, *_ in nets:
    for family in [None, *sorted(set(families.values()))]:
        chosen = [r for n, r in rows.items() if family in (None, families[n])]
        h1, h2, a, b = (np.mean([r[label][i][j] for r in chosen]) for i, j in ((0, 0), (0, 1), (1, 0), (1, 1)))
        print(f"MEAN {label} {family or 'all'}: hull N1 {h1:.2f} N2 {h2:.2f} | net N1 {a:.2f} ({a / h1:.3f}x)  "
              f"N2 {b:.2f} ({b / h2:.3f}x)")
