#pragma once
// The surface stage, composed once for every caller (`station reconstruct`, the
// surface stage of `station run`, the benches): a cloud with (or without)
// normals -> MPU implicit surface -> closing of the unseen parts (winding number)
// -> table plane -> extraction (Deformed Marching Cubes or marching cubes) ->
// small pieces dropped -> colour (MPU colour function, or nearest-neighbour
// transfer) -> edges split at colour boundaries. docs/architecture.md.
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "core/geometry.h"
#include "reconstruct/colour_function.h"
#include "reconstruct/dmc.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/mesh_clean.h"
#include "reconstruct/mpu.h"

namespace station {

enum class Extractor { kDmc, kMarchingCubes };
/// Where there is no data: closed (watertight), kept open, or decided by the data:
/// kAuto closes a cloud that encloses a volume (cloud_enclosure at least
/// kEnclosedAbove, reconstruct/winding_close.h) and keeps a one-sided patch open
/// (a single view, a wall fragment) instead of inflating it into a slab.
enum class HoleMode { kClose, kKeep, kAuto };
enum class ColourMethod { kMpu, kNearest };

/// HoleMode::kAuto's bound for a cloud whose views surround the object (a turntable
/// session, every gap between the views' turns under 120 degrees): the object on the
/// table is a solid, so a lower enclosure than kEnclosedAbove's 0.75 closes it. A CAD
/// part with holes and recesses scanned all round read 0.72 and was left open (mean
/// distance to the part 4.8 mm open, 1.7 mm closed); a hemisphere reads 0.65, a
/// single view 0.2-0.5, a plate seen from both sides 0.40 (kept open).
inline constexpr double kEnclosedAboveSurrounded = 0.6;

struct SurfaceParams {
  /// MPU tolerance epsilon_0; 0: from the cloud's noise level (suggest_epsilon0),
  /// at least MpuParams' default (the paper's 1e-4).
  double epsilon0 = 0;
  /// Cells along the longest side of the extraction box; 0 = auto: the cell follows
  /// the cloud's sample spacing, 1 / sqrt(density) (auto_resolution).
  int resolution = 0;
  Extractor extractor = Extractor::kDmc;
  /// The unseen parts: closed smoothly (watertight), or left open where there is no data.
  HoleMode hole = HoleMode::kAuto;
  /// With kAuto: the enclosure (cloud_enclosure) from which the cloud is closed:
  /// kEnclosedAbove (reconstruct/winding_close.h), or kEnclosedAboveSurrounded where the
  /// caller knows the views surround the object (`station run` on a turntable session).
  double enclosed_above = 0.75;
  /// With kClose: far from the data, inside and outside by the winding number of the
  /// oriented cloud, not MPU's extrapolation (reconstruct/winding_close.h).
  bool winding_close = true;
  /// With kClose: the table plane. The object rests on a table whose normal is `up`
  /// (the turntable axis in the cloud's frame): no surface below the cloud's lowest
  /// point along it, so the underside closes flat there. Unset: no table plane.
  std::optional<Vec3d> table_up;
  bool colour = true;  ///< colour the mesh when the cloud has colours
  ColourMethod colour_method = ColourMethod::kMpu;
  bool colour_multi = false;         ///< colour function: 3+ colours per cell (junctions)
  bool colour_noise_robust = false;  ///< colour function: no boundaries invented by noise
  /// Split mesh edges at colour boundaries (reconstruct/colour_edges.h; kMpu only).
  bool colour_edges = true;
  /// Drop pieces below this fraction of the largest piece's area (0 keeps all).
  double min_component = 0.01;
  /// Also flag, per vertex, where a colour-boundary (Type B) cell dominates (the
  /// report's picture). kMpu only.
  bool boundary_flags = false;
  /// How a too fine resolution is named in the memory check's error (e.g.
  /// "--resolution 4096"); empty: "resolution N".
  std::string resolution_name;
  /// The scans `input` was consolidated from (e.g. the registered views merged), with
  /// normals: after extraction the vertices move onto a local fit of them
  /// (reconstruct/scan_snap.h), so the mesh keeps the scans' detail that thinning and
  /// evening smoothed, where a held-out half of the scans says that helps. nullptr:
  /// the mesh stays on the fitted surface.
  const Cloud* scans = nullptr;
  double snap_significance = 0;  ///< ScanSnapParams::significance
  int threads = 0;  ///< 0 = all cores; the mesh does not depend on it
  /// Progress lines (what is being done, with its figures); may be empty.
  std::function<void(const std::string&)> note;
};

struct SurfaceTimings {
  double normals = 0, fit = 0, closing = 0, extract = 0, colour = 0, total = 0;  ///< seconds
  /// The mesh back to the scans: the snap, the scans' index and the rims' trim to them
  /// (the small pieces they support are decided after, outside this figure).
  double scans = 0;
};

struct SurfaceResult {
  Mesh mesh;
  bool normals_estimated = false;  ///< the cloud had none: PCA + MST orientation
  double epsilon0 = 0;             ///< the tolerance used
  HoleMode hole = HoleMode::kClose;  ///< the mode used (kAuto resolved to one of the others)
  std::optional<double> enclosure;   ///< with kAuto: cloud_enclosure of the input (after any turn)
  /// With kAuto: the cloud enclosed at most -kEnclosedAbove (all normals inwards) and
  /// its normals were turned before the fit.
  bool normals_flipped = false;
  MpuDiagnostics mpu;
  std::size_t winding_points = 0;  ///< clusters of the winding closing (0: not used)
  double winding_trust = 0;        ///< its trust distance
  std::optional<double> table_height;  ///< the table plane's height along up, when clipped
  double expected_faces = 0;       ///< the memory check's estimate (0: not checked)
  int resolution = 0;              ///< the resolution used (params' or the automatic one)
  bool resolution_auto = false;    ///< chosen by auto_resolution
  MarchingCubesStats extraction;   ///< cell size and counts (either extractor)
  DmcStats dmc;                    ///< DMC's own counts (zero with marching cubes)
  std::size_t rim_faces = 0;        ///< kKeep: faces dropped at the open rims
  std::size_t scan_rim_faces = 0;   ///< kKeep with scans: faces then dropped at rims beyond the scans
  std::size_t snapped_vertices = 0; ///< with SurfaceParams::scans: vertices moved onto them
  double snap_mean_move = 0;        ///< their mean move, input units
  bool snap_declined = false;       ///< the scans' held-out half said the snap would not help
  ComponentFilterStats pieces;
  bool coloured = false;
  std::size_t colour_nearest_vertices = 0;  ///< kMpu: vertices coloured from the nearest point
  std::size_t colour_edges_split = 0;
  std::optional<ColourDiagnostics> colour;  ///< kMpu
  std::vector<std::uint8_t> colour_boundary;  ///< with boundary_flags: 1 per Type B vertex
  SurfaceTimings seconds;
};

/// The automatic resolution: the extraction box's longest side over the cloud's
/// sample spacing (MpuDiagnostics::sample_spacing, 1 / sqrt(density); one cell per
/// spacing: finer cells only interpolate between the points, coarser ones drop detail
/// the points hold; the nearest neighbour's distance is half the spacing on random
/// samples and made 4x the vertices there, issue 27),
/// clamped to kAutoResolutionMin..kAutoResolutionMax (beyond 512 the memory check
/// runs: ask for it explicitly).
int auto_resolution(double longest_side, double spacing);
inline constexpr int kAutoResolutionMin = 64;
inline constexpr int kAutoResolutionMax = 512;

/// With HoleMode::kKeep, MPU trusts its surface within this many mean spacings of
/// the points (MpuParams::trust_factor; 4 otherwise): beyond it the mesh is left
/// open. Measured on the real dragon session (docs/run.md, issue 32): mesh ->
/// scans mean / p95 0.54 / 2.62 mm at 4, 0.33 / 1.17 at 2, 0.29 / 0.81 at 1.5,
/// scans -> mesh 0.126, 0.130 and 0.135 mm (the holes grow with a smaller factor).
inline constexpr double kKeepTrustFactor = 2.0;
/// With HoleMode::kKeep, faces at the open rims with a vertex further than this
/// many mean spacings from the points are dropped, ring by ring (trim_open_rims,
/// reconstruct/mesh_clean.h): the rims come back to the data instead of flaring
/// past it. Measured on the dragon session (trust 2): mesh -> scans mean / p95
/// 0.253 / 0.665 mm untrimmed, 0.235 / 0.520 at 2, 0.225 / 0.467 at 1.75, 0.217 /
/// 0.428 at 1.5, 0.199 / 0.369 at 1; scans -> mesh 0.082, 0.082, 0.084, 0.093,
/// 0.134 mm (the rims retreat from the data's edge too). Trimming instead of a
/// smaller trust keeps holes out of sparse interiors (trust 4 + trim 1.5: 0.236 /
/// 0.507, 0.089).
inline constexpr double kRimTrimFactor = 1.5;
/// With HoleMode::kKeep and SurfaceParams::scans (after the snap, unless the scans
/// hardly meet the mesh): the open rims are trimmed again, ring by ring, back to
/// within this many of the scans' median sample spacings (core/kdtree.h
/// sample_spacing) of a scan point; and a piece below `min_component` stays when at
/// least kPieceMinScans scan points lie nearest to it within that distance.
/// Consolidation thins the scans and pulls their borders in, so the rims trimmed to
/// the consolidated points (above) still flare past sparse scans, and sparse real
/// surface (a crevice) is left as pieces too small for the area bound. Measured on
/// the dragon session at 505 cells (docs/run.md): mesh -> scans mean / p95 0.217 /
/// 0.434 -> 0.202 / 0.377 mm, scans -> mesh 0.088 -> 0.078 mm (trimmed Poisson at
/// depth 9: 0.220 / 0.434, 0.081). Where the scans are as dense as their median, a
/// vertex on their surface lies beyond 1.5 spacings of every scan point with
/// probability exp(-2.25 pi) < 0.1 %; where they are sparser the trim reaches into
/// them (3-18 % at 4-2 points per mm^2 on the dragon, against its median 8.4), which
/// the measured scans -> mesh includes. Closed meshes are left as they were.
/// Where the nearest scan point's own spacing is sparse (sparse_allowance,
/// core/kdtree.h: 1.5 times the median or more, at most 4 times, so that a depth
/// camera's flying pixel, which reads as very sparse, holds no rim near it), the bound
/// is 1.5 of that one: a depth camera's far field (the Kinect scene: 5 % of the scan
/// points beyond 1.6 m made all of the gap to trimmed Poisson on scans -> mesh).
inline constexpr double kScanRimFactor = 1.5;
/// The scan points a small piece needs to stay (above): as many as one local fit of
/// the snap needs (ScanSnapParams::min_points).
inline constexpr std::size_t kPieceMinScans = 12;

/// The surface stage's e_col (ColourDiagnostics::e_col, a figure of the report) is
/// taken over at most this many input points, evenly strided
/// (ColourParams::e_col_max_points).
inline constexpr std::size_t kEColPoints = 50000;

/// The colour function's parameters of the surface stage (also the SDM surface's).
ColourParams colour_params(const SurfaceParams& params);

/// suggest_epsilon0 with the defaults, for a surface to be reconstructed from `cloud`:
/// too few points or all at one point are said in a user's terms ("1 point: too few to
/// reconstruct a surface from (at least 50 are needed)"), not in suggest_epsilon0's.
double surface_epsilon0(const Cloud& cloud);

/// The whole surface stage on `cloud` (normals estimated when missing). InvalidInput
/// for an empty cloud, an empty surface, or a resolution whose mesh would not fit in
/// the memory available (check_extraction_fits).
SurfaceResult reconstruct_surface(Cloud cloud, const SurfaceParams& params);

/// Before an extraction finer than 512 cells: marching cubes at 64 cells counts the
/// faces, which grow with the square of the resolution, and the peak memory is
/// estimated from them (kExtractionBytesPerFace). InvalidInput naming `what` (e.g.
/// "--resolution 4096"), with the finest resolution that would fit, when that is more
/// than 85 % of `available_bytes` (< 0: the machine's MemAvailable from /proc/meminfo;
/// no check when it cannot be read). Returns the estimated faces (0 when not checked).
double check_extraction_fits(const ImplicitFunction& f, const Aabb& box, int resolution,
                             const MarchingCubesOptions& options, const std::string& what,
                             double available_bytes = -1);
/// Peak bytes per output face of the surface stage (MPU + DMC) at high resolution,
/// measured on a 3,000-point sphere: 159 at 1024 cells (8.2 M faces, 1.3 GB), 128 at
/// 4096 (131 M faces, 16.7 GB).
inline constexpr double kExtractionBytesPerFace = 150;

/// How progress lines name an extractor, everywhere.
const char* extractor_label(Extractor extractor);

/// A SurfaceParams::note line as a command prints it: `prefix` + line, except the
/// notes about the input (no normals, no colours), which become `note_prefix` +
/// "FILE has no ..." naming `input`.
std::string surface_note(const std::string& input, const std::string& line, const std::string& prefix,
                         const std::string& note_prefix);

}  // namespace station
