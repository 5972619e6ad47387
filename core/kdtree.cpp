#include "core/kdtree.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>

#include <nanoflann.hpp>

namespace station {

namespace {

// nanoflann reads the points through this adaptor; it borrows the vector owned
// by PointIndex::Impl, which lives on the heap so moves never invalidate it.
struct PointsAdaptor {
  const std::vector<Vec3f>* pts;
  std::size_t kdtree_get_point_count() const { return pts->size(); }
  float kdtree_get_pt(std::size_t i, std::size_t dim) const { return (*pts)[i][int(dim)]; }
  template <class Bbox>
  bool kdtree_get_bbox(Bbox&) const {
    return false;  // let nanoflann compute it
  }
};

using Tree = nanoflann::KDTreeSingleIndexAdaptor<nanoflann::L2_Simple_Adaptor<float, PointsAdaptor>,
                                                 PointsAdaptor, 3, std::uint32_t>;

constexpr std::size_t kLeafSize = 16;

}  // namespace

struct PointIndex::Impl {
  std::vector<Vec3f> points;
  PointsAdaptor adaptor{&points};
  std::unique_ptr<Tree> tree;  // null when the set is empty

  explicit Impl(std::vector<Vec3f> p) : points(std::move(p)) {
    adaptor.pts = &points;
    if (!points.empty())
      tree = std::make_unique<Tree>(3, adaptor, nanoflann::KDTreeSingleIndexAdaptorParams(kLeafSize));
  }
};

PointIndex::PointIndex(std::vector<Vec3f> points) : impl_(std::make_unique<Impl>(std::move(points))) {}
PointIndex::~PointIndex() = default;
PointIndex::PointIndex(PointIndex&&) noexcept = default;
PointIndex& PointIndex::operator=(PointIndex&&) noexcept = default;

std::size_t PointIndex::size() const { return impl_->points.size(); }
const std::vector<Vec3f>& PointIndex::points() const { return impl_->points; }

std::pair<int, float> PointIndex::nearest(const Vec3f& q) const {
  if (!impl_->tree) return {-1, std::numeric_limits<float>::infinity()};
  std::uint32_t index = 0;
  float dist_sq = 0;
  impl_->tree->knnSearch(q.data(), 1, &index, &dist_sq);
  return {int(index), std::sqrt(dist_sq)};
}

std::pair<int, float> PointIndex::nearest_within(const Vec3f& q, float max_distance) const {
  constexpr std::pair<int, float> kNone{-1, std::numeric_limits<float>::infinity()};
  if (!impl_->tree || !(max_distance >= 0)) return kNone;
  std::uint32_t index = 0;
  float dist_sq = 0;
  nanoflann::KNNResultSet<float, std::uint32_t> result(1);
  result.init(&index, &dist_sq);
  // The result set's worst distance is the search bound: start it at the
  // squared radius (the next float up, so the bound is inclusive).
  dist_sq = std::nextafter(max_distance * max_distance, std::numeric_limits<float>::infinity());
  impl_->tree->findNeighbors(result, q.data(), nanoflann::SearchParams());
  if (result.size() == 0) return kNone;
  return {int(index), std::sqrt(dist_sq)};
}

std::vector<std::pair<int, float>> PointIndex::knn(const Vec3f& q, int k) const {
  std::vector<std::pair<int, float>> out;
  if (!impl_->tree || k <= 0) return out;
  const std::size_t n = std::min<std::size_t>(std::size_t(k), impl_->points.size());
  std::vector<std::uint32_t> idx(n);
  std::vector<float> dist_sq(n);
  // knnSearch returns its results sorted by distance, closest first.
  const std::size_t found = impl_->tree->knnSearch(q.data(), n, idx.data(), dist_sq.data());
  out.reserve(found);
  for (std::size_t i = 0; i < found; ++i) out.emplace_back(int(idx[i]), std::sqrt(dist_sq[i]));
  return out;
}

int PointIndex::knn_into(const Vec3f& q, int k, std::uint32_t* index, float* distance_sq) const {
  if (!impl_->tree || k <= 0) return 0;
  const std::size_t n = std::min<std::size_t>(std::size_t(k), impl_->points.size());
  return int(impl_->tree->knnSearch(q.data(), n, index, distance_sq));
}

std::vector<std::pair<int, float>> PointIndex::radius_search(const Vec3f& q, float radius, bool sorted) const {
  std::vector<std::pair<int, float>> out;
  if (!impl_->tree || !(radius >= 0)) return out;
  std::vector<std::pair<std::uint32_t, float>> hits;
  // L2_Simple_Adaptor works on squared distances, so the radius is squared too;
  // nanoflann keeps only dist < r, the next float up makes the bound inclusive.
  const float r_sq = std::nextafter(radius * radius, std::numeric_limits<float>::infinity());
  impl_->tree->radiusSearch(q.data(), r_sq, hits, nanoflann::SearchParams(32, 0.f, sorted));
  out.reserve(hits.size());
  for (const auto& h : hits) out.emplace_back(int(h.first), std::sqrt(h.second));
  return out;
}

std::vector<std::pair<int, float>> PointIndex::radius(const Vec3f& q, float radius) const {
  return radius_search(q, radius, true);
}

std::vector<std::pair<int, float>> PointIndex::radius_unsorted(const Vec3f& q, float radius) const {
  return radius_search(q, radius, false);
}

namespace {

// nanoflann's radius result set that gives up past `cap` points (addPoint
// returning false ends the search).
struct CappedRadiusSet {
  using DistanceType = float;
  using IndexType = std::uint32_t;
  float radius;
  std::size_t cap;
  std::vector<std::pair<std::uint32_t, float>>& hits;
  bool over = false;
  void init() { hits.clear(); }
  std::size_t size() const { return hits.size(); }
  bool full() const { return true; }
  bool addPoint(float dist, std::uint32_t index) {
    if (dist < radius) hits.emplace_back(index, dist);
    over = hits.size() > cap;
    return !over;
  }
  float worstDist() const { return radius; }
};

}  // namespace

std::optional<std::vector<std::pair<int, float>>> PointIndex::radius_at_most(const Vec3f& q, float radius,
                                                                             std::size_t count) const {
  std::vector<std::pair<int, float>> out;
  if (!impl_->tree || !(radius >= 0)) return out;
  std::vector<std::pair<std::uint32_t, float>> hits;
  // The bound and the order of radius_search (sorted as nanoflann sorts it).
  const float r_sq = std::nextafter(radius * radius, std::numeric_limits<float>::infinity());
  CappedRadiusSet set{r_sq, count, hits};
  impl_->tree->radiusSearchCustomCallback(q.data(), set, nanoflann::SearchParams(32, 0.f, false));
  if (set.over) return std::nullopt;
  std::sort(hits.begin(), hits.end(), nanoflann::IndexDist_Sorter());
  out.reserve(hits.size());
  for (const auto& h : hits) out.emplace_back(int(h.first), std::sqrt(h.second));
  return out;
}

namespace {

// nanoflann's radius result set that hands each point to a test and ends the search
// at the first one it accepts (addPoint returning false).
struct AcceptRadiusSet {
  using DistanceType = float;
  using IndexType = std::uint32_t;
  float radius;
  const std::function<bool(int, float)>& accept;
  bool found = false;
  void init() {}
  std::size_t size() const { return 0; }
  bool full() const { return true; }
  bool addPoint(float dist, std::uint32_t index) {
    if (dist < radius && accept(int(index), std::sqrt(dist))) found = true;
    return !found;
  }
  float worstDist() const { return radius; }
};

}  // namespace

bool PointIndex::any_in_radius(const Vec3f& q, float radius, const std::function<bool(int, float)>& accept) const {
  if (!impl_->tree || !(radius >= 0)) return false;
  // radius_search's bound: squared, the next float up (inclusive).
  AcceptRadiusSet set{std::nextafter(radius * radius, std::numeric_limits<float>::infinity()), accept};
  impl_->tree->radiusSearchCustomCallback(q.data(), set, nanoflann::SearchParams(32, 0.f, false));
  return set.found;
}

double local_sample_spacing(const PointIndex& index, int point) {
  constexpr int kNeighbours = 8;
  if (point < 0 || std::size_t(point) >= index.size()) return 0;
  const Vec3f& q = index.points()[std::size_t(point)];
  const auto k = index.knn(q, kNeighbours + 1);
  if (k.size() <= std::size_t(kNeighbours)) return 0;
  Vec3d centroid = Vec3d::Zero();
  for (std::size_t t = 1; t < k.size(); ++t) centroid += index.points()[std::size_t(k[t].first)].cast<double>();
  centroid /= double(k.size() - 1);
  const double r = k[kNeighbours].second;
  if (!(r > 0)) return 0;
  // The sector of angle theta whose centroid lies where the neighbours' does: a
  // sector's centroid lies 4 r sin(theta / 2) / (3 theta) from its apex (0 for the
  // whole disc, 0.42 r for a half, 0.60 r for a quarter), decreasing in theta.
  // Less what chance alone puts there: 8 points uniform on a disc have their centroid
  // r / 4 off on average in root mean square (E|x|^2 = r^2 / 2 over 8).
  const double seen = (centroid - q.cast<double>()).squaredNorm() / (r * r);
  const double offset = std::min(std::sqrt(std::max(0.0, seen - 0.5 / kNeighbours)), 0.66);
  double lo = 1e-3, hi = 2 * M_PI;
  for (int it = 0; it < 30; ++it) {
    const double mid = 0.5 * (lo + hi);
    (4 * std::sin(mid / 2) / (3 * mid) > offset ? lo : hi) = mid;
  }
  const double theta = 0.5 * (lo + hi);
  return r * std::sqrt(theta / (2.0 * kNeighbours));  // sqrt(area / 8), area theta r^2 / 2
}

namespace {

// The allowance from the point's and its neighbours' local spacings (sparse_allowance).
template <class Local>
double allowance_from(const PointIndex& index, int point, double median, double from, Local&& local) {
  if (!(median > 0) || point < 0 || std::size_t(point) >= index.size()) return 1;
  // The median over the point and its 8 nearest neighbours: a stray point (or a few)
  // near denser data reads as very sparse alone, not through its neighbours.
  std::uint32_t near[9];
  float dist_sq[9];
  const int found = index.knn_into(index.points()[std::size_t(point)], 9, near, dist_sq);
  if (found == 0) return 1;
  double spacing[9];
  for (int t = 0; t < found; ++t) spacing[t] = local(int(near[t]));
  std::nth_element(spacing, spacing + found / 2, spacing + found);
  const double ratio = spacing[found / 2] / median;
  return ratio >= from ? std::min(ratio, kSparseSpacingCap) : 1;
}

}  // namespace

double sparse_allowance(const PointIndex& index, int point, double median, double from) {
  return allowance_from(index, point, median, from, [&](int j) { return local_sample_spacing(index, j); });
}

SparseAllowances::SparseAllowances(const PointIndex& index, double median, double from)
    : index_(index),
      median_(median),
      from_(from),
      local_(new std::atomic<float>[index.size()]),
      allowance_(new std::atomic<float>[index.size()]) {
  for (std::size_t i = 0; i < index.size(); ++i)
    local_[i].store(-1.f, std::memory_order_relaxed), allowance_[i].store(-1.f, std::memory_order_relaxed);
}
SparseAllowances::~SparseAllowances() = default;

double SparseAllowances::local(int point) const {
  float v = local_[std::size_t(point)].load(std::memory_order_relaxed);
  if (v < 0) {
    v = float(local_sample_spacing(index_, point));
    local_[std::size_t(point)].store(v, std::memory_order_relaxed);
  }
  return v;
}

double SparseAllowances::operator()(int point) const {
  if (point < 0 || std::size_t(point) >= index_.size()) return 1;
  float v = allowance_[std::size_t(point)].load(std::memory_order_relaxed);
  if (v < 0) {
    v = float(allowance_from(index_, point, median_, from_, [&](int j) { return local(j); }));
    allowance_[std::size_t(point)].store(v, std::memory_order_relaxed);
  }
  return v;
}

double sample_spacing(const PointIndex& index, std::size_t max_samples) {
  constexpr int kNeighbours = 8;
  const std::size_t n = index.size();
  if (n <= std::size_t(kNeighbours) || max_samples == 0) return 0;
  const std::size_t stride = (n + max_samples - 1) / max_samples;
  std::vector<double> r;
  r.reserve(n / stride + 1);
  for (std::size_t i = 0; i < n; i += stride) {
    const auto k = index.knn(index.points()[i], kNeighbours + 1);
    if (k.size() > std::size_t(kNeighbours)) r.push_back(k[kNeighbours].second);
  }
  if (r.empty()) return 0;
  std::nth_element(r.begin(), r.begin() + std::ptrdiff_t(r.size() / 2), r.end());
  return r[r.size() / 2] * std::sqrt(M_PI / kNeighbours);
}

}  // namespace station
