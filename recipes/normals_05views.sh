#!/usr/bin/env bash
# Rebuild lookingglass/weights/normals_05views.safetensors (+ .json): the 5-view normal net, fine-tuned from the
# 10-view net's first run.
#
# Time on a 2-core CPU: ~3 h from scratch: the 10-view net's first run (~25 min of data + ~40 min, via
# recipes/normals_10views.sh; skipped if already made), then ~15 + ~22 min of 5-view data and ~20 + ~13 + ~21 + ~19 min
# of training, then ~7 min of data, ~6 min for the detail head and ~4 min for the gain head.
# Provenance: lookingglass/weights/normals_05views.json (2026-11-28). Usage: bash recipes/normals_05views.sh
# (settings: recipes/_lib.sh). Steps are skipped when their weights exist and resume when interrupted.
#
# Where this differs from the recorded commands:
# - The provenance starts from lookingglass/weights/normals_10views.safetensors, which on 2026-11-23 was still
#   the 10-view net's 2-epoch first run (init_sha256 e0c1ae03... is that file's SHA-256, as shipped on
#   2026-11-22); the file shipped now is the 2 + 6-epoch net. So this recipe starts from runs/normals10.
# - --max-scenes 613 is added (the folder held 613 scenes; it may hold more once points_05views.sh has run).
# - The same steps, schedule and seed; the weights need not be bit-identical (torch 2.13.0+cpu then).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/_lib.sh"
D5=$DATA/data5

# The 10-view net's first run (2 epochs), the starting weights.
STOP_AFTER=normals10 bash recipes/normals_10views.sh

# 2 epochs at 2e-4 halved after 1 on 613 5-view scenes, two DDP processes (~20 min).
step normals5 "$D5" 5 613 \
    "${DDP[@]}" train-normals --data "$D5" --views 5 --preset cpu --variant wr+cv \
    --init "$RUNS/normals10/weights.safetensors" --epochs 2 --lr 2e-4 --lr-halve-epochs 1 --max-scenes 613 \
    --out "$RUNS/normals5"

# 2 epochs on 1000 5-view scenes like users' captures (issue 27; as step 3 of normals_10views.sh: CAD parts,
# handles, thin parts and blobs beside the procedural shapes, hulls from masks 1-6x the image size, half the items
# degraded like 8-bit photos), from the run above; two DDP processes (~22 min of data, ~13 min of training).
GENERATE=generate_users step normals5users "$DATA/users5" 5 1000 \
    "${DDP[@]}" train-normals --data "$DATA/users5" --views 5 --preset cpu --variant wr+cv --seed 0 \
    --init "$RUNS/normals5/weights.safetensors" --epochs 2 --lr 2e-4 --lr-halve-epochs 1 --photo-noise 0.5 \
    --max-scenes 1000 --out "$RUNS/normals5users"

# 3 epochs with the angle loss (as step 4 of normals_10views.sh), from the run above, on the same scenes: 1e-4 for
# two epochs, then 5e-5; two DDP processes (~7 min an epoch).
GENERATE=generate_users step normals5angle "$DATA/users5" 5 1000 \
    "${DDP[@]}" train-normals --data "$DATA/users5" --views 5 --preset cpu --variant wr+cv --seed 0 \
    --init "$RUNS/normals5users/weights.safetensors" --epochs 3 --lr 1e-4 --lr-halve-epochs 2 --photo-noise 0.5 \
    --max-scenes 1000 --loss angle --out "$RUNS/normals5angle"

# 3 more angle-loss epochs from the run above (as step 5 of normals_10views.sh): 5e-5 for two epochs, then 2.5e-5,
# another shuffling seed; two DDP processes (~6 min an epoch).
GENERATE=generate_users step normals5angle2 "$DATA/users5" 5 1000 \
    "${DDP[@]}" train-normals --data "$DATA/users5" --views 5 --preset cpu --variant wr+cv --seed 1 \
    --init "$RUNS/normals5angle/weights.safetensors" --epochs 3 --lr 5e-5 --lr-halve-epochs 2 --photo-noise 0.5 \
    --max-scenes 1000 --loss angle --out "$RUNS/normals5angle2"

# The detail head (as step 6 of recipes/normals_10views.sh; docs/history.md, session 51): a local full-resolution
# correction of the decoder's output, trained alone on the frozen net above (angle loss), 2 epochs, a fourth seed,
# two DDP processes (~3 min an epoch). The recorded run started from the shipped net of 2026-11-26 with its gain
# head dropped, whose other weights are the run above's.
GENERATE=generate_users step normals5detail "$DATA/users5" 5 1000 \
    "${DDP[@]}" train-normals --data "$DATA/users5" --views 5 --preset cpu --variant wr+cv --seed 4 \
    --net.detail-head --detail-head-only --init "$RUNS/normals5angle2/weights.safetensors" --epochs 2 --lr 1e-3 \
    --lr-halve-epochs 1 --photo-noise 0.5 --max-scenes 1000 --loss angle --out "$RUNS/normals5detail"

# The gain head (as step 7 of recipes/normals_10views.sh; session 44): per pixel, how many degrees closer to the
# truth the net's N1/N2 are than the normals it was fed, trained alone on the frozen normals above (which stay
# bit-exact), 2 epochs on the first 600 scenes; two DDP processes (~2 min an epoch). The refine stage's normal term
# reads it. (Until 2026-11-28 the shipped net had no detail head and this step started from the run before it:
# runs/normals5gain.)
GENERATE=generate_users step normals5detailgain "$DATA/users5" 5 600 \
    "${DDP[@]}" train-normals --data "$DATA/users5" --views 5 --preset cpu --variant wr+cv --seed 0 \
    --net.gain-head --net.detail-head --gain-head-only --init "$RUNS/normals5detail/weights.safetensors" \
    --epochs 2 --lr 1e-3 --lr-halve-epochs 1 --photo-noise 0.5 --max-scenes 600 --out "$RUNS/normals5detailgain"

install_weights normals5detailgain normals_05views
