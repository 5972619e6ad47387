// station_bench: times the station's hot paths against anchor libraries in one
// process and prints one table (docs/benchmarks.md).
//
//   station_bench [--threads N] [--reps N] [--warmup N] [--generate]
//                 [--shared DIR] [--only raycast|io|distance] [--max-points N]
#include <malloc.h>
#include <omp.h>
#include <tbb/global_control.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>
#include <string>
#include <thread>

#include <embree3/rtcore_config.h>
#include <open3d/Open3D.h>
#include <pcl/pcl_config.h>

#include "core/error.h"
#include "harness.h"

namespace station::bench {

namespace {

using Clock = std::chrono::steady_clock;

/// A "VmXXX:   1234 kB" line of /proc/self/status in MiB; -1 when unreadable.
double status_mib(const std::string& key) {
  std::ifstream in("/proc/self/status");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind(key + ":", 0) != 0) continue;
    std::istringstream fields(line.substr(key.size() + 1));
    double kib = -1;
    fields >> kib;
    return kib < 0 ? -1 : kib / 1024.0;
  }
  return -1;
}

/// Resets VmHWM to the current RSS (Linux >= 4.0); false when not allowed.
bool reset_peak_rss() {
  std::ofstream out("/proc/self/clear_refs");
  if (!out) return false;
  out << "5";
  out.flush();
  return bool(out);
}

std::string cpu_model() {
  std::ifstream in("/proc/cpuinfo");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("model name", 0) == 0) {
      const auto colon = line.find(':');
      if (colon != std::string::npos) return line.substr(colon + 2);
    }
  return "unknown CPU";
}

std::string today() {
  const std::time_t now = std::time(nullptr);
  char buffer[32];
  std::strftime(buffer, sizeof buffer, "%Y-%m-%d %H:%M", std::localtime(&now));
  return buffer;
}

std::string format_ratio(const Row& row) {
  if (row.ours.median_ms <= 0 || row.theirs.median_ms <= 0) return "-";
  return format_fixed(row.theirs.median_ms / row.ours.median_ms, 2);
}

std::string format_mib(double mib) { return mib < 0 ? "-" : format_fixed(mib, 1); }

void print_table(const Report& report) {
  std::size_t name_width = 4, anchor_width = 6;
  for (const Row& row : report.rows) {
    name_width = std::max(name_width, row.name.size());
    anchor_width = std::max(anchor_width, row.anchor.size());
  }
  auto pad = [](const std::string& s, std::size_t width, bool right) {
    if (s.size() >= width) return s;
    const std::string fill(width - s.size(), ' ');
    return right ? fill + s : s + fill;
  };
  std::ostringstream out;
  out << pad("case", name_width, false) << " | " << pad("ours ms", 9, true) << " | "
      << pad("anchor ms", 9, true) << " | " << pad("anchor/ours", 11, true) << " | "
      << pad("ours +MiB", 9, true) << " | " << pad("anchor +MiB", 10, true) << " | "
      << "anchor\n";
  out << std::string(name_width, '-') << "-|-" << std::string(9, '-') << "-|-"
      << std::string(9, '-') << "-|-" << std::string(11, '-') << "-|-" << std::string(9, '-')
      << "-|-" << std::string(10, '-') << "-|-" << std::string(anchor_width, '-') << "\n";
  for (const Row& row : report.rows) {
    out << pad(row.name, name_width, false) << " | "
        << pad(format_fixed(row.ours.median_ms, 2), 9, true) << " | "
        << pad(row.theirs.median_ms > 0 ? format_fixed(row.theirs.median_ms, 2) : "-", 9, true)
        << " | " << pad(format_ratio(row), 11, true) << " | "
        << pad(format_mib(row.ours.peak_mib), 9, true) << " | "
        << pad(format_mib(row.theirs.peak_mib), 10, true) << " | " << row.anchor << "\n";
  }
  std::cout << out.str();
}

struct Group {
  std::string description;
  station::bench::CaseGroup run = nullptr;
};
/// Groups registered by their files (static initialisation; see harness.h).
std::map<std::string, Group>& registered_groups() {
  static std::map<std::string, Group> groups;
  return groups;
}

[[noreturn]] void usage(const std::string& problem, int status = 2) {
  std::string names = "raycast|io|distance";
  for (const auto& [name, group] : registered_groups()) names += "|" + name;
  (status ? std::cerr : std::cout)
      << "station_bench: " << problem << "\n"
      << "usage: station_bench [--threads N] [--reps N] [--warmup N] [--generate]\n"
      << "                     [--shared DIR] [--only " << names << "] [--max-points N]\n"
      << "  --max-points N: surface group: skip the clouds larger than N points (the 1M case)\n";
  for (const auto& [name, group] : registered_groups())
    (status ? std::cerr : std::cout) << "  " << name << ": " << group.description << "\n";
  std::exit(status);
}

int parse_count(const std::string& flag, const char* value, int min, long max = 1000) {
  if (!value) usage(flag + " needs a value");
  char* end = nullptr;
  const long n = std::strtol(value, &end, 10);
  if (end == value || *end != '\0' || n < min || n > max)
    usage(flag + ": bad value '" + value + "'");
  return int(n);
}

}  // namespace

bool register_group(const std::string& name, const std::string& description, CaseGroup run) {
  registered_groups()[name] = Group{description, run};
  return true;
}

std::string format_fixed(double value, int decimals) {
  char buffer[64];
  std::snprintf(buffer, sizeof buffer, "%.*f", decimals, value);
  return buffer;
}

namespace {

/// Timed runs of one side, collected one at a time.
class Sampler {
 public:
  /// One timed run (heap trimmed and RSS high-water mark reset first).
  void run(const std::function<void()>& body) {
    malloc_trim(0);
    const bool peak_known = reset_peak_rss();
    const double rss_before = status_mib("VmRSS");
    const auto start = Clock::now();
    body();
    const auto stop = Clock::now();
    times_.push_back(std::chrono::duration<double, std::milli>(stop - start).count());
    const double high_water = status_mib("VmHWM");
    if (peak_known && rss_before >= 0 && high_water >= 0)
      peak_ = std::max(peak_, std::max(0.0, high_water - rss_before));
  }
  Timing timing() const {
    std::vector<double> t = times_;
    std::sort(t.begin(), t.end());
    Timing timing;
    const std::size_t n = t.size();
    if (n == 0) return timing;
    timing.median_ms = n % 2 ? t[n / 2] : 0.5 * (t[n / 2 - 1] + t[n / 2]);
    timing.min_ms = t.front();
    timing.peak_mib = peak_;
    return timing;
  }

 private:
  std::vector<double> times_;
  double peak_ = -1;
};

}  // namespace

Timing measure(const Options& options, const std::function<void()>& run) {
  for (int i = 0; i < options.warmup; ++i) run();
  Sampler sampler;
  for (int i = 0; i < options.repetitions; ++i) sampler.run(run);
  return sampler.timing();
}

std::pair<Timing, Timing> measure_pair(const Options& options, const std::function<void()>& ours,
                                       const std::function<void()>& theirs) {
  for (int i = 0; i < options.warmup; ++i) {
    ours();
    theirs();
  }
  Sampler a, b;
  for (int i = 0; i < options.repetitions; ++i) {
    if (i % 2 == 0) {
      a.run(ours);
      b.run(theirs);
    } else {
      b.run(theirs);
      a.run(ours);
    }
  }
  return {a.timing(), b.timing()};
}

}  // namespace station::bench

int main(int argc, char** argv) {
  using namespace station::bench;
  Options options;
  options.source_dir = STATION_SOURCE_DIR;
  options.shared_dir = options.source_dir / ".." / "shared" / "data";
  std::string only;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    const char* value = i + 1 < argc ? argv[i + 1] : nullptr;
    if (arg == "--threads") {
      options.threads = parse_count(arg, value, 0), ++i;
    } else if (arg == "--reps") {
      options.repetitions = parse_count(arg, value, 1), ++i;
    } else if (arg == "--warmup") {
      options.warmup = parse_count(arg, value, 0), ++i;
    } else if (arg == "--max-points") {
      options.max_points = std::size_t(parse_count(arg, value, 1, 1000000000L)), ++i;
    } else if (arg == "--generate") {
      options.use_shared = false;
    } else if (arg == "--shared") {
      if (!value) usage("--shared needs a folder");
      options.shared_dir = value, ++i;
    } else if (arg == "--only") {
      if (!value) usage("--only needs a case group");
      only = value, ++i;
      if (only != "raycast" && only != "io" && only != "distance" && !registered_groups().count(only))
        usage("--only: unknown group '" + only + "'");
    } else if (arg == "-h" || arg == "--help") {
      usage("times the station against Embree, Open3D and PCL (docs/benchmarks.md)", 0);
    } else {
      usage("unknown argument '" + arg + "'");
    }
  }
  if (options.threads == 0) options.threads = int(std::max(1u, std::thread::hardware_concurrency()));

  // One thread count for every pool in the process: ours (TBB), Open3D's
  // raycaster and Embree (TBB; nthreads / "threads=N" given explicitly too) and
  // Open3D's KD-tree queries (OpenMP).
  tbb::global_control parallelism(tbb::global_control::max_allowed_parallelism,
                                  std::size_t(options.threads));
  omp_set_num_threads(options.threads);
  open3d::utility::SetVerbosityLevel(open3d::utility::VerbosityLevel::Error);

  std::error_code ec;
  options.temp_dir = fs::temp_directory_path() /
                     ("station-bench-" + std::to_string(::getpid()));
  fs::create_directories(options.temp_dir);

  std::cout << "station_bench  " << today() << "  " << cpu_model() << ", "
            << std::thread::hardware_concurrency() << " hardware threads; " << options.threads
            << " threads per side (TBB global_control, omp_set_num_threads, explicit counts)\n"
            << "anchors: Open3D " << OPEN3D_VERSION << ", Embree " << RTC_VERSION_STRING << ", PCL " << PCL_VERSION_PRETTY
            << "; warm-up " << options.warmup << ", median of " << options.repetitions
            << " runs\n\n";

  const auto start = std::chrono::steady_clock::now();
  Report report;
  int status = 0;
  try {
    if (only.empty() || only == "raycast") run_raycast_cases(options, report);
    if (only.empty() || only == "io") run_io_cases(options, report);
    if (only.empty() || only == "distance") run_distance_cases(options, report);
    for (const auto& [name, group] : registered_groups())
      if (only.empty() || only == name) group.run(options, report);
  } catch (const std::exception& e) {
    std::cerr << "station_bench: " << e.what() << "\n";
    status = 1;
  }
  fs::remove_all(options.temp_dir, ec);

  print_table(report);
  std::cout << "\nanchor/ours > 1: ours is faster. +MiB: peak resident-memory growth during one run.\n";
  for (const std::string& line : report.notes) std::cout << "- " << line << "\n";
  const double total_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::cout << "total bench time " << format_fixed(total_s, 1) << " s\n";
  return status;
}
