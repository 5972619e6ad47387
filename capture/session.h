#pragma once
// A scan session on disk: a folder holding `session.yaml` (the manifest) and one
// file per view. Schema: docs/session-format.md.
//
// Writes are crash-safe: each view file is written to a temporary and renamed,
// then the manifest is rewritten (also atomically) after every view, so an
// interrupted scan keeps every finished view and can be resumed.
#include <Eigen/Core>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "core/geometry.h"
#include "core/camera.h"

namespace station {

namespace fs = std::filesystem;

inline constexpr const char* kManifestName = "session.yaml";
inline constexpr int kManifestVersion = 1;

/// One view. Poses map the view's points (scanner frame) into the session's
/// object frame: p_object = pose * p_scanner.
struct ViewRecord {
  std::string file;                    ///< relative to the session folder (PLY/PCD)
  std::optional<double> angle_deg;     ///< turntable angle; empty for off-turntable views
  std::optional<Eigen::Matrix4d> initial_pose;    ///< prior for registration
  std::optional<Eigen::Matrix4d> reference_pose;  ///< truth, for measuring errors only
  std::string colour_image;             ///< relative path of a PNG/JPEG, empty when none
  std::optional<double> timestamp;     ///< seconds since the Unix epoch
  std::size_t points = 0;              ///< point count (informational; 0 = unknown)
};

struct SessionManifest {
  int version = kManifestVersion;
  std::string scanner;    ///< device URI that recorded it ("import" for imported scans)
  std::string turntable;  ///< device URI, empty when none
  std::optional<Intrinsics> intrinsics;
  std::optional<TurntableAxis> axis;
  std::string units = "m";
  /// The capture plan (used by --resume): views over 360 degrees.
  int planned_views = 0;
  double start_deg = 0;
  double step_deg = 0;
  std::string created;  ///< ISO 8601 UTC
  std::vector<ViewRecord> views;
};

/// Reads and validates a manifest; `path` is the session folder or the YAML file.
/// FormatError("FILE: views[3].angle_deg: not a number") naming the first problem.
/// Checks that every view file exists (IoError naming it when not).
SessionManifest read_manifest(const fs::path& path);
/// Writes `dir/session.yaml` atomically.
void write_manifest(const fs::path& dir, const SessionManifest& manifest);
/// The YAML text of a manifest (what write_manifest writes).
std::string manifest_to_yaml(const SessionManifest& manifest);
/// Parses YAML text; `name` labels error messages. Does not check view files.
SessionManifest manifest_from_yaml(const std::string& text, const std::string& name);

/// A session folder being recorded or read.
class Session {
 public:
  /// Creates `dir` (and parents) with an empty manifest; IoError if `dir` already
  /// holds a manifest (never overwrites a recording) or cannot be written.
  static Session create(const fs::path& dir, SessionManifest manifest);
  /// Opens an existing session (read_manifest's checks apply).
  static Session open(const fs::path& dir);

  const fs::path& dir() const { return dir_; }
  const SessionManifest& manifest() const { return manifest_; }
  SessionManifest& mutable_manifest() { return manifest_; }

  /// Writes the cloud as binary PLY "view_NNN.ply" (and the colour image as PNG
  /// when given: RGB rows, width*height*3 bytes), appends the record (file names
  /// filled in) and rewrites the manifest. Returns the view's index.
  std::size_t add_view(const Cloud& cloud, ViewRecord record,
                       const std::vector<std::uint8_t>& colour_rgb = {}, int colour_width = 0,
                       int colour_height = 0);
  /// Reads view i's cloud (FormatError/IoError naming the file).
  Cloud load_view(std::size_t i) const;
  /// Rewrites the manifest (atomic).
  void save() const;

 private:
  Session(fs::path dir, SessionManifest manifest);
  fs::path dir_;
  SessionManifest manifest_;
};

/// Rigid pose from translation + unit quaternion (x, y, z, w).
Eigen::Matrix4d pose_from_tq(const Vec3d& t, const Eigen::Vector4d& q_xyzw);

}  // namespace station
