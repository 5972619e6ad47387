#include "reconstruct/detail/dmc_internal.h"
#include "reconstruct/mesh_clean.h"

namespace station::detail::dmc {

Mesh Dmc::build_mesh() {
  std::vector<Key> surface = sorted_surface();
  if (halo_[0] || halo_[1] || halo_[2])  // the halo's cells are the blocks' below
    surface.erase(std::remove_if(surface.begin(), surface.end(), [&](Key c) { return in_halo(ki(c), kj(c), kk(c)); }),
                  surface.end());
  st_.surface_cells = surface.size();
  const auto& table = mc::triangle_table();
  const auto& ec = mc::edge_corners();
  // Per cell (key order) its configuration, then its first face (prefix sum); the
  // faces' crossings in parallel; vertex ids by first use in face order (serial), so
  // the mesh is the same for any thread count.
  std::vector<std::uint8_t> cfgs(surface.size());
  std::vector<std::uint32_t> handle(surface.size());  // block << 6 | local index
  parallel(surface.size(), [&](std::size_t i) {
    const std::int32_t b = nodes_.block_of(surface[i]);
    const int l = Lattice::local(surface[i]);
    handle[i] = std::uint32_t(b) << 6 | std::uint32_t(l);
    cfgs[i] = nodes_.blk(b).cfg[l];
  });
  std::vector<std::size_t> first(surface.size() + 1, 0);
  for (std::size_t i = 0; i < surface.size(); ++i) first[i + 1] = first[i] + table[cfgs[i]].size();
  // Faces hold crossing indices until the vertex ids replace them.
  Mesh mesh;
  mesh.faces.resize(first.back());
  // With vertex_edges: each face corner's lattice edge (global), kept for its vertex.
  std::vector<std::uint64_t> corner_edges(opt_.vertex_edges ? 3 * first.back() : 0);
  parallel(surface.size(), [&](std::size_t i) {
    const std::int32_t b = std::int32_t(handle[i] >> 6);
    const int l = int(handle[i] & 63), li = l & 3, lj = l >> 2 & 3, lk = l >> 4;
    std::size_t f = first[i];
    for (const auto& tri : table[cfgs[i]]) {
      for (int t = 0; t < 3; ++t) {
        const int c0 = ec[tri[t]][0];
        const auto [xb, xl] = nodes_.rel(b, li + (c0 & 1), lj + (c0 >> 1 & 1), lk + (c0 >> 2 & 1));
        const std::uint32_t x = nodes_.crossing_index(xb, xl, tri[t] / 4);
        if (x == Lattice::kNoCrossing) throw std::out_of_range("extract_dmc: internal error: crossing not computed");
        mesh.faces[f][t] = int(x);
        if (opt_.vertex_edges) {
          const Key p = nodes_.point(xb, xl);
          corner_edges[3 * f + std::size_t(t)] =
              lattice_edge_key(off_[0] + ki(p), off_[1] + kj(p), off_[2] + kk(p), tri[t] / 4);
        }
      }
      ++f;
    }
  });
  // At most one vertex per crossing: room for all at once (no doubling into fresh memory).
  std::vector<const Crossing*> edges;
  edges.reserve(nodes_.crossing_count());
  std::vector<std::uint64_t> edge_keys;
  if (opt_.vertex_edges) edge_keys.reserve(nodes_.crossing_count());
  for (std::size_t f = 0; f < mesh.faces.size(); ++f)
    for (int t = 0; t < 3; ++t) {
      Face& fc = mesh.faces[f];
      Crossing& x = nodes_.crossing_at(std::uint32_t(fc[t]));
      if (x.vid < 0) {
        x.vid = int(edges.size());
        edges.push_back(&x);
        if (opt_.vertex_edges) edge_keys.push_back(corner_edges[3 * f + std::size_t(t)]);
      }
      fc[t] = x.vid;
    }
  std::vector<std::uint64_t>().swap(corner_edges);
  mesh.vertices.resize(edges.size());
  if (opt_.normals) mesh.normals.resize(edges.size());
  parallel(edges.size(), [&](std::size_t v) {
    const Crossing& x = *edges[v];
    mesh.vertices[v] = x.pos.cast<float>();
    if (opt_.normals) mesh.normals[v] = x.normal.cast<float>();
  });
  tbb::enumerable_thread_specific<std::size_t> degenerate(0);
  parallel(mesh.faces.size(), [&](std::size_t f) {
    const Face& fc = mesh.faces[f];
    const Vec3f e1 = mesh.vertices[fc[1]] - mesh.vertices[fc[0]];
    const Vec3f e2 = mesh.vertices[fc[2]] - mesh.vertices[fc[0]];
    if (!(e1.cross(e2).norm() > 0)) ++degenerate.local();
  });
  for (std::size_t n : degenerate) st_.degenerate_faces += n;
  if (opt_.untrusted == UntrustedRegions::kLeaveOpen && !mesh.faces.empty())
    drop_untrusted(mesh, opt_.vertex_edges ? &edge_keys : nullptr);
  if (opt_.vertex_edges) opt_.vertex_edges->swap(edge_keys);
  return mesh;
}

void Dmc::drop_untrusted(Mesh& mesh, std::vector<std::uint64_t>* keys) {
  std::vector<char> keep(mesh.faces.size());
  parallel(mesh.faces.size(), [&](std::size_t fi) {
    const Face& fc = mesh.faces[fi];
    const Vec3d centroid = (mesh.vertices[fc[0]] + mesh.vertices[fc[1]] + mesh.vertices[fc[2]]).cast<double>() / 3;
    keep[fi] = f_.trusted(centroid);
  });
  st_.dropped_faces += keep_faces(mesh, keep, keys);
}

}  // namespace station::detail::dmc
