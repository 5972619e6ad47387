#include "reconstruct/colour_function.h"
#include "reconstruct/colour_transfer.h"
#include "reconstruct/detail/envelope_llt.h"
#include "reconstruct/detail/octree_split.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>
#include <tbb/task_arena.h>

#include <Eigen/Dense>
#include <Eigen/Sparse>
#include <algorithm>
#include <chrono>
#include <cstdint>
#include <unordered_map>
#include <functional>
#include <cmath>
#include <limits>
#include <optional>
#include <string>

#include "core/error.h"
#include "core/kdtree.h"
#include "core/normals.h"
#include "core/threads.h"

namespace station {
namespace {

constexpr int kChannels = 3;
constexpr double kRange[kChannels] = {100, 255, 255};  // r_L, r_a, r_b (eq. 4)
// RBF systems up to this size are factorised densely; larger ones (n_max raised, or a
// grown/max-depth ball) use a sparse Cholesky: psi has compact support 0.4 R_k.
constexpr int kDenseMax = 400;
// Ridge on the RBF matrices' diagonal (psi(0) = 1): keeps duplicated points with
// different colours solvable; interpolation error at the nodes ~ 1e-6 * |lambda|.
constexpr double kRbfRidge = 1e-6;

// Quadratic B-spline b2(t), support |t| < 3/2 (as reconstruct/mpu.cpp).
double bspline2(double t) {
  t = std::abs(t);
  if (t < 0.5) return 0.75 - t * t;
  if (t < 1.5) return 0.5 * (1.5 - t) * (1.5 - t);
  return 0;
}

double delta_e2(const Lab& a, const Lab& b) {
  return (a[0] - b[0]) * (a[0] - b[0]) + (a[1] - b[1]) * (a[1] - b[1]) + (a[2] - b[2]) * (a[2] - b[2]);
}

// psi(r) = (1 - r / support)^2 inside the support, with inv_support = 1 / support.
double psi(double r, double inv_support) {
  const double t = 1 - r * inv_support;
  return t > 0 ? t * t : 0;
}

// An RBF interpolant sum_i lambda_i psi(|d - node_i|) + q0 + q1 a + q2 b over a subset of
// a leaf's nodes, `cols` columns (3 colour channels, or boundary functions).
// A constant part (too few points for an RBF) has no ids and only q0.
struct RbfPart {
  std::vector<int> ids;        // indices into the leaf's nodes
  std::vector<double> lambda;  // ids.size() x cols, row-major
  std::vector<double> poly;    // 3 x cols, row-major (1, a, b)
  int cols = 0;
};

// A Type B leaf's RBFs (held apart from Leaf: most leaves are Type A, and a leaf's
// size is the colour function's memory on large clouds).
struct TypeBData {
  double rbf_support = 0.4;          // in local units
  std::vector<Vec3d> nodes;          // local coordinates of the ball's points, by u
  std::vector<double> node_u;        // their u coordinates, ascending
  std::vector<std::uint8_t> node_cluster;  // each node's cluster (clusters[j] holds it)
  std::vector<RbfPart> clusters;     // colour per cluster (cols = 3)
  RbfPart boundary;                  // cols = 1 (two clusters: b >= 0 -> cluster 0) or k
};

struct Leaf {
  ColourCellType type = ColourCellType::kA;
  Vec3d o = Vec3d::Zero(), u = Vec3d::UnitX(), v = Vec3d::UnitY();
  double inv_r = 1;  // 1 / R_k: local coordinates d = (y - o) / R_k
  // Type A: per channel c0 a^2 + c1 ab + c2 b^2 + c3 a + c4 b + c5, (a, b) = (d.u, d.v).
  double coef[kChannels][6] = {};
  // Type B (set with type kB).
  std::shared_ptr<TypeBData> rbf;
  int cluster_count() const { return rbf ? int(rbf->clusters.size()) : 0; }

  // The paper's Q_k(y): Type A's quadratic, or Type B's cluster chosen by its own
  // boundary function(s).
  Lab eval(const Vec3d& y) const { return eval_impl(y, nullptr, nullptr); }
  // Type B only: every cluster's side score (two clusters: b and -b; k clusters: b_c)
  // and colour at y. Returns the paper's choice (argmax, ties to the first).
  int eval_clusters(const Vec3d& y, double* score, Lab* colour) const {
    int chosen = 0;
    eval_impl(y, score, colour);
    for (int k = 1; k < cluster_count(); ++k)
      if (score[k] > score[chosen]) chosen = k;
    return chosen;
  }

 private:
  Lab eval_impl(const Vec3d& y, double* score_out, Lab* colour_out) const {
    const Vec3d d = (y - o) * inv_r;
    const double a = d.dot(u), b = d.dot(v);
    Lab out{};
    if (type == ColourCellType::kA) {
      const double basis[6] = {a * a, a * b, b * b, a, b, 1};
      for (int c = 0; c < kChannels; ++c) {
        double s = 0;
        for (int j = 0; j < 6; ++j) s += coef[c][j] * basis[j];
        out[c] = s;
      }
      return out;
    }
    const TypeBData& t = *rbf;
    const std::vector<double>& node_u = t.node_u;
    const RbfPart& boundary = t.boundary;
    const int k = int(t.clusters.size());
    const double rbf_support = t.rbf_support;
    // Nodes are sorted by their u coordinate: only those with |node_u - a| < support
    // can be within the RBF support.
    const std::size_t lo = std::lower_bound(node_u.begin(), node_u.end(), a - rbf_support) - node_u.begin();
    const std::size_t hi = std::upper_bound(node_u.begin(), node_u.end(), a + rbf_support) - node_u.begin();
    // One pass over [lo, hi) sums every part: each part's value is its polynomial, then
    // lambda psi over its nodes in ascending order where psi > 0 (a node's slot in its
    // cluster counted on the way; the boundary's RBF, when it has one, is on all nodes).
    double bv[16];
    Lab cv[16];
    int slot[16];
    for (int c = 0; c < boundary.cols; ++c)
      bv[c] = boundary.poly[c] + boundary.poly[boundary.cols + c] * a + boundary.poly[2 * boundary.cols + c] * b;
    for (int j = 0; j < k; ++j) {
      const RbfPart& part = t.clusters[j];
      for (int c = 0; c < kChannels; ++c)
        cv[j][c] = part.poly[c] + part.poly[kChannels + c] * a + part.poly[2 * kChannels + c] * b;
      slot[j] = int(std::lower_bound(part.ids.begin(), part.ids.end(), int(lo)) - part.ids.begin());
    }
    const bool boundary_rbf = !boundary.ids.empty();
    const double s2 = rbf_support * rbf_support, inv_support = 1 / rbf_support;
    for (std::size_t i = lo; i < hi; ++i) {
      const int j = t.node_cluster[i];
      const RbfPart& part = t.clusters[j];
      const int si = part.ids.empty() ? -1 : slot[j]++;
      const double r2 = (d - t.nodes[i]).squaredNorm();
      if (!(r2 < s2)) continue;
      const double p = psi(std::sqrt(r2), inv_support);
      if (!(p > 0)) continue;
      if (boundary_rbf)
        for (int c = 0; c < boundary.cols; ++c) bv[c] += boundary.lambda[i * boundary.cols + c] * p;
      if (si >= 0)
        for (int c = 0; c < kChannels; ++c) cv[j][c] += part.lambda[std::size_t(si) * kChannels + c] * p;
    }
    int chosen = 0;
    if (boundary.cols == 1) {
      chosen = bv[0] >= 0 ? 0 : 1;
    } else {
      for (int c = 1; c < boundary.cols; ++c)
        if (bv[c] > bv[chosen]) chosen = c;
    }
    if (score_out) {
      if (boundary.cols == 1) {
        score_out[0] = bv[0];
        score_out[1] = -bv[0];
      } else {
        for (int c = 0; c < boundary.cols; ++c) score_out[c] = bv[c];
      }
      for (int j = 0; j < k; ++j) colour_out[j] = cv[j];
      return colour_out[chosen];
    }
    return cv[chosen];
  }
};

struct Node {
  Vec3d center;
  double half = 0;
  double radius = 0;  // leaves: support radius R_k
  double reach = 0;
  int first_child = -1;
  int leaf = -1;
  int depth = 0;
};

}  // namespace

struct ColourFunction::Impl {
  ColourParams params;
  ColourDiagnostics diag;
  Vec3d center = Vec3d::Zero();
  double scale = 1;
  double diagonal = 1;  // world units, of the points' bounding cube
  std::vector<Vec3f> points;  // normalised
  std::vector<Vec3d> normals;  // empty when the input has none
  std::vector<Lab> labs;
  /// Per point and channel, how far its L*a*b* can be from the colour its 8-bit value
  /// stands for (ColourParams::quantisation_tolerance); empty when off.
  std::vector<std::array<float, 3>> quant;
  std::unique_ptr<PointIndex> index;
  std::vector<Node> nodes;
  std::vector<Leaf> leaves;

  struct Hit {
    int leaf;
    double w;
  };

  // The leaves whose ball holds y, with their weights w_k(y), in a fixed (traversal)
  // order.
  void gather(const Vec3d& y, std::vector<Hit>& hits) const {
    hits.clear();
    int stack[64 * 8];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
      const Node& nd = nodes[stack[--top]];
      const double r = (y - nd.center).norm();
      if (nd.first_child < 0) {
        if (nd.leaf < 0 || r >= nd.radius) continue;
        const double w = bspline2(1.5 * r / nd.radius);
        if (w > 0) hits.push_back({nd.leaf, w});
      } else {
        if (r >= nd.reach) continue;
        for (int c = 7; c >= 0; --c) stack[top++] = nd.first_child + c;
      }
    }
  }

  // The paper's blend: sum_k w_k Q_k / sum_k w_k, every leaf deciding its own side.
  bool blend_paper(const Vec3d& y, const std::vector<Hit>& hits, Lab& out) const {
    Lab swq{};
    double sw = 0;
    for (const Hit& h : hits) {
      const Lab q = leaves[h.leaf].eval(y);
      for (int c = 0; c < kChannels; ++c) swq[c] += h.w * q[c];
      sw += h.w;
    }
    if (!(sw > 1e-300)) return false;
    for (int c = 0; c < kChannels; ++c) out[c] = swq[c] / sw;
    return true;
  }

  // side_consensus (docs/colour.md). Every leaf at y votes on the side (colour class) of
  // y, then only predictions for the winning class are blended. Classes group the
  // leaves' colour predictions at y: each Type B leaf's clusters (their RBFs at y; the
  // heaviest Type B leaf's first) and each Type A leaf's quadratic; a prediction within
  // gamma / 2 of a class's first colour joins it, else starts a new class. Votes: a
  // Type B leaf gives each of its clusters' classes its side score (b and -b; b_c
  // one-vs-rest), clamped to the targets' range [-1, 1] (beyond it b only extrapolates
  // its linear part away from the nodes); a Type A leaf holds one colour in its ball and
  // gives its class +1; a leaf gives -1 to every class it does not have. The class of
  // the largest weighted sum wins. Then each leaf with that class contributes its
  // prediction for it (a Type B leaf its cluster's RBF), the others none: a one-colour
  // leaf whose ball reaches over the boundary, or a Type B leaf whose boundary lies a
  // little elsewhere, no longer mixes in the other colour.
  bool blend_consensus(const Vec3d& y, const std::vector<Hit>& hits, Lab& out) const {
    int ref = -1;
    for (std::size_t i = 0; i < hits.size(); ++i)
      if (leaves[hits[i].leaf].type == ColourCellType::kB && (ref < 0 || hits[i].w > hits[ref].w)) ref = int(i);
    if (ref < 0) return blend_paper(y, hits, out);
    thread_local std::vector<Lab> class_colour;
    thread_local std::vector<double> class_vote;
    // Per hit and class it has: the (clamped) score and the colour at y.
    struct Entry {
      int hit, cls;
      double score;
      Lab colour;
    };
    thread_local std::vector<Entry> at;
    class_colour.clear();
    class_vote.clear();
    at.clear();
    const double match2 = 0.25 * params.gamma * params.gamma;
    auto class_of = [&](const Lab& colour) {
      int cls = -1;
      double best = match2;
      for (int r = 0; r < int(class_colour.size()); ++r) {
        const double d = delta_e2(colour, class_colour[r]);
        if (d < best) best = d, cls = r;
      }
      if (cls < 0) {
        cls = int(class_colour.size());
        class_colour.push_back(colour);
        class_vote.push_back(0);
      }
      return cls;
    };
    auto add = [&](std::size_t first, int i, int cls, double score, const Lab& colour) {
      // Two clusters of one leaf in the same class: the one with the larger score.
      for (std::size_t j = first; j < at.size(); ++j)
        if (at[j].cls == cls) {
          if (score > at[j].score) at[j].score = score, at[j].colour = colour;
          return;
        }
      at.push_back({i, cls, score, colour});
    };
    auto visit_b = [&](int i) {
      const Leaf& leaf = leaves[hits[i].leaf];
      double score[16];
      Lab colour[16];
      leaf.eval_clusters(y, score, colour);
      const std::size_t first = at.size();
      for (int c = 0; c < leaf.cluster_count(); ++c)
        add(first, i, class_of(colour[c]), std::clamp(score[c], -1.0, 1.0), colour[c]);
    };
    visit_b(ref);
    for (int i = 0; i < int(hits.size()); ++i)
      if (i != ref && leaves[hits[i].leaf].type == ColourCellType::kB) visit_b(i);
    for (int i = 0; i < int(hits.size()); ++i)
      if (leaves[hits[i].leaf].type == ColourCellType::kA) {
        const Lab q = leaves[hits[i].leaf].eval(y);
        at.push_back({i, class_of(q), 1.0, q});
      }
    // Sum over leaves of w (score + 1) per class: the -1 of the leaves without the class
    // is common to all classes once shifted.
    for (const Entry& e : at) class_vote[e.cls] += hits[e.hit].w * (e.score + 1);
    int side = 0;
    for (int r = 1; r < int(class_colour.size()); ++r)
      if (class_vote[r] > class_vote[side]) side = r;
    Lab swq{};
    double sw = 0;
    for (const Entry& e : at) {
      if (e.cls != side) continue;
      for (int ch = 0; ch < kChannels; ++ch) swq[ch] += hits[e.hit].w * e.colour[ch];
      sw += hits[e.hit].w;
    }
    if (!(sw > 1e-300)) return false;
    for (int c = 0; c < kChannels; ++c) out[c] = swq[c] / sw;
    return true;
  }

  // The leaf nodes whose ball reaches into the ball (c, rad), in gather's traversal
  // order: for any y in that ball, gather(y) visits exactly those of them whose ball
  // holds y, in the same order, so hits_from gives gather's hits bit for bit.
  void gather_ball(const Vec3d& c, double rad, std::vector<int>& cand) const {
    cand.clear();
    int stack[64 * 8];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
      const int id = stack[--top];
      const Node& nd = nodes[id];
      const double r = (c - nd.center).norm();
      if (nd.first_child < 0) {
        if (nd.leaf >= 0 && r < nd.radius + rad) cand.push_back(id);
      } else {
        if (r >= nd.reach + rad) continue;
        for (int ch = 7; ch >= 0; --ch) stack[top++] = nd.first_child + ch;
      }
    }
  }
  void hits_from(const Vec3d& y, const std::vector<int>& cand, std::vector<Hit>& hits) const {
    hits.clear();
    for (int id : cand) {
      const Node& nd = nodes[id];
      const double r = (y - nd.center).norm();
      if (r >= nd.radius) continue;
      const double w = bspline2(1.5 * r / nd.radius);
      if (w > 0) hits.push_back({nd.leaf, w});
    }
  }

  // eval at many points (world units, all finite) at once: the points are grouped by
  // cells of side batch_cell, each group's leaves gathered once (gather_ball), then each
  // point's hits taken from them. The same values as eval, bit for bit.
  void eval_many(std::size_t n, const std::function<Vec3d(std::size_t)>& x_of,
                 const std::function<void(std::size_t, const Lab&)>& put) const {
    std::vector<std::pair<std::uint64_t, std::uint32_t>> order(n);
    const double inv = 1.0 / batch_cell;
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 4096), [&](const auto& r) {
      for (std::size_t i = r.begin(); i != r.end(); ++i) {
        const Vec3d y = (x_of(i) - center) * scale;
        std::uint64_t k = 0;
        for (int a = 0; a < 3; ++a) {
          const double q = std::clamp(std::floor(y[a] * inv) + 1048576.0, 0.0, 2097151.0);
          k |= std::uint64_t(q) << (21 * a);
        }
        order[i] = {k, std::uint32_t(i)};
      }
    });
    tbb::parallel_sort(order.begin(), order.end());
    std::vector<std::size_t> groups;
    for (std::size_t i = 0; i < n; ++i)
      if (i == 0 || order[i].first != order[i - 1].first || i - groups.back() >= 128) groups.push_back(i);
    groups.push_back(n);
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, groups.size() - 1, 4), [&](const auto& r) {
      std::vector<int> cand;
      std::vector<Hit> hits;
      std::vector<Vec3d> ys;
      for (std::size_t g = r.begin(); g != r.end(); ++g) {
        ys.clear();
        Vec3d lo = Vec3d::Constant(std::numeric_limits<double>::infinity()), hi = -lo;
        for (std::size_t i = groups[g]; i < groups[g + 1]; ++i) {
          ys.push_back((x_of(order[i].second) - center) * scale);
          lo = lo.cwiseMin(ys.back());
          hi = hi.cwiseMax(ys.back());
        }
        const Vec3d c = 0.5 * (lo + hi);
        double rad = 0;
        for (const Vec3d& y : ys) rad = std::max(rad, (y - c).norm());
        gather_ball(c, rad, cand);
        for (std::size_t i = groups[g]; i < groups[g + 1]; ++i) {
          const Vec3d& y = ys[i - groups[g]];
          hits_from(y, cand, hits);
          put(order[i].second, blend(y, hits));
        }
      }
    });
  }

  Lab eval(const Vec3d& x) const {
    const Vec3d y = (x - center) * scale;
    thread_local std::vector<Hit> hits;
    gather(y, hits);
    return blend(y, hits);
  }

  double batch_cell = 0.05;  // eval_many's grouping cell, normalised units (fit_colour)

  Lab blend(const Vec3d& y, const std::vector<Hit>& hits) const {
    Lab out{};
    const bool ok = params.side_consensus ? blend_consensus(y, hits, out) : blend_paper(y, hits, out);
    if (!ok || !std::isfinite(out[0]) || !std::isfinite(out[1]) || !std::isfinite(out[2]))
      return labs[index->nearest(y.cast<float>()).first];
    return out;
  }
};

namespace {

using Impl = ColourFunction::Impl;

struct CellResult {
  bool split = false;
  bool empty = false;
  bool grew = false;
  bool converged = true;
  bool rejected_b = false;
  bool fallback_a = false;
  int constant_clusters = 0;
  int linear_boundaries = 0;
  Leaf leaf;
  double radius = 0;
};

// Tangent frame of a ball: the weighted mean normal (paper's w^(k)), or the points' PCA
// normal without normals or when they cancel.
void tangent_frame(const Impl& s, const std::vector<int>& ids, const std::vector<double>& w, Leaf& leaf) {
  Vec3d n = Vec3d::Zero();
  if (!s.normals.empty())
    for (std::size_t i = 0; i < ids.size(); ++i) n += w[i] * s.normals[ids[i]];
  if (n.norm() > 1e-9) {
    n.normalize();
  } else {
    std::vector<Vec3d> pts(ids.size());
    for (std::size_t i = 0; i < ids.size(); ++i) pts[i] = s.points[ids[i]].cast<double>();
    n = ids.size() >= 3 ? pca_normal(pts.data(), int(pts.size())) : Vec3d::UnitZ();
    if (!(n.norm() > 0.5) || !n.allFinite()) n = Vec3d::UnitZ();
  }
  const Vec3d t = std::abs(n.x()) < 0.6 ? Vec3d::UnitX() : Vec3d::UnitY();
  leaf.u = (t - t.dot(n) * n).normalized();
  leaf.v = n.cross(leaf.u);
}

// Weighted least-squares bivariate quadratic per channel (Type A). Returns the weighted
// RMS residual (CIE76).
double fit_type_a(const Impl& s, const std::vector<int>& ids, const std::vector<double>& w, Leaf& leaf) {
  leaf.type = ColourCellType::kA;
  using Mat6 = Eigen::Matrix<double, 6, 6>;
  Mat6 A = Mat6::Zero();
  Eigen::Matrix<double, 6, kChannels> B = Eigen::Matrix<double, 6, kChannels>::Zero();
  for (std::size_t i = 0; i < ids.size(); ++i) {
    const Vec3d d = (s.points[ids[i]].cast<double>() - leaf.o) * leaf.inv_r;
    const double a = d.dot(leaf.u), b = d.dot(leaf.v);
    Eigen::Matrix<double, 6, 1> phi;
    phi << a * a, a * b, b * b, a, b, 1;
    A.noalias() += w[i] * phi * phi.transpose();
    for (int c = 0; c < kChannels; ++c) B.col(c) += w[i] * s.labs[ids[i]][c] * phi;
  }
  // Few or collinear points: a ridge on the higher terms pulls them to zero (towards a
  // plane, then a constant) instead of letting them blow up.
  const double tr = A.trace();
  const double ridge = ids.size() < 12 ? 1e-3 : 1e-8;
  for (int j = 0; j < 5; ++j) A(j, j) += ridge * tr + 1e-300;
  A(5, 5) += 1e-12 * tr + 1e-300;
  const Eigen::Matrix<double, 6, kChannels> X = A.ldlt().solve(B);
  bool finite = X.allFinite();
  for (int c = 0; c < kChannels; ++c)
    for (int j = 0; j < 6; ++j) leaf.coef[c][j] = finite ? X(j, c) : (j == 5 ? 0.0 : 0.0);
  if (!finite) {
    // Weighted mean colour.
    double ws = 0;
    Lab m{};
    for (std::size_t i = 0; i < ids.size(); ++i) {
      ws += w[i];
      for (int c = 0; c < kChannels; ++c) m[c] += w[i] * s.labs[ids[i]][c];
    }
    for (int c = 0; c < kChannels; ++c) leaf.coef[c][5] = m[c] / std::max(ws, 1e-300);
  }
  double se = 0, ws = 0;
  for (std::size_t i = 0; i < ids.size(); ++i) {
    const Lab q = leaf.eval(s.points[ids[i]].cast<double>());
    se += w[i] * std::pow(delta_e(q, s.labs[ids[i]]), 2);
    ws += w[i];
  }
  return std::sqrt(se / std::max(ws, 1e-300));
}

// Interpolates rhs (ids.size() x cols) at the nodes `ids` with psi + (1, a, b).
bool solve_rbf(const Leaf& leaf, const std::vector<int>& ids, const Eigen::MatrixXd& rhs, RbfPart& out) {
  const int n = int(ids.size());
  const int cols = int(rhs.cols());
  Eigen::MatrixXd P(n, 3);
  for (int i = 0; i < n; ++i) {
    const Vec3d& p = leaf.rbf->nodes[ids[i]];
    P(i, 0) = 1;
    P(i, 1) = p.dot(leaf.u);
    P(i, 2) = p.dot(leaf.v);
  }
  Eigen::MatrixXd Xp, Xh;  // B^-1 P, B^-1 h
  if (n <= kDenseMax) {
    // ids ascend, so their nodes ascend in u, and psi(r) = 0 for r >= support with
    // r >= |u_i - u_j|: row i of B is zero left of the first node within `support` in u
    // (envelope Cholesky, about 5x fewer operations than a dense one here).
    const TypeBData& tb = *leaf.rbf;
    const double support = tb.rbf_support, s2 = support * support, inv_support = 1 / support;
    thread_local detail::EnvelopeLlt llt;
    llt.reset(n);
    int first = 0;
    for (int i = 0; i < n; ++i) {
      const double ui = tb.node_u[ids[i]];
      while (first < i && !(tb.node_u[ids[first]] > ui - support)) ++first;
      double* row = llt.begin_row(i, first);
      const Vec3d& ni = tb.nodes[ids[i]];
      for (int j = first; j < i; ++j) {
        const double r2 = (ni - tb.nodes[ids[j]]).squaredNorm();
        if (r2 < s2) row[j - first] = psi(std::sqrt(r2), inv_support);
      }
      row[i - first] = 1 + kRbfRidge;
    }
    if (!llt.factor()) return false;
    Xp = P;
    Xh = rhs;
    llt.solve(Xp.data(), int(Xp.cols()), Xp.rows());
    llt.solve(Xh.data(), int(Xh.cols()), Xh.rows());
  } else {
    std::vector<Eigen::Triplet<double>> trip;
    for (int i = 0; i < n; ++i) {
      trip.emplace_back(i, i, 1 + kRbfRidge);
      for (int j = 0; j < i; ++j) {
        const double v = psi((leaf.rbf->nodes[ids[i]] - leaf.rbf->nodes[ids[j]]).norm(), 1 / leaf.rbf->rbf_support);
        if (v > 0) trip.emplace_back(i, j, v), trip.emplace_back(j, i, v);
      }
    }
    Eigen::SparseMatrix<double> B(n, n);
    B.setFromTriplets(trip.begin(), trip.end());
    Eigen::SimplicialLLT<Eigen::SparseMatrix<double>> llt(B);
    if (llt.info() != Eigen::Success) return false;
    Xp = llt.solve(P);
    Xh = llt.solve(rhs);
  }
  // Schur complement on the polynomial: (P^T B^-1 P) q = P^T B^-1 h; minimum-norm q when
  // the nodes are collinear in the tangent plane.
  const Eigen::Matrix3d S = P.transpose() * Xp;
  const Eigen::MatrixXd q = S.completeOrthogonalDecomposition().solve(P.transpose() * Xh);
  const Eigen::MatrixXd lambda = Xh - Xp * q;
  if (!q.allFinite() || !lambda.allFinite()) return false;
  out.ids = ids;
  out.cols = cols;
  out.lambda.resize(std::size_t(n) * cols);
  for (int i = 0; i < n; ++i)
    for (int c = 0; c < cols; ++c) out.lambda[std::size_t(i) * cols + c] = lambda(i, c);
  out.poly.resize(3 * std::size_t(cols));
  for (int j = 0; j < 3; ++j)
    for (int c = 0; c < cols; ++c) out.poly[j * cols + c] = q(j, c);
  return true;
}

// Convex hull (counter-clockwise, no collinear points) of 2-D points; 1 or 2 points for
// degenerate sets.
std::vector<Eigen::Vector2d> convex_hull(std::vector<Eigen::Vector2d> p) {
  std::sort(p.begin(), p.end(), [](const Eigen::Vector2d& x, const Eigen::Vector2d& y) {
    return x.x() < y.x() || (x.x() == y.x() && x.y() < y.y());
  });
  p.erase(std::unique(p.begin(), p.end()), p.end());
  if (p.size() < 3) return p;
  const auto cross = [](const Eigen::Vector2d& o, const Eigen::Vector2d& a, const Eigen::Vector2d& b) {
    return (a.x() - o.x()) * (b.y() - o.y()) - (a.y() - o.y()) * (b.x() - o.x());
  };
  std::vector<Eigen::Vector2d> h(2 * p.size());
  std::size_t k = 0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    while (k >= 2 && cross(h[k - 2], h[k - 1], p[i]) <= 0) --k;
    h[k++] = p[i];
  }
  for (std::size_t i = p.size() - 1, t = k + 1; i-- > 0;) {
    while (k >= t && cross(h[k - 2], h[k - 1], p[i]) <= 0) --k;
    h[k++] = p[i];
  }
  h.resize(k - 1);
  return h;
}

// Closest point to q on segment [a, b].
Eigen::Vector2d closest_on_segment(const Eigen::Vector2d& q, const Eigen::Vector2d& a, const Eigen::Vector2d& b) {
  const Eigen::Vector2d ab = b - a;
  const double l2 = ab.squaredNorm();
  const double t = l2 > 0 ? std::clamp((q - a).dot(ab) / l2, 0.0, 1.0) : 0.0;
  return a + t * ab;
}

// The max-margin line between two point sets in the plane, as b(a, b) = q0 + q1 a + q2 b
// with b = +1 / -1 at the margin on the side of `pos` / `neg`: the perpendicular bisector
// of the closest points of their convex hulls. Empty when some point is not strictly on
// its side (the sets are not separable by a line).
std::optional<Eigen::Vector3d> max_margin_line(const std::vector<Eigen::Vector2d>& pos,
                                               const std::vector<Eigen::Vector2d>& neg) {
  if (pos.empty() || neg.empty()) return std::nullopt;
  const std::vector<Eigen::Vector2d> hp = convex_hull(pos), hn = convex_hull(neg);
  double best = std::numeric_limits<double>::infinity();
  Eigen::Vector2d bp = Eigen::Vector2d::Zero(), bn = Eigen::Vector2d::Zero();
  // For disjoint convex polygons the closest pair has a vertex of one of them.
  const auto scan = [&](const std::vector<Eigen::Vector2d>& verts, const std::vector<Eigen::Vector2d>& poly,
                        bool verts_are_pos) {
    for (const Eigen::Vector2d& v : verts)
      for (std::size_t i = 0; i < poly.size(); ++i) {
        const Eigen::Vector2d c = closest_on_segment(v, poly[i], poly[(i + 1) % poly.size()]);
        const double d = (c - v).squaredNorm();
        if (d < best) {
          best = d;
          bp = verts_are_pos ? v : c;
          bn = verts_are_pos ? c : v;
        }
      }
  };
  scan(hp, hn, true);
  scan(hn, hp, false);
  const double dist = std::sqrt(best);
  if (!(dist > 0)) return std::nullopt;
  const Eigen::Vector2d n = (bp - bn) / dist, m = 0.5 * (bp + bn);
  const double half = 0.5 * dist;
  const Eigen::Vector3d q(-n.dot(m) / half, n.x() / half, n.y() / half);
  const auto b = [&](const Eigen::Vector2d& x) { return q(0) + q(1) * x.x() + q(2) * x.y(); };
  for (const Eigen::Vector2d& x : pos)
    if (!(b(x) > 0.5)) return std::nullopt;
  for (const Eigen::Vector2d& x : neg)
    if (!(b(x) < -0.5)) return std::nullopt;
  return q;
}

// Colour clusters of a ball (eq. 7, or farthest-point seeds for multi_colour); labels
// per point. Returns the number of clusters.
int cluster_colours(const Impl& s, const std::vector<int>& ids, int far_i, int far_j, std::vector<int>& label) {
  const ColourParams& p = s.params;
  std::vector<Lab> seeds{s.labs[ids[far_i]], s.labs[ids[far_j]]};
  if (p.multi_colour) {
    std::vector<double> dmin(ids.size());
    for (std::size_t i = 0; i < ids.size(); ++i)
      dmin[i] = std::min(delta_e(s.labs[ids[i]], seeds[0]), delta_e(s.labs[ids[i]], seeds[1]));
    while (int(seeds.size()) < p.max_clusters) {
      const std::size_t far = std::max_element(dmin.begin(), dmin.end()) - dmin.begin();
      if (!(dmin[far] > p.gamma)) break;
      seeds.push_back(s.labs[ids[far]]);
      for (std::size_t i = 0; i < ids.size(); ++i) dmin[i] = std::min(dmin[i], delta_e(s.labs[ids[i]], seeds.back()));
    }
  }
  label.assign(ids.size(), 0);
  for (std::size_t i = 0; i < ids.size(); ++i) {
    double best = delta_e(s.labs[ids[i]], seeds[0]);
    for (int k = 1; k < int(seeds.size()); ++k) {
      const double d = delta_e(s.labs[ids[i]], seeds[k]);
      if (d < best) best = d, label[i] = k;  // ties stay with the earlier seed (eq. 7: <=)
    }
  }
  return int(seeds.size());
}

// Noise test (option b): drops clusters that are too small (reassigning their points to
// the nearest remaining cluster mean) and checks the pairwise separation. False: Type A.
bool noise_check(const Impl& s, const std::vector<int>& ids, std::vector<int>& label, int& k) {
  const ColourParams& p = s.params;
  const double min_size = std::max<double>(p.min_rbf_points, p.noise_min_fraction * double(ids.size()));
  for (;;) {
    std::vector<int> count(k, 0);
    std::vector<Lab> mean(k, Lab{});
    for (std::size_t i = 0; i < ids.size(); ++i) {
      ++count[label[i]];
      for (int c = 0; c < kChannels; ++c) mean[label[i]][c] += s.labs[ids[i]][c];
    }
    for (int j = 0; j < k; ++j)
      for (int c = 0; c < kChannels; ++c) mean[j][c] /= std::max(count[j], 1);
    const int smallest = int(std::min_element(count.begin(), count.end()) - count.begin());
    if (count[smallest] < min_size) {
      if (k <= 2) return false;
      // Drop it: relabel to the nearest other mean, renumber.
      for (std::size_t i = 0; i < ids.size(); ++i) {
        int best = -1;
        double bd = 1e300;
        for (int j = 0; j < k; ++j) {
          if (j == smallest) continue;
          const double d = delta_e(s.labs[ids[i]], mean[j]);
          if (d < bd) bd = d, best = j;
        }
        label[i] = best > smallest ? best - 1 : best;
      }
      --k;
      continue;
    }
    std::vector<double> spread(k, 0);
    for (std::size_t i = 0; i < ids.size(); ++i) spread[label[i]] += std::pow(delta_e(s.labs[ids[i]], mean[label[i]]), 2);
    for (int j = 0; j < k; ++j) spread[j] = std::sqrt(spread[j] / count[j]);
    for (int a = 0; a < k; ++a)
      for (int b = a + 1; b < k; ++b)
        if (!(delta_e(mean[a], mean[b]) > p.noise_separation * (spread[a] + spread[b]))) return false;
    return true;
  }
}

bool fit_type_b(const Impl& s, std::vector<int> ids, const std::vector<int>& label_in, int k, CellResult& cr) {
  Leaf& leaf = cr.leaf;
  leaf.type = ColourCellType::kB;
  leaf.rbf = std::make_shared<TypeBData>();
  TypeBData& tb = *leaf.rbf;
  tb.rbf_support = s.params.rbf_radius_factor;
  // Nodes in ascending u (ties by point index), for the range search in eval().
  std::vector<int> order(ids.size());
  std::vector<double> us(ids.size());
  for (std::size_t i = 0; i < ids.size(); ++i) {
    order[i] = int(i);
    us[i] = ((s.points[ids[i]].cast<double>() - leaf.o) * leaf.inv_r).dot(leaf.u);
  }
  std::sort(order.begin(), order.end(), [&](int x, int y) { return us[x] < us[y] || (us[x] == us[y] && ids[x] < ids[y]); });
  std::vector<int> ids_sorted(ids.size()), label_sorted(ids.size());
  for (std::size_t i = 0; i < ids.size(); ++i) ids_sorted[i] = ids[order[i]], label_sorted[i] = label_in[order[i]];
  const std::vector<int>& label = label_sorted;
  ids = ids_sorted;
  tb.nodes.resize(ids.size());
  tb.node_u.resize(ids.size());
  for (std::size_t i = 0; i < ids.size(); ++i) {
    tb.nodes[i] = (s.points[ids[i]].cast<double>() - leaf.o) * leaf.inv_r;
    tb.node_u[i] = us[order[i]];
  }
  tb.node_cluster.assign(label.begin(), label.end());
  tb.clusters.assign(k, RbfPart{});
  for (int j = 0; j < k; ++j) {
    std::vector<int> sel;
    for (std::size_t i = 0; i < ids.size(); ++i)
      if (label[i] == j) sel.push_back(int(i));
    if (int(sel.size()) < std::max(s.params.min_rbf_points, 4)) {
      // Too few for an RBF with a linear polynomial: the cluster's mean colour.
      RbfPart& part = tb.clusters[j];
      part.cols = kChannels;
      part.poly.assign(3 * kChannels, 0);
      for (int i : sel)
        for (int c = 0; c < kChannels; ++c) part.poly[c] += s.labs[ids[i]][c] / double(std::max<std::size_t>(sel.size(), 1));
      ++cr.constant_clusters;
      continue;
    }
    Eigen::MatrixXd rhs(sel.size(), kChannels);
    for (std::size_t i = 0; i < sel.size(); ++i)
      for (int c = 0; c < kChannels; ++c) rhs(i, c) = s.labs[ids[sel[i]]][c];
    if (!solve_rbf(leaf, sel, rhs, tb.clusters[j])) return false;
  }
  if (k == 2 && s.params.linear_boundary) {
    std::vector<Eigen::Vector2d> pos, neg;
    for (std::size_t i = 0; i < ids.size(); ++i)
      (label[i] == 0 ? pos : neg).emplace_back(tb.nodes[i].dot(leaf.u), tb.nodes[i].dot(leaf.v));
    if (const std::optional<Eigen::Vector3d> q = max_margin_line(pos, neg)) {
      tb.boundary = RbfPart{};
      tb.boundary.cols = 1;
      tb.boundary.poly = {(*q)(0), (*q)(1), (*q)(2)};
      ++cr.linear_boundaries;
      return true;
    }
  }
  // Boundary function(s), targets +1 / -1 (eq. 11-12); one-vs-rest for k > 2.
  const int cols = k == 2 ? 1 : k;
  Eigen::MatrixXd rhs(ids.size(), cols);
  for (std::size_t i = 0; i < ids.size(); ++i)
    for (int c = 0; c < cols; ++c) rhs(i, c) = label[i] == c ? 1.0 : -1.0;
  std::vector<int> all(ids.size());
  for (std::size_t i = 0; i < ids.size(); ++i) all[i] = int(i);
  return solve_rbf(leaf, all, rhs, tb.boundary);
}

// Per colour, the largest L*a*b* change per channel within half an 8-bit step of each
// sRGB channel (first order: the half-step changes of R, G and B added up), cached
// per distinct colour.
std::vector<std::array<float, 3>> quantisation_bounds(const std::vector<Rgb>& colours) {
  std::unordered_map<std::uint32_t, std::array<float, 3>> cache;
  std::vector<std::array<float, 3>> out(colours.size());
  for (std::size_t i = 0; i < colours.size(); ++i) {
    const Rgb& c = colours[i];
    const std::uint32_t key = std::uint32_t(c.r) << 16 | std::uint32_t(c.g) << 8 | std::uint32_t(c.b);
    auto it = cache.find(key);
    if (it == cache.end()) {
      const double rgb[3] = {c.r / 255.0, c.g / 255.0, c.b / 255.0};
      const Lab at = srgb_to_lab(rgb[0], rgb[1], rgb[2]);
      std::array<float, 3> q{};
      for (int j = 0; j < 3; ++j) {
        double up[3] = {rgb[0], rgb[1], rgb[2]}, down[3] = {rgb[0], rgb[1], rgb[2]};
        up[j] += 0.5 / 255;
        down[j] -= 0.5 / 255;
        const Lab a = srgb_to_lab(up[0], up[1], up[2]), b = srgb_to_lab(down[0], down[1], down[2]);
        for (int k = 0; k < 3; ++k)
          q[k] += float(std::max(std::abs(a[k] - at[k]), std::abs(b[k] - at[k])));
      }
      it = cache.emplace(key, q).first;
    }
    out[i] = it->second;
  }
  return out;
}

CellResult fit_cell(const Impl& s, const Vec3d& o, double half, int depth) {
  const ColourParams& p = s.params;
  CellResult cr;
  const double R0 = p.alpha * 2 * half * std::sqrt(3.0);
  // A ball holding more than n_max points is split; the search gives up past them
  // (near the root the ball holds most of the cloud).
  std::vector<std::pair<int, float>> nn;
  if (depth < p.max_depth) {
    auto at_most = s.index->radius_at_most(o.cast<float>(), float(R0), std::size_t(std::max(p.n_max, 0)));
    if (!at_most) {
      cr.split = true;
      return cr;
    }
    nn = std::move(*at_most);
  } else {
    nn = s.index->radius(o.cast<float>(), float(R0));
  }
  if (nn.empty()) {
    // No data within the cell's support: no leaf (docs/colour.md). MPU grows such balls
    // to extrapolate the shape; colour is only asked for near the data, and a ball grown
    // from the inside of an object can swallow the whole cloud.
    cr.empty = true;
    return cr;
  }
  double R = R0;
  if (int(nn.size()) < p.n_min) {
    cr.grew = true;
    // Jump straight to the growth step that reaches the n_min-th nearest point.
    const auto kn = s.index->knn(o.cast<float>(), p.n_min);
    const double need = kn.empty() ? R0 : double(kn.back().second);
    int m = std::max(0, int(std::ceil((need / R0 - 1) / p.lambda)) - 1);
    do {
      R = R0 * (1 + m * p.lambda);
      nn = s.index->radius(o.cast<float>(), float(R));
      ++m;
    } while (int(nn.size()) < std::min<int>(p.n_min, int(s.points.size())));
  }
  // A grown ball can take in many points at once (points at equal distances): fit the
  // nearest ones only (nn is sorted by distance).
  if (int(nn.size()) > std::max(p.n_max, p.n_min)) nn.resize(std::max(p.n_max, p.n_min));
  cr.radius = R;
  Leaf& leaf = cr.leaf;
  leaf.o = o;
  leaf.inv_r = 1 / R;
  std::vector<int> ids(nn.size());
  std::vector<double> w(nn.size());
  for (std::size_t i = 0; i < nn.size(); ++i) {
    ids[i] = nn[i].first;
    w[i] = std::max(bspline2(1.5 * nn[i].second / R), 1e-3);
  }
  tangent_frame(s, ids, w, leaf);

  // Colour-difference test (eq. 5).
  if (p.type_b) {
    // Every colour within gamma / 2 of the first: no pair exceeds gamma (triangle
    // inequality), skip the quadratic search.
    double dfirst = 0;
    for (std::size_t i = 1; i < ids.size(); ++i) dfirst = std::max(dfirst, delta_e2(s.labs[ids[0]], s.labs[ids[i]]));
    double dmax = -1;
    int fi = 0, fj = 0;
    if (dfirst > 0.25 * p.gamma * p.gamma) {
      // The ball's colours side by side, channel by channel (the same sums, in the
      // same order, as delta_e2 on the points' labs).
      thread_local std::vector<double> ch;
      const std::size_t m = ids.size();
      ch.resize(3 * m);
      for (std::size_t i = 0; i < m; ++i)
        for (int c = 0; c < kChannels; ++c) ch[c * m + i] = s.labs[ids[i]][c];
      const double* L = ch.data();
      const double* A = L + m;
      const double* B = A + m;
      thread_local std::vector<double> row;
      row.resize(m);
      for (std::size_t i = 0; i + 1 < m; ++i) {
        const double li = L[i], ai = A[i], bi = B[i];
        double best = -1;
        for (std::size_t j = i + 1; j < m; ++j) {
          const double d = (li - L[j]) * (li - L[j]) + (ai - A[j]) * (ai - A[j]) + (bi - B[j]) * (bi - B[j]);
          row[j] = d;
          best = std::max(best, d);
        }
        if (best > dmax) {
          // The first j reaching the row's maximum: the pair the scan in order picks.
          std::size_t j = i + 1;
          while (row[j] != best) ++j;
          dmax = best, fi = int(i), fj = int(j);
        }
      }
    }
    if (dmax > p.gamma * p.gamma) {
      std::vector<int> label;
      int k = cluster_colours(s, ids, fi, fj, label);
      bool ok = true;
      if (p.noise_robust && !noise_check(s, ids, label, k)) {
        ok = false;
        cr.rejected_b = true;
      }
      if (ok) {
        CellResult trial = cr;
        if (fit_type_b(s, ids, label, k, trial)) return trial;
        cr.fallback_a = true;
      }
    }
  }
  // Type A with the accuracy test (eq. 4) over the points within alpha * d; phi(p) is
  // approximated by w_k(p) (docs/colour.md: same-depth weights sum to ~1.02).
  const double rms = fit_type_a(s, ids, w, leaf);
  double err = 0;
  for (std::size_t i = 0; i < ids.size(); ++i) {
    if (nn[i].second >= R0) continue;
    const Lab q = leaf.eval(s.points[ids[i]].cast<double>());
    const double phi = bspline2(1.5 * nn[i].second / R);
    for (int c = 0; c < kChannels; ++c) {
      double d = std::abs(q[c] - s.labs[ids[i]][c]);
      if (!s.quant.empty()) d = std::max(0.0, d - double(s.quant[ids[i]][c]));
      err = std::max(err, d / kRange[c] * phi);
    }
  }
  cr.converged = err < p.epsilon_col || (p.noise_robust && rms <= p.noise_accept_rms);
  if (!cr.converged && !cr.grew && depth < p.max_depth && int(ids.size()) >= p.split_min_points) cr.split = true;
  return cr;
}

}  // namespace

ColourFunction fit_colour(const Cloud& cloud, const ColourParams& params) {
  const auto t0 = std::chrono::steady_clock::now();
  cloud.check_consistent("colour_function input");
  if (!cloud.has_colours()) throw InvalidInput("colour_function: the cloud has no colours");
  if (cloud.empty()) throw InvalidInput("colour_function: empty cloud");
  const ColourParams& p = params;
  if (!(p.alpha > 0.5) || !(p.lambda > 0) || p.n_min < 1 || p.n_max < p.n_min || !(p.gamma > 0) ||
      !(p.epsilon_col > 0) || !(p.rbf_radius_factor > 0) || p.max_depth < 0 || p.max_depth > 20 ||
      p.threads < 0 || !(p.root_margin >= 0) || p.min_rbf_points < 0 || p.split_min_points < 0 || p.max_clusters < 2 ||
      p.max_clusters > 16 || !(p.noise_min_fraction >= 0 && p.noise_min_fraction < 0.5) ||
      !(p.noise_separation >= 0) || !(p.noise_accept_rms >= 0))
    throw InvalidInput(
        "colour_function: parameters out of range (alpha > 0.5, lambda > 0, 1 <= n_min <= n_max, gamma > 0, "
        "epsilon_col > 0, rbf_radius_factor > 0, 0 <= max_depth <= 20, threads >= 0, root_margin >= 0, "
        "min_rbf_points >= 0, split_min_points >= 0, 2 <= max_clusters <= 16, 0 <= noise_min_fraction < 0.5, noise_separation >= 0, "
        "noise_accept_rms >= 0)");
  if (!all_finite(cloud.points)) throw InvalidInput("colour_function: non-finite point coordinates");

  auto impl = std::make_shared<Impl>();
  Impl& s = *impl;
  s.params = p;
  s.diag.input_points = cloud.size();
  const Aabb box = bounding_box(cloud.points);
  const double side = (box.max - box.min).cast<double>().maxCoeff();
  if (!(side > 0)) throw InvalidInput("colour_function: all points are equal");
  // MPU's normalised frame (fit_mpu): the points' bounding cube has diagonal 1.
  s.center = box.center().cast<double>();
  s.scale = 1 / (side * std::sqrt(3.0));
  s.diagonal = side * std::sqrt(3.0);
  s.points.reserve(cloud.size());
  for (const Vec3f& q : cloud.points) s.points.push_back(((q.cast<double>() - s.center) * s.scale).cast<float>());
  if (cloud.has_normals()) {
    s.normals.resize(cloud.size());
    for (std::size_t i = 0; i < cloud.size(); ++i) {
      const Vec3d n = cloud.normals[i].cast<double>();
      const double len = n.norm();
      s.normals[i] = std::isfinite(len) && len > 1e-9 ? Vec3d(n / len) : Vec3d::Zero();
    }
  }
  s.labs.resize(cloud.size());
  for (std::size_t i = 0; i < cloud.size(); ++i) s.labs[i] = rgb_to_lab(cloud.colours[i]);
  if (p.quantisation_tolerance) s.quant = quantisation_bounds(cloud.colours);
  s.index = std::make_unique<PointIndex>(s.points);

  tbb::task_arena arena(worker_threads(p.threads));
  arena.execute([&] {
    // Breadth-first, level by level: cells fitted in parallel into their own slots,
    // children appended in cell order (deterministic for any thread count).
    Node root;
    root.center = Vec3d::Zero();
    root.half = 0.5 / std::sqrt(3.0) * (1 + p.root_margin);
    // Room for a leaf per point and for twice as many cells: growing by doubling copied
    // the leaves into fresh memory several times over, in serial code (room never used
    // is never touched; docs/dmc.md, "2026-12-06: memory touched where it is used").
    s.leaves.reserve(s.points.size());
    s.nodes.reserve(2 * s.points.size());
    s.nodes.push_back(root);
    std::vector<int> frontier{0};
    // The cells of a level in chunks, so that only a chunk's results are held at once
    // (a level of a million-point cloud holds hundreds of thousands of cells).
    constexpr std::size_t kChunk = 4096;
    std::vector<CellResult> res;
    for (int depth = 0; !frontier.empty(); ++depth) {
      std::vector<int> next;
      for (std::size_t begin = 0; begin < frontier.size(); begin += kChunk) {
        const std::size_t end = std::min(frontier.size(), begin + kChunk);
        res.assign(end - begin, CellResult{});
        tbb::parallel_for(tbb::blocked_range<std::size_t>(begin, end, 1), [&](const auto& range) {
          for (std::size_t i = range.begin(); i != range.end(); ++i) {
            const Node& nd = s.nodes[frontier[i]];
            res[i - begin] = fit_cell(s, nd.center, nd.half, depth);
          }
        });
        for (std::size_t i = begin; i < end; ++i) {
          const int id = frontier[i];
          CellResult& cr = res[i - begin];
          if (cr.split) {
            detail::split_cell(s.nodes, id, depth, next);
            continue;
          }
          Node& nd = s.nodes[id];
          if (cr.empty) {
            nd.radius = 0;  // a leaf without a function: never visited
            ++s.diag.empty_cells;
            continue;
          }
          nd.radius = cr.radius;
          nd.leaf = int(s.leaves.size());
          const int type = int(cr.leaf.type);
          if (cr.leaf.type == ColourCellType::kB && cr.leaf.cluster_count() > 2) ++s.diag.multi_colour_leaves;
          s.leaves.push_back(std::move(cr.leaf));
          ++s.diag.leaves;
          ++s.diag.leaves_by_type[type];
          if (s.diag.leaves_by_depth.size() <= std::size_t(depth)) s.diag.leaves_by_depth.resize(depth + 1);
          ++s.diag.leaves_by_depth[depth][type];
          if (cr.grew) ++s.diag.grown_leaves;
          if (type == 0 && !cr.converged) ++s.diag.unconverged_leaves;
          s.diag.constant_clusters += cr.constant_clusters;
          s.diag.linear_boundaries += cr.linear_boundaries;
          s.diag.rejected_type_b += cr.rejected_b;
          s.diag.fallback_type_a += cr.fallback_a;
        }
      }
      frontier.swap(next);
    }
  });
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
  {
    // eval_many's grouping cell: the median leaf radius (a group then gathers about the
    // leaves one point would, a few more at its rim).
    std::vector<double> radii;
    for (const Node& nd : s.nodes)
      if (nd.leaf >= 0 && nd.radius > 0) radii.push_back(nd.radius);
    if (!radii.empty()) {
      std::nth_element(radii.begin(), radii.begin() + radii.size() / 2, radii.end());
      s.batch_cell = std::max(1e-6, radii[radii.size() / 2]);
    }
  }
  s.diag.cells = s.nodes.size();
  s.diag.fit_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  ColourFunction out;
  out.impl_ = impl;
  if (p.compute_e_col) {
    const auto t1 = std::chrono::steady_clock::now();
    if (p.e_col_max_points > 0 && cloud.size() > p.e_col_max_points) {
      Cloud sample;
      const std::size_t m = p.e_col_max_points;
      sample.points.reserve(m);
      sample.colours.reserve(m);
      for (std::size_t i = 0; i < m; ++i) {
        const std::size_t k = i * cloud.size() / m;  // evenly strided, the first point included
        sample.points.push_back(cloud.points[k]);
        sample.colours.push_back(cloud.colours[k]);
      }
      impl->diag.e_col = out.e_col(sample, p.threads);
      impl->diag.e_col_points = m;
    } else {
      impl->diag.e_col = out.e_col(cloud, p.threads);
      impl->diag.e_col_points = cloud.size();
    }
    impl->diag.e_col_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count();
  }
  return out;
}

Lab ColourFunction::lab(const Vec3d& x_in) const {
  if (!impl_) throw InvalidInput("colour_function: not fitted");
  Vec3d x = x_in;
  if (surface_ && x.allFinite()) {
    const double tol = 1e-6 * impl_->diagonal;
    Vec3d y = x;
    for (int it = 0; it < projection_steps_; ++it) {
      const double f = surface_->value(y);
      const Vec3d g = surface_->gradient(y);
      const double g2 = g.squaredNorm();
      if (!std::isfinite(f) || !(g2 > 1e-20) || !g.allFinite()) break;
      const Vec3d step = f * g / g2;
      y -= step;
      if (step.norm() < tol) break;
    }
    // A projection that runs away (far from any surface) is not used.
    if (y.allFinite() && (y - x).norm() < 0.25 * impl_->diagonal) x = y;
  }
  if (!x.allFinite()) return {0, 0, 0};
  return impl_->eval(x);
}

std::array<double, 3> ColourFunction::srgb(const Vec3d& x) const { return lab_to_srgb(lab(x)); }
Rgb ColourFunction::rgb(const Vec3d& x) const { return lab_to_rgb(lab(x)); }

std::vector<Lab> ColourFunction::labs(const std::vector<Vec3f>& xs, int threads) const {
  if (!impl_) throw InvalidInput("colour_function: not fitted");
  std::vector<Lab> out(xs.size(), Lab{0, 0, 0});
  tbb::task_arena arena(worker_threads(threads));
  arena.execute([&] {
    if (surface_) {  // projected first: one point at a time
      tbb::parallel_for(tbb::blocked_range<std::size_t>(0, xs.size(), 256), [&](const auto& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) out[i] = lab(xs[i].cast<double>());
      });
      return;
    }
    std::vector<std::uint32_t> finite;  // non-finite points keep lab's {0, 0, 0}
    finite.reserve(xs.size());
    for (std::size_t i = 0; i < xs.size(); ++i)
      if (xs[i].allFinite()) finite.push_back(std::uint32_t(i));
    impl_->eval_many(
        finite.size(), [&](std::size_t i) { return Vec3d(xs[finite[i]].cast<double>()); },
        [&](std::size_t i, const Lab& l) { out[finite[i]] = l; });
  });
  return out;
}

std::vector<Rgb> ColourFunction::rgbs(const std::vector<Vec3f>& xs) const {
  const std::vector<Lab> l = labs(xs, impl_ ? impl_->params.threads : 0);
  std::vector<Rgb> out(xs.size());
  for (std::size_t i = 0; i < xs.size(); ++i) out[i] = lab_to_rgb(l[i]);
  return out;
}

void ColourFunction::set_surface(const ImplicitFunction* surface, int steps) {
  surface_ = surface;
  projection_steps_ = std::max(1, steps);
}

ColourCellType ColourFunction::dominant_type(const Vec3d& x) const {
  if (!impl_) return ColourCellType::kA;
  std::vector<Impl::Hit> hits;
  impl_->gather((x - impl_->center) * impl_->scale, hits);
  int leaf = -1;
  double best_w = 0;
  for (const Impl::Hit& h : hits)
    if (h.w > best_w) best_w = h.w, leaf = h.leaf;
  return leaf < 0 ? ColourCellType::kA : impl_->leaves[leaf].type;
}

double ColourFunction::e_col(const Cloud& coloured, int threads) const {
  coloured.check_consistent("e_col cloud");
  if (!coloured.has_colours() || coloured.empty()) throw InvalidInput("e_col: the cloud has no colours");
  std::vector<double> err(coloured.size());
  const std::vector<Lab> l = labs(coloured.points, threads);
  tbb::task_arena arena(worker_threads(threads));
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, coloured.size(), 256), [&](const auto& r) {
      for (std::size_t i = r.begin(); i != r.end(); ++i) {
        const auto f = lab_to_srgb(l[i]);
        // The paper converts the point's L*a*b* back to RGB: the identity to rounding.
        const auto c = lab_to_srgb(rgb_to_lab(coloured.colours[i]));
        err[i] = std::abs(f[0] - c[0]) + std::abs(f[1] - c[1]) + std::abs(f[2] - c[2]);
      }
    });
  });
  double sum = 0;
  for (double e : err) sum += e;  // fixed order: deterministic
  return sum / double(err.size());
}

const ColourDiagnostics& ColourFunction::diagnostics() const {
  if (!impl_) throw InvalidInput("colour_function: not fitted");
  return impl_->diag;
}
const ColourParams& ColourFunction::params() const {
  if (!impl_) throw InvalidInput("colour_function: not fitted");
  return impl_->params;
}

std::size_t colour_mesh(Mesh& mesh, const ColourFunction& f, const ImplicitFunction& surface,
                        const Cloud& coloured_points, int threads) {
  colour_mesh(mesh, f, threads);
  std::vector<char> untrusted(mesh.vertices.size(), 0);
  tbb::task_arena arena(worker_threads(threads));
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, mesh.vertices.size(), 1024), [&](const auto& r) {
      for (std::size_t i = r.begin(); i != r.end(); ++i)
        untrusted[i] = !surface.trusted(mesh.vertices[i].cast<double>());
    });
  });
  Mesh nn;  // the untrusted vertices only (transfer_colours colours each on its own)
  std::vector<std::size_t> at;
  for (std::size_t i = 0; i < mesh.vertices.size(); ++i)
    if (untrusted[i]) {
      nn.vertices.push_back(mesh.vertices[i]);
      at.push_back(i);
    }
  if (at.empty()) return 0;
  transfer_colours(nn, coloured_points, {4, threads});
  for (std::size_t j = 0; j < at.size(); ++j) mesh.colours[at[j]] = nn.colours[j];
  return at.size();
}

void colour_mesh(Mesh& mesh, const ColourFunction& f, int threads) {
  const std::vector<Lab> l = f.labs(mesh.vertices, threads);
  mesh.colours.resize(mesh.vertices.size());
  for (std::size_t i = 0; i < l.size(); ++i) mesh.colours[i] = lab_to_rgb(l[i]);
}

}  // namespace station
