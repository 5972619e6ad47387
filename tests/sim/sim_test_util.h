#pragma once
// Helpers shared by the sim tests: back-projection and a registry with the sim devices.
#include <Eigen/Geometry>
#include <string>
#include <vector>

#include "drivers/registry.h"
#include "drivers/scanner.h"
#include "sim/sim.h"

namespace station::test {

/// One valid depth pixel back-projected (scanner frame) with its pixel index.
struct Sample {
  Vec3d p;
  int pixel;
};

inline std::vector<Sample> back_project(const Frame& f) {
  std::vector<Sample> out;
  const Intrinsics& k = f.intrinsics;
  for (int v = 0; v < k.height; ++v)
    for (int u = 0; u < k.width; ++u) {
      const float z = f.depth[std::size_t(v) * k.width + u];
      if (z <= 0) continue;
      out.push_back({Vec3d((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z), v * k.width + u});
    }
  return out;
}

inline Vec3d apply(const Eigen::Matrix4d& T, const Vec3d& p) {
  return T.topLeftCorner<3, 3>() * p + T.topRightCorner<3, 1>();
}

inline DeviceRegistry sim_registry() {
  DeviceRegistry r;
  register_sim_devices(r);
  return r;
}

}  // namespace station::test
