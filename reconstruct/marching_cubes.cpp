#include "reconstruct/marching_cubes.h"

#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <unordered_map>
#include <unordered_set>

#include "core/error.h"
#include "reconstruct/mc_tables.h"
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

}  // namespace mc

namespace {

// Grid vertex / cell key: 21 bits per axis.
using Key = std::uint64_t;
Key key(std::int64_t i, std::int64_t j, std::int64_t k) {
  return Key(i) | Key(j) << 21 | Key(k) << 42;
}
int ki(Key k) { return int(k & 0x1FFFFF); }
int kj(Key k) { return int(k >> 21 & 0x1FFFFF); }
int kk(Key k) { return int(k >> 42 & 0x1FFFFF); }

}  // namespace

Mesh extract_marching_cubes(const ImplicitFunction& f, const Aabb& box, int resolution,
                            const MarchingCubesOptions& opt, MarchingCubesStats* stats) {
  if (!box.valid() || !all_finite({box.min, box.max}))
    throw InvalidInput("extract_marching_cubes: invalid bounding box");
  if (resolution < 1 || resolution > (1 << 20))
    throw InvalidInput("extract_marching_cubes: resolution must be in [1, 2^20]");
  const Vec3d lo = box.min.cast<double>();
  const Vec3d ext = (box.max - box.min).cast<double>();
  if (!(ext.maxCoeff() > 0)) throw InvalidInput("extract_marching_cubes: degenerate bounding box");
  const double h = ext.maxCoeff() / resolution;
  int n[3];
  for (int a = 0; a < 3; ++a) n[a] = std::max(1, int(std::ceil(ext[a] / h - 1e-9)));
  auto vpos = [&](int i, int j, int k) { return Vec3d(lo + h * Vec3d(i, j, k)); };

  MarchingCubesStats st;
  st.cell_size = h;
  const int threads = opt.threads == 0 ? tbb::this_task_arena::max_concurrency() : opt.threads;
  if (opt.threads < 0) throw InvalidInput("extract_marching_cubes: threads must be >= 0");
  tbb::task_arena arena(threads);

  std::unordered_map<Key, double> val;
  // Evaluates the missing grid vertices of `keys` in parallel.
  auto evaluate = [&](std::vector<Key>& keys) {
    std::sort(keys.begin(), keys.end());
    keys.erase(std::unique(keys.begin(), keys.end()), keys.end());
    keys.erase(std::remove_if(keys.begin(), keys.end(), [&](Key k) { return val.count(k) > 0; }), keys.end());
    std::vector<double> v(keys.size());
    arena.execute([&] {
      tbb::parallel_for(std::size_t(0), keys.size(), [&](std::size_t i) {
        const int a = ki(keys[i]), b = kj(keys[i]), c = kk(keys[i]);
        double x = f.value(vpos(a, b, c)) - opt.iso;
        if (!std::isfinite(x)) x = h;  // a NaN counts as outside
        // Outermost layer forced outside: caps surfaces that would leave the box.
        if (opt.close_at_box && (a == 0 || b == 0 || c == 0 || a == n[0] || b == n[1] || c == n[2]))
          x = std::max(x, 0.5 * h);
        v[i] = x;
      });
    });
    for (std::size_t i = 0; i < keys.size(); ++i) val.emplace(keys[i], v[i]);
    st.evaluations += keys.size();
  };
  auto in_grid = [&](int i, int j, int k) { return i >= 0 && j >= 0 && k >= 0 && i < n[0] && j < n[1] && k < n[2]; };

  std::unordered_set<Key> visited;
  std::vector<Key> frontier;
  auto push = [&](int i, int j, int k, std::vector<Key>& to) {
    if (!in_grid(i, j, k)) return;
    if (visited.insert(key(i, j, k)).second) to.push_back(key(i, j, k));
  };
  if (!opt.seeds.empty()) {
    for (const Vec3f& p : opt.seeds) {
      const Vec3d g = (p.cast<double>() - lo) / h;
      if (!g.allFinite() || (g.array() < 0).any() || g.x() >= n[0] || g.y() >= n[1] || g.z() >= n[2]) continue;
      push(int(std::floor(g.x())), int(std::floor(g.y())), int(std::floor(g.z())), frontier);
    }
  } else {
    // Scan lines along x every `step` cells in y and z; a sign change between two
    // neighbouring vertices seeds the four cells around that edge.
    const int step = opt.coarse_step > 0 ? opt.coarse_step : std::max(1, resolution / 32);
    std::vector<Key> keys;
    for (int k = 0; k <= n[2]; k += step)
      for (int j = 0; j <= n[1]; j += step)
        for (int i = 0; i <= n[0]; ++i) keys.push_back(key(i, j, k));
    evaluate(keys);
    for (int k = 0; k <= n[2]; k += step)
      for (int j = 0; j <= n[1]; j += step)
        for (int i = 0; i < n[0]; ++i)
          if ((val.at(key(i, j, k)) < 0) != (val.at(key(i + 1, j, k)) < 0))
            for (int dj = -1; dj <= 0; ++dj)
              for (int dk = -1; dk <= 0; ++dk) push(i, j + dj, k + dk, frontier);
  }

  // Continuation: a crossed cell passes the walk on across each face with a sign change.
  // A seed cell the surface misses (the point lies a little off f = 0) probes its 26
  // neighbours once instead.
  std::vector<Key> surface;
  bool first_wave = !opt.seeds.empty();
  while (!frontier.empty()) {
    std::vector<Key> keys;
    keys.reserve(frontier.size() * 8);
    for (Key c : frontier)
      for (int q = 0; q < 8; ++q) keys.push_back(key(ki(c) + (q & 1), kj(c) + (q >> 1 & 1), kk(c) + (q >> 2 & 1)));
    evaluate(keys);
    st.cells_visited += frontier.size();
    std::vector<Key> next;
    for (Key c : frontier) {
      const int i = ki(c), j = kj(c), k = kk(c);
      int config = 0;
      for (int q = 0; q < 8; ++q)
        if (val.at(key(i + (q & 1), j + (q >> 1 & 1), k + (q >> 2 & 1))) < 0) config |= 1 << q;
      if (config == 0 || config == 255) {
        if (first_wave)
          for (int q = 0; q < 27; ++q)
            if (q != 13) push(i + q % 3 - 1, j + q / 3 % 3 - 1, k + q / 9 - 1, next);
        continue;
      }
      surface.push_back(c);
      for (int a = 0; a < 3; ++a)
        for (int side = 0; side < 2; ++side) {
          int in = 0;
          for (int q = 0; q < 8; ++q)
            if ((q >> a & 1) == side && (config >> q & 1)) ++in;
          if (in == 0 || in == 4) continue;
          int d[3] = {0, 0, 0};
          d[a] = side ? 1 : -1;
          push(i + d[0], j + d[1], k + d[2], next);
        }
    }
    frontier.swap(next);
    first_wave = false;
  }
  std::sort(surface.begin(), surface.end());
  st.surface_cells = surface.size();

  // Triangles; one vertex per crossed grid edge, keyed by (lower vertex, axis).
  const auto& table = mc::triangle_table();
  const auto& ec = mc::edge_corners();
  std::unordered_map<Key, int> vid;
  std::vector<std::pair<Key, int>> edges;  // (lower vertex, axis) per mesh vertex
  Mesh mesh;
  for (Key c : surface) {
    const int i = ki(c), j = kj(c), k = kk(c);
    int config = 0;
    for (int q = 0; q < 8; ++q)
      if (val.at(key(i + (q & 1), j + (q >> 1 & 1), k + (q >> 2 & 1))) < 0) config |= 1 << q;
    for (const auto& tri : table[config]) {
      Face face;
      for (int t = 0; t < 3; ++t) {
        const int c0 = ec[tri[t]][0], axis = tri[t] / 4;
        const Key lowv = key(i + (c0 & 1), j + (c0 >> 1 & 1), k + (c0 >> 2 & 1));
        const auto [it, added] = vid.emplace(lowv * 3 + axis, int(edges.size()));
        if (added) edges.emplace_back(lowv, axis);
        face[t] = it->second;
      }
      mesh.faces.push_back(face);
    }
  }
  mesh.vertices.resize(edges.size());
  if (opt.normals) mesh.normals.resize(edges.size());
  arena.execute([&] {
    tbb::parallel_for(std::size_t(0), edges.size(), [&](std::size_t v) {
      const Key a = edges[v].first;
      const int ax = edges[v].second;
      const int i = ki(a), j = kj(a), k = kk(a);
      const Key b = key(i + (ax == 0), j + (ax == 1), k + (ax == 2));
      const double fa = val.at(a), fb = val.at(b);
      // Linear interpolation, kept off the grid corners so no triangle collapses.
      const double t = std::clamp(fa / (fa - fb), 1e-3, 1 - 1e-3);
      Vec3d p = vpos(i, j, k);
      p[ax] += t * h;
      mesh.vertices[v] = p.cast<float>();
      if (opt.normals) {
        const Vec3d g = f.gradient(p);
        const double len = g.norm();
        mesh.normals[v] = len > 0 && std::isfinite(len) ? Vec3f((g / len).cast<float>()) : Vec3f::Zero();
      }
    });
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
    std::vector<int> remap(mesh.vertices.size(), -1);
    Mesh out;
    for (std::size_t fi = 0; fi < mesh.faces.size(); ++fi) {
      if (!keep[fi]) {
        ++st.dropped_faces;
        continue;
      }
      Face fc = mesh.faces[fi];
      for (int t = 0; t < 3; ++t) {
        int& r = remap[fc[t]];
        if (r < 0) {
          r = int(out.vertices.size());
          out.vertices.push_back(mesh.vertices[fc[t]]);
          if (opt.normals) out.normals.push_back(mesh.normals[fc[t]]);
        }
        fc[t] = r;
      }
      out.faces.push_back(fc);
    }
    mesh = std::move(out);
  }
  if (stats) *stats = st;
  return mesh;
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
