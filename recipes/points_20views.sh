#!/usr/bin/env bash
# Rebuild lookingglass/weights/points_20views.safetensors (+ .json): the 20-view point net (issue 22), fine-tuned
# from the shipped 10-view point net (the last run of recipes/points_10views.sh) on the features of the 20-view
# normal net, on the 600 20-view scenes of recipes/normals_20views.sh.
#
# Time on a 2-core CPU: the 10-view point net and the 20-view normal net (~10.5 h, skipped if made), ~20 min of
# features, ~5 min of training; the second run (step 2) as much again.
# Provenance: lookingglass/weights/points_20views.json. Usage: bash recipes/points_20views.sh (settings:
# recipes/_lib.sh). Steps are skipped when their weights exist and resume when interrupted.
# Since session 92 train-points makes the features with `reconstruct`'s normal stage (the mirror average and the
# views' consensus: points/train.py TRAINING_FEATURES); the recorded runs used each view's own prediction.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/_lib.sh"

STOP_AFTER=points10users bash recipes/points_10views.sh
STOP_AFTER=normals20 bash recipes/normals_20views.sh

# 1. 4 epochs (1e-4, halved after 2) on the 600 20-view scenes, two DDP processes (points_on_users); the point net
# does not depend on the view count (its inputs are per-point statistics over the views).
points_on_users points20 20 "$RUNS/normals20/weights.safetensors" "$RUNS/points10users/weights.safetensors" 600

# 2. (session 54; shipped since) 4 more on the same scenes with the features of the 20-view hull-hinge normal net
#    (recipes/normals_20views.sh steps 3-4; its gain head leaves the normals bit-exact), as points_10views.sh step 9
#    does at 10 views.
STOP_AFTER=normals20hinge3gain bash recipes/normals_20views.sh
points_on_users points20hinge 20 "$RUNS/normals20hinge3gain/weights.safetensors" "$RUNS/points20/weights.safetensors" 600

install_weights points20hinge points_20views
