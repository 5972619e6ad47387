#include "reconstruct/marching_cubes.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <map>
#include <random>
#include <set>

#include "core/error.h"
#include "reconstruct/detail/mc_tables.h"

namespace station {
namespace {

struct Sphere : ImplicitFunction {
  Vec3d c;
  double r;
  Sphere(Vec3d c_, double r_) : c(c_), r(r_) {}
  double value(const Vec3d& x) const override { return (x - c).norm() - r; }
  Vec3d gradient(const Vec3d& x) const override { return (x - c).normalized(); }
};

// Sum of Gaussian blobs: a lumpy closed surface with many ambiguous faces at low resolution.
struct Blobs : ImplicitFunction {
  std::vector<Vec3d> centers;
  explicit Blobs(unsigned seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> u(-0.5, 0.5);
    for (int i = 0; i < 12; ++i) centers.emplace_back(u(rng), u(rng), u(rng));
  }
  double value(const Vec3d& x) const override {
    double s = 0;
    for (const Vec3d& c : centers) s += std::exp(-(x - c).squaredNorm() / 0.02);
    return 0.5 - s;  // inside where the blobs sum above 0.5
  }
  Vec3d gradient(const Vec3d& x) const override {
    Vec3d g = Vec3d::Zero();
    for (const Vec3d& c : centers) g += std::exp(-(x - c).squaredNorm() / 0.02) * 2 * (x - c) / 0.02;
    return g;
  }
};

// Closed oriented 2-manifold: every directed edge once, with its reverse present.
void expect_closed_oriented(const Mesh& m) {
  std::map<std::pair<int, int>, int> directed;
  for (const Face& f : m.faces)
    for (int t = 0; t < 3; ++t) ++directed[{f[t], f[(t + 1) % 3]}];
  int bad = 0;
  for (const auto& [e, n] : directed)
    if (n != 1 || !directed.count({e.second, e.first})) ++bad;
  EXPECT_EQ(bad, 0) << "non-manifold or open edges";
}

int euler(const Mesh& m) {
  std::set<std::pair<int, int>> edges;
  for (const Face& f : m.faces)
    for (int t = 0; t < 3; ++t) edges.insert(std::minmax(f[t], f[(t + 1) % 3]));
  return int(m.vertices.size()) - int(edges.size()) + int(m.faces.size());
}

TEST(MarchingCubesTable, EveryConfigurationIsClosedWithinTheCell) {
  const auto& table = mc::triangle_table();
  EXPECT_TRUE(table[0].empty());
  EXPECT_TRUE(table[255].empty());
  for (int c = 1; c < 255; ++c) {
    ASSERT_FALSE(table[c].empty()) << c;
    // Complementary configurations cut the same edges.
    std::set<int> a, b;
    for (const auto& t : table[c]) a.insert(t.begin(), t.end());
    for (const auto& t : table[255 - c]) b.insert(t.begin(), t.end());
    EXPECT_EQ(a, b) << c;
  }
}

TEST(MarchingCubes, SphereIsClosedManifoldGenusZeroAndAccurate) {
  const Sphere s(Vec3d(0.1, -0.05, 0.02), 0.8);
  Aabb box;
  box.extend(Vec3f(-1, -1, -1));
  box.extend(Vec3f(1, 1, 1));
  MarchingCubesStats st;
  const Mesh m = extract_marching_cubes(s, box, 40, {}, &st);
  ASSERT_GT(m.faces.size(), 1000u);
  m.check_consistent();
  expect_closed_oriented(m);
  EXPECT_EQ(euler(m), 2);
  double worst = 0, worst_normal = 0;
  for (std::size_t v = 0; v < m.vertices.size(); ++v) {
    const Vec3d p = m.vertices[v].cast<double>();
    worst = std::max(worst, std::abs(s.value(p)));
    worst_normal = std::max(worst_normal, 1 - m.normals[v].cast<double>().dot(s.gradient(p)));
  }
  EXPECT_LT(worst, st.cell_size);
  EXPECT_LT(worst_normal, 1e-6);
  // Outward orientation: positive signed volume.
  double vol = 0;
  for (const Face& f : m.faces)
    vol += m.vertices[f[0]].cast<double>().dot(m.vertices[f[1]].cast<double>().cross(m.vertices[f[2]].cast<double>())) / 6;
  EXPECT_NEAR(vol, 4.0 / 3 * M_PI * 0.8 * 0.8 * 0.8, 0.02);
  // Sparse: far fewer cells visited than the 64000 of the grid.
  EXPECT_LT(st.cells_visited, 20000u);
}

TEST(MarchingCubes, SeedsGiveTheSameMeshAsTheScan) {
  const Sphere s(Vec3d::Zero(), 0.5);
  Aabb box;
  box.extend(Vec3f(-1, -1, -1));
  box.extend(Vec3f(1, 1, 1));
  MarchingCubesOptions opt;
  opt.seeds = {Vec3f(0.5f, 0, 0)};
  const Mesh a = extract_marching_cubes(s, box, 32, opt);
  const Mesh b = extract_marching_cubes(s, box, 32);
  EXPECT_EQ(a.faces.size(), b.faces.size());
  EXPECT_EQ(a.vertices.size(), b.vertices.size());
}

TEST(MarchingCubes, AmbiguousFacesStayWatertight) {
  for (unsigned seed : {1u, 2u, 3u}) {
    const Blobs f(seed);
    Aabb box;
    box.extend(Vec3f(-1, -1, -1));
    box.extend(Vec3f(1, 1, 1));
    MarchingCubesOptions opt;
    opt.coarse_step = 1;  // find every component
    for (int res : {9, 17, 30}) {
      const Mesh m = extract_marching_cubes(f, box, res, opt);
      ASSERT_FALSE(m.faces.empty());
      expect_closed_oriented(m);
    }
  }
}

TEST(MarchingCubes, DeterministicAcrossThreads) {
  const Blobs f(7);
  Aabb box;
  box.extend(Vec3f(-1, -1, -1));
  box.extend(Vec3f(1, 1, 1));
  MarchingCubesOptions o1, o2;
  o1.threads = 1;
  o2.threads = 2;
  const Mesh a = extract_marching_cubes(f, box, 24, o1), b = extract_marching_cubes(f, box, 24, o2);
  ASSERT_EQ(a.faces.size(), b.faces.size());
  ASSERT_EQ(a.vertices.size(), b.vertices.size());
  for (std::size_t i = 0; i < a.vertices.size(); ++i) EXPECT_EQ(a.vertices[i], b.vertices[i]);
}

TEST(MarchingCubes, BadInput) {
  const Sphere s(Vec3d::Zero(), 0.5);
  EXPECT_THROW(extract_marching_cubes(s, Aabb{}, 10), InvalidInput);
  Aabb box;
  box.extend(Vec3f(0, 0, 0));
  EXPECT_THROW(extract_marching_cubes(s, box, 10), InvalidInput);
  box.extend(Vec3f(1, 1, 1));
  EXPECT_THROW(extract_marching_cubes(s, box, 0), InvalidInput);
}

}  // namespace
}  // namespace station
