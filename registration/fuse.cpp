#include "registration/fuse.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <unordered_map>

#include "core/kdtree.h"

namespace station {

namespace {

struct Cell {
  std::int64_t x, y, z;
  bool operator==(const Cell& o) const { return x == o.x && y == o.y && z == o.z; }
};

struct CellHash {
  std::size_t operator()(const Cell& c) const {
    // Large odd multipliers spread neighbouring cells over the buckets.
    return std::size_t(c.x * 73856093LL ^ c.y * 19349663LL ^ c.z * 83492791LL);
  }
};

/// One output point: running sums of what was fused into it.
struct Kept {
  Vec3d sum_pos = Vec3d::Zero();
  Vec3d sum_normal = Vec3d::Zero();
  Vec3d first_normal = Vec3d::Zero();
  double sum_rgb[3] = {0, 0, 0};
  int count = 0;
  Vec3f mean = Vec3f::Zero();  ///< sum_pos / count, what queries measure against
  Cell cell{0, 0, 0};          ///< the grid cell it is filed under (of `mean`)
};

}  // namespace

Cloud fuse_clouds(const std::vector<Cloud>& clouds, double distance, FuseStats* stats) {
  bool normals = true, colours = true;
  std::size_t input = 0;
  for (const Cloud& c : clouds) {
    input += c.size();
    if (c.empty()) continue;
    normals = normals && c.has_normals();
    colours = colours && c.has_colours();
  }
  const bool fuse = distance > 0 && std::isfinite(distance);
  const double inv = fuse ? 1.0 / distance : 0.0;
  const auto cell_of = [&](const Vec3f& p) {
    return Cell{std::int64_t(std::floor(double(p.x()) * inv)), std::int64_t(std::floor(double(p.y()) * inv)),
                std::int64_t(std::floor(double(p.z()) * inv))};
  };
  if (!fuse) {  // plain concatenation
    Cloud out;
    out.points.reserve(input);
    for (const Cloud& c : clouds)
      for (std::size_t i = 0; i < c.size(); ++i) {
        if (!c.points[i].allFinite()) continue;
        out.points.push_back(c.points[i]);
        if (normals) out.normals.push_back(c.normals[i]);
        if (colours) out.colours.push_back(c.colours[i]);
      }
    if (stats) *stats = FuseStats{input, out.size(), 0};
    return out;
  }
  std::vector<Kept> kept;
  kept.reserve(input);
  std::unordered_map<Cell, std::vector<std::uint32_t>, CellHash> grid;
  const auto file = [&](std::uint32_t m) { grid[kept[m].cell].push_back(m); };
  const auto unfile = [&](std::uint32_t m) {
    auto it = grid.find(kept[m].cell);
    if (it == grid.end()) return;
    auto& v = it->second;
    for (std::size_t k = 0; k < v.size(); ++k)
      if (v[k] == m) {
        v[k] = v.back();
        v.pop_back();
        break;
      }
  };
  const float max_sq = float(distance * distance);
  constexpr std::uint32_t kNone = std::numeric_limits<std::uint32_t>::max();
  std::vector<std::uint32_t> claim_point;  // per kept point: the claiming point of the current cloud
  std::vector<float> claim_dist;
  std::size_t fused_count = 0;

  for (const Cloud& c : clouds) {
    const std::size_t n = c.size();
    // 1. Each point's nearest kept point (from earlier clouds) within the
    //    distance; the grid is read-only here, so in parallel.
    std::vector<std::uint32_t> best(n, kNone);
    std::vector<float> best_sq(n, std::numeric_limits<float>::infinity());
    if (fuse && !kept.empty()) {
      tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 1024), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) {
          const Vec3f& p = c.points[i];
          if (!p.allFinite()) continue;
          const Cell q = cell_of(p);
          for (std::int64_t dx = -1; dx <= 1; ++dx)
            for (std::int64_t dy = -1; dy <= 1; ++dy)
              for (std::int64_t dz = -1; dz <= 1; ++dz) {
                const auto it = grid.find(Cell{q.x + dx, q.y + dy, q.z + dz});
                if (it == grid.end()) continue;
                for (std::uint32_t m : it->second) {
                  const float d = (kept[m].mean - p).squaredNorm();
                  if (d <= max_sq && (d < best_sq[i] || (d == best_sq[i] && m < best[i]))) {
                    best_sq[i] = d;
                    best[i] = m;
                  }
                }
              }
        }
      });
    }
    // 2. A kept point takes one point of this cloud: the nearest claim (the
    //    lower index on a tie). Serial, in point order: deterministic.
    claim_point.assign(kept.size(), kNone);
    claim_dist.assign(kept.size(), std::numeric_limits<float>::infinity());
    for (std::size_t i = 0; i < n; ++i) {
      const std::uint32_t m = best[i];
      if (m == kNone) continue;
      if (best_sq[i] < claim_dist[m]) {
        claim_dist[m] = best_sq[i];
        claim_point[m] = std::uint32_t(i);
      }
    }
    // 3. Fuse the winners, keep everything else as new points.
    const std::size_t before = kept.size();
    std::vector<std::uint32_t> moved;
    for (std::size_t i = 0; i < n; ++i) {
      const Vec3f& p = c.points[i];
      if (!p.allFinite()) continue;  // callers pass finite clouds; never let a NaN in
      std::uint32_t m = best[i];
      const bool fused = m != kNone && claim_point[m] == i;
      if (!fused) {
        m = std::uint32_t(kept.size());
        kept.emplace_back();
      }
      Kept& k = kept[m];
      k.sum_pos += p.cast<double>();
      if (normals) {
        Vec3d nv = c.normals[i].cast<double>();
        if (k.count == 0) k.first_normal = nv;
        else if (nv.dot(k.first_normal) < 0) nv = -nv;
        k.sum_normal += nv;
      }
      if (colours) {
        k.sum_rgb[0] += c.colours[i].r;
        k.sum_rgb[1] += c.colours[i].g;
        k.sum_rgb[2] += c.colours[i].b;
      }
      ++k.count;
      k.mean = (k.sum_pos / double(k.count)).cast<float>();
      if (fused) {
        moved.push_back(m);
        ++fused_count;
      }
    }
    if (!fuse) continue;
    // Re-file the fused points whose mean crossed into another cell, file the new ones.
    for (std::uint32_t m : moved) {
      const Cell cell = cell_of(kept[m].mean);
      if (cell == kept[m].cell) continue;
      unfile(m);
      kept[m].cell = cell;
      file(m);
    }
    for (std::size_t m = before; m < kept.size(); ++m) {
      kept[m].cell = cell_of(kept[m].mean);
      file(std::uint32_t(m));
    }
  }

  Cloud out;
  out.points.reserve(kept.size());
  for (const Kept& k : kept) out.points.push_back(k.mean);
  if (normals && !kept.empty()) {
    out.normals.reserve(kept.size());
    for (const Kept& k : kept) {
      const double len = k.sum_normal.norm();
      out.normals.push_back(len > 1e-12 ? Vec3f((k.sum_normal / len).cast<float>())
                                        : Vec3f(k.first_normal.cast<float>()));
    }
  }
  if (colours && !kept.empty()) {
    out.colours.reserve(kept.size());
    const auto channel = [](double sum, int count) {
      return std::uint8_t(std::lround(std::clamp(sum / double(count), 0.0, 255.0)));
    };
    for (const Kept& k : kept)
      out.colours.push_back(
          Rgb{channel(k.sum_rgb[0], k.count), channel(k.sum_rgb[1], k.count), channel(k.sum_rgb[2], k.count)});
  }
  if (stats) {
    stats->input = input;
    stats->output = out.size();
    stats->fused = fused_count;
  }
  return out;
}

double median_spacing(const std::vector<Vec3f>& points, std::size_t samples) {
  if (points.size() < 2 || samples == 0) return 0.0;
  const PointIndex index(points);
  const std::size_t step = std::max<std::size_t>(1, points.size() / samples);
  std::vector<double> d;
  for (std::size_t i = 0; i < points.size(); i += step) {
    const auto nn = index.knn(points[i], 2);  // itself first
    if (nn.size() == 2) d.push_back(nn[1].second);
  }
  if (d.empty()) return 0.0;
  std::nth_element(d.begin(), d.begin() + std::ptrdiff_t(d.size() / 2), d.end());
  return d[d.size() / 2];
}

}  // namespace station
