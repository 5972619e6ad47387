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

#include "core/error.h"
#include "core/io.h"
#include "core/texture.h"
#include "core/threads.h"
#include "eval/consolidation_metrics.h"
#include "eval/eval.h"
#include "reconstruct/sdm.h"
#include "registration/registration.h"
#include "station/config.h"
#include "station/json.h"

namespace station::cli {

namespace {

/// The most --samples eval takes (memory: see its option).
constexpr long long kMaxEvalSamples = 20000000;

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
  std::function<Rgb(int, double, double)> surface_colour() const {
    if (texture.empty() || textured.corner_uv.empty()) return {};
    return [this](int f, double u, double v) { return station::surface_colour(textured, texture, f, u, v); };
  }
};

void read_eval_input(const fs::path& p, EvalInput& in) {
  in.textured = read_textured_mesh(p);
  if (!in.textured.material_problem.empty())
    std::fprintf(stderr, "warning: %s: %s\n", p.c_str(), in.textured.material_problem.c_str());
  in.is_mesh = !in.textured.mesh.faces.empty();
  if (in.is_mesh && !in.textured.texture.empty() && !in.textured.corner_uv.empty())
    in.texture = load_texture(in.textured.texture);
}

std::string stats_json(const DirectedStats& s, JsonObject& j) {
  j.add("mean", s.mean).add("rms", s.rms).add("p95", s.p95).add("max", s.max).add("count", s.count);
  return j.str();
}

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
  // B's fault, said as B's (uniformity's own "area must be > 0" was blamed on A).
  if (!(m.area > 0) || !std::isfinite(m.area))
    throw InvalidInput("B: the reference mesh has zero or non-finite area (no surface to measure against)");
  m.accuracy = mean_distance_to_mesh(pts, ref, threads);
  m.uniformity = uniformity(pts, m.area);
  m.surface_uniformity = surface_uniformity(pts, ref, threads);
  m.sharp_edges = sharp_edges(ref, args.edge_angle).size();
  if (args.edge_radius > 0) m.edge = edge_error(pts, ref, args.edge_radius, args.edge_angle, threads);
  return m;
}

}  // namespace

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
  params.a_surface_colour = ia.surface_colour();
  params.b_surface_colour = ib.surface_colour();
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
    if (r.colour_error) j.add("color_error", *r.colour_error); else j.add_null("color_error");
    if (pm) {
      JsonObject p;
      p.add("points", pm->points).add("accuracy", pm->accuracy).add("uniformity", pm->surface_uniformity)
          .add("uniformity_3d", pm->uniformity).add("reference_area", pm->area)
          .add("sharp_edges", pm->sharp_edges).add("edge_angle_deg", pm_args.edge_angle);
      if (pm->edge) {
        // No point near a sharp edge (or no sharp edge): nothing was measured, not 0.
        p.add("edge_radius", pm_args.edge_radius);
        if (pm->edge->count > 0) p.add("edge_error", pm->edge->mean);
        else p.add_null("edge_error");
        p.add("edge_points", pm->edge->count);
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
    if (r.colour_error) std::printf("colour error e_col %.6g\n", *r.colour_error);
    else std::printf("colour error: n/a (colours missing on one side)\n");
    if (pm) {
      std::printf("points metrics (%zu points of A against mesh B):\n", pm->points);
      std::printf("  accuracy (mean distance to B) %.6g\n", pm->accuracy);
      std::printf("  uniformity (on B's surface) %.4f, in 3-D %.4f (B's area %.6g)\n",
                  pm->surface_uniformity, pm->uniformity, pm->area);
      if (pm->edge && pm->edge->count == 0 && pm->sharp_edges == 0)
        std::printf("  edge error: n/a (B has no sharp edge > %g deg)\n", pm_args.edge_angle);
      else if (pm->edge && pm->edge->count == 0)
        std::printf("  edge error: n/a (no point of A within %.6g of %zu sharp edges > %g deg)\n", pm_args.edge_radius,
                    pm->sharp_edges, pm_args.edge_angle);
      else if (pm->edge)
        std::printf("  edge error (within %.6g of %zu sharp edges > %g deg) %.6g over %zu points\n",
                    pm_args.edge_radius, pm->sharp_edges, pm_args.edge_angle, pm->edge->mean, pm->edge->count);
      else
        std::printf("  edge error: n/a (give --edge-radius, e.g. 2h; %zu sharp edges > %g deg)\n",
                    pm->sharp_edges, pm_args.edge_angle);
    }
  }
  return 0;
}

void add_eval_commands(CLI::App& app, std::vector<Command>& out) {
  struct State {
    Common c_eval;
    std::string eval_a, eval_b;
    int eval_samples = 200000;
    unsigned eval_seed = 1;
    PointsMetricsArgs eval_pm;
  };
  auto s = std::make_shared<State>();
  auto& c_eval = s->c_eval;
  auto& eval_a = s->eval_a;
  auto& eval_b = s->eval_b;
  auto& eval_samples = s->eval_samples;
  auto& eval_seed = s->eval_seed;
  auto& eval_pm = s->eval_pm;
  auto* eval = app.add_subcommand("eval", "Distances and colour error between two clouds or meshes");
  add_common(eval, c_eval);
  eval->add_option("a", eval_a, "result (cloud or mesh: .ply .pcd .obj .off)")->required();
  eval->add_option("b", eval_b, "reference (cloud or mesh)")->required();
  // Each sample holds a position, a normal and a colour (36 bytes) for both meshes at
  // once, and 16 bytes more while its distance is measured: about 90 bytes per --samples,
  // 1.8 GB at 20 M (100 x the default). The earlier cap, 100 M, needed about 9 GB for
  // the samples alone and ran out of memory with no word of the option.
  eval->add_option("--samples", eval_samples, "points sampled on each mesh (1..20,000,000)")
      ->capture_default_str()
      ->check(whole_number(1, kMaxEvalSamples));
  eval->add_option("--seed", eval_seed, "sampling seed")->capture_default_str()->check(whole_number(0, 4294967295LL));  // an unsigned seed, as before
  eval->add_flag("--points-metrics", eval_pm.enabled,
                 "also the consolidation metrics of A's points (a cloud's points, a mesh's vertices) "
                 "against mesh B: accuracy (mean distance to B), uniformity (Schloemer's normalised "
                 "mean nearest-neighbour distance, on B's surface and in 3-D) and, with --edge-radius, "
                 "edge error");
  eval->add_option("--edge-radius", eval_pm.edge_radius,
                   "edge error: mean distance to B of A's points within this distance of a sharp edge "
                   "of B (e.g. 2h of the consolidation; implies --points-metrics)")
      ->check(number_above(0));
  eval->add_option("--edge-angle", eval_pm.edge_angle,
                   "an edge of B is sharp when its faces' normals differ by more than this (degrees)")
      ->capture_default_str()->check(number_in(0.0, 180.0));


  out.push_back({eval, [s] {
                   if (s->eval_pm.edge_radius > 0) s->eval_pm.enabled = true;
                   // A's points are what the metrics measure: a complaint without a role names A.
                   return naming_the_file(
                       s->eval_a, s->eval_b,
                       [&] { return cmd_eval(s->c_eval, s->eval_a, s->eval_b, s->eval_samples, s->eval_seed, s->eval_pm); },
                       {{"A:", s->eval_a}, {"B:", s->eval_b}});
                 }});
}

}  // namespace station::cli
