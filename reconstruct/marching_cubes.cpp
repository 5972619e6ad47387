#include "reconstruct/marching_cubes.h"

#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>
#include <tbb/task_arena.h>

#include <Eigen/Geometry>
#include <algorithm>
#ifdef __GLIBC__
#include <malloc.h>
#endif
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <tuple>

#include "core/error.h"
#include "core/threads.h"
#include "reconstruct/detail/lattice_storage.h"
#include "reconstruct/detail/mc_tables.h"
#include "reconstruct/mesh_clean.h"
#include "reconstruct/mpu.h"

namespace station {
namespace mc {

const std::array<std::array<int, 2>, 12>& edge_corners() {
  static const std::array<std::array<int, 2>, 12> table = [] {
    std::array<std::array<int, 2>, 12> t{};
    for (int a = 0; a < 3; ++a) {
      int m = 0;
      for (int c = 0; c < 8; ++c)
        if (!(c >> a & 1)) t[4 * a + m++] = {c, c | 1 << a};
    }
    return t;
  }();
  return table;
}

namespace {

int edge_between(int c0, int c1) {
  const auto& ec = edge_corners();
  for (int e = 0; e < 12; ++e)
    if ((ec[e][0] == c0 && ec[e][1] == c1) || (ec[e][0] == c1 && ec[e][1] == c0)) return e;
  return -1;
}

Eigen::Vector3d corner_pos(int c) { return Eigen::Vector3d(c & 1, c >> 1 & 1, c >> 2 & 1); }

// One configuration: segments on the six faces, chained into closed polygons, each
// oriented against the inside->outside direction and fanned into triangles.
std::vector<std::array<int, 3>> triangulate(int config) {
  const auto& ec = edge_corners();
  auto inside = [&](int c) { return (config >> c & 1) != 0; };
  std::array<std::vector<int>, 12> adj;
  for (int a = 0; a < 3; ++a) {
    for (int side = 0; side < 2; ++side) {
      const int b = (a + 1) % 3, c = (a + 2) % 3;
      // The face's corners in cyclic order.
      int k[4];
      const int bits[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
      for (int i = 0; i < 4; ++i) k[i] = side << a | bits[i][0] << b | bits[i][1] << c;
      int e[4];
      for (int i = 0; i < 4; ++i) e[i] = edge_between(k[i], k[(i + 1) % 4]);
      std::vector<int> cut;
      for (int i = 0; i < 4; ++i)
        if (inside(k[i]) != inside(k[(i + 1) % 4])) cut.push_back(i);
      auto link = [&](int i, int j) {
        adj[e[i]].push_back(e[j]);
        adj[e[j]].push_back(e[i]);
      };
      if (cut.size() == 2) {
        link(cut[0], cut[1]);
      } else if (cut.size() == 4) {
        // Ambiguous face: cut off each inside corner on its own (edge i-1 and i
        // meet at corner k[i]).
        if (inside(k[0])) link(3, 0), link(1, 2);
        else link(0, 1), link(2, 3);
      }
    }
  }
  std::vector<std::array<int, 3>> tris;
  std::array<bool, 12> used{};
  for (int start = 0; start < 12; ++start) {
    if (used[start] || adj[start].empty()) continue;
    std::vector<int> poly{start};
    used[start] = true;
    int prev = -1, cur = start;
    while (true) {
      const int next = adj[cur][0] != prev ? adj[cur][0] : adj[cur][1];
      if (next == start) break;
      poly.push_back(next);
      used[next] = true;
      prev = cur;
      cur = next;
    }
    // Orientation: the Newell normal must agree with the inside->outside direction
    // summed over the polygon's edges.
    Eigen::Vector3d newell = Eigen::Vector3d::Zero(), out = Eigen::Vector3d::Zero();
    for (std::size_t i = 0; i < poly.size(); ++i) {
      const auto& e0 = ec[poly[i]];
      const auto& e1 = ec[poly[(i + 1) % poly.size()]];
      const Eigen::Vector3d p = 0.5 * (corner_pos(e0[0]) + corner_pos(e0[1]));
      const Eigen::Vector3d q = 0.5 * (corner_pos(e1[0]) + corner_pos(e1[1]));
      newell += p.cross(q);
      const int in = inside(e0[0]) ? e0[0] : e0[1], ou = in == e0[0] ? e0[1] : e0[0];
      out += corner_pos(ou) - corner_pos(in);
    }
    if (newell.dot(out) < 0) std::reverse(poly.begin(), poly.end());
    for (std::size_t i = 1; i + 1 < poly.size(); ++i) tris.push_back({poly[0], poly[i], poly[i + 1]});
  }
  return tris;
}

}  // namespace

const std::array<std::vector<std::array<int, 3>>, 256>& triangle_table() {
  static const std::array<std::vector<std::array<int, 3>>, 256> table = [] {
    std::array<std::vector<std::array<int, 3>>, 256> t;
    for (int c = 0; c < 256; ++c) t[c] = triangulate(c);
    return t;
  }();
  return table;
}

const std::array<std::uint8_t, 256>& crossed_faces() {
  static const std::array<std::uint8_t, 256> table = [] {
    std::array<std::uint8_t, 256> t{};
    for (int cfg = 0; cfg < 256; ++cfg)
      for (int a = 0; a < 3; ++a)
        for (int side = 0; side < 2; ++side) {
          int in = 0;
          for (int q = 0; q < 8; ++q)
            if ((q >> a & 1) == side && (cfg >> q & 1)) ++in;
          if (in != 0 && in != 4) t[cfg] |= std::uint8_t(1 << (2 * a + side));
        }
    return t;
  }();
  return table;
}

}  // namespace mc

namespace {

// Grid vertex / cell key: 21 bits per axis.
using Key = std::uint64_t;
Key key(std::int64_t i, std::int64_t j, std::int64_t k) {
  return Key(i) | Key(j) << 21 | Key(k) << 42;
}

// The lattice near the surface, in blocks of 4^3 lattice points (and of the 4^3 cells
// whose lowest corner they are), created as the walk reaches them: per block the
// values (float, sign kept), bit masks of the evaluated points, the visited and the
// crossed cells, the crossed edges starting at each point (vertex ids by popcount),
// and links to the 7 blocks above it so a cell's corners are found without hashing.
// Memory grows with the surface; nothing is kept per lattice point outside the blocks.
constexpr int kSide = 4;
constexpr std::int32_t kNone = -1, kUnknown = -2;

int local_index(int li, int lj, int lk) { return li | lj << 2 | lk << 4; }

using detail::Chunked;

struct Block {
  int bi, bj, bk;
  std::uint64_t evaluated = 0, inside = 0, visited = 0, surface = 0;  // inside: value < 0
  std::uint64_t edges[3] = {0, 0, 0};  // crossed edge from the point along each axis
  std::uint32_t vbase = 0;             // id of the block's first vertex
  std::uint32_t fbase = 0;             // index of the block's first face
  std::int32_t up[8];                  // block at + (q & 1, q >> 1 & 1, q >> 2 & 1); kNone until linked
  std::int32_t down[3] = {kUnknown, kUnknown, kUnknown};  // block at -1 along each axis
};

class BlockLattice {
 public:
  std::int32_t find(int bi, int bj, int bk) const { return table_.find(key(bi, bj, bk)); }
  std::int32_t get(int bi, int bj, int bk) {
    bool inserted = false;
    const std::int32_t b = table_.find_or_insert(key(bi, bj, bk), std::int32_t(blocks.size()), inserted);
    if (!inserted) return b;
    Block blk;
    blk.bi = bi, blk.bj = bj, blk.bk = bk;
    std::fill(std::begin(blk.up), std::end(blk.up), kNone);
    blk.up[0] = b;
    blocks.push_back(blk);
    values.push_back({});
    return b;
  }
  /// Links (creating them) the blocks above b that hold corners of cell l of b.
  void link(std::int32_t b, int l) {
    const int hi = int((l & 3) == 3) | int((l >> 2 & 3) == 3) << 1 | int((l >> 4) == 3) << 2;
    for (int q = 1; q < 8; ++q) {
      if ((q & hi) != q || blocks[b].up[q] != kNone) continue;
      const std::int32_t nb = get(blocks[b].bi + (q & 1), blocks[b].bj + (q >> 1 & 1), blocks[b].bk + (q >> 2 & 1));
      blocks[b].up[q] = nb;
    }
  }
  /// The block above b (offset q as in up), or kNone when there is none.
  std::int32_t above(std::int32_t b, int q) const {
    if (blocks[b].up[q] != kNone) return blocks[b].up[q];
    return find(blocks[b].bi + (q & 1), blocks[b].bj + (q >> 1 & 1), blocks[b].bk + (q >> 2 & 1));
  }
  /// The block next to b at -1 along axis a (created when missing).
  std::int32_t below(std::int32_t b, int a) {
    if (blocks[b].down[a] == kUnknown) {
      const std::int32_t nb = get(blocks[b].bi - (a == 0), blocks[b].bj - (a == 1), blocks[b].bk - (a == 2));
      blocks[b].down[a] = nb;
    }
    return blocks[b].down[a];
  }
  /// Block and local index of lattice point (li, lj, lk) relative to block b (0..4 per axis).
  std::pair<std::int32_t, int> at(std::int32_t b, int li, int lj, int lk) const {
    const int q = (li >> 2) | (lj >> 2) << 1 | (lk >> 2) << 2;
    return {blocks[b].up[q], local_index(li & 3, lj & 3, lk & 3)};
  }
  Chunked<Block> blocks;
  Chunked<std::array<float, 64>> values;  // per block

 private:
  static_assert(kNone == detail::BlockTable::kAbsent, "a missing block reads as kNone");
  detail::BlockTable table_;
};

// A value stored as float with its sign kept (a tiny negative value stays negative).
float to_float(double x) {
  float v = float(std::clamp(x, -double(std::numeric_limits<float>::max()), double(std::numeric_limits<float>::max())));
  if (x < 0 && !(v < 0)) v = -std::numeric_limits<float>::min();
  return v;
}


std::uint64_t packed(std::int32_t b, int l) { return std::uint64_t(b) << 6 | std::uint64_t(l); }

}  // namespace

Mesh extract_marching_cubes(const ImplicitFunction& f, const Aabb& box, int resolution,
                            const MarchingCubesOptions& opt, MarchingCubesStats* stats) {
  Vec3d lo;
  double h = 0;
  int n[3];
  int off[3] = {0, 0, 0}, global_n[3];
  if (opt.window) {
    check_window(*opt.window, "extract_marching_cubes");
    lo = opt.window->origin;
    h = opt.window->h;
    for (int a = 0; a < 3; ++a) {
      n[a] = opt.window->cells[std::size_t(a)];
      off[a] = opt.window->offset[std::size_t(a)];
      global_n[a] = opt.window->global_cells[std::size_t(a)];
    }
  } else {
    if (!box.valid() || !all_finite({box.min, box.max}))
      throw InvalidInput("extract_marching_cubes: invalid bounding box");
    if (resolution < 1 || resolution > (1 << 20))
      throw InvalidInput("extract_marching_cubes: resolution must be in [1, 2^20]");
    lo = box.min.cast<double>();
    const Vec3d ext = (box.max - box.min).cast<double>();
    if (!(ext.maxCoeff() > 0)) throw InvalidInput("extract_marching_cubes: degenerate bounding box");
    h = ext.maxCoeff() / resolution;
    for (int a = 0; a < 3; ++a) global_n[a] = n[a] = std::max(1, int(std::ceil(ext[a] / h - 1e-9)));
  }
  // Window point (i, j, k) is global point off + (i, j, k): the same double in every window.
  auto vpos = [&](int i, int j, int k) { return Vec3d(lo + h * Vec3d(off[0] + i, off[1] + j, off[2] + k)); };

  MarchingCubesStats st;
  st.cell_size = h;
  const int threads = worker_threads(opt.threads);
  if (opt.threads < 0) throw InvalidInput("extract_marching_cubes: threads must be >= 0");
  tbb::task_arena arena(threads);
  auto parallel = [&](std::size_t count, auto&& fn) {
    arena.execute([&] { tbb::parallel_for(std::size_t(0), count, fn); });
  };

  // f - iso at a grid vertex; NaN counts as outside, the outermost layer is forced
  // outside with close_at_box (caps surfaces that would leave the box).
  auto finish = [&](double value, int a, int b, int c) {
    double x = value - opt.iso;
    if (!std::isfinite(x)) x = h;
    if (opt.close_at_box && (a + off[0] == 0 || b + off[1] == 0 || c + off[2] == 0 || a + off[0] == global_n[0] ||
                             b + off[1] == global_n[1] || c + off[2] == global_n[2]))
      x = std::max(x, 0.5 * h);
    return x;
  };
  auto eval = [&](int a, int b, int c) { return finish(f.value(vpos(a, b, c)), a, b, c); };
  auto in_grid = [&](int i, int j, int k) { return i >= 0 && j >= 0 && k >= 0 && i < n[0] && j < n[1] && k < n[2]; };

  BlockLattice lat;
  std::vector<std::uint64_t> frontier;
  auto push = [&](int i, int j, int k, std::vector<std::uint64_t>& to) {
    if (!in_grid(i, j, k)) return;
    const std::int32_t b = lat.get(i >> 2, j >> 2, k >> 2);
    const int l = local_index(i & 3, j & 3, k & 3);
    if (lat.blocks[b].visited >> l & 1) return;
    lat.blocks[b].visited |= std::uint64_t(1) << l;
    to.push_back(packed(b, l));
  };
  if (!opt.seeds.empty()) {
    for (const Vec3f& p : opt.seeds) {
      const Vec3d g = (p.cast<double>() - lo) / h - Vec3d(off[0], off[1], off[2]);
      if (!g.allFinite() || (g.array() < 0).any() || g.x() >= n[0] || g.y() >= n[1] || g.z() >= n[2]) continue;
      push(int(std::floor(g.x())), int(std::floor(g.y())), int(std::floor(g.z())), frontier);
    }
  } else {
    // Scan lines along x every `step` cells in y and z; a sign change between two
    // neighbouring vertices seeds the four cells around that edge. Only the values at
    // the sign changes are kept (in the blocks).
    const int longest = opt.window ? std::max({n[0], n[1], n[2]}) : resolution;
    const int step = opt.coarse_step > 0 ? opt.coarse_step : std::max(1, longest / 32);
    std::vector<std::pair<int, int>> lines;  // (j, k)
    for (int k = 0; k <= n[2]; k += step)
      for (int j = 0; j <= n[1]; j += step) lines.emplace_back(j, k);
    std::vector<std::vector<std::pair<int, std::array<double, 2>>>> hits(lines.size());
    parallel(lines.size(), [&](std::size_t li) {
      const int j = lines[li].first, k = lines[li].second;
      double prev = eval(0, j, k);
      for (int i = 0; i < n[0]; ++i) {
        const double cur = eval(i + 1, j, k);
        if ((prev < 0) != (cur < 0)) hits[li].push_back({i, {prev, cur}});
        prev = cur;
      }
    });
    st.evaluations += lines.size() * std::size_t(n[0] + 1);
    auto store = [&](int i, int j, int k, double v) {
      const std::int32_t b = lat.get(i >> 2, j >> 2, k >> 2);
      const int l = local_index(i & 3, j & 3, k & 3);
      if (lat.blocks[b].evaluated >> l & 1) return;
      lat.blocks[b].evaluated |= std::uint64_t(1) << l;
      lat.values[b][l] = to_float(v);
      if (v < 0) lat.blocks[b].inside |= std::uint64_t(1) << l;
    };
    for (std::size_t li = 0; li < lines.size(); ++li) {
      const int j = lines[li].first, k = lines[li].second;
      for (const auto& [i, v] : hits[li]) {
        store(i, j, k, v[0]);
        store(i + 1, j, k, v[1]);
        for (int dj = -1; dj <= 0; ++dj)
          for (int dk = -1; dk <= 0; ++dk) push(i, j + dj, k + dk, frontier);
      }
    }
  }

  // Continuation: a crossed cell passes the walk on across each face with a sign change.
  // A seed cell the surface misses (the point lies a little off f = 0) probes its 26
  // neighbours once instead.
  const auto& faces_of = mc::crossed_faces();
  auto config = [&](std::int32_t b, int l) {
    const int li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
    int cfg = 0;
    for (int q = 0; q < 8; ++q) {
      const auto [cb, cl] = lat.at(b, li + (q & 1), lj + (q >> 1 & 1), lk + (q >> 2 & 1));
      cfg |= int(lat.blocks[cb].inside >> cl & 1) << q;
    }
    return cfg;
  };
  bool first_wave = !opt.seeds.empty();
  // With the untrusted surface dropped, a crossed cell whose centre lies beyond the
  // trust distance plus half a cell diagonal holds no face that stays (a face's
  // centroid lies in its cell): it is not part of the surface and does not pass the
  // walk on. On a one-sided scene the extrapolated surface beyond the data was 85 % of
  // the faces, walked and then dropped (docs/run.md). The faces kept are the same
  // wherever every trusted face connects to where the walk starts through cells within
  // that reach (a trusted patch reached only across untrusted surface is not).
  const bool prune = opt.untrusted == UntrustedRegions::kLeaveOpen;
  const double prune_reach = 0.5 * std::sqrt(3.0) * h * (1 + 1e-6);
  auto beyond_trust = [&](int i, int j, int k) {
    return prune && !f.may_be_trusted_near(vpos(i, j, k) + Vec3d::Constant(0.5 * h), prune_reach);
  };
  std::vector<std::uint64_t> next;
  tbb::enumerable_thread_specific<std::vector<std::uint64_t>> next_local, deferred_local;
  tbb::enumerable_thread_specific<std::size_t> evaluated_local(0);
  tbb::enumerable_thread_specific<std::vector<std::uint64_t>> claimed_local;
  std::vector<std::uint64_t> claimed;
  std::vector<std::size_t> groups;
  // Claims a bit: true for the one thread that set it (a plain load first: most bits
  // asked for are set already, and a locked or is dear).
  auto set_bit = [](std::uint64_t& mask, int bit) {
    const std::uint64_t m = std::uint64_t(1) << bit;
    if (__atomic_load_n(&mask, __ATOMIC_RELAXED) & m) return false;
    return !(__atomic_fetch_or(&mask, m, __ATOMIC_RELAXED) & m);
  };
  while (!frontier.empty()) {
    // Blocks holding the wave's corners (serial: blocks are created only here and in
    // the serial pushes below).
    for (std::uint64_t c : frontier) {
      const std::int32_t b = std::int32_t(c >> 6);
      const int l = int(c & 63);
      lat.link(b, l);
    }
    // Corners not evaluated yet, each claimed by one thread; then evaluated a block at
    // a time (f.values_near: the MPU surface walks its octree once per group).
    parallel(frontier.size(), [&](std::size_t fi) {
      const std::uint64_t c = frontier[fi];
      const std::int32_t b = std::int32_t(c >> 6);
      const int l = int(c & 63), li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
      std::vector<std::uint64_t>& mine = claimed_local.local();
      for (int q = 0; q < 8; ++q) {
        const auto [cb, cl] = lat.at(b, li + (q & 1), lj + (q >> 1 & 1), lk + (q >> 2 & 1));
        if (set_bit(lat.blocks[cb].evaluated, cl)) mine.push_back(packed(cb, cl));
      }
    });
    claimed.clear();
    for (auto& v : claimed_local) {
      claimed.insert(claimed.end(), v.begin(), v.end());
      v.clear();
    }
    // Keys unique: one order for any thread count.
    arena.execute([&] { tbb::parallel_sort(claimed.begin(), claimed.end()); });
    groups.clear();
    for (std::size_t i = 0; i < claimed.size(); ++i)
      if (i == 0 || claimed[i] >> 6 != claimed[i - 1] >> 6) groups.push_back(i);
    groups.push_back(claimed.size());
    parallel(groups.size() - 1, [&](std::size_t g) {
      const std::size_t first = groups[g], last = groups[g + 1];
      const std::int32_t cb = std::int32_t(claimed[first] >> 6);
      Block& blk = lat.blocks[cb];
      Vec3d xs[64];
      double vs[64];
      int ijk[64][3];
      for (Vec3d& x : xs) x.setZero();
      const int count = int(last - first);
      for (int t = 0; t < count; ++t) {
        const int cl = int(claimed[first + std::size_t(t)] & 63);
        ijk[t][0] = blk.bi * kSide + (cl & 3);
        ijk[t][1] = blk.bj * kSide + (cl >> 2 & 3);
        ijk[t][2] = blk.bk * kSide + (cl >> 4);
        xs[t] = vpos(ijk[t][0], ijk[t][1], ijk[t][2]);
      }
      f.values_near(xs, count, vs);
      for (int t = 0; t < count; ++t) {
        const int cl = int(claimed[first + std::size_t(t)] & 63);
        const float v = to_float(finish(vs[t], ijk[t][0], ijk[t][1], ijk[t][2]));
        lat.values[cb][cl] = v;
        if (v < 0) set_bit(blk.inside, cl);
      }
      evaluated_local.local() += std::size_t(count);
    });
    st.cells_visited += frontier.size();
    next.clear();
    if (first_wave) {
      for (std::uint64_t c : frontier) {
        const std::int32_t b = std::int32_t(c >> 6);
        const int l = int(c & 63);
        const int i = lat.blocks[b].bi * kSide + (l & 3), j = lat.blocks[b].bj * kSide + (l >> 2 & 3),
                  k = lat.blocks[b].bk * kSide + (l >> 4);
        const int cfg = config(b, l);
        if (cfg == 0 || cfg == 255) {
          for (int q = 0; q < 27; ++q)
            if (q != 13) push(i + q % 3 - 1, j + q / 3 % 3 - 1, k + q / 9 - 1, next);
          continue;
        }
        if (beyond_trust(i, j, k)) continue;
        lat.blocks[b].surface |= std::uint64_t(1) << l;
        const int fc = faces_of[cfg];
        if (fc & 1) push(i - 1, j, k, next);
        if (fc & 2) push(i + 1, j, k, next);
        if (fc & 4) push(i, j - 1, k, next);
        if (fc & 8) push(i, j + 1, k, next);
        if (fc & 16) push(i, j, k - 1, next);
        if (fc & 32) push(i, j, k + 1, next);
      }
    } else {
      // Crossed cells pass the walk on, in parallel (visited bits claimed atomically;
      // the order of the next wave does not change the set of cells reached).
      parallel(frontier.size(), [&](std::size_t fi) {
        const std::uint64_t c = frontier[fi];
        const std::int32_t b = std::int32_t(c >> 6);
        const int l = int(c & 63);
        const int cfg = config(b, l);
        if (cfg == 0 || cfg == 255) return;
        Block& blk = lat.blocks[b];
        const int loc[3] = {l & 3, l >> 2 & 3, l >> 4};
        const int glob[3] = {blk.bi * kSide + loc[0], blk.bj * kSide + loc[1], blk.bk * kSide + loc[2]};
        if (beyond_trust(glob[0], glob[1], glob[2])) return;
        set_bit(blk.surface, l);
        const int fc = faces_of[cfg];
        std::vector<std::uint64_t>& out = next_local.local();
        for (int a = 0; a < 3; ++a)
          for (int side = 0; side < 2; ++side) {
            if (!(fc >> (2 * a + side) & 1)) continue;
            // The neighbour across the face, found through the block links.
            if (side ? glob[a] + 1 >= n[a] : glob[a] == 0) continue;
            std::int32_t nb = b;
            int nl = l;
            if (side) {
              if (loc[a] == 3) nb = blk.up[1 << a], nl = l - (3 << (2 * a));
              else nl = l + (1 << (2 * a));
            } else {
              if (loc[a] == 0) {
                nb = blk.down[a], nl = l + (3 << (2 * a));
                if (nb == kUnknown) {  // not linked yet: the block may not exist
                  deferred_local.local().push_back(packed(b, l) << 2 | std::uint64_t(a));
                  continue;
                }
              } else {
                nl = l - (1 << (2 * a));
              }
            }
            if (set_bit(lat.blocks[nb].visited, nl)) out.push_back(packed(nb, nl));
          }
      });
      for (auto& v : next_local) {
        next.insert(next.end(), v.begin(), v.end());
        v.clear();
      }
      // Pushes into blocks below that were not linked, in a fixed order.
      std::vector<std::uint64_t> deferred;
      for (auto& v : deferred_local) {
        deferred.insert(deferred.end(), v.begin(), v.end());
        v.clear();
      }
      std::sort(deferred.begin(), deferred.end());
      for (std::uint64_t d : deferred) {
        const int a = int(d & 3);
        const std::int32_t nb = lat.below(std::int32_t(d >> 8), a);
        const int nl = int(d >> 2 & 63) + (3 << (2 * a));
        if (lat.blocks[nb].visited >> nl & 1) continue;
        lat.blocks[nb].visited |= std::uint64_t(1) << nl;
        next.push_back(packed(nb, nl));
      }
    }
    frontier.swap(next);
    first_wave = false;
  }
  for (std::size_t e : evaluated_local) st.evaluations += e;
  // The walk's buffers go before the mesh is allocated (peak memory).
  std::vector<std::uint64_t>().swap(frontier);
  std::vector<std::uint64_t>().swap(next);
  std::vector<std::uint64_t>().swap(claimed);
  std::vector<std::size_t>().swap(groups);
  next_local.clear();
  deferred_local.clear();
  claimed_local.clear();

  // Blocks in key order (z, y, x): the mesh's vertex and face order, fixed for any
  // thread count.
  std::vector<std::int32_t> order(lat.blocks.size());
  for (std::size_t b = 0; b < order.size(); ++b) order[b] = std::int32_t(b);
  auto bkey = [&](std::int32_t b) { return key(lat.blocks[b].bi, lat.blocks[b].bj, lat.blocks[b].bk); };
  std::sort(order.begin(), order.end(), [&](std::int32_t a, std::int32_t b) { return bkey(a) < bkey(b); });

  // Crossed edges: one vertex per grid edge with a sign change next to a crossed cell
  // (the walk crosses every face holding such an edge, so the cells around it are
  // either all crossed or none is: one of them decides; with the walk kept within
  // trust, any of them). Owned by the edge's lower end.
  auto surface_cell = [&](int i, int j, int k) {
    const std::int32_t b = lat.find(i >> 2, j >> 2, k >> 2);
    return b != kNone && (lat.blocks[b].surface >> local_index(i & 3, j & 3, k & 3) & 1);
  };
  parallel(lat.blocks.size(), [&](std::size_t bs) {
    const std::int32_t b = std::int32_t(bs);
    Block& blk = lat.blocks[b];
    for (std::uint64_t ev = blk.evaluated; ev; ev &= ev - 1) {
      const int l = __builtin_ctzll(ev);
      const int li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
      const bool in0 = blk.inside >> l & 1;
      const int i = blk.bi * kSide + li, j = blk.bj * kSide + lj, k = blk.bk * kSide + lk;
      for (int a = 0; a < 3; ++a) {
        const int d[3] = {a == 0, a == 1, a == 2};
        const int pi = li + d[0], pj = lj + d[1], pk = lk + d[2];
        const std::int32_t nb = lat.above(b, (pi >> 2) | (pj >> 2) << 1 | (pk >> 2) << 2);
        const int nl = local_index(pi & 3, pj & 3, pk & 3);
        if (nb == kNone || !(lat.blocks[nb].evaluated >> nl & 1)) continue;
        if (in0 == bool(lat.blocks[nb].inside >> nl & 1)) continue;
        // The first grid cell around the edge.
        const int b1 = (a + 1) % 3, b2 = (a + 2) % 3;
        bool crossed = false;
        for (int q = 0; q < 4; ++q) {
          int c[3] = {i, j, k};
          c[b1] -= q & 1;
          c[b2] -= q >> 1;
          if (!in_grid(c[0], c[1], c[2])) continue;
          crossed = surface_cell(c[0], c[1], c[2]);
          if (crossed || !prune) break;
        }
        if (crossed) blk.edges[a] |= std::uint64_t(1) << l;
      }
    }
  });
  std::size_t nverts = 0, nfaces = 0;
  const auto& table = mc::triangle_table();
  std::vector<std::uint32_t> block_faces(lat.blocks.size(), 0);
  parallel(lat.blocks.size(), [&](std::size_t b) {
    std::uint32_t count = 0;
    for (std::uint64_t s = lat.blocks[b].surface; s; s &= s - 1)
      count += std::uint32_t(table[config(std::int32_t(b), __builtin_ctzll(s))].size());
    block_faces[b] = count;
  });
  for (std::int32_t b : order) {
    Block& blk = lat.blocks[b];
    blk.vbase = std::uint32_t(nverts);
    blk.fbase = std::uint32_t(nfaces);
    nverts += std::size_t(detail::popcount64(blk.edges[0]) + detail::popcount64(blk.edges[1]) +
                          detail::popcount64(blk.edges[2]));
    nfaces += block_faces[b];
  }
  std::vector<std::uint32_t>().swap(block_faces);
  if (nverts > std::size_t(std::numeric_limits<int>::max()) || nfaces > std::size_t(std::numeric_limits<std::uint32_t>::max()))
    throw InvalidInput("extract_marching_cubes: the mesh is too large (over 2^31 vertices)");
  st.surface_cells = 0;
  for (std::size_t b = 0; b < lat.blocks.size(); ++b)
    st.surface_cells += std::size_t(detail::popcount64(lat.blocks[b].surface));

  // Vertices first; the values are then freed (the faces need only the inside bits),
  // so the lattice's values and the faces are never held together (peak memory).
  Mesh mesh;
  mesh.vertices.resize(nverts);
  if (opt.normals) mesh.normals.resize(nverts);
  std::vector<std::uint64_t> edge_keys;
  if (opt.vertex_edges) edge_keys.resize(nverts);
  const auto& ec = mc::edge_corners();
  tbb::enumerable_thread_specific<std::vector<Vec3d>> at_local, grad_local;
  parallel(lat.blocks.size(), [&](std::size_t bs) {
    const std::int32_t b = std::int32_t(bs);
    const Block& blk = lat.blocks[b];
    // Vertices: linear interpolation, kept off the grid corners so no triangle collapses.
    // Their normals: the block's gradients taken together (f.gradients_near).
    std::vector<Vec3d>& at = at_local.local();
    at.clear();
    std::uint32_t v = blk.vbase;
    for (int a = 0; a < 3; ++a)
      for (std::uint64_t e = blk.edges[a]; e; e &= e - 1, ++v) {
        const int l = __builtin_ctzll(e);
        const int li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
        const int i = blk.bi * kSide + li, j = blk.bj * kSide + lj, k = blk.bk * kSide + lk;
        const int pi = li + (a == 0), pj = lj + (a == 1), pk = lk + (a == 2);
        const std::int32_t nb = lat.above(b, (pi >> 2) | (pj >> 2) << 1 | (pk >> 2) << 2);
        const double fa = lat.values[b][l];
        const double fb = lat.values[nb][local_index(pi & 3, pj & 3, pk & 3)];
        const double t = std::clamp(fa / (fa - fb), 1e-3, 1 - 1e-3);
        Vec3d p = vpos(i, j, k);
        p[a] += t * h;
        mesh.vertices[v] = p.cast<float>();
        if (opt.vertex_edges) edge_keys[v] = lattice_edge_key(off[0] + i, off[1] + j, off[2] + k, a);
        if (opt.normals) at.push_back(p);
      }
    if (!opt.normals || at.empty()) return;
    std::vector<Vec3d>& grads = grad_local.local();
    grads.resize(at.size());
    f.gradients_near(at.data(), int(at.size()), grads.data());
    for (std::size_t k = 0; k < at.size(); ++k) {
      const Vec3d& g = grads[k];
      const double len = g.norm();
      mesh.normals[blk.vbase + k] = len > 0 && std::isfinite(len) ? Vec3f((g / len).cast<float>()) : Vec3f::Zero();
    }
  });
  lat.values.clear();
#ifdef __GLIBC__
  // The values' chunks (1 MiB each) come from the heap once glibc's mmap threshold
  // has risen; hand the freed pages back before the faces are allocated, or they
  // count in the peak (lens 512^3: about 4.7 MiB of 66).
  malloc_trim(0);
#endif
  mesh.faces.resize(nfaces);
  parallel(lat.blocks.size(), [&](std::size_t bs) {
    const std::int32_t b = std::int32_t(bs);
    const Block& blk = lat.blocks[b];
    // Faces of the block's crossed cells.
    std::uint32_t fi = blk.fbase;
    for (std::uint64_t s = blk.surface; s; s &= s - 1) {
      const int l = __builtin_ctzll(s);
      const int li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
      for (const auto& tri : table[config(b, l)]) {
        Face face;
        for (int t = 0; t < 3; ++t) {
          const int c0 = ec[tri[t]][0], axis = tri[t] / 4;
          const auto [ob, ol] = lat.at(b, li + (c0 & 1), lj + (c0 >> 1 & 1), lk + (c0 >> 2 & 1));
          const Block& owner = lat.blocks[ob];
          std::uint32_t id = owner.vbase + std::uint32_t(detail::popcount64(owner.edges[axis] & ((std::uint64_t(1) << ol) - 1)));
          for (int a = 0; a < axis; ++a) id += std::uint32_t(detail::popcount64(owner.edges[a]));
          face[t] = int(id);
        }
        mesh.faces[fi++] = face;
      }
    }
  });

  if (opt.untrusted == UntrustedRegions::kLeaveOpen && !mesh.faces.empty()) {
    std::vector<char> keep(mesh.faces.size());
    arena.execute([&] {
      tbb::parallel_for(std::size_t(0), mesh.faces.size(), [&](std::size_t fi) {
        const Face& fc = mesh.faces[fi];
        const Vec3d centroid =
            (mesh.vertices[fc[0]] + mesh.vertices[fc[1]] + mesh.vertices[fc[2]]).cast<double>() / 3;
        keep[fi] = f.trusted(centroid);
      });
    });
    st.dropped_faces += keep_faces(mesh, keep, opt.vertex_edges ? &edge_keys : nullptr);
  }
  if (opt.vertex_edges) opt.vertex_edges->swap(edge_keys);
  if (stats) *stats = st;
  return mesh;
}

void check_window(const LatticeWindow& w, const char* who) {
  const std::string name(who);
  if (!w.origin.allFinite() || !(w.h > 0) || !std::isfinite(w.h))
    throw InvalidInput(name + ": the lattice window needs a finite origin and a cell h > 0");
  for (std::size_t a = 0; a < 3; ++a) {
    if (w.global_cells[a] < 1 || w.global_cells[a] >= (1 << 20))
      throw InvalidInput(name + ": the global lattice must have 1 to 2^20 - 1 cells per axis");
    if (w.offset[a] < 0 || w.cells[a] < 1 || w.offset[a] + w.cells[a] > w.global_cells[a])
      throw InvalidInput(name + ": the lattice window must lie inside the global lattice");
  }
}

Aabb extraction_box(const MpuSurface& surface) {
  Aabb box = surface.bounds();
  const float pad = 0.05f * (box.max - box.min).maxCoeff();
  box.min.array() -= pad;
  box.max.array() += pad;
  return box;
}

Mesh extract_marching_cubes(const MpuSurface& surface, int resolution, MarchingCubesOptions options,
                            MarchingCubesStats* stats) {
  const Aabb box = extraction_box(surface);
  options.seeds = surface.points();
  // Capped either way: kLeaveOpen then drops the cap with the rest of the untrusted part.
  options.close_at_box = true;
  return extract_marching_cubes(static_cast<const ImplicitFunction&>(surface), box, resolution, options, stats);
}

}  // namespace station
