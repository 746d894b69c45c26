"""An eval-shapes run's Chamfer distances split by the true shape's genus (docs/results.md, the test splits'
"By genus" lines): no mask sees through a hole, so the hull of a genus > 0 shape has filled slots and tunnels, and
what each stage does there differs from what it does on genus-0 shapes.

Usage:
    .venv/bin/python scripts/experiments/genus_split.py DATA RUN.json
DATA is the split eval-shapes read (DATA/test/scene_NNNNN/mesh.ply, the true meshes), RUN.json its `--json` output.
Prints, for the genus-0 scenes and for the others, their count and the mean CD (x 1e4) of the hull, the PNet
surface and the refined mesh, and the refined mesh's over the hull's. The genus is the pipeline's own
(`lookingglass.points.stage.genus`, summed over the true mesh's bodies).
"""
import json
import sys
from pathlib import Path

import numpy as np
import trimesh

from lookingglass.points.stage import genus


def main() -> None:
    data, run = Path(sys.argv[1]), Path(sys.argv[2])
    scenes = sorted(json.loads(run.read_text())["scenes"], key=lambda s: s["index"])
    shape_genus = {s["index"]: genus(trimesh.load(data / "test" / f"scene_{s['index']:05d}" / "mesh.ply"))
                   for s in scenes}
    for name, holed in (("genus 0", False), ("genus > 0", True)):
        chosen = [s for s in scenes if (shape_genus[s["index"]] > 0) == holed]
        if not chosen:
            continue
        cd = {row: np.mean([s[row]["cd"] for s in chosen]) for row in ("vh", "pnet-RE", "refined")}
        print(f"{name}: {len(chosen)} scenes, CD hull {cd['vh']:.2f}, PNet surface {cd['pnet-RE']:.2f}, "
              f"refined {cd['refined']:.2f} ({cd['refined'] / cd['vh']:.3f} x the hull's)")


if __name__ == "__main__":
    main()
