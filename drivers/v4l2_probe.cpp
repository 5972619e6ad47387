#include "drivers/v4l2_probe.h"

#include <fcntl.h>
#include <linux/videodev2.h>

#include <cstring>
#include <filesystem>

namespace station {

std::vector<DeviceInfo> probe_v4l2(SysCalls& sys, const std::vector<std::string>& paths) {
  std::vector<DeviceInfo> found;
  for (const std::string& path : paths) {
    const int fd = sys.open(path.c_str(), O_RDWR | O_NONBLOCK);
    if (fd < 0) continue;
    v4l2_capability cap;
    std::memset(&cap, 0, sizeof cap);
    const int r = sys.ioctl(fd, VIDIOC_QUERYCAP, &cap);
    sys.close(fd);
    if (r < 0) continue;
    const std::uint32_t caps =
        (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
    if (!(caps & (V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_VIDEO_CAPTURE_MPLANE))) continue;
    // The kernel's strings are fixed-size and may lack a terminator.
    const std::string card(reinterpret_cast<const char*>(cap.card),
                           strnlen(reinterpret_cast<const char*>(cap.card), sizeof cap.card));
    const std::string driver(reinterpret_cast<const char*>(cap.driver),
                             strnlen(reinterpret_cast<const char*>(cap.driver), sizeof cap.driver));
    DeviceInfo info{"v4l2:" + path, DeviceKind::kScanner,
                    card + " (" + driver + "); V4L2 capture back-end not built yet", false};
    found.push_back(info);
  }
  return found;
}

std::vector<std::string> v4l2_device_paths() {
  std::vector<std::string> paths;
  for (int i = 0; i < 64; ++i) {
    const std::string p = "/dev/video" + std::to_string(i);
    std::error_code ec;
    if (std::filesystem::exists(p, ec)) paths.push_back(p);
  }
  return paths;
}

void register_v4l2_probe(DeviceRegistry& registry, std::shared_ptr<SysCalls> sys) {
  registry.add_scanner("v4l2:", nullptr, [sys] { return probe_v4l2(*sys, v4l2_device_paths()); });
}

}  // namespace station
