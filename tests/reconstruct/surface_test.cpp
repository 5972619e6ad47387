// The surface stage's automatic resolution (issue 32): the cell follows the
// cloud's mean spacing, so a denser cloud is meshed finer.
#include "reconstruct/surface.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>

#include "core/kdtree.h"
#include "reconstruct/winding_close.h"
#include "test_util.h"

namespace station {
namespace {

using test::fibonacci_sphere;

TEST(SurfaceResolution, AutoClampsTheLongestSideOverTheSpacing) {
  EXPECT_EQ(auto_resolution(0.2, 0.001), 200);
  EXPECT_EQ(auto_resolution(0.2, 0.0013), 154);  // ceil(153.8)
  EXPECT_EQ(auto_resolution(0.2, 0.01), kAutoResolutionMin);
  EXPECT_EQ(auto_resolution(0.2, 1e-5), kAutoResolutionMax);
  EXPECT_EQ(auto_resolution(0.2, 0), kAutoResolutionMin);
  EXPECT_EQ(auto_resolution(0.2, std::nan("")), kAutoResolutionMin);
}

TEST(SurfaceResolution, AutoFollowsTheCloudsSpacing) {
  SurfaceParams p;
  p.threads = 2;
  ASSERT_EQ(p.resolution, 0);  // auto by default
  int previous = 0;
  for (const int n : {20000, 80000}) {
    const SurfaceResult r = reconstruct_surface(fibonacci_sphere(n, 0.1), p);
    EXPECT_TRUE(r.resolution_auto);
    const double spacing = r.mpu.mean_spacing;
    ASSERT_GT(spacing, 0);
    std::printf("%d points: spacing %.5f, resolution %d, cell %.5f\n", n, spacing, r.resolution,
                r.extraction.cell_size);
    EXPECT_GT(r.resolution, kAutoResolutionMin);
    EXPECT_LT(r.resolution, kAutoResolutionMax);
    // One cell per spacing (the box's longest side over the resolution).
    EXPECT_NEAR(r.extraction.cell_size, spacing, 0.05 * spacing);
    EXPECT_GT(r.resolution, previous);  // 4x the points: about 2x the resolution
    if (previous > 0) {
      EXPECT_NEAR(double(r.resolution) / previous, 2.0, 0.2);
    }
    previous = r.resolution;
  }
  p.resolution = 48;  // explicit: used as given
  const SurfaceResult fixed = reconstruct_surface(fibonacci_sphere(8000, 0.1), p);
  EXPECT_FALSE(fixed.resolution_auto);
  EXPECT_EQ(fixed.resolution, 48);
}

}  // namespace
}  // namespace station

namespace station {
namespace {

Cloud cap(int n, double r, double min_z) {  // the part of a sphere above z = min_z * r
  Cloud all = fibonacci_sphere(n, r), out;
  for (std::size_t i = 0; i < all.size(); ++i)
    if (all.normals[i].z() >= min_z) {
      out.points.push_back(all.points[i]);
      out.normals.push_back(all.normals[i]);
    }
  return out;
}

TEST(SurfaceHole, EnclosureOfClosedAndOneSidedClouds) {
  const double sphere = cloud_enclosure(fibonacci_sphere(20000, 0.1));
  const double hemisphere = cloud_enclosure(cap(20000, 0.1, 0.0));
  Cloud plane;
  for (int i = 0; i < 100; ++i)
    for (int j = 0; j < 100; ++j) {
      plane.points.emplace_back(0.002f * i, 0.002f * j, 0.f);
      plane.normals.emplace_back(0.f, 0.f, 1.f);
    }
  const double flat = cloud_enclosure(plane);
  Cloud inwards = fibonacci_sphere(20000, 0.1);
  for (Vec3f& nrm : inwards.normals) nrm = -nrm;
  const double flipped = cloud_enclosure(inwards);
  std::printf("enclosure: sphere %.3f, hemisphere %.3f, plane %.3f, inward sphere %.3f\n", sphere,
              hemisphere, flat, flipped);
  EXPECT_GT(sphere, 0.9);
  EXPECT_GT(hemisphere, 0.5);  // its rim sees most of it
  EXPECT_LT(hemisphere, kEnclosedAbove);
  EXPECT_NEAR(flat, 0.0, 0.1);
  EXPECT_LT(flipped, -0.9);
  EXPECT_EQ(cloud_enclosure(Cloud{}), 0.0);
}

// hole auto: a sphere closes (no boundary edges); one view's worth of it, a cap of a
// third of the sphere, stays open instead of becoming a slab.
TEST(SurfaceHole, AutoClosesAnObjectAndKeepsAPatchOpen) {
  SurfaceParams p;
  p.threads = 2;
  p.resolution = 64;
  ASSERT_EQ(p.hole, HoleMode::kAuto);  // the default
  auto boundary_edges = [](const Mesh& m) { return test::open_edges(m); };
  const SurfaceResult sphere = reconstruct_surface(fibonacci_sphere(8000, 0.1), p);
  ASSERT_TRUE(sphere.enclosure.has_value());
  EXPECT_EQ(sphere.hole, HoleMode::kClose);
  EXPECT_EQ(boundary_edges(sphere.mesh), 0);
  const SurfaceResult patch = reconstruct_surface(cap(24000, 0.1, 0.33), p);
  ASSERT_TRUE(patch.enclosure.has_value());
  EXPECT_LT(*patch.enclosure, kEnclosedAbove);
  EXPECT_EQ(patch.hole, HoleMode::kKeep);
  EXPECT_GT(boundary_edges(patch.mesh), 0);
  // A closed cloud with every normal inwards is turned, then closed.
  Cloud inwards = fibonacci_sphere(8000, 0.1);
  for (Vec3f& n : inwards.normals) n = -n;
  const SurfaceResult turned = reconstruct_surface(inwards, p);
  EXPECT_TRUE(turned.normals_flipped);
  EXPECT_EQ(turned.hole, HoleMode::kClose);
  EXPECT_EQ(boundary_edges(turned.mesh), 0);
  EXPECT_FALSE(sphere.normals_flipped);
  // A hemisphere (0.65) stays open by default; where the views surround the object
  // (station run on a turntable session), the lower bound closes it.
  const Cloud half = cap(16000, 0.1, 0.0);
  const SurfaceResult open_half = reconstruct_surface(half, p);
  EXPECT_EQ(open_half.hole, HoleMode::kKeep);
  SurfaceParams around = p;
  around.enclosed_above = kEnclosedAboveSurrounded;
  const SurfaceResult closed_half = reconstruct_surface(half, around);
  ASSERT_TRUE(closed_half.enclosure.has_value());
  EXPECT_GT(*closed_half.enclosure, kEnclosedAboveSurrounded);
  EXPECT_EQ(closed_half.hole, HoleMode::kClose);
  EXPECT_EQ(boundary_edges(closed_half.mesh), 0);
  // ... but not a one-view patch.
  EXPECT_EQ(reconstruct_surface(cap(24000, 0.1, 0.33), around).hole, HoleMode::kKeep);
  // Closed by force, the same patch becomes a solid: no boundary edges.
  p.hole = HoleMode::kClose;
  EXPECT_EQ(boundary_edges(reconstruct_surface(cap(24000, 0.1, 0.33), p).mesh), 0);
}

// Normals that are all zero are none: estimated, as for a cloud without them (MPU
// refused such a cloud: "0 points with usable normals").
TEST(SurfaceHole, AllZeroNormalsAreEstimated) {
  SurfaceParams p;
  p.threads = 2;
  p.resolution = 48;
  Cloud zero = fibonacci_sphere(4000, 0.1);
  for (Vec3f& n : zero.normals) n = Vec3f::Zero();
  const SurfaceResult r = reconstruct_surface(zero, p);
  EXPECT_TRUE(r.normals_estimated);
  EXPECT_EQ(r.hole, HoleMode::kClose);
  EXPECT_EQ(test::open_edges(r.mesh), 0);
}

// Issue 32: with holes kept and the scans given, the rims come back to within
// kScanRimFactor of the scans' sample spacings (the consolidated points are 3 times
// sparser, and their own trim leaves the rims up to 1.5 of their spacings past the
// scans), and a small separate patch that 25 scan points support stays, while a speck
// of 9 goes; without the scans both go by the area bound and the rims flare.
TEST(SurfaceScans, KeptRimsComeBackToTheScansAndSupportedPiecesStay) {
  const float step = 0.0004f;
  Cloud scans, consolidated;
  // An n x n grid from (x0, y0) in the plane z = 0, normals up; the consolidated
  // points every third one (`thinned`) or the grid's centre alone.
  auto add_patch = [&](float x0, float y0, int n, bool thinned) {
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j) {
        const Vec3f q(x0 + step * float(i), y0 + step * float(j), 0);
        scans.points.push_back(q);
        scans.normals.push_back(Vec3f::UnitZ());
        if (thinned ? i % 3 == 1 && j % 3 == 1 : i == n / 2 && j == n / 2) {
          consolidated.points.push_back(q);
          consolidated.normals.push_back(Vec3f::UnitZ());
        }
      }
  };
  add_patch(0, 0, 101, true);         // 40 x 40 mm
  add_patch(0.05f, 0.02f, 5, false);  // 25 scan points, 10 mm beyond its edge
  add_patch(0.02f, 0.05f, 3, false);  // 9
  const Vec3f supported(0.0508f, 0.0208f, 0), speck(0.0204f, 0.0504f, 0);
  SurfaceParams p;
  p.threads = 2;
  p.resolution = 128;
  p.hole = HoleMode::kKeep;
  p.colour = false;
  const PointIndex scan_index(scans.points);
  const double reach = kScanRimFactor * sample_spacing(scan_index);
  ASSERT_GT(reach, 0.0003);
  auto furthest = [&](const Mesh& m) {
    double d = 0;
    for (const Vec3f& v : m.vertices) d = std::max(d, double(scan_index.nearest(v).second));
    return d;
  };
  auto near = [](const Mesh& m, const Vec3f& c, float r) {
    int n = 0;
    for (const Vec3f& v : m.vertices) n += (v - c).norm() < r;
    return n;
  };
  const SurfaceResult alone = reconstruct_surface(consolidated, p);
  EXPECT_GT(furthest(alone.mesh), 2 * reach);
  EXPECT_EQ(near(alone.mesh, supported, 0.002f), 0);
  EXPECT_EQ(alone.pieces.supported_components, 0u);

  p.scans = &scans;
  const SurfaceResult r = reconstruct_surface(consolidated, p);
  EXPECT_GT(r.scan_rim_faces, 0u);
  EXPECT_LE(furthest(r.mesh), reach + 1e-6);
  EXPECT_GT(near(r.mesh, supported, 0.0005f), 0);
  EXPECT_EQ(near(r.mesh, speck, 0.002f), 0);
  EXPECT_EQ(r.pieces.supported_components, 1u);
  EXPECT_GT(test::open_edges(r.mesh), 0);
  // Scans that hardly meet the mesh (1 m away: another object, other units) trim
  // nothing and keep nothing.
  Cloud elsewhere = scans;
  for (Vec3f& q : elsewhere.points) q.z() += 1.0f;
  p.scans = &elsewhere;
  const SurfaceResult off = reconstruct_surface(consolidated, p);
  EXPECT_EQ(off.scan_rim_faces, 0u);
  EXPECT_EQ(off.pieces.supported_components, 0u);
  EXPECT_EQ(off.mesh.faces.size(), alone.mesh.faces.size());
}

TEST(SurfaceScans, KeptRimsStayOverSparseScans) {
  // A 40 x 20 mm plane patch scanned at 0.4 mm on its left half and 1.2 mm on its
  // right (a depth camera's near and far field), consolidated to 1.2 mm all over. The
  // scans' median spacing is the dense half's; at 1.5 of it a vertex between the
  // sparse scans lies "beyond every scan point", and the trim ate into the sparse
  // half from its rims. With the local spacing there the mesh keeps it.
  Cloud scans, consolidated;
  auto add = [](Cloud& c, float x, float y) {
    c.points.emplace_back(x, y, 0.f);
    c.normals.push_back(Vec3f::UnitZ());
  };
  for (int i = 0; i <= 50; ++i)
    for (int j = 0; j <= 50; ++j) add(scans, 0.0004f * float(i), 0.0004f * float(j));
  for (int i = 1; i <= 16; ++i)
    for (int j = 0; j <= 16; ++j) add(scans, 0.02f + 0.0012f * float(i), 0.0012f * float(j));
  for (int i = 0; i <= 33; ++i)
    for (int j = 0; j <= 16; ++j) add(consolidated, 0.0012f * float(i), 0.0012f * float(j));
  SurfaceParams p;
  p.threads = 2;
  p.resolution = 100;
  p.hole = HoleMode::kKeep;
  p.colour = false;
  p.scans = &scans;
  const SurfaceResult r = reconstruct_surface(consolidated, p);
  // The mesh's area on the plane over the sparse half, inside its outermost scan points.
  double area = 0;
  for (const Face& f : r.mesh.faces) {
    const Vec3f a = r.mesh.vertices[std::size_t(f[0])], b = r.mesh.vertices[std::size_t(f[1])],
                c = r.mesh.vertices[std::size_t(f[2])];
    const Vec3f m = (a + b + c) / 3.f;
    if (m.x() > 0.0212f && m.x() < 0.0392f && m.y() > 0.f && m.y() < 0.0192f && std::abs(m.z()) < 0.0002f)
      area += 0.5 * double((b - a).cross(c - a).norm());
  }
  const double full = 0.018 * 0.0192;
  std::printf("sparse half: %.1f %% covered, %zu faces trimmed to the scans\n", 100 * area / full, r.scan_rim_faces);
  EXPECT_GT(area, 0.95 * full);
}

}  // namespace
}  // namespace station

namespace station {
namespace {

// Crossings of the line {(x, y, z): z real} with the mesh's faces.
int crossings(const Mesh& m, double x, double y) {
  int count = 0;
  for (const Face& f : m.faces) {
    const Vec3d a = m.vertices[f[0]].cast<double>(), b = m.vertices[f[1]].cast<double>(),
                c = m.vertices[f[2]].cast<double>();
    // Barycentric test in the xy projection.
    const double d = (b.y() - c.y()) * (a.x() - c.x()) + (c.x() - b.x()) * (a.y() - c.y());
    if (std::abs(d) < 1e-18) continue;
    const double l1 = ((b.y() - c.y()) * (x - c.x()) + (c.x() - b.x()) * (y - c.y())) / d;
    const double l2 = ((c.y() - a.y()) * (x - c.x()) + (a.x() - c.x()) * (y - c.y())) / d;
    const double l3 = 1 - l1 - l2;
    if (l1 >= 0 && l2 >= 0 && l3 >= 0 && (l1 > 0 || l2 > 0) && l3 < 1) ++count;
  }
  return count;
}

// A thin plate (40 x 40 x 1.5 mm) seen from both sides, the back view registered
// 0.3 mm off sideways (issue 32's example): one closed thin shape, two sheets
// along every line through it, not four.
TEST(SurfaceThinParts, ATwoSidedPlateWithAMisregisteredBackIsOneShape) {
  const float half = 0.02f, thick = 0.0015f, step = 0.0004f, offset = 0.0003f;
  Cloud c;
  for (float x = -half; x <= half; x += step)
    for (float y = -half; y <= half; y += step) {
      c.points.emplace_back(x, y, 0.5f * thick);
      c.normals.emplace_back(0.f, 0.f, 1.f);
      c.points.emplace_back(x + offset, y, -0.5f * thick);
      c.normals.emplace_back(0.f, 0.f, -1.f);
    }
  for (const HoleMode hole : {HoleMode::kAuto, HoleMode::kClose}) {
    SurfaceParams p;
    p.threads = 2;
    p.colour = false;
    p.hole = hole;
    const SurfaceResult r = reconstruct_surface(c, p);
    std::printf("plate: %zu points, %d cells (cell %.5f), %zu vertices, hole %s (enclosure %.3f)\n",
                c.size(), r.resolution, r.extraction.cell_size, r.mesh.vertices.size(),
                r.hole == HoleMode::kClose ? "closed" : "kept", r.enclosure.value_or(-9));
    int two = 0, lines = 0;
    for (double x = -0.015; x <= 0.0151; x += 0.005)
      for (double y = -0.015; y <= 0.0151; y += 0.005) {
        const int n = crossings(r.mesh, x + 1e-5, y + 2e-5);
        ++lines;
        two += n == 2;
        EXPECT_EQ(n, 2) << "at " << x << ", " << y;
      }
    EXPECT_EQ(two, lines);
  }
}

}  // namespace
}  // namespace station
