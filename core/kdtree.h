#pragma once
// Nearest-neighbour index over a fixed set of 3-D points (nanoflann inside;
// kept out of this header so including it stays cheap). Queries are const and
// thread-safe.
#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <utility>
#include <vector>

#include "core/geometry.h"

namespace station {

class PointIndex {
 public:
  /// Keeps a copy of the points. An empty set is allowed (queries return nothing).
  explicit PointIndex(std::vector<Vec3f> points);
  ~PointIndex();
  PointIndex(PointIndex&&) noexcept;
  PointIndex& operator=(PointIndex&&) noexcept;

  std::size_t size() const;
  const std::vector<Vec3f>& points() const;
  /// Index and Euclidean distance of the nearest point; {-1, inf} when empty.
  std::pair<int, float> nearest(const Vec3f& q) const;
  /// The nearest point if it lies within `max_distance` (inclusive), else
  /// {-1, inf}. The bound prunes the search: much cheaper than nearest() for
  /// queries far from every point (ICP's non-overlapping parts).
  std::pair<int, float> nearest_within(const Vec3f& q, float max_distance) const;
  /// The k nearest (fewer if the set is smaller), closest first: (index, distance).
  std::vector<std::pair<int, float>> knn(const Vec3f& q, int k) const;
  /// The same k nearest without allocating: indices and squared distances into the
  /// caller's arrays (room for k each), closest first; returns how many were found.
  int knn_into(const Vec3f& q, int k, std::uint32_t* index, float* distance_sq) const;
  /// All points within `radius` (Euclidean), closest first.
  std::vector<std::pair<int, float>> radius(const Vec3f& q, float radius) const;
  /// The same points in the index's own order (deterministic for the index, not
  /// sorted by distance): cheaper when the order does not matter.
  std::vector<std::pair<int, float>> radius_unsorted(const Vec3f& q, float radius) const;
  /// radius(q, radius) when it holds at most `count` points (the same points in the
  /// same order), else nothing: the search stops at the (count + 1)-th point, so a
  /// ball holding most of the cloud costs no more than a small one.
  std::optional<std::vector<std::pair<int, float>>> radius_at_most(const Vec3f& q, float radius,
                                                                   std::size_t count) const;
  /// Whether `accept(index, distance)` holds for some point within `radius` (inclusive,
  /// as radius()): the points are offered in radius_unsorted's order, and the search
  /// stops at the first accepted one.
  bool any_in_radius(const Vec3f& q, float radius, const std::function<bool(int, float)>& accept) const;

 private:
  std::vector<std::pair<int, float>> radius_search(const Vec3f& q, float radius, bool sorted) const;
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// The points' sample spacing, 1 / sqrt(density) with the density from the distance
/// to the 8th neighbour (as MpuDiagnostics::sample_spacing): the median over up to
/// `max_samples` evenly strided points. 0 with fewer than 9 points.
double sample_spacing(const PointIndex& index, std::size_t max_samples = 4096);

/// The sample spacing at one of the index's points, from its 8 nearest neighbours:
/// sqrt(area / 8), the area that of the disc to the 8th neighbour (radius r_8), or of
/// the sector whose centroid lies where the neighbours' does (a point at the data's
/// edge has them on one side: a half disc's centroid lies 0.42 r_8 off the point, a
/// quarter's at a corner 0.60 r_8), less the offset chance alone gives 8 points
/// (r_8 / 4 in root mean square). 0 with fewer than 9 points.
double local_sample_spacing(const PointIndex& index, int point);

/// Where data are sparser than usual (a depth camera's far field, a part seen at a
/// glancing angle), distances measured in their spacing reach further there: a point's
/// allowance is the local spacing round it over `median` (the median of
/// local_sample_spacing over the point and its 8 nearest neighbours, over
/// sample_spacing) where that is kSparseSpacing or more, at most kSparseSpacingCap, else
/// 1. The margin: the local estimate is rough at the data's corners (up to 1.3x on a
/// grid). The neighbours' median: a stray point near denser data (a depth camera's
/// flying pixel) reads as very sparse alone, and would hold surface round it.
inline constexpr double kSparseSpacing = 1.5;
inline constexpr double kSparseSpacingCap = 4;
double sparse_allowance(const PointIndex& index, int point, double median, double from = kSparseSpacing);

/// sparse_allowance at the index's points, each local spacing computed once, when first
/// asked for (thread-safe: racing threads store the same value). The index must outlive it.
class SparseAllowances {
 public:
  SparseAllowances(const PointIndex& index, double median, double from = kSparseSpacing);
  ~SparseAllowances();
  double operator()(int point) const;

 private:
  double local(int point) const;
  const PointIndex& index_;
  double median_, from_;
  std::unique_ptr<std::atomic<float>[]> local_, allowance_;  // < 0: not yet computed
};

}  // namespace station
