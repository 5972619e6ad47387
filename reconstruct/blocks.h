#pragma once
// Block-wise surface stage (issue 29, docs/blocks.md): a cloud too large for one
// machine is cut into blocks of one global extraction lattice; each block fits MPU
// (and the colour function) on its own points plus a margin, and extracts the cells
// of its window of the lattice. The blocks' meshes are stitched into one, vertex for
// vertex, because the lattice values on a face two blocks share are the same
// numbers in both: a lattice point belongs to the block whose half-open window
// holds it, that block evaluates its lower faces first and the blocks below it take
// those values (SeamValues), so both sides see the same crossings there. The blocks
// run in an order where every block's upper neighbours are done first
// (block_order), in sequence on one machine or spread over MPI ranks
// (station/blocks_run.cpp).
//
// What the blocks share is decided once from a summary of the whole cloud (every
// k-th point, BlockSummary): the tolerance, the hole mode, the resolution, the
// trust distance, the table height, and the far field of the winding closing.
#include <array>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "core/geometry.h"
#include "reconstruct/colour_function.h"
#include "reconstruct/dmc.h"
#include "reconstruct/implicit.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/surface.h"

namespace station {

/// The global lattice cut into blocks.
struct BlockGrid {
  LatticeWindow lattice;           ///< offset 0, cells = global_cells: the whole lattice
  std::array<int, 3> counts{1, 1, 1};  ///< blocks per axis
  /// Block boundaries per axis: splits[a][0] = 0 < ... < splits[a][counts[a]] = cells.
  std::array<std::vector<int>, 3> splits;
  double margin = 0;  ///< points within this distance of a block's window are its points too

  int size() const { return counts[0] * counts[1] * counts[2]; }
  /// Block id of (bi, bj, bk): bi + counts[0] * (bj + counts[1] * bk).
  int id(int bi, int bj, int bk) const { return bi + counts[0] * (bj + counts[1] * bk); }
  std::array<int, 3> coords(int id) const;
  /// The window of the lattice block `id` extracts.
  LatticeWindow window(int id) const;
  /// The window's box grown by the margin (the points the block loads).
  Aabb region(int id) const;
  /// Whether the global lattice plane `index` across axis a is a boundary between blocks.
  bool seam_plane(int a, int index) const;
  /// Whether a vertex on lattice edge `edge_key` lies on a face two blocks share.
  bool on_seam(std::uint64_t edge_key) const;
  /// The block whose window holds lattice point (i, j, k) (half-open, the last plane
  /// with the last block).
  int owner(int i, int j, int k) const;
};

/// A lattice point as a key (lattice_edge_key with axis 3).
inline std::uint64_t lattice_point_key(int i, int j, int k) { return lattice_edge_key(i, j, k, 3); }

/// Values of lattice points, by lattice_point_key. With DMC a table also carries where
/// a block moved a lattice point of its lower faces: the point's three coordinates
/// under seam_position_key(its key, axis); such a point's value is at its position.
using SeamTable = std::unordered_map<std::uint64_t, double>;

/// The key of coordinate `axis` (0, 1, 2) of a moved lattice point (bits 62-63 of its
/// lattice_point_key, otherwise 0, set to axis + 1), and of its DMC flags (the axis
/// bits 60-61 cleared, bit 62 set).
inline std::uint64_t seam_position_key(std::uint64_t point_key, int axis) {
  return point_key | std::uint64_t(axis + 1) << 62;
}
inline std::uint64_t seam_flags_key(std::uint64_t point_key) {
  return (point_key & ~(std::uint64_t(3) << 60)) | std::uint64_t(1) << 62;
}
inline bool is_seam_position_key(std::uint64_t key) { return key >> 62 != 0; }

/// Cells of the lattice below a block's lower faces that its DMC also deforms
/// (DmcOptions::halo), so that the points of those faces move as on the whole lattice.
inline constexpr int kDmcHaloCells = 2;

/// Cuts the lattice of `box` at `resolution` (the same cell as extract_marching_cubes)
/// into about `blocks` blocks (at most that many: the longest block side is halved
/// first), each loading its points within `margin` of its window. InvalidInput for an
/// invalid box, a resolution outside [1, 2^20) or blocks < 1.
BlockGrid plan_blocks(const Aabb& box, int resolution, int blocks, double margin);

/// An order of the blocks in which each block comes after every block holding a
/// lattice point of its window's upper faces (its +x, +y, +z neighbours and those
/// across their edges and corner): decreasing (bk, bj, bi). wave(id) numbers the
/// anti-diagonal (bi + bj + bk, largest first = wave 0): blocks of one wave depend
/// only on earlier waves, so they can run at once.
std::vector<int> block_order(const BlockGrid& grid);
int block_wave(const BlockGrid& grid, int id);

/// f with the lattice values of a table: at a position on a lattice point the table
/// holds, value() returns the table's value; everything else (other points, the
/// gradients, trust, sharpness) is f's.
class SeamValues : public ImplicitFunction {
 public:
  SeamValues(const ImplicitFunction& f, const LatticeWindow& lattice, const SeamTable& table)
      : f_(f), origin_(lattice.origin), h_(lattice.h), table_(table) {}
  double value(const Vec3d& x) const override;
  Vec3d gradient(const Vec3d& x) const override { return f_.gradient(x); }
  bool trusted(const Vec3d& x) const override { return f_.trusted(x); }
  bool may_be_trusted_near(const Vec3d& x, double radius) const override { return f_.may_be_trusted_near(x, radius); }
  bool may_be_sharp(const Vec3d& x, double radius) const override { return f_.may_be_sharp(x, radius); }
  void values_near(const Vec3d* xs, int n, double* out) const override;
  void gradients_near(const Vec3d* xs, int n, Vec3d* out) const override { f_.gradients_near(xs, n, out); }
  void values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const override;

 private:
  const double* lookup(const Vec3d& x) const;
  const ImplicitFunction& f_;
  Vec3d origin_;
  double h_;
  const SeamTable& table_;
};

/// What every block shares, decided from a summary of the whole cloud.
struct BlockSummary {
  Cloud far_field;           ///< every k-th point (with normals): the winding closing's far field
  std::size_t every = 1;     ///< k
  std::size_t points = 0;    ///< the whole cloud's points
  Aabb bounds;               ///< the whole cloud's bounds
  bool colours = false;      ///< the cloud has colours
  double epsilon0 = 0;
  HoleMode hole = HoleMode::kClose;  ///< resolved (never kAuto)
  std::optional<double> enclosure;   ///< with kAuto: cloud_enclosure of the summary
  bool flip_normals = false;         ///< kAuto found the normals facing inwards: each block turns them
  double mean_spacing = 0;    ///< the whole cloud's, estimated from the summary
  double sample_spacing = 0;  ///< likewise
  int resolution = 0;
  bool resolution_auto = false;
  std::optional<double> table_height;  ///< with a table plane: the lowest point along up
  Aabb box;                  ///< the extraction box (bounds grown by 5 % of the longest side)
};

/// Summary points: every k-th point, k = max(1, points / kSummaryPoints).
inline constexpr std::size_t kSummaryPoints = 200000;

/// Streams a cloud in chunks: calls `chunk` with consecutive pieces (normals and
/// colours as the source has them), in file order. Throws what the reader throws.
using CloudSource = std::function<void(const std::function<void(const Cloud& chunk)>& chunk)>;

/// A CloudSource over a cloud in memory (one chunk).
CloudSource memory_source(const Cloud& cloud);

/// The summary and the shared decisions. InvalidInput when the cloud is empty, has no
/// normals ("blocks need oriented normals: ..."), or non-finite coordinates.
BlockSummary summarise_cloud(const CloudSource& source, const SurfaceParams& params);

/// The margin of the blocks: far enough for MPU's support near the window's faces and
/// for the closing's trust ramp: max(kMarginCells cells, or kKeepMarginCells with the
/// holes kept, 8 mean spacings).
double block_margin(const BlockSummary& summary, double cell);
inline constexpr double kMarginCells = 8;
/// With the holes kept: the rims lie where the points thin out, and MPU's balls there
/// reach further (the dragon session's kept mesh in blocks was 0.84 cell from the
/// single one with 8 cells, 0.32 with 12).
inline constexpr double kKeepMarginCells = 12;

/// Memory of a block run per rank, as measured (docs/blocks.md: the bottle at 1 M
/// points, 4 to 64 blocks, colour on): a base (the process, the summary and its
/// closing) plus so many bytes per point of the largest block (its fit, its colour
/// function, its window's extraction).
inline constexpr double kBlockBaseBytes = 256.0 * 1024 * 1024;
inline constexpr double kBlockBytesPerPoint = 1536;
/// A lattice finer than the points' sample spacing (a --resolution above auto) makes
/// more surface cells than points: each point stands for (spacing / cell)^2 cells,
/// and each cell beyond the first costs this much: the slope from 600 to 1200 cells
/// on the bundled bottle session's 300k merged points in 4 blocks (333 and 682 MiB;
/// 269 MiB at the auto 446 cells, where the points' term alone over-estimates).
inline constexpr double kBlockBytesPerExtraCell = 800;

/// Each block's points (its region's, margin included), estimated from the summary
/// (its points, each standing for `every`).
std::vector<std::size_t> estimate_block_points(const BlockSummary& summary, const BlockGrid& grid);
/// A rank's peak memory for a run on `grid`: base + per point x the largest block's,
/// + per extra surface cell where the cell is finer than the points' sample spacing.
double estimate_block_bytes(const BlockSummary& summary, const BlockGrid& grid);

/// The block count of a run: `blocks` 0 is auto (a block per kAutoBlockPoints); with
/// `max_bytes` > 0 the fewest blocks whose estimate fits (when `blocks` is 0 or 1), or
/// `blocks` checked against it. Auto and the memory's count give every one of `ranks`
/// ranks at least kAutoBlocksPerRank blocks. InvalidInput, before any block runs, when
/// no count up to 4096 fits or the asked count does not (the message says what would).
int resolve_block_count(const BlockSummary& summary, int blocks, double max_bytes, int ranks = 1);
/// The ranks of one wave's blocks (`ids`): the largest first (by `points`, per block
/// id, e.g. estimate_block_points), each to the rank with the fewest points so far;
/// the same on every rank. Returns a rank per entry of `ids`.
std::vector<int> assign_blocks(const std::vector<int>& ids, const std::vector<std::size_t>& points, int ranks);

/// Auto: about 1.1 GB per rank at the measured rate (below 2 GB with the margins).
inline constexpr std::size_t kAutoBlockPoints = 500000;
inline constexpr int kAutoBlocksPerRank = 4;

/// One block's piece of the mesh and what the stitching needs.
/// The `edges` entry of a vertex on no lattice edge (a colour-edge split's): never on a seam.
inline constexpr std::uint64_t kNoLatticeEdge = ~std::uint64_t(0);

struct BlockMesh {
  Mesh mesh;
  std::vector<std::uint64_t> edges;  ///< per vertex: its lattice edge (lattice_edge_key), or kNoLatticeEdge
  std::vector<char> far;             ///< per vertex, with holes kept: beyond the rim-trim bound
  /// Per vertex, with SurfaceParams::boundary_flags and the colour function: 1 where a
  /// Type B (split) colour cell dominates (SurfaceResult::colour_boundary).
  std::vector<std::uint8_t> boundary;
  std::size_t points = 0;            ///< the block's points (window and margin)
  std::size_t colour_nearest_vertices = 0;
  std::size_t colour_edges_split = 0;  ///< edges split at colour boundaries (none on shared faces)
  /// The block's colour function (kMpu): its points, leaves (by type) and e_col; the
  /// stitched result's are their sums, e_col weighted by the points (margins counted).
  std::optional<ColourDiagnostics> colour;
  MpuDiagnostics mpu;
  DmcStats dmc;
  double seconds = 0;
};

/// The lattice values block `id` owns on its lower faces (the faces shared with the
/// blocks below it), from f at the lattice points exactly (origin + h * index).
SeamTable lower_face_values(const ImplicitFunction& f, const BlockGrid& grid, int id, int threads);

/// DMC's options for block `id`'s window (o.window set by the caller): a halo of
/// kDmcHaloCells below its lower faces, the points of its upper faces where `upper`
/// puts them, with the flags DMC gave them there (`given` holds them; keep it alive through the extraction), and its lower
/// faces' final values and positions into `lower` (which holds their lattice values,
/// lower_face_values, and must outlive the extraction).
void block_dmc_seams(DmcOptions& o, const BlockGrid& grid, int id, const SeamTable& upper, SeamTable& lower,
                     std::unordered_map<std::uint64_t, DmcPoint>& given);

/// The surface stage on one block: `points` are the block's (its region's), `upper`
/// holds the lattice values of its upper faces (from the blocks above, lower_face_values);
/// its own lower-face values go to `lower`. With DMC, the lower faces' points move as
/// on the whole lattice (a halo of kDmcHaloCells below them), and `lower` takes their
/// final values and positions; the upper faces' points stay where `upper` puts them.
/// Extracts the block's window only; no small pieces dropped, no rim trim (the
/// stitched mesh's); colour-edge splits except on the edges of shared faces.
BlockMesh reconstruct_block(const Cloud& points, const BlockGrid& grid, int id, const BlockSummary& summary,
                            const SurfaceParams& params, const SeamTable& upper, SeamTable& lower);

/// The blocks' meshes as one: vertices on shared faces are joined by their lattice edge
/// (the first block's position, normal and colour kept). `far` and `boundary` get the
/// joined vertices' flags when given (boundary: empty unless every piece has them).
Mesh stitch_blocks(std::vector<BlockMesh>& pieces, const BlockGrid& grid, std::vector<char>* far = nullptr,
                   std::vector<std::uint8_t>* boundary = nullptr);

/// The points of `source` inside block `id`'s region.
Cloud block_points(const CloudSource& source, const BlockGrid& grid, int id);

/// One streamed pass over `source` that sorts the points of the blocks `ids` into a
/// file each, `path(id)`: block_points's points, in the same order, for every one of
/// them at once (a rank reads the input once, not once a block). Each file records
/// its block's region (the grid it was sorted for) and its point count, is written as
/// `path(id)` + ".part" and renamed when the pass is done, so a file at `path(id)` is
/// whole. Memory: at most flush_points points a block, and kBucketBufferPoints in all
/// (not below 1024 a block). InvalidInput on repeated or out-of-range ids; IoError
/// naming the file when a write fails (a full disk); the .part files are removed then.
void bucket_points(const CloudSource& source, const BlockGrid& grid, const std::vector<int>& ids,
                   const std::function<std::string(int)>& path, std::size_t flush_points = 65536);
inline constexpr std::size_t kBucketBufferPoints = 4u << 20;
/// A bucket file's points. FormatError naming `path` on a file that is not one (cut
/// short, another file) or, with `region`, one sorted for another block's region.
Cloud read_bucket(const std::string& path, const Aabb* region = nullptr);
/// Whether the bucket file at `path` was sorted for `region` (false when it is not a
/// bucket file or cannot be read).
bool bucket_matches(const std::string& path, const Aabb& region);

struct BlockRunStats {
  int blocks = 0;
  std::array<int, 3> counts{1, 1, 1};
  std::size_t max_block_points = 0;
  std::size_t seam_vertices_joined = 0;
  std::size_t vertices = 0, faces = 0;  ///< the stitched mesh's
};

/// A CloudSource streaming a PLY file (stream_ply_points, 65,536 points at a time);
/// other formats are read whole.
CloudSource file_source(const std::string& path);

/// Bytes of a summary, a block's mesh and a seam table, and back (for ranks that
/// exchange them through a shared folder, and --resume). The readers throw
/// FormatError naming `what` on bytes that are not what they should be.
std::string to_bytes(const BlockSummary& summary);
BlockSummary summary_from_bytes(const std::string& bytes, const std::string& what);
std::string to_bytes(const BlockMesh& piece);
BlockMesh piece_from_bytes(const std::string& bytes, const std::string& what);
std::string to_bytes(const SeamTable& table);
SeamTable table_from_bytes(const std::string& bytes, const std::string& what);

/// The blocks' pieces, in this process, block after block, before they are stitched.
struct BlockPieces {
  BlockSummary summary;
  BlockGrid grid;
  std::vector<BlockMesh> pieces;  ///< by block id
};
BlockPieces reconstruct_block_pieces(const CloudSource& source, const SurfaceParams& params, int blocks,
                                     BlockRunStats* stats = nullptr, double max_bytes = 0);

/// The whole block-wise surface stage in this process, block after block (memory:
/// one block's points and fits at a time, plus the meshes). `blocks` and `max_bytes`
/// as resolve_block_count's.
SurfaceResult reconstruct_surface_blocks(const CloudSource& source, const SurfaceParams& params, int blocks,
                                         BlockRunStats* stats = nullptr, double max_bytes = 0);

/// The blocks' pieces (in block id order) stitched and finished as the single run
/// finishes its mesh (rims trimmed with holes kept, small pieces dropped), with the
/// summary's decisions in the result. InvalidInput when the surface is empty.
SurfaceResult assemble_blocks(std::vector<BlockMesh>& pieces, const BlockGrid& grid, const BlockSummary& summary,
                              const SurfaceParams& params, BlockRunStats* stats = nullptr);

/// assemble_blocks without the mesh in memory: the pieces are loaded one at a time
/// (`load(id)`, twice each, in id order) and the stitched mesh goes straight into a
/// binary PLY at `path` (atomic), its faces through the file `scratch` (removed after).
/// Memory: one piece, plus the shared faces' vertices. With holes closed it writes
/// assemble_blocks's mesh byte for byte; with holes kept the rims are trimmed block
/// by block, with the edges on shared faces never counted as open, so a rim that
/// meets a seam may keep a few faces the stitched mesh's trim drops. The result holds
/// no mesh: stats->vertices and faces say what was written.
SurfaceResult write_blocks_ply(const std::function<BlockMesh(int)>& load, const BlockGrid& grid,
                               const BlockSummary& summary, const SurfaceParams& params, const std::string& path,
                               const std::string& scratch, BlockRunStats* stats = nullptr);

}  // namespace station
