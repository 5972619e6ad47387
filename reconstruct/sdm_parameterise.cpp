// SDM projection of a mesh onto a plane, sphere or cylinder (paper section 4.2 and
// Fig. 6): the mesh is the SDM, control points are sampled on the simple surface,
// and the fitted positions give UVs.
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <map>

#include "core/error.h"
#include "core/mesh_topology.h"
#include "reconstruct/sdm.h"
#include "reconstruct/detail/sdm_internal.h"

namespace station {
namespace {

constexpr double kPi = 3.14159265358979323846;

Cloud sphere_points(int n) {
  Cloud c;
  const double golden = kPi * (3 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double z = 1 - 2 * (i + 0.5) / n, r = std::sqrt(std::max(0.0, 1 - z * z));
    const Vec3f d(float(r * std::cos(golden * i)), float(r * std::sin(golden * i)), float(z));
    c.points.push_back(d);
    c.normals.push_back(d);
  }
  return c;
}

// Sunflower points on the unit disc in z = `z` with normal (0, 0, nz).
void disc_points(int n, float z, float nz, Cloud& c) {
  const double golden = kPi * (3 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double r = std::sqrt((i + 0.5) / n), a = golden * i;
    c.points.push_back(Vec3f(float(r * std::cos(a)), float(r * std::sin(a)), z));
    c.normals.push_back(Vec3f(0, 0, nz));
  }
}

// The closed cylinder: side area 4 pi, caps pi each.
Cloud cylinder_points(int n) {
  Cloud c;
  const int side = n * 2 / 3, cap = (n - side) / 2;
  const int rings = std::max(2, int(std::sqrt(side / (2 * kPi) * 2)));
  const int per = std::max(3, side / rings);
  for (int i = 0; i < rings; ++i)
    for (int j = 0; j < per; ++j) {
      const double z = -1 + 2 * (i + 0.5) / rings, a = 2 * kPi * (j + 0.5 * (i % 2)) / per;
      c.points.push_back(Vec3f(float(std::cos(a)), float(std::sin(a)), float(z)));
      c.normals.push_back(Vec3f(float(std::cos(a)), float(std::sin(a)), 0));
    }
  disc_points(cap, -1, -1, c);
  disc_points(cap, 1, 1, c);
  return c;
}

float wrap_u(const Vec3f& p) { return float(std::atan2(p.y(), p.x()) / (2 * kPi) + 0.5); }

// The boundary of a disc-topology mesh as one ordered loop, or InvalidInput.
std::vector<int> boundary_loop(const Mesh& mesh) {
  std::map<std::pair<int, int>, int> count;
  for (const Face& f : mesh.faces)
    for (int k = 0; k < 3; ++k) {
      const int a = f[k], b = f[(k + 1) % 3];
      ++count[{std::min(a, b), std::max(a, b)}];
    }
  std::map<int, int> next;  // directed boundary edges as the faces run them
  for (const Face& f : mesh.faces)
    for (int k = 0; k < 3; ++k) {
      const int a = f[k], b = f[(k + 1) % 3];
      if (count[{std::min(a, b), std::max(a, b)}] == 1) next[a] = b;
    }
  if (next.empty()) throw InvalidInput("mesh: closed; a plane needs a mesh with one boundary loop");
  std::vector<int> loop{next.begin()->first};
  while (true) {
    auto it = next.find(loop.back());
    if (it == next.end()) throw InvalidInput("mesh: boundary is not a simple loop");
    if (it->second == loop.front()) break;
    loop.push_back(it->second);
    if (loop.size() > next.size()) throw InvalidInput("mesh: boundary is not a simple loop");
  }
  if (loop.size() != next.size())
    throw InvalidInput("mesh: " + std::to_string(next.size() - loop.size()) +
                       " boundary edges outside the first loop; a plane needs exactly one");
  return loop;
}

}  // namespace

ParameterisationResult sdm_parameterise(const Mesh& mesh, SimpleSurface surface,
                                        const SdmParams& params, int control_points,
                                        const SdmProgress& progress) {
  if (mesh.vertices.empty() || mesh.faces.empty()) throw InvalidInput("mesh: empty");
  if (!all_finite(mesh.vertices)) throw InvalidInput("mesh: non-finite coordinates");
  double mesh_area = 0;
  for (const Face& f : mesh.faces) {
    const Vec3d a = mesh.vertices[std::size_t(f[0])].cast<double>(), b = mesh.vertices[std::size_t(f[1])].cast<double>(),
                c = mesh.vertices[std::size_t(f[2])].cast<double>();
    mesh_area += 0.5 * (b - a).cross(c - a).norm();
  }
  if (!(mesh_area > 0)) throw InvalidInput("mesh: every face has zero area");
  // Each control point holds a few hundred bytes of search and blend state: 1e9 ran the
  // machine out of memory without a word.
  if (control_points < 0 || control_points > 10000000)
    throw InvalidInput("sdm_parameterise: control_points must be 0..10000000, got " + std::to_string(control_points));
  const int nv = int(mesh.vertices.size());
  const int n = control_points > 0 ? control_points : std::max(1000, 4 * nv);
  ParameterisationResult out;
  if (surface == SimpleSurface::kSphere || surface == SimpleSurface::kCylinder) {
    const Cloud cps = surface == SimpleSurface::kSphere ? sphere_points(n) : cylinder_points(n);
    SdmResult r = fit_sdm(mesh, cps, params, {}, progress);
    out.mesh = std::move(r.mesh);
    out.diagnostics = r.diagnostics;
    out.uv.resize(nv);
    for (int i = 0; i < nv; ++i) {
      const Vec3f& p = out.mesh.vertices[i];
      if (surface == SimpleSurface::kSphere) {
        const Vec3f d = p.norm() > 0 ? Vec3f(p.normalized()) : Vec3f(0, 0, 1);
        out.uv[i] = Vec2f(wrap_u(d), float(std::acos(std::clamp(d.z(), -1.f, 1.f)) / kPi));
      } else {
        // Arc length along the profile: bottom centre 0, rim 1, side to 3, top centre 4.
        const float r = p.head<2>().norm();
        const float d_side = std::abs(r - 1), d_bottom = std::abs(p.z() + 1), d_top = std::abs(p.z() - 1);
        float s;
        if (d_side <= d_bottom && d_side <= d_top)
          s = 1 + std::clamp(p.z() + 1, 0.f, 2.f);
        else if (d_bottom < d_top)
          s = std::min(r, 1.f);
        else
          s = 4 - std::min(r, 1.f);
        out.uv[i] = Vec2f(wrap_u(p), s / 4);
      }
    }
    return out;
  }
  // Plane: the mesh must be a disc. Its boundary loop is pinned to the unit circle by
  // arc length; the inside starts as the projection onto the mesh's least-squares
  // plane, scaled into the disc, and the SDM spreads it over the disc's points.
  mesh.check_consistent("mesh");
  const MeshTopology topo = mesh_topology(mesh);
  if (topo.components != 1 || topo.euler != 1 || topo.nonmanifold_edges || topo.nonmanifold_vertices)
    throw InvalidInput("mesh: a plane needs a connected disc (Euler characteristic 1), got " +
                       std::to_string(topo.components) + " component(s), Euler characteristic " +
                       std::to_string(topo.euler));
  const std::vector<int> loop = boundary_loop(mesh);
  Vec3d mean = Vec3d::Zero();
  for (const Vec3f& v : mesh.vertices) mean += v.cast<double>();
  mean /= nv;
  Eigen::Matrix3d C = Eigen::Matrix3d::Zero();
  for (const Vec3f& v : mesh.vertices) C += (v.cast<double>() - mean) * (v.cast<double>() - mean).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(C);
  Vec3d e1 = es.eigenvectors().col(2), e2 = es.eigenvectors().col(1);
  // Orient the frame so that the faces, projected, run counter-clockwise.
  double area = 0;
  for (const Face& f : mesh.faces) {
    auto pr = [&](int i) {
      const Vec3d q = mesh.vertices[i].cast<double>() - mean;
      return Eigen::Vector2d(q.dot(e1), q.dot(e2));
    };
    const Eigen::Vector2d a = pr(f[0]), b = pr(f[1]), c = pr(f[2]);
    area += (b - a).x() * (c - a).y() - (b - a).y() * (c - a).x();
  }
  if (area < 0) e2 = -e2;
  Mesh initial;
  initial.faces = mesh.faces;
  initial.vertices.resize(nv);
  double rmax = 0;
  for (int i = 0; i < nv; ++i) {
    const Vec3d q = mesh.vertices[i].cast<double>() - mean;
    initial.vertices[i] = Vec3f(float(q.dot(e1)), float(q.dot(e2)), 0);
    rmax = std::max(rmax, double(initial.vertices[i].norm()));
  }
  for (auto& v : initial.vertices) v /= float(rmax > 0 ? rmax : 1);
  // Boundary on the circle by arc length, starting at the loop's first vertex's angle.
  std::vector<double> cum(loop.size() + 1, 0);
  for (std::size_t k = 0; k < loop.size(); ++k)
    cum[k + 1] = cum[k] + (mesh.vertices[loop[(k + 1) % loop.size()]] - mesh.vertices[loop[k]]).norm();
  const double a0 = std::atan2(initial.vertices[loop[0]].y(), initial.vertices[loop[0]].x());
  std::vector<char> pinned(nv, 0);
  for (std::size_t k = 0; k < loop.size(); ++k) {
    const double a = a0 + 2 * kPi * cum[k] / std::max(cum.back(), 1e-30);
    initial.vertices[loop[k]] = Vec3f(float(std::cos(a)), float(std::sin(a)), 0);
    pinned[loop[k]] = 1;
  }
  Cloud cps;
  disc_points(n, 0, 1, cps);
  SdmParams p = params;
  p.place_template = false;
  SdmDiagnostics dg;
  dg.template_vertices = nv;
  dg.template_faces = int(mesh.faces.size());
  dg.control_points = n;
  SdmResult r = sdm_detail::run_sdm(initial, cps, p, {}, pinned, progress, dg);
  out.mesh = std::move(r.mesh);
  out.diagnostics = r.diagnostics;
  out.uv.resize(nv);
  for (int i = 0; i < nv; ++i)
    out.uv[i] = Vec2f((out.mesh.vertices[i].x() + 1) / 2, (out.mesh.vertices[i].y() + 1) / 2);
  return out;
}

}  // namespace station
