#pragma once
// `station run`: the whole job from a recorded session (or a cloud) to a
// coloured mesh and a report, as resumable stages:
//
//   register (sessions only) -> merged.ply
//   consolidate (WLOP)       -> consolidated.ply
//   surface (MPU + colour + extraction, or SDM)  -> mesh.ply
//   report                   -> report.html
//
// Every stage's output is written atomically into the run folder, and the run's
// state (run.yaml: per stage a key over its input and parameters, its output's
// hash, timings and figures) is rewritten after each finished stage. A run that
// is interrupted (Ctrl-C, a crash, a full disk) resumes with `resume`: a stage is
// redone only when its key changed (inputs or parameters) or its output is
// missing or altered. docs/run.md.
#include <atomic>
#include <filesystem>
#include <functional>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "core/geometry.h"
#include "station/config.h"
#include "station/progress.h"

namespace station {

struct RunRequest {
  std::filesystem::path input;    ///< a session folder (or its session.yaml), or a cloud file
  std::filesystem::path out_dir;  ///< created when missing
  bool resume = false;  ///< continue a run in out_dir; without it an earlier run there is an error
  bool quiet = false;   ///< no progress output
  bool report = true;   ///< write report.html
  /// Set (e.g. by a SIGINT handler) to stop after the stage in progress.
  const std::atomic<bool>* stop = nullptr;
  /// Gets every line and progress step the run prints (also when quiet).
  ProgressSink events;
  /// Under mpirun (rank 0): the surface stage's blocks go over the MPI ranks, which
  /// wait for it in receive_block_job (station/blocks_run.h); else in sequence here.
  bool blocks_over_ranks = false;
};

/// What one stage did (also what run.yaml keeps of it).
struct StageRecord {
  std::string name;
  std::string key;          ///< hex hash of the stage's input key and parameters
  std::string output;       ///< file name inside the run folder
  std::string output_hash;  ///< hex hash of the output file
  bool reused = false;      ///< taken from an earlier run (not redone)
  double seconds = 0;
  double peak_rss_mb = -1;  ///< peak resident memory during the stage (-1: unknown)
  std::map<std::string, double> figures;  ///< counts and quality figures
  std::vector<double> per_view;           ///< register: residual per view, mm
  std::vector<std::vector<double>> poses; ///< register: 4x4 row-major per view
  /// register: per view, how its turntable angle served: "none" (no angle),
  /// "used", "corrected", "rejected", "ignored" (registration/registration.h
  /// PriorUse), or "failed" (the view did not register).
  std::vector<std::string> view_prior;
  /// register: the turntable axis (the object's up) in the object frame, when the
  /// session has one; also shown as the figures up_x, up_y, up_z.
  std::optional<Vec3d> up;
};

struct RunResult {
  std::vector<StageRecord> stages;
  std::filesystem::path mesh;    ///< the final mesh
  std::filesystem::path report;  ///< empty when not written
  bool interrupted = false;      ///< stopped by RunRequest::stop before the end
  bool session = false;          ///< the input was a session
};

/// Runs (or resumes) the job. InvalidInput/IoError/FormatError name the file or
/// folder at fault; on a failed write the outputs of earlier stages stay intact.
RunResult run_pipeline(const StationConfig& config, const RunRequest& request);

/// The stages of a run folder's run.yaml (FormatError naming it when it is not one).
std::vector<StageRecord> read_run_stages(const std::filesystem::path& run_yaml);

/// 64-bit FNV-1a over bytes, as 16 hex digits (stage keys; not cryptographic).
std::string hash_hex(const std::string& bytes);
/// hash_hex of a file's contents (IoError naming it when unreadable).
std::string hash_file(const std::filesystem::path& path);

}  // namespace station
