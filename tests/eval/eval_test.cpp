#include "eval/eval.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <limits>

#include "core/error.h"
#include "test_util.h"

namespace station {
namespace {

using test::icosphere;

EvalParams params_with(int samples, int threads = 0, unsigned seed = 1) {
  EvalParams p;
  p.mesh_samples = samples;
  p.threads = threads;
  p.seed = seed;
  return p;
}

// Square [-1,1]^2 in the plane z = 0 (two triangles, normal +z), rigidly moved
// by `rot` after lifting it by `lift` along its normal.
Mesh square(float lift, const Eigen::Matrix3f& rot = Eigen::Matrix3f::Identity()) {
  Mesh m;
  for (Vec3f p : {Vec3f(-1, -1, lift), Vec3f(1, -1, lift), Vec3f(1, 1, lift), Vec3f(-1, 1, lift)})
    m.vertices.push_back(rot * p);
  m.faces = {Face(0, 1, 2), Face(0, 2, 3)};
  return m;
}

Eigen::Matrix3f some_rotation() {
  return Eigen::AngleAxisf(0.7f, Vec3f(1, 2, 3).normalized()).toRotationMatrix();
}

Mesh coloured(Mesh m, Rgb c) {
  m.colours.assign(m.vertices.size(), c);
  return m;
}

// ---- sample_mesh ----------------------------------------------------------------

TEST(SampleMesh, PointsLieOnTheSurfaceWithFaceNormals) {
  const Mesh sphere = icosphere(3, 2.0);
  const Cloud c = sample_mesh(sphere, 5000, 7);
  ASSERT_EQ(c.size(), 5000u);
  ASSERT_EQ(c.normals.size(), 5000u);
  EXPECT_FALSE(c.has_colours());
  for (std::size_t i = 0; i < c.size(); ++i) {
    // Level 3 chords sag at most ~1 % below the radius; never above it.
    EXPECT_LE(c.points[i].norm(), 2.0f + 1e-5f);
    EXPECT_GT(c.points[i].norm(), 1.98f);
    EXPECT_NEAR(c.normals[i].norm(), 1.f, 1e-5f);
    EXPECT_GT(c.normals[i].dot(c.points[i].normalized()), 0.99f);  // outward face normal
  }
}

TEST(SampleMesh, AreaWeighted) {
  // Box 4 x 1 x 1: the two end caps hold 2 of the 18 units of area.
  const Mesh b = test::box(Vec3f(0, 0, 0), Vec3f(4, 1, 1));
  const int n = 100000;
  const Cloud c = sample_mesh(b, n, 3);
  int caps = 0;
  for (const Vec3f& p : c.points)
    if (p.x() < 1e-5f || p.x() > 4 - 1e-5f) ++caps;
  EXPECT_NEAR(double(caps) / n, 2.0 / 18.0, 0.005);
}

TEST(SampleMesh, UniformWithinATriangle) {
  Mesh t;
  t.vertices = {Vec3f(0, 0, 0), Vec3f(1, 0, 0), Vec3f(0, 1, 0)};
  t.faces = {Face(0, 1, 2)};
  const int n = 100000;
  const Cloud c = sample_mesh(t, n, 11);
  Vec3d mean = Vec3d::Zero();
  int corner = 0;
  for (const Vec3f& p : c.points) {
    EXPECT_GE(p.x(), 0.f);
    EXPECT_GE(p.y(), 0.f);
    EXPECT_LE(p.x() + p.y(), 1.f + 1e-6f);
    mean += p.cast<double>();
    if (p.x() + p.y() < 0.5f) ++corner;  // the corner triangle holds 1/4 of the area
  }
  mean /= n;
  EXPECT_NEAR(mean.x(), 1.0 / 3, 0.005);
  EXPECT_NEAR(mean.y(), 1.0 / 3, 0.005);
  EXPECT_NEAR(double(corner) / n, 0.25, 0.005);
}

TEST(SampleMesh, InterpolatesColours) {
  Mesh t;
  t.vertices = {Vec3f(0, 0, 0), Vec3f(1, 0, 0), Vec3f(0, 1, 0)};
  t.faces = {Face(0, 1, 2)};
  t.colours = {Rgb{255, 0, 0}, Rgb{0, 255, 0}, Rgb{0, 0, 255}};
  const Cloud c = sample_mesh(t, 2000, 5);
  ASSERT_EQ(c.colours.size(), 2000u);
  for (std::size_t i = 0; i < c.size(); ++i) {
    const Rgb& k = c.colours[i];
    EXPECT_NEAR(int(k.r) + int(k.g) + int(k.b), 255, 2);
    // Green weight is the barycentric of vertex 1, i.e. the x coordinate here.
    EXPECT_NEAR(k.g / 255.0, c.points[i].x(), 1.0 / 255 + 1e-6);
    EXPECT_NEAR(k.b / 255.0, c.points[i].y(), 1.0 / 255 + 1e-6);
  }
}

TEST(SampleMesh, DeterministicForASeed) {
  const Mesh sphere = icosphere(2);
  const Cloud a = sample_mesh(sphere, 1000, 42), b = sample_mesh(sphere, 1000, 42),
              c = sample_mesh(sphere, 1000, 43);
  EXPECT_EQ(a.points, b.points);
  EXPECT_NE(a.points, c.points);
}

TEST(SampleMesh, RejectsBadInput) {
  Mesh no_faces;
  no_faces.vertices = {Vec3f(0, 0, 0)};
  EXPECT_THROW(sample_mesh(no_faces, 10, 1), InvalidInput);
  Mesh flat;
  flat.vertices = {Vec3f(0, 0, 0), Vec3f(1, 0, 0), Vec3f(2, 0, 0)};
  flat.faces = {Face(0, 1, 2)};
  EXPECT_THROW(sample_mesh(flat, 10, 1), InvalidInput);
  EXPECT_THROW(sample_mesh(icosphere(1), -1, 1), InvalidInput);
  EXPECT_EQ(sample_mesh(icosphere(1), 0, 1).size(), 0u);
}

// ---- distances --------------------------------------------------------------------

TEST(Evaluate, ConcentricSpheres) {
  const Mesh inner = icosphere(6, 1.0), outer = icosphere(6, 1.1);
  const EvalResult r = evaluate(inner, outer, params_with(50000));
  // Level-6 facets sag < 1e-5 below their sphere, so every distance is 0.1 to that.
  EXPECT_NEAR(r.chamfer, 0.1, 5e-5);
  EXPECT_NEAR(r.a_to_b.mean, 0.1, 5e-5);
  EXPECT_NEAR(r.b_to_a.mean, 0.1, 5e-5);
  EXPECT_NEAR(r.hausdorff, 0.1, 5e-5);
  EXPECT_NEAR(r.p95, 0.1, 5e-5);
  EXPECT_NEAR(r.a_to_b.rms, 0.1, 5e-5);
  EXPECT_EQ(r.a_to_b.count, 50000u);
  EXPECT_EQ(r.b_to_a.count, 50000u);
  ASSERT_TRUE(r.normal_consistency.has_value());
  EXPECT_NEAR(*r.normal_consistency, 1.0, 1e-3);
  EXPECT_FALSE(r.colour_error.has_value());
}

TEST(Evaluate, ShiftedPlaneMeshes) {
  const float d = 0.05f;
  const Eigen::Matrix3f rot = some_rotation();
  const EvalResult r = evaluate(square(0, rot), square(d, rot), params_with(20000));
  // Same extent, so every sample projects inside the other square: exactly d.
  EXPECT_NEAR(r.chamfer, d, 1e-6);
  EXPECT_NEAR(r.hausdorff, d, 1e-6);
  EXPECT_NEAR(r.p95, d, 1e-6);
  EXPECT_NEAR(r.a_to_b.rms, d, 1e-6);
  EXPECT_NEAR(r.b_to_a.mean, d, 1e-6);
  ASSERT_TRUE(r.normal_consistency.has_value());
  EXPECT_NEAR(*r.normal_consistency, 1.0, 1e-6);
}

TEST(Evaluate, InteriorGridAbovePlane) {
  const float d = 0.2f;
  const Eigen::Matrix3f rot = some_rotation();
  // Grid over the inner half of the square, lifted by d: its own distances to
  // the plane are exactly d; the plane's border is farther from the grid.
  Cloud grid;
  for (int i = 0; i <= 50; ++i)
    for (int j = 0; j <= 50; ++j)
      grid.points.push_back(rot * Vec3f(-0.5f + i * 0.02f, -0.5f + j * 0.02f, d));
  const EvalResult r = evaluate(grid, square(0, rot), params_with(20000));
  EXPECT_EQ(r.a_to_b.count, grid.size());
  EXPECT_NEAR(r.a_to_b.mean, d, 1e-6);
  EXPECT_NEAR(r.a_to_b.max, d, 1e-6);
  EXPECT_NEAR(r.a_to_b.p95, d, 1e-6);
  EXPECT_GT(r.b_to_a.mean, d + 0.05);
  EXPECT_LE(r.b_to_a.max, std::sqrt(0.5 + d * d) + 1e-5);
  EXPECT_GT(r.b_to_a.max, std::sqrt(0.5 + d * d) - 0.05);
  EXPECT_FALSE(r.normal_consistency.has_value());  // the grid has no normals
}

TEST(Evaluate, TwoCloudsExactStats) {
  Cloud a, b;
  a.points = {Vec3f(0, 0, 0)};
  for (int k = 1; k <= 100; ++k) b.points.push_back(Vec3f(float(k), 0, 0));
  const EvalResult r = evaluate(a, b);
  EXPECT_DOUBLE_EQ(r.a_to_b.mean, 1);
  EXPECT_DOUBLE_EQ(r.a_to_b.max, 1);
  EXPECT_DOUBLE_EQ(r.b_to_a.mean, 50.5);
  EXPECT_DOUBLE_EQ(r.b_to_a.rms, std::sqrt(338350.0 / 100));
  EXPECT_DOUBLE_EQ(r.b_to_a.p95, 95);  // nearest rank
  EXPECT_DOUBLE_EQ(r.b_to_a.max, 100);
  EXPECT_EQ(r.b_to_a.count, 100u);
  EXPECT_DOUBLE_EQ(r.chamfer, (1 + 50.5) / 2);
  EXPECT_DOUBLE_EQ(r.hausdorff, 100);
  EXPECT_DOUBLE_EQ(r.p95, 95);
}

TEST(Evaluate, IdenticalMeshesGiveZero) {
  const Mesh m = icosphere(4, 0.5);
  const EvalResult r = evaluate(m, m, params_with(20000));
  EXPECT_LT(r.chamfer, 1e-7);
  EXPECT_LT(r.hausdorff, 1e-6);
  ASSERT_TRUE(r.normal_consistency.has_value());
  EXPECT_NEAR(*r.normal_consistency, 1.0, 1e-6);
}

TEST(Evaluate, CloudAgainstItselfIsExactlyZero) {
  Cloud c = sample_mesh(icosphere(3), 3000, 9);
  const EvalResult r = evaluate(c, c);
  EXPECT_EQ(r.chamfer, 0);
  EXPECT_EQ(r.hausdorff, 0);
  EXPECT_EQ(r.p95, 0);
  ASSERT_TRUE(r.normal_consistency.has_value());
  EXPECT_NEAR(*r.normal_consistency, 1.0, 1e-6);
  c.normals.clear();
  EXPECT_FALSE(evaluate(c, c).normal_consistency.has_value());
}

TEST(Evaluate, FacelessMeshIsItsVertexCloud) {
  Mesh faceless = icosphere(2);
  faceless.faces.clear();
  Cloud shifted;
  for (const Vec3f& v : faceless.vertices) shifted.points.push_back(v * 1.5f);
  const EvalResult r = evaluate(faceless, shifted);
  EXPECT_EQ(r.a_to_b.count, faceless.vertices.size());
  EXPECT_NEAR(r.chamfer, 0.5, 1e-6);
  EXPECT_NEAR(r.hausdorff, 0.5, 1e-6);
}

// ---- colour -------------------------------------------------------------------------

TEST(Evaluate, ColourErrorOfAConstantOffset) {
  const Mesh m = icosphere(3);
  const Mesh a = coloured(m, Rgb{100, 50, 200}), b = coloured(m, Rgb{151, 50, 200});
  const EvalResult r = evaluate(a, b, params_with(10000));
  ASSERT_TRUE(r.colour_error.has_value());
  EXPECT_NEAR(*r.colour_error, 0.2, 1e-5);  // 51 / 255

  // Every channel off, against a cloud reference: (51 + 50 + 20) / 255.
  Cloud ref;
  ref.points = m.vertices;
  ref.colours.assign(ref.size(), Rgb{151, 0, 180});
  const EvalResult rc = evaluate(a, ref, params_with(10000));
  ASSERT_TRUE(rc.colour_error.has_value());
  EXPECT_NEAR(*rc.colour_error, 121.0 / 255, 1e-5);
}

TEST(Evaluate, ColourInterpolatedAtTheClosestPoint) {
  // The square's corner colours span a linear field (R along x, G along y); the
  // reference grid, slightly above the plane, carries that field rounded to 8 bits.
  Mesh a = square(0);
  auto field = [](float x, float y) {
    return Rgb{std::uint8_t(std::lround(127.5f * (x + 1))), std::uint8_t(std::lround(127.5f * (y + 1))),
               40};
  };
  for (const Vec3f& v : a.vertices) a.colours.push_back(field(v.x(), v.y()));
  Cloud b;
  for (int i = 0; i <= 40; ++i)
    for (int j = 0; j <= 40; ++j) {
      const float x = -1 + i * 0.05f, y = -1 + j * 0.05f;
      b.points.push_back(Vec3f(x, y, 0.01f));
      b.colours.push_back(field(x, y));
    }
  const EvalResult r = evaluate(a, b, params_with(1000));
  ASSERT_TRUE(r.colour_error.has_value());
  EXPECT_LT(*r.colour_error, 1.0 / 255);  // only the 8-bit rounding of two channels
}

TEST(Evaluate, SurfaceColourFunctionOverridesVertexColours) {
  // A mesh B without vertex colours, coloured by a function of the surface point:
  // red where x < 0, blue elsewhere (as a texture with a sharp boundary would be).
  const Mesh b = square(0);
  auto half = [&](int f, double u, double v) {
    const Face& t = b.faces[f];
    const Vec3f p = float(1 - u - v) * b.vertices[t[0]] + float(u) * b.vertices[t[1]] +
                    float(v) * b.vertices[t[2]];
    return p.x() < 0 ? Rgb{255, 0, 0} : Rgb{0, 0, 255};
  };
  Cloud a;  // a result whose colours follow the same boundary
  for (int i = 0; i < 100; ++i)
    for (int j = 0; j < 100; ++j) {
      const float x = -0.995f + i * 0.02f, y = -0.995f + j * 0.02f;
      a.points.push_back(Vec3f(x, y, 0));
      a.colours.push_back(x < 0 ? Rgb{255, 0, 0} : Rgb{0, 0, 255});
    }
  EvalParams p = params_with(20000);
  EXPECT_FALSE(evaluate(a, b, p).colour_error.has_value());
  p.b_surface_colour = half;
  const EvalResult r = evaluate(a, b, p);
  ASSERT_TRUE(r.colour_error.has_value());
  // Only samples within half a grid step of the boundary can pick the other side.
  EXPECT_LT(*r.colour_error, 0.03);
  // A result coloured all red is wrong on B's blue half: e_col = 2 * 1/2.
  a.colours.assign(a.size(), Rgb{255, 0, 0});
  EXPECT_NEAR(*evaluate(a, b, p).colour_error, 1.0, 0.03);
  // The function also colours mesh A at its closest points (swapped roles).
  EvalParams q = params_with(20000);
  q.a_surface_colour = half;
  EXPECT_NEAR(*evaluate(b, a, q).colour_error, 1.0, 0.03);
}

TEST(Evaluate, ColourErrorAbsentWithoutColours) {
  const Mesh m = icosphere(2);
  EXPECT_FALSE(evaluate(m, m, params_with(1000)).colour_error.has_value());
  EXPECT_FALSE(evaluate(coloured(m, Rgb{1, 2, 3}), m, params_with(1000)).colour_error.has_value());
  EXPECT_FALSE(evaluate(m, coloured(m, Rgb{1, 2, 3}), params_with(1000)).colour_error.has_value());
}

TEST(Evaluate, ColourErrorIsTakenAtTheReferencePoints) {
  // The result A has an extra, wrongly coloured point far from the reference B.
  // At B's points (the paper's input points) A's colour is right: e_col = 0.
  Cloud a, b;
  a.points = {Vec3f(0, 0, 0), Vec3f(10, 0, 0)};
  a.colours = {Rgb{255, 0, 0}, Rgb{0, 0, 255}};
  b.points = {Vec3f(0, 0, 0)};
  b.colours = {Rgb{255, 0, 0}};
  EXPECT_EQ(*evaluate(a, b).colour_error, 0.0);
  // Swapped, the reference's blue point finds only red: (1 + 0 + 1) / 2 points.
  EXPECT_NEAR(*evaluate(b, a).colour_error, 1.0, 1e-6);
}

// ---- determinism, scale, errors ---------------------------------------------------------

void expect_same(const EvalResult& x, const EvalResult& y) {
  EXPECT_EQ(x.chamfer, y.chamfer);
  EXPECT_EQ(x.hausdorff, y.hausdorff);
  EXPECT_EQ(x.p95, y.p95);
  EXPECT_EQ(x.a_to_b.rms, y.a_to_b.rms);
  EXPECT_EQ(x.b_to_a.rms, y.b_to_a.rms);
  EXPECT_EQ(x.normal_consistency, y.normal_consistency);
  EXPECT_EQ(x.colour_error, y.colour_error);
}

TEST(Evaluate, DeterministicAcrossRunsAndThreadCounts) {
  const Mesh a = coloured(icosphere(5, 1.0), Rgb{10, 20, 30});
  Cloud b = sample_mesh(coloured(icosphere(4, 1.05), Rgb{40, 20, 0}), 30000, 77);
  const EvalResult r1 = evaluate(a, b, params_with(30000, 1));
  const EvalResult r2 = evaluate(a, b, params_with(30000, 2));
  const EvalResult r3 = evaluate(a, b, params_with(30000, 2));
  const EvalResult r0 = evaluate(a, b, params_with(30000, 0));
  expect_same(r1, r2);
  expect_same(r2, r3);
  expect_same(r1, r0);
  const EvalResult other_seed = evaluate(a, b, params_with(30000, 2, 2));
  EXPECT_NE(other_seed.a_to_b.mean, r1.a_to_b.mean);
  EXPECT_NEAR(other_seed.a_to_b.mean, r1.a_to_b.mean, 1e-3);
}

TEST(Evaluate, ScaleInvariant) {
  auto run = [](double s) {
    return evaluate(icosphere(6, 1.0 * s), icosphere(6, 1.1 * s), params_with(20000));
  };
  const EvalResult unit = run(1);
  for (double s : {1e-3, 1e3}) {
    const EvalResult r = run(s);
    EXPECT_NEAR(r.chamfer / s, unit.chamfer, 1e-4 * unit.chamfer) << "scale " << s;
    EXPECT_NEAR(r.hausdorff / s, unit.hausdorff, 1e-3 * unit.hausdorff) << "scale " << s;
    EXPECT_NEAR(r.p95 / s, unit.p95, 1e-3 * unit.p95) << "scale " << s;
    EXPECT_NEAR(*r.normal_consistency, *unit.normal_consistency, 1e-5) << "scale " << s;
  }
}

TEST(Evaluate, RejectsEmptyAndNonFiniteInput) {
  const Mesh m = icosphere(1);
  Cloud empty;
  try {
    evaluate(empty, m);
    ADD_FAILURE() << "no throw";
  } catch (const InvalidInput& e) {
    EXPECT_STREQ(e.what(), "A: empty");
  }
  try {
    evaluate(m, Mesh{});
    ADD_FAILURE() << "no throw";
  } catch (const InvalidInput& e) {
    EXPECT_STREQ(e.what(), "B: empty");
  }
  Cloud nan_cloud;
  nan_cloud.points = {Vec3f(0, 0, 0), Vec3f(std::numeric_limits<float>::quiet_NaN(), 0, 0)};
  EXPECT_THROW(evaluate(nan_cloud, m), InvalidInput);
  Mesh inf_mesh = m;
  inf_mesh.vertices[3].y() = std::numeric_limits<float>::infinity();
  EXPECT_THROW(evaluate(m, inf_mesh), InvalidInput);
  EXPECT_THROW(evaluate(m, m, params_with(0)), InvalidInput);
  EXPECT_THROW(evaluate(m, m, params_with(100, -1)), InvalidInput);
}

}  // namespace
}  // namespace station
