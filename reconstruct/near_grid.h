#pragma once
// A bit grid over a point set's bounding box that answers "is x surely within
// `radius` of one of the points" without a nearest-neighbour search: a cell is set
// when every point of it lies within the radius of some input point (its centre within
// radius - half its diagonal, less a margin for float rounding). A set cell proves the
// distance is within the radius; an unset one proves nothing (ask the k-d tree).
//
// Used where a function is blended by the distance to the data (WindingClose's beta,
// MpuSurface::trusted): most queries lie near the data, and a 1-NN search per query was
// 16 % of the dragon's surface stage.
#include <cstdint>
#include <vector>

#include "core/geometry.h"

namespace station {

class NearGrid {
 public:
  NearGrid() = default;
  /// Cells of about radius / 2 (coarser where the box would need more than
  /// kMaxCells); empty (surely_near always false) when a cell would not fit inside the
  /// radius, or for no points or a radius <= 0. Parallel; the grid does not depend on
  /// the thread count.
  NearGrid(const std::vector<Vec3f>& points, double radius);

  /// True only when x lies within the radius of an input point (as a float distance
  /// from the k-d tree would measure it: the cells keep a margin for that rounding).
  bool surely_near(const Vec3d& x) const {
    if (bits_.empty()) return false;
    const double fx = (x.x() - origin_.x()) * inv_cell_, fy = (x.y() - origin_.y()) * inv_cell_,
                 fz = (x.z() - origin_.z()) * inv_cell_;
    if (!(fx >= 0 && fy >= 0 && fz >= 0 && fx < dims_[0] && fy < dims_[1] && fz < dims_[2])) return false;
    const std::size_t c = (std::size_t(fz) * std::size_t(dims_[1]) + std::size_t(fy)) * std::size_t(dims_[0]) + std::size_t(fx);
    return bits_[c >> 6] >> (c & 63) & 1;
  }
  bool empty() const { return bits_.empty(); }
  double cell() const { return cell_; }
  /// Cells set, and cells in all (for tests and diagnostics).
  std::size_t set_cells() const;
  std::size_t cells() const { return std::size_t(dims_[0]) * std::size_t(dims_[1]) * std::size_t(dims_[2]); }

  static constexpr double kMaxCells = 1 << 27;  // 16 MiB of bits

 private:
  Vec3d origin_ = Vec3d::Zero();
  double cell_ = 0, inv_cell_ = 0;
  int dims_[3] = {0, 0, 0};
  std::vector<std::uint64_t> bits_;
};

}  // namespace station
