#pragma once
// Internals of the SDM shared by sdm.cpp, sdm_topology.cpp and sdm_parameterise.cpp
// (not a public header).
#include <utility>
#include <vector>

#include "core/geometry.h"
#include "core/mesh_topology.h"
#include "reconstruct/sdm.h"

namespace station::sdm_detail {

using Adjacency = MeshAdjacency;

/// One 1-to-4 split of every face; midpoints appended in face order (normalised to
/// the unit sphere when `normalise`). make_icosphere_template applies it `level` times.
void subdivide_midpoint(std::vector<Vec3f>& v, std::vector<Face>& f, bool normalise);

/// Squared distance from p to triangle (a, b, c).
float point_triangle_dist2(const Vec3f& p, const Vec3f& a, const Vec3f& b, const Vec3f& c);

/// Runs both phases on `initial` (already placed) against `target` (unit outward
/// normals present, finite). Vertices with pinned[v] != 0 never move. Fills the
/// diagnostics it measures; the caller's fields (normals_estimated...) are kept.
SdmResult run_sdm(const Mesh& initial, const Cloud& target, const SdmParams& params,
                  const std::vector<Landmark>& landmarks, const std::vector<char>& pinned,
                  const SdmProgress& progress, SdmDiagnostics diagnostics, bool run_som = true);

}  // namespace station::sdm_detail
