#!/usr/bin/env bash
# Installs the anchor libraries (scripts/setup.sh --bench), builds station_bench
# in ./build-bench (Release, tests off) and runs it: our hot paths against
# Embree/Open3D/PCL in one process, one table (docs/benchmarks.md).
# Extra args go to station_bench (--threads N, --reps N, --generate, --only GROUP).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh --bench
cmake -S . -B build-bench -DCMAKE_BUILD_TYPE=Release \
  -DSTATION_BUILD_BENCH=ON -DSTATION_BUILD_TESTS=OFF >/dev/null
cmake --build build-bench -j"$(nproc)" --target station_bench station >/dev/null  # station: the blocks group runs it
# Open3D's OpenMP threads busy-wait by default and then fight ours for the
# cores (Poisson 10x slower under load: docs/benchmarks.md); libgomp reads this
# at load time, so it is set here rather than in main().
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-passive}"
# glibc backs large blocks with transparent huge pages only when asked at start-up;
# the station binary asks for it itself (station/main.cpp, docs/run.md "Huge
# pages"), station_bench runs both sides in one process, so it is set here for both.
export GLIBC_TUNABLES="${GLIBC_TUNABLES:-glibc.malloc.hugetlb=1}"
build-bench/bin/station_bench "$@"
