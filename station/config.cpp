#include "station/config.h"

#include <yaml-cpp/yaml.h>

#include <cmath>

#include "core/error.h"
#include "drivers/registry.h"

#ifndef STATION_SOURCE_DIR
#define STATION_SOURCE_DIR "."
#endif

namespace station {
namespace {

namespace fs = std::filesystem;

struct Reader {
  std::string file;
  [[noreturn]] void fail(const std::string& key, const std::string& what) const {
    throw FormatError(file + ": " + key + ": " + what);
  }
  double number(const YAML::Node& n, const std::string& key) const {
    try {
      double v = n.as<double>();
      if (!std::isfinite(v)) fail(key, "not a finite number");
      return v;
    } catch (const YAML::Exception&) {
      fail(key, "not a number");
    }
  }
  int integer(const YAML::Node& n, const std::string& key) const {
    try {
      return n.as<int>();
    } catch (const YAML::Exception&) {
      fail(key, "not an integer");
    }
  }
  bool boolean(const YAML::Node& n, const std::string& key) const {
    try {
      return n.as<bool>();
    } catch (const YAML::Exception&) {
      fail(key, "not true/false");
    }
  }
  std::string text(const YAML::Node& n, const std::string& key) const {
    if (!n.IsScalar()) fail(key, "not a string");
    return n.as<std::string>();
  }
  Vec3d vec3(const YAML::Node& n, const std::string& key) const {
    if (!n.IsSequence() || n.size() != 3) fail(key, "expected [x, y, z]");
    return {number(n[0], key + "[0]"), number(n[1], key + "[1]"), number(n[2], key + "[2]")};
  }
  void check_keys(const YAML::Node& n, const std::string& where,
                  std::initializer_list<const char*> known) const {
    if (!n.IsMap()) fail(where, "expected a mapping");
    for (const auto& kv : n) {
      const std::string k = kv.first.as<std::string>();
      bool ok = false;
      for (const char* c : known) ok = ok || k == c;
      if (!ok) fail(where.empty() ? k : where + "." + k, "unknown key");
    }
  }
};

void read_device(const Reader& r, const YAML::Node& node, const std::string& where,
                 const fs::path& base, std::string& uri, DeviceOptions& options) {
  r.check_keys(node, where, {"uri", "options"});
  if (node["uri"]) uri = r.text(node["uri"], where + ".uri");
  if (const YAML::Node o = node["options"]) {
    if (!o.IsMap()) r.fail(where + ".options", "expected a mapping");
    for (const auto& kv : o) {
      const std::string key = kv.first.as<std::string>();
      std::string value = r.text(kv.second, where + ".options." + key);
      // File options are relative to the profile, so a profile works from any folder.
      if ((key == "mesh" || key == "session") && !value.empty() && fs::path(value).is_relative())
        value = (base / value).lexically_normal().string();
      options[key] = value;
    }
  }
}

}  // namespace

std::string compose_uri(const std::string& uri, const DeviceOptions& options) {
  DeviceUri parsed = parse_device_uri(uri);
  for (const auto& [k, v] : options) parsed.options[k] = v;
  std::string out = parsed.scheme + ":" + parsed.path;
  char sep = '?';
  for (const auto& [k, v] : parsed.options) {
    std::string enc;
    for (unsigned char c : v) {
      if (c == '&' || c == '%' || c == '?' || c == '=' || c == ' ' || c < 0x20) {
        char buf[4];
        std::snprintf(buf, sizeof buf, "%%%02X", c);
        enc += buf;
      } else {
        enc += char(c);
      }
    }
    out += sep + k + "=" + enc;
    sep = '&';
  }
  return out;
}

fs::path default_config_path() {
  fs::path p = fs::path(STATION_SOURCE_DIR) / "config" / "default.yaml";
  return fs::exists(p) ? p : fs::path();
}

StationConfig load_config(const fs::path& path) {
  StationConfig cfg;
  if (path.empty()) return cfg;
  cfg.source = path;
  Reader r{path.string()};
  YAML::Node root;
  try {
    if (!fs::exists(path)) throw IoError(path.string() + ": cannot open: no such file");
    root = YAML::LoadFile(path.string());
  } catch (const YAML::ParserException& e) {
    throw FormatError(path.string() + ": line " + std::to_string(e.mark.line + 1) + ": " + e.msg);
  } catch (const YAML::BadFile&) {
    throw IoError(path.string() + ": cannot read");
  }
  if (root.IsNull()) return cfg;
  r.check_keys(root, "", {"scanner", "turntable", "capture", "threads"});
  const fs::path base = fs::absolute(path).parent_path();
  if (root["scanner"]) read_device(r, root["scanner"], "scanner", base, cfg.scanner_uri, cfg.scanner_options);
  if (root["turntable"])
    read_device(r, root["turntable"], "turntable", base, cfg.turntable_uri, cfg.turntable_options);
  if (root["threads"]) cfg.threads = r.integer(root["threads"], "threads");
  if (const YAML::Node c = root["capture"]) {
    r.check_keys(c, "capture",
                 {"views", "start_deg", "step_deg", "settle_s", "crop", "volume", "axis"});
    CaptureParams& p = cfg.capture;
    if (c["views"]) p.views = r.integer(c["views"], "capture.views");
    if (p.views < 1 || p.views > 3600) r.fail("capture.views", "must be 1..3600");
    if (c["start_deg"]) p.start_deg = r.number(c["start_deg"], "capture.start_deg");
    if (c["step_deg"]) p.step_deg = r.number(c["step_deg"], "capture.step_deg");
    if (c["settle_s"]) p.settle_s = r.number(c["settle_s"], "capture.settle_s");
    if (p.settle_s < 0) r.fail("capture.settle_s", "must not be negative");
    if (c["crop"]) p.crop = r.boolean(c["crop"], "capture.crop");
    if (const YAML::Node v = c["volume"]) {
      r.check_keys(v, "capture.volume", {"radius", "max_height", "table_clearance"});
      if (v["radius"]) p.volume.radius = r.number(v["radius"], "capture.volume.radius");
      if (v["max_height"]) p.volume.max_height = r.number(v["max_height"], "capture.volume.max_height");
      if (v["table_clearance"])
        p.volume.table_clearance = r.number(v["table_clearance"], "capture.volume.table_clearance");
    }
    if (const YAML::Node a = c["axis"]) {
      r.check_keys(a, "capture.axis", {"point", "direction"});
      if (!a["point"] || !a["direction"]) r.fail("capture.axis", "needs point and direction");
      TurntableAxis axis;
      axis.point = r.vec3(a["point"], "capture.axis.point");
      axis.direction = r.vec3(a["direction"], "capture.axis.direction");
      if (axis.direction.norm() < 1e-12) r.fail("capture.axis.direction", "zero vector");
      axis.direction.normalize();
      p.axis = axis;
    }
  }
  return cfg;
}

}  // namespace station
