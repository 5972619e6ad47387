#pragma once
// Private to bench/: timing, memory and the result table shared by the cases of
// station_bench. Every case runs ours and the anchor in this one process, with
// the same inputs and the same thread count.
#include <filesystem>
#include <functional>
#include <string>
#include <utility>
#include <vector>

namespace station::bench {

namespace fs = std::filesystem;

struct Options {
  int threads = 0;     ///< threads for both sides (0 = all cores, resolved in main)
  int warmup = 1;      ///< untimed runs before the timed ones
  int repetitions = 7; ///< timed runs; the median is reported
  fs::path source_dir; ///< repository root (bundled data)
  fs::path shared_dir; ///< shared data folder (../shared/data from the root)
  bool use_shared = true;  ///< false: generate the I/O inputs even when shared data exists
  fs::path temp_dir;   ///< scratch folder for generated inputs
  std::size_t max_points = 0;  ///< > 0: skip the surface cases with larger clouds (--max-points)
};

/// One measured side: median wall time and the peak RSS growth during a run.
struct Timing {
  double median_ms = 0;
  double min_ms = 0;
  double peak_mib = -1;  ///< < 0 when it could not be measured
};

/// Runs `run` options.warmup times untimed, then options.repetitions times timed.
/// Before every timed run the heap is trimmed and the kernel's RSS high-water
/// mark reset (/proc/self/clear_refs), so peak_mib is the largest growth of
/// resident memory over the RSS at the start of a run.
Timing measure(const Options& options, const std::function<void()>& run);

/// Both sides of a row, interleaved (ours, anchor, anchor, ours, ...) so that
/// drifts of a shared machine hit both alike; otherwise as measure().
std::pair<Timing, Timing> measure_pair(const Options& options, const std::function<void()>& ours,
                                       const std::function<void()>& theirs);

/// One line of the table.
struct Row {
  Row(std::string name_, std::string anchor_) : name(std::move(name_)), anchor(std::move(anchor_)) {}
  std::string name;
  std::string anchor;  ///< which anchor function the right side ran
  Timing ours, theirs;
};

/// Lines printed under the table (inputs, agreement, caveats).
struct Report {
  std::vector<Row> rows;
  std::vector<std::string> notes;
  void note(const std::string& line) { notes.push_back(line); }
};

void run_raycast_cases(const Options& options, Report& report);
void run_io_cases(const Options& options, Report& report);
void run_distance_cases(const Options& options, Report& report);

/// Further case groups register themselves from their own file, so a new
/// group needs no edit here or in station_bench.cpp:
///   static const bool registered = register_group("wlop", "WLOP vs CGAL", &run_wlop_cases);
/// `--only NAME` runs one group; without it every group runs, the built-in
/// ones first, then the registered ones by name.
using CaseGroup = void (*)(const Options& options, Report& report);
bool register_group(const std::string& name, const std::string& description, CaseGroup run);

/// "12.3" style formatting helpers.
std::string format_fixed(double value, int decimals);

}  // namespace station::bench
