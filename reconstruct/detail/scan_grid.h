#pragma once
// Internal to reconstruct/: the scans in a sparse grid for the snap's fixed-radius
// neighbour queries (reconstruct/scan_snap.cpp), here so that tests can hold it against
// the k-d tree.
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "core/error.h"
#include "core/geometry.h"

namespace station::detail {

// The scans bucketed in cubes of side `radius`, sorted cube by cube, side by side: a
// vertex's neighbours are in the 27 cubes round its own, read in runs instead of walked
// to through a k-d tree (half the snap's time on the Kinect scene went to that walk and
// its scattered reads). The points of a k-d tree's radius search (a float ball test;
// the tree squares the float radius where this rounds the squared one, which can differ
// by one unit in the last place exactly at the radius), in another order. The cubes
// start at the origin, so a point's cube does not depend on the others (an outlier far
// away changes nothing). A cube's key holds its coordinates modulo 2^21: cubes that far
// apart share a run, which costs distance tests, never a wrong point.
// Not WLOP's detail::RadiusGrid: its dense cell array may take 16 cells per point (64
// bytes per point, on top of double coordinates), and the snap runs over all the
// registered scans, tens of millions of points in a large session; here only the
// occupied cubes sit in a hash table (2-4 slots of 16 bytes per occupied cube), besides
// 25 bytes per point.
class ScanGrid {
 public:
  ScanGrid(const Cloud& scans, double radius) : radius_sq_(float(radius * radius)) {
    inv_ = 1 / radius;
    const std::size_t n = scans.size();
    if (n >= std::numeric_limits<std::uint32_t>::max())
      throw InvalidInput("snap to scans: " + std::to_string(n) + " scan points; at most 2^32 - 2 are supported");
    std::vector<std::uint64_t> cube(n);
    std::vector<std::uint32_t> order(n);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 4096), [&](const auto& r) {
      for (std::size_t i = r.begin(); i != r.end(); ++i) cube[i] = cube_of(scans.points[i]), order[i] = std::uint32_t(i);
    });
    tbb::parallel_sort(order.begin(), order.end(), [&](std::uint32_t a, std::uint32_t b) {
      return cube[a] < cube[b] || (cube[a] == cube[b] && a < b);
    });
    x_.resize(n), y_.resize(n), z_.resize(n), normal_.resize(n), half_.resize(n);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 4096), [&](const auto& r) {
      for (std::size_t k = r.begin(); k != r.end(); ++k) {
        const std::uint32_t i = order[k];
        x_[k] = scans.points[i].x(), y_[k] = scans.points[i].y(), z_[k] = scans.points[i].z();
        normal_[k] = scans.normals[i];
        half_[k] = (unsigned char)(i % 2);
      }
    });
    std::size_t cubes = 0;
    for (std::size_t k = 0; k < n; ++k) cubes += k == 0 || !(cube[order[k]] == cube[order[k - 1]]);
    std::size_t capacity = 16;
    shift_ = 60;
    while (capacity < 2 * cubes) capacity *= 2, --shift_;
    mask_ = capacity - 1;
    slots_.assign(capacity, Slot{});
    for (std::size_t k = 0; k < n;) {
      const std::uint64_t c = cube[order[k]];
      std::size_t end = k + 1;
      while (end < n && cube[order[end]] == c) ++end;
      std::size_t s = hash(c);
      while (slots_[s].end != 0) s = (s + 1) & mask_;
      slots_[s] = Slot{c, std::uint32_t(k), std::uint32_t(end)};
      k = end;
    }
  }

  /// f(k) for every stored point k within the radius of v (inclusive, as a k-d tree's
  /// float test: the next float up from radius^2).
  template <class F>
  void for_each_within(const Vec3f& v, F&& f) const {
    const Cube c = coordinates(v);
    const float bound = std::nextafter(radius_sq_, std::numeric_limits<float>::infinity());
    for (std::int64_t dz = -1; dz <= 1; ++dz)
      for (std::int64_t dy = -1; dy <= 1; ++dy)
        for (std::int64_t dx = -1; dx <= 1; ++dx) {
          const Slot* s = find(key(Cube{c.i + dx, c.j + dy, c.k + dz}));
          if (!s) continue;
          // The cube's hits first, without a branch per point (a third to a half of
          // the points pass), then f on each.
          const std::uint32_t count = s->end - s->begin;
          if (hits_.size() < count) hits_.resize(std::max<std::size_t>(count, 2 * hits_.size()));
          std::uint32_t found = 0;
          for (std::uint32_t k = s->begin; k != s->end; ++k) {
            const float ex = x_[k] - v.x(), ey = y_[k] - v.y(), ez = z_[k] - v.z();
            hits_[found] = k;
            found += ex * ex + ey * ey + ez * ez < bound;
          }
          for (std::uint32_t h = 0; h < found; ++h) f(hits_[h]);
        }
  }
  Vec3f point(std::uint32_t k) const { return {x_[k], y_[k], z_[k]}; }
  const Vec3f& normal(std::uint32_t k) const { return normal_[k]; }
  int half(std::uint32_t k) const { return half_[k]; }

 private:
  struct Cube {
    std::int64_t i = 0, j = 0, k = 0;
  };
  struct Slot {
    std::uint64_t key = 0;
    std::uint32_t begin = 0, end = 0;  // end 0: empty
  };
  Cube coordinates(const Vec3f& p) const {
    // Clamped far beyond any lattice a float cloud can hold, so the casts stay defined.
    const auto axis = [&](int a) {
      return std::int64_t(std::floor(std::clamp(double(p[a]) * inv_, -1e15, 1e15)));
    };
    return {axis(0), axis(1), axis(2)};
  }
  static std::uint64_t key(const Cube& c) {
    constexpr std::uint64_t kMask = (std::uint64_t(1) << 21) - 1;
    return (std::uint64_t(c.i) & kMask) | (std::uint64_t(c.j) & kMask) << 21 | (std::uint64_t(c.k) & kMask) << 42;
  }
  std::uint64_t cube_of(const Vec3f& p) const { return key(coordinates(p)); }
  // The product's high bits (Fibonacci hashing): every bit of the key reaches them, so
  // a tall column of cubes (x and y alike) spreads over the table too.
  std::size_t hash(std::uint64_t key) const { return std::size_t((key * 0x9E3779B97F4A7C15ull) >> shift_); }
  const Slot* find(std::uint64_t key) const {
    for (std::size_t s = hash(key);; s = (s + 1) & mask_) {
      if (slots_[s].end == 0) return nullptr;
      if (slots_[s].key == key) return &slots_[s];
    }
  }
  double inv_ = 0;
  float radius_sq_ = 0;
  std::vector<float> x_, y_, z_;
  std::vector<Vec3f> normal_;
  std::vector<unsigned char> half_;
  std::vector<Slot> slots_;
  std::size_t mask_ = 0;
  int shift_ = 60;  // 64 - log2(the table's size)
  static inline thread_local std::vector<std::uint32_t> hits_;
};

}  // namespace station::detail
