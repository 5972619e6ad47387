#include "reconstruct/detail/dmc_internal.h"
#include "reconstruct/mesh_clean.h"

namespace station::detail::dmc {

Mesh Dmc::build_mesh() {
  const std::vector<Key> surface = sorted_surface();
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
    cfgs[i] = std::uint8_t(config(b, l));
  });
  std::vector<std::size_t> first(surface.size() + 1, 0);
  for (std::size_t i = 0; i < surface.size(); ++i) first[i + 1] = first[i] + table[cfgs[i]].size();
  // Faces hold crossing indices until the vertex ids replace them.
  Mesh mesh;
  mesh.faces.resize(first.back());
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
      }
      ++f;
    }
  });
  std::vector<const Crossing*> edges;
  for (Face& fc : mesh.faces)
    for (int t = 0; t < 3; ++t) {
      Crossing& x = nodes_.crossing_at(std::uint32_t(fc[t]));
      if (x.vid < 0) {
        x.vid = int(edges.size());
        edges.push_back(&x);
      }
      fc[t] = x.vid;
    }
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
  if (opt_.untrusted == UntrustedRegions::kLeaveOpen && !mesh.faces.empty()) drop_untrusted(mesh);
  return mesh;
}

void Dmc::drop_untrusted(Mesh& mesh) {
  std::vector<char> keep(mesh.faces.size());
  parallel(mesh.faces.size(), [&](std::size_t fi) {
    const Face& fc = mesh.faces[fi];
    const Vec3d centroid = (mesh.vertices[fc[0]] + mesh.vertices[fc[1]] + mesh.vertices[fc[2]]).cast<double>() / 3;
    keep[fi] = f_.trusted(centroid);
  });
  st_.dropped_faces += keep_faces(mesh, keep);
}

}  // namespace station::detail::dmc
