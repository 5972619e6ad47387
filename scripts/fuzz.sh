#!/usr/bin/env bash
# Builds the libFuzzer targets (clang only) and runs each for SECONDS (default
# 15) from the test fixtures, failing on any crash, leak, UB, time-out or huge
# allocation. Usage: scripts/fuzz.sh [SECONDS]
set -euo pipefail
cd "$(dirname "$0")/.."
secs="${1:-15}"
if ! command -v clang++ >/dev/null 2>&1; then
  echo "fuzz: clang++ not installed; skipping the fuzz smoke run"
  exit 0
fi
CC=clang CXX=clang++ cmake -S . -B build-fuzz -DCMAKE_BUILD_TYPE=Release \
  -DSTATION_BUILD_FUZZERS=ON -DSTATION_BUILD_TESTS=OFF >/dev/null
cmake --build build-fuzz -j"$(nproc)" --target fuzzers >/dev/null
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
for f in ply pcd obj off manifest; do
  bin="build-fuzz/fuzz/${f}_fuzzer"
  [[ -x "$bin" ]] || { echo "fuzz: $bin missing"; exit 1; }
  mkdir -p "$work/$f"
  seeds=tests/data/io
  [[ $f == manifest ]] && seeds=fuzz/seeds/manifest
  if ! (cd "$work/$f" && "$OLDPWD/$bin" "$work/$f" "$OLDPWD/$seeds" -dict="$OLDPWD/fuzz/$f.dict" \
          -max_total_time="$secs" -rss_limit_mb=2048 -malloc_limit_mb=512 -timeout=5 \
          -print_final_stats=1 >"$work/$f.log" 2>&1); then
    tail -40 "$work/$f.log"
    echo "fuzz: ${f}_fuzzer found a problem (log above)"
    exit 1
  fi
  echo "fuzz: ${f}_fuzzer ok, $(grep -m1 -o 'stat::number_of_executed_units: *[0-9]*' "$work/$f.log" | grep -o '[0-9]*$') runs in ${secs}s"
done
