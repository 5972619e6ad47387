// Fusion of overlapping views in the merge (capture/fuse.h).
#include "registration/fuse.h"

#include <gtest/gtest.h>
#include <tbb/global_control.h>

#include <cmath>

namespace station {
namespace {

// A w x h grid of points 1 mm apart in the plane z = z0, starting at x0,
// coloured `rgb`, normals +z (or -z).
Cloud grid(int w, int h, float x0, float z0, Rgb rgb, float normal_z = 1.f) {
  Cloud c;
  for (int j = 0; j < h; ++j)
    for (int i = 0; i < w; ++i) {
      c.points.emplace_back(x0 + 0.001f * float(i), 0.001f * float(j), z0);
      c.normals.emplace_back(0.f, 0.f, normal_z);
      c.colours.push_back(rgb);
    }
  return c;
}

// Two views of one plane, the second shifted 0.3 mm along x and 0.1 mm off
// the plane, and reaching 10 columns further: the overlap is averaged point
// for point (each kept point takes one point of the later view), the rest of
// the second view is kept as it is.
TEST(Fuse, AveragesTheOverlapPointForPoint) {
  const Cloud a = grid(20, 20, 0.f, 0.f, Rgb{200, 0, 0});
  const Cloud b = grid(30, 20, 0.0003f, 0.0001f, Rgb{0, 0, 100}, -1.f);  // normals flipped
  FuseStats st;
  const Cloud f = fuse_clouds({a, b}, 0.0005, &st);
  EXPECT_EQ(st.input, 1000u);
  EXPECT_EQ(st.fused, 400u);  // the 20 x 20 overlap
  EXPECT_EQ(st.output, 600u);
  ASSERT_EQ(f.size(), 600u);
  ASSERT_TRUE(f.has_normals());
  ASSERT_TRUE(f.has_colours());
  // The first 400 are a's points averaged with b's: midway, mixed colour,
  // b's normal flipped to agree before averaging.
  for (std::size_t k = 0; k < 400; ++k) {
    EXPECT_NEAR(f.points[k].x(), a.points[k].x() + 0.00015f, 1e-7f) << k;
    EXPECT_NEAR(f.points[k].z(), 0.00005f, 1e-7f) << k;
    EXPECT_NEAR(f.normals[k].z(), 1.f, 1e-6f) << k;
    EXPECT_EQ(f.colours[k], (Rgb{100, 0, 50})) << k;
  }
  // The next 200 are b's own columns 20..29.
  for (std::size_t k = 400; k < 600; ++k) {
    EXPECT_NEAR(f.points[k].z(), 0.0001f, 1e-7f) << k;
    EXPECT_EQ(f.colours[k], (Rgb{0, 0, 100})) << k;
  }
  // A distance below the offset fuses nothing.
  FuseStats none;
  EXPECT_EQ(fuse_clouds({a, b}, 0.0002, &none).size(), 1000u);
  EXPECT_EQ(none.fused, 0u);
}

// Points of the same view never fuse, however close; a kept point takes at
// most one point per later view.
TEST(Fuse, KeepsAViewsOwnSamplingAndOnePointPerView) {
  Cloud a;
  a.points = {Vec3f(0, 0, 0), Vec3f(0.0001f, 0, 0)};
  EXPECT_EQ(fuse_clouds({a}, 0.01).size(), 2u);
  Cloud b;
  b.points = {Vec3f(0.0002f, 0, 0), Vec3f(0.0003f, 0, 0), Vec3f(0.0004f, 0, 0)};
  FuseStats st;
  const Cloud f = fuse_clouds({a, b}, 0.01, &st);
  // All three of b's points are nearest to a's second point, which takes the
  // nearest of them; the two others are kept as they are (no second choice).
  EXPECT_EQ(st.fused, 1u);
  ASSERT_EQ(f.size(), 4u);
  EXPECT_NEAR(f.points[1].x(), 0.00015f, 1e-9f);
  EXPECT_EQ(f.points[2], b.points[1]);
  EXPECT_FALSE(f.has_normals());
  EXPECT_FALSE(f.has_colours());
}

// Distance 0 concatenates; attributes only when every cloud has them;
// non-finite points are dropped; an empty cloud does not remove attributes.
TEST(Fuse, ConcatenatesAtDistanceZeroAndKeepsAttributesOnlyWhenAllHaveThem) {
  const Cloud a = grid(4, 4, 0.f, 0.f, Rgb{1, 2, 3});
  Cloud b = grid(4, 4, 0.f, 0.f, Rgb{4, 5, 6});
  FuseStats st;
  Cloud f = fuse_clouds({a, Cloud{}, b}, 0.0, &st);
  EXPECT_EQ(f.size(), 32u);
  EXPECT_EQ(st.fused, 0u);
  EXPECT_TRUE(f.has_colours());
  EXPECT_TRUE(f.has_normals());
  EXPECT_EQ(f.points[16], b.points[0]);
  b.colours.clear();
  b.points[3] = Vec3f(std::nanf(""), 0, 0);
  for (double d : {0.0, 0.0005}) {
    f = fuse_clouds({a, b}, d);
    EXPECT_FALSE(f.has_colours()) << d;
    EXPECT_TRUE(f.has_normals()) << d;
    for (const Vec3f& p : f.points) EXPECT_TRUE(p.allFinite()) << d;
  }
  EXPECT_EQ(fuse_clouds({a, b}, 0.0).size(), 31u);
  EXPECT_EQ(fuse_clouds({a, b}, std::nan("")).size(), 31u);  // not a distance: concatenates
  EXPECT_TRUE(fuse_clouds({}, 0.001).empty());
}

// The same output for any thread count.
TEST(Fuse, DeterministicAcrossThreadCounts) {
  std::vector<Cloud> views;
  for (int v = 0; v < 4; ++v) {
    Cloud c = grid(60, 60, 0.0002f * float(v), 0.00003f * float(v), Rgb{std::uint8_t(50 * v), 7, 9});
    // A little irregularity so that ties and re-filing across cells happen.
    for (std::size_t k = 0; k < c.size(); ++k) c.points[k].y() += 0.0001f * float((k * 7 + v) % 5);
    views.push_back(c);
  }
  Cloud one, two;
  {
    tbb::global_control gc(tbb::global_control::max_allowed_parallelism, 1);
    one = fuse_clouds(views, 0.0006);
  }
  {
    tbb::global_control gc(tbb::global_control::max_allowed_parallelism, 2);
    two = fuse_clouds(views, 0.0006);
  }
  ASSERT_EQ(one.size(), two.size());
  EXPECT_LT(one.size(), 4u * 3600u);
  for (std::size_t k = 0; k < one.size(); ++k) {
    EXPECT_EQ(one.points[k], two.points[k]) << k;
    EXPECT_EQ(one.colours[k], two.colours[k]) << k;
  }
}

TEST(Fuse, MedianSpacingOfAGrid) {
  const Cloud a = grid(50, 50, 0.f, 0.f, Rgb{});
  EXPECT_NEAR(median_spacing(a.points), 0.001, 1e-7);
  EXPECT_EQ(median_spacing({Vec3f::Zero()}), 0.0);
}

}  // namespace
}  // namespace station
