#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <filesystem>

#include "capture/session.h"
#include "core/error.h"
#include "sim/sim.h"
#include "sim_test_util.h"
#include "test_util.h"

namespace station {
namespace {

Cloud tagged_cloud(int tag) {
  Cloud c;
  for (int i = 0; i <= tag; ++i) c.points.push_back(Vec3f(float(tag), float(i), 0.5f));
  return c;
}

Eigen::Matrix4d pose_of(int tag) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.topLeftCorner<3, 3>() = Eigen::AngleAxisd(0.1 * tag, Vec3d::UnitZ()).matrix();
  T(0, 3) = tag;
  return T;
}

// Four views at 0, 90, 180, 270 degrees; view 1 has a 4x2 colour image.
void record(const std::filesystem::path& dir) {
  SessionManifest m;
  m.scanner = "sim:synthetic";
  Intrinsics k;
  k.width = 4;
  k.height = 2;
  k.fx = k.fy = 3;
  k.cx = 1.5;
  k.cy = 0.5;
  m.intrinsics = k;
  TurntableAxis axis;
  axis.point = Vec3d(0, 0.1, 0.45);
  m.axis = axis;
  Session s = Session::create(dir, m);
  for (int i = 0; i < 4; ++i) {
    ViewRecord r;
    r.angle_deg = 90.0 * i;
    r.reference_pose = pose_of(i);
    r.timestamp = 1.7e9 + i;
    std::vector<std::uint8_t> rgb;
    if (i == 1)
      for (int p = 0; p < 8; ++p) rgb.insert(rgb.end(), {std::uint8_t(p * 30), 7, 200});
    s.add_view(tagged_cloud(i), r, rgb, rgb.empty() ? 0 : 4, rgb.empty() ? 0 : 2);
  }
}

TEST(SimReplay, PlaysTheViewsInOrderThenStops) {
  test::TempDir dir("sim-replay");
  record(dir.path());
  DeviceRegistry reg = test::sim_registry();
  const std::string uri = "sim:replay?session=" + dir.path().string();
  auto s = reg.make_scanner(uri);
  EXPECT_THROW(s->grab(), DeviceError);
  s->open();
  const ScannerCapabilities caps = s->capabilities();
  EXPECT_TRUE(caps.points);
  EXPECT_FALSE(caps.depth);
  EXPECT_TRUE(caps.colour);
  ASSERT_TRUE(caps.axis);
  EXPECT_EQ(caps.axis->point, Vec3d(0, 0.1, 0.45));
  EXPECT_EQ(caps.intrinsics.width, 4);
  for (int i = 0; i < 4; ++i) {
    const Frame f = s->grab();
    EXPECT_EQ(f.points.points, tagged_cloud(i).points) << i;
    ASSERT_TRUE(f.reference_pose);
    EXPECT_LT((*f.reference_pose - pose_of(i)).norm(), 1e-12);
    EXPECT_DOUBLE_EQ(f.timestamp, 1.7e9 + i);
    if (i == 1) {
      ASSERT_EQ(f.colour.size(), 24u);
      EXPECT_EQ(f.colour[3], 30);  // RGB order survives the PNG round trip
      EXPECT_EQ(f.colour[4], 7);
      EXPECT_EQ(f.colour[5], 200);
      EXPECT_TRUE(f.colour_intrinsics.valid());
      EXPECT_EQ(f.colour_intrinsics.fx, 3);
    } else {
      EXPECT_FALSE(f.has_colour());
    }
  }
  try {
    s->grab();
    FAIL() << "expected the end of the recording";
  } catch (const DeviceError& e) {
    EXPECT_EQ(std::string(e.what()), uri + ": no more views (4 recorded)");
  }
  // Reopening starts again.
  s->close();
  s->open();
  EXPECT_EQ(s->grab().points.points, tagged_cloud(0).points);
}

TEST(SimReplay, FollowsTheTurntableOnceItMoves) {
  test::TempDir dir("sim-replay");
  record(dir.path());
  DeviceRegistry reg = test::sim_registry();
  auto s = reg.make_scanner("sim:replay?session=" + dir.path().string());
  auto t = reg.make_turntable("sim:turntable");
  s->open();
  t->open();
  t->rotate_to(180);
  EXPECT_EQ(s->grab().points.points, tagged_cloud(2).points);
  t->rotate_to(265);
  EXPECT_EQ(s->grab().points.points, tagged_cloud(3).points);
  t->rotate_to(350);  // closest (circularly) to 0
  EXPECT_EQ(s->grab().points.points, tagged_cloud(0).points);
  EXPECT_EQ(s->grab().points.points, tagged_cloud(0).points);  // the table did not move
  t->home();
  EXPECT_EQ(s->grab().points.points, tagged_cloud(0).points);
}

TEST(SimReplay, Errors) {
  DeviceRegistry reg = test::sim_registry();
  EXPECT_THROW(reg.make_scanner("sim:replay"), DeviceError);
  EXPECT_THROW(reg.make_scanner("sim:replay?session=x&speed=2"), DeviceError);
  auto s = reg.make_scanner("sim:replay?session=/nonexistent/session");
  try {
    s->open();
    FAIL() << "expected DeviceError";
  } catch (const DeviceError& e) {
    EXPECT_NE(std::string(e.what()).find("/nonexistent/session"), std::string::npos) << e.what();
  }
  // A session without views is at its end at once.
  test::TempDir dir("sim-replay");
  Session::create(dir.path(), SessionManifest{});
  auto empty = reg.make_scanner("sim:replay?session=" + dir.path().string());
  empty->open();
  EXPECT_THROW(empty->grab(), DeviceError);
}

}  // namespace
}  // namespace station
