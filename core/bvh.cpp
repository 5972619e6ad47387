#include "core/bvh.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <string>

#include <Eigen/Geometry>

#include "core/error.h"

namespace station {

namespace {

constexpr int kBins = 16;          // SAH bins per axis
constexpr int kMaxLeafSize = 8;    // never more triangles than this in a leaf...
constexpr int kMinSplitSize = 2;   // ...and never split fewer than this
constexpr double kTraversalCost = 1.0;  // relative to one triangle test
constexpr int kMaxSahDepth = 64;  // deeper than this, median splits bound the depth
constexpr int kStackSize = 128;   // > kMaxSahDepth + log2(max faces)

// Box in float: the geometry is float, and half-size nodes keep traversal in cache.
struct Box {
  Vec3f lo = Vec3f::Constant(std::numeric_limits<float>::max());
  Vec3f hi = Vec3f::Constant(-std::numeric_limits<float>::max());
  void extend(const Vec3f& p) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  void extend(const Box& b) {
    lo = lo.cwiseMin(b.lo);
    hi = hi.cwiseMax(b.hi);
  }
  bool empty() const { return lo.x() > hi.x(); }
  float area() const {
    if (empty()) return 0.f;
    const Vec3f d = hi - lo;
    return 2.f * (d.x() * d.y() + d.y() * d.z() + d.z() * d.x());
  }
};

// 32 bytes. Leaves: count > 0, triangles [first, first+count). Inner nodes:
// count == 0, children are siblings in the array: left at first-1, right at `first`.
struct Node {
  Vec3f lo, hi;
  int first = 0;
  int count = 0;
};

struct Tri {
  Vec3f a, b, c;
};

// Squared distance from p to a box (0 inside).
inline double box_distance2(const Node& n, const Vec3d& p) {
  double d2 = 0;
  for (int k = 0; k < 3; ++k) {
    const double lo = n.lo[k], hi = n.hi[k];
    const double e = p[k] < lo ? lo - p[k] : (p[k] > hi ? p[k] - hi : 0.0);
    d2 += e * e;
  }
  return d2;
}

// Precomputed ray data for slab tests.
struct RayPre {
  Vec3d o, d, inv;
  RayPre(const Ray& r) : o(r.origin), d(r.direction) {
    for (int k = 0; k < 3; ++k) inv[k] = 1.0 / d[k];  // +-inf for axis-parallel rays
  }
};

// Slab test; returns the entry distance or +inf when the box is missed within
// [t_min, t_max]. The exit distance is inflated by a few ulps so rounding never
// culls a box whose triangle the (double) triangle test would still hit.
inline double slab_entry(const Node& n, const RayPre& r, double t_min, double t_max) {
  double t0 = t_min, t1 = t_max;
  for (int k = 0; k < 3; ++k) {
    double a = (double(n.lo[k]) - r.o[k]) * r.inv[k];
    double b = (double(n.hi[k]) - r.o[k]) * r.inv[k];
    if (std::isnan(a) || std::isnan(b)) {
      // Axis-parallel ray starting exactly on a slab plane: inside that slab.
      if (r.o[k] < n.lo[k] || r.o[k] > n.hi[k]) return std::numeric_limits<double>::infinity();
      continue;
    }
    if (a > b) std::swap(a, b);
    b *= 1.0 + 1e-12;
    t0 = a > t0 ? a : t0;
    t1 = b < t1 ? b : t1;
    if (t0 > t1) return std::numeric_limits<double>::infinity();
  }
  return t0;
}

// Möller–Trumbore in double precision. Barycentrics accept a hair outside the
// triangle so rays through shared edges never slip between neighbours.
inline bool ray_triangle(const Tri& tri, const RayPre& r, double t_min, double t_max,
                         double& t, double& u, double& v) {
  constexpr double kEdgeSlack = 1e-10;
  const Vec3d a = tri.a.cast<double>();
  const Vec3d e1 = tri.b.cast<double>() - a;
  const Vec3d e2 = tri.c.cast<double>() - a;
  const Vec3d p = r.d.cross(e2);
  const double det = e1.dot(p);
  if (det == 0.0 || !std::isfinite(det)) return false;
  const double inv_det = 1.0 / det;
  const Vec3d s = r.o - a;
  const double uu = s.dot(p) * inv_det;
  if (uu < -kEdgeSlack || uu > 1.0 + kEdgeSlack) return false;
  const Vec3d q = s.cross(e1);
  const double vv = r.d.dot(q) * inv_det;
  if (vv < -kEdgeSlack || uu + vv > 1.0 + kEdgeSlack) return false;
  const double tt = e2.dot(q) * inv_det;
  if (!(tt >= t_min && tt <= t_max)) return false;
  t = tt;
  u = uu;
  v = vv;
  return true;
}

// Closest point on triangle abc to p (Ericson, Real-Time Collision Detection
// §5.1.5, region by region). Returns barycentrics (u, v) of b and c.
Vec3d closest_on_segment(const Vec3d& p, const Vec3d& a, const Vec3d& b, double& s) {
  const Vec3d ab = b - a;
  const double len2 = ab.squaredNorm();
  s = len2 > 0 ? std::clamp((p - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
  return a + s * ab;
}

Vec3d closest_on_triangle(const Vec3d& p, const Vec3d& a, const Vec3d& b, const Vec3d& c,
                          double& u, double& v) {
  const Vec3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) {
    u = v = 0;
    return a;
  }
  const Vec3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) {
    u = 1;
    v = 0;
    return b;
  }
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0 && d1 - d3 > 0) {
    const double w = d1 / (d1 - d3);
    u = w;
    v = 0;
    return a + w * ab;
  }
  const Vec3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) {
    u = 0;
    v = 1;
    return c;
  }
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0 && d2 - d6 > 0) {
    const double w = d2 / (d2 - d6);
    u = 0;
    v = w;
    return a + w * ac;
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0 && (d4 - d3) + (d5 - d6) > 0) {
    const double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    u = 1 - w;
    v = w;
    return b + w * (c - b);
  }
  const double denom = va + vb + vc;
  if (denom > 0 && std::isfinite(denom)) {
    const double vv = vb / denom, ww = vc / denom;
    u = vv;
    v = ww;
    return a + vv * ab + ww * ac;
  }
  // Degenerate (zero-area) triangle: the closest of its three edges.
  double s0, s1, s2;
  const Vec3d q0 = closest_on_segment(p, a, b, s0);
  const Vec3d q1 = closest_on_segment(p, b, c, s1);
  const Vec3d q2 = closest_on_segment(p, a, c, s2);
  const double e0 = (q0 - p).squaredNorm(), e1 = (q1 - p).squaredNorm(),
               e2 = (q2 - p).squaredNorm();
  if (e0 <= e1 && e0 <= e2) {
    u = s0;
    v = 0;
    return q0;
  }
  if (e1 <= e2) {
    u = 1 - s1;
    v = s1;
    return q1;
  }
  u = 0;
  v = s2;
  return q2;
}

}  // namespace

struct TriangleBvh::Impl {
  std::vector<Node> nodes;
  std::vector<Tri> tris;       // in leaf order
  std::vector<int> face_ids;   // leaf order -> index into mesh.faces

  void build(const Mesh& mesh);
};

void TriangleBvh::Impl::build(const Mesh& mesh) {
  const int n = int(mesh.faces.size());
  std::vector<Box> boxes(n);
  std::vector<Vec3f> centroids(n);
  std::vector<int> order(n);
  for (int i = 0; i < n; ++i) {
    const Face& f = mesh.faces[i];
    for (int k = 0; k < 3; ++k) boxes[i].extend(mesh.vertices[f[k]]);
    centroids[i] = boxes[i].lo + 0.5f * (boxes[i].hi - boxes[i].lo);
    order[i] = i;
  }

  nodes.reserve(std::size_t(n) * 2);
  struct Task {
    int node, begin, end, depth;
  };
  std::vector<Task> stack;
  nodes.emplace_back();
  stack.push_back({0, 0, n, 0});
  while (!stack.empty()) {
    const Task task = stack.back();
    stack.pop_back();
    const int count = task.end - task.begin;
    Box bounds, cbounds;
    for (int i = task.begin; i < task.end; ++i) {
      bounds.extend(boxes[order[i]]);
      cbounds.extend(centroids[order[i]]);
    }
    nodes[task.node].lo = bounds.lo;
    nodes[task.node].hi = bounds.hi;
    auto make_leaf = [&] {
      nodes[task.node].first = task.begin;
      nodes[task.node].count = count;
    };
    if (count < kMinSplitSize) {
      make_leaf();
      continue;
    }

    // Binned SAH over the widest centroid axis (one axis keeps build O(F) per level;
    // the widest is nearly always the SAH winner anyway).
    const Vec3f extent = cbounds.hi - cbounds.lo;
    int axis = 0;
    if (extent.y() > extent[axis]) axis = 1;
    if (extent.z() > extent[axis]) axis = 2;
    int mid = -1;
    if (task.depth >= kMaxSahDepth && count > kMaxLeafSize) {
      // Pathological (e.g. exponentially spaced) input: object median split.
      mid = task.begin + count / 2;
      std::nth_element(order.begin() + task.begin, order.begin() + mid, order.begin() + task.end,
                       [&](int x, int y) { return centroids[x][axis] < centroids[y][axis]; });
    } else if (task.depth >= kMaxSahDepth) {
      make_leaf();
      continue;
    } else if (extent[axis] > 0.f) {
      std::array<Box, kBins> bin_box;
      std::array<int, kBins> bin_count{};
      const double lo = cbounds.lo[axis];
      const double scale = kBins / double(extent[axis]);  // double: extent may be tiny
      auto bin_of = [&](int tri) {
        const int b = int((double(centroids[tri][axis]) - lo) * scale);
        return std::clamp(b, 0, kBins - 1);
      };
      for (int i = task.begin; i < task.end; ++i) {
        const int b = bin_of(order[i]);
        bin_box[b].extend(boxes[order[i]]);
        ++bin_count[b];
      }
      // Sweep from the right to get suffix areas, then from the left.
      std::array<float, kBins> right_area{};
      std::array<int, kBins> right_count{};
      Box acc;
      int acc_n = 0;
      for (int b = kBins - 1; b > 0; --b) {
        acc.extend(bin_box[b]);
        acc_n += bin_count[b];
        right_area[b] = acc.area();
        right_count[b] = acc_n;
      }
      double best_cost = std::numeric_limits<double>::infinity();
      int best_split = -1;
      acc = Box();
      acc_n = 0;
      for (int b = 0; b < kBins - 1; ++b) {
        acc.extend(bin_box[b]);
        acc_n += bin_count[b];
        if (acc_n == 0 || right_count[b + 1] == 0) continue;
        const double cost = double(acc.area()) * acc_n + double(right_area[b + 1]) * right_count[b + 1];
        if (cost < best_cost) {
          best_cost = cost;
          best_split = b;
        }
      }
      const double parent_area = bounds.area();
      const double leaf_cost = count;
      const double split_cost =
          kTraversalCost + (parent_area > 0 ? best_cost / parent_area : leaf_cost);
      if (best_split >= 0 && (split_cost < leaf_cost || count > kMaxLeafSize)) {
        auto it = std::partition(order.begin() + task.begin, order.begin() + task.end,
                                 [&](int tri) { return bin_of(tri) <= best_split; });
        mid = int(it - order.begin());
      } else if (count <= kMaxLeafSize) {
        make_leaf();
        continue;
      }
    } else if (count <= kMaxLeafSize) {
      make_leaf();
      continue;
    }
    if (mid <= task.begin || mid >= task.end) {
      // Coincident centroids (or no usable bin split) in a big node: halve by index
      // so leaves stay bounded.
      mid = task.begin + count / 2;
    }
    const int left = int(nodes.size());
    nodes.emplace_back();
    const int right = int(nodes.size());
    nodes.emplace_back();
    nodes[task.node].first = right;
    nodes[task.node].count = 0;
    stack.push_back({right, mid, task.end, task.depth + 1});
    stack.push_back({left, task.begin, mid, task.depth + 1});
  }

  tris.resize(n);
  face_ids = order;
  for (int i = 0; i < n; ++i) {
    const Face& f = mesh.faces[order[i]];
    tris[i] = {mesh.vertices[f[0]], mesh.vertices[f[1]], mesh.vertices[f[2]]};
  }
}

TriangleBvh::TriangleBvh(const Mesh& mesh) : impl_(std::make_unique<Impl>()) {
  if (mesh.faces.empty()) throw InvalidInput("bvh: mesh has no faces");
  const long nv = long(mesh.vertices.size());
  for (std::size_t i = 0; i < mesh.faces.size(); ++i) {
    const Face& f = mesh.faces[i];
    for (int k = 0; k < 3; ++k)
      if (f[k] < 0 || f[k] >= nv)
        throw InvalidInput("bvh: face " + std::to_string(i) + " has vertex index " +
                           std::to_string(f[k]) + " outside [0, " + std::to_string(nv) + ")");
  }
  for (std::size_t i = 0; i < mesh.vertices.size(); ++i)
    if (!mesh.vertices[i].allFinite())
      throw InvalidInput("bvh: vertex " + std::to_string(i) + " is not finite");
  impl_->build(mesh);
}

TriangleBvh::~TriangleBvh() = default;
TriangleBvh::TriangleBvh(TriangleBvh&&) noexcept = default;
TriangleBvh& TriangleBvh::operator=(TriangleBvh&&) noexcept = default;

std::size_t TriangleBvh::triangle_count() const { return impl_->tris.size(); }

namespace {

// Shared front-to-back traversal; `any_hit` stops at the first hit.
template <bool kAnyHit>
bool traverse(const std::vector<Node>& nodes, const std::vector<Tri>& tris, const Ray& ray,
              RayHit& best) {
  constexpr double kMiss = std::numeric_limits<double>::infinity();
  if (!(ray.t_min <= ray.t_max)) return false;
  const RayPre r(ray);
  double t_best = ray.t_max;
  bool found = false;
  struct Entry {
    int node;
    double t_entry;
  };
  Entry stack[kStackSize];
  int top = 0;
  if (slab_entry(nodes[0], r, ray.t_min, t_best) == kMiss) return false;
  int current = 0;
  for (;;) {
    const Node& node = nodes[current];
    if (node.count > 0) {
      for (int i = node.first; i < node.first + node.count; ++i) {
        double t, u, v;
        if (ray_triangle(tris[i], r, ray.t_min, t_best, t, u, v)) {
          found = true;
          t_best = t;
          best.t = t;
          best.face = i;  // leaf-order index; the caller maps it
          best.u = u;
          best.v = v;
          if (kAnyHit) return true;
        }
      }
    } else {
      const int left = node.first - 1, right = node.first;
      const double tl = slab_entry(nodes[left], r, ray.t_min, t_best);
      const double tr = slab_entry(nodes[right], r, ray.t_min, t_best);
      if (tl != kMiss && tr != kMiss) {
        // Near child first; the far one waits on the stack with its entry distance.
        if (tl <= tr) {
          stack[top++] = {right, tr};
          current = left;
        } else {
          stack[top++] = {left, tl};
          current = right;
        }
        continue;
      }
      if (tl != kMiss || tr != kMiss) {
        current = tl != kMiss ? left : right;
        continue;
      }
    }
    // Pop, skipping boxes entered beyond the best hit found since they were pushed.
    while (top > 0 && stack[top - 1].t_entry > t_best) --top;
    if (top == 0) break;
    current = stack[--top].node;
  }
  return found;
}

}  // namespace

std::optional<RayHit> TriangleBvh::intersect(const Ray& ray) const {
  RayHit hit;
  if (!traverse<false>(impl_->nodes, impl_->tris, ray, hit)) return std::nullopt;
  hit.face = impl_->face_ids[hit.face];
  return hit;
}

bool TriangleBvh::occluded(const Ray& ray) const {
  RayHit hit;
  return traverse<true>(impl_->nodes, impl_->tris, ray, hit);
}

ClosestPoint TriangleBvh::closest_point(const Vec3d& p) const {
  const auto& nodes = impl_->nodes;
  const auto& tris = impl_->tris;
  ClosestPoint best;
  double best_d2 = std::numeric_limits<double>::infinity();
  int best_leaf_index = -1;
  // Branch and bound: visit the nearer child box first, drop boxes farther than
  // the best distance so far.
  struct Entry {
    int node;
    double d2;
  };
  Entry stack[kStackSize];
  int top = 0;
  stack[top++] = {0, box_distance2(nodes[0], p)};
  while (top > 0) {
    const Entry e = stack[--top];
    if (e.d2 >= best_d2) continue;
    const Node& node = nodes[e.node];
    if (node.count > 0) {
      for (int i = node.first; i < node.first + node.count; ++i) {
        double u, v;
        const Vec3d q = closest_on_triangle(p, tris[i].a.cast<double>(), tris[i].b.cast<double>(),
                                            tris[i].c.cast<double>(), u, v);
        const double d2 = (q - p).squaredNorm();
        if (d2 < best_d2) {
          best_d2 = d2;
          best_leaf_index = i;
          best.point = q;
          best.u = u;
          best.v = v;
        }
      }
      continue;
    }
    const int left = node.first - 1, right = node.first;
    const double dl = box_distance2(nodes[left], p), dr = box_distance2(nodes[right], p);
    // Push the far child first so the near one is popped next.
    const Entry near_e = dl <= dr ? Entry{left, dl} : Entry{right, dr};
    const Entry far_e = dl <= dr ? Entry{right, dr} : Entry{left, dl};
    if (far_e.d2 < best_d2 && top < kStackSize) stack[top++] = far_e;
    if (near_e.d2 < best_d2 && top < kStackSize) stack[top++] = near_e;
  }
  best.face = best_leaf_index >= 0 ? impl_->face_ids[best_leaf_index] : -1;
  best.distance = std::sqrt(best_d2);
  return best;
}

}  // namespace station
