// FPFH descriptors (capture/features.h): invariant to rigid motion, equal on
// equal local shapes, different on different ones, bad input rejected.
#include "registration/features.h"

#include <gtest/gtest.h>

#include <limits>

#include <random>

#include <Eigen/Geometry>
#include <numeric>

#include "registration/icp.h"
#include "core/error.h"
#include "core/sampling.h"
#include "core/io.h"
#include "core/kdtree.h"
#include "test_util.h"

namespace station {
namespace {

float distance(const FpfhDescriptor& a, const FpfhDescriptor& b) {
  float d = 0;
  for (int i = 0; i < kFpfhBins; ++i) d += (a[i] - b[i]) * (a[i] - b[i]);
  return std::sqrt(d);
}

// Outward unit normals of a sphere centred at the origin.
std::vector<Vec3f> radial(const std::vector<Vec3f>& p) {
  std::vector<Vec3f> n;
  for (const Vec3f& q : p) n.push_back(q.normalized());
  return n;
}

TEST(Fpfh, InvariantToRigidMotionOnARealScan) {
  // Generic positions (a real scan, not a symmetric grid, where ties between
  // the two ends of a pair make the Darboux frame arbitrary).
  const Cloud c = read_cloud(test::source_dir() / "data/dragon_stand/dragonStandRight_0.ply");
  const std::vector<Vec3f> pts = voxel_downsample(c.points, 0.003);
  const PointIndex index(pts);
  const std::vector<Vec3f> nrm = pca_normals(index, 16, Vec3f::Zero());
  const auto f0 = compute_fpfh(index, nrm, 0.015);
  const Eigen::Matrix3f R = Eigen::AngleAxisf(1.1f, Vec3f(1, 2, 3).normalized()).toRotationMatrix();
  std::vector<Vec3f> pm, nm;
  for (std::size_t i = 0; i < pts.size(); ++i) {
    pm.push_back(R * pts[i] + Vec3f(0.3f, -0.2f, 1.0f));
    nm.push_back(R * nrm[i]);
  }
  const PointIndex index_m(pm);
  const auto f1 = compute_fpfh(index_m, nm, 0.015);
  ASSERT_EQ(f0.size(), pts.size());
  std::vector<float> d;
  for (std::size_t i = 0; i < f0.size(); ++i) d.push_back(distance(f0[i], f1[i]));
  std::sort(d.begin(), d.end());
  // Float rounding moves a few values across bin edges only.
  EXPECT_LT(d[d.size() / 2], 1e-3f);
  EXPECT_LT(d[d.size() * 99 / 100], 5.0f);
  for (int blk = 0; blk < 3; ++blk) {
    float s = 0;
    for (int b = 0; b < 11; ++b) s += f0[0][blk * 11 + b];
    EXPECT_NEAR(s, 100.0f, 1e-3);
  }
}

TEST(Fpfh, FlatDiffersFromCorner) {
  // Box faces sampled on grids; a face centre (flat) against a corner.
  std::vector<Vec3f> pts, nrm;
  const Vec3f ext(0.1f, 0.05f, 0.08f);
  for (int f = 0; f < 3; ++f)
    for (int s : {-1, 1})
      for (int i = 0; i <= 20; ++i)
        for (int j = 0; j <= 20; ++j) {
          Vec3f p, n = Vec3f::Zero();
          const int a = (f + 1) % 3, b = (f + 2) % 3;
          p[f] = s * ext[f];
          p[a] = -ext[a] + 2 * ext[a] * i / 20.0f;
          p[b] = -ext[b] + 2 * ext[b] * j / 20.0f;
          n[f] = float(s);
          pts.push_back(p);
          nrm.push_back(n);
        }
  const PointIndex index(pts);
  const auto f0 = compute_fpfh(index, nrm, 0.035);
  const auto centre = [&](int face) { return std::size_t(face * 441 + 10 * 21 + 10); };
  // Two flat centres: their own pairs are all (0, 0, 0), the middle bins
  // (neighbours' histograms near the face edges add a little).
  EXPECT_LT(distance(f0[centre(0)], f0[centre(1)]), 1.0f);
  EXPECT_GT(f0[centre(0)][5], 80.0f);
  EXPECT_GT(distance(f0[centre(0)], f0[0]), 30.0f);
}

TEST(Fpfh, SpherePointsLookAlikeAndNearestMatchesItself) {
  const Cloud s = test::icosphere(4, 0.1).as_cloud();
  const PointIndex index(s.points);
  const auto f = compute_fpfh(index, radial(s.points), 0.03);
  // All points of a sphere have the same neighbourhood shape.
  float worst = 0;
  for (std::size_t i = 1; i < f.size(); ++i) worst = std::max(worst, distance(f[0], f[i]));
  EXPECT_LT(worst, 25.0f);
  // Nearest descriptor of each descriptor in its own set is itself (or an equal one).
  const std::vector<FpfhDescriptor> q(f.begin(), f.begin() + 10);
  const std::vector<int> nn = nearest_descriptors(q, f);
  for (int i = 0; i < 10; ++i) EXPECT_FLOAT_EQ(distance(f[nn[i]], q[i]), 0.0f);
  EXPECT_EQ(nearest_descriptors(q, {}), std::vector<int>(10, -1));
}

// The k-d tree over many descriptors answers as the scan in index order does: the
// least distance, the lowest index among exact ties (duplicated descriptors, zero
// ones of isolated points).
TEST(Fpfh, NearestDescriptorsOverATreeAreTheScansAnswer) {
  std::mt19937 rng(21);
  std::gamma_distribution<float> g(0.6f, 8.f);
  std::vector<FpfhDescriptor> ref(3000);
  for (FpfhDescriptor& d : ref)
    for (float& b : d) b = g(rng);
  for (int k = 0; k < 40; ++k) ref[std::size_t(2900 - 37 * k)] = ref[std::size_t(k * 53)];  // duplicates
  for (int k = 0; k < 5; ++k) ref[std::size_t(100 + 400 * k)].fill(0.f);
  std::vector<FpfhDescriptor> q(600);
  for (std::size_t i = 0; i < q.size(); ++i) {
    q[i] = ref[(i * 7919) % ref.size()];
    if (i % 3 == 1)
      for (float& b : q[i]) b += std::normal_distribution<float>(0.f, 2.f)(rng);
    if (i % 50 == 0) q[i].fill(0.f);
  }
  const std::vector<int> nn = nearest_descriptors(q, ref);
  ASSERT_EQ(nn.size(), q.size());
  std::size_t tied = 0;
  for (std::size_t i = 0; i < q.size(); ++i) {
    float best = std::numeric_limits<float>::infinity();
    int bi = -1;
    for (std::size_t j = 0; j < ref.size(); ++j) {
      float d = 0;
      for (int b = 0; b < kFpfhBins; ++b) {
        const float e = q[i][std::size_t(b)] - ref[j][std::size_t(b)];
        d += e * e;
      }
      if (d < best) best = d, bi = int(j);
      else if (d == best) ++tied;
    }
    EXPECT_EQ(nn[i], bi) << i;
  }
  EXPECT_GT(tied, 10u);  // the ties were there to be broken
}

// Colour-gated matches (a cube's faces: alike in shape, told apart by their stickers):
// the nearest descriptor whose colour agrees, not the nearest one; none where no
// candidate agrees. Over the tree (many descriptors) and the scan (few) alike.
TEST(Fpfh, GatedMatchesTakeTheNearestDescriptorOfTheSameColour) {
  std::mt19937 rng(5);
  std::gamma_distribution<float> g(0.6f, 8.f);
  for (const std::size_t n : {std::size_t(100), std::size_t(2000)}) {
    std::vector<FpfhDescriptor> ref(n);
    std::vector<Vec3f> ref_colour(n);
    const Vec3f red(0.8f, 0.1f, 0.1f), blue(0.1f, 0.1f, 0.8f);
    for (std::size_t j = 0; j < n; ++j) {
      for (float& b : ref[j]) b = g(rng);
      ref_colour[j] = j % 2 ? blue : red;
    }
    // Each query: an odd (blue) reference descriptor, a little off, asked for in red.
    // Its nearest is that blue one; the gated answer must be a red one, and the
    // nearest red one by the scan.
    std::vector<FpfhDescriptor> q;
    std::vector<Vec3f> q_colour;
    for (std::size_t j = 1; j < n; j += 20) {
      FpfhDescriptor d = ref[j];
      d[0] += 0.5f;
      q.push_back(d);
      q_colour.push_back(red);
    }
    const std::vector<int> plain = nearest_descriptors(q, ref);
    const std::vector<int> gated = nearest_descriptors_gated(q, q_colour, ref, ref_colour, 0.08, int(n));
    ASSERT_EQ(gated.size(), q.size());
    for (std::size_t i = 0; i < q.size(); ++i) {
      EXPECT_EQ(plain[i] % 2, 1) << n << " " << i;
      ASSERT_GE(gated[i], 0) << n << " " << i;
      EXPECT_EQ(gated[i] % 2, 0) << n << " " << i;
      float best = std::numeric_limits<float>::infinity();
      int bi = -1;
      for (std::size_t j = 0; j < n; j += 2) {
        float d = 0;
        for (int b = 0; b < kFpfhBins; ++b) d += (q[i][std::size_t(b)] - ref[j][std::size_t(b)]) * (q[i][std::size_t(b)] - ref[j][std::size_t(b)]);
        if (d < best) best = d, bi = int(j);
      }
      EXPECT_EQ(gated[i], bi) << n << " " << i;
    }
    // Only the nearest candidate looked at: over the tree it is the blue one, so no
    // match; the scan looks at every descriptor.
    const std::vector<int> first_only = nearest_descriptors_gated(q, q_colour, ref, ref_colour, 0.08, 1);
    EXPECT_EQ(first_only, n < 256 ? gated : std::vector<int>(q.size(), -1)) << n;
    // A colour no reference descriptor has: no match.
    const std::vector<Vec3f> green(q.size(), Vec3f(0.1f, 0.8f, 0.1f));
    EXPECT_EQ(nearest_descriptors_gated(q, green, ref, ref_colour, 0.08, int(n)), std::vector<int>(q.size(), -1));
  }
  const std::vector<FpfhDescriptor> one(1);
  EXPECT_THROW(nearest_descriptors_gated(one, {}, one, {Vec3f::Zero()}, 0.1, 8), InvalidInput);
  EXPECT_THROW(nearest_descriptors_gated(one, {Vec3f::Zero()}, one, {Vec3f::Zero()}, 0.1, 0), InvalidInput);
}

TEST(Fpfh, BadInputIsRejected) {
  const Cloud s = test::icosphere(2, 0.1).as_cloud();
  const PointIndex index(s.points);
  EXPECT_THROW(compute_fpfh(index, {}, 0.03), InvalidInput);
  EXPECT_THROW(compute_fpfh(index, radial(s.points), 0.0), InvalidInput);
  // An isolated point gets a zero descriptor, not NaN.
  const PointIndex lone(std::vector<Vec3f>{Vec3f(0, 0, 0), Vec3f(1, 0, 0)});
  const auto f = compute_fpfh(lone, {Vec3f(0, 0, 1), Vec3f(0, 0, 1)}, 0.1);
  for (float x : f[0]) EXPECT_EQ(x, 0.0f);
}

}  // namespace
}  // namespace station
