// SDM helpers: midpoint subdivision, point-triangle distance, the icosphere template,
// landmark files (mesh topology and checks: core/mesh_topology.h).
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <numeric>
#include <sstream>
#include <unordered_map>

#include <Eigen/Geometry>

#include "core/error.h"
#include "core/io.h"
#include "reconstruct/sdm.h"
#include "reconstruct/detail/sdm_internal.h"

namespace station {

namespace sdm_detail {

void subdivide_midpoint(std::vector<Vec3f>& v, std::vector<Face>& f, bool normalise) {
  std::unordered_map<std::uint64_t, int> mid;
  auto midpoint = [&](int a, int b) {
    const std::uint64_t key = (std::uint64_t(std::min(a, b)) << 32) | std::uint32_t(std::max(a, b));
    auto it = mid.find(key);
    if (it != mid.end()) return it->second;
    const Vec3f m = 0.5f * (v[a] + v[b]);
    v.push_back(normalise ? Vec3f(m.normalized()) : m);
    return mid[key] = int(v.size()) - 1;
  };
  std::vector<Face> nf;
  nf.reserve(f.size() * 4);
  for (const Face& fc : f) {
    const int a = midpoint(fc[0], fc[1]), b = midpoint(fc[1], fc[2]), c = midpoint(fc[2], fc[0]);
    nf.push_back({fc[0], a, c});
    nf.push_back({fc[1], b, a});
    nf.push_back({fc[2], c, b});
    nf.push_back({a, b, c});
  }
  f.swap(nf);
}

float point_triangle_dist2(const Vec3f& p, const Vec3f& a, const Vec3f& b, const Vec3f& c) {
  // Closest point by Voronoi regions of the triangle (vertex, edge, face).
  const Vec3f ab = b - a, ac = c - a, ap = p - a;
  const float d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return ap.squaredNorm();
  const Vec3f bp = p - b;
  const float d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return bp.squaredNorm();
  const float vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) {
    const float v = d1 / (d1 - d3);
    return (ap - v * ab).squaredNorm();
  }
  const Vec3f cp = p - c;
  const float d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return cp.squaredNorm();
  const float vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) {
    const float w = d2 / (d2 - d6);
    return (ap - w * ac).squaredNorm();
  }
  const float va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
    const float w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    return (bp - w * (c - b)).squaredNorm();
  }
  const float denom = va + vb + vc;
  if (!(std::abs(denom) > 0)) {  // degenerate triangle: nearest of its edges
    auto seg = [&](const Vec3f& s, const Vec3f& e) {
      const Vec3f d = e - s;
      const float l2 = d.squaredNorm();
      const float t = l2 > 0 ? std::clamp((p - s).dot(d) / l2, 0.f, 1.f) : 0.f;
      return (p - s - t * d).squaredNorm();
    };
    return std::min({seg(a, b), seg(b, c), seg(c, a)});
  }
  const float v = vb / denom, w = vc / denom;
  return (ap - v * ab - w * ac).squaredNorm();
}

}  // namespace sdm_detail

Mesh make_icosphere_template(int level) {
  if (level < 0 || level > 7)
    throw InvalidInput("icosphere: level " + std::to_string(level) + " outside 0..7");
  const float g = (1.f + std::sqrt(5.f)) / 2.f;
  std::vector<Vec3f> v = {{-1, g, 0}, {1, g, 0},  {-1, -g, 0}, {1, -g, 0},
                          {0, -1, g}, {0, 1, g},  {0, -1, -g}, {0, 1, -g},
                          {g, 0, -1}, {g, 0, 1},  {-g, 0, -1}, {-g, 0, 1}};
  for (auto& p : v) p.normalize();
  std::vector<Face> f = {{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11},
                         {1, 5, 9},  {5, 11, 4}, {11, 10, 2}, {10, 7, 6}, {7, 1, 8},
                         {3, 9, 4},  {3, 4, 2},  {3, 2, 6},   {3, 6, 8},  {3, 8, 9},
                         {4, 9, 5},  {2, 4, 11}, {6, 2, 10},  {8, 6, 7},  {9, 8, 1}};
  for (int l = 0; l < level; ++l) sdm_detail::subdivide_midpoint(v, f, true);
  Mesh m;
  m.vertices = std::move(v);
  m.faces = std::move(f);
  m.normals = m.vertices;
  return m;
}

std::vector<Landmark> read_landmarks(const std::string& path) {
  // Read whole (a folder was read as no landmarks, silently; a device without end).
  std::istringstream in(read_file_bytes(path));
  std::vector<Landmark> out;
  std::string line;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    const auto first = line.find_first_not_of(" \t\r");
    if (first == std::string::npos || line[first] == '#') continue;
    std::istringstream s(line);
    Landmark l;
    long long idx = 0;
    double x, y, z;
    std::string extra;
    if (!(s >> idx >> x >> y >> z) || (s >> extra))
      throw FormatError(path + ":" + std::to_string(line_no) +
                        ": expected \"vertex_index x y z\"");
    // The coordinates within +-1e9, as the cloud readers' (1e30 put a vertex at 7e29).
    const auto usable = [](double c) { return std::isfinite(c) && std::abs(c) <= 1e9; };
    if (idx < 0 || idx > std::numeric_limits<int>::max() || !usable(x) || !usable(y) || !usable(z))
      throw FormatError(path + ":" + std::to_string(line_no) +
                        ": negative vertex index, or a coordinate not finite or beyond +-1e9");
    l.vertex = int(idx);
    l.point = Vec3f(float(x), float(y), float(z));
    out.push_back(l);
  }
  return out;
}

}  // namespace station
