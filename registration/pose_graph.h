#pragma once
// Pose-graph optimisation over SE(3) (Lu & Milios 1997; the information-matrix
// form of Choi, Zhou & Koltun 2015, "Robust reconstruction of indoor scenes",
// sec. 4): nodes are view poses X_i (object <- scanner i), edges measured
// relative motions Z_ij ~ X_i^-1 X_j with a 6x6 information matrix. Minimises
//   sum_edges e_ij^T Omega_ij e_ij,   e_ij = log(X_i^-1 X_j Z_ij^-1)
// (rotation part as an axis-angle vector, translation part as is: the small
// motion of frame i that ICP's Hessian describes) by Gauss-Newton on left
// perturbations X_i <- exp(delta_i) X_i, dense normal equations (a turntable
// session has tens of views, so 6N unknowns solve in microseconds), Jacobians
// by central differences. One node is held fixed (the gauge); nodes without
// edges stay where they are.
#include <Eigen/Core>
#include <vector>

#include "registration/icp.h"

namespace station {

struct PoseGraphEdge {
  int from = 0;  ///< i
  int to = 0;    ///< j
  /// Z_ij: maps view j's scanner-frame points into view i's (an ICP result with
  /// view i as target).
  Eigen::Matrix4d measurement = Eigen::Matrix4d::Identity();
  /// 6x6, rotation first, for a small motion of frame i about its origin.
  Matrix6d information = Matrix6d::Identity();
};

struct PoseGraphParams {
  int max_iterations = 20;
  /// Stop when the largest node update is below this (radians / metres).
  double tolerance = 1e-10;
  int fixed_node = 0;  ///< gauge
};

struct PoseGraphResult {
  std::vector<Eigen::Matrix4d> poses;
  int iterations = 0;
  double initial_cost = 0;
  double final_cost = 0;
  bool converged = false;
  /// Per edge after optimisation: rotation (degrees) and translation (metres)
  /// left between X_i^-1 X_j and the measurement.
  std::vector<double> edge_rotation_deg;
  std::vector<double> edge_translation;
};

/// Optimises `poses` (initial guess, one per node) against `edges`.
/// InvalidInput on an edge naming a node out of range.
PoseGraphResult optimize_pose_graph(std::vector<Eigen::Matrix4d> poses,
                                    const std::vector<PoseGraphEdge>& edges,
                                    const PoseGraphParams& params = {});

/// The turntable line and angles found by optimize_turntable_graph.
struct TurntableGraphModel {
  Vec3d point = Vec3d::Zero();      ///< on the axis, scanner frame
  Vec3d direction = Vec3d::UnitY(); ///< unit
  /// Per node: rotation about `direction` (radians, right-handed) taking the
  /// gauge node's scanner frame to the node's, i.e. X_f^-1 X_i = Rot(line,
  /// angle_i); 0 for the gauge, NaN for nodes off the table.
  std::vector<double> angles_rad;
};

/// The same cost as optimize_pose_graph, with the nodes flagged `on_table`
/// constrained to a rigid turntable: X_i = X_f Rot(L, phi_i), X_f the gauge
/// node's pose (held), L one line in the scanner frame (4 unknowns) and one
/// angle per node. Every view of a turntable session sees the object turned
/// about the same line by a fixed scanner, so this is exact for a rigid table;
/// it leaves 4 + (n - 1) unknowns instead of 6 (n - 1), so a view cannot slide
/// along a face its pairs barely hold. Nodes not on the table keep 6 free
/// unknowns. `axis_point` / `axis_direction`: the starting line (scanner
/// frame); the angles start from the poses. InvalidInput if the gauge node is
/// not on the table, on bad edges or a zero direction.
/// `group` (empty: all 0): per node, the run of table views it belongs to, for an
/// object that moved on the table between runs: group g's nodes are X_i = B_g
/// Rot(L, phi_i), one line L for all (the table did not move), B_0 = X_f and
/// each further group's base B_g 6 unknowns (its first node's angle held).
PoseGraphResult optimize_turntable_graph(std::vector<Eigen::Matrix4d> poses,
                                         const std::vector<PoseGraphEdge>& edges,
                                         const std::vector<bool>& on_table, const Vec3d& axis_point,
                                         const Vec3d& axis_direction, const PoseGraphParams& params = {},
                                         TurntableGraphModel* model = nullptr,
                                         const std::vector<int>& group = {});

/// e = (log R, t) of X_i^-1 X_j Z^-1 (the edge error above).
Vector6d pose_graph_error(const Eigen::Matrix4d& Xi, const Eigen::Matrix4d& Xj,
                          const Eigen::Matrix4d& Z);

}  // namespace station
