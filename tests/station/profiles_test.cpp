// Every shipped profile (config/*.yaml) loads, and its device options are ones
// the drivers accept (the devices are made from the URIs, not opened).
#include <gtest/gtest.h>

#include "core/error.h"
#include "drivers/real_devices.h"
#include "drivers/registry.h"
#include "sim/sim.h"
#include "station/config.h"
#include "test_util.h"

namespace station {
namespace {

namespace fs = std::filesystem;

TEST(Profiles, EveryShippedProfileLoadsAndNamesDevicesTheDriversAccept) {
  int n = 0;
  for (const auto& e : fs::directory_iterator(test::source_dir() / "config")) {
    if (e.path().extension() != ".yaml") continue;
    ++n;
    SCOPED_TRACE(e.path().string());
    StationConfig cfg;
    ASSERT_NO_THROW(cfg = load_config(e.path()));
    DeviceRegistry reg;
    register_sim_devices(reg);
    register_real_devices(reg);
    EXPECT_NO_THROW(reg.make_scanner(compose_uri(cfg.scanner_uri, cfg.scanner_options)));
    EXPECT_NO_THROW(reg.make_turntable(compose_uri(cfg.turntable_uri, cfg.turntable_options)));
  }
  EXPECT_GE(n, 3);  // default + one per real bench kind
}

TEST(Profiles, AWrongDeviceOptionIsCaughtByTheDriver) {
  DeviceRegistry reg;
  register_real_devices(reg);
  EXPECT_THROW(reg.make_turntable("horus:/dev/ttyUSB0?steps=200&stepz=3"), DeviceError);
  EXPECT_THROW(reg.make_scanner("v4l2:auto?fx=1&fy=1&cx=1&cy=1&distortion=1"), DeviceError);
}

}  // namespace
}  // namespace station
