// Blocks over MPI ranks (issue 29): `station reconstruct --blocks auto` on clouds of
// 1 M to 20 M points sampled on the textured mustard bottle, two ranks on this machine
// (mpirun --oversubscribe -n 2, one thread each), against the single run on 1 M
// points (two threads, no blocks): time per million points and each rank's peak
// memory. The station binary runs as a user runs it (the one built beside this bench);
// the clouds are written to the scratch folder first (binary PLY, streamed). Sizes
// above --max-points are skipped.
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <regex>
#include <string>
#include <vector>

#include <unistd.h>

#include "core/io.h"
#include "core/texture.h"
#include "harness.h"
#include "sampling.h"

namespace station::bench {

namespace {

struct Json {
  std::string text;
  double number(const std::string& key) const {
    std::smatch m;
    if (!std::regex_search(text, m, std::regex("\"" + key + "\":([-0-9.eE+]+)"))) return -1;
    return std::stod(m[1]);
  }
  std::vector<double> numbers(const std::string& key) const {
    std::smatch m;
    std::vector<double> out;
    if (!std::regex_search(text, m, std::regex("\"" + key + "\":\\[([^\\]]*)\\]"))) return out;
    const std::string list = m[1];
    std::size_t at = 0;
    while (at < list.size()) {
      std::size_t end = list.find(',', at);
      if (end == std::string::npos) end = list.size();
      out.push_back(std::stod(list.substr(at, end - at)));
      at = end + 1;
    }
    return out;
  }
};

// Runs a command; its stdout (the JSON summary) or an empty text when it failed.
Json run(const std::string& command) {
  Json j;
  FILE* p = popen((command + " 2>/dev/null").c_str(), "r");
  if (!p) return j;
  char buf[4096];
  std::size_t n;
  while ((n = fread(buf, 1, sizeof buf, p)) > 0) j.text.append(buf, n);
  if (pclose(p) != 0) j.text.clear();
  return j;
}

fs::path station_binary() {
  char self[4096];
  const ssize_t n = readlink("/proc/self/exe", self, sizeof self - 1);
  if (n <= 0) return "station";
  self[n] = 0;
  return fs::path(self).parent_path() / "station";
}

// `count` samples of the textured mesh into a binary PLY, a million at a time.
void write_samples(const TexturedMesh& tm, const Texture& texture, std::size_t count, const fs::path& out) {
  std::ofstream f(out, std::ios::binary | std::ios::trunc);
  std::string buf = ply_header(count, true, true, 0, false);
  for (std::size_t done = 0, part = 0; done < count; ++part) {
    const int n = int(std::min<std::size_t>(1000000, count - done));
    const Cloud c = sample_textured(tm, texture, n, unsigned(977 + part));
    for (int i = 0; i < n; ++i) put_ply_vertex(buf, c.points[std::size_t(i)], &c.normals[std::size_t(i)], &c.colours[std::size_t(i)]);
    f.write(buf.data(), std::streamsize(buf.size()));
    buf.clear();
    done += std::size_t(n);
  }
  if (!f) throw std::runtime_error(out.string() + ": write failed");
}

void run_blocks_cases(const Options& options, Report& report) {
  bool shared = false;
  const fs::path obj = mustard_obj(options, &shared);
  const TexturedMesh tm = read_textured_mesh(obj);
  const Texture texture = load_texture(tm.texture);
  const std::string station = station_binary().string();
  if (!fs::exists(station)) {
    report.note("blocks: skipped, no station binary beside the bench (" + station + ")");
    return;
  }
  setenv("OMPI_ALLOW_RUN_AS_ROOT", "1", 1);
  setenv("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1", 1);
  report.note(std::string("blocks: clouds sampled on ") +
              (shared ? "../shared/data/textured_objects/006_mustard_bottle" : "data/mustard_bottle (../shared/data missing)") +
              "/textured.obj with normals and colours; `station reconstruct --blocks auto --json` under `mpirun "
              "--oversubscribe -n 2` (one thread a rank) against the single run on 1 M points (two threads); the "
              "anchor column is the single run's time scaled to the cloud (per million points)");
  const std::vector<std::size_t> sizes = {1000000, 5000000, 10000000, 20000000};
  const fs::path dir = options.temp_dir / "blocks";
  fs::create_directories(dir);
  double single_per_m = -1, single_peak = -1;
  std::vector<std::string> table, wlop_table;
  wlop_table.push_back("wlop: points | run | seconds | peak MiB | output points");
  table.push_back("blocks: points | blocks | ranks | seconds | s per M points | vs 1 M single | peak MiB per rank | "
                  "vertices");
  for (const std::size_t n : sizes) {
    if (options.max_points > 0 && n > options.max_points) {
      report.note("blocks: " + std::to_string(n / 1000000) + " M skipped (--max-points)");
      continue;
    }
    const fs::path in = dir / ("mustard_" + std::to_string(n / 1000000) + "M.ply");
    const fs::path out = dir / "mesh.ply";
    write_samples(tm, texture, n, in);
    if (n == 1000000) {
      const Json j = run(station + " reconstruct " + in.string() + " -o " + out.string() + " --threads 2 --json");
      const double t = j.number("total");
      if (t <= 0) {
        report.note("blocks: the single run on 1 M points failed");
        return;
      }
      single_per_m = t;
      single_peak = j.number("peak_rss_mb");
      table.push_back("blocks: 1 M single | 1 | 1 | " + format_fixed(t, 1) + " | " + format_fixed(t, 1) + " | 1.00x | " +
                      format_fixed(single_peak, 0) + " | " + format_fixed(j.number("vertices"), 0));
    }
    const Json j = run("mpirun --oversubscribe -n 2 " + station + " reconstruct " + in.string() + " -o " +
                       out.string() + " --blocks auto --threads 1 --json");
    const double t = j.number("total");
    if (t <= 0) {
      report.note("blocks: the run on " + std::to_string(n / 1000000) + " M points failed");
      continue;
    }
    const double per_m = t / (double(n) / 1e6);
    const std::vector<double> peaks = j.numbers("rank_peak_rss_mb");
    std::string peak;
    for (const double p : peaks) peak += (peak.empty() ? "" : " / ") + format_fixed(p, 0);
    // The root's final figure includes the stitching, after its blocks.
    peak += " (root at the end " + format_fixed(j.number("peak_rss_mb"), 0) + ")";
    table.push_back("blocks: " + std::to_string(n / 1000000) + " M | " + format_fixed(j.number("blocks"), 0) + " | " +
                    format_fixed(j.number("ranks"), 0) + " | " + format_fixed(t, 1) + " | " + format_fixed(per_m, 1) +
                    " | " + format_fixed(single_per_m / per_m, 2) + "x | " + peak + " | " +
                    format_fixed(j.number("vertices"), 0));
    // Consolidation (WLOP, the run's defaults) whole (two threads) against in blocks
    // over the two ranks (auto: a block per 2 M points; 4 at 1 M), up to 5 M points.
    if (n <= 5000000) {
      const fs::path wout = dir / "wlop.ply";
      const std::string blocks = n < 2000000 ? "4" : "auto";
      const Json w = run(station + " consolidate " + in.string() + " -o " + wout.string() + " --blocks 1 --threads 2 --json");
      const Json b = run("mpirun --oversubscribe -n 2 " + station + " consolidate " + in.string() + " -o " +
                         wout.string() + " --blocks " + blocks + " --threads 1 --json");
      if (w.number("total") > 0 && b.number("total") > 0) {
        wlop_table.push_back("wlop: " + std::to_string(n / 1000000) + " M | whole, 2 threads | " +
                             format_fixed(w.number("total"), 1) + " | " + format_fixed(w.number("peak_rss_mb"), 0) +
                             " | " + format_fixed(w.number("output_points"), 0));
        wlop_table.push_back("wlop: " + std::to_string(n / 1000000) + " M | " + format_fixed(b.number("blocks"), 0) +
                             " blocks, 2 ranks x 1 thread | " + format_fixed(b.number("total"), 1) + " | " +
                             format_fixed(b.number("peak_rss_mb"), 0) + " (root) | " +
                             format_fixed(b.number("output_points"), 0));
      } else {
        report.note("blocks: the consolidation of " + std::to_string(n / 1000000) + " M points failed");
      }
    }
    Row row("blocks " + std::to_string(n / 1000000) + " M, 2 ranks", "1 M single run, x points");
    row.ours.median_ms = row.ours.min_ms = 1000 * t;
    row.theirs.median_ms = row.theirs.min_ms = 1000 * single_per_m * double(n) / 1e6;
    double most = -1;
    for (const double p : peaks) most = std::max(most, p);
    row.ours.peak_mib = std::max(most, j.number("peak_rss_mb"));
    row.theirs.peak_mib = single_peak;
    report.rows.push_back(row);
    std::error_code ec;
    fs::remove(in, ec);
  }
  for (const std::string& line : table) report.note(line);
  for (const std::string& line : wlop_table) report.note(line);
}

[[maybe_unused]] const bool registered =
    register_group("blocks", "blocks over two MPI ranks, 1 M to 20 M points, vs the 1 M single run (issue 29)",
                   &run_blocks_cases);

}  // namespace

}  // namespace station::bench
