"""Does the normal term's re-rendering check at step K agree with the one after all 32 steps?
Per scene of DATA/test and refine pass: the re-rendering error without the term, with the steps accepted
up to K = 8, 16, and at the end; and whether the stage kept the term.
Usage: .venv/bin/python scripts/experiments/normal_term_early_check.py DATA 0,1,2 OUT.jsonl (docs/history.md, session 88)"""
import json, sys, warnings
import numpy as np, torch, trimesh
import lookingglass.refine as R
from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.normals.stage import run_normal_stage
from lookingglass.pipeline import refine_stage
from lookingglass.points.stage import SurfaceConfig, surface_from_normals
from lookingglass.render.compare import photos_at, rerender
from lookingglass.weights import load_normal_net, load_point_net, shipped_weights

warnings.simplefilter("ignore")
torch.set_num_threads(1)
data, scenes, out = sys.argv[1], [int(s) for s in sys.argv[2].split(",")], sys.argv[3]
views = json.loads(open(f"{data}/test/config.json").read())["views"]
ds = TransparentSceneDataset(data, "test", views=views)
normal_net, point_net = load_normal_net(shipped_weights(views)[0]), load_point_net(shipped_weights(views, "points")[0])
trace = []
orig_descend = R._descend

def descend(x, x0, faces, target, precondition, step, iterations, growth=1.0, conjugate=False):
    accepted = [x.copy()]
    orig_loss = type(target).loss
    best = [None]

    def loss(self, vertices, faces_, grad=False):
        value, g = orig_loss(self, vertices, faces_, grad)
        if best[0] is None or value < best[0]:
            if best[0] is not None:
                accepted.append(vertices.copy())
            best[0] = value
        return value, g
    type(target).loss = loss
    try:
        result = orig_descend(x, x0, faces, target, precondition, step, iterations, growth, conjugate)
    finally:
        type(target).loss = orig_loss
    trace.append({"faces": faces, "accepted": accepted})
    return result
R._descend = descend

for i in scenes:
    capture, hull, truth = ds.capture(i), ds.hull(i), ds.meshes(i)[0]
    normals = run_normal_stage(capture, hull.mesh, normal_net, None)
    mesh, _ = surface_from_normals(hull, normals.maps, SurfaceConfig(), point_net)
    trace.clear()
    result = refine_stage(capture, hull, mesh, normal_net, R.RefineConfig())
    prepared = photos_at(capture, R.RefineConfig().rerender_width)
    weights = np.ones(capture.num_views)
    passes = []
    for k, t in enumerate(trace):
        acc = t["accepted"]
        errs = {}
        for steps in (0, 8, 16, len(acc) - 1):
            if steps < len(acc):
                m = trimesh.Trimesh(hull.denormalize_points(acc[steps]), t["faces"], process=False)
                errs[steps] = float(np.mean(rerender(m, capture, prepared=prepared).error))
        passes.append({"steps_accepted": len(acc) - 1, "errors": errs})
    rec = {"scene": i, "passes": passes,
           "report_passes": [{k: p.get(k) for k in ("kept", "normal_term_kept", "seconds")} for p in result.report["passes"]],
           "term": result.report.get("normal_term", {}).get("rerender_error")}
    print(json.dumps(rec), flush=True)
    with open(out, "a") as f:
        f.write(json.dumps(rec) + "\n")
