#pragma once
// Quality measures of a consolidated cloud (methods.md section 1, the paper's
// section 4): accuracy against a reference surface, uniformity (Schloemer et
// al. 2011, the paper's eq. 20), and the error near sharp edges of the reference.
// Distances are in the inputs' units.
#include <cstddef>
#include <vector>

#include "core/geometry.h"

namespace station {

/// Accuracy: mean distance from the points to the reference mesh's surface (exact
/// point-to-triangle distance). The paper's section 4.1 error. Parallel; the result
/// does not depend on `threads` (0 = all cores).
/// InvalidInput on no points, non-finite coordinates, or a mesh without faces.
double mean_distance_to_mesh(const std::vector<Vec3f>& points, const Mesh& reference,
                             int threads = 0);

/// Total area of the mesh's triangles.
double mesh_area(const Mesh& mesh);

/// Uniformity: Schloemer et al.'s normalised mean nearest-neighbour distance (the
/// paper's eq. 20), mean_i min_{j != i} |p_i - p_j| / d_hex, where
/// d_hex = sqrt(2 A / (sqrt(3) N)) is the nearest-neighbour distance of N points in
/// a hexagonal packing of area A (the densest packing, so values lie in [0, 1] up
/// to boundary and curvature effects; higher is more even). Schloemer measures on
/// the unit torus; as the paper does for closed surfaces, we use Euclidean
/// distances and the surface area A (e.g. mesh_area of the reference). Coincident
/// points count with distance 0. InvalidInput on fewer than 2 points, non-finite
/// coordinates or area <= 0.
double uniformity(const std::vector<Vec3f>& points, double area);

/// uniformity of the points' closest points on the reference surface, with the
/// reference's area. Use this for noisy points: scatter off the surface lengthens
/// 3-D nearest-neighbour distances and so inflates the plain measure (a noisy random
/// sample can score above an even one that lies on the surface).
/// InvalidInput as uniformity and mean_distance_to_mesh.
double surface_uniformity(const std::vector<Vec3f>& points, const Mesh& reference,
                          int threads = 0);

/// A mesh edge as a segment.
struct Segment {
  Vec3f a, b;
};

/// The sharp edges of a mesh: edges shared by exactly two faces whose normals differ
/// by more than `angle_degrees` (the dihedral angle's supplement: 0 for a flat pair,
/// 90 on a cube's edge). Vertices at identical positions are merged first, so meshes
/// stored with split vertices along creases work too. Boundary and non-manifold edges,
/// and edges of zero-area faces, are never sharp. Faces are assumed consistently
/// oriented. Sorted by (smaller, larger) merged vertex index: deterministic.
/// The default, 30 degrees, lies inside the range (25 to 60 degrees) over which the
/// number of sharp edges of the fandisk CAD part barely changes (728 to 699).
std::vector<Segment> sharp_edges(const Mesh& mesh, double angle_degrees = 30);

struct EdgeError {
  double mean = 0;        ///< mean distance to the reference of the points counted
  std::size_t count = 0;  ///< points within `radius` of a sharp edge
};

/// Edge error: the mean distance to the reference surface of the points within
/// `radius` (e.g. 2h) of a sharp edge of the reference (sharp_edges with
/// angle_degrees). count = 0 (and mean = 0) when no point is that close.
/// InvalidInput as mean_distance_to_mesh, or on radius <= 0.
EdgeError edge_error(const std::vector<Vec3f>& points, const Mesh& reference, double radius,
                     double angle_degrees = 30, int threads = 0);

}  // namespace station
