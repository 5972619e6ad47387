#include "capture/session.h"

#include <yaml-cpp/yaml.h>

#include <Eigen/Geometry>
#include <Eigen/LU>
#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <limits>
#include <map>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <set>
#include <system_error>
#include <utility>

#include "core/atomic_file.h"
#include "core/yaml_keys.h"
#include "core/error.h"
#include "core/io.h"

namespace station {
namespace {

constexpr const char* kFormatName = "station-session";
// Rotation blocks may carry rounding from other tools (text with 6-9 digits),
// so orthonormality is checked loosely; the last row must be exact up to noise.
constexpr double kRotationTolerance = 1e-4;
constexpr double kLastRowTolerance = 1e-9;
// Values this close to unit length are kept bit-for-bit so that written
// manifests round-trip exactly.
constexpr double kUnitTolerance = 1e-12;
// Turntable angles (degrees) beyond this many are not a recording: 1e308 passed
// as finite, turned into inf in radians and gave NaN poses.
constexpr double kMaxAngleDeg = 1e6;
const char* const kAngleRange = "beyond +-1e6 degrees";

// ---- numbers ------------------------------------------------------------------

// Shortest text that parses back to exactly `v` (locale-independent).
std::string format_double(double v) {
  char buf[64];
  auto res = std::to_chars(buf, buf + sizeof buf, v);
  return std::string(buf, res.ptr);
}

bool is_yaml_special_float(const std::string& s) {
  static const char* const kSpecial[] = {".inf", ".Inf", ".INF", "+.inf", "+.Inf", "+.INF",
                                         "-.inf", "-.Inf", "-.INF", ".nan", ".NaN", ".NAN"};
  return std::find_if(std::begin(kSpecial), std::end(kSpecial),
                      [&](const char* k) { return s == k; }) != std::end(kSpecial);
}

enum class NumberStatus { kOk, kNotNumber, kNotFinite, kOutOfRange };

// from_chars rather than yaml-cpp's stream conversion: exact, locale-independent
// and it tells overflow apart from garbage.
NumberStatus parse_double(const std::string& text, double& out) {
  if (is_yaml_special_float(text)) return NumberStatus::kNotFinite;
  const char* first = text.data();
  const char* last = text.data() + text.size();
  if (first != last && *first == '+') ++first;  // YAML allows a leading '+'
  if (first == last || (text[0] == '+' && (*first == '+' || *first == '-')))
    return NumberStatus::kNotNumber;
  auto res = std::from_chars(first, last, out);
  if (res.ec == std::errc::result_out_of_range) return NumberStatus::kOutOfRange;
  if (res.ec != std::errc() || res.ptr != last) return NumberStatus::kNotNumber;
  if (!std::isfinite(out)) return NumberStatus::kNotFinite;  // "inf"/"nan" spellings
  return NumberStatus::kOk;
}

bool parse_integer(const std::string& text, long long& out) {
  const char* first = text.data();
  const char* last = text.data() + text.size();
  if (first != last && *first == '+') ++first;
  if (first == last || (text[0] == '+' && (*first == '+' || *first == '-'))) return false;
  auto res = std::from_chars(first, last, out);
  return res.ec == std::errc() && res.ptr == last;
}

// ---- shared semantic checks (reader and writer) --------------------------------
// Each returns an empty string when fine, otherwise the problem in words.

std::string relative_path_problem(const std::string& s) {
  if (s.empty()) return "empty path";
  if (s.find('\0') != std::string::npos) return "path contains a NUL character";
  const fs::path p(s);
  if (p.is_absolute() || p.has_root_directory() || p.has_root_name())
    return "absolute path \"" + s + "\" not allowed (paths are relative to the session folder)";
  for (const auto& part : p)
    if (part == "..")
      return "path \"" + s + "\" leaves the session folder ('..' not allowed)";
  const fs::path normal = p.lexically_normal();
  if (normal.empty() || normal == "." || !normal.has_filename())
    return "path \"" + s + "\" does not name a file";
  return {};
}

// Key used to detect two records naming the same file ("a.ply" vs "./a.ply").
std::string path_key(const std::string& s) {
  return fs::path(s).lexically_normal().generic_string();
}

// A pose's translation and the axis point past this are a corrupt file or wrong units
// (the views' own coordinates are refused past it, core/io_detail.h): 1e300 made the
// report's errors infinite.
constexpr double kMaxPosition = 1e9;
constexpr const char* kPositionRange = "beyond +-1e9 (wrong units or a corrupt file?)";

std::string pose_problem(const Eigen::Matrix4d& m) {
  if (!m.allFinite()) return "not finite";
  if (m.topRightCorner<3, 1>().cwiseAbs().maxCoeff() > kMaxPosition) return std::string("translation ") + kPositionRange;
  const double last_row_error = std::max({std::abs(m(3, 0)), std::abs(m(3, 1)),
                                          std::abs(m(3, 2)), std::abs(m(3, 3) - 1.0)});
  if (last_row_error > kLastRowTolerance) return "last row is not [0, 0, 0, 1]";
  const Eigen::Matrix3d r = m.topLeftCorner<3, 3>();
  const double ortho_error = (r.transpose() * r - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (ortho_error > kRotationTolerance)
    return "rotation is not orthonormal (max |R^T R - I| = " + format_double(ortho_error) +
           ", tolerance 1e-4)";
  if (r.determinant() < 0) return "rotation is a reflection (determinant < 0)";
  return {};
}

// Unit vector along `v` without overflow; empty optional when v is zero or not finite.
template <int N>
std::optional<Eigen::Matrix<double, N, 1>> normalized_robust(const Eigen::Matrix<double, N, 1>& v) {
  if (!v.allFinite()) return std::nullopt;
  const double scale = v.cwiseAbs().maxCoeff();
  if (scale == 0) return std::nullopt;
  if (std::abs(v.norm() - 1.0) <= kUnitTolerance) return v;  // keep exact when already unit
  const Eigen::Matrix<double, N, 1> s = v / scale;  // scaled first: no overflow in norm()
  return s / s.norm();
}

// Validates a manifest about to be written, so the station never writes a file
// it would refuse to read. Calls report(path, problem) on the first problem.
template <typename Report>
void check_manifest(const SessionManifest& m, Report&& report) {
  if (m.units != "m" && m.units != "mm") report("units", "must be \"m\" or \"mm\", got \"" + m.units + "\"");
  if (m.intrinsics) {
    const Intrinsics& in = *m.intrinsics;
    if (in.width <= 0) report("intrinsics.width", "must be positive");
    if (in.height <= 0) report("intrinsics.height", "must be positive");
    if (!(std::isfinite(in.fx) && in.fx > 0)) report("intrinsics.fx", "must be a positive finite number");
    if (!(std::isfinite(in.fy) && in.fy > 0)) report("intrinsics.fy", "must be a positive finite number");
    if (!std::isfinite(in.cx)) report("intrinsics.cx", "not finite");
    if (!std::isfinite(in.cy)) report("intrinsics.cy", "not finite");
  }
  if (m.axis) {
    if (!m.axis->point.allFinite()) report("turntable_axis.point", "not finite");
    else if (m.axis->point.cwiseAbs().maxCoeff() > kMaxPosition) report("turntable_axis.point", kPositionRange);
    if (!normalized_robust<3>(m.axis->direction))
      report("turntable_axis.direction", "zero length or not finite");
  }
  if (m.planned_views < 0) report("plan.views", "must not be negative");
  if (!std::isfinite(m.start_deg)) report("plan.start_deg", "not finite");
  if (std::abs(m.start_deg) > kMaxAngleDeg) report("plan.start_deg", kAngleRange);
  if (!std::isfinite(m.step_deg)) report("plan.step_deg", "not finite");
  if (std::abs(m.step_deg) > kMaxAngleDeg) report("plan.step_deg", kAngleRange);
  std::map<std::string, std::size_t> seen;
  for (std::size_t i = 0; i < m.views.size(); ++i) {
    const ViewRecord& v = m.views[i];
    const std::string at = "views[" + std::to_string(i) + "]";
    if (auto p = relative_path_problem(v.file); !p.empty()) report(at + ".file", p);
    auto [it, inserted] = seen.emplace(path_key(v.file), i);
    if (!inserted)
      report(at + ".file", "\"" + v.file + "\" is also views[" + std::to_string(it->second) + "].file");
    if (v.angle_deg && !std::isfinite(*v.angle_deg)) report(at + ".angle_deg", "not finite");
    if (v.angle_deg && std::abs(*v.angle_deg) > kMaxAngleDeg)
      report(at + ".angle_deg", kAngleRange);
    if (v.initial_pose)
      if (auto p = pose_problem(*v.initial_pose); !p.empty()) report(at + ".initial_pose", p);
    if (v.reference_pose)
      if (auto p = pose_problem(*v.reference_pose); !p.empty()) report(at + ".reference_pose", p);
    if (!v.colour_image.empty())
      if (auto p = relative_path_problem(v.colour_image); !p.empty()) report(at + ".color_image", p);
    if (v.timestamp && !std::isfinite(*v.timestamp)) report(at + ".timestamp", "not finite");
  }
}

// ---- reading ------------------------------------------------------------------

// Parses the node tree with field paths for messages; every accessor checks the
// node type first, since yaml-cpp throws (or worse) on mismatched access.
class ManifestReader {
 public:
  explicit ManifestReader(std::string name) : name_(std::move(name)) {}

  [[noreturn]] void fail(const std::string& path, const std::string& problem) const {
    throw FormatError(name_ + ": " + (path.empty() ? std::string() : path + ": ") + problem);
  }

  SessionManifest read(const YAML::Node& root) const {
    if (!root.IsDefined() || root.IsNull()) fail("", "empty file (not a station session manifest)");
    if (!root.IsMap()) fail("", "not a station session manifest (top level is not a map)");

    SessionManifest m;
    const YAML::Node format = root["format"];
    if (absent(format)) fail("format", "missing (not a station session manifest)");
    if (const std::string f = str(format, "format"); f != kFormatName)
      fail("format", "expected \"" + std::string(kFormatName) + "\", got \"" + clip(f) + "\"");

    const YAML::Node version = root["version"];
    if (absent(version)) fail("version", "missing");
    const long long ver = integer(version, "version");
    if (ver < 1 || ver > kManifestVersion)
      fail("version", "unsupported version " + std::to_string(ver) + " (this build reads version " +
                          std::to_string(kManifestVersion) + ")");
    m.version = int(ver);

    if (const YAML::Node n = root["created"]; !absent(n)) m.created = str(n, "created");
    if (const YAML::Node n = root["scanner"]; !absent(n)) m.scanner = str(n, "scanner");
    if (const YAML::Node n = root["turntable"]; !absent(n)) m.turntable = str(n, "turntable");
    if (const YAML::Node n = root["units"]; !absent(n)) {
      m.units = str(n, "units");
      if (m.units != "m" && m.units != "mm")
        fail("units", "must be \"m\" or \"mm\", got \"" + clip(m.units) + "\"");
    }
    if (const YAML::Node n = root["intrinsics"]; !absent(n)) m.intrinsics = intrinsics(n, "intrinsics");
    if (const YAML::Node n = root["turntable_axis"]; !absent(n)) m.axis = axis(n, "turntable_axis");
    if (const YAML::Node n = root["plan"]; !absent(n)) plan(n, "plan", m);

    const YAML::Node views = root["views"];
    if (absent(views)) fail("views", "missing (write \"views: []\" for a session without views)");
    if (!views.IsSequence()) fail("views", "not a list");
    std::map<std::string, std::size_t> seen;
    std::size_t i = 0;
    for (const YAML::Node& v : views) {
      const std::string at = "views[" + std::to_string(i) + "]";
      m.views.push_back(view(v, at));
      auto [it, inserted] = seen.emplace(path_key(m.views.back().file), i);
      if (!inserted)
        fail(at + ".file", "\"" + clip(m.views.back().file) + "\" is also views[" +
                               std::to_string(it->second) + "].file");
      ++i;
    }
    return m;
  }

 private:
  // Absent keys and explicit nulls ("key:" or "key: ~") both mean "not given".
  static bool absent(const YAML::Node& n) { return !n.IsDefined() || n.IsNull(); }

  // Keeps messages short when a field holds something huge.
  static std::string clip(const std::string& s) {
    return s.size() <= 80 ? s : s.substr(0, 77) + "...";
  }

  void require_map(const YAML::Node& n, const std::string& path) const {
    if (!n.IsMap()) fail(path, "not a map");
  }

  YAML::Node required(const YAML::Node& map, const char* key, const std::string& path) const {
    YAML::Node n = map[key];
    if (absent(n)) fail(path + "." + key, "missing");
    return n;
  }

  std::string str(const YAML::Node& n, const std::string& path) const {
    if (!n.IsScalar()) fail(path, "not a string");
    return n.Scalar();
  }

  double number(const YAML::Node& n, const std::string& path) const {
    if (!n.IsScalar()) fail(path, "not a number");
    double v = 0;
    switch (parse_double(n.Scalar(), v)) {
      case NumberStatus::kOk: return v;
      case NumberStatus::kNotFinite: fail(path, "not finite");
      case NumberStatus::kOutOfRange: fail(path, "number out of range");
      case NumberStatus::kNotNumber: break;
    }
    fail(path, "not a number");
  }

  double angle(const YAML::Node& n, const std::string& path) const {
    const double v = number(n, path);
    if (std::abs(v) > kMaxAngleDeg) fail(path, kAngleRange);
    return v;
  }

  long long integer(const YAML::Node& n, const std::string& path) const {
    long long v = 0;
    if (!n.IsScalar() || !parse_integer(n.Scalar(), v)) fail(path, "not an integer");
    return v;
  }

  template <int N>
  Eigen::Matrix<double, N, 1> numbers(const YAML::Node& n, const std::string& path) const {
    if (!n.IsSequence()) fail(path, "not a list of " + std::to_string(N) + " numbers");
    if (n.size() != std::size_t(N))
      fail(path, "has " + std::to_string(n.size()) + " entries, expected " + std::to_string(N));
    Eigen::Matrix<double, N, 1> out;
    int i = 0;
    for (const YAML::Node& e : n) {
      out[i] = number(e, path + "[" + std::to_string(i) + "]");
      ++i;
    }
    return out;
  }

  Intrinsics intrinsics(const YAML::Node& n, const std::string& path) const {
    require_map(n, path);
    Intrinsics in;
    const long long w = integer(required(n, "width", path), path + ".width");
    const long long h = integer(required(n, "height", path), path + ".height");
    if (w <= 0 || w > std::numeric_limits<int>::max()) fail(path + ".width", "must be a positive int");
    if (h <= 0 || h > std::numeric_limits<int>::max()) fail(path + ".height", "must be a positive int");
    in.width = int(w);
    in.height = int(h);
    in.fx = number(required(n, "fx", path), path + ".fx");
    in.fy = number(required(n, "fy", path), path + ".fy");
    in.cx = number(required(n, "cx", path), path + ".cx");
    in.cy = number(required(n, "cy", path), path + ".cy");
    if (in.fx <= 0) fail(path + ".fx", "must be positive");
    if (in.fy <= 0) fail(path + ".fy", "must be positive");
    if (const YAML::Node d = n["distortion"]; !absent(d)) {
      if (!d.IsSequence() || d.size() != 5) fail(path + ".distortion", "expected [k1, k2, p1, p2, k3]");
      for (std::size_t i = 0; i < 5; ++i)
        in.distortion[i] = number(d[i], path + ".distortion[" + std::to_string(i) + "]");
    }
    return in;
  }

  TurntableAxis axis(const YAML::Node& n, const std::string& path) const {
    require_map(n, path);
    TurntableAxis a;
    a.point = numbers<3>(required(n, "point", path), path + ".point");
    if (a.point.cwiseAbs().maxCoeff() > kMaxPosition) fail(path + ".point", kPositionRange);
    const Vec3d d = numbers<3>(required(n, "direction", path), path + ".direction");
    auto unit = normalized_robust<3>(d);
    if (!unit) fail(path + ".direction", "zero length");
    a.direction = *unit;
    return a;
  }

  void plan(const YAML::Node& n, const std::string& path, SessionManifest& m) const {
    require_map(n, path);
    const long long views = integer(required(n, "views", path), path + ".views");
    if (views < 0 || views > std::numeric_limits<int>::max())
      fail(path + ".views", "must be a non-negative int");
    m.planned_views = int(views);
    m.start_deg = 0;
    m.step_deg = views > 0 ? 360.0 / double(views) : 0.0;
    if (const YAML::Node s = n["start_deg"]; !absent(s))
      m.start_deg = angle(s, path + ".start_deg");
    if (const YAML::Node s = n["step_deg"]; !absent(s)) m.step_deg = angle(s, path + ".step_deg");
  }

  Eigen::Matrix4d pose(const YAML::Node& n, const std::string& path) const {
    if (!n.IsMap())
      fail(path, "not a map (expected {matrix: [16 numbers]} or "
                 "{translation: [x, y, z], quaternion: [x, y, z, w]})");
    const YAML::Node mat = n["matrix"], t = n["translation"], q = n["quaternion"];
    Eigen::Matrix4d m;
    if (!absent(mat)) {
      if (!absent(t) || !absent(q))
        fail(path, "give either matrix or translation + quaternion, not both");
      const Eigen::Matrix<double, 16, 1> v = numbers<16>(mat, path + ".matrix");
      for (int r = 0; r < 4; ++r)
        for (int c = 0; c < 4; ++c) m(r, c) = v[4 * r + c];  // row-major in the file
      if (auto p = pose_problem(m); !p.empty()) fail(path + ".matrix", p);
      m.row(3) << 0, 0, 0, 1;  // remove noise below kLastRowTolerance
      return m;
    }
    if (absent(t) && absent(q))
      fail(path, "needs matrix or translation + quaternion");
    if (absent(t)) fail(path + ".translation", "missing (quaternion given without it)");
    if (absent(q)) fail(path + ".quaternion", "missing (translation given without it)");
    const Vec3d tv = numbers<3>(t, path + ".translation");
    if (tv.cwiseAbs().maxCoeff() > kMaxPosition) fail(path + ".translation", kPositionRange);
    const Eigen::Vector4d qv = numbers<4>(q, path + ".quaternion");
    if (!normalized_robust<4>(qv)) fail(path + ".quaternion", "zero length");
    return pose_from_tq(tv, qv);
  }

  ViewRecord view(const YAML::Node& n, const std::string& at) const {
    if (!n.IsMap()) fail(at, "not a map");
    ViewRecord v;
    v.file = str(required(n, "file", at), at + ".file");
    if (auto p = relative_path_problem(v.file); !p.empty()) fail(at + ".file", p);
    if (const YAML::Node x = n["angle_deg"]; !absent(x)) v.angle_deg = angle(x, at + ".angle_deg");
    if (const YAML::Node x = n["initial_pose"]; !absent(x)) v.initial_pose = pose(x, at + ".initial_pose");
    if (const YAML::Node x = n["reference_pose"]; !absent(x))
      v.reference_pose = pose(x, at + ".reference_pose");
    if (const YAML::Node x = n["color_image"]; !absent(x)) {
      v.colour_image = str(x, at + ".color_image");
      if (auto p = relative_path_problem(v.colour_image); !p.empty()) fail(at + ".color_image", p);
    }
    if (const YAML::Node x = n["timestamp"]; !absent(x)) v.timestamp = number(x, at + ".timestamp");
    if (const YAML::Node x = n["points"]; !absent(x)) {
      const long long p = integer(x, at + ".points");
      if (p < 0) fail(at + ".points", "must not be negative");
      v.points = std::size_t(p);
    }
    return v;
  }

  std::string name_;
};

// ---- writing ------------------------------------------------------------------

// Numbers go out as pre-formatted plain scalars (shortest exact form), never
// through yaml-cpp's stream conversion, which depends on the global locale.
void emit_number(YAML::Emitter& out, double v) { out << format_double(v); }

// Free-form strings are double-quoted so that values like "null", "123" or
// "yes" stay strings for every YAML reader.
void emit_string(YAML::Emitter& out, const std::string& s) { out << YAML::DoubleQuoted << s; }

void emit_pose(YAML::Emitter& out, const Eigen::Matrix4d& m) {
  out << YAML::Flow << YAML::BeginMap << YAML::Key << "matrix" << YAML::Value << YAML::Flow
      << YAML::BeginSeq;
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) emit_number(out, m(r, c));
  out << YAML::EndSeq << YAML::EndMap;
}

void emit_vec3(YAML::Emitter& out, const Vec3d& v) {
  out << YAML::Flow << YAML::BeginSeq;
  for (int i = 0; i < 3; ++i) emit_number(out, v[i]);
  out << YAML::EndSeq;
}

std::string utc_now_iso8601() {
  const std::time_t t = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

// The session folder and manifest file for a path naming either.
std::pair<fs::path, fs::path> resolve_session_path(const fs::path& path) {
  std::error_code ec;
  if (fs::is_directory(path, ec)) return {path, path / kManifestName};
  fs::path dir = path.parent_path();
  if (dir.empty()) dir = ".";
  return {dir, path};
}

}  // namespace

// ---- public API -------------------------------------------------------------------

Eigen::Matrix4d pose_from_tq(const Vec3d& t, const Eigen::Vector4d& q_xyzw) {
  const auto unit = normalized_robust<4>(q_xyzw);
  if (!unit) throw InvalidInput("pose_from_tq: quaternion is zero or not finite");
  if (!t.allFinite()) throw InvalidInput("pose_from_tq: translation is not finite");
  const Eigen::Quaterniond q((*unit)[3], (*unit)[0], (*unit)[1], (*unit)[2]);  // (w, x, y, z)
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.topLeftCorner<3, 3>() = q.toRotationMatrix();
  m.topRightCorner<3, 1>() = t;
  return m;
}

std::string manifest_to_yaml(const SessionManifest& m) {
  check_manifest(m, [](const std::string& path, const std::string& problem) {
    throw InvalidInput("session manifest: " + path + ": " + problem);
  });

  YAML::Emitter out;
  out << YAML::BeginMap;
  out << YAML::Key << "format" << YAML::Value << kFormatName;
  out << YAML::Key << "version" << YAML::Value << kManifestVersion;
  out << YAML::Key << "created" << YAML::Value;
  emit_string(out, m.created);
  out << YAML::Key << "scanner" << YAML::Value;
  emit_string(out, m.scanner);
  if (!m.turntable.empty()) {
    out << YAML::Key << "turntable" << YAML::Value;
    emit_string(out, m.turntable);
  }
  out << YAML::Key << "units" << YAML::Value << m.units;
  if (m.intrinsics) {
    const Intrinsics& in = *m.intrinsics;
    out << YAML::Key << "intrinsics" << YAML::Value << YAML::Flow << YAML::BeginMap;
    out << YAML::Key << "width" << YAML::Value << in.width;
    out << YAML::Key << "height" << YAML::Value << in.height;
    out << YAML::Key << "fx" << YAML::Value;
    emit_number(out, in.fx);
    out << YAML::Key << "fy" << YAML::Value;
    emit_number(out, in.fy);
    out << YAML::Key << "cx" << YAML::Value;
    emit_number(out, in.cx);
    out << YAML::Key << "cy" << YAML::Value;
    emit_number(out, in.cy);
    if (in.distorted()) {
      out << YAML::Key << "distortion" << YAML::Value << YAML::Flow << YAML::BeginSeq;
      for (double d : in.distortion) emit_number(out, d);
      out << YAML::EndSeq;
    }
    out << YAML::EndMap;
  }
  if (m.axis) {
    out << YAML::Key << "turntable_axis" << YAML::Value << YAML::Flow << YAML::BeginMap;
    out << YAML::Key << "point" << YAML::Value;
    emit_vec3(out, m.axis->point);
    out << YAML::Key << "direction" << YAML::Value;
    emit_vec3(out, m.axis->direction);
    out << YAML::EndMap;
  }
  // Omitted when all defaults, which reads back as the same values.
  if (m.planned_views != 0 || m.start_deg != 0 || m.step_deg != 0) {
    out << YAML::Key << "plan" << YAML::Value << YAML::Flow << YAML::BeginMap;
    out << YAML::Key << "views" << YAML::Value << m.planned_views;
    out << YAML::Key << "start_deg" << YAML::Value;
    emit_number(out, m.start_deg);
    out << YAML::Key << "step_deg" << YAML::Value;
    emit_number(out, m.step_deg);
    out << YAML::EndMap;
  }
  out << YAML::Key << "views" << YAML::Value;
  if (m.views.empty()) {
    out << YAML::Flow << YAML::BeginSeq << YAML::EndSeq;
  } else {
    out << YAML::BeginSeq;
    for (const ViewRecord& v : m.views) {
      out << YAML::BeginMap;
      out << YAML::Key << "file" << YAML::Value;
      emit_string(out, v.file);
      if (v.angle_deg) {
        out << YAML::Key << "angle_deg" << YAML::Value;
        emit_number(out, *v.angle_deg);
      }
      if (v.initial_pose) {
        out << YAML::Key << "initial_pose" << YAML::Value;
        emit_pose(out, *v.initial_pose);
      }
      if (v.reference_pose) {
        out << YAML::Key << "reference_pose" << YAML::Value;
        emit_pose(out, *v.reference_pose);
      }
      if (!v.colour_image.empty()) {
        out << YAML::Key << "color_image" << YAML::Value;
        emit_string(out, v.colour_image);
      }
      if (v.timestamp) {
        out << YAML::Key << "timestamp" << YAML::Value;
        emit_number(out, *v.timestamp);
      }
      if (v.points != 0) out << YAML::Key << "points" << YAML::Value << v.points;
      out << YAML::EndMap;
    }
    out << YAML::EndSeq;
  }
  out << YAML::EndMap;
  if (!out.good()) throw InvalidInput("session manifest: cannot emit YAML: " + out.GetLastError());
  return std::string(out.c_str()) + "\n";
}

SessionManifest manifest_from_yaml(const std::string& text, const std::string& name) {
  // yaml-cpp reports problems through its own exceptions (and a few std ones);
  // every one becomes a FormatError so callers and fuzzers see a single type.
  YAML::Node root;
  try {
    root = YAML::Load(text);
  } catch (const YAML::Exception& e) {
    std::string where;
    if (!e.mark.is_null())
      where = " at line " + std::to_string(e.mark.line + 1) + ", column " +
              std::to_string(e.mark.column + 1);
    throw FormatError(name + ": YAML syntax error" + where + ": " + e.msg);
  } catch (const std::exception& e) {
    throw FormatError(name + ": cannot parse YAML: " + e.what());
  }
  if (const std::string dup = duplicate_yaml_key_message(duplicate_yaml_key(root), name); !dup.empty())
    throw FormatError(dup);
  try {
    return ManifestReader(name).read(root);
  } catch (const Error&) {
    throw;
  } catch (const YAML::Exception& e) {
    throw FormatError(name + ": " + e.msg);
  } catch (const std::exception& e) {
    throw FormatError(name + ": " + e.what());
  }
}

SessionManifest read_manifest(const fs::path& path) {
  const auto [dir, file] = resolve_session_path(path);
  std::error_code ec;
  if (!fs::exists(file, ec)) {
    if (file.filename() == kManifestName && fs::is_directory(dir, ec))
      throw IoError(dir.string() + ": not a session folder (no " + kManifestName + ")");
    throw IoError(file.string() + ": no such file or folder");
  }
  // A view or mesh given for the session (`register s/view_000.ply`): said so, not
  // as the YAML parser's "syntax error at line 16" in the PLY's binary part.
  std::string ext = file.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char ch) { return char(std::tolower(ch)); });
  for (const char* cloud : {".ply", ".pcd", ".obj", ".off", ".stl", ".png", ".jpg", ".jpeg"})
    if (ext == cloud)
      throw IoError(file.string() + ": a " + ext.substr(1) + " file, not a session: give the session's folder (or its " +
                    kManifestName + ")");
  SessionManifest m = manifest_from_yaml(read_file_bytes(file), file.string());
  for (std::size_t i = 0; i < m.views.size(); ++i) {
    const fs::path view = dir / m.views[i].file;
    if (!fs::is_regular_file(view, ec)) {
      const char* problem = fs::is_directory(view, ec) ? "view file is a folder"
                            : fs::exists(view, ec)     ? "view file is not a regular file"
                                                       : "view file missing";
      throw IoError(view.string() + ": " + problem + " (views[" + std::to_string(i) + "] of " + file.string() + ")");
    }
  }
  return m;
}

void write_manifest(const fs::path& dir, const SessionManifest& manifest) {
  write_file_atomic(dir / kManifestName, manifest_to_yaml(manifest));
}

Session::Session(fs::path dir, SessionManifest manifest)
    : dir_(std::move(dir)), manifest_(std::move(manifest)) {}

Session Session::create(const fs::path& dir, SessionManifest manifest) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) throw IoError(dir.string() + ": cannot create the session folder: " + ec.message());
  if (!fs::is_directory(dir, ec))
    throw IoError(dir.string() + ": cannot create the session folder: a file of that name exists");
  // symlink_status so that even a dangling link named session.yaml counts.
  if (fs::symlink_status(dir / kManifestName, ec).type() != fs::file_type::not_found)
    throw IoError(dir.string() + ": already holds a session; use --resume or another folder");
  if (manifest.created.empty()) manifest.created = utc_now_iso8601();
  manifest.version = kManifestVersion;
  write_manifest(dir, manifest);
  return Session(dir, std::move(manifest));
}

Session Session::open(const fs::path& dir) {
  SessionManifest m = read_manifest(dir);
  return Session(resolve_session_path(dir).first, std::move(m));
}

std::size_t Session::add_view(const Cloud& cloud, ViewRecord record,
                              const std::vector<std::uint8_t>& colour_rgb, int colour_width,
                              int colour_height) {
  const bool has_colour = !colour_rgb.empty();
  if (has_colour && (colour_width <= 0 || colour_height <= 0 ||
                    colour_rgb.size() != std::size_t(colour_width) * std::size_t(colour_height) * 3))
    throw InvalidInput("add_view: colour image is " + std::to_string(colour_rgb.size()) +
                       " bytes, expected width*height*3 with width " + std::to_string(colour_width) +
                       " and height " + std::to_string(colour_height));

  // Names already committed to the manifest are never overwritten (an imported
  // or hand-edited manifest may use view_NNN names out of order). Files on disk
  // that the manifest does not list are leftovers of an interrupted add_view and
  // are overwritten.
  std::set<std::string> taken;
  for (const ViewRecord& v : manifest_.views) {
    taken.insert(path_key(v.file));
    if (!v.colour_image.empty()) taken.insert(path_key(v.colour_image));
  }
  const std::size_t index = manifest_.views.size();
  std::string ply, png;
  for (std::size_t n = index;; ++n) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "view_%03zu.ply", n);
    ply = buf;
    std::snprintf(buf, sizeof buf, "view_%03zu.png", n);
    png = buf;
    if (!taken.count(ply) && !(has_colour && taken.count(png))) break;
  }
  record.file = ply;
  if (has_colour) record.colour_image = png;
  record.points = cloud.size();

  // Validate the record (with the rest) before touching the disk; on any failure
  // the in-memory manifest is left as it was.
  manifest_.views.push_back(std::move(record));
  try {
    check_manifest(manifest_, [](const std::string& path, const std::string& problem) {
      throw InvalidInput("add_view: " + path + ": " + problem);
    });
    write_ply(dir_ / ply, cloud, PlyFormat::kBinaryLittleEndian);
    if (has_colour) {
      // OpenCV encodes BGR; swap channels by hand (no imgproc dependency).
      cv::Mat bgr(colour_height, colour_width, CV_8UC3);
      for (int y = 0; y < colour_height; ++y) {
        const std::uint8_t* src = colour_rgb.data() + std::size_t(y) * colour_width * 3;
        std::uint8_t* dst = bgr.ptr<std::uint8_t>(y);
        for (int x = 0; x < colour_width; ++x) {
          dst[3 * x + 0] = src[3 * x + 2];
          dst[3 * x + 1] = src[3 * x + 1];
          dst[3 * x + 2] = src[3 * x + 0];
        }
      }
      std::vector<std::uint8_t> encoded;
      bool ok = false;
      try {
        ok = cv::imencode(".png", bgr, encoded);
      } catch (const cv::Exception& e) {
        throw IoError((dir_ / png).string() + ": cannot encode PNG: " + e.what());
      }
      if (!ok) throw IoError((dir_ / png).string() + ": cannot encode PNG");
      write_file_atomic(dir_ / png, std::string_view(reinterpret_cast<const char*>(encoded.data()),
                                                     encoded.size()));
    }
    save();
  } catch (...) {
    manifest_.views.pop_back();
    throw;
  }
  return index;
}

Cloud Session::load_view(std::size_t i) const {
  if (i >= manifest_.views.size())
    throw InvalidInput("load_view: view " + std::to_string(i) + " out of range (session has " +
                       std::to_string(manifest_.views.size()) + " views)");
  return read_cloud(dir_ / manifest_.views[i].file);
}

void Session::save() const { write_manifest(dir_, manifest_); }

}  // namespace station
