#include "drivers/openni_scanner.h"

#include <chrono>
#include <cmath>
#include <sstream>

#include "core/error.h"
#include "drivers/serial_turntable.h"  // option readers

namespace station {

struct OpenniScanner::Parsed {
  bool registration = true;
  int width = 0, height = 0;
  int timeout_ms = 2000;
  int discard = 1;
  bool has_depth_k = false, has_colour_k = false;
  Intrinsics depth_k, colour_k;  ///< from options (fx.. only; sizes come from the stream)
};

namespace {

bool has_any(const DeviceOptions& o, const std::string& prefix) {
  for (const char* k : {"fx", "fy", "cx", "cy"})
    if (o.count(prefix + k)) return true;
  return false;
}

Intrinsics read_k(const DeviceOptions& o, const std::string& prefix, const std::string& who) {
  for (const char* k : {"fx", "fy", "cx", "cy"})
    if (!o.count(prefix + k))
      throw DeviceError(who + ": option " + prefix + k + " missing (give " + prefix + "fx " +
                        prefix + "fy " + prefix + "cx " + prefix + "cy together)");
  Intrinsics k;
  k.fx = option_number(o, prefix + "fx", 0, 1e-6, 1e6, who);
  k.fy = option_number(o, prefix + "fy", 0, 1e-6, 1e6, who);
  k.cx = option_number(o, prefix + "cx", 0, -1e6, 1e6, who);
  k.cy = option_number(o, prefix + "cy", 0, -1e6, 1e6, who);
  option_distortion(o, prefix + "distortion", k, who);
  return k;
}

std::unique_ptr<OpenniScanner::Parsed> parse(const DeviceOptions& o, const std::string& who) {
  reject_unknown_options(
      o,
      {"registration", "width", "height", "timeout_ms", "discard", "fx", "fy", "cx", "cy",
       "distortion", "color_fx", "color_fy", "color_cx", "color_cy", "color_distortion"},
      who);
  auto p = std::make_unique<OpenniScanner::Parsed>();
  if (auto it = o.find("registration"); it != o.end()) {
    if (it->second == "on" || it->second == "1")
      p->registration = true;
    else if (it->second == "off" || it->second == "0")
      p->registration = false;
    else
      throw DeviceError(who + ": option registration=" + it->second + ": expected on or off");
  }
  p->width = option_integer(o, "width", 0, 0, 8192, who);
  p->height = option_integer(o, "height", 0, 0, 8192, who);
  if ((p->width == 0) != (p->height == 0))
    throw DeviceError(who + ": options width and height go together");
  p->timeout_ms = option_integer(o, "timeout_ms", p->timeout_ms, 1, 600000, who);
  p->discard = option_integer(o, "discard", p->discard, 0, 100, who);
  if (has_any(o, "") || o.count("distortion")) {
    p->depth_k = read_k(o, "", who);
    p->has_depth_k = true;
  }
  const bool colour_given = has_any(o, "color_") || o.count("color_distortion");
  if (colour_given && p->registration)
    throw DeviceError(who +
                      ": color_* intrinsics are not used with registration=on (colour "
                      "shares the depth intrinsics)");
  if (colour_given) {
    p->colour_k = read_k(o, "color_", who);
    p->has_colour_k = true;
  }
  return p;
}

/// Intrinsics of a stream: the options' when given, else from its field of view.
Intrinsics stream_intrinsics(const OpenniApi::StreamInfo& s, bool given, Intrinsics k,
                             const std::string& who, const char* what, const char* prefix) {
  k.width = s.width;
  k.height = s.height;
  if (given) return k;
  if (!(s.hfov > 0.01f && s.hfov < 3.1f && s.vfov > 0.01f && s.vfov < 3.1f))
    throw DeviceError(who + ": the " + what + " stream reports no field of view; give " + prefix +
                      "fx " + prefix + "fy " + prefix + "cx " + prefix + "cy");
  k.fx = s.width / 2.0 / std::tan(s.hfov / 2.0);
  k.fy = s.height / 2.0 / std::tan(s.vfov / 2.0);
  k.cx = (s.width - 1) / 2.0;
  k.cy = (s.height - 1) / 2.0;
  return k;
}

std::string explain(const OpenniApi::Result& r, const std::string& fallback) {
  if (r.code == -3) return r.error;
  const std::string& e = r.error;
  auto has = [&](const char* w) { return e.find(w) != std::string::npos; };
  std::string why = fallback;
  if (has("LIBUSB_ERROR_BUSY") || has("busy") || has("Busy"))
    why = "busy (another program has it open)";
  if (has("LIBUSB_ERROR_ACCESS") || has("ermission"))
    why =
        "no permission to open the USB device (install libopenni2-0's udev rule "
        "60-libopenni2-0.rules and add the user to group plugdev)";
  std::string line = e;
  while (!line.empty() && (line.back() == '\n' || line.back() == ' ')) line.pop_back();
  if (const auto nl = line.rfind('\n'); nl != std::string::npos) line = line.substr(nl + 1);
  while (!line.empty() && (line.front() == '\t' || line.front() == ' ')) line.erase(0, 1);
  return line.empty() ? why : why + " (OpenNI2: " + line + ")";
}

}  // namespace

#ifndef STATION_HAVE_OPENNI2
std::unique_ptr<OpenniApi> make_openni2_api() { return nullptr; }
bool have_openni2() { return false; }
#endif

OpenniScanner::OpenniScanner(std::string uri, std::string path, DeviceOptions options,
                             std::unique_ptr<OpenniApi> api)
    : uri_(std::move(uri)),
      path_(path.empty() ? std::string("0") : std::move(path)),
      who_("openni:" + path_),
      raw_(std::move(options)),
      p_(parse(raw_, who_)),
      api_(std::move(api)) {
  if (!api_) throw DeviceError(who_ + ": this station was built without OpenNI2");
}

OpenniScanner::~OpenniScanner() {
  try {
    close();
  } catch (...) {
  }
}

void OpenniScanner::open() {
  if (open_) return;
  auto fail = [&](const std::string& why) {
    api_->close();
    throw DeviceError(who_ + ": " + why);
  };
  OpenniApi::Result r = api_->init();
  if (!r.ok()) fail(explain(r, "OpenNI2 could not start"));
  std::string device = path_;
  const bool numeric = path_.find_first_not_of("0123456789") == std::string::npos;
  if (numeric) {
    const auto uris = api_->device_uris();
    const auto idx = static_cast<std::size_t>(std::stoul(path_));
    if (uris.empty()) fail("no OpenNI2 device found");
    if (idx >= uris.size())
      fail("no OpenNI2 device with index " + path_ + " (" + std::to_string(uris.size()) +
           " found)");
    device = uris[idx];
  }
  OpenniApi::StreamInfo ds, cs;
  r = api_->open(device, p_->width, p_->height, p_->registration, ds, cs);
  if (!r.ok()) fail(explain(r, "could not open " + device));
  if (p_->width && (ds.width != p_->width || ds.height != p_->height))
    fail("asked " + std::to_string(p_->width) + "x" + std::to_string(p_->height) +
         ", device gives " + std::to_string(ds.width) + "x" + std::to_string(ds.height));
  try {
    depth_k_ = stream_intrinsics(ds, p_->has_depth_k, p_->depth_k, who_, "depth", "");
    if (p_->registration) {
      colour_k_ = depth_k_;
      if (cs.width != ds.width || cs.height != ds.height)
        fail("registration=on needs colour and depth of one size (depth " +
             std::to_string(ds.width) + "x" + std::to_string(ds.height) + ", colour " +
             std::to_string(cs.width) + "x" + std::to_string(cs.height) + ")");
    } else {
      colour_k_ = stream_intrinsics(cs, p_->has_colour_k, p_->colour_k, who_, "colour", "color_");
    }
  } catch (const DeviceError&) {
    api_->close();
    throw;
  }
  open_ = true;
}

void OpenniScanner::close() {
  if (api_) api_->close();
  open_ = false;
}

void OpenniScanner::configure(const DeviceOptions& options) {
  DeviceOptions merged = raw_;
  for (const auto& [k, v] : options) merged[k] = v;
  auto parsed = parse(merged, who_);
  const bool was_open = open_;
  if (was_open) close();
  raw_ = std::move(merged);
  p_ = std::move(parsed);
  if (was_open) open();
}

ScannerCapabilities OpenniScanner::capabilities() const {
  ScannerCapabilities c;
  c.depth = true;
  c.colour = true;
  c.intrinsics = depth_k_;
  return c;
}

Frame OpenniScanner::grab() {
  if (!open_) throw DeviceError(who_ + ": not open");
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::milliseconds(p_->timeout_ms);
  OpenniApi::Frames fr;
  for (int i = 0; i <= p_->discard; ++i) {
    const long long left = std::chrono::duration_cast<std::chrono::milliseconds>(
                               deadline - std::chrono::steady_clock::now())
                               .count();
    OpenniApi::Result r =
        left > 0 ? api_->read(fr, static_cast<int>(left)) : OpenniApi::Result{-2, ""};
    if (r.code == -2)
      throw DeviceError(who_ + ": no frame within " + std::to_string(p_->timeout_ms) +
                        " ms (the device stopped sending)");
    if (!r.ok()) {
      close();
      throw DeviceError(who_ + ": " + explain(r, "device gone while streaming (unplugged?)"));
    }
  }
  if (fr.width != depth_k_.width || fr.height != depth_k_.height ||
      fr.depth_mm.size() != static_cast<std::size_t>(fr.width) * fr.height ||
      fr.rgb.size() != static_cast<std::size_t>(fr.colour_width) * fr.colour_height * 3 ||
      fr.colour_width != colour_k_.width || fr.colour_height != colour_k_.height)
    throw DeviceError(who_ + ": frame of an unexpected size");
  Frame f;
  f.timestamp =
      std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  f.intrinsics = depth_k_;
  f.depth.resize(fr.depth_mm.size());
  for (std::size_t i = 0; i < fr.depth_mm.size(); ++i) f.depth[i] = fr.depth_mm[i] * 0.001f;
  f.colour_intrinsics = colour_k_;
  f.colour = std::move(fr.rgb);
  return f;
}

void register_openni(DeviceRegistry& registry,
                     std::function<std::unique_ptr<OpenniApi>()> make_api) {
  registry.add_scanner(
      "openni:",
      [make_api](const DeviceUri& uri, DeviceContext&) -> std::unique_ptr<Scanner> {
        return std::make_unique<OpenniScanner>(uri.text, uri.path, uri.options, make_api());
      },
      [make_api] {
        std::vector<DeviceInfo> out;
        auto api = make_api();
        if (!api) return out;
        if (api->init().ok()) {
          const auto uris = api->device_uris();
          for (std::size_t i = 0; i < uris.size(); ++i)
            out.push_back({"openni:" + std::to_string(i), DeviceKind::kScanner,
                           "OpenNI2 depth camera " + uris[i], true});
        }
        api->close();
        return out;
      });
}

}  // namespace station
