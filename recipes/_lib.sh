# Helpers the recipes share; sourced by recipes/*.sh, not run on its own.
#
# Settings (environment variables; relative paths are from the repository root):
#   RUNS=runs        run folders, one per training step (config, checkpoint, feature cache, weights)
#   DATA=data        datasets: DATA/data10 (10 views) and DATA/data5 (5 views), their train splits
#   VENV=.venv       the environment scripts/setup.sh makes
#   WEIGHTS=lookingglass/weights   where the finished weights are copied
#   STOP_AFTER=NAME  stop once the step NAME is done (a recipe that needs another's intermediate run)

cd "$(dirname "${BASH_SOURCE[0]}")/.."
RUNS=${RUNS:-runs}
DATA=${DATA:-data}
VENV=${VENV:-.venv}
WEIGHTS=${WEIGHTS:-lookingglass/weights}
export RUNS DATA VENV WEIGHTS
# One torch thread a process: on a shared 2-core machine two threads train 2-3x slower.
export OMP_NUM_THREADS=1

LG=("$VENV/bin/lookingglass")
# Two DDP processes, one per core, as the provenance ran them.
DDP=("$VENV/bin/torchrun" --nproc_per_node=2 -m lookingglass.cli)

# generate DIR VIEWS SCENES: training scenes 0 .. SCENES-1 of the VIEWS-view set in DIR/train (seed 0, cpu
# preset). Scene i depends only on (seed, split, i), and finished scenes are skipped: growing a set adds the
# new scenes only, and an interrupted run picks up where it stopped.
generate() {
    "${LG[@]}" generate --out "$1" --views "$2" --scenes "$3" --split train --seed 0 --preset cpu --workers 2
}

# generate_users DIR VIEWS SCENES: training scenes like users' captures (issue 27): 40% procedural shapes and
# 60% CAD parts, handles, thin parts and blobs (lookingglass/data/families.py), hulls carved from masks 1-6x the
# 128x96 images (log-uniform; a 480x360 photo is 3.75x). Seed 0, cpu preset, resumable like `generate`.
generate_users() {
    "${LG[@]}" generate --out "$1" --views "$2" --scenes "$3" --split train --seed 0 --preset cpu --workers 2 \
        --family-weights 0.4 0.2 0.1 0.1 0.2 --hull-mask-scale 1 6
}

# step NAME DIR VIEWS SCENES COMMAND...: unless RUNS/NAME/weights.safetensors exists (the step is done), make
# sure DIR holds the first SCENES training scenes (with `generate`, or the function named by GENERATE), then run COMMAND (a train-normals or train-points run with
# --out RUNS/NAME; run again after an interruption, it resumes from its checkpoint).
step() {
    local name=$1 dir=$2 views=$3 scenes=$4
    shift 4
    if [[ -f $RUNS/$name/weights.safetensors ]]; then
        echo "== $name: done ($RUNS/$name/weights.safetensors)"
    else
        "${GENERATE:-generate}" "$dir" "$views" "$scenes"
        echo "== $name: $*"
        "$@"
    fi
    if [[ ${STOP_AFTER:-} == "$name" ]]; then
        exit 0
    fi
}

# points_on_users NAME VIEWS NORMALS INIT [SCENES]: the point net's run on users' captures (issue 27): 4 epochs (1e-4,
# halved after 2) on the first SCENES (1000) VIEWS-view scenes of generate_users in DATA/usersVIEWS, on the features
# of the normal net NORMALS, from the point net INIT; two DDP processes; --out RUNS/NAME.
points_on_users() {
    local name=$1 views=$2 normals=$3 init=$4 scenes=${5:-1000}
    GENERATE=generate_users step "$name" "$DATA/users$views" "$views" "$scenes" \
        "${DDP[@]}" train-points --data "$DATA/users$views" --normals "$normals" --preset cpu \
        --epochs 4 --lr 1e-4 --lr-halve-epochs 2 --init "$init" --max-scenes "$scenes" --out "$RUNS/$name"
}

# reuse_features FROM TO: before run TO starts, hard-link run FROM's point-feature cache into it, as the
# provenance did. A cached scene depends only on the normal weights, the scene and the seed, and train-points
# refuses a cache made with other normal weights (features/source.json); scenes missing from it are made.
reuse_features() {
    local from=$RUNS/$1/features to=$RUNS/$2/features
    if [[ -e $to || -f $RUNS/$2/weights.safetensors ]]; then
        return 0
    fi
    mkdir -p "$RUNS/$2"
    rm -rf "$to.partial"
    cp -al "$from" "$to.partial"
    mv "$to.partial" "$to"
}

# install_weights RUN NAME: copy RUNS/RUN/weights.safetensors to WEIGHTS/NAME.safetensors, and its weights.json
# to WEIGHTS/NAME.json with the shipped file's "provenance" (the chain this recipe re-ran), "recipe" and the
# date of the rebuild added. Prints both SHA-256s: a rebuild follows the same network config and schedule, but
# bit-identical weights are not guaranteed (torch version, CPU).
install_weights() {
    local run=$RUNS/$1 dst=$WEIGHTS/$2
    echo "== install: $run/weights.safetensors -> $dst.safetensors"
    if [[ -f $dst.safetensors ]]; then
        echo "   before: $(sha256sum "$dst.safetensors")"
    fi
    cp "$run/weights.safetensors" "$dst.safetensors.tmp"
    "$VENV/bin/python" - "$run/weights.json" "$dst.json" "recipes/$2.sh" <<'PY'
import datetime, json, sys

run_json, shipped_json, recipe = sys.argv[1:]
meta = json.load(open(run_json))
try:
    shipped = json.load(open(shipped_json))
except FileNotFoundError:
    shipped = {}
if "provenance" in shipped:
    meta["provenance"] = shipped["provenance"]
meta["recipe"] = recipe
meta["rebuilt"] = datetime.date.today().isoformat()
with open(shipped_json + ".tmp", "w") as f:
    json.dump(meta, f, indent=2)
    f.write("\n")
PY
    mv "$dst.safetensors.tmp" "$dst.safetensors"
    mv "$dst.json.tmp" "$dst.json"
    echo "   after:  $(sha256sum "$dst.safetensors")"
}
