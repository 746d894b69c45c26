#!/usr/bin/env bash
# Every torch stage on a CUDA GPU, on small generated data: the check to run on a machine with a
# GPU (CI has none). Usage: bash scripts/gpu_smoke.sh [WORK_DIR]   (PY=python3 to pick the interpreter)
# Exits non-zero at the first failing step; prints what each step measured.
set -euo pipefail
PY=${PY:-python3}
W=${1:-$(mktemp -d)}
LG="$PY -m lookingglass.cli"
$PY - <<'PYEOF'
import torch
assert torch.cuda.is_available(), "no CUDA device"
print("GPU:", torch.cuda.get_device_name(), "| torch", torch.__version__)
PYEOF
$LG generate --out "$W/data" --scenes 4 --split train --quiet
$LG generate --out "$W/data" --scenes 2 --split test --quiet
$LG train-normals --data "$W/data" --out "$W/normals" --epochs 1 --device cuda --quiet
$LG train-points --data "$W/data" --normals "$W/normals/weights.safetensors" --out "$W/points" --epochs 1 \
    --device cuda --quiet
tail -n 1 "$W/normals/metrics.jsonl" "$W/points/metrics.jsonl"
$LG eval-normals --data "$W/data" --weights "wr+cv=lookingglass/weights/normals_10views.safetensors" \
    --latent-iterations 5 --device cuda --quiet
$LG eval-shapes --data "$W/data" --strategies RE --latent-iterations 5 --surface-points 8192 --device cuda --quiet
$LG demo --out "$W/demo" --device cuda --quiet
$PY - "$W/demo" <<'PYEOF'
import json, pathlib, sys
rep = json.loads(next(pathlib.Path(sys.argv[1]).rglob("report.json")).read_text())
print("demo report: device", rep["device"], "| stages", rep["stages_run"], "| total", rep["total_seconds"], "s",
      "| GPU peak", rep.get("gpu_peak_memory_mb"), "MB")
assert rep["device"].startswith("cuda"), "reconstruct did not run on the GPU"
PYEOF
echo "gpu smoke: all steps passed ($W)"
