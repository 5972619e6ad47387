#include "registration/features.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>

#include "core/error.h"
#include "core/kdtree.h"

#include <nanoflann.hpp>

namespace station {

namespace {

using Spfh = std::array<float, kFpfhBins>;

int bin_of(double x, double lo, double hi) {
  const int b = int(std::floor((x - lo) / (hi - lo) * 11.0));
  return std::min(10, std::max(0, b));
}

// Adds the pair (p, q) to h; false when the pair is degenerate.
bool pair_feature(const Vec3d& p1, const Vec3d& n1, const Vec3d& p2, const Vec3d& n2, Spfh& h,
                  float w) {
  Vec3d d = p2 - p1;
  const double dist = d.norm();
  if (!(dist > 0)) return false;
  d /= dist;
  // The source end is the one whose normal is closer to the connecting line.
  Vec3d ps = p1, ns = n1, nt = n2;
  Vec3d line = d;
  if (std::abs(n1.dot(d)) < std::abs(n2.dot(d))) {
    ps = p2;
    ns = n2;
    nt = n1;
    line = -d;
  }
  (void)ps;
  const Vec3d u = ns;
  Vec3d v = u.cross(line);
  const double vn = v.norm();
  if (!(vn > 1e-12)) return false;
  v /= vn;
  const Vec3d w3 = u.cross(v);
  const double alpha = v.dot(nt);
  const double phi = u.dot(line);
  const double theta = std::atan2(w3.dot(nt), u.dot(nt));
  h[bin_of(theta, -M_PI, M_PI)] += w;
  h[11 + bin_of(alpha, -1.0, 1.0)] += w;
  h[22 + bin_of(phi, -1.0, 1.0)] += w;
  return true;
}

}  // namespace

std::vector<FpfhDescriptor> compute_fpfh(const PointIndex& index, const std::vector<Vec3f>& normals,
                                         double radius, int max_neighbors) {
  const std::vector<Vec3f>& pts = index.points();
  const std::size_t n = pts.size();
  if (normals.size() != n)
    throw InvalidInput("fpfh: " + std::to_string(normals.size()) + " normals for " + std::to_string(n) +
                       " points");
  if (!(radius > 0)) throw InvalidInput("fpfh: radius must be positive");
  max_neighbors = std::max(1, max_neighbors);
  std::vector<std::vector<std::pair<int, float>>> nbrs(n);
  std::vector<Spfh> spfh(n);
  tbb::parallel_for(std::size_t(0), n, [&](std::size_t i) {
    auto r = index.radius(pts[i], float(radius));
    std::vector<std::pair<int, float>> keep;
    keep.reserve(std::min<std::size_t>(r.size(), max_neighbors));
    for (const auto& [j, dist] : r) {
      if (std::size_t(j) == i) continue;
      if (int(keep.size()) >= max_neighbors) break;
      keep.push_back({j, dist});
    }
    Spfh h{};
    const Vec3d pi = pts[i].cast<double>(), ni = normals[i].cast<double>();
    int used = 0;
    for (const auto& [j, dist] : keep)
      used += pair_feature(pi, ni, pts[j].cast<double>(), normals[j].cast<double>(), h, 1.0f);
    if (used > 0)
      for (float& x : h) x *= 100.0f / float(used);
    spfh[i] = h;
    nbrs[i] = std::move(keep);
  });
  std::vector<FpfhDescriptor> out(n);
  tbb::parallel_for(std::size_t(0), n, [&](std::size_t i) {
    FpfhDescriptor f = spfh[i];
    if (!nbrs[i].empty()) {
      Spfh acc{};
      for (const auto& [j, dist] : nbrs[i]) {
        const float w = 1.0f / std::max(dist, 1e-9f);
        for (int b = 0; b < kFpfhBins; ++b) acc[b] += w * spfh[j][b];
      }
      const float k = float(nbrs[i].size());
      for (int b = 0; b < kFpfhBins; ++b) f[b] += acc[b] / k;
    }
    for (int blk = 0; blk < 3; ++blk) {
      float s = 0;
      for (int b = 0; b < 11; ++b) s += f[blk * 11 + b];
      if (s > 0)
        for (int b = 0; b < 11; ++b) f[blk * 11 + b] *= 100.0f / s;
    }
    out[i] = f;
  });
  return out;
}

namespace {

// The descriptors for nanoflann (borrowed).
struct DescriptorsAdaptor {
  const std::vector<FpfhDescriptor>* d;
  std::size_t kdtree_get_point_count() const { return d->size(); }
  float kdtree_get_pt(std::size_t i, std::size_t dim) const { return (*d)[i][dim]; }
  template <class Bbox>
  bool kdtree_get_bbox(Bbox&) const {
    return false;
  }
};
using DescriptorTree = nanoflann::KDTreeSingleIndexAdaptor<nanoflann::L2_Simple_Adaptor<float, DescriptorsAdaptor>,
                                                          DescriptorsAdaptor, kFpfhBins, std::uint32_t>;

// The scan in index order: the first reference descriptor at the least squared
// distance (summed bin by bin in float, as nanoflann's L2_Simple_Adaptor sums it).
// Only the descriptors `take` accepts (every one by default).
template <class Take = bool (*)(std::size_t)>
int nearest_by_scan(const FpfhDescriptor& q, const std::vector<FpfhDescriptor>& reference,
                    Take take = [](std::size_t) { return true; }) {
  float best = std::numeric_limits<float>::infinity();
  int bi = -1;
  for (std::size_t j = 0; j < reference.size(); ++j) {
    if (!take(j)) continue;
    const FpfhDescriptor& r = reference[j];
    float d = 0;
    for (int b = 0; b < kFpfhBins && d < best; ++b) {
      const float e = q[std::size_t(b)] - r[std::size_t(b)];
      d += e * e;
    }
    if (d < best) {
      best = d;
      bi = int(j);
    }
  }
  return bi;
}

// Below this many reference descriptors the scan is as quick as a tree.
constexpr std::size_t kScanBelow = 256;

}  // namespace

std::vector<int> nearest_descriptors(const std::vector<FpfhDescriptor>& query,
                                     const std::vector<FpfhDescriptor>& reference) {
  std::vector<int> out(query.size(), -1);
  if (reference.empty()) return out;
  if (reference.size() < kScanBelow) {
    tbb::parallel_for(std::size_t(0), query.size(),
                      [&](std::size_t i) { out[i] = nearest_by_scan(query[i], reference); });
    return out;
  }
  // An exact k-d tree over the reference (FPFH lies near a low-dimensional set of
  // the 33 bins, so the tree prunes most of it): the same answer as the scan, the
  // lowest index among descriptors at exactly the least distance.
  const DescriptorsAdaptor adaptor{&reference};
  const DescriptorTree tree(kFpfhBins, adaptor, nanoflann::KDTreeSingleIndexAdaptorParams(16));
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, query.size(), 64), [&](const tbb::blocked_range<std::size_t>& r) {
    std::vector<std::pair<std::uint32_t, float>> ties;
    for (std::size_t i = r.begin(); i != r.end(); ++i) {
      std::uint32_t idx[2];
      float dsq[2];
      const std::size_t found = tree.knnSearch(query[i].data(), 2, idx, dsq);
      if (found == 0) continue;
      // The tree's running bound on a branch is summed in float, and may round a few
      // ulps high: where the second nearest is not clearly farther, every descriptor
      // within a relative 1e-4 of the nearest is looked at, and the least distance,
      // then the lowest index, taken (the scan's answer).
      if (found == 1 || dsq[1] > dsq[0] * (1 + 1e-4f)) {
        out[i] = int(idx[0]);
        continue;
      }
      tree.radiusSearch(query[i].data(), std::nextafter(dsq[0] * (1 + 1e-4f), std::numeric_limits<float>::infinity()),
                        ties, nanoflann::SearchParams(32, 0.f, false));
      std::pair<float, std::uint32_t> best{dsq[0], idx[0]};
      for (const auto& [j, d] : ties) best = std::min(best, std::make_pair(d, j));
      out[i] = int(best.second);
    }
  });
  return out;
}

std::vector<int> nearest_descriptors_gated(const std::vector<FpfhDescriptor>& query, const std::vector<Vec3f>& query_chroma,
                                           const std::vector<FpfhDescriptor>& reference,
                                           const std::vector<Vec3f>& reference_chroma, double gate, int candidates) {
  if (query_chroma.size() != query.size() || reference_chroma.size() != reference.size() || !(gate >= 0) ||
      candidates < 1)
    throw InvalidInput("colour-gated descriptor matches: one chromaticity per descriptor, gate >= 0, candidates >= 1");
  std::vector<int> out(query.size(), -1);
  if (reference.empty()) return out;
  const float g2 = float(gate * gate);
  const auto agrees = [&](std::size_t i, std::size_t j) {
    return (query_chroma[i] - reference_chroma[j]).squaredNorm() <= g2;
  };
  if (reference.size() < kScanBelow) {
    tbb::parallel_for(std::size_t(0), query.size(), [&](std::size_t i) {
      out[i] = nearest_by_scan(query[i], reference, [&](std::size_t j) { return agrees(i, j); });
    });
    return out;
  }
  // The nearest `candidates` descriptors by the tree, the first of them (the least
  // distance, then the lowest index) whose colour agrees.
  const DescriptorsAdaptor adaptor{&reference};
  const DescriptorTree tree(kFpfhBins, adaptor, nanoflann::KDTreeSingleIndexAdaptorParams(16));
  const std::size_t k = std::min<std::size_t>(std::size_t(candidates), reference.size());
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, query.size(), 64), [&](const tbb::blocked_range<std::size_t>& r) {
    std::vector<std::uint32_t> idx(k);
    std::vector<float> dsq(k);
    for (std::size_t i = r.begin(); i != r.end(); ++i) {
      const std::size_t found = tree.knnSearch(query[i].data(), k, idx.data(), dsq.data());
      std::pair<float, std::uint32_t> best{std::numeric_limits<float>::infinity(), 0};
      for (std::size_t c = 0; c < found; ++c)
        if (agrees(i, idx[c])) best = std::min(best, std::make_pair(dsq[c], idx[c]));
      if (std::isfinite(best.first)) out[i] = int(best.second);
    }
  });
  return out;
}

}  // namespace station
