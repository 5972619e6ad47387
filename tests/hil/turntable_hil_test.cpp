// Serial turntables on the bench: a Horus board (banner after Ctrl-X) or a
// FabScan board (pong to the ping). Moves the table and reads the angle back,
// then records a short session with the camera when one is there.
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <memory>

#include "capture/capture.h"
#include "core/error.h"
#include "drivers/fabscan_turntable.h"
#include "drivers/horus_turntable.h"
#include "drivers/real_devices.h"
#include "drivers/v4l2_camera.h"
#include "drivers/v4l2_probe.h"
#include "hil_common.h"
#include "test_util.h"

namespace station {
namespace {

std::vector<std::string> ports() {
  const std::string list = hil::env("HIL_SERIAL_PORTS");
  if (list.empty()) return serial_port_paths();
  std::vector<std::string> out;
  std::size_t start = 0;
  while (start <= list.size()) {
    auto comma = list.find(',', start);
    if (comma == std::string::npos) comma = list.size();
    if (comma > start) out.push_back(list.substr(start, comma - start));
    start = comma + 1;
  }
  return out;
}

/// Steps from HIL_STEPS / HIL_MICROSTEPS / HIL_DIRECTION (defaults: the Ciclop's
/// 200-step motor at 1/16 microstepping, for the smoke test only).
std::string stepper_query() {
  return "steps=" + hil::env("HIL_STEPS", "200") +
         "&microsteps=" + hil::env("HIL_MICROSTEPS", "16") +
         "&direction=" + hil::env("HIL_DIRECTION", "ccw");
}

std::string find_horus(std::string& why) {
  if (!hil::serial_probing_allowed()) {
    why =
        "serial probing off (set HIL=1, HIL_REQUIRE=1 or HIL_SERIAL_PORTS to probe for a Horus "
        "board)";
    return "";
  }
  for (const auto& p : ports()) {
    try {
      auto port = make_posix_serial_port();
      port->open(p, 115200);
      LineReader reader(*port);
      const std::string banner = horus_handshake(*port, reader, p, 3000);
      std::printf("[ HIL      ] %s: %s\n", p.c_str(), banner.c_str());
      return "horus:" + p + "?" + stepper_query();
    } catch (const Error&) {
    }
  }
  why = "no Horus banner on " + std::to_string(ports().size()) + " serial ports";
  return "";
}

std::string find_fabscan(std::string& why) {
  if (!hil::serial_probing_allowed()) {
    why =
        "serial probing off (set HIL=1, HIL_REQUIRE=1 or HIL_SERIAL_PORTS to probe for a FabScan "
        "board)";
    return "";
  }
  for (const auto& p : ports()) {
    const std::string uri = "fabscan:" + p + "?" + stepper_query() + "&connect_timeout_ms=3000";
    try {
      FabScanTurntable t(uri, p, fabscan_options(parse_device_uri(uri).options, uri),
                         make_posix_serial_port());
      t.open();
      t.close();
      return uri;
    } catch (const Error&) {
    }
  }
  why = "no FabScan pong on " + std::to_string(ports().size()) + " serial ports";
  return "";
}

void move_and_read_back(Turntable& t) {
  t.open();
  t.home();
  EXPECT_DOUBLE_EQ(t.angle(), 0.0);
  const double step = 360.0 / t.steps_per_revolution();
  for (double target : {30.0, 90.0, 180.0, 270.0}) {
    const auto t0 = std::chrono::steady_clock::now();
    t.rotate_to(target);
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::printf("[ HIL      ] rotate_to(%g) -> %g degrees in %.2f s\n", target, t.angle(), s);
    EXPECT_NEAR(t.angle(), target, step / 2 + 1e-9);
  }
  t.home();
  EXPECT_DOUBLE_EQ(t.angle(), 0.0);
  t.close();
}

TEST(HilTurntable, HorusMovesAndReportsTheAngle) {
  std::string why;
  const std::string uri = find_horus(why);
  if (uri.empty()) HIL_ABSENT(why);
  const DeviceUri u = parse_device_uri(uri);
  HorusTurntable t(uri, u.path, horus_options(u.options, uri), make_posix_serial_port());
  move_and_read_back(t);
}

TEST(HilTurntable, FabScanMovesAndReportsTheAngle) {
  std::string why;
  const std::string uri = find_fabscan(why);
  if (uri.empty()) HIL_ABSENT(why);
  const DeviceUri u = parse_device_uri(uri);
  FabScanTurntable t(uri, u.path, fabscan_options(u.options, uri), make_posix_serial_port());
  move_and_read_back(t);
}

TEST(HilBench, RecordsAShortSession) {
  const std::string cam_uri = hil::env("HIL_V4L2_URI");
  if (cam_uri.empty()) HIL_ABSENT("HIL_V4L2_URI not set (a depth camera URI with intrinsics)");
  std::string why;
  std::string table_uri = hil::env("HIL_TURNTABLE_URI");
  if (table_uri.empty()) table_uri = find_horus(why);
  if (table_uri.empty()) table_uri = find_fabscan(why);
  if (table_uri.empty()) HIL_ABSENT(why);
  DeviceRegistry reg;
  register_real_devices(reg);
  auto scanner = reg.make_scanner(cam_uri);
  auto table = reg.make_turntable(table_uri);
  scanner->open();
  table->open();
  test::TempDir dir("station-hil");
  SessionManifest m;
  m.scanner = cam_uri;
  m.turntable = table_uri;
  m.planned_views = 3;
  Session session = Session::create(dir / "session", m);
  CaptureParams params;
  params.views = 3;
  params.crop = false;
  const CaptureResult r = run_capture(*scanner, *table, session, params);
  EXPECT_EQ(r.recorded, 3);
  const Session again = Session::open(dir / "session");
  ASSERT_EQ(again.manifest().views.size(), 3u);
  for (std::size_t i = 0; i < 3; ++i) {
    ASSERT_TRUE(again.manifest().views[i].angle_deg.has_value());
    EXPECT_NEAR(*again.manifest().views[i].angle_deg, 120.0 * i,
                360.0 / table->steps_per_revolution());
  }
  std::printf("[ HIL      ] session: %zu points in %.1f s\n", r.points, r.seconds);
  table->home();
}

}  // namespace
}  // namespace station
