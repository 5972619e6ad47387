// Closing unseen parts by the winding number of the oriented cloud
// (reconstruct/winding_close.h): the winding number itself on a closed and an open
// sphere, and the MPU surface of an open-bottomed scan closed without flaring.
#include "reconstruct/winding_close.h"

#include <gtest/gtest.h>

#include <cmath>
#include <map>
#include <random>

#include "core/error.h"
#include "reconstruct/half_space_clip.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/mpu.h"
#include "test_util.h"

namespace station {
namespace {

// Unit-sphere samples (radius r) with outward normals, leaving out z/r < min_z.
Cloud sphere_cloud(int n, double r, double min_z, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g;
  Cloud c;
  while (int(c.size()) < n) {
    const Vec3d d = Vec3d(g(rng), g(rng), g(rng)).normalized();
    if (d.z() < min_z) continue;
    c.points.push_back((r * d).cast<float>());
    c.normals.push_back(d.cast<float>());
  }
  return c;
}

TEST(WindingNumber, OneInsideZeroOutsideHalfAcrossAHole) {
  const Cloud closed = sphere_cloud(20000, 1.0, -2, 1);
  const WindingNumber w(closed.points, closed.normals, 0.05);
  EXPECT_LT(w.size(), closed.size());
  for (const Vec3d& in : {Vec3d(0, 0, 0), Vec3d(0.5, 0.2, -0.3), Vec3d(0, 0, 0.8)}) EXPECT_NEAR(w(in), 1.0, 0.05);
  for (const Vec3d& out : {Vec3d(2, 0, 0), Vec3d(0, 1.2, 0.3), Vec3d(5, 5, 5)}) EXPECT_NEAR(w(out), 0.0, 0.05);
  // The bottom cap (z < 0) missing: at the centre of the hole's plane the points
  // subtend half the sphere of directions.
  const Cloud open = sphere_cloud(10000, 1.0, 0.0, 2);
  const WindingNumber h(open.points, open.normals, 0.05);
  EXPECT_NEAR(h(Vec3d(0, 0, 0)), 0.5, 0.05);
  EXPECT_GT(h(Vec3d(0, 0, 0.5)), 0.6);
  EXPECT_LT(h(Vec3d(0, 0, -0.5)), 0.4);
  // The analytic gradient agrees with central differences away from the points.
  for (const Vec3d& q : {Vec3d(0.1, 0.2, -0.4), Vec3d(0.7, -0.9, 0.2), Vec3d(0, 0, -1.5)}) {
    Vec3d g;
    const double v = h.evaluate(q, &g);
    EXPECT_DOUBLE_EQ(v, h(q));
    for (int a = 0; a < 3; ++a) {
      Vec3d e = Vec3d::Zero();
      e[a] = 1e-5;
      EXPECT_NEAR(g[a], (h(q + e) - h(q - e)) / 2e-5, 1e-4 * (1 + g.norm())) << q.transpose() << " axis " << a;
    }
  }
  EXPECT_THROW(WindingNumber(open.points, {}, 0.05), InvalidInput);
  EXPECT_THROW(WindingNumber(open.points, open.normals, 0), InvalidInput);
}

// evaluate_near gives evaluate()'s bits for clusters of every size: tight ones (the
// whole cluster on one side of most nodes), ones as wide as the cloud (mixed at the
// top of the tree), one point, and a cluster with a non-finite point; with and
// without gradients.
TEST(WindingNumber, EvaluateNearIsEvaluateBitForBit) {
  const Cloud open = sphere_cloud(10000, 1.0, 0.0, 2);
  const WindingNumber h(open.points, open.normals, 0.05);
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1, 1);
  int checked = 0;
  for (const Vec3d& centre : {Vec3d(0, 0, 0), Vec3d(0.98, 0, 0.1), Vec3d(0, 0, -1.2), Vec3d(3, 2, 1)})
    for (double box : {1e-3, 0.02, 0.3, 2.0})
      for (int count : {1, 7, 125}) {
        std::vector<Vec3d> xs;
        for (int i = 0; i < count; ++i) xs.push_back(centre + box * Vec3d(u(rng), u(rng), u(rng)));
        std::vector<double> w(xs.size()), w2(xs.size());
        std::vector<Vec3d> g(xs.size());
        h.evaluate_near(xs.data(), count, w.data(), g.data());
        h.evaluate_near(xs.data(), count, w2.data(), nullptr);
        for (int i = 0; i < count; ++i, ++checked) {
          Vec3d ge;
          const double we = h.evaluate(xs[std::size_t(i)], &ge);
          ASSERT_EQ(w[std::size_t(i)], we) << xs[std::size_t(i)].transpose() << " box " << box;
          ASSERT_EQ(w2[std::size_t(i)], we);
          ASSERT_EQ(g[std::size_t(i)], ge) << xs[std::size_t(i)].transpose() << " box " << box;
        }
      }
  EXPECT_EQ(checked, 4 * 4 * (1 + 7 + 125));
  std::vector<Vec3d> bad{Vec3d(0.1, 0, 0), Vec3d(std::nan(""), 0, 0)};
  double w[2];
  h.evaluate_near(bad.data(), 2, w, nullptr);
  EXPECT_EQ(w[0], h(bad[0]));
  EXPECT_TRUE(std::isnan(w[1]) == std::isnan(h(bad[1])));
}

// A cup upside down, as a turntable sees it: the side and the top of a cylinder,
// no bottom. MPU's fits on the side continue the tube below the rim until the
// extraction box stops them; the winding number spans the rim instead.
TEST(WindingClose, OpenTubeIsCappedAtItsRimNotAtTheBox) {
  const double r = 0.04, half = 0.05;
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(0, 1);
  Cloud cloud;
  const double side = 2 * M_PI * r * 2 * half, top = M_PI * r * r;
  while (cloud.size() < 6000) {
    if (u(rng) < side / (side + top)) {
      const double a = 2 * M_PI * u(rng), z = -half + 2 * half * u(rng);
      cloud.points.emplace_back(float(r * std::cos(a)), float(r * std::sin(a)), float(z));
      cloud.normals.emplace_back(float(std::cos(a)), float(std::sin(a)), 0.f);
    } else {
      const double a = 2 * M_PI * u(rng), q = r * std::sqrt(u(rng));
      cloud.points.emplace_back(float(q * std::cos(a)), float(q * std::sin(a)), float(half));
      cloud.normals.emplace_back(0.f, 0.f, 1.f);
    }
  }
  const MpuSurface surface = fit_mpu(cloud);
  const WindingClose closed(surface, cloud);
  Aabb box = surface.bounds();
  const float pad = 0.5f * (box.max - box.min).maxCoeff();
  box.min.array() -= pad;
  box.max.array() += pad;
  MarchingCubesOptions o;
  o.seeds = cloud.points;
  o.close_at_box = true;
  auto lowest = [](const Mesh& m) {
    double z = 1e30;
    for (const Vec3f& v : m.vertices) z = std::min(z, double(v.z()));
    return z;
  };
  const Mesh plain = extract_marching_cubes(surface, box, 64, o);
  const Mesh m = extract_marching_cubes(closed, box, 64, o);
  const double h = (box.max - box.min).maxCoeff() / 64;
  std::printf("open tube: lowest vertex %.4f (MPU alone %.4f, box %.4f), rim at %.4f, cell %.4f\n", lowest(m),
              lowest(plain), double(box.min.z()), -half, h);
  // Without the closing the tube runs on far below the rim (the issue this solves).
  EXPECT_LT(lowest(plain), -half - 0.5 * pad);
  ASSERT_GT(m.faces.size(), 100u);
  EXPECT_EQ(test::open_edges(m), 0);
  EXPECT_GT(lowest(m), -half - 0.5 * r);
  for (const Vec3f& v : m.vertices) EXPECT_LT(std::hypot(v.x(), v.y()), r + h) << v.transpose();
}

// values_near, gradients_near and values_gradients_near (one octree walk for a
// cluster of points) give value() and gradient() bit for bit, on the MPU surface and through the wrappers the
// station puts around it (the table clip, the winding closing), for clusters near the
// data, in the closed hole, across the table plane and far out.
TEST(WindingClose, NearQueriesAreOneByOneBitForBit) {
  const double r = 0.05;
  const Cloud cloud = sphere_cloud(4000, r, -0.6, 3);
  const MpuSurface surface = fit_mpu(cloud);
  const WindingClose closed(surface, cloud);
  const HalfSpaceClip clipped(closed, Vec3d(0, 0, 1), -0.7 * r);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1, 1);
  const ImplicitFunction* fs[] = {&surface, &closed, &clipped};
  int checked = 0, blended = 0, plane = 0;
  for (const Vec3d& centre : {Vec3d(r, 0, 0), Vec3d(0, 0, -0.9 * r), Vec3d(0.3 * r, 0, -0.7 * r), Vec3d(0, 0, 0),
                              Vec3d(5 * r, 2 * r, 0)}) {
    for (double box : {0.02 * r, 0.2 * r}) {
      std::vector<Vec3d> xs;
      for (int i = 0; i < 125; ++i) xs.push_back(centre + box * Vec3d(u(rng), u(rng), u(rng)));
      for (const ImplicitFunction* f : fs) {
        std::vector<double> values(xs.size());
        std::vector<Vec3d> grads(xs.size());
        f->values_near(xs.data(), int(xs.size()), values.data());
        f->gradients_near(xs.data(), int(xs.size()), grads.data());
        std::vector<double> both_values(xs.size());
        std::vector<Vec3d> both_grads(xs.size());
        f->values_gradients_near(xs.data(), int(xs.size()), both_values.data(), both_grads.data());
        for (std::size_t i = 0; i < xs.size(); ++i, ++checked) {
          ASSERT_EQ(values[i], f->value(xs[i])) << "point " << xs[i].transpose();
          ASSERT_EQ(grads[i], f->gradient(xs[i])) << "point " << xs[i].transpose();
          ASSERT_EQ(both_values[i], values[i]) << "point " << xs[i].transpose();
          ASSERT_EQ(both_grads[i], grads[i]) << "point " << xs[i].transpose();
          if (f == &closed && grads[i] != surface.gradient(xs[i])) ++blended;
          if (f == &clipped && grads[i] == Vec3d(0, 0, -1)) ++plane;
        }
      }
    }
  }
  EXPECT_EQ(checked, 5 * 2 * 3 * 125);
  EXPECT_GT(blended, 50);  // the winding blend's branch was exercised
  EXPECT_GT(plane, 50);    // and the table plane's
  // A non-finite point falls back to one-by-one evaluation for the cluster.
  std::vector<Vec3d> bad{Vec3d(r, 0, 0), Vec3d(std::nan(""), 0, 0)};
  double out[2];
  Vec3d gout[2];
  surface.values_near(bad.data(), 2, out);
  surface.gradients_near(bad.data(), 2, gout);
  EXPECT_EQ(out[0], surface.value(bad[0]));
  EXPECT_EQ(gout[0], surface.gradient(bad[0]));
  EXPECT_TRUE(std::isnan(out[1]) == std::isnan(surface.value(bad[1])));
  double both_out[2];
  Vec3d both_gout[2];
  surface.values_gradients_near(bad.data(), 2, both_out, both_gout);
  EXPECT_EQ(both_out[0], out[0]);
  EXPECT_EQ(both_gout[0], gout[0]);
  EXPECT_TRUE(std::isnan(both_out[1]) == std::isnan(out[1]));
}

TEST(WindingClose, OpenBottomedScanClosesWithoutFlaring) {
  const double r = 0.05;
  const Cloud cloud = sphere_cloud(4000, r, -0.6, 3);
  const MpuSurface surface = fit_mpu(cloud);
  const WindingClose closed(surface, cloud);
  EXPECT_GT(closed.trust_distance(), 0);
  Aabb box = surface.bounds();
  const float pad = 0.3f * (box.max - box.min).maxCoeff();
  box.min.array() -= pad;
  box.max.array() += pad;
  MarchingCubesOptions o;
  o.seeds = cloud.points;
  o.close_at_box = true;
  auto farthest = [](const Mesh& m) {
    double far = 0;
    for (const Vec3f& v : m.vertices) far = std::max(far, double(v.norm()));
    return far;
  };
  const Mesh plain = extract_marching_cubes(surface, box, 64, o);
  const Mesh m = extract_marching_cubes(closed, box, 64, o);
  std::printf("open bottom: farthest vertex %.4f (MPU alone %.4f), sphere radius %.4f\n", farthest(m),
              farthest(plain), r);
  ASSERT_GT(m.faces.size(), 100u);
  EXPECT_EQ(test::open_edges(m), 0);
  // Nothing beyond the sphere (the hole spanned inside it); near the data the mesh
  // is MPU's (the same as without the closing).
  EXPECT_LT(farthest(m), r * 1.04);
  const double h = (box.max - box.min).maxCoeff() / 64;
  for (const Vec3f& v : m.vertices)
    if (v.z() > -0.3 * r) {
      EXPECT_NEAR(v.norm(), r, 0.5 * h) << v.transpose();
    }
  EXPECT_THROW(WindingClose(surface, Cloud{}), InvalidInput);
  Cloud bare = cloud;
  bare.normals.clear();
  EXPECT_THROW(WindingClose(surface, bare), InvalidInput);
}

}  // namespace
}  // namespace station
