#pragma once
// The mesh's vertices onto the scans' local mean (issue 32, docs/run.md "Real
// multi-view scans"). The surface stage fits the consolidated points, a fifth of
// the registered scans, evened and thinned; the mesh then follows them, not the
// scans' own detail. This step moves each vertex along its normal to the
// weighted mean height of the scan points around it: only points within `radius`
// along the surface (biweight of the distance along the vertex's tangent plane)
// whose normals face the vertex's way within 30 degrees (the other side of a thin
// part, and both faces at a crease, are left out: a vertex on a sharp edge keeps
// its place), at least `min_points` of them, by the part of the mean beyond
// `significance` standard errors (scan noise alone does not move it), and never
// further than `max_move`.
// Vertices far from any scan (a closed bottom the scanner never saw) stay.
#include <cstddef>

#include "core/geometry.h"

namespace station {

struct ScanSnapParams {
  double radius = 0;    ///< along the surface, input units; 0: `cell`
  double max_move = 0;  ///< input units; 0: 0.5 x `cell`
  double cell = 0;      ///< the extraction lattice's cell (sets the defaults above)
  double min_cos = 0.866;  ///< scan normal . vertex normal at least this (30 degrees)
  int min_points = 3;
  /// A vertex moves by the part of the mean height beyond this many of its standard
  /// errors (0: by the whole mean): on noisy scans the mean is mostly noise.
  double significance = 1;
  int threads = 0;  ///< 0 = all cores; the result does not depend on it
};

struct ScanSnapStats {
  std::size_t moved = 0;     ///< vertices moved
  double mean_move = 0;      ///< mean |move| over those, input units
  double radius = 0;         ///< the radius used
};

/// Moves mesh.vertices (faces unchanged). InvalidInput when the scans have no
/// normals or non-finite points, or when neither radius nor cell is positive.
ScanSnapStats snap_to_scans(Mesh& mesh, const Cloud& scans, const ScanSnapParams& params);

}  // namespace station
