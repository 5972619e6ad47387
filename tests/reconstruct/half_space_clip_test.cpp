// The turntable plane as a bound of the solid (reconstruct/half_space_clip.h):
// an analytic sphere cut flat, and an MPU surface of an open-bottomed scan whose
// closing would otherwise extend below the lowest data point.
#include "reconstruct/half_space_clip.h"

#include <gtest/gtest.h>

#include <cmath>
#include <map>
#include <random>

#include "core/error.h"
#include "reconstruct/dmc.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/mpu.h"
#include "test_util.h"

namespace station {
namespace {

struct Sphere : ImplicitFunction {
  double value(const Vec3d& x) const override { return x.norm() - 1.0; }
  Vec3d gradient(const Vec3d& x) const override { return x.normalized(); }
};

float min_z(const Mesh& m) {
  float z = 1e30f;
  for (const Vec3f& v : m.vertices) z = std::min(z, v.z());
  return z;
}

TEST(HalfSpaceClip, ValueGradientAndTrust) {
  Sphere s;
  const HalfSpaceClip c(s, Vec3d(0, 0, 2), -0.5);  // normal normalised inside
  EXPECT_DOUBLE_EQ(c.value(Vec3d(0, 0, 0)), -0.5);          // inside both
  EXPECT_DOUBLE_EQ(c.value(Vec3d(0, 0, -0.8)), 0.3);        // inside the sphere, below the plane
  EXPECT_DOUBLE_EQ(c.value(Vec3d(0, 0, 2)), 1.0);           // outside the sphere
  EXPECT_TRUE(c.gradient(Vec3d(0, 0, -0.8)).isApprox(Vec3d(0, 0, -1)));
  EXPECT_TRUE(c.gradient(Vec3d(0.9, 0, 0)).isApprox(Vec3d(1, 0, 0)));
  EXPECT_THROW(HalfSpaceClip(s, Vec3d::Zero(), 0), InvalidInput);
  EXPECT_THROW(HalfSpaceClip(s, Vec3d(0, 0, 1), std::nan("")), InvalidInput);
}

TEST(HalfSpaceClip, SphereIsCutFlatAndStaysClosed) {
  Sphere s;
  const HalfSpaceClip c(s, Vec3d(0, 0, 1), -0.5);
  Aabb box;
  box.extend(Vec3f(-1.2f, -1.2f, -1.2f));
  box.extend(Vec3f(1.2f, 1.2f, 1.2f));
  const Mesh whole = extract_dmc(s, box, 40);
  EXPECT_LT(min_z(whole), -0.98f);  // without the clip the bottom is round
  const Mesh cut = extract_dmc(c, box, 40);
  ASSERT_GT(cut.faces.size(), 100u);
  EXPECT_EQ(test::open_edges(cut), 0);
  // Crossings on DMC's deformed edges are refined to f's tolerance, not exactly: a
  // small fraction of the cell size h = 0.06.
  EXPECT_GT(min_z(cut), -0.5f - 0.003f);
  // The flat face: vertices on the plane stay within the circle the sphere cuts.
  int on_plane = 0;
  for (const Vec3f& v : cut.vertices)
    if (std::abs(v.z() + 0.5f) < 2e-3f) {
      ++on_plane;
      EXPECT_LT(std::hypot(v.x(), v.y()), std::sqrt(0.75f) + 1e-3f);
    }
  EXPECT_GT(on_plane, 20);
}

// Points on a sphere's upper part only (the cap below z = -0.6 unseen, as a
// turntable's underside): MPU closes the hole; clipped at the lowest point the
// closed mesh never goes below it.
TEST(HalfSpaceClip, MpuClosingOfAnOpenBottomStopsAtTheLowestPoint) {
  std::mt19937 rng(3);
  std::normal_distribution<double> g;
  Cloud cloud;
  while (cloud.size() < 4000) {
    const Vec3d d = Vec3d(g(rng), g(rng), g(rng)).normalized();
    if (d.z() < -0.6) continue;
    cloud.points.push_back((0.05 * d).cast<float>());
    cloud.normals.push_back(d.cast<float>());
  }
  const float lowest = 0.05f * -0.6f;
  const MpuSurface surface = fit_mpu(cloud);
  Aabb box = surface.bounds();
  const float pad = 0.05f * (box.max - box.min).maxCoeff();
  box.min.array() -= pad;
  box.max.array() += pad;
  DmcOptions o;
  o.seeds = cloud.points;
  o.close_at_box = true;
  const HalfSpaceClip clipped(surface, Vec3d(0, 0, 1), lowest);
  const Mesh m = extract_dmc(clipped, box, 48, o);
  ASSERT_GT(m.faces.size(), 100u);
  EXPECT_EQ(test::open_edges(m), 0);
  const float h = (box.max - box.min).maxCoeff() / 48;
  EXPECT_GT(min_z(m), lowest - 0.05f * h);
  // Every vertex above the cut stays near the sphere (no flare sideways either).
  for (const Vec3f& v : m.vertices) {
    if (v.z() <= lowest + 0.002f) continue;
    EXPECT_NEAR(v.norm(), 0.05f, 0.004f) << v.transpose();
  }
}

}  // namespace
}  // namespace station
