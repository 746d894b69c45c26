#!/usr/bin/env bash
# Rebuild lookingglass/weights/normals_20views.safetensors (+ .json): the 20-view normal net (issue 22), fine-tuned
# from the shipped 10-view net (the last run of recipes/normals_10views.sh) on 600 20-view scenes like users' captures.
#
# Time on a 2-core CPU: the 10-view net (~4.5 h, skipped if made), ~30 min of 20-view data, ~25 min of training,
# ~6 min for the gain head.
# Provenance: lookingglass/weights/normals_20views.json. Usage: bash recipes/normals_20views.sh (settings:
# recipes/_lib.sh). Steps are skipped when their weights exist and resume when interrupted.
#
# Why so short: the net is the same at every view count (its weights are shared by the views; only the cost
# volume's neighbourhood changes with the rig), so 20 views need a fine-tune to the denser rig, not a new training.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/_lib.sh"

# The shipped 10-view net, the starting weights.
STOP_AFTER=normals10angle3 bash recipes/normals_10views.sh

# 2 angle-loss epochs (5e-5, then 2.5e-5) on 600 20-view scenes like users' captures (generate_users: CAD parts,
# handles, thin parts and blobs beside the procedural shapes; hulls from masks 1-6x the image size), half the items
# degraded like 8-bit photos; two DDP processes.
GENERATE=generate_users step normals20 "$DATA/users20" 20 600 \
    "${DDP[@]}" train-normals --data "$DATA/users20" --views 20 --preset cpu --variant wr+cv --seed 0 \
    --init "$RUNS/normals10angle3/weights.safetensors" --epochs 2 --lr 5e-5 --lr-halve-epochs 1 --photo-noise 0.5 \
    --max-scenes 600 --loss angle --out "$RUNS/normals20"

# The gain head (as step 6 of recipes/normals_10views.sh): per pixel, how many degrees closer to the truth the net's
# N1/N2 are than the hull's, trained alone on the frozen normals above (which stay bit-exact), 2 epochs on the same
# 600 scenes, two DDP processes. The refine stage's normal term reads it; without it the term is skipped at 20 views.
GENERATE=generate_users step normals20gain "$DATA/users20" 20 600 \
    "${DDP[@]}" train-normals --data "$DATA/users20" --views 20 --preset cpu --variant wr+cv --seed 0 \
    --net.gain-head --gain-head-only --init "$RUNS/normals20/weights.safetensors" --epochs 2 --lr 1e-3 \
    --lr-halve-epochs 1 --photo-noise 0.5 --max-scenes 600 --out "$RUNS/normals20gain"

install_weights normals20gain normals_20views
