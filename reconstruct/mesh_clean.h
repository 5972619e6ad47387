#pragma once
// Mesh clean-up after extraction: small disconnected pieces (spurious bubbles
// of an implicit fitted to noisy data, specks from stray points) are removed.
#include <cstddef>
#include <vector>

#include <cstdint>
#include <functional>

#include "core/geometry.h"

namespace station {

struct ComponentFilterStats {
  std::size_t components = 0;          ///< connected pieces before (faces sharing vertices)
  std::size_t removed_components = 0;
  std::size_t removed_faces = 0;
  double largest_area = 0;
  std::size_t supported_components = 0;  ///< below the area bound, kept for their data (PieceSupport)
};

/// Data that keeps a piece the area bound would drop: real surface seen sparsely (a
/// crevice, a part one view saw at a glancing angle) rather than a speck. A data point
/// counts for the piece of the mesh vertex nearest it, when that vertex lies within
/// `reach`.
struct PieceSupport {
  const std::vector<Vec3f>* points = nullptr;  ///< e.g. the registered scans
  double reach = 0;
  std::size_t min_points = 0;  ///< a small piece stays when at least this many count for it
};

/// Drops every connected piece whose area is below `min_area_fraction` x the
/// largest piece's area (0 keeps everything), then drops unreferenced vertices
/// (normals and colours follow). Face order and orientation are kept. With `support`,
/// a piece below the bound stays when enough of its data count for it (PieceSupport).
/// InvalidInput on an inconsistent mesh or a fraction outside [0, 1].
/// `vertex_flags` (one per vertex, when given) follow the vertices kept.
ComponentFilterStats remove_small_components(Mesh& mesh, double min_area_fraction,
                                             std::vector<std::uint8_t>* vertex_flags = nullptr,
                                             const PieceSupport* support = nullptr);

/// Erodes the mesh's open rims back to the data: faces on an open boundary (with an
/// edge used by that face alone) having a vertex further than `max_distance` from
/// the data (`distance`: a point's distance to the nearest data point, e.g.
/// MpuSurface::nearest_point_distance) are dropped, and again on the new boundary,
/// until no such face remains or `max_passes` passes ran. Closed meshes are left as
/// they are. Returns the faces dropped.
std::size_t trim_open_rims(Mesh& mesh, const std::function<double(const Vec3d&)>& distance, double max_distance,
                           int max_passes = 16);
/// The same with the far vertices given (far[v] != 0: further than the bound from the
/// data), e.g. judged block by block before the blocks' meshes were stitched.
/// InvalidInput when `far` is not one flag per vertex. With `pinned` (one flag per
/// vertex), an edge between two pinned vertices never counts as open: a block's edges
/// on a face it shares with another block, whose faces are on the other side.
/// `vertex_keys` (one per vertex) follow the vertices kept, as keep_faces's.
std::size_t trim_open_rims(Mesh& mesh, const std::vector<char>& far, int max_passes = 16,
                           const std::vector<char>* pinned = nullptr,
                           std::vector<std::uint64_t>* vertex_keys = nullptr);

/// Keeps the faces with keep[f] != 0, in order, and the vertices they use, numbered
/// in the order the kept faces first use them (normals and colours follow); returns
/// the number of faces dropped; `vertex_keys` (one per vertex) follow the vertices.
/// InvalidInput when `keep` is not one flag per face or the keys not one per vertex.
std::size_t keep_faces(Mesh& mesh, const std::vector<char>& keep, std::vector<std::uint64_t>* vertex_keys = nullptr);

}  // namespace station
