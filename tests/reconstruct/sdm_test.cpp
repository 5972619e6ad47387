#include "reconstruct/sdm.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <random>

#include <Eigen/Geometry>

#include "core/error.h"
#include "core/io.h"
#include "reconstruct/eval.h"
#include "test_util.h"

namespace station {
namespace {

// Points on the ellipsoid (x/a)^2 + (y/b)^2 + (z/c)^2 = 1 with outward normals
// (Fibonacci directions, pushed onto the surface).
Cloud ellipsoid_cloud(int n, const Vec3d& r) {
  Cloud c;
  const double golden = M_PI * (3 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double z = 1 - 2 * (i + 0.5) / n, rr = std::sqrt(1 - z * z);
    const Vec3d d(rr * std::cos(golden * i), rr * std::sin(golden * i), z);
    const Vec3d p = d.cwiseProduct(r);
    const Vec3d nrm = Vec3d(p.x() / (r.x() * r.x()), p.y() / (r.y() * r.y()), p.z() / (r.z() * r.z()))
                          .normalized();
    c.points.push_back(p.cast<float>());
    c.normals.push_back(nrm.cast<float>());
  }
  return c;
}

double signed_volume(const Mesh& m) {
  double v = 0;
  for (const Face& f : m.faces)
    v += m.vertices[f[0]].cast<double>().dot(
             m.vertices[f[1]].cast<double>().cross(m.vertices[f[2]].cast<double>())) /
         6.0;
  return v;
}

// Mean distance from the target's points to the fitted mesh (exact, BVH).
double mean_point_to_mesh(const Cloud& target, const Mesh& mesh) {
  Cloud a = target;
  EvalParams ep;
  ep.mesh_samples = 20000;
  const EvalResult r = evaluate(a, mesh, ep);
  return r.a_to_b.mean;
}

// The invariants every fit must keep: same topology, no folds, no self-intersections,
// outward orientation.
void expect_valid_fit(const Mesh& templ, const SdmResult& r) {
  ASSERT_EQ(r.mesh.faces, templ.faces);
  ASSERT_EQ(r.mesh.vertices.size(), templ.vertices.size());
  EXPECT_TRUE(all_finite(r.mesh.vertices));
  const MeshTopology t = mesh_topology(r.mesh);
  EXPECT_EQ(t.euler, 2);
  EXPECT_EQ(t.genus(), 0);
  EXPECT_EQ(count_folded_faces(r.mesh), 0);
  EXPECT_EQ(r.diagnostics.flipped_faces, 0);
  EXPECT_EQ(count_self_intersections(r.mesh), 0);
  EXPECT_GT(signed_volume(r.mesh), 0);
}

TEST(SdmTopology, IcosphereCountsAndGenus) {
  const Mesh m4 = make_icosphere_template(4);
  EXPECT_EQ(m4.vertices.size(), 2562u);
  EXPECT_EQ(m4.faces.size(), 5120u);
  EXPECT_EQ(make_icosphere_template(5).vertices.size(), 10242u);
  const MeshTopology t = mesh_topology(m4);
  EXPECT_EQ(t.euler, 2);
  EXPECT_EQ(t.genus(), 0);
  EXPECT_EQ(t.components, 1);
  EXPECT_EQ(count_folded_faces(m4), 0);
  EXPECT_EQ(count_self_intersections(m4), 0);
  EXPECT_GT(signed_volume(m4), 0);
  EXPECT_THROW(make_icosphere_template(-1), InvalidInput);
}

TEST(SdmTopology, DetectsIntersectionsFoldsAndBoundaries) {
  // Two interpenetrating spheres: intersections, two components. (Offset off the
  // symmetry planes: with a pure x shift the curve of intersection runs exactly
  // through mirrored edges, a degenerate case the counter leaves out.)
  Mesh a = make_icosphere_template(2), b = make_icosphere_template(2);
  const int n = int(a.vertices.size());
  for (auto& v : b.vertices) a.vertices.push_back(0.9f * v + Vec3f(0.5f, 0.13f, 0.07f));
  for (auto f : b.faces) a.faces.push_back(f + Face::Constant(n));
  a.normals.clear();
  EXPECT_GT(count_self_intersections(a), 0);
  EXPECT_EQ(mesh_topology(a).components, 2);
  EXPECT_EQ(mesh_topology(a).genus(), -1);
  // A vertex pushed over its neighbour: the faces between them fold over.
  Mesh c = make_icosphere_template(2);
  const Face f0 = c.faces[0];
  c.vertices[f0[0]] = c.vertices[f0[1]] + 1.5f * (c.vertices[f0[1]] - c.vertices[f0[0]]);
  EXPECT_GT(count_folded_faces(c), 0);
  // A face removed: boundary.
  Mesh d = make_icosphere_template(2);
  d.faces.pop_back();
  EXPECT_EQ(mesh_topology(d).boundary_edges, 3);
}

TEST(Sdm, SphereOntoEllipsoid) {
  const Vec3d r(1.0, 0.6, 0.4);
  const Cloud target = ellipsoid_cloud(20000, r);
  const Mesh templ = make_icosphere_template(3);
  SdmParams p;
  p.threads = 2;
  const SdmResult res = fit_sdm(templ, target, p);
  expect_valid_fit(templ, res);
  const double diag = 2 * r.norm();
  const double d = mean_point_to_mesh(target, res.mesh);
  EXPECT_LT(d, 0.005 * diag) << "D " << res.diagnostics.mean_distance;
  // Every vertex on the ellipsoid.
  double worst = 0;
  for (const Vec3f& v : res.mesh.vertices) {
    const Vec3d q = v.cast<double>().cwiseQuotient(r);
    worst = std::max(worst, std::abs(q.norm() - 1.0));
  }
  EXPECT_LT(worst, 0.05);
  std::printf("ellipsoid: D %.5f (diag %.3f) som %d it %.3fs energy %d rounds %.3fs anchors %d\n",
              d, diag, res.diagnostics.som_iterations, res.diagnostics.seconds_som,
              res.diagnostics.energy_rounds, res.diagnostics.seconds_energy,
              res.diagnostics.anchors);
}

}  // namespace
}  // namespace station
