#pragma once
// The block-wise surface stage of `station reconstruct --blocks` and `station run
// --blocks` (reconstruct/blocks.h, docs/blocks.md): the blocks run wave after wave
// (a wave's blocks depend only on earlier waves), spread over the MPI ranks when the
// process was started by mpirun (built with MPI), else in sequence. The ranks share a
// work folder (the blocks' lower-face values and meshes, one file each): rank 0 stitches
// the mesh. With `resume`, blocks whose files are there are not run again.
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "reconstruct/blocks.h"
#include "reconstruct/blocks_wlop.h"
#include "reconstruct/surface.h"

namespace station {

struct BlockRun {
  SurfaceResult result;  ///< the stitched mesh (rank 0 only; empty on the other ranks, and when written)
  bool written = false;  ///< the mesh went straight to `output` (its counts in stats)
  bool root = true;      ///< this process is rank 0 (or there is no MPI)
  int ranks = 1;
  int resumed = 0;       ///< blocks found done in the work folder
  std::vector<double> rank_peak_mb;  ///< rank 0: each rank's peak resident memory over its blocks (MiB)
  double memory_estimate = 0;  ///< with max_bytes: the estimated peak per rank (bytes)
  BlockRunStats stats;
};

/// Whether this process was started by an MPI launcher (mpirun's environment) and the
/// station was built with MPI.
bool launched_by_mpi();

/// This process's MPI rank and the ranks (0 and 1 when not launched by mpirun);
/// a barrier over them (nothing without MPI).
int mpi_rank();
int mpi_ranks();
void mpi_barrier();

/// `station run` under mpirun: rank 0 runs the job; the other ranks wait in
/// receive_block_job for the surface stage, run its blocks with rank 0 (run_blocks on
/// the same input), and wait again until rank 0 sends the stop (nullptr). The
/// profile is each rank's own (the same command line); the job carries what only rank
/// 0 knows.
struct BlockJob {
  /// What the ranks run: the surface stage's blocks, or the consolidation's
  /// (run_consolidate_blocks, `blocks` of them: 0 auto).
  enum class Kind { kSurface, kConsolidate } kind = Kind::kSurface;
  int blocks = 0;
  std::string input;        ///< the cloud the stage reads
  std::string work;         ///< the blocks' shared work folder
  std::optional<Vec3d> up;  ///< the table plane's up, from the register stage
};
void send_block_job(const BlockJob* job);  ///< rank 0; nothing with one rank
std::optional<BlockJob> receive_block_job();  ///< ranks > 0; nullopt at the stop

/// Consolidation in blocks (reconstruct/blocks_wlop.h): every rank plans from `input`
/// (a PLY, streamed; the same plan on every rank), sorts the points of its blocks out
/// of it in one streamed pass, consolidates them and writes each block's output into
/// `work_dir` (`wlop_<id>.ply`, or `wlop_<id>.empty` for a block without output); rank
/// 0 returns them gathered in block order (the other ranks an empty cloud). The work
/// folder is emptied first and removed after a run that finished; it must be shared by
/// the ranks (a block's file missing at the end is an error naming it). Without MPI, or
/// on one rank, the blocks run in sequence. `blocks` and `max_bytes` as
/// plan_consolidation's. Errors as run_blocks'.
struct WlopBlocksRun {
  Cloud cloud;  ///< rank 0: the consolidated cloud
  bool root = true;
  int ranks = 1;
  BlockWlopStats stats;
};
WlopBlocksRun run_consolidate_blocks(const std::string& input, const WlopParams& params, int blocks,
                                     const std::string& work_dir,
                                     const std::function<void(const std::string&)>& note = {}, double max_bytes = 0);

/// The blocks' work folder (OUT.blocks) is cleared, then removed once the output is
/// written: refused (InvalidInput) when an input lies in it, or when it exists holding
/// anything the blocks do not write (a user's folder of that name is never cleared).
void check_blocks_work_folder(const std::string& work, const std::vector<std::string>& inputs);

/// `blocks` and `max_bytes` as resolve_block_count's (0: auto, a block per
/// kAutoBlockPoints points; with max_bytes, the count that fits). The work
/// folder is made when missing and removed after a run that finished. InvalidInput /
/// IoError / FormatError as the stage's (on every rank, the failing rank's message on
/// rank 0). With `output` (a .ply path), rank 0 writes the mesh there streamed
/// (write_blocks_ply: no whole mesh in memory) instead of returning it.
BlockRun run_blocks(const std::string& input, const SurfaceParams& params, int blocks, const std::string& work_dir,
                    bool resume, const std::string& output = {}, double max_bytes = 0);

}  // namespace station
