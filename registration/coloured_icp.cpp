#include "registration/coloured_icp.h"

#include <tbb/parallel_for.h>

#include <Eigen/Cholesky>
#include <string>

#include "core/error.h"
#include "core/kdtree.h"

namespace station {

std::vector<float> intensities(const std::vector<Rgb>& colours) {
  std::vector<float> out(colours.size());
  for (std::size_t i = 0; i < colours.size(); ++i)
    out[i] = (float(colours[i].r) + float(colours[i].g) + float(colours[i].b)) / (3.0f * 255.0f);
  return out;
}

std::vector<float> sample_intensity(const std::vector<Vec3f>& points, const PointIndex& cloud_index,
                                    const std::vector<float>& cloud_intensity, double radius) {
  if (cloud_intensity.size() != cloud_index.size())
    throw InvalidInput("colour sampling: " + std::to_string(cloud_intensity.size()) +
                       " intensities for " + std::to_string(cloud_index.size()) + " points");
  std::vector<float> out(points.size(), 0.0f);
  if (cloud_index.size() == 0) return out;
  tbb::parallel_for(std::size_t(0), points.size(), [&](std::size_t i) {
    const auto near = radius > 0 ? cloud_index.radius(points[i], float(radius))
                                 : std::vector<std::pair<int, float>>{};
    if (near.empty()) {
      out[i] = cloud_intensity[cloud_index.nearest(points[i]).first];
      return;
    }
    double s = 0;
    for (const auto& [j, d] : near) s += cloud_intensity[j];
    out[i] = float(s / double(near.size()));
  });
  return out;
}

std::vector<Vec3f> intensity_gradients(const PointIndex& index, const std::vector<Vec3f>& normals,
                                       const std::vector<float>& intensity, int k) {
  const std::vector<Vec3f>& pts = index.points();
  if (normals.size() != pts.size() || intensity.size() != pts.size())
    throw InvalidInput("colour gradients: " + std::to_string(normals.size()) + " normals and " +
                       std::to_string(intensity.size()) + " intensities for " +
                       std::to_string(pts.size()) + " points");
  std::vector<Vec3f> out(pts.size(), Vec3f::Zero());
  tbb::parallel_for(std::size_t(0), pts.size(), [&](std::size_t i) {
    const auto nb = index.knn(pts[i], std::max(4, k));
    const Vec3d p = pts[i].cast<double>(), n = normals[i].cast<double>();
    if (!(n.squaredNorm() > 0.5)) return;
    Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
    Eigen::Vector3d b = Eigen::Vector3d::Zero();
    double scale2 = 0;
    int used = 0;
    for (const auto& [j, d] : nb) {
      if (std::size_t(j) == i) continue;
      const Vec3d q = pts[j].cast<double>();
      const Vec3d qp = q - n * n.dot(q - p);  // projection on p's tangent plane
      const Vec3d e = qp - p;
      A += e * e.transpose();
      b += e * double(intensity[j] - intensity[i]);
      scale2 += e.squaredNorm();
      ++used;
    }
    if (used < 3 || !(scale2 > 0)) return;
    // d . n = 0 as a row weighted like the whole neighbourhood (x10).
    const double w = 10.0 * scale2;
    A += w * n * n.transpose();
    const Eigen::Vector3d d = A.ldlt().solve(b);
    if (d.allFinite()) out[i] = (d - n * n.dot(d)).cast<float>();
  });
  return out;
}

}  // namespace station
