#pragma once
// Device abstraction: range/colour scanners. Real back-ends (V4L2, libusb) and
// the simulated scanner (sim/) implement the same interface; the capture loop
// sees only this header.
#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "core/camera.h"
#include "core/geometry.h"

namespace station {


/// One grab. A range camera fills `depth` (metres along the optical axis,
/// row-major width*height, 0 = no return); a device that measures points
/// directly fills `points` (scanner frame: x right, y down, z forward).
/// `color` is optional row-major RGB, color_intrinsics.width*height*3 bytes,
/// registered to the depth image when both have the same intrinsics.
struct Frame {
  Intrinsics intrinsics;
  std::vector<float> depth;
  Cloud points;
  Intrinsics colour_intrinsics;
  std::vector<std::uint8_t> colour;
  double timestamp = 0;  ///< seconds since the Unix epoch
  std::optional<Eigen::Matrix4d> reference_pose;  ///< truth known to a simulator (object frame <- scanner frame)
  bool has_depth() const { return !depth.empty(); }
  bool has_colour() const { return !colour.empty(); }
};


struct ScannerCapabilities {
  bool depth = false;   ///< delivers depth images
  bool points = false;  ///< delivers points directly
  bool colour = false;   ///< delivers a colour image
  Intrinsics intrinsics;
  /// Bench calibration the device knows itself (the simulator does); real
  /// devices leave it empty and the profile supplies it.
  std::optional<TurntableAxis> axis;
};

/// Device options: key/value pairs from the URI query or the YAML profile.
using DeviceOptions = std::map<std::string, std::string>;

class Scanner {
 public:
  virtual ~Scanner() = default;
  /// Connects to the device; DeviceError("URI: problem") when unplugged or busy.
  virtual void open() = 0;
  virtual void close() = 0;
  /// Applies options (resolution, exposure...); unknown keys are a DeviceError.
  virtual void configure(const DeviceOptions& options) = 0;
  virtual ScannerCapabilities capabilities() const = 0;
  /// Blocks until a frame is available; DeviceError on failure or time-out.
  virtual Frame grab() = 0;
  virtual std::string uri() const = 0;
  /// A resumed capture (after open()): the next grab is the session's view `view`.
  /// Real devices ignore it; the simulator keys its noise by the frame number, so
  /// that a resumed scan records the views an uninterrupted one would have.
  virtual void resume_at(std::uint64_t view) { (void)view; }
};

class Turntable {
 public:
  virtual ~Turntable() = default;
  virtual void open() = 0;
  virtual void close() = 0;
  /// Drives to the home (zero) position.
  virtual void home() = 0;
  /// Rotates to an absolute angle in degrees, [0, 360); blocks until there.
  virtual void rotate_to(double degrees) = 0;
  /// Current angle in degrees, as the device reports it.
  virtual double angle() const = 0;
  virtual int steps_per_revolution() const = 0;
  virtual std::string uri() const = 0;
};

}  // namespace station
