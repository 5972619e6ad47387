#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>

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

// trim_open_rims before 2026-12-06 (a sorted table of every face's edges): the
// reference the faster version must match face for face.
std::size_t sorted_edges_trim(Mesh& mesh, const std::vector<char>& far, int max_passes,
                              const std::vector<char>* pinned, std::vector<std::uint64_t>* vertex_keys) {
  const std::size_t nf = mesh.faces.size();
  if (nf == 0) return 0;
  auto far_face = [&](std::size_t f) {
    const Face& t = mesh.faces[f];
    return far[t[0]] || far[t[1]] || far[t[2]];
  };
  // Edges once: (key, face) sorted by key; each face's three edge groups; the
  // faces still alive on each edge.
  std::vector<std::pair<std::uint64_t, std::uint32_t>> ef;
  ef.reserve(3 * nf);
  for (std::size_t f = 0; f < nf; ++f)
    for (int k = 0; k < 3; ++k) {
      std::uint32_t a = std::uint32_t(mesh.faces[f][k]), b = std::uint32_t(mesh.faces[f][(k + 1) % 3]);
      if (a > b) std::swap(a, b);
      ef.emplace_back((std::uint64_t(a) << 32) | b, std::uint32_t(f));
    }
  std::sort(ef.begin(), ef.end());
  std::vector<std::uint32_t> group_start, face_edge(3 * nf);
  std::vector<int> alive_on;
  std::vector<int> next_slot(nf, 0);
  for (std::size_t i = 0; i < ef.size(); ++i) {
    if (i == 0 || ef[i].first != ef[i - 1].first) {
      group_start.push_back(std::uint32_t(i));
      // A pinned edge has faces beyond this mesh: never down to one.
      const std::uint32_t a = std::uint32_t(ef[i].first >> 32), b = std::uint32_t(ef[i].first & 0xffffffffu);
      alive_on.push_back(pinned && (*pinned)[a] && (*pinned)[b] ? 2 : 0);
    }
    const std::uint32_t g = std::uint32_t(group_start.size() - 1), f = ef[i].second;
    face_edge[3 * f + std::size_t(next_slot[f]++)] = g;
    ++alive_on[g];
  }
  group_start.push_back(std::uint32_t(ef.size()));
  std::vector<char> alive(nf, 1);
  auto on_rim = [&](std::size_t f) {
    for (int k = 0; k < 3; ++k)
      if (alive_on[face_edge[3 * f + std::size_t(k)]] == 1) return true;
    return false;
  };
  std::vector<std::uint32_t> layer;
  for (std::size_t f = 0; f < nf; ++f)
    if (far_face(f) && on_rim(f)) layer.push_back(std::uint32_t(f));
  std::size_t dropped = 0;
  for (int pass = 0; pass < max_passes && !layer.empty(); ++pass) {
    // Drop the whole layer first (a ring), then find the faces it exposed.
    for (const std::uint32_t f : layer) {
      alive[f] = 0;
      ++dropped;
      for (int k = 0; k < 3; ++k) --alive_on[face_edge[3 * std::size_t(f) + std::size_t(k)]];
    }
    std::vector<std::uint32_t> next;
    for (const std::uint32_t f : layer)
      for (int k = 0; k < 3; ++k) {
        const std::uint32_t g = face_edge[3 * std::size_t(f) + std::size_t(k)];
        if (alive_on[g] != 1) continue;
        for (std::uint32_t i = group_start[g]; i < group_start[g + 1]; ++i) {
          const std::uint32_t h = ef[i].second;
          if (alive[h] && far_face(h)) next.push_back(h);
        }
      }
    std::sort(next.begin(), next.end());
    next.erase(std::unique(next.begin(), next.end()), next.end());
    layer.swap(next);
  }
  if (dropped > 0) keep_faces(mesh, alive, vertex_keys);
  return dropped;
}

// The same faces, vertices and keys as the sorted-table version on random meshes: a
// grid with faces left out (rims, holes), degenerate faces (a repeated vertex),
// faces doubled, random far and pinned flags.
TEST(TrimOpenRims, MatchesTheSortedEdgeTableOnRandomMeshes) {
  std::mt19937 rng(17);
  std::uniform_real_distribution<float> u(0, 1);
  for (int trial = 0; trial < 60; ++trial) {
    Mesh m = grid(12);
    std::vector<Face> faces;
    for (const Face& f : m.faces) {
      const float r = u(rng);
      if (r < 0.08f) continue;                           // a hole
      if (r < 0.12f) faces.push_back(Face(f[0], f[0], f[1]));  // degenerate
      if (r > 0.96f) faces.push_back(f);                 // doubled
      faces.push_back(f);
    }
    if (trial % 5 == 0) faces.push_back(Face(3, 3, 3));
    m.faces = faces;
    const std::size_t nv = m.vertices.size();
    std::vector<char> far(nv), pinned(nv);
    const float far_share = 0.2f + 0.6f * u(rng);
    for (std::size_t v = 0; v < nv; ++v) far[v] = u(rng) < far_share, pinned[v] = u(rng) < 0.15f;
    std::vector<std::uint64_t> keys(nv);
    for (std::size_t v = 0; v < nv; ++v) keys[v] = 1000 + v;
    Mesh a = m, b = m;
    std::vector<std::uint64_t> ka = keys, kb = keys;
    const bool with_pins = trial % 2 == 1;
    const int passes = 1 + trial % 7;
    const std::size_t da = trim_open_rims(a, far, passes, with_pins ? &pinned : nullptr, &ka);
    const std::size_t db = sorted_edges_trim(b, far, passes, with_pins ? &pinned : nullptr, &kb);
    ASSERT_EQ(da, db) << "trial " << trial;
    ASSERT_EQ(a.faces, b.faces) << "trial " << trial;
    ASSERT_EQ(a.vertices, b.vertices) << "trial " << trial;
    ASSERT_EQ(ka, kb) << "trial " << trial;
  }
  // Out-of-range indices are refused, not written past.
  Mesh bad = grid(3);
  bad.faces.push_back(Face(0, 1, 999));
  EXPECT_THROW(trim_open_rims(bad, std::vector<char>(bad.vertices.size(), 1)), InvalidInput);
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
