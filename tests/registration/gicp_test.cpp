// Generalized ICP (IcpObjective::kGeneralized in capture/icp.h, Segal et al.
// 2009) on the analytic partial-overlap pair of the ICP test: known truth.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <cmath>
#include <random>

#include "registration/icp.h"

namespace station {
namespace {

// The front half of a bumpy ellipsoid 0.5 m ahead of the sensor (no symmetry).
std::vector<Vec3f> bumpy(int n, unsigned seed, double noise) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  std::normal_distribution<double> g(0, noise);
  std::vector<Vec3f> pts;
  while (int(pts.size()) < n) {
    Vec3d d(u(rng), u(rng), u(rng));
    if (d.norm() < 1e-3 || d.norm() > 1) continue;
    d.normalize();
    if (d.z() > 0.1) continue;
    const double r = 1 + 0.15 * std::sin(5 * d.x()) * std::cos(4 * d.y()) + 0.1 * d.x() * d.y();
    const Vec3d p = Vec3d(0.08 * d.x(), 0.05 * d.y(), 0.06 * d.z()) * r + Vec3d(0.01, 0.0, 0.5);
    pts.push_back((p + Vec3d(0, 0, g(rng))).cast<float>());
  }
  return pts;
}

Eigen::Matrix4d rigid(double angle_deg, const Vec3d& axis, const Vec3d& t) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.block<3, 3>(0, 0) = Eigen::AngleAxisd(angle_deg * M_PI / 180, axis.normalized()).toRotationMatrix();
  T.block<3, 1>(0, 3) = t;
  return T;
}

PreparedView prepared(const std::vector<Vec3f>& pts, const Eigen::Matrix4d& T) {
  Cloud c;
  for (const Vec3f& p : pts) c.points.push_back((T * p.cast<double>().homogeneous()).head<3>().cast<float>());
  PrepareParams pp;
  pp.voxel_size = 0.001;
  return prepare_view(c, pp);
}

TEST(Gicp, RecoversKnownTransformOnPartialOverlap) {
  std::vector<Vec3f> target_pts, source_world;
  for (const Vec3f& p : bumpy(30000, 2, 0.0001)) if (p.x() < 0.05f) target_pts.push_back(p);
  for (const Vec3f& p : bumpy(30000, 3, 0.0001)) if (p.x() > -0.03f) source_world.push_back(p);
  const Eigen::Matrix4d truth = rigid(20, Vec3d(0.1, 1, 0.2), Vec3d(0.01, -0.02, 0.015));
  const PreparedView target = prepared(target_pts, Eigen::Matrix4d::Identity());
  const PreparedView source = prepared(source_world, rigid_inverse(truth));
  // 5 degrees about the object's centre and 2 % of its 0.2 m size off.
  const Vec3d c(0.01, 0, 0.5);
  const Eigen::Matrix4d start = rigid(0, Vec3d::UnitZ(), c + Vec3d(0.004, 0, 0)) *
                                rigid(5, Vec3d(1, -0.5, 0.3), Vec3d::Zero()) *
                                rigid(0, Vec3d::UnitZ(), -c) * truth;
  IcpParams ip;
  ip.objective = IcpObjective::kGeneralized;
  ip.max_distance_start = 0.02;
  ip.max_distance_end = 0.003;
  const IcpResult r = icp_point_to_plane(source, target, start, ip);
  ASSERT_TRUE(r.converged) << r.message;
  const double rot = rotation_angle_deg(rigid_inverse(truth) * r.transform);
  const double tr = (r.transform.block<3, 1>(0, 3) - truth.block<3, 1>(0, 3)).norm();
  std::printf("gicp: %.4f deg, %.4f mm, %d iterations\n", rot, 1000 * tr, r.iterations);
  EXPECT_LT(rot, 0.05);
  EXPECT_LT(tr, 2e-4);
  EXPECT_GT(r.fitness, 0.5);
  // The information handed to the pose graph is positive definite.
  Eigen::SelfAdjointEigenSolver<Matrix6d> es(r.hessian);
  EXPECT_GT(es.eigenvalues()(0), 0.0);
  // Deterministic.
  EXPECT_EQ(icp_point_to_plane(source, target, start, ip).transform, r.transform);
  // Far apart: reported as a failure, not a pose.
  const IcpResult far = icp_point_to_plane(source, target, rigid(0, Vec3d::UnitZ(), Vec3d(1, 0, 0)) * truth, ip);
  EXPECT_FALSE(far.converged);
  EXPECT_FALSE(far.message.empty());
}

}  // namespace
}  // namespace station
