#pragma once
// The mesh's vertices onto the scans (issue 32, docs/run.md "Snap to the scans").
// The surface stage fits the consolidated points, a fifth of the registered scans,
// averaged over the consolidation's support h; the mesh then follows them, not the
// scans' own detail. This step moves each vertex along its normal onto a local fit
// of the scans: the height h(t) = a + b t^2 (a paraboloid round the vertex's normal,
// whose b takes the mean curvature so that a is the surface's height at the vertex,
// not the mean height of a curved patch) over the scan points within `radius` along
// the surface (biweight of the distance along the vertex's tangent plane) whose
// normals face the vertex's way within 30 degrees (the other side of a thin part,
// and the other face at a crease, are left out), at least `min_points` of them; the
// vertex moves by a, never further than `max_move`.
//
// Whether to move at all is decided by the scans themselves (`cross_validate`): the
// fits are made from every other scan point, and the snap is done only when their
// heights predict the other half's local mean height at the vertices better than
// the mesh does. On clean, dense scans (the Stanford dragon) it does; on scans whose
// noise the fitted surface has averaged better than any local fit can (the demo's
// simulated bottle) it does not, and the mesh stays. A snap that only ever looked at
// the points it fits would follow their noise: with a radius of one cell the old
// snap brought the dragon's mesh 5 % closer to the scans it fitted and 2 % further
// from a held-out half (docs/run.md).
// Vertices far from any scan (a closed bottom the scanner never saw) stay.
#include <cstddef>

#include "core/geometry.h"

namespace station {

struct ScanSnapParams {
  /// The fit's radius along the surface, input units; 0: the scans' WLOP support
  /// h = 4 d_bb / sqrt(n) (the scale the consolidation averaged them over), at least
  /// one `cell`.
  double radius = 0;
  double max_move = 0;  ///< input units; 0: 0.5 x `cell`
  double cell = 0;      ///< the extraction lattice's cell (sets the defaults above)
  double min_cos = 0.866;  ///< scan normal . vertex normal at least this (30 degrees)
  int min_points = 12;     ///< scan points a fit needs (two unknowns, a noise estimate)
  /// A vertex moves by the part of a beyond this many of its standard errors (0: by
  /// all of a). The cross-validation already keeps noise out; this is for callers
  /// who want to move only where a fit is sure.
  double significance = 0;
  /// Snap only when the fits predict a held-out half of the scans better than the mesh.
  bool cross_validate = true;
  int threads = 0;  ///< 0 = all cores; the result does not depend on it
};

struct ScanSnapStats {
  std::size_t moved = 0;  ///< vertices moved
  double mean_move = 0;   ///< mean |move| over those, input units
  double radius = 0;      ///< the fit's radius used
  /// The cross-validation (RMS over the sampled vertices of the held-out half's local
  /// mean height against the vertex, input units): as the mesh is, and as the fits
  /// from the other half would put it. 0 and 0 when not cross-validated.
  double held_out_rms_kept = 0, held_out_rms_snapped = 0;
  std::size_t held_out_vertices = 0;
  bool declined = false;  ///< the cross-validation kept the mesh as it was
};

/// Moves mesh.vertices (faces unchanged). InvalidInput when the scans have no
/// normals or non-finite points, or when neither radius nor cell is positive.
ScanSnapStats snap_to_scans(Mesh& mesh, const Cloud& scans, const ScanSnapParams& params);

}  // namespace station
