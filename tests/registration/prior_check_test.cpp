// Views placed from their neighbours' angles (issue 26, more than one move;
// registration/prior_check.h): the turntable's screw motion between two registered
// views, taken to the fraction of the turn a failed view's angle is, and only from
// a pair that turns as its angles say, in size and in sense.
#include "registration/prior_check.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>

#include "registration/icp.h"

namespace station {
namespace {

// A view at table angle a: turned by -a about the vertical line through c.
Eigen::Matrix4d table_pose(double angle_deg, const Vec3d& c = Vec3d(0.1, 0.05, 0)) {
  Eigen::Matrix4d P = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d R = Eigen::AngleAxisd(-angle_deg * M_PI / 180, Vec3d::UnitZ()).toRotationMatrix();
  P.block<3, 3>(0, 0) = R;
  P.block<3, 1>(0, 3) = (Eigen::Matrix3d::Identity() - R) * c;
  return P;
}

SessionManifest six_views() {
  SessionManifest m;
  for (int i = 0; i < 6; ++i) {
    ViewRecord v;
    v.file = "view_" + std::to_string(i) + ".ply";
    v.angle_deg = 30.0 * i;
    m.views.push_back(v);
  }
  return m;
}

TEST(ScrewPower, HalfATurnTwiceIsTheTurn) {
  const Eigen::Matrix4d T = table_pose(70) * [] {
    Eigen::Matrix4d slide = Eigen::Matrix4d::Identity();
    slide(2, 3) = 0.01;  // along the axis
    return slide;
  }();
  const Eigen::Matrix4d H = screw_power(T, 0.5);
  EXPECT_LT((H * H - T).norm(), 1e-9);
  EXPECT_NEAR(rotation_angle_deg(H), 35.0, 1e-9);
  EXPECT_LT((screw_power(T, 0) - Eigen::Matrix4d::Identity()).norm(), 1e-12);
  EXPECT_LT((screw_power(T, 1) - T).norm(), 1e-9);
}

TEST(NeighboursAngles, PlaceAFailedViewOnTheTurntable) {
  const SessionManifest m = six_views();
  std::vector<Eigen::Matrix4d> poses;
  for (int i = 0; i < 6; ++i) poses.push_back(table_pose(30.0 * i));
  std::vector<bool> registered(6, true);
  registered[3] = false;
  const auto X = pose_from_neighbours_angles(poses, registered, m, 3, 1.0, 8.0, 0.3);
  ASSERT_TRUE(X.has_value());
  EXPECT_LT((*X - table_pose(90)).norm(), 1e-9);
}

// The object moved after view 2 by minus twice the step to view 4 (-120 deg): the
// pair 2-4 turns by its angles' 60 deg, but the wrong way. The pair beside it (1-2)
// tells the sense, so no pose is made from it (the other pairs turn by the wrong
// amount); before the sense was checked, view 3 was placed 60 deg off.
TEST(NeighboursAngles, APairThatTurnsTheWrongWayPlacesNothing) {
  const SessionManifest m = six_views();
  std::vector<Eigen::Matrix4d> poses;
  for (int i = 0; i < 6; ++i) poses.push_back(table_pose(i < 3 ? 30.0 * i : 30.0 * i - 120));
  std::vector<bool> registered(6, true);
  registered[3] = false;
  ASSERT_NEAR(rotation_angle_deg(rigid_inverse(poses[2]) * poses[4]), 60.0, 1e-9);
  EXPECT_FALSE(pose_from_neighbours_angles(poses, registered, m, 3, 1.0, 8.0, 0.3).has_value());
  // Without a pair beside it (views 0, 1 and 5 without angles) the sense cannot be
  // told and the pair is used.
  SessionManifest bare = m;
  for (int i : {0, 1, 5}) bare.views[std::size_t(i)].angle_deg.reset();
  EXPECT_TRUE(pose_from_neighbours_angles(poses, registered, bare, 3, 1.0, 8.0, 0.3).has_value());
  // A pair that slides along its axis (the object lifted) is not a turntable's motion.
  std::vector<Eigen::Matrix4d> lifted;
  for (int i = 0; i < 6; ++i) lifted.push_back(table_pose(30.0 * i));
  for (int i = 4; i < 6; ++i) lifted[std::size_t(i)](2, 3) += 0.05;
  EXPECT_FALSE(pose_from_neighbours_angles(lifted, registered, m, 3, 1.0, 8.0, 0.3).has_value());
}

}  // namespace
}  // namespace station
