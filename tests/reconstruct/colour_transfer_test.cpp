#include "reconstruct/colour_transfer.h"

#include <gtest/gtest.h>

#include "core/error.h"
#include "test_util.h"

namespace station {
namespace {

TEST(ColourTransfer, HalvesKeepTheirColoursAndBoundaryBlursLittle) {
  Mesh mesh = test::icosphere(4, 1.0);
  Cloud cloud;
  for (const Vec3f& v : test::icosphere(5, 1.0).vertices) {
    cloud.points.push_back(v);
    cloud.colours.push_back(v.x() < 0 ? Rgb{255, 0, 0} : Rgb{0, 0, 255});
  }
  transfer_colours(mesh, cloud);
  ASSERT_EQ(mesh.colours.size(), mesh.vertices.size());
  int wrong = 0;
  for (std::size_t i = 0; i < mesh.vertices.size(); ++i) {
    const float x = mesh.vertices[i].x();
    if (std::abs(x) < 0.05f) continue;  // within about one input spacing of the boundary
    const Rgb want = x < 0 ? Rgb{255, 0, 0} : Rgb{0, 0, 255};
    wrong += !(mesh.colours[i] == want);
  }
  EXPECT_EQ(wrong, 0);
}

TEST(ColourTransfer, DeterministicAcrossThreadCounts) {
  Mesh a = test::icosphere(3, 1.0), b = a;
  Cloud cloud;
  int k = 0;
  for (const Vec3f& v : test::icosphere(4, 1.02).vertices) {
    cloud.points.push_back(v);
    cloud.colours.push_back(Rgb{std::uint8_t(k * 7), std::uint8_t(k * 13), std::uint8_t(k * 29)});
    ++k;
  }
  transfer_colours(a, cloud, {4, 1});
  transfer_colours(b, cloud, {4, 2});
  EXPECT_EQ(a.colours, b.colours);
}

TEST(ColourTransfer, NeedsColours) {
  Mesh m = test::icosphere(1);
  Cloud c;
  c.points = m.vertices;
  EXPECT_THROW(transfer_colours(m, c), InvalidInput);
  EXPECT_THROW(transfer_colours(m, Cloud{}), InvalidInput);
}

}  // namespace
}  // namespace station
