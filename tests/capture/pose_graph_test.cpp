// Pose-graph optimisation (capture/pose_graph.h).
#include "capture/pose_graph.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <random>

#include "core/error.h"

namespace station {
namespace {

Eigen::Matrix4d ring_pose(int k, int n) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.block<3, 3>(0, 0) = Eigen::AngleAxisd(-2 * M_PI * k / n, Vec3d::UnitY()).toRotationMatrix();
  T.block<3, 1>(0, 3) = T.block<3, 3>(0, 0) * Vec3d(0, 0, -0.4) + Vec3d(0, 0, 0.4);
  return T;
}

double max_error_deg(const std::vector<Eigen::Matrix4d>& a, const std::vector<Eigen::Matrix4d>& b) {
  double e = 0;
  for (std::size_t i = 0; i < a.size(); ++i)
    e = std::max(e, rotation_angle_deg(rigid_inverse(rigid_inverse(a[0]) * a[i]) * (rigid_inverse(b[0]) * b[i])));
  return e;
}

TEST(PoseGraph, LoopClosureRemovesAccumulatedDrift) {
  const int n = 15;
  std::vector<Eigen::Matrix4d> truth;
  for (int k = 0; k < n; ++k) truth.push_back(ring_pose(k, n));
  // Neighbour measurements with a small systematic error (0.1 degree each,
  // mostly about the ring's axis) plus noise: chaining them drifts by about
  // 1.4 degrees, which the loop closure spreads back over the ring.
  std::mt19937 rng(3);
  std::normal_distribution<double> g(0, 0.01 * M_PI / 180);
  const Eigen::Matrix4d bias = motion_exp((Vector6d() << 0.02 * M_PI / 180, 0.1 * M_PI / 180, 0, 0.0002, 0, 0).finished());
  std::vector<PoseGraphEdge> edges;
  for (int k = 0; k < n; ++k) {
    PoseGraphEdge e;
    e.from = k;
    e.to = (k + 1) % n;
    const Vector6d noise = (Vector6d() << g(rng), g(rng), g(rng), 0, 0, 0).finished();
    e.measurement = motion_exp(noise) * bias * rigid_inverse(truth[e.from]) * truth[e.to];
    e.information = Matrix6d::Identity() * 1e4;
    edges.push_back(e);
  }
  std::vector<Eigen::Matrix4d> chained{truth[0]};
  for (int k = 0; k + 1 < n; ++k) chained.push_back(chained.back() * edges[k].measurement);
  const double drift = max_error_deg(truth, chained);
  EXPECT_GT(drift, 1.0);

  const PoseGraphResult r = optimize_pose_graph(chained, edges);
  EXPECT_TRUE(r.converged);
  EXPECT_LT(r.final_cost, r.initial_cost);
  const double after = max_error_deg(truth, r.poses);
  EXPECT_LT(after, 0.2 * drift);
  EXPECT_EQ(r.poses[0], chained[0]);  // gauge held
  EXPECT_EQ(r.edge_rotation_deg.size(), edges.size());

  // Without the loop closure edge nothing constrains the drift.
  std::vector<PoseGraphEdge> open(edges.begin(), edges.end() - 1);
  EXPECT_NEAR(max_error_deg(truth, optimize_pose_graph(chained, open).poses), drift, 1e-6);

  EXPECT_THROW(optimize_pose_graph(chained, {PoseGraphEdge{0, n, Eigen::Matrix4d::Identity(), Matrix6d::Identity()}}),
               InvalidInput);
}

TEST(PoseGraph, ErrorIsZeroForConsistentMeasurement) {
  const Eigen::Matrix4d a = ring_pose(1, 7), b = ring_pose(3, 7);
  EXPECT_LT(pose_graph_error(a, b, rigid_inverse(a) * b).norm(), 1e-12);
}

}  // namespace
}  // namespace station
