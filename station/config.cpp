#include "station/config.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>

#include "core/error.h"
#include "core/io.h"
#include "core/threads.h"
#include "core/yaml_keys.h"
#include "drivers/registry.h"

#ifndef STATION_SOURCE_DIR
#define STATION_SOURCE_DIR "."
#endif

namespace station {
namespace {

namespace fs = std::filesystem;

// The largest bounding box diagonal a cloud of float coordinates can have (2 sqrt(3)
// FLT_MAX, about 1.2e39). A consolidation radius above it is larger than any cloud:
// refused with the profile, before `run` registers a session only to find it so.
const double kMaxCloudDiagonal = 2 * std::sqrt(3.0) * double(std::numeric_limits<float>::max());

struct Reader {
  std::string file;
  /// The keys given on the command line (dotted key -> "key=value" of --set): a bad
  /// value there is the option's fault, not the profile's.
  std::map<std::string, std::string> overridden;
  [[noreturn]] void fail(const std::string& key, const std::string& what) const {
    const std::string bare = key.substr(0, key.find('['));
    for (const auto& [k, kv] : overridden)
      if (k == bare || k.rfind(bare + ".", 0) == 0)
        throw InvalidInput("--set " + kv + ": " + (k == key ? "" : key + ": ") + what);
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
  /// `auto` (0) or an integer in [lo, hi].
  int auto_or_integer(const YAML::Node& n, const std::string& key, int lo, int hi) const {
    if (n.IsScalar() && n.Scalar() == "auto") return 0;
    const int v = integer(n, key);
    if (v < lo || v > hi) fail(key, "must be auto or " + std::to_string(lo) + ".." + std::to_string(hi));
    return v;
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
    if (!n.IsMap()) fail(where, "expected a mapping");  // (the whole file: load_config says so first)
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

/// "a.b.c=value" -> root[a][b][c] = value (a scalar; validated with the rest).
void apply_override(YAML::Node& root, const std::string& kv) {
  const auto eq = kv.find('=');
  if (eq == std::string::npos || eq == 0) throw InvalidInput("--set " + kv + ": expected section.key=value");
  const std::string key = kv.substr(0, eq), value = kv.substr(eq + 1);
  std::vector<std::string> parts;
  std::size_t start = 0;
  while (true) {
    const auto dot = key.find('.', start);
    parts.push_back(key.substr(start, dot == std::string::npos ? std::string::npos : dot - start));
    if (parts.back().empty()) throw InvalidInput("--set " + kv + ": empty key part");
    if (dot == std::string::npos) break;
    start = dot + 1;
  }
  if (root.IsNull()) root = YAML::Node(YAML::NodeType::Map);
  std::vector<YAML::Node> chain{root};
  for (std::size_t i = 0; i + 1 < parts.size(); ++i) {
    YAML::Node next = chain.back()[parts[i]];
    if (!next.IsDefined() || next.IsNull()) {
      chain.back()[parts[i]] = YAML::Node(YAML::NodeType::Map);
      next = chain.back()[parts[i]];
    } else if (!next.IsMap()) {
      throw InvalidInput("--set " + kv + ": " + parts[i] + " is not a section");
    }
    chain.push_back(next);
  }
  chain.back()[parts.back()] = value;
}

}  // namespace

const std::vector<std::string>& registration_objectives() {
  static const std::vector<std::string> names = {"point-to-plane", "symmetric", "point-to-point", "colored",
                                                 "generalized"};
  return names;
}

bool valid_registration_objective(const std::string& name) {
  const auto& n = registration_objectives();
  return std::find(n.begin(), n.end(), name) != n.end();
}

namespace {

void read_pipeline(const Reader& r, const YAML::Node& root, PipelineConfig& p) {
  if (const YAML::Node n = root["register"]) {
    r.check_keys(n, "register",
                 {"neighbors", "rounds", "loop_closure", "voxel_rel", "objective", "global", "check_angles", "prior_check",
                  "fuse", "fuse_distance", "rigid_turntable"});
    if (n["neighbors"]) p.reg.neighbors = r.integer(n["neighbors"], "register.neighbors");
    if (p.reg.neighbors < 1 || p.reg.neighbors > 8) r.fail("register.neighbors", "must be 1..8");
    if (n["rounds"]) p.reg.rounds = r.integer(n["rounds"], "register.rounds");
    if (p.reg.rounds < 1 || p.reg.rounds > 20) r.fail("register.rounds", "must be 1..20");
    if (n["loop_closure"]) p.reg.loop_closure = r.boolean(n["loop_closure"], "register.loop_closure");
    if (n["voxel_rel"]) p.reg.voxel_rel = r.number(n["voxel_rel"], "register.voxel_rel");
    // Coarser copies leave ICP's final correspondence distance (0.004 of the size) too
    // few points: at 0.015 a simulated bottle session came out half a turn off, from
    // 0.02 on every pair failed as "overlap none of the other views".
    if (p.reg.voxel_rel < 0 || p.reg.voxel_rel > 0.01)
      r.fail("register.voxel_rel", "must be 0..0.01 (coarser registration copies leave ICP too few points to match)");
    if (n["objective"]) p.reg.objective = r.text(n["objective"], "register.objective");
    if (!valid_registration_objective(p.reg.objective))
      r.fail("register.objective", "must be point-to-plane, symmetric, point-to-point, colored or generalized");
    if (n["global"]) p.reg.global = r.boolean(n["global"], "register.global");
    if (n["check_angles"]) p.reg.check_angles = r.boolean(n["check_angles"], "register.check_angles");
    if (n["prior_check"]) p.reg.prior_check = r.boolean(n["prior_check"], "register.prior_check");
    if (n["rigid_turntable"]) p.reg.rigid_turntable = r.text(n["rigid_turntable"], "register.rigid_turntable");
    if (p.reg.rigid_turntable != "auto" && p.reg.rigid_turntable != "on" && p.reg.rigid_turntable != "off")
      r.fail("register.rigid_turntable", "must be auto, on or off");
    if (n["fuse"]) p.reg.fuse = r.boolean(n["fuse"], "register.fuse");
    if (n["fuse_distance"]) p.reg.fuse_distance = r.number(n["fuse_distance"], "register.fuse_distance");
    if (!(p.reg.fuse_distance >= 0 && p.reg.fuse_distance <= 0.1))
      r.fail("register.fuse_distance", "must be 0..0.1 (metres; 0: the views' point spacing)");
  }
  if (const YAML::Node n = root["consolidate"]) {
    r.check_keys(n, "consolidate", {"enabled", "method", "points", "ratio", "iterations", "radius", "seed",
                                     "attraction", "fit_radius", "repulsion", "repulsion_weight", "blocks"});
    auto& c = p.consolidate;
    if (n["enabled"]) c.enabled = r.boolean(n["enabled"], "consolidate.enabled");
    if (n["method"]) c.method = r.text(n["method"], "consolidate.method");
    if (c.method != "wlop" && c.method != "edge-wlop") r.fail("consolidate.method", "must be wlop or edge-wlop");
    if (n["attraction"]) c.attraction = r.text(n["attraction"], "consolidate.attraction");
    if (c.attraction != "projection" && c.attraction != "l1")
      r.fail("consolidate.attraction", "must be projection or l1");
    if (n["fit_radius"]) c.fit_radius = r.number(n["fit_radius"], "consolidate.fit_radius");
    if (!(c.fit_radius >= 0) || !std::isfinite(c.fit_radius))
      r.fail("consolidate.fit_radius", "must be >= 0 (input units; 0: from the spacing and noise)");
    if (c.fit_radius > kMaxCloudDiagonal)
      r.fail("consolidate.fit_radius", "larger than any cloud can be (input units; 0: from the spacing and noise)");
    if (n["repulsion"]) c.repulsion = r.text(n["repulsion"], "consolidate.repulsion");
    if (c.repulsion != "full" && c.repulsion != "tangential")
      r.fail("consolidate.repulsion", "must be full or tangential");
    if (n["repulsion_weight"]) c.repulsion_weight = r.text(n["repulsion_weight"], "consolidate.repulsion_weight");
    if (c.repulsion_weight != "original" && c.repulsion_weight != "printed")
      r.fail("consolidate.repulsion_weight", "must be original or printed");
    if (n["points"]) {
      if (n["points"].IsScalar() && n["points"].Scalar() == "auto") {
        c.points_auto = true;
        c.points = 0;
      } else {
        const int v = r.integer(n["points"], "consolidate.points");
        if (v < 0) r.fail("consolidate.points", "must be auto or not negative");
        c.points_auto = false;
        c.points = std::size_t(v);
      }
    }
    if (n["ratio"]) c.ratio = r.number(n["ratio"], "consolidate.ratio");
    if (!(c.ratio > 0 && c.ratio <= 1)) r.fail("consolidate.ratio", "must be in (0, 1]");
    if (n["iterations"]) c.iterations = r.integer(n["iterations"], "consolidate.iterations");
    if (c.iterations < 1 || c.iterations > 1000) r.fail("consolidate.iterations", "must be 1..1000");
    if (n["seed"]) {
      // As eval's --seed: a whole number, 0 or more (a negative one was taken modulo 2^32).
      const int v = r.integer(n["seed"], "consolidate.seed");
      if (v < 0) r.fail("consolidate.seed", "must be a whole number, 0 or more");
      c.seed = unsigned(v);
    }
    if (n["radius"]) c.radius = r.number(n["radius"], "consolidate.radius");
    if (c.radius < 0) r.fail("consolidate.radius", "must not be negative (0: 4 d_bb / sqrt(|J|))");
    if (c.radius > kMaxCloudDiagonal)
      r.fail("consolidate.radius", "larger than any cloud can be (input units; 0: 4 d_bb / sqrt(|J|))");
    if (n["blocks"]) c.blocks = r.auto_or_integer(n["blocks"], "consolidate.blocks", 1, 4096);
  }
  if (const YAML::Node n = root["reconstruct"]) {
    r.check_keys(n, "reconstruct", {"surface", "resolution", "epsilon0", "extractor", "hole", "colour", "colour_method", "colour_multi",
                                     "colour_noise_robust", "colour_edges", "min_component", "table_plane", "winding_close",
                                     "blocks", "max_memory_gb", "snap_to_scans", "snap_significance"});
    auto& c = p.reconstruct;
    if (n["surface"]) c.surface = r.text(n["surface"], "reconstruct.surface");
    if (n["table_plane"]) c.table_plane = r.boolean(n["table_plane"], "reconstruct.table_plane");
    if (n["winding_close"]) c.winding_close = r.boolean(n["winding_close"], "reconstruct.winding_close");
    if (n["snap_to_scans"]) c.snap_to_scans = r.boolean(n["snap_to_scans"], "reconstruct.snap_to_scans");
    if (n["snap_significance"]) c.snap_significance = r.number(n["snap_significance"], "reconstruct.snap_significance");
    if (!(c.snap_significance >= 0 && c.snap_significance <= 100))
      r.fail("reconstruct.snap_significance", "must be 0..100 (standard errors)");
    if (c.surface != "mpu" && c.surface != "sdm") r.fail("reconstruct.surface", "must be mpu or sdm");
    if (n["resolution"]) c.resolution = r.auto_or_integer(n["resolution"], "reconstruct.resolution", 8, 4096);
    if (n["blocks"]) c.blocks = r.auto_or_integer(n["blocks"], "reconstruct.blocks", 1, 4096);
    if (n["max_memory_gb"]) c.max_memory_gb = r.number(n["max_memory_gb"], "reconstruct.max_memory_gb");
    if (!(c.max_memory_gb == 0 || (c.max_memory_gb >= 0.25 && c.max_memory_gb <= 1e6)))
      r.fail("reconstruct.max_memory_gb", "must be 0 (no bound) or at least 0.25 (GB per rank)");
    if (c.resolution > kMaxOnePieceResolution && !c.in_blocks())
      r.fail("reconstruct.resolution", "must be auto or 8.." + std::to_string(kMaxOnePieceResolution) +
                                           " in one piece (up to 4096 in blocks: reconstruct.blocks or "
                                           "max_memory_gb, docs/blocks.md)");
    if (n["epsilon0"]) c.epsilon0 = r.number(n["epsilon0"], "reconstruct.epsilon0");
    if (c.epsilon0 < 0 || c.epsilon0 > 0.1) r.fail("reconstruct.epsilon0", "must be 0 (automatic) .. 0.1");
    if (n["extractor"]) c.extractor = r.text(n["extractor"], "reconstruct.extractor");
    if (c.extractor != "mc" && c.extractor != "dmc") r.fail("reconstruct.extractor", "must be mc or dmc");
    if (n["hole"]) c.hole = r.text(n["hole"], "reconstruct.hole");
    if (c.hole != "auto" && c.hole != "close" && c.hole != "keep")
      r.fail("reconstruct.hole", "must be auto, close or keep");
    if (n["colour"]) c.colour = r.boolean(n["colour"], "reconstruct.colour");
    if (n["colour_method"]) c.colour_method = r.text(n["colour_method"], "reconstruct.colour_method");
    if (c.colour_method != "mpu" && c.colour_method != "nearest")
      r.fail("reconstruct.colour_method", "must be mpu or nearest");
    if (n["colour_multi"]) c.colour_multi = r.boolean(n["colour_multi"], "reconstruct.colour_multi");
    if (n["colour_noise_robust"])
      c.colour_noise_robust = r.boolean(n["colour_noise_robust"], "reconstruct.colour_noise_robust");
    if (n["colour_edges"]) c.colour_edges = r.boolean(n["colour_edges"], "reconstruct.colour_edges");
    if (n["min_component"]) c.min_component = r.number(n["min_component"], "reconstruct.min_component");
    if (c.min_component < 0 || c.min_component > 1) r.fail("reconstruct.min_component", "must be 0..1");
  }
  if (const YAML::Node n = root["sdm"]) {
    r.check_keys(n, "sdm", {"level"});
    if (n["level"]) p.sdm.level = r.integer(n["level"], "sdm.level");
    if (p.sdm.level < 0 || p.sdm.level > 7) r.fail("sdm.level", "must be 0..7");
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

namespace {
void flatten(const YAML::Node& n, const std::string& prefix, std::map<std::string, std::string>& out) {
  if (n.IsMap()) {
    for (const auto& kv : n) flatten(kv.second, (prefix.empty() ? "" : prefix + ".") + kv.first.as<std::string>(), out);
  } else if (n.IsScalar()) {
    out[prefix] = n.Scalar();
  }
}
}  // namespace

std::map<std::string, std::string> profile_values(const fs::path& path) {
  std::map<std::string, std::string> out;
  try {
    flatten(YAML::LoadFile(path.string()), "", out);
  } catch (const std::exception&) {
    out.clear();
  }
  return out;
}

StationConfig load_config(const fs::path& path, const std::vector<std::string>& overrides) {
  StationConfig cfg;
  cfg.source = path;
  Reader r{path.empty() ? std::string("built-in profile") : path.string(), {}};
  YAML::Node root;
  if (!path.empty()) {
    try {
      if (!fs::exists(path)) throw IoError(path.string() + ": cannot open: no such file");
      // Read whole first: a folder or a device is named as such (YAML::LoadFile gave
      // "internal error: basic_filebuf::underflow" for a folder).
      root = YAML::Load(read_file_bytes(path));
    } catch (const YAML::ParserException& e) {
      throw FormatError(path.string() + ": line " + std::to_string(e.mark.line + 1) + ": " + e.msg);
    } catch (const YAML::BadFile&) {
      throw IoError(path.string() + ": cannot read");
    }
    if (const std::string dup = duplicate_yaml_key_message(duplicate_yaml_key(root), path.string()); !dup.empty())
      throw FormatError(dup);
  }
  // A file that is one value or a list is no profile, whatever the overrides (a
  // --set on it failed inside yaml-cpp: "internal error").
  if (root.IsDefined() && !root.IsNull() && !root.IsMap())
    throw FormatError(r.file + ": expected a profile (a mapping of sections such as capture:, register:), got " +
                      (root.IsSequence() ? "a list" : "a single value"));
  for (const std::string& kv : overrides) {
    apply_override(root, kv);
    r.overridden[kv.substr(0, kv.find('='))] = kv;
  }
  if (root.IsNull()) return cfg;
  r.check_keys(root, "", {"scanner", "turntable", "capture", "register", "consolidate", "reconstruct",
                          "sdm", "threads"});
  read_pipeline(r, root, cfg.pipeline);
  const fs::path base = fs::absolute(path).parent_path();
  if (root["scanner"]) read_device(r, root["scanner"], "scanner", base, cfg.scanner_uri, cfg.scanner_options);
  if (root["turntable"])
    read_device(r, root["turntable"], "turntable", base, cfg.turntable_uri, cfg.turntable_options);
  if (root["threads"]) {
    cfg.threads = r.integer(root["threads"], "threads");
    if (cfg.threads < 0 || cfg.threads > kMaxThreads)
      r.fail("threads", "must be 0.." + std::to_string(kMaxThreads) + " (0: all cores)");
  }
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
    // The crop compares squared radii, so a negative radius cropped as its absolute value;
    // a height at or below the clearance kept nothing (every view empty).
    if (!(p.volume.radius > 0))
      r.fail("capture.volume.radius", "must be above 0 (metres, the working cylinder's radius about the axis)");
    if (!(p.volume.max_height > 0))
      r.fail("capture.volume.max_height", "must be above 0 (metres above the table top)");
    if (!(p.volume.table_clearance < p.volume.max_height)) {
      // The key given last: a --set one, else the one the file gives where it leaves
      // the other at its default.
      const YAML::Node v = c["volume"];
      const bool clearance_given = v && v["table_clearance"], height_given = v && v["max_height"];
      const bool blame_clearance = r.overridden.count("capture.volume.table_clearance") ||
                                   (!r.overridden.count("capture.volume.max_height") && clearance_given && !height_given);
      r.fail(blame_clearance ? "capture.volume.table_clearance" : "capture.volume.max_height",
             "the working volume's max_height must be above its table_clearance (metres above the table top)");
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
