#include "drivers/real_devices.h"

#include <gtest/gtest.h>

#include "core/error.h"

namespace station {
namespace {

std::string message(const std::function<void()>& f) {
  try {
    f();
  } catch (const DeviceError& e) {
    return e.what();
  }
  return "(no DeviceError)";
}

TEST(RealDevices, SerialTurntablesByUri) {
  DeviceRegistry reg;
  register_real_devices(reg);
  auto horus = reg.make_turntable("horus:/dev/ttyUSB-station-test?steps=200&microsteps=16");
  EXPECT_EQ(horus->uri(), "horus:/dev/ttyUSB-station-test?steps=200&microsteps=16");
  EXPECT_EQ(horus->steps_per_revolution(), 3200);
  EXPECT_EQ(message([&] { horus->open(); }),
            "/dev/ttyUSB-station-test: no such serial port (unplugged?)");
  auto fab = reg.make_turntable("fabscan:/dev/ttyACM-station-test?steps=400&microsteps=8");
  EXPECT_EQ(fab->steps_per_revolution(), 3200);
  EXPECT_NE(message([&] { reg.make_turntable("fabscan:/dev/ttyACM0"); }).find("'steps'"),
            std::string::npos);
  EXPECT_NE(
      message([&] { reg.make_scanner("horus:/dev/ttyUSB0?steps=200"); }).find("unknown scanner"),
      std::string::npos);
  // A scheme the station has no driver for names the ones it has, attached or not.
  const std::string unknown = message([&] { reg.make_turntable("serial:/dev/ttyUSB0"); });
  EXPECT_NE(unknown.find("serial:/dev/ttyUSB0: unknown turntable (supported: horus:..., "
                         "fabscan:...; attached now: "),
            std::string::npos)
      << unknown;
}

TEST(RealDevices, ListsWithoutOpeningSerialPorts) {
  DeviceRegistry reg;
  register_real_devices(reg);
  const auto paths = serial_port_paths();
  std::size_t turntables = 0;
  for (const auto& d : reg.list())
    if (d.kind == DeviceKind::kTurntable) ++turntables;
  EXPECT_EQ(turntables, 2 * paths.size());  // each port as horus: and fabscan:
}

}  // namespace
}  // namespace station
