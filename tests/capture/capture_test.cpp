#include "capture/capture.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include "core/error.h"
#include "core/io.h"
#include "test_util.h"

namespace station {
namespace {

// A bench whose axis stands 0.45 m in front of the scanner, 0.1 m below it.
TurntableAxis bench_axis() {
  TurntableAxis a;
  a.point = Vec3d(0, 0.1, 0.45);
  a.direction = Vec3d(0, -1, 0);
  return a;
}

class FakeTurntable : public Turntable {
 public:
  void open() override {}
  void close() override {}
  void home() override { angle_ = 0; ++homes; }
  void rotate_to(double d) override { angle_ = d; }
  double angle() const override { return angle_; }
  int steps_per_revolution() const override { return 3600; }
  std::string uri() const override { return "fake:table"; }
  int homes = 0;

 private:
  double angle_ = 0;
};

// Sees a fixed object (points in the object frame) through the turntable prior,
// so merging by turntable must give the object back exactly.
class FakeScanner : public Scanner {
 public:
  FakeScanner(const FakeTurntable& table, std::vector<Vec3f> object)
      : table_(table), object_(std::move(object)) {}
  void open() override {}
  void close() override {}
  void configure(const DeviceOptions&) override {}
  ScannerCapabilities capabilities() const override {
    ScannerCapabilities c;
    c.points = true;
    c.axis = bench_axis();
    return c;
  }
  Frame grab() override {
    if (unplug_at >= 0 && grabs == unplug_at) throw DeviceError("fake:scanner: unplugged");
    ++grabs;
    Frame f;
    const Eigen::Matrix4d pose = turntable_pose(bench_axis(), table_.angle());
    const Eigen::Matrix4d inv = pose.inverse();
    for (const Vec3f& p : object_)
      f.points.points.push_back((inv * p.cast<double>().homogeneous()).head<3>().cast<float>());
    f.timestamp = 1.0e9 + grabs;
    f.reference_pose = pose;
    return f;
  }
  std::string uri() const override { return "fake:scanner"; }
  int grabs = 0;
  int unplug_at = -1;

 private:
  const FakeTurntable& table_;
  std::vector<Vec3f> object_;
};

std::vector<Vec3f> object_points() {
  // Points on a small sphere standing on the table (object frame: z up).
  std::vector<Vec3f> pts;
  for (const Vec3f& v : test::icosphere(2, 0.03, Vec3f(0.01f, -0.005f, 0.04f)).vertices) pts.push_back(v);
  return pts;
}

TEST(TurntablePose, MapsAxisAndScannerWhereExpected) {
  const TurntableAxis a = bench_axis();
  const Eigen::Matrix4d T = table_from_scanner(a);
  // The axis point is the table origin; the scanner is on +x, above the table.
  EXPECT_LT((T * Eigen::Vector4d(0, 0.1, 0.45, 1)).head<3>().norm(), 1e-12);
  const Vec3d s = (T * Eigen::Vector4d(0, 0, 0, 1)).head<3>();
  EXPECT_NEAR(s.x(), 0.45, 1e-12);
  EXPECT_NEAR(s.y(), 0.0, 1e-12);
  EXPECT_NEAR(s.z(), 0.1, 1e-12);
  // A point 5 cm up the axis stays on the axis at every angle.
  for (double ang : {0.0, 30.0, 275.0}) {
    const Vec3d q = (turntable_pose(a, ang) * Eigen::Vector4d(0, 0.05, 0.45, 1)).head<3>();
    EXPECT_NEAR(q.head<2>().norm(), 0, 1e-12);
    EXPECT_NEAR(q.z(), 0.05, 1e-12);
  }
  // Rotating the table by +90 deg (counter-clockwise from above) brings the
  // object's +x side to face +y: the scanner (on +x) then sees the object's -y side.
  const Vec3d front = (turntable_pose(a, 90) * Eigen::Vector4d(0, 0, 0, 1)).head<3>();
  EXPECT_NEAR(front.x(), 0, 1e-12);
  EXPECT_NEAR(front.y(), -0.45, 1e-12);
}

TEST(FrameToCloud, BackProjectsDepthWithSensorFacingNormals) {
  Frame f;
  f.intrinsics = {8, 6, 10, 10, 3.5, 2.5};
  f.depth.assign(48, 2.0f);
  f.depth[0] = 0;                                   // no return
  f.depth[1] = std::numeric_limits<float>::quiet_NaN();  // broken pixel
  f.colour_intrinsics = f.intrinsics;
  f.colour.assign(48 * 3, 7);
  const Cloud c = frame_to_cloud(f);
  ASSERT_EQ(c.size(), 46u);
  ASSERT_TRUE(c.has_normals());
  ASSERT_TRUE(c.has_colours());
  for (std::size_t i = 0; i < c.size(); ++i) {
    EXPECT_FLOAT_EQ(c.points[i].z(), 2.0f);
    EXPECT_NEAR(c.normals[i].z(), -1.0f, 1e-5);
    EXPECT_EQ(c.colours[i].g, 7);
  }
  // Pixel (u=7, v=5): x = (7 - 3.5) * 2 / 10.
  EXPECT_NEAR(c.points.back().x(), 0.7f, 1e-6);
  EXPECT_NEAR(c.points.back().y(), 0.5f, 1e-6);
}

TEST(FrameToCloud, RejectsDepthWithoutIntrinsics) {
  Frame f;
  f.depth.assign(4, 1.0f);
  EXPECT_THROW(frame_to_cloud(f), InvalidInput);
}

TEST(CropToVolume, DropsTableAndBackground) {
  const TurntableAxis a = bench_axis();
  const Eigen::Matrix4d inv = table_from_scanner(a).inverse();
  auto from_table = [&](double x, double y, double z) {
    return (inv * Eigen::Vector4d(x, y, z, 1)).head<3>().cast<float>().eval();
  };
  Cloud c;
  c.points = {from_table(0, 0, 0.05), from_table(0.1, 0, 0.001), from_table(0.3, 0, 0.05),
              from_table(0, 0.05, 0.5), from_table(0.05, -0.05, 0.2)};
  const Cloud out = crop_to_volume(c, a, WorkingVolume{});
  ASSERT_EQ(out.size(), 2u);
  EXPECT_LT((out.points[0] - c.points[0]).norm(), 1e-6);
  EXPECT_LT((out.points[1] - c.points[4]).norm(), 1e-6);
}

TEST(Capture, MergeByTurntableRecoversTheObject) {
  test::TempDir dir;
  FakeTurntable table;
  FakeScanner scanner(table, object_points());
  Session s = Session::create(dir / "s", {});
  CaptureParams p;
  p.views = 8;
  const CaptureResult r = run_capture(scanner, table, s, p);
  EXPECT_EQ(r.recorded, 8);
  ASSERT_EQ(s.manifest().views.size(), 8u);
  ASSERT_TRUE(s.manifest().axis.has_value());
  EXPECT_DOUBLE_EQ(*s.manifest().views[3].angle_deg, 135.0);
  ASSERT_TRUE(s.manifest().views[3].reference_pose.has_value());
  const MergeResult m = merge_by_turntable(Session::open(dir / "s"));
  EXPECT_EQ(m.merged_views, 8);
  const auto obj = object_points();
  ASSERT_EQ(m.cloud.size(), 8 * obj.size());
  for (std::size_t i = 0; i < m.cloud.size(); ++i)
    EXPECT_LT((m.cloud.points[i] - obj[i % obj.size()]).norm(), 1e-5);
}

TEST(Capture, UnpluggedScannerThenResumeLosesNoView) {
  test::TempDir dir;
  FakeTurntable table;
  FakeScanner scanner(table, object_points());
  scanner.unplug_at = 5;
  CaptureParams p;
  p.views = 12;
  {
    Session s = Session::create(dir / "s", {});
    EXPECT_THROW(run_capture(scanner, table, s, p), DeviceError);
  }
  Session reopened = Session::open(dir / "s");
  ASSERT_EQ(reopened.manifest().views.size(), 5u);
  std::vector<std::string> before;
  for (const auto& v : reopened.manifest().views) before.push_back(read_file_bytes(dir / "s" / v.file));

  FakeScanner replugged(table, object_points());
  const CaptureResult r = run_capture(replugged, table, reopened, p);
  EXPECT_EQ(r.resumed_from, 5);
  EXPECT_EQ(r.recorded, 7);
  const Session done = Session::open(dir / "s");
  ASSERT_EQ(done.manifest().views.size(), 12u);
  for (std::size_t i = 0; i < before.size(); ++i)
    EXPECT_EQ(read_file_bytes(dir / "s" / done.manifest().views[i].file), before[i]) << i;
  for (std::size_t i = 0; i < 12; ++i) EXPECT_DOUBLE_EQ(*done.manifest().views[i].angle_deg, 30.0 * i);
  EXPECT_EQ(merge_by_turntable(done).merged_views, 12);
}

// A real turntable has no end stop: its zero after reopening is where it stands,
// so the hint says to turn it back first (the docs said "to the last view's angle",
// which offsets every resumed view); the simulated one needs no such advice.
TEST(Capture, ResumeHintAsksForTheTableAtItsStart) {
  test::TempDir dir;
  Session s = Session::create(dir / "s", {});
  FakeTurntable real;
  const std::string hint = resume_hint(s, real);
  EXPECT_EQ(hint.rfind("continue with: station scan --resume -o " + (dir / "s").string(), 0), 0u)
      << hint;
  EXPECT_NE(hint.find("turn the table back to where it stood when the scan started"),
            std::string::npos)
      << hint;
  class SimTable : public FakeTurntable {
   public:
    std::string uri() const override { return "sim:turntable?steps=3200"; }
  } sim;
  EXPECT_EQ(resume_hint(s, sim), "continue with: station scan --resume -o " + (dir / "s").string());
}

TEST(Capture, StopFlagInterruptsBetweenViewsAndResumes) {
  test::TempDir dir;
  FakeTurntable table;
  FakeScanner scanner(table, object_points());
  CaptureParams p;
  p.views = 6;
  std::atomic<bool> stop{false};
  Session s = Session::create(dir / "s", {});
  const CaptureResult r = run_capture(scanner, table, s, p, [&](const CaptureProgress& pr) {
    if (pr.view == 2) stop = true;
  }, &stop);
  EXPECT_TRUE(r.interrupted);
  EXPECT_EQ(Session::open(dir / "s").manifest().views.size(), 3u);
  stop = false;
  Session again = Session::open(dir / "s");
  EXPECT_EQ(run_capture(scanner, table, again, p).recorded, 3);
  EXPECT_EQ(Session::open(dir / "s").manifest().views.size(), 6u);
}

TEST(Capture, ResumeWithAnotherPlanIsRefused) {
  test::TempDir dir;
  FakeTurntable table;
  FakeScanner scanner(table, object_points());
  scanner.unplug_at = 2;
  CaptureParams p;
  p.views = 12;
  Session s = Session::create(dir / "s", {});
  EXPECT_THROW(run_capture(scanner, table, s, p), DeviceError);
  Session again = Session::open(dir / "s");
  p.views = 10;
  EXPECT_THROW(run_capture(scanner, table, again, p), InvalidInput);
}

TEST(Capture, MergeNeedsAnAxis) {
  test::TempDir dir;
  Session s = Session::create(dir / "s", {});
  EXPECT_THROW(merge_by_turntable(s), InvalidInput);
}

}  // namespace
}  // namespace station
