#pragma once
// Bounding volume hierarchy over a triangle mesh: ray casting (the simulated
// scanner) and closest-point queries (evaluation metrics). Built once, then
// queried concurrently from any number of threads (queries are const).
#include <limits>
#include <memory>
#include <optional>

#include "core/geometry.h"

namespace station {

struct Ray {
  Vec3d origin;
  Vec3d direction;  ///< need not be unit length; hit.t is in units of it
  double t_min = 0;
  double t_max = std::numeric_limits<double>::infinity();
};

struct RayHit {
  double t = 0;      ///< origin + t * direction is the hit point
  int face = -1;     ///< index into mesh.faces
  double u = 0, v = 0;  ///< barycentrics: point = (1-u-v) a + u b + v c
};

struct ClosestPoint {
  Vec3d point;
  double distance = 0;
  int face = -1;
  double u = 0, v = 0;  ///< barycentrics as in RayHit
};

class TriangleBvh {
 public:
  /// Copies the geometry; InvalidInput on an empty mesh or bad indices.
  /// Built with a binned surface-area heuristic; O(F log F).
  explicit TriangleBvh(const Mesh& mesh);
  ~TriangleBvh();
  TriangleBvh(TriangleBvh&&) noexcept;
  TriangleBvh& operator=(TriangleBvh&&) noexcept;

  /// Nearest hit with t in [t_min, t_max], both triangle sides count.
  std::optional<RayHit> intersect(const Ray& ray) const;
  /// True if anything is hit in [t_min, t_max] (shadow/occlusion test, early exit).
  bool occluded(const Ray& ray) const;
  /// Closest point of the surface to p.
  ClosestPoint closest_point(const Vec3d& p) const;
  std::size_t triangle_count() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace station
