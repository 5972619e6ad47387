#include "reconstruct/wlop.h"

#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <limits>
#include <random>

#include "core/error.h"
#include "core/io.h"
#include "eval/consolidation_metrics.h"
#include "eval/eval.h"
#include "test_util.h"

namespace station {
namespace {

// ---- helpers ---------------------------------------------------------------------

// Points on the unit sphere, denser towards +z (density ratio ~ 1:5 from pole to
// pole), with Gaussian noise of `noise` along all axes. Seeded.
Cloud uneven_sphere(int n, double noise, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0, 1);
  std::uniform_real_distribution<double> u(0, 1);
  Cloud c;
  while (int(c.size()) < n) {
    Vec3d d(g(rng), g(rng), g(rng));
    d.normalize();
    if (u(rng) > 0.2 + 0.8 * (d.z() + 1) / 2) continue;  // thin out towards -z
    const Vec3d p = d + noise * Vec3d(g(rng), g(rng), g(rng));
    c.points.push_back(p.cast<float>());
  }
  return c;
}

// Area-uniform samples of a mesh, then Gaussian noise (sigma = noise) and a
// density gradient along x (keep probability 0.3 .. 1).
Cloud noisy_uneven_sample(const Mesh& mesh, int n, double noise, unsigned seed) {
  const Cloud dense = sample_mesh(mesh, 3 * n, seed);
  const Aabb box = bounding_box(dense.points);
  std::mt19937 rng(seed + 1);
  std::normal_distribution<float> g(0, float(noise));
  std::uniform_real_distribution<float> u(0, 1);
  Cloud c;
  for (std::size_t i = 0; i < dense.size() && int(c.size()) < n; ++i) {
    const float t = (dense.points[i].x() - box.min.x()) / (box.max.x() - box.min.x());
    if (u(rng) > 0.3f + 0.7f * t) continue;
    c.points.push_back(dense.points[i] + Vec3f(g(rng), g(rng), g(rng)));
  }
  return c;
}

double mean_sphere_distance(const std::vector<Vec3f>& pts) {
  double s = 0;
  for (const Vec3f& p : pts) s += std::abs(double(p.norm()) - 1.0);
  return s / double(pts.size());
}

WlopParams plain(std::size_t target, double radius, int iterations) {
  WlopParams p;
  p.target_points = target;
  p.radius = radius;
  p.iterations = iterations;
  p.estimate_normals = false;
  return p;
}

// The paper's update, eq. 1 as printed (attraction eq. 2 / eq. 19, plain WLOP's E2
// whole): what the tests of the equations check. The default attraction is the
// projection (WlopAttraction::kProjection; consolidation_quality_test.cpp).
WlopParams printed(WlopParams p) {
  p.attraction = WlopAttraction::kL1;
  p.repulsion = WlopRepulsion::kFull;
  return p;
}

// Straightforward WLOP (methods.md section 1, eqs. 1-9): every sum over all pairs,
// in index order, with the header's conventions (strictly within h; E1 leaves out
// pairs closer than 1e-9 h, and so does E2 with beta = theta |eta'| / r; a point with
// no input point within h stays). printed_beta: beta = theta eta / r, eq. 5 as printed.
std::vector<Vec3d> reference_wlop(const std::vector<Vec3d>& p, std::vector<Vec3d> x, double h,
                                  double mu, int iterations, bool input_density = true,
                                  bool printed_beta = false) {
  const double s2 = (h / 4) * (h / 4);
  auto theta = [&](double r) { return std::exp(-r * r / s2); };
  auto eta = [](double r) { return -r; };
  auto eta_slope = [](double) { return -1.0; };  // d eta / dr
  std::vector<double> v(p.size(), 1.0);
  for (std::size_t j = 0; j < p.size(); ++j)
    for (std::size_t k = 0; k < p.size(); ++k) {
      const double r = (p[j] - p[k]).norm();
      if (k != j && r < h && input_density) v[j] += theta(r);
    }
  for (int it = 0; it < iterations; ++it) {
    std::vector<double> w(x.size(), 1.0);
    for (std::size_t i = 0; i < x.size(); ++i)
      for (std::size_t r = 0; r < x.size(); ++r) {
        const double d = (x[i] - x[r]).norm();
        if (r != i && d < h) w[i] += theta(d);
      }
    std::vector<Vec3d> next(x.size());
    for (std::size_t i = 0; i < x.size(); ++i) {
      Vec3d num1 = Vec3d::Zero();
      double den1 = 0;
      for (std::size_t j = 0; j < p.size(); ++j) {
        const double r = (x[i] - p[j]).norm();
        if (r < h && r > 1e-9 * h) {
          const double alpha = theta(r) / r;
          num1 += p[j] * (alpha / v[j]);
          den1 += alpha / v[j];
        }
      }
      if (den1 == 0) {
        next[i] = x[i];
        continue;
      }
      Vec3d num2 = Vec3d::Zero();
      double den2 = 0;
      for (std::size_t r = 0; r < x.size(); ++r) {
        const double d = (x[i] - x[r]).norm();
        if (r == i || d >= h) continue;
        double beta;
        if (printed_beta) {
          beta = d > 0 ? theta(d) * eta(d) / d : -1.0;  // eta(r)/r = -1
        } else {
          if (d <= 1e-9 * h) continue;
          beta = theta(d) * std::abs(eta_slope(d)) / d;
        }
        num2 += (x[i] - x[r]) * (w[r] * beta);
        den2 += w[r] * beta;
      }
      const Vec3d e1 = num1 / den1;
      const Vec3d e2 = den2 != 0 ? Vec3d(num2 / den2) : Vec3d::Zero();
      next[i] = e1 + mu * e2;
    }
    x.swap(next);
  }
  return x;
}

// ---- plain WLOP -------------------------------------------------------------------

TEST(Wlop, MatchesAllPairsReference) {
  const Cloud in = uneven_sphere(2000, 0.01, 3);
  const double h = 0.3;
  const WlopParams params = printed(plain(500, h, 10));
  const WlopResult r = consolidate(in, params);
  ASSERT_EQ(r.positions.size(), 500u);
  ASSERT_EQ(r.iterations, 10);
  EXPECT_EQ(r.radius, h);

  std::vector<Vec3d> p;
  for (const Vec3f& q : in.points) p.push_back(q.cast<double>());
  std::vector<Vec3d> x0;
  for (int j : initial_subset(p.size(), 500, params.seed)) x0.push_back(p[j]);
  const std::vector<Vec3d> ref = reference_wlop(p, x0, h, params.mu, 10);
  double worst = 0, moved = 0;
  for (std::size_t i = 0; i < ref.size(); ++i) {
    worst = std::max(worst, (r.positions[i] - ref[i]).norm());
    moved = std::max(moved, (ref[i] - x0[i]).norm());
  }
  EXPECT_LT(worst, 1e-9);
  EXPECT_GT(moved, 0.01);  // the points did move: the comparison means something
  for (std::size_t i = 0; i < ref.size(); ++i)
    EXPECT_EQ(r.cloud.points[i], r.positions[i].cast<float>());

  // Eq. 5 as printed (beta = -theta) against its own reference; the two betas differ.
  WlopParams printed = params;
  printed.repulsion_weight = RepulsionWeight::kPrinted;
  const WlopResult rp = consolidate(in, printed);
  const std::vector<Vec3d> ref_p = reference_wlop(p, x0, h, params.mu, 10, true, true);
  double worst_p = 0, apart = 0;
  for (std::size_t i = 0; i < ref_p.size(); ++i) {
    worst_p = std::max(worst_p, (rp.positions[i] - ref_p[i]).norm());
    apart = std::max(apart, (ref_p[i] - ref[i]).norm());
  }
  EXPECT_LT(worst_p, 1e-9);
  EXPECT_GT(apart, 1e-3);
}

TEST(Wlop, UniformInputDensityMatchesReference) {
  const Cloud in = uneven_sphere(1500, 0.01, 4);
  WlopParams params = printed(plain(400, 0.3, 10));
  params.input_density = InputDensity::kUniform;
  const WlopResult r = consolidate(in, params);
  std::vector<Vec3d> p, x0;
  for (const Vec3f& q : in.points) p.push_back(q.cast<double>());
  for (int j : initial_subset(p.size(), 400, params.seed)) x0.push_back(p[j]);
  const std::vector<Vec3d> ref = reference_wlop(p, x0, 0.3, params.mu, 10, false);
  const std::vector<Vec3d> weighted = reference_wlop(p, x0, 0.3, params.mu, 10, true);
  double worst = 0, apart = 0;
  for (std::size_t i = 0; i < ref.size(); ++i) {
    worst = std::max(worst, (r.positions[i] - ref[i]).norm());
    apart = std::max(apart, (weighted[i] - ref[i]).norm());
  }
  EXPECT_LT(worst, 1e-9);
  EXPECT_GT(apart, 1e-4);  // v_j matters on this uneven input
}

TEST(Wlop, IdenticalAcrossRunsAndThreadCounts) {
  const Cloud in = uneven_sphere(6000, 0.01, 5);
  WlopParams params = plain(1500, 0, 8);
  params.threads = 1;
  const WlopResult a = consolidate(in, params);
  const WlopResult b = consolidate(in, params);
  params.threads = 2;
  const WlopResult c = consolidate(in, params);
  ASSERT_EQ(a.positions.size(), c.positions.size());
  for (std::size_t i = 0; i < a.positions.size(); ++i) {
    EXPECT_EQ(a.positions[i], b.positions[i]) << i;
    EXPECT_EQ(a.positions[i], c.positions[i]) << i;
  }
  params.seed = 2;  // a different initial subset gives a different result
  const WlopResult d = consolidate(in, params);
  EXPECT_NE(a.positions[0], d.positions[0]);
}

std::vector<Vec3f> onto_unit_sphere(std::vector<Vec3f> pts) {
  for (Vec3f& p : pts) p.normalize();
  return pts;
}

TEST(Wlop, EvensOutANoisyUnevenSphereWithoutLosingAccuracy) {
  const Cloud in = uneven_sphere(20000, 0.01, 7);
  // h = 0.22: 8 times the input's mean 6-NN spacing (0.0276), the benchmark's rule.
  const WlopResult r = consolidate(in, plain(4000, 0.22, 35));
  ASSERT_EQ(r.cloud.size(), 4000u);
  // Evenness on the surface (noise would inflate 3-D neighbour distances).
  const double area = 4 * M_PI;
  const double u_in = uniformity(onto_unit_sphere(in.points), area);
  const double u_out = uniformity(onto_unit_sphere(r.cloud.points), area);
  // The starting point (the projection's spread-out subset): the same call, no iterations.
  const WlopResult start = consolidate(in, plain(4000, 0.22, 0));
  const double u_subset = uniformity(onto_unit_sphere(start.cloud.points), area);
  EXPECT_GT(u_out, u_in + 0.04) << u_in << " -> " << u_out;
  EXPECT_GT(u_out, u_subset + 0.04) << u_subset << " -> " << u_out;
  const double acc_in = mean_sphere_distance(in.points);
  const double acc_out = mean_sphere_distance(r.cloud.points);
  EXPECT_LT(acc_out, acc_in) << acc_in << " -> " << acc_out;
  for (const Vec3d& p : r.positions) ASSERT_TRUE(p.allFinite());
  EXPECT_EQ(r.isolated_points, 0u);
}

TEST(Wlop, TangentialRepulsionDriftsLessOffTheSurface) {
  // WlopRepulsion::kTangential drops E2's part along the local normal: the same
  // run lands closer to the sphere than E2 as printed, and still evens out.
  // Measured: accuracy 0.0170 -> 0.0051 at the default h (uniformity 0.63 -> 0.69),
  // 0.0067 -> 0.0025 at h = 0.22 (uniformity 0.52 -> 0.50; input 0.0079, 0.46).
  const Cloud in = uneven_sphere(20000, 0.01, 7);
  for (double h : {0.0, 0.22}) {
    WlopParams params = printed(plain(4000, h, 35));
    const WlopResult full = consolidate(in, params);
    params.repulsion = WlopRepulsion::kTangential;
    const WlopResult tangential = consolidate(in, params);
    const double acc_full = mean_sphere_distance(full.cloud.points);
    const double acc_tangential = mean_sphere_distance(tangential.cloud.points);
    EXPECT_LT(acc_tangential, 0.7 * acc_full) << "h " << h;
    EXPECT_LT(acc_tangential, mean_sphere_distance(in.points)) << "h " << h;
    const double u_in = uniformity(onto_unit_sphere(in.points), 4 * M_PI);
    const double u_out = uniformity(onto_unit_sphere(tangential.cloud.points), 4 * M_PI);
    EXPECT_GT(u_out, u_in + 0.02) << "h " << h;
    for (const Vec3d& p : tangential.positions) ASSERT_TRUE(p.allFinite());
    // Deterministic across thread counts like the rest.
    params.threads = 1;
    EXPECT_EQ(consolidate(in, params).positions, tangential.positions) << "h " << h;
  }
}

TEST(Wlop, DefaultRadiusEvensOutMore) {
  // The paper's h (0.1 here, about the output spacing) spreads the points more
  // evenly than the benchmark's, at the cost of accuracy (docs/consolidation.md).
  const Cloud in = uneven_sphere(20000, 0.01, 7);
  const WlopResult r = consolidate(in, plain(4000, 0, 35));
  const double u_out = uniformity(onto_unit_sphere(r.cloud.points), 4 * M_PI);
  EXPECT_GT(u_out, 0.6);
}

TEST(Wlop, OriginalRepulsionWeightSeparatesClosePairs) {
  // At a radius well above the output spacing (h/4 = 0.055 against a spacing of about
  // 0.06), eq. 5's printed beta = -theta lets points pair up: a neighbour's push
  // shrinks with its distance. WLOP's own beta = theta / r keeps pushing as a pair
  // closes (reconstruct/wlop.h RepulsionWeight).
  const Cloud in = uneven_sphere(20000, 0.01, 7);
  WlopParams params = printed(plain(4000, 0.22, 35));
  const WlopResult original = consolidate(in, params);
  params.repulsion_weight = RepulsionWeight::kPrinted;
  const WlopResult printed = consolidate(in, params);
  const double u_original = uniformity(onto_unit_sphere(original.cloud.points), 4 * M_PI);
  const double u_printed = uniformity(onto_unit_sphere(printed.cloud.points), 4 * M_PI);
  std::cout << "uniformity at h = 0.22: beta = theta / r " << u_original << ", printed " << u_printed
            << "; accuracy " << mean_sphere_distance(original.cloud.points) << ", "
            << mean_sphere_distance(printed.cloud.points) << "\n";
  EXPECT_GT(u_original, u_printed + 0.1);
  EXPECT_LT(mean_sphere_distance(original.cloud.points), 1.2 * mean_sphere_distance(printed.cloud.points));
}

TEST(Wlop, DefaultRadiusIsScaleInvariant) {
  Cloud in = uneven_sphere(3000, 0.01, 9);
  WlopParams params = plain(600, 0, 6);
  const WlopResult unit = consolidate(in, params);
  for (double scale : {1e-3, 1e3}) {
    Cloud scaled = in;
    for (Vec3f& p : scaled.points) p *= float(scale);
    const WlopResult r = consolidate(scaled, params);
    EXPECT_NEAR(r.radius, unit.radius * scale, 1e-6 * unit.radius * scale);
    double worst = 0;
    for (std::size_t i = 0; i < r.positions.size(); ++i)
      worst = std::max(worst, (r.positions[i] / scale - unit.positions[i]).norm());
    EXPECT_LT(worst, 1e-4) << "scale " << scale;
  }
  // h = 4 d_bb / sqrt(|J|).
  EXPECT_NEAR(unit.radius, 4 * unit.bbox_diagonal / std::sqrt(3000.0), 1e-12);
}

TEST(Wlop, InitialSubsetIsSeededDistinctAndSorted) {
  const std::vector<int> a = initial_subset(1000, 100, 4), b = initial_subset(1000, 100, 4);
  EXPECT_EQ(a, b);
  EXPECT_NE(a, initial_subset(1000, 100, 5));
  ASSERT_EQ(a.size(), 100u);
  for (std::size_t i = 1; i < a.size(); ++i) EXPECT_LT(a[i - 1], a[i]);
  EXPECT_GE(a.front(), 0);
  EXPECT_LT(a.back(), 1000);
  EXPECT_EQ(initial_subset(10, 50, 1).size(), 10u);
}

// ---- edge-preserving variant -----------------------------------------------------

using Vec2d = Eigen::Vector2d;

WlopParams edge(std::size_t target, double radius, int iterations) {
  WlopParams p = plain(target, radius, iterations);
  p.method = WlopMethod::kEdgeWlop;
  return p;
}

TEST(EdgeWlop, SharperThanWlopOnANoisyCube) {
  const Mesh cube = test::box(Vec3f(-1, -1, -1), Vec3f(1, 1, 1));
  const Cloud in = noisy_uneven_sample(cube, 25000, 0.005, 21);
  const WlopResult w = consolidate(in, printed(plain(4000, 0, 35)));
  const WlopResult e = consolidate(in, printed(edge(4000, 0, 35)));
  ASSERT_EQ(e.cloud.size(), 4000u);
  EXPECT_GT(e.mean_copies, 1.0);
  EXPECT_EQ(e.plain_fallbacks, 0u);
  const EdgeError ew = edge_error(w.cloud.points, cube, 2 * w.radius);
  const EdgeError ee = edge_error(e.cloud.points, cube, 2 * e.radius);
  ASSERT_GT(ew.count, 300u);
  ASSERT_GT(ee.count, 300u);
  EXPECT_LT(ee.mean, 0.75 * ew.mean) << ew.mean << " vs " << ee.mean;
  EXPECT_LT(mean_distance_to_mesh(e.cloud.points, cube), mean_distance_to_mesh(in.points, cube));
  for (const Vec3d& p : e.positions) ASSERT_TRUE(p.allFinite());
}

// Plain WLOP and edge-WLOP as printed (the paper's eq. 1) of `in` at radius h (0: the default) on a reference mesh:
// edge errors within 2h of its sharp edges, accuracies and surface uniformities, of
// the input too; printed under `label`.
struct WlopAndEdge {
  WlopResult w, e;
  EdgeError ew, ee;
  double acc_in, acc_w, acc_e, u_in, u_w, u_e;
};
WlopAndEdge run_both(const Cloud& in, const Mesh& reference, std::size_t target, double h, const char* label) {
  WlopAndEdge r;
  r.w = consolidate(in, printed(plain(target, h, 35)));
  r.e = consolidate(in, printed(edge(target, h, 35)));
  const double used = r.e.radius;
  r.ew = edge_error(r.w.cloud.points, reference, 2 * used);
  r.ee = edge_error(r.e.cloud.points, reference, 2 * used);
  r.acc_in = mean_distance_to_mesh(in.points, reference);
  r.acc_w = mean_distance_to_mesh(r.w.cloud.points, reference);
  r.acc_e = mean_distance_to_mesh(r.e.cloud.points, reference);
  r.u_in = surface_uniformity(in.points, reference);
  r.u_w = surface_uniformity(r.w.cloud.points, reference);
  r.u_e = surface_uniformity(r.e.cloud.points, reference);
  std::cout << label << ", h " << used << ": edge error wlop " << r.ew.mean << " edge-wlop " << r.ee.mean
            << "; accuracy input " << r.acc_in << " wlop " << r.acc_w << " edge-wlop " << r.acc_e
            << "; uniformity input " << r.u_in << " wlop " << r.u_w << " edge-wlop " << r.u_e << "\n";
  return r;
}

// One of the bundled CAD parts (tests/data/consolidation/NAME.off) and n points
// sampled unevenly from it with 0.3 % of its diagonal as noise.
struct SampledPart {
  Mesh mesh;
  double dbb;
  Cloud in;
};
SampledPart sampled_part(const char* name, int n, unsigned seed) {
  SampledPart s;
  s.mesh = read_mesh(test::source_dir() / "tests/data/consolidation" / (std::string(name) + ".off"));
  s.dbb = bounding_box(s.mesh.vertices).diagonal();
  s.in = noisy_uneven_sample(s.mesh, n, 0.003 * s.dbb, seed);
  return s;
}

TEST(EdgeWlop, SharperThanWlopOnFandisk) {
  // Hoppe's fandisk (tests/data/consolidation/README.md), 20k points sampled
  // unevenly with 0.3 % noise, consolidated to 4000 at the default h.
  const SampledPart fandisk = sampled_part("fandisk", 20000, 23);
  const WlopAndEdge r = run_both(fandisk.in, fandisk.mesh, 4000, 0, "fandisk 20k -> 4k");
  ASSERT_GT(r.ee.count, 1000u);
  EXPECT_LT(r.ee.mean, 0.75 * r.ew.mean) << r.ew.mean << " vs " << r.ee.mean;
  EXPECT_LT(r.acc_e, r.acc_in);
  EXPECT_GT(r.u_w, r.u_in + 0.1) << r.u_in << " -> " << r.u_w;
  EXPECT_GT(r.u_e, r.u_in + 0.1) << r.u_in << " -> " << r.u_e;
}

TEST(EdgeWlop, FandiskAtTheIssuesSetting) {
  // The issue's literal setting: 100k points (uneven, 0.3 % noise) to 20,000 at the
  // default h. Plain WLOP's accuracy with the whole E2 is about twice the input's here
  // (its drift off the surface; --repulsion tangential removes it).
  const SampledPart fandisk = sampled_part("fandisk", 100000, 41);
  const WlopAndEdge r = run_both(fandisk.in, fandisk.mesh, 20000, 0, "fandisk 100k -> 20k");
  ASSERT_GT(r.ee.count, 5000u);
  EXPECT_LT(r.ee.mean, 0.75 * r.ew.mean);
  EXPECT_LT(r.acc_e, r.acc_in);
  EXPECT_GT(r.u_w, r.u_in + 0.05);
  EXPECT_GT(r.u_e, r.u_in + 0.1);
}

TEST(EdgeWlop, SharperThanWlopOnBlade) {
  // CGAL's fan-blade part (tests/data/consolidation/README.md): 130 long, 10 wide
  // and 0.65 thick, so 0.3 % of d_bb (sigma = 0.39) is 60 % of the thickness and the
  // two faces overlap in the input. 20k points (not the issue's 100k, to keep the
  // test short; the fandisk test does the same) to 4000, at h = 4 d_bb / sqrt(100000),
  // the default h of the issue's 100k-point sample. At this input's own default h
  // (3.7, over 5 times the thickness) E1 mixes both faces and the rim and both
  // methods lose evenness (docs/consolidation.md).
  const SampledPart blade = sampled_part("blade", 20000, 24);
  const WlopAndEdge r = run_both(blade.in, blade.mesh, 4000, 4 * blade.dbb / std::sqrt(100000.0), "blade 20k -> 4k");
  ASSERT_GT(r.ee.count, 1000u);
  EXPECT_LT(r.ee.mean, 0.75 * r.ew.mean) << r.ew.mean << " vs " << r.ee.mean;
  // Edge-WLOP keeps the input's accuracy here (within 3 %) rather than improving
  // it; plain WLOP doubles the error.
  EXPECT_LT(r.acc_e, 1.05 * r.acc_in) << r.acc_in << " -> " << r.acc_e;
  EXPECT_GT(r.u_w, r.u_in + 0.05) << r.u_in << " -> " << r.u_w;
  EXPECT_GT(r.u_e, r.u_in + 0.05) << r.u_in << " -> " << r.u_e;
  for (const Vec3d& p : r.e.positions) ASSERT_TRUE(p.allFinite());
}

TEST(EdgeWlop, BladeAtTheIssuesSetting) {
  // The issue's literal setting: 100k points (uneven, 0.3 % noise) to 20,000 at the
  // default h (1.665, 2.6 times the blade's thickness). With eq. 5's printed beta the
  // edge variant's points paired up here (uniformity 0.36, below the input's 0.455);
  // WLOP's own beta = theta / r keeps them apart (docs/consolidation.md, "The
  // repulsion weight beta"). Plain WLOP's accuracy with the whole E2 is about twice
  // the input's (its drift off the surface; --repulsion tangential removes it).
  const SampledPart blade = sampled_part("blade", 100000, 24);
  // h = 0: the default, 4 d_bb / sqrt(100000) with d_bb of the noisy input.
  const WlopAndEdge r = run_both(blade.in, blade.mesh, 20000, 0, "blade 100k -> 20k");
  ASSERT_EQ(r.e.output_points, 20000u);
  ASSERT_GT(r.ee.count, 5000u);
  EXPECT_LT(r.ee.mean, 0.75 * r.ew.mean);
  EXPECT_LT(r.acc_e, r.acc_in);
  EXPECT_GT(r.u_w, r.u_in + 0.03);
  EXPECT_GT(r.u_e, r.u_in + 0.05);
}

// Two half-planes meeting at a convex crease along z (the x = y = 0 line) with
// the given opening angle (degrees), uniformly sampled; distance helpers.
struct Crease {
  Vec2d dir_b;
  Cloud cloud;
  explicit Crease(double angle, int n, unsigned seed) {
    const double t = (180 - angle) * M_PI / 180;
    dir_b = Vec2d(-std::cos(t), -std::sin(t));
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> u(0, 1);
    for (int i = 0; i < n; ++i) {
      const double s = u(rng), z = u(rng) - 0.5;
      const Vec2d q = i % 2 ? Vec2d(-s, 0) : Vec2d(s * dir_b);
      cloud.points.push_back(Vec3f(float(q.x()), float(q.y()), float(z)));
    }
  }
  double distance(const Vec3d& p) const {
    const Vec2d q(p.x(), p.y());
    const double da = q.x() <= 0 ? std::abs(q.y()) : q.norm();
    const double db = (q - dir_b * std::max(0.0, q.dot(dir_b))).norm();
    return std::min(da, db);
  }
  // Mean distance to the surface of the points within `reach` of the crease line
  // (and away from the open ends).
  double crease_error(const std::vector<Vec3d>& pts, double reach) const {
    double sum = 0;
    int n = 0;
    for (const Vec3d& p : pts)
      if (std::abs(p.z()) < 0.35 && Vec2d(p.x(), p.y()).norm() < reach) {
        sum += distance(p);
        ++n;
      }
    EXPECT_GT(n, 10);
    return sum / std::max(n, 1);
  }
};

TEST(EdgeWlop, TangentialRepulsionKeepsACreaseSharp) {
  const Crease crease(90, 16000, 25);
  const double h = 0.08;
  const WlopResult w = consolidate(crease.cloud, printed(plain(3200, h, 35)));
  WlopParams params = printed(edge(3200, h, 35));
  const WlopResult tangential = consolidate(crease.cloud, params);
  params.edge_repulsion = EdgeRepulsion::kFull;
  const WlopResult full = consolidate(crease.cloud, params);
  const double e_w = crease.crease_error(w.positions, h / 4);
  const double e_t = crease.crease_error(tangential.positions, h / 4);
  const double e_f = crease.crease_error(full.positions, h / 4);
  std::cout << "crease error: wlop " << e_w << ", edge tangential " << e_t << ", edge full " << e_f << "\n";
  EXPECT_LT(e_t, e_w) << e_w << " " << e_t << " " << e_f;
  EXPECT_LT(e_t, 0.5 * e_f) << e_w << " " << e_t << " " << e_f;
}

TEST(EdgeWlop, IdenticalAcrossThreadCounts) {
  const Mesh cube = test::box(Vec3f(-1, -1, -1), Vec3f(1, 1, 1));
  const Cloud in = noisy_uneven_sample(cube, 6000, 0.005, 27);
  WlopParams params = edge(1200, 0, 6);
  params.threads = 1;
  const WlopResult a = consolidate(in, params);
  params.threads = 2;
  const WlopResult b = consolidate(in, params);
  for (std::size_t i = 0; i < a.positions.size(); ++i) ASSERT_EQ(a.positions[i], b.positions[i]);
}

TEST(EdgeWlop, JacobianDensityAgreesWithExactEq18) {
  const Mesh cube = test::box(Vec3f(-1, -1, -1), Vec3f(1, 1, 1));
  const Cloud in = noisy_uneven_sample(cube, 5000, 0.002, 29);
  // One step from the same start: the same copies, and E1 moved by the weights
  // alone, which differ only where the density model is off.
  WlopParams params = printed(edge(1000, 0, 1));
  params.mu = 0;
  const WlopResult jacobian = consolidate(in, params);
  params.inverted_density = InvertedDensity::kExact;
  const WlopResult exact = consolidate(in, params);
  EXPECT_DOUBLE_EQ(exact.mean_copies, jacobian.mean_copies);
  const std::vector<int> start = initial_subset(in.size(), 1000, params.seed);
  double diff = 0, moved = 0;
  for (std::size_t i = 0; i < exact.positions.size(); ++i) {
    diff += (exact.positions[i] - jacobian.positions[i]).norm();
    moved += (exact.positions[i] - in.points[start[i]].cast<double>()).norm();
  }
  EXPECT_LT(diff, 0.15 * moved) << diff / 1000 << " vs moves of " << moved / 1000;
  // And over a full run both keep the cube's edges about as well.
  params = printed(edge(1000, 0, 20));
  const WlopResult j20 = consolidate(in, params);
  params.inverted_density = InvertedDensity::kExact;
  const WlopResult e20 = consolidate(in, params);
  const EdgeError ee = edge_error(e20.cloud.points, cube, 2 * e20.radius);
  const EdgeError ej = edge_error(j20.cloud.points, cube, 2 * j20.radius);
  EXPECT_NEAR(ee.mean, ej.mean, 0.2 * ee.mean);
}

TEST(EdgeWlop, UsesInputNormalsWhenAsked) {
  Cloud in = uneven_sphere(6000, 0.005, 31);
  for (const Vec3f& p : in.points) in.normals.push_back(p.normalized());
  WlopParams params = edge(1200, 0, 10);
  params.edge_normals = EdgeNormals::kInput;
  const WlopResult r = consolidate(in, params);
  EXPECT_LT(mean_sphere_distance(r.cloud.points), mean_sphere_distance(in.points));
  EXPECT_EQ(r.plain_fallbacks, 0u);
  // Without normals kInput falls back to the simple normals.
  in.normals.clear();
  const WlopResult s = consolidate(in, params);
  EXPECT_LT(mean_sphere_distance(s.cloud.points), mean_sphere_distance(in.points));
}

// ---- attributes ---------------------------------------------------------------------

TEST(WlopAttributes, ColoursAreCarried) {
  Cloud in = uneven_sphere(8000, 0.005, 33);
  for (const Vec3f& p : in.points)
    in.colours.push_back(p.z() > 0 ? Rgb{200, 30, 10} : Rgb{10, 40, 220});
  for (WlopMethod method : {WlopMethod::kWlop, WlopMethod::kEdgeWlop}) {
    WlopParams params = plain(1600, 0, 20);
    params.method = method;
    const WlopResult r = consolidate(in, params);
    ASSERT_EQ(r.cloud.colours.size(), r.cloud.size());
    int checked = 0;
    for (std::size_t i = 0; i < r.cloud.size(); ++i) {
      const float z = r.cloud.points[i].z();
      if (std::abs(z) < 1.5f * float(r.radius)) continue;  // a blend of both near z = 0
      const Rgb expected = z > 0 ? Rgb{200, 30, 10} : Rgb{10, 40, 220};
      EXPECT_EQ(r.cloud.colours[i], expected) << i;
      ++checked;
    }
    EXPECT_GT(checked, 1000);
  }
}

TEST(WlopAttributes, NormalsPointOutwards) {
  Cloud in = uneven_sphere(8000, 0.005, 35);
  for (Vec3f& p : in.points) p += Vec3f(0.3f, -0.2f, 5.f);  // off the origin
  const Vec3f centre(0.3f, -0.2f, 5.f);
  WlopParams params = plain(1600, 0, 20);
  params.estimate_normals = true;
  const WlopResult r = consolidate(in, params);  // no input normals: MST orientation
  ASSERT_EQ(r.cloud.normals.size(), r.cloud.size());
  for (std::size_t i = 0; i < r.cloud.size(); ++i) {
    EXPECT_NEAR(r.cloud.normals[i].norm(), 1.f, 1e-4f);
    EXPECT_GT(r.cloud.normals[i].dot(r.cloud.points[i] - centre), 0.8f) << i;
  }
  // With input normals, each output normal follows the nearby ones.
  for (const Vec3f& p : in.points) in.normals.push_back((p - centre).normalized());
  const WlopResult o = consolidate(in, params);
  for (std::size_t i = 0; i < o.cloud.size(); ++i)
    EXPECT_GT(o.cloud.normals[i].dot(o.cloud.points[i] - centre), 0.8f) << i;
}

TEST(WlopAttributes, NormalsPointOutwardsOnACube) {
  const Mesh cube = test::box(Vec3f(-1, -1, -1), Vec3f(1, 1, 1));
  const Cloud in = noisy_uneven_sample(cube, 12000, 0.003, 37);
  WlopParams params = edge(2000, 0, 20);
  params.estimate_normals = true;
  const WlopResult r = consolidate(in, params);
  for (std::size_t i = 0; i < r.cloud.size(); ++i)
    EXPECT_GT(r.cloud.normals[i].dot(r.cloud.points[i]), 0.f) << i;
}

// ---- bad input --------------------------------------------------------------------

TEST(WlopInput, FewerPointsThanRequestedProjectsThemAll) {
  const Cloud in = uneven_sphere(300, 0.01, 11);
  const WlopResult r = consolidate(in, plain(1000, 0, 5));
  EXPECT_TRUE(r.clamped);
  EXPECT_EQ(r.requested_points, 1000u);
  EXPECT_EQ(r.output_points, 300u);
  EXPECT_EQ(r.cloud.size(), 300u);
  for (const Vec3f& p : r.cloud.points) ASSERT_TRUE(p.allFinite());
}

// The profile's `points: auto`: ratio x |J| kept within [min(min_points, |J|), max_points].
TEST(WlopInput, RatioWithinBoundsOfPoints) {
  const Cloud in = uneven_sphere(3000, 0.01, 13);
  auto requested = [&](double ratio, std::size_t lo, std::size_t hi) {
    WlopParams p = plain(0, 0, 1);
    p.ratio = ratio;
    p.min_points = lo;
    p.max_points = hi;
    return consolidate(in, p).requested_points;
  };
  EXPECT_EQ(requested(0.2, 0, 0), 600u);
  EXPECT_EQ(requested(0.2, 1000, 0), 1000u);   // raised to the floor
  EXPECT_EQ(requested(0.2, 5000, 0), 3000u);   // the floor is at most the input
  EXPECT_EQ(requested(0.5, 0, 1200), 1200u);   // capped
  EXPECT_EQ(requested(0.2, 100, 1200), 600u);  // within both
  WlopParams crossed = plain(0, 0, 1);
  crossed.min_points = 2000;
  crossed.max_points = 1000;
  EXPECT_THROW(consolidate(in, crossed), InvalidInput);
  WlopParams fixed = plain(700, 0, 1);
  fixed.min_points = 1000;  // bounds only apply to the ratio
  EXPECT_EQ(consolidate(in, fixed).requested_points, 700u);
}

// An input point given twice, picked twice for the initial subset, would move as one
// point counted twice (the same E1 and E2 in every iteration).
TEST(WlopInput, DuplicatedPointsGiveDistinctOutputPoints) {
  const Cloud once = uneven_sphere(3000, 0.01, 12);
  Cloud twice;
  for (const Vec3f& p : once.points) {
    twice.points.push_back(p);
    twice.points.push_back(p);
  }
  auto coincident_pairs = [](const WlopResult& r) {
    std::vector<Vec3d> q = r.positions;
    std::sort(q.begin(), q.end(), [](const Vec3d& a, const Vec3d& b) {
      return std::lexicographical_compare(a.data(), a.data() + 3, b.data(), b.data() + 3);
    });
    int n = 0;
    for (std::size_t i = 1; i < q.size(); ++i) n += q[i] == q[i - 1];
    return n;
  };
  for (const WlopMethod method : {WlopMethod::kWlop, WlopMethod::kEdgeWlop}) {
    WlopParams params = plain(1500, 0, 10);
    params.method = method;
    const WlopResult r = consolidate(twice, params);
    EXPECT_EQ(r.output_points, 1500u);
    EXPECT_FALSE(r.clamped);
    EXPECT_EQ(coincident_pairs(r), 0);
  }
  // More points requested than there are distinct positions: all of them, once each.
  const WlopResult all = consolidate(twice, plain(4000, 0, 5));
  EXPECT_TRUE(all.clamped);
  EXPECT_EQ(all.output_points, 3000u);
  EXPECT_EQ(all.cloud.size(), 3000u);
  EXPECT_EQ(coincident_pairs(all), 0);
}

TEST(WlopInput, Rejected) {
  EXPECT_THROW(consolidate(Cloud{}, {}), InvalidInput);
  Cloud same;
  same.points.assign(50, Vec3f(1, 2, 3));
  EXPECT_THROW(consolidate(same, {}), InvalidInput);
  WlopParams explicit_radius;
  explicit_radius.radius = 0.1;
  EXPECT_THROW(consolidate(same, explicit_radius), InvalidInput);
  Cloud nan = uneven_sphere(100, 0.01, 1);
  nan.points[17].y() = std::numeric_limits<float>::quiet_NaN();
  EXPECT_THROW(consolidate(nan, {}), InvalidInput);
  Cloud inf = uneven_sphere(100, 0.01, 1);
  inf.points[3].x() = std::numeric_limits<float>::infinity();
  EXPECT_THROW(consolidate(inf, {}), InvalidInput);
  Cloud bad_colours = uneven_sphere(100, 0.01, 1);
  bad_colours.colours.resize(7);
  EXPECT_THROW(consolidate(bad_colours, {}), InvalidInput);

  const Cloud ok = uneven_sphere(100, 0.01, 1);
  auto with = [](auto change) {
    WlopParams p;
    change(p);
    return p;
  };
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.ratio = 0; })), InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.ratio = 1.5; })), InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.iterations = -1; })), InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.radius = -1; })), InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.radius = NAN; })), InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.fit_radius = -1; })), InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.fit_radius = INFINITY; })), InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.mu = 0.5; })), InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.threads = -1; })), InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.inversion_radius = 0.2; })),
               InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.shift_divisions = 0; })),
               InvalidInput);
  EXPECT_THROW(consolidate(ok, with([](WlopParams& p) { p.normal_neighbours = 2; })),
               InvalidInput);
}

// The issue's bad-input list for the edge variant: fewer points than requested,
// all points identical, NaN coordinates, no normals (estimated: the simple normals),
// plus degenerate neighbourhoods (a line, a handful of points).
TEST(WlopInput, EdgeVariantBadInput) {
  const Cloud few = uneven_sphere(300, 0.01, 11);
  const WlopResult r = consolidate(few, edge(1000, 0, 5));
  EXPECT_TRUE(r.clamped);
  EXPECT_EQ(r.cloud.size(), 300u);
  for (const Vec3d& p : r.positions) ASSERT_TRUE(p.allFinite());

  auto message = [](const Cloud& c, const WlopParams& p) -> std::string {
    try {
      consolidate(c, p);
    } catch (const InvalidInput& e) {
      return e.what();
    }
    return "";
  };
  Cloud same;
  same.points.assign(50, Vec3f(1, 2, 3));
  EXPECT_NE(message(same, edge(10, 0, 5)).find("coincide"), std::string::npos);
  Cloud nan = uneven_sphere(100, 0.01, 1);
  nan.points[17].y() = std::numeric_limits<float>::quiet_NaN();
  EXPECT_NE(message(nan, edge(10, 0, 5)).find("non-finite"), std::string::npos);

  // No normals while asked to use the input's: the simple normals are estimated
  // instead, giving exactly the default result.
  const Cloud in = uneven_sphere(3000, 0.01, 19);
  WlopParams params = edge(600, 0, 5);
  const WlopResult simple = consolidate(in, params);
  params.edge_normals = EdgeNormals::kInput;
  const WlopResult asked = consolidate(in, params);
  ASSERT_EQ(simple.positions.size(), asked.positions.size());
  for (std::size_t i = 0; i < simple.positions.size(); ++i)
    ASSERT_EQ(simple.positions[i], asked.positions[i]) << i;
  EXPECT_LT(simple.plain_fallbacks, 600u);

  // Degenerate neighbourhoods: points on a line (no plane to fit), and five points.
  Cloud line;
  for (int i = 0; i < 200; ++i) line.points.push_back(Vec3f(0.01f * float(i), 0, 0));
  Cloud five;
  for (int i = 0; i < 5; ++i) five.points.push_back(Vec3f(float(i % 2), float(i / 2), 0.1f * float(i)));
  for (const Cloud* c : {&line, &five}) {
    WlopParams p = edge(c->size() / 2, 0, 5);
    p.estimate_normals = true;
    const WlopResult d = consolidate(*c, p);
    ASSERT_EQ(d.cloud.size(), c->size() / 2);
    for (const Vec3d& q : d.positions) ASSERT_TRUE(q.allFinite());
    for (const Vec3f& n : d.cloud.normals) ASSERT_TRUE(n.allFinite());
  }
}

TEST(WlopInput, ProjectionOnDegenerateNeighbourhoodsGivesFinitePoints) {
  // No plane to fit: points on a line, five points, two clusters far apart; both methods
  // project by default and must return finite points where they cannot fit.
  Cloud line, five, far;
  for (int i = 0; i < 400; ++i) line.points.push_back(Vec3f(0.01f * float(i), 0, 0));
  for (int i = 0; i < 5; ++i) five.points.push_back(Vec3f(float(i % 2), float(i / 2), 0.1f * float(i)));
  far = uneven_sphere(300, 0.01, 3);
  for (int i = 0; i < 300; ++i) far.points.push_back(far.points[std::size_t(i)] + Vec3f(100, 0, 0));
  for (const Cloud* c : {&line, &five, &far})
    for (const WlopMethod m : {WlopMethod::kWlop, WlopMethod::kEdgeWlop}) {
      WlopParams p = plain(std::max<std::size_t>(2, c->size() / 4), 0, 10);
      p.method = m;
      const WlopResult r = consolidate(*c, p);
      ASSERT_EQ(r.positions.size(), p.target_points);
      for (const Vec3d& x : r.positions) ASSERT_TRUE(x.allFinite());
      EXPECT_GT(r.fit_radius, 0);
    }
}

TEST(WlopInput, IsolatedPointsStayAndNothingIsNaN) {
  // Two clusters far apart; a radius so small that some projected points have no
  // input neighbour other than (coincident) themselves after the first move.
  Cloud in = uneven_sphere(500, 0.0, 13);
  for (Vec3f& p : in.points) p *= 0.1f;
  in.points.push_back(Vec3f(5, 5, 5));  // a lone point
  WlopParams params = plain(501, 0.02, 5);
  const WlopResult r = consolidate(in, params);
  ASSERT_EQ(r.cloud.size(), 501u);
  for (const Vec3f& p : r.cloud.points) ASSERT_TRUE(p.allFinite());
  // The lone point is its own only neighbour, coincident: it stays where it is.
  bool found = false;
  for (const Vec3f& p : r.cloud.points) found |= p == Vec3f(5, 5, 5);
  EXPECT_TRUE(found);
  EXPECT_GE(r.isolated_points, 1u);
}

// The smallest distance between two of the points.
double closest_pair(const std::vector<Vec3f>& p) {
  double best = std::numeric_limits<double>::infinity();
  for (std::size_t i = 0; i < p.size(); ++i)
    for (std::size_t j = i + 1; j < p.size(); ++j) best = std::min(best, double((p[i] - p[j]).norm()));
  return best;
}

TEST(WlopInput, ZeroIterationsReturnsTheInitialSubset) {
  const Cloud in = uneven_sphere(400, 0.01, 15);
  // The paper's update starts from the random subset (initial_subset).
  const WlopResult r = consolidate(in, printed(plain(50, 0, 0)));
  const std::vector<int> subset = initial_subset(400, 50, 1);
  ASSERT_EQ(r.cloud.size(), 50u);
  for (std::size_t i = 0; i < subset.size(); ++i) EXPECT_EQ(r.cloud.points[i], in.points[subset[i]]);
  // The projection from a spread-out one: input points, in input order, none as close
  // together as the random subset's closest pair (the uneven sphere's dense cap).
  const WlopResult spread = consolidate(in, plain(50, 0, 0));
  ASSERT_EQ(spread.cloud.size(), 50u);
  std::size_t next = 0;
  for (const Vec3f& q : spread.cloud.points) {
    while (next < in.size() && in.points[next] != q) ++next;
    EXPECT_LT(next, in.size()) << "not an input point, or out of input order";
    ++next;
  }
  EXPECT_GT(closest_pair(spread.cloud.points), 2 * closest_pair(r.cloud.points));
}

}  // namespace
}  // namespace station
