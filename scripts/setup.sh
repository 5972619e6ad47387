#!/usr/bin/env bash
# Installs the Debian 12 packages the station needs, non-interactively and
# idempotently: packages already present are skipped without touching apt.
# Usage: scripts/setup.sh [--bench]   (--bench adds the anchor libraries for bench/)
set -euo pipefail

pkgs=(cmake g++ make pkg-config ccache
      libeigen3-dev libnanoflann-dev libflann-dev
      libpcl-dev libopencv-dev libusb-1.0-0-dev linux-libc-dev
      libyaml-cpp-dev libcli11-dev libtbb-dev libgtest-dev
      umockdev   # umockdev: V4L2 driver tests through the real system calls (umockdev-wrapper)
      libfreenect-dev   # Kinect v1 driver; its libfreenect0.5 ships fakenect (replay tests)
      libopenni2-dev   # OpenNI2 depth cameras (Xtion, Carmine, Orbbec) driver
      libcpp-httplib-dev nlohmann-json3-dev libjs-three   # station serve: HTTP server, JSON API, three.js for its page
      libopenmpi-dev openmpi-bin)   # blocks over MPI ranks (station run --blocks under mpirun)
if [[ "${1:-}" == "--bench" ]]; then
  # Anchors of bench/: Open3D 0.16 (C++: ICP, Poisson), Embree 3 (Open3D's ray
  # caster, driven directly), CGAL 5.5 (WLOP), VTK 9 (flying edges); PCL
  # (GICP) is in the base list already.
  pkgs+=(libopen3d-dev libembree-dev libcgal-dev libvtk9-dev)
fi

missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]} == 0)); then
  echo "setup: all ${#pkgs[@]} packages present"
  exit 0
fi

SUDO=""
if [[ $(id -u) -ne 0 ]]; then SUDO="sudo"; fi
echo "setup: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
echo "setup: done"
