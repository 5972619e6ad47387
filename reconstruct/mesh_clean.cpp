#include "reconstruct/mesh_clean.h"

#include <Eigen/Geometry>

#include <algorithm>
#include <memory>
#include <cstdint>
#include <numeric>
#include <utility>
#include <string>
#include <type_traits>
#include <vector>

#include "core/error.h"
#include "core/kdtree.h"
#include "core/union_find.h"

namespace station {


namespace {

// Per piece root, the data points whose nearest vertex (of the whole mesh) lies in a
// piece not kept (keep_root 0) and within `reach`.
std::vector<std::size_t> support_counts(const Mesh& mesh, UnionFind& uf, const std::vector<char>& keep_root,
                                        const PieceSupport& support) {
  std::vector<std::size_t> count(mesh.vertices.size(), 0);
  std::vector<Vec3f> small_vertices;
  for (std::size_t v = 0; v < mesh.vertices.size(); ++v)
    if (!keep_root[std::size_t(uf.find(int(v)))]) small_vertices.push_back(mesh.vertices[v]);
  if (small_vertices.empty()) return count;
  // The small pieces' own vertices first (most data points lie far from all of them),
  // then the whole mesh for the few within reach: a point nearer the large piece
  // counts for it, not for a speck beside it.
  const PointIndex near_small(std::move(small_vertices));
  std::unique_ptr<PointIndex> all;
  const float reach = float(support.reach);
  for (const Vec3f& q : *support.points) {
    if (!q.allFinite() || near_small.nearest_within(q, reach).first < 0) continue;
    if (!all) all = std::make_unique<PointIndex>(mesh.vertices);
    const auto [v, d] = all->nearest(q);
    if (v >= 0 && d <= reach) ++count[std::size_t(uf.find(v))];
  }
  return count;
}

}  // namespace

ComponentFilterStats remove_small_components(Mesh& mesh, double min_area_fraction,
                                             std::vector<std::uint8_t>* vertex_flags, const PieceSupport* support) {
  mesh.check_consistent();
  if (vertex_flags && vertex_flags->size() != mesh.vertices.size())
    throw InvalidInput("remove_small_components: one flag per vertex expected");
  if (!(min_area_fraction >= 0 && min_area_fraction <= 1))
    throw InvalidInput("remove_small_components: fraction " + std::to_string(min_area_fraction) +
                       " outside [0, 1]");
  ComponentFilterStats st;
  if (mesh.faces.empty()) return st;
  const std::size_t nv = mesh.vertices.size();
  UnionFind uf(nv);
  for (const Face& f : mesh.faces) {
    uf.unite(f[0], f[1]);
    uf.unite(f[0], f[2]);
  }
  std::vector<double> area(nv, 0.0);
  for (const Face& f : mesh.faces) {
    const Vec3d a = mesh.vertices[f[0]].cast<double>();
    const double A =
        0.5 * (mesh.vertices[f[1]].cast<double>() - a).cross(mesh.vertices[f[2]].cast<double>() - a).norm();
    area[uf.find(f[0])] += std::isfinite(A) ? A : 0.0;
  }
  std::vector<char> has_face(nv, 0);
  for (const Face& f : mesh.faces) has_face[uf.find(f[0])] = 1;
  for (std::size_t r = 0; r < nv; ++r)
    if (has_face[r] && uf.find(int(r)) == int(r)) {
      ++st.components;
      st.largest_area = std::max(st.largest_area, area[r]);
    }
  const double min_area = min_area_fraction * st.largest_area;
  std::vector<char> keep_root(nv, 1);
  for (std::size_t r = 0; r < nv; ++r)
    if (has_face[r] && uf.find(int(r)) == int(r) && area[r] < min_area) keep_root[r] = 0;
  if (support && support->points && support->min_points > 0 && support->reach > 0) {
    const std::vector<std::size_t> count = support_counts(mesh, uf, keep_root, *support);
    for (std::size_t r = 0; r < nv; ++r)
      if (!keep_root[r] && count[r] >= support->min_points) {
        keep_root[r] = 1;
        ++st.supported_components;
      }
  }
  for (std::size_t r = 0; r < nv; ++r)
    if (!keep_root[r]) ++st.removed_components;
  if (st.removed_components == 0) return st;
  std::vector<Face> faces;
  faces.reserve(mesh.faces.size());
  std::vector<int> remap(nv, -1);
  for (const Face& f : mesh.faces) {
    if (!keep_root[uf.find(f[0])]) {
      ++st.removed_faces;
      continue;
    }
    faces.push_back(f);
    for (int k = 0; k < 3; ++k) remap[f[k]] = 0;
  }
  Mesh out;
  std::vector<std::uint8_t> flags;
  for (std::size_t v = 0; v < nv; ++v) {
    if (remap[v] < 0) continue;
    remap[v] = int(out.vertices.size());
    if (vertex_flags) flags.push_back((*vertex_flags)[v]);
    out.vertices.push_back(mesh.vertices[v]);
    if (mesh.has_normals()) out.normals.push_back(mesh.normals[v]);
    if (mesh.has_colours()) out.colours.push_back(mesh.colours[v]);
  }
  for (Face& f : faces) f = Face(remap[f[0]], remap[f[1]], remap[f[2]]);
  out.faces = std::move(faces);
  mesh = std::move(out);
  if (vertex_flags) vertex_flags->swap(flags);
  return st;
}

std::size_t trim_open_rims(Mesh& mesh, const std::function<double(const Vec3d&)>& distance, double max_distance,
                           int max_passes) {
  if (mesh.faces.empty()) return 0;
  std::vector<char> far(mesh.vertices.size(), 0);
  for (std::size_t v = 0; v < mesh.vertices.size(); ++v)
    far[v] = !(distance(mesh.vertices[v].cast<double>()) <= max_distance);
  return trim_open_rims(mesh, far, max_passes);
}

std::size_t trim_open_rims(Mesh& mesh, const std::vector<char>& far, int max_passes,
                           const std::vector<char>* pinned, std::vector<std::uint64_t>* vertex_keys) {
  if (far.size() != mesh.vertices.size()) throw InvalidInput("trim_open_rims: one flag per vertex expected");
  if (pinned && pinned->size() != mesh.vertices.size())
    throw InvalidInput("trim_open_rims: one pinned flag per vertex expected");
  const std::size_t nf = mesh.faces.size();
  if (nf == 0) return 0;
  for (const Face& t : mesh.faces)
    for (int k = 0; k < 3; ++k)
      if (t[k] < 0 || std::size_t(t[k]) >= far.size())
        throw InvalidInput("trim_open_rims: face index " + std::to_string(t[k]) + " outside the " +
                           std::to_string(far.size()) + " vertices");
  auto far_face = [&](std::size_t f) {
    const Face& t = mesh.faces[f];
    return far[t[0]] || far[t[1]] || far[t[2]];
  };
  // The faces at each vertex (each face once), by a counting sort: the faces on an
  // edge {a, b} are among a's. No global edge table: sorting 3 F edge keys was
  // most of the trim's time (0.34 s of 0.35 at 900k faces).
  const std::size_t nv = mesh.vertices.size();
  std::vector<std::uint32_t> vf_start(nv + 1, 0), vf(3 * nf);
  auto distinct = [&](const Face& t, int k) {
    return (k == 0 || t[k] != t[0]) && (k < 2 || t[2] != t[1]);
  };
  for (std::size_t f = 0; f < nf; ++f)
    for (int k = 0; k < 3; ++k)
      if (distinct(mesh.faces[f], k)) ++vf_start[std::size_t(mesh.faces[f][k]) + 1];
  for (std::size_t v = 0; v < nv; ++v) vf_start[v + 1] += vf_start[v];
  {
    std::vector<std::uint32_t> fill(vf_start.begin(), vf_start.end() - 1);
    for (std::size_t f = 0; f < nf; ++f)
      for (int k = 0; k < 3; ++k)
        if (distinct(mesh.faces[f], k)) vf[fill[std::size_t(mesh.faces[f][k])]++] = std::uint32_t(f);
  }
  std::vector<char> alive(nf, 1);
  // How many edges of the live faces are {a, b} (a face that repeats a vertex can
  // hold the same edge twice); a pinned edge has faces beyond this mesh, two more.
  auto holds = [](const Face& t, int a, int b) {
    int count = 0;
    for (int k = 0; k < 3; ++k) {
      const int x = t[k], y = t[(k + 1) % 3];
      count += (x == a && y == b) || (x == b && y == a);
    }
    return count;
  };
  // The faces of the vertex of {a, b} that has fewer (a fan round one far vertex
  // would otherwise cost its size squared).
  auto fewer = [&](int a, int b) {
    return vf_start[std::size_t(b) + 1] - vf_start[std::size_t(b)] < vf_start[std::size_t(a) + 1] - vf_start[std::size_t(a)]
               ? b
               : a;
  };
  auto live_on = [&](int a, int b) {
    int count = pinned && (*pinned)[std::size_t(a)] && (*pinned)[std::size_t(b)] ? 2 : 0;
    const int c = fewer(a, b);
    for (std::uint32_t i = vf_start[std::size_t(c)]; i < vf_start[std::size_t(c) + 1]; ++i)
      if (alive[vf[i]]) count += holds(mesh.faces[vf[i]], a, b);
    return count;
  };
  auto edge = [&](std::size_t f, int k) { return std::pair{mesh.faces[f][k], mesh.faces[f][(k + 1) % 3]}; };
  auto on_rim = [&](std::size_t f) {
    for (int k = 0; k < 3; ++k) {
      const auto [a, b] = edge(f, k);
      if (live_on(a, b) == 1) return true;
    }
    return false;
  };
  std::vector<std::uint32_t> layer;
  for (std::size_t f = 0; f < nf; ++f)
    if (far_face(f) && on_rim(f)) layer.push_back(std::uint32_t(f));
  std::size_t dropped = 0;
  for (int pass = 0; pass < max_passes && !layer.empty(); ++pass) {
    // Drop the whole layer first (a ring), then find the faces it exposed.
    for (const std::uint32_t f : layer) {
      alive[f] = 0;
      ++dropped;
    }
    std::vector<std::uint32_t> next;
    for (const std::uint32_t f : layer)
      for (int k = 0; k < 3; ++k) {
        const auto [a, b] = edge(f, k);
        if (live_on(a, b) != 1) continue;
        const int c = fewer(a, b);
        for (std::uint32_t i = vf_start[std::size_t(c)]; i < vf_start[std::size_t(c) + 1]; ++i) {
          const std::uint32_t h = vf[i];
          if (alive[h] && holds(mesh.faces[h], a, b) > 0 && far_face(h)) next.push_back(h);
        }
      }
    std::sort(next.begin(), next.end());
    next.erase(std::unique(next.begin(), next.end()), next.end());
    layer.swap(next);
  }
  if (dropped > 0) keep_faces(mesh, alive, vertex_keys);
  return dropped;
}

std::size_t keep_faces(Mesh& mesh, const std::vector<char>& keep, std::vector<std::uint64_t>* vertex_keys) {
  if (keep.size() != mesh.faces.size()) throw InvalidInput("keep_faces: one flag per face expected");
  if (vertex_keys && vertex_keys->size() != mesh.vertices.size())
    throw InvalidInput("keep_faces: one key per vertex expected");
  // The kept faces in place, their vertices numbered by first use; then each vertex
  // array once, at its final size (growing new arrays by doubling took about twice their
  // size in fresh memory, which costs more than the copies: docs/dmc.md, "2026-12-06:
  // memory touched where it is used").
  std::vector<int> remap(mesh.vertices.size(), -1);
  std::vector<int> used;  // new vertex -> old
  std::size_t kept = 0;
  for (std::size_t fi = 0; fi < mesh.faces.size(); ++fi) {
    if (!keep[fi]) continue;
    Face fc = mesh.faces[fi];
    for (int t = 0; t < 3; ++t) {
      int& r = remap[fc[t]];
      if (r < 0) {
        r = int(used.size());
        used.push_back(fc[t]);
      }
      fc[t] = r;
    }
    mesh.faces[kept++] = fc;
  }
  const std::size_t dropped = mesh.faces.size() - kept;
  mesh.faces.resize(kept);
  auto gather = [&](auto& values) {
    std::remove_reference_t<decltype(values)> out(used.size());
    for (std::size_t k = 0; k < used.size(); ++k) out[k] = values[std::size_t(used[k])];
    values.swap(out);
  };
  gather(mesh.vertices);
  if (mesh.has_normals()) gather(mesh.normals);
  if (mesh.has_colours()) gather(mesh.colours);
  if (vertex_keys) gather(*vertex_keys);
  return dropped;
}

}  // namespace station
