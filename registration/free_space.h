#pragma once
// Free space as registered views saw it (docs/registration.md, "A free-space
// check"): a view whose sensor is known saw through the space between the
// sensor and each point it saw. A pose that puts another view's points there,
// by more than the noise, contradicts what was seen; a near-symmetric shape
// fitted turned puts part of the view outside the object, where a right pose
// puts it behind what the other views saw or where they did not look.
#include <memory>
#include <vector>

#include <Eigen/Core>

#include "core/geometry.h"

namespace station {

class PointIndex;

class FreeSpace {
 public:
  /// Adds a view's sight: its points (scanner frame, the sensor at the origin)
  /// placed by `pose`. Points at the sensor are skipped.
  void add(const std::vector<Vec3f>& points, const Eigen::Matrix4d& pose);
  bool empty() const { return sights_.empty(); }

  /// Share of (up to ~1000 of) `points`, moved by X, that lie in front of what
  /// some sight saw in their direction, by more than `margin`. A sight's point
  /// is in a point's direction within 2 * spacing / range radians (two point
  /// spacings at the point's range).
  double seen_through(const std::vector<Vec3f>& points, const Eigen::Matrix4d& X, double margin,
                      double spacing) const;

  FreeSpace();
  ~FreeSpace();
  FreeSpace(FreeSpace&&) noexcept;
  FreeSpace& operator=(FreeSpace&&) noexcept;

 private:
  struct Sight;
  std::vector<Sight> sights_;
};

}  // namespace station
