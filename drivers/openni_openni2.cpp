// The OpenniApi seam on OpenNI2 (Debian: libopenni2-dev). Compiled only when
// libopenni2 is found (drivers/CMakeLists.txt defines STATION_HAVE_OPENNI2).
#include <OpenNI.h>

#include <chrono>
#include <cstring>

#include "drivers/openni_scanner.h"

namespace station {

namespace {

class Openni2Api final : public OpenniApi {
 public:
  ~Openni2Api() override { close(); }

  Result init() override {
    if (initialized_) return {};
    if (openni::OpenNI::initialize() != openni::STATUS_OK)
      return {-1, openni::OpenNI::getExtendedError()};
    initialized_ = true;
    return {};
  }

  std::vector<std::string> device_uris() override {
    std::vector<std::string> out;
    if (!initialized_) return out;
    openni::Array<openni::DeviceInfo> list;
    openni::OpenNI::enumerateDevices(&list);
    for (int i = 0; i < list.getSize(); ++i) out.emplace_back(list[i].getUri());
    return out;
  }

  Result open(const std::string& uri, int width, int height, bool registration, StreamInfo& depth,
              StreamInfo& colour) override {
    if (!initialized_) return {-1, "not initialised"};
    if (device_.open(uri.c_str()) != openni::STATUS_OK) return failure();
    if (registration) {
      if (!device_.isImageRegistrationModeSupported(openni::IMAGE_REGISTRATION_DEPTH_TO_COLOR))
        return {-3, "the device cannot register depth to colour (use registration=off)"};
      if (device_.setImageRegistrationMode(openni::IMAGE_REGISTRATION_DEPTH_TO_COLOR) !=
          openni::STATUS_OK)
        return failure();
    }
    device_.setDepthColorSyncEnabled(true);  // best effort: not every device syncs
    Result r = make_stream(depth_, openni::SENSOR_DEPTH, openni::PIXEL_FORMAT_DEPTH_1_MM, width,
                           height, depth);
    if (!r.ok()) return r;
    return make_stream(colour_, openni::SENSOR_COLOR, openni::PIXEL_FORMAT_RGB888, width, height,
                       colour);
  }

  Result read(Frames& out, int timeout_ms) override {
    bool got_depth = false, got_colour = false;
    openni::VideoStream* streams[2] = {&depth_, &colour_};
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    while (!(got_depth && got_colour)) {
      const long long left = std::chrono::duration_cast<std::chrono::milliseconds>(
                                 deadline - std::chrono::steady_clock::now())
                                 .count();
      if (left <= 0) return {-2, ""};
      int ready = -1;
      const openni::Status s =
          openni::OpenNI::waitForAnyStream(streams, 2, &ready, static_cast<int>(left));
      if (s == openni::STATUS_TIME_OUT) return {-2, ""};
      if (s != openni::STATUS_OK || ready < 0) return failure();
      openni::VideoFrameRef f;
      if (streams[ready]->readFrame(&f) != openni::STATUS_OK || !f.isValid()) return failure();
      const int w = f.getWidth(), h = f.getHeight(), stride = f.getStrideInBytes();
      const auto* data = static_cast<const std::uint8_t*>(f.getData());
      if (ready == 0) {
        out.width = w;
        out.height = h;
        out.depth_mm.resize(static_cast<std::size_t>(w) * h);
        for (int v = 0; v < h; ++v)
          std::memcpy(out.depth_mm.data() + static_cast<std::size_t>(v) * w, data + v * stride,
                      static_cast<std::size_t>(w) * 2);
        got_depth = true;
      } else {
        out.colour_width = w;
        out.colour_height = h;
        out.rgb.resize(static_cast<std::size_t>(w) * h * 3);
        for (int v = 0; v < h; ++v)
          std::memcpy(out.rgb.data() + static_cast<std::size_t>(v) * w * 3, data + v * stride,
                      static_cast<std::size_t>(w) * 3);
        got_colour = true;
      }
    }
    return {};
  }

  void close() override {
    for (openni::VideoStream* s : {&depth_, &colour_})
      if (s->isValid()) {
        s->stop();
        s->destroy();
      }
    if (device_.isValid()) device_.close();
    if (initialized_) openni::OpenNI::shutdown();
    initialized_ = false;
  }

 private:
  static Result failure() { return {-1, openni::OpenNI::getExtendedError()}; }

  Result make_stream(openni::VideoStream& stream, openni::SensorType type,
                     openni::PixelFormat format, int width, int height, StreamInfo& info) {
    if (stream.create(device_, type) != openni::STATUS_OK) return failure();
    openni::VideoMode mode = stream.getVideoMode();
    const bool wrong_format = mode.getPixelFormat() != format;
    const bool wrong_size =
        width > 0 && (mode.getResolutionX() != width || mode.getResolutionY() != height);
    if (wrong_format || wrong_size) {
      // Pick a supported mode of the right format (and size, when asked).
      const openni::SensorInfo& si = stream.getSensorInfo();
      const auto& modes = si.getSupportedVideoModes();
      bool found = false;
      for (int i = 0; i < modes.getSize() && !found; ++i) {
        const openni::VideoMode& m = modes[i];
        if (m.getPixelFormat() != format) continue;
        if (width > 0 && (m.getResolutionX() != width || m.getResolutionY() != height)) continue;
        mode = m;
        found = true;
      }
      if (!found)
        return {-3, std::string("no supported ") +
                        (type == openni::SENSOR_DEPTH ? "DEPTH_1_MM" : "RGB888") + " mode" +
                        (width > 0 ? " of that size" : "")};
      if (stream.setVideoMode(mode) != openni::STATUS_OK) return failure();
    }
    if (stream.start() != openni::STATUS_OK) return failure();
    mode = stream.getVideoMode();
    info.width = mode.getResolutionX();
    info.height = mode.getResolutionY();
    info.hfov = stream.getHorizontalFieldOfView();
    info.vfov = stream.getVerticalFieldOfView();
    return {};
  }

  bool initialized_ = false;
  openni::Device device_;
  openni::VideoStream depth_, colour_;
};

}  // namespace

std::unique_ptr<OpenniApi> make_openni2_api() { return std::make_unique<Openni2Api>(); }
bool have_openni2() { return true; }

}  // namespace station
