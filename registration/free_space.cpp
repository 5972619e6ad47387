#include "registration/free_space.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>

#include <Eigen/Geometry>

#include "core/kdtree.h"

namespace station {

struct FreeSpace::Sight {
  Vec3d origin = Vec3d::Zero();
  std::unique_ptr<PointIndex> directions;  // unit vectors from the sensor
  std::vector<float> ranges;
  double angle_spacing = 0;  // radians
};

FreeSpace::FreeSpace()
    : lo_(Vec3d::Constant(std::numeric_limits<double>::infinity())),
      hi_(Vec3d::Constant(-std::numeric_limits<double>::infinity())) {}
FreeSpace::~FreeSpace() = default;
FreeSpace::FreeSpace(FreeSpace&&) noexcept = default;
FreeSpace& FreeSpace::operator=(FreeSpace&&) noexcept = default;

bool FreeSpace::empty() const { return sights_.empty(); }

int FreeSpace::add(const std::vector<Vec3f>& points, const Eigen::Matrix4d& pose) {
  Sight sight;
  sight.origin = pose.block<3, 1>(0, 3);
  std::vector<Vec3f> us;
  for (const Vec3f& q : points) {
    const Vec3d d = pose.block<3, 3>(0, 0) * q.cast<double>();
    const double r = d.norm();
    if (!(r > 0) || !std::isfinite(r)) continue;
    us.push_back((d / r).cast<float>());
    sight.ranges.push_back(float(r));
    lo_ = lo_.cwiseMin(sight.origin + d);
    hi_ = hi_.cwiseMax(sight.origin + d);
  }
  if (us.size() < 2) return -1;
  // The median angle from a point to its nearest neighbour, over up to 256 of them.
  std::vector<Vec3f> sample;
  for (std::size_t k = 0, stride = std::max<std::size_t>(1, us.size() / 256); k < us.size(); k += stride)
    sample.push_back(us[k]);
  sight.directions = std::make_unique<PointIndex>(std::move(us));
  std::vector<double> gaps;
  for (const Vec3f& u : sample) {
    const auto nn = sight.directions->knn(u, 2);
    if (nn.size() == 2) gaps.push_back(double(nn[1].second));
  }
  if (!gaps.empty()) {
    std::nth_element(gaps.begin(), gaps.begin() + std::ptrdiff_t(gaps.size() / 2), gaps.end());
    sight.angle_spacing = gaps[gaps.size() / 2];
  }
  sights_.push_back(std::move(sight));
  return int(sights_.size()) - 1;
}

double FreeSpace::seen_through(const std::vector<Vec3f>& points, const Eigen::Matrix4d& X, double margin,
                               double spacing, double grow, int skip) const {
  const std::size_t stride = std::max<std::size_t>(1, points.size() / 1000);
  const Vec3d lo = lo_ - Vec3d::Constant(grow), hi = hi_ + Vec3d::Constant(grow);
  std::size_t total = 0, seen = 0;
  for (std::size_t k = 0; k < points.size(); k += stride) {
    const Vec3d x = (X * points[k].cast<double>().homogeneous()).head<3>();
    if (!x.allFinite() || (x.array() < lo.array()).any() || (x.array() > hi.array()).any()) continue;
    ++total;
    for (std::size_t si = 0; si < sights_.size(); ++si) {
      if (int(si) == skip) continue;
      const Sight& sight = sights_[si];
      const Vec3d d = x - sight.origin;
      const double r = d.norm();
      if (!(r > margin)) continue;
      const double tolerance = 2 * std::max(spacing / r, sight.angle_spacing);
      const auto [j, dist] = sight.directions->nearest_within((d / r).cast<float>(), float(tolerance));
      if (j < 0 || !(double(sight.ranges[std::size_t(j)]) > r + margin)) continue;
      // Every sight point in the window beyond it too: at a silhouette, or on a
      // face the sight saw at a grazing angle, the nearest direction may hit the
      // far side while its neighbours in the window hit the point's own surface.
      const float far = float(r + margin);
      if (sight.directions->any_in_radius((d / r).cast<float>(), float(tolerance),
                                          [&](int i, float) { return sight.ranges[std::size_t(i)] <= far; }))
        continue;
      ++seen;
      break;
    }
  }
  return total ? double(seen) / double(total) : 0.0;
}

}  // namespace station
