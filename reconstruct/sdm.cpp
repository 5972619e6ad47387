// Self-organizing Deformable Model: phase 1 (competitive learning) and phase 2
// (energy minimisation). See reconstruct/sdm.h and docs/sdm.md.
#include "reconstruct/sdm.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <numeric>
#include <random>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>

#include "core/error.h"
#include "core/kdtree.h"
#include "core/normals.h"
#include "core/threads.h"
#include "reconstruct/detail/sdm_internal.h"

namespace station {
namespace sdm_detail {
namespace {

using Clock = std::chrono::steady_clock;
// Uniform grid over the vertices with O(1) moves (a doubly linked list per cell):
// the nearest-vertex index that is updated, not rebuilt, as vertices move.
// Vertices outside the box are kept in the nearest border cell; distances to a cell
// stay lower bounds for them (clamping into a box only brings a point closer to any
// query inside the box), so searches remain exact.
class VertexGrid {
 public:
  VertexGrid(const Aabb& box, float cell, const std::vector<Vec3f>& pos) : pos_(pos) {
    origin_ = box.min;
    cell_ = cell;
    inv_ = 1.f / cell;
    const Vec3f ext = box.max - box.min;
    n_[0] = std::max(1, int(std::ceil(ext.x() * inv_)));
    n_[1] = std::max(1, int(std::ceil(ext.y() * inv_)));
    n_[2] = std::max(1, int(std::ceil(ext.z() * inv_)));
    head_.assign(std::size_t(n_[0]) * n_[1] * n_[2], -1);
    const int nv = int(pos.size());
    next_.assign(nv, -1);
    prev_.assign(nv, -1);
    cell_of_.assign(nv, -1);
    for (int v = 0; v < nv; ++v) link(v, cell_index(pos[v]));
  }

  void update(int v) {
    const int c = cell_index(pos_[v]);
    if (c == cell_of_[v]) return;
    unlink(v);
    link(v, c);
  }

  /// Calls f(v) for every vertex in the cells overlapping the box [lo, hi].
  template <class F>
  void for_box(const Vec3f& lo, const Vec3f& hi, F f) const {
    int a[3], b[3];
    coords(lo, a);
    coords(hi, b);
    for (int z = a[2]; z <= b[2]; ++z)
      for (int y = a[1]; y <= b[1]; ++y)
        for (int x = a[0]; x <= b[0]; ++x)
          for (int v = head_[(std::size_t(z) * n_[1] + y) * n_[0] + x]; v >= 0; v = next_[v]) f(v);
  }

  /// Nearest vertex to q (Euclidean) among those with accept(v); -1 when none.
  template <class Accept>
  int nearest(const Vec3f& q, Accept accept, int max_shell = 4) const {
    int c[3];
    coords(q, c);
    int best = -1;
    float best_d2 = std::numeric_limits<float>::max();
    const int full = std::max({n_[0], n_[1], n_[2]});
    for (int s = 0; s <= std::min(max_shell, full); ++s) {
      for (int dz = -s; dz <= s; ++dz) {
        const int z = c[2] + dz;
        if (z < 0 || z >= n_[2]) continue;
        for (int dy = -s; dy <= s; ++dy) {
          const int y = c[1] + dy;
          if (y < 0 || y >= n_[1]) continue;
          const bool inner = std::abs(dz) != s && std::abs(dy) != s;
          for (int dx = -s; dx <= s; dx += (inner && s > 0) ? 2 * s : 1) {
            const int x = c[0] + dx;
            if (x < 0 || x >= n_[0]) continue;
            for (int v = head_[(std::size_t(z) * n_[1] + y) * n_[0] + x]; v >= 0; v = next_[v]) {
              const float d2 = (pos_[v] - q).squaredNorm();
              if (d2 < best_d2 && accept(v)) {
                best_d2 = d2;
                best = v;
              }
            }
          }
        }
      }
      // Unvisited vertices lie in shells > s: at least s cells away.
      const float bound = s * cell_;
      if (best >= 0 && best_d2 <= bound * bound) return best;
      if (s >= full) return best;
    }
    // Far away: scan everything (exact).
    best = -1;
    best_d2 = std::numeric_limits<float>::max();
    for (int v = 0; v < int(pos_.size()); ++v) {
      const float d2 = (pos_[v] - q).squaredNorm();
      if (d2 < best_d2 && accept(v)) {
        best_d2 = d2;
        best = v;
      }
    }
    return best;
  }

 private:
  void coords(const Vec3f& p, int c[3]) const {
    for (int k = 0; k < 3; ++k) {
      const float f = (p[k] - origin_[k]) * inv_;
      c[k] = std::isfinite(f) ? std::clamp(int(std::floor(f)), 0, n_[k] - 1) : 0;
    }
  }
  int cell_index(const Vec3f& p) const {
    int c[3];
    coords(p, c);
    return int((std::size_t(c[2]) * n_[1] + c[1]) * n_[0] + c[0]);
  }
  void link(int v, int c) {
    cell_of_[v] = c;
    prev_[v] = -1;
    next_[v] = head_[c];
    if (head_[c] >= 0) prev_[head_[c]] = v;
    head_[c] = v;
  }
  void unlink(int v) {
    const int c = cell_of_[v];
    if (prev_[v] >= 0)
      next_[prev_[v]] = next_[v];
    else
      head_[c] = next_[v];
    if (next_[v] >= 0) prev_[next_[v]] = prev_[v];
  }

  const std::vector<Vec3f>& pos_;
  Vec3f origin_;
  float cell_ = 1, inv_ = 1;
  int n_[3] = {1, 1, 1};
  std::vector<int> head_, next_, prev_, cell_of_;
};

struct Engine {
  const SdmParams& P;
  const Cloud& target;
  const std::vector<Face>& faces;
  const std::vector<Landmark>& landmarks;
  std::vector<char> pinned;
  std::vector<int> landmark_of;  // per vertex: its landmark (phase 2), or -1
  Adjacency adj;
  std::vector<Vec3f> pos;
  Cloud sc;                  // phase 1's control points: the target or a random subset of it
  std::vector<int> sc_index;  // their indices in the target
  std::unique_ptr<PointIndex> cp_index;  // over sc
  std::vector<int> nearest_cp;  // per vertex: its nearest control point (maybe stale, see som)
  float resee = 0;              // anchors re-seek their nearest control point after sliding this far
  std::vector<char> anchor;
  std::vector<float> free_lb;
  std::vector<float> anchor_slide;  // per anchor: distance slid since its nearest control point was sought  // per free vertex: lower bound of its distance to the cloud
  std::unique_ptr<VertexGrid> grid;
  float spacing = 0, tau = 0, diag = 0;
  float theta = 0;  // theta_e in the target's units (set at the start of phase 2)
  int threads = 1;

  Engine(const SdmParams& p, const Cloud& t, const std::vector<Face>& f,
         const std::vector<Landmark>& l, const std::vector<char>& pin)
      : P(p), target(t), faces(f), landmarks(l), pinned(pin) {}

  void refresh_nearest_cp() {
    tbb::parallel_for(tbb::blocked_range<int>(0, int(pos.size()), 256), [&](const tbb::blocked_range<int>& r) {
      for (int v = r.begin(); v < r.end(); ++v) nearest_cp[v] = cp_index->nearest(pos[v]).first;
    });
  }

  // -------------------------------------------------------------------------
  // Phase 1.
  void som(int T, SdmDiagnostics& diag_out, const SdmProgress& progress) {
    const int nv = int(pos.size());
    std::mt19937_64 rng(P.seed);
    std::uniform_real_distribution<double> uni(0.0, 1.0);
    // Selection probabilities: cumulative weights, drawn by binary search.
    std::vector<double> cum;
    std::vector<float> weights;
    if (!P.selection_weights.empty())
      for (int i : sc_index) weights.push_back(P.selection_weights[i]);
    if (weights.empty() && P.curvature_gain > 0) weights = curvature_weights();
    if (!weights.empty()) {
      cum.resize(weights.size());
      double s = 0;
      for (std::size_t i = 0; i < weights.size(); ++i) cum[i] = (s += weights[i]);
    }
    const int ncp = int(sc.size());
    const float sigma_s = P.sigma_start > 0 ? P.sigma_start : std::max(1.f, std::sqrt(float(nv)) / 8.f);
    const float sigma_f = std::min(P.sigma_final, sigma_s);
    const float cut = std::sqrt(-2.f * std::log(std::clamp(P.lambda_cutoff, 1e-6f, 0.999f)));
    std::vector<int> stamp(nv, -1), queue, hops(nv, 0);
    queue.reserve(nv);
    int skipped = 0;
    const int refresh_every = std::max(1000, T / 16);
    for (int t = 0; t < T; ++t) {
      if (t > 0 && t % refresh_every == 0) {
        refresh_nearest_cp();
        for (int v = 0; v < nv; ++v)
          if (!anchor[v]) free_lb[v] = (pos[v] - sc.points[nearest_cp[v]]).norm();
        if (progress) progress("som", double(t) / T);
      }
      const double frac = double(t) / T;
      const float eps = P.eps_start * std::pow(P.eps_final / P.eps_start, float(frac));
      const float sigma = sigma_s * std::pow(sigma_f / sigma_s, float(frac));
      // Draw a control point (or a landmark) and find the winner.
      Vec3f p;
      int k = -1;
      if (!landmarks.empty() && uni(rng) < P.landmark_probability) {
        const auto& l = landmarks[std::min<std::size_t>(landmarks.size() - 1,
                                                        std::size_t(uni(rng) * landmarks.size()))];
        p = l.point;
        k = l.vertex;
      } else {
        int idx;
        if (cum.empty())
          idx = std::min(ncp - 1, int(uni(rng) * ncp));
        else
          idx = std::min<int>(ncp - 1, int(std::upper_bound(cum.begin(), cum.end(),
                                                             uni(rng) * cum.back()) -
                                           cum.begin()));
        p = sc.points[idx];
        const Vec3f np = sc.normals[idx];
        k = grid->nearest(p, [&](int v) { return np.dot(pos[v] - p) >= 0.f; });
      }
      if (k < 0) {
        ++skipped;
        continue;
      }
      // Breadth-first neighbourhood up to the cut-off.
      const int max_hops = int(sigma * cut);
      queue.clear();
      queue.push_back(k);
      stamp[k] = t;
      hops[k] = 0;
      for (std::size_t qi = 0; qi < queue.size(); ++qi) {
        const int u = queue[qi];
        if (hops[u] >= max_hops) continue;
        for (int j = adj.ring_start[u]; j < adj.ring_start[u + 1]; ++j) {
          const int w = adj.ring[j];
          if (stamp[w] == t) continue;
          stamp[w] = t;
          hops[w] = hops[u] + 1;
          queue.push_back(w);
        }
      }
      const Vec3f vk = pos[k];
      for (int i : queue) {
        if (pinned[i]) continue;
        const float L = float(hops[i]);
        const float lam = std::exp(-0.5f * (L / sigma) * (L / sigma));
        const float step = eps * lam;
        Vec3f& v = pos[i];
        if (!anchor[i]) {
          const Vec3f dv = step * ((p - v) + P.alpha * (v - vk));  // eq. 10
          v += dv;
          // The distance to the cloud is 1-Lipschitz: only query it when the bound
          // says the vertex may have come within tau.
          free_lb[i] -= dv.norm();
          if (free_lb[i] < tau) {
            const auto [q, d] = cp_index->nearest(v);
            nearest_cp[i] = q;
            free_lb[i] = d;
            if (d < tau) anchor[i] = 1;
          }
        } else {
          // Geodesic step approximated: move along the tangent plane at the nearest
          // control point, then project back onto the tangent plane there.
          // The nearest control point (whose tangent plane stands for the surface) is
          // re-sought once the vertex has slid `resee` since the last search.
          const Vec3f& n = sc.normals[nearest_cp[i]];
          Vec3f d = p - v;
          d -= n * n.dot(d);
          v += step * d;
          anchor_slide[i] += step * d.norm();
          if (anchor_slide[i] > resee) {
            nearest_cp[i] = cp_index->nearest(v).first;
            anchor_slide[i] = 0;
          }
          const int q = nearest_cp[i];
          const Vec3f& n2 = sc.normals[q];
          v -= n2 * n2.dot(v - sc.points[q]);
        }
        grid->update(i);
      }
    }
    diag_out.som_iterations = T;
    diag_out.som_skipped = skipped;
    diag_out.anchors = int(std::count(anchor.begin(), anchor.end(), 1));
  }

  std::vector<float> curvature_weights() const {
    const int ncp = int(sc.size());
    std::vector<float> var(ncp, 0.f);
    tbb::parallel_for(tbb::blocked_range<int>(0, ncp, 512), [&](const tbb::blocked_range<int>& r) {
      for (int i = r.begin(); i < r.end(); ++i) {
        const auto nn = cp_index->knn(sc.points[i], 12);
        Vec3d mean = Vec3d::Zero();
        for (auto& [j, d] : nn) mean += sc.points[j].cast<double>();
        mean /= double(nn.size());
        Eigen::Matrix3d C = Eigen::Matrix3d::Zero();
        for (auto& [j, d] : nn) {
          const Vec3d y = sc.points[j].cast<double>() - mean;
          C += y * y.transpose();
        }
        const double tr = C.trace();
        const double lmin = tr > 0 ? (C / tr).selfadjointView<Eigen::Lower>().eigenvalues()(0) : 0;
        var[i] = float(std::max(0.0, lmin));
      }
    });
    const double mean = std::accumulate(var.begin(), var.end(), 0.0) / std::max(1, ncp);
    std::vector<float> w(ncp, 1.f);
    if (mean > 0)
      for (int i = 0; i < ncp; ++i) w[i] = 1.f + P.curvature_gain * float(var[i] / mean);
    return w;
  }

  // -------------------------------------------------------------------------
  // Phase 2.
  struct Assignment {
    std::vector<int> owner;             // per control point: nearest vertex
    std::vector<int> omega_start, omega;  // control points of each vertex
    std::vector<float> dist;            // per control point: distance to the owner's faces
    double mean_distance = 0;
  };

  Assignment assign() const {
    const int ncp = int(target.size()), nv = int(pos.size());
    Assignment a;
    a.owner.assign(ncp, -1);
    std::vector<float>& dist = a.dist;
    dist.assign(ncp, 0.f);
    // A k-d tree over the vertices as they are (built per call, milliseconds): exact
    // nearest vertex in O(log n) even for points far from the mesh, where the vertex
    // grid falls back to a full scan (e.g. a mesh mapped onto a surface around it).
    const PointIndex vertices(pos);
    tbb::parallel_for(tbb::blocked_range<int>(0, ncp, 512), [&](const tbb::blocked_range<int>& r) {
      for (int i = r.begin(); i < r.end(); ++i) {
        const Vec3f& p = target.points[i];
        const int v = vertices.nearest(p).first;
        a.owner[i] = v;
        float best = std::numeric_limits<float>::max();
        for (int j = adj.vf_start[v]; j < adj.vf_start[v + 1]; ++j) {
          const Face& f = faces[adj.vf[j]];
          best = std::min(best, point_triangle_dist2(p, pos[f[0]], pos[f[1]], pos[f[2]]));
        }
        dist[i] = std::sqrt(best);
      }
    });
    a.omega_start.assign(nv + 1, 0);
    for (int o : a.owner) ++a.omega_start[o + 1];
    for (int v = 0; v < nv; ++v) a.omega_start[v + 1] += a.omega_start[v];
    a.omega.resize(ncp);
    std::vector<int> fill(a.omega_start.begin(), a.omega_start.end() - 1);
    for (int i = 0; i < ncp; ++i) a.omega[fill[a.owner[i]]++] = i;
    double s = 0;
    for (float d : dist) s += d;
    a.mean_distance = ncp ? s / ncp : 0;
    return a;
  }

  std::vector<std::vector<int>> colour_classes() const {
    const int nv = int(pos.size());
    std::vector<int> colour(nv, -1);
    std::vector<char> used;
    int ncol = 0;
    // Distance-2 colouring: vertices of one class share no neighbour, so their moves
    // (computed in parallel against the same positions) never touch a common face.
    for (int v = 0; v < nv; ++v) {
      used.assign(ncol + 1, 0);
      for (int j = adj.ring_start[v]; j < adj.ring_start[v + 1]; ++j) {
        const int u = adj.ring[j];
        if (colour[u] >= 0) used[colour[u]] = 1;
        for (int k = adj.ring_start[u]; k < adj.ring_start[u + 1]; ++k)
          if (colour[adj.ring[k]] >= 0) used[colour[adj.ring[k]]] = 1;
      }
      int c = 0;
      while (used[c]) ++c;
      colour[v] = c;
      ncol = std::max(ncol, c + 1);
    }
    std::vector<std::vector<int>> classes(ncol);
    for (int v = 0; v < nv; ++v) classes[colour[v]].push_back(v);
    return classes;
  }

  // Number of faces at v (with v moved to c) facing against the reference normal.
  int bad_faces(int v, const Vec3f& c, const Vec3f& ref) const {
    int bad = 0;
    for (int j = adj.vf_start[v]; j < adj.vf_start[v + 1]; ++j) {
      const Face& f = faces[adj.vf[j]];
      const Vec3f a = f[0] == v ? c : pos[f[0]];
      const Vec3f b = f[1] == v ? c : pos[f[1]];
      const Vec3f d = f[2] == v ? c : pos[f[2]];
      const Vec3f n = (b - a).cross(d - a);
      const float len = n.norm();
      if (!(len > 1e-12f * diag * diag) || n.dot(ref) < 0.2f * len) ++bad;
    }
    return bad;
  }

  // Sum of squared point-to-face distances over v's faces with v at c; stops once the
  // sum reaches `bound` (terms are non-negative, so a candidate that reaches the best
  // energy so far cannot beat it: the comparison e < bound gives the same answer).
  float energy(int v, const Vec3f& c, const int* pts, int npts,
               float bound = std::numeric_limits<float>::infinity()) const {
    float e = 0;
    for (int j = adj.vf_start[v]; j < adj.vf_start[v + 1]; ++j) {
      const Face& f = faces[adj.vf[j]];
      const Vec3f a = f[0] == v ? c : pos[f[0]];
      const Vec3f b = f[1] == v ? c : pos[f[1]];
      const Vec3f d = f[2] == v ? c : pos[f[2]];
      for (int k = 0; k < npts; ++k) e += point_triangle_dist2(target.points[pts[k]], a, b, d);
      if (e >= bound) return e;
    }
    return e;
  }

  // Whether the faces at v, with v moved to c, would cut another face: faces at the
  // vertices found (vertex grid) within the box of v's faces grown by their longest
  // edge (any face crossing them has a vertex there, given edges of similar length).
  bool crosses_nearby(int v, const Vec3f& c) const {
    struct Near {
      int face;
      Vec3f lo, hi;
    };
    thread_local std::vector<Near> near_faces;
    thread_local std::vector<std::uint32_t> seen;  // per face: the last call that saw it
    thread_local std::uint32_t call = 0;
    if (seen.size() != faces.size()) seen.assign(faces.size(), 0), call = 0;
    if (++call == 0) std::fill(seen.begin(), seen.end(), 0), call = 1;
    Vec3f lo = c, hi = c;
    float longest = 0;
    for (int j = adj.ring_start[v]; j < adj.ring_start[v + 1]; ++j) {
      const Vec3f& u = pos[adj.ring[j]];
      lo = lo.cwiseMin(u);
      hi = hi.cwiseMax(u);
      longest = std::max(longest, (u - c).norm());
    }
    const Vec3f pad = Vec3f::Constant(longest);
    // Each face once, only those meeting the moved fan's box (lo, hi) and not at v:
    // the same set of pairs as testing every face found, so the same answer.
    near_faces.clear();
    grid->for_box(lo - pad, hi + pad, [&](int u) {
      for (int j = adj.vf_start[u]; j < adj.vf_start[u + 1]; ++j) {
        const int g = adj.vf[j];
        if (seen[g] == call) continue;
        seen[g] = call;
        const Face& B = faces[g];
        if (B[0] == v || B[1] == v || B[2] == v) continue;
        const Vec3f &b0 = pos[B[0]], &b1 = pos[B[1]], &b2 = pos[B[2]];
        const Vec3f blo = b0.cwiseMin(b1).cwiseMin(b2), bhi = b0.cwiseMax(b1).cwiseMax(b2);
        if ((blo.array() > hi.array()).any() || (bhi.array() < lo.array()).any()) continue;
        near_faces.push_back({g, blo, bhi});
      }
    });
    for (int j = adj.vf_start[v]; j < adj.vf_start[v + 1]; ++j) {
      const Face& A = faces[adj.vf[j]];
      const Vec3f a[3] = {A[0] == v ? c : pos[A[0]], A[1] == v ? c : pos[A[1]], A[2] == v ? c : pos[A[2]]};
      const Vec3f alo = a[0].cwiseMin(a[1]).cwiseMin(a[2]), ahi = a[0].cwiseMax(a[1]).cwiseMax(a[2]);
      for (const Near& n : near_faces) {
        if ((n.lo.array() > ahi.array()).any() || (n.hi.array() < alo.array()).any()) continue;
        const Face& B = faces[n.face];
        const Vec3f b[3] = {pos[B[0]], pos[B[1]], pos[B[2]]};
        if (faces_intersect(A, B, a, b)) return true;
      }
    }
    return false;
  }

  Vec3f best_move(int v, const Assignment& a) const {
    const Vec3f cur = pos[v];
    // Reference orientation: the area-weighted normal of the ring as it is.
    Vec3f ref = Vec3f::Zero();
    Vec3f centroid = Vec3f::Zero();
    for (int j = adj.vf_start[v]; j < adj.vf_start[v + 1]; ++j) {
      const Face& f = faces[adj.vf[j]];
      ref += (pos[f[1]] - pos[f[0]]).cross(pos[f[2]] - pos[f[0]]);
    }
    const int rs = adj.ring_start[v], re = adj.ring_start[v + 1];
    float ring_edge2 = 0;
    for (int j = rs; j < re; ++j) {
      centroid += pos[adj.ring[j]];
      ring_edge2 = std::max(ring_edge2, (pos[adj.ring[j]] - cur).squaredNorm());
    }
    if (re > rs) centroid /= float(re - rs);
    if (ref.norm() > 0) ref.normalize();
    int cur_bad = bad_faces(v, cur, ref);
    Vec3f best = cur;
    if (landmark_of[v] >= 0) {
      // A landmark vertex goes as close to its point as it can without folding a face
      // or cutting another (phase 2 keeps it there; fold repair may have moved it).
      const Vec3f target_point = landmarks[landmark_of[v]].point;
      for (float w : {1.f, 0.75f, 0.5f, 0.25f}) {
        const Vec3f c = cur + w * (target_point - cur);
        if (bad_faces(v, c, ref) <= cur_bad && !crosses_nearby(v, c)) return c;
      }
      return cur;
    }
    const int os = a.omega_start[v], oe = a.omega_start[v + 1], no = oe - os;
    bool fitted = false;
    if (no > 0) {
      double m = 0;
      for (int k = os; k < oe; ++k) m += a.dist[a.omega[k]];
      fitted = m / no < 0.5 * theta;
    }
    if (no > 0 && !fitted) {
      // Energy over an evenly spread subset of Omega_i (at most 16 points).
      constexpr int kMaxEnergyPoints = 12;
      int pts[kMaxEnergyPoints];
      const int ne = std::min(no, kMaxEnergyPoints);
      for (int k = 0; k < ne; ++k) pts[k] = a.omega[os + int(std::int64_t(k) * no / ne)];
      float best_e = energy(v, cur, pts, ne);
      const int nc = std::min(no, std::max(1, P.max_candidates));
      Vec3f mean = Vec3f::Zero();
      for (int k = os; k < oe; ++k) mean += target.points[a.omega[k]];
      mean /= float(no);
      for (int k = 0; k <= nc; ++k) {
        const Vec3f pj = k == nc ? mean : target.points[a.omega[os + int(std::int64_t(k) * no / nc)]];
        for (float w : P.steps) {
          const Vec3f c = cur + w * (pj - cur);  // eq. 19
          const float e = energy(v, c, pts, ne, best_e);
          if (e < best_e) {
            const int b = bad_faces(v, c, ref);
            if (b <= cur_bad) best_e = e, best = c;
          }
        }
      }
    } else if (no == 0 && P.membrane > 0) {
      const Vec3f c = cur + P.membrane * (centroid - cur);
      if (bad_faces(v, c, ref) <= cur_bad) best = c;
    }
    if (P.relax > 0) {
      Vec3f d = centroid - best;
      d -= ref * ref.dot(d);
      const Vec3f c = best + P.relax * d;
      if (bad_faces(v, c, ref) <= bad_faces(v, best, ref)) best = c;
    }
    // Moves far shorter than the fan's edges cannot reach another sheet unless it is
    // already about to touch; those are left to the final intersection check.
    if (best != cur && (best - cur).squaredNorm() > 1e-4f * ring_edge2 && crosses_nearby(v, best))
      return cur;
    return best;
  }

  // Fold repair (not in the paper): the vertices of folded faces and their rings are
  // moved to their neighbours' centroid (umbrella smoothing) until no face is folded
  // or `iterations` passes are spent. Returns the folded faces left.
  // Umbrella smoothing of the marked vertices (one pass, independent sets in turn).
  void smooth_marked(const std::vector<std::vector<int>>& classes, const std::vector<char>& mark,
                     std::vector<Vec3f>& next) {
    for (const auto& cls : classes) {
      tbb::parallel_for(tbb::blocked_range<std::size_t>(0, cls.size(), 256), [&](const auto& r) {
        for (std::size_t i = r.begin(); i < r.end(); ++i) {
          const int v = cls[i];
          if (!mark[v] || pinned[v]) continue;
          Vec3f c = Vec3f::Zero();
          const int rs = adj.ring_start[v], re = adj.ring_start[v + 1];
          for (int j = rs; j < re; ++j) c += pos[adj.ring[j]];
          if (re > rs) next[v] = c / float(re - rs);
        }
      });
      for (int v : cls)
        if (mark[v] && !pinned[v]) {
          pos[v] = next[v];
          grid->update(v);
        }
    }
  }

  void grow(std::vector<char>& mark, int rings) const {
    for (int g = 0; g < rings; ++g) {
      std::vector<char> m2 = mark;
      for (int v = 0; v < int(mark.size()); ++v)
        if (mark[v])
          for (int j = adj.ring_start[v]; j < adj.ring_start[v + 1]; ++j) m2[adj.ring[j]] = 1;
      mark.swap(m2);
    }
  }

  // Self-intersection repair (not in the paper): the vertices of intersecting faces
  // and two rings around them are smoothed, then folds repaired, until none is left
  // or `iterations` rounds are spent. Returns the intersecting pairs left.
  int repair_intersections(const std::vector<std::vector<int>>& classes, int iterations) {
    std::vector<char> mark(pos.size());
    std::vector<Vec3f> next(pos.size());
    for (int it = 0;; ++it) {
      const auto pairs = self_intersecting_pairs(pos, faces);
      if (pairs.empty() || it == iterations) return int(pairs.size());
      std::fill(mark.begin(), mark.end(), 0);
      for (const auto& [a, b] : pairs)
        for (int k = 0; k < 3; ++k) mark[faces[a][k]] = mark[faces[b][k]] = 1;
      grow(mark, 1 + it / 3);
      for (int pass = 0; pass < 2; ++pass) smooth_marked(classes, mark, next);
      repair_folds(classes, P.repair_iterations);
    }
  }

  int repair_folds(const std::vector<std::vector<int>>& classes, int iterations) {
    const int nf = int(faces.size()), nv = int(pos.size());
    std::vector<Vec3f> fn(nf), vn(nv);
    std::vector<char> mark(nv);
    std::vector<Vec3f> next(nv);
    int folded = 0;
    for (int it = 0; it <= iterations; ++it) {
      for (int fi = 0; fi < nf; ++fi) {
        const Face& f = faces[fi];
        const Vec3f n = (pos[f[1]] - pos[f[0]]).cross(pos[f[2]] - pos[f[0]]);
        const float l = n.norm();
        fn[fi] = l > 0 ? Vec3f(n / l) : Vec3f::Zero();
      }
      std::fill(mark.begin(), mark.end(), 0);
      std::fill(vn.begin(), vn.end(), Vec3f::Zero());
      for (int fi = 0; fi < nf; ++fi)
        for (int k = 0; k < 3; ++k) vn[faces[fi][k]] += fn[fi];
      folded = 0;
      for (int fi = 0; fi < nf; ++fi) {
        const Face& f = faces[fi];
        if (face_folded(fn[fi], vn[f[0]] + vn[f[1]] + vn[f[2]])) {
          ++folded;
          for (int k = 0; k < 3; ++k) mark[faces[fi][k]] = 1;
        }
      }
      if (folded == 0 || it == iterations) break;
      grow(mark, 1 + (it >= iterations / 2));
      smooth_marked(classes, mark, next);
    }
    return folded;
  }

  // Phase-2 rounds until D < theta_e, max_rounds, or two stalled rounds; ends in the
  // best state seen. Returns the rounds run; D in dg.mean_distance.
  int run_rounds(int max_rounds, const std::vector<std::vector<int>>& classes, SdmDiagnostics& dg,
                 const SdmProgress& progress) {
    double prev = std::numeric_limits<double>::max();
    std::vector<Vec3f> next(pos.size());
    std::vector<Vec3f> best_pos = pos;
    double best_d = std::numeric_limits<double>::max();
    int rounds = 0, stalled = 0;
    for (;; ++rounds) {
      const Assignment a = assign();
      if (a.mean_distance < best_d) {
        best_d = a.mean_distance;
        best_pos = pos;
      }
      dg.mean_distance = a.mean_distance;
      if (progress) progress("energy", std::min(1.0, double(rounds) / std::max(1, max_rounds)));
      if (a.mean_distance < theta || rounds >= max_rounds) break;
      // Stop after two rounds in a row that gain less than min_improvement.
      stalled = (rounds > 0 && prev - a.mean_distance < P.min_improvement * prev) ? stalled + 1 : 0;
      if (stalled >= 2) break;
      prev = a.mean_distance;
      for (const auto& cls : classes) {
        tbb::parallel_for(tbb::blocked_range<std::size_t>(0, cls.size(), 64), [&](const auto& r) {
          for (std::size_t i = r.begin(); i < r.end(); ++i) {
            const int v = cls[i];
            next[v] = pinned[v] ? pos[v] : best_move(v, a);
          }
        });
        for (int v : cls) {
          pos[v] = next[v];
          grid->update(v);
        }
      }
      repair_folds(classes, P.repair_iterations);
    }
    // Keep the best state seen (the last round's moves may have made D worse).
    if (dg.mean_distance > best_d) {
      pos = best_pos;
      for (int v = 0; v < int(pos.size()); ++v) grid->update(v);
      dg.mean_distance = best_d;
    }
    return rounds;
  }

  void energy_phase(SdmDiagnostics& dg, const SdmProgress& progress) {
    const auto classes = colour_classes();
    dg.colours = int(classes.size());
    double edge = 0;
    for (const Face& f : faces) edge += (pos[f[0]] - pos[f[1]]).norm();
    theta = float(P.theta_e * edge / std::max<std::size_t>(1, faces.size()));
    dg.distance_after_som = assign().mean_distance;
    repair_folds(classes, P.repair_iterations);
    repair_intersections(classes, P.repair_iterations);
    int rounds = run_rounds(P.max_energy_rounds, classes, dg, progress);
    // Intersections repaired by smoothing, then a few rounds to bring the smoothed
    // parts back onto the target; twice at most.
    for (int k = 0; k < 2; ++k) {
      if (self_intersecting_pairs(pos, faces).empty()) break;
      repair_intersections(classes, P.repair_iterations);
      rounds += run_rounds(5, classes, dg, progress);
    }
    dg.self_intersections = repair_intersections(classes, P.repair_iterations);
    dg.mean_distance = assign().mean_distance;
    dg.energy_rounds = rounds;
  }
};

}  // namespace

SdmResult run_sdm(const Mesh& initial, const Cloud& target, const SdmParams& params,
                  const std::vector<Landmark>& landmarks, const std::vector<char>& pinned,
                  const SdmProgress& progress, SdmDiagnostics dg, bool run_som) {
  const auto t0 = Clock::now();
  Engine E(params, target, initial.faces, landmarks, pinned);
  const int nv = int(initial.vertices.size());
  const int ncp = int(target.size());
  E.pos = initial.vertices;
  E.adj = build_adjacency(nv, initial.faces);
  tbb::task_arena arena(params.threads > 0 ? params.threads : tbb::task_arena::automatic);
  arena.execute([&] {
    // Phase 1 runs on at most som_points control points (a seeded random subset).
    const int som_max = params.som_points > 0 ? params.som_points : 8 * nv;
    E.sc_index.resize(ncp);
    std::iota(E.sc_index.begin(), E.sc_index.end(), 0);
    if (ncp > som_max) {
      std::mt19937_64 rng(params.seed * 7919u + 17u);
      for (int i = 0; i < som_max; ++i) {
        std::uniform_int_distribution<int> pick(i, ncp - 1);
        std::swap(E.sc_index[i], E.sc_index[pick(rng)]);
      }
      E.sc_index.resize(som_max);
      std::sort(E.sc_index.begin(), E.sc_index.end());
    }
    for (int i : E.sc_index) {
      E.sc.points.push_back(target.points[i]);
      E.sc.normals.push_back(target.normals[i]);
    }
    const int nsc = int(E.sc.size());
    E.cp_index = std::make_unique<PointIndex>(E.sc.points);
    // Control-point spacing (mean nearest-neighbour distance over a spread subset).
    const int ns = std::min(nsc, 4000);
    double sum = 0;
    for (int s = 0; s < ns; ++s) {
      const auto nn = E.cp_index->knn(E.sc.points[std::size_t(std::int64_t(s) * nsc / ns)], 2);
      if (nn.size() == 2) sum += nn[1].second;
    }
    E.spacing = float(sum / std::max(1, ns));
    E.tau = params.tau_factor * E.spacing;
    const Aabb tbox = bounding_box(target.points);
    E.diag = tbox.diagonal();
    dg.spacing = E.spacing;
    dg.tau = E.tau;
    dg.diagonal = E.diag;
    E.nearest_cp.assign(nv, 0);
    E.refresh_nearest_cp();
    E.anchor.assign(nv, 0);
    E.landmark_of.assign(nv, -1);
    E.free_lb.resize(nv);
    E.anchor_slide.assign(nv, 0.f);
    for (int v = 0; v < nv; ++v) E.free_lb[v] = (E.pos[v] - E.sc.points[E.nearest_cp[v]]).norm();
    // Vertex grid over target and template, cell about 1.5 expected edge lengths.
    Aabb box = tbox;
    for (const Vec3f& v : E.pos) box.extend(v);
    const Vec3f pad = Vec3f::Constant(0.02f * box.diagonal() + 1e-6f);
    box.min -= pad;
    box.max += pad;
    const double area = 2.0 * nsc * double(E.spacing) * E.spacing;
    const float edge = float(1.5 * std::sqrt(area / std::max(1, nv)));
    const float bd = box.diagonal();
    const float cell = std::clamp(edge, bd / 200.f, bd / 8.f);
    E.grid = std::make_unique<VertexGrid>(box, cell, E.pos);
    E.resee = std::max(4.f * E.spacing, 0.2f * edge / 1.5f);

    const auto t1 = Clock::now();
    // Landmark draws come on top of the control-point draws.
    const double lm_share = landmarks.empty() ? 0.0 : std::min(0.9f, params.landmark_probability);
    const int T = params.som_iterations > 0 ? params.som_iterations
                                            : int(8.0 * nv / (1.0 - lm_share));
    if (run_som) E.som(T, dg, progress);
    dg.seconds_som = seconds_since(t1);
    // Landmarks: pinned on their points for phase 2. The vertex's neighbourhood is
    // carried along (translated by the vertex's offset, weighted by a Gaussian of
    // sigma = 2 hops) so that the snap does not fold the faces around it.
    {
      std::vector<int> hop(nv, -1), queue;
      for (const auto& l : landmarks) {
        const Vec3f offset = l.point - E.pos[l.vertex];
        std::fill(hop.begin(), hop.end(), -1);
        queue.assign(1, l.vertex);
        hop[l.vertex] = 0;
        for (std::size_t q = 0; q < queue.size(); ++q) {
          const int u = queue[q];
          if (hop[u] >= 6) continue;
          for (int j = E.adj.ring_start[u]; j < E.adj.ring_start[u + 1]; ++j)
            if (hop[E.adj.ring[j]] < 0) {
              hop[E.adj.ring[j]] = hop[u] + 1;
              queue.push_back(E.adj.ring[j]);
            }
        }
        for (int u : queue) {
          if (E.pinned[u]) continue;
          const float h = hop[u] / 2.f;
          E.pos[u] += std::exp(-0.5f * h * h) * offset;
          E.grid->update(u);
        }
        E.pos[l.vertex] = l.point;
        E.grid->update(l.vertex);
        E.landmark_of[l.vertex] = int(&l - landmarks.data());
      }
    }
    const auto t2 = Clock::now();
    E.energy_phase(dg, progress);
    dg.seconds_energy = seconds_since(t2);
  });
  SdmResult res;
  res.mesh.vertices = std::move(E.pos);
  res.mesh.faces = initial.faces;
  res.mesh.normals = vertex_normals(res.mesh);
  dg.flipped_faces = count_folded_faces(res.mesh);
  dg.seconds_total = seconds_since(t0);
  res.diagnostics = dg;
  return res;
}

}  // namespace sdm_detail

namespace {

void check_params(const SdmParams& p) {
  auto bad = [](const std::string& what) { throw InvalidInput("sdm: " + what); };
  if (p.som_iterations < 0) bad("som_iterations < 0");
  if (!(p.eps_start > 0 && p.eps_start <= 1 && p.eps_final > 0 && p.eps_final <= 1))
    bad("learning rates must be in (0, 1]");
  if (!(p.sigma_start >= 0 && p.sigma_final > 0)) bad("sigma_final must be > 0, sigma_start >= 0");
  if (!(p.lambda_cutoff > 0 && p.lambda_cutoff < 1)) bad("lambda_cutoff must be in (0, 1)");
  if (!(p.alpha >= 0 && p.alpha <= 1)) bad("alpha must be in [0, 1]");
  if (!(p.tau_factor > 0)) bad("tau_factor must be > 0");
  if (!(p.theta_e >= 0)) bad("theta_e must be >= 0");
  if (p.max_energy_rounds < 0) bad("max_energy_rounds < 0");
  if (p.steps.empty()) bad("no phase-2 steps w");
  for (float w : p.steps)
    if (!(w > 0 && w <= 1)) bad("phase-2 steps w must be in (0, 1]");
  if (!(p.relax >= 0 && p.relax <= 1 && p.membrane >= 0 && p.membrane <= 1))
    bad("relax and membrane must be in [0, 1]");
  if (!(p.landmark_probability >= 0 && p.landmark_probability <= 1))
    bad("landmark_probability must be in [0, 1]");
  if (!(p.template_margin > 0)) bad("template_margin must be > 0");
  if (p.threads < 0) bad("threads < 0");
  if (p.normal_k < 3) bad("normal_k < 3");
}

}  // namespace

namespace {

// Checks the inputs and gives the target with unit outward normals (estimated when
// missing) and the placed template.
void prepare(const Mesh& template_mesh, const Cloud& target_in, const SdmParams& params,
             const std::vector<Landmark>& landmarks, Cloud& target, Mesh& initial,
             SdmDiagnostics& dg) {
  check_params(params);
  if (template_mesh.vertices.empty() || template_mesh.faces.empty())
    throw InvalidInput("template: empty mesh");
  if (!all_finite(template_mesh.vertices)) throw InvalidInput("template: non-finite coordinates");
  const MeshTopology topo = mesh_topology(template_mesh);
  if (topo.genus() != 0) {
    std::string why;
    if (topo.boundary_edges) why = std::to_string(topo.boundary_edges) + " boundary edges (not closed)";
    else if (topo.nonmanifold_edges || topo.nonmanifold_vertices) why = "not a manifold";
    else if (topo.components != 1) why = std::to_string(topo.components) + " components";
    else if (topo.misoriented_edges) why = "inconsistently oriented faces";
    else if (topo.unused_vertices) why = std::to_string(topo.unused_vertices) + " vertices in no face";
    else why = "genus " + std::to_string((2 - topo.euler) / 2) + " (Euler characteristic " +
               std::to_string(topo.euler) + ")";
    throw InvalidInput("template: must be a closed, connected, oriented genus-0 mesh: " + why);
  }
  // Oriented, but which way: faces wound inwards gave a fitted mesh whose normals face
  // into the object, written without a word.
  double volume = 0;
  for (const Face& f : template_mesh.faces) {
    const Vec3d a = template_mesh.vertices[std::size_t(f[0])].cast<double>(),
                b = template_mesh.vertices[std::size_t(f[1])].cast<double>(),
                c = template_mesh.vertices[std::size_t(f[2])].cast<double>();
    volume += a.dot(b.cross(c)) / 6;
  }
  if (!(volume > 0))
    throw InvalidInput("template: its faces wind inwards (signed volume " + std::to_string(volume) +
                       "): the fitted normals would face into the object; reverse each face's vertex order");
  target_in.check_consistent("target");
  const int nv = int(template_mesh.vertices.size());
  const int need = std::max(params.min_control_points, nv / 4);
  if (int(target_in.size()) < need)
    throw InvalidInput("target: " + std::to_string(target_in.size()) +
                       " control points, at least " + std::to_string(need) +
                       " needed for a template of " + std::to_string(nv) + " vertices");
  if (!all_finite(target_in.points)) throw InvalidInput("target: non-finite coordinates");
  {
    const Aabb tb = bounding_box(target_in.points);
    if (!((tb.max - tb.min).maxCoeff() > 0)) throw InvalidInput("target: all points coincide");
  }
  if (!params.selection_weights.empty()) {
    if (params.selection_weights.size() != target_in.size())
      throw InvalidInput("sdm: selection_weights must hold one weight per control point");
    double s = 0;
    for (float w : params.selection_weights) {
      if (!(w >= 0) || !std::isfinite(w)) throw InvalidInput("sdm: negative or non-finite selection weight");
      s += w;
    }
    if (!(s > 0)) throw InvalidInput("sdm: selection weights sum to zero");
  }
  for (std::size_t i = 0; i < landmarks.size(); ++i) {
    const auto& l = landmarks[i];
    if (l.vertex < 0 || l.vertex >= nv)
      throw InvalidInput("landmark " + std::to_string(i) + ": vertex " + std::to_string(l.vertex) +
                         " outside the template's 0.." + std::to_string(nv - 1));
    if (!l.point.allFinite()) throw InvalidInput("landmark " + std::to_string(i) + ": non-finite point");
    for (std::size_t j = 0; j < i; ++j)
      if (landmarks[j].vertex == l.vertex)
        throw InvalidInput("landmark " + std::to_string(i) + ": vertex " +
                           std::to_string(l.vertex) + " already pinned by landmark " +
                           std::to_string(j));
  }

  dg = SdmDiagnostics{};
  dg.template_vertices = nv;
  dg.template_faces = int(template_mesh.faces.size());
  dg.control_points = int(target_in.size());
  target = Cloud{};
  target.points = target_in.points;
  bool estimate = !target_in.has_normals();
  if (!estimate) {
    target.normals = target_in.normals;
    for (auto& n : target.normals) {
      const float l = n.norm();
      if (!(l > 0) || !std::isfinite(l)) {
        estimate = true;
        break;
      }
      n /= l;
    }
  }
  if (estimate) {
    target.normals = estimate_normals(target.points, params.normal_k, params.threads);
    orient_normals_mst(target.points, target.normals, params.normal_k);
    dg.normals_estimated = true;
  }

  initial = Mesh{};
  initial.faces = template_mesh.faces;
  initial.vertices = template_mesh.vertices;
  if (params.place_template) {
    const Aabb tb = bounding_box(target.points), mb = bounding_box(initial.vertices);
    Vec3f text = (tb.max - tb.min) * params.template_margin;
    const float floor_ext = 0.05f * text.maxCoeff() + 1e-9f;
    text = text.cwiseMax(Vec3f::Constant(floor_ext));
    const Vec3f mext = (mb.max - mb.min).cwiseMax(Vec3f::Constant(1e-12f));
    const Vec3f scale = text.cwiseQuotient(mext);
    for (auto& v : initial.vertices)
      v = tb.center() + (v - mb.center()).cwiseProduct(scale);
  }
}

}  // namespace

SdmResult fit_sdm(const Mesh& template_mesh, const Cloud& target_in, const SdmParams& params,
                  const std::vector<Landmark>& landmarks, const SdmProgress& progress) {
  Cloud target;
  Mesh initial;
  SdmDiagnostics dg;
  prepare(template_mesh, target_in, params, landmarks, target, initial, dg);
  const std::vector<char> pinned(initial.vertices.size(), 0);
  return sdm_detail::run_sdm(initial, target, params, landmarks, pinned, progress, dg);
}

SdmResult fit_sdm_icosphere(int level, const Cloud& target_in, const SdmParams& params,
                            const std::vector<Landmark>& landmarks, const SdmProgress& progress,
                            int coarse_level) {
  const Mesh fine = make_icosphere_template(level);
  if (coarse_level < 0) throw InvalidInput("sdm: coarse_level < 0");
  if (level <= coarse_level) return fit_sdm(fine, target_in, params, landmarks, progress);
  const auto t0 = std::chrono::steady_clock::now();
  // Full fit at the coarse level (landmarks on coarse vertices only: subdivision keeps
  // the coarse vertices' indices).
  const Mesh coarse = make_icosphere_template(coarse_level);
  Cloud target;
  Mesh initial;
  SdmDiagnostics dg;
  prepare(fine, target_in, params, landmarks, target, initial, dg);  // checks against the fine level
  std::vector<Landmark> coarse_lm;
  for (const auto& l : landmarks)
    if (l.vertex < int(coarse.vertices.size())) coarse_lm.push_back(l);
  SdmResult r = fit_sdm(coarse, target, params, coarse_lm, progress);
  const SdmDiagnostics cd = r.diagnostics;
  // Subdivide the fitted mesh (paper section 4.1: level 5 from the fitted level 4) and
  // polish every finer level with phase 2 only.
  Mesh m = std::move(r.mesh);
  m.normals.clear();
  SdmDiagnostics last = cd;
  for (int l = coarse_level + 1; l <= level; ++l) {
    sdm_detail::subdivide_midpoint(m.vertices, m.faces, false);
    SdmDiagnostics d0 = dg;
    d0.template_vertices = int(m.vertices.size());
    d0.template_faces = int(m.faces.size());
    const std::vector<char> pinned(m.vertices.size(), 0);
    std::vector<Landmark> lm;
    for (const auto& x : landmarks)
      if (x.vertex < int(m.vertices.size())) lm.push_back(x);
    SdmResult rl = sdm_detail::run_sdm(m, target, params, lm, pinned, progress, d0, false);
    last = rl.diagnostics;
    m = std::move(rl.mesh);
    m.normals.clear();
  }
  m.normals = vertex_normals(m);
  SdmResult out;
  out.mesh = std::move(m);
  out.diagnostics = last;
  out.diagnostics.som_iterations = cd.som_iterations;
  out.diagnostics.som_skipped = cd.som_skipped;
  out.diagnostics.anchors = cd.anchors;
  out.diagnostics.seconds_som = cd.seconds_som;
  out.diagnostics.distance_after_som = cd.distance_after_som;
  out.diagnostics.energy_rounds += cd.energy_rounds;
  out.diagnostics.seconds_energy += cd.seconds_energy;
  out.diagnostics.seconds_total =
      seconds_since(t0);
  return out;
}

}  // namespace station
