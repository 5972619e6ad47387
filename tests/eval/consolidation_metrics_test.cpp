#include "eval/consolidation_metrics.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "core/error.h"
#include "test_util.h"

namespace station {
namespace {

// Square [-1, 1]^2 at z = 0 as two triangles.
Mesh square() {
  Mesh m;
  m.vertices = {Vec3f(-1, -1, 0), Vec3f(1, -1, 0), Vec3f(1, 1, 0), Vec3f(-1, 1, 0)};
  m.faces = {Face(0, 1, 2), Face(0, 2, 3)};
  return m;
}

TEST(ConsolidationMetrics, AccuracyIsTheMeanDistance) {
  std::vector<Vec3f> pts = {Vec3f(0, 0, 0.1f), Vec3f(0.5f, 0.5f, -0.3f), Vec3f(0.2f, -0.4f, 0)};
  EXPECT_NEAR(mean_distance_to_mesh(pts, square()), (0.1 + 0.3 + 0) / 3, 1e-7);
  EXPECT_NEAR(mean_distance_to_mesh(pts, square(), 1), mean_distance_to_mesh(pts, square(), 2), 0);
  EXPECT_THROW(mean_distance_to_mesh({}, square()), InvalidInput);
  EXPECT_THROW(mean_distance_to_mesh(pts, Mesh{}), InvalidInput);
  pts[1].x() = NAN;
  EXPECT_THROW(mean_distance_to_mesh(pts, square()), InvalidInput);
}

TEST(ConsolidationMetrics, MeshArea) {
  EXPECT_NEAR(mesh_area(square()), 4.0, 1e-12);
  EXPECT_NEAR(mesh_area(test::box(Vec3f(0, 0, 0), Vec3f(1, 2, 3))), 22.0, 1e-5);
}

TEST(ConsolidationMetrics, HexagonalPackingHasUniformityOne) {
  // A hexagonal lattice of spacing d covers sqrt(3)/2 d^2 per point.
  const double d = 0.1;
  std::vector<Vec3f> pts;
  for (int r = 0; r < 20; ++r)
    for (int c = 0; c < 20; ++c)
      pts.push_back(Vec3f(float(c * d + (r % 2) * d / 2), float(r * d * std::sqrt(3.0) / 2), 0));
  const double area = double(pts.size()) * std::sqrt(3.0) / 2 * d * d;
  EXPECT_NEAR(uniformity(pts, area), 1.0, 1e-5);
  // Random points score about 0.47 (Poisson: mean NN distance 0.5 / sqrt(density)).
  std::mt19937 rng(1);
  std::uniform_real_distribution<float> u(0, 1);
  std::vector<Vec3f> random;
  for (int i = 0; i < 20000; ++i) random.push_back(Vec3f(u(rng), u(rng), 0));
  EXPECT_NEAR(uniformity(random, 1.0), 0.5 / 1.0746, 0.02);
  // Coincident points count with distance 0.
  pts.push_back(pts[0]);
  EXPECT_LT(uniformity(pts, area), 1.0);
  EXPECT_THROW(uniformity({Vec3f(0, 0, 0)}, 1.0), InvalidInput);
  EXPECT_THROW(uniformity(random, 0.0), InvalidInput);
}

TEST(ConsolidationMetrics, SurfaceUniformityIgnoresOffSurfaceScatter) {
  // A lattice on the square, jittered along z only: on the surface it is still
  // a perfect lattice, while 3-D distances grow.
  const Mesh sq = square();
  std::vector<Vec3f> pts;
  std::mt19937 rng(2);
  std::normal_distribution<float> g(0, 0.02f);
  const int k = 40;
  for (int i = 0; i < k; ++i)
    for (int j = 0; j < k; ++j)
      pts.push_back(Vec3f(-1 + (i + 0.5f) * 2.f / k, -1 + (j + 0.5f) * 2.f / k, g(rng)));
  const double on_surface = surface_uniformity(pts, sq);
  // Square lattice: NN distance 2/k against the hexagonal sqrt(2A / (sqrt(3) N)).
  const double expected = (2.0 / k) / std::sqrt(2 * 4.0 / (std::sqrt(3.0) * k * k));
  EXPECT_NEAR(on_surface, expected, 1e-4);
  EXPECT_GT(uniformity(pts, mesh_area(sq)), on_surface + 0.01);
}

TEST(ConsolidationMetrics, SharpEdgesOfABox) {
  const Mesh box = test::box(Vec3f(0, 0, 0), Vec3f(1, 2, 3));
  const std::vector<Segment> edges = sharp_edges(box);
  EXPECT_EQ(edges.size(), 12u);  // the face diagonals are flat
  for (const Segment& s : edges) {
    const float len = (s.b - s.a).norm();
    EXPECT_TRUE(std::abs(len - 1) < 1e-6 || std::abs(len - 2) < 1e-6 || std::abs(len - 3) < 1e-6);
  }
  EXPECT_EQ(sharp_edges(box, 95).size(), 0u);
  // Split vertices (every face its own corners) give the same edges.
  Mesh split;
  for (const Face& f : box.faces) {
    const int base = int(split.vertices.size());
    for (int k = 0; k < 3; ++k) split.vertices.push_back(box.vertices[f[k]]);
    split.faces.push_back(Face(base, base + 1, base + 2));
  }
  EXPECT_EQ(sharp_edges(split).size(), 12u);
  // A fine sphere has none; a square has only boundary edges, never sharp.
  EXPECT_EQ(sharp_edges(test::icosphere(3)).size(), 0u);
  EXPECT_EQ(sharp_edges(square()).size(), 0u);
}

TEST(ConsolidationMetrics, EdgeErrorCountsOnlyPointsNearSharpEdges) {
  const Mesh box = test::box(Vec3f(-1, -1, -1), Vec3f(1, 1, 1));
  std::vector<Vec3f> pts = {
      Vec3f(1.05f, 0.95f, 0),  // near the edge x = y = 1, 0.05 off the surface
      Vec3f(0.98f, 0.98f, 0),  // near that edge, 0.02 inside
      Vec3f(0, 0, 1.2f),       // middle of the top face, 0.2 above: not near an edge
  };
  const EdgeError e = edge_error(pts, box, 0.1);
  EXPECT_EQ(e.count, 2u);
  EXPECT_NEAR(e.mean, (0.05 + 0.02) / 2, 1e-6);
  const EdgeError none = edge_error({Vec3f(0, 0, 1)}, box, 0.1);
  EXPECT_EQ(none.count, 0u);
  EXPECT_EQ(none.mean, 0.0);
  EXPECT_EQ(edge_error(pts, square(), 0.1).count, 0u);  // no sharp edges at all
  EXPECT_THROW(edge_error(pts, box, 0.0), InvalidInput);
}

}  // namespace
}  // namespace station
