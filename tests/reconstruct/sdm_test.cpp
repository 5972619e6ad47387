#include "reconstruct/sdm.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <random>

#include <Eigen/Geometry>

#include "core/error.h"
#include "core/io.h"
#include "core/mesh_topology.h"
#include "core/stanford_conf.h"
#include "core/kdtree.h"
#include "eval/eval.h"
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


// A torus as a (u, v) grid: closed, genus 1.
Mesh torus_mesh(int nu, int nv) {
  Mesh m;
  for (int i = 0; i < nu; ++i)
    for (int j = 0; j < nv; ++j) {
      const double a = 2 * M_PI * i / nu, b = 2 * M_PI * j / nv;
      m.vertices.push_back(Vec3f(float((1 + 0.4 * std::cos(b)) * std::cos(a)),
                                 float((1 + 0.4 * std::cos(b)) * std::sin(a)), float(0.4 * std::sin(b))));
    }
  for (int i = 0; i < nu; ++i)
    for (int j = 0; j < nv; ++j) {
      const int a = i * nv + j, b = ((i + 1) % nu) * nv + j, c = ((i + 1) % nu) * nv + (j + 1) % nv,
                d = i * nv + (j + 1) % nv;
      m.faces.push_back({a, b, c});
      m.faces.push_back({a, c, d});
    }
  return m;
}

Cloud sampled(const std::filesystem::path& path, int n) {
  const Mesh m = read_mesh(path);
  return sample_mesh(m, n, 11);
}

void print_diag(const char* name, const SdmResult& r, double d) {
  const auto& g = r.diagnostics;
  std::printf("%s: D %.6f (%.3f%% of diag) som %d steps %.3fs, energy %d rounds %.3fs, total %.3fs\n",
              name, d, 100 * d / g.diagonal, g.som_iterations, g.seconds_som, g.energy_rounds,
              g.seconds_energy, g.seconds_total);
}

TEST(Sdm, SphereOntoFandiskWithSharpFeatures) {
  const auto path = test::source_dir() / "tests/data/consolidation/fandisk.off";
  const Cloud target = sampled(path, 10000);
  const Mesh templ = make_icosphere_template(3);  // level 4 and more points: docs/sdm.md
  SdmParams p;
  p.threads = 2;
  const SdmResult res = fit_sdm(templ, target, p);
  expect_valid_fit(templ, res);
  const double diag = bounding_box(target.points).diagonal();
  const double d = mean_point_to_mesh(target, res.mesh);
  EXPECT_LT(d, 0.005 * diag);
  // And the mesh lies on the fandisk (not only the points near the mesh).
  EvalParams ep;
  ep.mesh_samples = 20000;
  const EvalResult e = evaluate(res.mesh, read_mesh(path), ep);
  EXPECT_LT(e.a_to_b.mean, 0.005 * diag);
  print_diag("fandisk", res, d);
}

TEST(Sdm, SphereOntoMustardBottle) {
  const auto path = test::source_dir() / "data/mustard_bottle/textured.obj";
  const Cloud target = sampled(path, 10000);
  const Mesh templ = make_icosphere_template(3);  // level 4 and more points: docs/sdm.md
  SdmParams p;
  p.threads = 2;
  const SdmResult res = fit_sdm(templ, target, p);
  expect_valid_fit(templ, res);
  const double diag = bounding_box(target.points).diagonal();
  const double d = mean_point_to_mesh(target, res.mesh);
  EXPECT_LT(d, 0.005 * diag);
  print_diag("mustard", res, d);
}

TEST(Sdm, UndersideRemovedGivesClosedMesh) {
  const Vec3d r(1.0, 0.7, 0.5);
  const Cloud full = ellipsoid_cloud(20000, r);
  Cloud top;  // the bottom 30 % of the height never seen
  for (std::size_t i = 0; i < full.size(); ++i)
    if (full.points[i].z() > -0.2f) {
      top.points.push_back(full.points[i]);
      top.normals.push_back(full.normals[i]);
    }
  const Mesh templ = make_icosphere_template(3);
  SdmParams p;
  p.threads = 2;
  const SdmResult res = fit_sdm(templ, top, p);
  expect_valid_fit(templ, res);
  const MeshTopology t = mesh_topology(res.mesh);
  EXPECT_TRUE(t.closed_manifold());
  EXPECT_EQ(t.boundary_edges, 0);
  EXPECT_LT(mean_point_to_mesh(top, res.mesh), 0.005 * 2 * r.norm());
  // The hole is spanned, not ballooned: nothing far below the cut or outside the
  // ellipsoid's box.
  for (const Vec3f& v : res.mesh.vertices) {
    EXPECT_GT(v.z(), -0.2f - 0.15f);
    EXPECT_LT(v.head<2>().cwiseAbs().cwiseQuotient(r.head<2>().cast<float>()).maxCoeff(), 1.05f);
  }
}

TEST(Sdm, LandmarksEndOnTheirPoints) {
  const Vec3d r(1.0, 0.6, 0.4);
  const Cloud target = ellipsoid_cloud(20000, r);
  const Mesh templ = make_icosphere_template(3);
  // Six template vertices pinned to the ellipsoid points in their directions turned
  // by 25 degrees about z: the fit has to twist to honour them.
  std::vector<Landmark> lm;
  const double turn = 25 * M_PI / 180;
  for (int v : {0, 3, 5, 8, 100, 400}) {
    const Vec3d d = templ.vertices[v].cast<double>();
    const Vec3d e(std::cos(turn) * d.x() - std::sin(turn) * d.y(),
                  std::sin(turn) * d.x() + std::cos(turn) * d.y(), d.z());
    // Point of the ellipsoid in direction e.
    const double s = 1 / e.cwiseQuotient(r).norm();
    lm.push_back({v, (s * e).cast<float>()});
  }
  SdmParams p;
  p.threads = 2;
  const SdmResult res = fit_sdm(templ, target, p, lm);
  expect_valid_fit(templ, res);
  // The control points' spacing: mean nearest-neighbour distance of the whole cloud.
  const PointIndex index(target.points);
  double spacing = 0;
  for (const Vec3f& q : target.points) spacing += index.knn(q, 2)[1].second;
  spacing /= double(target.size());
  for (const auto& l : lm)
    EXPECT_LT((res.mesh.vertices[l.vertex] - l.point).norm(), spacing) << "landmark vertex " << l.vertex;
  EXPECT_LT(mean_point_to_mesh(target, res.mesh), 0.005 * 2 * r.norm());
}

TEST(Sdm, SameResultForAnyThreadCount) {
  const Cloud target = ellipsoid_cloud(5000, Vec3d(1.0, 0.8, 0.5));
  const Mesh templ = make_icosphere_template(2);
  SdmParams p;
  p.threads = 1;
  const SdmResult a = fit_sdm(templ, target, p);
  p.threads = 2;
  const SdmResult b = fit_sdm(templ, target, p);
  EXPECT_EQ(a.mesh.vertices, b.mesh.vertices);
}

TEST(Sdm, CoarseToFineKeepsIcosphereNumbering) {
  const Cloud target = ellipsoid_cloud(20000, Vec3d(1.0, 0.6, 0.4));
  SdmParams p;
  p.threads = 2;
  const SdmResult res = fit_sdm_icosphere(4, target, p, {}, {}, 3);
  const Mesh templ = make_icosphere_template(4);
  expect_valid_fit(templ, res);
  EXPECT_LT(mean_point_to_mesh(target, res.mesh), 0.003 * 2 * Vec3d(1.0, 0.6, 0.4).norm());
}

TEST(Sdm, TargetWithoutNormalsGetsThemEstimated) {
  Cloud target = ellipsoid_cloud(8000, Vec3d(1.0, 0.6, 0.4));
  target.normals.clear();
  const Mesh templ = make_icosphere_template(2);
  SdmParams p;
  p.threads = 2;
  const SdmResult res = fit_sdm(templ, target, p);
  EXPECT_TRUE(res.diagnostics.normals_estimated);
  expect_valid_fit(templ, res);
  EXPECT_LT(mean_point_to_mesh(target, res.mesh), 0.01 * 2 * Vec3d(1.0, 0.6, 0.4).norm());
}

TEST(Sdm, BadInputIsRefusedClearly) {
  const Cloud target = ellipsoid_cloud(3000, Vec3d(1.0, 0.6, 0.4));
  const Mesh sphere = make_icosphere_template(2);
  auto message = [&](const Mesh& templ, const Cloud& cloud, const std::vector<Landmark>& lm = {}) {
    try {
      fit_sdm(templ, cloud, SdmParams{}, lm);
    } catch (const InvalidInput& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  // Genus 1 template.
  EXPECT_NE(message(torus_mesh(24, 12), target).find("genus 1"), std::string::npos);
  // Open template.
  Mesh open = sphere;
  open.faces.pop_back();
  EXPECT_NE(message(open, target).find("boundary edges"), std::string::npos);
  // Too few control points.
  Cloud few;
  few.points.assign(target.points.begin(), target.points.begin() + 20);
  few.normals.assign(target.normals.begin(), target.normals.begin() + 20);
  EXPECT_NE(message(sphere, few).find("control points"), std::string::npos);
  // Non-finite points.
  Cloud nan = target;
  nan.points[7].x() = std::nanf("");
  EXPECT_NE(message(sphere, nan).find("non-finite"), std::string::npos);
  // Every control point at one place: the template would collapse onto it.
  Cloud same = target;
  for (Vec3f& q : same.points) q = Vec3f(1, 2, 3);
  EXPECT_NE(message(sphere, same).find("all points coincide"), std::string::npos);
  // Landmarks out of range / pinned twice.
  EXPECT_NE(message(sphere, target, {{100000, Vec3f::Zero()}}).find("landmark 0"), std::string::npos);
  EXPECT_NE(message(sphere, target, {{1, Vec3f::Zero()}, {1, Vec3f::Ones()}}).find("landmark 1"),
            std::string::npos);
  EXPECT_THROW(fit_sdm(Mesh{}, target), InvalidInput);
  // A template whose faces wind inwards (was fitted, its normals facing in).
  Mesh inside_out = sphere;
  for (Face& f : inside_out.faces) std::swap(f[1], f[2]);
  EXPECT_NE(message(inside_out, target).find("faces wind inwards"), std::string::npos);
  // A mesh to parameterise with no area at all (every face on one point).
  Mesh flat = sphere;
  for (Vec3f& v : flat.vertices) v = Vec3f(1, 2, 3);
  try {
    sdm_parameterise(flat, SimpleSurface::kSphere, SdmParams{}, 0);
    ADD_FAILURE() << "a mesh without area was parameterised";
  } catch (const InvalidInput& e) {
    EXPECT_NE(std::string(e.what()).find("every face has zero area"), std::string::npos) << e.what();
  }
}

TEST(Sdm, ReadLandmarks) {
  test::TempDir dir;
  const auto good = dir / "lm.txt";
  {
    std::ofstream f(good);
    f << "# vertex x y z\n12 0.5 -1 2e-3\n\n  7 1 2 3\n";
  }
  const auto lm = read_landmarks(good.string());
  ASSERT_EQ(lm.size(), 2u);
  EXPECT_EQ(lm[0].vertex, 12);
  EXPECT_FLOAT_EQ(lm[0].point.z(), 2e-3f);
  EXPECT_EQ(lm[1].vertex, 7);
  const auto bad = dir / "bad.txt";
  {
    std::ofstream f(bad);
    f << "1 2 3 4\n5 6 seven 8\n";
  }
  try {
    read_landmarks(bad.string());
    FAIL() << "no error";
  } catch (const FormatError& e) {
    EXPECT_NE(std::string(e.what()).find(":2:"), std::string::npos) << e.what();
  }
  EXPECT_THROW(read_landmarks((dir / "missing.txt").string()), IoError);
}


// A lumpy closed genus-0 mesh: an icosphere stretched and bumped.
Mesh lumpy(int level, const Vec3f& scale) {
  Mesh m = make_icosphere_template(level);
  for (auto& v : m.vertices) {
    const float bump = 1 + 0.15f * std::sin(3 * v.x()) * std::cos(2 * v.y());
    v = bump * v.cwiseProduct(scale);
  }
  m.normals.clear();
  return m;
}

TEST(SdmParameterise, SphereGivesOneToOneMapAndUvs) {
  const Mesh m = lumpy(3, Vec3f(1.0f, 0.7f, 0.5f));
  SdmParams p;
  p.threads = 2;
  const ParameterisationResult r = sdm_parameterise(m, SimpleSurface::kSphere, p);
  ASSERT_EQ(r.uv.size(), m.vertices.size());
  EXPECT_EQ(r.mesh.faces, m.faces);
  for (const Vec3f& v : r.mesh.vertices) EXPECT_NEAR(v.norm(), 1.0, 0.03);
  EXPECT_EQ(count_folded_faces(r.mesh), 0);
  EXPECT_EQ(count_self_intersections(r.mesh), 0);
  for (const Face& f : r.mesh.faces) {  // every face faces outwards on the sphere
    const Vec3f n = (r.mesh.vertices[f[1]] - r.mesh.vertices[f[0]])
                        .cross(r.mesh.vertices[f[2]] - r.mesh.vertices[f[0]]);
    EXPECT_GT(n.dot(r.mesh.vertices[f[0]] + r.mesh.vertices[f[1]] + r.mesh.vertices[f[2]]), 0);
  }
  for (const Vec2f& uv : r.uv) {
    EXPECT_GE(uv.minCoeff(), 0.f);
    EXPECT_LE(uv.maxCoeff(), 1.f);
  }
}

// Low-poly meshes: the fold test used to compare a face with the faces across its
// edges only, and on a tetrahedron or a square pyramid (valence-3 corners) those
// normals sum against every face; the repair then smoothed the mesh into a point
// (all four vertices at one spot, every face "flipped").
TEST(SdmParameterise, LowPolyMeshesMapOntoTheSphere) {
  Mesh tet;
  tet.vertices = {Vec3f(1, 1, 1), Vec3f(-1, -1, 1), Vec3f(-1, 1, -1), Vec3f(1, -1, -1)};
  tet.faces = {Face(0, 2, 1), Face(0, 1, 3), Face(0, 3, 2), Face(1, 2, 3)};
  EXPECT_EQ(count_folded_faces(tet), 0);
  Mesh pyramid;
  pyramid.vertices = {Vec3f(1, 1, 0), Vec3f(-1, 1, 0), Vec3f(-1, -1, 0), Vec3f(1, -1, 0),
                      Vec3f(0, 0, 1.5f)};
  pyramid.faces = {Face(0, 1, 4), Face(1, 2, 4), Face(2, 3, 4),
                   Face(3, 0, 4), Face(0, 2, 1), Face(0, 3, 2)};
  EXPECT_EQ(count_folded_faces(pyramid), 0);
  SdmParams p;
  p.threads = 2;
  for (const Mesh* m : {&tet, &pyramid}) {
    SCOPED_TRACE(m->vertices.size());
    ASSERT_TRUE(mesh_topology(*m).closed_manifold());
    const ParameterisationResult r = sdm_parameterise(*m, SimpleSurface::kSphere, p);
    EXPECT_EQ(count_folded_faces(r.mesh), 0);
    for (const Face& f : r.mesh.faces) {  // every face faces outwards on the sphere
      const Vec3f n = (r.mesh.vertices[f[1]] - r.mesh.vertices[f[0]])
                          .cross(r.mesh.vertices[f[2]] - r.mesh.vertices[f[0]]);
      EXPECT_GT(n.dot(r.mesh.vertices[f[0]] + r.mesh.vertices[f[1]] + r.mesh.vertices[f[2]]), 0);
    }
    // The vertices spread over the sphere: no two within 30 degrees of each other.
    for (std::size_t i = 0; i < r.mesh.vertices.size(); ++i)
      for (std::size_t j = i + 1; j < r.mesh.vertices.size(); ++j)
        EXPECT_LT(r.mesh.vertices[i].normalized().dot(r.mesh.vertices[j].normalized()),
                  std::cos(0.5236f))
            << i << " " << j;
  }
}

TEST(SdmParameterise, CylinderWithCaps) {
  const Mesh m = lumpy(3, Vec3f(0.5f, 0.5f, 1.2f));
  SdmParams p;
  p.threads = 2;
  const ParameterisationResult r = sdm_parameterise(m, SimpleSurface::kCylinder, p);
  EXPECT_EQ(count_folded_faces(r.mesh), 0);
  EXPECT_EQ(count_self_intersections(r.mesh), 0);
  for (const Vec3f& v : r.mesh.vertices) {
    // Distance to the closed cylinder's surface.
    const float rr = v.head<2>().norm(), dz = std::abs(v.z()) - 1;
    const float d = rr <= 1 && dz <= 0 ? std::min(1 - rr, -dz)
                                       : Eigen::Vector2f(std::max(rr - 1, 0.f), std::max(dz, 0.f)).norm();
    EXPECT_LT(d, 0.05f);
  }
  for (const Vec2f& uv : r.uv) {
    EXPECT_GE(uv.minCoeff(), 0.f);
    EXPECT_LE(uv.maxCoeff(), 1.f);
  }
}

TEST(SdmParameterise, PlaneForADisc) {
  // The upper cap of a lumpy sphere (faces above z = -0.2): a disc.
  const Mesh full = lumpy(3, Vec3f(1.0f, 0.8f, 0.9f));
  Mesh cap;
  std::vector<int> remap(full.vertices.size(), -1);
  for (const Face& f : full.faces) {
    const Vec3f c = (full.vertices[f[0]] + full.vertices[f[1]] + full.vertices[f[2]]) / 3;
    if (c.z() < -0.2f) continue;
    Face g;
    for (int k = 0; k < 3; ++k) {
      if (remap[f[k]] < 0) {
        remap[f[k]] = int(cap.vertices.size());
        cap.vertices.push_back(full.vertices[f[k]]);
      }
      g[k] = remap[f[k]];
    }
    cap.faces.push_back(g);
  }
  ASSERT_EQ(mesh_topology(cap).euler, 1);
  SdmParams p;
  p.threads = 2;
  const ParameterisationResult r = sdm_parameterise(cap, SimpleSurface::kPlane, p);
  // Every UV triangle keeps its orientation (a one-to-one map onto the disc).
  int flipped = 0;
  for (const Face& f : cap.faces) {
    const Vec2f a = r.uv[f[0]], b = r.uv[f[1]], c = r.uv[f[2]];
    if ((b - a).x() * (c - a).y() - (b - a).y() * (c - a).x() <= 0) ++flipped;
  }
  EXPECT_EQ(flipped, 0);
  for (const Vec2f& uv : r.uv) EXPECT_LE((uv - Vec2f(0.5f, 0.5f)).norm(), 0.5f + 1e-4f);
  // A closed mesh is refused for the plane.
  EXPECT_THROW(sdm_parameterise(full, SimpleSurface::kPlane, p), InvalidInput);
}


// The real dragon: the 15 turntable scans bundled in data/dragon_stand (every 5th
// point of Stanford's scans, 93,846 points) merged with Stanford's alignment, normals
// estimated, fitted by a level-5 icosphere (10,242 vertices): issue 8's regression.
TEST(SdmRealData, DragonLevel5) {
  const Cloud target = merge_stanford_scans(test::source_dir() / "data/dragon_stand/dragonStandRight.conf");
  ASSERT_GT(target.size(), 90000u);
  SdmParams p;
  p.threads = 2;
  const SdmResult res = fit_sdm_icosphere(5, target, p);
  const Mesh templ = make_icosphere_template(5);
  EXPECT_TRUE(res.diagnostics.normals_estimated);
  expect_valid_fit(templ, res);
  const double diag = res.diagnostics.diagonal;
  const double d = mean_point_to_mesh(target, res.mesh);
  print_diag("dragon", res, d);
  // Regression bound (docs/sdm.md has the measured value), with margin.
  EXPECT_LT(d, 0.002 * diag);  // measured 0.125 % (2026-12-01)
}


// Timings for docs/sdm.md (not a unit test: run with --gtest_also_run_disabled_tests
// --gtest_filter='*DISABLED_Benchmark*'). 100,000 points, 2 threads, levels 4 and 5.
TEST(SdmBench, DISABLED_Benchmark) {
  for (const char* rel : {"tests/data/consolidation/fandisk.off", "data/mustard_bottle/textured.obj"}) {
    const Mesh src = read_mesh(test::source_dir() / rel);
    const Cloud target = sample_mesh(src, 100000, 5);
    for (int level : {4, 5}) {
      SdmParams p;
      p.threads = 2;
      const SdmResult r = fit_sdm_icosphere(level, target, p);
      EvalParams ep;
      ep.mesh_samples = 100000;
      const EvalResult e = evaluate(r.mesh, src, ep);
      const auto& g = r.diagnostics;
      std::printf("%s level %d: %.2f s (phase 1 %.2f s, phase 2 %.2f s, %d rounds), D %.3f%% of "
                  "diag, mesh->surface %.3f%%, surface->mesh %.3f%%, folds %d, intersections %d\n",
                  rel, level, g.seconds_total, g.seconds_som, g.seconds_energy, g.energy_rounds,
                  100 * g.mean_distance / g.diagonal, 100 * e.a_to_b.mean / g.diagonal,
                  100 * e.b_to_a.mean / g.diagonal, g.flipped_faces, count_self_intersections(r.mesh));
    }
  }
}

}  // namespace
}  // namespace station
