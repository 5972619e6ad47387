#include "station/blocks_run.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <regex>

#include <sys/resource.h>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/io.h"
#include "core/threads.h"

#ifdef STATION_HAVE_MPI
#include <mpi.h>
#endif

namespace station {

namespace fs = std::filesystem;

namespace {

// The blocks' work folder, with the file system's reason when it cannot be made
// (not the library's "filesystem error: cannot create directories: ..." text).
void make_work_folder(const fs::path& work) {
  std::error_code ec;
  fs::create_directories(work, ec);
  if (ec) throw IoError(work.string() + ": cannot make the blocks' work folder: " + ec.message());
}

std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

// The ranks: MPI's when launched by mpirun, else one. One for the process (MPI is
// started once, at the first use, and finished at exit).
class Ranks {
 public:
  static Ranks& get() {
    static Ranks r;
    return r;
  }
  Ranks(const Ranks&) = delete;
  Ranks& operator=(const Ranks&) = delete;

 private:
  Ranks() {
#ifdef STATION_HAVE_MPI
    if (launched_by_mpi()) {
      int init = 0;
      MPI_Initialized(&init);
      if (!init) {
        MPI_Init(nullptr, nullptr);
        owns_ = true;
      }
      MPI_Comm_rank(MPI_COMM_WORLD, &rank_);
      MPI_Comm_size(MPI_COMM_WORLD, &size_);
      mpi_ = true;
    }
#endif
  }

 public:
  ~Ranks() {
#ifdef STATION_HAVE_MPI
    if (owns_) MPI_Finalize();
#endif
  }
  int rank() const { return rank_; }
  int size() const { return size_; }
  void barrier() const {
#ifdef STATION_HAVE_MPI
    if (mpi_) MPI_Barrier(MPI_COMM_WORLD);
#endif
  }
  /// Whether any rank failed (each passes its own flag); the first failing rank's
  /// message reaches every rank in `message`.
  bool any_failed(bool failed, std::string& message) const {
#ifdef STATION_HAVE_MPI
    if (mpi_) {
      const int mine = failed ? rank_ : size_;
      int first = size_;
      MPI_Allreduce(&mine, &first, 1, MPI_INT, MPI_MIN, MPI_COMM_WORLD);
      if (first == size_) return false;
      broadcast(message, first);
      if (first != rank_) message = "rank " + std::to_string(first) + ": " + message;
      return true;
    }
#endif
    return failed;
  }
  /// Each rank's `value` at rank 0 (in rank order; {value} without MPI).
  std::vector<double> gather(double value) const {
    std::vector<double> all(std::size_t(size_), value);
#ifdef STATION_HAVE_MPI
    if (mpi_) MPI_Gather(&value, 1, MPI_DOUBLE, all.data(), 1, MPI_DOUBLE, 0, MPI_COMM_WORLD);
#endif
    return all;
  }
  /// `bytes` from rank `from` to every rank.
  void broadcast(std::string& bytes, int from) const {
#ifdef STATION_HAVE_MPI
    if (mpi_) {
      unsigned long long n = bytes.size();
      MPI_Bcast(&n, 1, MPI_UNSIGNED_LONG_LONG, from, MPI_COMM_WORLD);
      bytes.resize(std::size_t(n));
      // In pieces below 2^31 bytes (MPI counts are int).
      for (std::size_t at = 0; at < bytes.size(); at += std::size_t(1) << 30) {
        const int len = int(std::min<std::size_t>(std::size_t(1) << 30, bytes.size() - at));
        MPI_Bcast(bytes.data() + at, len, MPI_CHAR, from, MPI_COMM_WORLD);
      }
    }
#endif
    (void)from;
  }

 private:
  int rank_ = 0, size_ = 1;
  bool mpi_ = false, owns_ = false;
};

// Runs fn; its error (any std::exception) as a message, empty when none.
template <class Fn>
std::string attempt(Fn&& fn) {
  try {
    fn();
  } catch (const std::exception& e) {
    return e.what()[0] ? e.what() : "unknown error";
  }
  return {};
}

// The version of the block files (summary, seam tables, pieces) a work folder holds.
constexpr const char* kBlockFilesVersion = "station blocks 6";

// Rethrows a message as the error kind its text says it was (the kinds keep their
// exit codes); InvalidInput otherwise.
[[noreturn]] void fail_with(const std::string& message) { throw InvalidInput(message); }

}  // namespace

bool launched_by_mpi() {
#ifdef STATION_HAVE_MPI
  for (const char* v : {"OMPI_COMM_WORLD_SIZE", "PMIX_RANK", "PMI_RANK", "PMI_SIZE"})
    if (std::getenv(v)) return true;
#endif
  return false;
}

int mpi_rank() { return Ranks::get().rank(); }
int mpi_ranks() { return Ranks::get().size(); }
void mpi_barrier() { Ranks::get().barrier(); }

void send_block_job(const BlockJob* job) {
  const Ranks& r = Ranks::get();
  if (r.size() < 2 || r.rank() != 0) return;
  std::string m;
  if (job) {
    char up[128] = "none";
    if (job->up) std::snprintf(up, sizeof up, "%.17g %.17g %.17g", job->up->x(), job->up->y(), job->up->z());
    m = "job\n" + job->input + "\n" + job->work + "\n" + up + "\n" +
        (job->kind == BlockJob::Kind::kConsolidate ? "consolidate" : "surface") + "\n" + std::to_string(job->blocks) +
        "\n";
  } else {
    m = "stop\n";
  }
  r.broadcast(m, 0);
}

std::optional<BlockJob> receive_block_job() {
  const Ranks& r = Ranks::get();
  if (r.size() < 2 || r.rank() == 0) return std::nullopt;
  std::string m;
  r.broadcast(m, 0);
  std::vector<std::string> lines;
  for (std::size_t at = 0; at < m.size();) {
    const std::size_t end = m.find('\n', at);
    lines.push_back(m.substr(at, end == std::string::npos ? std::string::npos : end - at));
    if (end == std::string::npos) break;
    at = end + 1;
  }
  if (lines.size() < 6 || lines[0] != "job") return std::nullopt;
  BlockJob job;
  job.input = lines[1];
  job.work = lines[2];
  job.kind = lines[4] == "consolidate" ? BlockJob::Kind::kConsolidate : BlockJob::Kind::kSurface;
  job.blocks = std::atoi(lines[5].c_str());
  if (lines[3] != "none") {
    Vec3d up;
    if (std::sscanf(lines[3].c_str(), "%lf %lf %lf", &up.x(), &up.y(), &up.z()) == 3) job.up = up;
  }
  return job;
}

WlopBlocksRun run_consolidate_blocks(const std::string& input, const WlopParams& params, int blocks,
                                     const std::string& work_dir, const std::function<void(const std::string&)>& note_fn,
                                     double max_bytes) {
  const auto t0 = std::chrono::steady_clock::now();
  const Ranks& ranks = Ranks::get();
  WlopBlocksRun run;
  run.root = ranks.rank() == 0;
  run.ranks = ranks.size();
  const auto note = [&](const std::string& line) {
    if (note_fn) note_fn(ranks.size() > 1 ? "rank " + std::to_string(ranks.rank()) + ": " + line : line);
  };
  const CloudSource source = file_source(input);
  const fs::path work(work_dir);
  ConsolidationPlan plan;
  // Every rank plans from the file: the same numbers, so nothing to send.
  std::string error = attempt([&] {
    plan = plan_consolidation(source, params, blocks, max_bytes);
    if (run.root) {  // an earlier run's outputs must not be taken for this one's
      std::error_code ec;
      fs::remove_all(work, ec);
      if (ec) throw IoError(work.string() + ": cannot clear the work folder: " + ec.message());
    }
  });
  if (ranks.any_failed(!error.empty(), error)) fail_with(error);  // (every rank past the clearing)
  const BlockGrid& grid = plan.grid;
  if (run.root)
    note(std::to_string(plan.points) + " points in " + std::to_string(grid.size()) + " blocks (" +
         std::to_string(grid.counts[0]) + " x " + std::to_string(grid.counts[1]) + " x " + std::to_string(grid.counts[2]) +
         ") on " + std::to_string(ranks.size()) + " rank" + (ranks.size() > 1 ? "s" : "") + ", h " +
         fmt("%.3g", plan.radius) + ", margin " + fmt("%.3g", grid.margin) + ", " + std::to_string(plan.output_points) +
         " points out");
  std::vector<int> ids(std::size_t(grid.size()));
  for (int id = 0; id < grid.size(); ++id) ids[std::size_t(id)] = id;
  const std::vector<int> owner = assign_blocks(ids, plan.box_points, ranks.size());
  const auto points_file = [&](int id) { return work / ("wlop_points_" + std::to_string(id) + ".bin"); };
  const auto out_file = [&](int id) { return work / ("wlop_" + std::to_string(id) + ".ply"); };
  const auto empty_file = [&](int id) { return work / ("wlop_" + std::to_string(id) + ".empty"); };
  std::size_t max_points = 0;
  error = attempt([&] {
    std::vector<int> mine;
    for (int id : ids)
      if (owner[std::size_t(id)] == ranks.rank() && plan.box_points[std::size_t(id)] > 0) mine.push_back(id);
    if (mine.empty()) return;
    make_work_folder(work);
    note("sorting " + input + " into " + std::to_string(mine.size()) + " block" + (mine.size() > 1 ? "s" : "") +
         " (one streamed pass)");
    bucket_points(source, grid, mine, [&](int id) { return points_file(id).string(); });
    for (int id : mine) {
      const Aabb region = grid.region(id);
      const Cloud pts = read_bucket(points_file(id).string(), &region);
      max_points = std::max(max_points, pts.size());
      const auto tb = std::chrono::steady_clock::now();
      const Cloud part = consolidate_block(pts, plan, id, params);
      if (!part.empty()) {  // written whole or not at all
        const fs::path f = out_file(id), part_path = f.string() + ".part";
        write_ply(part_path, part);
        fs::rename(part_path, f);
      } else {
        write_file_atomic(empty_file(id), "");
      }
      fs::remove(points_file(id));
      const auto c = grid.coords(id);
      note("block " + std::to_string(id + 1) + "/" + std::to_string(grid.size()) + " (" + std::to_string(c[0]) + ", " +
           std::to_string(c[1]) + ", " + std::to_string(c[2]) + "): " + std::to_string(pts.size()) + " points -> " +
           std::to_string(part.size()) + ", " + fmt("%.2f s", seconds_since(tb)));
    }
  });
  if (ranks.any_failed(!error.empty(), error)) fail_with(error);
  ranks.barrier();
  run.stats.blocks = grid.size();
  if (run.root) {
    error = attempt([&] {
      for (int id : ids) {
        if (plan.box_points[std::size_t(id)] == 0 || fs::exists(empty_file(id))) continue;
        if (!fs::exists(out_file(id)))
          throw IoError(out_file(id).string() + ": a block's output is missing (the work folder must be shared by the "
                        "ranks)");
        append_block_output(run.cloud, read_cloud(out_file(id)), out_file(id).string());
      }
      std::error_code ec;
      fs::remove_all(work, ec);
    });
  }
  const std::vector<double> most = ranks.gather(double(max_points));
  for (double m : most) run.stats.max_block_points = std::max(run.stats.max_block_points, std::size_t(m));
  if (ranks.any_failed(!error.empty(), error)) fail_with(error);
  run.stats.seconds = seconds_since(t0);
  return run;
}

BlockRun run_blocks(const std::string& input, const SurfaceParams& p, int blocks, const std::string& work_dir,
                    bool resume, const std::string& output, double max_bytes) {
  const auto t0 = std::chrono::steady_clock::now();
  const Ranks& ranks = Ranks::get();
  BlockRun run;
  run.root = ranks.rank() == 0;
  run.ranks = ranks.size();
  const auto note = [&](const std::string& line) {
    if (p.note) p.note(ranks.size() > 1 ? "rank " + std::to_string(ranks.rank()) + ": " + line : line);
  };
  const auto root_note = [&](const std::string& line) {
    if (run.root) note(line);
  };
  const CloudSource source = file_source(input);
  const fs::path work(work_dir);

  // The shared decisions, once (rank 0), then to every rank.
  std::string bytes, error;
  bool fresh = false;  // a new summary, saved once every rank has its block count
  if (run.root) {
    error = attempt([&] {
      const fs::path saved = work / "summary.bin";
      if (resume && fs::exists(saved)) {
        bytes = read_file_bytes(saved);
        (void)summary_from_bytes(bytes, saved.string());
        root_note("resuming the blocks in " + work.string());
      } else {
        root_note("summarising " + input + " (a streamed pass for its bounds, spacing and closing)");
        bytes = to_bytes(summarise_cloud(source, p));
        fresh = true;
      }
    });
  }
  if (ranks.any_failed(!error.empty(), error)) fail_with(error);
  ranks.broadcast(bytes, 0);
  const BlockSummary s = summary_from_bytes(bytes, (work / "summary.bin").string());
  const double cell = double((s.box.max - s.box.min).maxCoeff()) / s.resolution;
  // The same on every rank; one that cannot fit throws here, before anything is written.
  blocks = resolve_block_count(s, blocks, max_bytes, ranks.size());
  if (run.root && fresh) {
    error = attempt([&] {
      make_work_folder(work);
      write_file_atomic(work / "summary.bin", bytes);
    });
  }
  if (ranks.any_failed(!error.empty(), error)) fail_with(error);
  bytes.clear();
  const BlockGrid grid = plan_blocks(s.box, s.resolution, blocks, block_margin(s, cell));
  // The grid (and the block files' version) a work folder was made for: --resume
  // takes up only a folder made for this one.
  const std::string signature = std::string(kBlockFilesVersion) + " counts " + std::to_string(grid.counts[0]) + " " +
                                std::to_string(grid.counts[1]) + " " + std::to_string(grid.counts[2]) + " margin " +
                                fmt("%.17g", grid.margin) + "\n";
  if (run.root) {
    error = attempt([&] {
      const fs::path f = work / "grid.txt";
      if (fresh) {
        write_file_atomic(f, signature);
      } else if (!fs::exists(f) || read_file_bytes(f) != signature) {
        throw InvalidInput(work.string() + ": made by another station version or for another block grid (" +
                           "--blocks, --max-memory, --hole); run again without --resume");
      }
    });
  }
  if (ranks.any_failed(!error.empty(), error)) fail_with(error);
  root_note(std::to_string(s.points) + " points in " + std::to_string(grid.size()) + " blocks (" +
            std::to_string(grid.counts[0]) + " x " + std::to_string(grid.counts[1]) + " x " +
            std::to_string(grid.counts[2]) + ") on " + std::to_string(ranks.size()) + " rank" +
            (ranks.size() > 1 ? "s" : "") + ", one lattice of " + std::to_string(s.resolution) + " cells (cell " +
            fmt("%.3g", cell) + (s.resolution_auto ? ", auto: the points' sample spacing " + fmt("%.3g", s.sample_spacing) : "") +
            "; margin " + fmt("%.3g", grid.margin) + "); " +
            (s.hole == HoleMode::kClose ? "closing" : "keeping") + " the unseen parts");
  if (max_bytes > 0) {
    run.memory_estimate = estimate_block_bytes(s, grid);
    root_note("memory: about " + fmt("%.2f GB", run.memory_estimate / 1e9) + " per rank (--max-memory " +
              fmt("%.2f GB", max_bytes / 1e9) + ")");
  }
  const auto faces_file = [&](int id) { return work / ("faces_" + std::to_string(id) + ".bin"); };
  const auto piece_file = [&](int id) { return work / ("piece_" + std::to_string(id) + ".bin"); };

  const auto points_file = [&](int id) { return work / ("points_" + std::to_string(id) + ".bin"); };

  // Waves: a wave's blocks take lattice values only from earlier waves.
  std::map<int, std::vector<int>> waves;
  for (int id : block_order(grid)) waves[block_wave(grid, id)].push_back(id);
  int done = 0, resumed = 0;
  std::size_t max_points = 0;
  // Within a wave, the largest blocks first, each to the least loaded rank.
  const std::vector<std::size_t> estimate = estimate_block_points(s, grid);
  std::map<int, std::vector<int>> owners;
  for (const auto& [wave, ids] : waves) owners[wave] = assign_blocks(ids, estimate, ranks.size());
  // This rank's blocks, sorted out of the input in one streamed pass (each into
  // points_<id>.bin, removed when the block is done), not one pass a block.
  error = attempt([&] {
    // With --resume, a block's file is kept when it was sorted for this grid.
    std::vector<int> unsorted;
    for (const auto& [wave, ids] : waves)
      for (std::size_t t = 0; t < ids.size(); ++t) {
        const int id = ids[t];
        if (owners[wave][t] != ranks.rank()) continue;
        if (resume && fs::exists(faces_file(id)) && fs::exists(piece_file(id))) continue;
        if (resume && fs::exists(points_file(id)) && bucket_matches(points_file(id).string(), grid.region(id)))
          continue;
        unsorted.push_back(id);
      }
    if (unsorted.empty()) return;
    note("sorting " + input + " into " + std::to_string(unsorted.size()) + " block" +
         (unsorted.size() > 1 ? "s" : "") + " (one streamed pass)");
    make_work_folder(work);
    bucket_points(source, grid, unsorted, [&](int id) { return points_file(id).string(); });
  });
  if (ranks.any_failed(!error.empty(), error)) fail_with(error);
  for (const auto& [wave, ids] : waves) {
    const std::vector<int>& owner = owners[wave];
    error = attempt([&] {
      for (std::size_t t = 0; t < ids.size(); ++t) {
        if (owner[t] != ranks.rank()) continue;
        const int id = ids[t];
        const auto c = grid.coords(id);
        const std::string where = "block " + std::to_string(id + 1) + "/" + std::to_string(grid.size()) + " (" +
                                  std::to_string(c[0]) + ", " + std::to_string(c[1]) + ", " + std::to_string(c[2]) + ")";
        if (resume && fs::exists(faces_file(id)) && fs::exists(piece_file(id))) {
          ++resumed;
          note(where + ": done before, skipped (--resume)");
          continue;
        }
        SeamTable upper;
        for (int q = 1; q < 8; ++q) {
          const int ni = c[0] + (q & 1), nj = c[1] + (q >> 1 & 1), nk = c[2] + (q >> 2 & 1);
          if (ni >= grid.counts[0] || nj >= grid.counts[1] || nk >= grid.counts[2]) continue;
          const fs::path f = faces_file(grid.id(ni, nj, nk));
          const SeamTable t = table_from_bytes(read_file_bytes(f), f.string());
          upper.insert(t.begin(), t.end());
        }
        const Aabb region = grid.region(id);
        const Cloud pts = read_bucket(points_file(id).string(), &region);
        max_points = std::max(max_points, pts.size());
        SeamTable lower;
        const BlockMesh piece = reconstruct_block(pts, grid, id, s, p, upper, lower);
        write_file_atomic(piece_file(id), to_bytes(piece));
        write_file_atomic(faces_file(id), to_bytes(lower));  // last: the block counts as done
        fs::remove(points_file(id));
        ++done;
        note(where + ": " + std::to_string(pts.size()) + " points, " + std::to_string(piece.mesh.faces.size()) +
             " faces, " + fmt("%.2f s", piece.seconds));
      }
    });
    if (ranks.any_failed(!error.empty(), error)) fail_with(error);
    ranks.barrier();
  }
  // Each rank's peak memory so far (its blocks), for the run's summary.
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  run.rank_peak_mb = ranks.gather(double(ru.ru_maxrss) / 1024.0);
  run.resumed = resumed;
  run.stats.blocks = grid.size();
  run.stats.counts = grid.counts;
  run.stats.max_block_points = max_points;
  if (!run.root) return run;

  // Rank 0: the pieces stitched into one mesh, finished as the single run's; into a
  // PLY straight from the pieces' files (one in memory at a time).
  const auto load = [&](int id) {
    const fs::path f = piece_file(id);
    return piece_from_bytes(read_file_bytes(f), f.string());
  };
  if (!output.empty()) {
    run.result = write_blocks_ply(load, grid, s, p, output, (work / "faces.tmp").string(), &run.stats);
    run.written = true;
  } else {
    std::vector<BlockMesh> pieces(std::size_t(grid.size()));
    for (int id = 0; id < grid.size(); ++id) pieces[std::size_t(id)] = load(id);
    run.result = assemble_blocks(pieces, grid, s, p, &run.stats);
  }
  SurfaceResult& out = run.result;
  out.seconds.total = seconds_since(t0);
  return run;
}

void check_blocks_work_folder(const std::string& work, const std::vector<std::string>& inputs) {
  std::error_code ec;
  const fs::path folder = fs::weakly_canonical(fs::absolute(work), ec);
  for (const std::string& in : inputs) {
    if (in.empty()) continue;
    const fs::path p = fs::weakly_canonical(fs::absolute(in), ec);
    const fs::path rel = p.lexically_relative(folder);
    if (!rel.empty() && *rel.begin() != "..")
      throw InvalidInput(in + ": inside " + work + ", the blocks' work folder for this output, which is cleared; "
                         "move it or choose another output");
  }
  if (!fs::exists(folder, ec)) return;
  if (!fs::is_directory(folder, ec))
    throw InvalidInput(work + ": the blocks' work folder for this output is a file; move it or choose another output");
  // The files the blocks write (below and in reconstruct/blocks.cpp), the
  // .part files they rename into place, and write_file_atomic's temporaries (a run
  // killed mid-way leaves those for --resume).
  static const std::regex ours(
      R"((summary\.bin|grid\.txt|faces\.tmp|(faces|piece|points|wlop_points)_[0-9]+\.bin|wlop_[0-9]+\.(ply|empty))(\.part)?(\.tmp-.*)?)");
  for (const fs::directory_entry& e : fs::directory_iterator(folder, ec))
    if (!e.is_regular_file(ec) || !std::regex_match(e.path().filename().string(), ours))
      throw InvalidInput(work + ": the blocks' work folder for this output holds " + e.path().filename().string() +
                         ", which the blocks did not write; it would be cleared: move it or choose another output");
}

}  // namespace station
