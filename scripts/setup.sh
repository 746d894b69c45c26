#!/usr/bin/env bash
# Create .venv beside this repository and install lookingglass with its test dependencies.
# torch is pinned first so pip takes the CPU build (an unpinned torch pulls a multi-GB CUDA build);
# pyproject.toml accepts any compatible torch if you install your own (e.g. a CUDA build) first.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
quiet_pip() { .venv/bin/python -m pip install -q "$@" 2>&1 | { grep -v "^WARNING: Location" || true; }; }
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -c "import torch" 2>/dev/null || quiet_pip "torch==2.13.0"
quiet_pip -e ".[test]"
.venv/bin/python -c "import lookingglass, torch, mitsuba; print('lookingglass', lookingglass.__version__, '| torch', torch.__version__)"
