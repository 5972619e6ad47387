#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include <tbb/parallel_for.h>

#include "core/kdtree.h"
#include "reconstruct/mpu.h"
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

// A long thin box: the cells coarsen until the grid fits kMaxCells (one cube-root
// step assumes all three axes shrink; here only one does).
TEST(NearGrid, ALongBoxStaysWithinTheCellCap) {
  std::vector<Vec3f> line;
  for (int i = 0; i <= 1000; ++i) line.push_back(Vec3f(float(i) * 100.0f, 0, 0));
  const NearGrid g(line, 0.01);
  EXPECT_LE(double(g.cells()), NearGrid::kMaxCells);
  for (int i = 0; i <= 1000; i += 100)
    if (g.surely_near(Vec3d(i * 100.0, 0, 0))) SUCCEED();  // may be empty: then only the search
  EXPECT_FALSE(g.surely_near(Vec3d(50.0, 0, 0)));           // 50 from every point
}

// MpuSurface::trusted answers as the search does ("nearest input point within
// trust_factor mean spacings"), its first calls made from inside a parallel loop (the
// grid is built on the first call, itself in parallel).
TEST(NearGrid, MpuTrustedIsTheSearchsAnswerFromAParallelLoop) {
  std::mt19937 rng(5);
  std::normal_distribution<float> g(0, 1);
  Cloud c;
  for (int i = 0; i < 4000; ++i) {
    const Vec3f n = Vec3f(g(rng), g(rng), g(rng)).normalized();
    c.points.push_back(0.3f * n);
    c.normals.push_back(n);
  }
  const MpuSurface s = fit_mpu(c, MpuParams{});
  const double trust = s.params().trust_factor * s.diagnostics().mean_spacing;
  std::uniform_real_distribution<double> u(-0.4, 0.4);
  std::vector<Vec3d> xs(100000);
  for (Vec3d& x : xs) x = Vec3d(u(rng), u(rng), u(rng));
  std::vector<char> got(xs.size());
  tbb::parallel_for(std::size_t(0), xs.size(), [&](std::size_t i) { got[i] = s.trusted(xs[i]); });
  int yes = 0, checked = 0;
  for (std::size_t i = 0; i < xs.size(); ++i) {
    const double d = s.nearest_point_distance(xs[i]);
    if (std::abs(d / trust - 1) < 1e-6) continue;  // on the boundary, to rounding
    ++checked;
    yes += got[i];
    EXPECT_EQ(bool(got[i]), d <= trust) << i << ": " << d << " against " << trust;
  }
  std::printf("trusted: %d of %d queries\n", yes, checked);
  EXPECT_GT(yes, 1000);
  EXPECT_LT(yes, checked);
}

}  // namespace
}  // namespace station
