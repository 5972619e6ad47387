// The surface stage's automatic resolution (issue 32): the cell follows the
// cloud's mean spacing, so a denser cloud is meshed finer.
#include "reconstruct/surface.h"

#include <gtest/gtest.h>

#include <cmath>

namespace station {
namespace {

Cloud fibonacci_sphere(int n, double r) {
  Cloud c;
  const double golden = M_PI * (3 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double z = 1 - 2 * (i + 0.5) / n, rr = std::sqrt(1 - z * z);
    const Vec3d d(rr * std::cos(golden * i), rr * std::sin(golden * i), z);
    c.points.push_back((r * d).cast<float>());
    c.normals.push_back(d.cast<float>());
  }
  return c;
}

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
