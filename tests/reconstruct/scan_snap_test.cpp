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
  // A plate 0.04 thick (faces at z = +-0.02, scanned from both sides with a little
  // noise); the mesh's two sheets fitted 0.02 outside each face. The search radius
  // (a cell, 0.1) reaches both faces: each sheet must go onto its own, where every
  // scan point counted would put both near the middle.
  Cloud scans;
  add_face(scans, 40000, 0.02f, 1.f, 0.001, 1);
  add_face(scans, 40000, -0.02f, -1.f, 0.001, 2);
  Mesh top = plate(20, 0.04f, true), bottom = plate(20, -0.04f, false);
  ScanSnapParams p;
  p.cell = 0.1;
  snap_to_scans(top, scans, p);
  snap_to_scans(bottom, scans, p);
  double top_z = 0, bottom_z = 0;
  for (const Vec3f& v : top.vertices) top_z += v.z() / double(top.vertices.size());
  for (const Vec3f& v : bottom.vertices) bottom_z += v.z() / double(bottom.vertices.size());
  EXPECT_NEAR(top_z, 0.02, 0.002);
  EXPECT_NEAR(bottom_z, -0.02, 0.002);
  // A sheet 0.08 off its face (within the radius) moves by half a cell, no more.
  Mesh far = plate(20, 0.10f, true);
  const ScanSnapStats st = snap_to_scans(far, scans, p);
  EXPECT_EQ(st.moved, far.vertices.size());
  for (const Vec3f& v : far.vertices) EXPECT_NEAR(v.z(), 0.10f - 0.05f, 1e-4f);
}

TEST(ScanSnap, NoiseAloneDoesNotMoveTheMesh) {
  // A sheet on the face of noisy scans (sigma 0.01, a tenth of a cell): at the default
  // significance almost nothing moves; by the whole mean (0) every vertex takes the
  // noise of its neighbourhood's mean.
  Cloud scans;
  add_face(scans, 20000, 0.f, 1.f, 0.01, 3);
  Mesh cautious = plate(20, 0.f, true), whole = cautious;
  ScanSnapParams p;
  p.cell = 0.1;
  const ScanSnapStats a = snap_to_scans(cautious, scans, p);
  p.significance = 0;
  const ScanSnapStats b = snap_to_scans(whole, scans, p);
  std::printf("noise: significance 1 moved %zu (mean %.5f), 0 moved %zu (mean %.5f) of %zu\n", a.moved, a.mean_move,
              b.moved, b.mean_move, whole.vertices.size());
  // How far each sheet now lies from the true face z = 0 (RMS).
  const auto rms = [](const Mesh& m) {
    double s = 0;
    for (const Vec3f& v : m.vertices) s += double(v.z()) * v.z();
    return std::sqrt(s / double(m.vertices.size()));
  };
  std::printf("noise: RMS off the face %.5f (significance 1) against %.5f (0)\n", rms(cautious), rms(whole));
  EXPECT_EQ(b.moved, whole.vertices.size());
  // Measured: 133 of 441 moved (a third of pure-noise means lie beyond one standard
  // error), RMS 0.00049 against 0.00127.
  EXPECT_LT(double(a.moved), 0.4 * double(b.moved));
  EXPECT_LT(rms(cautious), 0.4 * rms(whole));
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
