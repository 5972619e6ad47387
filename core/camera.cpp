#include "core/camera.h"

#include <cmath>

#include <Eigen/Geometry>

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

Eigen::Matrix4d table_from_scanner(const TurntableAxis& axis) {
  const Vec3d z = axis.direction.normalized();
  // The scanner sits at the origin of its own frame.
  Vec3d x = -axis.point;
  x -= x.dot(z) * z;
  if (x.norm() < 1e-9) {  // scanner on the axis (looking straight down): any x will do
    x = z.unitOrthogonal();
  }
  x.normalize();
  const Vec3d y = z.cross(x);
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.block<1, 3>(0, 0) = x.transpose();
  T.block<1, 3>(1, 0) = y.transpose();
  T.block<1, 3>(2, 0) = z.transpose();
  T.block<3, 1>(0, 3) = -(T.block<3, 3>(0, 0) * axis.point);
  return T;
}

Eigen::Matrix4d turntable_pose(const TurntableAxis& axis, double angle_deg) {
  Eigen::Matrix4d R = Eigen::Matrix4d::Identity();
  R.block<3, 3>(0, 0) =
      Eigen::AngleAxisd(-angle_deg * M_PI / 180.0, Vec3d::UnitZ()).toRotationMatrix();
  return R * table_from_scanner(axis);
}

}  // namespace station
