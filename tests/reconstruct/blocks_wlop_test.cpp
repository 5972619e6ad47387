// Consolidation in blocks (issue 29): WLOP block by block gives what it gives on the
// whole cloud (as many points, as accurate, as even), and the blocks' seams show
// neither a doubled band nor a gap.
#include "reconstruct/blocks_wlop.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <numeric>
#include <cstdio>
#include <random>

#include "core/error.h"
#include "core/io.h"
#include "core/kdtree.h"
#include "eval/consolidation_metrics.h"
#include "eval/eval.h"
#include "test_util.h"

namespace station {
namespace {

struct Noisy {
  Mesh mesh;
  double dbb = 0, area = 0;
  Cloud in;
};

// The bundled bottle: n area-uniform samples with their normals, Gaussian noise of
// 0.3 % of the diagonal.
Noisy bottle(int n) {
  Noisy s;
  s.mesh = read_mesh(test::source_dir() / "data/mustard_bottle/textured.obj");
  s.dbb = bounding_box(s.mesh.vertices).diagonal();
  s.area = mesh_area(s.mesh);
  s.in = sample_mesh(s.mesh, n, 5);
  std::mt19937 rng(11);
  std::normal_distribution<float> g(0, float(0.003 * s.dbb));
  for (Vec3f& p : s.in.points) p += Vec3f(g(rng), g(rng), g(rng));
  return s;
}

// Distance to the nearest point of `pts` from reference samples within `band` of a
// seam plane of `grid` (near) and from the others (far): the means.
std::pair<double, double> coverage(const std::vector<Vec3f>& pts, const Mesh& mesh, const BlockGrid& grid, double band) {
  const PointIndex index(pts);
  const Cloud probe = sample_mesh(mesh, 40000, 21);
  double near = 0, far = 0;
  int nn = 0, nf = 0;
  for (const Vec3f& q : probe.points) {
    bool at_seam = false;
    for (int a = 0; a < 3; ++a)
      for (std::size_t s = 1; s + 1 < grid.splits[std::size_t(a)].size(); ++s) {
        const double plane = grid.lattice.origin[a] + grid.lattice.h * grid.splits[std::size_t(a)][s];
        at_seam = at_seam || std::abs(q[a] - plane) < band;
      }
    const double d = index.nearest(q).second;
    (at_seam ? near : far) += d;
    ++(at_seam ? nn : nf);
  }
  return {near / std::max(nn, 1), far / std::max(nf, 1)};
}

TEST(BlockWlop, BlocksConsolidateAsTheWholeCloud) {
  const Noisy s = bottle(100000);
  for (const WlopAttraction attraction : {WlopAttraction::kL1, WlopAttraction::kProjection}) {
    WlopParams p;
    p.method = attraction == WlopAttraction::kL1 ? WlopMethod::kEdgeWlop : WlopMethod::kWlop;  // the run's; the library's
    p.attraction = attraction;
    p.target_points = 20000;
    p.threads = 2;
    const WlopResult whole = consolidate(s.in, p);
    BlockWlopStats st;
    const Cloud blocks = consolidate_blocks(memory_source(s.in), p, 8, &st);
    const ConsolidationPlan plan = plan_consolidation(memory_source(s.in), p, 8);
    EXPECT_EQ(st.blocks, 8);
    EXPECT_LT(st.max_block_points, s.in.size() / 2);
    EXPECT_DOUBLE_EQ(plan.radius, whole.radius);
    ASSERT_TRUE(blocks.has_normals());
    ASSERT_EQ(blocks.normals.size(), blocks.size());
    const double acc_w = mean_distance_to_mesh(whole.cloud.points, s.mesh) / s.dbb;
    const double acc_b = mean_distance_to_mesh(blocks.points, s.mesh) / s.dbb;
    const double uni_w = uniformity(whole.cloud.points, s.area), uni_b = uniformity(blocks.points, s.area);
    const auto [near, far] = coverage(blocks.points, s.mesh, plan.grid, whole.radius);
    const auto [near_w, far_w] = coverage(whole.cloud.points, s.mesh, plan.grid, whole.radius);
    // Close pairs: a band where two blocks' outputs overlap would double the density.
    const PointIndex bi(blocks.points);
    int close = 0;
    for (const Vec3f& q : blocks.points)
      if (bi.knn(q, 2).back().second < 0.25 * std::sqrt(s.area / double(blocks.size()))) ++close;
    const PointIndex wi(whole.cloud.points);
    int close_w = 0;
    for (const Vec3f& q : whole.cloud.points)
      if (wi.knn(q, 2).back().second < 0.25 * std::sqrt(s.area / double(whole.cloud.size()))) ++close_w;
    std::printf("%s: points %zu whole / %zu blocks; accuracy %.3f / %.3f per mille; uniformity %.3f / %.3f; "
                "coverage near seams / elsewhere %.3g / %.3g (whole %.3g / %.3g); close pairs %d / %d\n",
                attraction == WlopAttraction::kL1 ? "edge-WLOP, l1" : "WLOP, projection", whole.cloud.size(),
                blocks.size(), 1000 * acc_w, 1000 * acc_b, uni_w, uni_b, near, far, near_w, far_w, close_w, close);
    EXPECT_NEAR(double(blocks.size()), double(whole.cloud.size()), 0.02 * double(whole.cloud.size()));
    EXPECT_LT(acc_b, 1.1 * acc_w);
    EXPECT_GT(uni_b, uni_w - 0.02);
    EXPECT_LT(near, 1.1 * far);  // no gap along the seams
    EXPECT_LT(close, 2 * close_w + 50);  // no doubled band (a few pairs where the blocks meet: 20-100)
  }
}

TEST(BlockWlop, TheBlockCountFollowsThePointsAndTheMemoryBound) {
  EXPECT_EQ(wlop_block_count(100000, 0, 0), 1);
  EXPECT_EQ(wlop_block_count(5000000, 0, 0), 3);
  EXPECT_EQ(wlop_block_count(5000000, 7, 0), 7);
  // 0.5 GB holds blocks of about 1.75 M points with their margins: 3 for 5 M, 6 for 10 M.
  EXPECT_EQ(wlop_block_count(5000000, 0, 0.5e9), 3);
  EXPECT_EQ(wlop_block_count(10000000, 0, 0.5e9), 6);
  // 0.3 GB: about 0.8 M points a block.
  EXPECT_EQ(wlop_block_count(5000000, 0, 0.3e9), 7);
  EXPECT_THROW(wlop_block_count(5000000, 0, 0.1e9), InvalidInput);
  EXPECT_THROW(wlop_block_count(5000000, -1, 0), InvalidInput);
}

// Boxes are not even: with a memory bound the plan adds blocks until the largest box,
// its margin counted, fits.
TEST(BlockWlop, ThePlanSplitsUntilTheLargestBoxFits) {
  Cloud cloud;
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(0, 1);
  for (int i = 0; i < 600000; ++i) {
    // Half the points in a tenth of the box's width.
    const float x = i % 2 ? 0.1f * u(rng) : u(rng);
    cloud.points.emplace_back(x, u(rng), 0.01f * u(rng));
  }
  const double max_bytes = kWlopBaseBytes + 200000 * kWlopBytesPerPoint;  // 200,000 points a block
  const int even = wlop_block_count(cloud.size(), 0, max_bytes);
  const ConsolidationPlan plan = plan_consolidation(memory_source(cloud), WlopParams{}, 0, max_bytes);
  const std::size_t largest = *std::max_element(plan.box_points.begin(), plan.box_points.end());
  std::printf("%d blocks for even boxes, %d planned; the largest box %zu points\n", even, plan.grid.size(), largest);
  EXPECT_GT(plan.grid.size(), even);
  EXPECT_LE(double(largest) * 4 / 3, 200000.0);
  EXPECT_EQ(std::accumulate(plan.box_points.begin(), plan.box_points.end(), std::size_t(0)), cloud.size());
  // Without a bound, the count asked for.
  EXPECT_EQ(plan_consolidation(memory_source(cloud), WlopParams{}, 5).grid.size(), 4);  // at most 5: 2 x 2 x 1
}

TEST(BlockWlop, BadInputIsRefusedByName) {
  Cloud empty;
  EXPECT_THROW(plan_consolidation(memory_source(empty), WlopParams{}, 2), InvalidInput);
  Cloud same;
  same.points.assign(100, Vec3f(1, 2, 3));
  EXPECT_THROW(plan_consolidation(memory_source(same), WlopParams{}, 2), InvalidInput);
  Cloud nan = same;
  nan.points[3].x() = std::nanf("");
  EXPECT_THROW(plan_consolidation(memory_source(nan), WlopParams{}, 2), InvalidInput);
  EXPECT_THROW(plan_consolidation(memory_source(bottle(1000).in), WlopParams{}, -1), InvalidInput);
}

}  // namespace
}  // namespace station
