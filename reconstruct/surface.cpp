#include "reconstruct/surface.h"

#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <memory>

#include "core/error.h"
#include "core/kdtree.h"
#include "core/normals.h"
#include "core/threads.h"
#include "reconstruct/colour_transfer.h"
#include "reconstruct/colour_edges.h"
#include "reconstruct/half_space_clip.h"
#include "reconstruct/scan_snap.h"
#include "reconstruct/winding_close.h"

namespace station {

namespace {

using Clock = std::chrono::steady_clock;

std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

// One flag per vertex of `mesh`: far(vertex), in parallel over `threads`.
template <class Far>
std::vector<char> far_from(const Mesh& mesh, int threads, const Far& far) {
  std::vector<char> flags(mesh.vertices.size(), 0);
  tbb::task_arena(worker_threads(threads)).execute([&] {
    tbb::parallel_for(std::size_t(0), mesh.vertices.size(),
                      [&](std::size_t v) { flags[v] = far(mesh.vertices[v]) ? 1 : 0; });
  });
  return flags;
}

}  // namespace

const char* extractor_label(Extractor extractor) {
  return extractor == Extractor::kDmc ? "Deformed Marching Cubes" : "marching cubes";
}

std::string surface_note(const std::string& input, const std::string& line, const std::string& prefix,
                         const std::string& note_prefix) {
  if (line.rfind("no normals", 0) == 0) return note_prefix + input + " has " + line;
  if (line.rfind("the cloud has", 0) == 0) return note_prefix + input + line.substr(9);
  return prefix + line;
}

ColourParams colour_params(const SurfaceParams& p) {
  ColourParams cp;
  cp.threads = p.threads;
  cp.multi_colour = p.colour_multi;
  cp.noise_robust = p.colour_noise_robust;
  cp.e_col_max_points = kEColPoints;
  return cp;
}

double surface_epsilon0(const Cloud& cloud) {
  constexpr std::size_t kNeeded = 50;  // suggest_epsilon0's default k
  const std::size_t n = cloud.size();
  if (n < kNeeded)
    throw InvalidInput(std::to_string(n) + (n == 1 ? " point" : " points") +
                       ": too few to reconstruct a surface from (at least " + std::to_string(kNeeded) + " are needed)");
  if (all_finite(cloud.points)) {
    const Aabb box = bounding_box(cloud.points);
    if (!((box.max - box.min).maxCoeff() > 0)) throw InvalidInput("all points are the same point: no surface to reconstruct");
  }
  return suggest_epsilon0(cloud, int(kNeeded));
}

SurfaceResult reconstruct_surface(Cloud input, const SurfaceParams& p) {
  const auto t0 = Clock::now();
  const auto note = [&](const std::string& line) {
    if (p.note) p.note(line);
  };
  if (input.empty()) throw InvalidInput("reconstruct_surface: empty cloud");
  SurfaceResult out;
  bool zero_normals = false;
  if (input.has_normals()) {
    // Normals that are all zero (or not finite) are none: a writer that fills the
    // fields without estimating them. Estimated as for a cloud without them (MPU
    // refused the cloud, "0 points with usable normals").
    zero_normals = !any_usable_normal(input.normals);
    if (zero_normals) input.normals.clear();
  }
  if (!input.has_normals()) {
    // MPU needs oriented normals: estimate them (PCA) and orient them consistently.
    note(zero_normals ? "the normals are all zero; estimating them (PCA, MST orientation)"
                      : "no normals; estimating them (PCA, MST orientation)");
    input.normals = estimate_normals(input.points, 12, p.threads);
    orient_normals_mst(input.points, input.normals, 12);
    out.normals_estimated = true;
  }
  out.seconds.normals = seconds_since(t0);

  out.hole = p.hole;
  // The winding number's area per point, for the enclosure and the closing alike
  // (the points do not change between them; a turn of the normals does not matter).
  std::vector<double> areas;
  const auto point_areas_once = [&]() -> const std::vector<double>* {
    if (areas.empty()) tbb::task_arena(worker_threads(p.threads)).execute([&] { areas = point_areas(input.points, input.normals); });
    return &areas;
  };
  if (p.hole == HoleMode::kAuto) {
    // (in an arena of p.threads: the winding number's construction runs in parallel)
    const std::vector<double>* a = point_areas_once();
    tbb::task_arena(worker_threads(p.threads)).execute([&] { out.enclosure = cloud_enclosure(input, a); });
    if (*out.enclosure <= -kEnclosedAbove) {
      // A closed cloud whose normals all face inwards: turned, then closed.
      for (Vec3f& n : input.normals) n = -n;
      note("the cloud's normals face inwards (it encloses " + fmt("%.2f", *out.enclosure) +
           "): turned outwards");
      out.normals_flipped = true;
      out.enclosure = -*out.enclosure;
    }
    const std::string encloses = "(hole auto: the cloud encloses " + fmt("%.2f", *out.enclosure);
    const std::string bound =
        fmt("%.2g", p.enclosed_above) + (p.enclosed_above != kEnclosedAbove ? " for views all round the object" : "");
    if (*out.enclosure >= p.enclosed_above) {
      out.hole = HoleMode::kClose;
      note("closing the unseen parts " + encloses + ", at least " + bound + ")");
    } else {
      out.hole = HoleMode::kKeep;
      note("leaving the unseen parts open " + encloses + ", below " + bound + ": a one-sided patch)");
    }
  }

  MpuParams mp;
  // The paper's 1e-4 suits clean data only; noisy scans get a tolerance from their noise.
  mp.epsilon0 = p.epsilon0 > 0 ? p.epsilon0 : std::max(mp.epsilon0, surface_epsilon0(input));
  mp.threads = p.threads;
  // Holes kept: the mesh stops within kKeepTrustFactor spacings of the points.
  if (out.hole == HoleMode::kKeep) mp.trust_factor = kKeepTrustFactor, mp.sparse_trust = true;
  out.epsilon0 = mp.epsilon0;
  note("MPU on " + std::to_string(input.size()) + " points (epsilon0 " + fmt("%.3g", mp.epsilon0) + ")");
  const auto t1 = Clock::now();
  // The fits take the points in Z order: their ball searches, octrees and the
  // extraction seeded from the points work on neighbourhoods, and a cloud in random
  // order (a random subset, a shuffled file) made each of them a cache miss per point
  // (mustard 100k in random order: 3.2-3.4 -> 2.3-2.8 s; docs/mpu.md). The statistics
  // taken over the input's order (epsilon0's and the enclosure's samples, the winding
  // closing's clusters) keep it, as a blocked run's summary does.
  // (The sorted copy lives only for each fit: MpuSurface keeps its own points.)
  const std::vector<std::uint32_t> z_order = spatial_order(input.points);
  const MpuSurface surface = fit_mpu(reordered(input, z_order), mp);
  out.mpu = surface.diagnostics();
  out.seconds.fit = seconds_since(t1);

  const auto t2 = Clock::now();
  const bool close = out.hole == HoleMode::kClose;
  std::unique_ptr<WindingClose> winding;
  if (close && p.winding_close) {
    // The trust distance from the fit's own mean spacing (all points), and the voxel
    // from the cloud's bounds: the values a block of the same cloud takes from its
    // summary (reconstruct_block), so a blocked run closes as this one does.
    WindingCloseParams wp;
    if (out.mpu.mean_spacing > 0) {
      wp.trust_distance = mp.trust_factor * out.mpu.mean_spacing;
      wp.voxel = std::max(wp.trust_distance / 2, double(bounding_box(input.points).diagonal()) / 200);
    }
    wp.areas = point_areas_once();
    tbb::task_arena(worker_threads(p.threads)).execute([&] { winding = std::make_unique<WindingClose>(surface, input, wp); });
    out.winding_points = winding->winding_points();
    out.winding_trust = winding->trust_distance();
    note("unseen parts closed by the winding number (" + std::to_string(out.winding_points) +
         " clusters, beyond " + fmt("%.3g", out.winding_trust) + " of the data)");
  }
  const ImplicitFunction& closed = winding ? static_cast<const ImplicitFunction&>(*winding) : surface;
  std::unique_ptr<HalfSpaceClip> clip;
  if (close && p.table_up && p.table_up->norm() > 0) {
    const Vec3d u = p.table_up->normalized();
    double lowest = std::numeric_limits<double>::infinity();
    for (const Vec3f& q : input.points) lowest = std::min(lowest, u.dot(q.cast<double>()));
    clip = std::make_unique<HalfSpaceClip>(closed, u, lowest);
    out.table_height = lowest;
    note("closed flat at the table plane (lowest point along the turntable axis)");
  }
  const ImplicitFunction& f = clip ? static_cast<const ImplicitFunction&>(*clip) : closed;
  out.seconds.closing = seconds_since(t2);

  MarchingCubesOptions mo;
  mo.untrusted = close ? UntrustedRegions::kClose : UntrustedRegions::kLeaveOpen;
  mo.threads = p.threads;
  // The box and seeds of the MpuSurface overloads of the extractors.
  const Aabb box = extraction_box(surface);
  mo.seeds = surface.points();
  mo.close_at_box = true;
  const double longest = double((box.max - box.min).maxCoeff());
  out.resolution_auto = p.resolution <= 0;
  // The cell follows the sample spacing (1 / sqrt(density)), not the nearest
  // neighbour's distance, which is half of it on random samples (MpuDiagnostics).
  const double spacing = out.mpu.sample_spacing > 0 ? out.mpu.sample_spacing : out.mpu.mean_spacing;
  out.resolution = out.resolution_auto ? auto_resolution(longest, spacing) : p.resolution;
  const int resolution = out.resolution;
  if (out.resolution_auto)
    note("extracting at resolution " + std::to_string(resolution) + " (" + extractor_label(p.extractor) +
         "; auto: cell " + fmt("%.3g", longest / resolution) + ", the points' sample spacing " +
         fmt("%.3g", spacing) +
         (resolution == kAutoResolutionMin || resolution == kAutoResolutionMax
              ? ", clamped to " + std::to_string(kAutoResolutionMin) + ".." + std::to_string(kAutoResolutionMax) + ")"
              : std::string(")")));
  else
    note("extracting at resolution " + std::to_string(resolution) + " (" + extractor_label(p.extractor) + ")");
  const auto t3 = Clock::now();
  out.expected_faces = check_extraction_fits(
      f, box, resolution, mo,
      p.resolution_name.empty() ? "resolution " + std::to_string(resolution) : p.resolution_name);
  if (out.expected_faces > 0) note("about " + fmt("%.1f", out.expected_faces / 1e6) + " M faces expected");
  Mesh mesh;
  if (p.extractor == Extractor::kDmc) {
    DmcOptions dopt;
    static_cast<MarchingCubesOptions&>(dopt) = mo;
    mesh = extract_dmc(f, box, resolution, dopt, &out.dmc);
    out.extraction = out.dmc;
  } else {
    mesh = extract_marching_cubes(f, box, resolution, mo, &out.extraction);
  }
  out.seconds.extract = seconds_since(t3);
  if (mesh.faces.empty()) throw InvalidInput("the reconstructed surface is empty");
  if (!close && out.mpu.mean_spacing > 0) {
    // Holes kept: the rims come back to the data (no flaps beyond the points).
    const double bound = kRimTrimFactor * out.mpu.mean_spacing;
    out.rim_faces = trim_open_rims(mesh, far_from(mesh, p.threads, [&](const Vec3f& x) {
                                     return !surface.near_points(x.cast<double>(), bound);
                                   }));
    if (out.rim_faces > 0)
      note("open rims brought back to the data (" + std::to_string(out.rim_faces) + " faces further than " +
           fmt("%.3g", bound) + " from the points)");
  }
  const auto t_scans = Clock::now();
  bool scans_meet_mesh = false;  // the snap ran and found the scans around the mesh
  std::unique_ptr<PointIndex> scan_index;
  if (p.scans && !p.scans->empty()) {
    if (!p.scans->has_normals()) {
      note("the scans have no normals: the mesh stays on the fitted surface");
    } else {
      ScanSnapParams sp;
      sp.cell = out.extraction.cell_size;
      sp.significance = p.snap_significance;
      sp.threads = p.threads;
      const ScanSnapStats st = snap_to_scans(mesh, *p.scans, sp);
      out.snapped_vertices = st.moved;
      out.snap_mean_move = st.mean_move;
      out.snap_declined = st.declined;
      const std::string held_out = st.held_out_vertices == 0
                                       ? std::string()
                                       : " (fits from each half of the scans at " +
                                             std::to_string(st.held_out_vertices) + " vertices: the mesh " +
                                             fmt("%.3g", st.held_out_rms_kept) + " RMS off them, their noise " +
                                             fmt("%.3g", st.held_out_rms_snapped) + ")";
      if (st.too_few_fitted)
        note("vertices stay on the fitted surface: only " + std::to_string(st.held_out_vertices) + " of " +
             std::to_string(st.sampled_vertices) + " sampled vertices have scan points facing their way within " +
             fmt("%.3g", st.radius) +
             " in each half of the scans (are they of this object, in its units, with outward normals?)");
      else if (st.declined)
        note("vertices stay on the fitted surface: local fits of the scans within " + fmt("%.3g", st.radius) +
             " would not bring it closer to them" + held_out);
      else
        note("vertices onto local fits of the scans within " + fmt("%.3g", st.radius) + ": " +
             std::to_string(st.moved) + " of " + std::to_string(mesh.vertices.size()) + " moved, by " +
             fmt("%.3g", st.mean_move) + " on average" + held_out);
      if (!st.too_few_fitted) scans_meet_mesh = true;
    }
  }
  PieceSupport support;
  // Non-finite scans: the snap has said so.
  if (scans_meet_mesh && !close) scan_index = std::make_unique<PointIndex>(p.scans->points);
  if (scan_index) {
    // Holes kept: the scans are the data the mesh must stay near. Its rims come back
    // to them (the consolidated points' rims lie inside the scans' own), and small
    // pieces that they support stay (kScanRimFactor, kPieceMinScans).
    const double spacing = sample_spacing(*scan_index);
    const double reach = kScanRimFactor * spacing;
    if (reach > 0) {
      support = {&p.scans->points, reach, kPieceMinScans};
      // A vertex is far when it lies beyond kScanRimFactor of the scans' spacing from
      // every scan point: their median spacing, or where the nearest scan point's data
      // are sparse, its own (sparse_allowance).
      const SparseAllowances allowance(*scan_index, spacing);
      out.scan_rim_faces = trim_open_rims(mesh, far_from(mesh, p.threads, [&](const Vec3f& x) {
                                            if (scan_index->nearest_within(x, float(reach)).first >= 0) return false;
                                            const auto [j, d] = scan_index->nearest(x);
                                            if (j < 0) return true;
                                            const double a = allowance(j);
                                            return a == 1 || d > reach * a;
                                          }));
      if (out.scan_rim_faces > 0)
        note("open rims brought back to the scans (" + std::to_string(out.scan_rim_faces) + " faces further than " +
             fmt("%.3g", reach) + ", " + fmt("%.3g", kScanRimFactor) +
             " of their median sample spacing, or of the local one where sparser)");
    }
  }
  out.seconds.scans = seconds_since(t_scans);
  out.pieces = remove_small_components(mesh, p.min_component, nullptr, &support);
  if (out.pieces.removed_components > 0)
    note("removed " + std::to_string(out.pieces.removed_components) + " small pieces (" +
         std::to_string(out.pieces.removed_faces) + " faces)");
  if (out.pieces.supported_components > 0)
    note("kept " + std::to_string(out.pieces.supported_components) + " small pieces that " +
         std::to_string(kPieceMinScans) + " or more scan points support");

  const auto t4 = Clock::now();
  out.coloured = p.colour && input.has_colours();
  if (out.coloured && p.colour_method == ColourMethod::kNearest) {
    transfer_colours(mesh, input, {4, p.threads});
  } else if (out.coloured) {
    note("colour function on " + std::to_string(input.size()) + " points");
    const ColourFunction cf = fit_colour(reordered(input, z_order), colour_params(p));
    out.colour_nearest_vertices = colour_mesh(mesh, cf, surface, input, p.threads);
    if (p.colour_edges) {
      ColourEdgeParams ep;
      ep.threads = p.threads;
      out.colour_edges_split = sharpen_colour_edges(mesh, cf, ep).split_edges;
    }
    out.colour = cf.diagnostics();
    note("colour function: " + std::to_string(out.colour->leaves_by_type[0]) + " cells smooth (A), " +
         std::to_string(out.colour->leaves_by_type[1]) + " split at a boundary (B), e_col " +
         fmt("%.4f", out.colour->e_col) +
         (out.colour->e_col_points > 0 && out.colour->e_col_points < input.size()
              ? " over " + std::to_string(out.colour->e_col_points) + " of the points"
              : std::string()) +
         (out.colour_edges_split ? "; " + std::to_string(out.colour_edges_split) + " edges split at colour boundaries"
                                 : std::string()));
    if (p.boundary_flags) {
      out.colour_boundary.resize(mesh.vertices.size());
      for (std::size_t i = 0; i < mesh.vertices.size(); ++i)
        out.colour_boundary[i] = cf.dominant_type(mesh.vertices[i].cast<double>()) == ColourCellType::kB;
    }
  } else if (p.colour) {
    note("the cloud has no colours; the mesh is left uncoloured");
  }
  out.seconds.colour = seconds_since(t4);
  out.mesh = std::move(mesh);
  out.seconds.total = seconds_since(t0);
  return out;
}

int auto_resolution(double longest_side, double mean_spacing) {
  if (!(longest_side > 0) || !(mean_spacing > 0) || !std::isfinite(longest_side / mean_spacing))
    return kAutoResolutionMin;
  const double cells = std::ceil(longest_side / mean_spacing);
  return int(std::clamp(cells, double(kAutoResolutionMin), double(kAutoResolutionMax)));
}

double check_extraction_fits(const ImplicitFunction& f, const Aabb& box, int resolution,
                             const MarchingCubesOptions& options, const std::string& what,
                             double available_bytes) {
  constexpr int kCoarse = 64;
  if (resolution <= 512) return 0;
  double available = available_bytes;
  if (available < 0) {
    available = 0;
    std::ifstream meminfo("/proc/meminfo");
    double kb = 0;
    for (std::string line; std::getline(meminfo, line);)
      if (std::sscanf(line.c_str(), "MemAvailable: %lf kB", &kb) == 1) available = kb * 1024;
  }
  if (!(available > 0)) return 0;
  const Mesh coarse = extract_marching_cubes(f, box, kCoarse, options);
  const double scale = double(resolution) / kCoarse;
  const double faces = double(coarse.faces.size()) * scale * scale;
  const double need = faces * kExtractionBytesPerFace;
  if (need <= 0.85 * available) return faces;
  const int finest =
      int(kCoarse * std::sqrt(0.85 * available / (kExtractionBytesPerFace * double(coarse.faces.size()))));
  char buf[256];
  std::snprintf(buf, sizeof buf,
                ": the mesh would have about %.0f M faces and need about %.1f GiB; %.1f GiB are available: use at "
                "most %d",
                faces / 1e6, need / 1073741824.0, available / 1073741824.0, finest);
  throw InvalidInput(what + buf);
}

}  // namespace station
