#include "station/cli.h"

#include <CLI/CLI.hpp>
#include <cstdio>
#include <new>

#include "core/error.h"
#include "station/commands.h"

#ifndef STATION_VERSION
#define STATION_VERSION "dev"
#endif

namespace station {

using namespace cli;

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
