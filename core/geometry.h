#pragma once
// Core data: point clouds and triangle meshes. Positions are metres in the
// frame the producer states (scanner frame for raw views, object frame after
// merging). Colours are 8-bit sRGB.
#include <Eigen/Core>
#include <cstdint>
#include <limits>
#include <vector>

namespace station {

using Vec3f = Eigen::Vector3f;
using Vec3d = Eigen::Vector3d;
using Vec2f = Eigen::Vector2f;
using Face = Eigen::Vector3i;  ///< three vertex indices, counter-clockwise seen from outside

/// 8-bit sRGB colour.
struct Rgb {
  std::uint8_t r = 0, g = 0, b = 0;
  friend bool operator==(const Rgb& a, const Rgb& b) {
    return a.r == b.r && a.g == b.g && a.b == b.b;
  }
};

/// N points; normals and colours are either empty or hold N entries.
struct Cloud {
  std::vector<Vec3f> points;
  std::vector<Vec3f> normals;
  std::vector<Rgb> colours;

  std::size_t size() const { return points.size(); }
  bool empty() const { return points.empty(); }
  bool has_normals() const { return !normals.empty(); }
  bool has_colours() const { return !colours.empty(); }
  /// Throws InvalidInput if normals/colours are present but sized differently.
  void check_consistent(const char* what = "cloud") const;
};

/// Triangle mesh: V vertices, F faces; normals and colours are per vertex,
/// either empty or V entries.
struct Mesh {
  std::vector<Vec3f> vertices;
  std::vector<Face> faces;
  std::vector<Vec3f> normals;
  std::vector<Rgb> colours;

  bool has_normals() const { return !normals.empty(); }
  bool has_colours() const { return !colours.empty(); }
  /// Throws InvalidInput on attribute size mismatch or out-of-range face indices.
  void check_consistent(const char* what = "mesh") const;
  /// The vertices (with their normals and colours) as a cloud.
  Cloud as_cloud() const;
};

/// Axis-aligned bounding box of a set of points (empty box when none).
struct Aabb {
  Vec3f min = Vec3f::Constant(std::numeric_limits<float>::max());
  Vec3f max = Vec3f::Constant(-std::numeric_limits<float>::max());
  void extend(const Vec3f& p) {
    min = min.cwiseMin(p);
    max = max.cwiseMax(p);
  }
  bool valid() const { return (min.array() <= max.array()).all(); }
  float diagonal() const { return valid() ? (max - min).norm() : 0.f; }
  Vec3f center() const { return 0.5f * (min + max); }
};
Aabb bounding_box(const std::vector<Vec3f>& points);

/// True when every coordinate of every point is finite.
bool all_finite(const std::vector<Vec3f>& points);

/// The points' indices in Z order (Morton order on a 2^21 lattice over the finite
/// points' bounding cube); equal cells and non-finite points keep their index order
/// (non-finite ones first). Nearby points come out near each other, so neighbourhood
/// work on a cloud taken in this order reads memory in runs.
std::vector<std::uint32_t> spatial_order(const std::vector<Vec3f>& points);

/// The cloud's points, with their normals and colours, in `order` (indices into it).
Cloud reordered(const Cloud& cloud, const std::vector<std::uint32_t>& order);

/// Area-weighted per-vertex normals (unit length; zero for isolated vertices).
std::vector<Vec3f> vertex_normals(const Mesh& mesh);

/// Applies a rigid (or any affine) 4x4 transform to points and rotates normals.
void transform_cloud(Cloud& cloud, const Eigen::Matrix4d& T);

}  // namespace station
