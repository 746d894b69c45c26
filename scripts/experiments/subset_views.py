"""A validation set at another view count, made from one that has more views: each scene's scene.json
keeps the chosen cameras; images, masks, the environment map and the ground truth are linked, not copied
(`lookingglass generate-validation` renders 5, 10 or 20 views only).

Usage (docs/results.md, the 15-view figures of session 68: views 3, 7, 11, 15 and 19 of 20 dropped):
    .venv/bin/python scripts/experiments/subset_views.py data/val240v20 data/val240v15 --drop-every 4
then `lookingglass validate --data data/val240v15 --out runs/val240v15 --device cpu`.
"""
import argparse
import os
from pathlib import Path

from lookingglass.fileio import read_json, resolved_path, write_json

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("src", type=Path, help="a validation set (index.json, one folder per shape)")
parser.add_argument("dst", type=Path, help="the new set's folder")
parser.add_argument("--drop-every", type=int, default=4,
                    help="drop view i where i %% N == N - 1 (4: 20 views -> 15)")
args = parser.parse_args()
if resolved_path(args.dst) == resolved_path(args.src):
    parser.error("dst must be another folder: the source set is never modified")

index = read_json(args.src / "index.json", "validation set index")
keep = [i for i in range(index["views"]) if i % args.drop_every != args.drop_every - 1]
for name in index["shapes"]:
    scene_src, scene_dst = args.src / name / "scene", args.dst / name / "scene"
    scene_dst.mkdir(parents=True, exist_ok=True)
    for link, target in [(scene_dst / "images", scene_src / "images"), (scene_dst / "masks", scene_src / "masks"),
                         (scene_dst / "envmap.hdr", scene_src / "envmap.hdr"),
                         (args.dst / name / "ground_truth.ply", args.src / name / "ground_truth.ply")]:
        if not link.exists():
            os.symlink(target.resolve(), link)
    spec = read_json(scene_src / "scene.json", "scene file")
    spec["views"] = [spec["views"][i] for i in keep]
    write_json(scene_dst / "scene.json", spec)
index.update(views=len(keep), derived_from=f"{args.src}, views {keep}")
write_json(args.dst / "index.json", index)
print(f"{args.dst}: {len(index['shapes'])} scenes, {len(keep)} views each ({keep})")
