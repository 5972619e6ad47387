#pragma once
// Internal to reconstruct/: a uniform grid for fixed-radius neighbour queries,
// the one query WLOP makes (every sum of methods.md section 1 runs over the
// points within h). Points are stored sorted by cell as a structure of arrays,
// so a query scans a few contiguous runs instead of walking a tree; rebuilding
// is one counting sort, cheap enough to do for WLOP's projected set on every
// iteration. Build is single-threaded; const queries are thread-safe.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/geometry.h"

namespace station::detail {

class RadiusGrid {
 public:
  /// (Re)builds over n points for queries of radius up to `radius` (> 0, finite).
  /// Reuses its storage between builds. Points in one cell keep their input order,
  /// so the sorted order (and every sum taken in it) depends on the points and
  /// their order alone.
  void build(const Vec3d* points, std::size_t n, double radius);

  /// The coordinate arrays (and callers' arrays indexed by sorted position, by
  /// convention) hold this many readable entries past the end, so vector loops
  /// may load whole lanes at a run's end and mask the extra ones.
  static constexpr int kPad = 8;

  std::size_t size() const { return id_.size(); }
  double radius() const { return radius_; }
  /// Coordinates in sorted order (N entries each, then kPad zeros).
  const double* xs() const { return x_.data(); }
  const double* ys() const { return y_.data(); }
  const double* zs() const { return z_.data(); }
  /// Input index of each sorted position.
  const std::vector<int>& ids() const { return id_; }
  /// Sorted position of each input index.
  const std::vector<int>& positions() const { return pos_; }

  /// Runs [begin, end) of sorted positions that together hold every point within
  /// radius() of q (and some farther ones), in a fixed order for a grid and q.
  struct Run {
    int begin, end;
  };
  /// Upper bound on the runs of one query (5 x 5 rows of cells in y and z).
  static constexpr int kMaxRuns = 25;
  /// Writes the runs for q into out[0..count) and returns count (<= kMaxRuns).
  int runs(const Vec3d& q, Run* out) const {
    if (id_.empty()) return 0;
    int count = 0;
    const double r2 = radius_ * radius_;
    const Vec3d c = (q - origin_).cwiseProduct(inv_cell_);  // q in cell units
    const int z0 = cell_index(c.z() - reach_[2], 2), z1 = cell_index(c.z() + reach_[2], 2);
    const int y0 = cell_index(c.y() - reach_[1], 1), y1 = cell_index(c.y() + reach_[1], 1);
    // Squared gaps from q to each row's slab in y and in z (at most 5 each).
    double gy[8], gz[8];
    for (int iy = y0; iy <= y1; ++iy) gy[iy - y0] = gap(c.y(), iy, 1);
    for (int iz = z0; iz <= z1; ++iz) gz[iz - z0] = gap(c.z(), iz, 2);
    for (int iz = z0; iz <= z1; ++iz) {
      if (gz[iz - z0] > r2) continue;
      for (int iy = y0; iy <= y1; ++iy) {
        const double gyz = gz[iz - z0] + gy[iy - y0];
        if (gyz > r2) continue;
        // The row's cells along x that the ball reaches at this (y, z) gap.
        const double rx = std::sqrt(r2 - gyz) * inv_cell_[0];
        if (c.x() + rx < 0 || c.x() - rx > n_[0]) continue;
        const int x0 = cell_index(c.x() - rx, 0), x1 = cell_index(c.x() + rx, 0);
        const std::size_t row = (std::size_t(iz) * n_[1] + iy) * n_[0];
        const std::uint32_t b = start_[row + x0], e = start_[row + x1 + 1];
        if (b < e) out[count++] = Run{int(b), int(e)};
      }
    }
    return count;
  }

  /// Calls visit(begin, end) for each of runs(q).
  template <class Visit>
  void for_each_run(const Vec3d& q, Visit&& visit) const {
    Run r[kMaxRuns];
    const int n = runs(q, r);
    for (int i = 0; i < n; ++i) visit(r[i].begin, r[i].end);
  }

 private:
  // Cell containing coordinate v (cell units) along axis a, clamped to the grid.
  // Clamping in double first keeps far-away queries from overflowing int; a ball
  // that misses the grid gives an empty loop (or rows whose gap exceeds r).
  // (Truncation is floor here: negative values clamp to 0 anyway, and std::floor
  // is a library call on the x86-64 baseline.)
  int cell_index(double v, int a) const {
    if (!(v > 0)) return 0;
    return v >= n_[a] ? n_[a] - 1 : int(v);
  }
  // Squared distance (world units) from coordinate c (cell units) to cell slab i
  // along axis a.
  double gap(double c, int i, int a) const {
    const double d = c < i ? i - c : (c > i + 1 ? c - (i + 1) : 0.0);
    return d * d * cell_[a] * cell_[a];
  }

  double radius_ = 0;
  // Cell size, its inverse and the radius in cells, per axis: cells are long in y
  // and z (rows) and short along x, the run direction, where a finer split costs
  // nothing (a row's cells stay one contiguous run) and trims the run to the ball.
  Vec3d cell_ = Vec3d::Ones(), inv_cell_ = Vec3d::Ones(), reach_ = Vec3d::Ones();
  Vec3d origin_ = Vec3d::Zero();
  int n_[3] = {0, 0, 0};
  std::vector<std::uint32_t> start_;  // cell key -> first sorted position; size cells + 1
  std::vector<std::uint32_t> key_;    // scratch: cell key of each input point
  std::vector<double> x_, y_, z_;
  std::vector<int> id_, pos_;
};

}  // namespace station::detail
