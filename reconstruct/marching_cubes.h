#pragma once
// Sparse marching cubes (Lorensen & Cline 1987) on a uniform grid: only the cells
// the surface passes through are visited, found by continuation from seed cells
// (Wyvill-style surface tracking), so memory grows with the surface area, not with
// resolution^3. The lattice near the surface lives in blocks of 4^3 points created as
// the walk reaches them (float values, bit masks for evaluated / visited / crossed,
// vertex ids of crossed edges by popcount; docs/dmc.md, "Sparse storage"): no hash
// lookup per point, each lattice value evaluated once, walk and mesh parallel. The
// case table is derived at start-up from one rule per cube face (reconstruct/mc_tables.h):
// on an ambiguous face the inside (f < iso) corners are kept apart. The rule depends
// only on the face's four corners, so the two cells sharing a face agree and the mesh
// is watertight on closed surfaces.
#include <vector>

#include "core/geometry.h"
#include "reconstruct/implicit.h"

namespace station {

class MpuSurface;

/// What to do where ImplicitFunction::trusted() is false (no data near; e.g. the
/// underside a turntable never sees).
enum class UntrustedRegions {
  kClose,     ///< keep the extrapolated surface: closes the hole smoothly (watertight)
  kLeaveOpen, ///< drop triangles whose centroid is untrusted: an open mesh, no invented surface
};

struct MarchingCubesOptions {
  /// Iso-value: the surface is f = iso; inside is f < iso.
  double iso = 0;
  /// Points on or near the surface (e.g. the input cloud) where the walk starts. Empty:
  /// the grid is scanned along lines every coarse_step cells in y and z (finds every
  /// surface component crossing one of those lines).
  std::vector<Vec3f> seeds;
  /// Spacing (in cells) of the scan lines when there are no seeds; 0 = max(1, resolution / 32).
  int coarse_step = 0;
  /// Vertex normals from the normalised gradient (outward for f > 0 outside).
  bool normals = true;
  UntrustedRegions untrusted = UntrustedRegions::kClose;
  /// Treat the grid's outermost vertices as outside (f > iso), so a surface that would
  /// leave the box is capped by a lid just inside it and the mesh stays closed.
  bool close_at_box = false;
  /// Threads for the function evaluations (0 = all cores). The mesh does not depend on it.
  int threads = 0;
};

struct MarchingCubesStats {
  std::size_t cells_visited = 0;    ///< cells whose corners were evaluated
  std::size_t surface_cells = 0;    ///< cells the surface crosses
  std::size_t evaluations = 0;      ///< f evaluations at grid vertices
  std::size_t dropped_faces = 0;    ///< faces removed as untrusted
  double cell_size = 0;             ///< h, input units
};

/// Triangle mesh of {f = iso} inside `box` on a grid of `resolution` cells along the
/// box's longest side (cubic cells of side h = longest side / resolution). Vertices
/// are shared between cells (one per crossed grid edge, linear interpolation),
/// faces counter-clockwise seen from outside (f > iso). The surface is cut open where
/// it leaves the box. Deterministic for any thread count.
/// InvalidInput on an invalid or degenerate box, resolution < 1 or > 2^20.
Mesh extract_marching_cubes(const ImplicitFunction& f, const Aabb& box, int resolution,
                            const MarchingCubesOptions& options = {},
                            MarchingCubesStats* stats = nullptr);

/// The extraction box of an MPU surface: the input's bounding box grown by 5 % of
/// its longest side on every side (used by both extractors' MpuSurface overloads).
Aabb extraction_box(const MpuSurface& surface);

/// The MPU surface's mesh: the box is the input's bounding box grown by 5 % of its
/// longest side on every side, the seeds are the input points (options.seeds is
/// replaced), close_at_box is set: where MPU's
/// extrapolation beyond the data (e.g. a turntable scan's unseen underside) leaves
/// the box, it is capped there, so with kClose the mesh is watertight; with kLeaveOpen the
/// extrapolated part and the cap are dropped wherever they are far from the data.
Mesh extract_marching_cubes(const MpuSurface& surface, int resolution,
                            MarchingCubesOptions options = {},
                            MarchingCubesStats* stats = nullptr);

}  // namespace station
