#include "eval/consolidation_metrics.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <string>
#include <tuple>

#include <Eigen/Geometry>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include "core/bvh.h"
#include "core/error.h"
#include "core/kdtree.h"
#include "core/threads.h"

namespace station {

namespace {

void check_points(const std::vector<Vec3f>& points, const char* what) {
  if (points.empty()) throw InvalidInput(std::string(what) + ": no points");
  if (!all_finite(points)) throw InvalidInput(std::string(what) + ": non-finite coordinates");
}

int arena_threads(int threads, const char* what) {
  if (threads < 0) throw InvalidInput(std::string(what) + ": threads must be >= 0");
  return worker_threads(threads);
}

// Closest points of the mesh to the points, in point order.
std::vector<ClosestPoint> closest(const std::vector<Vec3f>& points, const Mesh& mesh, int threads,
                                  const char* what) {
  check_points(points, what);
  if (mesh.faces.empty()) throw InvalidInput(std::string(what) + ": reference mesh has no faces");
  const TriangleBvh bvh(mesh);
  std::vector<ClosestPoint> c(points.size());
  tbb::task_arena arena(arena_threads(threads, what));
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, points.size(), 512),
                      [&](const tbb::blocked_range<std::size_t>& r) {
                        for (std::size_t i = r.begin(); i < r.end(); ++i)
                          c[i] = bvh.closest_point(points[i].cast<double>());
                      });
  });
  return c;
}

double segment_distance(const Vec3d& p, const Vec3d& a, const Vec3d& b) {
  const Vec3d ab = b - a;
  const double len2 = ab.squaredNorm();
  const double t = len2 > 0 ? std::clamp((p - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
  return (p - (a + t * ab)).norm();
}

}  // namespace

double mean_distance_to_mesh(const std::vector<Vec3f>& points, const Mesh& reference, int threads) {
  const std::vector<ClosestPoint> c = closest(points, reference, threads, "accuracy");
  double sum = 0;
  for (const ClosestPoint& x : c) sum += x.distance;  // in point order: any thread count
  return sum / double(c.size());
}

double mesh_area(const Mesh& mesh) {
  mesh.check_consistent("mesh_area");
  double area = 0;
  for (const Face& f : mesh.faces) {
    const Vec3d a = mesh.vertices[f[0]].cast<double>(), b = mesh.vertices[f[1]].cast<double>(),
                c = mesh.vertices[f[2]].cast<double>();
    area += 0.5 * (b - a).cross(c - a).norm();
  }
  return area;
}

double uniformity(const std::vector<Vec3f>& points, double area) {
  if (points.size() < 2) throw InvalidInput("uniformity: fewer than 2 points");
  check_points(points, "uniformity");
  if (!(area > 0) || !std::isfinite(area)) throw InvalidInput("uniformity: area must be > 0");
  const PointIndex index(points);
  double sum = 0;
  for (std::size_t i = 0; i < points.size(); ++i) {
    // The two nearest: the point itself (or a coincident one) and its neighbour.
    const auto nn = index.knn(points[i], 2);
    sum += nn.size() == 2 ? double(nn[1].second) : 0.0;
  }
  const double n = double(points.size());
  const double d_hex = std::sqrt(2.0 * area / (std::sqrt(3.0) * n));
  return sum / n / d_hex;
}

double surface_uniformity(const std::vector<Vec3f>& points, const Mesh& reference, int threads) {
  const std::vector<ClosestPoint> c = closest(points, reference, threads, "uniformity");
  std::vector<Vec3f> on_surface(c.size());
  for (std::size_t i = 0; i < c.size(); ++i) on_surface[i] = c[i].point.cast<float>();
  return uniformity(on_surface, mesh_area(reference));
}

std::vector<Segment> sharp_edges(const Mesh& mesh, double angle_degrees) {
  mesh.check_consistent("sharp_edges");
  // Merge vertices at identical positions.
  std::map<std::tuple<float, float, float>, int> ids;
  std::vector<int> merged(mesh.vertices.size());
  std::vector<Vec3f> position;
  for (std::size_t v = 0; v < mesh.vertices.size(); ++v) {
    const Vec3f& p = mesh.vertices[v];
    const auto [it, added] = ids.try_emplace({p.x(), p.y(), p.z()}, int(position.size()));
    if (added) position.push_back(p);
    merged[v] = it->second;
  }
  // Unit face normals (zero for degenerate faces).
  std::vector<Vec3d> normal(mesh.faces.size());
  for (std::size_t f = 0; f < mesh.faces.size(); ++f) {
    const Vec3d a = position[merged[mesh.faces[f][0]]].cast<double>(),
                b = position[merged[mesh.faces[f][1]]].cast<double>(),
                c = position[merged[mesh.faces[f][2]]].cast<double>();
    const Vec3d n = (b - a).cross(c - a);
    const double len = n.norm();
    normal[f] = len > 0 ? Vec3d(n / len) : Vec3d::Zero();
  }
  // Edge -> the faces using it.
  std::map<std::pair<int, int>, std::vector<int>> faces_of;
  for (std::size_t f = 0; f < mesh.faces.size(); ++f)
    for (int k = 0; k < 3; ++k) {
      const int a = merged[mesh.faces[f][k]], b = merged[mesh.faces[f][(k + 1) % 3]];
      if (a != b) faces_of[std::minmax(a, b)].push_back(int(f));
    }
  const double cos_limit = std::cos(angle_degrees * M_PI / 180.0);
  std::vector<Segment> out;
  for (const auto& [edge, faces] : faces_of) {
    if (faces.size() != 2) continue;
    const Vec3d &n0 = normal[faces[0]], &n1 = normal[faces[1]];
    if (n0.isZero() || n1.isZero()) continue;
    if (n0.dot(n1) < cos_limit) out.push_back(Segment{position[edge.first], position[edge.second]});
  }
  return out;
}

EdgeError edge_error(const std::vector<Vec3f>& points, const Mesh& reference, double radius,
                     double angle_degrees, int threads) {
  check_points(points, "edge error");
  if (!(radius > 0) || !std::isfinite(radius)) throw InvalidInput("edge error: radius must be > 0");
  const std::vector<Segment> edges = sharp_edges(reference, angle_degrees);
  EdgeError out;
  if (edges.empty()) return out;
  // Segments found through their midpoints: a point within `radius` of a segment
  // is within radius + half the longest segment of its midpoint.
  std::vector<Vec3f> mid(edges.size());
  float half = 0;
  for (std::size_t e = 0; e < edges.size(); ++e) {
    mid[e] = 0.5f * (edges[e].a + edges[e].b);
    half = std::max(half, 0.5f * (edges[e].b - edges[e].a).norm());
  }
  const PointIndex index(mid);
  std::vector<Vec3f> near;
  for (const Vec3f& p : points) {
    const Vec3d q = p.cast<double>();
    for (const auto& [e, d] : index.radius(p, float(radius) + half * 1.0001f)) {
      if (segment_distance(q, edges[e].a.cast<double>(), edges[e].b.cast<double>()) <= radius) {
        near.push_back(p);
        break;
      }
    }
  }
  if (near.empty()) return out;
  out.count = near.size();
  out.mean = mean_distance_to_mesh(near, reference, threads);
  return out;
}

}  // namespace station
