// Implicit surface + colour (issues 5 and 7): our MPU fit + mesh extraction +
// MPU colour function against Open3D 0.16's
// TriangleMesh::CreateFromPointCloudPoisson (with colours) on the same clouds
// with normals and colours, sampled on the textured YCB mustard bottle, whose
// mesh and texture are the reference surface and colour. Our grid resolution is
// chosen so that our mesh has about as many vertices as Poisson's. A synthetic
// sphere painted in two colours with a sharp boundary gives the width of the
// colour transition on each side's mesh.
#include <omp.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <chrono>
#include <cmath>
#include <memory>
#include <random>
#include <tuple>

#include <open3d/geometry/PointCloud.h>
#include <open3d/geometry/TriangleMesh.h>

#include "core/io.h"
#include "core/texture.h"
#include "harness.h"
#include "open3d_convert.h"
#include "sampling.h"
#include "reconstruct/colour_edges.h"
#include "reconstruct/colour_function.h"
#include "reconstruct/dmc.h"
#include "eval/eval.h"
#include "reconstruct/marching_cubes.h"
#include "reconstruct/mesh_clean.h"
#include "reconstruct/mpu.h"
#include "reconstruct/surface.h"

namespace station::bench {

namespace {

// Three significant digits (colour errors span 1e-8 .. 1e-1).
std::string significant(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.3g", v);
  return buf;
}

using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

/// What `station reconstruct` does (station/cli.cpp): MPU with epsilon0 from the
/// cloud's noise, sparse MC or DMC, small pieces removed, MPU colour function on the
/// vertices (k-NN colours where the surface is untrusted).
struct OurPipeline {
  int resolution = 128;
  bool dmc = false;
  int threads = 0;
  bool colour = true;
  bool colour_edges = true;  ///< sharpen_colour_edges after colouring (the station's default)
  // Filled by run():
  Mesh mesh;
  double seconds_fit = 0, seconds_extract = 0, seconds_colour = 0, cell_size = 0;
  std::size_t leaves = 0;
  std::array<std::size_t, 2> colour_cells{};
  std::size_t colour_edges_split = 0;

  void run(const Cloud& cloud) {
    auto t0 = Clock::now();
    MpuParams mp;
    mp.epsilon0 = std::max(mp.epsilon0, suggest_epsilon0(cloud));
    mp.threads = threads;
    const MpuSurface surface = fit_mpu(cloud, mp);
    seconds_fit = seconds_since(t0);
    leaves = surface.diagnostics().leaves;
    t0 = Clock::now();
    MarchingCubesOptions mo;
    mo.threads = threads;
    if (dmc) {
      DmcOptions d;
      static_cast<MarchingCubesOptions&>(d) = mo;
      DmcStats stats;
      mesh = extract_dmc(surface, resolution, d, &stats);
      cell_size = stats.cell_size;
    } else {
      MarchingCubesStats stats;
      mesh = extract_marching_cubes(surface, resolution, mo, &stats);
      cell_size = stats.cell_size;
    }
    remove_small_components(mesh, 0.01);
    seconds_extract = seconds_since(t0);
    seconds_colour = 0;
    if (!colour) return;
    t0 = Clock::now();
    ColourParams cp;
    cp.threads = threads;
    cp.compute_e_col = false;  // e_col is measured against the reference below, for both sides
    const ColourFunction cf = fit_colour(cloud, cp);
    colour_mesh(mesh, cf, surface, cloud, threads);
    if (colour_edges) {
      ColourEdgeParams ep;
      ep.threads = threads;
      colour_edges_split = sharpen_colour_edges(mesh, cf, ep).split_edges;
    }
    colour_cells = cf.diagnostics().leaves_by_type;
    seconds_colour = seconds_since(t0);
  }
};

struct PoissonRun {
  int depth = 8;
  int threads = 0;
  Mesh mesh;
  void run(const open3d::geometry::PointCloud& pcd) {
    auto [m, densities] = open3d::geometry::TriangleMesh::CreateFromPointCloudPoisson(
        pcd, std::size_t(depth), 0.0f, 1.1f, false, threads);
    mesh = from_open3d(*m);
  }
};

std::string mm(double metres) { return format_fixed(metres * 1000.0, 3) + " mm"; }
std::string pct(double x) { return format_fixed(100.0 * x, 3) + " %"; }

/// Our resolution giving about `target_vertices` vertices, from one probe
/// extraction (MC) at `probe` cells: the vertex count grows as resolution^2.
int matched_resolution(const Cloud& cloud, int threads, std::size_t target_vertices, int probe) {
  OurPipeline p;
  p.resolution = probe;
  p.threads = threads;
  p.colour = false;
  p.run(cloud);
  const double scale = std::sqrt(double(target_vertices) / double(std::max<std::size_t>(1, p.mesh.vertices.size())));
  return std::max(16, int(std::lround(probe * scale)));
}

/// Transition across the sharp two-colour boundary, the plane n.x = offset on the
/// sphere (measure_colour_transition, reconstruct/eval.h).
using Transition = ColourTransition;
Transition measure_transition(const Mesh& mesh, const Vec3d& n, double offset, const Rgb& a, const Rgb& b,
                              double h) {
  return measure_colour_transition(mesh, [&](const Vec3d& x) { return n.dot(x) - offset; }, a, b, h);
}

std::string describe(const Transition& t, double h, double diagonal) {
  return "band (0.1 < t < 0.9) " + std::to_string(t.band) + " of " + std::to_string(t.vertices) +
         " vertices, width (2 x p95 |s|) " + mm(t.width) + " = " + format_fixed(t.width / h, 2) + " cells = " +
         pct(t.width / diagonal) + " of the diagonal (max |s| in band " + format_fixed(t.max_band / h, 2) +
         " cells); wrong side: " + std::to_string(t.wrong) + " vertices (" +
         format_fixed(100.0 * double(t.wrong) / double(std::max<std::size_t>(1, t.vertices)), 3) + " %), " +
         std::to_string(t.wrong_far) + " more than one cell away (max " + format_fixed(t.max_wrong / h, 2) +
         " cells)";
}

}  // namespace

void run_surface_cases(const Options& options, Report& report) {
  const int threads = options.threads;
  // ---- reference: the textured YCB mustard bottle ------------------------------
  bool shared = false;
  const fs::path obj = mustard_obj(options, &shared);
  const TexturedMesh reference = read_textured_mesh(obj);
  const Texture texture = load_texture(reference.texture);
  const double diagonal = bounding_box(reference.mesh.vertices).diagonal();
  report.note(std::string("surface: reference ") + (shared ? "../shared/data/textured_objects/006_mustard_bottle" :
              "data/mustard_bottle (../shared/data missing or --generate: the bundled copy of the same YCB model)") +
              "/textured.obj (" + std::to_string(reference.mesh.faces.size()) + " triangles, " +
              std::to_string(texture.width) + "^2 texture, diagonal " + mm(diagonal) +
              "); clouds: area-uniform samples with interpolated vertex normals and texture colours, no noise");

  EvalParams eval;
  eval.threads = threads;
  eval.b_surface_colour = [&](int f, double u, double v) { return surface_colour(reference, texture, f, u, v); };
  // Two colour errors: against the texture (B = the reference mesh's samples, which
  // hold print finer than any input sampling) and the paper's e_col (methods.md): at
  // every input point, the mesh's colour at its closest point against the point's own.
  auto quality = [&](const Mesh& mesh, const Cloud& input) {
    const EvalResult r = evaluate(mesh, reference.mesh, eval);
    EvalParams at_input;
    at_input.threads = threads;
    const EvalResult ri = evaluate(mesh, input, at_input);
    return "mean distance to the reference " + mm(r.a_to_b.mean) + " (" + pct(r.a_to_b.mean / diagonal) +
           " of the diagonal), Chamfer " + mm(r.chamfer) + ", e_col against the texture " +
           (r.colour_error ? format_fixed(*r.colour_error, 4) : std::string("-")) + ", at the input points " +
           (ri.colour_error ? significant(*ri.colour_error) : std::string("-"));
  };

  // ---- the mustard rows: 100k at depth 8, 1M at depth 10 ------------------------
  struct Case {
    int points;
    int depth;
    int probe;
    bool reduced;  ///< fewer runs (each takes tens of seconds)
  };
  const std::vector<Case> cases = {{100000, 8, 128, false}, {1000000, 10, 256, true}};
  for (const Case& c : cases) {
    if (options.max_points > 0 && std::size_t(c.points) > options.max_points) {
      report.note("surface: mustard " + std::to_string(c.points / 1000) + "k skipped (--max-points)");
      continue;
    }
    const Cloud cloud = sample_textured(reference, texture, c.points, 7);
    const open3d::geometry::PointCloud pcd = to_open3d(cloud);
    const std::string label = "mustard " + std::to_string(c.points / 1000) + "k";
    Options opt = options;
    if (c.reduced) {
      opt.warmup = 0;
      opt.repetitions = std::min(options.repetitions, 2);
    } else {
      opt.repetitions = std::min(options.repetitions, 3);
    }
    // Poisson first: its vertex count sets our resolution (this run is also the warm-up).
    PoissonRun poisson;
    poisson.depth = c.depth;
    poisson.threads = threads;
    auto t0 = Clock::now();
    poisson.run(pcd);
    const double poisson_first_s = seconds_since(t0);
    const int resolution = matched_resolution(cloud, threads, poisson.mesh.vertices.size(), c.probe);

    OurPipeline ours;
    ours.resolution = resolution;
    ours.threads = threads;
    Row row{label + ": MPU + MC " + std::to_string(resolution) + " + colour",
            "TriangleMesh::CreateFromPointCloudPoisson depth " + std::to_string(c.depth) + " (colours)"};
    std::tie(row.ours, row.theirs) =
        measure_pair(opt, [&] { ours.run(cloud); }, [&] { poisson.run(pcd); });
    report.rows.push_back(row);
    const double poisson_cell = 1.1 * (bounding_box(cloud.points).max - bounding_box(cloud.points).min).maxCoeff() /
                                double(1 << c.depth);
    report.note(label + " (" + std::to_string(opt.repetitions) + " timed runs" +
                (c.reduced ? ", no warm-up" : "") + "): ours MPU fit " + format_fixed(ours.seconds_fit, 2) +
                " s (" + std::to_string(ours.leaves) + " leaves) + MC " + format_fixed(ours.seconds_extract, 2) +
                " s (cell " + mm(ours.cell_size) + ") + colour function " + format_fixed(ours.seconds_colour, 2) +
                " s (" + std::to_string(ours.colour_cells[0]) + " A / " + std::to_string(ours.colour_cells[1]) +
                " B cells, " + std::to_string(ours.colour_edges_split) + " edges split at colour boundaries), " +
                std::to_string(ours.mesh.vertices.size()) + " vertices; " + quality(ours.mesh, cloud));
    report.note(label + ": Poisson depth " + std::to_string(c.depth) + " (cell " + mm(poisson_cell) + ", first run " +
                format_fixed(poisson_first_s, 2) + " s), " + std::to_string(poisson.mesh.vertices.size()) +
                " vertices; " + quality(poisson.mesh, cloud));

    {
      // Issue 5's comparison: geometry only, our fit + extraction against Poisson on the
      // same cloud without colours (one run at 1M).
      OurPipeline g = ours;
      g.colour = false;
      open3d::geometry::PointCloud plain = pcd;
      plain.colors_.clear();
      PoissonRun pg = poisson;
      Options gopt = opt;
      if (c.reduced) gopt.repetitions = 1;
      Row grow{label + ": MPU + MC " + std::to_string(resolution) + ", no colour",
               "TriangleMesh::CreateFromPointCloudPoisson depth " + std::to_string(c.depth) + " (no colours)"};
      std::tie(grow.ours, grow.theirs) = measure_pair(gopt, [&] { g.run(cloud); }, [&] { pg.run(plain); });
      report.rows.push_back(grow);
      report.note(label + ", no colour (" + std::to_string(gopt.repetitions) + " timed runs): ours fit " +
                  format_fixed(g.seconds_fit, 2) + " s + MC " + format_fixed(g.seconds_extract, 2) + " s, " +
                  std::to_string(g.mesh.vertices.size()) + " vertices; Poisson " +
                  std::to_string(pg.mesh.vertices.size()) + " vertices");
    }

    {
      // Issue 27: the station's default surface stage as `station reconstruct` and
      // `station run` compose it (reconstruct_surface with SurfaceParams' defaults: MPU,
      // hole auto with the winding-number closing, DMC at the automatic resolution,
      // small pieces dropped, the colour function, colour-edge splits), against the
      // coloured Poisson runs of the first row (the same runs).
      SurfaceParams sp;
      sp.threads = threads;
      SurfaceResult def;
      Row drow{label + ": default surface stage (MPU + closing + DMC auto + colour)",
               row.anchor + " (same runs as the first row)"};
      drow.ours = measure(opt, [&] { def = reconstruct_surface(cloud, sp); });
      drow.theirs = row.theirs;
      report.rows.push_back(drow);
      const SurfaceTimings& t = def.seconds;
      report.note(label + ", default surface stage: resolution " + std::to_string(def.resolution) + " (cell " +
                  mm(def.extraction.cell_size) + ", " + (def.resolution_auto ? "auto" : "given") + "), hole " +
                  (def.hole == HoleMode::kClose ? "closed" : "kept") + "; fit " + format_fixed(t.fit, 2) +
                  " s + closing " + format_fixed(t.closing, 2) + " s + DMC " + format_fixed(t.extract, 2) +
                  " s + colour " + format_fixed(t.colour, 2) + " s (of which e_col " +
                  format_fixed(def.colour ? def.colour->e_col_seconds : 0.0, 2) + " s), " +
                  std::to_string(def.mesh.vertices.size()) + " vertices; " + quality(def.mesh, cloud));
    }

    if (!c.reduced) {
      // The same with Deformed Marching Cubes (the station's default extractor); the
      // anchor column repeats the Poisson timing of the row above.
      OurPipeline d = ours;
      d.dmc = true;
      Row drow{label + ": MPU + DMC " + std::to_string(resolution) + " + colour", row.anchor + " (same runs as above)"};
      drow.ours = measure(opt, [&] { d.run(cloud); });
      drow.theirs = row.theirs;
      report.rows.push_back(drow);
      report.note(label + " with DMC: fit " + format_fixed(d.seconds_fit, 2) + " s + DMC " +
                  format_fixed(d.seconds_extract, 2) + " s + colour " + format_fixed(d.seconds_colour, 2) + " s, " +
                  std::to_string(d.mesh.vertices.size()) + " vertices; " + quality(d.mesh, cloud));
    }
  }

  // ---- colour transition: a sphere painted in two colours ----------------------
  // 100k at depth 8 (DMC, the station's default extractor) and the 1M at
  // depth 10 (MC, one timed run: DMC at 1024 would dominate the group's time).
  struct SphereCase {
    int points;
    int depth;
    int probe;
    bool reduced;
  };
  const std::vector<SphereCase> sphere_cases = {{100000, 8, 128, false}, {1000000, 10, 256, true}};
  for (const SphereCase& c : sphere_cases) {
    if (options.max_points > 0 && std::size_t(c.points) > options.max_points) {
      report.note("surface: sphere " + std::to_string(c.points / 1000) + "k skipped (--max-points)");
      continue;
    }
    const double radius = 0.05;
    const Vec3d plane = Vec3d(0.3, 0.2, 1.0).normalized();  // not aligned with either grid
    const double offset = 0.004;
    const Rgb red{220, 30, 30}, blue{30, 40, 200};
    Cloud sphere;
    std::mt19937_64 rng(11);
    std::normal_distribution<double> gauss(0.0, 1.0);
    for (int i = 0; i < c.points; ++i) {
      Vec3d d(gauss(rng), gauss(rng), gauss(rng));
      d.normalize();
      const Vec3d p = radius * d;
      sphere.points.push_back(p.cast<float>());
      sphere.normals.push_back(d.cast<float>());
      sphere.colours.push_back(plane.dot(p) - offset > 0 ? blue : red);
    }
    const double sphere_diagonal = 2 * radius * std::sqrt(3.0);
    const open3d::geometry::PointCloud pcd = to_open3d(sphere);
    PoissonRun poisson;
    poisson.depth = c.depth;
    poisson.threads = threads;
    poisson.run(pcd);
    const int resolution = matched_resolution(sphere, threads, poisson.mesh.vertices.size(), c.probe);
    OurPipeline ours;
    ours.resolution = resolution;
    ours.threads = threads;
    ours.dmc = !c.reduced;
    Options opt = options;
    if (c.reduced) {
      opt.warmup = 0;
      opt.repetitions = 1;
    } else {
      opt.repetitions = std::min(options.repetitions, 3);
    }
    const std::string label = "sphere " + std::to_string(c.points / 1000) + "k";
    Row row{label + ", two colours: MPU + " + (ours.dmc ? "DMC " : "MC ") + std::to_string(resolution) + " + colour",
            "TriangleMesh::CreateFromPointCloudPoisson depth " + std::to_string(c.depth) + " (colours)"};
    std::tie(row.ours, row.theirs) = measure_pair(opt, [&] { ours.run(sphere); }, [&] { poisson.run(pcd); });
    report.rows.push_back(row);
    const double poisson_cell = 1.1 * 2 * radius / double(1 << c.depth);
    const Transition t_ours = measure_transition(ours.mesh, plane, offset, red, blue, ours.cell_size);
    const Transition t_poisson = measure_transition(poisson.mesh, plane, offset, red, blue, poisson_cell);
    EvalParams at_input;
    at_input.threads = threads;
    auto e_col = [&](const Mesh& mesh) {
      const EvalResult r = evaluate(mesh, sphere, at_input);
      return r.colour_error ? significant(*r.colour_error) : std::string("-");
    };
    report.note(label + ": r = 5 cm, " + std::to_string(c.points / 1000) +
                "k points, exact normals, red / blue split by a tilted plane (sharp): colour coordinate t of a "
                "vertex = its colour projected on red -> blue, s = its distance to the plane");
    report.note(label + ", ours (" + (ours.dmc ? "DMC " : "MC ") + std::to_string(resolution) + ", cell " +
                mm(ours.cell_size) + ", " + std::to_string(ours.colour_cells[1]) +
                " Type B cells, " + std::to_string(ours.colour_edges_split) +
                " edges split at the boundary, e_col at the input points " + e_col(ours.mesh) + "): " +
                describe(t_ours, ours.cell_size, sphere_diagonal));
    report.note(label + ", Poisson depth " + std::to_string(c.depth) + " (cell " + mm(poisson_cell) +
                ", e_col at the input points " + e_col(poisson.mesh) + "): " +
                describe(t_poisson, poisson_cell, sphere_diagonal));
  }
}

static const bool registered =
    register_group("surface", "MPU + colour + MC/DMC vs Open3D Poisson (issues 5, 7)", &run_surface_cases);

}  // namespace station::bench
