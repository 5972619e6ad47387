#include "reconstruct/mpu.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <cmath>
#include <functional>
#include <random>
#include <limits>
#include <map>
#include <set>

#include "core/error.h"
#include "eval/eval.h"
#include "reconstruct/dmc.h"
#include "reconstruct/marching_cubes.h"
#include "test_util.h"

namespace station {
namespace {

Cloud sphere_cloud(int n, double r) { return test::fibonacci_sphere(n, r); }

// Torus around z (major R, minor r), seeded uniform angles.
Cloud torus_cloud(int n, double R, double r, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 2 * M_PI);
  Cloud c;
  for (int i = 0; i < n; ++i) {
    const double a = u(rng), b = u(rng);
    const Vec3d nrm(std::cos(b) * std::cos(a), std::cos(b) * std::sin(a), std::sin(b));
    const Vec3d p = Vec3d(R * std::cos(a), R * std::sin(a), 0) + r * nrm;
    c.points.push_back(p.cast<float>());
    c.normals.push_back(nrm.cast<float>());
  }
  return c;
}
double torus_distance(const Vec3d& p, double R, double r) {
  const double q = std::hypot(p.x(), p.y()) - R;
  return std::abs(std::hypot(q, p.z()) - r);
}

double max_abs_f_normalised(const MpuSurface& s, const Cloud& c) {
  double worst = 0;
  for (const Vec3f& p : c.points) worst = std::max(worst, std::abs(s.value(p.cast<double>())) * s.scale());
  return worst;
}

// Every undirected edge shared by exactly two faces.
void expect_closed(const Mesh& m) {
  std::map<std::pair<int, int>, int> count;
  for (const Face& f : m.faces)
    for (int t = 0; t < 3; ++t) ++count[std::minmax(f[t], f[(t + 1) % 3])];
  int bad = 0;
  for (const auto& [e, n] : count) bad += n != 2;
  EXPECT_EQ(bad, 0);
}

void expect_finite(const Mesh& m) {
  ASSERT_TRUE(all_finite(m.vertices));
  ASSERT_TRUE(all_finite(m.normals));
}

TEST(Mpu, SphereFitsTheSamplesAndMeshesAccurately) {
  const Cloud c = sphere_cloud(3000, 1.0);
  const MpuSurface s = fit_mpu(c);
  EXPECT_LT(max_abs_f_normalised(s, c), s.params().epsilon0);
  // Sign convention: negative inside, positive outside; gradient outward.
  EXPECT_LT(s.value(Vec3d::Zero()), 0);
  EXPECT_GT(s.value(Vec3d(1.3, 0, 0)), 0);
  EXPECT_GT(s.gradient(Vec3d(0, 0.99, 0)).normalized().dot(Vec3d::UnitY()), 0.99);
  MarchingCubesStats st;
  const Mesh m = extract_marching_cubes(s, 64, {}, &st);
  expect_finite(m);
  double mean = 0;
  for (const Vec3f& v : m.vertices) mean += std::abs(v.cast<double>().norm() - 1.0);
  mean /= m.vertices.size();
  const double diag = s.bounds().diagonal();
  EXPECT_LT(mean, 0.002 * diag) << "mean distance " << mean;
  EXPECT_GT(m.faces.size(), 5000u);
}

TEST(Mpu, GradientMatchesFiniteDifferencesAndBatchesAgree) {
  const Cloud c = torus_cloud(4000, 1.0, 0.35, 3);
  const MpuSurface s = fit_mpu(c);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1.3, 1.3);
  std::vector<Vec3d> xs;
  for (int i = 0; i < 50; ++i) xs.emplace_back(u(rng), u(rng), 0.3 * u(rng));
  const auto vals = s.values(xs);
  const auto grads = s.gradients(xs);
  for (std::size_t i = 0; i < xs.size(); ++i) {
    EXPECT_EQ(vals[i], s.value(xs[i]));
    const double e = 1e-6;
    Vec3d fd;
    for (int a = 0; a < 3; ++a) {
      Vec3d d = Vec3d::Zero();
      d[a] = e;
      fd[a] = (s.value(xs[i] + d) - s.value(xs[i] - d)) / (2 * e);
    }
    EXPECT_LT((fd - grads[i]).norm(), 1e-4 * std::max(1.0, fd.norm())) << i;
  }
}

TEST(Mpu, TorusMeshIsCloseAndGenusOne) {
  const Cloud c = torus_cloud(6000, 1.0, 0.35, 1);
  const MpuSurface s = fit_mpu(c);
  EXPECT_LT(max_abs_f_normalised(s, c), s.params().epsilon0);
  const Mesh m = extract_marching_cubes(s, 64);
  expect_finite(m);
  double mean = 0;
  for (const Vec3f& v : m.vertices) mean += torus_distance(v.cast<double>(), 1.0, 0.35);
  mean /= m.vertices.size();
  EXPECT_LT(mean, 0.002 * s.bounds().diagonal());
  std::set<std::pair<int, int>> edges;
  for (const Face& f : m.faces)
    for (int t = 0; t < 3; ++t) edges.insert(std::minmax(f[t], f[(t + 1) % 3]));
  EXPECT_EQ(int(m.vertices.size()) - int(edges.size()) + int(m.faces.size()), 0);
  const auto& d = s.diagnostics();
  EXPECT_EQ(d.leaves, d.leaves_by_type[0] + d.leaves_by_type[1] + d.leaves_by_type[2] + d.leaves_by_type[3]);
}

TEST(Mpu, DeterministicAcrossThreads) {
  const Cloud c = torus_cloud(3000, 1.0, 0.35, 2);
  MpuParams p1, p2;
  p1.threads = 1;
  p2.threads = 2;
  const MpuSurface a = fit_mpu(c, p1), b = fit_mpu(c, p2);
  EXPECT_EQ(a.diagnostics().cells, b.diagnostics().cells);
  for (int i = 0; i < 200; ++i) {
    const Vec3d x = c.points[i * 7].cast<double>() * 1.1;
    EXPECT_EQ(a.value(x), b.value(x));
  }
}

// Queries far from the data (beyond the range where the walk's float bounds are
// used, docs/mpu.md "Evaluation") take the exact tests: no leaf holds them, so f is
// the distance to the root centre and the gradient points away from it; just inside
// that range, where the float bounds are used, the same holds.
TEST(Mpu, FarQueriesAreBeyondEverySupport) {
  const Cloud c = torus_cloud(3000, 1.0, 0.35, 2);
  const MpuSurface s = fit_mpu(c);
  const Vec3d centre = s.center();
  for (const double normalised : {1.9, 2.1, 50.0}) {
    for (const Vec3d& dir : {Vec3d(1, 0, 0), Vec3d(0, -1, 0), Vec3d(1, 1, 1).normalized()}) {
      const Vec3d x = centre + dir * (normalised / s.scale());
      EXPECT_EQ(s.weight_sum(x), 0.0);
      EXPECT_NEAR(s.value(x), (x - centre).norm(), 1e-9 * (x - centre).norm());
      EXPECT_NEAR(s.gradient(x).dot(dir), 1.0, 1e-9);
    }
  }
  // Near the data both paths agree with the surface: f changes sign across it.
  EXPECT_LT(s.value(Vec3d(1.0, 0, 0)), 0.0);
  EXPECT_GT(s.value(Vec3d(1.0, 0, 0.5)), 0.0);
}

// A part of a cloud fit in the whole cloud's frame (MpuParams::frame, with the whole
// fit's spacing) is the whole fit there, value for value (the blocks of
// reconstruct/blocks.h rely on it); in its own frame its octree, its epsilon0 in input
// units and so its fits differ (measured: 1.7e-3 at radius 0.1).
TEST(Mpu, APartInTheWholesFrameIsTheWholeFitThere) {
  std::mt19937 rng(4);
  std::normal_distribution<double> g(0, 1);
  Cloud c;
  while (c.size() < 30000) {
    Vec3d d(g(rng), g(rng), g(rng));
    d.normalize();
    const double r = 0.1 * (1 + 0.15 * std::sin(5 * d.x()) * std::cos(4 * d.y()));
    c.points.push_back((r * d).cast<float>());
    c.normals.push_back(d.cast<float>());
  }
  MpuParams mp;
  mp.epsilon0 = 1e-3;
  const MpuSurface whole = fit_mpu(c, mp);
  Cloud part;
  for (std::size_t i = 0; i < c.size(); ++i)
    if (c.points[i].x() < 0.03f) {
      part.points.push_back(c.points[i]);
      part.normals.push_back(c.normals[i]);
    }
  MpuParams framed = mp;
  framed.frame = bounding_box(c.points);
  framed.mean_spacing = whole.diagnostics().mean_spacing;
  const MpuSurface in_frame = fit_mpu(part, framed), own = fit_mpu(part, mp);
  double framed_diff = 0, own_diff = 0;
  int probes = 0;
  while (probes < 600) {  // on and near the surface, well inside the part (x < -0.027)
    Vec3d d(g(rng), g(rng), g(rng));
    d.normalize();
    if (d.x() > -0.3) continue;
    for (double s : {0.9, 1.0, 1.1}) {
      const Vec3d x = s * 0.1 * d;
      framed_diff = std::max(framed_diff, std::abs(in_frame.value(x) - whole.value(x)));
      own_diff = std::max(own_diff, std::abs(own.value(x) - whole.value(x)));
      ++probes;
    }
  }
  EXPECT_LT(framed_diff, 1e-12);
  EXPECT_GT(own_diff, 1e-4);
  // The part's own spacing is still the one reported.
  EXPECT_NEAR(in_frame.diagnostics().mean_spacing, own.diagnostics().mean_spacing,
              1e-5 * own.diagnostics().mean_spacing);
  // A frame that does not hold the points is refused.
  MpuParams small = mp;
  small.frame = bounding_box(part.points);
  EXPECT_THROW((void)fit_mpu(c, small), InvalidInput);
  MpuParams bad = mp;
  bad.mean_spacing = -1;
  EXPECT_THROW((void)fit_mpu(c, bad), InvalidInput);
  MpuParams endless = mp;
  endless.frame = bounding_box(c.points);
  endless.frame.max.x() = std::numeric_limits<float>::infinity();
  EXPECT_THROW((void)fit_mpu(c, endless), InvalidInput);
  MpuParams flat = mp;
  flat.frame.min = flat.frame.max = Vec3f::Zero();
  EXPECT_THROW((void)fit_mpu(c, flat), InvalidInput);
}

TEST(Mpu, ScaleInvariant) {
  // The same sphere at 1, 1e-3 and 1e3: same fit in the normalised frame, so f / scale
  // agrees (up to float rounding of the input).
  std::vector<double> probes;
  for (double scale : {1.0, 1e-3, 1e3}) {
    Cloud c = sphere_cloud(2000, 1.0);
    for (Vec3f& p : c.points) p = (p.cast<double>() * scale).cast<float>();
    const MpuSurface s = fit_mpu(c);
    EXPECT_LT(max_abs_f_normalised(s, c), s.params().epsilon0) << scale;
    for (const Vec3d& x : {Vec3d(0, 0, 0), Vec3d(0.5, 0.2, -0.1), Vec3d(0.9, 0.3, 0.3)})
      probes.push_back(s.value(x * scale) / scale);
  }
  for (int i = 0; i < 3; ++i) {
    EXPECT_LT(probes[i], 0);
    EXPECT_NEAR(probes[i], probes[3 + i], 1e-4);
    EXPECT_NEAR(probes[i], probes[6 + i], 1e-4);
  }
}

TEST(Mpu, UntrustedRegionsCanBeLeftOpen) {
  // A sphere seen from above only (z > 0): the bottom half has no data.
  Cloud full = sphere_cloud(4000, 1.0), c;
  for (std::size_t i = 0; i < full.size(); ++i)
    if (full.points[i].z() > 0.f) c.points.push_back(full.points[i]), c.normals.push_back(full.normals[i]);
  const MpuSurface s = fit_mpu(c);
  EXPECT_TRUE(s.trusted(Vec3d(0, 0, 1)));
  EXPECT_FALSE(s.trusted(Vec3d(0, 0, -1)));
  EXPECT_GT(s.weight_sum(Vec3d(0, 0, 1)), 0);
  MarchingCubesOptions opt;
  const Mesh closed = extract_marching_cubes(s, 40, opt);
  {
    SCOPED_TRACE("closed");
    expect_closed(closed);
  }
  opt.untrusted = UntrustedRegions::kLeaveOpen;
  MarchingCubesStats st;
  const Mesh open = extract_marching_cubes(s, 40, opt, &st);
  expect_finite(closed);
  expect_finite(open);
  EXPECT_GT(st.dropped_faces, 0u);
  EXPECT_LT(open.faces.size(), closed.faces.size());
  // What is left lies near the data.
  double far = 0;
  for (const Vec3f& v : open.vertices) far = std::max(far, s.nearest_point_distance(v.cast<double>()));
  EXPECT_LT(far, s.params().trust_factor * s.diagnostics().mean_spacing + st.cell_size);
}

// f as it is, except that it never says where it is surely untrusted: the walk of an
// extraction then goes wherever the surface goes.
class WalkEverywhere : public ImplicitFunction {
 public:
  explicit WalkEverywhere(const ImplicitFunction& f) : f_(f) {}
  double value(const Vec3d& x) const override { return f_.value(x); }
  Vec3d gradient(const Vec3d& x) const override { return f_.gradient(x); }
  bool trusted(const Vec3d& x) const override { return f_.trusted(x); }
  bool may_be_sharp(const Vec3d& x, double radius) const override { return f_.may_be_sharp(x, radius); }
  void values_near(const Vec3d* xs, int n, double* out) const override { f_.values_near(xs, n, out); }
  void gradients_near(const Vec3d* xs, int n, Vec3d* out) const override { f_.gradients_near(xs, n, out); }
  void values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const override {
    f_.values_gradients_near(xs, n, values, grads);
  }

 private:
  const ImplicitFunction& f_;
};

// As extract_marching_cubes / extract_dmc do for an MPU surface, untrusted surface dropped.
DmcOptions left_open(const MpuSurface& s) {
  DmcOptions opt;
  opt.seeds = s.points();
  opt.close_at_box = true;
  opt.untrusted = UntrustedRegions::kLeaveOpen;
  return opt;
}

TEST(Mpu, LeftOpenTheWalkStopsBeyondTheTrustDistance) {
  // A cap of a sphere (z > 0.6: a one-sided patch). MPU's extrapolation beyond it is a
  // surface the walk used to follow all the way, only to drop it. With the untrusted
  // surface dropped the walk now stops beyond the trust distance: the same mesh, bit
  // for bit, for both extractors, from a fraction of the cells.
  Cloud full = sphere_cloud(20000, 1.0), c;
  for (std::size_t i = 0; i < full.size(); ++i)
    if (full.points[i].z() > 0.6f) c.points.push_back(full.points[i]), c.normals.push_back(full.normals[i]);
  const MpuSurface s = fit_mpu(c);
  const WalkEverywhere everywhere(s);
  const Aabb box = extraction_box(s);
  const DmcOptions opt = left_open(s);
  MarchingCubesStats mc_bounded, mc_everywhere;
  const Mesh a = extract_marching_cubes(s, box, 96, opt, &mc_bounded);
  const Mesh b = extract_marching_cubes(everywhere, box, 96, opt, &mc_everywhere);
  DmcStats dmc_bounded, dmc_everywhere;
  const Mesh d = extract_dmc(s, box, 96, opt, &dmc_bounded);
  const Mesh e = extract_dmc(everywhere, box, 96, opt, &dmc_everywhere);
  std::printf("cap left open, bounded / everywhere: MC %zu / %zu cells visited, %zu / %zu faces dropped; DMC %zu / "
              "%zu surface cells, %zu / %zu faces dropped\n",
              mc_bounded.cells_visited, mc_everywhere.cells_visited, mc_bounded.dropped_faces,
              mc_everywhere.dropped_faces, dmc_bounded.surface_cells, dmc_everywhere.surface_cells,
              dmc_bounded.dropped_faces, dmc_everywhere.dropped_faces);
  ASSERT_GT(a.faces.size(), 1000u);
  EXPECT_EQ(a.vertices, b.vertices);
  EXPECT_EQ(a.faces, b.faces);
  EXPECT_EQ(a.normals, b.normals);
  ASSERT_GT(d.faces.size(), 1000u);
  EXPECT_EQ(d.vertices, e.vertices);
  EXPECT_EQ(d.faces, e.faces);
  // The walk's first wave visits the seeds' neighbourhoods either way; what goes is the
  // surface beyond them.
  EXPECT_LT(mc_bounded.cells_visited, mc_everywhere.cells_visited);
  EXPECT_LT(5 * mc_bounded.dropped_faces, mc_everywhere.dropped_faces);
  EXPECT_LT(dmc_bounded.surface_cells, dmc_everywhere.surface_cells);
  EXPECT_LT(2 * dmc_bounded.dropped_faces, dmc_everywhere.dropped_faces);
  EXPECT_EQ(d.normals, e.normals);
  // The thin-part floods stay within the walk's reach too (on the Kinect scene a flood
  // that did not searched 78x the points, walking the extrapolation point by point).
  EXPECT_LE(dmc_bounded.searched, dmc_everywhere.searched);
  // Without seeds (the walk starts from scan lines) the same.
  DmcOptions lines = opt;
  lines.seeds.clear();
  EXPECT_EQ(extract_marching_cubes(s, box, 96, lines).faces, extract_marching_cubes(everywhere, box, 96, lines).faces);
}

// MpuParams::sparse_trust: a plane sampled densely on its left half and at 3x the
// spacing on its right (a depth camera's far field), with a stray point in the middle
// of a 20 mm hole in the dense half. The plain trust distance (from the mean spacing,
// which the dense half sets) leaves gaps all over the sparse half; each point's
// allowance closes them, while the stray, whose neighbours are dense, holds no more
// than before. may_be_trusted_near stays a bound of trusted (the walk bounded by it
// gives the same mesh as an unbounded one).
TEST(Mpu, SparseTrustReachesOverSparseDataNotRoundAStray) {
  std::mt19937 rng(12);
  std::uniform_real_distribution<float> u(0, 1);
  const Vec3f hole(0.25f, 0.5f, 0.f);
  Cloud c;
  auto add = [&](const Vec3f& q) { c.points.push_back(q), c.normals.push_back(Vec3f::UnitZ()); };
  for (int i = 0; i < 18000; ++i) {  // spacing 1 / sqrt(36,000) = 5.3 mm
    const Vec3f q(0.5f * u(rng), u(rng), 0.f);
    if ((q - hole).norm() > 0.02f) add(q);
  }
  for (int i = 0; i < 2000; ++i) add(Vec3f(0.5f + 0.5f * u(rng), u(rng), 0.f));  // 15.8 mm
  add(hole);
  MpuParams p;
  p.trust_factor = 2;
  const MpuSurface plain = fit_mpu(c, p);
  p.sparse_trust = true;
  const MpuSurface sparse = fit_mpu(c, p);
  int inside = 0, plain_trusted = 0, sparse_trusted = 0;
  for (int i = 0; i < 4000; ++i) {
    const Vec3d x(0.6 + 0.3 * u(rng), 0.1 + 0.8 * u(rng), 0);
    ++inside;
    plain_trusted += plain.trusted(x);
    sparse_trusted += sparse.trusted(x);
  }
  std::printf("sparse half trusted: %.3f plain, %.3f with the allowance\n", double(plain_trusted) / inside,
              double(sparse_trusted) / inside);
  EXPECT_LT(plain_trusted, 0.5 * inside);
  EXPECT_GT(sparse_trusted, 0.95 * inside);
  // Round the stray: the same answers.
  for (int i = 0; i < 400; ++i) {
    const double a = 2 * M_PI * u(rng), r = 0.004 + 0.012 * u(rng);
    const Vec3d x = hole.cast<double>() + r * Vec3d(std::cos(a), std::sin(a), 0);
    ASSERT_EQ(plain.trusted(x), sparse.trusted(x)) << r;
  }
  // The dense half's gaps: no change.
  for (int i = 0; i < 2000; ++i) {
    const Vec3d x(0.05 + 0.35 * u(rng), 0.05 + 0.9 * u(rng), 0.01 * (u(rng) - 0.5));
    if ((x - hole.cast<double>()).norm() < 0.04) continue;
    ASSERT_EQ(plain.trusted(x), sparse.trusted(x));
  }
  // may_be_trusted_near(x, r) holds wherever some y within r of x is trusted.
  int bounded = 0;
  for (int i = 0; i < 600; ++i) {
    const Vec3d x(1.2 * u(rng) - 0.1, 1.2 * u(rng) - 0.1, 0.1 * (u(rng) - 0.5));
    const double r = 0.02 * u(rng);
    for (int t = 0; t < 30; ++t) {
      const Vec3d y = x + r * Vec3d(u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5).normalized() * double(u(rng));
      if (sparse.trusted(y)) {
        ASSERT_TRUE(sparse.may_be_trusted_near(x, r)) << x.transpose() << " r " << r;
        ++bounded;
        break;
      }
    }
  }
  EXPECT_GT(bounded, 100);
  // The walk bounded by it: the same mesh as walking everywhere.
  const WalkEverywhere everywhere(sparse);
  const Aabb box = extraction_box(sparse);
  const DmcOptions opt = left_open(sparse);
  const Mesh a = extract_marching_cubes(sparse, box, 128, opt), b = extract_marching_cubes(everywhere, box, 128, opt);
  ASSERT_GT(a.faces.size(), 1000u);
  EXPECT_EQ(a.faces, b.faces);
  EXPECT_EQ(a.vertices, b.vertices);
  // near_points: the rims' test on the same scale.
  const Vec3d gap(0.75, 0.5, 0);
  const double d = sparse.nearest_point_distance(gap);
  EXPECT_EQ(plain.near_points(gap, 0.5 * d), false);
  EXPECT_EQ(plain.near_points(gap, 1.01 * d), true);
  EXPECT_EQ(sparse.near_points(gap, 0.5 * d), true);  // its nearest points' allowance is 2 or more
  EXPECT_EQ(sparse.near_points(gap, 0.1 * d), false);  // at most 4
}

TEST(Mpu, LeftOpenTheWalkStopsBeyondTheTrustDistanceAtCreases) {
  // The upper part of a cube (its top and the sides above z = -0.1): sharp edges and
  // corners, which DMC's feature step moves lattice points onto, and open below. The
  // same meshes with the walk bounded and unbounded.
  Cloud c;
  std::mt19937 rng(12);
  std::uniform_real_distribution<float> u(-0.5f, 0.5f), side(-0.1f, 0.5f);
  for (int k = 0; k < 6000; ++k) {
    c.points.emplace_back(u(rng), u(rng), 0.5f);
    c.normals.emplace_back(0.f, 0.f, 1.f);
  }
  for (int k = 0; k < 3000; ++k)
    for (int f = 0; f < 4; ++f) {
      const float a = u(rng), z = side(rng), sign = f % 2 ? 1.f : -1.f;
      if (f < 2) c.points.emplace_back(0.5f * sign, a, z), c.normals.emplace_back(sign, 0.f, 0.f);
      else c.points.emplace_back(a, 0.5f * sign, z), c.normals.emplace_back(0.f, sign, 0.f);
    }
  const MpuSurface s = fit_mpu(c);
  const WalkEverywhere everywhere(s);
  const Aabb box = extraction_box(s);
  const DmcOptions opt = left_open(s);
  DmcStats bounded, unbounded;
  const Mesh d = extract_dmc(s, box, 64, opt, &bounded);
  const Mesh e = extract_dmc(everywhere, box, 64, opt, &unbounded);
  std::printf("cube's top left open: DMC %zu / %zu surface cells, %zu corner and %zu edge moves\n",
              bounded.surface_cells, unbounded.surface_cells, bounded.moved_corner, bounded.moved_edge);
  ASSERT_GT(d.faces.size(), 1000u);
  EXPECT_GT(bounded.moved_edge, 0u);
  EXPECT_LT(bounded.surface_cells, unbounded.surface_cells);
  EXPECT_LE(bounded.searched, unbounded.searched);
  EXPECT_EQ(d.vertices, e.vertices);
  EXPECT_EQ(d.faces, e.faces);
  EXPECT_EQ(d.normals, e.normals);
}

TEST(Mpu, BadInput) {
  Cloud c = sphere_cloud(100, 1.0);
  Cloud no_normals = c;
  no_normals.normals.clear();
  EXPECT_THROW(fit_mpu(no_normals), InvalidInput);
  Cloud three = sphere_cloud(3, 1.0);
  EXPECT_THROW(fit_mpu(three), InvalidInput);
  Cloud same;
  for (int i = 0; i < 50; ++i) same.points.emplace_back(1, 2, 3), same.normals.emplace_back(0, 0, 1);
  EXPECT_THROW(fit_mpu(same), InvalidInput);
  Cloud nan = c;
  nan.points[5].x() = std::nanf("");
  EXPECT_THROW(fit_mpu(nan), InvalidInput);
  MpuParams bad;
  bad.alpha = 0.1;
  EXPECT_THROW(fit_mpu(c, bad), InvalidInput);
  // Zero normals are dropped, not fatal.
  Cloud zeros = sphere_cloud(500, 1.0);
  zeros.normals[3] = Vec3f::Zero();
  EXPECT_EQ(fit_mpu(zeros).diagnostics().dropped_points, 1u);
}

TEST(Mpu, DegenerateCloudsGiveFiniteOutput) {
  // Every point duplicated.
  Cloud dup = sphere_cloud(800, 1.0);
  const Cloud orig = dup;
  dup.points.insert(dup.points.end(), orig.points.begin(), orig.points.end());
  dup.normals.insert(dup.normals.end(), orig.normals.begin(), orig.normals.end());
  const MpuSurface sd = fit_mpu(dup);
  EXPECT_LT(max_abs_f_normalised(sd, dup), 10 * sd.params().epsilon0);
  // A planar patch and a line of points.
  Cloud plane, line;
  std::mt19937 rng(4);
  std::uniform_real_distribution<float> u(-1, 1);
  for (int i = 0; i < 400; ++i) {
    plane.points.emplace_back(u(rng), u(rng), 0.f);
    plane.normals.emplace_back(0.f, 0.f, 1.f);
    line.points.emplace_back(u(rng), 0.f, 0.f);
    line.normals.emplace_back(0.f, 0.f, 1.f);
  }
  for (const Cloud* c : {&plane, &line}) {
    const MpuSurface s = fit_mpu(*c);
    EXPECT_TRUE(std::isfinite(s.value(Vec3d(0.1, 0.2, 0.3))));
    EXPECT_TRUE(s.gradient(Vec3d(0.1, 0.2, 0.3)).allFinite());
    EXPECT_LT(std::abs(s.value(Vec3d(0.1, 0, 0))), 1e-3);
    const Mesh m = extract_marching_cubes(s, 24);
    expect_finite(m);
    EXPECT_FALSE(m.faces.empty());
  }
}

TEST(Mpu, CubeKeepsItsCorners) {
  const Mesh box = test::box(Vec3f(-1, -1, -1), Vec3f(1, 1, 1));
  const Cloud c = sample_mesh(box, 12000, 3);
  const MpuSurface s = fit_mpu(c);
  const auto& d = s.diagnostics();
  EXPECT_GT(d.leaves_by_type[int(MpuFitType::kEdge)] + d.leaves_by_type[int(MpuFitType::kCorner)], 0u);
  EXPECT_LT(max_abs_f_normalised(s, c), s.params().epsilon0 * 10);
  // The corner stays on the surface (a smooth fit would round it off).
  const double diag = s.bounds().diagonal();
  for (const Vec3d& corner : {Vec3d(1, 1, 1), Vec3d(-1, 1, -1), Vec3d(1, -1, -1)})
    EXPECT_LT(std::abs(s.value(corner)), 0.002 * diag) << corner.transpose();
  const Mesh m = extract_marching_cubes(s, 48);
  expect_finite(m);
}

// An L-shaped block (a unit-high slab over the L of [0,2]x[0,1] and [0,1]x[0,2]):
// at (1, 1, 1) and (1, 1, 0) the notch's concave edge meets the top and the bottom
// along two convex edges, a saddle (mixed) corner: max(min(f_x, f_y), f_top).
Cloud l_block_cloud(int n, unsigned seed) {
  struct Face {
    Vec3f o, a, b, normal;  // o + s a + t b, s, t in [0, 1]
  };
  const std::vector<Face> faces = {
      {{0, 0, 1}, {2, 0, 0}, {0, 1, 0}, {0, 0, 1}},  {{0, 1, 1}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}},
      {{0, 0, 0}, {2, 0, 0}, {0, 1, 0}, {0, 0, -1}}, {{0, 1, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, -1}},
      {{0, 0, 0}, {0, 2, 0}, {0, 0, 1}, {-1, 0, 0}}, {{0, 0, 0}, {2, 0, 0}, {0, 0, 1}, {0, -1, 0}},
      {{2, 0, 0}, {0, 1, 0}, {0, 0, 1}, {1, 0, 0}},  {{1, 1, 0}, {1, 0, 0}, {0, 0, 1}, {0, 1, 0}},
      {{1, 1, 0}, {0, 1, 0}, {0, 0, 1}, {1, 0, 0}},  {{0, 2, 0}, {1, 0, 0}, {0, 0, 1}, {0, 1, 0}}};
  std::vector<double> area;
  for (const Face& f : faces) area.push_back(f.a.cross(f.b).norm());
  std::mt19937 rng(seed);
  std::discrete_distribution<int> pick(area.begin(), area.end());
  std::uniform_real_distribution<float> u(0, 1);
  Cloud c;
  for (int i = 0; i < n; ++i) {
    const Face& f = faces[pick(rng)];
    c.points.push_back(f.o + u(rng) * f.a + u(rng) * f.b);
    c.normals.push_back(f.normal);
  }
  return c;
}

TEST(Mpu, SaddleCornerOfAnLBlockStaysSharp) {
  const Cloud c = l_block_cloud(30000, 7);
  const MpuSurface s = fit_mpu(c);
  EXPECT_GT(s.diagnostics().leaves_by_type[int(MpuFitType::kCorner)], 0u);
  EXPECT_LT(max_abs_f_normalised(s, c), s.params().epsilon0 * 10);
  const double diag = s.bounds().diagonal();
  for (const Vec3d& corner : {Vec3d(1, 1, 1), Vec3d(1, 1, 0)}) {
    std::printf("saddle corner (%g %g %g): f = %.2e (diag %.3f)\n", corner.x(), corner.y(), corner.z(),
                s.value(corner), diag);
    EXPECT_LT(std::abs(s.value(corner)), 0.002 * diag) << corner.transpose();
  }
  // Just inside the notch, above the corner's level and on its diagonal, is outside;
  // just inside the solid next to the corner is inside.
  EXPECT_GT(s.value(Vec3d(1.02, 1.02, 0.98)), 0.0);
  EXPECT_LT(s.value(Vec3d(0.98, 0.98, 0.98)), 0.0);
  EXPECT_GT(s.value(Vec3d(0.98, 0.98, 1.02)), 0.0);
}

TEST(Mpu, LongBoxKeepsItsEdges) {
  const Mesh box = test::box(Vec3f(-2, -0.5f, -0.5f), Vec3f(2, 0.5f, 0.5f));
  const Cloud c = sample_mesh(box, 20000, 5);
  const MpuSurface s = fit_mpu(c);
  const auto& d = s.diagnostics();
  EXPECT_GT(d.leaves_by_type[int(MpuFitType::kEdge)], 0u);
  const double diag = s.bounds().diagonal();
  for (const Vec3d& edge_point : {Vec3d(0.3, 0.5, 0.5), Vec3d(-0.7, -0.5, 0.5), Vec3d(1.1, 0.5, -0.5)})
    EXPECT_LT(std::abs(s.value(edge_point)), 0.002 * diag) << edge_point.transpose();
  // A point just outside the edge, on the bisector, is outside (a rounded edge would
  // also say so, but a much smaller value).
  EXPECT_GT(s.value(Vec3d(0.3, 0.52, 0.52)), 0.01);
}

TEST(Mpu, SuggestedEpsilonFollowsTheNoise) {
  EXPECT_EQ(suggest_epsilon0(sphere_cloud(5000, 1.0)), 1e-4);
  Cloud noisy = sphere_cloud(20000, 1.0);
  std::mt19937 rng(9);
  std::normal_distribution<float> g(0, 0.01f);
  for (std::size_t i = 0; i < noisy.size(); ++i) noisy.points[i] += g(rng) * noisy.normals[i];
  const double eps = suggest_epsilon0(noisy);
  const double sigma_normalised = 0.01 / (2 * std::sqrt(3.0));
  EXPECT_GT(eps, 1.5 * sigma_normalised);
  EXPECT_LT(eps, 4.5 * sigma_normalised);
  // ... and with it the noisy sphere meshes as one piece.
  MpuParams p;
  p.epsilon0 = eps;
  const Mesh m = extract_marching_cubes(fit_mpu(noisy, p), 48);
  std::vector<int> parent(m.vertices.size());
  for (std::size_t i = 0; i < parent.size(); ++i) parent[i] = int(i);
  std::function<int(int)> find = [&](int x) { return parent[x] == x ? x : parent[x] = find(parent[x]); };
  for (const Face& f : m.faces) parent[find(f[1])] = find(f[0]), parent[find(f[2])] = find(f[0]);
  int components = 0;
  for (std::size_t i = 0; i < parent.size(); ++i) components += find(int(i)) == int(i);
  EXPECT_EQ(components, 1);
  EXPECT_THROW(suggest_epsilon0(sphere_cloud(5, 1.0)), InvalidInput);
}

TEST(Mpu, FewPointsSpreadNormalsUseTheQuadric) {
  // 40 points on a small sphere: the root ball holds both sides, normals spread, and
  // a general quadric (which contains the sphere) fits exactly.
  const Cloud c = sphere_cloud(40, 0.3);
  const MpuSurface s = fit_mpu(c);
  EXPECT_GT(s.diagnostics().leaves_by_type[int(MpuFitType::kQuadric)], 0u);
  EXPECT_LT(max_abs_f_normalised(s, c), s.params().epsilon0);
  EXPECT_LT(s.value(Vec3d::Zero()), 0);
  EXPECT_GT(s.value(Vec3d(0.5, 0, 0)), 0);
}

}  // namespace
}  // namespace station
