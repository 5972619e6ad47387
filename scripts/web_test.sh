#!/usr/bin/env bash
# The station page in a real browser (tests/web/station_page.mjs): installs
# Debian's Chromium, and node/npm when missing, then playwright-core from npm
# (tests/web/package-lock.json), and runs the test against build/bin/station.
# When Chromium cannot start the test fails; it never skips.
# Usage: scripts/web_test.sh [--screenshot docs/serve.png]
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
if [[ $(id -u) -ne 0 ]]; then SUDO="sudo"; fi
need=()
command -v chromium >/dev/null || need+=(chromium)
command -v node >/dev/null || need+=(nodejs)
command -v npm >/dev/null || need+=(npm)
if ((${#need[@]})); then
  echo "web_test: installing ${need[*]}"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi
if [[ ! -x build/bin/station ]]; then scripts/build.sh; fi
(cd tests/web && npm ci --no-audit --no-fund --loglevel=error)
if [[ "${1:-}" == "--screenshot" ]]; then export STATION_WEB_SCREENSHOT="$(realpath -m "${2:?--screenshot FILE}")"; fi
node tests/web/station_page.mjs
