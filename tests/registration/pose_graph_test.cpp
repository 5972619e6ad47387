// Pose-graph optimisation (capture/pose_graph.h).
#include "registration/pose_graph.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <cstdio>
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

// A rigid turntable: the object turned about one tilted line by a fixed
// scanner; X_i = X_0 Rot(line, phi_i).
struct Turntable {
  Vec3d p{0.01, 0.0, 0.42};
  Vec3d d = Vec3d(0.03, 1.0, -0.02).normalized();
  Eigen::Matrix4d X0 = motion_exp((Vector6d() << 0.1, -0.2, 0.05, 0.01, 0.02, -0.03).finished());
  Eigen::Matrix4d pose(double phi) const {
    Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
    T.block<3, 3>(0, 0) = Eigen::AngleAxisd(phi, d).toRotationMatrix();
    T.block<3, 1>(0, 3) = p - T.block<3, 3>(0, 0) * p;
    return X0 * T;
  }
};

// Translation error of view i relative to view 0, at a point 0.42 m in front of
// the scanner (where the object is).
double max_object_error(const std::vector<Eigen::Matrix4d>& a, const std::vector<Eigen::Matrix4d>& b) {
  double e = 0;
  const Vec3d at(0, 0, 0.42);
  for (std::size_t i = 0; i < a.size(); ++i) {
    const Eigen::Matrix4d A = rigid_inverse(a[0]) * a[i], B = rigid_inverse(b[0]) * b[i];
    e = std::max(e, (A.block<3, 3>(0, 0) * at + A.block<3, 1>(0, 3) - B.block<3, 3>(0, 0) * at -
                     B.block<3, 1>(0, 3)).norm());
  }
  return e;
}

TEST(PoseGraph, RigidTurntableHoldsWhatThePairsLeaveFree) {
  const Turntable tt;
  const int n = 12;
  std::vector<Eigen::Matrix4d> truth;
  for (int k = 0; k < n; ++k) truth.push_back(tt.pose(-2 * M_PI * k / n));
  // Pairs (k, k+1) and (k, k+2) whose ICP barely holds one sliding direction of
  // frame k (information 1e-4 of the others along it) and got it 1 mm wrong,
  // in a different direction per pair, plus 0.01 degree of rotation noise.
  std::mt19937 rng(7);
  std::normal_distribution<double> g(0, 0.01 * M_PI / 180);
  std::vector<PoseGraphEdge> edges;
  for (int k = 0; k < n; ++k)
    for (int s = 1; s <= 2; ++s) {
      PoseGraphEdge e;
      e.from = k;
      e.to = (k + s) % n;
      const Vec3d slide = Eigen::AngleAxisd(0.7 * k + s, Vec3d::UnitY()) * Vec3d::UnitX();
      Vector6d err;
      err << g(rng), g(rng), g(rng), 0.001 * slide;
      e.measurement = motion_exp(err) * rigid_inverse(truth[e.from]) * truth[e.to];
      e.information = Matrix6d::Identity() * 1e6;
      e.information.block<3, 3>(3, 3) -= (1e6 - 1e2) * slide * slide.transpose();
      edges.push_back(e);
    }
  // Start: the poses of a prior 3 degrees and 2 % of 0.2 m off.
  std::vector<Eigen::Matrix4d> start;
  std::uniform_real_distribution<double> off(-3, 3);
  for (int k = 0; k < n; ++k) start.push_back(tt.pose(-2 * M_PI * k / n + (k ? off(rng) * M_PI / 180 : 0)));
  const Vec3d p0 = tt.p + Vec3d(0.004, 0, 0), d0 = (tt.d + Vec3d(0.03, 0, 0.02)).normalized();

  const PoseGraphResult free_graph = optimize_pose_graph(start, edges);
  TurntableGraphModel model;
  const PoseGraphResult rigid =
      optimize_turntable_graph(start, edges, std::vector<bool>(n, true), p0, d0, {}, &model);
  EXPECT_TRUE(rigid.converged);
  EXPECT_EQ(rigid.poses[0], start[0]);  // gauge held
  const double free_err = max_object_error(truth, free_graph.poses);
  const double rigid_err = max_object_error(truth, rigid.poses);
  std::printf("object translation error: free %.4f mm, rigid turntable %.4f mm\n", 1000 * free_err,
              1000 * rigid_err);
  EXPECT_GT(free_err, 1e-4);
  EXPECT_LT(rigid_err, 0.3 * free_err);
  EXPECT_LT(max_error_deg(truth, rigid.poses), 0.02);
  // The line found is the truth's.
  EXPECT_GT(std::abs(model.direction.dot(tt.d)), std::cos(0.05 * M_PI / 180));
  const Vec3d to_line = (tt.p - model.point) - model.direction * model.direction.dot(tt.p - model.point);
  EXPECT_LT(to_line.norm(), 2e-4);
  ASSERT_EQ(model.angles_rad.size(), std::size_t(n));
  EXPECT_EQ(model.angles_rad[0], 0.0);
  const double sense = model.direction.dot(tt.d) > 0 ? 1 : -1;
  for (int k = 1; k < n; ++k)
    EXPECT_NEAR(std::remainder(sense * model.angles_rad[k] + 2 * M_PI * k / n, 2 * M_PI), 0, 0.02 * M_PI / 180);

  // Exact measurements: the truth, also with one node off the table (its
  // pose has 6 free unknowns and is found from its edges alone).
  for (PoseGraphEdge& e : edges) e.measurement = rigid_inverse(truth[e.from]) * truth[e.to];
  std::vector<bool> table(n, true);
  table[5] = false;
  start[5] = motion_exp((Vector6d() << 0.02, -0.01, 0.03, 0.004, -0.003, 0.002).finished()) * truth[5];
  const PoseGraphResult exact = optimize_turntable_graph(start, edges, table, p0, d0);
  EXPECT_LT(max_error_deg(truth, exact.poses), 1e-6);
  EXPECT_LT(max_object_error(truth, exact.poses), 1e-8);
  EXPECT_LT(exact.final_cost, 1e-9 * exact.initial_cost);

  // The gauge must be on the table; the line must be one.
  PoseGraphParams gauge5;
  gauge5.fixed_node = 5;
  EXPECT_THROW(optimize_turntable_graph(start, edges, table, p0, d0, gauge5), InvalidInput);
  EXPECT_THROW(optimize_turntable_graph(start, edges, table, p0, Vec3d::Zero()), InvalidInput);
  EXPECT_THROW(optimize_turntable_graph(start, edges, std::vector<bool>(n - 1, true), p0, d0), InvalidInput);
}

}  // namespace
// An object that moved on the table between two runs of views (knocked after
// view 5: 20 degrees about the table's up and 2 cm across): each run turns about
// the one line, the second with its own base pose. From exact pair motions (and
// one pair across the move) and a start 3 degrees off, the two-group turntable
// graph finds the truth; one group cannot fit it.
TEST(PoseGraph, TwoTurntableRunsOfAMovedObject) {
  const Turntable tt;
  const int n = 12;
  // The move D of the object in the object frame: view i after it sees D p.
  const Eigen::Matrix4d D = [&] {
    Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
    m.block<3, 3>(0, 0) = Eigen::AngleAxisd(20 * M_PI / 180, tt.d).toRotationMatrix();
    m.block<3, 1>(0, 3) = Vec3d(0.02, 0, 0.005);
    return m;
  }();
  std::vector<Eigen::Matrix4d> truth;
  for (int k = 0; k < n; ++k) {
    const Eigen::Matrix4d X = tt.pose(-2 * M_PI * k / n);
    truth.push_back(k < 6 ? X : Eigen::Matrix4d(rigid_inverse(D) * X));
  }
  std::vector<PoseGraphEdge> edges;
  for (int k = 0; k < n; ++k)
    for (int s = 1; s <= 2; ++s) {
      PoseGraphEdge e;
      e.from = k;
      e.to = (k + s) % n;
      e.measurement = rigid_inverse(truth[e.from]) * truth[e.to];
      e.information = Matrix6d::Identity() * 1e6;
      edges.push_back(e);
    }
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> off(-3, 3);
  std::vector<Eigen::Matrix4d> start;
  for (int k = 0; k < n; ++k)
    start.push_back(k ? Eigen::Matrix4d(motion_exp((Vector6d() << 0, off(rng) * M_PI / 180, 0, 0.001, 0, 0).finished()) * truth[k])
                      : truth[0]);
  std::vector<int> group(n, 0);
  for (int k = 6; k < n; ++k) group[k] = 1;
  const Vec3d p0 = tt.p + Vec3d(0.004, 0, 0), d0 = (tt.d + Vec3d(0.03, 0, 0.02)).normalized();
  const PoseGraphResult two =
      optimize_turntable_graph(start, edges, std::vector<bool>(n, true), p0, d0, {}, nullptr, group);
  const PoseGraphResult one = optimize_turntable_graph(start, edges, std::vector<bool>(n, true), p0, d0);
  std::printf("moved object: two runs %.2e deg / %.2e m, one turntable %.3f deg / %.4f m\n",
              max_error_deg(truth, two.poses), max_object_error(truth, two.poses), max_error_deg(truth, one.poses),
              max_object_error(truth, one.poses));
  EXPECT_LT(max_error_deg(truth, two.poses), 1e-5);
  EXPECT_LT(max_object_error(truth, two.poses), 1e-7);
  EXPECT_GT(max_object_error(truth, one.poses), 1e-3);
  std::vector<int> bad(n, 0);
  bad[0] = 1;  // the gauge must be in group 0
  EXPECT_THROW(optimize_turntable_graph(start, edges, std::vector<bool>(n, true), p0, d0, {}, nullptr, bad),
               InvalidInput);
}

}  // namespace station
