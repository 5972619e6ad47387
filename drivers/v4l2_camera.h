#pragma once
// V4L2 cameras as a Scanner: colour nodes (YUYV, MJPEG), depth nodes (Z16,
// Y16: 16-bit units times a depth scale), or a depth node and a colour node of
// one device combined into one scanner with their extrinsics. Everything goes
// through the SysCalls seam (open/ioctl/mmap/poll), so tests serve frames from
// an in-process fake kernel.
//
// URIs
//   v4l2:/dev/video2?fx=..&fy=..&cx=..&cy=..           one node (depth or colour)
//   v4l2:/dev/video2?color=/dev/video4&extrinsics=...   depth + colour
//   v4l2:auto?card=RealSense                            pick nodes by formats
// Options (URI or profile)
//   format      YUYV | MJPG | Z16 | Y16 | auto (default: the first the node
//               offers in that order of preference)
//   width, height  requested size (the driver may adjust; the frame reports
//               what it got); default: the node's current size
//   buffers     mmap buffers (4); timeout_ms  frame time-out (2000)
//   exposure    fixed exposure (V4L2_CID_EXPOSURE_ABSOLUTE, 100 us units);
//               switches auto exposure off
//   white_balance  fixed white balance in kelvin; switches auto WB off
//   depth_scale metres per depth unit (0.001)
//   fx fy cx cy intrinsics of the depth (or only) node in pixels; required
//               for depth (plain V4L2 does not report them)
//   color       path of the colour node to pair with a depth node
//   color_format, color_width, color_height, color_fx, color_fy, color_cx,
//               color_cy  the colour node's settings
//   extrinsics  12 comma-separated numbers, row-major 3x4 [R|t] mapping depth
//               camera points to colour camera points (metres); with it the
//               colour image is registered to the depth image
//   card        (auto) substring of the card name to pick nodes from
#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "drivers/registry.h"
#include "drivers/syscalls.h"

namespace station {

/// BT.601 limited-range YUYV (4:2:2, Y0 U Y1 V) to packed RGB. `stride` bytes
/// per source row (>= 2*width).
void yuyv_to_rgb(const std::uint8_t* src, int width, int height, int stride,
                 std::vector<std::uint8_t>& rgb);
/// JPEG (MJPEG frame) to packed RGB; DeviceError "WHO: ..." when it does not
/// decode or has another size than expected.
void mjpeg_to_rgb(const std::uint8_t* data, std::size_t size, int width, int height,
                  const std::string& who, std::vector<std::uint8_t>& rgb);
/// 16-bit little-endian depth units to metres (0 stays 0 = no return).
void depth16_to_metres(const std::uint8_t* src, int width, int height, int stride, double scale,
                       std::vector<float>& metres);
/// Colour registered to the depth image: each depth pixel is back-projected,
/// moved by `depth_to_color` (3x4, row-major) and projected into the colour
/// image; pixels without depth or outside the colour image are black.
std::vector<std::uint8_t> register_colour_to_depth(const std::vector<float>& depth,
                                                  const Intrinsics& depth_k,
                                                  const std::vector<std::uint8_t>& rgb,
                                                  const Intrinsics& colour_k,
                                                  const std::array<double, 12>& depth_to_colour);

/// FourCC as text ("YUYV").
std::string fourcc_text(std::uint32_t fourcc);

/// One capture node, streaming through mmap buffers.
class V4l2Stream {
 public:
  struct Settings {
    std::string format = "auto";
    int width = 0, height = 0;
    int buffers = 4;
    int timeout_ms = 2000;
    std::optional<int> exposure, white_balance;
  };
  /// What one dequeued buffer holds; valid until the next next_frame()/stop().
  struct Raw {
    const std::uint8_t* data = nullptr;
    std::size_t bytes = 0;
    std::uint32_t fourcc = 0;
    int width = 0, height = 0, stride = 0;
  };
  V4l2Stream(std::shared_ptr<SysCalls> sys, std::string path, std::string who);
  ~V4l2Stream();
  /// Open, check capabilities, negotiate the format, set controls, map
  /// buffers and start streaming. DeviceError "WHO: ..." on each failure
  /// (busy, not a capture node, format not offered...).
  void start(const Settings& s);
  void stop();
  bool running() const { return fd_ >= 0; }
  /// Waits (poll) for the next frame; DeviceError on time-out or unplug.
  Raw next_frame();
  std::uint32_t fourcc() const { return fourcc_; }
  int width() const { return width_; }
  int height() const { return height_; }

 private:
  void set_control(std::uint32_t id, int value, const char* name);
  void requeue();
  std::shared_ptr<SysCalls> sys_;
  std::string path_, who_;
  int fd_ = -1;
  int timeout_ms_ = 2000;
  std::uint32_t fourcc_ = 0;
  int width_ = 0, height_ = 0, stride_ = 0;
  struct Buffer {
    void* start = nullptr;
    std::size_t length = 0;
  };
  std::vector<Buffer> buffers_;
  int held_ = -1;  ///< index of the buffer handed out, requeued on the next call
  bool streaming_ = false;
};

/// Formats a node offers for video capture (ENUM_FMT), and its card name.
struct V4l2NodeInfo {
  std::string path, card, driver;
  std::vector<std::uint32_t> formats;
  bool has_depth() const;
  bool has_colour() const;
};
std::vector<V4l2NodeInfo> describe_v4l2_nodes(SysCalls& sys, const std::vector<std::string>& paths);

class V4l2Camera final : public Scanner {
 public:
  /// `uri` parsed; `paths` are the candidate nodes for "v4l2:auto".
  V4l2Camera(std::shared_ptr<SysCalls> sys, const DeviceUri& uri,
             std::vector<std::string> paths = {});
  ~V4l2Camera() override;
  void open() override;
  void close() override;
  void configure(const DeviceOptions& options) override;
  ScannerCapabilities capabilities() const override;
  Frame grab() override;
  std::string uri() const override { return uri_.text; }

 private:
  struct Parsed;
  static std::unique_ptr<Parsed> parse(const DeviceUri& uri);
  std::shared_ptr<SysCalls> sys_;
  DeviceUri uri_;
  std::vector<std::string> paths_;
  std::unique_ptr<Parsed> p_;
  std::unique_ptr<V4l2Stream> main_, colour_;
  bool main_is_depth_ = false;
};

/// "v4l2:" scanner factory + lister (replaces register_v4l2_probe).
void register_v4l2_camera(DeviceRegistry& registry, std::shared_ptr<SysCalls> sys);

}  // namespace station
