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
#include <array>
#include <cstdint>
#include <optional>
#include <vector>

#include "core/geometry.h"
#include "reconstruct/implicit.h"

namespace station {

class MpuSurface;

/// A window onto a larger lattice (block-wise extraction, reconstruct/blocks.h):
/// lattice point (i, j, k) of the window is point offset + (i, j, k) of the global
/// lattice, at origin + h * (offset + (i, j, k)) exactly (the same double in every
/// window), and the window's cells are offset + [0, cells) per axis. close_at_box
/// then caps at the global lattice's outermost layer (0 and global_cells), not at
/// the window's, so two windows that share a face see the same lattice there.
struct LatticeWindow {
  Vec3d origin = Vec3d::Zero();
  double h = 0;
  std::array<int, 3> offset{0, 0, 0};
  std::array<int, 3> cells{1, 1, 1};
  std::array<int, 3> global_cells{1, 1, 1};
};

/// InvalidInput (naming `who`) unless the window lies inside its global lattice, with
/// a finite origin and h > 0.
void check_window(const LatticeWindow& window, const char* who);

/// A global lattice edge as one 64-bit key: its lower end (i, j, k), 20 bits each,
/// and its axis (0, 1, 2) in the top bits. Vertices of windows that share a face
/// are the same vertex exactly when their keys are equal.
inline std::uint64_t lattice_edge_key(int i, int j, int k, int axis) {
  return std::uint64_t(i) | std::uint64_t(j) << 20 | std::uint64_t(k) << 40 | std::uint64_t(axis) << 60;
}

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
  /// Set: extract on this window of a larger lattice; the box and resolution
  /// arguments are then ignored (the window's own checks apply).
  std::optional<LatticeWindow> window;
  /// Non-null: filled with each output vertex's lattice_edge_key in the global
  /// lattice (the window's, or the box's lattice), in vertex order, after any
  /// untrusted faces were dropped.
  std::vector<std::uint64_t>* vertex_edges = nullptr;
};

struct MarchingCubesStats {
  std::size_t cells_visited = 0;    ///< cells whose corners were evaluated
  std::size_t surface_cells = 0;    ///< cells the surface crosses (kLeaveOpen: those the walk kept)
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
