// The FreenectApi seam on libfreenect (asynchronous API). Compiled only when
// libfreenect-dev is found (drivers/CMakeLists.txt defines STATION_HAVE_FREENECT).
// Under fakenect (LD_LIBRARY_PATH=/usr/lib/<arch>/fakenect) the same calls
// replay a recording.
#include <libfreenect.h>
#include <sys/time.h>

#include <map>
#include <mutex>

#include "drivers/kinect_scanner.h"

namespace station {

namespace {

class LibfreenectApi;

// libfreenect's log callback has no user pointer: map contexts to their API.
std::mutex g_log_mutex;
std::map<freenect_context*, LibfreenectApi*> g_log_owner;

class LibfreenectApi final : public FreenectApi {
 public:
  ~LibfreenectApi() override { close(); }

  Result init() override {
    if (ctx_) return {};
    log_.clear();
    if (freenect_init(&ctx_, nullptr) < 0 || !ctx_) {
      ctx_ = nullptr;
      return {-1, "freenect_init failed (libusb could not start)"};
    }
    {
      std::lock_guard<std::mutex> lock(g_log_mutex);
      g_log_owner[ctx_] = this;
    }
    freenect_set_log_level(ctx_, FREENECT_LOG_ERROR);
    freenect_set_log_callback(ctx_, &LibfreenectApi::on_log);
    return {0, take_log()};
  }

  int device_count() override { return ctx_ ? freenect_num_devices(ctx_) : 0; }

  std::vector<KinectDepthFormat> depth_formats() override {
    std::vector<KinectDepthFormat> out;
    const int n = freenect_get_depth_mode_count();
    for (int i = 0; i < n; ++i) {
      const freenect_frame_mode m = freenect_get_depth_mode(i);
      if (!m.is_valid || m.resolution != FREENECT_RESOLUTION_MEDIUM) continue;
      if (m.depth_format == FREENECT_DEPTH_REGISTERED)
        out.push_back(KinectDepthFormat::kRegistered);
      if (m.depth_format == FREENECT_DEPTH_MM) out.push_back(KinectDepthFormat::kMillimetres);
      if (m.depth_format == FREENECT_DEPTH_11BIT) out.push_back(KinectDepthFormat::kRaw11Bit);
    }
    return out;
  }

  Result open(int index) override {
    if (!ctx_) return {-1, "no context"};
    const int rc = freenect_open_device(ctx_, &dev_, index);
    if (rc < 0) dev_ = nullptr;
    return {rc < 0 ? rc : 0, take_log()};
  }

  Result start(KinectDepthFormat format, DepthSink depth, VideoSink video) override {
    if (!dev_) return {-1, "device not open"};
    depth_sink_ = std::move(depth);
    video_sink_ = std::move(video);
    freenect_depth_format want = FREENECT_DEPTH_REGISTERED;
    if (format == KinectDepthFormat::kMillimetres) want = FREENECT_DEPTH_MM;
    if (format == KinectDepthFormat::kRaw11Bit) want = FREENECT_DEPTH_11BIT;
    // Modes are looked up by enumeration: Debian's fakenect aborts on
    // freenect_find_depth_mode for anything but 11-bit.
    freenect_frame_mode dmode{}, vmode{};
    for (int i = 0; i < freenect_get_depth_mode_count(); ++i) {
      const freenect_frame_mode m = freenect_get_depth_mode(i);
      if (m.is_valid && m.resolution == FREENECT_RESOLUTION_MEDIUM && m.depth_format == want)
        dmode = m;
    }
    for (int i = 0; i < freenect_get_video_mode_count(); ++i) {
      const freenect_frame_mode m = freenect_get_video_mode(i);
      if (m.is_valid && m.resolution == FREENECT_RESOLUTION_MEDIUM &&
          m.video_format == FREENECT_VIDEO_RGB)
        vmode = m;
    }
    if (!dmode.is_valid || dmode.width != kKinectWidth || dmode.height != kKinectHeight)
      return {-1, "depth mode not offered"};
    if (!vmode.is_valid || vmode.width != kKinectWidth || vmode.height != kKinectHeight)
      return {-1, "640x480 RGB video mode not offered"};
    freenect_set_user(dev_, this);
    if (freenect_set_depth_mode(dev_, dmode) < 0)
      return {-1, take_log() + "\nset_depth_mode failed"};
    if (freenect_set_video_mode(dev_, vmode) < 0)
      return {-1, take_log() + "\nset_video_mode failed"};
    freenect_set_depth_callback(dev_, &LibfreenectApi::on_depth);
    freenect_set_video_callback(dev_, &LibfreenectApi::on_video);
    if (freenect_start_depth(dev_) < 0) return {-1, take_log() + "\nstart_depth failed"};
    depth_running_ = true;
    if (freenect_start_video(dev_) < 0) return {-1, take_log() + "\nstart_video failed"};
    video_running_ = true;
    return {0, take_log()};
  }

  Result process_events(int timeout_ms) override {
    if (!ctx_) return {-1, "no context"};
    timeval tv{};
    tv.tv_sec = timeout_ms / 1000;
    tv.tv_usec = (timeout_ms % 1000) * 1000;
    const int rc = freenect_process_events_timeout(ctx_, &tv);
    return {rc < 0 ? rc : 0, take_log()};
  }

  Result set_tilt(double degrees) override {
    if (!dev_) return {-1, "device not open"};
    const int rc = freenect_set_tilt_degs(dev_, degrees);
    return {rc < 0 ? rc : 0, take_log()};
  }

  Result tilt_state(TiltState& s) override {
    if (!dev_) return {-1, "device not open"};
    const int rc = freenect_update_tilt_state(dev_);
    if (rc < 0) return {rc, take_log()};
    freenect_raw_tilt_state* st = freenect_get_tilt_state(dev_);
    if (!st) return {-1, "no tilt state"};
    s.degrees = freenect_get_tilt_degs(st);
    const freenect_tilt_status_code code = freenect_get_tilt_status(st);
    s.moving = code == TILT_STATUS_MOVING;
    s.limit = code == TILT_STATUS_LIMIT;
    return {0, take_log()};
  }

  void close() override {
    if (dev_) {
      if (depth_running_) freenect_stop_depth(dev_);
      if (video_running_) freenect_stop_video(dev_);
      depth_running_ = video_running_ = false;
      freenect_close_device(dev_);
      dev_ = nullptr;
    }
    if (ctx_) {
      freenect_shutdown(ctx_);
      std::lock_guard<std::mutex> lock(g_log_mutex);
      g_log_owner.erase(ctx_);
      ctx_ = nullptr;
    }
  }

 private:
  static void on_log(freenect_context* ctx, freenect_loglevel, const char* msg) {
    std::lock_guard<std::mutex> lock(g_log_mutex);
    auto it = g_log_owner.find(ctx);
    if (it != g_log_owner.end() && msg) it->second->log_ += msg;
  }
  static void on_depth(freenect_device* dev, void* data, std::uint32_t ts) {
    auto* self = static_cast<LibfreenectApi*>(freenect_get_user(dev));
    if (self && self->depth_sink_) self->depth_sink_(static_cast<const std::uint16_t*>(data), ts);
  }
  static void on_video(freenect_device* dev, void* data, std::uint32_t ts) {
    auto* self = static_cast<LibfreenectApi*>(freenect_get_user(dev));
    if (self && self->video_sink_) self->video_sink_(static_cast<const std::uint8_t*>(data), ts);
  }
  std::string take_log() {
    std::lock_guard<std::mutex> lock(g_log_mutex);
    std::string out;
    out.swap(log_);
    return out;
  }

  freenect_context* ctx_ = nullptr;
  freenect_device* dev_ = nullptr;
  bool depth_running_ = false, video_running_ = false;
  DepthSink depth_sink_;
  VideoSink video_sink_;
  std::string log_;
};

}  // namespace

std::unique_ptr<FreenectApi> make_libfreenect_api() { return std::make_unique<LibfreenectApi>(); }
bool have_libfreenect() { return true; }

}  // namespace station
