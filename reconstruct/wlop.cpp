#include "reconstruct/wlop.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdint>
#include <limits>
#include <random>
#include <string>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <Eigen/Eigenvalues>

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
// kProjection's default fit radius r_f = max(kFitRadii h_0, kFitSigmas sigma), h_0 the
// default h (4 d_bb / sqrt |J|) whatever h is set to: about 130 input points within r_f
// on an object of area d_bb^2 where the noise allows. (The input's own spacing, its
// 16-NN distance, grows with the noise: 1.6 times on the cube at 0.3 %.) The fit's
// weights must spread along the surface well beyond the noise's spread across it, or
// its normal tilts with the noise (at r_f = 3 sigma the two are equal and a noisy plane
// was not flattened at all; 4.5 sigma gives twice the spread).
constexpr double kFitSigmas = 4.5;
constexpr double kFitRadii = 1.5;
// The edge variant's faces: neighbours whose simple normals lie within this angle of a
// face's (unsigned) count as its points; a face needs this share of the fit's weight;
// below kFaceAgreement of the weight agreeing with the plain plane, faces are sought;
// candidate normals from at most kFaceCandidates neighbours.
constexpr double kFaceAngle = 35.0;
constexpr double kFaceSupport = 0.15;
constexpr double kFaceAgreement = 0.9;
constexpr std::size_t kFaceCandidates = 12;
// Points of a face normal's plane fit (evenly strided over the neighbours within r_f).
constexpr int kSeedPoints = 48;
// kProjection: the fits' input is thinned to about this many points within r_f.
constexpr double kFitPoints = 192;
// kProjection's initial set (spread_subset): dart-throwing passes at most, and the
// cells of the grid that holds the kept points at most.
// The darts: the first kSpreadCandidates x |I| of the random order.
constexpr int kSpreadPasses = 8;
constexpr std::size_t kSpreadCandidates = 4;
constexpr double kSpreadCells = 16e6;
// kProjection's repulsion radius in output spacings (sqrt(2 A / (sqrt 3 |I|)), the
// nearest-neighbour distance of |I| points hexagonally packed on the estimated area).
constexpr double kRepulsionSpacings = 2.6;
// The centroid's pull along the plane acts beyond this many standard deviations of the
// fit's weights (iterate, below). 0.3 until 2026-12-06; 0.4 evens a part whose faces
// end in rims (docs/consolidation.md, "Third pass"). Where the edge variant fits two or
// more faces it stays 0.3: with 0.4 the points near the cube's edges lay 9 % further
// from the faces.
constexpr double kPullDeadZone = 0.4;
constexpr double kPullDeadZoneCrease = 0.3;
// With oriented normals, the area (and E2's radius) is measured again after this many
// iterations, each point counting its neighbours on its own side only
// (repulsion_radius).
constexpr int kOneSideAreaAfter = 6;
// ... among this many times the k nearest.
constexpr int kOneSideSearch = 3;
// curvature_offset's gate: the squared number of standard deviations b must exceed.
constexpr double kCurvatureGate = 4.0;
// Noise estimate: at most this many input points sampled, at neighbourhood sizes
// k = 16, 64, 256 (the smallest whose median residual is below a quarter of its
// median radius).
constexpr int kNoiseSamples = 2048;

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

// The first `count` entries of v drawn by a partial Fisher-Yates shuffle driven by
// std::mt19937_64(seed), with a plain modulo (bias < 2^-40 for any size we hold;
// std::uniform_int_distribution would differ between standard libraries).
void shuffle_front(std::vector<int>& v, std::size_t count, unsigned seed) {
  std::mt19937_64 rng(seed);
  for (std::size_t i = 0; i < count; ++i) {
    const std::size_t j = i + std::size_t(rng() % std::uint64_t(v.size() - i));
    std::swap(v[i], v[j]);
  }
}

// One pass of dart throwing: the candidates in the given order, each kept unless a kept
// one lies within r of it (a grid of cells no smaller than r holds the kept ones).
std::vector<int> dart_throw(const std::vector<Vec3d>& p, const std::vector<int>& order, double r) {
  if (order.empty()) return {};
  Vec3d lo = p[std::size_t(order[0])], hi = lo;
  for (int j : order) {
    lo = lo.cwiseMin(p[std::size_t(j)]);
    hi = hi.cwiseMax(p[std::size_t(j)]);
  }
  double cell = r;
  Eigen::Vector3i dim;
  for (;;) {  // at most kSpreadCells cells: coarser cells just hold more points each
    double d[3];
    for (int a = 0; a < 3; ++a) d[a] = std::ceil((hi[a] - lo[a]) / cell) + 1;
    if (d[0] * d[1] * d[2] <= kSpreadCells) {
      for (int a = 0; a < 3; ++a) dim[a] = std::max(1, int(d[a]));
      break;
    }
    cell *= 1.25;
  }
  std::vector<int> head(std::size_t(dim[0]) * std::size_t(dim[1]) * std::size_t(dim[2]), -1), next, kept;
  const auto index = [&](const Vec3d& q, int a) {
    return std::clamp(int((q[a] - lo[a]) / cell), 0, dim[a] - 1);
  };
  const double r2 = r * r;
  for (int j : order) {
    const Vec3d& q = p[std::size_t(j)];
    const int cx = index(q, 0), cy = index(q, 1), cz = index(q, 2);
    bool free = true;
    for (int z = std::max(0, cz - 1); free && z <= std::min(dim[2] - 1, cz + 1); ++z)
      for (int y = std::max(0, cy - 1); free && y <= std::min(dim[1] - 1, cy + 1); ++y)
        for (int x = std::max(0, cx - 1); free && x <= std::min(dim[0] - 1, cx + 1); ++x)
          for (int k = head[(std::size_t(z) * std::size_t(dim[1]) + std::size_t(y)) * std::size_t(dim[0]) + std::size_t(x)];
               k >= 0 && free; k = next[std::size_t(k)])
            free = (p[std::size_t(kept[std::size_t(k)])] - q).squaredNorm() >= r2;
    if (!free) continue;
    const std::size_t c = (std::size_t(cz) * std::size_t(dim[1]) + std::size_t(cy)) * std::size_t(dim[0]) + std::size_t(cx);
    next.push_back(head[c]);
    head[c] = int(kept.size());
    kept.push_back(j);
  }
  return kept;
}

// kProjection's initial set: `count` of the candidates spread out by dart throwing (a
// maximal Poisson-disk sample) in a seeded random order, the disk radius found by the
// power law count ~ r^-2 over a few passes; then the first `count` kept, in that order
// (or, where no radius keeps enough, the last pass's kept ones and the others in order).
// Returned sorted. A random subset carries the input's density and its random clumps,
// which E2 only evens out locally: measured at 35 iterations (all the input thrown),
// uniformity 0.840 -> 0.854 on the Rubik's cube at 1 % noise, 0.884 -> 0.900 at 0.3 %,
// 0.854 -> 0.862 on the mustard bottle at 1 %; with the first 4 |I| thrown (below),
// 0.852, 0.899 and 0.862.
std::vector<int> spread_subset(const std::vector<Vec3d>& p, std::vector<int> order, std::size_t count,
                               unsigned seed, double dbb) {
  if (!order.empty()) shuffle_front(order, order.size() - 1, seed);
  if (count >= order.size() || count == 0) {
    order.resize(std::min(count, order.size()));
    std::sort(order.begin(), order.end());
    return order;
  }
  // The darts: the first kSpreadCandidates x count of the random order (a dense input
  // need not be thrown whole: 1M -> 20k took 2.2 s so).
  const std::vector<int> darts(order.begin(),
                               order.begin() + std::ptrdiff_t(std::min(order.size(), kSpreadCandidates * count)));
  double r = dbb / std::sqrt(double(count));
  std::vector<int> best, last;
  std::size_t before = 0;
  for (int pass = 0; pass < kSpreadPasses; ++pass) {
    last = dart_throw(p, darts, r);
    const std::size_t n = last.size();
    if (n >= count && (best.empty() || n < best.size())) best = last;
    if (n >= count && n <= count + count / 50) break;
    if (n < count && pass > 0 && n <= before) break;  // no more distinct positions to gain
    before = n;
    // count ~ r^-2; aim a little high so that the next pass keeps enough.
    r *= std::sqrt(double(n) / double(count)) * (n >= count ? 1.0 : 0.99);
    if (!(r > 0) || !std::isfinite(r)) break;
  }
  if (best.empty()) {
    best = last;
    std::vector<char> taken(p.size(), 0);
    for (int j : best) taken[std::size_t(j)] = 1;
    for (int j : order)
      if (best.size() < count && !taken[std::size_t(j)]) best.push_back(j);
  }
  best.resize(count);
  std::sort(best.begin(), best.end());
  return best;
}

struct Scratch {
  int faces = 0;  // kProjection's edge variant: the faces the last fit found (0: one plane)
  Neighbours input;
  Neighbours fit;              // kProjection: the input within r_f
  std::vector<double> fw, rw;  // its weights, and those of one face (edge variant)
  std::vector<Vec3d> nrm;      // edge variant: its simple normals
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
        dbb_(result.bbox_diagonal),
        frame_dbb_(params.frame_diagonal > 0 ? params.frame_diagonal : result.bbox_diagonal),
        frame_nj_(double(params.frame_points > 0 ? params.frame_points : input.size())) {}

  void run();

 private:
  void setup();
  void iterate(bool last);
  void colours();
  void normals();

  // kProjection's fit at q: the weighted centroid of the input within r_f as an offset
  // m from q, and the plane (a point on it as an offset from q, and its unit normal n;
  // n = 0 where fewer than 3 points or no plane). The edge variant's plane is the
  // nearest face's where the faces disagree. False when no input point is within r_f.
  // `lateral` is the normal of the plain fit at this point in the iteration before (zero
  // when none), which sets the weights; it is updated.
  // `side` (oriented input normals only, else null): the point's side, updated.
  bool fit_plane(const Vec3d& q, Scratch& s, Vec3d& m, Vec3d& on_plane, Vec3d& n, Vec3d& lateral,
                 Vec3d* side) const;
  void estimate_noise();
  // The fits' weight of a squared distance: (1 - r^2 / r_f^2)^2 within r_f (the
  // biweight: smooth, no exponential, and as wide as exp(-r^2 / (r_f / 2)^2), standard
  // deviation r_f / sqrt 8 along each axis).
  double fit_weight(double r2) const {
    const double u = 1 - r2 * fit_inv_s2_;
    return u > 0 ? u * u : 0.0;
  }
  // kProjection, once the initial points are projected: the area they cover and E2's
  // radius from it. one_side (with oriented normals): each point's neighbours on its
  // own side only.
  void repulsion_radius(bool one_side);
  // kProjection, after the last iteration: every point onto its fitted plane (the
  // last E2 step left it up to a step's sag off a curved surface).
  void project();

  // The edge variant's E2 sums at a crease (the fit found two or more faces; n the
  // normal of the face q went onto): each neighbour's offset d from q is split into its
  // parts along the face's plane (t) and across it (a), and counted as lying at
  // |t| + |a| along t: the distance over the surface to a point across a right-angled
  // crease, where the straight distance is shorter (sqrt(t^2 + a^2)) and so weighed
  // more in E2 and pushed the points off the crease from both sides (beta = theta / r,
  // whatever repulsion_weight says).
  KernelSums unfolded_repulsion(const Vec3d& q, const Vec3d& n) const;
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
  // The scale of the defaults (h, r_f) and of eq. 10: the whole cloud's when the input
  // is a part of it (WlopParams::frame_diagonal / frame_points), else the input's.
  double frame_dbb_ = 0, frame_nj_ = 0;
  std::size_t nj_ = 0;
  Kernel kernel_{1.0};
  Kernel repulsion_{1.0};  // E2's and w_i's theta: kernel_ but with kProjection
  std::vector<Vec3d> p_;            // input, double
  RadiusGrid input_grid_, x_grid_;  // input: built once; projected: every iteration
  std::vector<double> inv_v_;       // 1 / v_j by input-grid sorted position
  // Edge variant, by input-grid sorted position (kFloatPad more records): the
  // simple normal n (eqs. 11-12) with the sign of the PCA normal m, which only
  // serves to orient it, and v_j (detail::EdgeRecord).
  std::vector<float> records_;
  bool oriented_ = false;  // n are the input's (oriented) normals
  // kProjection: the input's grid for radius r_f (input_grid_ itself when r_f = h), the
  // fit weights' 1 / v_j and (edge variant) the simple normals by its sorted position.
  bool projection_ = false;
  const RadiusGrid* fit_ = nullptr;
  RadiusGrid fit_grid_;
  double rf2_ = 0, fit_inv_s2_ = 0, fit_sigma_ = 0, face_cos_ = 1;
  std::vector<double> fit_inv_v_;
  std::vector<Vec3f> fit_seed_;
  std::vector<int> fit_id_;  // input index of each fit-grid sorted position
  std::vector<Vec3f> fit_side_;   // their normals, by fit-grid sorted position
  std::vector<Vec3d> side_;       // each projected point's side: its normal, oriented
  std::vector<Vec3d> x_, x_next_;   // projected set
  std::vector<Vec3d> xn_;           // kProjection: each point's plain fit normal (by index)
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
    if (projection_ && params_.iterations > 0) {
      project();
      repulsion_radius(false);
    }
    for (int k = 0; k < params_.iterations; ++k) {
      iterate(k + 1 == params_.iterations);
      if (projection_ && !side_.empty() && k + 1 == kOneSideAreaAfter && k + 1 < params_.iterations)
        repulsion_radius(true);
      if (params_.progress) params_.progress(k + 1, params_.iterations);
    }
    if (projection_ && params_.iterations > 0) project();
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
  const double h = params_.radius > 0 ? params_.radius : 4.0 * frame_dbb_ / std::sqrt(frame_nj_);
  kernel_ = Kernel(h);
  result_.radius = h;

  input_grid_.build(p_.data(), nj_, h);
  const bool edge = params_.method == WlopMethod::kEdgeWlop;
  projection_ = params_.attraction == WlopAttraction::kProjection;
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
      if (!edge || projection_) continue;
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
  // kProjection starts from a spread-out subset instead (spread_subset, whose darts
  // never keep two of one position; where it must fill up with others, it is drawn
  // again over the first occurrences as above).
  std::vector<int> all(nj_);
  for (std::size_t j = 0; j < nj_; ++j) all[j] = int(j);
  std::vector<int> subset = projection_ ? spread_subset(p_, all, ni_, params_.seed, dbb_)
                                        : initial_subset(nj_, ni_, params_.seed);
  if (has_coincident(p_, subset)) {
    const std::vector<int> distinct = first_occurrences(p_);
    if (distinct.size() < ni_) {
      ni_ = distinct.size();
      result_.output_points = ni_;
      result_.clamped = true;
    }
    if (projection_) {
      subset = spread_subset(p_, distinct, ni_, params_.seed, dbb_);
    } else {
      subset = initial_subset(distinct.size(), ni_, params_.seed);
      for (int& j : subset) j = distinct[std::size_t(j)];
    }
  }
  if (projection_) {
    estimate_noise();
    const double rf = params_.fit_radius > 0 ? params_.fit_radius
                                             : std::max(kFitRadii * 4.0 * frame_dbb_ / std::sqrt(frame_nj_),
                                                        kFitSigmas * result_.noise);
    result_.fit_radius = rf;
    rf2_ = rf * rf;
    fit_inv_s2_ = 1.0 / rf2_;  // weights (1 - r^2 / r_f^2)^2
    fit_sigma_ = rf / (2 * std::sqrt(2.0));  // their standard deviation along each axis
    face_cos_ = std::cos(kFaceAngle * M_PI / 180.0);
    // The fits need tens of points, not the thousands a dense input puts within r_f:
    // where the input holds more than kFitPoints within r_f on average (counted around
    // a strided sample), the fits use a seeded random subset of it that holds about
    // that many. With oriented normals a fit keeps to its own side's points (below), so
    // those are what is counted: where both faces of a thin part lie within r_f, a
    // count over both halved each fit (the blade: about 96 points a fit, accuracy 0.71
    // per mille of d_bb; docs/consolidation.md, "Fourth pass").
    if (rf == h) {
      fit_ = &input_grid_;
    } else {
      fit_grid_.build(p_.data(), nj_, rf);
      fit_ = &fit_grid_;
    }
    {
      Scratch& s = scratch_.local();
      const std::size_t stride = std::max<std::size_t>(1, nj_ / kNoiseSamples);
      double sum = 0, samples = 0;
      const bool sides = input_.has_normals();
      const int* counted = fit_->ids().data();
      for (std::size_t j = 0; j < nj_; j += stride, ++samples) {
        gather(*fit_, p_[j], rf2_, s.fit);
        Vec3f side = Vec3f::Zero();
        if (sides) side = input_.normals[j];
        if (!(side.squaredNorm() > 0)) {
          sum += s.fit.n;
          continue;
        }
        int same = 0;
        for (int k = 0; k < s.fit.n; ++k)
          same += input_.normals[std::size_t(counted[s.fit.pos[k]])].dot(side) > 0;
        sum += same;
      }
      const double mean = sum / std::max(1.0, samples);
      std::vector<int> kept;
      if (mean > 2 * kFitPoints) {
        kept = initial_subset(nj_, std::size_t(std::llround(double(nj_) * kFitPoints / mean)),
                              params_.seed + 1);
        std::vector<Vec3d> pts(kept.size());
        for (std::size_t k = 0; k < kept.size(); ++k) pts[k] = p_[std::size_t(kept[k])];
        fit_grid_.build(pts.data(), pts.size(), rf);
        fit_ = &fit_grid_;
      }
      result_.fit_points = kept.empty() ? nj_ : kept.size();
      const std::vector<int>& ids = fit_->ids();
      fit_id_.resize(ids.size());
      for (std::size_t sp = 0; sp < ids.size(); ++sp)
        fit_id_[sp] = kept.empty() ? ids[sp] : kept[std::size_t(ids[sp])];
    }
    const std::size_t nf = fit_id_.size();
    const std::vector<int>& input_pos = input_grid_.positions();
    fit_inv_v_.assign(nf + RadiusGrid::kPad, 1.0);
    for (std::size_t sp = 0; sp < nf; ++sp)
      fit_inv_v_[sp] = inv_v_[std::size_t(input_pos[std::size_t(fit_id_[sp])])];
    // With oriented input normals, each fit keeps to the points of its own side: the
    // two faces of a part thinner than the noise is wide are told apart by them alone.
    // (Without them, a part thinner than r_f is fitted as one sheet: docs/consolidation.md.)
    if (input_.has_normals()) {
      fit_side_.resize(nf);
      for (std::size_t sp = 0; sp < nf; ++sp) fit_side_[sp] = input_.normals[std::size_t(fit_id_[sp])];
      // And the fits' density weights 1 / v_j count the points of the same side only.
      // Eq. 6 over both sides weighs a point by how far it lies from the other face:
      // where the faces are closer than the noise is wide, a face's points that strayed
      // towards the other have more neighbours than those that strayed away, so the
      // weighted centroid lay outside the face (the blade at 0.3 % noise: both faces'
      // points 0.18 of the thickness outwards; accuracy 1.20 -> 0.69 per mille of d_bb).
      if (!uniform) {
        const int* ids = input_grid_.ids().data();
        tbb::parallel_for(tbb::blocked_range<int>(0, int(nf), kGrain), [&](const tbb::blocked_range<int>& r) {
          Scratch& s = scratch_.local();
          for (int sp = r.begin(); sp < r.end(); ++sp) {
            const std::size_t id = std::size_t(fit_id_[std::size_t(sp)]);
            const Vec3f& side = input_.normals[id];
            if (!(side.squaredNorm() > 0)) continue;  // no side: eq. 6 over both, as set above
            gather(input_grid_, p_[id], kernel_.h2, s.input);
            double v = 0;  // p_j itself included (theta(0) = 1), eq. 6's "1 +"
            for (int k = 0; k < s.input.n; ++k)
              if (input_.normals[std::size_t(ids[s.input.pos[k]])].dot(side) > 0 || ids[s.input.pos[k]] == int(id))
                v += kernel_.theta(double(s.input.r2[k]));
            fit_inv_v_[std::size_t(sp)] = 1.0 / std::max(1.0, v);
          }
        });
      }
    }
    if (edge) {
      // The faces' normals: the input's own (EdgeNormals::kInput), else the simple
      // normals (eqs. 11-12) over each fit point's neighbours within r_f, the scale
      // the noise allows (within h they would be as noisy as the noise is wide).
      fit_seed_.assign(nf, Vec3f::Zero());
      tbb::parallel_for(tbb::blocked_range<int>(0, int(nf), kGrain), [&](const tbb::blocked_range<int>& r) {
        Scratch& s = scratch_.local();
        for (int sp = r.begin(); sp < r.end(); ++sp) {
          const int id = fit_id_[std::size_t(sp)];
          if (input_normals) {
            fit_seed_[std::size_t(sp)] = input_.normals[std::size_t(id)].normalized();
            continue;
          }
          gather(*fit_, p_[std::size_t(id)], rf2_, s.fit);
          const Neighbours& nb = s.fit;
          const int stride = std::max(1, (nb.n + kSeedPoints - 1) / kSeedPoints);
          s.points.clear();
          for (int k = 0; k < nb.n; k += stride)
            s.points.emplace_back(double(nb.dx[k]), double(nb.dy[k]), double(nb.dz[k]));
          fit_seed_[std::size_t(sp)] = simple_normal(s.points.data(), int(s.points.size()), 4).cast<float>();
        }
      });
    }
  }
  repulsion_ = kernel_;
  result_.repulsion_radius = repulsion_.h;
  x_.resize(ni_);
  for (std::size_t i = 0; i < ni_; ++i) x_[i] = p_[subset[i]];
  x_next_.resize(ni_);
  xn_.assign(ni_, Vec3d::Zero());
  if (projection_ && input_.has_normals()) {
    side_.resize(ni_);
    for (std::size_t i = 0; i < ni_; ++i) side_[i] = input_.normals[std::size_t(subset[i])].cast<double>();
  }
  w_.assign(ni_ + RadiusGrid::kPad, 1.0);
  isolated_.assign(ni_, 0);
  copies_.assign(ni_, 0);
}

// The least-spread direction (unit) of a weighted set of offsets around their weighted
// mean; zero when the weights vanish or fewer than 3 points.
bool weighted_plane(const Neighbours& nb, const double* w, Vec3d& mean, Vec3d& normal) {
  // One pass: the weights' sums of 1, d and d d^T (offsets d of order r_f from x_i, so
  // the covariance E[d d^T] - m m^T loses nothing that matters in double).
  double sw = 0, sx = 0, sy = 0, sz = 0, sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
  for (int k = 0; k < nb.n; ++k) {
    const double wk = w[k], x = nb.dx[k], y = nb.dy[k], z = nb.dz[k];
    sw += wk;
    sx += wk * x;
    sy += wk * y;
    sz += wk * z;
    sxx += wk * x * x;
    sxy += wk * x * y;
    sxz += wk * x * z;
    syy += wk * y * y;
    syz += wk * y * z;
    szz += wk * z * z;
  }
  if (!(sw > 0)) return false;
  const Vec3d m(sx / sw, sy / sw, sz / sw);
  mean = m;
  normal = Vec3d::Zero();
  if (nb.n < 3) return true;
  Eigen::Matrix3d c;
  c << sxx / sw - m.x() * m.x(), sxy / sw - m.x() * m.y(), sxz / sw - m.x() * m.z(),
       0, syy / sw - m.y() * m.y(), syz / sw - m.y() * m.z(),
       0, 0, szz / sw - m.z() * m.z();
  c(1, 0) = c(0, 1);
  c(2, 0) = c(0, 2);
  c(2, 1) = c(1, 2);
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
  es.computeDirect(c);
  if (es.info() != Eigen::Success) return true;
  const Vec3d n = es.eigenvectors().col(0);
  if (n.allFinite() && n.norm() > 0.5) normal = n.normalized();
  return true;
}

// The plane through the weighted centroid lies inside a curved surface by about its
// curvature times the weights' mean squared radius over 2 (on a unit sphere sampled with
// 6,000 points, 0.009 at the default r_f: worse than the noise). The heights above the
// plane are fitted as h = a + b r^2 (r the distance along the plane from the centroid;
// the mean curvature's paraboloid; the part of the curvature that differs between
// directions averages out under round weights); the offset of the surface below x_i,
// b (rho^2 - mean r^2) with rho x_i's distance along the plane from the centroid, is
// shrunk by max(0, 1 - kCurvatureGate var b / b^2), so that where b is within two of its
// standard deviations (flat parts) the plane is kept and the fit's noise is not raised by
// the extra unknown (b^2 / (b^2 + var b) instead cost the flat cube 25 % of its accuracy).
double curvature_offset(const Neighbours& nb, const double* w, const Vec3d& m, const Vec3d& n) {
  double s0 = 0, s1 = 0, s2 = 0, t1 = 0, hh = 0, q0 = 0, q1 = 0, q2 = 0;
  for (int k = 0; k < nb.n; ++k) {
    const Vec3d d = Vec3d(nb.dx[k], nb.dy[k], nb.dz[k]) - m;
    const double h = n.dot(d), r2 = d.squaredNorm() - h * h, wk = w[k], w2 = wk * wk;
    s0 += wk;
    s1 += wk * r2;
    s2 += wk * r2 * r2;
    t1 += wk * h * r2;
    hh += wk * h * h;
    q0 += w2;
    q1 += w2 * r2;
    q2 += w2 * r2 * r2;
  }
  if (!(s0 > 0) || nb.n < 8) return 0;
  const double mean = s1 / s0;
  const double sxx = s2 - s1 * mean;  // sum w (r^2 - mean)^2
  if (!(sxx > 0)) return 0;
  // sum w h = 0 about the centroid, so b = sum w (r^2 - mean) h / sxx = t1 / sxx.
  const double b = t1 / sxx;
  const double residual = std::max(0.0, (hh - b * t1) / s0);
  const double spread = q2 - 2 * mean * q1 + mean * mean * q0;  // sum w^2 (r^2 - mean)^2
  const double var_b = residual * spread / (sxx * sxx);
  const double gain = b * b > 0 ? std::max(0.0, 1 - kCurvatureGate * var_b / (b * b)) : 0.0;
  if (!std::isfinite(gain)) return 0;
  const Vec3d along = -m + m.dot(n) * n;  // x_i's offset from the centroid along the plane
  return gain * b * (along.squaredNorm() - mean);
}

void Consolidator::project() {
  tbb::parallel_for(tbb::blocked_range<int>(0, int(ni_), kGrain), [&](const tbb::blocked_range<int>& r) {
    Scratch& s = scratch_.local();
    for (int i = r.begin(); i < r.end(); ++i) {
      Vec3d m, on_plane, n;
      if (fit_plane(x_[i], s, m, on_plane, n, xn_[i], side_.empty() ? nullptr : &side_[i]))
        x_[i] += on_plane.dot(n) * n;
    }
  });
}

void Consolidator::repulsion_radius(bool one_side) {
  // Each projected point stands for pi rho^2 / (k - 1) of the surface, rho the distance
  // to its k-th nearest (itself counted): for a random sample of an area, the expected
  // share. Measured on the projected points, not the input, whose noise widens rho
  // (fandisk at 1 % noise: the input's estimate was 2.65 x the area).
  // Where two faces are closer than rho, both are counted: the blade's area came out
  // 0.84 x its own, E2's radius 8 % short. Counting only the neighbours on the point's
  // own side (one_side) is right once each face is even (1.03 x after 6 iterations,
  // 0.99 at the end) but not at the start, where the spread subset holds the two
  // faces as one even set and each face alone is a random half of it (1.20 x); hence
  // the second measurement (docs/consolidation.md, "Third pass").
  const int k = int(std::min<std::size_t>(16, ni_));
  one_side = one_side && side_.size() == ni_;
  if (k < 4) return;
  std::vector<Vec3f> pts(ni_);
  for (std::size_t i = 0; i < ni_; ++i) pts[i] = x_[i].cast<float>();
  const PointIndex index(pts);
  std::vector<double> share(ni_);
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, ni_, kGrain), [&](const tbb::blocked_range<std::size_t>& r) {
    for (std::size_t i = r.begin(); i < r.end(); ++i) {
      double rho = 0;
      if (one_side && side_[i].squaredNorm() > 0) {
        // The k-th nearest facing i's way among its kOneSideSearch * k nearest (the
        // farthest of those where fewer face its way). A point without a side (a zero
        // normal) counts both sides, as fit_plane does.
        const auto nn = index.knn(pts[i], kOneSideSearch * k);
        int same = 0;
        for (const auto& [j, d] : nn) {
          rho = double(d);
          if (side_[std::size_t(j)].dot(side_[i]) > 0 && ++same == k) break;
        }
      } else {
        const auto nn = index.knn(pts[i], k);
        rho = nn.empty() ? 0.0 : double(nn.back().second);
      }
      share[i] = M_PI * rho * rho / double(k - 1);
    }
  });
  double area = 0;
  for (double a : share) area += a;  // in index order: the same sum for any thread count
  result_.area = area;
  // The output's spacing in a hexagonal packing of that area.
  const double spacing = std::sqrt(2.0 * area / (std::sqrt(3.0) * double(ni_)));
  const double hr = kRepulsionSpacings * spacing;
  if (hr > 0 && std::isfinite(hr)) repulsion_ = Kernel(hr);
  result_.repulsion_radius = repulsion_.h;
}

void Consolidator::estimate_noise() {
  // The median RMS residual of plane fits (PCA) over the k nearest input points of a
  // strided sample of the input, at the smallest k whose median residual is below a
  // quarter of its median neighbourhood radius: a ball not much wider than the noise's
  // spread holds a blob rather than a sheet and understates it. Curvature adds to it
  // (an upper bound on the noise). Deterministic: fixed sample, medians.
  std::vector<Vec3f> pts(input_.points);
  const PointIndex index(std::move(pts));
  const std::size_t stride = std::max<std::size_t>(1, nj_ / kNoiseSamples);
  std::vector<std::size_t> sample;
  for (std::size_t j = 0; j < nj_; j += stride) sample.push_back(j);
  double sigma = 0;
  for (int k : {16, 64, 256}) {
    const int kk = int(std::min<std::size_t>(std::size_t(k), nj_));
    if (kk < 4) break;
    std::vector<double> residual(sample.size()), radius(sample.size());
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, sample.size(), 16),
                      [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t i = r.begin(); i < r.end(); ++i) {
        const Vec3f& q = input_.points[sample[i]];
        const auto nn = index.knn(q, kk);
        Vec3d m = Vec3d::Zero();
        for (const auto& [id, d] : nn) m += (input_.points[std::size_t(id)] - q).cast<double>();
        m /= double(nn.size());
        Eigen::Matrix3d c = Eigen::Matrix3d::Zero();
        for (const auto& [id, d] : nn) {
          const Vec3d e = (input_.points[std::size_t(id)] - q).cast<double>() - m;
          c.noalias() += e * e.transpose();
        }
        Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
        es.computeDirect(c / double(nn.size()), Eigen::EigenvaluesOnly);
        residual[i] = std::sqrt(std::max(0.0, es.eigenvalues()(0)));
        radius[i] = nn.empty() ? 0.0 : double(nn.back().second);
      }
    });
    auto median = [](std::vector<double> v) {
      std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(v.size() / 2), v.end());
      return v[v.size() / 2];
    };
    sigma = median(residual);
    if (sigma < 0.25 * median(radius) || kk < k) break;
  }
  result_.noise = sigma;
}

bool Consolidator::fit_plane(const Vec3d& q, Scratch& s, Vec3d& m, Vec3d& on_plane, Vec3d& n,
                             Vec3d& lateral, Vec3d* side) const {
  s.faces = 0;
  gather(*fit_, q, rf2_, s.fit);
  Neighbours& nb = s.fit;
  if (side != nullptr && side->squaredNorm() > 0) {
    // Only the neighbours whose normal faces the same way.
    int kept = 0;
    for (int k = 0; k < nb.n; ++k) {
      if (!(fit_side_[std::size_t(nb.pos[k])].cast<double>().dot(*side) > 0)) continue;
      nb.pos[kept] = nb.pos[k];
      nb.dx[kept] = nb.dx[k];
      nb.dy[kept] = nb.dy[k];
      nb.dz[kept] = nb.dz[k];
      nb.r2[kept] = nb.r2[k];
      ++kept;
    }
    nb.n = kept;
  }
  if (nb.n == 0) return false;
  s.fw.resize(std::size_t(nb.n));
  // The weights are those of the distance along the plane: weights of the 3-D distance
  // favour the points at x_i's own height and hold the fit towards it (measured: one
  // projection of a noisy plane kept a third of the offset). The plane is the one of
  // the iteration before; the first time, a fit with 3-D weights gives it.
  // (A zero normal gives the weights of the 3-D distance.)
  const auto lateral_weights = [&](const Vec3d& along_normal) {
    for (int k = 0; k < nb.n; ++k) {
      const double along = along_normal.dot(Vec3d(nb.dx[k], nb.dy[k], nb.dz[k]));
      const double r2 = std::max(0.0, double(nb.r2[k]) - along * along);
      s.fw[std::size_t(k)] = fit_weight(r2) * fit_inv_v_[std::size_t(nb.pos[k])];
    }
  };
  if (lateral.isZero()) {
    lateral_weights(lateral);
    if (!weighted_plane(nb, s.fw.data(), m, n)) return false;
    if (n.isZero()) return true;
    lateral = n;
  }
  lateral_weights(lateral);
  if (!weighted_plane(nb, s.fw.data(), m, n)) return false;
  if (!n.isZero()) lateral = n;
  if (side != nullptr && !n.isZero()) *side = n.dot(*side) < 0 ? Vec3d(-n) : n;
  on_plane = m;
  if (!n.isZero()) on_plane += curvature_offset(nb, s.fw.data(), m, n) * n;
  if (params_.method != WlopMethod::kEdgeWlop || n.isZero()) return true;
  // Faces: where the neighbours' simple normals (eqs. 11-12, which stay with their face
  // up to a crease, unlike PCA's) do not all agree with the plane, up to three planes
  // are fitted, each to the neighbours whose normal lies within kFaceAngle of a
  // candidate normal (the candidates: the normals of evenly strided neighbours, the
  // best supported first), and x_i goes onto the nearest of them.
  const std::size_t count = std::size_t(nb.n);
  s.rw.resize(count);
  s.nrm.resize(count);
  double total = 0, agree = 0;
  for (std::size_t k = 0; k < count; ++k) {
    s.nrm[k] = fit_seed_[std::size_t(nb.pos[k])].cast<double>();
    total += s.fw[k];
    if (std::abs(s.nrm[k].dot(n)) > face_cos_) agree += s.fw[k];
  }
  if (agree >= kFaceAgreement * total) return true;
  // Candidate normals and their support (weight of the neighbours within kFaceAngle).
  const std::size_t stride = std::max<std::size_t>(1, count / kFaceCandidates);
  Vec3d cand[kFaceCandidates + 1];
  double support[kFaceCandidates + 1];
  int candidates = 0;
  for (std::size_t c = 0; c < count && candidates <= int(kFaceCandidates); c += stride) {
    if (!(s.nrm[c].squaredNorm() > 0.25)) continue;
    cand[candidates] = s.nrm[c];
    support[candidates++] = 0;
  }
  // (Counted over at most kSeedPoints evenly strided neighbours: a share needs no more.)
  const std::size_t step = std::max<std::size_t>(1, (count + kSeedPoints - 1) / kSeedPoints);
  for (std::size_t k = 0; k < count; k += step)
    for (int c = 0; c < candidates; ++c)
      if (std::abs(s.nrm[k].dot(cand[c])) > face_cos_) support[c] += s.fw[k];
  // Faces, the best supported first, each at least kFaceAngle from the ones before.
  Vec3d faces[3];
  int found = 0;
  double best_distance = std::numeric_limits<double>::infinity();
  Vec3d best_point = on_plane, best_normal = n;
  while (found < 3) {
    int pick = -1;
    for (int c = 0; c < candidates; ++c) {
      bool taken = false;
      for (int g = 0; g < found; ++g) taken = taken || std::abs(cand[c].dot(faces[g])) > face_cos_;
      if (!taken && (pick < 0 || support[c] > support[pick])) pick = c;
    }
    if (pick < 0 || !(support[pick] * double(step) >= kFaceSupport * total)) break;
    const Vec3d best = cand[pick];
    faces[found++] = best;
    for (std::size_t k = 0; k < count; ++k)
      s.rw[k] = std::abs(s.nrm[k].dot(best)) > face_cos_ ? s.fw[k] : 0.0;
    Vec3d point, normal;
    if (!weighted_plane(nb, s.rw.data(), point, normal) || normal.isZero()) continue;
    point += curvature_offset(nb, s.rw.data(), point, normal) * normal;
    const double distance = std::abs(point.dot(normal));
    if (distance < best_distance) {
      best_distance = distance;
      best_point = point;
      best_normal = normal;
    }
  }
  on_plane = best_point;
  n = best_normal;
  s.faces = found;
  return true;
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
  const double D = frame_dbb_ * agreement / (2.0 * kh);  // |x_i - c_i|
  // R must keep 2R - |p - c_i| > 0 over the neighbourhood (f stays a bijection).
  const double R = std::max(params_.inversion_radius * frame_dbb_, D + h);
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
  x_grid_.build(x_.data(), ni_, repulsion_.h);
  const int* xids = x_grid_.ids().data();
  const KernelShape shape = repulsion_.shape();
  // w_i of eq. 7 from the current iterate, stored by sorted position (the sum
  // includes x_i itself, which is the "1 +").
  tbb::parallel_for(tbb::blocked_range<int>(0, int(ni_), kGrain), [&](const tbb::blocked_range<int>& r) {
    for (int sp = r.begin(); sp < r.end(); ++sp)
      w_[sp] = detail::density_sum(x_grid_, x_[xids[sp]], shape).w;
  });
  const bool edge = params_.method == WlopMethod::kEdgeWlop;
  // E2 of eq. 3 at x_i (sorted position sp); the sums are over x_r - x_i, so
  // E2 = -d / w. beta = theta / r has E1's form (a pair closer than 1e-9 h left out,
  // x_i itself with it); beta = -theta (eq. 5 as printed): the signs cancel.
  const auto repulsion = [&](const Vec3d& q, int sp) {
    return params_.repulsion_weight == RepulsionWeight::kOriginal
               ? detail::attraction_sum(x_grid_, w_.data(), q, shape)
               : detail::repulsion_sum(x_grid_, w_.data(), q, shape, sp);
  };
  // Eq. 1 for every point from the previous iterate (Jacobi), in the projected
  // grid's order so that neighbouring points run one after another.
  tbb::parallel_for(tbb::blocked_range<int>(0, int(ni_), kGrain), [&](const tbb::blocked_range<int>& r) {
    Scratch& s = scratch_.local();
    for (int sp = r.begin(); sp < r.end(); ++sp) {
      const int i = xids[sp];
      const Vec3d& q = x_[i];
      if (projection_) {
        Vec3d m, on_plane, n;
        copies_[i] = -1;
        if (!fit_plane(q, s, m, on_plane, n, xn_[i], side_.empty() ? nullptr : &side_[i])) {
          x_next_[i] = q;
          isolated_[i] = 1;
          continue;
        }
        isolated_[i] = 0;
        // Onto the plane; along it, the centroid's pull beyond a dead zone of
        // kPullDeadZone standard deviations of the fit's weights. Inside the data the
        // centroid is within that of x_i (it wanders with the input's random density,
        // which would gather the points into clumps); at an open border it lies inwards
        // by most of one and holds the points on the data against E2.
        const Vec3d lateral = m - m.dot(n) * n;
        const double len = lateral.norm(), dead = (s.faces >= 2 ? kPullDeadZoneCrease : kPullDeadZone) * fit_sigma_;
        Vec3d next = q + on_plane.dot(n) * n;
        if (len > dead) next += (1 - dead / len) * lateral;
        // At a crease, E2 over distances along the surface (unfolded_repulsion).
        const KernelSums e2 = s.faces >= 2 ? unfolded_repulsion(q, n) : repulsion(q, sp);
        if (e2.w > 0) {
          Vec3d step = -params_.mu * e2.d / e2.w;
          step -= step.dot(n) * n;
          next += step;
        }
        x_next_[i] = next;
        continue;
      }
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
      const KernelSums e2 = repulsion(q, sp);
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
    if (edge && !projection_) {
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

KernelSums Consolidator::unfolded_repulsion(const Vec3d& q, const Vec3d& n) const {
  const double *xs = x_grid_.xs(), *ys = x_grid_.ys(), *zs = x_grid_.zs();
  KernelSums out;
  x_grid_.for_each_run(q, [&](int b, int e) {
    for (int p = b; p < e; ++p) {
      const Vec3d d(xs[p] - q.x(), ys[p] - q.y(), zs[p] - q.z());
      if (!(d.squaredNorm() < repulsion_.h2)) continue;
      const double across = d.dot(n);
      const Vec3d t = d - across * n;
      const double tl = t.norm(), l = tl + std::abs(across);
      if (!(l < repulsion_.h) || l * l <= repulsion_.eps2 || !(tl > 0)) continue;
      const double a = repulsion_.theta(l * l) / l * w_[std::size_t(p)];
      out.w += a;
      out.d += (a * l / tl) * t;
    }
  });
  return out;
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
  if (!(p.fit_radius >= 0) || !std::isfinite(p.fit_radius)) fail("fit_radius must be >= 0 and finite");
  if (!(p.frame_diagonal >= 0) || !std::isfinite(p.frame_diagonal)) fail("frame_diagonal must be >= 0 and finite");
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
  shuffle_front(pool, count, seed);
  pool.resize(count);
  std::sort(pool.begin(), pool.end());
  return pool;
}

void check_radii_within(const WlopParams& params, double diagonal) {
  // A neighbourhood as large as the cloud itself is no neighbourhood: every point
  // repels every other (points thrown off the object) and the work is n^2 (1e308 hung).
  for (const auto& [name, r] : {std::pair<const char*, double>{"radius", params.radius}, {"fit_radius", params.fit_radius}})
    if (r > diagonal) {
      char buf[160];
      std::snprintf(buf, sizeof buf, "consolidate: %s %.4g is larger than the cloud itself (bounding box diagonal %.4g)",
                    name, r, diagonal);
      throw InvalidInput(std::string(buf) + "; 0 takes it from the points' spacing");
    }
}

std::size_t wlop_requested_points(std::size_t n, const WlopParams& params) {
  if (params.target_points > 0) return params.target_points;
  std::size_t want = std::max<std::size_t>(1, std::size_t(std::llround(params.ratio * double(n))));
  if (params.max_points > 0) want = std::min(want, params.max_points);
  return std::max(want, std::min(params.min_points, n));
}

WlopResult consolidate(const Cloud& input, const WlopParams& params) {
  validate(input, params);
  WlopResult result;
  result.input_points = input.size();
  const Aabb box = bounding_box(input.points);
  result.bbox_diagonal = (box.max.cast<double>() - box.min.cast<double>()).norm();
  if (!(result.bbox_diagonal > 0))
    throw InvalidInput("consolidate: all input points coincide (zero bounding box)");
  check_radii_within(params, std::max(result.bbox_diagonal, params.frame_diagonal));
  if (params.max_points > 0 && params.min_points > params.max_points)
    throw InvalidInput("consolidate: min_points (" + std::to_string(params.min_points) + ") above max_points (" +
                       std::to_string(params.max_points) + ")");
  result.requested_points = wlop_requested_points(input.size(), params);
  result.clamped = result.requested_points > input.size();
  result.output_points = std::min(result.requested_points, input.size());

  Consolidator c(input, params, result);
  c.run();
  return result;
}

}  // namespace station
