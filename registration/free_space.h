#pragma once
// Free space as registered views saw it (docs/registration.md, "A free-space
// check"): a view whose sensor is known saw through the space between the
// sensor and each point it saw. A pose that puts another view's points there,
// by more than the noise, contradicts what was seen; a near-symmetric shape
// fitted turned puts part of the view outside the object, where a right pose
// puts it behind what the other views saw or where they did not look.
#include <vector>

#include <Eigen/Core>

#include "core/geometry.h"

namespace station {

class FreeSpace {
 public:
  FreeSpace();
  ~FreeSpace();
  FreeSpace(FreeSpace&&) noexcept;
  FreeSpace& operator=(FreeSpace&&) noexcept;

  /// Adds a view's sight: its points (scanner frame, the sensor at the origin)
  /// placed by `pose`. Points at the sensor or not finite are skipped. Returns
  /// the sight's index, or -1 where fewer than two points were left (no sight).
  int add(const std::vector<Vec3f>& points, const Eigen::Matrix4d& pose);
  bool empty() const;

  /// Share of (up to ~1000 of) `points`, moved by X, that lie in front of what
  /// some sight saw in their direction, by more than `margin`. A sight's point
  /// is in a point's direction within twice the larger of `spacing` / range
  /// and the sight's own angular spacing (its points' median angle to their
  /// nearest neighbour: the pixels, where they are coarser than `spacing`).
  /// Only points within `grow` of the sights' bounding box count (a hand or a
  /// stand in a hand-held view is not the object). `skip`: a sight (add's
  /// index) left out, the view's own.
  double seen_through(const std::vector<Vec3f>& points, const Eigen::Matrix4d& X, double margin, double spacing,
                      double grow, int skip = -1) const;

 private:
  struct Sight;
  std::vector<Sight> sights_;
  Vec3d lo_, hi_;  // the sights' points' bounding box
};

}  // namespace station
