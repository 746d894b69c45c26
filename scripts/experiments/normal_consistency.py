"""Multi-view consistency as the normal term's trust: each view's predicted N1 (N2) is carried to the
mesh vertex its pixel's first (second) hit lands nearest, averaged per view over a small neighbourhood
of the mesh, and the views are fused; where the views that see a vertex agree (small spread), the
fused prediction is trusted. The network's errors in different views come from different photos, so
agreement is evidence it does not have to know about itself (sessions 40-41: a learned error or gain
head did not find where the prediction beats the mesh).

Usage, after `lookingglass validate --data data/val480 --out runs/val480`:
    .venv/bin/python scripts/experiments/normal_consistency.py data/val480 runs/val480 duck,pebble 16 [spread_deg] [fused|pred] [margin_deg]
Per scene: how well the spread tells where the fused prediction beats the mesh (against the ground truth),
then CD, CDN-mean of the refined mesh without the term and with it.
"""
import sys, dataclasses, warnings
import numpy as np, torch
from pathlib import Path
import lookingglass.refine as refine_mod
from lookingglass.metrics import shape_metrics
from lookingglass.config import PipelineConfig
from lookingglass.physics.optics import IOR_AIR, interface
from lookingglass.render.differentiable import vertex_normals_t
from lookingglass.render.raycast import RayCaster
from hull_fed_scene import hull_fed_scene
warnings.simplefilter("ignore")
root, out = Path(sys.argv[1]), Path(sys.argv[2])
iterations = int(sys.argv[4])
tau = float(sys.argv[5]) if len(sys.argv) > 5 else 5.0
mode = sys.argv[6] if len(sys.argv) > 6 else "fused"
margin = float(sys.argv[7]) if len(sys.argv) > 7 else 0.0
ROUNDS = 2  # neighbourhood averaging rounds over the mesh (the 128x96 pixel is ~1 edge of the remeshed surface)
cfg = PipelineConfig()
angle = lambda a, b: torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))  # noqa: E731


def hit_vertices(vertices, faces, cams, ior):
    """(V, H, W) long: the vertex nearest each pixel's first hit and second hit (-1 where none)."""
    caster = RayCaster.of(vertices, faces)
    o, d = cams.pixel_rays()
    o, d = o.reshape(-1, 3).double(), d.reshape(-1, 3).double()
    t1, f1, u1, v1 = caster.intersect_raw(o.numpy(), d.numpy())
    h = f1 >= 0
    nearest = lambda f, u, v: faces[f, np.argmax(np.stack([1 - u - v, u, v], 1), 1)]  # noqa: E731
    vert1 = np.full(len(f1), -1); vert1[h] = nearest(f1[h], u1[h], v1[h])
    vn = vertex_normals_t(torch.as_tensor(vertices), torch.as_tensor(faces)).numpy()
    fi = faces[f1[h]]
    w = np.stack([1 - u1[h] - v1[h], u1[h], v1[h]], 1)[:, :, None]
    n1 = torch.as_tensor((w * vn[fi]).sum(1)); n1 = torch.nn.functional.normalize(n1, dim=-1)
    p1 = o[h] + torch.as_tensor(t1[h]).double()[:, None] * d[h]
    _, refr, _, tir = interface(d[h], n1, IOR_AIR / ior)
    go = ((d[h] * n1).sum(-1) < 0) & ~tir
    _, f2, u2, v2 = caster.intersect_raw(p1[go].numpy(), refr[go].numpy(), offset=True)
    vert2 = np.full(len(f1), -1)
    idx = np.flatnonzero(h)[go.numpy()]
    ok = f2 >= 0
    vert2[idx[ok]] = nearest(f2[ok], u2[ok], v2[ok])
    shape = (cams.num_views, cams.height, cams.width)
    return torch.as_tensor(vert1).view(shape), torch.as_tensor(vert2).view(shape)


def fuse(vert, normals_world, n_vertices, average):
    """Per-vertex fusion of one hit's predictions: fused (N, 3), spread (N,) degrees, views (N,)."""
    V = vert.shape[0]
    sums = np.zeros((V, n_vertices, 3)); counts = np.zeros((V, n_vertices))
    for v in range(V):
        m = vert[v] >= 0
        np.add.at(sums[v], vert[v][m].numpy(), normals_world[v][m].numpy())
        np.add.at(counts[v], vert[v][m].numpy(), 1.0)
        for _ in range(ROUNDS):
            sums[v] = average @ sums[v]; counts[v] = average @ counts[v]
    sees = counts > 0.3
    unit = sums / np.maximum(np.linalg.norm(sums, axis=-1, keepdims=True), 1e-12)
    fused = (unit * sees[..., None]).sum(0)
    fused /= np.maximum(np.linalg.norm(fused, axis=-1, keepdims=True), 1e-12)
    cos = np.clip((unit * fused[None]).sum(-1), -1, 1)
    spread = np.where(sees, np.degrees(np.arccos(cos)), 0).sum(0) / np.maximum(sees.sum(0), 1)
    return torch.as_tensor(fused), torch.as_tensor(spread), torch.as_tensor(sees.sum(0))


for name in sys.argv[3].split(","):
    sc = hull_fed_scene(root, out, name, cfg)
    cap, gt, hull, stage, x, maps, truth, surf = sc.cap, sc.gt, sc.hull, sc.stage, sc.x, sc.maps, sc.truth, sc.surf
    info = {}

    def consistency_of(cls, stage, hull, vertices, faces, trust_gain):
        cams, tb = cls.mesh_seen(stage, hull, vertices, faces)
        cams64 = cams.to(dtype=torch.float64)
        vert1, vert2 = hit_vertices(vertices, faces, cams64, x.ior)
        average = sp_average(faces, len(vertices))
        valid = x.mask.cpu() & tb.valid & ~maps.tir & (vert1 >= 0) & (vert2 >= 0)
        fused, target, ok = [], [], valid.clone()
        spread_ok = {t: torch.ones_like(valid) for t in (2, 3, 4, 6, 8)}
        for vert, n in ((vert1, maps.n1), (vert2, maps.n2)):
            nw = cams64.camera_to_world(n.double())
            f, s, k = fuse(vert, nw, len(vertices), average)
            vi = vert.clamp(min=0)
            fcam = cams64.world_to_camera(f[vi.view(-1)].view(*vi.shape, 3)).float()
            fused.append(fcam)
            ok &= (s[vi] < tau) & (k[vi] >= 2)
            for t in spread_ok:
                spread_ok[t] &= (s[vi] < t) & (k[vi] >= 2)
        n_mesh = (tb.normal1, tb.normal2)
        n_true = (truth.normal1, truth.normal2)
        vt = valid & truth.mask
        for hit in (0, 1):
            e_mesh, e_pred, e_fused = (angle(a, n_true[hit])[vt] for a in (n_mesh[hit], (maps.n1, maps.n2)[hit], fused[hit]))
            print(f"  N{hit + 1} median error: mesh {e_mesh.median():.2f} pred {e_pred.median():.2f} "
                  f"fused {e_fused.median():.2f}", flush=True)
        for t in (2, 3, 4, 6, 8):
            sel = vt & spread_ok[t]
            g = sum(angle(n_mesh[h], n_true[h]) - angle(fused[h], n_true[h]) for h in (0, 1))
            b = (angle(fused[0], n_true[0]) < angle(n_mesh[0], n_true[0])) & (angle(fused[1], n_true[1]) < angle(n_mesh[1], n_true[1]))
            print(f"    spread < {t}: {float(sel.sum() / vt.sum()):.3f} trusted, precision {float(b[sel].float().mean()):.2f}, "
                  f"median gain {float(g[sel].median()) if sel.any() else 0:+.2f}", flush=True)
        trusted = ok & vt
        if margin > 0:
            trusted &= (angle(fused[0], n_mesh[0]) > margin) | (angle(fused[1], n_mesh[1]) > margin)
        better = (angle(fused[0], n_true[0]) < angle(n_mesh[0], n_true[0])) & (angle(fused[1], n_true[1]) < angle(n_mesh[1], n_true[1]))
        gain = sum(angle(n_mesh[h], n_true[h]) - angle(fused[h], n_true[h]) for h in (0, 1))
        info["share"] = float(trusted.sum() / vt.sum().clamp(min=1))
        print(f"  spread < {tau}: trusted {info['share']:.3f} of {int(vt.sum())} px, fused better at both hits on "
              f"{float(better[trusted].float().mean()):.2f} (base {float(better[vt].float().mean()):.2f}); "
              f"gain N1+N2 trusted {float(gain[trusted].mean()):+.2f} rest {float(gain[vt & ~trusted].mean()):+.2f}",
              flush=True)
        weight = (valid & ok).float()
        if margin > 0:
            weight *= ((angle(fused[0], n_mesh[0]) > margin) | (angle(fused[1], n_mesh[1]) > margin)).float()
        n1, n2 = (fused[0], fused[1]) if mode == "fused" else (maps.n1.float(), maps.n2.float())
        return cls.from_maps(cams, n1, n2, weight > 0, float(x.ior))

    def sp_average(faces, n):
        return (refine_mod.sp.identity(n, format="csr") - refine_mod.uniform_laplacian(faces, n)).tocsr()

    rows = []
    for n in ((0, iterations) if iterations else (0,)):
        refine_mod._NormalTarget.of = classmethod(consistency_of)
        rc = dataclasses.replace(cfg.refine, normal_iterations=max(n, 1) if iterations else 1)
        if n == 0 and iterations:
            rc = dataclasses.replace(cfg.refine, normal_iterations=0)
        r = refine_mod.refine_surface(surf, hull, cap.masks, cap.cameras, rc, capture=cap, normals=stage)
        m = shape_metrics(r.refined, gt)
        rows.append(f"{rc.normal_iterations} steps: CD {m['cd']:.2f} CDN-mean {m['cdn_mean']:.2f} kept {r.report['kept']} "
                    f"iou {min(r.report['silhouette_iou_after']):.3f}")
    print(name, f"trusted {info.get('share', 0):.3f} |", " | ".join(rows), flush=True)
