"""The normal stage's predicted N1 / N2 medians with and without the views' consensus and the mirror
average, per scene and per family, against the hull's (the 90-degree rule for a missing normal, as
`validate`'s tables).

Usage, after `lookingglass validate --data DATA --out RUNS` (it reads the hulls that run left):
    .venv/bin/python scripts/experiments/consensus_normals.py DATA RUNS [0,1,0m,1m] [A.safetensors,B.safetensors]
The third argument lists the `--normals.consensus-px` values to compare (0: each view's own prediction),
each with an `m` for `--normals.mirror-average` on (without it: off); the fourth, normal nets to compare
(default: the shipped one for the capture's view count; columns suffixed /0, /1, ... in the order given).
"""
import json
import sys
from pathlib import Path

import numpy as np

from lookingglass.capture.scene import load_capture
from lookingglass.metrics import load_mesh, normal_angle_errors
from lookingglass.normals.stage import NormalStageConfig, run_normal_stage
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.weights import load_normal_net, shipped_weights

root, runs = Path(sys.argv[1]), Path(sys.argv[2])
values = (sys.argv[3] if len(sys.argv) > 3 else "0,1").split(",")
nets = sys.argv[4].split(",") if len(sys.argv) > 4 else [None]
index = json.loads((root / "index.json").read_text())["shapes"]
rows = []
for name in sorted(index):
    capture = load_capture(root / name / "scene")
    hull, truth_mesh = load_mesh(runs / name / "visual_hull.ply"), load_mesh(root / name / "ground_truth.ply")
    row = {"name": name, "family": index[name]}
    for j, path in enumerate(nets):
        weights = load_normal_net(path or shipped_weights(capture.num_views)[0])
        label = "" if len(nets) == 1 else f"/{j}"
        for value in values:
            px = float(value.rstrip("m"))
            stage = run_normal_stage(capture, hull, weights, NormalStageConfig(consensus_px=px,
                                                                               mirror_average=value.endswith("m")))
            truth = trace_two_bounce(truth_mesh, stage.maps.cameras, ior=capture.ior)
            first = stage.maps.mask & truth.mask
            second = first & truth.valid
            if "n1_hull" not in row:
                row["n1_hull"] = normal_angle_errors(stage.inputs.vh_n1, truth.normal1, first)["median"]
                row["n2_hull"] = normal_angle_errors(stage.inputs.vh_n2, truth.normal2, second)["median"]
            row[f"n1_{value}{label}"] = normal_angle_errors(stage.maps.n1, truth.normal1, first)["median"]
            row[f"n2_{value}{label}"] = normal_angle_errors(stage.maps.n2, truth.normal2, second)["median"]
    rows.append(row)
    print(" ".join(f"{k} {v:.2f}" if isinstance(v, float) else str(v) for k, v in row.items()), flush=True)
keys = [k for k in rows[0] if k[:3] in ("n1_", "n2_")]
for family in ["all", *sorted({r["family"] for r in rows})]:
    chosen = [r for r in rows if family in ("all", r["family"])]
    mean = {k: float(np.mean([r[k] for r in chosen])) for k in keys}
    print(f"{family:8s}", "  ".join(f"{k} {mean[k]:.2f} ({mean[k] / mean[k[:2] + '_hull']:.3f} x)" for k in keys))
