#include "core/sampling.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <unordered_map>
#include <utility>

#include "core/kdtree.h"

namespace station {

std::vector<Vec3f> voxel_downsample(const std::vector<Vec3f>& points, double voxel_size) {
  if (voxel_size <= 0) return points;
  struct Acc {
    Vec3d sum = Vec3d::Zero();
    int n = 0;
    std::size_t first = 0;  // first point index: gives a deterministic output order
  };
  std::unordered_map<std::uint64_t, Acc> cells;
  cells.reserve(points.size() / 2 + 1);
  const double inv = 1.0 / voxel_size;
  for (std::size_t i = 0; i < points.size(); ++i) {
    const Vec3f& p = points[i];
    // 21 bits per axis (offset so negatives pack): +-1 km at 1 mm voxels.
    const auto key_of = [&](float c) {
      return std::uint64_t(std::int64_t(std::floor(c * inv)) + (1 << 20)) & 0x1fffff;
    };
    const std::uint64_t key = key_of(p.x()) | (key_of(p.y()) << 21) | (key_of(p.z()) << 42);
    auto [it, fresh] = cells.try_emplace(key);
    if (fresh) it->second.first = i;
    it->second.sum += p.cast<double>();
    ++it->second.n;
  }
  std::vector<std::pair<std::size_t, Vec3f>> out;
  out.reserve(cells.size());
  for (const auto& [key, acc] : cells) out.emplace_back(acc.first, (acc.sum / acc.n).cast<float>());
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  std::vector<Vec3f> result;
  result.reserve(out.size());
  for (auto& [i, p] : out) result.push_back(p);
  return result;
}

std::vector<std::size_t> statistical_inliers(const std::vector<Vec3f>& points, int k, double std_ratio,
                                             std::vector<std::uint32_t>* neighbours) {
  std::vector<std::size_t> keep;
  if (k <= 0 || points.size() <= std::size_t(k) + 1) {
    keep.resize(points.size());
    for (std::size_t i = 0; i < points.size(); ++i) keep[i] = i;
    return keep;
  }
  const PointIndex index(points);
  std::vector<double> mean_dist(points.size());
  const std::size_t row = std::size_t(k) + 1;
  if (neighbours) neighbours->assign(points.size() * row, std::numeric_limits<std::uint32_t>::max());
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, points.size(), 512),
                    [&](const tbb::blocked_range<std::size_t>& r) {
                      // One buffer per range, not three allocations per point (the
                      // registration's prepare runs this over every scanned point).
                      std::vector<std::uint32_t> own(neighbours ? 0 : row);
                      std::vector<float> dist_sq(row);
                      for (std::size_t i = r.begin(); i != r.end(); ++i) {
                        std::uint32_t* idx = neighbours ? neighbours->data() + i * row : own.data();
                        // Sorted, closest first: the point itself, then its k neighbours.
                        const int found = index.knn_into(points[i], k + 1, idx, dist_sq.data());
                        double s = 0;
                        for (int j = 1; j < found; ++j) s += std::sqrt(dist_sq[std::size_t(j)]);
                        mean_dist[i] = found > 1 ? s / double(found - 1) : 0.0;
                      }
                    });
  double mean = 0, sq = 0;
  for (double d : mean_dist) mean += d;
  mean /= double(points.size());
  for (double d : mean_dist) sq += (d - mean) * (d - mean);
  const double threshold = mean + std_ratio * std::sqrt(sq / double(points.size()));
  for (std::size_t i = 0; i < points.size(); ++i)
    if (mean_dist[i] <= threshold) keep.push_back(i);
  return keep;
}

}  // namespace station
