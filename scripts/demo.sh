#!/usr/bin/env bash
# The main job: set up, build, then scan the bundled YCB mustard bottle on the
# simulated turntable (12 views) into out/demo/, consolidate the merged cloud
# (WLOP), reconstruct a coloured mesh (MPU + marching cubes) and measure it
# against the original textured mesh.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build.sh
rm -rf out/demo
build/bin/station scan --config config/default.yaml -o out/demo
build/bin/station consolidate out/demo/merged.ply -o out/demo/consolidated.ply --points 20000
build/bin/station reconstruct out/demo/consolidated.ply -o out/demo/mesh.ply --resolution 128
build/bin/station eval out/demo/mesh.ply data/mustard_bottle/textured.obj
echo "session: out/demo/session.yaml  merged cloud: out/demo/merged.ply  coloured mesh: out/demo/mesh.ply"
