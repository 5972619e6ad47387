#include "station/commands.h"

#include <CLI/CLI.hpp>
#include <sys/resource.h>
#include <tbb/global_control.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
#include <cmath>
#include <csignal>
#include <unistd.h>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <sstream>

#include "capture/capture.h"
#include "capture/session.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/io.h"
#include "core/stanford_conf.h"
#include "core/threads.h"
#include "drivers/registry.h"
#include "reconstruct/sdm.h"
#include "registration/registration.h"
#include "station/config.h"
#include "station/json.h"
#include "station/blocks_run.h"
#include "station/params.h"
#include "station/pipeline.h"
#include "station/progress.h"

namespace station::cli {

namespace {

std::atomic<bool> g_stop{false};

/// First Ctrl-C: stop after the step in progress (a view, a stage); second: abort now.
extern "C" void on_sigint(int) {
  if (g_stop) {
    on_interrupt(0);  // abort now: what is half-written goes
    return;
  }
  g_stop = true;
  static const char msg[] = "\nstopping after the step in progress (Ctrl-C again to abort now)\n";
  [[maybe_unused]] auto n = ::write(2, msg, sizeof msg - 1);
}

/// A new session goes into a new or an empty folder: in one holding other files the
/// session's (view_000.ply, its colour image, merged.ply) replaced the user's silently.
/// (A folder with a session.yaml: Session::create says it holds a session.)
void check_new_session_folder(const fs::path& dir, const char* command) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return;
  if (fs::symlink_status(dir / kManifestName, ec).type() != fs::file_type::not_found) return;
  if (!fs::is_empty(dir, ec))
    throw IoError(dir.string() + ": holds other files and no session; " + command +
                  " into a new or an empty folder");
}

int run_job(const StationConfig& cfg, const Common& c, const RunArgs& a, bool blocks_over_ranks = false) {
  RunRequest req;
  req.blocks_over_ranks = blocks_over_ranks;
  req.input = a.in;
  req.out_dir = a.out;
  req.resume = a.resume;
  req.quiet = a.quiet || c.json;
  req.report = !a.no_report;
  req.stop = &g_stop;
  g_stop = false;
  std::signal(SIGINT, on_sigint);
  RunResult r;
  try {
    r = run_pipeline(cfg, req);
  } catch (const IoError& e) {
    default_interrupt_handling();
    // A failed write (full disk...) leaves every finished stage's output in place;
    // say so only where some stage did finish (not for a missing input).
    std::error_code ec;
    if (!fs::exists(fs::path(a.out) / "run.yaml", ec)) throw;
    throw IoError(std::string(e.what()) + "; finished stages in " + a.out +
                  " are intact: fix the cause (a full disk: free space) and rerun with --resume");
  }
  default_interrupt_handling();
  if (r.interrupted) {
    std::fprintf(stderr, "run: interrupted after %zu stages; continue with: station run %s -o %s --resume\n",
                 r.stages.size(), a.in.c_str(), a.out.c_str());
    return 130;
  }
  if (c.json) {
    JsonObject stages;
    for (const StageRecord& s : r.stages) {
      JsonObject st;
      st.add("seconds", s.seconds).add("peak_rss_mb", s.peak_rss_mb).add("reused", s.reused).add("output", s.output);
      JsonObject figs;
      for (const auto& [k, v] : s.figures) figs.add(k, v);
      st.add("figures", figs);
      stages.add(s.name, st);
    }
    print_summary(JsonObject()
                      .add("command", "run")
                      .add("input", a.in)
                      .add("out", a.out)
                      .add("mesh", r.mesh.string())
                      .add("report", r.report.string())
                      .add("stages", stages));
  } else if (!a.quiet) {
    double total = 0;
    std::printf("%-12s %9s %10s %7s\n", "stage", "time s", "peak MiB", "reused");
    for (const StageRecord& s : r.stages) {
      std::printf("%-12s %9.2f %10.0f %7s\n", s.name.c_str(), s.seconds, s.peak_rss_mb, s.reused ? "yes" : "no");
      total += s.seconds;
    }
    std::printf("%-12s %9.2f\n", "total", total);
    std::printf("mesh: %s\n", r.mesh.c_str());
    if (!r.report.empty()) std::printf("report: %s\n", r.report.c_str());
  }
  // Views that failed registration (named by the register stage's warnings, also when
  // it was reused) make a partial result, as for `station register`.
  for (const StageRecord& s : r.stages)
    if (s.name == "register" && s.figures.count("failed_views") && s.figures.at("failed_views") > 0) {
      if (!c.json)
        std::fprintf(stderr, "run: %.0f of %.0f views failed registration; the mesh is made from the others\n",
                     s.figures.at("failed_views"), s.figures.count("views") ? s.figures.at("views") : 0.0);
      return 3;
    }
  return 0;
}

int capture_into(Session& session, Scanner& scanner, Turntable& turntable,
                 const CaptureParams& params, const Common& c, const char* command,
                 std::chrono::steady_clock::time_point t0) {
  Progress bar(command, params.views, c.json);
  std::signal(SIGINT, on_sigint);
  CaptureResult res;
  try {
    res = run_capture(
        scanner, turntable, session, params,
        [&](const CaptureProgress& p) {
          char note[96];
          std::snprintf(note, sizeof note, "view %d at %.1f deg: %zu points", p.view, p.angle_deg, p.points);
          bar.update(p.view + 1, note);
        },
        &g_stop);
  } catch (const Error& e) {
    default_interrupt_handling();
    // The views recorded before the failure are in the session (each one committed to
    // its manifest as it came): say so, and how to go on.
    const std::size_t kept = session.manifest().views.size();
    std::string next = "; the " + std::to_string(kept) + " views recorded before it are kept in " +
                       session.dir().string();
    // A replay resumes the same way: the session names its scanner (sim:replay).
    next += ": once the cause is fixed, " + resume_hint(session, turntable);
    if (kept == 0) next = "; nothing was recorded in " + session.dir().string();
    if (dynamic_cast<const DeviceError*>(&e)) throw DeviceError(e.what() + next);
    if (dynamic_cast<const IoError*>(&e)) throw IoError(e.what() + next);
    if (dynamic_cast<const FormatError*>(&e)) throw FormatError(e.what() + next);
    throw InvalidInput(e.what() + next);
  }
  default_interrupt_handling();
  scanner.close();
  turntable.close();
  if (res.interrupted) {
    std::fprintf(stderr, "%s: interrupted after %zu views; %s\n", session.dir().c_str(),
                 session.manifest().views.size(), resume_hint(session, turntable).c_str());
    return 130;
  }
  bar.finish();
  if (const std::string w = check_recorded_points(session, std::size_t(res.resumed_from)); !w.empty())
    std::fprintf(stderr, "warning: %s\n", w.c_str());
  const double t_capture = seconds_since(t0);
  const auto t1 = std::chrono::steady_clock::now();
  JsonObject merged = write_merged(session, session.dir() / "merged.ply", c.json);
  JsonObject j;
  j.add("command", command)
      .add("session", session.dir().string())
      .add("views", session.manifest().views.size())
      .add("recorded", res.recorded)
      .add("resumed_from", res.resumed_from)
      .add("points", res.points)
      .add("merged", merged)
      .add("timings_s", JsonObject().add("capture", t_capture).add("merge", seconds_since(t1)));
  if (c.json) {
    print_summary(j);
  } else {
    std::printf("%s: %zu views (%d new, %zu points) in %s\n", command,
                session.manifest().views.size(), res.recorded, res.points, session.dir().c_str());
    if (session.manifest().axis) std::printf("merged by turntable: %s\n", (session.dir() / "merged.ply").c_str());
  }
  return 0;
}

}  // namespace

std::string check_recorded_points(const Session& session, std::size_t first_new) {
  const std::vector<ViewRecord>& views = session.manifest().views;
  std::vector<std::size_t> empty;
  // (A view of an earlier run may not say how many points it holds: 0 is unknown.)
  for (std::size_t i = first_new; i < views.size(); ++i)
    if (views[i].points == 0) empty.push_back(i);
  if (empty.empty()) return {};
  const char* why =
      "is the object inside the working volume (capture.volume), above the table clearance and within the "
      "scanner's range? (a simulated mesh: check its scale)";
  const std::size_t recorded = views.size() - std::min(first_new, views.size());
  if (empty.size() == recorded)
    throw NoPointsRecorded(session.dir().string() + ": no points in any of the " + std::to_string(recorded) +
                           (first_new > 0 ? " views recorded now: " : " views: ") + why);
  std::string list;
  for (std::size_t k = 0; k < empty.size() && k < 8; ++k) list += (k ? ", " : "") + std::to_string(empty[k]);
  if (empty.size() > 8) list += ", ...";
  return std::to_string(empty.size()) + " of " + std::to_string(recorded) + " views have no points (views " +
         list + "): " + why;
}

/// A session this command created whose first view failed: what it wrote goes again
/// (the manifest, a view file written before its colour image or the manifest
/// failed), as the message says nothing was recorded; a stub would make the next try
/// say "already holds a session" or "holds other files". The folder was new or empty
/// (check_new_session_folder), so all in it is the command's; a new one goes too.
void drop_unrecorded_session(const Session& session, bool folder_existed, bool empty_views_too) {
  const std::vector<ViewRecord>& views = session.manifest().views;
  if (!views.empty() && !empty_views_too) return;
  if (std::any_of(views.begin(), views.end(), [](const ViewRecord& v) { return v.points > 0; })) return;
  std::error_code ec;
  for (const fs::directory_entry& e : fs::directory_iterator(session.dir(), ec)) fs::remove_all(e.path(), ec);
  if (!folder_existed) fs::remove(session.dir(), ec);
}

int cmd_devices(const Common& c) {
  load_common(c);
  DeviceRegistry reg = make_registry();
  JsonObject j;
  int n = 0;
  for (const DeviceInfo& d : reg.list()) {
    const char* kind = d.kind == DeviceKind::kScanner ? "scanner" : "turntable";
    if (!c.json)
      std::printf("%-10s %-40s %s%s\n", kind, d.uri.c_str(), d.description.c_str(),
                  d.available ? "" : " (unavailable)");
    j.add(d.uri, JsonObject().add("kind", kind).add("description", d.description).add("available", d.available));
    ++n;
  }
  if (c.json) print_summary(JsonObject().add("command", "devices").add("count", n).add("devices", j));
  return 0;
}

namespace {

// Ranks > 0 of `mpirun station run`: the consolidation's and the surface stage's blocks
// with rank 0, until
// rank 0 says stop (station/blocks_run.h).
int block_worker(const StationConfig& cfg, const Common& c) {
  auto threads = limit_threads(cfg.threads);
  const auto& rc = cfg.pipeline.reconstruct;
  while (const std::optional<BlockJob> job = receive_block_job()) {
    if (job->kind == BlockJob::Kind::kConsolidate) {
      const auto note = [&](const std::string& line) {
        if (!c.json) std::fprintf(stderr, "  consolidate: %s\n", line.c_str());
      };
      try {
        (void)run_consolidate_blocks(job->input, wlop_params(cfg.pipeline, cfg.threads), job->blocks, job->work, note,
                                     rc.max_memory_gb * 1e9);
      } catch (const std::exception&) {
        // Every rank fails alike; rank 0 reports it and sends the stop.
      }
      continue;
    }
    SurfaceParams sp = surface_params(cfg.pipeline, cfg.threads);
    sp.table_up = job->up;
    sp.boundary_flags = true;
    sp.note = [&](const std::string& line) {
      if (!c.json) std::fprintf(stderr, "  surface: %s\n", line.c_str());
    };
    try {
      (void)run_blocks(job->input, sp, rc.blocks, job->work, false, {}, rc.max_memory_gb * 1e9);
    } catch (const std::exception&) {
      // Every rank fails alike; rank 0 reports it and sends the stop.
    }
  }
  return 0;
}

// A session's name in a batch: its folder's (a cloud file's stem), made unique.
std::string batch_name(const std::string& in, std::map<std::string, int>& seen) {
  fs::path p = fs::path(in).lexically_normal();
  if (p.filename().empty()) p = p.parent_path();
  if (p.filename() == "session.yaml") p = p.parent_path();
  std::string name = fs::is_directory(p) ? p.filename().string() : p.stem().string();
  if (name.empty() || name == "." || name == "..") name = "session";
  const int n = ++seen[name];
  return n == 1 ? name : name + "_" + std::to_string(n);
}

// `station run --batch LIST`: every session of the list (a path a line, relative to
// the list's folder; blank lines and # comments skipped) into OUT/<name>, spread one
// session at a time over the MPI ranks under mpirun (in sequence without), then a
// summary table (OUT/batch.tsv, printed by rank 0). Exit 3 when any session failed.
int run_batch(const StationConfig& cfg, const Common& c, const RunArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  // Read whole: a folder or a device is named as such (a FIFO blocked, /dev/zero ran on).
  std::istringstream list(read_file_bytes(a.batch));
  std::vector<std::string> sessions, names;
  std::map<std::string, int> seen;
  for (std::string line; std::getline(list, line);) {
    const auto b = line.find_first_not_of(" \t\r"), e = line.find_last_not_of(" \t\r");
    if (b == std::string::npos || line[b] == '#') continue;
    fs::path path = line.substr(b, e - b + 1);
    if (path.is_relative()) path = fs::path(a.batch).parent_path() / path;
    sessions.push_back(path.string());
    names.push_back(batch_name(path.string(), seen));
  }
  if (sessions.empty()) throw InvalidInput(a.batch + ": no sessions in the batch list");
  const int rank = mpi_rank(), ranks = mpi_ranks();
  const fs::path out = a.out, lines = out / ".batch";
  fs::create_directories(lines);
  auto threads = limit_threads(cfg.threads);
  const bool quiet = a.quiet || c.json;
  for (std::size_t i = 0; i < sessions.size(); ++i) {
    if (int(i % std::size_t(ranks)) != rank) continue;
    const std::string who = ranks > 1 ? "batch (rank " + std::to_string(rank) + "): " : "batch: ";
    if (!quiet)
      std::fprintf(stderr, "%s%zu/%zu %s -> %s\n", who.c_str(), i + 1, sessions.size(), sessions[i].c_str(),
                   (out / names[i]).c_str());
    const auto ts = std::chrono::steady_clock::now();
    std::string status = "ok", message, mesh;
    double vertices = 0;
    try {
      RunRequest req;
      req.input = sessions[i];
      req.out_dir = out / names[i];
      req.resume = a.resume;
      req.quiet = quiet || ranks > 1;
      req.report = !a.no_report;
      const RunResult r = run_pipeline(cfg, req);
      mesh = r.mesh.string();
      for (const StageRecord& st : r.stages) {
        if (st.name == "surface" && st.figures.count("vertices")) vertices = st.figures.at("vertices");
        if (st.name == "register" && st.figures.count("failed_views") && st.figures.at("failed_views") > 0) {
          status = "partial";
          message = std::to_string(int(st.figures.at("failed_views"))) + " views failed registration";
        }
      }
    } catch (const std::exception& e) {
      status = "failed";
      message = e.what();
    }
    for (char& ch : message)
      if (ch == '\t' || ch == '\n') ch = ' ';
    const double secs = seconds_since(ts);
    char row[64];
    std::snprintf(row, sizeof row, "%.2f\t%.0f", secs, vertices);
    write_file_atomic(lines / (std::to_string(i) + ".tsv"),
                      sessions[i] + "\t" + status + "\t" + row + "\t" + mesh + "\t" + message + "\n");
    if (!quiet)
      std::fprintf(stderr, "%s%s: %s in %.1f s%s%s\n", who.c_str(), names[i].c_str(), status.c_str(), secs,
                   message.empty() ? "" : ": ", message.c_str());
  }
  mpi_barrier();
  if (rank != 0) return 0;
  std::string table = "session\tstatus\tseconds\tvertices\tmesh\tmessage\n";
  int failed = 0, partial = 0;
  std::vector<std::vector<std::string>> rows;
  for (std::size_t i = 0; i < sessions.size(); ++i) {
    const fs::path f = lines / (std::to_string(i) + ".tsv");
    std::string line = fs::exists(f) ? read_file_bytes(f) : sessions[i] + "\tfailed\t0\t0\t\tno result (its rank stopped)\n";
    table += line;
    std::vector<std::string> cols;
    std::stringstream ss(line.substr(0, line.find('\n')));
    for (std::string col; std::getline(ss, col, '\t');) cols.push_back(col);
    cols.resize(6);
    failed += cols[1] == "failed";
    partial += cols[1] == "partial";
    rows.push_back(cols);
  }
  write_file_atomic(out / "batch.tsv", table);
  std::error_code ec;
  fs::remove_all(lines, ec);
  if (c.json) {
    print_summary(JsonObject()
                      .add("command", "run")
                      .add("batch", a.batch)
                      .add("out", a.out)
                      .add("sessions", int(sessions.size()))
                      .add("failed", failed)
                      .add("partial", partial)
                      .add("ranks", ranks)
                      .add("table", (out / "batch.tsv").string())
                      .add("timings_s", JsonObject().add("total", seconds_since(t0))));
  } else {
    std::printf("%-24s %-8s %9s %10s  %s\n", "session", "status", "time s", "vertices", "mesh or message");
    for (std::size_t i = 0; i < rows.size(); ++i)
      std::printf("%-24s %-8s %9s %10s  %s\n", names[i].c_str(), rows[i][1].c_str(), rows[i][2].c_str(),
                  rows[i][3].c_str(), rows[i][1] == "failed" ? rows[i][5].c_str() : rows[i][4].c_str());
    std::printf("batch: %zu sessions on %d rank%s, %d failed, %d partial, %.1f s -> %s\n", sessions.size(), ranks,
                ranks > 1 ? "s" : "", failed, partial, seconds_since(t0), (out / "batch.tsv").c_str());
  }
  return failed + partial > 0 ? 3 : 0;
}

}  // namespace

int cmd_run(const Common& c, const RunArgs& a) {
  StationConfig cfg = load_common(c, a.set);
  if (!a.batch.empty()) {
    if (!a.in.empty()) throw InvalidInput("station run: give a session or --batch LIST, not both");
    return run_batch(cfg, c, a);
  }
  if (a.in.empty()) throw InvalidInput("station run: give a session (or a cloud file) or --batch LIST");
  if (mpi_ranks() > 1) {
    // Under mpirun: rank 0 runs the job, the others its surface stage's blocks.
    if (mpi_rank() > 0) return block_worker(cfg, c);
    struct Stop {
      ~Stop() { send_block_job(nullptr); }
    } stop;
    return run_job(cfg, c, a, true);
  }
  return run_job(cfg, c, a);
}


int cmd_scan(const Common& c, const ScanArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  // --set section.key=value overrides the profile; a plain key=value is a scanner option.
  std::vector<std::string> profile_set, scanner_set;
  for (const std::string& kv : a.set) {
    const auto eq = kv.find('=');
    if (eq == std::string::npos || eq == 0) throw UsageError("--set " + kv + ": expected key=value");
    (kv.substr(0, eq).find('.') != std::string::npos ? profile_set : scanner_set).push_back(kv);
  }
  StationConfig cfg = load_common(c, profile_set);
  auto threads = limit_threads(cfg.threads);
  for (const std::string& kv : scanner_set) {
    const auto eq = kv.find('=');
    cfg.scanner_options[kv.substr(0, eq)] = kv.substr(eq + 1);
  }
  std::string scanner_uri = a.scanner.empty() ? compose_uri(cfg.scanner_uri, cfg.scanner_options) : a.scanner;
  std::string turntable_uri =
      a.turntable.empty() ? compose_uri(cfg.turntable_uri, cfg.turntable_options) : a.turntable;
  const fs::path dir = a.out;
  std::optional<Session> session;
  if (a.resume) {
    session = Session::open(dir);
    const SessionManifest& m = session->manifest();
    // Resume with the devices and the plan the session was started with.
    if (a.scanner.empty() && !m.scanner.empty()) scanner_uri = m.scanner;
    if (a.turntable.empty() && !m.turntable.empty()) turntable_uri = m.turntable;
    if (m.planned_views > 0) {
      cfg.capture.views = m.planned_views;
      cfg.capture.start_deg = m.start_deg;
      cfg.capture.step_deg = m.step_deg;
    }
    if (int(m.views.size()) >= cfg.capture.views) {
      if (!c.json) std::printf("%s: already complete (%zu views)\n", dir.c_str(), m.views.size());
    }
  }
  if (!session) check_new_session_folder(dir, "scan");  // (before the devices are opened)
  DeviceRegistry reg = make_registry();
  auto scanner = reg.make_scanner(scanner_uri);
  auto turntable = reg.make_turntable(turntable_uri);
  scanner->open();
  turntable->open();
  const bool created = !session;
  const bool existed = fs::exists(dir);
  if (!session) {
    SessionManifest m;
    m.scanner = scanner_uri;
    m.turntable = turntable_uri;
    session = Session::create(dir, m);
  }
  int code = 0;
  try {
    code = capture_into(*session, *scanner, *turntable, cfg.capture, c, "scan", t0);
  } catch (const NoPointsRecorded& e) {
    if (!created) throw;
    drop_unrecorded_session(*session, existed, true);
    throw NoPointsRecorded(std::string(e.what()) + "; nothing was kept");
  } catch (const Error&) {
    if (created) drop_unrecorded_session(*session, existed);
    throw;
  }
  if (code != 0 || !a.run) return code;
  RunArgs ra;
  ra.in = dir.string();
  ra.out = (dir / "run").string();
  ra.resume = fs::exists(dir / "run" / "run.yaml");
  return run_job(cfg, c, ra);
}

int cmd_replay(const Common& c, const std::string& source, const std::string& out) {
  const auto t0 = std::chrono::steady_clock::now();
  StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  Session src = Session::open(source);
  const SessionManifest& sm = src.manifest();
  if (sm.views.empty()) throw InvalidInput(source + ": the session has no views to replay");
  CaptureParams params = cfg.capture;
  params.views = sm.planned_views > 0 ? sm.planned_views : int(sm.views.size());
  params.start_deg = sm.planned_views > 0 ? sm.start_deg : 0;
  params.step_deg = sm.planned_views > 0 ? sm.step_deg : 360.0 / params.views;
  params.views = std::min<int>(params.views, int(sm.views.size()));
  params.crop = false;  // a recording is replayed as it was recorded
  params.axis = sm.axis;
  check_new_session_folder(out, "replay");
  DeviceRegistry reg = make_registry();
  const std::string scanner_uri = compose_uri("sim:replay", {{"session", fs::absolute(source).string()}});
  auto scanner = reg.make_scanner(scanner_uri);
  auto turntable = reg.make_turntable("sim:turntable");
  scanner->open();
  turntable->open();
  SessionManifest m;
  m.scanner = scanner_uri;
  m.turntable = "sim:turntable";
  m.units = sm.units;
  m.intrinsics = sm.intrinsics;
  const bool existed = fs::exists(out);
  Session dst = Session::create(out, m);
  try {
    return capture_into(dst, *scanner, *turntable, params, c, "replay", t0);
  } catch (const NoPointsRecorded& e) {
    drop_unrecorded_session(dst, existed, true);
    throw NoPointsRecorded(std::string(e.what()) + "; nothing was kept");
  } catch (const Error&) {
    drop_unrecorded_session(dst, existed);
    throw;
  }
}

// Files whose names end in a number (scan_0.ply, scan_24.ply, ...) given in
// text order, not in the order of those numbers, as a shell glob gives them:
// the first pair out of numeric order, or none.
static std::optional<std::pair<std::string, std::string>> text_ordered_numbers(const std::vector<std::string>& files) {
  std::vector<long long> numbers;
  for (const std::string& f : files) {
    const std::string stem = fs::path(f).stem().string();
    std::size_t k = stem.size();
    while (k > 0 && std::isdigit(static_cast<unsigned char>(stem[k - 1]))) --k;
    if (k == stem.size() || stem.size() - k > 15) return std::nullopt;
    numbers.push_back(std::stoll(stem.substr(k)));
  }
  for (std::size_t i = 1; i < numbers.size(); ++i)
    if (numbers[i] < numbers[i - 1])
      return std::make_pair(fs::path(files[i - 1]).filename().string(), fs::path(files[i]).filename().string());
  return std::nullopt;
}

int cmd_import(const Common& c, const ImportArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  load_common(c);
  if (a.every < 1) throw InvalidInput("--every must be at least 1");
  if (!std::isfinite(a.start)) throw UsageError("--start: must be a finite angle in degrees");
  if (!std::isfinite(a.step)) throw UsageError("--step: must be a finite angle in degrees");
  // The files the import writes (its manifest, view_NNN.ply): they never replace a file
  // being imported, and a failed import removes those it created (below).
  std::vector<std::string> files{(fs::path(a.out) / kManifestName).string()};
  for (std::size_t i = 0; i < a.files.size(); ++i) {
    char name[64];
    std::snprintf(name, sizeof name, "view_%03zu.ply", i);
    files.push_back((fs::path(a.out) / name).string());
  }
  {
    std::vector<std::string> inputs = a.files;
    inputs.push_back(a.stanford_conf);
    inputs.push_back(c.config);
    check_not_an_input(files, inputs);
  }
  // Nor a file of the user's that happens to have a view's name (add_view replaces
  // files its manifest does not list). (A session.yaml there: Session::create says so.)
  for (std::size_t k = 1; k < files.size(); ++k) {
    std::error_code ec;
    if (fs::symlink_status(files[k], ec).type() != fs::file_type::not_found)
      throw IoError(files[k] + ": exists, and an import never replaces a file; import into a new or an empty folder");
  }
  std::map<std::string, Eigen::Matrix4d> poses;
  if (!a.stanford_conf.empty()) {
    const std::vector<StanfordScan> scans = read_stanford_conf(a.stanford_conf);
    for (const StanfordScan& scan : scans) poses[scan.file] = scan.pose;
    if (poses.empty())
      throw FormatError(a.stanford_conf + ": no 'bmesh FILE tx ty tz qx qy qz qw' line: not a Stanford .conf");
    const bool any = std::any_of(a.files.begin(), a.files.end(), [&](const std::string& f) {
      return poses.count(fs::path(f).filename().string()) > 0;
    });
    if (!any)
      throw InvalidInput(a.stanford_conf + ": names none of the imported files (its first is " +
                         scans.front().file + ")");
  }
  for (std::size_t i = 0; i < a.files.size(); ++i)
    for (std::size_t j = 0; j < i; ++j)
      if (a.files[i] == a.files[j] || same_file(a.files[i], a.files[j]))
        throw InvalidInput(a.files[i] + ": given twice (views " + std::to_string(j) + " and " + std::to_string(i) +
                           "); a view is imported once");
  // Read everything first: a bad file aborts before anything is written.
  std::vector<Cloud> clouds;
  for (const std::string& f : a.files) {
    Cloud cl = read_cloud(f);
    if (cl.empty()) throw InvalidInput(f + ": no points; an empty view cannot be imported");
    if (a.every > 1) {
      Cloud s;
      for (std::size_t i = 0; i < cl.size(); i += a.every) {
        s.points.push_back(cl.points[i]);
        if (cl.has_normals()) s.normals.push_back(cl.normals[i]);
        if (cl.has_colours()) s.colours.push_back(cl.colours[i]);
      }
      cl = std::move(s);
    }
    clouds.push_back(std::move(cl));
  }
  // The same scan under two names (a copy made by mistake): registered, it pins two
  // views together; said, not refused, since the user may mean it.
  for (std::size_t i = 0; i < clouds.size(); ++i)
    for (std::size_t j = 0; j < i; ++j)
      if (clouds[i].points == clouds[j].points) {
        std::fprintf(stderr, "warning: %s has the same points as %s: the same scan imported twice?\n",
                     a.files[i].c_str(), a.files[j].c_str());
        break;
      }
  if (const auto pair = text_ordered_numbers(a.files))
    std::fprintf(stderr,
                 "warning: the files are not in the order of the numbers in their names (%s before %s), as a "
                 "shell glob sorts them; the views are taken in the order given%s. Give them in turntable order "
                 "(e.g. ls -v) unless that is it\n",
                 pair->first.c_str(), pair->second.c_str(), a.has_step ? ", and --step gives their angles in it" : "");
  SessionManifest m;
  m.scanner = "import";
  m.units = a.units;
  if (a.has_step) {
    m.planned_views = int(a.files.size());
    m.start_deg = a.start;
    m.step_deg = a.step;
  }
  // A failed import leaves nothing of its own behind (no stub session.yaml that would
  // block a retry, no empty folder): the files and folders it creates go again.
  CreatedOutputs created(a.out, std::vector<fs::path>(files.begin(), files.end()));
  Session s = Session::create(a.out, m);
  Progress bar("import", int(a.files.size()), c.json);
  std::size_t total = 0;
  for (std::size_t i = 0; i < a.files.size(); ++i) {
    ViewRecord rec;
    if (a.has_step) rec.angle_deg = std::fmod(a.start + a.step * double(i), 360.0);
    const std::string name = fs::path(a.files[i]).filename().string();
    auto it = poses.find(name);
    if (it != poses.end()) rec.reference_pose = it->second;
    else if (!poses.empty()) std::fprintf(stderr, "note: %s has no pose in %s\n", name.c_str(), a.stanford_conf.c_str());
    s.add_view(clouds[i], rec);
    total += clouds[i].size();
    bar.update(int(i) + 1, name);
  }
  bar.finish();
  created.keep();
  if (c.json)
    print_summary(JsonObject().add("command", "import").add("session", a.out).add("views", a.files.size())
                      .add("points", total).add("timings_s", JsonObject().add("import", seconds_since(t0))));
  else
    std::printf("import: %zu views, %zu points -> %s\n", a.files.size(), total, a.out.c_str());
  return 0;
}

void add_capture_commands(CLI::App& app, std::vector<Command>& out) {
  struct State {
    Common c_dev, c_scan, c_run, c_replay, c_import;
    ScanArgs scan_args;
    RunArgs run_args;
    std::string replay_src, replay_out = "out/replay";
    ImportArgs import_args;
    CLI::Option* step_opt = nullptr;
  };
  auto s = std::make_shared<State>();
  auto& c_dev = s->c_dev;
  auto& c_scan = s->c_scan;
  auto& c_run = s->c_run;
  auto& c_replay = s->c_replay;
  auto& c_import = s->c_import;
  auto& scan_args = s->scan_args;
  auto& run_args = s->run_args;
  auto& replay_src = s->replay_src;
  auto& replay_out = s->replay_out;
  auto& import_args = s->import_args;
  auto* devices = app.add_subcommand("devices", "List the devices the station can drive");
  add_common(devices, c_dev);

  auto* scan = app.add_subcommand("scan", "Scan an object on the turntable into a session folder");
  add_common(scan, c_scan);
  scan->add_option("-o,--out", scan_args.out, "session folder to write (or resume)")->capture_default_str();
  scan->add_flag("--resume", scan_args.resume, "continue an interrupted scan in --out");
  add_profile_options(scan, "scan", c_scan);
  scan->add_option("--scanner", scan_args.scanner, "scanner URI (overrides the profile)");
  scan->add_option("--turntable", scan_args.turntable, "turntable URI (overrides the profile)");
  scan->add_option("--set", scan_args.set,
                   "scanner option key=value, or profile key section.key=value (repeatable), e.g. --set noise=0.001");
  scan->add_flag("--run", scan_args.run, "then run the whole job (station run) into <out>/run");

  auto* runc = app.add_subcommand("run", "The whole job: register, consolidate, reconstruct a coloured mesh, report");
  add_common(runc, c_run);
  runc->add_option("input", run_args.in, "session folder (or session.yaml) or a cloud file");
  runc->add_option("--batch", run_args.batch,
                   "a list of sessions (a path a line) instead of one: each into OUT/<name>, one session a rank "
                   "under mpirun, then a summary table OUT/batch.tsv (exit 3 when any failed)");
  runc->add_option("-o,--out", run_args.out, "run folder: every stage's output, mesh.ply, report.html")->required();
  runc->add_flag("--resume", run_args.resume,
                 "continue a run in --out: finished stages whose inputs and parameters are unchanged are kept");
  runc->add_option("--set", run_args.set, "profile override section.key=value (repeatable), e.g. --set reconstruct.resolution=192");
  add_profile_options(runc, "run", c_run);
  runc->add_flag("--quiet", run_args.quiet, "no progress output");
  runc->add_flag("--no-report", run_args.no_report, "do not write report.html");

  auto* replay = app.add_subcommand("replay", "Play a recorded session back through the simulated scanner");
  add_common(replay, c_replay);
  replay->add_option("session", replay_src, "recorded session folder")->required();
  replay->add_option("-o,--out", replay_out, "session folder to write")->capture_default_str();


  auto* import = app.add_subcommand("import", "Make a session from view files recorded elsewhere");
  add_common(import, c_import);
  import->add_option("files", import_args.files, "view files (.ply .pcd; a mesh .obj .off gives its vertices), in turntable order")->required();
  import->add_option("-o,--out", import_args.out, "session folder to create")->required();
  import->add_option("--stanford-conf", import_args.stanford_conf, "Stanford .conf with reference poses (bmesh lines)");
  import->add_option("--start", import_args.start, "turntable angle of the first view, degrees")->check(finite_number());
  s->step_opt = import->add_option("--step", import_args.step, "turntable step between views, degrees (no angles without it)")->check(finite_number());
  import->add_option("--every", import_args.every, "keep every N-th point (downsample)")->capture_default_str()->check(whole_number(1, 2147483647));
  import->add_option("--units", import_args.units, "units of the files (recorded, not converted)")->check(CLI::IsMember({"m", "mm"}));


  out.push_back({devices, [s] { return cmd_devices(s->c_dev); }});
  out.push_back({scan, [s] { return cmd_scan(s->c_scan, s->scan_args); }});
  out.push_back({runc, [s] { return cmd_run(s->c_run, s->run_args); }});
  out.push_back({replay, [s] { return cmd_replay(s->c_replay, s->replay_src, s->replay_out); }});
  out.push_back({import, [s] {
                   s->import_args.has_step = s->step_opt->count() > 0;
                   return cmd_import(s->c_import, s->import_args);
                 }});
}

}  // namespace station::cli
