#pragma once
// Shared test helpers: procedural shapes and temporary folders.
#include <filesystem>
#include <string>

#include "core/geometry.h"

namespace station::test {

/// Icosphere of `radius` around `center`, subdivided `level` times (20 * 4^level faces),
/// outward-facing counter-clockwise faces.
Mesh icosphere(int level, double radius = 1.0, const Vec3f& center = Vec3f::Zero());
/// Axis-aligned box [min, max] as 12 triangles, outward-facing.
Mesh box(const Vec3f& min, const Vec3f& max);
/// n points on the sphere of radius r about the origin (Fibonacci spiral), with
/// outward unit normals.
Cloud fibonacci_sphere(int n, double r = 1.0);

/// A fresh empty folder under the system temp dir, removed with the object.
class TempDir {
 public:
  explicit TempDir(const std::string& tag = "station-test");
  ~TempDir();
  const std::filesystem::path& path() const { return path_; }
  std::filesystem::path operator/(const std::string& name) const { return path_ / name; }

 private:
  std::filesystem::path path_;
};

/// Undirected edges used by other than exactly two faces (0 for a closed manifold).
int open_edges(const Mesh& m);

/// Repository root (for bundled data).
std::filesystem::path source_dir();

/// Runs a shell command; its stdout and stderr together, and its exit code (-1 when
/// it did not exit normally).
struct CommandResult {
  int code = -1;
  std::string out;
};
CommandResult run_command(const std::string& command);

}  // namespace station::test
