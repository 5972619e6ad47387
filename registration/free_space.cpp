#include "registration/free_space.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Geometry>

#include "core/kdtree.h"

namespace station {

struct FreeSpace::Sight {
  Vec3d origin = Vec3d::Zero();
  std::unique_ptr<PointIndex> directions;  // unit vectors from the sensor
  std::vector<float> ranges;
};

FreeSpace::FreeSpace() = default;
FreeSpace::~FreeSpace() = default;
FreeSpace::FreeSpace(FreeSpace&&) noexcept = default;
FreeSpace& FreeSpace::operator=(FreeSpace&&) noexcept = default;

void FreeSpace::add(const std::vector<Vec3f>& points, const Eigen::Matrix4d& pose) {
  Sight sight;
  sight.origin = pose.block<3, 1>(0, 3);
  std::vector<Vec3f> us;
  for (const Vec3f& q : points) {
    const Vec3d d = pose.block<3, 3>(0, 0) * q.cast<double>();
    const double r = d.norm();
    if (!(r > 0) || !std::isfinite(r)) continue;
    us.push_back((d / r).cast<float>());
    sight.ranges.push_back(float(r));
  }
  if (us.empty()) return;
  sight.directions = std::make_unique<PointIndex>(std::move(us));
  sights_.push_back(std::move(sight));
}

double FreeSpace::seen_through(const std::vector<Vec3f>& points, const Eigen::Matrix4d& X, double margin,
                               double spacing) const {
  const std::size_t stride = std::max<std::size_t>(1, points.size() / 1000);
  std::size_t total = 0, seen = 0;
  for (std::size_t k = 0; k < points.size(); k += stride) {
    const Vec3d x = (X * points[k].cast<double>().homogeneous()).head<3>();
    if (!x.allFinite()) continue;
    ++total;
    for (const Sight& sight : sights_) {
      const Vec3d d = x - sight.origin;
      const double r = d.norm();
      if (!(r > margin)) continue;
      const auto [j, dist] = sight.directions->nearest_within((d / r).cast<float>(), float(2 * spacing / r));
      if (j >= 0 && double(sight.ranges[std::size_t(j)]) > r + margin) {
        ++seen;
        break;
      }
    }
  }
  return total ? double(seen) / double(total) : 0.0;
}

}  // namespace station
