#include "reconstruct/scan_snap.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <cmath>

#include "core/error.h"
#include "core/kdtree.h"
#include "core/threads.h"

namespace station {

ScanSnapStats snap_to_scans(Mesh& mesh, const Cloud& scans, const ScanSnapParams& p) {
  ScanSnapStats stats;
  if (!scans.has_normals()) throw InvalidInput("snap to scans: the scans have no normals");
  if (!all_finite(scans.points)) throw InvalidInput("snap to scans: non-finite scan coordinates");
  const double radius = p.radius > 0 ? p.radius : p.cell;
  const double max_move = p.max_move > 0 ? p.max_move : 0.5 * p.cell;
  if (!(radius > 0) || !(max_move > 0) || !std::isfinite(radius) || !std::isfinite(max_move) || p.threads < 0 ||
      !(p.significance >= 0) || !(p.min_cos >= -1 && p.min_cos <= 1) || p.min_points < 1)
    throw InvalidInput("snap to scans: need a positive radius and largest move (or cell), significance >= 0, -1 <= min_cos <= 1, min_points >= 1, threads >= 0");
  stats.radius = radius;
  if (mesh.vertices.empty() || scans.points.empty()) return stats;
  const PointIndex index(scans.points);
  const std::vector<Vec3f> normals = vertex_normals(mesh);
  std::vector<Vec3f> moved = mesh.vertices;
  std::vector<double> move(mesh.vertices.size(), -1);
  tbb::task_arena arena(worker_threads(p.threads));
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, mesh.vertices.size(), 512), [&](const auto& range) {
      for (std::size_t i = range.begin(); i != range.end(); ++i) {
        const Vec3d n = normals[i].cast<double>();
        if (!(n.squaredNorm() > 0.5) || !mesh.vertices[i].allFinite()) continue;
        const Vec3d v = mesh.vertices[i].cast<double>();
        double sw = 0, sw2 = 0, sh = 0, shh = 0;
        int count = 0;
        for (const auto& [j, d] : index.radius_unsorted(mesh.vertices[i], float(radius))) {
          const Vec3d sn = scans.normals[std::size_t(j)].cast<double>();
          const double len = sn.norm();
          if (!(len > 0) || sn.dot(n) < p.min_cos * len) continue;
          const Vec3d q = scans.points[std::size_t(j)].cast<double>() - v;
          const double h = q.dot(n);
          const double t2 = (q - h * n).squaredNorm() / (radius * radius);
          if (t2 >= 1) continue;
          const double w = (1 - t2) * (1 - t2);
          sw += w;
          sw2 += w * w;
          sh += w * h;
          shh += w * h * h;
          ++count;
        }
        if (count < p.min_points || !(sw > 0)) continue;
        // The mean height's standard error from the points' spread about it
        // (effective count (sum w)^2 / sum w^2): only the part of the mean beyond
        // `significance` standard errors moves the vertex, so scan noise does not.
        const double mean = sh / sw;
        const double var = std::max(0.0, shh / sw - mean * mean);
        const double n_eff = sw * sw / sw2;
        if (!(n_eff > 1)) continue;  // one point's worth: no spread to judge it by
        const double se = std::sqrt(var / (n_eff - 1));
        const double beyond = std::max(0.0, std::abs(mean) - p.significance * se);
        if (!(beyond > 0)) continue;
        const double h = std::clamp(std::copysign(beyond, mean), -max_move, max_move);
        moved[i] = (v + h * n).cast<float>();
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
