#pragma once
// Internals of the SDM shared by sdm.cpp, sdm_topology.cpp and sdm_parameterise.cpp
// (not a public header).
#include <utility>
#include <vector>

#include "core/geometry.h"
#include "reconstruct/sdm.h"

namespace station::sdm_detail {

/// Vertex-to-vertex (1-ring) and vertex-to-face adjacency in CSR form.
struct Adjacency {
  std::vector<int> ring_start, ring;  // neighbours of v: ring[ring_start[v] .. ring_start[v+1])
  std::vector<int> vf_start, vf;      // faces at v
};
Adjacency build_adjacency(int vertex_count, const std::vector<Face>& faces);

/// One 1-to-4 split of every face; midpoints appended in face order (normalised to
/// the unit sphere when `normalise`). make_icosphere_template applies it `level` times.
void subdivide_midpoint(std::vector<Vec3f>& v, std::vector<Face>& f, bool normalise);

/// A face of unit normal n (zero when degenerate) is folded when it faces against
/// the surface around it: n . (the sum of its three corners' vertex normals) < 0, a
/// vertex normal being the sum of the unit normals of the faces at it, the face's
/// own included. (Against the faces across its edges alone, every face of a
/// tetrahedron or of a square pyramid counts as folded: their normals sum to
/// minus its own, and the repair then shrank such meshes to a point.)
inline bool folded(const Vec3f& n, const Vec3f& corner_normals) {
  return n.isZero() || n.dot(corner_normals) < 0;
}

/// Squared distance from p to triangle (a, b, c).
float point_triangle_dist2(const Vec3f& p, const Vec3f& a, const Vec3f& b, const Vec3f& c);

/// Faces A and B (vertex positions a[3], b[3]) intersect: an edge of one crosses the
/// other, not counting edges through a shared vertex; faces sharing an edge never do.
bool faces_intersect(const Face& A, const Face& B, const Vec3f* a, const Vec3f* b);

/// Face pairs (i < j) that intersect (see count_self_intersections).
std::vector<std::pair<int, int>> self_intersecting_pairs(const std::vector<Vec3f>& vertices,
                                                         const std::vector<Face>& faces);

/// Runs both phases on `initial` (already placed) against `target` (unit outward
/// normals present, finite). Vertices with pinned[v] != 0 never move. Fills the
/// diagnostics it measures; the caller's fields (normals_estimated...) are kept.
SdmResult run_sdm(const Mesh& initial, const Cloud& target, const SdmParams& params,
                  const std::vector<Landmark>& landmarks, const std::vector<char>& pinned,
                  const SdmProgress& progress, SdmDiagnostics diagnostics, bool run_som = true);

}  // namespace station::sdm_detail
