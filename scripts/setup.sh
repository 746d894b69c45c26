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
# Headless Chromium for the browser test of report.html (tests/test_report.py; skipped without it)
# and demo's summary.png: Debian's package, installed when apt-get can be run (as root or by sudo).
if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1 \
        && command -v apt-get >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ]; then SUDO=""; elif sudo -n true 2>/dev/null; then SUDO="sudo -n"; else SUDO=none; fi
    if [ "$SUDO" != none ]; then
        { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq --no-install-recommends chromium >/dev/null; } \
            || echo "could not install chromium: the report's browser test will be skipped"
    else
        echo "chromium is missing and apt-get needs root: the report's browser test will be skipped"
    fi
fi
.venv/bin/python -c "import lookingglass, torch, mitsuba, pycolmap; print('lookingglass', lookingglass.__version__, '| torch', torch.__version__, '| pycolmap', pycolmap.__version__)"
