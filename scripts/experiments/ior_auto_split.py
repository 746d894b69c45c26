"""`--ior auto` on a variable-IoR test split (issue 22 item 3): each scene reconstructed on `reconstruct`'s path
with the IoR held at 1.4723 (the stored hull, then `lookingglass.pipeline.stage_meshes` with the shipped
nets), then `lookingglass.ior.estimate_ior` on the refined mesh, against the scene's true IoR.

Usage (the split: `lookingglass generate --out data/data10_varior --split test --ior-range 1.3 1.7 --ior-per-shape 5`):
    .venv/bin/python scripts/experiments/ior_auto_split.py data/data10_varior FIRST LAST [--json OUT.json] [--meshes DIR]
(--meshes: the refined meshes are kept there and reused by a later run, which then only estimates.)
Prints one line per scene and the median |error| over all and over the estimates flagged reliable.
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np

from lookingglass.config import PipelineConfig
from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.ior import estimate_ior
from lookingglass.metrics import load_mesh
from lookingglass.physics.constants import IOR_GLASS
from lookingglass.pipeline import stage_meshes
from lookingglass.weights import load_normal_net, load_point_net, shipped_weights


def main(argv: list[str]) -> int:
    out = argv[argv.index("--json") + 1] if "--json" in argv else None
    meshes = Path(argv[argv.index("--meshes") + 1]) if "--meshes" in argv else None
    args = [a for a in argv if not a.startswith("--") and a not in (out, str(meshes))]
    ds = TransparentSceneDataset(args[0], "test", views=10)
    first, last = int(args[1]), min(int(args[2]), len(ds))
    config = PipelineConfig(device="cpu")
    normal_net = load_normal_net(shipped_weights(10)[0])
    point_net = load_point_net(shipped_weights(10, "points")[0])
    rows = []
    for i in range(first, last):
        capture, hull = ds.capture(i, IOR_GLASS), ds.hull(i)
        true_ior = ds.capture(i).ior
        kept = meshes / f"scene_{i:05d}.ply" if meshes else None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if kept is not None and kept.exists():  # made by an earlier run: the estimate alone
                mesh = load_mesh(kept)
            else:
                mesh = stage_meshes(capture, hull, normal_net, point_net, config).refined.mesh
                if kept is not None:
                    kept.parent.mkdir(parents=True, exist_ok=True)
                    mesh.export(kept)
            est = estimate_ior(mesh, capture, config.ior_range)
        rows.append({"scene": i, "true": true_ior, "estimate": est.value, "uncertainty": est.uncertainty,
                     "reliable": est.reliable, "contrast": est.contrast, "seconds": est.seconds})
        err = np.abs([r["estimate"] - r["true"] for r in rows])
        print(f"{i} true {true_ior:.4f} est {est.value:.4f} +- {est.uncertainty:.4f} err {est.value - true_ior:+.4f} "
              f"contrast {est.contrast:.3f} {'reliable' if est.reliable else 'flagged'} ({est.seconds:.1f} s)  "
              f"median |err| so far {np.median(err):.4f}", flush=True)
    err = np.abs([r["estimate"] - r["true"] for r in rows])
    good = np.abs([r["estimate"] - r["true"] for r in rows if r["reliable"]])
    summary = {"scenes": len(rows), "median_abs_error": float(np.median(err)), "within_0.03": float((err <= 0.03).mean()),
               "reliable": len(good), "median_abs_error_reliable": float(np.median(good)) if len(good) else None}
    print(json.dumps(summary))
    if out:
        with open(out, "w") as f:
            json.dump({"summary": summary, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
