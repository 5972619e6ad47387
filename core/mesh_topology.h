#pragma once
// Combinatorics and sanity checks of triangle meshes: adjacency, topology (Euler
// characteristic, components, manifoldness, genus), folded faces and
// self-intersections. Used by the SDM (reconstruct/sdm.h), the tests and the benches.
#include <utility>
#include <vector>

#include "core/geometry.h"

namespace station {

/// Vertex-to-vertex (1-ring) and vertex-to-face adjacency in CSR form.
struct MeshAdjacency {
  std::vector<int> ring_start, ring;  // neighbours of v: ring[ring_start[v] .. ring_start[v+1])
  std::vector<int> vf_start, vf;      // faces at v
};
MeshAdjacency build_adjacency(int vertex_count, const std::vector<Face>& faces);

/// Combinatorial facts about a triangle mesh.
struct MeshTopology {
  int vertices = 0, edges = 0, faces = 0;
  int euler = 0;                ///< V - E + F
  int components = 0;           ///< connected components (over faces' edges)
  int boundary_edges = 0;       ///< edges with one face
  int nonmanifold_edges = 0;    ///< edges with three or more faces
  int misoriented_edges = 0;    ///< interior edges whose two faces run it the same way
  int nonmanifold_vertices = 0; ///< vertices whose faces do not form one fan
  int unused_vertices = 0;      ///< vertices in no face
  bool closed_manifold() const {
    return boundary_edges == 0 && nonmanifold_edges == 0 && nonmanifold_vertices == 0;
  }
  /// Genus of a closed, connected, oriented manifold ((2 - euler) / 2); -1 otherwise.
  int genus() const;
};
MeshTopology mesh_topology(const Mesh& mesh);

/// A face of unit normal n (zero when degenerate) is folded when it faces against
/// the surface around it: n . (the sum of its three corners' vertex normals) < 0, a
/// vertex normal being the sum of the unit normals of the faces at it, the face's
/// own included. (Against the faces across its edges alone, every face of a
/// tetrahedron or of a square pyramid counts as folded: their normals sum to
/// minus its own, and the repair then shrank such meshes to a point.)
inline bool face_folded(const Vec3f& n, const Vec3f& corner_normals) {
  return n.isZero() || n.dot(corner_normals) < 0;
}

/// Faces whose unit normal has a negative dot product with the sum of its three
/// corners' vertex normals (each the sum of the unit normals of the faces at that
/// corner, its own included): a fold; plus degenerate faces.
int count_folded_faces(const Mesh& mesh);

/// Pairs of faces that intersect and share no vertex, plus pairs sharing exactly one
/// vertex whose opposite edge crosses the other face (uniform-grid broad phase,
/// segment-triangle narrow phase; coplanar overlaps are not counted).
int count_self_intersections(const Mesh& mesh);

/// Faces A and B (vertex positions a[3], b[3]) intersect: an edge of one crosses the
/// other, not counting edges through a shared vertex; faces sharing an edge never do.
bool faces_intersect(const Face& A, const Face& B, const Vec3f* a, const Vec3f* b);

/// Face pairs (i < j) that intersect (see count_self_intersections).
std::vector<std::pair<int, int>> self_intersecting_pairs(const std::vector<Vec3f>& vertices,
                                                         const std::vector<Face>& faces);

}  // namespace station
