#include <gtest/gtest.h>

#include <random>

#include "core/kdtree.h"
#include "reconstruct/near_grid.h"

namespace station {
namespace {

// A set cell is a proof: every query it answers lies within the radius of a point (as
// the k-d tree measures it), and it answers most queries well inside the radius.
TEST(NearGrid, AnswersOnlyWhatTheSearchWouldAndMostNearQueries) {
  std::mt19937 rng(3);
  std::normal_distribution<float> g(0, 1);
  std::vector<Vec3f> pts;
  for (int i = 0; i < 20000; ++i) {
    Vec3f p(g(rng), g(rng), g(rng));
    pts.push_back(Vec3f(100, -50, 20) + 0.05f * p.normalized());  // a sphere shell, off the origin
  }
  const PointIndex index(pts);
  const double radius = 0.004;
  const NearGrid grid(pts, radius);
  ASSERT_FALSE(grid.empty());
  EXPECT_GT(grid.set_cells(), 0u);
  std::uniform_real_distribution<double> u(-0.06, 0.06);
  int answered = 0, well_inside = 0, answered_inside = 0;
  for (int i = 0; i < 200000; ++i) {
    const Vec3d x = Vec3d(100, -50, 20) + Vec3d(u(rng), u(rng), u(rng));
    const double d = index.nearest(x.cast<float>()).second;
    const bool yes = grid.surely_near(x);
    if (yes) {
      ++answered;
      ASSERT_LE(d, radius) << "a set cell more than the radius from every point";
    }
    if (d <= 0.5 * radius) {
      ++well_inside;
      answered_inside += yes;
    }
  }
  std::printf("near grid: %d answered; of %d queries within half the radius, %d answered\n", answered,
              well_inside, answered_inside);
  EXPECT_GT(answered_inside, well_inside / 2);
}

TEST(NearGrid, EmptyForNoPointsOrNoRadius) {
  EXPECT_TRUE(NearGrid({}, 1.0).empty());
  EXPECT_TRUE(NearGrid({Vec3f(0, 0, 0)}, 0.0).empty());
  EXPECT_FALSE(NearGrid({Vec3f(0, 0, 0)}, 0.0).surely_near(Vec3d::Zero()));
  const NearGrid one({Vec3f(1, 2, 3), Vec3f(NAN, 0, 0)}, 0.5);
  EXPECT_FALSE(one.empty());
  EXPECT_TRUE(one.surely_near(Vec3d(1, 2, 3)));
  EXPECT_FALSE(one.surely_near(Vec3d(1.6, 2, 3)));
  EXPECT_FALSE(one.surely_near(Vec3d(NAN, 2, 3)));
}

}  // namespace
}  // namespace station
