#include "registration/viewpoint.h"

#include <Eigen/Eigenvalues>
#include <cmath>

#include "core/error.h"

namespace station {

namespace {

constexpr double kCos80 = 0.17364817766693041;  // cos(80 degrees)
constexpr std::size_t kMinPoints = 16;
constexpr double kFarExtents = 100;  // the estimated viewpoint's distance, in view extents
// Below this mean bulge (sum n . (p - centroid) over the points, per point and view
// extent) a view is taken as flat; the dragon's scans bulge 0.01-0.09.
constexpr double kMinBulge = 1e-3;

// Share of the points with a normal whose line of sight from `eye` is more than 80
// degrees from it; `far` = `eye` is a direction (the sensor at infinity along it).
double grazing_share(const std::vector<Vec3f>& points, const std::vector<Vec3f>& normals,
                     const Vec3d& eye, bool far) {
  std::size_t counted = 0, grazing = 0;
  for (std::size_t i = 0; i < points.size(); ++i) {
    const Vec3d n = normals[i].cast<double>();
    if (n.squaredNorm() == 0) continue;
    const Vec3d sight = far ? eye : Vec3d(eye - points[i].cast<double>());
    const double len = sight.norm();
    if (!(len > 0)) continue;
    ++counted;
    if (std::abs(n.dot(sight)) < kCos80 * len * n.norm()) ++grazing;
  }
  return counted ? double(grazing) / double(counted) : 0.0;
}

}  // namespace

ViewpointEstimate estimate_viewpoint(const std::vector<Vec3f>& points,
                                     const std::vector<Vec3f>& normals) {
  if (normals.size() != points.size())
    throw InvalidInput("viewpoint: normals and points differ in count");
  ViewpointEstimate e;
  std::size_t with_normal = 0;
  for (const Vec3f& n : normals) with_normal += n.squaredNorm() > 0;
  if (with_normal < kMinPoints) return e;
  e.grazing_origin = e.grazing_estimate = grazing_share(points, normals, Vec3d::Zero(), false);
  if (e.grazing_origin <= kMaxGrazingShare) return e;

  // The dominant normal direction, and the view's centroid and extent.
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  Vec3d centroid = Vec3d::Zero();
  Aabb box;
  for (std::size_t i = 0; i < points.size(); ++i) {
    centroid += points[i].cast<double>();
    box.extend(points[i]);
    const Vec3d n = normals[i].cast<double>();
    if (n.squaredNorm() > 0) scatter += n.normalized() * n.normalized().transpose();
  }
  centroid /= double(points.size());
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver(scatter);
  Vec3d d = solver.eigenvectors().col(2).normalized();
  // The side: with normals turned towards d, the view should bulge towards d.
  double bulge = 0;
  for (std::size_t i = 0; i < points.size(); ++i) {
    Vec3d n = normals[i].cast<double>();
    if (n.squaredNorm() == 0) continue;
    if (n.dot(d) < 0) n = -n;
    bulge += n.normalized().dot(points[i].cast<double>() - centroid);
  }
  // A flat view does not say which side it was seen from: the origin stays.
  const double extent = std::max(double(box.diagonal()), 1e-6);
  if (std::abs(bulge) < kMinBulge * double(points.size()) * extent) return e;
  if (bulge < 0) d = -d;
  e.grazing_estimate = grazing_share(points, normals, d, true);
  // A sampling that is even over the surface (voxel grids, synthetic views) sees
  // its silhouette band from any viewpoint: the origin stays unless the estimate
  // passes the test the origin fails, and clearly.
  if (e.grazing_estimate > kMaxGrazingShare ||
      e.grazing_estimate > kGrazingRatio * e.grazing_origin) {
    e.grazing_estimate = e.grazing_origin;
    return e;
  }
  e.at_origin = false;
  e.viewpoint = (centroid + kFarExtents * extent * d).cast<float>();
  return e;
}

}  // namespace station
