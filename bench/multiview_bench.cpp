// Real multi-view scans (issue 32): the Stanford dragon session registered by
// register_views with the profile's parameters (config/default.yaml), then the
// station's own surface stage (the profile's consolidation and reconstruct_surface,
// closed and with holes kept) against Open3D 0.16's Poisson on the same merged
// cloud with its normals, closed and density-trimmed (the 5 % of vertices of
// lowest density removed), at the depth whose vertex count is nearest ours and
// at depth 9. Distances against the merged scans, as `station eval MESH merged.ply`.
#include <omp.h>
#include <open3d/geometry/PointCloud.h>
#include <open3d/geometry/TriangleMesh.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "capture/capture.h"
#include "dragon_session.h"
#include "eval/eval.h"
#include "harness.h"
#include "open3d_convert.h"
#include "reconstruct/surface.h"
#include "reconstruct/wlop.h"
#include "registration/registration.h"
#include "station/config.h"
#include "station/params.h"

namespace station::bench {

namespace {

using Clock = std::chrono::steady_clock;

std::string mm(double metres) { return format_fixed(metres * 1000.0, 2); }

struct PoissonRun {
  int depth = 9;
  int threads = 0;
  bool trim = false;  // remove the 5 % of vertices of lowest density
  Mesh mesh;
  void run(const open3d::geometry::PointCloud& pcd) {
    auto [m, density] = open3d::geometry::TriangleMesh::CreateFromPointCloudPoisson(
        pcd, std::size_t(depth), 0.0f, 1.1f, false, threads);
    if (trim && !density.empty()) {
      std::vector<double> sorted = density;
      const std::size_t k = sorted.size() / 20;
      std::nth_element(sorted.begin(), sorted.begin() + long(k), sorted.end());
      const double cut = sorted[k];
      std::vector<bool> drop(density.size());
      for (std::size_t i = 0; i < density.size(); ++i) drop[i] = density[i] < cut;
      m->RemoveVerticesByMask(drop);
    }
    mesh = from_open3d(*m);
  }
};

std::string quality(const Mesh& mesh, const Cloud& scans, int threads) {
  EvalParams ep;
  ep.threads = threads;
  const EvalResult r = evaluate(mesh, scans, ep);
  return std::to_string(mesh.vertices.size()) + " vertices; mesh -> scans mean / p95 / max " +
         mm(r.a_to_b.mean) + " / " + mm(r.a_to_b.p95) + " / " + mm(r.a_to_b.max) +
         " mm, scans -> mesh mean " + format_fixed(r.b_to_a.mean * 1000.0, 4) + " mm";
}

// Ours (the profile's consolidation, then the surface stage in each of `modes`: closed
// or with holes kept) against Poisson on the same merged cloud, with the held-out
// halves at Poisson depth 9's vertex count. `label` starts every row and note.
void compare_with_poisson(const std::string& label, const Cloud& merged, const std::optional<Vec3d>& up,
                          const std::vector<bool>& modes, const StationConfig& cfg, const Options& options,
                          Report& report) {
  const int threads = options.threads;
  // Ours: the profile's consolidation, then the surface stage (closed, kept).
  WlopParams wp = wlop_params(cfg.pipeline, threads);
  auto t0 = Clock::now();
  const WlopResult consolidated = consolidate(merged, wp);
  const double consolidate_s = std::chrono::duration<double>(Clock::now() - t0).count();
  const open3d::geometry::PointCloud pcd = to_open3d(merged);
  Options opt = options;
  opt.repetitions = std::min(options.repetitions, 3);
  // The merged scans split by index parity, and the even half consolidated (made once).
  struct Halves {
    Cloud even, odd, consolidated;
  };
  std::optional<Halves> half;
  for (const bool closed : modes) {
    SurfaceParams sp = surface_params(cfg.pipeline, threads);
    // The run's default: the mesh onto local fits of the merged scans where a
    // held-out half of them says so (reconstruct.snap_to_scans).
    if (cfg.pipeline.reconstruct.snap_to_scans) sp.scans = &merged;
    sp.hole = closed ? HoleMode::kClose : HoleMode::kKeep;
    if (closed && cfg.pipeline.reconstruct.table_plane) sp.table_up = up;
    SurfaceResult ours;
    auto run_ours = [&] { ours = reconstruct_surface(consolidated.cloud, sp); };
    run_ours();
    // Poisson at the depth whose vertex count is nearest ours, and at depth 9.
    int matched = 6;
    std::size_t best = std::size_t(-1);
    for (int depth = 6; depth <= 9; ++depth) {
      PoissonRun probe;
      probe.depth = depth;
      probe.threads = threads;
      probe.trim = !closed;
      probe.run(pcd);
      const std::size_t gap =
          std::size_t(std::llabs(static_cast<long long>(probe.mesh.vertices.size()) -
                                 static_cast<long long>(ours.mesh.vertices.size())));
      if (gap < best) best = gap, matched = depth;
    }
    const std::string mode = closed ? "closed" : "holes kept / trimmed 5 %";
    const std::vector<int> depths =
        matched == 9 ? std::vector<int>{9} : std::vector<int>{matched, 9};
    for (const int depth : depths) {
      PoissonRun poisson;
      poisson.depth = depth;
      poisson.threads = threads;
      poisson.trim = !closed;
      Row row{label + " session, " + mode + ": surface stage (" + std::to_string(ours.resolution) +
                  " cells)",
              "CreateFromPointCloudPoisson depth " + std::to_string(depth) +
                  (closed ? "" : " + density trim")};
      std::tie(row.ours, row.theirs) = measure_pair(opt, run_ours, [&] { poisson.run(pcd); });
      report.rows.push_back(row);
      if (depth == depths.front())
        report.note(label + " " + mode + ": ours (consolidation " + format_fixed(consolidate_s, 2) + " s to " +
                    std::to_string(consolidated.cloud.size()) + " points, not in the rows; cell " +
                    mm(ours.extraction.cell_size) + " mm) " + quality(ours.mesh, merged, threads));
      report.note(label + " " + mode + ": Poisson depth " + std::to_string(depth) +
                  " on the merged cloud " + quality(poisson.mesh, merged, threads));
      if (depth != 9 || poisson.mesh.vertices.empty() || ours.mesh.vertices.empty()) continue;
      // Matched vertex count (issue 32's targets): ours again at the
      // resolution whose mesh has about Poisson depth 9's vertices (the count
      // grows with the square of the resolution; one correction step).
      SurfaceParams matched_sp = sp;
      SurfaceResult at;
      const auto resolution_for = [](const SurfaceResult& r, std::size_t want) {
        return int(std::lround(r.resolution * std::sqrt(double(want) / double(r.mesh.vertices.size()))));
      };
      matched_sp.resolution = resolution_for(ours, poisson.mesh.vertices.size());
      at = reconstruct_surface(consolidated.cloud, matched_sp);
      if (at.mesh.vertices.empty()) continue;
      matched_sp.resolution = resolution_for(at, poisson.mesh.vertices.size());
      auto run_matched = [&] { at = reconstruct_surface(consolidated.cloud, matched_sp); };
      Row mrow{label + " session, " + mode + ": surface stage at Poisson's vertex count (" +
                   std::to_string(matched_sp.resolution) + " cells)",
               "CreateFromPointCloudPoisson depth 9" + std::string(closed ? "" : " + density trim")};
      std::tie(mrow.ours, mrow.theirs) = measure_pair(opt, run_matched, [&] { poisson.run(pcd); });
      report.rows.push_back(mrow);
      report.note(label + " " + mode + ": ours at " + std::to_string(matched_sp.resolution) + " cells (cell " +
                  mm(at.extraction.cell_size) + " mm) " + quality(at.mesh, merged, threads));
      // The same without the snap to the scans, for comparison.
      {
        SurfaceParams plain_sp = matched_sp;
        plain_sp.scans = nullptr;
        SurfaceResult pl;
        Row prow{label + " session, " + mode + ": at Poisson's vertex count, without the snap to the scans",
                 mrow.anchor + " (same runs as above)"};
        prow.ours = measure(opt, [&] { pl = reconstruct_surface(consolidated.cloud, plain_sp); });
        prow.theirs = mrow.theirs;
        report.rows.push_back(prow);
        report.note(label + " " + mode + ": ours at " + std::to_string(plain_sp.resolution) +
                    " cells without the snap " + quality(pl.mesh, merged, threads));
      }
      // Held out: ours and Poisson from the even half of the merged scans,
      // measured against the odd half, which neither saw. Against the scans they
      // were fitted to, a surface is rewarded for following their noise. (With
      // holes kept since 2026-12-06: the kept mesh's rims and pieces follow the
      // scans it is given, so the half it did not see is the fair measure.)
      {
        if (!half) {
          half.emplace();
          for (std::size_t i = 0; i < merged.size(); ++i) {
            Cloud& to = i % 2 ? half->odd : half->even;
            to.points.push_back(merged.points[i]);
            to.normals.push_back(merged.normals[i]);
          }
          half->consolidated = consolidate(half->even, wp).cloud;
        }
        const std::string held = label + (closed ? " held out" : " held out, holes kept / trimmed 5 %");
        for (const bool snap : {true, false}) {
          SurfaceParams hsp = matched_sp;
          hsp.scans = snap ? &half->even : nullptr;
          const SurfaceResult h = reconstruct_surface(half->consolidated, hsp);
          report.note(held + ": ours from the even half (" + std::to_string(half->consolidated.size()) +
                      " consolidated points, " + std::to_string(matched_sp.resolution) + " cells" +
                      (snap ? (h.snap_declined ? ", the snap declined" : ", snapped")
                            : ", without the snap") +
                      ") against the odd half: " + quality(h.mesh, half->odd, threads));
        }
        PoissonRun half_poisson;
        half_poisson.depth = 9;
        half_poisson.threads = threads;
        half_poisson.trim = !closed;
        half_poisson.run(to_open3d(half->even));
        report.note(held + ": Poisson depth 9 from the even half against the odd half: " +
                    quality(half_poisson.mesh, half->odd, threads));
      }
    }
  }
}

void run_multiview_cases(const Options& options, Report& report) {
  const DragonSession s = load_dragon(options);
  const StationConfig cfg = load_config(options.source_dir / "config" / "default.yaml");
  const RegistrationResult reg =
      register_views(s.clouds, s.manifest, registration_params(cfg.pipeline));
  const Cloud& merged = reg.merged;
  if (merged.empty() || !merged.has_normals())
    throw std::runtime_error("multiview: the dragon did not register");
  std::optional<Vec3d> up;
  if (reg.axis && !reg.poses.empty()) {
    std::size_t first = 0;  // the first registered view, as the run takes it
    while (first + 1 < reg.views.size() && !reg.views[first].registered) ++first;
    up = reg.poses[first].topLeftCorner<3, 3>() * reg.axis->direction;
  }
  report.note("multiview: " + s.where + ", " + std::to_string(s.clouds.size()) +
              " views registered by the profile (" + std::to_string(reg.failed_views.size()) +
              " failed), merged " + std::to_string(merged.size()) +
              " points with normals; distances in mm against the merged scans");
  compare_with_poisson("dragon", merged, up, {true, false}, cfg, options, report);
}

[[maybe_unused]] const bool registered = register_group(
    "multiview",
    "real multi-view session: surface stage vs Open3D Poisson on the same merged cloud (issue 32)",
    &run_multiview_cases);


// The three real Kinect frames of ../shared/data/rgbd_frames/pcl_kinect_sequence
// (640 x 480, depth in mm, fx = fy = 525, cx = 320, cy = 240), or the bundled
// half-resolution copies (tests/data/kinect_frames) when that is missing: a
// hand-held sensor's views of a laptop and a box on a carpet, no poses, no angles.
struct KinectSession {
  std::vector<Cloud> clouds;
  SessionManifest manifest;
  std::string where;
};

KinectSession load_kinect(const Options& options) {
  KinectSession s;
  const fs::path shared = options.shared_dir / "rgbd_frames" / "pcl_kinect_sequence";
  std::vector<std::pair<std::string, std::string>> files;  // depth, colour
  double scale = 1;
  if (options.use_shared && fs::exists(shared)) {
    for (const char* t : {"20121214T142255.814212", "20121214T142256.068683", "20121214T142256.332395"})
      files.emplace_back((shared / (std::string("frame_") + t + "_depth.tiff")).string(),
                         (shared / (std::string("frame_") + t + "_rgb.tiff")).string());
    s.where = "../shared/data/rgbd_frames/pcl_kinect_sequence (3 frames, 640 x 480)";
  } else {
    const fs::path dir = options.source_dir / "tests" / "data" / "kinect_frames";
    for (int k = 0; k < 3; ++k)
      files.emplace_back((dir / ("frame" + std::to_string(k) + "_depth.png")).string(),
                         (dir / ("frame" + std::to_string(k) + "_rgb.png")).string());
    scale = 0.5;
    s.where = "tests/data/kinect_frames (bundled: 3 frames at 320 x 240; ../shared missing)";
  }
  s.manifest.scanner = "import";
  Intrinsics in;
  in.fx = in.fy = 525 * scale;
  in.cx = 320 * scale;
  in.cy = 240 * scale;
  for (const auto& [depth_file, colour_file] : files) {
    const Frame f = read_rgbd_frame(depth_file, colour_file, in);
    s.clouds.push_back(frame_to_cloud(f));
    ViewRecord view;
    view.file = fs::path(depth_file).filename().string();
    s.manifest.views.push_back(view);
  }
  return s;
}

// The Kinect frames registered by the profile (no angles), then compared as the
// dragon is, with holes kept: a one-sided scene, which `hole: auto` leaves open.
void run_multiview_kinect_cases(const Options& options, Report& report) {
  const KinectSession s = load_kinect(options);
  const StationConfig cfg = load_config(options.source_dir / "config" / "default.yaml");
  const RegistrationResult reg = register_views(s.clouds, s.manifest, registration_params(cfg.pipeline));
  if (reg.merged.empty() || !reg.merged.has_normals())
    throw std::runtime_error("multiview: the Kinect frames did not register");
  report.note("multiview kinect: " + s.where + ", registered by the profile without angles (" +
              std::to_string(reg.failed_views.size()) + " failed), merged " + std::to_string(reg.merged.size()) +
              " points with normals; distances in mm against the merged scans");
  compare_with_poisson("kinect", reg.merged, std::nullopt, {false}, cfg, options, report);
}

[[maybe_unused]] const bool registered_kinect = register_group(
    "multiview_kinect",
    "real multi-view Kinect frames (a one-sided scene): surface stage vs Open3D Poisson, holes kept (issue 32)",
    &run_multiview_kinect_cases);

}  // namespace

}  // namespace station::bench
