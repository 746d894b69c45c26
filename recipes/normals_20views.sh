#!/usr/bin/env bash
# Rebuild lookingglass/weights/normals_20views.safetensors (+ .json): the 20-view normal net (issues 22 and 27),
# fine-tuned from the shipped 10-view net (its hull-hinge run, step 7 of recipes/normals_10views.sh) on 600 20-view
# scenes like users' captures (steps 3-4 below). Steps 1-2 made the previous 20-view net (from the 10-view net of
# 2026-11-25); recipes/points_20views.sh still starts from the point net trained on its features.
#
# Time on a 2-core CPU: the 10-view net (~6 h, skipped if made), ~30 min of 20-view data, ~25 min of training and
# ~6 min for the gain head (steps 1-2), then ~20 min for the hinge fine-tune and ~6 min for its gain head (steps 3-4).
# Provenance: lookingglass/weights/normals_20views.json. Usage: bash recipes/normals_20views.sh (settings:
# recipes/_lib.sh). Steps are skipped when their weights exist and resume when interrupted.
#
# Why so short: the net is the same at every view count (its weights are shared by the views; only the cost
# volume's neighbourhood changes with the rig), so 20 views need a fine-tune to the denser rig, not a new training.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/_lib.sh"

# 1. The 10-view net of 2026-11-25 (step 5 of recipes/normals_10views.sh), the starting weights.
STOP_AFTER=normals10angle3 bash recipes/normals_10views.sh

# 2. 2 angle-loss epochs (5e-5, then 2.5e-5) on 600 20-view scenes like users' captures (generate_users: CAD parts,
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

# 3. (session 54; shipped since) The same fine-tune from the shipped 10-view net with its detail head and the hull
#    hinge (step 7 of recipes/normals_10views.sh): 6 angle-loss epochs on the same 600 scenes in which a pixel the
#    net makes worse than the hull it was fed weighs twice, as three runs of 2 epochs (5e-5, then 2.5e-5), each with
#    its own shuffling seed; two DDP processes (~3-4 min an epoch on a quiet machine). At 20 views the hull is
#    already close (N1 ~4 deg on 480x360 masks) and the net must mostly hold back.
STOP_AFTER=normals10hinge bash recipes/normals_10views.sh
init=$RUNS/normals10hinge
for run in 1 2 3; do
    name=normals20hinge$([[ $run == 1 ]] || echo "$run")
    GENERATE=generate_users step "$name" "$DATA/users20" 20 600 \
        "${DDP[@]}" train-normals --data "$DATA/users20" --views 20 --preset cpu --variant wr+cv --seed $((4 + run)) \
        --net.detail-head --init "$init/weights.safetensors" --epochs 2 --lr 5e-5 --lr-halve-epochs 1 \
        --photo-noise 0.5 --max-scenes 600 --loss angle --hull-hinge 1 --out "$RUNS/$name"
    init=$RUNS/$name
done

# 4. Its gain head, as step 2 (the normals stay bit-exact).
GENERATE=generate_users step normals20hinge3gain "$DATA/users20" 20 600 \
    "${DDP[@]}" train-normals --data "$DATA/users20" --views 20 --preset cpu --variant wr+cv --seed 0 \
    --net.gain-head --net.detail-head --gain-head-only --init "$RUNS/normals20hinge3/weights.safetensors" \
    --epochs 2 --lr 1e-3 --lr-halve-epochs 1 --photo-noise 0.5 --max-scenes 600 --out "$RUNS/normals20hinge3gain"

install_weights normals20hinge3gain normals_20views
