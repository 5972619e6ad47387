// Issue 30: consolidation with the default attraction (WlopAttraction::kProjection) on
// scanned objects and CAD parts with real noise levels, against the issue's targets:
// mean distance to the reference at most half the input's, uniformity (the paper's
// eq. 20, uniformity() with the reference's area) at least 0.85 for plain WLOP and 0.80
// for edge-WLOP, edge-WLOP's error near sharp edges at least 20 % below plain WLOP's.
// Samples: area-uniform points of the bundled meshes (data/, tests/data/consolidation)
// with Gaussian noise of a fraction of the diagonal, 100,000 to 20,000 as in the issue.
// docs/consolidation.md, "Projection", has the table these runs print.
#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <random>
#include <string>

#include "core/io.h"
#include "eval/consolidation_metrics.h"
#include "eval/eval.h"
#include "reconstruct/wlop.h"
#include "test_util.h"

namespace station {
namespace {

struct Sample {
  Mesh mesh;
  double dbb = 0, area = 0;
  Cloud in;
};

// n area-uniform points of the mesh with Gaussian noise sigma = noise * d_bb along each
// axis; with_normals keeps the faces' (oriented) normals, as a scan's are.
Sample noisy_sample(const std::filesystem::path& path, int n, double noise, bool with_normals,
                    unsigned seed) {
  Sample s;
  s.mesh = read_mesh(test::source_dir() / path);
  s.dbb = bounding_box(s.mesh.vertices).diagonal();
  s.area = mesh_area(s.mesh);
  s.in = sample_mesh(s.mesh, n, seed);
  std::mt19937 rng(seed + 7);
  std::normal_distribution<float> g(0, float(noise * s.dbb));
  for (Vec3f& p : s.in.points) p += Vec3f(g(rng), g(rng), g(rng));
  if (!with_normals) s.in.normals.clear();
  return s;
}

struct Measured {
  double accuracy = 0, uniformity = 0, surface_uniformity = 0, edge = 0;
};

Measured measure(const std::vector<Vec3f>& pts, const Sample& s, double edge_radius) {
  Measured m;
  m.accuracy = mean_distance_to_mesh(pts, s.mesh) / s.dbb;
  m.uniformity = uniformity(pts, s.area);
  m.surface_uniformity = surface_uniformity(pts, s.mesh);
  m.edge = edge_error(pts, s.mesh, edge_radius).mean / s.dbb;
  return m;
}

struct Both {
  Measured input, wlop, edge;
};

// Both methods at their defaults, 20,000 points; distances in per mille of d_bb.
Both run(const Sample& s, const std::string& label) {
  WlopParams p;
  p.target_points = 20000;
  p.estimate_normals = false;
  const WlopResult w = consolidate(s.in, p);
  p.method = WlopMethod::kEdgeWlop;
  const WlopResult e = consolidate(s.in, p);
  EXPECT_EQ(w.output_points, 20000u);
  EXPECT_EQ(e.output_points, 20000u);
  for (const Vec3d& x : e.positions) EXPECT_TRUE(x.allFinite());
  const double reach = 2 * w.radius;  // 2h, the default h
  std::vector<Vec3f> subset;
  for (int j : initial_subset(s.in.size(), 20000, 1)) subset.push_back(s.in.points[std::size_t(j)]);
  Both b{measure(subset, s, reach), measure(w.cloud.points, s, reach), measure(e.cloud.points, s, reach)};
  const auto line = [&](const char* what, const Measured& m) {
    std::cout << "  " << what << ": accuracy " << 1000 * m.accuracy << ", near edges " << 1000 * m.edge
              << ", uniformity " << m.uniformity << " (on the surface " << m.surface_uniformity << ")\n";
  };
  std::cout << label << " (noise estimate " << 1000 * w.noise / s.dbb << " per mille, r_f "
            << w.fit_radius / w.radius << " h; " << w.seconds << " s / " << e.seconds << " s)\n";
  line("input", b.input);
  line("wlop", b.wlop);
  line("edge-wlop", b.edge);
  return b;
}

void expect_issue_targets(const Both& b, double plain_uniformity = 0.85) {
  EXPECT_LT(b.wlop.accuracy, 0.5 * b.input.accuracy);
  EXPECT_LT(b.edge.accuracy, 0.5 * b.input.accuracy);
  EXPECT_GT(b.wlop.uniformity, plain_uniformity);
  EXPECT_GT(b.edge.uniformity, 0.80);
  // And evener on the surface than the input (a random sample: about 0.46).
  EXPECT_GT(b.wlop.surface_uniformity, b.input.surface_uniformity + 0.25);
  EXPECT_GT(b.edge.surface_uniformity, b.input.surface_uniformity + 0.25);
}

TEST(ConsolidationQuality, MustardBottle) {
  // Measured: 0.3 %: accuracy 2.40 -> 0.51 / 0.51, uniformity 0.908 / 0.906;
  // 1 %: 7.95 -> 1.86 / 1.70, uniformity 0.862 / 0.847.
  const Both a = run(noisy_sample("data/mustard_bottle/textured.obj", 100000, 0.003, false, 3),
                     "mustard bottle, 0.3 %");
  expect_issue_targets(a);
  const Both b = run(noisy_sample("data/mustard_bottle/textured.obj", 100000, 0.01, false, 3),
                     "mustard bottle, 1 %");
  expect_issue_targets(b);
}

TEST(ConsolidationQuality, RubiksCube) {
  // Measured: 0.3 %: accuracy 2.39 -> 0.62 / 0.61, near edges 0.95 / 0.90 (the scanned
  // cube's edges are rounded: its "sharp edges" are the grooves between the cubelets,
  // where edge-WLOP gains 5 %, not the issue's 20 %), uniformity 0.899 / 0.892; 1 %:
  // 7.87 -> 1.91 / 1.43, near edges 3.21 / 2.42 (25 % lower), uniformity 0.853 / 0.836
  // (0.840 / 0.844 from a random initial subset).
  const Both a = run(noisy_sample("data/rubiks_cube/textured.obj", 100000, 0.003, false, 5),
                     "Rubik's cube, 0.3 %");
  expect_issue_targets(a);
  EXPECT_LT(a.edge.edge, a.wlop.edge);
  const Both b = run(noisy_sample("data/rubiks_cube/textured.obj", 100000, 0.01, false, 5),
                     "Rubik's cube, 1 %");
  expect_issue_targets(b);
  EXPECT_LT(b.edge.edge, 0.8 * b.wlop.edge);
}

TEST(ConsolidationQuality, FandiskEdgesSharper) {
  // Measured: accuracy 2.37 -> 0.63 / 0.52, near edges 0.98 / 0.71 (28 % lower; 0.68
  // with the gap at the edges that CubeEdgesAreSampled checks), uniformity 0.877 / 0.875.
  const Both b = run(noisy_sample("tests/data/consolidation/fandisk.off", 100000, 0.003, false, 9),
                     "fandisk, 0.3 %");
  expect_issue_targets(b);
  EXPECT_LT(b.edge.edge, 0.8 * b.wlop.edge);
}

TEST(ConsolidationQuality, BladeWithScannerNormals) {
  // A flat strip 10 x 129 x 0.65 (thinning to its rims) and sigma = 0.39: the faces
  // overlap in the input and only the oriented normals (which a scan carries) tell them
  // apart. Measured: accuracy 1.82 -> 0.557 / 0.557 (0.31 x the input's; 0.71 while the
  // fits' subset was sized over both faces, 1.20 while the fits' density weights
  // counted both faces, which put each face 0.18 of the thickness outwards);
  // uniformity 0.875 / 0.875 (0.864 before the subset's size; 0.820 while the area behind E2's
  // radius counted both faces, 0.84 x the strip's, and the centroid's dead zone was
  // 0.3: within 0.5 of the rims there were half the points an even sample puts there,
  // 0.65 now); near-edge errors equal to the
  // whole's (its sharp edges are the rims, where the error is no larger than elsewhere).
  const Both b = run(noisy_sample("tests/data/consolidation/blade.off", 100000, 0.003, true, 11),
                     "blade, 0.3 %, with normals");
  expect_issue_targets(b);
  // The fits' input thinned to about kFitPoints a fit counting the fit's own side only
  // (0.31 x the input's; 0.39 x while both faces were counted, each fit then held half).
  EXPECT_LT(b.wlop.accuracy, 0.35 * b.input.accuracy);
  EXPECT_LT(b.edge.accuracy, 0.35 * b.input.accuracy);
}

// Points whose nearest point on the unit cube's surface lies within `reach` of one of
// its edges.
int near_cube_edges(const std::vector<Vec3f>& points, double reach) {
  int n = 0;
  for (const Vec3f& p : points) {
    const Vec3f q = p.cwiseMax(Vec3f::Zero()).cwiseMin(Vec3f::Ones());
    int close = 0;
    for (int a = 0; a < 3; ++a) close += std::min(std::abs(q[a]), std::abs(q[a] - 1.0f)) < reach;
    n += close >= 2;
  }
  return n;
}

TEST(ConsolidationQuality, CubeEdgesAreSampled) {
  // Edge-WLOP samples the edge itself: within h/8 of the cube's edges it puts at least
  // 80 % of the points an even sample of the surface puts there. Measured: 185 against
  // 205 (plain WLOP: 0; edge-WLOP with E2 over straight distances at the creases, as
  // away from them: 135, a gap on both sides of every edge), and near-edge error 26 %
  // below plain WLOP's (0.79 against 1.08 per mille; 0.71 with the gap).
  Sample s;
  s.mesh = test::box(Vec3f::Zero(), Vec3f::Ones());
  s.dbb = std::sqrt(3.0);
  s.area = 6;
  s.in = sample_mesh(s.mesh, 100000, 3);
  std::mt19937 rng(5);
  std::normal_distribution<float> g(0, float(0.003 * s.dbb));
  for (Vec3f& p : s.in.points) p += Vec3f(g(rng), g(rng), g(rng));
  s.in.normals.clear();
  const Both b = run(s, "unit cube, 0.3 %");
  WlopParams p;
  p.target_points = 20000;
  p.estimate_normals = false;
  p.method = WlopMethod::kEdgeWlop;
  const WlopResult e = consolidate(s.in, p);
  const double reach = e.radius / 8;
  const int even = near_cube_edges(sample_mesh(s.mesh, 20000, 9).points, reach);
  const int edge = near_cube_edges(e.cloud.points, reach);
  std::cout << "  within h/8 of an edge: edge-wlop " << edge << ", an even sample " << even << "\n";
  EXPECT_GT(edge, 0.8 * even);
  EXPECT_LT(b.edge.edge, 0.8 * b.wlop.edge);
  EXPECT_LT(b.edge.accuracy, 0.5 * b.input.accuracy);
  EXPECT_GT(b.edge.uniformity, 0.80);
}

TEST(ConsolidationQuality, OpenBorderStaysOnTheData) {
  // A unit square (a one-sided patch, as one view is): E2 pushes the border points
  // outwards; the fit's pull beyond its dead zone holds them on the data.
  Mesh square;
  square.vertices = {Vec3f(0, 0, 0), Vec3f(1, 0, 0), Vec3f(1, 1, 0), Vec3f(0, 1, 0)};
  square.faces = {Face{0, 1, 2}, Face{0, 2, 3}};
  Sample s;
  s.mesh = square;
  s.dbb = bounding_box(square.vertices).diagonal();
  s.area = 1;
  for (const double noise : {0.003, 0.01}) {
    s.in = sample_mesh(square, 50000, 13);
    std::mt19937 rng(17);
    std::normal_distribution<float> g(0, float(noise * s.dbb));
    for (Vec3f& p : s.in.points) p += Vec3f(g(rng), g(rng), g(rng));
    s.in.normals.clear();
    WlopParams p;
    p.target_points = 10000;
    p.estimate_normals = false;
    const WlopResult r = consolidate(s.in, p);
    const double spacing = std::sqrt(2.0 / (std::sqrt(3.0) * 10000));
    int beyond = 0;
    double height = 0;
    for (const Vec3f& q : r.cloud.points) {
      const double out = std::max({-q.x(), -q.y(), q.x() - 1.0f, q.y() - 1.0f, 0.0f});
      if (out > spacing) ++beyond;
      height += std::abs(q.z());
    }
    height /= double(r.cloud.size());
    std::cout << "square, noise " << noise << ": " << beyond << " points beyond the border by a spacing, "
              << "mean height " << height << ", uniformity " << uniformity(r.cloud.points, 1.0) << "\n";
    EXPECT_LT(beyond, 20) << noise;
    EXPECT_LT(height, 0.5 * 0.8 * noise * s.dbb) << noise;  // input: 0.8 sigma
  }
}

}  // namespace
}  // namespace station
