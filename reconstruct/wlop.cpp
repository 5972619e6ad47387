#include "reconstruct/wlop.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <string>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include "core/error.h"
#include "core/kdtree.h"
#include "core/normals.h"
#include "core/threads.h"
#include "reconstruct/detail/radius_grid.h"
#include "reconstruct/detail/wlop_kernels.h"

namespace station {

namespace {

using detail::KernelShape;
using detail::KernelSums;
using detail::RadiusGrid;
using Clock = std::chrono::steady_clock;

// Pairs closer than this (relative to h) are left out of E1: alpha = theta / r is
// singular at r = 0, and every initial x_i sits exactly on its input point.
constexpr double kCoincident = 1e-9;
// Below this |sum n_l| / k_h the normals around x_i cancel (a thin sheet, noise
// on a needle) and c_i of eq. 10 would sit on x_i: plain E1 is used there.
constexpr double kMinNormalAgreement = 0.2;
// Simple normals (eqs. 11-12) use at most this many of a point's neighbours
// within h, evenly strided: a plane fit needs far fewer than a dense cloud holds.
constexpr int kSimpleNormalPoints = 32;
constexpr int kGrain = 64;

// theta of eq. 8 as a function of the squared distance, with the cut-off at h.
struct Kernel {
  double h, h2, inv_s2, eps2;
  explicit Kernel(double radius)
      : h(radius), h2(radius * radius), inv_s2(16.0 / (radius * radius)),
        eps2(kCoincident * kCoincident * radius * radius) {}
  double theta(double r2) const { return std::exp(-r2 * inv_s2); }
  KernelShape shape() const { return KernelShape{h2, inv_s2, eps2}; }
};

// The points of a grid strictly within h of a query: sorted positions and
// offsets p - q (float: they feed the edge variant's float kernels and the simple
// normals' plane fits). Buffers grow to the largest neighbourhood seen and stay.
struct Neighbours {
  std::vector<int> pos;
  std::vector<float> dx, dy, dz, r2;
  int n = 0;
  // Room for m entries plus kFloatPad for vector loops reading past the end.
  void fit(std::size_t m) {
    m += detail::kFloatPad;
    if (pos.size() < m) {
      const std::size_t cap = std::max(m, 2 * pos.size());
      pos.resize(cap);
      dx.resize(cap);
      dy.resize(cap);
      dz.resize(cap);
      r2.resize(cap);
    }
  }
};

// Collects the grid's points within h of q, in the grid's fixed run order.
void gather(const RadiusGrid& grid, const Vec3d& q, double h2, Neighbours& nb) {
  nb.n = 0;
  grid.for_each_run(q, [&](int b, int e) {
    nb.fit(std::size_t(nb.n + (e - b)));
    nb.n = detail::gather_run(grid.xs(), grid.ys(), grid.zs(), b, e, q, h2, nb.n, nb.pos.data(),
                              nb.dx.data(), nb.dy.data(), nb.dz.data(), nb.r2.data());
  });
}

// WlopRepulsion::kTangential's local normal at q: the PCA normal (core/normals.h)
// of the grid's points within h of q, as offsets from q in `buffer`. Zero when
// fewer than 3 are within h.
Vec3d least_spread(const RadiusGrid& grid, const Vec3d& q, double h2, std::vector<Vec3d>& buffer) {
  const double *xs = grid.xs(), *ys = grid.ys(), *zs = grid.zs();
  buffer.clear();
  grid.for_each_run(q, [&](int b, int e) {
    for (int p = b; p < e; ++p) {
      const Vec3d d(xs[p] - q.x(), ys[p] - q.y(), zs[p] - q.z());
      if (d.squaredNorm() < h2) buffer.push_back(d);
    }
  });
  return pca_normal(buffer.data(), int(buffer.size()));
}

// Growable float arrays with kFloatPad spare readable entries for vector loops
// (which mask the lanes past the end).
struct Padded {
  std::vector<float> v;
  float* fit(std::size_t n) {
    if (v.size() < n + detail::kFloatPad) v.resize(std::max(n + detail::kFloatPad, 2 * v.size()), 0.0f);
    return v.data();
  }
  float* data() { return v.data(); }
};

bool position_less(const Vec3d& a, const Vec3d& b) {
  return a.x() != b.x() ? a.x() < b.x() : a.y() != b.y() ? a.y() < b.y() : a.z() < b.z();
}

// Whether two of the subset's points share a position.
bool has_coincident(const std::vector<Vec3d>& p, const std::vector<int>& subset) {
  std::vector<Vec3d> q;
  q.reserve(subset.size());
  for (int j : subset) q.push_back(p[std::size_t(j)]);
  std::sort(q.begin(), q.end(), position_less);
  for (std::size_t i = 1; i < q.size(); ++i)
    if (q[i] == q[i - 1]) return true;
  return false;
}

// The lowest index of each distinct position, ascending.
std::vector<int> first_occurrences(const std::vector<Vec3d>& p) {
  std::vector<int> order(p.size());
  for (std::size_t j = 0; j < p.size(); ++j) order[j] = int(j);
  std::sort(order.begin(), order.end(), [&](int a, int b) {
    const Vec3d &pa = p[std::size_t(a)], &pb = p[std::size_t(b)];
    return pa == pb ? a < b : position_less(pa, pb);
  });
  std::vector<int> first;
  for (std::size_t i = 0; i < order.size(); ++i)
    if (i == 0 || p[std::size_t(order[i])] != p[std::size_t(order[i - 1])]) first.push_back(order[i]);
  std::sort(first.begin(), first.end());
  return first;
}

struct Scratch {
  Neighbours input;
  std::vector<Vec3d> points;  // simple normals' neighbourhood; kTangential's PCA neighbourhood
  // Edge variant: per neighbour, its signed simple normal, v_j and the weight 1/v';
  // the upsampled, inverted neighbourhood U (eq. 14) as offsets from x'_i, one block
  // of k_h entries per copy (entry k of each block is neighbour k).
  Padded nx, ny, nz, v, w;
  Padded ux, uy, uz, ur2, uw;
};

class Consolidator {
 public:
  Consolidator(const Cloud& input, const WlopParams& params, WlopResult& result)
      : input_(input), params_(params), result_(result), ni_(result.output_points),
        dbb_(result.bbox_diagonal) {}

  void run();

 private:
  void setup();
  void iterate(bool last);
  void colours();
  void normals();

  // E1 of eq. 2 at q from its input neighbours; false when no weight.
  bool plain_e1(const Vec3d& q, Vec3d& e1) const;
  // E1 of eq. 19 (edge variant); false when it falls back or has no weight.
  bool edge_e1(const Vec3d& q, const Neighbours& nb, Scratch& s, Vec3d& e1, int& copies,
               Vec3d& axis) const;

  const Cloud& input_;
  const WlopParams& params_;
  WlopResult& result_;

  std::size_t ni_ = 0;
  double dbb_ = 0;
  std::size_t nj_ = 0;
  Kernel kernel_{1.0};
  std::vector<Vec3d> p_;            // input, double
  RadiusGrid input_grid_, x_grid_;  // input: built once; projected: every iteration
  std::vector<double> inv_v_;       // 1 / v_j by input-grid sorted position
  // Edge variant, by input-grid sorted position (kFloatPad more records): the
  // simple normal n (eqs. 11-12) with the sign of the PCA normal m, which only
  // serves to orient it, and v_j (detail::EdgeRecord).
  std::vector<float> records_;
  bool oriented_ = false;  // n are the input's (oriented) normals
  std::vector<Vec3d> x_, x_next_;   // projected set
  std::vector<double> w_;           // w_i by projected-grid sorted position
  std::vector<int> copies_;         // edge variant: K per point (-1: plain E1)
  std::vector<char> isolated_;
  tbb::enumerable_thread_specific<Scratch> scratch_;
};

void Consolidator::run() {
  const auto t0 = Clock::now();
  const int threads =
      worker_threads(params_.threads);
  tbb::task_arena arena(threads);
  arena.execute([&] {
    auto t = Clock::now();
    setup();
    result_.seconds_setup = seconds_since(t);
    t = Clock::now();
    for (int k = 0; k < params_.iterations; ++k) {
      iterate(k + 1 == params_.iterations);
      if (params_.progress) params_.progress(k + 1, params_.iterations);
    }
    result_.iterations = params_.iterations;
    result_.seconds_iterations = seconds_since(t);
    t = Clock::now();
    result_.positions = x_;
    result_.cloud.points.resize(ni_);
    for (std::size_t i = 0; i < ni_; ++i) result_.cloud.points[i] = x_[i].cast<float>();
    if (input_.has_colours()) colours();
    if (params_.estimate_normals) normals();
    result_.seconds_attributes = seconds_since(t);
  });
  result_.seconds = seconds_since(t0);
}

void Consolidator::setup() {
  nj_ = input_.size();
  p_.resize(nj_);
  for (std::size_t j = 0; j < nj_; ++j) p_[j] = input_.points[j].cast<double>();
  const double h = params_.radius > 0 ? params_.radius : 4.0 * dbb_ / std::sqrt(double(nj_));
  kernel_ = Kernel(h);
  result_.radius = h;

  input_grid_.build(p_.data(), nj_, h);
  const bool edge = params_.method == WlopMethod::kEdgeWlop;
  const bool input_normals = edge && params_.edge_normals == EdgeNormals::kInput && input_.has_normals();
  oriented_ = input_normals;
  inv_v_.assign(nj_ + RadiusGrid::kPad, 1.0);
  const bool uniform = params_.input_density == InputDensity::kUniform;
  if (edge) {
    records_.assign((nj_ + detail::kFloatPad) * detail::kRecordFloats, 0.0f);
  }
  // Input densities v_j (eq. 6) and, for the edge variant, the simple normals
  // (eqs. 11-12) with PCA normals that only serve to orient them.
  const auto set_normals = [&](int sp, const Vec3f& n, const Vec3f& m) {
    float* r = &records_[std::size_t(sp) * detail::kRecordFloats];
    r[detail::kNx] = n.x();
    r[detail::kNy] = n.y();
    r[detail::kNz] = n.z();
    r[detail::kMx] = m.x();
    r[detail::kMy] = m.y();
    r[detail::kMz] = m.z();
  };
  tbb::parallel_for(tbb::blocked_range<int>(0, int(nj_), kGrain), [&](const tbb::blocked_range<int>& r) {
    Scratch& s = scratch_.local();
    const int* ids = input_grid_.ids().data();
    const KernelShape shape = kernel_.shape();
    for (int sp = r.begin(); sp < r.end(); ++sp) {
      const Vec3d& q = p_[ids[sp]];
      // The sum includes p_j itself (theta(0) = 1), which is eq. 6's "1 +".
      const double v = uniform ? 1.0 : detail::density_sum(input_grid_, q, shape).w;
      inv_v_[sp] = 1.0 / v;
      if (!edge) continue;
      records_[std::size_t(sp) * detail::kRecordFloats + detail::kV] = float(v);
      if (input_normals) {
        const Vec3f n = input_.normals[ids[sp]].normalized();  // zero stays zero
        set_normals(sp, n, n);
        continue;
      }
      gather(input_grid_, q, kernel_.h2, s.input);
      const Neighbours& nb = s.input;
      const int stride = (nb.n + kSimpleNormalPoints - 1) / kSimpleNormalPoints;
      s.points.clear();
      for (int k = 0; k < nb.n; k += std::max(stride, 1))
        s.points.emplace_back(double(nb.dx[k]), double(nb.dy[k]), double(nb.dz[k]));
      Vec3d m;
      Vec3d n = simple_normal(s.points.data(), int(s.points.size()), 4, &m);
      if (n.dot(m) < 0) n = -n;
      set_normals(sp, n.cast<float>(), m.cast<float>());
    }
  });

  // Initial projected set: a seeded random subset of the input, of distinct positions.
  // Two picks of one position (an input point given twice) would get the same E1 and
  // E2 in every iteration, a coincident pair being left out of E2 (or giving it no
  // offset), and stay one point counted twice. Then the subset is drawn from the first
  // occurrence of each position instead (the same draw where the input has no
  // duplicates); with fewer positions than requested, all of them are taken.
  std::vector<int> subset = initial_subset(nj_, ni_, params_.seed);
  if (has_coincident(p_, subset)) {
    const std::vector<int> distinct = first_occurrences(p_);
    if (distinct.size() < ni_) {
      ni_ = distinct.size();
      result_.output_points = ni_;
      result_.clamped = true;
    }
    subset = initial_subset(distinct.size(), ni_, params_.seed);
    for (int& j : subset) j = distinct[std::size_t(j)];
  }
  x_.resize(ni_);
  for (std::size_t i = 0; i < ni_; ++i) x_[i] = p_[subset[i]];
  x_next_.resize(ni_);
  w_.assign(ni_ + RadiusGrid::kPad, 1.0);
  isolated_.assign(ni_, 0);
  copies_.assign(ni_, 0);
}

bool Consolidator::plain_e1(const Vec3d& q, Vec3d& e1) const {
  // Sums of (p_j - q) rather than p_j: the same E1, without cancellation.
  const KernelSums s = detail::attraction_sum(input_grid_, inv_v_.data(), q, kernel_.shape());
  if (!(s.w > 0)) return false;
  e1 = q + s.d / s.w;
  return true;
}

bool Consolidator::edge_e1(const Vec3d& q, const Neighbours& nb, Scratch& s, Vec3d& e1,
                           int& copies, Vec3d& axis) const {
  const int kh = nb.n;
  if (kh == 0) return false;
  const double h = kernel_.h, h2 = kernel_.h2;

  // Eq. 10: c_i from the mean simple normal. Signs are made consistent through
  // the PCA normals (smooth across edges, unlike the simple ones), relative to
  // the one of the input point nearest x_i.
  const int nearest = detail::nearest(nb.r2.data(), kh);
  const float* ref = &records_[std::size_t(nb.pos[nearest]) * detail::kRecordFloats + detail::kMx];
  float *snx = s.nx.fit(kh), *sny = s.ny.fit(kh), *snz = s.nz.fit(kh), *sv = s.v.fit(kh);
  const Vec3d sum = detail::signed_normal_sum(nb.pos.data(), kh, records_.data(), ref, oriented_,
                                              snx, sny, snz, sv);
  const double agreement = sum.norm();
  if (!(agreement >= kMinNormalAgreement * kh)) return false;  // normals cancel: plain E1
  const Vec3d a = -sum / agreement;                // unit axis, from c_i towards x_i
  axis = a;
  const double D = dbb_ * agreement / (2.0 * kh);  // |x_i - c_i|
  // R must keep 2R - |p - c_i| > 0 over the neighbourhood (f stays a bijection).
  const double R = std::max(params_.inversion_radius * dbb_, D + h);
  const double Q = 2 * R - D;                        // |x'_i - c_i|
  const double shift = R / params_.shift_divisions;  // |l| (eq. 15)

  // Eqs. 14-15: copies t = 0, 1, ... of the neighbours, shifted by t l and inverted
  // with radius R + t |l| / 2, until k'_h >= k_h (or max_copies). Every neighbour
  // goes into every copy; the ones that land beyond h of x'_i weigh nothing in E1'.
  int K = 0, count = 0;
  while (K < params_.max_copies && count < kh) {
    const std::size_t end = std::size_t(K + 1) * kh, off = std::size_t(K) * kh;
    float *ux = s.ux.fit(end), *uy = s.uy.fit(end), *uz = s.uz.fit(end), *ur2 = s.ur2.fit(end);
    if (params_.inverted_density == InvertedDensity::kExact) s.uw.fit(end);
    count += detail::invert_copy(nb.dx.data(), nb.dy.data(), nb.dz.data(), nb.r2.data(), kh,
                                 D + K * shift, Q, a, h2, ux + off, uy + off, uz + off, ur2 + off);
    ++K;
  }
  copies = K;
  const int total = K * kh;

  // Eq. 18: density weights 1 / v'_s of U.
  float* uw = s.uw.data();
  const bool exact = params_.inverted_density == InvertedDensity::kExact;
  if (exact) {
    // Literally: over the points of U within h of u_s (only those of U within h
    // of x'_i weigh anything in E1').
    const float *ux = s.ux.data(), *uy = s.uy.data(), *uz = s.uz.data(), *ur2 = s.ur2.data();
    const double reach2 = 4 * h2;  // a neighbour of a point within h of x'_i is within 2h
    for (int i = 0; i < total; ++i) {
      uw[i] = 0;
      if (ur2[i] >= h2) continue;
      double v = 1;
      for (int j = 0; j < total; ++j) {
        if (j == i || ur2[j] >= reach2) continue;
        const double dx = double(ux[i]) - ux[j], dy = double(uy[i]) - uy[j], dz = double(uz[i]) - uz[j];
        const double d2 = dx * dx + dy * dy + dz * dz;
        if (d2 < h2) v += kernel_.theta(d2);
      }
      uw[i] = float(1.0 / v);
    }
  } else {
    // The input density v_j carried into the inverted space: a surface element with
    // normal n at lateral scale g is stretched by sigma = g sqrt(1 + (g^2 - 1)(n.a)^2)
    // (f's Jacobian is -1 along the ray and g across it), so copy t holds density
    // rho / sigma_t there, and the K copies overlap: v' - 1 = (v_j - 1) sum_t 1/sigma_t,
    // with g_t taken on the axis.
    double g[64];
    for (int t = 0; t < K; ++t) g[t] = Q / (D + t * shift);
    detail::edge_weights(snx, sny, snz, sv, kh, a, g, K, s.w.fit(kh));
  }
  // Eqs. 16-17: E1' over U, as an offset e from x'_i (points beyond h are masked),
  // copy by copy (the Jacobian weights are per neighbour, the same in every copy).
  KernelSums sums;
  for (int t = 0; t < K; ++t) {
    const std::size_t off = std::size_t(t) * kh;
    const float* weight = exact ? uw + off : s.w.data();
    const KernelSums part = detail::attraction_sum(s.ux.data() + off, s.uy.data() + off,
                                                   s.uz.data() + off, s.ur2.data() + off,
                                                   weight, kh, kernel_.shape());
    sums.w += part.w;
    sums.d += part.d;
  }
  if (!(sums.w > 0)) return false;
  const Vec3d e = sums.d / sums.w;
  // Eq. 19: E1 = f(E1', c_i, R), relative to x_i without cancellation:
  // E1' - c_i = (Q + e_a) a + e_perp, |.| = Q + e_a + eps.
  const double ea = e.dot(a);
  const Vec3d ep = e - ea * a;
  const double ep2 = ep.squaredNorm();
  const double dw = std::sqrt((Q + ea) * (Q + ea) + ep2);
  const double eps = ep2 / (dw + Q + ea);
  const double back = D - ea - eps;  // 2R - |E1' - c_i|
  e1 = q + (-ea - eps - back * eps / dw) * a + (back / dw) * ep;
  return true;
}

void Consolidator::iterate(bool last) {
  x_grid_.build(x_.data(), ni_, kernel_.h);
  const int* xids = x_grid_.ids().data();
  const KernelShape shape = kernel_.shape();
  // w_i of eq. 7 from the current iterate, stored by sorted position (the sum
  // includes x_i itself, which is the "1 +").
  tbb::parallel_for(tbb::blocked_range<int>(0, int(ni_), kGrain), [&](const tbb::blocked_range<int>& r) {
    for (int sp = r.begin(); sp < r.end(); ++sp)
      w_[sp] = detail::density_sum(x_grid_, x_[xids[sp]], shape).w;
  });
  const bool edge = params_.method == WlopMethod::kEdgeWlop;
  // Eq. 1 for every point from the previous iterate (Jacobi), in the projected
  // grid's order so that neighbouring points run one after another.
  tbb::parallel_for(tbb::blocked_range<int>(0, int(ni_), kGrain), [&](const tbb::blocked_range<int>& r) {
    Scratch& s = scratch_.local();
    for (int sp = r.begin(); sp < r.end(); ++sp) {
      const int i = xids[sp];
      const Vec3d& q = x_[i];
      Vec3d e1, axis = Vec3d::Zero();
      int copies = -1;
      bool ok = false;
      if (edge) {
        gather(input_grid_, q, kernel_.h2, s.input);
        ok = edge_e1(q, s.input, s, e1, copies, axis);
      }
      if (!ok) ok = plain_e1(q, e1);
      copies_[i] = copies;
      if (!ok) {  // no input point within h: E1 and E2 are undefined; stay
        x_next_[i] = q;
        isolated_[i] = 1;
        continue;
      }
      isolated_[i] = 0;
      // E2 of eq. 3; the sums are over x_r - x_i, so E2 = -d / w. beta = theta / r
      // has E1's form (a pair closer than 1e-9 h left out, x_i itself with it);
      // beta = -theta (eq. 5 as printed): the signs cancel.
      const KernelSums e2 = params_.repulsion_weight == RepulsionWeight::kOriginal
                                ? detail::attraction_sum(x_grid_, w_.data(), q, shape)
                                : detail::repulsion_sum(x_grid_, w_.data(), q, shape, sp);
      Vec3d next = e1;
      if (e2.w > 0) {
        Vec3d step = -params_.mu * e2.d / e2.w;
        // Edge variant: E2 without its part along the inversion axis (see the header).
        if (copies >= 0 && params_.edge_repulsion == EdgeRepulsion::kTangential)
          step -= step.dot(axis) * axis;
        // Plain WLOP, kTangential: E2 without its part along the local normal.
        if (!edge && params_.repulsion == WlopRepulsion::kTangential) {
          const Vec3d nrm = least_spread(x_grid_, q, kernel_.h2, s.points);
          step -= step.dot(nrm) * nrm;
        }
        next += step;
      }
      x_next_[i] = next;
    }
  });
  x_.swap(x_next_);
  if (last) {
    result_.isolated_points = std::size_t(std::count(isolated_.begin(), isolated_.end(), 1));
    if (edge) {
      std::size_t fallbacks = 0, total = 0, counted = 0;
      for (std::size_t i = 0; i < ni_; ++i) {
        if (isolated_[i]) continue;
        if (copies_[i] < 0) {
          ++fallbacks;
        } else {
          total += std::size_t(copies_[i]);
          ++counted;
        }
      }
      result_.plain_fallbacks = fallbacks;
      result_.mean_copies = counted ? double(total) / double(counted) : 0.0;
    }
  }
}

void Consolidator::colours() {
  const std::vector<Vec3d>& x = x_;
  std::vector<Rgb>& out = result_.cloud.colours;
  out.assign(ni_, Rgb{});
  const int* ids = input_grid_.ids().data();
  std::vector<char> missing(ni_, 0);
  // The weights of E1 (alpha_ij / v_j); a coincident input point, singular in
  // E1, is given the weight of one at 1e-9 h so that its colour dominates.
  tbb::parallel_for(tbb::blocked_range<int>(0, int(ni_), kGrain), [&](const tbb::blocked_range<int>& r) {
    Scratch& s = scratch_.local();
    for (int i = r.begin(); i < r.end(); ++i) {
      gather(input_grid_, x[i], kernel_.h2, s.input);
      const Neighbours& nb = s.input;
      double sw = 0, sr = 0, sg = 0, sb = 0;
      for (int k = 0; k < nb.n; ++k) {
        const double r2 = std::max(double(nb.r2[k]), kernel_.eps2);
        const double a = kernel_.theta(r2) / std::sqrt(r2) * inv_v_[nb.pos[k]];
        const Rgb& c = input_.colours[ids[nb.pos[k]]];
        sw += a;
        sr += a * c.r;
        sg += a * c.g;
        sb += a * c.b;
      }
      if (!(sw > 0)) {
        missing[i] = 1;
        continue;
      }
      auto channel = [&](double v) {
        return std::uint8_t(std::clamp(std::lround(v / sw), 0l, 255l));
      };
      out[i] = Rgb{channel(sr), channel(sg), channel(sb)};
    }
  });
  if (std::find(missing.begin(), missing.end(), 1) == missing.end()) return;
  const PointIndex index(input_.points);
  for (std::size_t i = 0; i < ni_; ++i)
    if (missing[i]) out[i] = input_.colours[index.nearest(result_.cloud.points[i]).first];
}

void Consolidator::normals() {
  const int k = std::min<int>(params_.normal_neighbours, int(ni_));
  std::vector<Vec3f>& n = result_.cloud.normals;
  if (k < 3) {
    n.assign(ni_, Vec3f::Zero());
    return;
  }
  n = estimate_normals(result_.cloud.points, k, 0);
  if (input_.has_normals())
    orient_normals_to(result_.cloud.points, n, input_.points, input_.normals, 8, 0);
  else
    orient_normals_mst(result_.cloud.points, n, k);
}

void validate(const Cloud& input, const WlopParams& p) {
  auto fail = [](const std::string& what) { throw InvalidInput("consolidate: " + what); };
  if (input.empty()) fail("empty input");
  input.check_consistent("consolidate input");
  if (!all_finite(input.points)) fail("input has non-finite coordinates");
  if (p.target_points == 0 && !(p.ratio > 0 && p.ratio <= 1)) fail("ratio must be in (0, 1]");
  if (p.iterations < 0) fail("iterations must be >= 0");
  if (!(p.radius >= 0) || !std::isfinite(p.radius)) fail("radius must be >= 0 and finite");
  if (!(p.mu >= 0 && p.mu < 0.5)) fail("mu must be in [0, 0.5)");
  if (p.threads < 0) fail("threads must be >= 0");
  if (!(p.inversion_radius > 0.25) || !std::isfinite(p.inversion_radius))
    fail("inversion_radius must be > 0.25 (units of d_bb)");
  if (p.shift_divisions < 1) fail("shift_divisions must be >= 1");
  if (p.max_copies < 1 || p.max_copies > 64) fail("max_copies must be in [1, 64]");
  if (p.normal_neighbours < 3) fail("normal_neighbours must be >= 3");
}

}  // namespace

std::vector<int> initial_subset(std::size_t n, std::size_t count, unsigned seed) {
  count = std::min(count, n);
  std::vector<int> pool(n);
  for (std::size_t i = 0; i < n; ++i) pool[i] = int(i);
  std::mt19937_64 rng(seed);
  // Partial Fisher-Yates with a plain modulo (bias < 2^-40 for any n we hold);
  // std::uniform_int_distribution would differ between standard libraries.
  for (std::size_t i = 0; i < count; ++i) {
    const std::size_t j = i + std::size_t(rng() % std::uint64_t(n - i));
    std::swap(pool[i], pool[j]);
  }
  pool.resize(count);
  std::sort(pool.begin(), pool.end());
  return pool;
}

WlopResult consolidate(const Cloud& input, const WlopParams& params) {
  validate(input, params);
  WlopResult result;
  result.input_points = input.size();
  const Aabb box = bounding_box(input.points);
  result.bbox_diagonal = (box.max.cast<double>() - box.min.cast<double>()).norm();
  if (!(result.bbox_diagonal > 0))
    throw InvalidInput("consolidate: all input points coincide (zero bounding box)");
  result.requested_points =
      params.target_points > 0
          ? params.target_points
          : std::max<std::size_t>(1, std::size_t(std::llround(params.ratio * double(input.size()))));
  result.clamped = result.requested_points > input.size();
  result.output_points = std::min(result.requested_points, input.size());

  Consolidator c(input, params, result);
  c.run();
  return result;
}

}  // namespace station
