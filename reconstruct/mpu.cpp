#include "reconstruct/mpu.h"

#include <tbb/collaborative_call_once.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>

#include "core/error.h"
#include "core/kdtree.h"
#include "core/normals.h"
#include "core/threads.h"
#include "reconstruct/detail/octree_split.h"
#include "reconstruct/near_grid.h"

namespace station {
namespace {

constexpr double kPi = 3.14159265358979323846;

// Quadratic B-spline b2(t), support |t| < 3/2.
double bspline2(double t) {
  t = std::abs(t);
  if (t < 0.5) return 0.75 - t * t;
  if (t < 1.5) return 0.5 * (1.5 - t) * (1.5 - t);
  return 0;
}
// d b2 / dt for t >= 0.
double bspline2_deriv(double t) {
  if (t < 0.5) return -2 * t;
  if (t < 1.5) return -(1.5 - t);
  return 0;
}

// w = h(u, v) over the plane through `origin` with normal n; Q = w - h, so Q > 0 on
// the side n points to (outside).
struct Bivariate {
  Vec3d origin = Vec3d::Zero(), u = Vec3d::UnitX(), v = Vec3d::UnitY(), n = Vec3d::UnitZ();
  double c[6] = {0, 0, 0, 0, 0, 0};  // c0 u^2 + c1 uv + c2 v^2 + c3 u + c4 v + c5
  double eval(const Vec3d& x, Vec3d* g) const {
    const Vec3d d = x - origin;
    const double a = d.dot(u), b = d.dot(v), w = d.dot(n);
    const double h = c[0] * a * a + c[1] * a * b + c[2] * b * b + c[3] * a + c[4] * b + c[5];
    if (g) {
      const double ha = 2 * c[0] * a + c[1] * b + c[3];
      const double hb = c[1] * a + 2 * c[2] * b + c[4];
      *g = n - ha * u - hb * v;
    }
    return w - h;
  }
};

// Q(x) = a . phi(y), y = (x - origin) / scale, phi = [y0^2, y1^2, y2^2, y0y1, y1y2,
// y2y0, y0, y1, y2, 1]; scaling by the ball radius keeps the normal equations
// conditioned.
struct Quadric {
  Vec3d origin = Vec3d::Zero();
  double inv_scale = 1;
  double a[10] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
  static void basis(const Vec3d& y, double* phi) {
    phi[0] = y[0] * y[0]; phi[1] = y[1] * y[1]; phi[2] = y[2] * y[2];
    phi[3] = y[0] * y[1]; phi[4] = y[1] * y[2]; phi[5] = y[2] * y[0];
    phi[6] = y[0]; phi[7] = y[1]; phi[8] = y[2]; phi[9] = 1;
  }
  // d phi / d y_k for k = 0..2 (rows).
  static void basis_grad(const Vec3d& y, double (*dphi)[10]) {
    for (int k = 0; k < 3; ++k)
      for (int j = 0; j < 10; ++j) dphi[k][j] = 0;
    dphi[0][0] = 2 * y[0]; dphi[1][1] = 2 * y[1]; dphi[2][2] = 2 * y[2];
    dphi[0][3] = y[1]; dphi[1][3] = y[0];
    dphi[1][4] = y[2]; dphi[2][4] = y[1];
    dphi[2][5] = y[0]; dphi[0][5] = y[2];
    dphi[0][6] = 1; dphi[1][7] = 1; dphi[2][8] = 1;
  }
  double eval(const Vec3d& x, Vec3d* g) const {
    const Vec3d y = (x - origin) * inv_scale;
    const double q = a[0] * y[0] * y[0] + a[1] * y[1] * y[1] + a[2] * y[2] * y[2] +
                     a[3] * y[0] * y[1] + a[4] * y[1] * y[2] + a[5] * y[2] * y[0] +
                     a[6] * y[0] + a[7] * y[1] + a[8] * y[2] + a[9];
    if (g) {
      *g = Vec3d(2 * a[0] * y[0] + a[3] * y[1] + a[5] * y[2] + a[6],
                 2 * a[1] * y[1] + a[3] * y[0] + a[4] * y[2] + a[7],
                 2 * a[2] * y[2] + a[4] * y[1] + a[5] * y[0] + a[8]) *
           inv_scale;
    }
    return q;
  }
};

struct LocalFit {
  MpuFitType type = MpuFitType::kBivariate;
  Quadric quadric;
  Bivariate piece[3];
  int pieces = 1;
  bool take_max = true;  // convex feature: intersection of the pieces' insides
  // Saddle corner (three pieces, edges of both kinds): pieces 0 and 1 meet at the
  // odd edge and are combined first, by the opposite of take_max; the result is
  // then combined with piece 2 by take_max. E.g. a notch's corner, where a concave
  // edge (0, 1) meets a top face (2) along two convex edges: max(min(f0, f1), f2).
  bool saddle = false;
  double eval(const Vec3d& x, Vec3d* g) const {
    if (type == MpuFitType::kQuadric) return quadric.eval(x, g);
    Vec3d gb;
    if (saddle) {
      Vec3d g0, g1, g2;
      const double q0 = piece[0].eval(x, g ? &g0 : nullptr);
      const double q1 = piece[1].eval(x, g ? &g1 : nullptr);
      const double q2 = piece[2].eval(x, g ? &g2 : nullptr);
      const bool first = take_max ? q0 <= q1 : q0 >= q1;  // inner: the opposite op
      const double inner = first ? q0 : q1;
      const bool outer_inner = take_max ? inner >= q2 : inner <= q2;
      if (g) *g = outer_inner ? (first ? g0 : g1) : g2;
      return outer_inner ? inner : q2;
    }
    double best = piece[0].eval(x, g ? &gb : nullptr);
    Vec3d best_g = gb;
    for (int i = 1; i < pieces; ++i) {
      const double q = piece[i].eval(x, g ? &gb : nullptr);
      if (take_max ? q > best : q < best) best = q, best_g = gb;
    }
    if (g) *g = best_g;
    return best;
  }
};

struct Node {
  Vec3d center;
  double half = 0;    // half the cell side
  double radius = 0;  // support radius R (leaves)
  double reach = 0;   // max distance from center to any point of a descendant leaf's ball
  int first_child = -1;
  int fit = -1;     // a leaf's fit in Impl::fits (sharp or quadric fits), or -1
  int single = -1;  // a leaf's single bivariate fit in Impl::singles, or -1
  int depth = 0;
};

}  // namespace

struct MpuSurface::Impl {
  MpuParams params;
  MpuDiagnostics diag;
  Vec3d center = Vec3d::Zero();  // world -> normalised: (x - center) * scale
  double scale = 1;
  Aabb bounds;
  std::vector<Vec3f> world_points;
  std::vector<Vec3f> points;  // normalised
  std::vector<Vec3d> normals;
  std::unique_ptr<PointIndex> index;  // over `points`
  std::vector<Node> nodes;
  // The leaves' fits: the common single bivariate ones (144 bytes) apart from the
  // others (a LocalFit holds every kind, 560 bytes); `singles` is only needed until
  // build_walk has copied them into the leaf records.
  std::vector<LocalFit> fits;
  std::vector<Bivariate> singles;
  double trust_radius = 0;  // normalised
  // Cells surely within trust_radius of a point (trusted() without a search); built
  // on the first trusted() call. Those calls come from inside parallel loops and the
  // build runs one itself: collaborative_call_once lets a thread that waits on the
  // build work on it (std::call_once could be re-entered on the building thread).
  mutable NearGrid trust_grid;
  mutable tbb::collaborative_once_flag trust_grid_once;
  // The distance from q (normalised) to its nearest point, or 0 where the trust grid
  // proves it within trust_radius (infinite with no points).
  double trust_distance(const Vec3d& q) const {
    tbb::collaborative_call_once(trust_grid_once, [&] { trust_grid = NearGrid(points, trust_radius); });
    if (trust_grid.surely_near(q)) return 0;
    const auto [id, d] = index->nearest(q.cast<float>());
    return id >= 0 ? double(d) : std::numeric_limits<double>::infinity();
  }

  // With params.sparse_trust (and a median spacing): each point's allowance
  // (sparse_allowance), computed when first asked for; null otherwise.
  std::unique_ptr<SparseAllowances> allowances;
  // Some point p within (reach x allowance(p) + extra) x slack of q (normalised), given
  // that the nearest one lies `nearest` away; without sparse_trust, the nearest within
  // that with an allowance of 1. `slack` > 1 makes a bound (may_be_trusted_near) safe
  // against float rounding; the test itself (trusted) takes 1.
  bool within_allowance(const Vec3d& q, double nearest, double reach, double extra, double slack) const {
    if (nearest <= (reach + extra) * slack) return true;
    if (!allowances || !(nearest <= (reach * kSparseSpacingCap + extra) * slack)) return false;
    const float search = float((reach * kSparseSpacingCap + extra) * slack);
    return index->any_in_radius(q.cast<float>(), search, [&](int k, float d) {
      return d <= (reach * (*allowances)(k) + extra) * slack;
    });
  }

  // Evaluation layout, built once after the fit (the queries' time is mostly
  // cache misses on the octree's nodes and fits, docs/mpu.md "Evaluation"):
  // - per node, a float copy of its centre and squared reach (a leaf's: its
  //   support radius), enlarged so that it never rejects what the exact test
  //   would keep, and a link: first child, or -(leaf record + 1). 20 bytes, the
  //   8 children of a node side by side.
  // - per leaf, one 192-byte record with its exact centre and radius and, for the
  //   common single bivariate fit, the fit itself (other fits: `fits`).
  struct WalkNode {
    float x, y, z, r2;
    std::int32_t link;
  };
  struct alignas(64) LeafRecord {
    Vec3d center;
    double radius = 0;
    Bivariate bivariate;  // when single
    std::int32_t fit = -1;
    bool single = false;
  };
  std::vector<WalkNode> walk;
  std::vector<LeafRecord> leaf_records;
  // Per node: some leaf in its subtree has a sharp fit (edge or corner).
  std::vector<char> sharp_below;
  // Queries farther out than this (normalised) take the exact double test
  // throughout: the float bounds' slack covers the rounding of coordinates up to it.
  static constexpr double kFloatRange = 2.0;

  void build_walk() {
    walk.resize(nodes.size());
    leaf_records.clear();
    leaf_records.reserve(singles.size() + fits.size());
    for (std::size_t i = 0; i < nodes.size(); ++i) {
      const Node& nd = nodes[i];
      const double r = (nd.first_child < 0 ? nd.radius : nd.reach) * (1 + 1e-6) + 1e-6;
      WalkNode& w = walk[i];
      w = {float(nd.center.x()), float(nd.center.y()), float(nd.center.z()), float(r * r * (1 + 1e-6)),
           nd.first_child};
      if (nd.first_child >= 0) continue;  // every other node is a fitted leaf
      LeafRecord rec;
      rec.center = nd.center;
      rec.radius = nd.radius;
      rec.fit = nd.fit;
      rec.single = nd.single >= 0;
      if (rec.single) rec.bivariate = singles[std::size_t(nd.single)];
      w.link = -std::int32_t(leaf_records.size()) - 1;
      leaf_records.push_back(rec);
    }
    // Children come after their parent in `nodes`.
    sharp_below.assign(nodes.size(), 0);
    for (std::size_t i = nodes.size(); i-- > 0;) {
      const Node& nd = nodes[i];
      if (nd.first_child < 0) {
        sharp_below[i] = nd.fit >= 0 && fits[std::size_t(nd.fit)].pieces > 1;
      } else {
        for (int c = 0; c < 8; ++c) sharp_below[i] |= sharp_below[std::size_t(nd.first_child + c)];
      }
    }
  }

  // value() (with out) and gradient() (with grads) at n points (world units) from one walk: the
  // leaves that may reach the points' bounding ball, gathered in accumulate()'s
  // depth-first order, then for each point the same exact test and sums as
  // accumulate() and eval() (so the same bits).
  void near(const Vec3d* xs, int n, double* out, Vec3d* grads) const {
    if (n <= 0) return;
    thread_local std::vector<Vec3d> ys;
    thread_local std::vector<std::int32_t> leaves;
    // The gathered leaves' centres and radii, side by side: most leaves miss most of
    // the batch's points (the DMC's batches: ~16 points, ~150 leaves each), and their
    // exact test then reads these instead of each leaf's 192-byte record.
    thread_local std::vector<double> lx, ly, lz, lr, lr2;
    thread_local std::vector<std::uint32_t> inside;
    ys.resize(std::size_t(n));
    Vec3d lo = Vec3d::Constant(std::numeric_limits<double>::infinity()), hi = -lo;
    for (int i = 0; i < n; ++i) {
      ys[std::size_t(i)] = (xs[i] - center) * scale;
      lo = lo.cwiseMin(ys[std::size_t(i)]);
      hi = hi.cwiseMax(ys[std::size_t(i)]);
    }
    if (!lo.allFinite() || !hi.allFinite()) {
      for (int i = 0; i < n; ++i) {
        const double v = eval(xs[i], grads ? &grads[i] : nullptr);
        if (out) out[i] = v;
      }
      return;
    }
    const Vec3d mid = 0.5 * (lo + hi);
    const double rb = 0.5 * (hi - lo).norm() * (1 + 1e-9) + 1e-12;
    leaves.clear();
    lx.clear(), ly.clear(), lz.clear(), lr.clear(), lr2.clear();
    int stack[64 * 8];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
      const int i = stack[--top];
      // A node is passed over when the ball (mid, rb) misses its bound on the walk
      // (its reach, a leaf's radius, times 1 + 1e-6 plus 1e-6, in float). Every leaf
      // whose support holds one of the batch's points is kept: that point lies within
      // rb of mid, and the bound exceeds the support by more than the float rounding
      // of the node's centre (the octree lies within its root cube, |c| < 1). A leaf
      // kept beyond those adds nothing: the per-point test below gives it weight 0, in
      // the same depth-first order, so the sums are accumulate()'s bit for bit.
      const WalkNode& b = walk[std::size_t(i)];
      const double dx = mid.x() - double(b.x), dy = mid.y() - double(b.y), dz = mid.z() - double(b.z);
      const double bound = std::sqrt(double(b.r2)) + rb;
      if (dx * dx + dy * dy + dz * dz > bound * bound) continue;
      const std::int32_t link = b.link;
      if (link >= 0) {
        for (int c = 7; c >= 0; --c) stack[top++] = link + c;
      } else {
        leaves.push_back(-link - 1);
        const LeafRecord& leaf = leaf_records[std::size_t(-link - 1)];
        lr.push_back(leaf.radius);
        lx.push_back(leaf.center.x()), ly.push_back(leaf.center.y()), lz.push_back(leaf.center.z());
        lr2.push_back(leaf.radius * leaf.radius * (1 + 1e-9));  // looser than leaf_weight's 1e-12
      }
    }
    const std::size_t m = leaves.size();
    inside.resize(m);
    for (int k = 0; k < n; ++k) {
      const Vec3d& y = ys[std::size_t(k)];
      double swq = 0, sw = 0;
      Vec3d gwq = Vec3d::Zero(), gw = Vec3d::Zero();
      // First the leaves whose support may hold y, all at once on the side-by-side
      // coordinates (leaf_weight's first test with a looser bound, so it keeps every leaf
      // that test keeps however the squared distance is summed), in order; then
      // leaf_weight decides each of those exactly.
      std::size_t count = 0;
      const double yx = y.x(), yy = y.y(), yz = y.z();
      for (std::size_t j = 0; j < m; ++j) {
        const double dx = yx - lx[j], dy = yy - ly[j], dz = yz - lz[j];
        inside[count] = std::uint32_t(j);
        count += dx * dx + dy * dy + dz * dz > lr2[j] ? 0 : 1;
      }
      for (std::size_t c = 0; c < count; ++c) {
        const std::size_t j = inside[c];
        Vec3d d;
        double r = 0;
        const double w = leaf_weight(Vec3d(lx[j], ly[j], lz[j]), lr[j], y, d, r);
        if (w <= 0) continue;
        add_weighted(leaf_records[std::size_t(leaves[j])], y, w, d, r, swq, sw, grads ? &gwq : nullptr, &gw);
      }
      if (grads) grads[k] = gradient_from(y, swq, sw, gwq, gw);
      if (out) out[k] = value_from(y, swq, sw);
    }
  }

  bool may_be_sharp(const Vec3d& y, double r) const {
    if (nodes.empty() || !sharp_below[0]) return false;
    int stack[64 * 8];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
      const Node& nd = nodes[std::size_t(stack[--top])];
      const double reach = (nd.first_child < 0 ? nd.radius : nd.reach) + r;
      if ((y - nd.center).squaredNorm() > reach * reach) continue;
      if (nd.first_child < 0) return true;
      for (int c = 0; c < 8; ++c)
        if (sharp_below[std::size_t(nd.first_child + c)]) stack[top++] = nd.first_child + c;
    }
    return false;
  }

  // Accumulates sum w Q, sum w, and (when grads) their gradients, in normalised units.
  // Visits the leaves whose ball holds y in depth-first order (children 0..7).
  void accumulate(const Vec3d& y, double& swq, double& sw, Vec3d* gwq, Vec3d* gw) const {
    const bool prefilter = y.cwiseAbs().maxCoeff() <= kFloatRange;
    const float yx = float(y.x()), yy = float(y.y()), yz = float(y.z());
    // Whether node i may reach y: the float bound first (conservative), or the
    // exact test when y is too far out for the bounds' slack.
    auto may_reach = [&](int i) {
      if (prefilter) {
        const WalkNode& b = walk[i];
        const float dx = yx - b.x, dy = yy - b.y, dz = yz - b.z;
        return dx * dx + dy * dy + dz * dz <= b.r2;
      }
      const Node& nd = nodes[i];
      const double r = nd.first_child < 0 ? nd.radius : nd.reach;
      return (y - nd.center).squaredNorm() <= r * r * (1 + 1e-12);
    };
    int stack[64 * 8];
    int top = 0;
    if (may_reach(0)) stack[top++] = 0;
    while (top > 0) {
      const std::int32_t link = walk[stack[--top]].link;
      if (link >= 0) {
        for (int c = 7; c >= 0; --c) {
          if (!may_reach(link + c)) continue;
          stack[top++] = link + c;
          // A leaf's record is read soon: start loading it now (the walk's time
          // is mostly these loads).
          const std::int32_t child = walk[link + c].link;
          if (child < 0) {
            __builtin_prefetch(&leaf_records[std::size_t(-child - 1)]);
          } else {
            __builtin_prefetch(&walk[std::size_t(child)]);
          }
        }
        continue;
      }
      // A leaf: decided exactly.
      add_leaf(leaf_records[std::size_t(-link - 1)], y, swq, sw, gwq, gw);
    }
  }

  // The weight of a leaf at y, decided exactly (0 outside its support), with d = y -
  // its centre and r = |d| (for the weight's gradient).
  static double leaf_weight(const Vec3d& center, double radius, const Vec3d& y, Vec3d& d, double& r) {
    d = y - center;
    const double r2 = d.squaredNorm();
    if (r2 > radius * radius * (1 + 1e-12)) return 0;
    r = std::sqrt(r2);
    if (r >= radius) return 0;
    return bspline2(1.5 * r / radius);
  }
  double leaf_fit(const LeafRecord& leaf, const Vec3d& y, Vec3d* g) const {
    return leaf.single ? leaf.bivariate.eval(y, g) : fits[leaf.fit].eval(y, g);
  }
  // f (world units) from the sums at y; beyond every support a positive (outside)
  // distance-like value.
  double value_from(const Vec3d& y, double swq, double sw) const {
    if (sw <= 1e-300) return (y - nodes[0].center).norm() / scale;
    return swq / sw / scale;
  }

  // One leaf's terms of sum w Q and sum w at y (nothing outside its support) and, when
  // gwq is given, of their gradients (into gwq and gw). accumulate() and near() share it.
  void add_leaf(const LeafRecord& leaf, const Vec3d& y, double& swq, double& sw, Vec3d* gwq,
                Vec3d* gw) const {
    Vec3d d;
    double r = 0;
    const double w = leaf_weight(leaf.center, leaf.radius, y, d, r);
    if (w > 0) add_weighted(leaf, y, w, d, r, swq, sw, gwq, gw);
  }
  // The same with the leaf's weight w > 0 at y, d and r from leaf_weight.
  void add_weighted(const LeafRecord& leaf, const Vec3d& y, double w, const Vec3d& d, double r, double& swq,
                    double& sw, Vec3d* gwq, Vec3d* gw) const {
    if (!gwq) {
      swq += w * leaf_fit(leaf, y, nullptr);
      sw += w;
      return;
    }
    Vec3d gq;
    const double q = leaf_fit(leaf, y, &gq);
    const double t = 1.5 * r / leaf.radius;
    const Vec3d gwt = r > 0 ? Vec3d(bspline2_deriv(t) * 1.5 / leaf.radius / r * d) : Vec3d::Zero();
    swq += w * q;
    sw += w;
    *gwq += gwt * q + w * gq;
    *gw += gwt;
  }

  Vec3d gradient_from(const Vec3d& y, double swq, double sw, const Vec3d& gwq, const Vec3d& gw) const {
    if (sw <= 1e-300) {
      const Vec3d d = y - nodes[0].center;
      const double r = d.norm();
      return r > 0 ? Vec3d(d / r) : Vec3d::UnitZ();
    }
    // Gradient in the normalised frame equals the world one (f_world = f_norm / scale).
    return (gwq * sw - swq * gw) / (sw * sw);
  }

  double eval(const Vec3d& x, Vec3d* grad) const {
    const Vec3d y = (x - center) * scale;
    double swq = 0, sw = 0;
    Vec3d gwq = Vec3d::Zero(), gw = Vec3d::Zero();
    accumulate(y, swq, sw, grad ? &gwq : nullptr, grad ? &gw : nullptr);
    if (grad) *grad = gradient_from(y, swq, sw, gwq, gw);
    return value_from(y, swq, sw);
  }
};

namespace {

struct CellFit {
  LocalFit fit;
  double error = 0;
  double radius = 0;
  bool grew = false;
  int points = 0;  // in the ball before any growth
};

// Weighted least-squares bivariate quadratic over the plane (q, n).
Bivariate fit_bivariate(const MpuSurface::Impl& s, const std::vector<int>& ids,
                        const std::vector<double>& w, const Vec3d& n, double R, double curvature_ridge = 1e-6) {
  Bivariate b;
  double W = 0;
  Vec3d q = Vec3d::Zero();
  for (std::size_t i = 0; i < ids.size(); ++i) {
    q += w[i] * s.points[ids[i]].cast<double>();
    W += w[i];
  }
  b.origin = q / W;
  b.n = n;
  // Any tangent frame; built from the normal's smallest component for stability.
  Vec3d t = std::abs(n.x()) < 0.6 ? Vec3d::UnitX() : (std::abs(n.y()) < 0.6 ? Vec3d::UnitY() : Vec3d::UnitZ());
  b.u = (t - t.dot(n) * n).normalized();
  b.v = n.cross(b.u);
  Eigen::Matrix<double, 6, 6> A = Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 6, 1> rhs = Eigen::Matrix<double, 6, 1>::Zero();
  for (std::size_t i = 0; i < ids.size(); ++i) {
    const Vec3d d = (s.points[ids[i]].cast<double>() - b.origin) / R;
    const double a = d.dot(b.u), bb = d.dot(b.v), h = d.dot(n);
    Eigen::Matrix<double, 6, 1> phi;
    phi << a * a, a * bb, bb * bb, a, bb, 1;
    A += w[i] * phi * phi.transpose();
    rhs += w[i] * h * phi;
  }
  // Small ridge on the curved and slope terms: a collinear or tiny neighbourhood
  // leaves them undetermined; zero (a plane) is the safe default.
  const double ridge = 1e-6 * (A.trace() + 1e-300);
  for (int k = 0; k < 5; ++k) A(k, k) += k < 3 ? curvature_ridge * (A.trace() + 1e-300) : ridge;
  const Eigen::Matrix<double, 6, 1> c = A.ldlt().solve(rhs);
  b.c[0] = c[0] / R; b.c[1] = c[1] / R; b.c[2] = c[2] / R;
  b.c[3] = c[3]; b.c[4] = c[4]; b.c[5] = c[5] * R;
  for (double& v : b.c)
    if (!std::isfinite(v)) v = 0;
  return b;
}

Quadric fit_quadric(const MpuSurface::Impl& s, const std::vector<int>& ids,
                    const std::vector<double>& w, const Vec3d& o, double half, double R) {
  Quadric Q;
  Q.origin = o;
  Q.inv_scale = 1 / R;
  using M10 = Eigen::Matrix<double, 10, 10>;
  using V10 = Eigen::Matrix<double, 10, 1>;
  M10 A = M10::Zero();
  V10 rhs = V10::Zero();
  double W = 0;
  for (double x : w) W += x;
  const double gw = s.params.quadric_normal_weight * R;  // residual scale of normal rows
  double phi[10], dphi[3][10];
  for (std::size_t i = 0; i < ids.size(); ++i) {
    const Vec3d y = (s.points[ids[i]].cast<double>() - o) / R;
    const double wi = w[i] / W;
    Quadric::basis(y, phi);
    Eigen::Map<V10> p(phi);
    A += wi * p * p.transpose();
    Quadric::basis_grad(y, dphi);
    const Vec3d& n = s.normals[ids[i]];
    for (int k = 0; k < 3; ++k) {
      // grad_x Q = grad_y Q / R; residual (grad_x Q - n) * gw.
      Eigen::Map<V10> g(dphi[k]);
      const double sc = gw / R;
      A += wi * sc * sc * g * g.transpose();
      rhs += wi * sc * gw * n[k] * g;
    }
  }
  // Auxiliary points (Ohtake section 3.2): cell corners and centre whose signed
  // distance d to the 6 nearest points' tangent planes agrees in sign.
  std::vector<std::pair<Vec3d, double>> aux;
  for (int c = 0; c < 9; ++c) {
    const Vec3d q = c == 8 ? o : Vec3d(o + half * Vec3d(c & 1 ? 1 : -1, c & 2 ? 1 : -1, c & 4 ? 1 : -1));
    const auto nn = s.index->knn(q.cast<float>(), 6);
    int pos = 0, neg = 0;
    double sum = 0;
    for (const auto& [id, dist] : nn) {
      const double d = (q - s.points[id].cast<double>()).dot(s.normals[id]);
      (d > 0 ? pos : neg) += 1;
      sum += d;
    }
    if (!nn.empty() && (pos == 0 || neg == 0)) aux.emplace_back(q, sum / nn.size());
  }
  for (const auto& [q, d] : aux) {
    Quadric::basis((q - o) / R, phi);
    Eigen::Map<V10> p(phi);
    const double wa = s.params.quadric_aux_weight / aux.size();
    A += wa * p * p.transpose();
    rhs += wa * d * p;
  }
  const double ridge = 1e-9 * (A.trace() + 1e-300);
  for (int k = 0; k < 10; ++k) A(k, k) += ridge;
  const V10 a = A.ldlt().solve(rhs);
  for (int k = 0; k < 10; ++k) Q.a[k] = std::isfinite(a[k]) ? a[k] : 0;
  return Q;
}

double taubin_error(const MpuSurface::Impl& s, const std::vector<int>& ids, const LocalFit& f) {
  double err = 0;
  Vec3d g;
  for (int id : ids) {
    const double q = f.eval(s.points[id].cast<double>(), &g);
    err = std::max(err, std::abs(q) / std::max(g.norm(), 1e-12));
  }
  return err;
}

// Sharp feature (Ohtake section 3.3): cluster the normals around 2 or 3 seeds, fit a
// bivariate quadratic per cluster, combine by max (convex) or min (concave).
bool fit_sharp(const MpuSurface::Impl& s, const std::vector<int>& ids, const std::vector<double>& w,
               const Vec3d& mean_n, double R, LocalFit& out) {
  const MpuParams& p = s.params;
  const double sharp_cos = std::cos(p.sharp_angle_deg * kPi / 180);
  const double tight_cos = std::cos(p.cluster_angle_deg * kPi / 180);
  // Seeds: the normal furthest from the mean, then the one furthest from the seeds.
  std::vector<Vec3d> seeds;
  auto furthest = [&](auto&& score) {
    int best = -1;
    double bs = 2;
    for (std::size_t i = 0; i < ids.size(); ++i) {
      const double sc = score(s.normals[ids[i]]);
      if (sc < bs) bs = sc, best = int(i);
    }
    return std::make_pair(best, bs);
  };
  seeds.push_back(s.normals[ids[furthest([&](const Vec3d& n) { return n.dot(mean_n); }).first]]);
  auto [i2, c2] = furthest([&](const Vec3d& n) { return n.dot(seeds[0]); });
  if (c2 > sharp_cos) return false;  // normals do not spread enough for an edge
  seeds.push_back(s.normals[ids[i2]]);
  auto [i3, c3] = furthest([&](const Vec3d& n) { return std::max(n.dot(seeds[0]), n.dot(seeds[1])); });
  if (c3 < tight_cos) seeds.push_back(s.normals[ids[i3]]);
  const int k = int(seeds.size());
  std::vector<int> label(ids.size());
  for (int it = 0; it < 5; ++it) {
    std::vector<Vec3d> sum(k, Vec3d::Zero());
    for (std::size_t i = 0; i < ids.size(); ++i) {
      int best = 0;
      for (int c = 1; c < k; ++c)
        if (s.normals[ids[i]].dot(seeds[c]) > s.normals[ids[i]].dot(seeds[best])) best = c;
      label[i] = best;
      sum[best] += s.normals[ids[i]];
    }
    for (int c = 0; c < k; ++c)
      if (sum[c].norm() > 0) seeds[c] = sum[c].normalized();
  }
  std::vector<std::vector<int>> cid(k);
  std::vector<std::vector<double>> cw(k);
  for (std::size_t i = 0; i < ids.size(); ++i) {
    if (s.normals[ids[i]].dot(seeds[label[i]]) < tight_cos) return false;  // not a clean cluster
    cid[label[i]].push_back(ids[i]);
    cw[label[i]].push_back(std::max(w[i], 1e-6));
  }
  for (int c = 0; c < k; ++c)
    if (cid[c].size() < 6) return false;
  out.pieces = k;
  out.type = k == 2 ? MpuFitType::kEdge : MpuFitType::kCorner;
  for (int c = 0; c < k; ++c) out.piece[c] = fit_bivariate(s, cid[c], cw[c], seeds[c], R);
  // How the pieces combine: max (convex: the insides intersect) or min (concave), and
  // for three pieces also the saddle (mixed) corners, where one edge is of the other
  // kind: the odd pair is combined first, the result with the third piece (Ohtake et
  // al. 2003 combine three pieces by max and min). Telling the kinds apart by where
  // each cluster's centroid lies against the other pieces fails near saddle corners
  // (a face wrapping around the corner has its centroid on either side), so every
  // combination is tried and the one with the least Taubin error on the cell's points
  // kept (2 for an edge, 8 for a corner; only sharp cells pay for it).
  const Bivariate fitted[3] = {out.piece[0], out.piece[1], out.piece[2]};
  LocalFit trial = out, best;
  double best_err = std::numeric_limits<double>::infinity();
  auto consider = [&]() {
    const double e = taubin_error(s, ids, trial);
    if (e < best_err) best_err = e, best = trial;
  };
  for (bool take_max : {true, false}) {
    trial.saddle = false;
    trial.take_max = take_max;
    for (int c = 0; c < k; ++c) trial.piece[c] = fitted[c];
    consider();
    if (k != 3) continue;
    for (int third = 0; third < 3; ++third) {
      trial.saddle = true;
      trial.piece[0] = fitted[(third + 1) % 3];
      trial.piece[1] = fitted[(third + 2) % 3];
      trial.piece[2] = fitted[third];
      consider();
    }
  }
  out = best;
  return true;
}

CellFit fit_cell(const MpuSurface::Impl& s, const Vec3d& o, double half, bool ball_first) {
  const MpuParams& p = s.params;
  CellFit cf;
  double R = p.alpha * 2 * half * std::sqrt(3.0);
  // The n_min nearest points first: most cells (the empty children of split
  // cells) hold fewer than n_min points in their ball, which then grows R <- R +
  // lambda R until it does. When the n_min-th nearest point lies clearly outside,
  // the first ball search is skipped, and so are the growth steps that stay clearly
  // inside that point's distance (the same sequence of R, so the same final R);
  // the loop below then decides exactly. The ball's points come in the index's
  // order: the fit does not need them sorted.
  // With ball_first (the parent's ball was dense, so this one likely holds n_min
  // points) the ball is searched first and the nearest points only when it holds
  // fewer: the same lists and radius either way.
  // fit_mpu needs at least n_min points, so there are n_min nearest.
  std::vector<std::pair<int, float>> nn, nearest;
  if (ball_first) nn = s.index->radius_unsorted(o.cast<float>(), float(R));
  if (ball_first && int(nn.size()) >= p.n_min) {
    cf.points = int(nn.size());
  } else {
    nearest = s.index->knn(o.cast<float>(), p.n_min);
    if (double(nearest.back().second) > R * (1 + 1e-5)) {
      cf.grew = true;
      nn.clear();
      for (const auto& [id, d] : nearest) cf.points += double(d) <= R ? 1 : 0;
    } else {
      if (!ball_first) nn = s.index->radius_unsorted(o.cast<float>(), float(R));
      cf.points = int(nn.size());
    }
  }
  if (int(nn.size()) < p.n_min) {
    const double inside = double(nearest.back().second) * (1 - 1e-5);
    for (double next = R + p.lambda * R; next < inside; next = R + p.lambda * R) R = next;
  }
  while (int(nn.size()) < p.n_min) {
    R += p.lambda * R;
    cf.grew = true;
    nn = s.index->radius_unsorted(o.cast<float>(), float(R));
  }
  cf.radius = R;
  // Coarse cells hold most of the cloud; a deterministic stride sample keeps their
  // fit cost bounded. The list is in the k-d tree's order, which walks space
  // region by region, so a stride over it spans the ball.
  if (p.max_fit_points > 0 && int(nn.size()) > p.max_fit_points) {
    const double stride = double(nn.size()) / p.max_fit_points;
    std::vector<std::pair<int, float>> sub(p.max_fit_points);
    for (int i = 0; i < p.max_fit_points; ++i) sub[i] = nn[std::size_t(i * stride)];
    nn.swap(sub);
  }
  std::vector<int> ids(nn.size());
  std::vector<double> w(nn.size());
  Vec3d mean_n = Vec3d::Zero();
  double wsum = 0;
  for (std::size_t i = 0; i < nn.size(); ++i) {
    ids[i] = nn[i].first;
    // Points on the ball's rim would get weight 0; keep a floor so a grown ball's
    // outermost points still count.
    w[i] = std::max(bspline2(1.5 * nn[i].second / R), 1e-3);
    mean_n += w[i] * s.normals[ids[i]];
    wsum += w[i];
  }
  // Normals spread (or cancel): general quadric; otherwise a height function.
  bool agree = mean_n.norm() > 1e-9;
  if (agree) {
    for (int id : ids)
      if (s.normals[id].dot(mean_n.normalized()) <= p.bivariate_min_cos) {
        agree = false;
        break;
      }
  }
  if (agree) {
    cf.fit.type = MpuFitType::kBivariate;
    cf.fit.piece[0] = fit_bivariate(s, ids, w, mean_n.normalized(), R, cf.grew ? p.grown_curvature_ridge : 1e-6);
  } else {
    cf.fit.type = MpuFitType::kQuadric;
    cf.fit.quadric = fit_quadric(s, ids, w, o, half, R);
  }
  cf.error = taubin_error(s, ids, cf.fit);
  // A sharp fit replaces the smooth one only when it meets the tolerance or is much
  // better: wide balls on smooth but curved parts (grown cells) also spread their
  // normals, and a spurious crease there is worse than a smooth misfit.
  if (p.sharp_features && cf.error > p.epsilon0 && mean_n.norm() > 0.3 * wsum) {
    LocalFit sharp;
    if (fit_sharp(s, ids, w, mean_n.normalized(), R, sharp)) {
      const double e = taubin_error(s, ids, sharp);
      if (e <= p.epsilon0 || e < 0.25 * cf.error) cf.fit = sharp, cf.error = e;
    }
  }
  return cf;
}

}  // namespace

MpuSurface fit_mpu(const Cloud& cloud, const MpuParams& params) {
  const auto t0 = std::chrono::steady_clock::now();
  cloud.check_consistent("fit_mpu input");
  if (!cloud.has_normals())
    throw InvalidInput(
        "fit_mpu: the cloud has no normals; MPU needs outward normals (estimate and orient "
        "them first: core/normals.h estimate_normals + orient_normals_mst)");
  if (!(params.alpha > 0.5) || !(params.lambda > 0) || params.n_min < 6 || (params.max_fit_points != 0 && params.max_fit_points < params.n_min) || params.split_min_points < 0 || !(params.epsilon0 > 0) ||
      params.max_depth < 0 || params.max_depth > 20 || params.threads < 0 || !(params.root_margin >= 0) ||
      !(params.trust_factor > 0) || !(params.mean_spacing >= 0) || !std::isfinite(params.mean_spacing) ||
      !(params.median_spacing >= 0) || !std::isfinite(params.median_spacing))
    throw InvalidInput(
        "fit_mpu: parameters out of range (alpha > 0.5, lambda > 0, n_min >= 6, max_fit_points 0 or >= n_min, split_min_points >= 0, epsilon0 > 0, "
        "0 <= max_depth <= 20, threads >= 0, root_margin >= 0, trust_factor > 0, mean_spacing >= 0, median_spacing >= 0)");
  if (!all_finite(cloud.points)) throw InvalidInput("fit_mpu: non-finite point coordinates");

  auto impl = std::make_shared<MpuSurface::Impl>();
  MpuSurface::Impl& s = *impl;
  s.params = params;
  s.diag.input_points = cloud.size();
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    const Vec3d n = cloud.normals[i].cast<double>();
    const double len = n.norm();
    if (!std::isfinite(len) || len < 1e-6) {
      ++s.diag.dropped_points;
      continue;
    }
    s.world_points.push_back(cloud.points[i]);
    s.normals.push_back(n / len);
  }
  if (int(s.world_points.size()) < params.n_min)
    throw InvalidInput("fit_mpu: " + std::to_string(s.world_points.size()) +
                       " points with usable normals; at least n_min = " + std::to_string(params.n_min) +
                       " needed");
  s.bounds = bounding_box(s.world_points);
  const bool framed = !(params.frame.min == Aabb().min && params.frame.max == Aabb().max);  // set at all
  if (framed && !(params.frame.valid() && params.frame.min.allFinite() && params.frame.max.allFinite() &&
                  (params.frame.max - params.frame.min).maxCoeff() > 0))
    throw InvalidInput("fit_mpu: the frame must be a finite box of positive size");
  if (framed &&
      !((params.frame.min.array() <= s.bounds.min.array()).all() && (s.bounds.max.array() <= params.frame.max.array()).all()))
    throw InvalidInput("fit_mpu: the frame does not hold the points");
  const Aabb& frame = framed ? params.frame : s.bounds;
  const double side = (frame.max - frame.min).cast<double>().maxCoeff();
  if (!(side > 0)) throw InvalidInput("fit_mpu: all points are equal");
  // Unit-diagonal bounding cube: side 1/sqrt(3).
  s.center = frame.center().cast<double>();
  s.scale = 1 / (side * std::sqrt(3.0));
  s.points.reserve(s.world_points.size());
  for (const Vec3f& p : s.world_points) s.points.push_back(((p.cast<double>() - s.center) * s.scale).cast<float>());
  s.index = std::make_unique<PointIndex>(s.points);

  tbb::task_arena arena(worker_threads(params.threads));
  arena.execute([&] {
    // Mean spacing from every point's nearest neighbour (trust measure), and the
    // sample spacing from the 8th neighbour (MpuDiagnostics::sample_spacing).
    constexpr int kDensityNeighbours = 8;
    std::vector<double> nnd(s.points.size()), density(s.points.size());
    tbb::parallel_for(std::size_t(0), s.points.size(), [&](std::size_t i) {
      const auto k = s.index->knn(s.points[i], kDensityNeighbours + 1);
      nnd[i] = k.size() > 1 ? k[1].second : 0;
      density[i] = k.size() > std::size_t(kDensityNeighbours)
                       ? k[kDensityNeighbours].second * std::sqrt(M_PI / kDensityNeighbours)
                       : 0;
    });
    double sum = 0;
    for (double d : nnd) sum += d;
    const double spacing = sum / nnd.size();
    const double trusted = params.mean_spacing > 0 ? params.mean_spacing * s.scale : spacing;
    s.trust_radius = params.trust_factor * std::max(trusted, 1e-9);
    std::nth_element(density.begin(), density.begin() + density.size() / 2, density.end());
    s.diag.sample_spacing = density[density.size() / 2] / s.scale;
    const double median = params.median_spacing > 0 ? params.median_spacing * s.scale : density[density.size() / 2];
    if (params.sparse_trust && median > 0)
      s.allowances = std::make_unique<SparseAllowances>(*s.index, median, kSparseTrustFrom);
    s.diag.mean_spacing = spacing / s.scale;

    // Breadth-first build: each level's cells are fitted in parallel into their own
    // slots, then children are appended in cell order: deterministic for any thread count.
    Node root;
    root.center = Vec3d::Zero();
    root.half = 0.5 / std::sqrt(3.0) * (1 + params.root_margin);
    s.nodes.push_back(root);
    std::vector<int> frontier{0};
    s.diag.leaves_by_depth.assign(params.max_depth + 1, 0);
    // One buffer for every level's fits: a fresh one per level (CellFit is over 600
    // bytes) was a fifth of the fit's time in zeroing, copying and page faults. A level
    // in chunks of 4096 cells (2.5 MiB of fits): sized for a whole level the buffer was
    // 30-60 MiB of fresh memory, value-initialised in serial code (fresh memory costs
    // about 3 ms per MiB in page faults on the VMs we measure on; docs/dmc.md,
    // "2026-12-06: memory touched where it is used").
    constexpr std::size_t kChunk = 4096;
    std::vector<CellFit> fits;
    // Room for a leaf per point, and for twice as many cells: growing by doubling copied
    // each store into fresh memory several times over (room never used is never touched).
    s.singles.reserve(s.points.size());
    s.nodes.reserve(2 * s.points.size());
    // Per frontier cell, its parent's ball's point count: a child's ball is an eighth
    // of its parent's in volume, so past kBallFirst * n_min points in the parent's
    // most children crossed by the surface hold n_min (fit_cell's ball_first).
    constexpr int kBallFirst = 8;
    std::vector<int> parent_points{0}, next_parent_points;
    for (int depth = 0; !frontier.empty(); ++depth) {
      std::vector<int> next;
      next_parent_points.clear();
      for (std::size_t begin = 0; begin < frontier.size(); begin += kChunk) {
        const std::size_t end = std::min(frontier.size(), begin + kChunk);
        fits.resize(end - begin);
        tbb::parallel_for(begin, end, [&](std::size_t i) {
          const Node& nd = s.nodes[frontier[i]];
          fits[i - begin] = fit_cell(s, nd.center, nd.half, parent_points[i] >= kBallFirst * params.n_min);
        });
        for (std::size_t i = begin; i < end; ++i) {
          const int id = frontier[i];
          const CellFit& cf = fits[i - begin];
          // A grown ball already holds only the n_min nearest points: splitting
          // would fit the same points again, so it stays a leaf.
          const bool split = cf.error > params.epsilon0 && !cf.grew &&
                             cf.points >= params.split_min_points && depth < params.max_depth;
          if (split) {
            detail::split_cell(s.nodes, id, depth, next);
            next_parent_points.insert(next_parent_points.end(), 8, cf.points);
          } else {
            Node& nd = s.nodes[id];
            nd.radius = cf.radius;
            const LocalFit& f = cf.fit;
            if (f.type != MpuFitType::kQuadric && f.pieces == 1 && !f.saddle) {
              nd.single = int(s.singles.size());
              s.singles.push_back(f.piece[0]);
            } else {
              nd.fit = int(s.fits.size());
              s.fits.push_back(f);
            }
            ++s.diag.leaves;
            ++s.diag.leaves_by_type[int(cf.fit.type)];
            ++s.diag.leaves_by_depth[depth];
            if (cf.grew) ++s.diag.grown_leaves;
            if (cf.error > params.epsilon0) ++s.diag.unconverged_leaves;
            s.diag.max_leaf_error = std::max(s.diag.max_leaf_error, cf.error);
          }
        }
      }
      frontier.swap(next);
      parent_points.swap(next_parent_points);
    }
  });
  // Reach, bottom-up (children always follow their parent in `nodes`).
  for (int i = int(s.nodes.size()) - 1; i >= 0; --i) {
    Node& nd = s.nodes[i];
    if (nd.first_child < 0) {
      nd.reach = nd.radius;
    } else {
      nd.reach = 0;
      for (int c = 0; c < 8; ++c) {
        const Node& ch = s.nodes[nd.first_child + c];
        nd.reach = std::max(nd.reach, ch.reach + (ch.center - nd.center).norm());
      }
    }
  }
  s.build_walk();
  s.singles = {};  // copied into the leaf records
  s.diag.cells = s.nodes.size();
  while (s.diag.leaves_by_depth.size() > 1 && s.diag.leaves_by_depth.back() == 0) s.diag.leaves_by_depth.pop_back();
  s.diag.fit_seconds = seconds_since(t0);
  MpuSurface out;
  out.impl_ = std::move(impl);
  return out;
}

double suggest_epsilon0(const Cloud& cloud, int k, double factor) {
  if (k < 10 || !(factor > 0)) throw InvalidInput("suggest_epsilon0: k >= 10 and factor > 0 needed");
  if (int(cloud.size()) < k)
    throw InvalidInput("suggest_epsilon0: " + std::to_string(cloud.size()) + " points, fewer than the " +
                       std::to_string(k) + " needed to estimate the noise level");
  if (!all_finite(cloud.points)) throw InvalidInput("suggest_epsilon0: non-finite point coordinates");
  const Aabb box = bounding_box(cloud.points);
  const double side = (box.max - box.min).cast<double>().maxCoeff();
  if (!(side > 0)) throw InvalidInput("suggest_epsilon0: all points are equal");
  const double scale = 1 / (side * std::sqrt(3.0));
  const PointIndex index(cloud.points);
  // 5000 evenly spread points: the median residual is a stable statistic well
  // before that (mustard 100k: epsilon0 1.3188e-4 from 20000, 1.3229e-4 from
  // 5000), and the k-nearest queries were ~5 % of a 100k reconstruction.
  const std::size_t n = std::min<std::size_t>(cloud.size(), 5000);
  const double stride = double(cloud.size()) / n;
  std::vector<double> rms(n);
  tbb::parallel_for(std::size_t(0), n, [&](std::size_t i) {
    const auto nn = index.knn(cloud.points[std::size_t(i * stride)], k);
    std::vector<Vec3d> pts;
    Vec3d mean = Vec3d::Zero();
    for (const auto& [id, d] : nn) pts.push_back(cloud.points[id].cast<double>()), mean += pts.back();
    mean /= pts.size();
    // The given normals when there are any: with noise above the point spacing a
    // neighbourhood is a noise blob whose thinnest (PCA) direction underestimates it.
    Vec3d nrm = Vec3d::Zero();
    if (cloud.has_normals())
      for (const auto& [id, d] : nn) nrm += cloud.normals[id].cast<double>();
    nrm = nrm.norm() > 1e-9 ? Vec3d(nrm.normalized()) : pca_normal(pts.data(), int(pts.size()));
    if (nrm.norm() < 0.5) nrm = Vec3d::UnitZ();
    // Residual of a quadratic height fit over the PCA plane: a plane's residual would
    // mistake curvature for noise.
    const Vec3d t = std::abs(nrm.x()) < 0.6 ? Vec3d::UnitX() : Vec3d::UnitY();
    const Vec3d u = (t - t.dot(nrm) * nrm).normalized(), v = nrm.cross(u);
    double spread = 1e-300;
    for (const Vec3d& p : pts) spread = std::max(spread, (p - mean).norm());
    Eigen::Matrix<double, 6, 6> A = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> b = Eigen::Matrix<double, 6, 1>::Zero();
    std::vector<Eigen::Matrix<double, 6, 1>> rows;
    std::vector<double> hs;
    for (const Vec3d& p : pts) {
      const Vec3d d = (p - mean) / spread;
      Eigen::Matrix<double, 6, 1> phi;
      phi << d.dot(u) * d.dot(u), d.dot(u) * d.dot(v), d.dot(v) * d.dot(v), d.dot(u), d.dot(v), 1;
      A += phi * phi.transpose();
      b += d.dot(nrm) * phi;
      rows.push_back(phi);
      hs.push_back(d.dot(nrm));
    }
    A.diagonal().array() += 1e-9 * A.trace();
    const Eigen::Matrix<double, 6, 1> c = A.ldlt().solve(b);
    double ss = 0;
    for (std::size_t j = 0; j < rows.size(); ++j) ss += std::pow(rows[j].dot(c) - hs[j], 2);
    ss *= spread * spread * double(pts.size()) / std::max<double>(1, double(pts.size()) - 6);  // unbiased
    rms[i] = std::sqrt(ss / pts.size());
  });
  std::nth_element(rms.begin(), rms.begin() + n / 2, rms.end());
  return std::max(1e-4, factor * rms[n / 2] * scale);
}

double MpuSurface::value(const Vec3d& x) const { return impl_->eval(x, nullptr); }
Vec3d MpuSurface::gradient(const Vec3d& x) const {
  Vec3d g;
  impl_->eval(x, &g);
  return g;
}
double MpuSurface::value_gradient(const Vec3d& x, Vec3d& grad) const { return impl_->eval(x, &grad); }

std::vector<double> MpuSurface::values(const std::vector<Vec3d>& xs) const {
  std::vector<double> out(xs.size());
  tbb::task_arena arena(worker_threads(impl_->params.threads));
  arena.execute([&] {
    tbb::parallel_for(std::size_t(0), xs.size(), [&](std::size_t i) { out[i] = value(xs[i]); });
  });
  return out;
}
std::vector<Vec3d> MpuSurface::gradients(const std::vector<Vec3d>& xs) const {
  std::vector<Vec3d> out(xs.size());
  tbb::task_arena arena(worker_threads(impl_->params.threads));
  arena.execute([&] {
    tbb::parallel_for(std::size_t(0), xs.size(), [&](std::size_t i) { out[i] = gradient(xs[i]); });
  });
  return out;
}

double MpuSurface::weight_sum(const Vec3d& x) const {
  double swq = 0, sw = 0;
  impl_->accumulate((x - impl_->center) * impl_->scale, swq, sw, nullptr, nullptr);
  return sw;
}
double MpuSurface::nearest_point_distance(const Vec3d& x) const {
  const auto [id, d] = impl_->index->nearest(((x - impl_->center) * impl_->scale).cast<float>());
  return id < 0 ? std::numeric_limits<double>::infinity() : d / impl_->scale;
}
void MpuSurface::values_near(const Vec3d* xs, int n, double* out) const { impl_->near(xs, n, out, nullptr); }
void MpuSurface::gradients_near(const Vec3d* xs, int n, Vec3d* out) const {
  impl_->near(xs, n, nullptr, out);
}
void MpuSurface::values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const {
  impl_->near(xs, n, values, grads);
}
bool MpuSurface::may_be_sharp(const Vec3d& x, double radius) const {
  return impl_->may_be_sharp((x - impl_->center) * impl_->scale, radius * impl_->scale);
}
bool MpuSurface::trusted(const Vec3d& x) const {
  const Vec3d q = (x - impl_->center) * impl_->scale;
  return impl_->within_allowance(q, impl_->trust_distance(q), impl_->trust_radius, 0, 1);
}
bool MpuSurface::may_be_trusted_near(const Vec3d& x, double radius) const {
  // A float distance's rounding: a millionth of the reach more.
  const Vec3d q = (x - impl_->center) * impl_->scale;
  return impl_->within_allowance(q, impl_->trust_distance(q), impl_->trust_radius, radius * impl_->scale, 1 + 1e-6);
}
bool MpuSurface::near_points(const Vec3d& x, double distance) const {
  const Vec3d q = (x - impl_->center) * impl_->scale;
  const auto [id, d] = impl_->index->nearest(q.cast<float>());
  return id >= 0 && impl_->within_allowance(q, d, distance * impl_->scale, 0, 1);
}
Vec3d MpuSurface::center() const { return impl_->center; }
double MpuSurface::scale() const { return impl_->scale; }
Aabb MpuSurface::bounds() const { return impl_->bounds; }
const std::vector<Vec3f>& MpuSurface::points() const { return impl_->world_points; }
const MpuDiagnostics& MpuSurface::diagnostics() const { return impl_->diag; }
const MpuParams& MpuSurface::params() const { return impl_->params; }

}  // namespace station
