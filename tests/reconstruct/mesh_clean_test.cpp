#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "core/error.h"
#include "core/kdtree.h"
#include "reconstruct/mesh_clean.h"
#include "test_util.h"

namespace station {
namespace {

Mesh join(Mesh a, const Mesh& b) {
  const int off = int(a.vertices.size());
  a.vertices.insert(a.vertices.end(), b.vertices.begin(), b.vertices.end());
  a.normals.insert(a.normals.end(), b.normals.begin(), b.normals.end());
  a.colours.insert(a.colours.end(), b.colours.begin(), b.colours.end());
  for (Face f : b.faces) a.faces.push_back(f + Face::Constant(off));
  return a;
}

Mesh painted(Mesh m, Rgb c) {
  m.colours.assign(m.vertices.size(), c);
  m.normals = vertex_normals(m);
  return m;
}

// A 20 x 20 grid of unit squares (two triangles each) in the z = 0 plane.
Mesh grid(int n) {
  Mesh m;
  for (int y = 0; y <= n; ++y)
    for (int x = 0; x <= n; ++x) m.vertices.emplace_back(float(x), float(y), 0.f);
  auto id = [n](int x, int y) { return y * (n + 1) + x; };
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      m.faces.emplace_back(id(x, y), id(x + 1, y), id(x + 1, y + 1));
      m.faces.emplace_back(id(x, y), id(x + 1, y + 1), id(x, y + 1));
    }
  return m;
}

TEST(TrimOpenRims, ErodesFromTheRimToTheDataOnly) {
  // Data over x <= 12 everywhere, and nowhere in the disc of radius 2.5 about (6, 10).
  std::vector<Vec3f> data;
  for (float y = 0; y <= 20; y += 0.5f)
    for (float x = 0; x <= 12; x += 0.5f)
      if (std::hypot(x - 6.f, y - 10.f) > 2.5f) data.emplace_back(x, y, 0.f);
  const PointIndex index(data);
  const auto distance = [&](const Vec3d& x) { return double(index.nearest(x.cast<float>()).second); };
  Mesh m = grid(20);
  const std::size_t dropped = trim_open_rims(m, distance, 1.0, 100);
  EXPECT_GT(dropped, 0u);
  float max_x = 0;
  for (const Vec3f& v : m.vertices) max_x = std::max(max_x, v.x());
  EXPECT_LE(max_x, 13.f);  // the part beyond the data is gone, a vertex at most 1 past it
  EXPECT_GE(max_x, 12.f);
  // The data's gap inside is not on a rim: its faces stay.
  bool centre = false;
  for (const Vec3f& v : m.vertices) centre |= v.x() == 6.f && v.y() == 10.f;
  EXPECT_TRUE(centre);
  // A closed mesh has no rim: nothing goes, however far the data.
  Mesh sphere = test::icosphere(2, 1.0, Vec3f(100, 0, 0));
  const std::size_t faces = sphere.faces.size();
  EXPECT_EQ(trim_open_rims(sphere, distance, 1.0), 0u);
  EXPECT_EQ(sphere.faces.size(), faces);
}

TEST(RemoveSmallComponents, DropsSpecksAndKeepsTheObjectWithItsAttributes) {
  const Mesh big = painted(test::icosphere(3, 1.0), {200, 10, 10});
  const Mesh speck = painted(test::icosphere(1, 0.05, Vec3f(3, 0, 0)), {0, 0, 255});
  const Mesh medium = painted(test::icosphere(2, 0.5, Vec3f(-3, 0, 0)), {0, 255, 0});
  Mesh m = join(join(speck, big), medium);  // the speck first: indices must be remapped
  // Per-vertex flags follow their vertices: 1 on the medium sphere's.
  std::vector<std::uint8_t> flags(m.vertices.size());
  for (std::size_t i = 0; i < flags.size(); ++i) flags[i] = m.vertices[i].x() < -2;
  std::vector<std::uint8_t> short_flags(3);
  Mesh copy = m;
  EXPECT_THROW(remove_small_components(copy, 0.01, &short_flags), InvalidInput);
  const ComponentFilterStats st = remove_small_components(m, 0.01, &flags);
  ASSERT_EQ(flags.size(), m.vertices.size());
  for (std::size_t i = 0; i < flags.size(); ++i) EXPECT_EQ(flags[i], m.vertices[i].x() < -2 ? 1 : 0);
  EXPECT_EQ(st.components, 3u);
  EXPECT_EQ(st.removed_components, 1u);
  EXPECT_EQ(st.removed_faces, speck.faces.size());
  EXPECT_EQ(m.faces.size(), big.faces.size() + medium.faces.size());
  EXPECT_EQ(m.vertices.size(), big.vertices.size() + medium.vertices.size());
  ASSERT_NO_THROW(m.check_consistent());
  for (std::size_t i = 0; i < m.vertices.size(); ++i) {
    // No speck vertex survives; colours still belong to their vertices.
    EXPECT_LT(m.vertices[i].x(), 2.5f);
    if (m.vertices[i].x() < -2) EXPECT_EQ(m.colours[i].g, 255);
    else EXPECT_EQ(m.colours[i].r, 200);
  }
  // A larger threshold removes the medium sphere too (area 0.25 of the big one).
  Mesh m2 = join(big, medium);
  EXPECT_EQ(remove_small_components(m2, 0.3).removed_components, 1u);
  EXPECT_EQ(m2.faces.size(), big.faces.size());
  // 0 keeps everything.
  Mesh m3 = join(big, speck);
  EXPECT_EQ(remove_small_components(m3, 0).removed_components, 0u);
  EXPECT_EQ(m3.faces.size(), big.faces.size() + speck.faces.size());
}

// A piece below the area bound stays when enough data points lie nearest to it; a
// point nearer the large piece counts for that one, not for a speck beside it.
TEST(RemoveSmallComponents, DataKeepsASupportedSmallPiece) {
  const Mesh big = test::icosphere(3, 1.0);
  const Mesh seen = test::icosphere(1, 0.05, Vec3f(3, 0, 0));     // seen by 12 data points
  const Mesh unseen = test::icosphere(1, 0.05, Vec3f(0, 3, 0));   // by 11
  const Mesh beside = test::icosphere(1, 0.05, Vec3f(1.2f, 0, 0));  // 0.15 from the big sphere
  std::vector<Vec3f> data;
  // 0.001 outside the specks' vertices.
  for (int i = 0; i < 12; ++i) data.push_back(Vec3f(3, 0, 0) + 1.02f * (seen.vertices[std::size_t(i)] - Vec3f(3, 0, 0)));
  for (int i = 0; i < 11; ++i) data.push_back(Vec3f(0, 3, 0) + 1.02f * (unseen.vertices[std::size_t(i)] - Vec3f(0, 3, 0)));
  // On the big sphere, within reach of the speck beside it too, but nearer the sphere.
  for (int i = 0; i < 30; ++i) data.push_back(Vec3f(1.02f, 0.001f * float(i), 0));
  data.push_back(Vec3f(std::nanf(""), 0, 0));  // ignored
  PieceSupport support{&data, 0.2, 12};
  Mesh m = join(join(join(big, seen), unseen), beside);
  const ComponentFilterStats st = remove_small_components(m, 0.01, nullptr, &support);
  EXPECT_EQ(st.components, 4u);
  EXPECT_EQ(st.supported_components, 1u);
  EXPECT_EQ(st.removed_components, 2u);
  EXPECT_EQ(m.faces.size(), big.faces.size() + seen.faces.size());
  for (const Vec3f& v : m.vertices) EXPECT_TRUE(v.norm() < 1.01f || (v - Vec3f(3, 0, 0)).norm() < 0.06f);
  // Out of reach the same points keep nothing; without support the area bound alone.
  Mesh far = join(join(join(big, seen), unseen), beside);
  support.reach = 1e-6;
  EXPECT_EQ(remove_small_components(far, 0.01, nullptr, &support).removed_components, 3u);
  Mesh none = join(join(join(big, seen), unseen), beside);
  EXPECT_EQ(remove_small_components(none, 0.01).removed_components, 3u);
}

TEST(RemoveSmallComponents, EmptyAndBadInput) {
  Mesh empty;
  EXPECT_EQ(remove_small_components(empty, 0.1).components, 0u);
  Mesh m = test::icosphere(1);
  EXPECT_THROW(remove_small_components(m, 1.5), InvalidInput);
  m.faces.push_back({0, 1, 99999});
  EXPECT_THROW(remove_small_components(m, 0.1), InvalidInput);
}

TEST(KeepFaces, KeepsFlaggedFacesAndRenumbersVerticesByFirstUse) {
  Mesh m;
  for (int v = 0; v < 5; ++v) {
    m.vertices.push_back(Vec3f(float(v), 0, 0));
    m.normals.push_back(Vec3f(0, 0, 1));
    m.colours.push_back(Rgb{std::uint8_t(10 * v), 0, 0});
  }
  m.faces = {Face(0, 1, 2), Face(4, 3, 2), Face(0, 2, 3)};
  EXPECT_EQ(keep_faces(m, {0, 1, 1}), 1u);
  ASSERT_EQ(m.faces.size(), 2u);
  ASSERT_EQ(m.vertices.size(), 4u);  // vertex 1 only in the dropped face
  EXPECT_EQ(m.faces[0], Face(0, 1, 2));  // old 4, 3, 2 first
  EXPECT_EQ(m.faces[1], Face(3, 2, 1));  // old 0, 2, 3
  EXPECT_EQ(m.vertices[0].x(), 4.f);
  EXPECT_EQ(m.colours[3].r, 0);  // old vertex 0
  EXPECT_EQ(m.normals.size(), 4u);
  EXPECT_THROW(keep_faces(m, {1}), InvalidInput);
}

}  // namespace
}  // namespace station
