#pragma once
// OpenNI2 depth cameras (PrimeSense Carmine, Asus Xtion, Orbbec Astra...) as a
// Scanner, through Debian's libopenni2. Same shape as the Kinect driver: the
// logic talks to OpenNI2 through the small OpenniApi seam (unit tests use a
// fake); the OpenNI2 binding (openni_openni2.cpp) is compiled only when
// libopenni2-dev is found (STATION_HAVE_OPENNI2).
//
// URI  openni:0        the first device OpenNI2 enumerates (index)
//      openni:Dummy    an OpenNI2 device URI (here OpenNI2's own DummyDevice)
// Options (URI or profile)
//   registration  on (default): IMAGE_REGISTRATION_DEPTH_TO_COLOR, colour and
//                 depth share intrinsics; off: each keeps its own. "on" on a
//                 device that cannot register is an error.
//   width height  depth and colour mode (default: the streams' current mode)
//   fx fy cx cy distortion  depth intrinsics; default from the depth stream's
//                 field of view (fx = width / 2 / tan(hfov / 2), centre of the
//                 image); a device that reports no field of view needs them
//   color_fx color_fy color_cx color_cy color_distortion  (registration=off)
//   timeout_ms    one grab (2000); discard  pairs dropped per grab (1)
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "drivers/registry.h"

namespace station {

class OpenniApi {
 public:
  struct Result {
    int code = 0;       ///< 0 ok; < 0 failure (-2 time-out; -3 `error` is the whole reason)
    std::string error;  ///< OpenNI::getExtendedError() when failed
    bool ok() const { return code >= 0; }
  };
  struct StreamInfo {
    int width = 0, height = 0;
    float hfov = 0, vfov = 0;  ///< radians; 0 when the device does not say
  };
  /// One depth frame (millimetres, 0 = none) and one RGB frame.
  struct Frames {
    int width = 0, height = 0;
    std::vector<std::uint16_t> depth_mm;
    int colour_width = 0, colour_height = 0;
    std::vector<std::uint8_t> rgb;
  };
  virtual ~OpenniApi() = default;
  virtual Result init() = 0;
  virtual std::vector<std::string> device_uris() = 0;
  /// Opens the device, creates depth (DEPTH_1_MM) and colour (RGB888) streams
  /// at width x height (0: keep the current mode), sets registration, starts.
  virtual Result open(const std::string& device_uri, int width, int height, bool registration,
                      StreamInfo& depth, StreamInfo& colour) = 0;
  /// Waits until it has a new depth and a new colour frame.
  virtual Result read(Frames& out, int timeout_ms) = 0;
  virtual void close() = 0;
};

std::unique_ptr<OpenniApi> make_openni2_api();  ///< nullptr without libopenni2
bool have_openni2();

class OpenniScanner final : public Scanner {
 public:
  OpenniScanner(std::string uri, std::string path, DeviceOptions options,
                std::unique_ptr<OpenniApi> api);
  ~OpenniScanner() override;
  /// DeviceError "openni:0: no OpenNI2 device found", "...: busy ...", etc.
  void open() override;
  void close() override;
  void configure(const DeviceOptions& options) override;
  ScannerCapabilities capabilities() const override;
  Frame grab() override;
  std::string uri() const override { return uri_; }
  struct Parsed;  ///< parsed options (defined in the .cpp)

 private:
  std::string uri_, path_, who_;
  DeviceOptions raw_;
  std::unique_ptr<Parsed> p_;
  std::unique_ptr<OpenniApi> api_;
  bool open_ = false;
  Intrinsics depth_k_, colour_k_;
};

void register_openni(DeviceRegistry& registry,
                     std::function<std::unique_ptr<OpenniApi>()> make_api);

}  // namespace station
