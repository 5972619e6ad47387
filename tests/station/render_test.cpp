// The report's software rasteriser on scenes whose pictures are known.
#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>

#include "core/error.h"
#include "station/render.h"
#include "test_util.h"

namespace station {
namespace {

/// Rgb as 0xRRGGBB, so gtest can compare and print it.
int hex(Rgb c) { return c.r << 16 | c.g << 8 | c.b; }

Mesh square(float z, Rgb c, float half = 1.f) {
  Mesh m;
  m.vertices = {{-half, -half, z}, {half, -half, z}, {half, half, z}, {-half, half, z}};
  m.faces = {{0, 1, 2}, {0, 2, 3}};
  m.colours.assign(4, c);
  return m;
}

Mesh join(Mesh a, const Mesh& b) {
  const int off = int(a.vertices.size());
  a.vertices.insert(a.vertices.end(), b.vertices.begin(), b.vertices.end());
  a.colours.insert(a.colours.end(), b.colours.begin(), b.colours.end());
  for (Face f : b.faces) a.faces.push_back(f + Face::Constant(off));
  return a;
}

RenderView front_view(float extent = 2.f) {
  RenderView v;
  v.toward_eye = Vec3d::UnitZ();
  v.up = Vec3d::UnitY();
  v.box.extend(Vec3f(-extent, -extent, -extent));
  v.box.extend(Vec3f(extent, extent, extent));
  v.width = v.height = 101;
  v.margin = 0;
  return v;
}

TEST(Render, NearerSurfaceHidesFartherOneWhateverTheOrder) {
  RenderOptions o;
  o.shade = false;
  const Mesh red = square(0.5f, {255, 0, 0}), blue = square(-0.5f, {0, 0, 255}, 1.5f);
  for (const Mesh& m : {join(red, blue), join(blue, red)}) {
    const Image img = render_mesh(m, front_view(), o);
    EXPECT_EQ(hex(img.at(50, 50)), hex(Rgb{255, 0, 0}));
    // Outside the red square but inside the larger blue one.
    // Box half-diagonal = 2 sqrt(3) fills 50.5 px: 1 unit = 14.6 px; blue reaches 1.5 units = 22 px.
    EXPECT_EQ(hex(img.at(50 + 18, 50)), hex(Rgb{0, 0, 255}));
    EXPECT_EQ(hex(img.at(2, 2)), hex(o.background));
  }
}

TEST(Render, OrientationRightAndUpAreTheImagesRightAndUp) {
  // A small green square at +x and a yellow one at +y (camera looking down -z).
  RenderOptions o;
  o.shade = false;
  Mesh gx = square(0, {0, 255, 0}, 0.2f), yy = square(0, {255, 255, 0}, 0.2f);
  for (Vec3f& v : gx.vertices) v.x() += 1.f;
  for (Vec3f& v : yy.vertices) v.y() += 1.f;
  const Image img = render_mesh(join(gx, yy), front_view(), o);
  const int unit = int(50.5 / (2 * std::sqrt(3.0)));
  EXPECT_EQ(hex(img.at(50 + unit, 50)), hex(Rgb{0, 255, 0}));   // right
  EXPECT_EQ(hex(img.at(50, 50 - unit)), hex(Rgb{255, 255, 0}));  // up = smaller row
  EXPECT_EQ(hex(img.at(50 - unit, 50)), hex(o.background));
  EXPECT_EQ(hex(img.at(50, 50 + unit)), hex(o.background));
}

TEST(Render, HeadlightShadingDarkensObliqueFaces) {
  RenderOptions o;
  o.use_colours = false;
  o.base = {200, 200, 200};
  o.ambient = 0.2;
  Mesh tilted = square(0, {}, 1.f);
  // Rotate 60 degrees about y: cos = 0.5 towards the eye.
  for (Vec3f& v : tilted.vertices) v = Vec3f(v.x() * 0.5f, v.y(), -v.x() * std::sqrt(3.f) / 2);
  const Image img = render_mesh(tilted, front_view(), o);
  const Rgb c = img.at(50, 50);
  EXPECT_NEAR(c.r, 200 * (0.2 + 0.8 * 0.5), 1.0);
}

TEST(Render, ColoursAreInterpolatedAcrossAFace) {
  RenderOptions o;
  o.shade = false;
  Mesh m = square(0, {}, 1.5f);
  m.colours = {{0, 0, 0}, {255, 255, 255}, {255, 255, 255}, {0, 0, 0}};  // dark left, light right
  const Image img = render_mesh(m, front_view(), o);
  EXPECT_LT(img.at(35, 50).r, 80);
  EXPECT_GT(img.at(65, 50).r, 175);
  EXPECT_NEAR(img.at(50, 50).r, 128, 8);
}

TEST(Render, PointsAreDrawnWithTheirColours) {
  Cloud c;
  c.points = {{0, 0, 0}, {1, 0, 0}};
  c.colours = {{255, 0, 0}, {0, 0, 255}};
  RenderOptions o;
  o.point_size = 3;
  const Image img = render_points(c, front_view(), o);
  const int unit = int(50.5 / (2 * std::sqrt(3.0)));
  EXPECT_EQ(hex(img.at(50, 50)), hex(Rgb{255, 0, 0}));
  EXPECT_EQ(hex(img.at(50 + unit, 50)), hex(Rgb{0, 0, 255}));
  EXPECT_EQ(hex(img.at(50, 60)), hex(o.background));
  // Override colours.
  const std::vector<Rgb> green(2, Rgb{0, 200, 0});
  EXPECT_EQ(hex(render_points(c, front_view(), o, &green).at(50, 50)), hex(Rgb{0, 200, 0}));
}

TEST(Render, IgnoresNonFiniteGeometryAndBadIndices) {
  Mesh m = square(0, {10, 20, 30});
  m.vertices.push_back(Vec3f(std::nanf(""), 0, 0));
  m.faces.push_back({0, 1, 4});
  m.faces.push_back({0, 1, 99});
  EXPECT_NO_THROW(render_mesh(m, front_view()));
  RenderView bad = front_view();
  bad.width = 0;
  EXPECT_THROW(render_mesh(m, bad), InvalidInput);
}

TEST(Render, PngRoundTripsThroughOpenCv) {
  Image img(7, 5, {1, 2, 3});
  img.set(6, 4, {250, 100, 0});
  const std::string png = encode_png(img);
  ASSERT_GT(png.size(), 8u);
  EXPECT_EQ(png.substr(1, 3), "PNG");
  const cv::Mat back = cv::imdecode(std::vector<uchar>(png.begin(), png.end()), cv::IMREAD_COLOR);
  ASSERT_EQ(back.cols, 7);
  ASSERT_EQ(back.rows, 5);
  const cv::Vec3b px = back.at<cv::Vec3b>(4, 6);  // BGR
  EXPECT_EQ(px[2], 250);
  EXPECT_EQ(px[1], 100);
  EXPECT_EQ(px[0], 0);
}

TEST(Render, Base64MatchesRfc4648Vectors) {
  EXPECT_EQ(base64(""), "");
  EXPECT_EQ(base64("f"), "Zg==");
  EXPECT_EQ(base64("fo"), "Zm8=");
  EXPECT_EQ(base64("foo"), "Zm9v");
  EXPECT_EQ(base64("foobar"), "Zm9vYmFy");
  EXPECT_EQ(base64(std::string("\xff\x00\x10", 3)), "/wAQ");
}

TEST(Render, StandardViewsSeeTheObjectFromFourSidesAndAbove) {
  // A unit box: every standard view shows it centred.
  const Mesh b = test::box(Vec3f(-0.5f, -0.5f, 0), Vec3f(0.5f, 0.5f, 1));
  const Aabb box = bounding_box(b.vertices);
  for (int q = 0; q < 4; ++q) {
    const Image img = render_mesh(b, view_from_side(q, box, 64));
    EXPECT_NE(hex(img.at(32, 32)), hex(Rgb{255, 255, 255})) << q;
    EXPECT_EQ(hex(img.at(1, 1)), hex(Rgb{255, 255, 255})) << q;
  }
  const Image top = render_mesh(b, view_from_above(box, 64));
  EXPECT_NE(hex(top.at(32, 32)), hex(Rgb{255, 255, 255}));
}

}  // namespace
}  // namespace station
