#pragma once
// Consolidation in blocks (issue 29, docs/blocks.md "Consolidation in blocks"): WLOP
// is local (every term of eq. 1 reaches h at most), so a cloud too large for one
// process is consolidated block by block. The blocks are boxes of the cloud's bounds;
// each consolidates its points within a margin of kWlopMarginRadii h of its box, at the
// whole cloud's scale (h, r_f and eq. 10 from the whole cloud's d_bb and |J|:
// WlopParams::frame_diagonal / frame_points), with its share of |I|, and keeps the
// output points inside its box. Blocks do not depend on each other: they run in any
// order, on any rank.
#include <cstddef>
#include <functional>
#include <string>
#include <vector>

#include "reconstruct/blocks.h"
#include "reconstruct/wlop.h"

namespace station {

/// The margin of a WLOP block, in units of h: the attraction and the densities reach
/// h, the repulsion less, and a point moves a fraction of h an iteration.
inline constexpr double kWlopMarginRadii = 4;
/// `blocks` 0 (auto): a block per this many input points.
inline constexpr std::size_t kAutoWlopBlockPoints = 2'000'000;

/// A WLOP block's peak memory, fitted on the bench (docs/blocks.md: 269 MiB at 1 M
/// points, 866 MiB at 5 M): a base and a cost a point of its region.
inline constexpr double kWlopBaseBytes = 128.0 * (1 << 20);
inline constexpr double kWlopBytesPerPoint = 160;

/// The block count for `points` input points: `blocks` when it is a count, else (0,
/// auto) a block per kAutoWlopBlockPoints, and with `max_bytes` > 0 at least as many
/// as keep a block (its margin counted as a third more points) within it.
/// InvalidInput when max_bytes cannot hold a block of 100,000 points.
int wlop_block_count(std::size_t points, int blocks, double max_bytes);

/// What the blocks of one WLOP run share: one streamed pass over the cloud.
struct ConsolidationPlan {
  std::size_t points = 0;         ///< |J| of the whole cloud
  Aabb bounds;                    ///< its bounds
  double diagonal = 0;            ///< its d_bb
  double radius = 0;              ///< h (params.radius, or 4 d_bb / sqrt |J|)
  std::size_t output_points = 0;  ///< |I| of the whole run, as consolidate() would take it
  /// The input points in each block's box (its share of |I| with kL1; the ranks'
  /// assignment).
  std::vector<std::size_t> box_points;
  /// kProjection: the surface's area, estimated on every k-th point (k = |J| / 200,000)
  /// as consolidate() estimates it (each point standing for pi rho^2 / 15, rho the
  /// distance to its 16th nearest); the blocks' shares of |I| follow the area, as the
  /// single run's spread-out start does. 0 with kL1, where the shares follow the points
  /// (the single run's random start does).
  double area = 0;
  BlockGrid grid;                 ///< the blocks; margin kWlopMarginRadii h
};

/// The plan of consolidating `source` with `params` in about `blocks` blocks (0: auto,
/// wlop_block_count's; with `max_bytes`, more until the largest box, its margin
/// counted, fits). InvalidInput on an empty cloud, non-finite coordinates, all points
/// at one place, blocks < 0, a bound that cannot hold a block, or a bad radius.
ConsolidationPlan plan_consolidation(const CloudSource& source, const WlopParams& params, int blocks,
                                     double max_bytes = 0);

/// The number of points of `source` (one streamed pass).
std::size_t count_points(const CloudSource& source);

/// Block `id`'s output: `points` are the points of its region (its box and the margin;
/// block_points or read_bucket); WLOP with the whole cloud's scale and target
/// share x (region / box), its output points inside its box kept (a point that left
/// the bounds counts for the nearest box). Empty when the box holds no input point.
/// `diagnostics` gets the block's WlopResult (its cloud emptied).
Cloud consolidate_block(const Cloud& points, const ConsolidationPlan& plan, int id, const WlopParams& params,
                        WlopResult* diagnostics = nullptr);

/// The block whose box holds x (the nearest box for a point outside the bounds).
int wlop_block_of(const BlockGrid& grid, const Vec3f& x);

/// Appends a block's output to the gathered cloud; FormatError naming `what` when
/// its attributes (normals, colours) differ from those gathered so far.
void append_block_output(Cloud& to, const Cloud& part, const std::string& what);

/// The whole cloud consolidated block by block, in sequence (one block's points in
/// memory at a time; the output whole). `note` gets a line a block.
struct BlockWlopStats {
  int blocks = 0;
  std::size_t max_block_points = 0;
  double seconds = 0;
};
Cloud consolidate_blocks(const CloudSource& source, const WlopParams& params, int blocks, BlockWlopStats* stats = nullptr,
                         const std::function<void(const std::string&)>& note = {}, double max_bytes = 0);

}  // namespace station
