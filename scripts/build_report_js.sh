#!/usr/bin/env bash
# Rebuild lookingglass/report/static/three-bundle.min.js (three.js + OrbitControls + GLTFLoader,
# the only JavaScript report.html embeds) from the versions pinned in scripts/report_js/package.json
# and package-lock.json. Needs node and npm (the npm registry) at build time only: report.html
# embeds the bundle and never touches the network.
set -euo pipefail
cd "$(dirname "$0")/report_js"
npm ci --no-audit --no-fund
static=../../lookingglass/report/static
version=$(node -p "require('./node_modules/three/package.json').version")
./node_modules/.bin/esbuild entry.js --bundle --minify --format=iife --global-name=LG3 \
    --target=es2020 --legal-comments=none \
    --banner:js="/* three.js ${version} (MIT, see LICENSE-three.txt) with OrbitControls and GLTFLoader, bundled by scripts/build_report_js.sh */" \
    --outfile="$static/three-bundle.min.js"
cp node_modules/three/LICENSE "$static/LICENSE-three.txt"
ls -l "$static"
