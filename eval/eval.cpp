#include "eval/eval.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <random>
#include <string>

#include <Eigen/Geometry>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/task_arena.h>

#include "core/bvh.h"
#include "core/error.h"
#include "core/kdtree.h"
#include "core/threads.h"

namespace station {

namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

Vec3f to_unit_rgb(const Rgb& c) { return Vec3f(c.r, c.g, c.b) / 255.f; }

// A unit normal, or NaN when the input has no usable direction (zero or
// non-finite), so that the pair is left out of the normal consistency.
Vec3f unit_or_nan(const Vec3f& n) {
  const float len = n.norm();
  if (!(len > 0.f) || !std::isfinite(len)) return Vec3f::Constant(kNaN);
  return n / len;
}

// 53-bit uniform double in [0, 1) from two 32-bit draws. Spelled out rather than
// std::uniform_real_distribution, whose output differs between standard
// libraries; the samples (and so every metric) then depend on the seed alone.
double uniform01(std::mt19937& rng) {
  const std::uint32_t a = rng() >> 5, b = rng() >> 6;
  return (a * 67108864.0 + b) * (1.0 / 9007199254740992.0);
}

// The points one side contributes: a cloud's points or a mesh's samples.
struct Queries {
  std::vector<Vec3f> points;
  std::vector<Vec3f> normals;  ///< unit (or NaN = unusable); empty when none
  std::vector<Vec3f> colours;   ///< RGB in [0,1]; empty when none
};

std::vector<Vec3f> face_normals(const Mesh& mesh) {
  std::vector<Vec3f> n(mesh.faces.size());
  for (std::size_t f = 0; f < mesh.faces.size(); ++f) {
    const Face& t = mesh.faces[f];
    const Vec3d a = mesh.vertices[t[0]].cast<double>(), b = mesh.vertices[t[1]].cast<double>(),
                c = mesh.vertices[t[2]].cast<double>();
    n[f] = unit_or_nan((b - a).cross(c - a).normalized().cast<float>());
  }
  return n;
}

// Area-uniform samples with float colours (kept unrounded for the colour error).
using SurfaceColour = std::function<Rgb(int, double, double)>;

Queries sample_surface(const Mesh& mesh, int count, unsigned seed, const std::string& what,
                       const SurfaceColour& surface_colour = {}) {
  if (count < 0) throw InvalidInput(what + ": negative sample count");
  if (mesh.faces.empty()) throw InvalidInput(what + ": mesh has no faces");
  mesh.check_consistent(what.c_str());

  const std::size_t nf = mesh.faces.size();
  std::vector<double> cumulative(nf);
  double total = 0;
  for (std::size_t f = 0; f < nf; ++f) {
    const Face& t = mesh.faces[f];
    const Vec3d a = mesh.vertices[t[0]].cast<double>(), b = mesh.vertices[t[1]].cast<double>(),
                c = mesh.vertices[t[2]].cast<double>();
    total += 0.5 * (b - a).cross(c - a).norm();
    cumulative[f] = total;
  }
  if (!(total > 0) || !std::isfinite(total))
    throw InvalidInput(what + ": mesh has zero or non-finite area");

  const std::vector<Vec3f> fn = face_normals(mesh);
  const bool coloured = surface_colour || mesh.has_colours();
  Queries out;
  out.points.resize(count);
  out.normals.resize(count);
  if (coloured) out.colours.resize(count);

  std::mt19937 rng(seed);
  for (int i = 0; i < count; ++i) {
    // upper_bound never lands on a zero-area face: its cumulative value equals
    // its predecessor's, which is already <= r.
    const double r = uniform01(rng) * total;
    const std::size_t f =
        std::min<std::size_t>(std::upper_bound(cumulative.begin(), cumulative.end(), r) -
                                  cumulative.begin(),
                              nf - 1);
    // sqrt(r1) makes the barycentrics uniform over the triangle's area.
    const double s = std::sqrt(uniform01(rng)), r2 = uniform01(rng);
    const double w0 = 1 - s, w1 = s * (1 - r2), w2 = s * r2;
    const Face& t = mesh.faces[f];
    out.points[i] = (w0 * mesh.vertices[t[0]].cast<double>() + w1 * mesh.vertices[t[1]].cast<double>() +
                     w2 * mesh.vertices[t[2]].cast<double>())
                        .cast<float>();
    out.normals[i] = fn[f];
    if (surface_colour)
      out.colours[i] = to_unit_rgb(surface_colour(int(f), w1, w2));
    else if (coloured)
      out.colours[i] = float(w0) * to_unit_rgb(mesh.colours[t[0]]) +
                      float(w1) * to_unit_rgb(mesh.colours[t[1]]) +
                      float(w2) * to_unit_rgb(mesh.colours[t[2]]);
  }
  return out;
}

Queries cloud_queries(const Cloud& cloud) {
  Queries q;
  q.points = cloud.points;
  if (cloud.has_normals()) {
    q.normals.resize(cloud.size());
    for (std::size_t i = 0; i < cloud.size(); ++i) q.normals[i] = unit_or_nan(cloud.normals[i]);
  }
  if (cloud.has_colours()) {
    q.colours.resize(cloud.size());
    for (std::size_t i = 0; i < cloud.size(); ++i) q.colours[i] = to_unit_rgb(cloud.colours[i]);
  }
  return q;
}

// One validated input: a mesh with faces, or a cloud (a faceless mesh becomes
// the cloud of its vertices).
struct Side {
  std::string name;
  const Mesh* mesh = nullptr;
  Cloud cloud;  // used when mesh is null
  SurfaceColour surface_colour;  // only with a mesh

  bool has_normals() const { return mesh || cloud.has_normals(); }
  bool has_colours() const {
    return mesh ? bool(surface_colour) || mesh->has_colours() : cloud.has_colours();
  }
};

Side prepare(const Shape& shape, const std::string& name, const SurfaceColour& surface_colour) {
  Side side;
  side.name = name;
  if (const Mesh* m = std::get_if<Mesh>(&shape)) {
    if (m->vertices.empty()) throw InvalidInput(name + ": empty");
    m->check_consistent(name.c_str());
    if (!all_finite(m->vertices)) throw InvalidInput(name + ": non-finite coordinates");
    if (!m->faces.empty()) {
      side.mesh = m;
      side.surface_colour = surface_colour;
    } else {
      side.cloud.points = m->vertices;
      side.cloud.normals = m->normals;
      side.cloud.colours = m->colours;
    }
  } else {
    const Cloud& c = std::get<Cloud>(shape);
    if (c.empty()) throw InvalidInput(name + ": empty");
    c.check_consistent(name.c_str());
    if (!all_finite(c.points)) throw InvalidInput(name + ": non-finite coordinates");
    side.cloud = c;
  }
  return side;
}

// What the other side's points are measured against: the exact surface of a
// mesh (BVH) or the nearest point of a cloud (k-d tree).
class Target {
 public:
  struct Hit {
    double distance;
    Vec3f normal;  ///< unit or NaN
    Vec3f colour;   ///< RGB in [0,1]; unset without colours
  };

  explicit Target(const Side& side) : side_(side) {
    if (side.mesh) {
      bvh_ = std::make_unique<TriangleBvh>(*side.mesh);
      normals_ = face_normals(*side.mesh);
      if (side.mesh->has_colours())
        for (const Rgb& c : side.mesh->colours) colours_.push_back(to_unit_rgb(c));
    } else {
      index_ = std::make_unique<PointIndex>(side.cloud.points);
      for (const Vec3f& n : side.cloud.normals) normals_.push_back(unit_or_nan(n));
      for (const Rgb& c : side.cloud.colours) colours_.push_back(to_unit_rgb(c));
    }
  }

  Hit query(const Vec3f& q) const {
    Hit h{0, Vec3f::Constant(kNaN), Vec3f::Zero()};
    if (bvh_) {
      const ClosestPoint cp = bvh_->closest_point(q.cast<double>());
      h.distance = cp.distance;
      h.normal = normals_[cp.face];
      if (side_.surface_colour) {
        h.colour = to_unit_rgb(side_.surface_colour(cp.face, cp.u, cp.v));
      } else if (!colours_.empty()) {
        const Face& t = side_.mesh->faces[cp.face];
        h.colour = float(1 - cp.u - cp.v) * colours_[t[0]] + float(cp.u) * colours_[t[1]] +
                  float(cp.v) * colours_[t[2]];
      }
    } else {
      const int i = index_->nearest(q).first;
      // Recomputed in double: nanoflann's float squared distance loses the
      // small distances between nearly coincident shapes.
      h.distance = (q.cast<double>() - side_.cloud.points[i].cast<double>()).norm();
      if (!normals_.empty()) h.normal = normals_[i];
      if (!colours_.empty()) h.colour = colours_[i];
    }
    return h;
  }

 private:
  const Side& side_;
  std::unique_ptr<TriangleBvh> bvh_;
  std::unique_ptr<PointIndex> index_;
  std::vector<Vec3f> normals_;
  std::vector<Vec3f> colours_;
};

struct Directed {
  DirectedStats stats;
  std::optional<double> normal_consistency;
  std::optional<double> colour_error;
};

// Distances (and normal/colour agreement) from every query point to the target.
// Each query writes only its own slot and the sums run in index order, so the
// result does not depend on the thread count or scheduling.
Directed measure(const Queries& from, const Target& to, bool with_normals, bool with_colours) {
  const std::size_t n = from.points.size();
  std::vector<double> dist(n);
  std::vector<float> ndot(with_normals ? n : 0);
  std::vector<float> cerr(with_colours ? n : 0);
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, 256), [&](const auto& range) {
    for (std::size_t i = range.begin(); i != range.end(); ++i) {
      const Target::Hit h = to.query(from.points[i]);
      dist[i] = h.distance;
      if (with_normals) ndot[i] = std::abs(from.normals[i].dot(h.normal));  // NaN if unusable
      if (with_colours) cerr[i] = (from.colours[i] - h.colour).cwiseAbs().sum();
    }
  });

  Directed d;
  double sum = 0, sum_sq = 0, max = 0;
  for (double x : dist) {
    sum += x;
    sum_sq += x * x;
    max = std::max(max, x);
  }
  d.stats.count = n;
  d.stats.mean = sum / double(n);
  d.stats.rms = std::sqrt(sum_sq / double(n));
  d.stats.max = max;
  // Nearest-rank 95th percentile: the smallest value with at least 95 % of the
  // distances at or below it.
  const std::size_t rank = std::size_t(std::ceil(0.95 * double(n))) - 1;
  std::nth_element(dist.begin(), dist.begin() + rank, dist.end());
  d.stats.p95 = dist[rank];

  if (with_normals) {
    double s = 0;
    std::size_t c = 0;
    for (float v : ndot)
      if (std::isfinite(v)) {
        s += std::min(v, 1.f);  // rounding can push |n.n| a hair above 1
        ++c;
      }
    if (c > 0) d.normal_consistency = s / double(c);
  }
  if (with_colours) {
    double s = 0;
    for (float v : cerr) s += v;
    d.colour_error = s / double(n);
  }
  return d;
}

}  // namespace

Cloud sample_mesh(const Mesh& mesh, int count, unsigned seed) {
  Queries q = sample_surface(mesh, count, seed, "mesh");
  Cloud c;
  c.points = std::move(q.points);
  c.normals = std::move(q.normals);
  for (const Vec3f& col : q.colours) {
    auto to8 = [](float v) { return std::uint8_t(std::lround(std::clamp(v, 0.f, 1.f) * 255.f)); };
    c.colours.push_back(Rgb{to8(col.x()), to8(col.y()), to8(col.z())});
  }
  return c;
}

EvalResult evaluate(const Shape& a, const Shape& b, const EvalParams& params) {
  if (params.mesh_samples <= 0) throw InvalidInput("eval: mesh_samples must be positive");
  if (params.threads < 0) throw InvalidInput("eval: threads must be >= 0");
  const Side side_a = prepare(a, "A", params.a_surface_colour);
  const Side side_b = prepare(b, "B", params.b_surface_colour);

  const int threads =
      worker_threads(std::max(params.threads, 0));
  tbb::task_arena arena(threads);
  EvalResult result;
  arena.execute([&] {
    Queries qa, qb;
    std::unique_ptr<Target> ta, tb;
    // Sampling is sequential per mesh (one seeded stream); the four set-up jobs
    // are independent, so they overlap.
    auto queries_of = [&](const Side& s, Queries& q) {
      q = s.mesh ? sample_surface(*s.mesh, params.mesh_samples, params.seed, s.name,
                                  s.surface_colour)
                 : cloud_queries(s.cloud);
    };
    tbb::parallel_invoke([&] { queries_of(side_a, qa); }, [&] { queries_of(side_b, qb); },
                         [&] { ta = std::make_unique<Target>(side_a); },
                         [&] { tb = std::make_unique<Target>(side_b); });

    const bool normals = side_a.has_normals() && side_b.has_normals();
    const bool colours = side_a.has_colours() && side_b.has_colours();
    // e_col is taken at B's (the reference's) points only, see eval.h.
    const Directed ab = measure(qa, *tb, normals, false);
    const Directed ba = measure(qb, *ta, normals, colours);

    result.a_to_b = ab.stats;
    result.b_to_a = ba.stats;
    result.chamfer = 0.5 * (ab.stats.mean + ba.stats.mean);
    result.hausdorff = std::max(ab.stats.max, ba.stats.max);
    result.p95 = std::max(ab.stats.p95, ba.stats.p95);
    if (ab.normal_consistency && ba.normal_consistency)
      result.normal_consistency = 0.5 * (*ab.normal_consistency + *ba.normal_consistency);
    else if (ab.normal_consistency || ba.normal_consistency)
      result.normal_consistency = ab.normal_consistency ? ab.normal_consistency : ba.normal_consistency;
    result.colour_error = ba.colour_error;
  });
  return result;
}

ColourTransition measure_colour_transition(const Mesh& mesh,
                                           const std::function<double(const Vec3d&)>& signed_distance,
                                           const Rgb& a, const Rgb& b, double cell) {
  const Vec3d ca(a.r, a.g, a.b), axis = Vec3d(b.r, b.g, b.b) - ca;
  ColourTransition out;
  out.vertices = std::min(mesh.vertices.size(), mesh.colours.size());
  std::vector<double> band;
  for (std::size_t i = 0; i < out.vertices; ++i) {
    const double t = (Vec3d(mesh.colours[i].r, mesh.colours[i].g, mesh.colours[i].b) - ca).dot(axis) / axis.squaredNorm();
    const double s = signed_distance(mesh.vertices[i].cast<double>());
    if (t > 0.1 && t < 0.9) {
      band.push_back(std::abs(s));
      out.max_band = std::max(out.max_band, std::abs(s));
    }
    if ((t > 0.5 && s < 0) || (t < 0.5 && s > 0)) {
      ++out.wrong;
      out.wrong_far += std::abs(s) > cell;
      out.max_wrong = std::max(out.max_wrong, std::abs(s));
    }
  }
  out.band = band.size();
  if (!band.empty()) {
    std::sort(band.begin(), band.end());
    out.width = 2 * band[std::min(band.size() - 1, std::size_t(0.95 * double(band.size())))];
  }
  return out;
}

}  // namespace station
