#include "core/mesh_topology.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <numeric>
#include <unordered_map>

#include <Eigen/Geometry>

#include "core/error.h"

namespace station {

namespace {

// Segment [s, e] crosses triangle (a, b, c) strictly inside (Moller-Trumbore, with a
// small tolerance so that touching at shared vertices does not count).
bool segment_hits_triangle(const Vec3d& s, const Vec3d& e, const Vec3d& a, const Vec3d& b,
                           const Vec3d& c) {
  const Vec3d d = e - s, e1 = b - a, e2 = c - a;
  const Vec3d p = d.cross(e2);
  const double det = e1.dot(p);
  const double scale = e1.norm() * e2.norm() * d.norm();
  if (std::abs(det) <= 1e-12 * scale) return false;  // parallel (coplanar not counted)
  const double inv = 1.0 / det;
  const Vec3d t0 = s - a;
  const double u = t0.dot(p) * inv;
  if (u < 1e-7 || u > 1 - 1e-7) return false;
  const Vec3d q = t0.cross(e1);
  const double v = d.dot(q) * inv;
  if (v < 1e-7 || u + v > 1 - 1e-7) return false;
  const double t = e2.dot(q) * inv;
  return t > 1e-7 && t < 1 - 1e-7;
}

}  // namespace

MeshAdjacency build_adjacency(int n, const std::vector<Face>& faces) {
  MeshAdjacency a;
  a.vf_start.assign(n + 1, 0);
  for (const Face& f : faces)
    for (int k = 0; k < 3; ++k) ++a.vf_start[f[k] + 1];
  for (int v = 0; v < n; ++v) a.vf_start[v + 1] += a.vf_start[v];
  a.vf.resize(a.vf_start[n]);
  std::vector<int> fill(a.vf_start.begin(), a.vf_start.end() - 1);
  for (int fi = 0; fi < int(faces.size()); ++fi)
    for (int k = 0; k < 3; ++k) a.vf[fill[faces[fi][k]]++] = fi;
  // Rings: the other vertices of the faces at v, sorted and unique.
  std::vector<std::vector<int>> rings(n);
  for (int v = 0; v < n; ++v) {
    auto& r = rings[v];
    for (int j = a.vf_start[v]; j < a.vf_start[v + 1]; ++j)
      for (int k = 0; k < 3; ++k)
        if (faces[a.vf[j]][k] != v) r.push_back(faces[a.vf[j]][k]);
    std::sort(r.begin(), r.end());
    r.erase(std::unique(r.begin(), r.end()), r.end());
  }
  a.ring_start.assign(n + 1, 0);
  for (int v = 0; v < n; ++v) a.ring_start[v + 1] = a.ring_start[v] + int(rings[v].size());
  a.ring.reserve(a.ring_start[n]);
  for (auto& r : rings) a.ring.insert(a.ring.end(), r.begin(), r.end());
  return a;
}

int MeshTopology::genus() const {
  if (!closed_manifold() || components != 1 || misoriented_edges != 0 || unused_vertices != 0)
    return -1;
  return (2 - euler) / 2;
}

MeshTopology mesh_topology(const Mesh& mesh) {
  mesh.check_consistent("mesh");
  MeshTopology t;
  const int n = int(mesh.vertices.size());
  t.vertices = n;
  t.faces = int(mesh.faces.size());
  // Undirected edge -> (face count, sum of directions: +1 when a face runs it a->b, a<b).
  std::unordered_map<std::uint64_t, std::pair<int, int>> edges;
  edges.reserve(mesh.faces.size() * 2);
  std::vector<int> parent(t.faces);
  std::iota(parent.begin(), parent.end(), 0);
  auto find = [&](int x) {
    while (parent[x] != x) x = parent[x] = parent[parent[x]];
    return x;
  };
  std::unordered_map<std::uint64_t, int> edge_face;
  std::vector<char> used(n, 0);
  for (int fi = 0; fi < t.faces; ++fi) {
    const Face& f = mesh.faces[fi];
    for (int k = 0; k < 3; ++k) {
      used[f[k]] = 1;
      const int a = f[k], b = f[(k + 1) % 3];
      const std::uint64_t key = (std::uint64_t(std::min(a, b)) << 32) | std::uint32_t(std::max(a, b));
      auto& e = edges[key];
      ++e.first;
      e.second += a < b ? 1 : -1;
      auto it = edge_face.find(key);
      if (it == edge_face.end())
        edge_face[key] = fi;
      else
        parent[find(fi)] = find(it->second);
    }
  }
  t.edges = int(edges.size());
  for (const auto& [key, e] : edges) {
    if (e.first == 1) ++t.boundary_edges;
    if (e.first >= 3) ++t.nonmanifold_edges;
    if (e.first == 2 && e.second != 0) ++t.misoriented_edges;
  }
  for (int fi = 0; fi < t.faces; ++fi)
    if (find(fi) == fi) ++t.components;
  for (int v = 0; v < n; ++v)
    if (!used[v]) ++t.unused_vertices;
  t.euler = t.vertices - t.edges + t.faces;
  // Vertex fans: the faces at v, linked through shared edges at v, must be one fan.
  const auto adj = build_adjacency(n, mesh.faces);
  for (int v = 0; v < n; ++v) {
    const int b = adj.vf_start[v], e = adj.vf_start[v + 1];
    if (e - b == 0) continue;
    std::vector<int> par(e - b);
    std::iota(par.begin(), par.end(), 0);
    auto fnd = [&](int x) {
      while (par[x] != x) x = par[x] = par[par[x]];
      return x;
    };
    std::map<int, int> other;  // ring vertex -> first local face holding it
    for (int j = b; j < e; ++j) {
      const Face& f = mesh.faces[adj.vf[j]];
      for (int k = 0; k < 3; ++k) {
        if (f[k] == v) continue;
        auto it = other.find(f[k]);
        if (it == other.end())
          other[f[k]] = j - b;
        else
          par[fnd(j - b)] = fnd(it->second);
      }
    }
    int roots = 0;
    for (int j = 0; j < e - b; ++j)
      if (fnd(j) == j) ++roots;
    if (roots != 1) ++t.nonmanifold_vertices;
  }
  return t;
}

int count_folded_faces(const Mesh& mesh) {
  const int nf = int(mesh.faces.size());
  std::vector<Vec3f> fn(nf);
  int bad = 0;
  for (int fi = 0; fi < nf; ++fi) {
    const Face& f = mesh.faces[fi];
    const Vec3f n = (mesh.vertices[f[1]] - mesh.vertices[f[0]])
                        .cross(mesh.vertices[f[2]] - mesh.vertices[f[0]]);
    const float len = n.norm();
    fn[fi] = len > 0 ? Vec3f(n / len) : Vec3f::Zero();
  }
  std::vector<Vec3f> vn(mesh.vertices.size(), Vec3f::Zero());
  for (int fi = 0; fi < nf; ++fi)
    for (int k = 0; k < 3; ++k) vn[mesh.faces[fi][k]] += fn[fi];
  for (int fi = 0; fi < nf; ++fi) {
    const Face& f = mesh.faces[fi];
    if (face_folded(fn[fi], vn[f[0]] + vn[f[1]] + vn[f[2]])) ++bad;
  }
  return bad;
}

bool faces_intersect(const Face& A, const Face& B, const Vec3f* a, const Vec3f* b) {
  int shared = 0, sa = -1, sb = -1;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      if (A[i] == B[j]) ++shared, sa = i, sb = j;
  if (shared >= 2) return false;
  Vec3d pa[3], pb[3];
  for (int k = 0; k < 3; ++k) pa[k] = a[k].cast<double>(), pb[k] = b[k].cast<double>();
  if (shared == 0) {
    for (int k = 0; k < 3; ++k)
      if (segment_hits_triangle(pa[k], pa[(k + 1) % 3], pb[0], pb[1], pb[2]) ||
          segment_hits_triangle(pb[k], pb[(k + 1) % 3], pa[0], pa[1], pa[2]))
        return true;
    return false;
  }
  return segment_hits_triangle(pa[(sa + 1) % 3], pa[(sa + 2) % 3], pb[0], pb[1], pb[2]) ||
         segment_hits_triangle(pb[(sb + 1) % 3], pb[(sb + 2) % 3], pa[0], pa[1], pa[2]);
}

std::vector<std::pair<int, int>> self_intersecting_pairs(const std::vector<Vec3f>& vertices,
                                                         const std::vector<Face>& faces) {
  struct View {
    const std::vector<Vec3f>& vertices;
    const std::vector<Face>& faces;
  } mesh{vertices, faces};
  std::vector<std::pair<int, int>> out;
  const int nf = int(mesh.faces.size());
  if (nf == 0) return out;
  const Aabb box = bounding_box(mesh.vertices);
  double edge = 0;
  for (const Face& f : mesh.faces) edge += (mesh.vertices[f[0]] - mesh.vertices[f[1]]).norm();
  edge /= nf;
  const Vec3f ext = box.max - box.min;
  const double cell = std::max({edge * 2.0, double(ext.maxCoeff()) / 256.0, 1e-12});
  const int nx = std::max(1, int(ext.x() / cell) + 1), ny = std::max(1, int(ext.y() / cell) + 1),
            nz = std::max(1, int(ext.z() / cell) + 1);
  auto cell_of = [&](double x, double lo, int n) {
    return std::clamp(int((x - lo) / cell), 0, n - 1);
  };
  std::unordered_map<std::int64_t, std::vector<int>> grid;
  for (int fi = 0; fi < nf; ++fi) {
    const Face& f = mesh.faces[fi];
    const auto& V = mesh.vertices;
    const Vec3f lo = V[f[0]].cwiseMin(V[f[1]]).cwiseMin(V[f[2]]);
    const Vec3f hi = V[f[0]].cwiseMax(V[f[1]]).cwiseMax(V[f[2]]);
    const int x0 = cell_of(lo.x(), box.min.x(), nx), x1 = cell_of(hi.x(), box.min.x(), nx);
    const int y0 = cell_of(lo.y(), box.min.y(), ny), y1 = cell_of(hi.y(), box.min.y(), ny);
    const int z0 = cell_of(lo.z(), box.min.z(), nz), z1 = cell_of(hi.z(), box.min.z(), nz);
    for (int z = z0; z <= z1; ++z)
      for (int y = y0; y <= y1; ++y)
        for (int x = x0; x <= x1; ++x)
          grid[(std::int64_t(z) * ny + y) * nx + x].push_back(fi);
  }
  std::vector<std::uint64_t> pairs;
  for (const auto& [key, list] : grid)
    for (std::size_t i = 0; i < list.size(); ++i)
      for (std::size_t j = i + 1; j < list.size(); ++j)
        pairs.push_back((std::uint64_t(std::min(list[i], list[j])) << 32) |
                        std::uint32_t(std::max(list[i], list[j])));
  std::sort(pairs.begin(), pairs.end());
  pairs.erase(std::unique(pairs.begin(), pairs.end()), pairs.end());
  for (std::uint64_t key : pairs) {
    const Face& A = mesh.faces[key >> 32];
    const Face& B = mesh.faces[key & 0xffffffffu];
    const Vec3f a[3] = {mesh.vertices[A[0]], mesh.vertices[A[1]], mesh.vertices[A[2]]};
    const Vec3f b[3] = {mesh.vertices[B[0]], mesh.vertices[B[1]], mesh.vertices[B[2]]};
    const bool hit = faces_intersect(A, B, a, b);
    if (hit) out.emplace_back(int(key >> 32), int(key & 0xffffffffu));
  }
  return out;
}

int count_self_intersections(const Mesh& mesh) {
  return int(self_intersecting_pairs(mesh.vertices, mesh.faces).size());
}

}  // namespace station
