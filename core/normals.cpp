#include "core/normals.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <queue>
#include <tuple>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include "core/error.h"
#include "core/kdtree.h"
#include "core/threads.h"

namespace station {

namespace {

int arena_threads(int threads) {
  if (threads < 0) throw InvalidInput("normals: threads must be >= 0");
  return worker_threads(threads);
}

// Smallest-eigenvalue eigenvector of a symmetric 3x3 matrix. The closed form:
// several times faster than the iterative solver, and the eigenvector it is least
// accurate for (two nearly equal eigenvalues) is never the normal of a surface patch.
Vec3d smallest_eigenvector(const Eigen::Matrix3d& m) {
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
  es.computeDirect(m);
  return es.eigenvectors().col(0).normalized();
}

}  // namespace

Vec3d pca_normal(const Vec3d* points, int n) {
  if (n < 3) return Vec3d::Zero();
  Vec3d c = Vec3d::Zero();
  for (int i = 0; i < n; ++i) c += points[i];
  c /= n;
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (int i = 0; i < n; ++i) {
    const Vec3d y = points[i] - c;
    cov.noalias() += y * y.transpose();
  }
  if (!(cov.trace() > 0)) return Vec3d::Zero();
  return smallest_eigenvector(cov);
}

Vec3d simple_normal(const Vec3d* points, int n, int iterations, Vec3d* pca) {
  if (pca) *pca = Vec3d::Zero();
  if (n < 3) return Vec3d::Zero();
  Vec3d c = Vec3d::Zero();
  for (int i = 0; i < n; ++i) c += points[i];
  c /= n;  // p_j + q_j of eq. 12
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (int i = 0; i < n; ++i) {
    const Vec3d y = points[i] - c;
    cov.noalias() += y * y.transpose();
  }
  if (!(cov.trace() > 0)) return Vec3d::Zero();
  Vec3d normal = smallest_eigenvector(cov);
  if (pca) *pca = normal;
  // Floor on |n . y| so points on the current plane do not get infinite weight.
  const double floor = 1e-3 * std::sqrt(cov.trace() / n);
  for (int it = 0; it < iterations; ++it) {
    Eigen::Matrix3d weighted = Eigen::Matrix3d::Zero();
    for (int i = 0; i < n; ++i) {
      const Vec3d y = points[i] - c;
      weighted.noalias() += (y * y.transpose()) / std::max(std::abs(normal.dot(y)), floor);
    }
    Vec3d next = smallest_eigenvector(weighted);
    if (next.dot(normal) < 0) next = -next;
    normal = next;
  }
  return normal;
}

bool any_usable_normal(const std::vector<Vec3f>& normals) {
  return std::any_of(normals.begin(), normals.end(), [](const Vec3f& n) {
    const float len = n.norm();
    return std::isfinite(len) && len >= 1e-6f;
  });
}

std::vector<Vec3f> estimate_normals(const std::vector<Vec3f>& points, int k, int threads) {
  if (k < 3) throw InvalidInput("normals: k must be >= 3");
  if (!all_finite(points)) throw InvalidInput("normals: non-finite coordinates");
  if (points.empty()) return {};
  return estimate_normals(PointIndex(points), k, threads);
}

std::vector<Vec3f> estimate_normals(const PointIndex& index, int k, int threads) {
  if (k < 3) throw InvalidInput("normals: k must be >= 3");
  const std::vector<Vec3f>& points = index.points();
  std::vector<Vec3f> normals(points.size(), Vec3f::Zero());
  tbb::task_arena arena(arena_threads(threads));
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, points.size(), 256),
                      [&](const tbb::blocked_range<std::size_t>& range) {
                        // Buffers per task, not per point (k-NN without allocation).
                        std::vector<std::uint32_t> idx(static_cast<std::size_t>(k));
                        std::vector<float> dsq(idx.size());
                        std::vector<Vec3d> nb(idx.size());
                        for (std::size_t i = range.begin(); i < range.end(); ++i) {
                          const int found = index.knn_into(points[i], k, idx.data(), dsq.data());
                          for (int m = 0; m < found; ++m) nb[std::size_t(m)] = points[idx[std::size_t(m)]].cast<double>();
                          normals[i] = pca_normal(nb.data(), found).cast<float>();
                        }
                      });
  });
  return normals;
}

void orient_normals_mst(const std::vector<Vec3f>& points, std::vector<Vec3f>& normals, int k) {
  if (normals.size() != points.size())
    throw InvalidInput("orient normals: normals and points differ in count");
  if (k < 1) throw InvalidInput("orient normals: k must be >= 1");
  const std::size_t n = points.size();
  if (n == 0) return;
  const PointIndex index(points);

  // Symmetric kNN graph as adjacency lists (sorted, duplicates removed).
  std::vector<std::vector<int>> adjacent(n);
  for (std::size_t i = 0; i < n; ++i)
    for (const auto& [j, d] : index.knn(points[i], k + 1))
      if (std::size_t(j) != i) {
        adjacent[i].push_back(j);
        adjacent[j].push_back(int(i));
      }
  for (auto& a : adjacent) {
    std::sort(a.begin(), a.end());
    a.erase(std::unique(a.begin(), a.end()), a.end());
  }

  auto cost = [&](int a, int b) {
    return 1.0 - std::abs(double(normals[a].dot(normals[b])));
  };
  // Seeds in order of decreasing height: each one not reached from an earlier
  // seed starts a new component.
  std::vector<int> by_height(n);
  for (std::size_t i = 0; i < n; ++i) by_height[i] = int(i);
  std::stable_sort(by_height.begin(), by_height.end(),
                   [&](int a, int b) { return points[a].z() > points[b].z(); });

  std::vector<char> done(n, 0);
  // (cost, node, parent): the smallest cost first, then the smallest node index.
  using Entry = std::tuple<double, int, int>;
  std::priority_queue<Entry, std::vector<Entry>, std::greater<Entry>> queue;
  for (int seed : by_height) {
    if (done[seed]) continue;
    if (normals[seed].z() < 0) normals[seed] = -normals[seed];
    queue.emplace(0.0, seed, -1);
    while (!queue.empty()) {
      const auto [c, node, parent] = queue.top();
      queue.pop();
      if (done[node]) continue;
      done[node] = 1;
      if (parent >= 0 && normals[node].dot(normals[parent]) < 0) normals[node] = -normals[node];
      for (int next : adjacent[node])
        if (!done[next]) queue.emplace(cost(node, next), next, node);
    }
  }
}

void orient_normals_towards(const std::vector<Vec3f>& points, std::vector<Vec3f>& normals, const Vec3f& viewpoint,
                            bool zero_faces_viewpoint) {
  for (std::size_t i = 0; i < points.size() && i < normals.size(); ++i) {
    Vec3f& n = normals[i];
    if (zero_faces_viewpoint && n.squaredNorm() == 0) n = (viewpoint - points[i]).normalized();
    if (n.dot(viewpoint - points[i]) < 0) n = -n;
  }
}

void orient_normals_to(const std::vector<Vec3f>& points, std::vector<Vec3f>& normals,
                       const std::vector<Vec3f>& reference_points,
                       const std::vector<Vec3f>& reference_normals, int k, int threads) {
  if (normals.size() != points.size())
    throw InvalidInput("orient normals: normals and points differ in count");
  if (reference_normals.size() != reference_points.size())
    throw InvalidInput("orient normals: reference normals and points differ in count");
  if (k < 1) throw InvalidInput("orient normals: k must be >= 1");
  if (reference_points.empty() || points.empty()) return;
  const PointIndex index(reference_points);
  tbb::task_arena arena(arena_threads(threads));
  arena.execute([&] {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, points.size(), 256),
                      [&](const tbb::blocked_range<std::size_t>& range) {
                        for (std::size_t i = range.begin(); i < range.end(); ++i) {
                          Vec3d sum = Vec3d::Zero();
                          for (const auto& [j, d] : index.knn(points[i], k))
                            sum += reference_normals[j].cast<double>();
                          if (normals[i].cast<double>().dot(sum) < 0) normals[i] = -normals[i];
                        }
                      });
  });
}

}  // namespace station
