#include "station/cli.h"

#include <sys/resource.h>
#include <tbb/global_control.h>

#include <CLI/CLI.hpp>
#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
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
#include "registration/axis_calibration.h"
#include "registration/registration.h"
#include "capture/session.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/io.h"
#include "core/stanford_conf.h"
#include "core/texture.h"
#include "drivers/registry.h"
#include "drivers/v4l2_probe.h"
#include "reconstruct/color_transfer.h"
#include "eval/consolidation_metrics.h"
#include "eval/eval.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/mpu.h"
#include "core/normals.h"
#include "reconstruct/wlop.h"
#include "sim/sim.h"
#include "station/config.h"
#include "station/json.h"
#include "station/params.h"
#include "station/pipeline.h"
#include "reconstruct/dmc.h"
#include "reconstruct/sdm.h"
#include "reconstruct/surface.h"
#include "reconstruct/colour_edges.h"
#include "reconstruct/colour_function.h"
#include "drivers/real_devices.h"
#include "capture/camera_calibration.h"
#include "station/progress.h"

#ifndef STATION_VERSION
#define STATION_VERSION "dev"
#endif

namespace station {
namespace {

namespace fs = std::filesystem;

std::atomic<bool> g_stop{false};
/// First Ctrl-C: stop after the step in progress (a view, a stage); second: abort now.
extern "C" void on_sigint(int) {
  if (g_stop) {
    std::signal(SIGINT, SIG_DFL);
    std::raise(SIGINT);
    return;
  }
  g_stop = true;
  static const char msg[] = "\nstopping after the step in progress (Ctrl-C again to abort now)\n";
  [[maybe_unused]] auto n = ::write(2, msg, sizeof msg - 1);
}

/// A bad value of a command-line option: a usage error (exit 2), as CLI11's own.
class UsageError : public InvalidInput {
 public:
  using InvalidInput::InvalidInput;
};

/// Options every subcommand takes.
struct Common {
  std::string config;
  int threads = -1;
  bool json = false;
  /// Profile overrides from the command's profile options (station/params.h), in
  /// the order given, and how the user spelled each ("--resolution 5").
  std::vector<std::string> overrides;
  std::map<std::string, std::string> spelled;
};

void add_common(CLI::App* cmd, Common& c) {
  cmd->add_option("--config", c.config, "YAML profile (default: config/default.yaml)");
  cmd->add_option("--threads", c.threads, "worker threads (0 = all cores)")->check(CLI::NonNegativeNumber);
  cmd->add_flag("--json", c.json, "print a one-line JSON summary on stdout");
}

/// The command's options that stand for profile keys (station/params.h): each
/// becomes an override of its key, checked by the profile's rules.
void add_profile_options(CLI::App* cmd, const std::string& command, Common& c) {
  static const std::map<std::string, std::string> defaults = profile_values(default_config_path());
  for (const ProfileOption& o : profile_options()) {
    if (o.command != command) continue;
    const auto d = defaults.find(o.key);
    const std::string help = o.help + " (profile " + o.key +
                             (d != defaults.end() && o.flag_value.empty() ? "; default " + d->second : "") + ")";
    if (!o.flag_value.empty()) {
      cmd->add_flag_callback(
          o.option,
          [&c, o] {
            c.overrides.push_back(o.key + "=" + o.flag_value);
            c.spelled[c.overrides.back()] = o.option;
          },
          help);
      continue;
    }
    CLI::Option* opt = cmd->add_option_function<std::string>(
        o.option,
        [&c, o](const std::string& v) {
          c.overrides.push_back(o.key + "=" + v);
          c.spelled[c.overrides.back()] = o.option + " " + v;
          for (const std::string& i : o.implies) c.overrides.push_back(i);
        },
        help);
    if (!o.choices.empty()) opt->check(CLI::IsMember(o.choices));
  }
}

/// The profile with the command's overrides: `extra` (e.g. --set's) first, then the
/// profile options', so an option beats a --set of the same key. A bad value names
/// the option as given.
StationConfig load_common(const Common& c, const std::vector<std::string>& extra = {}) {
  std::vector<std::string> overrides = extra;
  overrides.insert(overrides.end(), c.overrides.begin(), c.overrides.end());
  StationConfig cfg;
  try {
    cfg = load_config(c.config.empty() ? default_config_path() : fs::path(c.config), overrides);
  } catch (const InvalidInput& e) {
    const std::string what = e.what();
    for (const auto& [kv, option] : c.spelled)
      if (what.rfind("--set " + kv + ":", 0) == 0) throw UsageError(option + what.substr(6 + kv.size()));
    throw;
  }
  if (c.threads >= 0) cfg.threads = c.threads;
  return cfg;
}

std::unique_ptr<tbb::global_control> limit_threads(int threads) {
  if (threads <= 0) return nullptr;
  return std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism,
                                               std::size_t(threads));
}

/// Prints a --json summary line, with the process's peak resident memory.
void print_summary(JsonObject j) {
  rusage ru{};
  ::getrusage(RUSAGE_SELF, &ru);
  j.add("peak_rss_mb", double(ru.ru_maxrss) / 1024.0);
  std::printf("%s\n", j.str().c_str());
}

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// The library names the data it complains about by role ("target: 3 control points...",
// "mesh: empty", "suggest_epsilon0: 3 points..."); at the command line the message must
// name the file. A message that already names the input or the output, or an option
// ("--..."), stays as it is; one that starts with a role in `roles` names that role's
// file; any other names the input.
template <class Fn>
int naming_the_file(const std::string& in, const std::string& out, Fn&& fn,
                    const std::vector<std::pair<std::string, std::string>>& roles = {}) {
  try {
    return fn();
  } catch (const InvalidInput& e) {
    const std::string what = e.what();
    const auto names = [&](const std::string& path) { return !path.empty() && what.find(path) != std::string::npos; };
    if (what.rfind("--", 0) == 0 || names(in) || names(out)) throw;
    std::string file = in;
    for (const auto& [role, path] : roles)
      if (what.rfind(role, 0) == 0) file = path;
    if (file.empty() || names(file)) throw;
    throw InvalidInput(file + ": " + what);
  }
}

// An output never replaces a recording: the manifest, a view file or a view's colour
// image of a session in any folder above it (all checked before the work).
void check_not_a_recording(const std::string& out) {
  if (out.empty()) return;
  std::error_code ec;
  const fs::path p = fs::absolute(out, ec).lexically_normal();
  for (fs::path dir = p.parent_path();; dir = dir.parent_path()) {
    const fs::path manifest = dir / kManifestName;
    if (fs::is_regular_file(manifest, ec)) {
      bool recorded = p == manifest;
      try {
        for (const ViewRecord& v : manifest_from_yaml(read_file_bytes(manifest), manifest.string()).views)
          recorded = recorded || p == (dir / v.file).lexically_normal() ||
                     (!v.color_image.empty() && p == (dir / v.color_image).lexically_normal());
      } catch (const Error&) {
        // An unreadable manifest lists nothing to compare with; the manifest itself is guarded.
      }
      if (recorded)
        throw InvalidInput(out + ": part of the session recorded in " + dir.string() + "; write the output elsewhere");
    }
    if (dir.empty() || dir == dir.root_path()) break;
  }
}

// An output's format is checked before the work, not after it: `kind` names what is
// written ("a cloud", "a mesh"), `exts` the lower-case extensions it can be written as.
void check_output_name(const std::string& out, const char* kind, std::initializer_list<const char*> exts) {
  check_not_a_recording(out);
  std::string ext = fs::path(out).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char ch) { return char(std::tolower(ch)); });
  std::string list;
  for (const char* e : exts) {
    if (ext == e) return;
    list += std::string(list.empty() ? "" : " or ") + e;
  }
  throw InvalidInput(out + ": " + kind + " is written as " + list + "; name the output that way");
}

DeviceRegistry make_registry() {
  DeviceRegistry reg;
  register_sim_devices(reg);
  register_real_devices(reg);  // serial turntables, V4L2 cameras (drivers/real_devices.h)
  return reg;
}

/// Writes the turntable-merged cloud of a session next to it, when it has an axis.
JsonObject write_merged(const Session& session, const fs::path& out, bool quiet) {
  JsonObject j;
  if (!session.manifest().axis) {
    if (!quiet)
      std::fprintf(stderr, "note: %s has no turntable axis; merged cloud not written\n",
                   session.dir().c_str());
    return j.add_null("path");
  }
  MergeResult merged = merge_by_turntable(session);
  if (merged.cloud.empty()) throw InvalidInput(session.dir().string() + ": no points in any view");
  write_ply(out, merged.cloud);
  return j.add("path", out.string())
      .add("points", merged.cloud.size())
      .add("views", merged.merged_views)
      .add("skipped_views", merged.skipped_views)
      .add("colours", merged.cloud.has_colors());
}

// ---- devices -------------------------------------------------------------------

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

// ---- scan / replay -------------------------------------------------------------

struct ScanArgs {
  std::string out = "out/scan";
  bool resume = false;
  std::string scanner, turntable;
  std::vector<std::string> set;
  bool run = false;  ///< go on with `station run` into <session>/run
};

// ---- run ------------------------------------------------------------------------

struct RunArgs {
  std::string in, out;
  bool resume = false, quiet = false, no_report = false;
  std::vector<std::string> set;
};

int run_job(const StationConfig& cfg, const Common& c, const RunArgs& a) {
  RunRequest req;
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
    std::signal(SIGINT, SIG_DFL);
    // A failed write (full disk...) leaves every finished stage's output in place.
    throw IoError(std::string(e.what()) + "; finished stages in " + a.out +
                  " are intact: free space and rerun with --resume");
  }
  std::signal(SIGINT, SIG_DFL);
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

int cmd_run(const Common& c, const RunArgs& a) {
  StationConfig cfg = load_common(c, a.set);
  return run_job(cfg, c, a);
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
    std::signal(SIGINT, SIG_DFL);
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
  std::signal(SIGINT, SIG_DFL);
  scanner.close();
  turntable.close();
  if (res.interrupted) {
    std::fprintf(stderr, "%s: interrupted after %zu views; %s\n", session.dir().c_str(),
                 session.manifest().views.size(), resume_hint(session, turntable).c_str());
    return 130;
  }
  bar.finish();
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

int cmd_scan(const Common& c, const ScanArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  // --set section.key=value overrides the profile; a plain key=value is a scanner option.
  std::vector<std::string> profile_set, scanner_set;
  for (const std::string& kv : a.set) {
    const auto eq = kv.find('=');
    if (eq == std::string::npos || eq == 0) throw InvalidInput("--set " + kv + ": expected key=value");
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
  DeviceRegistry reg = make_registry();
  auto scanner = reg.make_scanner(scanner_uri);
  auto turntable = reg.make_turntable(turntable_uri);
  scanner->open();
  turntable->open();
  if (!session) {
    SessionManifest m;
    m.scanner = scanner_uri;
    m.turntable = turntable_uri;
    session = Session::create(dir, m);
  }
  const int code = capture_into(*session, *scanner, *turntable, cfg.capture, c, "scan", t0);
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
  Session dst = Session::create(out, m);
  return capture_into(dst, *scanner, *turntable, params, c, "replay", t0);
}

// ---- eval ----------------------------------------------------------------------

/// An eval input: a cloud, or a mesh with its texture when it has one.
struct EvalInput {
  TexturedMesh textured;
  Texture texture;
  bool is_mesh = false;
  Shape shape() const {
    if (is_mesh) return textured.mesh;
    return textured.mesh.as_cloud();
  }
  /// The texture as a surface colour, when there is one.
  std::function<Rgb(int, double, double)> surface_color() const {
    if (texture.empty() || textured.corner_uv.empty()) return {};
    return [this](int f, double u, double v) { return station::surface_color(textured, texture, f, u, v); };
  }
};

void read_eval_input(const fs::path& p, EvalInput& in) {
  in.textured = read_textured_mesh(p);
  in.is_mesh = !in.textured.mesh.faces.empty();
  if (in.is_mesh && !in.textured.texture.empty() && !in.textured.corner_uv.empty())
    in.texture = load_texture(in.textured.texture);
}

std::string stats_json(const DirectedStats& s, JsonObject& j) {
  j.add("mean", s.mean).add("rms", s.rms).add("p95", s.p95).add("max", s.max).add("count", s.count);
  return j.str();
}

/// `station eval --points-metrics`: the consolidation metrics of A's points against
/// reference mesh B (reconstruct/consolidation_metrics.h).
struct PointsMetricsArgs {
  bool enabled = false;
  double edge_radius = 0;   ///< points within this distance of a sharp edge count (0: no edge error)
  double edge_angle = 30;   ///< degrees between face normals that make an edge sharp
};

struct PointsMetrics {
  std::size_t points = 0;
  double accuracy = 0, uniformity = 0, surface_uniformity = 0, area = 0;
  std::size_t sharp_edges = 0;
  std::optional<EdgeError> edge;
};

PointsMetrics points_metrics(const EvalInput& a, const EvalInput& b, const PointsMetricsArgs& args,
                             int threads) {
  if (!b.is_mesh) throw InvalidInput("--points-metrics: B must be a mesh (the reference surface)");
  const std::vector<Vec3f>& pts = a.textured.mesh.vertices;  // a cloud's points, a mesh's vertices
  const Mesh& ref = b.textured.mesh;
  PointsMetrics m;
  m.points = pts.size();
  m.area = mesh_area(ref);
  m.accuracy = mean_distance_to_mesh(pts, ref, threads);
  m.uniformity = uniformity(pts, m.area);
  m.surface_uniformity = surface_uniformity(pts, ref, threads);
  m.sharp_edges = sharp_edges(ref, args.edge_angle).size();
  if (args.edge_radius > 0) m.edge = edge_error(pts, ref, args.edge_radius, args.edge_angle, threads);
  return m;
}

int cmd_eval(const Common& c, const std::string& a, const std::string& b, int samples, unsigned seed,
             const PointsMetricsArgs& pm_args) {
  const auto t0 = std::chrono::steady_clock::now();
  StationConfig cfg = load_common(c);
  EvalInput ia, ib;
  read_eval_input(a, ia);
  read_eval_input(b, ib);
  // Inputs of very different sizes are most often in different units (a mesh in
  // millimetres against a scan in metres): the distances then mean nothing.
  const double da = bounding_box(ia.textured.mesh.vertices).diagonal();
  const double db = bounding_box(ib.textured.mesh.vertices).diagonal();
  if (da > 0 && db > 0 && std::max(da / db, db / da) > 10)
    std::fprintf(stderr,
                 "warning: %s is %.0fx the size of %s (bounding-box diagonals %.4g and %.4g): "
                 "different units?\n",
                 (da > db ? a : b).c_str(), std::max(da / db, db / da), (da > db ? b : a).c_str(),
                 std::max(da, db), std::min(da, db));
  std::optional<PointsMetrics> pm;
  if (pm_args.enabled) pm = points_metrics(ia, ib, pm_args, cfg.threads);
  const Shape sa = ia.shape(), sb = ib.shape();
  EvalParams params;
  params.a_surface_color = ia.surface_color();
  params.b_surface_color = ib.surface_color();
  params.mesh_samples = samples;
  params.seed = seed;
  params.threads = cfg.threads;
  EvalResult r = evaluate(sa, sb, params);
  if (c.json) {
    JsonObject ab, ba;
    stats_json(r.a_to_b, ab);
    stats_json(r.b_to_a, ba);
    JsonObject j;
    j.add("command", "eval").add("a", a).add("b", b).add("chamfer", r.chamfer)
        .add("hausdorff", r.hausdorff).add("p95", r.p95).add("a_to_b", ab).add("b_to_a", ba);
    if (r.normal_consistency) j.add("normal_consistency", *r.normal_consistency); else j.add_null("normal_consistency");
    if (r.color_error) j.add("color_error", *r.color_error); else j.add_null("color_error");
    if (pm) {
      JsonObject p;
      p.add("points", pm->points).add("accuracy", pm->accuracy).add("uniformity", pm->surface_uniformity)
          .add("uniformity_3d", pm->uniformity).add("reference_area", pm->area)
          .add("sharp_edges", pm->sharp_edges).add("edge_angle_deg", pm_args.edge_angle);
      if (pm->edge) {
        p.add("edge_radius", pm_args.edge_radius).add("edge_error", pm->edge->mean)
            .add("edge_points", pm->edge->count);
      } else {
        p.add_null("edge_radius").add_null("edge_error").add_null("edge_points");
      }
      j.add("points_metrics", p);
    }
    j.add("timings_s", JsonObject().add("eval", seconds_since(t0)));
    print_summary(j);
  } else {
    std::printf("A: %s\nB: %s\n", a.c_str(), b.c_str());
    std::printf("%-12s %12s %12s %12s %12s %10s\n", "direction", "mean", "rms", "p95", "max", "count");
    auto row = [](const char* n, const DirectedStats& s) {
      std::printf("%-12s %12.6g %12.6g %12.6g %12.6g %10zu\n", n, s.mean, s.rms, s.p95, s.max, s.count);
    };
    row("A->B", r.a_to_b);
    row("B->A", r.b_to_a);
    std::printf("chamfer (mean symmetric) %.6g\nhausdorff %.6g\np95 %.6g\n", r.chamfer, r.hausdorff, r.p95);
    if (r.normal_consistency) std::printf("normal consistency %.4f\n", *r.normal_consistency);
    else std::printf("normal consistency: n/a (normals missing)\n");
    if (r.color_error) std::printf("colour error e_col %.6g\n", *r.color_error);
    else std::printf("colour error: n/a (colours missing on one side)\n");
    if (pm) {
      std::printf("points metrics (%zu points of A against mesh B):\n", pm->points);
      std::printf("  accuracy (mean distance to B) %.6g\n", pm->accuracy);
      std::printf("  uniformity (on B's surface) %.4f, in 3-D %.4f (B's area %.6g)\n",
                  pm->surface_uniformity, pm->uniformity, pm->area);
      if (pm->edge)
        std::printf("  edge error (within %.6g of %zu sharp edges > %g deg) %.6g over %zu points\n",
                    pm_args.edge_radius, pm->sharp_edges, pm_args.edge_angle, pm->edge->mean, pm->edge->count);
      else
        std::printf("  edge error: n/a (give --edge-radius, e.g. 2h; %zu sharp edges > %g deg)\n",
                    pm->sharp_edges, pm_args.edge_angle);
    }
  }
  return 0;
}

// ---- import --------------------------------------------------------------------

struct ImportArgs {
  std::vector<std::string> files;
  std::string out;
  std::string stanford_conf;
  double start = 0;
  double step = 0;
  bool has_step = false;
  int every = 1;
  std::string units = "m";
};

int cmd_import(const Common& c, const ImportArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  load_common(c);
  if (a.every < 1) throw InvalidInput("--every must be at least 1");
  std::map<std::string, Eigen::Matrix4d> poses;
  if (!a.stanford_conf.empty())
    for (const StanfordScan& scan : read_stanford_conf(a.stanford_conf)) poses[scan.file] = scan.pose;
  // Read everything first: a bad file aborts before anything is written.
  std::vector<Cloud> clouds;
  for (const std::string& f : a.files) {
    Cloud cl = read_cloud(f);
    if (a.every > 1) {
      Cloud s;
      for (std::size_t i = 0; i < cl.size(); i += a.every) {
        s.points.push_back(cl.points[i]);
        if (cl.has_normals()) s.normals.push_back(cl.normals[i]);
        if (cl.has_colors()) s.colors.push_back(cl.colors[i]);
      }
      cl = std::move(s);
    }
    clouds.push_back(std::move(cl));
  }
  SessionManifest m;
  m.scanner = "import";
  m.units = a.units;
  if (a.has_step) {
    m.planned_views = int(a.files.size());
    m.start_deg = a.start;
    m.step_deg = a.step;
  }
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
  if (c.json)
    print_summary(JsonObject().add("command", "import").add("session", a.out).add("views", a.files.size())
                      .add("points", total).add("timings_s", JsonObject().add("import", seconds_since(t0))));
  else
    std::printf("import: %zu views, %zu points -> %s\n", a.files.size(), total, a.out.c_str());
  return 0;
}

// ---- register / calibrate -------------------------------------------------------

/// Registers a session with a progress bar; shared by `register` and `calibrate`.
RegistrationResult register_with_progress(const Session& session, const RegistrationParams& params, bool quiet) {
  std::unique_ptr<Progress> bar;
  std::string stage;
  RegistrationResult r = register_session(session, params, [&](const RegistrationProgress& p) {
    if (p.stage != stage) {
      if (bar) bar->finish();
      stage = p.stage;
      bar = std::make_unique<Progress>("register: " + stage, p.total, quiet);
    }
    bar->update(p.done);
  });
  if (bar) bar->finish();
  for (int v : r.failed_views)
    if (!quiet) std::fprintf(stderr, "warning: %s\n", r.views[v].message.c_str());
  for (const std::string& w : r.warnings)
    if (!quiet) std::fprintf(stderr, "warning: %s\n", w.c_str());
  if (r.degenerate && !quiet) std::fprintf(stderr, "note: %s\n", r.degeneracy_message.c_str());
  return r;
}

JsonObject registration_json(const RegistrationResult& r) {
  JsonObject j;
  j.add("views", r.views.size()).add("failed_views", r.failed_views.size()).add("degenerate", r.degenerate);
  j.add("warnings", r.warnings);
  j.add("pair_rmse_m", r.mean_pair_rmse);
  j.add("rigid_turntable", JsonObject()
                               .add("used", r.rigid_turntable)
                               .add("deviation_deg", r.rigid_deviation_deg)
                               .add("deviation_m", r.rigid_deviation));
  if (r.fuse_distance > 0)
    j.add("fuse", JsonObject()
                      .add("distance_m", r.fuse_distance)
                      .add("input_points", r.fuse.input)
                      .add("fused_points", r.fuse.fused)
                      .add("output_points", r.fuse.output));
  if (r.views_with_reference > 0) {
    JsonObject ref;
    ref.add("views", r.views_with_reference)
        .add("max_rotation_deg", r.max_rotation_error_deg)
        .add("median_rotation_deg", r.median_rotation_error_deg)
        .add("max_translation_m", r.max_translation_error)
        .add("median_translation_m", r.median_translation_error)
        .add("max_object_translation_m", r.max_object_translation_error)
        .add("median_object_translation_m", r.median_object_translation_error);
    // The same pairs' residual under the reference poses: which poses fit the scans better.
    if (r.mean_reference_pair_rmse) ref.add("pair_rmse_m", *r.mean_reference_pair_rmse);
    j.add("reference", ref);
  }
  JsonObject per_view;
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    const ViewDiagnostics& v = r.views[i];
    JsonObject o;
    o.add("registered", v.registered).add("initial", to_string(v.initial)).add("points", v.points)
        .add("angle_rejected", v.angle_rejected);
    if (v.rotation_error_deg) o.add("rotation_error_deg", *v.rotation_error_deg);
    if (v.translation_error) o.add("translation_error_m", *v.translation_error);
    if (v.object_translation_error) o.add("object_translation_error_m", *v.object_translation_error);
    if (!v.message.empty()) o.add("message", v.message);
    per_view.add(std::to_string(i), o);
  }
  j.add("per_view", per_view);
  // Pairs of the last round (earlier rounds refine the same pairs).
  JsonObject per_pair;
  const int last_round = r.pairs.empty() ? 0 : r.pairs.back().round;
  for (const PairDiagnostics& p : r.pairs) {
    if (p.round != last_round) continue;
    JsonObject o;
    o.add("converged", p.converged).add("fitness", p.fitness).add("inlier_rmse_m", p.inlier_rmse)
        .add("correspondences", p.correspondences).add("iterations", p.iterations)
        .add("loop_closure", p.loop_closure).add("degenerate", p.degenerate);
    for (const PairResidual& pr : r.pair_residuals)
      if (pr.from == p.from && pr.to == p.to) {
        o.add("residual_rmse_m", pr.rmse);
        if (pr.reference_rmse) o.add("reference_residual_rmse_m", *pr.reference_rmse);
      }
    if (!p.message.empty()) o.add("message", p.message);
    per_pair.add(std::to_string(p.from) + "-" + std::to_string(p.to), o);
  }
  j.add("per_pair", per_pair);
  j.add("timings_s", JsonObject()
                         .add("prepare", r.seconds_prepare)
                         .add("initial", r.seconds_initial)
                         .add("refine", r.seconds_refine)
                         .add("merge", r.seconds_merge)
                         .add("total", r.seconds_total));
  return j;
}

void print_registration(const RegistrationResult& r) {
  std::printf("%-5s %-10s %-16s %9s %12s %14s\n", "view", "status", "initial pose", "points",
              "rot err deg", "trans err mm");
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    const ViewDiagnostics& v = r.views[i];
    char rot[32] = "-", tr[32] = "-";
    if (v.rotation_error_deg) std::snprintf(rot, sizeof rot, "%.3f", *v.rotation_error_deg);
    if (v.translation_error) std::snprintf(tr, sizeof tr, "%.3f", *v.translation_error * 1000);
    std::printf("%-5zu %-10s %-16s %9zu %12s %14s\n", i,
                v.registered ? (v.angle_rejected ? "ok*" : "ok") : "FAILED",
                to_string(v.initial), v.points, rot, tr);
  }
  if (r.views_with_reference > 0)
    std::printf("against reference poses (%d views, relative to view 0): rotation max %.3f deg, "
                "median %.3f deg; translation max %.3f mm, median %.3f mm\n",
                r.views_with_reference, r.max_rotation_error_deg, r.median_rotation_error_deg,
                r.max_translation_error * 1000, r.median_translation_error * 1000);
  if (r.views_with_reference > 0)
    std::printf("  translation at the object (each view's centroid): max %.3f mm, median %.3f mm\n",
                r.max_object_translation_error * 1000, r.median_object_translation_error * 1000);
  if (r.rigid_turntable)
    std::printf("rigid turntable: the views lie on one axis (at most %.3f deg / %.3f mm from the free poses)\n",
                r.rigid_deviation_deg, r.rigid_deviation * 1000);
  if (!r.pair_residuals.empty()) {
    std::printf("pair residual (RMS point-to-plane over %zu refined pairs): %.4f mm",
                r.pair_residuals.size(), r.mean_pair_rmse * 1000);
    if (r.mean_reference_pair_rmse)
      std::printf("; under the reference poses %.4f mm", *r.mean_reference_pair_rmse * 1000);
    std::printf("\n");
  }
  for (const ViewDiagnostics& v : r.views)
    if (v.angle_rejected) {
      std::printf("ok*: the commanded turntable angle was wrong; the pose comes from global registration\n");
      break;
    }
}

struct RegisterArgs {
  std::string session, out, poses_out;
};

int cmd_register(const Common& c, const RegisterArgs& a) {
  check_output_name(a.out, "a cloud", {".ply"});
  check_not_a_recording(a.poses_out);
  StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  const std::string& session_dir = a.session;
  const std::string& out = a.out;
  const std::string& poses_out = a.poses_out;
  const Session session = Session::open(session_dir);
  const RegistrationResult r = register_with_progress(session, registration_params(cfg.pipeline), c.json);
  if (r.merged.empty()) throw InvalidInput(session_dir + ": no view could be registered");
  write_ply(out, r.merged);
  if (!poses_out.empty()) write_poses_yaml(poses_out, r, session.manifest());
  if (c.json) {
    JsonObject j = registration_json(r);
    j.add("command", "register").add("session", session_dir).add("output", out)
        .add("points", r.merged.size());
    if (!poses_out.empty()) j.add("poses", poses_out);
    print_summary(j);
  } else {
    print_registration(r);
    if (r.fuse_distance > 0)
      std::printf("fused %zu of %zu points into earlier views' points (within %.3f mm)\n", r.fuse.fused,
                  r.fuse.input, r.fuse_distance * 1000);
    std::printf("register: %zu of %zu views, %zu points -> %s\n", r.views.size() - r.failed_views.size(),
                r.views.size(), r.merged.size(), out.c_str());
  }
  return r.failed_views.empty() ? 0 : 3;
}

int cmd_calibrate_turntable(const Common& c, const std::string& session_dir, const std::string& out) {
  check_not_a_recording(out);
  StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  const Session session = Session::open(session_dir);
  const SessionManifest& m = session.manifest();
  // The axis is fitted to free poses: on poses held on one rigid turntable the
  // tilt and translation residuals would be zero by construction, and they are
  // what tells a wobbling table or a shifting object.
  RegistrationParams rp = registration_params(cfg.pipeline);
  rp.rigid_turntable = RigidTurntable::kOff;
  const RegistrationResult r = register_with_progress(session, rp, c.json);
  std::vector<Eigen::Matrix4d> poses;
  std::vector<double> angles;
  for (std::size_t i = 0; i < m.views.size(); ++i) {
    if (!m.views[i].angle_deg || !r.views[i].registered) continue;
    poses.push_back(r.poses[i]);
    angles.push_back(*m.views[i].angle_deg);
  }
  if (poses.size() < 2)
    throw InvalidInput(session_dir + ": fewer than two registered views with turntable angles");
  AxisFitParams fp;
  if (m.axis) fp.point_near = m.axis->point;
  const AxisFitResult fit = calibrate_axis(poses, angles, fp);
  if (!fit.ok) throw InvalidInput(session_dir + ": turntable axis not determined: " + fit.message);
  // A profile fragment: copy its `capture.axis` into a bench profile.
  char buf[512];
  std::snprintf(buf, sizeof buf,
                "# Turntable axis calibrated from %s (scanner frame, metres)\n"
                "# rms residuals: angle %.4f deg, tilt %.4f deg, translation %.4f mm\n"
                "capture:\n  axis:\n    point: [%.9g, %.9g, %.9g]\n    direction: [%.9g, %.9g, %.9g]\n",
                session_dir.c_str(), fit.rms_angle_deg, fit.rms_tilt_deg, fit.rms_translation * 1000,
                fit.axis.point.x(), fit.axis.point.y(), fit.axis.point.z(), fit.axis.direction.x(),
                fit.axis.direction.y(), fit.axis.direction.z());
  if (!out.empty()) write_file_atomic(out, std::string(buf));
  if (c.json) {
    print_summary(JsonObject()
                      .add("command", "calibrate turntable")
                      .add("session", session_dir)
                      .add("point", std::vector<double>{fit.axis.point.x(), fit.axis.point.y(), fit.axis.point.z()})
                      .add("direction", std::vector<double>{fit.axis.direction.x(), fit.axis.direction.y(), fit.axis.direction.z()})
                      .add("rms_angle_deg", fit.rms_angle_deg)
                      .add("rms_tilt_deg", fit.rms_tilt_deg)
                      .add("rms_translation_m", fit.rms_translation)
                      .add("views", poses.size()));
  } else {
    std::printf("%s", buf);
    std::printf("%-5s %12s %10s %14s\n", "view", "angle deg", "tilt deg", "trans mm");
    for (std::size_t i = 0; i < fit.residuals.size(); ++i)
      std::printf("%-5zu %12.4f %10.4f %14.4f\n", i, fit.residuals[i].angle_deg, fit.residuals[i].tilt_deg,
                  fit.residuals[i].translation * 1000);
    if (!out.empty()) std::printf("written: %s\n", out.c_str());
  }
  return 0;
}

std::string fmt_double(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4f", v);
  return buf;
}

int cmd_calibrate_camera(const Common& c, const std::vector<std::string>& images, const std::string& board,
                         double square, const std::string& out) {
  check_not_a_recording(out);
  ChessboardSpec spec;
  spec.square = square;
  if (std::sscanf(board.c_str(), "%dx%d", &spec.inner_cols, &spec.inner_rows) != 2)
    throw InvalidInput("--board " + board + ": expected COLSxROWS, e.g. 9x6");
  std::vector<fs::path> files(images.begin(), images.end());
  if (!c.json) std::fprintf(stderr, "calibrate camera: finding the chessboard in %zu images...\n", files.size());
  const CameraCalibration cal = calibrate_camera(files, spec);
  const std::string fragment = camera_profile_fragment(cal, std::to_string(files.size()) + " images");
  if (!out.empty()) write_file_atomic(out, fragment);
  const Intrinsics& k = cal.intrinsics;
  if (c.json) {
    std::vector<double> per;
    for (const CameraImageResult& r : cal.images) per.push_back(r.used ? r.rms_px : -1);
    print_summary(JsonObject()
                      .add("command", "calibrate camera")
                      .add("images", cal.images.size())
                      .add("used_images", cal.used_images)
                      .add("rms_px", cal.rms_px)
                      .add("per_image_rms_px", per)
                      .add("intrinsics", std::vector<double>{double(k.width), double(k.height), k.fx, k.fy, k.cx, k.cy})
                      .add("distortion", std::vector<double>(k.distortion.begin(), k.distortion.end())));
  } else {
    std::printf("%s", fragment.c_str());
    std::printf("%-40s %8s %s\n", "image", "rms px", "");
    for (const CameraImageResult& r : cal.images)
      std::printf("%-40s %8s %s\n", r.file.c_str(), r.used ? fmt_double(r.rms_px).c_str() : "-",
                  r.used ? (r.rms_px > 3 * cal.rms_px ? "<- suspicious" : "") : r.message.c_str());
    if (!out.empty()) std::printf("written: %s\n", out.c_str());
  }
  return 0;
}

// ---- fit (SDM) ---------------------------------------------------------------------

struct FitArgs {
  std::string in, out, templ = "icosphere:5", landmarks;
  bool no_colour = false;
};

int cmd_fit(const Common& c, const FitArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  check_output_name(a.out, "a mesh", {".ply", ".obj"});
  StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  const Cloud target = read_cloud(a.in);
  std::vector<Landmark> landmarks;
  if (!a.landmarks.empty()) landmarks = read_landmarks(a.landmarks);
  SdmParams sp;
  sp.threads = cfg.threads;
  Progress bar("fit: SDM", 100, c.json);
  const SdmProgress progress = [&](const std::string& phase, double f) {
    bar.update(int(std::lround(100 * f)), phase);
  };
  SdmResult fit;
  if (a.templ.rfind("icosphere:", 0) == 0) {
    int level = -1;
    try {
      level = std::stoi(a.templ.substr(10));
    } catch (const std::exception&) {
    }
    if (level < 0 || level > 7) throw InvalidInput("--template " + a.templ + ": expected icosphere:L with L in 0..7");
    fit = fit_sdm_icosphere(level, target, sp, landmarks, progress);
  } else {
    fit = fit_sdm(read_mesh(a.templ), target, sp, landmarks, progress);
  }
  bar.finish();
  Mesh mesh = fit.mesh;
  const bool colour = target.has_colors() && !a.no_colour;
  if (colour) {
    ColourParams cp;
    cp.threads = cfg.threads;
    colour_mesh(mesh, fit_colour(target, cp), cfg.threads);
  }
  write_mesh(a.out, mesh);
  const SdmDiagnostics& d = fit.diagnostics;
  if (c.json) {
    print_summary(JsonObject()
                      .add("command", "fit")
                      .add("input", a.in)
                      .add("output", a.out)
                      .add("template", a.templ)
                      .add("vertices", mesh.vertices.size())
                      .add("faces", mesh.faces.size())
                      .add("control_points", d.control_points)
                      .add("mean_distance", d.mean_distance)
                      .add("mean_distance_rel", d.diagonal > 0 ? d.mean_distance / d.diagonal : 0.0)
                      .add("flipped_faces", d.flipped_faces)
                      .add("self_intersections", d.self_intersections)
                      .add("landmarks", landmarks.size())
                      .add("colours", colour)
                      .add("timings_s", JsonObject()
                                            .add("som", d.seconds_som)
                                            .add("energy", d.seconds_energy)
                                            .add("total", seconds_since(t0))));
  } else {
    std::printf("fit: %zu vertices onto %d control points: mean distance %.4g (%.3f %% of the diagonal), "
                "%d flipped faces, %d self-intersections, %.2fs -> %s\n",
                mesh.vertices.size(), d.control_points, d.mean_distance,
                d.diagonal > 0 ? 100 * d.mean_distance / d.diagonal : 0.0, d.flipped_faces, d.self_intersections,
                d.seconds_total, a.out.c_str());
  }
  return 0;
}

// ---- parameterise (SDM onto a simple surface) ---------------------------------------

struct ParameteriseArgs {
  std::string in, out, onto = "sphere", mapped;
  int control_points = 0;
};

/// Per-corner UVs from per-vertex ones; on the sphere and the cylinder u wraps at 1,
/// so a face that straddles the seam gets its small u values raised by 1 (texture
/// repeat then samples the right side) instead of spanning the whole image.
std::vector<Vec2f> corner_uvs(const Mesh& mesh, const std::vector<Vec2f>& uv, bool wrap_u) {
  std::vector<Vec2f> out;
  out.reserve(3 * mesh.faces.size());
  for (const Face& f : mesh.faces) {
    Vec2f t[3] = {uv[f[0]], uv[f[1]], uv[f[2]]};
    if (wrap_u) {
      const float hi = std::max({t[0].x(), t[1].x(), t[2].x()});
      for (Vec2f& c : t)
        if (hi - c.x() > 0.5f) c.x() += 1.f;
    }
    out.insert(out.end(), t, t + 3);
  }
  return out;
}

int cmd_parameterise(const Common& c, const ParameteriseArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  check_output_name(a.out, "a mesh with UVs", {".obj"});
  check_not_a_recording(a.mapped);
  const SimpleSurface surface = a.onto == "plane" ? SimpleSurface::kPlane
                                : a.onto == "cylinder" ? SimpleSurface::kCylinder
                                                       : SimpleSurface::kSphere;
  const Mesh mesh = read_mesh(a.in);
  if (mesh.faces.empty()) throw InvalidInput(a.in + ": no faces (parameterise needs a mesh)");
  SdmParams sp;
  sp.threads = cfg.threads;
  Progress bar("parameterise: SDM", 100, c.json);
  const ParameterisationResult r = sdm_parameterise(
      mesh, surface, sp, a.control_points,
      [&](const std::string& phase, double f) { bar.update(int(std::lround(100 * f)), phase); });
  bar.finish();
  Mesh textured = mesh;
  textured.normals.clear();
  const auto uv = corner_uvs(mesh, r.uv, surface != SimpleSurface::kPlane);
  // Each write is atomic: a failure leaves no half-written file.
  if (!a.mapped.empty()) write_mesh(a.mapped, r.mesh);
  write_obj(a.out, textured, uv);
  const SdmDiagnostics& d = r.diagnostics;
  if (c.json) {
    print_summary(JsonObject()
                      .add("command", "parameterise")
                      .add("input", a.in)
                      .add("output", a.out)
                      .add("onto", a.onto)
                      .add("vertices", mesh.vertices.size())
                      .add("faces", mesh.faces.size())
                      .add("control_points", d.control_points)
                      .add("flipped_faces", d.flipped_faces)
                      .add("self_intersections", d.self_intersections)
                      .add("timings_s", JsonObject().add("total", seconds_since(t0))));
  } else {
    std::printf("parameterise: %zu vertices onto the %s (%d control points), %d flipped faces, %.2fs -> %s\n",
                mesh.vertices.size(), a.onto.c_str(), d.control_points, d.flipped_faces, seconds_since(t0),
                a.out.c_str());
  }
  return 0;
}

// ---- consolidate -----------------------------------------------------------------

struct ConsolidateArgs {
  std::string in, out;
};

int cmd_consolidate(const Common& c, const ConsolidateArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  check_output_name(a.out, "a cloud", {".ply"});
  StationConfig cfg = load_common(c);
  const auto& pc = cfg.pipeline.consolidate;
  const Cloud input = read_cloud(a.in);
  const double t_read = seconds_since(t0);
  WlopParams p = wlop_params(cfg.pipeline, cfg.threads);
  if (!c.json)
    std::fprintf(stderr, "consolidate: %s, %zu points, %s, %d iterations...\n", a.in.c_str(),
                 input.size(), pc.method.c_str(), pc.iterations);
  Progress bar(std::string("consolidate: ") + wlop_label(pc.method) + " iterations", pc.iterations, c.json);
  p.progress = [&](int done, int) { bar.update(done); };
  const WlopResult r = consolidate(input, p);
  bar.finish();
  write_ply(a.out, r.cloud);
  if (c.json) {
    print_summary(JsonObject()
                      .add("command", "consolidate")
                      .add("input", a.in)
                      .add("output", a.out)
                      .add("method", pc.method)
                      .add("input_points", r.input_points)
                      .add("output_points", r.cloud.size())
                      .add("clamped", r.clamped)
                      .add("iterations", r.iterations)
                      .add("radius", r.radius)
                      .add("isolated_points", r.isolated_points)
                      .add("timings_s", JsonObject()
                                            .add("read", t_read)
                                            .add("setup", r.seconds_setup)
                                            .add("iterations", r.seconds_iterations)
                                            .add("attributes", r.seconds_attributes)
                                            .add("total", seconds_since(t0))));
  } else {
    std::printf("consolidate: %zu -> %zu points (%s, %d iterations, h = %.6g) in %.2fs -> %s\n",
                r.input_points, r.cloud.size(), pc.method.c_str(), r.iterations, r.radius,
                r.seconds, a.out.c_str());
    if (r.clamped)
      std::printf("note: asked for %zu points but the input has %zu distinct ones; all were projected\n",
                  r.requested_points, r.output_points);
  }
  return 0;
}

// ---- reconstruct ----------------------------------------------------------------

struct ReconstructArgs {
  std::string in, out;
  /// The turntable axis in the cloud's frame, "x,y,z" (run.yaml's register figures
  /// up_x, up_y, up_z): enables the table plane. Empty: none.
  std::string up;
};

std::optional<Vec3d> parse_up(const std::string& text) {
  if (text.empty()) return std::nullopt;
  Vec3d v;
  char comma1 = 0, comma2 = 0, rest = 0;
  if (std::sscanf(text.c_str(), "%lf %c %lf %c %lf %c", &v.x(), &comma1, &v.y(), &comma2, &v.z(), &rest) != 5 ||
      comma1 != ',' || comma2 != ',' || !v.allFinite() || !(v.norm() > 0))
    throw InvalidInput("--up " + text + ": expected a non-zero direction x,y,z");
  return v;
}

int cmd_reconstruct(const Common& c, const ReconstructArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  check_output_name(a.out, "a mesh", {".ply", ".obj"});
  StationConfig cfg = load_common(c);
  const auto& rc = cfg.pipeline.reconstruct;
  SurfaceParams sp = surface_params(cfg.pipeline, cfg.threads);
  if (rc.table_plane) sp.table_up = parse_up(a.up);
  sp.resolution_name = "--resolution " + std::to_string(rc.resolution);
  sp.note = [&](const std::string& line) {
    if (!c.json) std::fprintf(stderr, "%s\n", surface_note(a.in, line, "reconstruct: ", "note: ").c_str());
  };
  Cloud input = read_cloud(a.in);
  const std::size_t points = input.size();
  const double t_read = seconds_since(t0);
  const SurfaceResult r = reconstruct_surface(std::move(input), sp);
  write_mesh(a.out, r.mesh);
  const MpuDiagnostics& d = r.mpu;
  if (c.json) {
    const DmcStats& ds = r.dmc;
    print_summary(JsonObject()
                      .add("command", "reconstruct")
                      .add("input", a.in)
                      .add("output", a.out)
                      .add("points", points)
                      .add("normals_estimated", r.normals_estimated)
                      .add("vertices", r.mesh.vertices.size())
                      .add("faces", r.mesh.faces.size())
                      .add("leaves", d.leaves)
                      .add("leaves_by_type", JsonObject()
                                                 .add("bivariate", d.leaves_by_type[0])
                                                 .add("quadric", d.leaves_by_type[1])
                                                 .add("edge", d.leaves_by_type[2])
                                                 .add("corner", d.leaves_by_type[3]))
                      .add("unconverged_leaves", d.unconverged_leaves)
                      .add("removed_pieces", r.pieces.removed_components)
                      .add("epsilon0", r.epsilon0)
                      .add("cell_size", r.extraction.cell_size)
                      .add("colours", r.coloured)
                      .add("extractor", rc.extractor)
                      .add("winding_close", r.winding_points > 0)
                      .add("table_plane", bool(r.table_height))
                      .add("dmc", JsonObject()
                                      .add("probed", ds.probed)
                                      .add("searched", ds.searched)
                                      .add("moved_barycentre", ds.moved_barycentre)
                                      .add("moved_corner", ds.moved_corner)
                                      .add("moved_edge", ds.moved_edge)
                                      .add("smooth_cells", ds.smooth_cells)
                                      .add("seconds_traversal", ds.seconds_traversal)
                                      .add("seconds_barycentre", ds.seconds_barycentre)
                                      .add("seconds_features", ds.seconds_features)
                                      .add("seconds_mesh", ds.seconds_mesh))
                      .add("colour_method", r.coloured ? rc.colour_method : std::string("none"))
                      .add("e_col", r.colour ? r.colour->e_col : -1.0)
                      .add("colour_edges_split", r.colour_edges_split)
                      .add("timings_s", JsonObject()
                                            .add("read", t_read)
                                            .add("fit", r.seconds.normals + r.seconds.fit)
                                            .add("extract", r.seconds.closing + r.seconds.extract)
                                            .add("colour", r.seconds.colour)
                                            .add("total", seconds_since(t0))));
  } else {
    std::printf("MPU: %zu leaves (bivariate %zu, quadric %zu, edge %zu, corner %zu), fit %.2fs\n",
                d.leaves, d.leaves_by_type[0], d.leaves_by_type[1], d.leaves_by_type[2],
                d.leaves_by_type[3], r.seconds.fit);
    std::printf("reconstruct: %zu vertices, %zu faces (cell %.4g, extract %.2fs) -> %s\n",
                r.mesh.vertices.size(), r.mesh.faces.size(), r.extraction.cell_size, r.seconds.extract,
                a.out.c_str());
  }
  return 0;
}

}  // namespace

int run_cli(int argc, char** argv) {
  CLI::App app{"station: capture-to-mesh station for turntable 3D-scanning benches"};
  app.set_version_flag("--version", STATION_VERSION);
  app.require_subcommand(1);

  Common c_dev, c_scan, c_replay, c_eval, c_import;
  auto* devices = app.add_subcommand("devices", "List the devices the station can drive");
  add_common(devices, c_dev);

  ScanArgs scan_args;
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

  RunArgs run_args;
  Common c_run;
  auto* runc = app.add_subcommand("run", "The whole job: register, consolidate, reconstruct a coloured mesh, report");
  add_common(runc, c_run);
  runc->add_option("input", run_args.in, "session folder (or session.yaml) or a cloud file")->required();
  runc->add_option("-o,--out", run_args.out, "run folder: every stage's output, mesh.ply, report.html")->required();
  runc->add_flag("--resume", run_args.resume,
                 "continue a run in --out: finished stages whose inputs and parameters are unchanged are kept");
  runc->add_option("--set", run_args.set, "profile override section.key=value (repeatable), e.g. --set reconstruct.resolution=192");
  add_profile_options(runc, "run", c_run);
  runc->add_flag("--quiet", run_args.quiet, "no progress output");
  runc->add_flag("--no-report", run_args.no_report, "do not write report.html");

  std::string replay_src, replay_out = "out/replay";
  auto* replay = app.add_subcommand("replay", "Play a recorded session back through the simulated scanner");
  add_common(replay, c_replay);
  replay->add_option("session", replay_src, "recorded session folder")->required();
  replay->add_option("-o,--out", replay_out, "session folder to write")->capture_default_str();

  std::string eval_a, eval_b;
  int eval_samples = 200000;
  unsigned eval_seed = 1;
  auto* eval = app.add_subcommand("eval", "Distances and colour error between two clouds or meshes");
  add_common(eval, c_eval);
  eval->add_option("a", eval_a, "result (cloud or mesh: .ply .pcd .obj .off)")->required();
  eval->add_option("b", eval_b, "reference (cloud or mesh)")->required();
  eval->add_option("--samples", eval_samples, "points sampled on each mesh")->capture_default_str()->check(CLI::Range(1, 100000000));
  eval->add_option("--seed", eval_seed, "sampling seed")->capture_default_str();
  PointsMetricsArgs eval_pm;
  eval->add_flag("--points-metrics", eval_pm.enabled,
                 "also the consolidation metrics of A's points (a cloud's points, a mesh's vertices) "
                 "against mesh B: accuracy (mean distance to B), uniformity (Schloemer's normalised "
                 "mean nearest-neighbour distance, on B's surface and in 3-D) and, with --edge-radius, "
                 "edge error");
  eval->add_option("--edge-radius", eval_pm.edge_radius,
                   "edge error: mean distance to B of A's points within this distance of a sharp edge "
                   "of B (e.g. 2h of the consolidation; implies --points-metrics)")
      ->check(CLI::PositiveNumber);
  eval->add_option("--edge-angle", eval_pm.edge_angle,
                   "an edge of B is sharp when its faces' normals differ by more than this (degrees)")
      ->capture_default_str()->check(CLI::Range(0.0, 180.0));

  ImportArgs import_args;
  auto* import = app.add_subcommand("import", "Make a session from view files recorded elsewhere");
  add_common(import, c_import);
  import->add_option("files", import_args.files, "view files (.ply .pcd), in turntable order")->required();
  import->add_option("-o,--out", import_args.out, "session folder to create")->required();
  import->add_option("--stanford-conf", import_args.stanford_conf, "Stanford .conf with reference poses (bmesh lines)");
  import->add_option("--start", import_args.start, "turntable angle of the first view, degrees");
  auto* step_opt = import->add_option("--step", import_args.step, "turntable step between views, degrees (no angles without it)");
  import->add_option("--every", import_args.every, "keep every N-th point (downsample)")->capture_default_str();
  import->add_option("--units", import_args.units, "units of the files (recorded, not converted)")->check(CLI::IsMember({"m", "mm"}));

  RegisterArgs reg_args;
  Common c_reg;
  auto* reg = app.add_subcommand("register", "Align the views of a session and merge them into one cloud");
  add_common(reg, c_reg);
  reg->add_option("session", reg_args.session, "session folder")->required();
  reg->add_option("-o,--out", reg_args.out, "merged cloud (.ply)")->required();
  reg->add_option("--poses-out", reg_args.poses_out, "write the refined poses and diagnostics (YAML)");
  add_profile_options(reg, "register", c_reg);

  std::string cal_session, cal_out;
  Common c_cal;
  auto* cal = app.add_subcommand("calibrate", "Calibrate bench devices: the camera (chessboard images) or the turntable axis (a session)");
  auto* cal_tt = cal->add_subcommand("turntable", "Fit the turntable axis to a registered session");
  cal->require_subcommand(1);
  add_common(cal_tt, c_cal);
  cal_tt->add_option("session", cal_session, "session folder (views with turntable angles)")->required();
  cal_tt->add_option("-o,--out", cal_out, "write the axis as a profile fragment (capture.axis)");
  std::vector<std::string> cam_images;
  std::string cam_board = "9x6", cam_out;
  double cam_square = 0.025;
  Common c_cam;
  auto* cal_cam = cal->add_subcommand("camera", "Intrinsics and lens distortion from chessboard images");
  add_common(cal_cam, c_cam);
  cal_cam->add_option("images", cam_images, "PNG/JPEG images of a chessboard, 3 or more")->required();
  cal_cam->add_option("--board", cam_board, "inner corners COLSxROWS")->capture_default_str();
  cal_cam->add_option("--square", cam_square, "square side, metres")->capture_default_str()->check(CLI::PositiveNumber);
  cal_cam->add_option("-o,--out", cam_out, "write the result as a profile fragment (scanner.options)");

  ConsolidateArgs cons_args;
  Common c_cons;
  auto* cons = app.add_subcommand("consolidate", "Thin and even out a cloud by WLOP (or edge-preserving WLOP)");
  add_common(cons, c_cons);
  cons->add_option("input", cons_args.in, "input cloud (.ply .pcd .obj .off)")->required();
  cons->add_option("-o,--out", cons_args.out, "output cloud (.ply)")->required();
  add_profile_options(cons, "consolidate", c_cons);
  cons->get_option("--ratio")->excludes(cons->get_option("--points"));

  FitArgs fit_args;
  Common c_fit;
  auto* fitc = app.add_subcommand("fit", "Fit a template mesh to a cloud (Self-organizing Deformable Model)");
  add_common(fitc, c_fit);
  fitc->add_option("input", fit_args.in, "cloud (normals estimated when missing)")->required();
  fitc->add_option("-o,--out", fit_args.out, "fitted mesh (.ply or .obj); same vertex numbering as the template")->required();
  fitc->add_option("--template", fit_args.templ,
                   "icosphere:L (L = 0..7; 5 = 10,242 vertices) or a closed genus-0 mesh file")
      ->capture_default_str();
  fitc->add_option("--landmarks", fit_args.landmarks,
                   "pinned pairs, one \"vertex_index x y z\" per line ('#' comments)");
  fitc->add_flag("--no-colour", fit_args.no_colour, "do not colour the mesh from the input's colours");

  ParameteriseArgs par_args;
  Common c_par;
  auto* parc = app.add_subcommand("parameterise",
                                  "Map a mesh onto a plane, sphere or cylinder (SDM) and write it with UVs");
  add_common(parc, c_par);
  parc->add_option("input", par_args.in, "mesh: closed genus 0 for sphere and cylinder, a disc for plane")->required();
  parc->add_option("-o,--out", par_args.out, "the input mesh with texture coordinates (.obj)")->required();
  parc->add_option("--onto", par_args.onto, "simple surface: sphere (longitude, colatitude), cylinder "
                                            "(angle, profile length), plane (unit disc)")
      ->check(CLI::IsMember({"plane", "sphere", "cylinder"}))
      ->capture_default_str();
  parc->add_option("--mapped", par_args.mapped, "also write the mesh as mapped onto the surface (.ply or .obj)");
  parc->add_option("--control-points", par_args.control_points,
                   "control points sampled on the surface (0 = 4 x the mesh's vertices)")
      ->check(CLI::NonNegativeNumber)
      ->capture_default_str();

  ReconstructArgs rec_args;
  Common c_rec;
  auto* rec = app.add_subcommand("reconstruct", "Fit an MPU implicit surface with colour to a cloud and mesh it (Deformed Marching Cubes)");
  add_common(rec, c_rec);
  rec->add_option("input", rec_args.in, "cloud with normals (estimated when missing)")->required();
  rec->add_option("-o,--out", rec_args.out, "mesh (.ply or .obj)")->required();
  add_profile_options(rec, "reconstruct", c_rec);
  rec->add_option("--up", rec_args.up,
                  "the turntable axis in the cloud's frame, x,y,z (a run's register figures up_x, up_y, up_z): "
                  "with --hole close the underside closes flat at the table plane (profile "
                  "reconstruct.table_plane)");

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  import_args.has_step = step_opt->count() > 0;
  try {
    if (*devices) return cmd_devices(c_dev);
    if (*scan) return cmd_scan(c_scan, scan_args);
    if (*runc) return cmd_run(c_run, run_args);
    if (*replay) return cmd_replay(c_replay, replay_src, replay_out);
    if (*eval) {
      if (eval_pm.edge_radius > 0) eval_pm.enabled = true;
      // A's points are what the metrics measure: a complaint without a role names A.
      return naming_the_file(eval_a, eval_b, [&] { return cmd_eval(c_eval, eval_a, eval_b, eval_samples, eval_seed, eval_pm); },
                             {{"A:", eval_a}, {"B:", eval_b}});
    }
    if (*import) return cmd_import(c_import, import_args);
    if (*cons) return naming_the_file(cons_args.in, cons_args.out, [&] { return cmd_consolidate(c_cons, cons_args); });
    if (*rec) return naming_the_file(rec_args.in, rec_args.out, [&] { return cmd_reconstruct(c_rec, rec_args); });
    if (*fitc)
      return naming_the_file(fit_args.in, fit_args.out, [&] { return cmd_fit(c_fit, fit_args); },
                             {{"template:", fit_args.templ}, {"landmark ", fit_args.landmarks}});
    if (*parc) return naming_the_file(par_args.in, par_args.out, [&] { return cmd_parameterise(c_par, par_args); });
    if (*reg) return cmd_register(c_reg, reg_args);
    if (*cal_tt) return cmd_calibrate_turntable(c_cal, cal_session, cal_out);
    if (*cal_cam) return cmd_calibrate_camera(c_cam, cam_images, cam_board, cam_square, cam_out);
  } catch (const UsageError& e) {
    std::fprintf(stderr, "station: %s\n", e.what());
    return 2;
  } catch (const Error& e) {
    std::fprintf(stderr, "station: %s\n", e.what());
    return 1;
  } catch (const std::bad_alloc&) {
    std::fprintf(stderr, "station: out of memory\n");
    return 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "station: internal error: %s\n", e.what());
    return 1;
  }
  return 2;
}

}  // namespace station
