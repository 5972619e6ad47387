// WLOP's vector kernels (reconstruct/wlop_kernels.h) against scalar double
// references, for every kernel set this CPU can run (the first is what
// consolidate uses; the others would run on other CPUs).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "reconstruct/detail/radius_grid.h"
#include "reconstruct/wlop.h"
#include "reconstruct/detail/wlop_kernels.h"

namespace station::detail {
namespace {

// Restores the default kernel set when a test ends.
struct VariantGuard {
  ~VariantGuard() { use_kernel_variant(kernel_variants().front()); }
};

constexpr int kN = 37;  // not a multiple of any lane count: tails are exercised

struct Offsets {
  std::vector<float> dx, dy, dz, r2;
};

// kN offsets within about h of the origin (some beyond h, one at the origin).
Offsets random_offsets(double h, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.1 * h, 1.1 * h);
  Offsets o;
  for (int k = 0; k < kN + kFloatPad; ++k) {
    double x = u(rng), y = u(rng), z = 0.2 * u(rng);
    if (k == 5) x = y = z = 0;
    o.dx.push_back(float(x));
    o.dy.push_back(float(y));
    o.dz.push_back(float(z));
    o.r2.push_back(float(x * x + y * y + z * z));
  }
  return o;
}

TEST(WlopKernels, VariantsAreListedAndUnknownOnesRejected) {
  const std::vector<std::string> names = kernel_variants();
  ASSERT_FALSE(names.empty());
  EXPECT_EQ(names.back(), "base");
  for (const std::string& n : names) EXPECT_TRUE(n == "avx512" || n == "avx2" || n == "base") << n;
  EXPECT_THROW(use_kernel_variant("nonsense"), std::invalid_argument);
  // Says which sets this machine could check (a CPU without AVX-512 cannot run that one).
  std::string list;
  for (const std::string& n : names) list += " " + n;
  std::printf("kernel sets on this CPU:%s%s\n", list.c_str(),
              std::find(names.begin(), names.end(), "avx512") != names.end()
                  ? ""
                  : " (no AVX-512 here: that set is not checked)");
}

// A noisy cube (edges and corners), 3,000 points.
Cloud noisy_cube() {
  std::mt19937 rng(21);
  std::normal_distribution<double> g(0, 1);
  Cloud cloud;
  while (cloud.size() < 3000) {
    Vec3d d(g(rng), g(rng), g(rng));
    d = d.cwiseQuotient(d.cwiseAbs().maxCoeff() * Vec3d::Ones());  // on a cube: edges and corners
    cloud.points.push_back((d + 0.005 * Vec3d(g(rng), g(rng), g(rng))).cast<float>());
  }
  return cloud;
}

// Both methods, both repulsions, on every kernel set this CPU has: the same bits as
// the first (default) set, point for point, and the same copy counts. The sets differ
// in speed only (one logical lane width, no hardware estimates, no FMA contraction),
// so one input gives one output on any machine. Before, the AVX-512 set drifted from
// the others by up to 0.7 % of h (its 14-bit 1/sqrt estimate and FMA tipped discrete
// choices for a few points).
TEST(WlopKernels, EveryKernelSetGivesTheSameBits) {
  VariantGuard guard;
  const Cloud cloud = noisy_cube();
  struct Case {
    WlopMethod method;
    WlopRepulsion repulsion;
    WlopAttraction attraction;
    const char* label;
  };
  const Case cases[] = {
      {WlopMethod::kEdgeWlop, WlopRepulsion::kFull, WlopAttraction::kL1, "edge-wlop"},
      {WlopMethod::kWlop, WlopRepulsion::kFull, WlopAttraction::kL1, "wlop"},
      {WlopMethod::kWlop, WlopRepulsion::kTangential, WlopAttraction::kL1, "wlop tangential"},
      {WlopMethod::kWlop, WlopRepulsion::kTangential, WlopAttraction::kProjection, "wlop projection"},
      {WlopMethod::kEdgeWlop, WlopRepulsion::kTangential, WlopAttraction::kProjection,
       "edge-wlop projection"}};
  for (const Case& c : cases) {
    WlopParams p;
    p.method = c.method;
    p.repulsion = c.repulsion;
    p.attraction = c.attraction;
    p.target_points = 600;
    p.iterations = 10;
    p.estimate_normals = true;
    std::vector<Vec3d> first;
    std::vector<Vec3f> first_normals;
    double first_copies = 0;
    for (const std::string& name : kernel_variants()) {
      use_kernel_variant(name);
      const WlopResult r = consolidate(cloud, p);
      ASSERT_EQ(r.positions.size(), 600u) << name;
      if (c.method == WlopMethod::kEdgeWlop && c.attraction == WlopAttraction::kL1) {
        EXPECT_GT(r.mean_copies, 1.0) << name;
      }
      if (first.empty()) {
        first = r.positions;
        first_normals = r.cloud.normals;
        first_copies = r.mean_copies;
        continue;
      }
      std::size_t differ = 0;
      double worst = 0;
      for (std::size_t i = 0; i < first.size(); ++i) {
        differ += r.positions[i] != first[i];
        worst = std::max(worst, (r.positions[i] - first[i]).norm());
      }
      EXPECT_EQ(differ, 0u) << c.label << ": " << name << " against " << kernel_variants().front()
                            << ", largest difference " << worst / r.radius << " h";
      EXPECT_TRUE(r.cloud.normals == first_normals) << c.label << ": " << name;
      EXPECT_EQ(r.mean_copies, first_copies) << c.label << ": " << name;
    }
  }
}

TEST(WlopKernels, InvertCopyMatchesTheSphericalInversion) {
  VariantGuard guard;
  const double h = 0.05, D = 0.4, Q = 0.8, shift = 0.03;
  const Vec3d a = Vec3d(0.3, -0.2, 0.93).normalized();
  const Offsets o = random_offsets(h, 7);
  for (const std::string& name : kernel_variants()) {
    use_kernel_variant(name);
    for (int t = 0; t < 3; ++t) {
      const double Dt = D + t * shift;
      std::vector<float> ux(kN + kFloatPad), uy(ux), uz(ux), ur2(ux);
      const int count = invert_copy(o.dx.data(), o.dy.data(), o.dz.data(), o.r2.data(), kN, Dt, Q,
                                    a, h * h, ux.data(), uy.data(), uz.data(), ur2.data());
      // f(p, c, r) = c + (2r - |p - c|) (p - c) / |p - c| with x_i at the origin,
      // c = -Dt a and r such that f(x_i) lies Q from c.
      const Vec3d c = -Dt * a;
      const double r = (Q + Dt) / 2;
      const auto f = [&](const Vec3d& p) {
        const Vec3d d = p - c;
        return Vec3d(c + (2 * r - d.norm()) * d / d.norm());
      };
      const Vec3d xi = f(Vec3d::Zero());
      int expected = 0;
      for (int k = 0; k < kN; ++k) {
        const Vec3d p(o.dx[k], o.dy[k], o.dz[k]);
        const Vec3d u = f(p) - xi;
        // Float: about 1e-7 relative to the offset (copies beyond h are magnified).
        const double tol = 1e-6 * std::max(h, u.norm());
        EXPECT_NEAR(ux[k], u.x(), tol) << name << " t " << t << " k " << k;
        EXPECT_NEAR(uy[k], u.y(), tol) << name << " t " << t << " k " << k;
        EXPECT_NEAR(uz[k], u.z(), tol) << name << " t " << t << " k " << k;
        EXPECT_NEAR(ur2[k], u.squaredNorm(), 2 * tol * std::max(h, u.norm())) << name << " t " << t << " k " << k;
        expected += u.squaredNorm() < h * h;
      }
      EXPECT_EQ(count, expected) << name << " t " << t;
      EXPECT_GT(expected, 3);
      EXPECT_LT(expected, kN);
    }
  }
}

TEST(WlopKernels, FloatAttractionAndWeightsMatchScalarSums) {
  VariantGuard guard;
  const double h = 0.05;
  const KernelShape shape{h * h, 16 / (h * h), 1e-18 * h * h};
  const Offsets o = random_offsets(h, 11);
  std::vector<float> weight(kN + kFloatPad), nx(weight), ny(weight), nz(weight), v(weight);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int k = 0; k < kN + kFloatPad; ++k) {
    weight[k] = float(0.5 + 0.5 * std::abs(u(rng)));
    const Vec3d n = Vec3d(u(rng), u(rng), u(rng)).normalized();
    nx[k] = float(n.x());
    ny[k] = float(n.y());
    nz[k] = float(n.z());
    v[k] = float(1 + 10 * std::abs(u(rng)));
  }
  const Vec3d a = Vec3d(0.1, 0.7, -0.7).normalized();
  const double g[3] = {1.6, 1.45, 1.3};
  for (const std::string& name : kernel_variants()) {
    use_kernel_variant(name);
    const KernelSums s = attraction_sum(o.dx.data(), o.dy.data(), o.dz.data(), o.r2.data(),
                                        weight.data(), kN, shape);
    double w = 0;
    Vec3d d = Vec3d::Zero();
    for (int k = 0; k < kN; ++k) {
      const double r2 = o.r2[k];
      if (!(r2 > shape.eps2 && r2 < shape.h2)) continue;
      const double alpha = std::exp(-r2 * shape.inv_s2) / std::sqrt(r2) * weight[k];
      w += alpha;
      d += alpha * Vec3d(o.dx[k], o.dy[k], o.dz[k]);
    }
    ASSERT_GT(w, 0);
    EXPECT_NEAR(s.w, w, 1e-6 * w) << name;
    EXPECT_LT((s.d - d).norm(), 1e-6 * w * h) << name;

    std::vector<float> out(kN + kFloatPad);
    edge_weights(nx.data(), ny.data(), nz.data(), v.data(), kN, a, g, 3, out.data());
    for (int k = 0; k < kN; ++k) {
      const double c = Vec3d(nx[k], ny[k], nz[k]).dot(a);
      double S = 0;
      for (double gt : g) S += 1 / (gt * std::sqrt(1 + (gt * gt - 1) * c * c));
      const double expected = 1 / (1 + (v[k] - 1) * S);
      EXPECT_NEAR(out[k], expected, 1e-6 * expected) << name << " k " << k;
    }
  }
}

TEST(WlopKernels, NearestAndSignedNormalSum) {
  VariantGuard guard;
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1, 1);
  const int m = 200;  // records by sorted position
  std::vector<float> rec((m + kFloatPad) * kRecordFloats, 0.f);
  for (int p = 0; p < m; ++p) {
    const Vec3d n = Vec3d(u(rng), u(rng), u(rng)).normalized();
    const Vec3d pca = (n + 0.3 * Vec3d(u(rng), u(rng), u(rng))).normalized();
    float* r = &rec[std::size_t(p) * kRecordFloats];
    r[kNx] = float(n.x());
    r[kNy] = float(n.y());
    r[kNz] = float(n.z());
    r[kMx] = float(pca.x());
    r[kMy] = float(pca.y());
    r[kMz] = float(pca.z());
    r[kV] = float(p + 1);
  }
  std::vector<int> pos(kN + kFloatPad);
  std::vector<float> r2(kN + kFloatPad);
  for (int k = 0; k < kN + kFloatPad; ++k) {
    pos[k] = (k * 7 + 3) % m;
    r2[k] = float(1 + u(rng));
  }
  r2[29] = r2[17] = 0.01f;  // a tie: the first wins
  r2[kN + 1] = 0.0f;        // past the end: never the answer
  const float ref[3] = {0.f, 0.6f, 0.8f};
  for (const std::string& name : kernel_variants()) {
    use_kernel_variant(name);
    EXPECT_EQ(nearest(r2.data(), kN), 17) << name;
    EXPECT_EQ(nearest(r2.data(), 1), 0) << name;
    for (bool oriented : {false, true}) {
      std::vector<float> ox(kN + kFloatPad), oy(ox), oz(ox), ov(ox);
      const Vec3d sum = signed_normal_sum(pos.data(), kN, rec.data(), ref, oriented, ox.data(),
                                          oy.data(), oz.data(), ov.data());
      Vec3d expected = Vec3d::Zero();
      int flipped = 0;
      for (int k = 0; k < kN; ++k) {
        const float* r = &rec[std::size_t(pos[k]) * kRecordFloats];
        const double dot = r[kMx] * ref[0] + r[kMy] * ref[1] + r[kMz] * ref[2];
        const double sign = oriented || dot >= 0 ? 1 : -1;
        flipped += sign < 0;
        EXPECT_EQ(ox[k], float(sign * r[kNx])) << name << " k " << k;
        EXPECT_EQ(oy[k], float(sign * r[kNy])) << name << " k " << k;
        EXPECT_EQ(oz[k], float(sign * r[kNz])) << name << " k " << k;
        EXPECT_EQ(ov[k], r[kV]) << name << " k " << k;
        expected += sign * Vec3d(r[kNx], r[kNy], r[kNz]);
      }
      EXPECT_LT((sum - expected).norm(), 1e-5) << name;
      if (!oriented) {
        EXPECT_GT(flipped, 5);
      }
    }
  }
}

TEST(WlopKernels, GatherRunKeepsThePointsWithinHInOrder) {
  VariantGuard guard;
  std::mt19937 rng(13);
  std::uniform_real_distribution<double> u(0, 1);
  const int m = 203;  // coordinates by sorted position, 8 readable past the end
  std::vector<double> xs(m + 8), ys(m + 8), zs(m + 8);
  for (int p = 0; p < m + 8; ++p) {
    xs[p] = u(rng);
    ys[p] = u(rng);
    zs[p] = u(rng);
  }
  const Vec3d q(0.5, 0.45, 0.55);
  const double h2 = 0.35 * 0.35;
  for (const std::string& name : kernel_variants()) {
    use_kernel_variant(name);
    // Two runs appended one after the other, the first ending mid-block.
    const int runs[2][2] = {{3, 70}, {101, m}};
    std::vector<int> pos(m + 16, -1);
    std::vector<float> dx(m + 16), dy(dx), dz(dx), r2(dx);
    int n = 0;
    for (const auto& run : runs)
      n = gather_run(xs.data(), ys.data(), zs.data(), run[0], run[1], q, h2, n, pos.data(),
                     dx.data(), dy.data(), dz.data(), r2.data());
    std::vector<int> expected;
    for (const auto& run : runs)
      for (int p = run[0]; p < run[1]; ++p) {
        const double x = xs[p] - q.x(), y = ys[p] - q.y(), z = zs[p] - q.z();
        if (x * x + y * y + z * z < h2) expected.push_back(p);
      }
    ASSERT_EQ(n, int(expected.size())) << name;
    ASSERT_GT(n, 10);
    ASSERT_LT(n, m - 80);
    for (int k = 0; k < n; ++k) {
      const int p = expected[k];
      EXPECT_EQ(pos[k], p) << name << " k " << k;
      EXPECT_EQ(dx[k], float(xs[p] - q.x())) << name << " k " << k;
      EXPECT_EQ(dy[k], float(ys[p] - q.y())) << name << " k " << k;
      EXPECT_EQ(dz[k], float(zs[p] - q.z())) << name << " k " << k;
      const double x = xs[p] - q.x(), y = ys[p] - q.y(), z = zs[p] - q.z();
      EXPECT_EQ(r2[k], float(x * x + y * y + z * z)) << name << " k " << k;
    }
  }
}

TEST(WlopKernels, GridSumsMatchScalarSums) {
  VariantGuard guard;
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<Vec3d> pts;
  for (int i = 0; i < 3000; ++i) pts.emplace_back(u(rng), u(rng), 0.1 * u(rng));
  const double h = 0.08;
  RadiusGrid grid;
  grid.build(pts.data(), pts.size(), h);
  std::vector<double> weight(pts.size() + RadiusGrid::kPad, 0.0);
  for (std::size_t p = 0; p < pts.size(); ++p) weight[p] = 0.5 + u(rng);
  const KernelShape shape{h * h, 16 / (h * h), 1e-18 * h * h};
  const int* ids = grid.ids().data();
  for (const std::string& name : kernel_variants()) {
    use_kernel_variant(name);
    for (int sp : {0, 17, 1500, 2999}) {
      const Vec3d q = pts[ids[sp]] + Vec3d(0.001, -0.002, 0.0005);
      double dens = 0, wa = 0, wr = 0;
      Vec3d da = Vec3d::Zero(), dr = Vec3d::Zero();
      for (std::size_t p = 0; p < pts.size(); ++p) {
        const Vec3d d = pts[ids[p]] - q;
        const double r2 = d.squaredNorm();
        if (r2 >= h * h) continue;
        const double theta = std::exp(-r2 * shape.inv_s2);
        dens += theta;
        if (r2 > shape.eps2) {
          wa += theta / std::sqrt(r2) * weight[p];
          da += theta / std::sqrt(r2) * weight[p] * d;
        }
        if (int(p) != sp) {
          wr += theta * weight[p];
          dr += theta * weight[p] * d;
        }
      }
      const KernelSums sd = density_sum(grid, q, shape);
      const KernelSums sa = attraction_sum(grid, weight.data(), q, shape);
      const KernelSums sr = repulsion_sum(grid, weight.data(), q, shape, sp);
      EXPECT_NEAR(sd.w, dens, 1e-12 * dens) << name;
      EXPECT_NEAR(sa.w, wa, 1e-12 * wa) << name;
      EXPECT_LT((sa.d - da).norm(), 1e-12 * wa * h) << name;
      EXPECT_NEAR(sr.w, wr, 1e-12 * wr) << name;
      EXPECT_LT((sr.d - dr).norm(), 1e-12 * wr * h) << name;
      EXPECT_GT(dens, 1) << name;  // more than q's own term: the sums mean something
    }
  }
}

}  // namespace
}  // namespace station::detail
