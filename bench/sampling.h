#pragma once
// Private to bench/: clouds sampled on the textured reference meshes.
#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include <Eigen/Geometry>

#include "core/geometry.h"
#include "core/texture.h"
#include "harness.h"

namespace station::bench {

/// The textured YCB mustard bottle: ../shared/data's when there (and not
/// --generate), else the bundled copy of the same model; `shared` says which.
inline fs::path mustard_obj(const Options& options, bool* shared) {
  const fs::path obj = options.shared_dir / "textured_objects" / "006_mustard_bottle" / "textured.obj";
  *shared = options.use_shared && fs::exists(obj);
  return *shared ? obj : options.source_dir / "data" / "mustard_bottle" / "textured.obj";
}

/// Area-uniform samples on a textured mesh: positions, normals interpolated from
/// the area-weighted vertex normals, colours from the texture (surface_color).
inline Cloud sample_textured(const TexturedMesh& tm, const Texture& texture, int count, unsigned seed) {
  const Mesh& mesh = tm.mesh;
  const std::vector<Vec3f> vn = vertex_normals(mesh);
  std::vector<double> cumulative(mesh.faces.size());
  double total = 0;
  for (std::size_t f = 0; f < mesh.faces.size(); ++f) {
    const Face& t = mesh.faces[f];
    const Vec3d a = mesh.vertices[t[0]].cast<double>(), b = mesh.vertices[t[1]].cast<double>(),
                c = mesh.vertices[t[2]].cast<double>();
    total += 0.5 * (b - a).cross(c - a).norm();
    cumulative[f] = total;
  }
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  Cloud cloud;
  cloud.points.reserve(count);
  cloud.normals.reserve(count);
  cloud.colours.reserve(count);
  for (int i = 0; i < count; ++i) {
    const double pick = unit(rng) * total;
    const int f = int(std::min<std::size_t>(
        std::lower_bound(cumulative.begin(), cumulative.end(), pick) - cumulative.begin(),
        mesh.faces.size() - 1));
    double r1 = std::sqrt(unit(rng)), r2 = unit(rng);
    const double u = r1 * (1 - r2), v = r1 * r2;  // point = (1-u-v) a + u b + v c
    const Face& t = mesh.faces[f];
    const Vec3f p = float(1 - u - v) * mesh.vertices[t[0]] + float(u) * mesh.vertices[t[1]] +
                    float(v) * mesh.vertices[t[2]];
    Vec3f n = float(1 - u - v) * vn[t[0]] + float(u) * vn[t[1]] + float(v) * vn[t[2]];
    if (n.norm() < 1e-12f) {
      n = (mesh.vertices[t[1]] - mesh.vertices[t[0]]).cross(mesh.vertices[t[2]] - mesh.vertices[t[0]]);
    }
    cloud.points.push_back(p);
    cloud.normals.push_back(n.normalized());
    cloud.colours.push_back(surface_colour(tm, texture, f, u, v));
  }
  return cloud;
}

}  // namespace station::bench
