#include "reconstruct/colour_edges.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <map>
#include <random>
#include <utility>

#include "core/error.h"
#include "eval/eval.h"
#include "test_util.h"

namespace station {
namespace {

const Rgb kRed{220, 30, 30}, kBlue{30, 40, 200}, kGreen{40, 190, 60};

// n random points on the unit sphere with exact normals, coloured by `paint`.
template <class Paint>
Cloud painted_sphere(int n, unsigned seed, Paint paint) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> gauss(0.0, 1.0);
  Cloud c;
  for (int i = 0; i < n; ++i) {
    const Vec3d d = Vec3d(gauss(rng), gauss(rng), gauss(rng)).normalized();
    c.points.push_back(d.cast<float>());
    c.normals.push_back(d.cast<float>());
    c.colours.push_back(paint(d));
  }
  return c;
}

const Vec3d kPlane = Vec3d(0.3, 0.2, 1.0).normalized();  // tilted against the mesh
Rgb two_colours(const Vec3d& p) { return kPlane.dot(p) > 0.1 ? kBlue : kRed; }
Rgb three_colours(const Vec3d& p) {
  if (p.z() < -0.2) return kGreen;
  return p.x() > 0.05 ? kBlue : kRed;
}

// Every edge in exactly two faces, opposite ways (closed, consistently oriented).
bool closed_and_oriented(const Mesh& m) {
  std::map<std::pair<int, int>, int> directed;
  for (const Face& f : m.faces)
    for (int e = 0; e < 3; ++e) ++directed[{f[e], f[(e + 1) % 3]}];
  for (const auto& [edge, count] : directed) {
    if (count != 1) return false;
    auto it = directed.find({edge.second, edge.first});
    if (it == directed.end() || it->second != 1) return false;
  }
  return true;
}

double area(const Mesh& m, double* smallest = nullptr) {
  double sum = 0, least = 1e300;
  for (const Face& f : m.faces) {
    const Vec3d a = m.vertices[std::size_t(f[0])].cast<double>(), b = m.vertices[std::size_t(f[1])].cast<double>(),
                c = m.vertices[std::size_t(f[2])].cast<double>();
    const double x = 0.5 * (b - a).cross(c - a).norm();
    sum += x;
    least = std::min(least, x);
  }
  if (smallest) *smallest = least;
  return sum;
}

double signed_volume(const Mesh& m) {
  double v = 0;
  for (const Face& f : m.faces)
    v += m.vertices[std::size_t(f[0])].cast<double>().dot(
             m.vertices[std::size_t(f[1])].cast<double>().cross(m.vertices[std::size_t(f[2])].cast<double>())) /
         6.0;
  return v;
}

double e_col_at(const Mesh& mesh, const Cloud& input) {
  EvalParams p;
  p.mesh_samples = 1000;
  return *evaluate(mesh, input, p).colour_error;
}

TEST(ColourEdges, SharpensATwoColourBoundaryAndKeepsTheSurface) {
  const Cloud c = painted_sphere(20000, 3, two_colours);
  ColourParams cp;
  cp.compute_e_col = false;
  const ColourFunction f = fit_colour(c, cp);
  Mesh mesh = test::icosphere(5, 1.0);  // 10,242 vertices: edges ~1.6x the point spacing
  mesh.normals = mesh.vertices;           // unit sphere: the normals are the positions
  colour_mesh(mesh, f);
  const Mesh before = mesh;
  const double e_before = e_col_at(mesh, c);
  const ColourEdgeStats s = sharpen_colour_edges(mesh, f);
  const double e_after = e_col_at(mesh, c);
  std::printf("e_col at the input points: %.3g -> %.3g (%zu edges split)\n", e_before, e_after, s.split_edges);
  // The boundary crosses ~2 pi 0.995 / 0.02 edges' worth of the sphere.
  EXPECT_GT(s.split_edges, 200u);
  EXPECT_EQ(s.split_edges, s.candidate_edges);
  EXPECT_EQ(s.three_way_faces, 0u);
  EXPECT_EQ(mesh.vertices.size(), before.vertices.size() + s.new_vertices);
  EXPECT_EQ(mesh.faces.size(), s.faces_after);
  // The colour error at the input points falls: what is left is the strip 1/16 of an
  // edge wide and where the function itself puts the boundary. Measured 0.0067 ->
  // 3e-8: the strip lies in the gap between the red and the blue samples.
  EXPECT_LT(e_after, 0.35 * e_before) << e_before << " -> " << e_after;
  // Same surface: watertight, oriented, same area and volume, no degenerate face.
  EXPECT_TRUE(closed_and_oriented(before));
  EXPECT_TRUE(closed_and_oriented(mesh));
  double smallest = 0;
  EXPECT_NEAR(area(mesh, &smallest), area(before), 1e-5 * area(before));
  EXPECT_GT(smallest, 1e-9);
  EXPECT_NEAR(signed_volume(mesh), signed_volume(before), 1e-5 * std::abs(signed_volume(before)));
  // Old vertices keep their place and colour; new ones have unit normals.
  for (std::size_t i = 0; i < before.vertices.size(); ++i) {
    ASSERT_EQ(mesh.vertices[i], before.vertices[i]);
    ASSERT_EQ(mesh.colours[i].r, before.colours[i].r);
  }
  for (std::size_t i = before.vertices.size(); i < mesh.vertices.size(); ++i)
    ASSERT_NEAR(mesh.normals[i].norm(), 1.f, 1e-5f);
  // No face spans red and blue except in the strips: a face with both colours has all
  // its vertices within 1/8 of the longest edge of its boundary crossing.
  std::size_t mixed = 0;
  for (const Face& face : mesh.faces) {
    bool red = false, blue = false;
    for (int k = 0; k < 3; ++k) {
      const Rgb& col = mesh.colours[std::size_t(face[k])];
      red |= col.r > 150;
      blue |= col.b > 150;
    }
    mixed += red && blue;
  }
  EXPECT_GT(mixed, 0u);
  EXPECT_LE(mixed, 2 * s.split_edges);

  // Deterministic for any thread count.
  Mesh again = before;
  ColourEdgeParams one;
  one.threads = 1;
  sharpen_colour_edges(again, f, one);
  EXPECT_EQ(again.vertices, mesh.vertices);
  EXPECT_EQ(again.faces, mesh.faces);
}

TEST(ColourEdges, ThreeColourJunctionStaysWatertight) {
  const Cloud c = painted_sphere(20000, 4, three_colours);
  ColourParams cp;
  cp.compute_e_col = false;
  cp.multi_colour = true;
  const ColourFunction f = fit_colour(c, cp);
  Mesh mesh = test::icosphere(4, 1.0);
  colour_mesh(mesh, f);
  const Mesh before = mesh;
  const double e_before = e_col_at(mesh, c);
  const ColourEdgeStats s = sharpen_colour_edges(mesh, f);
  EXPECT_GT(s.split_edges, 50u);
  EXPECT_TRUE(closed_and_oriented(mesh));
  double smallest = 0;
  EXPECT_NEAR(area(mesh, &smallest), area(before), 1e-5 * area(before));
  EXPECT_GT(smallest, 1e-9);
  const double e_after = e_col_at(mesh, c);
  std::printf("three colours: e_col at the input points %.3g -> %.3g (%zu edges split, %zu three-way faces)\n",
              e_before, e_after, s.split_edges, s.three_way_faces);
  EXPECT_LT(e_after, 0.5 * e_before);
}

TEST(ColourEdges, LeavesSmoothOrUncolouredMeshesAlone) {
  // One colour everywhere: nothing to split.
  const Cloud c = painted_sphere(5000, 5, [](const Vec3d&) { return kRed; });
  const ColourFunction f = fit_colour(c);
  Mesh mesh = test::icosphere(3, 1.0);
  colour_mesh(mesh, f);
  const Mesh before = mesh;
  ColourEdgeStats s = sharpen_colour_edges(mesh, f);
  EXPECT_EQ(s.candidate_edges, 0u);
  EXPECT_EQ(mesh.faces, before.faces);
  // No colours: left as it is.
  Mesh plain = test::icosphere(3, 1.0);
  s = sharpen_colour_edges(plain, f);
  EXPECT_EQ(s.split_edges, 0u);
  EXPECT_FALSE(plain.has_colours());
  // Ends not coloured by the function (here painted by hand) are not touched.
  Mesh painted = test::icosphere(3, 1.0);
  painted.colours.clear();
  for (const Vec3f& v : painted.vertices) painted.colours.push_back(v.z() > 0 ? kBlue : kRed);
  s = sharpen_colour_edges(painted, f);
  EXPECT_GT(s.candidate_edges, 0u);
  EXPECT_EQ(s.split_edges, 0u);
  // Bad parameters.
  ColourEdgeParams bad;
  bad.steps = 0;
  EXPECT_THROW(sharpen_colour_edges(mesh, f, bad), InvalidInput);
}

}  // namespace
}  // namespace station
