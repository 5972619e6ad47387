#pragma once
// Camera and turntable geometry shared by the drivers, capture, registration and
// the session format: pinhole intrinsics with lens distortion, the turntable axis,
// and the turntable prior (a view's pose from its table angle).
#include <Eigen/Core>
#include <array>

#include "core/geometry.h"

namespace station {

/// Pinhole intrinsics of a range or colour camera, in pixels, with Brown-Conrady
/// lens distortion in OpenCV's order and convention (k1, k2, p1, p2, k3): a ray
/// with normalised coordinates (x, y) = (X/Z, Y/Z) lands on pixel
/// (fx x_d + cx, fy y_d + cy), where (x_d, y_d) is (x, y) distorted.
struct Intrinsics {
  int width = 0, height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  std::array<double, 5> distortion{};  ///< k1, k2, p1, p2, k3; all zero = none
  bool valid() const { return width > 0 && height > 0 && fx > 0 && fy > 0; }
  bool distorted() const {
    for (double d : distortion)
      if (d != 0) return true;
    return false;
  }
};

/// Normalised undistorted ray (x, y) = (X/Z, Y/Z) of pixel (u, v): inverts the
/// distortion by fixed-point iteration (exact to ~1e-12 for ordinary lenses).
Eigen::Vector2d pixel_to_ray(const Intrinsics& k, double u, double v);
/// Pixel of the ray (x, y) = (X/Z, Y/Z), distortion applied.
Eigen::Vector2d ray_to_pixel(const Intrinsics& k, double x, double y);

/// Turntable rotation axis in the scanner frame (metres; direction unit length,
/// pointing up, from the table top towards the object; `point` lies on the table
/// top). Positive angles turn the table counter-clockwise seen from above
/// (right-handed about `direction`).
struct TurntableAxis {
  Vec3d point = Vec3d::Zero();
  Vec3d direction = -Vec3d::UnitY();
};

/// Rigid transform taking scanner-frame points into the turntable frame at
/// angle 0: origin at axis.point, z along axis.direction, x towards the scanner
/// (the scanner's origin projected onto the table plane). A view taken at table
/// angle a maps to the object frame with rotate_z(-a) * table_from_scanner.
Eigen::Matrix4d table_from_scanner(const TurntableAxis& axis);
/// The turntable prior: object frame <- scanner frame for a view at `angle_deg`.
Eigen::Matrix4d turntable_pose(const TurntableAxis& axis, double angle_deg);

}  // namespace station
