#pragma once
// Private to bench/: our clouds and meshes to and from Open3D's (positions, normals
// and colours, whichever the source has).
#include <algorithm>
#include <cmath>
#include <cstdint>

#include <open3d/geometry/PointCloud.h>
#include <open3d/geometry/TriangleMesh.h>

#include "core/geometry.h"

namespace station::bench {

inline open3d::geometry::PointCloud to_open3d(const Cloud& cloud) {
  open3d::geometry::PointCloud out;
  out.points_.reserve(cloud.size());
  for (const Vec3f& p : cloud.points) out.points_.push_back(p.cast<double>());
  for (const Vec3f& n : cloud.normals) out.normals_.push_back(n.cast<double>());
  for (const Rgb& c : cloud.colours) out.colors_.emplace_back(c.r / 255.0, c.g / 255.0, c.b / 255.0);
  return out;
}

inline Mesh from_open3d(const open3d::geometry::TriangleMesh& in) {
  Mesh out;
  out.vertices.reserve(in.vertices_.size());
  for (const Eigen::Vector3d& v : in.vertices_) out.vertices.push_back(v.cast<float>());
  for (const Eigen::Vector3i& f : in.triangles_) out.faces.push_back(f);
  for (const Eigen::Vector3d& n : in.vertex_normals_) out.normals.push_back(n.cast<float>());
  auto byte = [](double x) { return std::uint8_t(std::lround(std::clamp(x, 0.0, 1.0) * 255.0)); };
  for (const Eigen::Vector3d& c : in.vertex_colors_) out.colours.push_back(Rgb{byte(c[0]), byte(c[1]), byte(c[2])});
  return out;
}

}  // namespace station::bench
