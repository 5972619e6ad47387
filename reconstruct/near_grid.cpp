#include "reconstruct/near_grid.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <tbb/parallel_for.h>

namespace station {

NearGrid::NearGrid(const std::vector<Vec3f>& points, double radius) {
  if (points.empty() || !(radius > 0) || !std::isfinite(radius)) return;
  Vec3d lo = Vec3d::Constant(std::numeric_limits<double>::infinity()), hi = -lo;
  double max_abs = 0;
  for (const Vec3f& p : points) {
    if (!p.allFinite()) continue;
    const Vec3d q = p.cast<double>();
    lo = lo.cwiseMin(q);
    hi = hi.cwiseMax(q);
    max_abs = std::max(max_abs, q.cwiseAbs().maxCoeff());
  }
  if (!(lo.array() <= hi.array()).all()) return;
  origin_ = lo - Vec3d::Constant(radius);
  const Vec3d ext = hi + Vec3d::Constant(radius) - origin_;
  cell_ = 0.5 * radius;
  auto cells = [&](double c) {
    double total = 1;
    for (int a = 0; a < 3; ++a) total *= std::floor(ext[a] / c) + 1;
    return total;
  };
  // Coarser until it fits (a flat or long box shrinks on fewer axes than the cube root
  // assumes).
  for (double total = cells(cell_); total > kMaxCells; total = cells(cell_)) cell_ *= 1.01 * std::cbrt(total / kMaxCells);
  // Every point of a cell within `inner` of its centre's point is within the radius,
  // less a margin for the float coordinates and distance a k-d tree query uses.
  const double inner = radius * (1 - 1e-5) - 0.5 * std::sqrt(3.0) * cell_ - 4e-7 * max_abs;
  if (!(inner > 0)) return;
  inv_cell_ = 1 / cell_;
  for (int a = 0; a < 3; ++a) dims_[a] = int(std::floor(ext[a] * inv_cell_)) + 1;
  const std::size_t n = std::size_t(dims_[0]) * std::size_t(dims_[1]) * std::size_t(dims_[2]);
  bits_.assign((n + 63) / 64, 0);
  const double inner2 = inner * inner;
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, points.size(), 1024), [&](const auto& r) {
    for (std::size_t i = r.begin(); i < r.end(); ++i) {
      if (!points[i].allFinite()) continue;
      const Vec3d p = points[i].cast<double>();
      int c0[3], c1[3];
      for (int a = 0; a < 3; ++a) {
        c0[a] = std::max(0, int(std::ceil((p[a] - inner - origin_[a]) * inv_cell_ - 0.5)));
        c1[a] = std::min(dims_[a] - 1, int(std::floor((p[a] + inner - origin_[a]) * inv_cell_ - 0.5)));
      }
      for (int z = c0[2]; z <= c1[2]; ++z)
        for (int y = c0[1]; y <= c1[1]; ++y)
          for (int x = c0[0]; x <= c1[0]; ++x) {
            const Vec3d centre = origin_ + cell_ * Vec3d(x + 0.5, y + 0.5, z + 0.5);
            if ((centre - p).squaredNorm() > inner2) continue;
            const std::size_t c = (std::size_t(z) * std::size_t(dims_[1]) + std::size_t(y)) * std::size_t(dims_[0]) + std::size_t(x);
            __atomic_fetch_or(&bits_[c >> 6], std::uint64_t(1) << (c & 63), __ATOMIC_RELAXED);
          }
    }
  });
}

std::size_t NearGrid::set_cells() const {
  std::size_t n = 0;
  for (std::uint64_t w : bits_) n += std::size_t(__builtin_popcountll(w));
  return n;
}

}  // namespace station
