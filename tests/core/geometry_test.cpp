#include "core/geometry.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <random>
#include <limits>

#include "core/error.h"
#include "test_util.h"

namespace station {
namespace {

TEST(Geometry, CloudConsistencyChecksAttributeSizes) {
  Cloud c;
  c.points = {Vec3f(0, 0, 0), Vec3f(1, 0, 0)};
  EXPECT_NO_THROW(c.check_consistent());
  c.normals = {Vec3f(0, 0, 1)};
  try {
    c.check_consistent("view 3");
    FAIL() << "expected InvalidInput";
  } catch (const InvalidInput& e) {
    EXPECT_NE(std::string(e.what()).find("view 3"), std::string::npos);
    EXPECT_NE(std::string(e.what()).find("normals"), std::string::npos);
  }
  c.normals.clear();
  c.colours = {Rgb{1, 2, 3}, Rgb{}, Rgb{}};
  EXPECT_THROW(c.check_consistent(), InvalidInput);
  c.colours.pop_back();
  EXPECT_NO_THROW(c.check_consistent());
}

TEST(Geometry, MeshConsistencyChecksFaceIndices) {
  Mesh m = test::box(Vec3f::Zero(), Vec3f::Ones());
  EXPECT_NO_THROW(m.check_consistent());
  m.faces.push_back(Face(0, 1, 8));
  EXPECT_THROW(m.check_consistent(), InvalidInput);
  m.faces.back() = Face(-1, 1, 2);
  EXPECT_THROW(m.check_consistent(), InvalidInput);
  m.faces.pop_back();
  m.colours.resize(7);
  EXPECT_THROW(m.check_consistent(), InvalidInput);
  m.colours.resize(8);
  m.normals.resize(9);
  EXPECT_THROW(m.check_consistent(), InvalidInput);
}

TEST(Geometry, AsCloudKeepsVertexAttributes) {
  Mesh m = test::box(Vec3f::Zero(), Vec3f::Ones());
  m.colours.assign(m.vertices.size(), Rgb{9, 8, 7});
  const Cloud c = m.as_cloud();
  EXPECT_EQ(c.points, m.vertices);
  EXPECT_TRUE(c.normals.empty());
  ASSERT_EQ(c.colours.size(), 8u);
  EXPECT_EQ(c.colours[5], (Rgb{9, 8, 7}));
}

TEST(Geometry, BoundingBox) {
  const Aabb empty = bounding_box({});
  EXPECT_FALSE(empty.valid());
  EXPECT_EQ(empty.diagonal(), 0.f);
  const Aabb b = bounding_box({Vec3f(1, 2, 3), Vec3f(-1, 5, 0), Vec3f(0, 0, 4)});
  ASSERT_TRUE(b.valid());
  EXPECT_EQ(b.min, Vec3f(-1, 0, 0));
  EXPECT_EQ(b.max, Vec3f(1, 5, 4));
  EXPECT_NEAR(b.diagonal(), std::sqrt(4.f + 25.f + 16.f), 1e-5);
}

TEST(Geometry, AllFinite) {
  std::vector<Vec3f> p = {Vec3f(1, 2, 3)};
  EXPECT_TRUE(all_finite(p));
  EXPECT_TRUE(all_finite({}));
  p.emplace_back(0, std::numeric_limits<float>::quiet_NaN(), 0);
  EXPECT_FALSE(all_finite(p));
  p.back() = Vec3f(0, 0, -std::numeric_limits<float>::infinity());
  EXPECT_FALSE(all_finite(p));
}

TEST(Geometry, VertexNormalsOfSpherePointOutwards) {
  const Vec3f centre(1, -2, 0.5f);
  const Mesh m = test::icosphere(2, 2.0, centre);
  const auto n = vertex_normals(m);
  ASSERT_EQ(n.size(), m.vertices.size());
  for (std::size_t i = 0; i < n.size(); ++i) {
    EXPECT_NEAR(n[i].norm(), 1.f, 1e-5);
    EXPECT_GT(n[i].dot((m.vertices[i] - centre).normalized()), 0.99f) << i;
  }
}

TEST(Geometry, VertexNormalsAreAreaWeightedAndZeroWhenIsolated) {
  Mesh m;
  // A big triangle in z=0 and a small one tilted, sharing vertex 0; vertex 5 unused.
  m.vertices = {Vec3f(0, 0, 0), Vec3f(10, 0, 0), Vec3f(0, 10, 0),
                Vec3f(0, -0.1f, 0), Vec3f(0, 0, 0.1f), Vec3f(5, 5, 5)};
  m.faces = {Face(0, 1, 2), Face(0, 3, 4)};
  const auto n = vertex_normals(m);
  EXPECT_GT(n[0].z(), 0.99f);  // dominated by the big triangle
  EXPECT_NEAR(n[3].x(), -1.f, 1e-6);
  EXPECT_EQ(n[5], Vec3f::Zero());
  m.faces.push_back(Face(0, 1, 6));
  EXPECT_THROW(vertex_normals(m), InvalidInput);
}

TEST(Geometry, TransformCloudMovesPointsAndRotatesNormals) {
  Cloud c;
  c.points = {Vec3f(1, 0, 0), Vec3f(0, 2, 0)};
  c.normals = {Vec3f(1, 0, 0), Vec3f(0, 1, 0)};
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.topLeftCorner<3, 3>() = Eigen::AngleAxisd(M_PI / 2, Vec3d::UnitZ()).toRotationMatrix();
  T.topRightCorner<3, 1>() = Vec3d(0, 0, 5);
  transform_cloud(c, T);
  EXPECT_TRUE(c.points[0].isApprox(Vec3f(0, 1, 5), 1e-6f));
  EXPECT_TRUE(c.points[1].isApprox(Vec3f(-2, 0, 5), 1e-6f));
  EXPECT_TRUE(c.normals[0].isApprox(Vec3f(0, 1, 0), 1e-6f));
  EXPECT_TRUE(c.normals[1].isApprox(Vec3f(-1, 0, 0), 1e-6f));
}

TEST(Geometry, TransformCloudKeepsNormalsPerpendicularUnderScaling) {
  // Plane x + y = 1 with normal (1,1,0)/sqrt2; stretch x by 4.
  Cloud c;
  c.points = {Vec3f(1, 0, 0), Vec3f(0, 1, 0), Vec3f(0, 1, 3)};
  c.normals.assign(3, Vec3f(1, 1, 0).normalized());
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T(0, 0) = 4;
  transform_cloud(c, T);
  const Vec3f along = c.points[1] - c.points[0];
  EXPECT_NEAR(c.normals[0].dot(along), 0.f, 1e-5);
  EXPECT_NEAR(c.normals[0].norm(), 1.f, 1e-5);
}

// spatial_order: a permutation; nearby points next to each other (an 8 x 8 x 8 grid in
// random order comes out as its 2 x 2 x 2 blocks, one after another, each block's
// points within one cell of each other); equal points and non-finite ones in index
// order, non-finite first; reordered carries normals and colours along.
TEST(Geometry, SpatialOrderIsZOrder) {
  std::vector<Vec3f> grid;
  for (int x = 0; x < 8; ++x)
    for (int y = 0; y < 8; ++y)
      for (int z = 0; z < 8; ++z) grid.emplace_back(float(x), float(y), float(z));
  std::vector<Vec3f> shuffled = grid;
  std::mt19937 rng(3);
  std::shuffle(shuffled.begin(), shuffled.end(), rng);
  const std::vector<std::uint32_t> order = spatial_order(shuffled);
  ASSERT_EQ(order.size(), shuffled.size());
  std::vector<std::uint32_t> sorted = order;
  std::sort(sorted.begin(), sorted.end());
  for (std::size_t i = 0; i < sorted.size(); ++i) ASSERT_EQ(sorted[i], i);  // a permutation
  for (std::size_t b = 0; b < order.size(); b += 8) {
    const Vec3f first = shuffled[order[b]];
    for (std::size_t i = b; i < b + 8; ++i) {
      const Vec3f p = shuffled[order[i]];
      // the same 2 x 2 x 2 block as the run's first point
      EXPECT_EQ((p / 2).array().floor().matrix(), (first / 2).array().floor().matrix()) << "run " << b / 8;
    }
  }
  EXPECT_EQ(shuffled[order.front()], Vec3f(0, 0, 0));
  EXPECT_EQ(shuffled[order.back()], Vec3f(7, 7, 7));
  // On the 0..7 grid the top three of the 21 bits per axis are x, y, z themselves, so
  // the whole order is the plain bit interleave of (x, y, z), x lowest.
  auto interleave = [](const Vec3f& p) {
    int key = 0;
    for (int bit = 0; bit < 3; ++bit)
      for (int a = 0; a < 3; ++a) key |= ((int(p[a]) >> bit) & 1) << (3 * bit + a);
    return key;
  };
  for (std::size_t i = 0; i < order.size(); ++i) ASSERT_EQ(interleave(shuffled[order[i]]), int(i)) << i;
  // One point, equal points, a flat cloud (one side of zero extent).
  EXPECT_EQ(spatial_order({Vec3f(1, 2, 3)}), (std::vector<std::uint32_t>{0}));
  EXPECT_EQ(spatial_order({Vec3f(1, 2, 3), Vec3f(1, 2, 3)}), (std::vector<std::uint32_t>{0, 1}));
  EXPECT_EQ(spatial_order({Vec3f(3, 0, 5), Vec3f(0, 0, 5), Vec3f(0, 3, 5), Vec3f(3, 3, 5)}),
            (std::vector<std::uint32_t>{1, 0, 2, 3}));

  const float nan = std::numeric_limits<float>::quiet_NaN();
  const std::vector<Vec3f> odd{{1, 1, 1}, {0, 0, 0}, {nan, 0, 0}, {1, 1, 1}, {0, 0, std::numeric_limits<float>::infinity()}};
  EXPECT_EQ(spatial_order(odd), (std::vector<std::uint32_t>{2, 4, 1, 0, 3}));
  EXPECT_TRUE(spatial_order({}).empty());

  Cloud c;
  c.points = {{2, 0, 0}, {0, 0, 0}};
  c.normals = {{1, 0, 0}, {0, 1, 0}};
  c.colours = {Rgb{1, 2, 3}, Rgb{4, 5, 6}};
  const Cloud r = reordered(c, spatial_order(c.points));
  EXPECT_EQ(r.points[0], Vec3f(0, 0, 0));
  EXPECT_EQ(r.normals[0], Vec3f(0, 1, 0));
  EXPECT_TRUE(r.colours[0] == (Rgb{4, 5, 6}));
  EXPECT_THROW(reordered(c, {0, 2}), InvalidInput);
}

}  // namespace
}  // namespace station
