// Turntable axis fitting (capture/axis_calibration.h).
#include "registration/axis_calibration.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <random>

#include "capture/capture.h"

namespace station {
namespace {

TurntableAxis tilted_axis() {
  TurntableAxis a;
  a.point = Vec3d(0.02, 0.1, 0.5);
  a.direction = Vec3d(0.1, -1, 0.05).normalized();
  return a;
}

double line_distance(const TurntableAxis& a, const Vec3d& p) {
  const Vec3d d = a.direction.normalized();
  const Vec3d v = p - a.point;
  return (v - v.dot(d) * d).norm();
}

TEST(AxisCalibration, RecoversAKnownAxisFromNoisyNeighbourMotions) {
  const TurntableAxis truth = tilted_axis();
  std::mt19937 rng(7);
  std::normal_distribution<double> g(0, 0.02 * M_PI / 180);  // 0.02 degree pose noise
  std::normal_distribution<double> gt(0, 0.0001);
  std::vector<AxisMotion> motions;
  for (int k = 0; k < 12; ++k) {
    const double a = 30 * k, b = 30 * (k + 1);
    AxisMotion m;
    m.transform = turntable_pose(truth, a).inverse() * turntable_pose(truth, b);
    Eigen::Matrix4d noise = Eigen::Matrix4d::Identity();
    noise.block<3, 3>(0, 0) = (Eigen::AngleAxisd(g(rng), Vec3d::UnitX()) * Eigen::AngleAxisd(g(rng), Vec3d::UnitY()) *
                               Eigen::AngleAxisd(g(rng), Vec3d::UnitZ())).toRotationMatrix();
    noise.block<3, 1>(0, 3) = Vec3d(gt(rng), gt(rng), gt(rng));
    m.transform = noise * m.transform;
    m.angle_deg = b - a;
    motions.push_back(m);
  }
  const AxisFitResult r = fit_turntable_axis(motions);
  ASSERT_TRUE(r.ok) << r.message;
  EXPECT_LT(std::acos(std::min(1.0, r.axis.direction.dot(truth.direction))) * 180 / M_PI, 0.05);
  EXPECT_LT(line_distance(truth, r.axis.point), 0.001);
  EXPECT_LT(r.rms_angle_deg, 0.1);
  EXPECT_LT(r.rms_tilt_deg, 0.1);
  // The returned point is the foot of the perpendicular from the scanner origin.
  EXPECT_NEAR(r.axis.point.dot(r.axis.direction), 0.0, 1e-6);

  // A wrong commanded angle shows in that motion's residual, not the others'.
  motions[3].angle_deg += 3;
  const AxisFitResult w = fit_turntable_axis(motions);
  EXPECT_NEAR(w.residuals[3].angle_deg, -3, 0.1);
  EXPECT_LT(std::abs(w.residuals[4].angle_deg), 0.1);
}

TEST(AxisCalibration, CalibratesFromRegisteredPosesAndRejectsTooLittleMotion) {
  const TurntableAxis truth = tilted_axis();
  std::vector<Eigen::Matrix4d> poses;
  std::vector<double> angles;
  for (int k = 0; k < 8; ++k) {
    angles.push_back(45 * k + 10);
    // Registered poses live in any object frame: a fixed transform on the left.
    poses.push_back(Eigen::Affine3d(Eigen::AngleAxisd(0.3, Vec3d::UnitZ())).matrix() *
                    turntable_pose(truth, angles.back()));
  }
  poses[2](0, 0) = std::nan("");  // a failed view is skipped
  AxisFitParams fp;
  fp.point_near = truth.point;
  const AxisFitResult r = calibrate_axis(poses, angles, fp);
  ASSERT_TRUE(r.ok) << r.message;
  EXPECT_LT((r.axis.direction - truth.direction).norm(), 1e-9);
  EXPECT_LT((r.axis.point - truth.point).norm(), 1e-9);
  EXPECT_LT(r.rms_translation, 1e-9);
  EXPECT_FALSE(r.residuals[2].used);

  EXPECT_FALSE(calibrate_axis({Eigen::Matrix4d::Identity(), Eigen::Matrix4d::Identity()}, {0, 1}).ok);
  EXPECT_FALSE(calibrate_axis({Eigen::Matrix4d::Identity()}, {0, 1}).ok);
}

}  // namespace
}  // namespace station
