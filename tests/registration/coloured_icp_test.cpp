// Coloured ICP (Park et al. 2017; capture/coloured_icp.h, IcpObjective::kColored):
// a textured plane slid along itself, where geometry alone cannot see the
// motion, and the colour gradients against an analytic ramp.
#include "registration/coloured_icp.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>

#include "registration/icp.h"
#include "registration/registration.h"
#include "core/error.h"
#include "core/kdtree.h"

namespace station {
namespace {

// Texture fixed to the world plane z = 0.5 (x, y in metres).
float texture(double x, double y) {
  const double l = 0.04;
  return float(0.5 + 0.4 * std::sin(2 * M_PI * x / l) * std::sin(2 * M_PI * y / l + 0.7));
}

Rgb grey(float v) {
  const auto c = std::uint8_t(std::lround(std::clamp(v, 0.0f, 1.0f) * 255));
  return Rgb{c, c, c};
}

// A grid on the world plane seen from frame X (world <- frame): the points in
// the frame's coordinates, coloured by the world texture.
Cloud plane_view(const Eigen::Matrix4d& X, double offset) {
  Cloud c;
  const Eigen::Matrix4d Xi = rigid_inverse(X);
  for (int i = 0; i <= 100; ++i)
    for (int j = 0; j <= 100; ++j) {
      const Vec3d w(-0.1 + 0.002 * i + offset, -0.1 + 0.002 * j + offset, 0.5);
      c.points.push_back((Xi.block<3, 3>(0, 0) * w + Xi.block<3, 1>(0, 3)).cast<float>());
      c.colours.push_back(grey(texture(w.x(), w.y())));
    }
  return c;
}

TEST(ColouredIcp, TexturedPlaneSlidAlongItselfIsRecoveredOnlyWithColour) {
  // Source frame: world <- source is a 6 mm / 4 mm slide and a 2 degree turn
  // about the plane's normal through its centre: invisible to geometry.
  Eigen::Matrix4d X = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d Rz = Eigen::AngleAxisd(2.0 * M_PI / 180, Vec3d::UnitZ()).toRotationMatrix();
  X.block<3, 3>(0, 0) = Rz;
  X.block<3, 1>(0, 3) = Vec3d(0.006, -0.004, 0) + (Vec3d(0, 0, 0.5) - Rz * Vec3d(0, 0, 0.5));
  const Cloud target = plane_view(Eigen::Matrix4d::Identity(), 0.0);
  const Cloud source = plane_view(X, 0.001);  // different samples of the surface
  PrepareParams pp;
  pp.voxel_size = 0;
  pp.intensity = true;
  const PreparedView t = prepare_view(target, pp), s = prepare_view(source, pp);
  ASSERT_EQ(t.intensity.size(), t.points.size());
  ASSERT_EQ(t.intensity_gradient.size(), t.points.size());
  IcpParams ip;
  ip.max_distance_start = 0.01;
  ip.max_distance_end = 0.003;
  ip.max_iterations = 200;
  const IcpResult geo = icp_point_to_plane(s, t, Eigen::Matrix4d::Identity(), ip);
  ip.objective = IcpObjective::kColoured;
  const IcpResult col = icp_point_to_plane(s, t, Eigen::Matrix4d::Identity(), ip);
  const Eigen::Matrix4d eg = rigid_inverse(X) * geo.transform, ec = rigid_inverse(X) * col.transform;
  std::printf("point-to-plane: %.3f deg %.3f mm; coloured: %.4f deg %.4f mm (%d iterations)\n",
              rotation_angle_deg(eg), 1000 * eg.block<3, 1>(0, 3).norm(), rotation_angle_deg(ec),
              1000 * ec.block<3, 1>(0, 3).norm(), col.iterations);
  EXPECT_TRUE(col.converged) << col.message;
  EXPECT_LT(rotation_angle_deg(ec), 0.1);
  EXPECT_LT((ec.block<3, 1>(0, 3)).norm(), 3e-4);
  // Geometry alone leaves the slide (it stays near the start).
  EXPECT_GT((eg.block<3, 1>(0, 3)).norm(), 4e-3);
  EXPECT_GT(rotation_angle_deg(eg), 1.5);
}

// In other units the coloured system is the same system: lambda is set for residuals
// in metres, so with every length x 1000 (IcpParams::units_per_metre 1000, the lengths
// given in millimetres) the rotation rows grow by 1000^2 and the translation rows stay,
// colour term included (H_mm = D H_m D, D = diag(1000 x 3, 1 x 3)). Where geometry
// leaves the turn about the plane's normal free, that entry is colour's alone.
TEST(ColouredIcp, TheSameSystemInMillimetres) {
  Eigen::Matrix4d X = Eigen::Matrix4d::Identity();
  X.block<3, 1>(0, 3) = Vec3d(0.0005, -0.0003, 0);
  const Cloud target = plane_view(Eigen::Matrix4d::Identity(), 0.0);
  const Cloud source = plane_view(X, 0.001);
  Cloud target_mm = target, source_mm = source;
  for (Cloud* c : {&target_mm, &source_mm})
    for (Vec3f& p : c->points) p *= 1000.0f;
  PrepareParams pp;
  pp.voxel_size = 0;
  pp.intensity = true;
  IcpParams ip;
  ip.objective = IcpObjective::kColoured;
  ip.max_distance_start = 0.01;
  ip.max_distance_end = 0.003;
  ip.max_iterations = 200;
  IcpParams mm = ip;
  mm.units_per_metre = 1000;
  mm.max_distance_start *= 1000;
  mm.max_distance_end *= 1000;
  mm.convergence_translation *= 1000;
  mm.coloured_reference_distance *= 1000;
  const IcpResult a = icp_point_to_plane(prepare_view(source, pp), prepare_view(target, pp), Eigen::Matrix4d::Identity(), ip);
  const IcpResult b =
      icp_point_to_plane(prepare_view(source_mm, pp), prepare_view(target_mm, pp), Eigen::Matrix4d::Identity(), mm);
  ASSERT_TRUE(a.converged) << a.message;
  ASSERT_TRUE(b.converged) << b.message;
  std::printf("rotation about the normal: H %.6g (m), %.6g (mm, / 1e6); translation x: %.6g, %.6g\n", a.hessian(2, 2),
              b.hessian(2, 2) / 1e6, a.hessian(3, 3), b.hessian(3, 3));
  EXPECT_NEAR(b.hessian(2, 2) / 1e6, a.hessian(2, 2), 0.01 * a.hessian(2, 2));
  EXPECT_NEAR(b.hessian(3, 3), a.hessian(3, 3), 0.01 * a.hessian(3, 3));
  EXPECT_NEAR(b.transform(0, 3) / 1000, a.transform(0, 3), 2e-6);
}

// The same through register_views: the objective chosen in RegistrationParams
// reaches every round, colours are kept in the merge.
TEST(ColouredIcp, SessionOfTwoTexturedPlaneViews) {
  Eigen::Matrix4d X = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d Rz = Eigen::AngleAxisd(1.0 * M_PI / 180, Vec3d::UnitZ()).toRotationMatrix();
  X.block<3, 3>(0, 0) = Rz;
  X.block<3, 1>(0, 3) = Vec3d(-0.004, 0.005, 0) + (Vec3d(0, 0, 0.5) - Rz * Vec3d(0, 0, 0.5));
  const std::vector<Cloud> clouds = {plane_view(Eigen::Matrix4d::Identity(), 0.0), plane_view(X, 0.001)};
  SessionManifest m;
  m.scanner = "test";
  for (int i = 0; i < 2; ++i) {
    ViewRecord v;
    v.file = "view_" + std::to_string(i) + ".ply";
    v.initial_pose = Eigen::Matrix4d::Identity();  // the slide is unknown
    v.reference_pose = i == 0 ? Eigen::Matrix4d::Identity() : X;
    m.views.push_back(v);
  }
  // The final distance must exceed the 2 mm sampling of the planes (0.4 % of
  // their 0.28 m diagonal would be 1.1 mm, no correspondences at all).
  RegistrationParams geo;
  geo.icp_end_rel = 0.012;
  const RegistrationResult a = register_views(clouds, m, geo);
  RegistrationParams col = geo;
  col.icp.objective = IcpObjective::kColoured;
  col.final_objective = IcpObjective::kColoured;
  col.icp.max_iterations = 100;
  const RegistrationResult b = register_views(clouds, m, col);
  std::printf("session: point-to-plane %.3f deg %.3f mm, coloured %.4f deg %.4f mm\n",
              a.max_rotation_error_deg, 1000 * a.max_translation_error, b.max_rotation_error_deg,
              1000 * b.max_translation_error);
  ASSERT_EQ(b.views_with_reference, 2);
  EXPECT_TRUE(b.failed_views.empty());
  EXPECT_LT(b.max_rotation_error_deg, 0.1);
  EXPECT_LT(b.max_translation_error, 5e-4);
  ASSERT_EQ(a.views_with_reference, 2);
  EXPECT_GT(a.max_translation_error, 4e-3);
  EXPECT_TRUE(b.merged.has_colours());

  // The same session in millimetres (`units: mm`, every length x 1000): the colour
  // term keeps the paper's balance (lambda is set for residuals in metres), so colour
  // still finds the slide. Weighted in the session's units as given, it was a millionth
  // of that and the run was point-to-plane's (the slide left, over 4 mm).
  std::vector<Cloud> mm_clouds = clouds;
  for (Cloud& c : mm_clouds)
    for (Vec3f& p : c.points) p *= 1000.0f;
  SessionManifest mm = m;
  mm.units = "mm";
  for (ViewRecord& v : mm.views) v.reference_pose->block<3, 1>(0, 3) *= 1000.0;
  const RegistrationResult c = register_views(mm_clouds, mm, col);
  std::printf("session in mm: coloured %.4f deg %.4f mm\n", c.max_rotation_error_deg, c.max_translation_error);
  ASSERT_EQ(c.views_with_reference, 2);
  EXPECT_TRUE(c.failed_views.empty());
  EXPECT_EQ(c.mm_per_unit, 1.0);
  EXPECT_LT(c.max_rotation_error_deg, 0.1);
  EXPECT_LT(c.max_translation_error, 0.5);
}

TEST(ColouredIcp, WithoutColoursItIsPointToPlane) {
  Cloud target = plane_view(Eigen::Matrix4d::Identity(), 0.0);
  Cloud source = plane_view(Eigen::Matrix4d::Identity(), 0.001);
  target.colours.clear();
  source.colours.clear();
  PrepareParams pp;
  pp.voxel_size = 0;
  pp.intensity = true;
  const PreparedView t = prepare_view(target, pp), s = prepare_view(source, pp);
  EXPECT_TRUE(t.intensity.empty());
  IcpParams ip;
  const IcpResult a = icp_point_to_plane(s, t, Eigen::Matrix4d::Identity(), ip);
  ip.objective = IcpObjective::kColoured;
  const IcpResult b = icp_point_to_plane(s, t, Eigen::Matrix4d::Identity(), ip);
  EXPECT_TRUE(a.transform.isApprox(b.transform));
  EXPECT_EQ(a.converged, b.converged);
}

TEST(ColouredIcp, GradientOfALinearRampIsExactAndTangent) {
  // Intensity 0.2 + 3 x + 1 y on the tilted plane z = 0.3 x: the gradient in
  // the plane is the projection of (3, 1, 0) on it.
  std::vector<Vec3f> pts, normals;
  std::vector<float> in;
  const Vec3d n = Vec3d(-0.3, 0, 1).normalized();
  for (int i = 0; i < 30; ++i)
    for (int j = 0; j < 30; ++j) {
      const double x = 0.005 * i, y = 0.005 * j, z = 0.3 * x;
      pts.emplace_back(float(x), float(y), float(z));
      normals.push_back(n.cast<float>());
      in.push_back(float(0.2 + 3 * x + 1 * y));
    }
  const PointIndex index(pts);
  const std::vector<Vec3f> g = intensity_gradients(index, normals, in, 12);
  // On the plane, intensity(x, y) with x = u . e1 ...: the true tangent gradient
  // G satisfies G . t = dI along t for the plane's tangents t.
  const Vec3d t1 = Vec3d(1, 0, 0.3).normalized(), t2(0, 1, 0);
  const Vec3d& gi = g[15 * 30 + 15].cast<double>();
  EXPECT_NEAR(gi.dot(t1), 3 / std::sqrt(1 + 0.09), 1e-2);
  EXPECT_NEAR(gi.dot(t2), 1.0, 1e-2);
  EXPECT_NEAR(gi.dot(n), 0.0, 1e-4);
  EXPECT_THROW(intensity_gradients(index, normals, std::vector<float>(3), 12), InvalidInput);
}

}  // namespace
}  // namespace station
