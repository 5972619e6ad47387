// The ray-cast scanner against analytic shapes: geometry, noise, occlusion by
// the turntable disk, determinism, turntable motion, colours, errors.
#include <gtest/gtest.h>
#include <tbb/global_control.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <fstream>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "capture/capture.h"
#include "capture/session.h"
#include "core/bvh.h"
#include "core/error.h"
#include "core/io.h"
#include "sim/bench.h"
#include "sim_test_util.h"
#include "test_util.h"

namespace station {
namespace {

using test::apply;
using test::back_project;

constexpr double kRadius = 0.05;
const Vec3d kCentre(0, 0, 0.05);  // the sphere rests on the table

struct Rig {
  DeviceRegistry registry = test::sim_registry();
  std::unique_ptr<Scanner> scanner;
  std::unique_ptr<Turntable> turntable;
};

// A scanner (and turntable) on one bench; `query` is appended to the mesh URI.
Rig make_rig(const std::filesystem::path& mesh, const std::string& query = "",
             bool with_turntable = false) {
  Rig rig;
  rig.scanner = rig.registry.make_scanner("sim:synthetic?mesh=" + mesh.string() + query);
  rig.scanner->open();
  if (with_turntable) {
    rig.turntable = rig.registry.make_turntable("sim:turntable");
    rig.turntable->open();
  }
  return rig;
}

class SyntheticSphere : public ::testing::Test {
 protected:
  void SetUp() override {
    write_ply(dir_ / "sphere.ply", test::icosphere(5, kRadius, kCentre.cast<float>()));
  }
  std::filesystem::path sphere() const { return dir_ / "sphere.ply"; }
  test::TempDir dir_{"sim-test"};
};

// Splits a view (object frame) into sphere and disk points; fails on anything else.
struct Split {
  std::vector<Vec3d> sphere, disk;
  std::vector<int> sphere_pixels;
};

Split split_view(const Frame& f, double tolerance) {
  Split s;
  const Eigen::Matrix4d pose = *f.reference_pose;
  for (const auto& sample : back_project(f)) {
    const Vec3d q = apply(pose, sample.p);
    if (std::abs((q - kCentre).norm() - kRadius) <= tolerance) {
      s.sphere.push_back(q);
      s.sphere_pixels.push_back(sample.pixel);
    } else if (std::abs(q.z()) <= tolerance && q.head<2>().norm() <= 0.15 + tolerance) {
      s.disk.push_back(q);
    } else {
      ADD_FAILURE() << "point on neither sphere nor disk: " << q.transpose();
      break;
    }
  }
  return s;
}

TEST_F(SyntheticSphere, NoiselessPointsLieOnTheSphereOrTheDisk) {
  Rig rig = make_rig(sphere(), "&noise=0");
  const ScannerCapabilities caps = rig.scanner->capabilities();
  EXPECT_TRUE(caps.depth);
  EXPECT_TRUE(caps.colour);
  ASSERT_TRUE(caps.axis);
  const Frame f = rig.scanner->grab();
  ASSERT_EQ(f.depth.size(), 640u * 480u);
  EXPECT_EQ(f.intrinsics.width, 640);
  EXPECT_DOUBLE_EQ(f.intrinsics.fx, 320.0 / std::tan(25.0 * M_PI / 180.0));
  EXPECT_DOUBLE_EQ(f.intrinsics.cx, 319.5);
  EXPECT_DOUBLE_EQ(f.intrinsics.cy, 239.5);
  EXPECT_EQ(f.colour_intrinsics.fx, f.intrinsics.fx);
  EXPECT_EQ(f.colour.size(), 640u * 480u * 3);
  EXPECT_GT(f.timestamp, 1.6e9);
  ASSERT_TRUE(f.reference_pose);
  // Faceting of a level-5 icosphere of 5 cm: faces sag at most ~1.2e-5 m.
  const Split s = split_view(f, 3e-5);
  EXPECT_GT(s.sphere.size(), 10000u);
  EXPECT_GT(s.disk.size(), 1000u);
  // The camera looks at the sphere's centre (mid-height target): the sphere is
  // in the middle of the image.
  Vec3d mean = Vec3d::Zero();
  for (const Vec3d& q : s.sphere) mean += q;
  mean /= double(s.sphere.size());
  EXPECT_GT(mean.x(), 0.02);  // the camera is on the table's +x side
  EXPECT_NEAR(mean.y(), 0.0, 1e-3);
  // The axis reported in the scanner frame matches the reference pose.
  const Vec3d axis_point = apply(*f.reference_pose, caps.axis->point);
  const Vec3d axis_dir = f.reference_pose->topLeftCorner<3, 3>() * caps.axis->direction;
  EXPECT_LT(axis_point.norm(), 1e-12);
  EXPECT_LT((axis_dir - Vec3d::UnitZ()).norm(), 1e-12);
  // And the capture loop's turntable prior reproduces the truth exactly.
  EXPECT_LT((turntable_pose(*caps.axis, 0) - *f.reference_pose).norm(), 1e-12);
  // Camera height: target at mid-height 0.05, 20 degrees up at 0.45 m.
  const Vec3d camera = f.reference_pose->topRightCorner<3, 1>();
  EXPECT_NEAR(camera.x(), 0.45, 1e-12);
  EXPECT_NEAR(camera.z(), 0.05 + 0.45 * std::tan(20 * M_PI / 180), 1e-8);  // float mesh
}

TEST_F(SyntheticSphere, DepthNoiseHasTheRequestedSigma) {
  Rig clean = make_rig(sphere(), "&noise=0");
  Rig noisy = make_rig(sphere(), "&noise=0.001&seed=5");
  const Frame a = clean.scanner->grab(), b = noisy.scanner->grab();
  const Split s = split_view(a, 3e-5);
  double sum = 0, sum2 = 0;
  int n = 0;
  for (int pixel : s.sphere_pixels) {
    if (b.depth[pixel] <= 0) continue;
    const double r = double(b.depth[pixel]) - double(a.depth[pixel]);
    sum += r;
    sum2 += r * r;
    ++n;
  }
  ASSERT_GT(n, 10000);
  const double mean = sum / n, sd = std::sqrt(sum2 / n - mean * mean);
  EXPECT_NEAR(mean, 0.0, 1e-4);
  EXPECT_NEAR(sd, 0.001, 0.00005);
  // Every noisy sphere point is still within a few sigma (plus faceting) of the
  // sphere: the displacement is along the ray.
  for (const auto& sample : back_project(b)) {
    const Vec3d q = apply(*b.reference_pose, sample.p);
    if (std::abs(q.z()) < 0.006) continue;  // the disk (also noisy) and the sphere's foot
    EXPECT_LT(std::abs((q - kCentre).norm() - kRadius), 6 * 0.001 * 1.2 + 3e-5);
  }
}

TEST_F(SyntheticSphere, QuadraticNoiseAndDropouts) {
  Rig clean = make_rig(sphere(), "&noise=0");
  Rig noisy = make_rig(sphere(), "&noise=0&noise_quadratic=0.01&dropout=0.25");
  const Frame a = clean.scanner->grab(), b = noisy.scanner->grab();
  int valid = 0, dropped = 0;
  double z2 = 0, r2 = 0;
  for (std::size_t i = 0; i < a.depth.size(); ++i) {
    if (a.depth[i] <= 0) {
      EXPECT_EQ(b.depth[i], 0.f);  // dropouts never create returns
      continue;
    }
    if (b.depth[i] <= 0) {
      ++dropped;
      continue;
    }
    ++valid;
    const double z = a.depth[i], r = b.depth[i] - a.depth[i];
    const double sigma = 0.01 * z * z;
    z2 += sigma * sigma;
    r2 += r * r;
  }
  EXPECT_NEAR(double(dropped) / (valid + dropped), 0.25, 0.01);
  EXPECT_NEAR(std::sqrt(r2 / valid), std::sqrt(z2 / valid), 0.05 * std::sqrt(z2 / valid));
}

TEST_F(SyntheticSphere, MaxRangeCutsReturns) {
  Rig rig = make_rig(sphere(), "&noise=0&max_range=0.43");
  const Frame f = rig.scanner->grab();
  int n = 0;
  for (float z : f.depth) {
    if (z > 0) {
      EXPECT_LE(z, 0.43f);
      ++n;
    }
  }
  EXPECT_GT(n, 100);
}

TEST(SyntheticDisk, TheTableHidesWhatIsBelowIt) {
  test::TempDir dir("sim-test");
  // A sphere sunk halfway into the table (center=0 keeps it where it is).
  write_ply(dir / "s.ply", test::icosphere(4, kRadius));
  for (const char* elevation : {"20", "-20"}) {
    Rig rig = make_rig(dir / "s.ply", std::string("&noise=0&elevation_deg=") + elevation +
                                          "&target_height=0.0");
    const Frame f = rig.scanner->grab();
    int on_sphere_below = 0, on_sphere_above = 0, on_disk = 0;
    for (const auto& sample : back_project(f)) {
      const Vec3d q = apply(*f.reference_pose, sample.p);
      if (std::abs(q.z()) < 1e-6) {
        ++on_disk;
        EXPECT_GT(q.head<2>().norm(), kRadius - 2e-3);  // the disk is cut by the sphere
        EXPECT_LE(q.head<2>().norm(), 0.15 + 1e-6);
      } else {
        EXPECT_LT(std::abs(q.norm() - kRadius), 1e-4);
        (q.z() < 0 ? on_sphere_below : on_sphere_above)++;
      }
    }
    EXPECT_GT(on_disk, 1000) << elevation;
    if (std::string(elevation) == "20") {
      EXPECT_EQ(on_sphere_below, 0);  // seen from above, the table hides the lower half
      EXPECT_GT(on_sphere_above, 1000);
    } else {
      EXPECT_EQ(on_sphere_above, 0);  // seen from below, the disk hides the upper half
      EXPECT_GT(on_sphere_below, 1000);
    }
  }
}

TEST_F(SyntheticSphere, DiskIsGreyAndDefaultMeshColourLightGrey) {
  Rig rig = make_rig(sphere(), "&noise=0");
  const Frame f = rig.scanner->grab();
  int disk = 0, object = 0, background = 0;
  for (const auto& sample : back_project(f)) {
    const Vec3d q = apply(*f.reference_pose, sample.p);
    const std::uint8_t* c = &f.colour[std::size_t(sample.pixel) * 3];
    if (std::abs(q.z()) < 1e-6) {
      EXPECT_EQ(c[0], 128);
      EXPECT_EQ(c[1], 128);
      EXPECT_EQ(c[2], 128);
      ++disk;
    } else {
      EXPECT_EQ(c[0], 200);
      EXPECT_EQ(c[2], 200);
      ++object;
    }
  }
  for (std::size_t i = 0; i < f.depth.size(); ++i)
    if (f.depth[i] == 0) {
      ++background;
      EXPECT_EQ(f.colour[3 * i], 0);
    }
  EXPECT_GT(disk, 1000);
  EXPECT_GT(object, 1000);
  EXPECT_GT(background, 1000);
}

TEST_F(SyntheticSphere, SameSeedSameFramesWhateverTheThreadCount) {
  const std::string q = "&noise=0.001&dropout=0.1&color_noise=3&seed=42";
  Frame a, b, c, a2;
  {
    Rig rig = make_rig(sphere(), q);
    a = rig.scanner->grab();
    a2 = rig.scanner->grab();
  }
  {
    tbb::global_control one(tbb::global_control::max_allowed_parallelism, 1);
    Rig rig = make_rig(sphere(), q);
    b = rig.scanner->grab();
  }
  {
    Rig rig = make_rig(sphere(), "&noise=0.001&dropout=0.1&color_noise=3&seed=43");
    c = rig.scanner->grab();
  }
  EXPECT_EQ(a.depth, b.depth);
  EXPECT_EQ(a.colour, b.colour);
  EXPECT_NE(a.depth, c.depth);
  EXPECT_NE(a.colour, c.colour);
  EXPECT_NE(a.depth, a2.depth);  // the next frame has fresh noise
  // Reopening restarts the frame sequence.
  Rig rig = make_rig(sphere(), q);
  rig.scanner->grab();
  rig.scanner->close();
  rig.scanner->open();
  EXPECT_EQ(rig.scanner->grab().depth, a.depth);
}

// A scan stopped after two views and resumed by a new process records the views an
// uninterrupted scan does (the frame counter restarted at 0 on open(), so the resumed
// views had the noise of frames 0, 1, ...).
TEST_F(SyntheticSphere, AResumedScanRecordsTheSameViews) {
  const std::string q = "&noise=0.001&dropout=0.1&color_noise=3&width=160&height=120";
  CaptureParams p;
  p.views = 4;
  {
    Rig rig = make_rig(sphere(), q, true);
    Session whole = Session::create(dir_ / "whole", {});
    run_capture(*rig.scanner, *rig.turntable, whole, p);
  }
  {
    Rig rig = make_rig(sphere(), q, true);
    Session part = Session::create(dir_ / "part", {});
    std::atomic<bool> stop{false};
    run_capture(*rig.scanner, *rig.turntable, part, p,
                [&](const CaptureProgress& pr) { stop = pr.view == 1; }, &stop);
  }
  ASSERT_EQ(Session::open(dir_ / "part").manifest().views.size(), 2u);
  {
    Rig rig = make_rig(sphere(), q, true);
    Session part = Session::open(dir_ / "part");
    EXPECT_EQ(run_capture(*rig.scanner, *rig.turntable, part, p).recorded, 2);
  }
  const Session whole = Session::open(dir_ / "whole"), part = Session::open(dir_ / "part");
  ASSERT_EQ(part.manifest().views.size(), 4u);
  for (std::size_t i = 0; i < 4; ++i) {
    const ViewRecord& a = whole.manifest().views[i];
    const ViewRecord& b = part.manifest().views[i];
    EXPECT_DOUBLE_EQ(*a.angle_deg, *b.angle_deg) << i;
    EXPECT_EQ(read_file_bytes(dir_ / "whole" / a.file), read_file_bytes(dir_ / "part" / b.file)) << i;
    EXPECT_EQ(read_file_bytes(dir_ / "whole" / a.colour_image),
              read_file_bytes(dir_ / "part" / b.colour_image))
        << i;
  }
}

// Distance from q to the surface of the box [lo, hi].
double box_surface_distance(const Vec3d& q, const Vec3d& lo, const Vec3d& hi) {
  const Vec3d outside = (lo - q).cwiseMax(q - hi).cwiseMax(0.0);
  if (outside.norm() > 0) return outside.norm();
  return std::min((q - lo).minCoeff(), (hi - q).minCoeff());
}

TEST(SyntheticTurntable, RotatingTheTableTurnsTheObject) {
  test::TempDir dir("sim-test");
  const Vec3f lo(-0.04f, -0.03f, 0.f), hi(0.02f, 0.05f, 0.08f);
  write_ply(dir / "box.ply", test::box(lo, hi));
  Rig rig = make_rig(dir / "box.ply", "&noise=0", /*with_turntable=*/true);
  rig.turntable->home();
  const Frame f0 = rig.scanner->grab();
  rig.turntable->rotate_to(90);
  EXPECT_DOUBLE_EQ(rig.turntable->angle(), 90.0);
  const Frame f90 = rig.scanner->grab();
  // Poses differ by the table rotation: object_from_camera(a) = Rz(-a) * table_from_camera.
  EXPECT_LT((*f90.reference_pose - sim::rotate_z_deg(-90) * *f0.reference_pose).norm(), 1e-12);
  const ScannerCapabilities caps = rig.scanner->capabilities();
  EXPECT_LT((turntable_pose(*caps.axis, 90) - *f90.reference_pose).norm(), 1e-12);

  // Both views land on the same box in the object frame; each sees its own side.
  auto face_counts = [&](const Frame& f, int& plus_x, int& minus_y) {
    plus_x = minus_y = 0;
    for (const auto& s : back_project(f)) {
      const Vec3d q = apply(*f.reference_pose, s.p);
      if (std::abs(q.z()) < 1e-6) continue;  // table
      EXPECT_LT(box_surface_distance(q, lo.cast<double>(), hi.cast<double>()), 1e-5);
      const bool interior_z = q.z() < hi.z() - 1e-3;
      if (std::abs(q.x() - hi.x()) < 1e-5 && interior_z && q.y() > lo.y() + 1e-3) ++plus_x;
      if (std::abs(q.y() - lo.y()) < 1e-5 && interior_z && q.x() < hi.x() - 1e-3) ++minus_y;
    }
  };
  int px0, my0, px90, my90;
  face_counts(f0, px0, my0);
  face_counts(f90, px90, my90);
  EXPECT_GT(px0, 2000);   // the camera on +x sees the +x face at 0 degrees...
  EXPECT_EQ(my0, 0);
  EXPECT_EQ(px90, 0);     // ...and, a quarter turn counter-clockwise later, the -y face
  EXPECT_GT(my90, 2000);
  // The clouds in the scanner frame differ.
  EXPECT_NE(f0.depth, f90.depth);
}

TEST(SyntheticTurntable, BenchIsSharedWhicheverDeviceComesFirst) {
  test::TempDir dir("sim-test");
  write_ply(dir / "box.ply", test::box({-0.02f, -0.02f, 0}, {0.02f, 0.02f, 0.04f}));
  DeviceRegistry reg = test::sim_registry();
  auto table = reg.make_turntable("sim:turntable?steps=360");
  table->open();
  table->rotate_to(30);
  auto scanner = reg.make_scanner("sim:synthetic?noise=0&mesh=" + (dir / "box.ply").string());
  scanner->open();
  const Frame f30 = scanner->grab();
  table->rotate_to(0);
  const Frame f0 = scanner->grab();
  EXPECT_LT((*f30.reference_pose - sim::rotate_z_deg(-30) * *f0.reference_pose).norm(), 1e-12);
  // Another registry is another bench.
  DeviceRegistry other = test::sim_registry();
  auto lone = other.make_scanner("sim:synthetic?noise=0&mesh=" + (dir / "box.ply").string());
  lone->open();
  table->rotate_to(45);
  EXPECT_LT((*lone->grab().reference_pose - *f0.reference_pose).norm(), 1e-12);
}

TEST(SyntheticPlacement, CenterAndScale) {
  test::TempDir dir("sim-test");
  // Millimetre box off the axis and floating: centre=1 puts it on the table, on the axis.
  write_ply(dir / "box.ply", test::box({100, 200, 50}, {140, 260, 90}));
  Rig rig = make_rig(dir / "box.ply", "&noise=0&scale=0.001&center=1");
  const Frame f = rig.scanner->grab();
  const Vec3d lo(0.1, 0.2, 0.05), hi(0.14, 0.26, 0.09);
  int n = 0;
  for (const auto& s : back_project(f)) {
    const Vec3d q = apply(*f.reference_pose, s.p);  // object frame: the scaled file frame
    if (box_surface_distance(q, lo, hi) < 1e-5) {
      ++n;
      continue;
    }
    // Otherwise the table top, which sits at the box's bottom (z = 0.05 here).
    EXPECT_NEAR(q.z(), 0.05, 1e-6);
    const Eigen::Vector2d on_table = q.head<2>() - Eigen::Vector2d(0.12, 0.23);
    EXPECT_LE(on_table.norm(), 0.15 + 1e-6);
  }
  EXPECT_GT(n, 2000);
  // The axis (table frame z) passes through the box's xy centre.
  const ScannerCapabilities caps = rig.scanner->capabilities();
  const Vec3d axis_point = apply(*f.reference_pose, caps.axis->point);
  EXPECT_LT((axis_point - Vec3d(0.12, 0.23, 0.05)).norm(), 1e-7);  // float mesh
}

TEST(SyntheticColour, VertexColoursAreInterpolated) {
  test::TempDir dir("sim-test");
  Mesh m = test::icosphere(4, kRadius, kCentre.cast<float>());
  for (const Vec3f& v : m.vertices)
    m.colours.push_back(v.z() > kCentre.z() ? Rgb{255, 0, 0} : Rgb{0, 0, 255});
  write_ply(dir / "c.ply", m);
  Rig rig = make_rig(dir / "c.ply", "&noise=0");
  const Frame f = rig.scanner->grab();
  int red = 0, blue = 0;
  for (const auto& s : back_project(f)) {
    const Vec3d q = apply(*f.reference_pose, s.p);
    const std::uint8_t* c = &f.colour[std::size_t(s.pixel) * 3];
    if (std::abs(q.z()) < 1e-6) continue;  // disk
    if (q.z() > kCentre.z() + 0.01) {
      EXPECT_EQ(Rgb({c[0], c[1], c[2]}), Rgb({255, 0, 0}));
      ++red;
    } else if (q.z() < kCentre.z() - 0.01) {
      EXPECT_EQ(Rgb({c[0], c[1], c[2]}), Rgb({0, 0, 255}));
      ++blue;
    } else {
      EXPECT_EQ(c[1], 0);  // a blend of red and blue near the equator
      EXPECT_EQ(int(c[0]) + int(c[2]), 255);
    }
  }
  EXPECT_GT(red, 1000);
  EXPECT_GT(blue, 1000);
}

TEST(SyntheticColour, ColourNoiseHasTheRequestedSigma) {
  test::TempDir dir("sim-test");
  write_ply(dir / "s.ply", test::icosphere(4, kRadius, kCentre.cast<float>()));
  Rig rig = make_rig(dir / "s.ply", "&noise=0&color_noise=4");
  const Frame f = rig.scanner->grab();
  double sum = 0, sum2 = 0;
  int n = 0;
  for (const auto& s : back_project(f)) {
    const Vec3d q = apply(*f.reference_pose, s.p);
    if (std::abs(q.z()) < 1e-6) continue;
    for (int ch = 0; ch < 3; ++ch) {
      const double r = double(f.colour[std::size_t(s.pixel) * 3 + ch]) - 200.0;
      sum += r;
      sum2 += r * r;
      ++n;
    }
  }
  ASSERT_GT(n, 10000);
  EXPECT_NEAR(sum / n, 0.0, 0.1);
  EXPECT_NEAR(std::sqrt(sum2 / n), std::sqrt(16.0 + 1.0 / 12), 0.1);  // + rounding
}

TEST(SyntheticColour, TextureSampling) {
  Texture t;
  t.width = 4;
  t.height = 2;
  // Row 0 (top): red red green green; row 1: blue blue white white.
  const Rgb px[2][4] = {{{255, 0, 0}, {255, 0, 0}, {0, 255, 0}, {0, 255, 0}},
                        {{0, 0, 255}, {0, 0, 255}, {255, 255, 255}, {255, 255, 255}}};
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 4; ++c) {
      t.rgb.push_back(px[r][c].r);
      t.rgb.push_back(px[r][c].g);
      t.rgb.push_back(px[r][c].b);
    }
  // Texel centres: u = (i + 0.5) / 4, v = 1 - (j + 0.5) / 2.
  EXPECT_EQ(sample_texture(t, 0.125, 0.75), Rgb({255, 0, 0}));
  EXPECT_EQ(sample_texture(t, 0.875, 0.75), Rgb({0, 255, 0}));
  EXPECT_EQ(sample_texture(t, 0.125, 0.25), Rgb({0, 0, 255}));
  EXPECT_EQ(sample_texture(t, 0.875, 0.25), Rgb({255, 255, 255}));
  // Corners clamp to the edge texels; outside [0, 1] repeats.
  EXPECT_EQ(sample_texture(t, 0.0, 1.0), Rgb({255, 0, 0}));
  EXPECT_EQ(sample_texture(t, 1.0, 0.0), Rgb({255, 255, 255}));
  EXPECT_EQ(sample_texture(t, 1.125, -0.75), Rgb({0, 0, 255}));
  EXPECT_EQ(sample_texture(t, -0.125, 1.75), Rgb({0, 255, 0}));
  // Bilinear halfway between red and green texels.
  EXPECT_EQ(sample_texture(t, 0.5, 0.75), Rgb({128, 128, 0}));
  // Non-finite coordinates do not crash.
  sample_texture(t, std::nan(""), INFINITY);
  EXPECT_EQ(sample_texture(Texture{}, 0.5, 0.5), Rgb{});
}

TEST(SyntheticColour, ObjTextureIsSampledThroughUvs) {
  test::TempDir dir("sim-test");
  // 16x16 texture, quadrants: top-left red, top-right green, bottom-left blue,
  // bottom-right yellow (OpenCV writes BGR).
  cv::Mat img(16, 16, CV_8UC3);
  for (int r = 0; r < 16; ++r)
    for (int c = 0; c < 16; ++c) {
      cv::Vec3b bgr = r < 8 ? (c < 8 ? cv::Vec3b(0, 0, 255) : cv::Vec3b(0, 255, 0))
                            : (c < 8 ? cv::Vec3b(255, 0, 0) : cv::Vec3b(0, 255, 255));
      img.at<cv::Vec3b>(r, c) = bgr;
    }
  ASSERT_TRUE(cv::imwrite((dir / "tex.png").string(), img));
  {
    std::ofstream(dir / "quad.mtl") << "newmtl m\nmap_Kd tex.png\n";
    // A 10 cm square standing in the plane x = 0, facing the camera (+x);
    // u runs along +y, v along +z.
    std::ofstream(dir / "quad.obj") << "mtllib quad.mtl\nusemtl m\n"
                                       "v 0 -0.05 0\nv 0 0.05 0\nv 0 0.05 0.1\nv 0 -0.05 0.1\n"
                                       "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
                                       "f 1/1 2/2 3/3\nf 1/1 3/3 4/4\n";
  }
  Rig rig = make_rig(dir / "quad.obj", "&noise=0");
  const Frame f = rig.scanner->grab();
  int counts[4] = {0, 0, 0, 0};
  for (const auto& s : back_project(f)) {
    const Vec3d q = apply(*f.reference_pose, s.p);
    if (std::abs(q.x()) > 1e-6) continue;  // the table
    const Rgb c{f.colour[std::size_t(s.pixel) * 3], f.colour[std::size_t(s.pixel) * 3 + 1],
                f.colour[std::size_t(s.pixel) * 3 + 2]};
    const bool left = q.y() < -0.005, right = q.y() > 0.005;
    const bool top = q.z() > 0.055, bottom = q.z() < 0.045;
    if (top && left) {
      EXPECT_EQ(c, Rgb({255, 0, 0}));
      ++counts[0];
    } else if (top && right) {
      EXPECT_EQ(c, Rgb({0, 255, 0}));
      ++counts[1];
    } else if (bottom && left) {
      EXPECT_EQ(c, Rgb({0, 0, 255}));
      ++counts[2];
    } else if (bottom && right) {
      EXPECT_EQ(c, Rgb({255, 255, 0}));
      ++counts[3];
    }
  }
  for (int k = 0; k < 4; ++k) EXPECT_GT(counts[k], 1000) << k;
  // And the quadrants appear where a camera on +x sees them: u (object +y) to
  // the image right, v (up) to the image top.
  const Intrinsics& k = f.intrinsics;
  auto colour_at = [&](int u, int v) {
    const std::uint8_t* p = &f.colour[(std::size_t(v) * k.width + u) * 3];
    return Rgb{p[0], p[1], p[2]};
  };
  int u_left = -1, v_top = -1;
  for (int u = 0; u < k.width && u_left < 0; ++u)
    for (int v = 0; v < k.height; ++v)
      if (colour_at(u, v) == Rgb({255, 0, 0})) {
        u_left = u;
        v_top = v;
        break;
      }
  ASSERT_GE(u_left, 0);
  EXPECT_LT(u_left, k.width / 2);
  EXPECT_LT(v_top, k.height / 2);
}

TEST(SyntheticOptions, ParsesEveryKey) {
  const DeviceOptions o = {{"mesh", "a.ply"},          {"scale", "0.001"},   {"center", "true"},
                           {"width", "320"},           {"height", "240"},    {"fov_deg", "60"},
                           {"distance", "0.5"},        {"elevation_deg", "-10"},
                           {"target_height", "0.1"},   {"noise", "0.002"},   {"noise_quadratic", "0.1"},
                           {"dropout", "0.5"},         {"color_noise", "3"}, {"table_radius", "0.2"},
                           {"max_range", "2"},         {"seed", "4000000000"}, {"color", "off"}};
  const SyntheticParams p = synthetic_params_from_options(o, "sim:synthetic");
  EXPECT_EQ(p.mesh, "a.ply");
  EXPECT_EQ(p.scale, 0.001);
  EXPECT_TRUE(p.center);
  EXPECT_EQ(p.width, 320);
  EXPECT_EQ(p.height, 240);
  EXPECT_EQ(p.fov_deg, 60);
  EXPECT_EQ(p.distance, 0.5);
  EXPECT_EQ(p.elevation_deg, -10);
  EXPECT_EQ(p.target_height, 0.1);
  EXPECT_EQ(p.noise, 0.002);
  EXPECT_EQ(p.noise_quadratic, 0.1);
  EXPECT_EQ(p.dropout, 0.5);
  EXPECT_EQ(p.colour_noise, 3);
  EXPECT_EQ(p.table_radius, 0.2);
  EXPECT_EQ(p.max_range, 2);
  EXPECT_EQ(p.seed, 4000000000u);
  EXPECT_FALSE(p.colour);
  const SyntheticParams d = synthetic_params_from_options({}, "sim:synthetic");
  EXPECT_EQ(d.width, 640);
  EXPECT_FALSE(d.center);
}

TEST(SyntheticOptions, BadOptionsNameTheUriAndKey) {
  auto message = [](const DeviceOptions& o) -> std::string {
    try {
      synthetic_params_from_options(o, "sim:synthetic?x");
    } catch (const DeviceError& e) {
      return e.what();
    }
    return "(no error)";
  };
  EXPECT_NE(message({{"nosie", "1"}}).find("sim:synthetic?x: unknown option 'nosie'"),
            std::string::npos);
  for (auto [key, value] :
       std::vector<std::pair<std::string, std::string>>{{"noise", "abc"},
                                                        {"noise", "-1"},
                                                        {"noise", "nan"},
                                                        {"scale", "0"},
                                                        {"width", "0"},
                                                        {"width", "12.5"},
                                                        {"height", ""},
                                                        {"fov_deg", "180"},
                                                        {"elevation_deg", "90"},
                                                        {"dropout", "1.5"},
                                                        {"seed", "-1"},
                                                        {"seed", "99999999999"},
                                                        {"center", "maybe"},
                                                        {"max_range", "inf"},
                                                        {"distance", "1e999"}}) {
    const std::string m = message({{key, value}});
    EXPECT_NE(m.find("sim:synthetic?x: option '" + key + "'"), std::string::npos) << m;
  }
  // Through the registry and configure() as well.
  DeviceRegistry reg = test::sim_registry();
  EXPECT_THROW(reg.make_scanner("sim:synthetic?bogus=1"), DeviceError);
  auto s = reg.make_scanner("sim:synthetic?mesh=x.ply");
  EXPECT_THROW(s->configure({{"bogus", "1"}}), DeviceError);
  EXPECT_THROW(s->configure({{"width", "wide"}}), DeviceError);
}

TEST(SyntheticErrors, MissingMeshAndGrabBeforeOpen) {
  DeviceRegistry reg = test::sim_registry();
  auto s = reg.make_scanner("sim:synthetic?mesh=/nonexistent/dir/thing.ply");
  EXPECT_THROW(s->grab(), DeviceError);
  try {
    s->open();
    FAIL() << "open() should throw";
  } catch (const DeviceError& e) {
    EXPECT_NE(std::string(e.what()).find("/nonexistent/dir/thing.ply"), std::string::npos);
  }
  EXPECT_THROW(reg.make_scanner("sim:synthetic")->open(), DeviceError);
  // A file that is not a mesh: still a DeviceError naming it.
  test::TempDir dir("sim-test");
  std::ofstream(dir / "junk.ply") << "not a ply\n";
  auto j = reg.make_scanner("sim:synthetic?mesh=" + (dir / "junk.ply").string());
  try {
    j->open();
    FAIL() << "open() should throw";
  } catch (const DeviceError& e) {
    EXPECT_NE(std::string(e.what()).find("junk.ply"), std::string::npos) << e.what();
  }
  // An OBJ whose material library is missing: every view would come out uncoloured.
  std::ofstream(dir / "lost.obj") << "mtllib lost.mtl\nv 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n";
  auto lost = reg.make_scanner("sim:synthetic?mesh=" + (dir / "lost.obj").string());
  try {
    lost->open();
    FAIL() << "open() should throw";
  } catch (const DeviceError& e) {
    EXPECT_NE(std::string(e.what()).find("lost.obj: its material library 'lost.mtl' could not be read"),
              std::string::npos)
        << e.what();
  }
}

TEST_F(SyntheticSphere, ConfigureWhileOpen) {
  Rig rig = make_rig(sphere(), "&noise=0");
  rig.scanner->configure({{"width", "64"}, {"height", "48"}, {"color", "0"}});
  const Frame f = rig.scanner->grab();
  EXPECT_EQ(f.depth.size(), 64u * 48u);
  EXPECT_FALSE(f.has_colour());
  EXPECT_EQ(rig.scanner->capabilities().intrinsics.width, 64);
  EXPECT_FALSE(rig.scanner->capabilities().colour);
  // A new mesh reloads the scene at once; a missing one fails and leaves the
  // scanner as it was.
  EXPECT_THROW(rig.scanner->configure({{"mesh", "/nonexistent.ply"}}), DeviceError);
  EXPECT_EQ(rig.scanner->grab().depth, f.depth);
}

TEST_F(SyntheticSphere, AxisKnownBeforeOpenWithAnExplicitTarget) {
  DeviceRegistry reg = test::sim_registry();
  auto automatic = reg.make_scanner("sim:synthetic?mesh=" + sphere().string());
  EXPECT_FALSE(automatic->capabilities().axis);  // aims at the mesh's mid-height: needs the mesh
  auto s = reg.make_scanner("sim:synthetic?target_height=0.05&mesh=" + sphere().string());
  const auto before = s->capabilities().axis;
  ASSERT_TRUE(before);
  s->open();
  automatic->open();
  const auto after = s->capabilities().axis;
  EXPECT_LT((before->point - after->point).norm(), 1e-15);
  EXPECT_LT((before->direction - after->direction).norm(), 1e-15);
  // Mid-height of this sphere is 0.05 too, up to float rounding.
  EXPECT_LT((automatic->capabilities().axis->point - after->point).norm(), 1e-8);
}

TEST(SyntheticTiming, FullViewOfA330kFaceMesh) {
  test::TempDir dir("sim-test");
  const Mesh m = test::icosphere(7, 0.08, Vec3f(0, 0, 0.08f));
  write_ply(dir / "big.ply", m);
  const auto t0 = std::chrono::steady_clock::now();
  Rig rig = make_rig(dir / "big.ply", "&noise=0.0005&dropout=0.01&color_noise=2");
  const auto t1 = std::chrono::steady_clock::now();
  Frame f = rig.scanner->grab();
  const auto t2 = std::chrono::steady_clock::now();
  for (int i = 0; i < 3; ++i) f = rig.scanner->grab();
  const auto t3 = std::chrono::steady_clock::now();
  std::size_t valid = 0;
  for (float z : f.depth) valid += z > 0;
  auto ms = [](auto a, auto b) { return std::chrono::duration<double, std::milli>(b - a).count(); };
  std::printf("[ timing ] %zu faces: open (read + BVH) %.0f ms, 640x480 grab %.0f ms (first), "
              "%.0f ms (mean of 3 more); %zu valid pixels\n",
              m.faces.size(), ms(t0, t1), ms(t1, t2), ms(t2, t3) / 3, valid);
  EXPECT_GT(valid, 50000u);
}

}  // namespace
}  // namespace station

namespace station {
namespace {

TEST(SyntheticBundled, MustardBottleTextureAndTruth) {
  const auto obj = test::source_dir() / "data" / "mustard_bottle" / "textured.obj";
  if (!std::filesystem::exists(obj)) GTEST_SKIP() << "bundled sample missing";
  const auto t0 = std::chrono::steady_clock::now();
  Rig rig = make_rig(obj, "&noise=0", /*with_turntable=*/true);
  const auto t1 = std::chrono::steady_clock::now();
  rig.turntable->rotate_to(135);
  const Frame f = rig.scanner->grab();
  const auto t2 = std::chrono::steady_clock::now();
  std::printf("[ timing ] mustard bottle: open %.0f ms, grab %.0f ms\n",
              std::chrono::duration<double, std::milli>(t1 - t0).count(),
              std::chrono::duration<double, std::milli>(t2 - t1).count());
  // Object points (above the table) lie on the mesh in its own frame, and carry
  // the texture's colours rather than the default grey.
  const TriangleBvh bvh(read_mesh(obj));
  int object = 0, yellow = 0;
  for (const auto& s : back_project(f)) {
    const Vec3d q = apply(*f.reference_pose, s.p);
    if (std::abs(q.z()) < 1e-6) continue;
    ++object;
    EXPECT_LT(bvh.closest_point(q).distance, 1e-5);
    const std::uint8_t* c = &f.colour[std::size_t(s.pixel) * 3];
    yellow += c[0] > 150 && c[1] > 120 && c[2] < 100;
  }
  EXPECT_GT(object, 5000);
  EXPECT_GT(yellow, object / 3);
}

}  // namespace
}  // namespace station
