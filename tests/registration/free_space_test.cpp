// registration/free_space.h on a plane seen from the origin: what lies in front of
// it along a line of sight was seen through; a sight left out (`skip`) says nothing.
#include "registration/free_space.h"

#include <gtest/gtest.h>

#include <vector>

namespace station {
namespace {

// A 41 x 41 grid on the plane z = `z` (x, y in [-0.2, 0.2] z), seen from the origin.
std::vector<Vec3f> plane(float z) {
  std::vector<Vec3f> p;
  for (int i = -20; i <= 20; ++i)
    for (int j = -20; j <= 20; ++j) p.push_back(Vec3f(0.01f * float(i) * z, 0.01f * float(j) * z, z));
  return p;
}

TEST(FreeSpace, PointsInFrontOfWhatASightSawAreSeenThroughUnlessItIsSkipped) {
  FreeSpace free;
  ASSERT_TRUE(free.empty());
  // Sight 0: the plane 1 m ahead; sight 1: a plane behind the sensor, which sees
  // none of the directions below.
  ASSERT_EQ(free.add(plane(1.0f), Eigen::Matrix4d::Identity()), 0);
  ASSERT_EQ(free.add(plane(-1.0f), Eigen::Matrix4d::Identity()), 1);
  // Too few points for a sight: none made.
  EXPECT_EQ(free.add({Vec3f(0, 0, 1)}, Eigen::Matrix4d::Identity()), -1);
  const double margin = 0.01, spacing = 0.01, grow = 0.1;
  const std::vector<Vec3f> before = plane(0.8f), behind = plane(1.2f);
  EXPECT_EQ(free.seen_through(before, Eigen::Matrix4d::Identity(), margin, spacing, grow), 1.0);
  EXPECT_EQ(free.seen_through(behind, Eigen::Matrix4d::Identity(), margin, spacing, grow), 0.0);
  // Within the margin of what was seen: not seen through.
  EXPECT_EQ(free.seen_through(plane(0.995f), Eigen::Matrix4d::Identity(), margin, spacing, grow), 0.0);
  EXPECT_EQ(free.seen_through(before, Eigen::Matrix4d::Identity(), margin, spacing, grow, 1), 1.0);
  EXPECT_EQ(free.seen_through(before, Eigen::Matrix4d::Identity(), margin, spacing, grow, 0), 0.0);
}

}  // namespace
}  // namespace station
