"""A second pass of the normal network, fed the refined mesh in place of the hull, and the refine stage's
normal term toward what it predicts. Fed the refined mesh, the network's correction is a correction of
that mesh (sessions 40-41: trust decided against the hull cannot say where to beat the mesh).

Usage, after `lookingglass validate --data data/val480 --out runs/val480`:
    .venv/bin/python scripts/experiments/second_pass_normals.py data/val480 runs/val480 duck,mug 16 gain|all|better [iterations] [nolatent] [gain=2]
Per scene: CD, CDN-mean and the re-rendering error of the refined mesh (mesh.ply) and of the second pass,
which the refine stage keeps or rejects as it does its own result.
"""
import sys, dataclasses, warnings, types
import torch
from pathlib import Path
import lookingglass.refine as refine_mod
from lookingglass.capture.scene import load_capture
from lookingglass.metrics import load_mesh, shape_metrics
from lookingglass.hull import carve_visual_hull
from lookingglass.config import PipelineConfig
from lookingglass.normals.stage import SECOND_PASS, run_normal_stage
from lookingglass.render.tracer import trace_two_bounce
from lookingglass.weights import load_normal_net, shipped_weights
warnings.simplefilter("ignore")
root, out = Path(sys.argv[1]), Path(sys.argv[2])
steps, rule = int(sys.argv[4]), sys.argv[5]
outer = int(sys.argv[6]) if len(sys.argv) > 6 else 0
cfg = PipelineConfig()
# as the refine stage's second pass (normals/stage.py), with the normal stage's latent steps unless nolatent
stage_config = SECOND_PASS if "nolatent" in sys.argv[7:] else dataclasses.replace(SECOND_PASS, latent=cfg.normals.latent)
angle = lambda a, b: torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))  # noqa: E731
totals = []
for name in sys.argv[3].split(","):
    cap = load_capture(root / name / "scene"); gt = load_mesh(root / name / "ground_truth.ply")
    hull = carve_visual_hull(cap.masks, cap.cameras, cfg.hull)
    mesh = load_mesh(out / name / "mesh.ply")
    stage = run_normal_stage(cap, mesh, load_normal_net(shipped_weights(cap.num_views)[0]), stage_config)
    x, maps = stage.inputs, stage.maps
    share = {}

    def rule_of(cls, stage, hull, vertices, faces, trust_gain):
        cams, tb = cls.mesh_seen(stage, hull, vertices, faces)
        valid = x.mask.cpu() & tb.valid & ~maps.tir
        if rule == "better":  # an oracle: where the ground truth says the second pass beats the mesh at both hits
            truth = trace_two_bounce(gt, x.cameras, ior=cap.ior)
            valid &= truth.mask & (angle(maps.n1, truth.normal1) < angle(tb.normal1, truth.normal1)) \
                & (angle(maps.n2, truth.normal2) < angle(tb.normal2, truth.normal2))
        share["trusted"] = float(valid.float().mean())
        return cls.from_maps(cams, maps.n1.float(), maps.n2.float(), valid, float(x.ior))

    gain = next((float(a.split("=", 1)[1]) for a in sys.argv[7:] if a.startswith("gain=")), 2.0)
    if rule != "gain":  # else the refine stage's own rule: the gain head's gain over the mesh fed
        refine_mod._NormalTarget.of = classmethod(rule_of)
    rc = dataclasses.replace(cfg.refine, normal_iterations=steps, iterations=outer, normal_trust_gain=gain)
    r = refine_mod.refine_surface(mesh, hull, cap.masks, cap.cameras, rc, capture=cap, normals=stage)
    m0, m1 = shape_metrics(mesh, gt), shape_metrics(r.refined, gt)
    rr = r.report["rerender_error"]
    totals.append((m0["cd"], m1["cd"], m0["cdn_mean"], m1["cdn_mean"], rr[0], rr[1], r.report["kept"] == "refined"))
    share.setdefault("trusted", r.report.get("normal_term", {}).get("trusted_share", 0))
    print(f"{name} trusted {share.get('trusted', 0):.3f} | mesh CD {m0['cd']:.2f} CDN-mean {m0['cdn_mean']:.2f} "
          f"rerender {rr[0]:.4f} | second pass CD {m1['cd']:.2f} CDN-mean {m1['cdn_mean']:.2f} rerender {rr[1]:.4f} "
          f"iou {min(r.report['silhouette_iou_after']):.3f} kept {r.report['kept']} "
          f"{r.report.get('kept_why', '')}", flush=True)
if totals:
    n = len(totals)
    mean = [sum(t[i] for t in totals) / n for i in range(6)]
    # what a keep rule "the second pass only where it re-renders better" gives
    kept_cd = sum(t[1] if t[5] < t[4] else t[0] for t in totals) / n
    kept_cdn = sum(t[3] if t[5] < t[4] else t[2] for t in totals) / n
    print(f"MEAN mesh CD {mean[0]:.3f} CDN-mean {mean[2]:.3f} rerender {mean[4]:.4f} | second pass CD {mean[1]:.3f} "
          f"CDN-mean {mean[3]:.3f} rerender {mean[5]:.4f} | kept where it re-renders better: CD {kept_cd:.3f} "
          f"CDN-mean {kept_cdn:.3f}")
