#include "drivers/real_devices.h"

#include <algorithm>
#include <filesystem>

#include "drivers/fabscan_turntable.h"
#include "drivers/horus_turntable.h"
#include "drivers/kinect_scanner.h"
#include "drivers/openni_scanner.h"
#include "drivers/v4l2_camera.h"

namespace station {

std::vector<std::string> serial_port_paths() {
  std::vector<std::string> paths;
  std::error_code ec;
  for (const auto& entry : std::filesystem::directory_iterator("/dev", ec)) {
    const std::string name = entry.path().filename().string();
    if (name.rfind("ttyUSB", 0) == 0 || name.rfind("ttyACM", 0) == 0)
      paths.push_back(entry.path().string());
  }
  std::sort(paths.begin(), paths.end());
  return paths;
}

void register_serial_turntables(DeviceRegistry& registry) {
  registry.add_turntable(
      "horus:",
      [](const DeviceUri& uri, DeviceContext&) -> std::unique_ptr<Turntable> {
        return std::make_unique<HorusTurntable>(
            uri.text, uri.path, horus_options(uri.options, uri.text), make_posix_serial_port());
      },
      [] {
        std::vector<DeviceInfo> out;
        for (const auto& p : serial_port_paths())
          out.push_back({"horus:" + p, DeviceKind::kTurntable,
                         "serial port (Ciclop/Horus board if it answers the banner; not probed)",
                         true});
        return out;
      });
  registry.add_turntable(
      "fabscan:",
      [](const DeviceUri& uri, DeviceContext&) -> std::unique_ptr<Turntable> {
        return std::make_unique<FabScanTurntable>(
            uri.text, uri.path, fabscan_options(uri.options, uri.text), make_posix_serial_port());
      },
      [] {
        std::vector<DeviceInfo> out;
        for (const auto& p : serial_port_paths())
          out.push_back({"fabscan:" + p, DeviceKind::kTurntable,
                         "serial port (FabScan board if it answers the ping; not probed)", true});
        return out;
      });
}

void register_v4l2_cameras(DeviceRegistry& registry, std::shared_ptr<SysCalls> sys) {
  register_v4l2_camera(registry, std::move(sys));
}

void register_real_devices(DeviceRegistry& registry) {
  register_serial_turntables(registry);
  register_v4l2_cameras(registry, real_syscalls());
#ifdef STATION_HAVE_FREENECT
  // Kinect v1 through libfreenect (kinect:N); listed by freenect_num_devices.
  register_kinect(registry, [] { return make_libfreenect_api(); });
#endif
#ifdef STATION_HAVE_OPENNI2
  // OpenNI2 depth cameras (openni:N or openni:<OpenNI2 URI>); listed by enumerateDevices.
  register_openni(registry, [] { return make_openni2_api(); });
#endif
}

}  // namespace station
