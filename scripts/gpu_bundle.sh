#!/usr/bin/env bash
# Pack what a bare GPU machine (Python 3.12 with torch, numpy, scipy, scikit-image, OpenCV, typer, rich;
# no network) lacks to run `lookingglass` from a checkout, into devdata/ (ignored by git, < 45 MB):
#   site.tar.xz     trimesh, embreex, rtree, manifold3d, OpenEXR and a pymeshlab cut down to the plugins
#                   lookingglass calls (its wheel is 106 MB, over what such a machine is sent),
#   syslibs.tar.xz  the system libraries pymeshlab loads that a CUDA image has no copy of (libGL, X11, ...),
#   env.sh          `source devdata/env.sh` there unpacks both and sets PYTHONPATH / LD_LIBRARY_PATH,
#   val/            one validation scene (its photos as Radiance .hdr, a quarter of the EXRs' size).
# Usage (here, then carry devdata/ over):  bash scripts/gpu_bundle.sh [VAL_DATA] [SCENE]
#   e.g. bash scripts/gpu_bundle.sh data/val480 duck; on the GPU machine:
#   source devdata/env.sh && python3 -m lookingglass.cli validate --data devdata/val --out /tmp/v --device cuda
set -euo pipefail
VAL=${1:-data/val480}
SCENE=${2:-duck}
PY=${PY:-.venv/bin/python}
OUT=devdata
grep -qx "/$OUT/" .git/info/exclude 2>/dev/null || echo "/$OUT/" >> .git/info/exclude
rm -rf "$OUT" && mkdir -p "$OUT"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# Wheels for the GPU machine's Python (3.12, x86-64), at the versions installed here.
ver() { "$PY" -c "import importlib.metadata as m; print(m.version('$1'))"; }
for pkg in trimesh embreex rtree manifold3d OpenEXR pymeshlab; do
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_35_x86_64 --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_24_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$tmp/whl" "$pkg==$(ver "$pkg")" 2>&1 | grep -v "^WARNING" || true
done
mkdir -p "$tmp/site"
for w in "$tmp"/whl/*.whl; do (cd "$tmp/site" && unzip -q -o "$w"); done
# pymeshlab's wheel keeps its package under *.data/purelib; keep the plugins lookingglass's filters live in.
mv "$tmp"/site/pymeshlab-*.data/purelib/pymeshlab "$tmp/site/" && rm -rf "$tmp"/site/pymeshlab-*.data
keep=" filter_clean filter_create filter_func filter_layer filter_measure filter_meshing filter_quality"
keep+=" filter_sampling filter_screened_poisson filter_select filter_unsharp io_base "
for f in "$tmp"/site/pymeshlab/lib/plugins/*.so; do
  n=$(basename "$f" .so); n=${n#lib}
  [[ "$keep" == *" $n "* ]] || rm "$f"
done
(cd "$tmp/site/pymeshlab" && rm -rf tests lib/libembree4* lib/libicu*.so.70 lib/lib3mf* lib/libxerces* lib/libIFX* \
  lib/libIDTF* lib/libE57* lib/libmpfr* lib/libgmp*)
tar cJf "$OUT/site.tar.xz" -C "$tmp/site" .

# System libraries pymeshlab's Qt and GL links need, from this machine (Debian 12, glibc 2.36: older than the
# CUDA image's, so they load there).
mkdir -p "$tmp/sys"
for l in libGL.so.1 libGLX.so.0 libGLdispatch.so.0 libOpenGL.so.0 libX11.so.6 libxcb.so.1 libXau.so.6 \
         libXdmcp.so.6 libbsd.so.0 libmd.so.0 libfontconfig.so.1 libfreetype.so.6 libexpat.so.1 libgmp.so.10 \
         libp11-kit.so.0 libgpg-error.so.0 libcom_err.so.2 libbrotlicommon.so.1 libbrotlidec.so.1 libffi.so.8 \
         libpng16.so.16; do
  cp -L "/lib/x86_64-linux-gnu/$l" "$tmp/sys/"
done
tar cJf "$OUT/syslibs.tar.xz" -C "$tmp/sys" .

cat > "$OUT/env.sh" <<'EOF'
# source devdata/env.sh (on the GPU machine, in the checkout's root)
mkdir -p /tmp/lg_site /tmp/lg_sys
[ -d /tmp/lg_site/pymeshlab ] || tar xJf devdata/site.tar.xz -C /tmp/lg_site
[ -e /tmp/lg_sys/libGL.so.1 ] || tar xJf devdata/syslibs.tar.xz -C /tmp/lg_sys
export PYTHONPATH=/tmp/lg_site:$PWD${PYTHONPATH:+:$PYTHONPATH}
export LD_LIBRARY_PATH=/tmp/lg_site/pymeshlab/lib:/tmp/lg_sys${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
export PYTHONUNBUFFERED=1
EOF

# One validation scene, photos as .hdr (linear, as the EXRs are).
mkdir -p "$OUT/val"
cp -r "$VAL/$SCENE" "$OUT/val/"
"$PY" - "$VAL" "$SCENE" "$OUT/val" <<'EOF'
import json, sys
from pathlib import Path
from lookingglass.capture.images import read_raw, write_image
src, scene, out = Path(sys.argv[1]), sys.argv[2], Path(sys.argv[3])
index = json.loads((src / "index.json").read_text())
index["shapes"] = {scene: index["shapes"][scene]}
(out / "index.json").write_text(json.dumps(index, indent=2))
folder = out / scene / "scene"
spec = json.loads((folder / "scene.json").read_text())
for view in spec["views"]:
    old = folder / view["image"]
    if old.suffix == ".exr":
        write_image(old.with_suffix(".hdr"), read_raw(old)[0])
        old.unlink()
        view["image"] = str(Path(view["image"]).with_suffix(".hdr"))
(folder / "scene.json").write_text(json.dumps(spec, indent=2))
EOF
du -sh "$OUT"/*
