// The turntable line most free poses share (registration/axis_consensus.h): a
// ring of views turned about one line, some of them moved onto a twin (half a
// turn about the object's own axis, a degree off the table's and 3 mm aside, as
// a registration without angles leaves a near-symmetric bottle): the views on the
// line are told from the twins, and the line and each view's turn recovered.
#include "registration/axis_consensus.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "registration/icp.h"

namespace station {
namespace {

constexpr double kDeg = M_PI / 180;

struct Ring {
  Vec3d point{0.02, -0.01, 0.3};
  Vec3d direction = Vec3d(0.05, 1, 0.1).normalized();
  std::vector<Eigen::Matrix4d> poses;
  std::vector<Vec3d> centres;
};

// `views` views `step` degrees apart about the ring's line, from one scanner
// pose; a little pose noise (0.02 deg, 0.05 mm).
Ring ring(int views, double step, unsigned seed = 1) {
  Ring r;
  Eigen::Matrix4d scanner = Eigen::Matrix4d::Identity();
  scanner.block<3, 3>(0, 0) = Eigen::AngleAxisd(0.3, Vec3d(1, 0.2, 0).normalized()).toRotationMatrix();
  scanner.block<3, 1>(0, 3) = Vec3d(0.01, 0.05, -0.1);
  std::mt19937 rng(seed);
  std::normal_distribution<double> n(0, 1);
  for (int k = 0; k < views; ++k) {
    Eigen::Matrix4d noise = Eigen::Matrix4d::Identity();
    noise.block<3, 3>(0, 0) = Eigen::AngleAxisd(0.02 * kDeg, Vec3d(n(rng), n(rng), n(rng)).normalized()).toRotationMatrix();
    noise.block<3, 1>(0, 3) = 5e-5 * Vec3d(n(rng), n(rng), n(rng));
    r.poses.push_back(noise * turn_about_line(r.point, r.direction, k * step * kDeg) * scanner);
    r.centres.push_back(Vec3d(0.01, 0.0, 0.45));  // the object, 0.45 m before the scanner
  }
  return r;
}

TEST(AxisConsensus, TwinsOffTheLineAreToldFromTheViewsOnIt) {
  Ring r = ring(12, 30);
  // The object's own axis: a degree off the table's, 3 mm aside.
  const Vec3d own = Eigen::AngleAxisd(1.0 * kDeg, r.direction.unitOrthogonal()) * r.direction;
  const Eigen::Matrix4d twin = turn_about_line(r.point + 0.003 * r.direction.unitOrthogonal(), own, M_PI);
  const std::vector<int> twins = {1, 3, 7, 8};
  for (int k : twins) r.poses[std::size_t(k)] = twin * r.poses[std::size_t(k)];
  // Bounds as the registration gives them: 0.4 of 0.75 deg and of 1 % of a 0.2 m object.
  const AxisConsensus c = turntable_consensus(r.poses, r.centres, 0.3, 0.0008);
  ASSERT_TRUE(c.found);
  EXPECT_EQ(c.inliers, (std::vector<int>{0, 2, 4, 5, 6, 9, 10, 11}));
  for (int k : twins) EXPECT_GT(c.deviation_deg[std::size_t(k)], 0.3) << k;
  EXPECT_LT(std::acos(std::min(1.0, std::abs(c.direction.dot(r.direction)))) / kDeg, 0.1);
  // The found point lies on the true line.
  const Vec3d off = c.point - r.point;
  EXPECT_LT((off - off.dot(r.direction) * r.direction).norm(), 1e-3);
  // Each inlier's turn from the reference is its place in the ring (the line's sign is free).
  const double sign = c.direction.dot(r.direction) > 0 ? 1 : -1;
  for (int k : c.inliers) {
    const double want = (k - c.reference) * 30.0;
    EXPECT_LT(std::abs(std::remainder(sign * c.turn[std::size_t(k)] / kDeg - want, 360.0)), 0.2) << k;
  }
}

// Views stacked on a few turns of another line (a cube's chain collapsing its views
// onto two of its faces) outnumber the ring's spread views, but a turntable takes
// each view at its own angle: the line with more distinct turns wins.
TEST(AxisConsensus, ViewsStackedOnFewTurnsLoseToASpreadRing) {
  Ring r = ring(6, 60, 3);
  const Ring other = ring(1, 0, 4);
  const Vec3d level = r.direction.unitOrthogonal();
  for (int k = 0; k < 7; ++k) {
    const double turn = (k < 4 ? 0.0 : 90.0) * kDeg;
    // A quarter turn about a line parallel to the table's, then 0 or 90 deg about a
    // level line: off the ring's line, on two turns of another.
    r.poses.push_back(turn_about_line(r.point, level, turn) *
                      turn_about_line(r.point + Vec3d(0.01, 0, 0), r.direction, M_PI / 2) * other.poses[0]);
    // (The stacked views differ by pose noise only.)
    r.poses.back().block<3, 1>(0, 3) += 2e-5 * Vec3d(k, -k, 0.5 * k);
    r.centres.push_back(other.centres[0]);
  }
  const AxisConsensus c = turntable_consensus(r.poses, r.centres, 0.3, 0.0008);
  ASSERT_TRUE(c.found);
  EXPECT_EQ(c.distinct_turns, 6);
  EXPECT_EQ(c.inliers, (std::vector<int>{0, 1, 2, 3, 4, 5}));
  EXPECT_LT(std::acos(std::min(1.0, std::abs(c.direction.dot(r.direction)))) / kDeg, 0.1);
}

TEST(AxisConsensus, ARingWithoutTwinsKeepsEveryView) {
  const Ring r = ring(8, 45, 2);
  const AxisConsensus c = turntable_consensus(r.poses, r.centres, 0.3, 0.0008);
  ASSERT_TRUE(c.found);
  EXPECT_EQ(c.inliers.size(), 8u);
}

TEST(AxisConsensus, TooFewViewsOrNonFinitePosesFindNone) {
  Ring r = ring(3, 30);
  r.poses[1](0, 0) = std::numeric_limits<double>::quiet_NaN();
  const AxisConsensus c = turntable_consensus(r.poses, r.centres, 0.3, 0.0008);
  EXPECT_FALSE(c.found);
  EXPECT_TRUE(std::isinf(c.deviation_deg[1]));
  // Views that barely turn give no line.
  const Ring close = ring(5, 2);
  EXPECT_FALSE(turntable_consensus(close.poses, close.centres, 0.3, 0.0008).found);
}

}  // namespace
}  // namespace station

namespace station {
namespace {

// A calibrated turntable's line (scanner frame) put into the poses' frame by one
// view's pose: every view of the ring turns about it from that view.
TEST(AxisConsensus, ACalibratedAxisIsTheLineEveryViewTurnsAbout) {
  // Poses object <- scanner of views turned about the scanner-frame line (p, d):
  // P_k = P_0 Rot_scanner(-phi_k) about (p, d).
  const Vec3d p(0.01, 0.03, 0.45), d = Vec3d(0.02, -0.94, -0.34).normalized();
  Eigen::Matrix4d P0 = Eigen::Matrix4d::Identity();
  P0.block<3, 3>(0, 0) = Eigen::AngleAxisd(0.4, Vec3d(0.3, 1, -0.2).normalized()).toRotationMatrix();
  P0.block<3, 1>(0, 3) = Vec3d(0.1, -0.2, 0.05);
  std::vector<Eigen::Matrix4d> poses;
  for (int k = 0; k < 6; ++k) poses.push_back(P0 * turn_about_line(p, d, -k * 60 * kDeg));
  const AxisConsensus c = calibrated_consensus(p, d, poses, 2);
  ASSERT_TRUE(c.found);
  EXPECT_EQ(c.reference, 2);
  EXPECT_EQ(c.inliers, std::vector<int>{2});
  EXPECT_EQ(c.distinct_turns, 1);
  // Each view is the reference turned about the line: P_k = Rot_line(phi) P_2.
  for (int k = 0; k < 6; ++k) {
    const Eigen::Matrix4d M = poses[std::size_t(k)] * rigid_inverse(poses[2]);
    const double phi = turn_about_axis(M.block<3, 3>(0, 0), c.direction);
    EXPECT_LT((turn_about_line(c.point, c.direction, phi) - M).norm(), 1e-9) << k;
    EXPECT_NEAR(std::abs(std::remainder(phi / kDeg, 360.0)), std::abs(std::remainder((k - 2) * 60.0, 360.0)), 1e-6) << k;
  }
  EXPECT_FALSE(calibrated_consensus(p, d, poses, 6).found);
  EXPECT_FALSE(calibrated_consensus(p, Vec3d::Zero(), poses, 0).found);
  poses[1](0, 0) = std::nan("");
  EXPECT_FALSE(calibrated_consensus(p, d, poses, 1).found);
}

}  // namespace
}  // namespace station
