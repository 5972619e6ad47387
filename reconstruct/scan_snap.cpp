#include "reconstruct/scan_snap.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>

#include "core/error.h"
#include "reconstruct/detail/scan_grid.h"
#include "core/threads.h"

namespace station {
namespace {

// The weighted moments of a paraboloid fit h(t) = a + b t^2 (biweight weights w of
// t / radius along the tangent plane; q*: the squared weights', for the standard
// error).
struct Moments {
  double s0 = 0, s1 = 0, s2 = 0, sh = 0, sht = 0, shh = 0, q0 = 0, q1 = 0, q2 = 0;
  int count = 0;
  void add(double w, double t2, double h) {
    s0 += w, s1 += w * t2, s2 += w * t2 * t2;
    sh += w * h, sht += w * h * t2, shh += w * h * h;
    q0 += w * w, q1 += w * w * t2, q2 += w * w * t2 * t2;
    ++count;
  }
};

// The scan points round a vertex, side by side (the reweighted fits' loops run over
// them many times): each point's biweight weight w along the tangent plane, t^2 (its
// squared distance along the plane over the radius squared), its height h along the
// vertex's normal, and which half of the scans it is in (its index's parity: the merged
// scans hold each view's points in scan order, so the two halves are even, interleaved
// halves of every view).
struct Samples {
  std::vector<double> w, t2, h;
  std::vector<unsigned char> half;
  std::size_t size() const { return w.size(); }
  std::size_t count(int which) const { return std::size_t(std::count(half.begin(), half.end(), which)); }
};

using detail::ScanGrid;

// One neighbourhood search for a vertex: the scan points within `radius` along the
// tangent plane whose normals face n's way.
void gather(const ScanGrid& grid, const Vec3f& vertex, const Vec3d& n, double radius, double min_cos,
            Samples& out) {
  out.w.clear(), out.t2.clear(), out.h.clear(), out.half.clear();
  const Vec3d v = vertex.cast<double>();
  grid.for_each_within(vertex, [&](std::uint32_t j) {
    const Vec3d sn = grid.normal(j).cast<double>();
    const double len = sn.norm();
    if (!(len > 0) || sn.dot(n) < min_cos * len) return;
    const Vec3d q = grid.point(j).cast<double>() - v;
    const double h = q.dot(n);
    const double t2 = (q - h * n).squaredNorm() / (radius * radius);
    if (t2 >= 1) return;
    out.w.push_back((1 - t2) * (1 - t2)), out.t2.push_back(t2), out.h.push_back(h);
    out.half.push_back((unsigned char)grid.half(j));
  });
}

struct HeightFit {
  double a = 0;      ///< the height at the vertex, along its normal
  double se = 0;     ///< its standard error (of the least-squares fit)
  double b = 0;      ///< the curvature term: height per (t / radius)^2
  double sigma = 0;  ///< the least-squares fit's RMS residual
};

// The weighted least-squares fit from the moments, when they hold `min_points` points.
std::optional<HeightFit> solve(const Moments& m, int min_points) {
  if (m.count < min_points || !(m.s0 > 0)) return std::nullopt;
  const double det = m.s0 * m.s2 - m.s1 * m.s1;
  if (!(det > 1e-9 * m.s0 * m.s2)) return std::nullopt;  // every point at one distance
  const double a = (m.s2 * m.sh - m.s1 * m.sht) / det, b = (m.s0 * m.sht - m.s1 * m.sh) / det;
  const double n_eff = m.s0 * m.s0 / m.q0;
  if (!(n_eff > 2) || !std::isfinite(a)) return std::nullopt;
  const double rss =
      std::max(0.0, m.shh - 2 * (a * m.sh + b * m.sht) + a * a * m.s0 + 2 * a * b * m.s1 + b * b * m.s2);
  const double sigma2 = rss / m.s0 * n_eff / (n_eff - 2);
  // Var a = sigma^2 [M^-1 W M^-1]_00 (weighted least squares, W the squared weights'
  // moments); the first row of M^-1 is (s2, -s1) / det.
  const double r0 = m.s2 / det, r1 = -m.s1 / det;
  const double var = sigma2 * (r0 * r0 * m.q0 + 2 * r0 * r1 * m.q1 + r1 * r1 * m.q2);
  return HeightFit{a, std::sqrt(std::max(0.0, var)), b, std::sqrt(rss / m.s0)};
}

// Iterations of the least-absolute-deviations refit, and the floor of its weights 1 / |r|
// as a share of the least-squares fit's RMS residual (docs/run.md, "The fit in absolute
// distances": on the dragon's held-out halves 6 and 12 iterations gave the same figure).
constexpr int kL1Iterations = 8;
constexpr double kL1Floor = 0.05;
// The refit stops when its height moves by less than this share of the floor.
constexpr double kL1Settled = 0.01;

// The fit h(t) = a + b t^2 from the samples of one half (0, 1) or of all (-1): least
// squares first, then refitted to least absolute deviations (iteratively reweighted,
// each point's weight over max(|r|, a floor)). The station's measure of a mesh against
// scans is their mean absolute distance, which a least-absolute fit minimises, and a
// scanner's noise has tails (mixed pixels at silhouettes, speckle) that pull a
// least-squares fit. The standard error is the least-squares fit's, times sqrt(pi / 2)
// after the refit (what a median loses against a mean on normal noise). `absolute` false:
// the least-squares fit alone (the held-out check's, below). The refit is over all the
// samples only (what the snap moves by).
std::optional<HeightFit> fit_heights(const Samples& samples, int half, int min_points, bool absolute) {
  Moments m;
  const std::size_t n = samples.size();
  for (std::size_t k = 0; k < n; ++k)
    if (half < 0 || samples.half[k] == half) m.add(samples.w[k], samples.t2[k], samples.h[k]);
  auto fit = solve(m, min_points);
  if (!absolute || !fit || !(fit->sigma > 0)) return fit;
  if (half >= 0) throw std::logic_error("snap to scans: a half's fit is least squares");
  const double floor = kL1Floor * fit->sigma;
  double a = fit->a, b = fit->b;
  const double* w = samples.w.data();
  const double* t2 = samples.t2.data();
  const double* h = samples.h.data();
  for (int it = 0; it < kL1Iterations; ++it) {
    double s0 = 0, s1 = 0, s2 = 0, sh = 0, sht = 0;  // the reweighted normal equations
    for (std::size_t k = 0; k < n; ++k) {
      const double wk = w[k] / std::max(floor, std::abs(h[k] - a - b * t2[k]));
      s0 += wk, s1 += wk * t2[k], s2 += wk * t2[k] * t2[k], sh += wk * h[k], sht += wk * h[k] * t2[k];
    }
    const double det = s0 * s2 - s1 * s1;
    if (!(det > 1e-9 * s0 * s2)) break;
    const double next = (s2 * sh - s1 * sht) / det;
    b = (s0 * sht - s1 * sh) / det;
    const bool settled = std::abs(next - a) < kL1Settled * floor;
    a = next;
    if (settled) break;
  }
  if (std::isfinite(a) && std::isfinite(b)) {
    fit->a = a, fit->b = b;
    // A least-absolute estimate's standard error on normal noise: sqrt(pi / 2) the
    // least-squares one (its efficiency 2 / pi).
    fit->se *= std::sqrt(M_PI / 2);
  }
  return fit;
}

// A half's own fit needs half the points a whole fit does (what each half holds of them).
int half_min_points(const ScanSnapParams& p) { return std::max(3, p.min_points / 2); }

// The move along the normal: the part of the fit's height plus `correction` (the sag's)
// beyond `significance` standard errors, at most max_move.
double move_of(const HeightFit& f, const ScanSnapParams& p, double max_move, double correction = 0) {
  const double target = f.a + correction;
  const double beyond = std::max(0.0, std::abs(target) - p.significance * f.se);
  return std::clamp(std::copysign(beyond, target), -max_move, max_move);
}

// At most this many vertices are cross-validated (evenly strided): enough to tell a
// gain of a few per cent, at a fraction of the snap's own cost.
constexpr std::size_t kHeldOutVertices = 40000;
// The check needs at least this share of the sampled vertices fitted from both halves.
// Fewer: the scans hardly meet the mesh (inward normals, other units, another object),
// and the few fits there are (inward normals find the far side of thin parts) would
// decide for the whole mesh. The dragon's closed mesh has 74 % fitted (its closed
// bottom has no scans), the demo's bottle 91 %; with the dragon's scan normals
// turned inwards 2 of 39,305 (which moved 22 vertices by 0.27 mm before this test).
constexpr double kMinFittedShare = 0.1;

}  // namespace

ScanSnapStats snap_to_scans(Mesh& mesh, const Cloud& scans, const ScanSnapParams& p) {
  ScanSnapStats stats;
  if (!scans.has_normals()) throw InvalidInput("snap to scans: the scans have no normals");
  if (scans.normals.size() != scans.points.size())
    throw InvalidInput("snap to scans: " + std::to_string(scans.normals.size()) + " normals for " +
                       std::to_string(scans.points.size()) + " scan points");
  if (!all_finite(scans.points)) throw InvalidInput("snap to scans: non-finite scan coordinates");
  if (!(p.radius >= 0) || !(p.max_move >= 0) || !(p.cell >= 0) || !std::isfinite(p.radius) ||
      !std::isfinite(p.max_move) || !std::isfinite(p.cell) || (p.cell == 0 && (p.radius == 0 || p.max_move == 0)) ||
      p.threads < 0 || !(p.significance >= 0) || !(p.min_cos >= -1 && p.min_cos <= 1) || p.min_points < 3)
    throw InvalidInput(
        "snap to scans: need a positive radius and largest move (or cell), significance >= 0, -1 <= min_cos <= 1, "
        "min_points >= 3, threads >= 0");
  double radius = p.radius;
  if (radius == 0) {
    // The scans' WLOP support (reconstruct/wlop.h's default h) over their bounding box.
    const Aabb box = bounding_box(scans.points);
    const double diagonal = (box.max - box.min).cast<double>().norm();
    radius = std::max(p.cell, 4 * diagonal / std::sqrt(double(scans.size())));
  }
  const double max_move = p.max_move > 0 ? p.max_move : 0.5 * p.cell;
  stats.radius = radius;
  if (mesh.vertices.empty() || !(radius > 0)) return stats;
  const std::vector<Vec3f> normals = vertex_normals(mesh);
  const auto usable = [&](std::size_t i) {
    return normals[i].squaredNorm() > 0.5f && mesh.vertices[i].allFinite();
  };
  tbb::task_arena arena(worker_threads(p.threads));
  std::unique_ptr<ScanGrid> grid_ptr;
  arena.execute([&] { grid_ptr = std::make_unique<ScanGrid>(scans, radius); });
  const ScanGrid& grid = *grid_ptr;

  if (p.cross_validate) {
    // Two fits at evenly strided vertices, one from the even and one from the odd scan
    // points: independent estimates m_e, m_o of the move, each with the variance v of
    // a half's fit. With mu the move the whole scans' fit tends to, E[m_e m_o] = mu^2,
    // the mesh's squared error to that height if it stays; E[(m_e - m_o)^2] / 4 = v / 2,
    // about the whole fit's variance, its squared error if it moves. A vertex that
    // either half cannot fit alone is left out of the sums, and does not move below either.
    // The check's fits are least squares: it asks whether the scans show an offset at
    // all, which least squares tells with less noise (a least-absolute fit's variance is
    // 1.57x on normal noise: on PipelineTest's coarse session it declined a snap that
    // took 5 % off the Chamfer against the true mesh).
    const std::size_t stride = std::max<std::size_t>(1, (mesh.vertices.size() + kHeldOutVertices - 1) / kHeldOutVertices);
    const std::size_t samples = (mesh.vertices.size() + stride - 1) / stride;
    std::vector<double> stay(samples, 0), go(samples, 0);
    std::vector<char> fitted(samples, 0);
    arena.execute([&] {
      tbb::parallel_for(tbb::blocked_range<std::size_t>(0, samples, 256), [&](const auto& range) {
        for (std::size_t s = range.begin(); s != range.end(); ++s) {
          const std::size_t i = s * stride;
          if (!usable(i)) continue;
          thread_local Samples ss;
          gather(grid, mesh.vertices[i], normals[i].cast<double>(), radius, p.min_cos, ss);
          const auto even = fit_heights(ss, 0, half_min_points(p), false);
          if (!even) continue;
          const auto odd = fit_heights(ss, 1, half_min_points(p), false);
          if (!odd) continue;
          const double me = move_of(*even, p, max_move), mo = move_of(*odd, p, max_move);
          stay[s] = me * mo;
          go[s] = 0.25 * (me - mo) * (me - mo);
          fitted[s] = 1;
        }
      });
    });
    double sum_stay = 0, sum_go = 0;  // in vertex order: the same for any thread count
    for (std::size_t s = 0; s < samples; ++s) {
      if (usable(s * stride)) ++stats.sampled_vertices;
      if (fitted[s]) sum_stay += stay[s], sum_go += go[s], ++stats.held_out_vertices;
    }
    if (stats.held_out_vertices == 0 ||
        double(stats.held_out_vertices) < kMinFittedShare * double(stats.sampled_vertices)) {
      stats.declined = true;
      stats.too_few_fitted = true;
      return stats;
    }
    stats.held_out_rms_kept = std::sqrt(std::max(0.0, sum_stay) / double(stats.held_out_vertices));
    stats.held_out_rms_snapped = std::sqrt(sum_go / double(stats.held_out_vertices));
    if (!(sum_go < sum_stay)) {
      stats.declined = true;
      return stats;
    }
  }

  std::vector<Vec3f> moved = mesh.vertices;
  std::vector<double> move(mesh.vertices.size(), -1);
  // The flat triangles between vertices on the fitted surface cut its curves: for a
  // height b' t^2 (b' = b / radius^2) the linear interpolation over a triangle lies
  // b' S / 12 above it on average, S the sum of its squared edges. Each vertex moves
  // against the mean of its faces' sag, so that the facets straddle the surface.
  std::vector<double> edge_sum(mesh.vertices.size(), 0);  // sum over the vertex's faces of S
  std::vector<int> face_count(mesh.vertices.size(), 0);
  for (const Face& f : mesh.faces) {
    const Vec3f &u = mesh.vertices[std::size_t(f[0])], &v = mesh.vertices[std::size_t(f[1])],
                &w = mesh.vertices[std::size_t(f[2])];
    const double sq = double((u - v).squaredNorm() + (v - w).squaredNorm() + (w - u).squaredNorm());
    for (int k = 0; k < 3; ++k) edge_sum[std::size_t(f[k])] += sq, ++face_count[std::size_t(f[k])];
  }
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, mesh.vertices.size(), 256), [&](const auto& range) {
      for (std::size_t i = range.begin(); i != range.end(); ++i) {
        if (!usable(i)) continue;
        const Vec3d n = normals[i].cast<double>();
        thread_local Samples ss;
        gather(grid, mesh.vertices[i], n, radius, p.min_cos, ss);
        const auto even = std::ptrdiff_t(ss.count(0));
        const auto odd = std::ptrdiff_t(ss.size()) - even;
        // With the check, only vertices that each half alone can fit (those it judged).
        if (p.cross_validate && (even < half_min_points(p) || odd < half_min_points(p))) continue;
        const auto fit = fit_heights(ss, -1, p.min_points, true);
        if (!fit) continue;
        const double sag = face_count[i] > 0 ? fit->b / (radius * radius) * edge_sum[i] / face_count[i] / 12 : 0;
        const double h = move_of(*fit, p, max_move, -sag);
        if (h == 0) continue;
        moved[i] = (mesh.vertices[i].cast<double>() + h * n).cast<float>();
        move[i] = std::abs(h);
      }
    });
  });
  double sum = 0;
  for (double m : move)
    if (m >= 0) ++stats.moved, sum += m;
  stats.mean_move = stats.moved ? sum / double(stats.moved) : 0;
  mesh.vertices = std::move(moved);
  return stats;
}

}  // namespace station
