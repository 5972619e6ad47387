#!/usr/bin/env bash
# The main job: set up, build, then scan the bundled YCB mustard bottle on the
# simulated turntable (12 views) into out/demo/ and measure the turntable-merged
# cloud against the original mesh.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build.sh
rm -rf out/demo
build/bin/station scan --config config/default.yaml -o out/demo
build/bin/station eval out/demo/merged.ply data/mustard_bottle/textured.obj
echo "session: out/demo/session.yaml   coloured cloud: out/demo/merged.ply"
