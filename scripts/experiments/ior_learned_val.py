"""The learned IoR estimate (lookingglass/ior_net.py) on a validation set of known, varied IoR
(`lookingglass generate-validation --out data/val480_ior --ior-range 1.3 1.7`): each scene's hull carved
as `reconstruct` carves it (or, with `--mesh RUN`, the mesh `reconstruct` kept, RUN/<scene>/mesh.ply, after
`lookingglass validate --data data/val480_ior --out RUN`), then the net, against scene.json's IoR.

    .venv/bin/python scripts/experiments/ior_learned_val.py data/val480_ior WEIGHTS.safetensors [--mesh RUN]
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from lookingglass.capture.scene import load_capture
from lookingglass.config import PipelineConfig
from lookingglass.hull import carve_visual_hull
from lookingglass.ior_net import learned_ior, load_ior_net
from lookingglass.metrics import load_mesh


def main(argv: list[str]) -> int:
    root, net = Path(argv[0]), load_ior_net(argv[1])
    run = Path(argv[argv.index("--mesh") + 1]) if "--mesh" in argv else None
    config = PipelineConfig(device="cpu")
    errors = []
    for name in sorted(p.name for p in root.iterdir() if (p / "scene" / "scene.json").exists()):
        folder = root / name / "scene"
        capture = load_capture(folder)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = (load_mesh(run / name / "mesh.ply") if run is not None
                    else carve_visual_hull(capture.masks, capture.cameras, config.hull).mesh)
            found = learned_ior(capture, mesh, net, config.ior_range)
        errors.append(found.value - capture.ior)
        print(f"{name:16s} true {capture.ior:.4f} learned {found.value:.4f} +- {found.uncertainty:.4f} "
              f"error {errors[-1]:+.4f} ({found.seconds:.1f} s)", flush=True)
    errors = np.abs(errors)
    print(f"median |error| {np.median(errors):.4f}, within 0.03: {(errors <= 0.03).sum()}/{len(errors)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
