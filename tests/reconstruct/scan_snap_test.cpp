// reconstruct/scan_snap.h: the mesh's vertices onto the scans' local mean.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "core/error.h"
#include "reconstruct/scan_snap.h"
#include "test_util.h"

namespace station {
namespace {

// A square grid mesh in the plane z = height, [-1, 1]^2, n x n cells.
Mesh plate(int n, float height, bool up) {
  Mesh m;
  for (int j = 0; j <= n; ++j)
    for (int i = 0; i <= n; ++i) m.vertices.emplace_back(-1.f + 2.f * i / n, -1.f + 2.f * j / n, height);
  for (int j = 0; j < n; ++j)
    for (int i = 0; i < n; ++i) {
      const int a = j * (n + 1) + i, b = a + 1, c = a + n + 1, d = c + 1;
      if (up) {
        m.faces.push_back({a, b, d});
        m.faces.push_back({a, d, c});
      } else {
        m.faces.push_back({a, d, b});
        m.faces.push_back({a, c, d});
      }
    }
  return m;
}

// Scan points on z = height over [-1.2, 1.2]^2 with the given normal's sign and noise.
void add_face(Cloud& c, int n, float height, float nz, double noise, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1.2f, 1.2f);
  std::normal_distribution<double> g(0.0, noise);
  for (int k = 0; k < n; ++k) {
    c.points.emplace_back(u(rng), u(rng), float(height + g(rng)));
    c.normals.emplace_back(0.f, 0.f, nz);
  }
}

TEST(ScanSnap, VerticesGoOntoTheScansOfASphere) {
  // The fitted surface 2 % inside the scans (a thinned, smoothed cloud's mesh).
  Mesh mesh = test::icosphere(4, 0.98);
  const Cloud scans = test::fibonacci_sphere(60000, 1.0);
  ScanSnapParams p;
  p.cell = 0.08;  // about the mesh's edge
  const ScanSnapStats st = snap_to_scans(mesh, scans, p);
  double before = 0.02, after = 0;
  for (const Vec3f& v : mesh.vertices) after += std::abs(v.norm() - 1.0) / double(mesh.vertices.size());
  std::printf("sphere: %zu of %zu moved, mean move %.4f, |r - 1| %.4f -> %.5f\n", st.moved, mesh.vertices.size(),
              st.mean_move, before, after);
  EXPECT_EQ(st.moved, mesh.vertices.size());
  EXPECT_LT(after, 0.1 * before);
}

TEST(ScanSnap, AThinPartKeepsBothSidesAndMovesAtMostHalfACell) {
  // A plate 0.1 thick (faces at z = +-0.05, scanned from both sides with a little
  // noise); the mesh's two sheets fitted 0.03 outside each face. Each sheet must go
  // onto its own face: with every scan point counted, both would meet in the middle.
  Cloud scans;
  add_face(scans, 40000, 0.05f, 1.f, 0.002, 1);
  add_face(scans, 40000, -0.05f, -1.f, 0.002, 2);
  Mesh top = plate(20, 0.08f, true), bottom = plate(20, -0.08f, false);
  ScanSnapParams p;
  p.cell = 0.1;
  snap_to_scans(top, scans, p);
  snap_to_scans(bottom, scans, p);
  double top_z = 0, bottom_z = 0;
  for (const Vec3f& v : top.vertices) top_z += v.z() / double(top.vertices.size());
  for (const Vec3f& v : bottom.vertices) bottom_z += v.z() / double(bottom.vertices.size());
  EXPECT_NEAR(top_z, 0.05, 0.005);
  EXPECT_NEAR(bottom_z, -0.05, 0.005);
  // A sheet 0.2 off its face moves by half a cell at most.
  Mesh far = plate(20, 0.25f, true);
  snap_to_scans(far, scans, p);
  for (const Vec3f& v : far.vertices) EXPECT_GE(v.z(), 0.25f - 0.05f - 1e-5f);
}

TEST(ScanSnap, ScansWithoutNormalsAreRefused) {
  Mesh mesh = plate(4, 0.f, true);
  Cloud scans;
  scans.points = {Vec3f(0, 0, 0), Vec3f(0.1f, 0, 0), Vec3f(0, 0.1f, 0)};
  ScanSnapParams p;
  p.cell = 0.5;
  EXPECT_THROW(snap_to_scans(mesh, scans, p), InvalidInput);
  scans.normals.assign(3, Vec3f(0, 0, 1));
  p.cell = 0;
  EXPECT_THROW(snap_to_scans(mesh, scans, p), InvalidInput);
}

}  // namespace
}  // namespace station
