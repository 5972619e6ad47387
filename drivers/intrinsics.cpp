#include <cmath>

#include "drivers/scanner.h"

namespace station {

namespace {
Eigen::Vector2d distort(const std::array<double, 5>& d, double x, double y) {
  const double r2 = x * x + y * y;
  const double radial = 1 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]));
  return {x * radial + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x),
          y * radial + d[2] * (r2 + 2 * y * y) + 2 * d[3] * x * y};
}
}  // namespace

Eigen::Vector2d ray_to_pixel(const Intrinsics& k, double x, double y) {
  const Eigen::Vector2d p = k.distorted() ? distort(k.distortion, x, y) : Eigen::Vector2d(x, y);
  return {k.fx * p.x() + k.cx, k.fy * p.y() + k.cy};
}

Eigen::Vector2d pixel_to_ray(const Intrinsics& k, double u, double v) {
  const Eigen::Vector2d target((u - k.cx) / k.fx, (v - k.cy) / k.fy);
  if (!k.distorted()) return target;
  // Fixed point: x <- x + (target - distort(x)). Converges for the monotonic part
  // of any lens a calibration produces; stop early once below 1e-14.
  Eigen::Vector2d x = target;
  for (int it = 0; it < 50; ++it) {
    const Eigen::Vector2d step = target - distort(k.distortion, x.x(), x.y());
    x += step;
    if (step.squaredNorm() < 1e-28) break;
  }
  return x;
}

}  // namespace station
