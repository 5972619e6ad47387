#include "drivers/kinect_scanner.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <sstream>
#include <thread>

#include "core/error.h"
#include "drivers/serial_turntable.h"  // option readers

namespace station {

namespace {

double now_seconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

bool contains(const std::string& text, const char* what) {
  return text.find(what) != std::string::npos;
}

/// Last non-empty line of libfreenect's log, for error messages.
std::string log_tail(const std::string& log) {
  std::string line, last;
  std::istringstream ss(log);
  while (std::getline(ss, line))
    if (!line.empty()) last = line;
  return last;
}

/// Why a libfreenect call failed, from what it logged (libusb error names or codes).
std::string explain_failure(const std::string& log, const char* fallback) {
  if (contains(log, "LIBUSB_ERROR_BUSY") || (contains(log, "claim") && contains(log, "-6")))
    return "busy (another program has it open)";
  if (contains(log, "LIBUSB_ERROR_ACCESS") || contains(log, ": -3"))
    return "no permission to open the USB device (install libfreenect's udev rule "
           "60-libfreenect0.5.rules and add the user to group plugdev)";
  if (contains(log, "LIBUSB_ERROR_NO_DEVICE") || contains(log, ": -4") ||
      contains(log, "disappeared") || contains(log, "marked dead"))
    return "device gone (unplugged?)";
  const std::string tail = log_tail(log);
  return tail.empty() ? std::string(fallback)
                      : std::string(fallback) + " (libfreenect: " + tail + ")";
}

Intrinsics default_intrinsics(double f) {
  Intrinsics k;
  k.width = kKinectWidth;
  k.height = kKinectHeight;
  k.fx = k.fy = f;
  k.cx = 319.5;
  k.cy = 239.5;
  return k;
}

void read_intrinsics(const DeviceOptions& o, const std::string& prefix, Intrinsics& k,
                     const std::string& uri) {
  k.fx = option_number(o, prefix + "fx", k.fx, 1e-6, 1e6, uri);
  k.fy = option_number(o, prefix + "fy", k.fy, 1e-6, 1e6, uri);
  k.cx = option_number(o, prefix + "cx", k.cx, -1e6, 1e6, uri);
  k.cy = option_number(o, prefix + "cy", k.cy, -1e6, 1e6, uri);
  option_distortion(o, prefix + "distortion", k, uri);
}

}  // namespace

std::string kinect_depth_format_name(KinectDepthFormat f) {
  switch (f) {
    case KinectDepthFormat::kRegistered:
      return "registered";
    case KinectDepthFormat::kMillimetres:
      return "mm";
    case KinectDepthFormat::kRaw11Bit:
      return "11bit";
  }
  return "?";
}

float kinect_disparity_to_metres(std::uint16_t raw) {
  if (raw >= kKinectNoDisparity) return 0.0f;
  const double denom = -0.0030711016 * raw + 3.3309495161;
  if (denom < 0.1) return 0.0f;  // beyond 10 m: outside the fit (and the sensor's range)
  return static_cast<float>(1.0 / denom);
}

KinectOptions kinect_options(const std::string& path, const DeviceOptions& o,
                             const std::string& uri) {
  reject_unknown_options(
      o,
      {"depth_format", "tilt_deg", "tilt_timeout_ms", "timeout_ms", "discard", "fx", "fy", "cx",
       "cy", "distortion", "color_fx", "color_fy", "color_cx", "color_cy", "color_distortion"},
      uri);
  KinectOptions k;
  if (!path.empty()) {
    char* end = nullptr;
    const long idx = std::strtol(path.c_str(), &end, 10);
    if (*end != '\0' || idx < 0 || idx > 63)
      throw DeviceError(uri + ": device index '" + path + "': expected 0, 1, 2...");
    k.index = static_cast<int>(idx);
  }
  if (auto it = o.find("depth_format"); it != o.end()) {
    if (it->second == "registered")
      k.depth_format = KinectDepthFormat::kRegistered;
    else if (it->second == "mm")
      k.depth_format = KinectDepthFormat::kMillimetres;
    else if (it->second == "11bit")
      k.depth_format = KinectDepthFormat::kRaw11Bit;
    else
      throw DeviceError(uri + ": option depth_format=" + it->second +
                        ": expected registered, mm or 11bit");
  }
  if (o.count("tilt_deg")) k.tilt_deg = option_number(o, "tilt_deg", 0, -27, 27, uri);
  k.tilt_timeout_ms = option_integer(o, "tilt_timeout_ms", k.tilt_timeout_ms, 0, 60000, uri);
  k.timeout_ms = option_integer(o, "timeout_ms", k.timeout_ms, 1, 600000, uri);
  k.discard = option_integer(o, "discard", k.discard, 0, 100, uri);

  const bool registered = k.depth_format == KinectDepthFormat::kRegistered;
  // Registered depth lies in the colour camera's image: the colour camera's
  // intrinsics apply to both. Otherwise depth is in the IR camera's view.
  k.depth_intrinsics = default_intrinsics(registered ? 525.0 : 580.0);
  read_intrinsics(o, "", k.depth_intrinsics, uri);
  if (registered) {
    for (const char* key : {"color_fx", "color_fy", "color_cx", "color_cy", "color_distortion"})
      if (o.count(key))
        throw DeviceError(uri + ": option " + key +
                          ": not used with depth_format=registered (colour is registered to "
                          "depth and shares fx fy cx cy)");
    k.colour_intrinsics = k.depth_intrinsics;
  } else {
    k.colour_intrinsics = default_intrinsics(525.0);
    read_intrinsics(o, "color_", k.colour_intrinsics, uri);
  }
  return k;
}

KinectScanner::KinectScanner(std::string uri, std::string path, DeviceOptions options,
                             std::unique_ptr<FreenectApi> api)
    : uri_(std::move(uri)),
      path_(std::move(path)),
      who_("kinect:" + (path_.empty() ? std::string("0") : path_)),
      raw_options_(std::move(options)),
      opts_(kinect_options(path_, raw_options_, who_)),
      api_(std::move(api)) {
  if (!api_) throw DeviceError(who_ + ": this station was built without libfreenect");
}

KinectScanner::~KinectScanner() {
  try {
    close();
  } catch (...) {
  }
}

void KinectScanner::open() {
  if (open_) return;
  auto fail = [&](const std::string& why) {
    api_->close();
    throw DeviceError(who_ + ": " + why);
  };
  FreenectApi::Result r = api_->init();
  if (!r.ok()) fail(explain_failure(r.log, "libfreenect could not start (no USB access?)"));
  const int count = api_->device_count();
  if (count <= 0) fail("no Kinect found");
  if (opts_.index >= count)
    fail("no Kinect with index " + std::to_string(opts_.index) + " (" + std::to_string(count) +
         " found)");
  const auto formats = api_->depth_formats();
  bool offered = false;
  std::string names;
  for (auto f : formats) {
    offered = offered || f == opts_.depth_format;
    names += (names.empty() ? "" : ", ") + kinect_depth_format_name(f);
  }
  if (!offered)
    fail("depth format '" + kinect_depth_format_name(opts_.depth_format) +
         "' not offered by this libfreenect (offers: " + (names.empty() ? "none" : names) + ")");
  r = api_->open(opts_.index);
  if (!r.ok()) fail(explain_failure(r.log, "could not open the device"));

  if (opts_.tilt_deg) {
    r = api_->set_tilt(*opts_.tilt_deg);
    if (!r.ok()) fail(explain_failure(r.log, "tilt motor did not accept the angle"));
    const auto t0 = std::chrono::steady_clock::now();
    for (;;) {
      FreenectApi::TiltState s;
      r = api_->tilt_state(s);
      if (!r.ok()) fail(explain_failure(r.log, "could not read the tilt motor's state"));
      if (s.limit) {
        std::ostringstream m;
        m << "tilt motor stopped at its limit (asked " << *opts_.tilt_deg << " deg, reports "
          << s.degrees << ")";
        fail(m.str());
      }
      if (!s.moving) break;
      if (std::chrono::steady_clock::now() - t0 > std::chrono::milliseconds(opts_.tilt_timeout_ms))
        fail("tilt motor still moving after " + std::to_string(opts_.tilt_timeout_ms) + " ms");
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
  }

  depth_raw_.assign(static_cast<std::size_t>(kKinectWidth) * kKinectHeight, 0);
  rgb_.assign(static_cast<std::size_t>(kKinectWidth) * kKinectHeight * 3, 0);
  r = api_->start(
      opts_.depth_format,
      [this](const std::uint16_t* d, std::uint32_t) {
        if (depth_ready_) return;  // keep the first frame of this grab
        if (++depth_seen_ <= opts_.discard) return;
        std::memcpy(depth_raw_.data(), d, depth_raw_.size() * sizeof(std::uint16_t));
        depth_ready_ = true;
      },
      [this](const std::uint8_t* rgb, std::uint32_t) {
        if (video_ready_) return;
        if (++video_seen_ <= opts_.discard) return;
        std::memcpy(rgb_.data(), rgb, rgb_.size());
        video_ready_ = true;
      });
  if (!r.ok()) fail(explain_failure(r.log, "could not start the depth and colour streams"));
  open_ = true;
}

void KinectScanner::close() {
  if (api_) api_->close();
  open_ = false;
}

void KinectScanner::configure(const DeviceOptions& options) {
  DeviceOptions merged = raw_options_;
  for (const auto& [k, v] : options) merged[k] = v;
  KinectOptions parsed = kinect_options(path_, merged, who_);  // throws before changing anything
  const bool was_open = open_;
  if (was_open) close();
  raw_options_ = std::move(merged);
  opts_ = std::move(parsed);
  if (was_open) open();
}

ScannerCapabilities KinectScanner::capabilities() const {
  ScannerCapabilities c;
  c.depth = true;
  c.colour = true;
  c.intrinsics = opts_.depth_intrinsics;
  return c;
}

Frame KinectScanner::grab() {
  if (!open_) throw DeviceError(who_ + ": not open");
  depth_seen_ = video_seen_ = 0;
  depth_ready_ = video_ready_ = false;
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::milliseconds(opts_.timeout_ms);
  while (!(depth_ready_ && video_ready_)) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                          deadline - std::chrono::steady_clock::now())
                          .count();
    if (left <= 0) {
      std::string what = !depth_ready_ && !video_ready_ ? "frame"
                         : !depth_ready_                ? "depth frame"
                                                        : "colour frame";
      throw DeviceError(who_ + ": no " + what + " within " + std::to_string(opts_.timeout_ms) +
                        " ms (the device stopped sending)");
    }
    FreenectApi::Result r = api_->process_events(static_cast<int>(std::min<long long>(left, 100)));
    if (!r.ok() || contains(r.log, "disappeared") || contains(r.log, "marked dead")) {
      close();
      const std::string tail = log_tail(r.log);
      throw DeviceError(who_ + ": device gone while streaming (unplugged?)" +
                        (tail.empty() ? std::string() : " (libfreenect: " + tail + ")"));
    }
  }
  Frame f;
  f.timestamp = now_seconds();
  f.intrinsics = opts_.depth_intrinsics;
  f.depth.resize(depth_raw_.size());
  if (opts_.depth_format == KinectDepthFormat::kRaw11Bit) {
    for (std::size_t i = 0; i < depth_raw_.size(); ++i)
      f.depth[i] = kinect_disparity_to_metres(depth_raw_[i]);
  } else {
    // Millimetres; 0 = no data. (libfreenect also uses 0 here for no data.)
    for (std::size_t i = 0; i < depth_raw_.size(); ++i)
      f.depth[i] = static_cast<float>(depth_raw_[i]) * 0.001f;
  }
  f.colour_intrinsics = opts_.colour_intrinsics;
  f.colour = rgb_;
  return f;
}

std::optional<double> KinectScanner::tilt_degrees() {
  if (!open_) return std::nullopt;
  FreenectApi::TiltState s;
  if (!api_->tilt_state(s).ok()) return std::nullopt;
  return s.degrees;
}

#ifndef STATION_HAVE_FREENECT
std::unique_ptr<FreenectApi> make_libfreenect_api() { return nullptr; }
bool have_libfreenect() { return false; }
#endif

void register_kinect(DeviceRegistry& registry, FreenectApiFactory make_api) {
  registry.add_scanner(
      "kinect:",
      [make_api](const DeviceUri& uri, DeviceContext&) -> std::unique_ptr<Scanner> {
        return std::make_unique<KinectScanner>(uri.text, uri.path, uri.options, make_api());
      },
      [make_api] {
        std::vector<DeviceInfo> out;
        auto api = make_api();
        if (!api) return out;
        if (api->init().ok()) {
          const int n = api->device_count();
          for (int i = 0; i < n; ++i)
            out.push_back({"kinect:" + std::to_string(i), DeviceKind::kScanner,
                           "Kinect v1 (libfreenect): registered depth + RGB 640x480, tilt", true});
        }
        api->close();
        return out;
      });
}

}  // namespace station
