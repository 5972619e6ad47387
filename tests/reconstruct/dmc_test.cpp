#include "reconstruct/dmc.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <limits>
#include <map>
#include <numeric>
#include <random>
#include <set>

#include "core/bvh.h"
#include "core/error.h"
#include "eval/eval.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/mpu.h"
#include "test_util.h"

namespace station {
namespace {

Aabb cube_box(double r) {
  Aabb b;
  b.extend(Vec3f(-r, -r, -r));
  b.extend(Vec3f(r, r, r));
  return b;
}

struct Sphere : ImplicitFunction {
  Vec3d c;
  double r;
  Sphere(Vec3d c_, double r_) : c(c_), r(r_) {}
  double value(const Vec3d& x) const override { return (x - c).norm() - r; }
  Vec3d gradient(const Vec3d& x) const override { return (x - c).normalized(); }
};

// The paper's "contact lens": max(x^2+y^2+z^2-9, 8.9-x^2-y^2-z^2, y), a half shell
// about 0.0167 thick.
struct Lens : ImplicitFunction {
  double value(const Vec3d& x) const override {
    const double r2 = x.squaredNorm();
    return std::max({r2 - 9, 8.9 - r2, x.y()});
  }
  Vec3d gradient(const Vec3d& x) const override {
    const double r2 = x.squaredNorm();
    const double a = r2 - 9, b = 8.9 - r2, c = x.y();
    if (a >= b && a >= c) return 2 * x;
    if (b >= c) return -2 * x;
    return Vec3d::UnitY();
  }
};

// Sphere of radius 0.5 with a thin cone (the spike) along `axis`: base radius r0 at the
// sphere's centre plane, tip at distance `tip` from the centre.
struct Spike : ImplicitFunction {
  Vec3d axis;
  double r0, tip;
  Spike(double r0_, double tip_) : axis(Vec3d(1, 0.7, 0.4).normalized()), r0(r0_), tip(tip_) {}
  double cone(const Vec3d& x, Vec3d* grad) const {
    const double t = x.dot(axis);
    const Vec3d radial = x - t * axis;
    const double rho = radial.norm();
    const double tan_a = r0 / tip, cos_a = 1 / std::sqrt(1 + tan_a * tan_a);
    // Distance-like: (rho - R(t)) cos(alpha), R(t) = (tip - t) tan(alpha).
    const double side = (rho - (tip - t) * tan_a) * cos_a;
    const double back = -t;
    if (grad) {
      if (side >= back) {
        const Vec3d rdir = rho > 0 ? Vec3d(radial / rho) : Vec3d(axis.unitOrthogonal());
        *grad = (rdir + tan_a * axis) * cos_a;
      } else {
        *grad = -axis;
      }
    }
    return std::max(side, back);
  }
  double value(const Vec3d& x) const override { return std::min(x.norm() - 0.5, cone(x, nullptr)); }
  Vec3d gradient(const Vec3d& x) const override {
    Vec3d g;
    const double c = cone(x, &g);
    return x.norm() - 0.5 <= c ? Vec3d(x.normalized()) : g;
  }
};

// Cube of half side a, rotated 30 degrees about x then 30 degrees about y.
struct RotatedCube : ImplicitFunction {
  Eigen::Matrix3d R;  // object -> world
  double a;
  explicit RotatedCube(double a_) : a(a_) {
    R = (Eigen::AngleAxisd(M_PI / 6, Vec3d::UnitY()) * Eigen::AngleAxisd(M_PI / 6, Vec3d::UnitX())).toRotationMatrix();
  }
  double value(const Vec3d& x) const override { return (R.transpose() * x).cwiseAbs().maxCoeff() - a; }
  Vec3d gradient(const Vec3d& x) const override {
    const Vec3d y = R.transpose() * x;
    int k;
    y.cwiseAbs().maxCoeff(&k);
    Vec3d g = Vec3d::Zero();
    g[k] = y[k] < 0 ? -1 : 1;
    return R * g;
  }
  Vec3d corner(int c) const { return R * Vec3d(c & 1 ? a : -a, c & 2 ? a : -a, c & 4 ? a : -a); }
};

// Two slabs with a slot of width `gap` between them, normal `u`, extent 2 * 0.6 laterally.
struct Slot : ImplicitFunction {
  Eigen::Matrix3d R;  // rows: lateral 1, lateral 2, normal
  double gap, half;
  explicit Slot(double gap_) : gap(gap_), half(0.3) {
    const Vec3d u = Vec3d(1, 2, 3).normalized();
    const Vec3d e1 = u.unitOrthogonal(), e2 = u.cross(e1);
    R.row(0) = e1;
    R.row(1) = e2;
    R.row(2) = u;
  }
  double value(const Vec3d& x) const override {
    const Vec3d y = R * x;
    return std::max({std::abs(y[0]) - 0.6, std::abs(y[1]) - 0.6, std::abs(y[2]) - half, 0.5 * gap - std::abs(y[2])});
  }
  Vec3d gradient(const Vec3d& x) const override {
    const Vec3d y = R * x;
    const double v[4] = {std::abs(y[0]) - 0.6, std::abs(y[1]) - 0.6, std::abs(y[2]) - half, 0.5 * gap - std::abs(y[2])};
    const int k = int(std::max_element(v, v + 4) - v);
    Vec3d g = Vec3d::Zero();
    if (k < 3) g[k] = y[k] < 0 ? -1 : 1;
    else g[2] = y[2] < 0 ? 1 : -1;
    return R.transpose() * g;
  }
};

// A lumpy sphere r = 1 + 0.1 sin 5x cos 4y sampled at an icosphere's vertices, with
// the sphere's normals (approximate, enough for these fits).
Cloud lumpy_sphere_cloud(int level) {
  const Mesh ico = test::icosphere(level, 1.0);
  Cloud cloud;
  for (const Vec3f& v : ico.vertices) {
    const float r = 1.0f + 0.1f * std::sin(5 * v.x()) * std::cos(4 * v.y());
    cloud.points.push_back(v * r);
    cloud.normals.push_back(v.normalized());
  }
  return cloud;
}

// Every undirected edge in exactly two faces, used once in each direction (closed,
// consistently oriented 2-manifold).
int bad_edges(const Mesh& m) {
  std::map<std::pair<int, int>, int> directed;
  for (const Face& f : m.faces)
    for (int t = 0; t < 3; ++t) ++directed[{f[t], f[(t + 1) % 3]}];
  int bad = 0;
  for (const auto& [e, n] : directed)
    if (n != 1 || !directed.count({e.second, e.first})) ++bad;
  return bad;
}

int euler(const Mesh& m) {
  std::set<std::pair<int, int>> edges;
  for (const Face& f : m.faces)
    for (int t = 0; t < 3; ++t) edges.insert(std::minmax(f[t], f[(t + 1) % 3]));
  return int(m.vertices.size()) - int(edges.size()) + int(m.faces.size());
}

int degenerate_faces(const Mesh& m) {
  int n = 0;
  for (const Face& f : m.faces) {
    const Vec3d a = m.vertices[f[0]].cast<double>(), b = m.vertices[f[1]].cast<double>(),
                c = m.vertices[f[2]].cast<double>();
    if (!((b - a).cross(c - a).norm() > 0)) ++n;
  }
  return n;
}

int duplicate_vertices(const Mesh& m) {
  std::set<std::array<float, 3>> seen;
  int n = 0;
  for (const Vec3f& v : m.vertices)
    if (!seen.insert({v.x(), v.y(), v.z()}).second) ++n;
  return n;
}

int components(const Mesh& m) {
  std::vector<int> parent(m.vertices.size());
  std::iota(parent.begin(), parent.end(), 0);
  std::function<int(int)> find = [&](int x) { return parent[x] == x ? x : parent[x] = find(parent[x]); };
  for (const Face& f : m.faces)
    for (int t = 1; t < 3; ++t) parent[find(f[t])] = find(f[0]);
  std::set<int> roots;
  for (const Face& f : m.faces) roots.insert(find(f[0]));
  return int(roots.size());
}

double area(const Mesh& m) {
  double a = 0;
  for (const Face& f : m.faces)
    a += 0.5 * (m.vertices[f[1]] - m.vertices[f[0]]).cast<double>().cross((m.vertices[f[2]] - m.vertices[f[0]]).cast<double>()).norm();
  return a;
}

// Fraction of the points within `tol` of the mesh.
double covered(const Mesh& m, const std::vector<Vec3d>& pts, double tol) {
  if (m.faces.empty()) return 0;
  const TriangleBvh bvh(m);
  std::size_t n = 0;
  for (const Vec3d& p : pts) n += bvh.closest_point(p).distance <= tol;
  return double(n) / pts.size();
}

void expect_clean(const Mesh& m, const char* what) {
  EXPECT_EQ(bad_edges(m), 0) << what << ": open or non-manifold edges";
  EXPECT_EQ(degenerate_faces(m), 0) << what;
  EXPECT_EQ(duplicate_vertices(m), 0) << what;
  for (const Vec3f& v : m.vertices) ASSERT_TRUE(v.allFinite()) << what;
}

TEST(Dmc, SphereIsClosedManifoldAndOnTheSurface) {
  const Sphere s(Vec3d(0.1, -0.05, 0.02), 0.8);
  DmcStats st;
  const Mesh m = extract_dmc(s, cube_box(1), 40, {}, &st);
  ASSERT_FALSE(m.faces.empty());
  expect_clean(m, "sphere");
  EXPECT_EQ(euler(m), 2);
  EXPECT_EQ(st.degenerate_faces, 0u);
  const double h = st.cell_size;
  double worst = 0;
  for (const Vec3f& v : m.vertices) worst = std::max(worst, std::abs(s.value(v.cast<double>())));
  EXPECT_LT(worst, 1e-3 * h);  // refined crossings
  // A smooth thick surface needs no moves.
  EXPECT_EQ(st.moved_barycentre + st.moved_gap + st.moved_corner + st.moved_edge, 0u);
  // Its thin-part probes are all answered by the lattice's own values (thick
  // everywhere, every value past the surface evaluated).
  std::printf("sphere: %zu probed, %zu answered by the lattice\n", st.probed, st.lattice_thick);
  EXPECT_GT(st.probed, 0u);
  EXPECT_EQ(st.lattice_thick, st.probed);
  ASSERT_EQ(m.normals.size(), m.vertices.size());
  for (std::size_t i = 0; i < m.vertices.size(); ++i)
    EXPECT_GT(m.normals[i].dot((m.vertices[i].cast<double>() - s.c).normalized().cast<float>()), 0.99f);
}

// The crossings' refinement (Newton along the edge, value and gradient together):
// vertices far closer to the surface than the linear interpolation's, on an analytic
// sphere and on an MPU surface, and never worse at the worst vertex.
TEST(Dmc, RefinedCrossingsLieOnTheSurface) {
  const Sphere s(Vec3d(0.1, -0.05, 0.02), 0.8);
  const MpuSurface mpu = fit_mpu(lumpy_sphere_cloud(4));
  struct Err {
    double mean = 0, worst = 0;
  };
  auto error = [](const ImplicitFunction& f, const Mesh& m, double h) {
    Err e;
    for (const Vec3f& v : m.vertices) {
      const Vec3d x = v.cast<double>();
      const double d = std::abs(f.value(x)) / f.gradient(x).norm() / h;
      e.mean += d;
      e.worst = std::max(e.worst, d);
    }
    e.mean /= double(m.vertices.size());
    return e;
  };
  for (int which = 0; which < 2; ++which) {
    DmcOptions linear;
    linear.refine_steps = 0;
    DmcStats st0, st2;
    const Mesh m0 = which == 0 ? extract_dmc(s, cube_box(1), 40, linear, &st0) : extract_dmc(mpu, 48, linear, &st0);
    const Mesh m2 = which == 0 ? extract_dmc(s, cube_box(1), 40, {}, &st2) : extract_dmc(mpu, 48, {}, &st2);
    const ImplicitFunction& f = which == 0 ? static_cast<const ImplicitFunction&>(s) : mpu;
    const Err e0 = error(f, m0, st0.cell_size), e2 = error(f, m2, st2.cell_size);
    std::printf("%s: vertex error / h, linear mean %.2e worst %.2e; refined mean %.2e worst %.2e\n",
                which == 0 ? "sphere 40^3" : "MPU lumpy sphere 48^3", e0.mean, e0.worst, e2.mean, e2.worst);
    EXPECT_LT(e2.mean, 0.01 * e0.mean);
    EXPECT_LE(e2.worst, e0.worst);
    EXPECT_LT(e2.worst, 2e-3);
  }
}

TEST(Dmc, ContactLensIsAClosedShell) {
  const Lens lens;
  const Aabb box = cube_box(3.2);
  DmcStats st;
  const Mesh dmc = extract_dmc(lens, box, 120, {}, &st);
  const Mesh mc = extract_marching_cubes(lens, box, 120);
  const double h = st.cell_size;
  // Samples of the analytic surface: outer and inner half spheres, rim.
  std::mt19937 rng(7);
  std::normal_distribution<double> nd;
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<Vec3d> pts;
  for (int i = 0; i < 6000; ++i) {
    Vec3d d(nd(rng), -std::abs(nd(rng)), nd(rng));
    d.normalize();
    pts.push_back(d * (i % 2 ? 3.0 : std::sqrt(8.9)));
  }
  const double cov_dmc = covered(dmc, pts, 0.1 * h), cov_mc = covered(mc, pts, 0.1 * h);
  const double true_area = 2 * M_PI * 9 + 2 * M_PI * 8.9 + M_PI * 0.1;
  std::printf("lens: DMC %zu faces, area %.2f / %.2f, covered %.4f; MC %zu faces covered %.4f; moved %zu, "
              "searched %zu, probed %zu, answered by the lattice %zu\n",
              dmc.faces.size(), area(dmc), true_area, cov_dmc, mc.faces.size(), cov_mc, st.moved_barycentre,
              st.searched, st.probed, st.lattice_thick);
  // Closed (every edge in exactly two faces), covering the analytic surface: 99 % of
  // its samples within a tenth of a cell of the mesh, 99 % of its area (and not more:
  // no stray sheets), where MC keeps a few percent.
  EXPECT_EQ(bad_edges(dmc), 0);
  EXPECT_EQ(degenerate_faces(dmc), 0);
  // A shell thinner than a cell everywhere: the lattice takes no part for thick.
  EXPECT_EQ(st.lattice_thick, 0u);
  EXPECT_GE(cov_dmc, 0.99);
  EXPECT_LT(cov_mc, 0.1);
  EXPECT_GE(area(dmc), 0.99 * true_area);
  EXPECT_LE(area(dmc), 1.01 * true_area);
}

TEST(Dmc, ThinSpikeKeepsItsLength) {
  const Spike spike(0.02, 0.9);
  const Aabb box = cube_box(1);
  DmcStats st;
  const Mesh dmc = extract_dmc(spike, box, 80, {}, &st);
  const Mesh mc = extract_marching_cubes(spike, box, 80);
  // Reach of the spike along its axis, on the component holding the sphere (bits cut
  // off the spike do not count).
  auto reach = [&](const Mesh& m) {
    std::vector<int> parent(m.vertices.size());
    std::iota(parent.begin(), parent.end(), 0);
    std::function<int(int)> find = [&](int x) { return parent[x] == x ? x : parent[x] = find(parent[x]); };
    for (const Face& f : m.faces)
      for (int t = 1; t < 3; ++t) parent[find(f[t])] = find(f[0]);
    int main = -1;
    double lowest = 1e9;
    for (std::size_t i = 0; i < m.vertices.size(); ++i)
      if (m.vertices[i].x() < lowest) lowest = m.vertices[i].x(), main = find(int(i));
    double best = 0;
    for (std::size_t i = 0; i < m.vertices.size(); ++i)
      if (find(int(i)) == main) best = std::max(best, m.vertices[i].cast<double>().dot(spike.axis));
    return (best - 0.5) / (spike.tip - 0.5);
  };
  std::printf("spike: DMC reach %.3f (moved %zu, reverted %zu, corners %zu, searched %zu, %d components), MC reach %.3f\n",
              reach(dmc), st.moved_barycentre, st.reverted, st.moved_corner, st.searched, components(dmc), reach(mc));
  expect_clean(dmc, "spike");
  EXPECT_GE(reach(dmc), 0.95);
  EXPECT_LT(reach(mc), 0.6);
}

TEST(Dmc, RotatedCubeKeepsCornersAndEdges) {
  const RotatedCube cube(0.52);
  DmcStats st;
  const Mesh m = extract_dmc(cube, cube_box(1), 32, {}, &st);
  const double h = st.cell_size;
  expect_clean(m, "cube");
  EXPECT_EQ(euler(m), 2);
  const TriangleBvh bvh(m);
  double worst_corner = 0, worst_edge = 0, worst_near_corner = 0;
  for (int c = 0; c < 8; ++c) {
    double best = 1e9;
    for (const Vec3f& v : m.vertices) best = std::min(best, (v.cast<double>() - cube.corner(c)).norm());
    worst_corner = std::max(worst_corner, best);
  }
  for (int c = 0; c < 8; ++c)
    for (int a = 0; a < 3; ++a) {
      if (c >> a & 1) continue;
      const Vec3d p = cube.corner(c), q = cube.corner(c | 1 << a);
      for (int i = 1; i < 40; ++i) {
        const Vec3d x = p + (q - p) * (i / 40.0);
        const double d = bvh.closest_point(x).distance;
        // Within h of a corner two edges may cross the same Omega, which holds one point:
        // measured apart (docs/dmc.md).
        if (std::min((x - p).norm(), (x - q).norm()) < h) {
          worst_near_corner = std::max(worst_near_corner, d);
          continue;
        }
        worst_edge = std::max(worst_edge, d);
      }
    }
  std::printf("cube: worst corner %.4f h, worst edge %.4f h (%.4f h within h of a corner); corners moved %zu, "
              "edge points %zu, turns filled %zu\n",
              worst_corner / h, worst_edge / h, worst_near_corner / h, st.moved_corner, st.moved_edge, st.filled_turns);
  EXPECT_LT(worst_corner, 0.01 * h);
  EXPECT_LT(worst_edge, 0.01 * h);
  EXPECT_LT(worst_near_corner, 0.25 * h);
  // Plain MC rounds them.
  const Mesh mc = extract_marching_cubes(cube, cube_box(1), 32);
  const TriangleBvh mbvh(mc);
  double mc_corner = 0;
  for (int c = 0; c < 8; ++c) mc_corner = std::max(mc_corner, mbvh.closest_point(cube.corner(c)).distance);
  EXPECT_GT(mc_corner, 0.1 * h);
}

TEST(Dmc, ThinSlotStaysOpen) {
  const double h = 2.0 / 64;
  const Slot slot(0.2 * h);
  DmcStats st;
  const Mesh dmc = extract_dmc(slot, cube_box(1), 64, {}, &st);
  const Mesh mc = extract_marching_cubes(slot, cube_box(1), 64);
  // Samples of the slot's mid-plane, away from its rim.
  std::vector<Vec3d> pts;
  for (int i = 0; i < 40; ++i)
    for (int j = 0; j < 40; ++j) {
      const Vec3d y(-0.5 + i / 39.0, -0.5 + j / 39.0, 0);
      pts.push_back(slot.R.transpose() * y);
    }
  const double cov_dmc = covered(dmc, pts, 0.2 * h), cov_mc = covered(mc, pts, 0.2 * h);
  std::printf("slot: DMC mid-plane covered %.3f, %d components (gap moves %zu); MC covered %.3f, %d components\n",
              cov_dmc, components(dmc), st.moved_gap, cov_mc, components(mc));
  expect_clean(dmc, "slot");
  EXPECT_GE(cov_dmc, 0.99);
  EXPECT_LT(cov_mc, 0.2);
  // The slabs are separate closed surfaces with DMC; MC joins them (plus small bubbles
  // where lattice points fall into the slot).
  auto slabs_joined = [&](const Mesh& m) {
    std::vector<int> parent(m.vertices.size());
    std::iota(parent.begin(), parent.end(), 0);
    std::function<int(int)> find = [&](int x) { return parent[x] == x ? x : parent[x] = find(parent[x]); };
    for (const Face& f : m.faces)
      for (int t = 1; t < 3; ++t) parent[find(f[t])] = find(f[0]);
    const Vec3d u = slot.R.row(2).transpose();
    int lo = 0, hi = 0;
    for (std::size_t i = 0; i < m.vertices.size(); ++i) {
      if (m.vertices[i].cast<double>().dot(u) < m.vertices[lo].cast<double>().dot(u)) lo = int(i);
      if (m.vertices[i].cast<double>().dot(u) > m.vertices[hi].cast<double>().dot(u)) hi = int(i);
    }
    return find(lo) == find(hi);
  };
  EXPECT_EQ(components(dmc), 2);
  EXPECT_FALSE(slabs_joined(dmc));
  EXPECT_TRUE(slabs_joined(mc));
}

struct NanSphere : Sphere {
  NanSphere() : Sphere(Vec3d::Zero(), 0.7) {}
  double value(const Vec3d& x) const override {
    return x.x() > 0.3 ? std::numeric_limits<double>::quiet_NaN() : Sphere::value(x);
  }
  Vec3d gradient(const Vec3d& x) const override {
    return x.x() > 0.3 ? Vec3d::Constant(std::numeric_limits<double>::quiet_NaN()) : Sphere::gradient(x);
  }
};

struct Constant : ImplicitFunction {
  double v;
  explicit Constant(double v_) : v(v_) {}
  double value(const Vec3d&) const override { return v; }
  Vec3d gradient(const Vec3d&) const override { return Vec3d::Zero(); }
};

TEST(Dmc, BadInputGivesValidMeshesOrClearErrors) {
  const Aabb box = cube_box(1);
  // NaN in places counts as outside: a valid closed mesh, finite everywhere.
  const Mesh nan_mesh = extract_dmc(NanSphere(), box, 24);
  ASSERT_FALSE(nan_mesh.faces.empty());
  EXPECT_EQ(bad_edges(nan_mesh), 0);
  for (const Vec3f& v : nan_mesh.vertices) ASSERT_TRUE(v.allFinite());
  // No surface in the box.
  EXPECT_TRUE(extract_dmc(Constant(1), box, 24).faces.empty());
  EXPECT_TRUE(extract_dmc(Constant(std::numeric_limits<double>::quiet_NaN()), box, 24).faces.empty());
  // Inside everywhere: nothing without close_at_box, a closed lid just inside the box with it.
  EXPECT_TRUE(extract_dmc(Constant(-1), box, 24).faces.empty());
  DmcOptions closed;
  closed.close_at_box = true;
  const Mesh lid = extract_dmc(Constant(-1), box, 24, closed);
  ASSERT_FALSE(lid.faces.empty());
  expect_clean(lid, "lid");
  EXPECT_EQ(euler(lid), 2);
  // A sphere larger than the box: cut open at the box, or capped with close_at_box.
  const Sphere big(Vec3d::Zero(), 1.2);
  EXPECT_FALSE(extract_dmc(big, box, 24).faces.empty());
  const Mesh capped = extract_dmc(big, box, 24, closed);
  expect_clean(capped, "capped");

  DmcOptions o;
  try {
    extract_dmc(big, Aabb{}, 24);
    FAIL();
  } catch (const InvalidInput& e) {
    EXPECT_NE(std::string(e.what()).find("extract_dmc"), std::string::npos);
  }
  EXPECT_THROW(extract_dmc(big, box, 0), InvalidInput);
  o.search_step = -1;
  EXPECT_THROW(extract_dmc(big, box, 24, o), InvalidInput);
  o = {};
  o.threads = -2;
  EXPECT_THROW(extract_dmc(big, box, 24, o), InvalidInput);
  o = {};
  o.theta_sharp = 2;
  EXPECT_THROW(extract_dmc(big, box, 24, o), InvalidInput);
  o = {};
  o.refine_steps = -1;
  EXPECT_THROW(extract_dmc(big, box, 24, o), InvalidInput);
}

TEST(Dmc, DeterministicForAnyThreadCount) {
  // Thin parts (lens: step 1's flood), features (rotated cube: step 2), a thin slot;
  // 1, 2 and 4 threads: vertices, normals and faces identical.
  const Lens lens;
  const RotatedCube cube(0.52);
  const Slot slot(0.2 * 2.0 / 32);  // 0.2 h at 32^3 over [-1, 1]^3
  struct Case {
    const ImplicitFunction* f;
    Aabb box;
    int res;
  };
  const Case cases[] = {{&lens, cube_box(3.2), 48}, {&cube, cube_box(1), 40}, {&slot, cube_box(1), 32}};
  for (const Case& c : cases) {
    DmcOptions one;
    one.threads = 1;
    const Mesh a = extract_dmc(*c.f, c.box, c.res, one);
    ASSERT_FALSE(a.faces.empty());
    for (int threads : {2, 4}) {
      DmcOptions many;
      many.threads = threads;
      const Mesh b = extract_dmc(*c.f, c.box, c.res, many);
      ASSERT_EQ(a.vertices.size(), b.vertices.size());
      ASSERT_EQ(a.normals.size(), b.normals.size());
      ASSERT_EQ(a.faces.size(), b.faces.size());
      for (std::size_t i = 0; i < a.vertices.size(); ++i) ASSERT_EQ(a.vertices[i], b.vertices[i]);
      for (std::size_t i = 0; i < a.normals.size(); ++i) ASSERT_EQ(a.normals[i], b.normals[i]);
      for (std::size_t i = 0; i < a.faces.size(); ++i) ASSERT_EQ(a.faces[i], b.faces[i]);
    }
  }
}

TEST(Dmc, MpuSurfaceIsClosedManifold) {
  const Mesh ico = test::icosphere(3, 1.0);
  Cloud c;
  for (const Vec3f& v : ico.vertices) {
    c.points.push_back(v);
    c.normals.push_back(v.normalized());
  }
  const MpuSurface s = fit_mpu(c);
  DmcStats st;
  const Mesh m = extract_dmc(s, 32, {}, &st);
  ASSERT_FALSE(m.faces.empty());
  expect_clean(m, "mpu");
  EXPECT_EQ(euler(m), 2);
  double worst = 0;
  for (const Vec3f& v : m.vertices) worst = std::max(worst, std::abs(double(v.norm()) - 1.0));
  EXPECT_LT(worst, 0.02);
}

// On an MPU surface the feature step works only near the fit's own edge and corner
// leaves (ImplicitFunction::may_be_sharp): a noisy scan's smooth surface bends enough
// within a cell to pass the normals' test, and used to get creases there; a cube's
// edges and corners, which MPU fits as sharp, are still found.
TEST(Dmc, FeatureStepFollowsTheMpuSurfacesSharpFits) {
  // A sphere of radius 1 scanned with 0.3 % noise, normals off by a few degrees.
  std::mt19937 rng(4);
  std::normal_distribution<double> g(0, 1);
  Cloud noisy;
  for (int i = 0; i < 30000; ++i) {
    Vec3d d(g(rng), g(rng), g(rng));
    d.normalize();
    noisy.points.push_back((d * (1 + 0.003 * g(rng))).cast<float>());
    noisy.normals.push_back((d + 0.05 * Vec3d(g(rng), g(rng), g(rng))).normalized().cast<float>());
  }
  const MpuSurface sphere = fit_mpu(noisy);
  DmcOptions everywhere;
  everywhere.features_where_sharp = false;
  DmcStats st_all, st_sharp;
  const Mesh m_all = extract_dmc(sphere, 96, everywhere, &st_all);
  const Mesh m_sharp = extract_dmc(sphere, 96, {}, &st_sharp);
  std::printf("noisy sphere: MPU sharp leaves %zu; edges moved %zu / corners %zu (everywhere) -> %zu / %zu (%zu cells "
              "left as smooth)\n",
              sphere.diagnostics().leaves_by_type[2] + sphere.diagnostics().leaves_by_type[3], st_all.moved_edge,
              st_all.moved_corner, st_sharp.moved_edge, st_sharp.moved_corner, st_sharp.smooth_cells);
  expect_clean(m_sharp, "noisy sphere");
  EXPECT_EQ(euler(m_sharp), 2);
  EXPECT_GT(st_all.moved_edge + st_all.moved_corner, 20u);
  EXPECT_LT(10 * (st_sharp.moved_edge + st_sharp.moved_corner), st_all.moved_edge + st_all.moved_corner);
  EXPECT_GT(st_sharp.smooth_cells, 0u);

  // A cube of half side 0.5 sampled on its faces with exact normals: MPU fits its
  // edges and corners as sharp, and DMC still puts lattice points on them.
  const Mesh box = test::box(Vec3f(-0.5f, -0.5f, -0.5f), Vec3f(0.5f, 0.5f, 0.5f));
  const Cloud cube = sample_mesh(box, 40000, 9);
  const MpuSurface cube_fit = fit_mpu(cube);
  DmcStats st_cube;
  const Mesh m_cube = extract_dmc(cube_fit, 32, {}, &st_cube);
  const double h = st_cube.cell_size;
  double worst = 0;
  for (int c = 0; c < 8; ++c) {
    const Vec3d corner(c & 1 ? 0.5 : -0.5, c & 2 ? 0.5 : -0.5, c & 4 ? 0.5 : -0.5);
    double best = std::numeric_limits<double>::infinity();
    for (const Vec3f& v : m_cube.vertices) best = std::min(best, (v.cast<double>() - corner).norm());
    worst = std::max(worst, best);
  }
  std::printf("MPU cube: corners moved %zu, edges %zu, farthest corner %.3f h\n", st_cube.moved_corner,
              st_cube.moved_edge, worst / h);
  expect_clean(m_cube, "mpu cube");
  EXPECT_GT(st_cube.moved_corner, 0u);
  EXPECT_GT(st_cube.moved_edge, 0u);
  EXPECT_LT(worst, 0.1 * h);
}

// Timing (not a test): DMC vs MC on the analytic functions. Run with
// --gtest_also_run_disabled_tests --gtest_filter='*DmcTiming*'; STATION_DMC_RES picks the
// resolutions (default "128,256").
TEST(DmcTiming, DISABLED_AnalyticFunctions) {
  std::vector<int> res{128, 256};
  if (const char* e = std::getenv("STATION_DMC_RES")) {
    res.clear();
    for (const char* p = e; *p;) {
      res.push_back(std::atoi(p));
      while (*p && *p != ',') ++p;
      if (*p) ++p;
    }
  }
  const Sphere sphere(Vec3d(0.01, 0.02, -0.03), 0.8);
  const Lens lens;
  const Spike spike(0.02, 0.9);
  const RotatedCube cube(0.52);
  struct Case {
    const char* name;
    const ImplicitFunction* f;
    Aabb box;
  };
  const Case cases[] = {{"sphere", &sphere, cube_box(1)}, {"lens", &lens, cube_box(3.2)},
                        {"spike", &spike, cube_box(1)}, {"cube", &cube, cube_box(1)}};
  for (int r : res)
    for (const Case& c : cases) {
      auto time = [&](auto&& fn) {
        double best = 1e9;
        for (int rep = 0; rep < 3; ++rep) {
          const auto t0 = std::chrono::steady_clock::now();
          fn();
          best = std::min(best, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
        }
        return best;
      };
      MarchingCubesStats ms;
      DmcStats ds;
      std::size_t mf = 0, df = 0;
      const double tm = time([&] { mf = extract_marching_cubes(*c.f, c.box, r, {}, &ms).faces.size(); });
      const double td = time([&] { df = extract_dmc(*c.f, c.box, r, {}, &ds).faces.size(); });
      std::printf("%-6s %4d^3  MC %.3f s (%zu faces, %zu evals)  DMC %.3f s (%zu faces, %zu evals, %zu grads, "
                  "%zu probed, %zu searched)  ratio %.2f\n",
                  c.name, r, tm, mf, ms.evaluations, td, df, ds.evaluations, ds.gradient_evaluations, ds.probed,
                  ds.searched, td / tm);
      std::printf("         phases: traversal %.3f  step 1 %.3f  step 2 %.3f  mesh %.3f\n", ds.seconds_traversal,
                  ds.seconds_barycentre, ds.seconds_features, ds.seconds_mesh);
    }
  // An MPU surface (evaluations dear): a torus-like lumpy sphere sampled from a mesh.
  const MpuSurface mpu = fit_mpu(lumpy_sphere_cloud(5));
  for (int r : res) {
    const auto t0 = std::chrono::steady_clock::now();
    MarchingCubesStats ms;
    const std::size_t mf = extract_marching_cubes(mpu, r, {}, &ms).faces.size();
    const auto t1 = std::chrono::steady_clock::now();
    DmcStats ds;
    const std::size_t df = extract_dmc(mpu, r, {}, &ds).faces.size();
    const auto t2 = std::chrono::steady_clock::now();
    const double tm = std::chrono::duration<double>(t1 - t0).count(), td = std::chrono::duration<double>(t2 - t1).count();
    std::printf("mpu    %4d^3  MC %.3f s (%zu faces, %zu evals)  DMC %.3f s (%zu faces, %zu evals, %zu grads, %zu probed, "
                "%zu searched)  ratio %.2f\n",
                r, tm, mf, ms.evaluations, td, df, ds.evaluations, ds.gradient_evaluations, ds.probed, ds.searched,
                td / tm);
    std::printf("         phases: traversal %.3f  step 1 %.3f  step 2 %.3f  mesh %.3f\n", ds.seconds_traversal,
                ds.seconds_barycentre, ds.seconds_features, ds.seconds_mesh);
  }
}

}  // namespace
}  // namespace station
