#!/usr/bin/env bash
# The main job: set up, build, then scan the bundled YCB mustard bottle on the
# simulated turntable (12 views) into out/demo/session, run the whole job on it
# (station run: register, consolidate, MPU + colour, mesh, report) into
# out/demo/run, and measure the mesh against the original textured mesh.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build.sh
rm -rf out/demo
build/bin/station scan --config config/default.yaml -o out/demo/session
build/bin/station run out/demo/session -o out/demo/run
build/bin/station eval out/demo/run/mesh.ply data/mustard_bottle/textured.obj
echo "coloured mesh: out/demo/run/mesh.ply   report: out/demo/run/report.html   session: out/demo/session/"
