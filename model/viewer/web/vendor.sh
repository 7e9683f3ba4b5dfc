#!/usr/bin/env bash
# Refreshes the browser viewer's vendored renderer from npm: three.js and Spark (World Labs'
# Gaussian splatting renderer for three.js), both MIT. Run by hand after changing the versions
# below; it rewrites vendor/ and vendor/SHA256SUMS, which `.ci/run` checks (`sha256sum -c`). The
# files are embedded in the `chatsplat` binary (model/viewer/src/assets.rs): the page needs no
# network.
set -euo pipefail
THREE=0.180.0
SPARK=2.2.0
here="$(cd "$(dirname "$0")" && pwd)"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
cd "$tmp"
npm init -y >/dev/null
npm install --no-audit --no-fund --ignore-scripts "three@$THREE" "@sparkjsdev/spark@$SPARK" >/dev/null
out="$here/vendor"
rm -rf "$out"
mkdir -p "$out"
cp node_modules/three/build/three.module.min.js node_modules/three/build/three.core.min.js "$out/"
# Spark imports three's full-screen-quad pass from the examples folder
cp node_modules/three/examples/jsm/postprocessing/Pass.js "$out/three-Pass.js"
cp node_modules/three/LICENSE "$out/LICENSE-three"
cp node_modules/@sparkjsdev/spark/dist/spark.module.min.js "$out/"
cp node_modules/@sparkjsdev/spark/LICENSE "$out/LICENSE-spark"
printf 'three %s\n@sparkjsdev/spark %s\n' "$THREE" "$SPARK" > "$out/VERSIONS"
(cd "$out" && sha256sum three.module.min.js three.core.min.js three-Pass.js spark.module.min.js VERSIONS > SHA256SUMS)
cat "$out/SHA256SUMS"
