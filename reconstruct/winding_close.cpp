#include "reconstruct/winding_close.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <unordered_map>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "core/error.h"
#include "core/kdtree.h"
#include "reconstruct/mpu.h"
#include "reconstruct/near_grid.h"

namespace station {

namespace {

constexpr double kFourPi = 4.0 * 3.14159265358979323846;

struct WPoint {
  Vec3d p;
  Vec3d dipole;  // area x unit normal
};

struct WNode {
  Vec3d centre = Vec3d::Zero();
  Vec3d dipole = Vec3d::Zero();
  double radius = 0;
  int begin = 0, end = 0;    // points [begin, end) of the reordered array
  int left = -1, right = -1;  // children (both or neither)
};

constexpr int kLeafSize = 8;
constexpr double kFarRatio = 2.0;  // a cluster is far when distance > 2 x its radius

}  // namespace

struct WindingNumber::Impl {
  std::vector<WPoint> pts;
  std::vector<WNode> nodes;

  int build(int begin, int end) {
    const int id = int(nodes.size());
    nodes.push_back({});
    WNode n;
    n.begin = begin;
    n.end = end;
    double weight = 0;
    Vec3d lo = Vec3d::Constant(std::numeric_limits<double>::infinity()), hi = -lo;
    for (int i = begin; i < end; ++i) {
      const double a = pts[i].dipole.norm();
      n.centre += a * pts[i].p;
      weight += a;
      n.dipole += pts[i].dipole;
      lo = lo.cwiseMin(pts[i].p);
      hi = hi.cwiseMax(pts[i].p);
    }
    n.centre = weight > 0 ? Vec3d(n.centre / weight) : Vec3d(0.5 * (lo + hi));
    for (int i = begin; i < end; ++i) n.radius = std::max(n.radius, (pts[i].p - n.centre).norm());
    if (end - begin > kLeafSize) {
      int axis = 0;
      (hi - lo).maxCoeff(&axis);
      const int mid = begin + (end - begin) / 2;
      std::nth_element(pts.begin() + begin, pts.begin() + mid, pts.begin() + end,
                       [axis](const WPoint& a, const WPoint& b) { return a.p[axis] < b.p[axis]; });
      n.left = build(begin, mid);
      n.right = build(mid, end);
    }
    nodes[id] = n;
    return id;
  }
};

std::vector<double> point_areas(const std::vector<Vec3f>& points, const std::vector<Vec3f>& normals) {
  if (points.size() != normals.size()) throw InvalidInput("winding number: points and normals differ in count");
  // Area per point from the local density: the disc reaching the k-th neighbour
  // holds k points, so a point stands for pi r_k^2 / k (uneven density, such as the
  // overlaps of merged views, is handled by construction).
  constexpr int kNeighbours = 8;
  std::vector<Vec3f> finite;
  std::vector<std::size_t> at;
  for (std::size_t i = 0; i < points.size(); ++i)
    if (points[i].allFinite() && normals[i].allFinite()) {
      finite.push_back(points[i]);
      at.push_back(i);
    }
  const PointIndex index(finite);
  std::vector<double> area(points.size(), 0);
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, finite.size(), 1024), [&](const auto& range) {
    for (std::size_t i = range.begin(); i != range.end(); ++i) {
      const auto nn = index.knn(finite[i], kNeighbours + 1);  // the point itself first
      if (nn.size() < 2) continue;
      const double r = nn.back().second;
      area[at[i]] = 3.14159265358979323846 * r * r / double(nn.size() - 1);
    }
  });
  return area;
}

WindingNumber::WindingNumber(const std::vector<Vec3f>& points, const std::vector<Vec3f>& normals, double voxel,
                             const std::vector<double>* areas)
    : impl_(std::make_unique<Impl>()) {
  if (points.size() != normals.size()) throw InvalidInput("winding number: points and normals differ in count");
  if (!(voxel > 0) || !std::isfinite(voxel)) throw InvalidInput("winding number: the voxel must be positive");
  if (areas && areas->size() != points.size()) throw InvalidInput("winding number: areas and points differ in count");
  // The areas of the points with finite coordinates and normals (the others are left
  // out of the tree and the sums alike).
  const std::vector<double> computed = areas ? std::vector<double>() : point_areas(points, normals);
  const std::vector<double>& all_areas = areas ? *areas : computed;
  std::vector<Vec3f> finite;
  std::vector<Vec3d> fnormals;
  std::vector<double> area;
  for (std::size_t i = 0; i < points.size(); ++i)
    if (points[i].allFinite() && normals[i].allFinite()) {
      finite.push_back(points[i]);
      fnormals.push_back(normals[i].cast<double>());
      area.push_back(all_areas[i]);
    }
  struct Acc {
    Vec3d p = Vec3d::Zero(), dipole = Vec3d::Zero();
    double weight = 0;
  };
  std::unordered_map<std::uint64_t, Acc> cells;
  auto key = [voxel](const Vec3f& p) {
    std::uint64_t k = 0;
    for (int a = 0; a < 3; ++a)
      k = (k << 21) | (std::uint64_t(std::int64_t(std::floor(p[a] / voxel)) + (1 << 20)) & 0x1FFFFF);
    return k;
  };
  for (std::size_t i = 0; i < finite.size(); ++i) {
    Acc& a = cells[key(finite[i])];
    a.p += area[i] * finite[i].cast<double>();
    a.weight += area[i];
    const double len = fnormals[i].norm();
    if (len > 0) a.dipole += area[i] / len * fnormals[i];
  }
  std::vector<std::pair<std::uint64_t, Acc>> sorted(cells.begin(), cells.end());
  std::sort(sorted.begin(), sorted.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  for (const auto& [k, a] : sorted)
    if (a.weight > 0 && a.dipole.squaredNorm() > 0) impl_->pts.push_back({a.p / a.weight, a.dipole});
  if (!impl_->pts.empty()) impl_->build(0, int(impl_->pts.size()));
}

WindingNumber::~WindingNumber() = default;
WindingNumber::WindingNumber(WindingNumber&&) noexcept = default;
WindingNumber& WindingNumber::operator=(WindingNumber&&) noexcept = default;

std::size_t WindingNumber::size() const { return impl_->pts.size(); }

double WindingNumber::operator()(const Vec3d& x) const { return evaluate(x, nullptr); }

double WindingNumber::evaluate(const Vec3d& x, Vec3d* grad) const {
  const auto& nodes = impl_->nodes;
  if (grad) *grad = Vec3d::Zero();
  if (nodes.empty()) return 0;
  double sum = 0;
  Vec3d g = Vec3d::Zero();
  // One dipole D at c seen from x: D . r / |r|^3 with r = c - x; its gradient in x
  // is (3 (D . r) r / |r|^2 - D) / |r|^3.
  auto add = [&](const Vec3d& D, const Vec3d& r) {
    const double r2 = r.squaredNorm();
    if (!(r2 > 0)) return;
    const double inv3 = 1.0 / (r2 * std::sqrt(r2));
    const double dr = D.dot(r);
    sum += dr * inv3;
    if (grad) g += (3 * dr / r2 * r - D) * inv3;
  };
  int stack[128];
  int top = 0;
  stack[top++] = 0;
  while (top > 0) {
    const WNode& n = nodes[stack[--top]];
    const Vec3d d = n.centre - x;
    if (d.squaredNorm() > kFarRatio * kFarRatio * n.radius * n.radius) {
      add(n.dipole, d);
    } else if (n.left < 0) {
      for (int i = n.begin; i < n.end; ++i) add(impl_->pts[i].dipole, impl_->pts[i].p - x);
    } else if (top + 2 <= 128) {
      stack[top++] = n.left;
      stack[top++] = n.right;
    }
  }
  if (grad) *grad = g / kFourPi;
  return sum / kFourPi;
}

void WindingNumber::evaluate_near(const Vec3d* xs, int n, double* w, Vec3d* grads) const {
  if (n <= 0) return;
  const auto& nodes = impl_->nodes;
  const auto& pts = impl_->pts;
  Vec3d lo = Vec3d::Constant(std::numeric_limits<double>::infinity()), hi = -lo;
  for (int i = 0; i < n; ++i) {
    lo = lo.cwiseMin(xs[i]);
    hi = hi.cwiseMax(xs[i]);
  }
  if (nodes.empty() || n == 1 || !lo.allFinite() || !hi.allFinite()) {
    for (int i = 0; i < n; ++i) w[i] = evaluate(xs[i], grads ? &grads[i] : nullptr);
    return;
  }
  const Vec3d mid = 0.5 * (lo + hi);
  double rb = 0;
  for (int i = 0; i < n; ++i) rb = std::max(rb, (xs[i] - mid).norm());
  // Per point sums, filled in the order evaluate() fills them: the same depth-first
  // walk (children pushed left then right), one point's contributions in that order.
  thread_local std::vector<double> sum;
  thread_local std::vector<Vec3d> g;
  sum.assign(std::size_t(n), 0.0);
  g.assign(std::size_t(n), Vec3d::Zero());
  auto add = [&](int i, const Vec3d& D, const Vec3d& r) {
    const double r2 = r.squaredNorm();
    if (!(r2 > 0)) return;
    const double inv3 = 1.0 / (r2 * std::sqrt(r2));
    const double dr = D.dot(r);
    sum[std::size_t(i)] += dr * inv3;
    if (grads) g[std::size_t(i)] += (3 * dr / r2 * r - D) * inv3;
  };
  // One point through the subtree of `root`, as evaluate() walks it, with `base`
  // entries already on evaluate()'s stack (its depth limit then drops the same nodes).
  auto one = [&](int i, int root, int base) {
    const Vec3d& x = xs[i];
    int stack[128];
    int top = 0;
    stack[top++] = root;
    while (top > 0) {
      const WNode& nd = nodes[std::size_t(stack[--top])];
      const Vec3d d = nd.centre - x;
      if (d.squaredNorm() > kFarRatio * kFarRatio * nd.radius * nd.radius) {
        add(i, nd.dipole, d);
      } else if (nd.left < 0) {
        for (int k = nd.begin; k < nd.end; ++k) add(i, pts[std::size_t(k)].dipole, pts[std::size_t(k)].p - x);
      } else if (base + top + 2 <= 128) {
        stack[top++] = nd.left;
        stack[top++] = nd.right;
      }
    }
  };
  int stack[128];
  int top = 0;
  stack[top++] = 0;
  while (top > 0) {
    const int id = stack[--top];
    const WNode& nd = nodes[std::size_t(id)];
    const double dc = (nd.centre - mid).norm(), reach = kFarRatio * nd.radius;
    // A margin over the rounding of the distances: where the cluster is not clearly
    // on one side, every point decides for itself.
    const double margin = 1e-9 * (dc + rb + reach) + 1e-300;
    if (dc - rb > reach + margin) {  // far from every point
      for (int i = 0; i < n; ++i) add(i, nd.dipole, nd.centre - xs[i]);
    } else if (dc + rb < reach - margin && nd.left >= 0) {  // near every point
      if (top + 2 <= 128) {
        stack[top++] = nd.left;
        stack[top++] = nd.right;
      }
    } else {
      for (int i = 0; i < n; ++i) one(i, id, top);
    }
  }
  for (int i = 0; i < n; ++i) {
    w[i] = sum[std::size_t(i)] / kFourPi;
    if (grads) grads[i] = g[std::size_t(i)] / kFourPi;
  }
}

namespace {

// Mean nearest-neighbour spacing over an even subset of at most 4,000 points.
double subset_spacing(const PointIndex& index, const std::vector<Vec3f>& points) {
  const std::size_t n = points.size(), m = std::min<std::size_t>(n, 4000);
  double sum = 0;
  int counted = 0;
  for (std::size_t s = 0; s < m; ++s) {
    const auto nn = index.knn(points[s * n / m], 2);
    if (nn.size() == 2) sum += nn[1].second, ++counted;
  }
  return counted ? sum / counted : 0;
}

}  // namespace

double cloud_enclosure(const Cloud& cloud, const std::vector<double>* areas) {
  if (cloud.points.empty() || !cloud.has_normals()) return 0;
  const PointIndex index(cloud.points);
  const double diag = bounding_box(cloud.points).diagonal();
  const double t1 = 4 * subset_spacing(index, cloud.points);
  const double voxel = std::max(0.5 * t1, std::max(diag, 1e-9) / 200);
  const WindingNumber w(cloud.points, cloud.normals, voxel, areas);
  const std::size_t n = cloud.points.size(), m = std::min<std::size_t>(n, 2000);
  std::vector<double> sums;
  sums.reserve(m);
  for (std::size_t s = 0; s < m; ++s) {
    const std::size_t i = s * n / m;
    const Vec3d nrm = cloud.normals[i].cast<double>();
    if (!(nrm.squaredNorm() > 0)) continue;
    const Vec3d p = cloud.points[i].cast<double>(), d = voxel * nrm.normalized();
    sums.push_back(w(p - d) + w(p + d));
  }
  if (sums.empty()) return 0;
  std::nth_element(sums.begin(), sums.begin() + long(sums.size() / 2), sums.end());
  return sums[sums.size() / 2];
}

// ---- WindingClose -------------------------------------------------------------------

struct WindingClose::Index {
  PointIndex points;
  NearGrid near;  // within t1 of the data: beta = 0 without a search
};

WindingClose::WindingClose(const ImplicitFunction& f, const Cloud& cloud, const WindingCloseParams& params)
    : f_(f), mpu_(dynamic_cast<const MpuSurface*>(&f)) {
  if (cloud.points.empty()) throw InvalidInput("winding close: empty cloud");
  if (!cloud.has_normals()) throw InvalidInput("winding close: the cloud has no normals");
  if (!(params.ramp > 1) || !(params.trust_distance >= 0) || !(params.voxel >= 0))
    throw InvalidInput("winding close: need ramp > 1, trust_distance >= 0, voxel >= 0");
  index_ = std::make_unique<Index>(Index{PointIndex(cloud.points), NearGrid()});
  t1_ = params.trust_distance;
  if (t1_ <= 0) t1_ = 4 * subset_spacing(index_->points, cloud.points);
  const Aabb box = bounding_box(cloud.points);
  const double diag = box.diagonal();
  if (!(t1_ > 0)) t1_ = 1e-3 * std::max(diag, 1e-9);
  t2_ = params.ramp * t1_;
  const double voxel = params.voxel > 0 ? params.voxel : std::max(0.5 * t1_, diag / 200);
  index_->near = NearGrid(cloud.points, t1_);
  w_ = std::make_unique<WindingNumber>(cloud.points, cloud.normals, voxel, params.areas);
}

WindingClose::~WindingClose() = default;

double WindingClose::blend(const Vec3d& x, Vec3d* grad) const {
  if (index_->near.surely_near(x)) {  // d <= t1: what the search below would give
    if (grad) *grad = Vec3d::Zero();
    return 0;
  }
  const auto [id, d] = index_->points.nearest(x.cast<float>());
  const double beta = std::clamp((d - t1_) / (t2_ - t1_), 0.0, 1.0);
  if (grad) {
    *grad = Vec3d::Zero();
    if (beta > 0 && beta < 1 && id >= 0 && d > 0)
      *grad = (x - index_->points.points()[id].cast<double>()) / (double(d) * (t2_ - t1_));
  }
  return beta;
}

double WindingClose::value(const Vec3d& x) const {
  const double beta = blend(x, nullptr);
  if (beta <= 0) return f_.value(x);
  const double s = (0.5 - (*w_)(x)) * 2 * t2_;
  if (beta >= 1) return s;
  const double f = f_.value(x);
  if (!std::isfinite(f)) return s;
  return (1 - beta) * f + beta * s;
}

bool WindingClose::all_trusted(const Vec3d* xs, int n) const {
  if (n < 1) return false;
  {
    int i = 0;
    while (i < n && index_->near.surely_near(xs[i])) ++i;
    if (i == n) return true;
  }
  if (n < 2) return false;
  Vec3d lo = xs[0], hi = xs[0];
  for (int i = 1; i < n; ++i) {
    lo = lo.cwiseMin(xs[i]);
    hi = hi.cwiseMax(xs[i]);
  }
  if (!lo.allFinite() || !hi.allFinite()) return false;
  const Vec3d mid = 0.5 * (lo + hi);
  double rb = 0;
  for (int i = 0; i < n; ++i) rb = std::max(rb, (xs[i] - mid).norm());
  const double d = index_->points.nearest(mid.cast<float>()).second;
  // Every point is within d + rb of an input point; the margin covers the float
  // rounding of the coordinates and distances that blend() sees.
  return d + rb + 1e-4 * t1_ + 1e-6 * mid.norm() < t1_;
}

void WindingClose::winding_where_blended(const Vec3d* xs, int n, const std::vector<double>& beta,
                                         std::vector<double>& w, std::vector<Vec3d>* grads) const {
  w.assign(std::size_t(std::max(n, 0)), 0.0);
  if (grads) grads->assign(w.size(), Vec3d::Zero());
  std::vector<Vec3d> at;
  std::vector<int> which;
  for (int i = 0; i < n; ++i)
    if (beta[std::size_t(i)] > 0) {
      at.push_back(xs[i]);
      which.push_back(i);
    }
  if (at.empty()) return;
  std::vector<double> wv(at.size());
  std::vector<Vec3d> gv(grads ? at.size() : 0);
  w_->evaluate_near(at.data(), int(at.size()), wv.data(), grads ? gv.data() : nullptr);
  for (std::size_t k = 0; k < at.size(); ++k) {
    w[std::size_t(which[k])] = wv[k];
    if (grads) (*grads)[std::size_t(which[k])] = gv[k];
  }
}

void WindingClose::values_near(const Vec3d* xs, int n, double* out) const {
  // Within the trust distance throughout: beta = 0 for every point (what blend()
  // would find one query at a time), so g = f.
  if (all_trusted(xs, n)) {
    f_.values_near(xs, n, out);
    return;
  }
  // Local buffers: f may itself be a function that calls values_near.
  std::vector<double> beta(std::size_t(std::max(n, 0))), fv;
  std::vector<Vec3d> need;
  for (int i = 0; i < n; ++i) {
    beta[std::size_t(i)] = blend(xs[i], nullptr);
    if (beta[std::size_t(i)] < 1) need.push_back(xs[i]);
  }
  fv.resize(need.size());
  if (!need.empty()) f_.values_near(need.data(), int(need.size()), fv.data());
  std::vector<double> wv;
  winding_where_blended(xs, n, beta, wv, nullptr);
  std::size_t k = 0;
  for (int i = 0; i < n; ++i) {
    const double b = beta[std::size_t(i)];
    if (b <= 0) {
      out[i] = fv[k++];
      continue;
    }
    const double s = (0.5 - wv[std::size_t(i)]) * 2 * t2_;
    if (b >= 1) {
      out[i] = s;
      continue;
    }
    const double f = fv[k++];
    out[i] = std::isfinite(f) ? (1 - b) * f + b * s : s;
  }
}

Vec3d WindingClose::gradient(const Vec3d& x) const {
  Vec3d gbeta;
  const double beta = blend(x, &gbeta);
  if (beta <= 0) return f_.gradient(x);
  Vec3d gw;
  const double w = w_->evaluate(x, &gw);
  const Vec3d gs = -2 * t2_ * gw;
  if (beta >= 1) return gs;
  Vec3d gf;
  double f;
  if (mpu_) {
    f = mpu_->value_gradient(x, gf);  // one octree walk for both
  } else {
    f = f_.value(x);
    gf = f_.gradient(x);
  }
  if (!std::isfinite(f)) return gs;
  const double s = (0.5 - w) * 2 * t2_;
  return (1 - beta) * gf + beta * gs + (s - f) * gbeta;
}

void WindingClose::values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const {
  if (all_trusted(xs, n)) {  // beta = 0 throughout (see values_near)
    f_.values_gradients_near(xs, n, values, grads);
    return;
  }
  blended_values_gradients(xs, n, values, grads);
}

void WindingClose::blended_values_gradients(const Vec3d* xs, int n, double* values, Vec3d* grads) const {
  // As values_near, with f's values and gradients taken together.
  // Local buffers: f may itself be a function that calls *_near.
  const std::size_t m = std::size_t(std::max(n, 0));
  std::vector<double> beta(m), fv;
  std::vector<Vec3d> gbeta(m), need, gf;
  for (int i = 0; i < n; ++i) {
    beta[std::size_t(i)] = blend(xs[i], &gbeta[std::size_t(i)]);
    if (beta[std::size_t(i)] < 1) need.push_back(xs[i]);
  }
  fv.resize(need.size());
  gf.resize(need.size());
  if (!need.empty()) f_.values_gradients_near(need.data(), int(need.size()), fv.data(), gf.data());
  std::vector<double> wv;
  std::vector<Vec3d> gwv;
  winding_where_blended(xs, n, beta, wv, &gwv);
  std::size_t k = 0;
  for (int i = 0; i < n; ++i) {
    const double b = beta[std::size_t(i)];
    if (b <= 0) {
      values[i] = fv[k];
      grads[i] = gf[k++];
      continue;
    }
    const Vec3d& gw = gwv[std::size_t(i)];
    const double w = wv[std::size_t(i)];
    const double s = (0.5 - w) * 2 * t2_;
    const Vec3d gs = -2 * t2_ * gw;
    if (b >= 1) {
      values[i] = s;
      grads[i] = gs;
      continue;
    }
    const double f = fv[k];
    const Vec3d g = gf[k++];
    if (!std::isfinite(f)) {
      values[i] = s;
      grads[i] = gs;
      continue;
    }
    values[i] = (1 - b) * f + b * s;
    grads[i] = (1 - b) * g + b * gs + (s - f) * gbeta[std::size_t(i)];
  }
}

void WindingClose::gradients_near(const Vec3d* xs, int n, Vec3d* out) const {
  if (all_trusted(xs, n)) {  // beta = 0 throughout (see values_near)
    f_.gradients_near(xs, n, out);
    return;
  }
  // The blend's gradient needs f's values where it blends: both together.
  std::vector<double> values(std::size_t(std::max(n, 0)));
  blended_values_gradients(xs, n, values.data(), out);
}

}  // namespace station
