// The sensor check of registration/viewpoint.h: views in their scanner frame keep
// the origin; views stored in the object's frame (the Stanford scans) get a
// viewpoint from which their normals face outwards.
#include "registration/viewpoint.h"

#include <gtest/gtest.h>

#include <cmath>
#include <vector>

#include "core/error.h"
#include "core/io.h"
#include "core/kdtree.h"
#include "core/normals.h"
#include "core/sampling.h"
#include "dragon_session.h"
#include "registration/registration.h"
#include "test_util.h"

namespace station {
namespace {

const Vec3d kCentre(0.01, -0.01, 0.5);
const Vec3d kRadii(0.1, 0.06, 0.045);

// A range view of an ellipsoid as a sensor at the origin sees it: one ray per pixel
// of a 200 x 200 image (so the silhouette is sampled thinly, as a scanner does).
std::vector<Vec3f> ellipsoid_range_view() {
  std::vector<Vec3f> pts;
  const Vec3d inv = kRadii.cwiseInverse();
  for (int v = 0; v < 200; ++v)
    for (int u = 0; u < 200; ++u) {
      const Vec3d ray = Vec3d((u - 99.5) / 400.0, (v - 99.5) / 400.0, 1.0).normalized();
      // |inv .* (t ray - c)|^2 = 1
      const Vec3d a = ray.cwiseProduct(inv), b = kCentre.cwiseProduct(inv);
      const double qa = a.squaredNorm(), qb = -2 * a.dot(b), qc = b.squaredNorm() - 1;
      const double disc = qb * qb - 4 * qa * qc;
      if (disc < 0) continue;
      const double t = (-qb - std::sqrt(disc)) / (2 * qa);
      pts.push_back((t * ray).cast<float>());
    }
  return pts;
}

Vec3d outward(const Vec3f& p) {  // the ellipsoid's outward normal at p (sensor frame)
  return (p.cast<double>() - kCentre).cwiseQuotient(kRadii.cwiseProduct(kRadii)).normalized();
}

ViewpointEstimate estimate(const std::vector<Vec3f>& pts, std::vector<Vec3f>* normals = nullptr) {
  const PointIndex index(pts);
  std::vector<Vec3f> n = estimate_normals(index, 16);
  const ViewpointEstimate e = estimate_viewpoint(pts, n);
  for (std::size_t i = 0; i < n.size(); ++i)
    if (n[i].dot(e.viewpoint - pts[i]) < 0) n[i] = -n[i];
  if (normals) *normals = n;
  return e;
}

TEST(Viewpoint, ARangeViewInItsScannerFrameKeepsTheOrigin) {
  const std::vector<Vec3f> pts = ellipsoid_range_view();
  ASSERT_GT(pts.size(), 10000u);
  const ViewpointEstimate e = estimate(pts);
  std::printf("scanner frame: %zu points, grazing from the origin %.3f\n", pts.size(),
              e.grazing_origin);
  EXPECT_TRUE(e.at_origin);
  EXPECT_LT(e.grazing_origin, kMaxGrazingShare);
  EXPECT_EQ(e.viewpoint, Vec3f::Zero());
}

TEST(Viewpoint, TheSameViewInTheObjectsFrameGetsAViewpointInFrontOfIt) {
  // Stored in another frame: the origin on a table 4 cm below the object (the
  // Stanford scans have theirs inside the dragon).
  const Vec3d origin = kCentre + Vec3d(0, 0.1, 0.0);
  std::vector<Vec3f> pts;
  for (const Vec3f& p : ellipsoid_range_view())
    pts.push_back((p.cast<double>() - origin).cast<float>());
  std::vector<Vec3f> normals;
  const ViewpointEstimate e = estimate(pts, &normals);
  std::printf("object frame: grazing from the origin %.3f, from the estimate %.3f\n",
              e.grazing_origin, e.grazing_estimate);
  EXPECT_FALSE(e.at_origin);
  EXPECT_GT(e.grazing_origin, kMaxGrazingShare);
  EXPECT_LE(e.grazing_estimate, kGrazingRatio * e.grazing_origin);
  // The true sensor is at -origin, about 0.5 m along -z from the object.
  Vec3d centroid = Vec3d::Zero();
  for (const Vec3f& p : pts) centroid += p.cast<double>();
  centroid /= double(pts.size());
  const Vec3d to_sensor = (-origin - centroid).normalized();
  EXPECT_GT((e.viewpoint.cast<double>() - centroid).normalized().dot(to_sensor),
            std::cos(20 * M_PI / 180));
  std::size_t out = 0;
  for (std::size_t i = 0; i < pts.size(); ++i)
    out +=
        normals[i].cast<double>().dot(outward((pts[i].cast<double>() + origin).cast<float>())) > 0;
  EXPECT_GT(double(out) / double(pts.size()), 0.99);
  // Towards the origin, as before: a large part would face inwards.
  std::size_t origin_in = 0;
  for (std::size_t i = 0; i < pts.size(); ++i)
    origin_in +=
        (-pts[i].cast<double>()).dot(outward((pts[i].cast<double>() + origin).cast<float>())) < 0;
  EXPECT_GT(double(origin_in) / double(pts.size()), 0.1);
}

// A flat view does not tell its side: seen edge-on from the origin (in its plane),
// it keeps the origin rather than guess.
TEST(Viewpoint, AFlatViewKeepsTheOrigin) {
  std::vector<Vec3f> pts;
  for (int i = 0; i < 60; ++i)
    for (int j = 0; j < 60; ++j) pts.emplace_back(0.1f + 0.002f * i, 0.002f * j - 0.06f, 0.f);
  const std::vector<Vec3f> normals(pts.size(), Vec3f::UnitZ());
  const ViewpointEstimate e = estimate_viewpoint(pts, normals);
  EXPECT_GT(e.grazing_origin, kMaxGrazingShare);
  EXPECT_TRUE(e.at_origin);
}

TEST(Viewpoint, TooFewNormalsKeepTheOrigin) {
  const std::vector<Vec3f> pts = {Vec3f(0.1f, 0, 0.5f), Vec3f(0, 0.1f, 0.5f), Vec3f(0, 0, 0.6f)};
  const std::vector<Vec3f> normals(3, Vec3f::UnitX());
  EXPECT_TRUE(estimate_viewpoint(pts, normals).at_origin);
  EXPECT_THROW(estimate_viewpoint(pts, std::vector<Vec3f>(2, Vec3f::UnitX())), InvalidInput);
}

// The bundled Stanford dragon: every scan is stored in the object's frame, and the
// merged cloud's normals face outwards (80 % inwards when they faced the origin).
TEST(Viewpoint, TheDragonScansAreNotInTheirScannerFrameAndMergeFacingOutwards) {
  std::vector<Cloud> clouds;
  const SessionManifest m = test::dragon_session(clouds);
  const RegistrationResult r = register_views(clouds, m);
  ASSERT_EQ(r.views.size(), 15u);
  for (const ViewDiagnostics& v : r.views) {
    EXPECT_TRUE(v.viewpoint_estimated);
    EXPECT_GT(v.grazing_origin, kMaxGrazingShare);
  }
  bool warned = false;
  for (const std::string& w : r.notes)
    warned |= w.find("not stored in their scanner frame") != std::string::npos;
  EXPECT_TRUE(warned);
  ASSERT_TRUE(r.merged.has_normals());
  Vec3d c = Vec3d::Zero();
  for (const Vec3f& p : r.merged.points) c += p.cast<double>();
  c /= double(r.merged.size());
  std::size_t out = 0;
  for (std::size_t i = 0; i < r.merged.size(); ++i)
    out += (r.merged.points[i].cast<double>() - c).dot(r.merged.normals[i].cast<double>()) > 0;
  const double share = double(out) / double(r.merged.size());
  std::printf("dragon: %.1f %% of the merged normals point away from the centroid\n", 100 * share);
  EXPECT_GT(share, 0.75);
}

}  // namespace
}  // namespace station
