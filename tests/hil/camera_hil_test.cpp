// A V4L2 camera on the bench: a node offering Z16/Y16 (depth) or YUYV/MJPG
// (colour). Grabs frames and checks their format and timing.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

#include "core/error.h"
#include "drivers/v4l2_camera.h"
#include "drivers/v4l2_probe.h"
#include "hil_common.h"

namespace station {
namespace {

/// The URI to test: HIL_V4L2_URI, or the first depth node, else the first colour
/// node. Depth nodes get placeholder intrinsics (a 60 degree field of view) when
/// the URI gives none: enough to check formats, not for measuring.
std::string find_camera(std::string& why) {
  const std::string given = hil::env("HIL_V4L2_URI");
  if (!given.empty()) return given;
  const auto nodes = describe_v4l2_nodes(*real_syscalls(), v4l2_device_paths());
  const V4l2NodeInfo* pick = nullptr;
  for (const auto& n : nodes)
    if (n.has_depth()) {
      pick = &n;
      break;
    }
  if (!pick)
    for (const auto& n : nodes)
      if (n.has_colour()) {
        pick = &n;
        break;
      }
  if (!pick) {
    why = "no V4L2 capture node with Z16, Y16, YUYV or MJPG (" + std::to_string(nodes.size()) +
          " capture nodes found); set HIL_V4L2_URI to name one";
    return "";
  }
  std::string uri = "v4l2:" + pick->path;
  if (pick->has_depth()) uri += "?fx=0&fy=0&cx=0&cy=0";  // placeholder, replaced below
  return uri;
}

TEST(HilCamera, GrabsFramesOfTheNegotiatedFormatAtARegularRate) {
  std::string why;
  std::string uri = find_camera(why);
  if (uri.empty()) HIL_ABSENT(why);
  if (uri.find("fx=0&fy=0&cx=0&cy=0") != std::string::npos) {
    // Learn the node's size first, then give intrinsics of a 60 degree view.
    DeviceUri probe = parse_device_uri(uri);
    V4l2Stream s(real_syscalls(), probe.path, uri);
    s.start({});
    const int w = s.width(), h = s.height();
    s.stop();
    const double f = w / (2 * std::tan(30.0 * M_PI / 180));
    uri = "v4l2:" + probe.path + "?fx=" + std::to_string(f) + "&fy=" + std::to_string(f) +
          "&cx=" + std::to_string(w / 2.0) + "&cy=" + std::to_string(h / 2.0);
  }
  std::printf("[ HIL      ] camera %s\n", uri.c_str());
  V4l2Camera cam(real_syscalls(), parse_device_uri(uri));
  cam.open();
  const ScannerCapabilities caps = cam.capabilities();
  std::vector<double> stamps;
  const int n = std::stoi(hil::env("HIL_FRAMES", "15"));
  for (int i = 0; i < n; ++i) {
    const Frame f = cam.grab();
    stamps.push_back(f.timestamp);
    if (caps.depth) {
      ASSERT_EQ(f.depth.size(), static_cast<std::size_t>(f.intrinsics.width) * f.intrinsics.height);
      const auto valid =
          std::count_if(f.depth.begin(), f.depth.end(), [](float d) { return d > 0; });
      const bool finite =
          std::all_of(f.depth.begin(), f.depth.end(), [](float d) { return std::isfinite(d); });
      EXPECT_TRUE(finite);
      if (i == n - 1) {
        EXPECT_GT(valid, 0) << "every depth pixel is 0 (covered lens, or wrong depth_scale?)";
        std::printf("[ HIL      ] depth %dx%d, %.0f%% valid\n", f.intrinsics.width,
                    f.intrinsics.height, 100.0 * valid / f.depth.size());
      }
    }
    if (caps.colour) {
      ASSERT_EQ(f.colour.size(),
                static_cast<std::size_t>(f.colour_intrinsics.width) * f.colour_intrinsics.height * 3);
    }
  }
  cam.close();
  // Timing: frames keep coming (no stall longer than a second), in order.
  double worst = 0;
  for (std::size_t i = 1; i < stamps.size(); ++i) {
    EXPECT_GE(stamps[i], stamps[i - 1]);
    worst = std::max(worst, stamps[i] - stamps[i - 1]);
  }
  const double fps = (stamps.size() - 1) / std::max(1e-9, stamps.back() - stamps.front());
  std::printf("[ HIL      ] %zu frames, %.1f fps, longest gap %.0f ms\n", stamps.size(), fps,
              worst * 1000);
  EXPECT_LT(worst, 1.0);
}

TEST(HilCamera, SecondOpenIsBusyOrShared) {
  std::string why;
  std::string uri = find_camera(why);
  if (uri.empty()) HIL_ABSENT(why);
  const DeviceUri u = parse_device_uri(uri);
  V4l2Stream first(real_syscalls(), u.path, uri);
  first.start({});
  V4l2Stream second(real_syscalls(), u.path, uri);
  try {
    second.start({});
    // Some drivers let two readers stream; then there is nothing to check.
    std::printf("[ HIL      ] %s allows a second stream\n", u.path.c_str());
  } catch (const DeviceError& e) {
    EXPECT_NE(std::string(e.what()).find("busy"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace station
