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
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <sstream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "station/blocks_run.h"
#include "core/io.h"
#include "core/range_image.h"
#include "core/normals.h"
#include "core/threads.h"
#include "reconstruct/colour_function.h"
#include "reconstruct/dmc.h"
#include "reconstruct/mpu.h"
#include "reconstruct/sdm.h"
#include "reconstruct/surface.h"
#include "reconstruct/wlop.h"
#include "registration/registration.h"
#include "station/config.h"
#include "station/json.h"
#include "station/params.h"
#include "station/progress.h"

namespace station::cli {

namespace {

/// A cloud that spans less than a micrometre (in metres; a nanometre in millimetres)
/// is no scan of an object: wrong units or a corrupt file. The methods' tolerances
/// did not hold there (a sphere 1e-12 across was fitted with 14.5 % error and 1,010
/// flipped faces, and reconstructed open, exit 0). Clouds whose points all coincide
/// are left to the methods' own message.
void check_cloud_size(const Cloud& cloud, const std::string& file) {
  if (cloud.empty()) return;
  const double d = bounding_box(cloud.points).diagonal();
  if (d > 0 && d < 1e-6) {
    char buf[96];
    std::snprintf(buf, sizeof buf, "%.3g", d);
    throw InvalidInput(file + ": the cloud spans only " + buf +
                       " (under a micrometre in metres): wrong units or a corrupt file?");
  }
}

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

// --up's form: three finite numbers x,y,z whose length is finite and not zero. 1e308,0,0
// overflows the length and 1e-200,0,0 underflows it: neither normalises, and they failed
// late, in the table plane's clip.
const char* const kUpForm = "expected a direction x,y,z (finite numbers, a finite and non-zero length)";

bool read_up(const std::string& text, Vec3d& v) {
  char comma1 = 0, comma2 = 0, rest = 0;
  return std::sscanf(text.c_str(), "%lf %c %lf %c %lf %c", &v.x(), &comma1, &v.y(), &comma2, &v.z(), &rest) == 5 &&
         comma1 == ',' && comma2 == ',' && v.allFinite() && std::isfinite(v.norm()) && v.norm() > 0;
}

std::optional<Vec3d> parse_up(const std::string& text) {
  if (text.empty()) return std::nullopt;
  Vec3d v;
  if (!read_up(text, v)) throw InvalidInput("--up " + text + ": " + kUpForm);
  return v;
}

/// --up checked as the command line is parsed: a usage error naming --up, whether or
/// not the table plane is on.
CLI::Validator up_direction() {
  return CLI::Validator(
      [](std::string& text) -> std::string {
        Vec3d v;
        if (text.empty() || read_up(text, v)) return {};
        return std::string(kUpForm) + " (got " + text + ")";
      },
      "X,Y,Z");
}

}  // namespace

int cmd_fit(const Common& c, const FitArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  check_output_name(a.out, "a mesh", {".ply", ".obj"});
  check_not_an_input({a.out}, {a.in, a.landmarks, a.templ.rfind("icosphere:", 0) == 0 ? std::string() : a.templ, c.config});
  check_output_path(a.out);  // (a missing folder, a device: before the fit, not after it)
  StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  const Cloud target = read_cloud(a.in);
  check_cloud_size(target, a.in);
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
    // One digit and nothing after it ("1e9" was read as 1, "2.5" as 2).
    const std::string l = a.templ.substr(10);
    const int level = l.size() == 1 && l[0] >= '0' && l[0] <= '9' ? l[0] - '0' : -1;
    if (level < 0 || level > 7) throw UsageError("--template " + a.templ + ": expected icosphere:L with L in 0..7");
    fit = fit_sdm_icosphere(level, target, sp, landmarks, progress);
  } else {
    fit = fit_sdm(read_mesh(a.templ), target, sp, landmarks, progress);
  }
  bar.finish();
  Mesh mesh = fit.mesh;
  const bool colour = target.has_colours() && !a.no_colour;
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

int cmd_parameterise(const Common& c, const ParameteriseArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  check_output_name(a.out, "a mesh with UVs", {".obj"});
  if (!a.mapped.empty()) check_output_name(a.mapped, "a mesh", {".ply", ".obj"});  // (was found after the SDM work)
  check_not_an_input({a.out, a.mapped}, {a.in, c.config});
  check_output_path(a.out);
  if (!a.mapped.empty()) check_output_path(a.mapped);
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
  // Each write is atomic: a failure leaves no half-written file; and both outputs or
  // neither: when one cannot be written, the other one this command created goes again.
  CreatedOutputs created({}, {a.out, a.mapped});
  if (!a.mapped.empty()) write_mesh(a.mapped, r.mesh);
  write_obj(a.out, textured, uv);
  created.keep();
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

int cmd_consolidate(const Common& c, const ConsolidateArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  check_output_name(a.out, "a cloud", {".ply"});
  check_not_an_input({a.out}, {a.in, c.config});
  check_output_path(a.out);
  StationConfig cfg = load_common(c);
  const auto& pc = cfg.pipeline.consolidate;
  WlopParams p = wlop_params(cfg.pipeline, cfg.threads);
  // The JSON summary's common head (in blocks or in one piece).
  const auto summary = [&] {
    return JsonObject().add("command", "consolidate").add("input", a.in).add("output", a.out).add("method", pc.method);
  };
  if (pc.blocks != 1) {
    // In blocks (reconstruct/blocks_wlop.h): asked for, under mpirun, or a cloud above
    // the auto block size; streamed, over the ranks under mpirun.
    bool split = pc.blocks > 1 || mpi_ranks() > 1;
    if (!split) split = count_points(file_source(a.in)) > kAutoWlopBlockPoints;
    if (split) {
      const auto note = [&](const std::string& line) {
        if (!c.json) std::fprintf(stderr, "consolidate: %s\n", line.c_str());
      };
      check_blocks_work_folder(a.out + ".blocks", {a.in, c.config});
      const WlopBlocksRun run = run_consolidate_blocks(a.in, p, pc.blocks, a.out + ".blocks", note);
      if (!run.root) return 0;
      write_ply(a.out, run.cloud);
      if (c.json) {
        print_summary(summary()
                          .add("output_points", run.cloud.size())
                          .add("blocks", run.stats.blocks)
                          .add("ranks", run.ranks)
                          .add("max_block_points", run.stats.max_block_points)
                          .add("timings_s", JsonObject().add("total", seconds_since(t0))));
      } else {
        std::printf("consolidate: %zu points (%s, %d blocks on %d rank%s) in %.2fs -> %s\n", run.cloud.size(),
                    pc.method.c_str(), run.stats.blocks, run.ranks, run.ranks > 1 ? "s" : "", seconds_since(t0),
                    a.out.c_str());
      }
      return 0;
    }
  }
  std::string oriented;
  const Cloud input = read_cloud_oriented(a.in, cfg.threads, oriented);
  check_cloud_size(input, a.in);
  if (!oriented.empty() && !c.json) std::fprintf(stderr, "note: %s\n", oriented.c_str());
  const double t_read = seconds_since(t0);
  if (!c.json)
    std::fprintf(stderr, "consolidate: %s, %zu points, %s, %d iterations...\n", a.in.c_str(),
                 input.size(), pc.method.c_str(), pc.iterations);
  Progress bar(std::string("consolidate: ") + wlop_label(pc.method) + " iterations", pc.iterations, c.json);
  p.progress = [&](int done, int) { bar.update(done); };
  const WlopResult r = consolidate(input, p);
  bar.finish();
  write_ply(a.out, r.cloud);
  if (c.json) {
    print_summary(summary()
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

int cmd_reconstruct(const Common& c, const ReconstructArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  check_output_name(a.out, "a mesh", {".ply", ".obj"});
  check_not_an_input({a.out}, {a.in, a.scans, c.config});
  StationConfig cfg = load_common(c);
  const auto& rc = cfg.pipeline.reconstruct;
  SurfaceParams sp = surface_params(cfg.pipeline, cfg.threads);
  if (rc.table_plane) sp.table_up = parse_up(a.up);
  sp.resolution_name = "--resolution " + (rc.resolution > 0 ? std::to_string(rc.resolution) : std::string("auto"));
  sp.note = [&](const std::string& line) {
    if (!c.json) std::fprintf(stderr, "%s\n", surface_note(a.in, line, "reconstruct: ", "note: ").c_str());
  };
  const bool in_blocks = rc.in_blocks() || a.resume;
  // In one piece the output is checked before the work; a run in blocks keeps its
  // blocks' files when the output cannot be written at the end, for --resume.
  if (!in_blocks) check_output_path(a.out);
  if (!a.scans.empty() && in_blocks)
    throw InvalidInput("--scans does not go with --blocks, --max-memory or --resume (the blocks are not snapped)");
  if (in_blocks) {
    // Blocks of one lattice: streamed, never the whole cloud in memory; over the MPI
    // ranks under mpirun (station/blocks_run.h).
    if (rc.blocks == 1 && rc.max_memory_gb == 0)
      throw UsageError("--resume goes with --blocks (auto or a count) or --max-memory");
    const std::string work = a.out + ".blocks";
    check_blocks_work_folder(work, {a.in, c.config});
    // A PLY is written streamed from the blocks' files (never the whole mesh in memory).
    std::string ext = std::filesystem::path(a.out).extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char ch) { return char(std::tolower(ch)); });
    const bool ply = ext == ".ply";
    const BlockRun run =
        run_blocks(a.in, sp, rc.blocks, work, a.resume, ply ? a.out : std::string(), rc.max_memory_gb * 1e9);
    if (!run.root) return 0;
    if (!run.written) write_mesh(a.out, run.result.mesh);
    std::error_code ec;
    std::filesystem::remove_all(work, ec);  // the output is written: the blocks' files go
    const SurfaceResult& r = run.result;
    if (c.json) {
      print_summary(JsonObject()
                        .add("command", "reconstruct")
                        .add("input", a.in)
                        .add("output", a.out)
                        .add("points", r.mpu.input_points)
                        .add("vertices", run.stats.vertices)
                        .add("faces", run.stats.faces)
                        .add("blocks", run.stats.blocks)
                        .add("ranks", run.ranks)
                        .add("resumed_blocks", run.resumed)
                        .add("memory_estimate_gb", run.memory_estimate / 1e9)
                        .add("rank_peak_rss_mb", run.rank_peak_mb)
                        .add("seam_vertices_joined", run.stats.seam_vertices_joined)
                        .add("removed_pieces", r.pieces.removed_components)
                        .add("epsilon0", r.epsilon0)
                        .add("cell_size", r.extraction.cell_size)
                        .add("resolution", r.resolution)
                        .add("resolution_auto", r.resolution_auto)
                        .add("hole", std::string(r.hole == HoleMode::kClose ? "close" : "keep"))
                        .add("rim_faces", r.rim_faces)
                        .add("scan_rim_faces", r.scan_rim_faces)
                        .add("supported_pieces", r.pieces.supported_components)
                        .add("colours", r.coloured)
                        .add("e_col", r.colour ? r.colour->e_col : -1.0)
                        .add("colour_edges_split", r.colour_edges_split)
                        .add("extractor", rc.extractor)
                        .add("timings_s", JsonObject().add("total", seconds_since(t0))));
    } else {
      std::printf("reconstruct: %zu vertices, %zu faces in %d blocks on %d rank%s (cell %.4g) in %.2fs -> %s\n",
                  run.stats.vertices, run.stats.faces, run.stats.blocks, run.ranks, run.ranks > 1 ? "s" : "",
                  r.extraction.cell_size, seconds_since(t0), a.out.c_str());
    }
    return 0;
  }
  std::string oriented;
  Cloud input = read_cloud_oriented(a.in, cfg.threads, oriented);
  check_cloud_size(input, a.in);
  if (!oriented.empty() && !c.json) std::fprintf(stderr, "note: %s\n", oriented.c_str());
  Cloud scans;
  if (!a.scans.empty()) {
    scans = read_cloud(a.scans);
    if (scans.empty()) throw InvalidInput(a.scans + ": no points");
    if (!scans.has_normals() || !any_usable_normal(scans.normals))
      throw InvalidInput(a.scans + ": the scans have no normals" + (scans.has_normals() ? " (all zero)" : "") +
                         " (needed to tell a thin part's sides apart)");
    sp.scans = &scans;
  }
  const std::size_t points = input.size();
  const double t_read = seconds_since(t0);
  const SurfaceResult r = reconstruct_surface(std::move(input), sp);
  // The cleanup after the extraction (rims trimmed back to the data, small pieces
  // removed) can leave nothing: an error, not an empty mesh file.
  if (r.mesh.faces.empty()) throw InvalidInput(a.in + ": the reconstructed surface is empty");
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
                      .add("resolution", r.resolution)
                      .add("resolution_auto", r.resolution_auto)
                      .add("hole", std::string(r.hole == HoleMode::kClose ? "close" : "keep"))
                      .add("enclosure", r.enclosure ? *r.enclosure : std::nan(""))
                      .add("rim_faces", r.rim_faces)
                      .add("scan_rim_faces", r.scan_rim_faces)
                      .add("supported_pieces", r.pieces.supported_components)
                      .add("snapped_vertices", r.snapped_vertices)
                      .add("snap_declined", r.snap_declined)
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
                                            .add("scans", r.seconds.scans)
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

void add_surface_commands(CLI::App& app, std::vector<Command>& out) {
  struct State {
    ConsolidateArgs cons_args;
    FitArgs fit_args;
    ParameteriseArgs par_args;
    ReconstructArgs rec_args;
    Common c_cons, c_fit, c_par, c_rec;
  };
  auto s = std::make_shared<State>();
  auto& cons_args = s->cons_args;
  auto& fit_args = s->fit_args;
  auto& par_args = s->par_args;
  auto& rec_args = s->rec_args;
  auto& c_cons = s->c_cons;
  auto& c_fit = s->c_fit;
  auto& c_par = s->c_par;
  auto& c_rec = s->c_rec;
  auto* cons = app.add_subcommand("consolidate", "Thin and even out a cloud by WLOP (or edge-preserving WLOP)");
  add_common(cons, c_cons);
  cons->add_option("input", cons_args.in, "input cloud (.ply .pcd .obj .off)")->required();
  cons->add_option("-o,--out", cons_args.out, "output cloud (.ply)")->required();
  add_profile_options(cons, "consolidate", c_cons);
  cons->get_option("--ratio")->excludes(cons->get_option("--points"));


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
                   "control points sampled on the surface (0 = 4 x the mesh's vertices; at most 10,000,000)")
      ->check(whole_number(0, 10000000))
      ->capture_default_str();


  auto* rec = app.add_subcommand("reconstruct", "Fit an MPU implicit surface with colour to a cloud and mesh it (Deformed Marching Cubes)");
  add_common(rec, c_rec);
  rec->add_option("input", rec_args.in, "cloud with normals (estimated when missing)")->required();
  rec->add_option("-o,--out", rec_args.out, "mesh (.ply or .obj)")->required();
  add_profile_options(rec, "reconstruct", c_rec);
  rec->add_option("--scans", rec_args.scans,
                  "the scans the input was consolidated from (e.g. a run's merged.ply, with normals): the mesh's "
                  "vertices move onto local fits of them where a held-out half says so, keeping the scans' detail "
                  "(docs/run.md)");
  rec->add_flag("--resume", rec_args.resume,
                "with --blocks: blocks finished by an interrupted run (in OUT.blocks/) are not run again");
  rec->add_option("--up", rec_args.up,
                  "the turntable axis in the cloud's frame, x,y,z (a run's register stage `up` in run.yaml): "
                  "when the surface is closed (--hole close, or auto closing) the underside closes flat at the table plane (profile "
                  "reconstruct.table_plane)")
      ->check(up_direction());


  out.push_back({cons, [s] {
                   return naming_the_file(s->cons_args.in, s->cons_args.out,
                                          [&] { return cmd_consolidate(s->c_cons, s->cons_args); });
                 }});
  out.push_back({fitc, [s] {
                   return naming_the_file(s->fit_args.in, s->fit_args.out, [&] { return cmd_fit(s->c_fit, s->fit_args); },
                                          {{"template:", s->fit_args.templ}, {"landmark ", s->fit_args.landmarks}});
                 }});
  out.push_back({parc, [s] {
                   // (A message naming the --mapped output is its own.)
                   std::vector<std::pair<std::string, std::string>> roles;
                   if (!s->par_args.mapped.empty()) roles.push_back({s->par_args.mapped, s->par_args.mapped});
                   return naming_the_file(s->par_args.in, s->par_args.out,
                                          [&] { return cmd_parameterise(s->c_par, s->par_args); }, roles);
                 }});
  out.push_back({rec, [s] {
                   return naming_the_file(s->rec_args.in, s->rec_args.out,
                                          [&] { return cmd_reconstruct(s->c_rec, s->rec_args); });
                 }});
}

}  // namespace station::cli
