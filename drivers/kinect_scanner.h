#pragma once
// The Kinect v1 (Xbox 360 Kinect, Kinect for Windows) as a Scanner, through
// libfreenect's asynchronous API. The driver logic here needs no libfreenect:
// it talks to the library through the small FreenectApi seam, so unit tests run
// against an in-process fake. The libfreenect binding (kinect_freenect.cpp) is
// compiled only when libfreenect-dev is found (STATION_HAVE_FREENECT).
//
// URI  kinect:0?tilt_deg=10&...     (the path is the device index; "kinect:" = 0)
// Options (URI or profile)
//   depth_format  registered (default): FREENECT_DEPTH_REGISTERED, millimetres
//                 already mapped onto the colour camera by the Kinect's own
//                 registration tables, so colour and depth share intrinsics;
//                 mm: FREENECT_DEPTH_MM, millimetres in the IR camera's view;
//                 11bit: raw disparity (FREENECT_DEPTH_11BIT, 2047 = no data),
//                 converted to metres by kinect_disparity_to_metres. Only the
//                 formats the library offers can be used (Debian's fakenect
//                 replays 11bit only).
//   tilt_deg      tilt motor angle set at open(), degrees in [-27, 27]; open()
//                 waits (tilt_timeout_ms, 3000) until the motor stops
//   fx fy cx cy   depth intrinsics in pixels (640x480). Defaults: registered:
//                 the colour camera's 525, 525, 319.5, 239.5; mm/11bit: the IR
//                 camera's 580, 580, 319.5, 239.5 (see docs/devices.md)
//   distortion    k1,k2,p1,p2,k3 of the depth image (OpenCV order; default none)
//   color_fx color_fy color_cx color_cy color_distortion
//                 colour intrinsics for mm/11bit (registered: the depth ones)
//   timeout_ms    time-out of one grab (2000)
//   discard       frames of each stream dropped at the start of every grab (2):
//                 libfreenect queues about one frame of USB transfers while
//                 nobody pumps events, so the first frame after a turntable move
//                 may show the table where it was
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "drivers/registry.h"

namespace station {

inline constexpr int kKinectWidth = 640;
inline constexpr int kKinectHeight = 480;
/// Raw 11-bit disparity value meaning "no data".
inline constexpr std::uint16_t kKinectNoDisparity = 2047;

enum class KinectDepthFormat { kRegistered, kMillimetres, kRaw11Bit };
/// "registered", "mm", "11bit".
std::string kinect_depth_format_name(KinectDepthFormat f);

/// Raw 11-bit disparity to metres: z = 1 / (a*raw + b), a = -0.0030711016,
/// b = 3.3309495161 (the first-order fit from ROS' kinect_calibration data,
/// OpenKinect wiki "Imaging Information"). 0 (no return) for 2047, and for raw
/// values where the fit leaves its range (z outside (0, 10] m).
float kinect_disparity_to_metres(std::uint16_t raw);

/// What the driver needs from libfreenect: one context, one device, one depth
/// and one RGB stream at 640x480. Each call returns a Result whose `log` holds
/// the messages libfreenect logged meanwhile (errors name the libusb cause:
/// "Failed to claim camera interface: LIBUSB_ERROR_BUSY").
class FreenectApi {
 public:
  struct Result {
    int code = 0;  ///< 0 ok, < 0 failure
    std::string log;
    bool ok() const { return code >= 0; }
  };
  struct TiltState {
    double degrees = 0;   ///< freenect_get_tilt_degs (from the accelerometer)
    bool moving = false;  ///< TILT_STATUS_MOVING
    bool limit = false;   ///< TILT_STATUS_LIMIT
  };
  /// 640*480 uint16 (mm or raw disparity, per the started format).
  using DepthSink = std::function<void(const std::uint16_t* depth, std::uint32_t timestamp)>;
  /// 640*480*3 RGB bytes.
  using VideoSink = std::function<void(const std::uint8_t* rgb, std::uint32_t timestamp)>;

  virtual ~FreenectApi() = default;
  /// Creates the context (libusb); failure means USB cannot be used at all.
  virtual Result init() = 0;
  /// Kinects on the bus (freenect_num_devices); init() first.
  virtual int device_count() = 0;
  /// Depth formats the library offers at 640x480 (freenect_get_depth_mode).
  virtual std::vector<KinectDepthFormat> depth_formats() = 0;
  virtual Result open(int index) = 0;
  /// Sets the modes and callbacks and starts depth and video.
  virtual Result start(KinectDepthFormat format, DepthSink depth, VideoSink video) = 0;
  /// Handles USB events for up to `timeout_ms`, calling the sinks.
  virtual Result process_events(int timeout_ms) = 0;
  virtual Result set_tilt(double degrees) = 0;
  virtual Result tilt_state(TiltState& state) = 0;
  /// Stops the streams, closes the device and the context (idempotent).
  virtual void close() = 0;
};

/// Makes one FreenectApi per scanner (each its own libfreenect context).
using FreenectApiFactory = std::function<std::unique_ptr<FreenectApi>()>;

/// The libfreenect binding; nullptr when the build has no libfreenect.
std::unique_ptr<FreenectApi> make_libfreenect_api();
/// True when the station was built with libfreenect.
bool have_libfreenect();

struct KinectOptions {
  int index = 0;
  KinectDepthFormat depth_format = KinectDepthFormat::kRegistered;
  std::optional<double> tilt_deg;
  int tilt_timeout_ms = 3000;
  int timeout_ms = 2000;
  int discard = 2;
  Intrinsics depth_intrinsics;  ///< filled with the format's defaults unless given
  Intrinsics colour_intrinsics;
};
/// Parses and checks the options; DeviceError "WHO: option ...: problem".
KinectOptions kinect_options(const std::string& path, const DeviceOptions& options,
                             const std::string& uri);

class KinectScanner final : public Scanner {
 public:
  KinectScanner(std::string uri, std::string path, DeviceOptions options,
                std::unique_ptr<FreenectApi> api);
  ~KinectScanner() override;
  /// Errors name the device as "kinect:N" (without the options):
  /// DeviceError "kinect:0: no Kinect found" (none on the bus), "...: busy (another
  /// program has it open)", "...: no permission ..." (udev rule), "...: depth
  /// format 'registered' not offered by this libfreenect (offers: 11bit)".
  void open() override;
  void close() override;
  /// Validates first (a bad option changes nothing), then reopens if open.
  void configure(const DeviceOptions& options) override;
  ScannerCapabilities capabilities() const override;
  /// The next depth frame and the next colour frame after `discard` of each.
  /// DeviceError "kinect:0: no frame within N ms (...)" or "kinect:0: device gone
  /// while streaming (unplugged?)"; after an unplug the scanner is closed.
  Frame grab() override;
  std::string uri() const override { return uri_; }
  /// Tilt reported by the accelerometer, degrees (nullopt when closed).
  std::optional<double> tilt_degrees();
  const KinectOptions& options() const { return opts_; }

 private:
  std::string uri_, path_;
  std::string who_;  ///< "kinect:N", the name in error messages
  DeviceOptions raw_options_;
  KinectOptions opts_;
  std::unique_ptr<FreenectApi> api_;
  bool open_ = false;
  // Frames delivered by the callbacks during one grab.
  std::vector<std::uint16_t> depth_raw_;
  std::vector<std::uint8_t> rgb_;
  int depth_seen_ = 0, video_seen_ = 0;
  bool depth_ready_ = false, video_ready_ = false;
};

/// "kinect:" scanner factory + lister (freenect_num_devices) on `make_api`.
void register_kinect(DeviceRegistry& registry, FreenectApiFactory make_api);

}  // namespace station
