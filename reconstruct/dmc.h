#pragma once
// Deformed Marching Cubes (Fujimoto, Moriya & Nakayama 2007; docs/dmc.md): the sparse
// marching cubes of reconstruct/marching_cubes.h on a lattice whose points may move,
// each inside its own box Omega = p + h*[-0.5, 0.5)^3, so cells never fold and the MC
// case table still applies:
//   1. barycentre step: lattice points next to a part thinner than the lattice move to
//      the centroid of the inside samples (step s) of their box, so the part keeps
//      lattice points inside (and, beyond the paper, points inside a thin slot of outside
//      move to the centroid of the outside samples, so the slot stays open);
//   2. feature step: sharp edges and corners found from the crossings and normals of
//      each cell (Kobbelt et al. 2001) pull the nearest lattice points onto them;
//   3. marching cubes on the deformed lattice, crossings refined on f along the
//      deformed edges.
// Lattice values are f at the moved positions. Sparse (the lattice points near the
// surface, in blocks of 4^3 behind a block hash), parallel (TBB), deterministic for
// any thread count.
#include <array>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <unordered_map>

#include "core/geometry.h"
#include "reconstruct/implicit.h"
#include "reconstruct/marching_cubes.h"

namespace station {

class MpuSurface;

/// A lattice point as DMC left it (blocks hand their shared faces' points on).
struct DmcPoint {
  Vec3d pos = Vec3d::Zero();
  double value = 0;
  std::uint8_t flags = 0;
};

/// Everything MarchingCubesOptions has (iso, seeds, coarse_step, normals, untrusted,
/// close_at_box, threads; same meaning), plus the DMC steps. A MarchingCubesOptions
/// converts: `DmcOptions d; static_cast<MarchingCubesOptions&>(d) = mc_options;`.
struct DmcOptions : MarchingCubesOptions {
  /// Barycentre search step s in input units; 0 = h / 5. Rounded so that h / s samples
  /// fit each axis of Omega (at most 16).
  double search_step = 0;
  /// Sharp edge when the smallest dot product of two crossing normals of a cell is below.
  double theta_sharp = 0.9;
  /// Corner when a third normal's |dot| with the edge direction is above.
  double phi_corner = 0.7;
  /// Step 1: move lattice points into thin inside parts.
  bool barycentre = true;
  /// Beyond the paper: move lattice points into thin gaps of outside (slots).
  bool thin_gaps = true;
  /// Step 2: move lattice points onto sharp edges and corners.
  bool features = true;
  /// Step 2 only in cells where f says it may have a crease
  /// (ImplicitFunction::may_be_sharp; analytic functions: everywhere; the MPU surface:
  /// near its edge and corner fits). false: wherever the crossing normals say so, which on
  /// a noisy scan also takes bends of the smooth surface for edges (docs/dmc.md).
  bool features_where_sharp = true;
  /// At most this many evaluations of f (value and gradient together) refine each
  /// crossing after the linear interpolation: Newton steps along the edge, kept in the
  /// bracket (Illinois steps where Newton's quadratic model is not trusted); fewer once
  /// |f| is at round-off or the Newton step's estimated error is under 1e-4 of the edge.
  /// Cells with a suspected sharp feature refine their crossings to round-off for the
  /// feature planes.
  int refine_steps = 2;

  // ---- blocks (reconstruct/blocks.h): DMC's moves at the faces a window shares
  /// With a window: the lattice also covers this many cells below the window's lower
  /// faces (within the global lattice), so that the points of those faces move as on
  /// the whole lattice; the faces of those cells are not emitted. 0: the window's faces
  /// are all fixed.
  std::array<int, 3> halo{0, 0, 0};
  /// With a window: lattice points of the window's faces that an earlier block moved
  /// (key lattice_edge_key(i, j, k, 3), global indices): they stay there, with that
  /// value and what DMC knew of them (its internal flags, as report gave them).
  const std::unordered_map<std::uint64_t, DmcPoint>* given = nullptr;
  /// With a window: receives every lattice point DMC entered (global indices): its
  /// final position, value (f - iso) and the flags its moves left (0: none).
  std::function<void(int i, int j, int k, const DmcPoint& point)> report;
};

struct DmcStats : MarchingCubesStats {
  std::size_t gradient_evaluations = 0;  ///< gradients of f taken (search pruning, crossings)
  std::size_t probed = 0;            ///< lattice points given the thin-part probe
  std::size_t lattice_thick = 0;     ///< of those, answered by the lattice alone (no evaluation)
  std::size_t searched = 0;          ///< lattice points whose Omega was sampled at step s
  std::size_t moved_barycentre = 0;  ///< moved into thin inside parts (step 1)
  std::size_t moved_gap = 0;         ///< moved into thin outside gaps (beyond the paper)
  std::size_t bridged = 0;           ///< step-1 moves joining diagonal neighbours (docs/dmc.md)
  std::size_t reverted = 0;          ///< step-1 moves undone (isolated specks, see docs/dmc.md)
  std::size_t moved_corner = 0;      ///< moved onto corners (step 2)
  std::size_t moved_edge = 0;        ///< moved onto sharp edges (step 2)
  std::size_t vetoed = 0;            ///< feature moves refused (would join separate parts)
  std::size_t smooth_cells = 0;      ///< cells whose normals suggested a feature where f is smooth (skipped)
  std::size_t filled_turns = 0;      ///< outside points in a turn of an edge chain moved in
  std::size_t degenerate_faces = 0;  ///< zero-area faces in the output (expected 0)
  double search_step = 0;            ///< s actually used, input units
  /// Wall time of the phases: traversal of the plain lattice, step 1 (with the surface
  /// update), step 2, crossings + mesh.
  double seconds_traversal = 0, seconds_barycentre = 0, seconds_features = 0, seconds_mesh = 0;
};

/// Triangle mesh of {f = iso} inside `box` on a lattice of `resolution` cells along the
/// box's longest side, by Deformed Marching Cubes. Same conventions as
/// extract_marching_cubes (cell size, seeds/scan lines, close_at_box, untrusted regions,
/// counter-clockwise faces seen from outside, one vertex per crossed lattice edge); the
/// lattice points of the box's outermost layer never move. f returning NaN counts as
/// outside. InvalidInput on an invalid box, resolution outside [1, 2^20], threads < 0,
/// search_step < 0, refine_steps < 0, or thresholds outside [-1, 1].
Mesh extract_dmc(const ImplicitFunction& f, const Aabb& box, int resolution,
                 const DmcOptions& options = {}, DmcStats* stats = nullptr);

/// The MPU surface's mesh with the conventions of extract_marching_cubes(MpuSurface):
/// box = input bounds grown by 5 % of the longest side, seeds = the input points,
/// close_at_box set.
Mesh extract_dmc(const MpuSurface& surface, int resolution, DmcOptions options = {},
                 DmcStats* stats = nullptr);

}  // namespace station
