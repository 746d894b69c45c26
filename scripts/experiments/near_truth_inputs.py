"""A training split whose normal-net inputs come, for a share of the scenes, from a mesh near the truth instead of the
visual hull (issue 27: the refine stage's second pass feeds the normal net the refined mesh, 3.6 degrees N1 median
on the validation set, and the net, trained on hulls only, answers 4.6 degrees: it corrects a good input anyway; fed
the ground truth itself it answers 3.1 degrees).

Usage: .venv/bin/python scripts/experiments/near_truth_inputs.py SRC DST [--share 0.5] [--seed 0]
SRC/train: a split made by `lookingglass generate`; DST/train gets the same scenes (maps.npz rewritten, the other
files linked) where, in a seeded `share` of them, vh_mask / vh_n1 / vh_n2 / vh_valid / vh_tir are the two-bounce maps
of the ground truth perturbed like a refined mesh: its sharp edges rounded (Taubin smoothing, 0-12 passes after
subdividing to edges of 0.02), a smooth displacement along the normals (three random plane waves, wavelength
0.3-2, amplitude up to 0.012 each) and an offset of -0.004 to +0.010 (refined meshes sit outside the object). meta.json
says which ("input": {"kind": "hull"} or {"kind": "near_truth", ...the draw}). Every SRC scene must be finished (a
partial split is refused). Resumable: finished scenes are kept, and DST/train/near_truth.json records --share and
--seed so that a rerun with others is refused rather than mixing two draws. SRC is only read.
"""
import argparse
import json
import os
import shutil
from pathlib import Path

import numpy as np
import torch
import trimesh

from lookingglass.data.dataset import _bool, _f16, is_finished, load_maps, load_scene_mesh, load_scene_meta, scene_cameras
from lookingglass.fileio import write_atomic, write_json
from lookingglass.render.tracer import trace_two_bounce


def near_truth(gt: trimesh.Trimesh, rng: np.random.Generator) -> tuple[trimesh.Trimesh, dict]:
    """gt perturbed like a refined mesh (see the module docstring), with the draw."""
    v, f = trimesh.remesh.subdivide_to_size(gt.vertices, gt.faces, max_edge=0.02, max_iter=8)
    mesh = trimesh.Trimesh(v, f, process=True)
    passes = int(rng.integers(0, 13))
    if passes:
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=passes)
    p = mesh.vertices
    waves = []
    displacement = np.zeros(len(p))
    for _ in range(3):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        wavelength = rng.uniform(0.3, 2.0)
        amplitude = rng.uniform(0, 0.012)
        phase = rng.uniform(0, 2 * np.pi)
        displacement += amplitude * np.sin(2 * np.pi * p @ direction / wavelength + phase)
        waves.append([round(float(wavelength), 3), round(float(amplitude), 5)])
    offset = float(rng.uniform(-0.004, 0.010))
    mesh = trimesh.Trimesh(p + (displacement + offset)[:, None] * mesh.vertex_normals, mesh.faces, process=False)
    return mesh, {"taubin_passes": passes, "waves": waves, "offset": round(offset, 5)}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("src")
    parser.add_argument("dst")
    parser.add_argument("--share", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    src, dst = Path(args.src) / "train", Path(args.dst) / "train"
    scenes = sorted(d for d in src.iterdir() if d.is_dir() and d.name.startswith("scene_"))
    unfinished = [d.name for d in scenes if not is_finished(d)]
    if unfinished:
        raise SystemExit(f"{src}: unfinished scene(s) {', '.join(unfinished[:5])}: let `generate` finish first")
    dst.mkdir(parents=True, exist_ok=True)
    draw = {"share": args.share, "seed": args.seed}
    recorded = dst / "near_truth.json"
    if recorded.is_file() and json.loads(recorded.read_text()) != draw:
        raise SystemExit(f"{recorded} holds another draw ({json.loads(recorded.read_text())}); pick another DST")
    write_json(recorded, draw)
    shutil.copy(src / "config.json", dst / "config.json")
    torch.set_num_threads(1)
    for k, scene in enumerate(scenes):
        out = dst / scene.name
        if (out / "meta.json").is_file():
            continue
        out.mkdir(exist_ok=True)
        meta = load_scene_meta(scene)
        maps = load_maps(scene)
        rng = np.random.default_rng([args.seed, meta["index"]])
        if rng.random() < args.share:
            mesh, draw = near_truth(load_scene_mesh(scene), rng)
            tb = trace_two_bounce(mesh, scene_cameras(meta), meta["ior"], meta["ext_ior"], threads=1)
            maps.update(vh_mask=_bool(tb.mask), vh_n1=_f16(tb.normal1), vh_n2=_f16(tb.normal2),
                        vh_valid=_bool(tb.valid), vh_tir=_bool(tb.tir))
            meta["input"] = {"kind": "near_truth", **draw}
        else:
            meta["input"] = {"kind": "hull"}
        for name in ("mesh.ply", "hull.npz"):
            if not (out / name).exists():
                os.symlink((scene / name).resolve(), out / name)
        write_atomic(out / "maps.npz", lambda p: np.savez_compressed(p, **maps))
        write_json(out / "meta.json", meta)
        if k % 50 == 0:
            print(f"{k}/{len(scenes)}", flush=True)


if __name__ == "__main__":
    main()
