"""The refine stage's normal term with the network's own N1/N2 as the target, but weighted by an oracle
that knows, from the ground truth, where the prediction is better than the mesh the term starts from.
Asks: if the normal net could say where it is right (a confidence output), would its normals carry the
mesh toward issue 25's bar? (the plain term, weighted by the rendering error, makes the mesh worse).

Usage, after `lookingglass validate --data data/val480 --out runs/val480`:
    .venv/bin/python scripts/experiments/normal_confidence_oracle.py data/val480 runs/val480 duck,key 8 [margin_deg] [better|hull|triangle]
Per scene: CD, CDN-mean of the refined mesh without the term and with it, the share of pixels trusted.
"""
import sys, dataclasses, warnings, types
import numpy as np, torch
from pathlib import Path
import lookingglass.refine as refine_mod
from lookingglass.metrics import shape_metrics
from lookingglass.config import PipelineConfig
from hull_fed_scene import hull_fed_scene
warnings.simplefilter("ignore")
root, out = Path(sys.argv[1]), Path(sys.argv[2])
iterations = int(sys.argv[4])
margin = float(sys.argv[5]) if len(sys.argv) > 5 else 0.0
rule = sys.argv[6] if len(sys.argv) > 6 else "better"
cfg = PipelineConfig()
angle = lambda a, b: torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))  # noqa: E731
for name in sys.argv[3].split(","):
    sc = hull_fed_scene(root, out, name, cfg)
    cap, gt, hull, stage, x, maps, truth, surf = sc.cap, sc.gt, sc.hull, sc.stage, sc.x, sc.maps, sc.truth, sc.surf
    share = {}

    def oracle_of(cls, stage, hull, vertices, faces, trust_gain):
        cams, tb = cls.mesh_seen(stage, hull, vertices, faces)
        valid = x.mask.cpu() & tb.valid & truth.mask & ~maps.tir
        # the camera-frame normals of the mesh, the prediction and the truth at the same pixels
        if rule == "better":  # the prediction closer to the truth than the mesh
            better1 = angle(maps.n1, truth.normal1) + margin < angle(tb.normal1, truth.normal1)
            better2 = angle(maps.n2, truth.normal2) + margin < angle(tb.normal2, truth.normal2)
        elif rule == "hull":  # the prediction closer to the truth than the hull (what a gain head learns)
            better1 = angle(maps.n1, truth.normal1) + margin < angle(x.vh_n1, truth.normal1)
            better2 = (angle(maps.n2, truth.normal2) + margin < angle(x.vh_n2, truth.normal2)) & x.vh_valid
        else:  # "triangle": what a head predicting its own error e could decide: the mesh is off by at least
            # angle(mesh, pred) - e, so it is surely worse than the prediction where that exceeds e
            better1 = angle(tb.normal1, maps.n1) > 2 * angle(maps.n1, truth.normal1) + margin
            better2 = angle(tb.normal2, maps.n2) > 2 * angle(maps.n2, truth.normal2) + margin
        weight = (valid & better1 & better2).float()
        share["trusted"] = float(weight.sum() / valid.sum().clamp(min=1))
        return cls.from_maps(cams, maps.n1.float(), maps.n2.float(), weight > 0, float(x.ior))

    rows = []
    for n in (0, iterations):
        refine_mod._NormalTarget.of = classmethod(oracle_of)
        rc = dataclasses.replace(cfg.refine, normal_iterations=n)
        r = refine_mod.refine_surface(surf, hull, cap.masks, cap.cameras, rc, capture=cap, normals=stage)
        m = shape_metrics(r.refined, gt)
        rows.append(f"{n} steps: CD {m['cd']:.2f} CDN-mean {m['cdn_mean']:.2f} kept {r.report['kept']} "
                    f"iou {min(r.report['silhouette_iou_after']):.3f}")
    print(name, f"trusted {share.get('trusted', 0):.2f} |", " | ".join(rows), flush=True)
