#include "core/bvh.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include <Eigen/Geometry>

#include "core/error.h"
#include "test_util.h"

namespace station {
namespace {

// Analytic ray-sphere intersection (nearest t >= 0), for the reference.
std::optional<double> ray_sphere(const Vec3d& o, const Vec3d& d, const Vec3d& c, double r) {
  const Vec3d oc = o - c;
  const double a = d.squaredNorm(), b = 2 * oc.dot(d), cc = oc.squaredNorm() - r * r;
  const double disc = b * b - 4 * a * cc;
  if (disc < 0) return std::nullopt;
  const double s = std::sqrt(disc);
  const double t0 = (-b - s) / (2 * a), t1 = (-b + s) / (2 * a);
  if (t0 >= 0) return t0;
  if (t1 >= 0) return t1;
  return std::nullopt;
}

Vec3d vertex(const Mesh& m, int face, int k) { return m.vertices[m.faces[face][k]].cast<double>(); }

Vec3d bary_point(const Mesh& m, int face, double u, double v) {
  return (1 - u - v) * vertex(m, face, 0) + u * vertex(m, face, 1) + v * vertex(m, face, 2);
}

// Independent reference for closest_point: plane projection when it falls
// inside the triangle, else the nearest of the three edges.
double segment_distance(const Vec3d& p, const Vec3d& a, const Vec3d& b) {
  const Vec3d ab = b - a;
  const double l2 = ab.squaredNorm();
  const double s = l2 > 0 ? std::clamp((p - a).dot(ab) / l2, 0.0, 1.0) : 0.0;
  return (a + s * ab - p).norm();
}

double triangle_distance(const Vec3d& p, const Vec3d& a, const Vec3d& b, const Vec3d& c) {
  const Vec3d n = (b - a).cross(c - a);
  const double n2 = n.squaredNorm();
  if (n2 > 1e-30) {
    const Vec3d q = p - n * ((p - a).dot(n) / n2);
    const double wa = (b - q).cross(c - q).dot(n), wb = (c - q).cross(a - q).dot(n),
                 wc = (a - q).cross(b - q).dot(n);
    if (wa >= 0 && wb >= 0 && wc >= 0) return (p - q).norm();
  }
  return std::min({segment_distance(p, a, b), segment_distance(p, b, c), segment_distance(p, c, a)});
}

double brute_closest(const Mesh& m, const Vec3d& p) {
  double best = std::numeric_limits<double>::infinity();
  for (int f = 0; f < int(m.faces.size()); ++f)
    best = std::min(best, triangle_distance(p, vertex(m, f, 0), vertex(m, f, 1), vertex(m, f, 2)));
  return best;
}

Mesh random_soup(int n, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> pos(-1.f, 1.f), small(-0.15f, 0.15f);
  Mesh m;
  for (int i = 0; i < n; ++i) {
    const Vec3f c(pos(rng), pos(rng), pos(rng));
    for (int k = 0; k < 3; ++k) m.vertices.push_back(c + Vec3f(small(rng), small(rng), small(rng)));
    m.faces.push_back({3 * i, 3 * i + 1, 3 * i + 2});
  }
  return m;
}

TEST(Bvh, RejectsEmptyAndBadMeshes) {
  EXPECT_THROW(TriangleBvh(Mesh{}), InvalidInput);
  Mesh m = test::box({0, 0, 0}, {1, 1, 1});
  m.faces.push_back({0, 1, 8});
  EXPECT_THROW(TriangleBvh{m}, InvalidInput);
  m.faces.back() = {-1, 0, 1};
  EXPECT_THROW(TriangleBvh{m}, InvalidInput);
  Mesh nan_mesh = test::box({0, 0, 0}, {1, 1, 1});
  nan_mesh.vertices[3].x() = std::nanf("");
  EXPECT_THROW(TriangleBvh{nan_mesh}, InvalidInput);
}

TEST(Bvh, SphereHitsMatchAnalytic) {
  const double radius = 1.0;
  const Mesh m = test::icosphere(4, radius);
  const TriangleBvh bvh(m);
  EXPECT_EQ(bvh.triangle_count(), m.faces.size());
  std::mt19937 rng(7);
  std::normal_distribution<double> g;
  std::uniform_real_distribution<double> off(-1.3, 1.3);
  // Faceting: the flat faces lie at most ~1e-3 inside the sphere (level 4).
  const double facet = 1.5e-3;
  int hits = 0, misses = 0;
  for (int i = 0; i < 4000; ++i) {
    Vec3d o(g(rng), g(rng), g(rng));
    o = o.normalized() * 3.0;
    const Vec3d target(off(rng), off(rng), off(rng));
    const Vec3d d = (target - o) * 0.7;  // deliberately not unit length
    const auto ref = ray_sphere(o, d, Vec3d::Zero(), radius);
    const auto ref_inner = ray_sphere(o, d, Vec3d::Zero(), radius - facet);
    const auto hit = bvh.intersect({o, d});
    if (ref_inner) {
      // Clearly through the sphere: the hit lies between the two spheres that
      // bracket the facets.
      ASSERT_TRUE(hit) << i;
      EXPECT_GE(hit->t, *ref - 1e-9) << i;
      EXPECT_LE(hit->t, *ref_inner + 1e-9) << i;
    }
    if (!ref) {
      EXPECT_FALSE(hit) << i;
    }
    if (hit) {
      ++hits;
      const Vec3d p = o + hit->t * d;
      EXPECT_NEAR(p.norm(), radius, facet);
      EXPECT_LT((bary_point(m, hit->face, hit->u, hit->v) - p).norm(), 1e-9);
      EXPECT_GE(hit->u, -1e-9);
      EXPECT_GE(hit->v, -1e-9);
      EXPECT_LE(hit->u + hit->v, 1 + 1e-9);
      EXPECT_TRUE(bvh.occluded({o, d}));
    } else {
      ++misses;
      EXPECT_FALSE(bvh.occluded({o, d}));
    }
  }
  EXPECT_GT(hits, 500);
  EXPECT_GT(misses, 500);
}

TEST(Bvh, CentralRaysOnSphere) {
  const Mesh m = test::icosphere(4, 0.5, Vec3f(1, 2, 3));
  const TriangleBvh bvh(m);
  std::mt19937 rng(3);
  std::normal_distribution<double> g;
  for (int i = 0; i < 1000; ++i) {
    const Vec3d dir = Vec3d(g(rng), g(rng), g(rng)).normalized();
    const Vec3d c(1, 2, 3);
    // From outside towards the centre: t = 2 - radius up to faceting.
    auto hit = bvh.intersect({c + 2.0 * dir, -dir});
    ASSERT_TRUE(hit);
    EXPECT_NEAR(hit->t, 1.5, 1.5e-3);
    // From the centre outwards: back faces count too.
    hit = bvh.intersect({c, dir});
    ASSERT_TRUE(hit);
    EXPECT_NEAR(hit->t, 0.5, 1.5e-3);
  }
}

TEST(Bvh, BoxExactHitsAndMisses) {
  const Mesh m = test::box({-1, -0.5f, 0}, {1, 0.5f, 2});
  const TriangleBvh bvh(m);
  // Axis-aligned, straight on.
  auto hit = bvh.intersect({{5, 0.1, 1.2}, {-1, 0, 0}});
  ASSERT_TRUE(hit);
  EXPECT_DOUBLE_EQ(hit->t, 4.0);
  hit = bvh.intersect({{0.3, 0.2, -3}, {0, 0, 2}});
  ASSERT_TRUE(hit);
  EXPECT_DOUBLE_EQ(hit->t, 1.5);
  // Oblique.
  hit = bvh.intersect({{0, -3, 1}, Vec3d(0.2, 1, 0.1)});
  ASSERT_TRUE(hit);
  EXPECT_NEAR(hit->t, 2.5, 1e-12);
  // Through a face diagonal (the edge shared by the face's two triangles) and a corner.
  hit = bvh.intersect({{5, 0, 1}, {-1, 0, 0}});
  ASSERT_TRUE(hit);
  EXPECT_NEAR(hit->t, 4.0, 1e-12);
  hit = bvh.intersect({{3, 2.5, 4}, Vec3d(-2, -2, -2)});
  ASSERT_TRUE(hit);
  EXPECT_NEAR(hit->t, 1.0, 1e-12);
  // Misses: beside, away, too short, interval past the box.
  EXPECT_FALSE(bvh.intersect({{5, 0.6, 1}, {-1, 0, 0}}));
  EXPECT_FALSE(bvh.intersect({{5, 0, 1}, {1, 0, 0}}));
  EXPECT_FALSE(bvh.intersect({{5, 0, 1}, {-1, 0, 0}, 0, 3.9}));
  EXPECT_FALSE(bvh.intersect({{5, 0, 1}, {-1, 0, 0}, 6.1}));
  EXPECT_FALSE(bvh.occluded({{5, 0, 1}, {-1, 0, 0}, 0, 3.9}));
  // t_min between the two walls: the far wall (both sides count).
  hit = bvh.intersect({{5, 0, 1}, {-1, 0, 0}, 4.5});
  ASSERT_TRUE(hit);
  EXPECT_NEAR(hit->t, 6.0, 1e-12);
  // Axis-parallel ray lying in a slab plane of the bounding box.
  EXPECT_TRUE(bvh.occluded({{0, 0.5, -1}, {0, 0, 1}}));
  // Degenerate interval.
  EXPECT_FALSE(bvh.intersect({{5, 0, 1}, {-1, 0, 0}, 5, 4}));
}

TEST(Bvh, GridOfRaysIsWatertight) {
  // Rays through every vertex and edge of a finely tessellated sphere's front must
  // all hit: no cracks between neighbouring triangles.
  const Mesh m = test::icosphere(3, 1.0);
  const TriangleBvh bvh(m);
  for (const Vec3f& v : m.vertices) {
    const Vec3d p = v.cast<double>();
    EXPECT_TRUE(bvh.occluded({p * 3.0, -p})) << p.transpose();
  }
  for (const Face& f : m.faces) {
    const Vec3d mid = 0.5 * (m.vertices[f[0]] + m.vertices[f[1]]).cast<double>();
    EXPECT_TRUE(bvh.occluded({mid * 3.0, -mid}));
  }
}

TEST(Bvh, NearestOfOverlappingSurfaces) {
  // Two concentric spheres: the ray from outside must report the outer one.
  Mesh m = test::icosphere(2, 1.0);
  const Mesh inner = test::icosphere(2, 0.5);
  const int offset = int(m.vertices.size());
  m.vertices.insert(m.vertices.end(), inner.vertices.begin(), inner.vertices.end());
  for (Face f : inner.faces) m.faces.push_back(f.array() + offset);
  const TriangleBvh bvh(m);
  for (int i = 0; i < 50; ++i) {
    const double a = i * 0.37;
    const Vec3d dir(std::cos(a), std::sin(a), 0.3 * std::sin(3 * a));
    auto hit = bvh.intersect({dir.normalized() * 4.0, -dir.normalized()});
    ASSERT_TRUE(hit);
    EXPECT_LT(hit->face, int(m.faces.size() - inner.faces.size()));
    EXPECT_NEAR(hit->t, 3.0, 0.02);
  }
}

TEST(Bvh, ClosestPointMatchesBruteForce) {
  for (const Mesh& m : {random_soup(1500, 11), test::icosphere(3, 0.7, Vec3f(0.1f, 0, -0.2f)),
                        test::box({0, 0, 0}, {1, 2, 3})}) {
    const TriangleBvh bvh(m);
    std::mt19937 rng(5);
    std::uniform_real_distribution<double> pos(-2.0, 2.5);
    for (int i = 0; i < 600; ++i) {
      const Vec3d p(pos(rng), pos(rng), pos(rng));
      const ClosestPoint c = bvh.closest_point(p);
      const double ref = brute_closest(m, p);
      ASSERT_GE(c.face, 0);
      EXPECT_NEAR(c.distance, ref, 1e-9) << i;
      EXPECT_NEAR((c.point - p).norm(), c.distance, 1e-12);
      EXPECT_LT((bary_point(m, c.face, c.u, c.v) - c.point).norm(), 1e-9);
      EXPECT_GE(c.u, -1e-12);
      EXPECT_GE(c.v, -1e-12);
      EXPECT_LE(c.u + c.v, 1 + 1e-12);
      // The point lies on the face it names.
      EXPECT_NEAR(triangle_distance(c.point, vertex(m, c.face, 0), vertex(m, c.face, 1),
                                    vertex(m, c.face, 2)),
                  0.0, 1e-9);
    }
  }
}

TEST(Bvh, ClosestPointOnSurfaceAndDegenerateFaces) {
  Mesh m = test::box({0, 0, 0}, {1, 1, 1});
  // A zero-area sliver and a collapsed face must not break anything.
  m.vertices.push_back({2, 0, 0});
  m.vertices.push_back({3, 0, 0});
  m.vertices.push_back({4, 0, 0});
  m.faces.push_back({8, 9, 10});
  m.faces.push_back({9, 9, 9});
  const TriangleBvh bvh(m);
  ClosestPoint c = bvh.closest_point({0.5, 0.5, 1.0});
  EXPECT_NEAR(c.distance, 0.0, 1e-12);
  c = bvh.closest_point({3.5, 1.0, 0.0});
  EXPECT_NEAR(c.distance, 1.0, 1e-12);
  EXPECT_NEAR((c.point - Vec3d(3.5, 0, 0)).norm(), 0.0, 1e-12);
  EXPECT_NEAR((bary_point(m, c.face, c.u, c.v) - c.point).norm(), 0.0, 1e-12);
  c = bvh.closest_point({0.5, 0.5, 0.4});  // inside the box: nearest wall
  EXPECT_NEAR(c.distance, 0.4, 1e-7);
}

TEST(Bvh, OccludedAgreesWithIntersect) {
  const Mesh m = random_soup(3000, 2);
  const TriangleBvh bvh(m);
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> pos(-1.5, 1.5);
  int hits = 0;
  for (int i = 0; i < 3000; ++i) {
    const Ray r{{pos(rng), pos(rng), pos(rng)}, {pos(rng), pos(rng), pos(rng)}, 0.0, 1.0};
    const bool occ = bvh.occluded(r);
    EXPECT_EQ(occ, bvh.intersect(r).has_value()) << i;
    hits += occ;
  }
  EXPECT_GT(hits, 100);
}

TEST(Bvh, IntersectIsNearestByBruteForce) {
  const Mesh m = random_soup(800, 4);
  const TriangleBvh bvh(m);
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> pos(-1.5, 1.5);
  for (int i = 0; i < 500; ++i) {
    const Vec3d o(pos(rng), pos(rng), pos(rng)), d(pos(rng), pos(rng), pos(rng));
    const auto hit = bvh.intersect({o, d});
    double best = std::numeric_limits<double>::infinity();
    for (int f = 0; f < int(m.faces.size()); ++f) {
      // Plane hit, then inside test with the independent edge functions.
      const Vec3d a = vertex(m, f, 0), b = vertex(m, f, 1), c = vertex(m, f, 2);
      const Vec3d n = (b - a).cross(c - a);
      const double dn = d.dot(n);
      if (dn == 0) continue;
      const double t = (a - o).dot(n) / dn;
      if (t < 0) continue;
      const Vec3d q = o + t * d;
      if ((b - q).cross(c - q).dot(n) >= 0 && (c - q).cross(a - q).dot(n) >= 0 &&
          (a - q).cross(b - q).dot(n) >= 0)
        best = std::min(best, t);
    }
    if (std::isinf(best)) {
      EXPECT_FALSE(hit) << i;
    } else {
      ASSERT_TRUE(hit) << i;
      EXPECT_NEAR(hit->t, best, 1e-9 * (1 + best));
    }
  }
}

TEST(Bvh, ExponentiallySpacedTrianglesKeepDepthBounded) {
  // SAH would peel these off one by one (a 400-deep tree); queries must still be
  // exact, which needs the depth bound to keep traversal stacks in range.
  Mesh m;
  for (int i = 0; i < 400; ++i) {
    const float x = std::pow(1.1f, float(i));
    const int base = int(m.vertices.size());
    m.vertices.push_back({x, -1, -1});
    m.vertices.push_back({x, 1, -1});
    m.vertices.push_back({x, 0, 1});
    m.faces.push_back({base, base + 1, base + 2});
  }
  const TriangleBvh bvh(m);
  for (int i = 0; i < 400; i += 7) {
    const double x = std::pow(1.1f, float(i));
    const auto hit = bvh.intersect({{x - 0.01, 0, 0}, {1, 0, 0}});
    ASSERT_TRUE(hit) << i;
    EXPECT_EQ(hit->face, i);
    const ClosestPoint c = bvh.closest_point({x, 0.2, 0});
    EXPECT_EQ(c.face, i);
    EXPECT_NEAR(c.distance, 0.0, 1e-9 * x);
  }
  // A ray along the whole row hits the first one it meets.
  const auto hit = bvh.intersect({{1e30, 0, 0}, {-1, 0, 0}});
  ASSERT_TRUE(hit);
  EXPECT_EQ(hit->face, 399);
}

TEST(Bvh, MoveKeepsTheTree) {
  TriangleBvh a(test::box({0, 0, 0}, {1, 1, 1}));
  TriangleBvh b(std::move(a));
  EXPECT_TRUE(b.occluded({{0.5, 0.5, -1}, {0, 0, 1}}));
  TriangleBvh c(test::icosphere(1));
  c = std::move(b);
  EXPECT_EQ(c.triangle_count(), 12u);
}

}  // namespace
}  // namespace station
