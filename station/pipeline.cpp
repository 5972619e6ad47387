#include "station/pipeline.h"

#include "reconstruct/blocks.h"
#include "station/blocks_run.h"

#include <tbb/global_control.h>
#include <yaml-cpp/yaml.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <memory>
#include <optional>
#include <sstream>

#include "registration/registration.h"
#include "capture/session.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/io.h"
#include "core/range_image.h"
#include "reconstruct/colour_function.h"
#include "reconstruct/sdm.h"
#include "reconstruct/surface.h"
#include "reconstruct/winding_close.h"
#include "reconstruct/wlop.h"
#include "station/params.h"
#include "station/progress.h"
#include "station/render.h"
#include "station/report.h"

namespace station {

namespace fs = std::filesystem;

std::string hash_hex(const std::string& bytes) {
  std::uint64_t h = 1469598103934665603ull;
  for (unsigned char c : bytes) {
    h ^= c;
    h *= 1099511628211ull;
  }
  char buf[17];
  std::snprintf(buf, sizeof buf, "%016llx", (unsigned long long)h);
  return buf;
}

std::string hash_file(const fs::path& path) { return hash_hex(read_file_bytes(path)); }

namespace {

using Clock = std::chrono::steady_clock;
constexpr int kStateVersion = 1;
constexpr const char* kStateFile = "run.yaml";

double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

/// Peak RSS of the process since the last reset (/proc/self/status VmHWM), MiB.
double peak_rss_mb() {
  std::ifstream in("/proc/self/status");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("VmHWM:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  return -1;
}
/// Resets the high-water mark to the current RSS (Linux >= 4.0; ignored if not allowed).
void reset_peak_rss() {
  std::ofstream out("/proc/self/clear_refs");
  if (out) out << "5";
}

// ---- run.yaml ---------------------------------------------------------------------

struct RunState {
  std::string input;
  std::vector<StageRecord> stages;
  const StageRecord* find(const std::string& name) const {
    for (const StageRecord& s : stages)
      if (s.name == name) return &s;
    return nullptr;
  }
};

std::string state_yaml(const RunState& st) {
  YAML::Emitter e;
  e.SetDoublePrecision(17);
  e << YAML::BeginMap << YAML::Key << "version" << YAML::Value << kStateVersion;
  e << YAML::Key << "input" << YAML::Value << st.input;
  e << YAML::Key << "stages" << YAML::Value << YAML::BeginSeq;
  for (const StageRecord& s : st.stages) {
    e << YAML::BeginMap;
    e << YAML::Key << "name" << YAML::Value << s.name;
    e << YAML::Key << "key" << YAML::Value << s.key;
    e << YAML::Key << "output" << YAML::Value << s.output;
    e << YAML::Key << "output_hash" << YAML::Value << s.output_hash;
    e << YAML::Key << "seconds" << YAML::Value << s.seconds;
    e << YAML::Key << "peak_rss_mb" << YAML::Value << s.peak_rss_mb;
    e << YAML::Key << "figures" << YAML::Value << YAML::BeginMap;
    for (const auto& [k, v] : s.figures) e << YAML::Key << k << YAML::Value << v;
    e << YAML::EndMap;
    if (!s.per_view.empty()) e << YAML::Key << "per_view" << YAML::Value << YAML::Flow << s.per_view;
    if (!s.view_prior.empty()) e << YAML::Key << "view_prior" << YAML::Value << YAML::Flow << s.view_prior;
    if (s.up) e << YAML::Key << "up" << YAML::Value << YAML::Flow << std::vector<double>{s.up->x(), s.up->y(), s.up->z()};
    if (!s.poses.empty()) {
      e << YAML::Key << "poses" << YAML::Value << YAML::BeginSeq;
      for (const auto& p : s.poses) e << YAML::Flow << p;
      e << YAML::EndSeq;
    }
    e << YAML::EndMap;
  }
  e << YAML::EndSeq << YAML::EndMap;
  return std::string(e.c_str()) + "\n";
}

RunState read_state(const fs::path& file) {
  RunState st;
  try {
    const YAML::Node root = YAML::LoadFile(file.string());
    if (!root.IsMap() || !root["version"] || root["version"].as<int>() != kStateVersion)
      throw FormatError(file.string() + ": not a run state of version " + std::to_string(kStateVersion));
    st.input = root["input"].as<std::string>("");
    for (const YAML::Node& n : root["stages"]) {
      StageRecord s;
      s.name = n["name"].as<std::string>();
      s.key = n["key"].as<std::string>();
      s.output = n["output"].as<std::string>();
      s.output_hash = n["output_hash"].as<std::string>();
      s.seconds = n["seconds"].as<double>(0);
      s.peak_rss_mb = n["peak_rss_mb"].as<double>(-1);
      if (n["figures"])
        for (const auto& kv : n["figures"]) s.figures[kv.first.as<std::string>()] = kv.second.as<double>();
      if (n["per_view"]) s.per_view = n["per_view"].as<std::vector<double>>();
      if (n["view_prior"]) s.view_prior = n["view_prior"].as<std::vector<std::string>>();
      if (n["poses"])
        for (const YAML::Node& p : n["poses"]) s.poses.push_back(p.as<std::vector<double>>());
      if (n["up"]) {
        const auto up = n["up"].as<std::vector<double>>();
        if (up.size() != 3) throw FormatError(file.string() + ": a stage's up is not 3 numbers");
        s.up = Vec3d(up[0], up[1], up[2]);
      } else if (s.figures.count("up_x") && s.figures.count("up_y") && s.figures.count("up_z")) {
        s.up = Vec3d(s.figures.at("up_x"), s.figures.at("up_y"), s.figures.at("up_z"));  // states written before `up`
      }
      st.stages.push_back(std::move(s));
    }
  } catch (const YAML::Exception& e) {
    throw FormatError(file.string() + ": unreadable run state (" + e.msg +
                      "); remove it to start the run afresh");
  }
  return st;
}

// ---- inputs -----------------------------------------------------------------------

bool is_session(const fs::path& p) {
  if (fs::is_directory(p)) return fs::exists(p / "session.yaml");
  return p.filename() == "session.yaml";
}

/// Key of the input: the manifest and every view file, or the cloud file.
std::string input_key(const fs::path& input, bool session) {
  if (!session) return hash_file(input);
  const fs::path dir = fs::is_directory(input) ? input : input.parent_path();
  const SessionManifest m = read_manifest(dir);
  std::string all = read_file_bytes(dir / "session.yaml");
  for (const ViewRecord& v : m.views) all += hash_file(dir / v.file);
  return hash_hex(all);
}

std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

/// Parameters of a stage as text: part of its key.
std::string register_key(const PipelineConfig& p) {
  std::ostringstream s;
  s << "register/neighbors=" << p.reg.neighbors << ";rounds=" << p.reg.rounds
    << ";loop=" << p.reg.loop_closure << ";voxel=" << fmt("%.17g", p.reg.voxel_rel)
    << ";objective=" << p.reg.objective << ";global=" << p.reg.global << ";check_angles=" << p.reg.check_angles
    << ";prior_check=" << p.reg.prior_check
    << ";fuse=" << p.reg.fuse << ";fuse_distance=" << fmt("%.17g", p.reg.fuse_distance)
    << ";rigid_turntable=" << p.reg.rigid_turntable
    << ";viewpoint=checked"  // since issue 32: imported views' normals face their estimated sensor
    << ";chain=retried;turn_gap=1";  // since 2026-12-07: the second chain; the register stage's turn_gap_deg
  return s.str();
}
std::string consolidate_key(const PipelineConfig& p) {
  const auto& c = p.consolidate;
  std::ostringstream s;
  s << "consolidate/method=" << c.method << ";points=" << (c.points_auto ? "auto:" + std::to_string(kAutoPointsMin) + "-" + std::to_string(kAutoPointsMax) : std::to_string(c.points)) << ";ratio=" << fmt("%.17g", c.ratio)
    << ";iterations=" << c.iterations << ";seed=" << c.seed << ";attraction=" << c.attraction << ";fit_radius=" << c.fit_radius << ";repulsion=" << c.repulsion
    << ";repulsion_weight=" << c.repulsion_weight
    << ";range_image=facing";  // since 2026-12-07: an organised PCD's estimated normals face its sensor
  if (c.radius > 0) s << ";radius=" << fmt("%.17g", c.radius);  // (absent from keys of earlier runs)
  if (c.blocks != 0) s << ";blocks=" << c.blocks;                  // (auto: absent, as before blocks)
  else if (p.reconstruct.max_memory_gb > 0) s << ";max_memory=" << fmt("%.17g", p.reconstruct.max_memory_gb);
  return s.str();
}
std::string surface_key(const PipelineConfig& p) {
  const auto& c = p.reconstruct;
  std::ostringstream s;
  s << "surface/" << c.surface << ";resolution=" << c.resolution << ";epsilon0=" << fmt("%.17g", c.epsilon0)
    << ";extractor=" << c.extractor << ";hole=" << c.hole << ";range_image=facing" << ";colour=" << c.colour
    << ";colour_method=" << c.colour_method << ";multi=" << c.colour_multi << ";noise=" << c.colour_noise_robust
    << ";colour_edges=" << c.colour_edges
    << ";min_component=" << fmt("%.17g", c.min_component) << ";table_plane=" << c.table_plane
    << ";winding_close=" << c.winding_close;
  // (absent from keys before issue 32's snap; not done in blocks)
  if (c.snap_to_scans && p.consolidate.enabled && !c.in_blocks())
    s << ";snap_to_scans=1;snap_significance=" << fmt("%.17g", c.snap_significance) << ";snap_fit=paraboloid_cv"
      << ";scan_rim=" << kScanRimFactor << ";piece_scans=" << kPieceMinScans;
  // Since issue 27 the colour function's eq. 4 counts residuals beyond each colour's
  // 8-bit quantisation: a run before it is redone.
  if (c.colour && c.colour_method == "mpu") s << ";colour_eq4=quantised";
  // Since issue 32: what decides the unseen parts and the kept rims.
  if (c.hole != "close")
    s << ";enclosed_above=" << kEnclosedAbove << ";keep_trust=" << kKeepTrustFactor << ";rim_trim=" << kRimTrimFactor
      << ";enclosed_surrounded=" << kEnclosedAboveSurrounded;
  if (c.resolution == 0) s << ";auto_cells=" << kAutoResolutionMin << "-" << kAutoResolutionMax;
  if (c.surface == "sdm") s << ";level=" << p.sdm.level;
  return s.str();
}

// ---- the report ---------------------------------------------------------------

Rgb palette(std::size_t i) {
  static const Rgb colours[] = {{228, 26, 28},  {55, 126, 184}, {77, 175, 74},   {152, 78, 163},
                                {255, 127, 0},  {166, 86, 40},  {247, 129, 191}, {102, 102, 102},
                                {23, 190, 207}, {188, 189, 34}, {31, 119, 180},  {140, 86, 75}};
  return colours[i % (sizeof colours / sizeof colours[0])];
}

Cloud thin(const Cloud& c, std::size_t max_points) {
  if (c.size() <= max_points) return c;
  Cloud out;
  const double step = double(c.size()) / max_points;
  for (std::size_t k = 0; k < max_points; ++k) {
    const std::size_t i = std::size_t(k * step);
    out.points.push_back(c.points[i]);
    if (c.has_normals()) out.normals.push_back(c.normals[i]);
    if (c.has_colours()) out.colours.push_back(c.colours[i]);
  }
  return out;
}

std::string seconds_text(double s) { return fmt(s < 10 ? "%.2f" : "%.1f", s); }

void write_report(const fs::path& out_dir, const fs::path& input, bool session, const RunResult& run,
                  const fs::path& report_path) {
  std::vector<ReportSection> sections;
  Vec3d up = Vec3d::UnitZ();
  for (const StageRecord& r : run.stages)
    if (r.name == "register" && r.up) up = *r.up;
  {
    ReportSection s;
    s.title = "Stages";
    s.text = "Input: " + input.string() + ". Run folder: " + out_dir.string() +
             ". Stages marked 'reused' were taken from an earlier run with the same inputs and parameters.";
    ReportTable t;
    t.header = {"stage", "output", "time (s)", "peak memory (MiB)", "reused", "figures"};
    double total = 0;
    for (const StageRecord& r : run.stages) {
      std::string figs;
      for (const auto& [k, v] : r.figures) figs += (figs.empty() ? "" : ", ") + k + " " + fmt("%.6g", v);
      t.rows.push_back({r.name, r.output, seconds_text(r.seconds),
                        r.peak_rss_mb >= 0 ? fmt("%.0f", r.peak_rss_mb) : "-", r.reused ? "yes" : "no", figs});
      total += r.seconds;
    }
    t.rows.push_back({"total", "", seconds_text(total), "", "", ""});
    s.tables.push_back(t);
    sections.push_back(s);
  }
  const StageRecord* reg = nullptr;
  for (const StageRecord& r : run.stages)
    if (r.name == "register") reg = &r;
  if (session && reg) {
    const fs::path dir = fs::is_directory(input) ? input : input.parent_path();
    const Session ses = Session::open(dir);
    ReportSection s;
    s.title = "Views and registration";
    s.text = "Every view placed by its registered pose, seen from above and from the front, one colour per view "
             "(coverage: gaps show what the scanner never saw). Below: each view's residual after registration "
             "(mean inlier RMS of its final-round pairs; red above 3x the median).";
    Cloud all;
    std::vector<Rgb> colours;
    const std::size_t per_view = std::max<std::size_t>(2000, 120000 / std::max<std::size_t>(1, ses.manifest().views.size()));
    for (std::size_t i = 0; i < ses.manifest().views.size() && i < reg->poses.size(); ++i) {
      Cloud v;
      try {
        v = thin(ses.load_view(i), per_view);
      } catch (const std::exception&) {
        continue;  // a failed view is reported by the register stage already
      }
      Eigen::Matrix4d T;
      for (int k = 0; k < 16; ++k) T(k / 4, k % 4) = reg->poses[i][k];
      transform_cloud(v, T);
      for (const Vec3f& p : v.points) {
        if (!p.allFinite()) continue;
        all.points.push_back(p);
        colours.push_back(palette(i));
      }
    }
    if (!all.empty()) {
      RenderOptions o;
      o.shade = false;
      o.point_size = 1;
      const Aabb box = bounding_box(all.points);
      // Seen from above only the footprint matters: drop the extent along up.
      const Vec3f c = box.center(), u = up.cast<float>();
      Aabb flat;
      for (const Vec3f& p : all.points) flat.extend(p - (p - c).dot(u) * u);
      s.figures.push_back({"views from above", encode_png(render_points(all, view_from_above(flat, 360, up), o, &colours))});
      s.figures.push_back({"views from the front", encode_png(render_points(all, view_from_side(0, box, 360, up), o, &colours))});
    }
    std::vector<std::string> labels;
    for (std::size_t i = 0; i < reg->per_view.size(); ++i) labels.push_back(std::to_string(i));
    std::vector<double> sorted = reg->per_view;
    std::sort(sorted.begin(), sorted.end());
    const double median = sorted.empty() ? 0 : sorted[sorted.size() / 2];
    s.svg = svg_bar_chart(reg->per_view, labels, "mm", 3 * median);
    sections.push_back(s);
  }
  for (const StageRecord& r : run.stages) {
    if (r.name != "consolidate") continue;
    const Cloud c = thin(read_cloud(out_dir / r.output), 150000);
    ReportSection s;
    s.title = "Consolidated cloud";
    s.text = std::to_string(c.size()) + " points shown.";
    RenderOptions o;
    o.point_size = 2;
    const Aabb box = bounding_box(c.points);
    s.figures.push_back({"front", encode_png(render_points(c, view_from_side(0, box, 360, up), o))});
    s.figures.push_back({"side", encode_png(render_points(c, view_from_side(1, box, 360, up), o))});
    sections.push_back(s);
  }
  if (!run.mesh.empty() && fs::exists(run.mesh)) {
    const Mesh m = read_mesh(run.mesh);
    const Aabb box = bounding_box(m.vertices);
    ReportSection s;
    s.title = "Mesh";
    s.text = std::to_string(m.vertices.size()) + " vertices, " + std::to_string(m.faces.size()) + " faces. " +
             run.mesh.filename().string() + ", from four sides" + (m.has_colours() ? ", with and without colour." : ".");
    const char* names[] = {"front", "left", "back", "right"};
    for (int q = 0; q < 4; ++q) {
      RenderOptions o;
      if (m.has_colours())
        s.figures.push_back({std::string(names[q]) + ", colour", encode_png(render_mesh(m, view_from_side(q, box, 300, up), o))});
      o.use_colours = false;
      s.figures.push_back({std::string(names[q]) + ", shape", encode_png(render_mesh(m, view_from_side(q, box, 300, up), o))});
    }
    sections.push_back(s);
    // Colour-boundary cells: vertices where a Type B (two-colour, split) cell of the
    // colour function dominates, written by the surface stage.
    const fs::path bfile = out_dir / "colour_boundary.bin";
    if (fs::exists(bfile)) {
      const std::string flags = read_file_bytes(bfile);
      if (flags.size() == m.vertices.size()) {
        Mesh marked = m;
        marked.colours.resize(marked.vertices.size());
        std::size_t nb = 0;
        for (std::size_t i = 0; i < flags.size(); ++i) {
          marked.colours[i] = flags[i] ? Rgb{220, 30, 30} : Rgb{210, 210, 210};
          nb += flags[i] != 0;
        }
        ReportSection b;
        b.title = "Colour boundaries";
        b.text = "Red: where the colour function fits a boundary (Type B cells: two colour clusters split by a "
                 "boundary function), " + std::to_string(nb) + " of " + std::to_string(flags.size()) +
                 " vertices. Elsewhere colour varies smoothly (Type A: one quadratic per channel).";
        for (int q = 0; q < 4; q += 2)
          b.figures.push_back({names[q], encode_png(render_mesh(marked, view_from_side(q, box, 300, up)))});
        sections.push_back(b);
      }
    }
  }
  write_file_atomic(report_path, report_html("Station run: " + input.filename().string(), sections));
}

// ---- the stages -------------------------------------------------------------------

class Runner {
 public:
  Runner(const StationConfig& cfg, const RunRequest& req) : cfg_(cfg), req_(req) {}

  RunResult run() {
    if (req_.input.empty() || !fs::exists(req_.input))
      throw IoError(req_.input.string() + ": no such session or cloud");
    session_ = is_session(req_.input);
    if (!session_ && fs::is_directory(req_.input))
      throw IoError(req_.input.string() + ": not a session folder (no session.yaml)");
    result_.session = session_;
    std::error_code ec;
    const fs::path state_file = req_.out_dir / kStateFile;
    check_outputs_are_not_inputs();
    // The run writes merged.ply, mesh.ply, report.html... into its folder: never into a
    // session (a scan's own merged.ply would be replaced) or over files it did not write.
    if (fs::is_directory(req_.out_dir, ec) && !fs::exists(state_file, ec)) {
      if (is_session(req_.out_dir))
        throw InvalidInput(req_.out_dir.string() + ": holds a scan session; write the run to another folder");
      if (fs::directory_iterator(req_.out_dir, ec) != fs::directory_iterator())
        throw InvalidInput(req_.out_dir.string() + ": not empty and not a run folder; choose another folder");
    }
    fs::create_directories(req_.out_dir, ec);
    if (ec || !fs::is_directory(req_.out_dir))
      throw IoError(req_.out_dir.string() + ": cannot create the run folder" + (ec ? ": " + ec.message() : ""));
    if (fs::exists(state_file)) {
      if (!req_.resume)
        throw InvalidInput(req_.out_dir.string() +
                           ": holds an earlier run; add --resume to continue it, or choose another folder");
      old_ = read_state(state_file);
    }
    state_.input = fs::absolute(req_.input).lexically_normal().string();
    auto threads = cfg_.threads > 0 ? std::make_unique<tbb::global_control>(
                                          tbb::global_control::max_allowed_parallelism, std::size_t(cfg_.threads))
                                    : nullptr;
    say("run: hashing the input " + req_.input.string());
    std::string key = input_key(req_.input, session_);
    fs::path cloud_file = req_.input;
    const int total = (session_ ? 1 : 0) + (cfg_.pipeline.consolidate.enabled ? 1 : 0) + 1;
    int index = 0;
    if (session_) {
      key = hash_hex(key + register_key(cfg_.pipeline));
      stage(++index, total, "register", req_.input, key, "merged.ply", [&](StageRecord& r) { do_register(r); });
      cloud_file = req_.out_dir / "merged.ply";
      if (stopped()) return finish_interrupted();
    }
    fs::path scans_file;  // the cloud the consolidation thins (the surface's scans)
    if (cfg_.pipeline.consolidate.enabled) {
      scans_file = cloud_file;
      key = hash_hex(key + consolidate_key(cfg_.pipeline));
      stage(++index, total, "consolidate", cloud_file, key, "consolidated.ply",
            [&](StageRecord& r) { do_consolidate(r, cloud_file); });
      cloud_file = req_.out_dir / "consolidated.ply";
      if (stopped()) return finish_interrupted();
    }
    key = hash_hex(key + surface_key(cfg_.pipeline));
    stage(++index, total, "surface", cloud_file, key, "mesh.ply", [&](StageRecord& r) { do_surface(r, cloud_file, scans_file); });
    result_.mesh = req_.out_dir / "mesh.ply";
    if (req_.report) {
      say("run: writing the report");
      result_.report = req_.out_dir / "report.html";
      write_report(req_.out_dir, req_.input, session_, result_, result_.report);
    }
    return result_;
  }

 private:
  /// The files the run writes into its folder never replace its input (a cloud file
  /// in the run folder, or a session's manifest or views): refused before any work.
  void check_outputs_are_not_inputs() const {
    std::vector<fs::path> inputs;
    if (!session_) {
      inputs.push_back(req_.input);
    } else {
      const fs::path dir = fs::is_directory(req_.input) ? req_.input : req_.input.parent_path();
      inputs.push_back(dir / "session.yaml");
      try {
        for (const ViewRecord& v : read_manifest(dir).views) {
          inputs.push_back(dir / v.file);
          if (!v.colour_image.empty()) inputs.push_back(dir / v.colour_image);
        }
      } catch (const Error&) {
        // An unreadable manifest is reported by the register stage; it lists nothing here.
      }
    }
    // What this run writes: a cloud given as input is not registered (no merged.ply),
    // and consolidation or the report may be off (a rerun on the folder's own
    // merged.ply or consolidated.ply is then legitimate).
    std::vector<const char*> written{kStateFile, "mesh.ply", "colour_boundary.bin"};
    if (session_) written.push_back("merged.ply");
    if (cfg_.pipeline.consolidate.enabled) written.push_back("consolidated.ply");
    if (req_.report) written.push_back("report.html");
    for (const char* name : written)
      for (const fs::path& in : inputs)
        if (const fs::path out = req_.out_dir / name; same_file(out, in))
          throw InvalidInput(out.string() + " is also an input" +
                             (out.lexically_normal() == in.lexically_normal() ? "" : " (" + in.string() + ")") +
                             "; choose another output folder");
  }

  bool stopped() const { return req_.stop && req_.stop->load(); }
  RunResult finish_interrupted() {
    result_.interrupted = true;
    return result_;
  }
  void say(const std::string& line) const {
    if (req_.events) req_.events({ProgressEvent::Kind::kLine, {}, line, 0, 0, 0});
    if (!req_.quiet) std::fprintf(stderr, "%s\n", line.c_str());
  }

  /// Runs stage `name` on `input` (a cloud or the session), unless its output can be kept.
  template <class F>
  void stage(int index, int total, const std::string& name, const fs::path& input, const std::string& key,
             const std::string& output, F&& work) {
    const fs::path out = req_.out_dir / output;
    if (const StageRecord* old = old_.find(name); old && old->key == key && old->output == output && fs::exists(out)) {
      if (hash_file(out) == old->output_hash) {
        StageRecord r = *old;
        r.reused = true;
        say("[" + std::to_string(index) + "/" + std::to_string(total) + "] " + name + ": unchanged, kept " +
            out.string());
        record(r);
        stage_event(name, "kept", index, total, r.seconds);
        return;
      }
      say("[" + std::to_string(index) + "/" + std::to_string(total) + "] " + name + ": " + out.string() +
          " was altered since the last run; redoing it");
    }
    say("[" + std::to_string(index) + "/" + std::to_string(total) + "] " + name + "...");
    stage_event(name, "start", index, total, 0);
    StageRecord r;
    r.name = name;
    r.key = key;
    r.output = output;
    reset_peak_rss();
    const auto t0 = Clock::now();
    try {
      work(r);
    } catch (const InvalidInput& e) {
      // The library names its data by role ("fit_mpu: 0 points..."); the run names the
      // stage's input file, and the stage unless the message starts with it. A message
      // that names one of the stage's profile keys ("consolidate.radius ...") is about
      // the parameter, not the input: it stays as it is.
      const std::string what = e.what();
      if (what.find(input.string()) != std::string::npos || what.rfind(name + ".", 0) == 0) throw;
      throw InvalidInput(input.string() + ": " + (what.rfind(name + ":", 0) == 0 ? "" : name + ": ") + what);
    }
    r.seconds = seconds_since(t0);
    r.peak_rss_mb = peak_rss_mb();
    r.output_hash = hash_file(out);
    record(r);
    say("[" + std::to_string(index) + "/" + std::to_string(total) + "] " + name + ": done in " +
        seconds_text(r.seconds) + " s -> " + out.string());
    stage_event(name, "done", index, total, r.seconds);
  }
  void stage_event(const std::string& name, const char* what, int index, int total, double seconds) const {
    if (req_.events) req_.events({ProgressEvent::Kind::kStage, name, what, index, total, seconds});
  }

  /// Adds the stage to the result and rewrites run.yaml (the commit point of the stage).
  void record(const StageRecord& r) {
    result_.stages.push_back(r);
    state_.stages.push_back(r);
    write_file_atomic(req_.out_dir / kStateFile, state_yaml(state_));
  }

  void do_register(StageRecord& r) {
    const fs::path dir = fs::is_directory(req_.input) ? req_.input : req_.input.parent_path();
    const Session session = Session::open(dir);
    if (session.manifest().views.empty()) throw InvalidInput(dir.string() + ": the session has no views");
    const RegistrationParams p = registration_params(cfg_.pipeline);
    std::unique_ptr<Progress> bar;
    std::string sub;
    const RegistrationResult reg = register_session(session, p, [&](const RegistrationProgress& pr) {
      if (pr.stage != sub) {
        if (bar) bar->finish();
        sub = pr.stage;
        bar = std::make_unique<Progress>("  register: " + sub, pr.total, req_.quiet, req_.events);
      }
      bar->update(pr.done);
    });
    if (bar) bar->finish();
    for (int v : reg.failed_views) say("warning: " + reg.views[v].message);
    for (const std::string& w : reg.warnings) say("warning: " + w);
    for (const std::string& w : reg.notes) say("note: " + w);
    if (reg.degenerate) say("note: " + reg.degeneracy_message);
    if (reg.merged.empty()) throw InvalidInput(dir.string() + ": no view could be registered");
    write_ply(req_.out_dir / "merged.ply", reg.merged);
    r.figures["views"] = double(reg.views.size());
    r.figures["failed_views"] = double(reg.failed_views.size());
    r.figures["points"] = double(reg.merged.size());
    r.figures["degenerate"] = reg.degenerate ? 1 : 0;
    int rejected = 0;
    for (const ViewDiagnostics& v : reg.views) rejected += v.angle_rejected ? 1 : 0;
    r.figures["angles_rejected"] = rejected;
    r.figures["rigid_turntable"] = reg.rigid_turntable ? 1 : 0;
    if (reg.rigid_deviation_deg > 0 || reg.rigid_deviation > 0) {
      r.figures["rigid_deviation_deg"] = reg.rigid_deviation_deg;
      r.figures["rigid_deviation_mm"] = reg.rigid_deviation * reg.mm_per_unit;
    }
    if (reg.views_with_reference > 0) {
      r.figures["max_rotation_error_deg"] = reg.max_rotation_error_deg;
      r.figures["max_translation_error_mm"] = reg.max_translation_error * reg.mm_per_unit;
    }
    // Residual per view: mean inlier RMS of the final round's pairs that involve it.
    int last_round = 0;
    for (const PairDiagnostics& pd : reg.pairs) last_round = std::max(last_round, pd.round);
    std::vector<double> sum(reg.views.size(), 0);
    std::vector<int> count(reg.views.size(), 0);
    for (const PairDiagnostics& pd : reg.pairs) {
      if (pd.round != last_round || !pd.converged) continue;
      for (int v : {pd.from, pd.to})
        if (v >= 0 && v < int(sum.size())) {
          sum[v] += pd.inlier_rmse * reg.mm_per_unit;
          ++count[v];
        }
    }
    for (std::size_t i = 0; i < sum.size(); ++i)
      r.per_view.push_back(count[i] ? sum[i] / count[i] : std::nan(""));
    if (reg.axis && !reg.poses.empty()) {
      // The object's up (the turntable axis) in the object frame, for the report's views.
      int first = 0;
      while (first + 1 < int(reg.views.size()) && !reg.views[first].registered) ++first;
      const Vec3d up = reg.poses[first].topLeftCorner<3, 3>() * reg.axis->direction;
      r.up = up;
      // The largest gap between the registered views' turns about the axis (the twist
      // of each view's rotation from the first's): under 120 degrees, the views
      // surround the object (do_surface).
      std::vector<double> turns;
      const Vec3d a = reg.axis->direction.normalized();
      for (std::size_t i = 0; i < reg.views.size(); ++i) {
        if (!reg.views[i].registered) continue;
        const Eigen::Matrix3d rel =
            reg.poses[std::size_t(first)].topLeftCorner<3, 3>().transpose() * reg.poses[i].topLeftCorner<3, 3>();
        // A view not turned about the table's axis (taken off the table: from above, in
        // the hand) says nothing of the ring: its twist would close a real gap.
        const Eigen::AngleAxisd turn(rel);
        if (turn.angle() > 2 * M_PI / 180 && std::abs(turn.axis().dot(a)) < std::cos(10 * M_PI / 180)) continue;
        const Eigen::Quaterniond q(rel);
        double t = 2 * std::atan2(q.vec().dot(a), q.w()) * 180 / M_PI;
        t = std::fmod(t + 720, 360);
        turns.push_back(t);
      }
      std::sort(turns.begin(), turns.end());
      double gap = 360;
      if (turns.size() >= 2) {
        gap = turns.front() + 360 - turns.back();
        for (std::size_t k = 1; k < turns.size(); ++k) gap = std::max(gap, turns[k] - turns[k - 1]);
      }
      r.figures["turn_gap_deg"] = gap;
      r.figures["up_x"] = up.x();
      r.figures["up_y"] = up.y();
      r.figures["up_z"] = up.z();
    }
    for (const ViewDiagnostics& v : reg.views) r.view_prior.push_back(v.registered ? to_string(v.prior) : "failed");
    for (const Eigen::Matrix4d& T : reg.poses) {
      std::vector<double> row(16);
      for (int k = 0; k < 16; ++k) row[k] = T(k / 4, k % 4);
      r.poses.push_back(row);
    }
  }

  void do_consolidate(StageRecord& r, const fs::path& in) {
    try {
      consolidate_stage(r, in);
    } catch (const InvalidInput& e) {
      // check_radii_within names the library's parameter ("consolidate: radius 10 is
      // larger than the cloud itself ..."), known only once the cloud is merged; the
      // run names the profile key that set it.
      const std::string what = e.what();
      for (const std::string key : {"radius", "fit_radius"})
        if (const std::string said = "consolidate: " + key + " "; what.rfind(said, 0) == 0)
          throw InvalidInput("consolidate." + key + " " + what.substr(said.size()));
      throw;
    }
  }

  void consolidate_stage(StageRecord& r, const fs::path& in) {
    const auto& c = cfg_.pipeline.consolidate;
    WlopParams p = wlop_params(cfg_.pipeline, cfg_.threads);
    const double max_bytes = cfg_.pipeline.reconstruct.max_memory_gb * 1e9;
    // auto: a block per 2 M points, and within --max-memory (reconstruct.max_memory_gb);
    // counted on a streamed pass, so that a cloud for blocks is never read whole.
    if (c.blocks != 1) {
      const CloudSource source = file_source(in.string());
      const std::size_t points = count_points(source);
      if (points == 0) throw InvalidInput(in.string() + ": empty cloud");
      if (wlop_block_count(points, c.blocks, max_bytes) > 1) {
        // WLOP in blocks at the whole cloud's scale (docs/blocks.md): over the ranks
        // under mpirun (they stream the same file), else in sequence here (also a batch
        // session's on its rank: the other ranks run their own sessions).
        const auto note = [&](const std::string& line) { say("  consolidate: " + line); };
        Cloud out;
        if (req_.blocks_over_ranks) {
          const fs::path work = req_.out_dir / "consolidate.blocks";
          BlockJob job;
          job.kind = BlockJob::Kind::kConsolidate;
          job.blocks = c.blocks;
          job.input = in.string();
          job.work = work.string();
          send_block_job(&job);
          WlopBlocksRun run = run_consolidate_blocks(in.string(), p, c.blocks, work.string(), note, max_bytes);
          r.figures["blocks"] = double(run.stats.blocks);
          r.figures["ranks"] = double(run.ranks);
          out = std::move(run.cloud);
        } else {
          BlockWlopStats st;
          out = consolidate_blocks(source, p, c.blocks, &st, note, max_bytes);
          r.figures["blocks"] = double(st.blocks);
          r.figures["ranks"] = 1;
        }
        write_ply(req_.out_dir / "consolidated.ply", out);
        r.figures["input_points"] = double(points);
        r.figures["points"] = double(out.size());
        return;
      }
    }
    std::string oriented;
    const Cloud input = read_cloud_oriented(in, cfg_.threads, oriented);
    if (input.empty()) throw InvalidInput(in.string() + ": empty cloud");
    if (!oriented.empty()) say("  note: " + oriented);
    Progress bar(std::string("  consolidate: ") + wlop_label(c.method) + " iterations", c.iterations, req_.quiet, req_.events);
    p.progress = [&](int done, int) { bar.update(done); };
    const WlopResult w = consolidate(input, p);
    bar.finish();
    write_ply(req_.out_dir / "consolidated.ply", w.cloud);
    r.figures["input_points"] = double(w.input_points);
    r.figures["points"] = double(w.cloud.size());
    r.figures["radius"] = w.radius;
  }

  void do_surface(StageRecord& r, const fs::path& in, const fs::path& scans_file) {
    std::error_code ec;
    fs::remove(req_.out_dir / "colour_boundary.bin", ec);  // a report side file of the last surface
    const auto& c = cfg_.pipeline.reconstruct;
    std::string oriented;
    Cloud input = read_cloud_oriented(in, cfg_.threads, oriented);
    if (input.empty()) throw InvalidInput(in.string() + ": empty cloud");
    if (!oriented.empty()) say("  note: " + oriented);
    if (c.surface == "sdm") return do_sdm(r, in, input);
    SurfaceParams sp = surface_params(cfg_.pipeline, cfg_.threads);
    // The table plane (docs/run.md): a session's object frame knows its up, and
    // the object rests on the table, so nothing of it lies below its lowest point.
    if (c.table_plane)
      for (const StageRecord& s : result_.stages)
        if (s.name == "register" && s.up) sp.table_up = *s.up;
    // Views all round the object (no gap between their turns about the table's axis
    // of 120 degrees or more): a solid on the table, closed from a lower enclosure
    // (kEnclosedAboveSurrounded). Not in blocks (every rank must decide alike).
    if (!c.in_blocks())
      for (const StageRecord& s : result_.stages)
        if (s.name == "register" && s.figures.count("turn_gap_deg") && s.figures.at("turn_gap_deg") < 120)
          sp.enclosed_above = kEnclosedAboveSurrounded;
    r.figures["enclosed_above"] = sp.enclosed_above;
    sp.resolution_name =
        "reconstruct.resolution " + (c.resolution > 0 ? std::to_string(c.resolution) : std::string("auto"));
    sp.boundary_flags = true;
    sp.note = [&](const std::string& line) { say(surface_note(in, line, "  surface: ", "  note: ")); };
    SurfaceResult sr;
    if (c.in_blocks() && c.snap_to_scans)
      say("  note: reconstruct.snap_to_scans is not done in blocks: the mesh stays on the fitted surface");
    if (c.in_blocks() && req_.blocks_over_ranks) {
      // Blocks of one lattice over the MPI ranks: the others run them with this one
      // from the same file (docs/blocks.md).
      input = Cloud{};
      const fs::path work = req_.out_dir / "surface.blocks";
      std::error_code ec;
      fs::remove_all(work, ec);  // an earlier run's blocks: this stage runs again
      BlockJob job;
      job.input = in.string();
      job.work = work.string();
      job.up = sp.table_up;
      send_block_job(&job);
      BlockRun run = run_blocks(in.string(), sp, c.blocks, work.string(), false, {}, c.max_memory_gb * 1e9);
      fs::remove_all(work, ec);
      r.figures["blocks"] = double(run.stats.blocks);
      r.figures["ranks"] = double(run.ranks);
      sr = std::move(run.result);
    } else if (c.in_blocks()) {
      // Blocks of one lattice, in sequence here (docs/blocks.md).
      BlockRunStats st;
      sr = reconstruct_surface_blocks(memory_source(input), sp, c.blocks, &st, c.max_memory_gb * 1e9);
      r.figures["blocks"] = double(st.blocks);
      r.figures["ranks"] = 1;
    } else {
      // The scans the consolidation thinned: the mesh's vertices onto local fits of them.
      Cloud scans;
      if (c.snap_to_scans && scans_file.empty())
        say("  note: reconstruct.snap_to_scans needs the consolidation (the cloud it thins): the mesh stays on the "
            "fitted surface");
      if (c.snap_to_scans && !scans_file.empty()) {
        scans = read_cloud(scans_file);
        sp.scans = &scans;  // (without normals reconstruct_surface says so and leaves the mesh)
      }
      sr = reconstruct_surface(std::move(input), sp);
      if (sp.scans) {
        r.figures["snapped_vertices"] = double(sr.snapped_vertices);
        r.figures["snap_declined"] = sr.snap_declined ? 1 : 0;
      }
    }
    if (sr.winding_points > 0) r.figures["winding_points"] = double(sr.winding_points);
    if (sr.table_height) r.figures["table_height"] = *sr.table_height;
    r.figures["removed_pieces"] = double(sr.pieces.removed_components);
    if (sr.colour) {
      r.figures["colour_nearest_vertices"] = double(sr.colour_nearest_vertices);
      if (c.colour_edges) r.figures["colour_edges_split"] = double(sr.colour_edges_split);
      r.figures["colour_leaves_a"] = double(sr.colour->leaves_by_type[0]);
      r.figures["colour_leaves_b"] = double(sr.colour->leaves_by_type[1]);
      r.figures["e_col"] = sr.colour->e_col;
      // Where the colour function splits cells at a boundary (Type B), for the report.
      if (!sr.colour_boundary.empty())  // (not made in blocks)
        write_file_atomic(req_.out_dir / "colour_boundary.bin",
                          std::string(sr.colour_boundary.begin(), sr.colour_boundary.end()));
    }
    // The cleanup after the extraction can leave nothing: an error, not an empty mesh.
    if (sr.mesh.faces.empty()) throw InvalidInput("the reconstructed surface is empty");
    write_ply(req_.out_dir / "mesh.ply", sr.mesh);
    r.figures["leaves"] = double(sr.mpu.leaves);
    r.figures["epsilon0"] = sr.epsilon0;
    r.figures["cell_size"] = sr.extraction.cell_size;
    r.figures["resolution"] = double(sr.resolution);
    r.figures["closed"] = sr.hole == HoleMode::kClose ? 1.0 : 0.0;
    r.figures["rim_faces"] = double(sr.rim_faces);
    r.figures["scan_rim_faces"] = double(sr.scan_rim_faces);
    r.figures["supported_pieces"] = double(sr.pieces.supported_components);
    if (sr.enclosure) r.figures["enclosure"] = *sr.enclosure;
    r.figures["vertices"] = double(sr.mesh.vertices.size());
    r.figures["faces"] = double(sr.mesh.faces.size());
    r.figures["coloured"] = sr.coloured ? 1 : 0;
  }

  /// The SDM alternative: a level-L icosphere fitted to the cloud (reconstruct/sdm.h),
  /// coloured by the colour function when the cloud has colours.
  void do_sdm(StageRecord& r, const fs::path& in, const Cloud& input) {
    const auto& c = cfg_.pipeline.reconstruct;
    SdmParams sp;
    sp.threads = cfg_.threads;
    const int level = cfg_.pipeline.sdm.level;
    say("  surface: SDM, level-" + std::to_string(level) + " icosphere onto " + std::to_string(input.size()) +
        " points");
    Progress bar("  surface: SDM", 100, req_.quiet, req_.events);
    const SdmResult fit = fit_sdm_icosphere(level, input, sp, {}, [&](const std::string& phase, double f) {
      bar.update(int(std::lround(100 * f)), phase);
    });
    bar.finish();
    Mesh mesh = fit.mesh;
    const bool colour = c.colour && input.has_colours();
    if (colour) {
      colour_mesh(mesh, fit_colour(input, colour_params(surface_params(cfg_.pipeline, cfg_.threads))),
                  cfg_.threads);
    }
    write_ply(req_.out_dir / "mesh.ply", mesh);
    const SdmDiagnostics& d = fit.diagnostics;
    r.figures["vertices"] = double(mesh.vertices.size());
    r.figures["faces"] = double(mesh.faces.size());
    r.figures["mean_distance"] = d.mean_distance;
    r.figures["flipped_faces"] = d.flipped_faces;
    r.figures["self_intersections"] = d.self_intersections;
    r.figures["coloured"] = colour ? 1 : 0;
    (void)in;
  }

  const StationConfig& cfg_;
  const RunRequest& req_;
  bool session_ = false;
  RunState old_, state_;
  RunResult result_;
};

}  // namespace

RunResult run_pipeline(const StationConfig& config, const RunRequest& request) {
  // A run that fails before its first stage is recorded leaves no empty folder behind.
  CreatedOutputs created(request.out_dir);
  RunResult r = Runner(config, request).run();
  created.keep();
  return r;
}

std::vector<StageRecord> read_run_stages(const fs::path& run_yaml) { return read_state(run_yaml).stages; }

}  // namespace station
