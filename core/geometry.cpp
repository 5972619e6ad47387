#include "core/geometry.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <utility>
#include <string>

#include "core/error.h"

namespace station {

namespace {

std::string size_problem(const char* what, const char* attribute, std::size_t got,
                         std::size_t want) {
  return std::string(what) + ": " + attribute + " has " + std::to_string(got) +
         " entries, expected " + std::to_string(want);
}

}  // namespace

void Cloud::check_consistent(const char* what) const {
  if (!normals.empty() && normals.size() != points.size())
    throw InvalidInput(size_problem(what, "normals", normals.size(), points.size()));
  if (!colours.empty() && colours.size() != points.size())
    throw InvalidInput(size_problem(what, "colours", colours.size(), points.size()));
}

void Mesh::check_consistent(const char* what) const {
  if (!normals.empty() && normals.size() != vertices.size())
    throw InvalidInput(size_problem(what, "normals", normals.size(), vertices.size()));
  if (!colours.empty() && colours.size() != vertices.size())
    throw InvalidInput(size_problem(what, "colours", colours.size(), vertices.size()));
  const auto n = static_cast<long long>(vertices.size());
  for (std::size_t f = 0; f < faces.size(); ++f) {
    for (int k = 0; k < 3; ++k) {
      const long long i = faces[f][k];
      if (i < 0 || i >= n)
        throw InvalidInput(std::string(what) + ": face " + std::to_string(f) + " has vertex index " +
                           std::to_string(i) + " outside [0, " + std::to_string(n) + ")");
    }
  }
}

Cloud Mesh::as_cloud() const {
  Cloud c;
  c.points = vertices;
  c.normals = normals;
  c.colours = colours;
  return c;
}

Aabb bounding_box(const std::vector<Vec3f>& points) {
  Aabb box;
  for (const Vec3f& p : points) box.extend(p);
  return box;
}

namespace {

// The low 21 bits of x, spread to every third bit.
std::uint64_t spread_bits3(std::uint64_t x) {
  x &= 0x1fffff;
  x = (x | x << 32) & 0x1f00000000ffffull;
  x = (x | x << 16) & 0x1f0000ff0000ffull;
  x = (x | x << 8) & 0x100f00f00f00f00full;
  x = (x | x << 4) & 0x10c30c30c30c30c3ull;
  x = (x | x << 2) & 0x1249249249249249ull;
  return x;
}

}  // namespace

std::vector<std::uint32_t> spatial_order(const std::vector<Vec3f>& points) {
  if (points.size() > std::numeric_limits<std::uint32_t>::max())
    throw InvalidInput("spatial_order: more than 2^32 - 1 points");
  Aabb box;
  for (const Vec3f& p : points)
    if (p.allFinite()) box.extend(p);
  std::vector<std::pair<std::uint64_t, std::uint32_t>> keys(points.size());
  const double side = box.valid() ? double((box.max - box.min).maxCoeff()) : 0.0;
  const double scale = side > 0 ? double((1u << 21) - 1) / side : 0.0;
  for (std::size_t i = 0; i < points.size(); ++i) {
    std::uint64_t key = 0;
    if (points[i].allFinite()) {
      std::uint64_t q[3];
      for (int a = 0; a < 3; ++a)
        q[a] = std::uint64_t(std::clamp((double(points[i][a]) - double(box.min[a])) * scale, 0.0, double((1u << 21) - 1)));
      key = 1 + (spread_bits3(q[0]) | spread_bits3(q[1]) << 1 | spread_bits3(q[2]) << 2);
    }
    keys[i] = {key, std::uint32_t(i)};
  }
  std::sort(keys.begin(), keys.end());  // (key, index): ties in index order
  std::vector<std::uint32_t> order(points.size());
  for (std::size_t i = 0; i < keys.size(); ++i) order[i] = keys[i].second;
  return order;
}

Cloud reordered(const Cloud& cloud, const std::vector<std::uint32_t>& order) {
  cloud.check_consistent("reordered cloud");
  Cloud out;
  out.points.reserve(order.size());
  if (cloud.has_normals()) out.normals.reserve(order.size());
  if (cloud.has_colours()) out.colours.reserve(order.size());
  for (const std::uint32_t i : order) {
    if (i >= cloud.size()) throw InvalidInput("reordered: index " + std::to_string(i) + " out of range");
    out.points.push_back(cloud.points[i]);
    if (cloud.has_normals()) out.normals.push_back(cloud.normals[i]);
    if (cloud.has_colours()) out.colours.push_back(cloud.colours[i]);
  }
  return out;
}

bool all_finite(const std::vector<Vec3f>& points) {
  for (const Vec3f& p : points)
    if (!std::isfinite(p.x()) || !std::isfinite(p.y()) || !std::isfinite(p.z())) return false;
  return true;
}

std::vector<Vec3f> vertex_normals(const Mesh& mesh) {
  const auto n = static_cast<long long>(mesh.vertices.size());
  // Accumulate in double: large meshes sum many small cross products.
  std::vector<Vec3d> acc(mesh.vertices.size(), Vec3d::Zero());
  for (std::size_t f = 0; f < mesh.faces.size(); ++f) {
    const Face& face = mesh.faces[f];
    for (int k = 0; k < 3; ++k)
      if (face[k] < 0 || face[k] >= n)
        throw InvalidInput("vertex_normals: face " + std::to_string(f) +
                           " has an out-of-range vertex index " + std::to_string(face[k]));
    const Vec3d a = mesh.vertices[face[0]].cast<double>();
    const Vec3d b = mesh.vertices[face[1]].cast<double>();
    const Vec3d c = mesh.vertices[face[2]].cast<double>();
    // The unnormalised cross product's length is twice the area: area weighting for free.
    const Vec3d w = (b - a).cross(c - a);
    for (int k = 0; k < 3; ++k) acc[face[k]] += w;
  }
  std::vector<Vec3f> out(acc.size(), Vec3f::Zero());
  for (std::size_t i = 0; i < acc.size(); ++i) {
    const double len = acc[i].norm();
    if (len > 0 && std::isfinite(len)) out[i] = (acc[i] / len).cast<float>();
  }
  return out;
}

void transform_cloud(Cloud& cloud, const Eigen::Matrix4d& T) {
  const Eigen::Matrix3d A = T.topLeftCorner<3, 3>();
  const Vec3d t = T.topRightCorner<3, 1>();
  for (Vec3f& p : cloud.points) p = (A * p.cast<double>() + t).cast<float>();
  if (cloud.normals.empty()) return;
  // Normals transform by the inverse transpose (equal to A for a rotation); for a
  // singular A there is no such matrix, so fall back to A itself.
  const double det = A.determinant();
  const Eigen::Matrix3d N = (std::abs(det) > 1e-12) ? Eigen::Matrix3d(A.inverse().transpose()) : A;
  for (Vec3f& nrm : cloud.normals) {
    Vec3d v = N * nrm.cast<double>();
    const double len = v.norm();
    if (len > 0 && std::isfinite(len)) v /= len;
    nrm = v.cast<float>();
  }
}

}  // namespace station
