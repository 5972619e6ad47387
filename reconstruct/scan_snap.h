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
// and the other face at a crease, are left out), at least `min_points` of them. The
// fit is in absolute distances (least squares refitted by reweighting), as the mesh
// is measured against the scans by their mean absolute distance and a scanner's
// noise has tails. The vertex moves by a, less its facets' sag (the flat triangles
// between vertices on a curved surface cut it: b' S / 12 on average, S the sum of a
// triangle's squared edges, b' the fit's curvature term), never further than
// `max_move`.
//
// Whether to move at all is decided by the scans themselves (`cross_validate`): at
// strided vertices the fit is made twice, from the even and from the odd scan points,
// two independent estimates m_e, m_o of the move. Their product estimates the square
// of the offset between the mesh and where the fits tend (E[m_e m_o] = mu^2), a
// quarter of their squared difference the variance of the fit from all the points;
// the snap is done only when, summed over the vertices, the offset is the larger. On
// clean, dense scans (the Stanford dragon) it is; on scans whose noise the fitted
// surface has averaged better than a local fit can (the demo's simulated bottle) it
// is not, and the mesh stays. The halves share what every view shares (its
// registration error, noise correlated along a scan line), which reads as offset, and
// the check measures against the fits' expectation, not the true surface: it tells
// noise from a real offset, not a fit's bias from the mesh's. A snap judged only on
// the points it fits follows their noise: the old one-cell mean brought the dragon's
// mesh 14 % closer to the half it fitted and 3 % closer to the other (docs/run.md).
// Vertices far from any scan (a closed bottom the scanner never saw) stay.
#include <cstddef>

#include "core/geometry.h"

namespace station {

struct ScanSnapParams {
  /// The fit's radius along the surface, input units; 0: the scans' default WLOP
  /// support h = 4 d_bb / sqrt(n) (the scale the consolidation averages them over at
  /// its default radius), at least one `cell`.
  double radius = 0;
  double max_move = 0;  ///< input units; 0: 0.5 x `cell`
  double cell = 0;      ///< the extraction lattice's cell (sets the defaults above)
  double min_cos = 0.866;  ///< scan normal . vertex normal at least this (30 degrees)
  int min_points = 12;     ///< scan points a fit needs (two unknowns, a noise estimate)
  /// A vertex moves by the part of a beyond this many of its standard errors (0: by
  /// all of a). The cross-validation already keeps noise out; this is for callers
  /// who want to move only where a fit is sure.
  double significance = 0;
  /// Snap only when the two halves of the scans agree on an offset larger than the fit's
  /// noise (above); then only vertices that each half alone can fit (min_points / 2
  /// points) move.
  bool cross_validate = true;
  int threads = 0;  ///< 0 = all cores; the result does not depend on it
};

struct ScanSnapStats {
  std::size_t moved = 0;  ///< vertices moved
  double mean_move = 0;   ///< mean |move| over those, input units
  double radius = 0;      ///< the fit's radius used
  /// The cross-validation, over the sampled vertices fitted from both halves (input
  /// units): sqrt(mean m_e m_o), the mesh's RMS offset from where the fits tend (0
  /// when the mean is negative), and sqrt(mean (m_e - m_o)^2 / 4), the fit's RMS
  /// noise. 0 and 0 when not cross-validated.
  double held_out_rms_kept = 0, held_out_rms_snapped = 0;
  std::size_t held_out_vertices = 0;  ///< sampled vertices fitted from both halves
  std::size_t sampled_vertices = 0;   ///< vertices sampled (with a normal)
  /// Declined because under a tenth of the sampled vertices have scan points facing
  /// their way in each half: the scans hardly meet the mesh (inward normals, other
  /// units, another object).
  bool too_few_fitted = false;
  bool declined = false;  ///< the cross-validation kept the mesh as it was (also when no vertex was fitted)
};

/// Moves mesh.vertices (faces unchanged). InvalidInput when the scans have no normals
/// (or not one per point) or non-finite points, or when the radius or the largest
/// move is neither given nor set by a positive cell.
ScanSnapStats snap_to_scans(Mesh& mesh, const Cloud& scans, const ScanSnapParams& params);

}  // namespace station
