#include "capture/pose_graph.h"

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <cmath>
#include <string>

#include "core/error.h"

namespace station {

namespace {

Vec3d log_rotation(const Eigen::Matrix3d& R) {
  const Eigen::AngleAxisd aa(R);
  return aa.axis() * aa.angle();
}

double edge_cost(const std::vector<Eigen::Matrix4d>& X, const PoseGraphEdge& e) {
  const Vector6d r = pose_graph_error(X[e.from], X[e.to], e.measurement);
  return r.dot(e.information * r);
}

}  // namespace

Vector6d pose_graph_error(const Eigen::Matrix4d& Xi, const Eigen::Matrix4d& Xj,
                          const Eigen::Matrix4d& Z) {
  const Eigen::Matrix4d E = rigid_inverse(Xi) * Xj * rigid_inverse(Z);
  Vector6d e;
  e.head<3>() = log_rotation(E.block<3, 3>(0, 0));
  e.tail<3>() = E.block<3, 1>(0, 3);
  return e;
}

PoseGraphResult optimize_pose_graph(std::vector<Eigen::Matrix4d> poses,
                                    const std::vector<PoseGraphEdge>& edges,
                                    const PoseGraphParams& params) {
  const int n = int(poses.size());
  for (const PoseGraphEdge& e : edges)
    if (e.from < 0 || e.to < 0 || e.from >= n || e.to >= n || e.from == e.to)
      throw InvalidInput("pose graph: edge " + std::to_string(e.from) + "-" + std::to_string(e.to) +
                         " names no pair of distinct nodes among " + std::to_string(n));
  PoseGraphResult res;
  const auto total_cost = [&](const std::vector<Eigen::Matrix4d>& X) {
    double c = 0;
    for (const PoseGraphEdge& e : edges) c += edge_cost(X, e);
    return c;
  };
  res.initial_cost = total_cost(poses);
  const int dim = 6 * n;
  const double h = 1e-6;
  double cost = res.initial_cost;
  for (int it = 0; it < params.max_iterations && n > 1; ++it) {
    Eigen::MatrixXd H = Eigen::MatrixXd::Zero(dim, dim);
    Eigen::VectorXd g = Eigen::VectorXd::Zero(dim);
    for (const PoseGraphEdge& e : edges) {
      const Vector6d r = pose_graph_error(poses[e.from], poses[e.to], e.measurement);
      // Central differences on left perturbations of both ends; the error is
      // smooth and cheap, and this keeps the code free of SE(3) Jacobian algebra.
      Eigen::Matrix<double, 6, 12> J;
      for (int side = 0; side < 2; ++side) {
        const int node = side == 0 ? e.from : e.to;
        for (int k = 0; k < 6; ++k) {
          Vector6d d = Vector6d::Zero();
          d(k) = h;
          Eigen::Matrix4d Xp = motion_exp(d) * poses[node];
          Eigen::Matrix4d Xm = motion_exp(-d) * poses[node];
          const Vector6d rp = side == 0 ? pose_graph_error(Xp, poses[e.to], e.measurement)
                                        : pose_graph_error(poses[e.from], Xp, e.measurement);
          const Vector6d rm = side == 0 ? pose_graph_error(Xm, poses[e.to], e.measurement)
                                        : pose_graph_error(poses[e.from], Xm, e.measurement);
          J.col(6 * side + k) = (rp - rm) / (2 * h);
        }
      }
      const Eigen::Matrix<double, 12, 12> Hl = J.transpose() * e.information * J;
      const Eigen::Matrix<double, 12, 1> gl = J.transpose() * e.information * r;
      const int idx[2] = {6 * e.from, 6 * e.to};
      for (int a = 0; a < 2; ++a) {
        g.segment<6>(idx[a]) += gl.segment<6>(6 * a);
        for (int b = 0; b < 2; ++b) H.block<6, 6>(idx[a], idx[b]) += Hl.block<6, 6>(6 * a, 6 * b);
      }
    }
    // Gauge: the fixed node's block becomes identity with a zero gradient; nodes
    // without edges get the same through the ridge.
    const int f = std::clamp(params.fixed_node, 0, n - 1);
    H.block(6 * f, 0, 6, dim).setZero();
    H.block(0, 6 * f, dim, 6).setZero();
    H.block<6, 6>(6 * f, 6 * f).setIdentity();
    g.segment<6>(6 * f).setZero();
    const double ridge = 1e-12 * (H.trace() / dim + 1.0);
    for (int i = 0; i < dim; ++i) H(i, i) += (H(i, i) == 0 ? 1.0 : ridge);
    const Eigen::VectorXd dx = H.ldlt().solve(-g);
    if (!dx.allFinite()) break;
    std::vector<Eigen::Matrix4d> next = poses;
    for (int i = 0; i < n; ++i) next[i] = motion_exp(dx.segment<6>(6 * i)) * poses[i];
    const double next_cost = total_cost(next);
    res.iterations = it + 1;
    if (next_cost > cost * (1 + 1e-12) + 1e-300) {
      // No further decrease: at the minimum to numerical precision (or GN
      // overshot far from it); keep the better poses.
      res.converged = true;
      break;
    }
    poses = std::move(next);
    cost = next_cost;
    if (dx.cwiseAbs().maxCoeff() < params.tolerance) {
      res.converged = true;
      break;
    }
  }
  if (n <= 1) res.converged = true;
  res.final_cost = cost;
  for (const PoseGraphEdge& e : edges) {
    const Vector6d r = pose_graph_error(poses[e.from], poses[e.to], e.measurement);
    res.edge_rotation_deg.push_back(r.head<3>().norm() * 180.0 / M_PI);
    res.edge_translation.push_back(r.tail<3>().norm());
  }
  res.poses = std::move(poses);
  return res;
}

}  // namespace station
