#include "reconstruct/detail/radius_grid.h"

#include <algorithm>
#include <limits>

#include "core/error.h"

namespace station::detail {

namespace {

// Dense cell arrays are allowed this many cells per point (plus a floor), so
// memory stays linear in the point count however small the radius is.
constexpr double kCellsPerPoint = 16.0;
constexpr double kMinCells = 1 << 16;

}  // namespace

void RadiusGrid::build(const Vec3d* points, std::size_t n, double radius) {
  if (!(radius > 0) || !std::isfinite(radius)) throw InvalidInput("radius grid: radius must be > 0");
  if (n >= std::numeric_limits<std::uint32_t>::max() / 2)
    throw InvalidInput("radius grid: too many points");
  radius_ = radius;
  id_.resize(n);
  pos_.resize(n);
  x_.assign(n + kPad, 0.0);
  y_.assign(n + kPad, 0.0);
  z_.assign(n + kPad, 0.0);
  key_.resize(n);
  if (n == 0) {
    n_[0] = n_[1] = n_[2] = 0;
    start_.assign(1, 0);
    return;
  }

  Vec3d lo = points[0], hi = points[0];
  for (std::size_t i = 1; i < n; ++i) {
    lo = lo.cwiseMin(points[i]);
    hi = hi.cwiseMax(points[i]);
  }
  const Vec3d extent = hi - lo;
  // Cells of radius / 2 in y and z (so a query visits at most 5 x 5 rows) and
  // radius / 8 along x. Cells a hair larger than that, so that the exact reach
  // (which bounds the rows) always covers the radius. When that many cells would
  // not fit the budget, coarser ones along x, then radius, then larger.
  const double widen = 1 + 1e-12;
  const double budget = std::max(kMinCells, kCellsPerPoint * double(n));
  auto cells_for = [&](const Vec3d& cell) {
    double total = 1;
    for (int a = 0; a < 3; ++a) total *= std::floor(extent[a] / cell[a]) + 1;
    return total;
  };
  const Vec3d options[] = {Vec3d(8, 2, 2), Vec3d(4, 2, 2), Vec3d(2, 2, 2), Vec3d(1, 1, 1)};
  bool fitted = false;
  for (const Vec3d& per_radius : options) {
    reach_ = per_radius;
    cell_ = (radius * widen) * per_radius.cwiseInverse();
    if (cells_for(cell_) <= budget) {
      fitted = true;
      break;
    }
  }
  if (!fitted) {
    // Larger cells than the radius: one cell each way always covers it.
    while (cells_for(cell_) > budget) cell_ *= 1.25;
    reach_ = Vec3d::Ones();
  }
  inv_cell_ = cell_.cwiseInverse();
  origin_ = lo;
  for (int a = 0; a < 3; ++a) n_[a] = int(std::floor(extent[a] / cell_[a])) + 1;

  const std::size_t cells = std::size_t(n_[0]) * n_[1] * n_[2];
  start_.assign(cells + 1, 0);
  for (std::size_t i = 0; i < n; ++i) {
    const Vec3d c = (points[i] - origin_).cwiseProduct(inv_cell_);
    const int ix = std::min(int(c.x()), n_[0] - 1), iy = std::min(int(c.y()), n_[1] - 1),
              iz = std::min(int(c.z()), n_[2] - 1);
    key_[i] = std::uint32_t((std::size_t(iz) * n_[1] + iy) * n_[0] + ix);
    ++start_[key_[i] + 1];
  }
  for (std::size_t c = 0; c < cells; ++c) start_[c + 1] += start_[c];
  // Stable scatter: within a cell, input order. start_ is shifted back after.
  for (std::size_t i = 0; i < n; ++i) {
    const std::uint32_t p = start_[key_[i]]++;
    id_[p] = int(i);
    pos_[i] = int(p);
    x_[p] = points[i].x();
    y_[p] = points[i].y();
    z_[p] = points[i].z();
  }
  for (std::size_t c = cells; c > 0; --c) start_[c] = start_[c - 1];
  start_[0] = 0;
}

}  // namespace station::detail
