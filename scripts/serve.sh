#!/usr/bin/env bash
# Set up, build, then serve the station page on http://127.0.0.1:8080/ (sessions
# in out/station). Options go to `station serve` (docs/serve.md), e.g. --port 9000.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build.sh
exec build/bin/station serve "$@"
