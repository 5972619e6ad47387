#include "core/kdtree.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <thread>
#include <cmath>
#include <random>

namespace station {
namespace {

std::vector<Vec3f> random_points(int n, unsigned seed, float scale = 1.f) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-scale, scale);
  std::vector<Vec3f> p(n);
  for (auto& x : p) x = Vec3f(u(rng), u(rng), u(rng));
  return p;
}

// Brute-force reference: every point with its distance, closest first.
std::vector<std::pair<int, float>> brute_sorted(const std::vector<Vec3f>& pts, const Vec3f& q) {
  std::vector<std::pair<int, float>> all;
  for (int i = 0; i < int(pts.size()); ++i) all.emplace_back(i, (pts[i] - q).norm());
  std::sort(all.begin(), all.end(), [](auto& a, auto& b) { return a.second < b.second; });
  return all;
}

TEST(PointIndex, NearestMatchesBruteForce) {
  const auto pts = random_points(3000, 1);
  PointIndex index(pts);
  EXPECT_EQ(index.size(), pts.size());
  for (const Vec3f& q : random_points(300, 2, 1.5f)) {
    const auto ref = brute_sorted(pts, q);
    const auto [i, d] = index.nearest(q);
    EXPECT_EQ(i, ref[0].first);
    EXPECT_NEAR(d, ref[0].second, 1e-6f);
  }
}

// nearest_within: the same point as nearest() when it lies within the bound,
// nothing otherwise; the bound is inclusive; empty sets and bad bounds give nothing.
TEST(PointIndex, NearestWithinMatchesBruteForce) {
  const auto pts = random_points(3000, 3);
  PointIndex index(pts);
  int found = 0, missed = 0;
  for (const Vec3f& q : random_points(400, 4, 1.8f)) {
    const auto ref = brute_sorted(pts, q);
    for (float r : {0.02f, 0.08f, 0.3f}) {
      const auto [i, d] = index.nearest_within(q, r);
      if (ref[0].second <= r) {
        EXPECT_EQ(i, ref[0].first);
        EXPECT_NEAR(d, ref[0].second, 1e-6f);
        ++found;
      } else {
        EXPECT_EQ(i, -1);
        EXPECT_TRUE(std::isinf(d));
        ++missed;
      }
    }
  }
  EXPECT_GT(found, 100);  // both branches are exercised
  EXPECT_GT(missed, 100);
  // Inclusive: a query exactly at distance r from its nearest point finds it.
  const auto [i, d] = index.nearest_within(pts[7] + Vec3f(0, 0, 0), 0.0f);
  EXPECT_EQ(i, 7);
  EXPECT_EQ(d, 0.0f);
  EXPECT_EQ(index.nearest_within(pts[7], -1.0f).first, -1);
  EXPECT_EQ(index.nearest_within(pts[7], std::nanf("")).first, -1);
  EXPECT_EQ(PointIndex({}).nearest_within(Vec3f::Zero(), 1.0f).first, -1);
}

TEST(PointIndex, NearestOfAnIndexedPointIsItself) {
  const auto pts = random_points(500, 3);
  PointIndex index(pts);
  for (int i = 0; i < int(pts.size()); ++i) {
    const auto [j, d] = index.nearest(pts[i]);
    EXPECT_EQ(j, i);
    EXPECT_EQ(d, 0.f);
  }
}

TEST(PointIndex, KnnOrderedAndMatchesBruteForce) {
  const auto pts = random_points(2000, 4);
  PointIndex index(pts);
  for (const Vec3f& q : random_points(100, 5)) {
    const auto ref = brute_sorted(pts, q);
    const auto got = index.knn(q, 12);
    ASSERT_EQ(got.size(), 12u);
    for (std::size_t k = 0; k < got.size(); ++k) {
      EXPECT_EQ(got[k].first, ref[k].first) << "rank " << k;
      EXPECT_NEAR(got[k].second, ref[k].second, 1e-6f);
      if (k > 0) {
        EXPECT_LE(got[k - 1].second, got[k].second);
      }
    }
  }
}

TEST(PointIndex, KnnIntoMatchesKnn) {
  const auto pts = random_points(2000, 14);
  PointIndex index(pts);
  std::uint32_t idx[16];
  float dsq[16];
  for (const Vec3f& q : random_points(100, 15)) {
    const auto ref = index.knn(q, 16);
    ASSERT_EQ(index.knn_into(q, 16, idx, dsq), 16);
    for (int k = 0; k < 16; ++k) {
      EXPECT_EQ(int(idx[k]), ref[std::size_t(k)].first) << "rank " << k;
      EXPECT_EQ(std::sqrt(dsq[k]), ref[std::size_t(k)].second);
    }
  }
  // Fewer points than asked for, none asked for, an empty set.
  PointIndex small(random_points(5, 16));
  EXPECT_EQ(small.knn_into(Vec3f::Zero(), 16, idx, dsq), 5);
  EXPECT_EQ(small.knn_into(Vec3f::Zero(), 0, idx, dsq), 0);
  EXPECT_EQ(PointIndex(std::vector<Vec3f>{}).knn_into(Vec3f::Zero(), 4, idx, dsq), 0);
}

TEST(PointIndex, KnnReturnsFewerWhenSetIsSmall) {
  const auto pts = random_points(5, 6);
  PointIndex index(pts);
  const auto got = index.knn(Vec3f::Zero(), 10);
  ASSERT_EQ(got.size(), 5u);
  const auto ref = brute_sorted(pts, Vec3f::Zero());
  for (int k = 0; k < 5; ++k) EXPECT_EQ(got[k].first, ref[k].first);
  EXPECT_TRUE(index.knn(Vec3f::Zero(), 0).empty());
}

TEST(PointIndex, RadiusMatchesBruteForce) {
  const auto pts = random_points(3000, 7);
  PointIndex index(pts);
  for (const Vec3f& q : random_points(100, 8)) {
    const float r = 0.25f;
    const auto ref = brute_sorted(pts, q);
    std::vector<std::pair<int, float>> expect;
    for (const auto& e : ref)
      if (e.second <= r) expect.push_back(e);
    const auto got = index.radius(q, r);
    ASSERT_EQ(got.size(), expect.size());
    for (std::size_t k = 0; k < got.size(); ++k) {
      EXPECT_EQ(got[k].first, expect[k].first);
      EXPECT_NEAR(got[k].second, expect[k].second, 1e-6f);
      EXPECT_LE(got[k].second, r);
    }
  }
}

TEST(PointIndex, RadiusUnsortedHoldsTheSamePointsAsRadius) {
  const auto pts = random_points(3000, 9);
  PointIndex index(pts);
  for (const Vec3f& q : random_points(50, 10)) {
    const auto sorted = index.radius(q, 0.3f);
    auto unsorted = index.radius_unsorted(q, 0.3f);
    ASSERT_EQ(unsorted, index.radius_unsorted(q, 0.3f));  // the same order every time
    std::sort(unsorted.begin(), unsorted.end(), [](auto& a, auto& b) { return a.first < b.first; });
    auto expect = sorted;
    std::sort(expect.begin(), expect.end(), [](auto& a, auto& b) { return a.first < b.first; });
    EXPECT_EQ(unsorted, expect);
  }
  EXPECT_TRUE(index.radius_unsorted(Vec3f(9, 9, 9), 0.1f).empty());
}

// any_in_radius: the points of radius_unsorted offered in its order until one is
// accepted (inclusive at the radius); false when none is, or none lies within.
TEST(PointIndex, AnyInRadiusOffersTheBallUntilOneIsAccepted) {
  const auto pts = random_points(3000, 19);
  PointIndex index(pts);
  int answered = 0;
  for (const Vec3f& q : random_points(50, 20)) {
    for (float r : {0.0f, 0.1f, 0.3f}) {
      const auto ball = index.radius_unsorted(q, r);
      std::vector<std::pair<int, float>> offered;
      // Accept nothing: every point of the ball offered, in its order.
      EXPECT_FALSE(index.any_in_radius(q, r, [&](int j, float d) { return offered.emplace_back(j, d), false; }));
      ASSERT_EQ(offered, ball);
      // Accept the third: the search stops there.
      offered.clear();
      const bool found = index.any_in_radius(q, r, [&](int j, float d) { return offered.emplace_back(j, d), offered.size() == 3; });
      EXPECT_EQ(found, ball.size() >= 3);
      EXPECT_EQ(offered.size(), std::min<std::size_t>(3, ball.size()));
      answered += found;
    }
  }
  EXPECT_GT(answered, 30);
  EXPECT_TRUE(index.any_in_radius(pts[5], 0.0f, [](int j, float) { return j == 5; }));  // at distance 0
  EXPECT_FALSE(index.any_in_radius(Vec3f(9, 9, 9), 0.1f, [](int, float) { return true; }));
  EXPECT_FALSE(PointIndex(std::vector<Vec3f>{}).any_in_radius(Vec3f::Zero(), 1.0f, [](int, float) { return true; }));
}

// radius_at_most: radius() itself (the same points in the same order) when the
// ball holds at most `count` points, nothing when it holds more; inclusive at the
// count and at the radius.
TEST(PointIndex, RadiusAtMostIsRadiusOrNothing) {
  const auto pts = random_points(3000, 11);
  PointIndex index(pts);
  int whole = 0, refused = 0;
  for (const Vec3f& q : random_points(60, 12)) {
    for (float r : {0.05f, 0.2f, 0.6f}) {
      const auto all = index.radius(q, r);
      for (std::size_t count : {std::size_t(0), std::size_t(5), all.size(), all.size() + 1, std::size_t(200)}) {
        const auto got = index.radius_at_most(q, r, count);
        if (all.size() <= count) {
          ASSERT_TRUE(got.has_value()) << all.size() << " <= " << count;
          EXPECT_EQ(*got, all);
          ++whole;
        } else {
          EXPECT_FALSE(got.has_value()) << all.size() << " > " << count;
          ++refused;
        }
      }
    }
  }
  EXPECT_GT(whole, 100);
  EXPECT_GT(refused, 100);
  PointIndex three({Vec3f(0, 0, 0), Vec3f(1, 0, 0), Vec3f(3, 0, 0)});
  const auto two = three.radius_at_most(Vec3f(0, 0, 0), 1.f, 2);
  ASSERT_TRUE(two.has_value());
  EXPECT_EQ(two->size(), 2u);  // the point at 1 counts
  EXPECT_FALSE(three.radius_at_most(Vec3f(0, 0, 0), 1.f, 1).has_value());
  const auto none = PointIndex(std::vector<Vec3f>{}).radius_at_most(Vec3f::Zero(), 1.f, 0);
  ASSERT_TRUE(none.has_value());
  EXPECT_TRUE(none->empty());
}

TEST(PointIndex, RadiusIsInclusive) {
  PointIndex index({Vec3f(0, 0, 0), Vec3f(1, 0, 0), Vec3f(3, 0, 0)});
  const auto got = index.radius(Vec3f(0, 0, 0), 1.f);
  ASSERT_EQ(got.size(), 2u);
  EXPECT_EQ(got[0].first, 0);
  EXPECT_EQ(got[1].first, 1);
  EXPECT_EQ(got[1].second, 1.f);
}

// 1 / sqrt(density) from the 8th neighbour: a random sample of a square of side 1
// with n points has spacing 1 / sqrt(n); a plane grid of step s reads 0.886 s
// (its 8th neighbour lies at sqrt(2) s).
TEST(SampleSpacing, OneOverTheSquareRootOfTheDensity) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(0, 1);
  std::vector<Vec3f> p(40000);
  for (auto& x : p) x = Vec3f(u(rng), u(rng), 0.5f);
  EXPECT_NEAR(sample_spacing(PointIndex(p)), 1.0 / 200, 0.1 / 200);
  std::vector<Vec3f> grid;
  for (int i = 0; i < 100; ++i)
    for (int j = 0; j < 100; ++j) grid.emplace_back(0.002f * float(i), 0.002f * float(j), 0);
  EXPECT_NEAR(sample_spacing(PointIndex(grid)), 0.002 * std::sqrt(2.0) * std::sqrt(M_PI / 8), 1e-5);
  EXPECT_EQ(sample_spacing(PointIndex(std::vector<Vec3f>(8, Vec3f::Zero()))), 0.0);
  EXPECT_EQ(sample_spacing(PointIndex({})), 0.0);
}

// The spacing at a point, from its own 8 neighbours: a random sample at two densities
// (3x the spacing on the right) reads each side's, and at the data's edge, where the
// neighbours lie on one side, the same as inside (the disc alone reads sqrt 2 more).
TEST(SampleSpacing, LocalSpacingFollowsTheDensityAndTheEdge) {
  std::mt19937 rng(6);
  std::uniform_real_distribution<float> left(0, 0.5f), right(0.5f, 1), v(0, 1);
  std::vector<Vec3f> p;
  for (int i = 0; i < 36000; ++i) p.emplace_back(left(rng), v(rng), 0.f);  // density 72,000
  for (int i = 0; i < 4000; ++i) p.emplace_back(right(rng), v(rng), 0.f);  // density 8,000
  const PointIndex index(p);
  auto median = [&](auto&& in) {
    std::vector<double> s;
    for (std::size_t i = 0; i < p.size(); ++i)
      if (in(p[i])) s.push_back(local_sample_spacing(index, int(i)));
    std::nth_element(s.begin(), s.begin() + std::ptrdiff_t(s.size() / 2), s.end());
    return s[s.size() / 2];
  };
  const double dense = median([](const Vec3f& x) { return x.x() > 0.1f && x.x() < 0.4f && x.y() > 0.1f && x.y() < 0.9f; });
  const double sparse = median([](const Vec3f& x) { return x.x() > 0.6f && x.x() < 0.9f && x.y() > 0.1f && x.y() < 0.9f; });
  const double edge = median([](const Vec3f& x) { return x.x() < 0.001f && x.y() > 0.1f && x.y() < 0.9f; });
  std::printf("local spacing: dense %.5f (1 / sqrt(density) %.5f), sparse %.5f (%.5f), at the edge %.5f\n", dense,
              1 / std::sqrt(72000.0), sparse, 1 / std::sqrt(8000.0), edge);
  EXPECT_NEAR(dense, 1 / std::sqrt(72000.0), 0.15 / std::sqrt(72000.0));
  EXPECT_NEAR(sparse, 1 / std::sqrt(8000.0), 0.15 / std::sqrt(8000.0));
  EXPECT_NEAR(edge, dense, 0.15 * dense);
  EXPECT_EQ(local_sample_spacing(PointIndex(std::vector<Vec3f>(8, Vec3f::Zero())), 0), 0.0);
  EXPECT_EQ(local_sample_spacing(index, -1), 0.0);
  EXPECT_EQ(local_sample_spacing(index, int(p.size())), 0.0);
}

// sparse_allowance: 1 on the dense half and on a stray point beside it (its
// neighbours' spacing decides, not its own), the density ratio's square root (3) on the
// sparse half, capped at kSparseSpacingCap, and from `from` on only.
TEST(SampleSpacing, SparseAllowanceFollowsTheNeighbourhoodNotAStrayPoint) {
  std::mt19937 rng(8);
  std::uniform_real_distribution<float> left(0, 0.5f), right(0.5f, 1), v(0, 1);
  std::vector<Vec3f> p;
  const Vec3f hole(0.25f, 0.5f, 0.f);  // a hole of 20 mm radius in the dense half, a stray point at its centre
  for (int i = 0; i < 36000; ++i) {
    const Vec3f q(left(rng), v(rng), 0.f);  // density 72,000
    if ((q - hole).norm() > 0.02f) p.push_back(q);
  }
  for (int i = 0; i < 4000; ++i) p.emplace_back(right(rng), v(rng), 0.f);  // density 8,000
  const int stray = int(p.size());
  p.push_back(hole);
  const PointIndex index(p);
  const double median = sample_spacing(index);
  ASSERT_NEAR(median, 1 / std::sqrt(72000.0), 0.15 / std::sqrt(72000.0));
  EXPECT_GT(local_sample_spacing(index, stray), 2 * kSparseSpacing * median);  // alone it reads sparse
  EXPECT_EQ(sparse_allowance(index, stray, median), 1.0);
  std::vector<double> dense, sparse;
  for (int i = 0; i < stray; ++i) {
    if (p[std::size_t(i)].y() < 0.1f || p[std::size_t(i)].y() > 0.9f) continue;
    if (p[std::size_t(i)].x() > 0.1f && p[std::size_t(i)].x() < 0.4f && (p[std::size_t(i)] - hole).norm() > 0.03f && i % 20 == 0)
      dense.push_back(sparse_allowance(index, i, median));
    if (p[std::size_t(i)].x() > 0.6f && p[std::size_t(i)].x() < 0.9f && i % 2 == 0) sparse.push_back(sparse_allowance(index, i, median));
  }
  const auto share_one = [](const std::vector<double>& a) {
    return double(std::count(a.begin(), a.end(), 1.0)) / double(a.size());
  };
  std::sort(sparse.begin(), sparse.end());
  std::printf("allowance: dense %.3f at 1, sparse median %.2f (sqrt 9 = 3)\n", share_one(dense), sparse[sparse.size() / 2]);
  EXPECT_GT(share_one(dense), 0.99);
  EXPECT_NEAR(sparse[sparse.size() / 2], 3.0, 0.3);
  EXPECT_LE(sparse.back(), kSparseSpacingCap);
  // From 3.5 on, the sparse half (3x) stays at 1 too.
  int i = 0;
  while (!(p[std::size_t(i)].x() > 0.7f && p[std::size_t(i)].x() < 0.8f && p[std::size_t(i)].y() > 0.4f && p[std::size_t(i)].y() < 0.6f)) ++i;
  EXPECT_GT(sparse_allowance(index, i, median), 2.0);
  EXPECT_EQ(sparse_allowance(index, i, median, 3.5), 1.0);
  EXPECT_EQ(sparse_allowance(index, i, 0.0), 1.0);
  EXPECT_EQ(sparse_allowance(index, -1, median), 1.0);
}

// SparseAllowances: sparse_allowance at every point, cached, from two threads at once
// (the cache keeps each local spacing as a float: the same to float rounding).
TEST(SampleSpacing, CachedAllowancesAreSparseAllowances) {
  std::mt19937 rng(9);
  std::uniform_real_distribution<float> left(0, 0.5f), right(0.5f, 1), v(0, 1);
  std::vector<Vec3f> p;
  for (int i = 0; i < 9000; ++i) p.emplace_back(left(rng), v(rng), 0.f);
  for (int i = 0; i < 1000; ++i) p.emplace_back(right(rng), v(rng), 0.f);
  const PointIndex index(p);
  const double median = sample_spacing(index);
  const SparseAllowances cached(index, median, 2.0);
  std::vector<double> got(p.size());
  std::thread other([&] {
    for (std::size_t i = p.size(); i-- > 0;) got[i] = cached(int(i));
  });
  for (std::size_t i = 0; i < p.size(); ++i) got[i] = cached(int(i));
  other.join();
  int sparse = 0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    const double expect = sparse_allowance(index, int(i), median, 2.0);
    ASSERT_NEAR(got[i], expect, 1e-5 * expect) << i;
    sparse += got[i] > 1;
  }
  EXPECT_GT(sparse, 500);
  EXPECT_EQ(cached(-1), 1.0);
  EXPECT_EQ(cached(int(p.size())), 1.0);
}

TEST(PointIndex, EmptySet) {
  PointIndex index(std::vector<Vec3f>{});
  EXPECT_EQ(index.size(), 0u);
  const auto [i, d] = index.nearest(Vec3f::Zero());
  EXPECT_EQ(i, -1);
  EXPECT_TRUE(std::isinf(d));
  EXPECT_TRUE(index.knn(Vec3f::Zero(), 3).empty());
  EXPECT_TRUE(index.radius(Vec3f::Zero(), 10.f).empty());
}

TEST(PointIndex, SurvivesMove) {
  const auto pts = random_points(200, 9);
  PointIndex a(pts);
  PointIndex b(std::move(a));
  const auto ref = brute_sorted(pts, Vec3f(0.1f, 0.2f, 0.3f));
  EXPECT_EQ(b.nearest(Vec3f(0.1f, 0.2f, 0.3f)).first, ref[0].first);
  PointIndex c(std::vector<Vec3f>{Vec3f::Zero()});
  c = std::move(b);
  EXPECT_EQ(c.size(), pts.size());
  EXPECT_EQ(c.nearest(Vec3f(0.1f, 0.2f, 0.3f)).first, ref[0].first);
  EXPECT_EQ(c.points()[7], pts[7]);
}

}  // namespace
}  // namespace station
