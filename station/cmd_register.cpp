#include "station/commands.h"

#include <CLI/CLI.hpp>
#include <sys/resource.h>
#include <tbb/global_control.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
#include <csignal>
#include <unistd.h>
#include <cstdio>
#include <regex>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <sstream>

#include "capture/camera_calibration.h"
#include "capture/session.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/io.h"
#include "reconstruct/sdm.h"
#include "registration/axis_calibration.h"
#include "registration/registration.h"
#include "station/config.h"
#include "station/json.h"
#include "station/params.h"
#include "station/progress.h"

namespace station::cli {

namespace {

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
  for (const std::string& w : r.notes)
    if (!quiet) std::fprintf(stderr, "note: %s\n", w.c_str());
  if (r.degenerate && !quiet) std::fprintf(stderr, "note: %s\n", r.degeneracy_message.c_str());
  return r;
}

JsonObject registration_json(const RegistrationResult& r) {
  // Lengths in metres whatever the session's units (the keys say _m).
  const double m = r.mm_per_unit / 1000;
  JsonObject j;
  j.add("views", r.views.size()).add("failed_views", r.failed_views.size()).add("degenerate", r.degenerate);
  j.add("warnings", r.warnings);
  j.add("notes", r.notes);
  j.add("pair_rmse_m", m * r.mean_pair_rmse);
  j.add("prior_kept", r.prior_kept);
  if (!r.prior_comparison.empty()) j.add("prior_comparison", r.prior_comparison);
  j.add("rigid_turntable", JsonObject()
                               .add("used", r.rigid_turntable)
                               .add("runs", r.turntable_groups)
                               .add("moved_before_views", std::vector<double>(r.run_starts.begin(), r.run_starts.end()))
                               .add("deviation_deg", r.rigid_deviation_deg)
                               .add("deviation_m", m * r.rigid_deviation));
  if (r.fuse_distance > 0)
    j.add("fuse", JsonObject()
                      .add("distance_m", m * r.fuse_distance)
                      .add("input_points", r.fuse.input)
                      .add("fused_points", r.fuse.fused)
                      .add("output_points", r.fuse.output));
  if (r.views_with_reference > 0) {
    JsonObject ref;
    ref.add("views", r.views_with_reference)
        .add("max_rotation_deg", r.max_rotation_error_deg)
        .add("median_rotation_deg", r.median_rotation_error_deg)
        .add("max_translation_m", m * r.max_translation_error)
        .add("median_translation_m", m * r.median_translation_error)
        .add("max_object_translation_m", m * r.max_object_translation_error)
        .add("median_object_translation_m", m * r.median_object_translation_error);
    // The same pairs' residual under the reference poses: which poses fit the scans better.
    if (r.mean_reference_pair_rmse) ref.add("pair_rmse_m", m * *r.mean_reference_pair_rmse);
    j.add("reference", ref);
  }
  JsonObject per_view;
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    const ViewDiagnostics& v = r.views[i];
    JsonObject o;
    o.add("registered", v.registered).add("initial", to_string(v.initial)).add("points", v.points)
        .add("angle_rejected", v.angle_rejected).add("prior", to_string(v.prior));
    if (v.angle_error_deg) o.add("angle_error_deg", *v.angle_error_deg);
    if (v.rotation_error_deg) o.add("rotation_error_deg", *v.rotation_error_deg);
    if (v.translation_error) o.add("translation_error_m", m * *v.translation_error);
    if (v.object_translation_error) o.add("object_translation_error_m", m * *v.object_translation_error);
    if (v.seen_through) o.add("seen_through", *v.seen_through);
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
    o.add("converged", p.converged).add("fitness", p.fitness).add("inlier_rmse_m", m * p.inlier_rmse)
        .add("correspondences", p.correspondences).add("iterations", p.iterations)
        .add("loop_closure", p.loop_closure).add("degenerate", p.degenerate);
    for (const PairResidual& pr : r.pair_residuals)
      if (pr.from == p.from && pr.to == p.to) {
        o.add("residual_rmse_m", m * pr.rmse);
        if (pr.reference_rmse) o.add("reference_residual_rmse_m", m * *pr.reference_rmse);
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
  std::printf("%-5s %-10s %-16s %-10s %9s %9s %12s %14s\n", "view", "status", "initial pose", "angle",
              "angle err", "points", "rot err deg", "trans err mm");
  for (std::size_t i = 0; i < r.views.size(); ++i) {
    const ViewDiagnostics& v = r.views[i];
    char rot[32] = "-", tr[32] = "-", ae[32] = "-";
    if (v.rotation_error_deg) std::snprintf(rot, sizeof rot, "%.3f", *v.rotation_error_deg);
    if (v.translation_error) std::snprintf(tr, sizeof tr, "%.3f", *v.translation_error * r.mm_per_unit);
    if (v.angle_error_deg) std::snprintf(ae, sizeof ae, "%.2f", *v.angle_error_deg);
    std::printf("%-5zu %-10s %-16s %-10s %9s %9zu %12s %14s\n", i,
                v.registered ? (v.angle_rejected ? "ok*" : "ok") : "FAILED", to_string(v.initial),
                v.prior == PriorUse::kNone ? "-" : to_string(v.prior), ae, v.points, rot, tr);
  }
  if (!r.prior_comparison.empty())
    std::printf("turntable prior checked: %s; kept: %s (angle: what became of each view's commanded angle; "
                "angle err: registered minus commanded, degrees)\n",
                r.prior_comparison.c_str(), r.prior_kept.c_str());
  // Relative to the first registered view with a reference pose (it said "view 0"
  // when view 0 had failed).
  std::size_t anchor = 0;
  while (anchor < r.views.size() && !(r.views[anchor].registered && r.views[anchor].rotation_error_deg)) ++anchor;
  if (r.views_with_reference > 0)
    std::printf("against reference poses (%d views, relative to view %zu): rotation max %.3f deg, "
                "median %.3f deg; translation max %.3f mm, median %.3f mm\n",
                r.views_with_reference, anchor, r.max_rotation_error_deg, r.median_rotation_error_deg,
                r.max_translation_error * r.mm_per_unit, r.median_translation_error * r.mm_per_unit);
  if (r.views_with_reference > 0)
    std::printf("  translation at the object (each view's centroid): max %.3f mm, median %.3f mm\n",
                r.max_object_translation_error * r.mm_per_unit, r.median_object_translation_error * r.mm_per_unit);
  if (r.rigid_turntable)
    std::printf("rigid turntable: the views lie on one axis (at most %.3f deg / %.3f mm from the free poses)\n",
                r.rigid_deviation_deg, r.rigid_deviation * r.mm_per_unit);
  else if (r.turntable_groups >= 2) {
    std::string before;
    for (std::size_t k = 0; k < r.run_starts.size(); ++k)
      before += (k ? (k + 1 == r.run_starts.size() ? " and " : ", ") : "") + std::to_string(r.run_starts[k]);
    std::printf("rigid turntable: %d runs of views on one axis (the object moved before view%s %s)\n",
                r.turntable_groups, r.run_starts.size() > 1 ? "s" : "", before.c_str());
  }
  if (!r.pair_residuals.empty()) {
    std::printf("pair residual (RMS point-to-plane over %zu refined pairs): %.4f mm",
                r.pair_residuals.size(), r.mean_pair_rmse * r.mm_per_unit);
    if (r.mean_reference_pair_rmse)
      std::printf("; under the reference poses %.4f mm", *r.mean_reference_pair_rmse * r.mm_per_unit);
    std::printf("\n");
  }
  for (const ViewDiagnostics& v : r.views)
    if (v.angle_rejected) {
      std::printf("ok*: the commanded turntable angle was wrong; the pose comes from global registration\n");
      break;
    }
}

std::string fmt_double(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4f", v);
  return buf;
}

}  // namespace

int cmd_register(const Common& c, const RegisterArgs& a) {
  check_output_name(a.out, "a cloud", {".ply"});
  if (!a.poses_out.empty()) check_output_name(a.poses_out, "the poses file", {".yaml", ".yml"});
  // Before the registration (minutes on a large session): a missing or unwritable
  // folder, a device, FIFO or folder at either name.
  check_output_path(a.out);
  if (!a.poses_out.empty()) check_output_path(a.poses_out);
  check_not_an_input({a.out, a.poses_out}, {c.config});
  StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  const std::string& session_dir = a.session;
  const std::string& out = a.out;
  const std::string& poses_out = a.poses_out;
  const Session session = Session::open(session_dir);
  if (session.manifest().views.empty()) throw InvalidInput(session_dir + ": the session has no views");
  const RegistrationResult r = register_with_progress(session, registration_params(cfg.pipeline), c.json);
  if (r.merged.empty()) throw InvalidInput(session_dir + ": no view could be registered");
  // Both outputs or neither: when one cannot be written, the other one this command
  // created goes again.
  CreatedOutputs created({}, {out, poses_out});
  write_ply(out, r.merged);
  if (!poses_out.empty()) write_poses_yaml(poses_out, r, session.manifest());
  created.keep();
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
                  r.fuse.input, r.fuse_distance * r.mm_per_unit);
    std::printf("register: %zu of %zu views, %zu points -> %s\n", r.views.size() - r.failed_views.size(),
                r.views.size(), r.merged.size(), out.c_str());
  }
  return r.failed_views.empty() ? 0 : 3;
}

int cmd_calibrate_turntable(const Common& c, const std::string& session_dir, const std::string& out) {
  // A profile fragment (YAML went into a .ply as readily); checked before the work.
  if (!out.empty()) {
    check_output_name(out, "a profile fragment", {".yaml", ".yml"});
    check_output_path(out);
  }
  check_not_an_input({out}, {c.config});
  StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  const Session session = Session::open(session_dir);
  const SessionManifest& m = session.manifest();
  if (m.views.empty()) throw InvalidInput(session_dir + ": the session has no views");
  // The axis is fitted to free poses: on poses held on one rigid turntable the
  // tilt and translation residuals would be zero by construction, and they are
  // what tells a wobbling table or a shifting object.
  RegistrationParams rp = registration_params(cfg.pipeline);
  rp.rigid_turntable = RigidTurntable::kOff;
  const RegistrationResult r = register_with_progress(session, rp, c.json);
  std::vector<Eigen::Matrix4d> poses;
  std::vector<double> angles;
  std::vector<std::size_t> used;  // the session's view index of each fitted pose
  for (std::size_t i = 0; i < m.views.size(); ++i) {
    if (!m.views[i].angle_deg || !r.views[i].registered) continue;
    poses.push_back(r.poses[i]);
    angles.push_back(*m.views[i].angle_deg);
    used.push_back(i);
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
                "# Turntable axis calibrated from %s (scanner frame, %s)\n"
                "# rms residuals: angle %.4f deg, tilt %.4f deg, translation %.4f mm\n"
                "capture:\n  axis:\n    point: [%.9g, %.9g, %.9g]\n    direction: [%.9g, %.9g, %.9g]\n",
                session_dir.c_str(), m.units == "mm" ? "millimetres" : "metres", fit.rms_angle_deg, fit.rms_tilt_deg,
                fit.rms_translation * r.mm_per_unit,
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
                      .add("rms_translation_m", fit.rms_translation * r.mm_per_unit / 1000)
                      .add("views", poses.size()));
  } else {
    std::printf("%s", buf);
    std::printf("%-5s %12s %10s %14s\n", "view", "angle deg", "tilt deg", "trans mm");
    for (std::size_t i = 0; i < fit.residuals.size(); ++i)
      std::printf("%-5zu %12.4f %10.4f %14.4f\n", used[i], fit.residuals[i].angle_deg, fit.residuals[i].tilt_deg,
                  fit.residuals[i].translation * r.mm_per_unit);
    if (!out.empty()) std::printf("written: %s\n", out.c_str());
  }
  // A view that could not be read or registered leaves the axis to the others: a
  // partial result, exit 3 as register's, with the views named.
  if (!r.failed_views.empty()) {
    std::string names;
    for (int v : r.failed_views)
      names += (names.empty() ? "" : ", ") + std::string("views[") + std::to_string(v) + "] (" +
               m.views[std::size_t(v)].file + ")";
    std::fprintf(stderr, "calibrate turntable: the axis is fitted to %zu of %zu views; not registered: %s\n",
                 poses.size(), m.views.size(), names.c_str());
    return 3;
  }
  return 0;
}

int cmd_calibrate_camera(const Common& c, const std::vector<std::string>& images, const std::string& board,
                         double square, const std::string& out) {
  if (!out.empty()) {
    check_output_name(out, "a profile fragment", {".yaml", ".yml"});
    check_output_path(out);
  }
  {
    std::vector<std::string> inputs = images;
    inputs.push_back(c.config);
    check_not_an_input({out}, inputs);
  }
  // The profile is read and checked as by every command (a missing or bad --config is
  // refused before any image is read; it used to be ignored), though no key of it
  // changes the calibration; its threads bound the worker threads.
  const StationConfig cfg = load_common(c);
  auto threads = limit_threads(cfg.threads);
  ChessboardSpec spec;
  spec.square = square;
  {
    // Two whole numbers and nothing else ("9x6x2" was read as 9x6, 2147483648 overflowed).
    const std::regex form("([0-9]{1,4})x([0-9]{1,4})");
    std::smatch m;
    if (!std::regex_match(board, m, form))
      throw UsageError("--board " + board + ": expected COLSxROWS inner corners, e.g. 9x6");
    spec.inner_cols = std::stoi(m[1]);
    spec.inner_rows = std::stoi(m[2]);
    if (spec.inner_cols < 3 || spec.inner_rows < 3)
      throw UsageError("--board " + board + ": the chessboard needs at least 3x3 inner corners");
  }
  if (!(square >= 1e-6 && square <= 100)) {
    char given[32];
    std::snprintf(given, sizeof given, "%g", square);
    throw UsageError(std::string("--square ") + given + ": the square's side in metres, 1e-6 to 100");
  }
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

void add_register_commands(CLI::App& app, std::vector<Command>& out) {
  struct State {
    RegisterArgs reg_args;
    Common c_reg, c_cal, c_cam;
    std::string cal_session, cal_out;
    std::vector<std::string> cam_images;
    std::string cam_board = "9x6", cam_out;
    double cam_square = 0.025;
  };
  auto s = std::make_shared<State>();
  auto& reg_args = s->reg_args;
  auto& c_reg = s->c_reg;
  auto& c_cal = s->c_cal;
  auto& c_cam = s->c_cam;
  auto& cal_session = s->cal_session;
  auto& cal_out = s->cal_out;
  auto& cam_images = s->cam_images;
  auto& cam_board = s->cam_board;
  auto& cam_out = s->cam_out;
  auto& cam_square = s->cam_square;
  auto* reg = app.add_subcommand("register", "Align the views of a session and merge them into one cloud");
  add_common(reg, c_reg);
  reg->add_option("session", reg_args.session, "session folder")->required();
  reg->add_option("-o,--out", reg_args.out, "merged cloud (.ply)")->required();
  reg->add_option("--poses-out", reg_args.poses_out, "write the refined poses and diagnostics (YAML: named .yaml or .yml)");
  add_profile_options(reg, "register", c_reg);


  auto* cal = app.add_subcommand("calibrate", "Calibrate bench devices: the camera (chessboard images) or the turntable axis (a session)");
  auto* cal_tt = cal->add_subcommand("turntable", "Fit the turntable axis to a registered session");
  cal->require_subcommand(1);
  add_common(cal_tt, c_cal);
  cal_tt->add_option("session", cal_session, "session folder (views with turntable angles)")->required();
  cal_tt->add_option("-o,--out", cal_out, "write the axis as a profile fragment (capture.axis)");
  auto* cal_cam = cal->add_subcommand("camera", "Intrinsics and lens distortion from chessboard images");
  add_common(cal_cam, c_cam);
  cal_cam->add_option("images", cam_images, "PNG/JPEG images of a chessboard, 3 or more")->required();
  cal_cam->add_option("--board", cam_board, "inner corners COLSxROWS")->capture_default_str();
  cal_cam->add_option("--square", cam_square, "square side, metres")->capture_default_str()->check(number_above(0));
  cal_cam->add_option("-o,--out", cam_out, "write the result as a profile fragment (scanner.options)");


  out.push_back({reg, [s] { return cmd_register(s->c_reg, s->reg_args); }});
  out.push_back({cal_tt, [s] { return cmd_calibrate_turntable(s->c_cal, s->cal_session, s->cal_out); }});
  out.push_back({cal_cam, [s] {
                   return cmd_calibrate_camera(s->c_cam, s->cam_images, s->cam_board, s->cam_square, s->cam_out);
                 }});
}

}  // namespace station::cli
