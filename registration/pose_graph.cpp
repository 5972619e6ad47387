#include "registration/pose_graph.h"

#include <Eigen/Cholesky>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
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

void check_edges(const std::vector<PoseGraphEdge>& edges, int n) {
  for (const PoseGraphEdge& e : edges)
    if (e.from < 0 || e.to < 0 || e.from >= n || e.to >= n || e.from == e.to)
      throw InvalidInput("pose graph: edge " + std::to_string(e.from) + "-" + std::to_string(e.to) +
                         " names no pair of distinct nodes among " + std::to_string(n));
}

void edge_diagnostics(const std::vector<Eigen::Matrix4d>& poses, const std::vector<PoseGraphEdge>& edges,
                      PoseGraphResult& res) {
  for (const PoseGraphEdge& e : edges) {
    const Vector6d r = pose_graph_error(poses[e.from], poses[e.to], e.measurement);
    res.edge_rotation_deg.push_back(r.head<3>().norm() * 180.0 / M_PI);
    res.edge_translation.push_back(r.tail<3>().norm());
  }
}

/// Rotation by `angle` about the line (p, d), d unit.
Eigen::Matrix4d line_rotation(const Vec3d& p, const Vec3d& d, double angle) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d R = Eigen::AngleAxisd(angle, d).toRotationMatrix();
  T.block<3, 3>(0, 0) = R;
  T.block<3, 1>(0, 3) = p - R * p;
  return T;
}

/// Unknowns of the turntable graph: the line, one angle per table node but the
/// gauge, a free pose per other node.
struct TurntableState {
  Vec3d p, d;
  std::vector<double> angle;
  std::vector<Eigen::Matrix4d> base;  // per group: B_g (B_0 = the gauge's pose, held)
  std::vector<Eigen::Matrix4d> free;  // poses of the nodes off the table (others unused)
};

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
  check_edges(edges, n);
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
  edge_diagnostics(poses, edges, res);
  res.poses = std::move(poses);
  return res;
}

PoseGraphResult optimize_turntable_graph(std::vector<Eigen::Matrix4d> poses,
                                         const std::vector<PoseGraphEdge>& edges,
                                         const std::vector<bool>& on_table, const Vec3d& axis_point,
                                         const Vec3d& axis_direction, const PoseGraphParams& params,
                                         TurntableGraphModel* model, const std::vector<int>& group_in) {
  const int n = int(poses.size());
  check_edges(edges, n);
  const std::vector<int> group = group_in.empty() ? std::vector<int>(std::size_t(n), 0) : group_in;
  if (int(group.size()) != n || std::any_of(group.begin(), group.end(), [](int g) { return g < 0; }))
    throw InvalidInput("turntable pose graph: one group (>= 0) per node expected");
  const int groups = 1 + *std::max_element(group.begin(), group.end());
  const int f = params.fixed_node;
  if (int(on_table.size()) != n || f < 0 || f >= n || !on_table[f])
    throw InvalidInput("turntable pose graph: the gauge node " + std::to_string(f) +
                       " must be one of the nodes on the table (" + std::to_string(on_table.size()) +
                       " flags for " + std::to_string(n) + " nodes)");
  if (!axis_point.allFinite() || !axis_direction.allFinite() || axis_direction.norm() == 0)
    throw InvalidInput("turntable pose graph: the starting axis is not a line");
  const Eigen::Matrix4d Xf = poses[f];
  const Eigen::Matrix4d Xf_inv = rigid_inverse(Xf);

  // Unknown layout: [0, 4) the line (two tilts of d, two shifts of p across d),
  // then one angle per table node but the gauge, then 6 per other node.
  if (group[f] != 0) throw InvalidInput("turntable pose graph: the gauge node must be in group 0");
  // Each further group's first table node holds its angle (its base turns instead).
  std::vector<int> anchor(std::size_t(groups), -1);
  anchor[0] = f;
  for (int i = 0; i < n; ++i)
    if (on_table[i] && anchor[group[i]] < 0) anchor[group[i]] = i;
  std::vector<int> index(n, -1);
  int dim = 4;
  for (int i = 0; i < n; ++i)
    if (on_table[i] && i != anchor[group[i]]) index[i] = dim++;
  std::vector<int> base_index(std::size_t(groups), -1);
  for (int g = 1; g < groups; ++g)
    if (anchor[g] >= 0) {
      base_index[g] = dim;
      dim += 6;
    }
  for (int i = 0; i < n; ++i)
    if (!on_table[i]) {
      index[i] = dim;
      dim += 6;
    }

  TurntableState s;
  s.d = axis_direction.normalized();
  s.p = axis_point;
  s.angle.assign(n, 0.0);
  s.free = poses;
  s.base.assign(std::size_t(groups), Xf);
  for (int g = 1; g < groups; ++g)
    if (anchor[g] >= 0) s.base[g] = poses[anchor[g]];
  for (int i = 0; i < n; ++i)
    if (on_table[i] && i != anchor[group[i]]) {
      const Eigen::Matrix4d rel = (group[i] == 0 ? Xf_inv : rigid_inverse(s.base[group[i]])) * poses[i];
      const Eigen::AngleAxisd aa(Eigen::Matrix3d(rel.block<3, 3>(0, 0)));
      s.angle[i] = aa.angle() * (aa.axis().dot(s.d) >= 0 ? 1.0 : -1.0);
    }
  const auto pose = [&](const TurntableState& st, int i) -> Eigen::Matrix4d {
    if (!on_table[i]) return st.free[i];
    return st.base[group[i]] * line_rotation(st.p, st.d, st.angle[i]);
  };
  // Applies step x (full or one unknown) to a state.
  const auto apply = [&](const TurntableState& st, const Eigen::VectorXd& x) {
    TurntableState out = st;
    const Vec3d u1 = st.d.unitOrthogonal(), u2 = st.d.cross(u1);
    out.d = (st.d + x(0) * u1 + x(1) * u2).normalized();
    out.p = st.p + x(2) * u1 + x(3) * u2;
    for (int i = 0; i < n; ++i) {
      if (index[i] < 0) continue;
      if (on_table[i])
        out.angle[i] += x(index[i]);
      else
        out.free[i] = motion_exp(x.segment<6>(index[i])) * st.free[i];
    }
    for (int g = 1; g < groups; ++g)
      if (base_index[g] >= 0) out.base[g] = motion_exp(x.segment<6>(base_index[g])) * st.base[g];
    return out;
  };
  const auto total_cost = [&](const TurntableState& st) {
    double c = 0;
    for (const PoseGraphEdge& e : edges) {
      const Vector6d r = pose_graph_error(pose(st, e.from), pose(st, e.to), e.measurement);
      c += r.dot(e.information * r);
    }
    return c;
  };

  PoseGraphResult res;
  res.initial_cost = total_cost(s);
  double cost = res.initial_cost;
  const double h = 1e-6;
  std::vector<int> unknowns;
  for (int it = 0; it < params.max_iterations; ++it) {
    Eigen::MatrixXd H = Eigen::MatrixXd::Zero(dim, dim);
    Eigen::VectorXd g = Eigen::VectorXd::Zero(dim);
    for (const PoseGraphEdge& e : edges) {
      // The unknowns this edge depends on: the line and the ends' angles, or
      // the ends' free poses.
      unknowns.clear();
      bool line = false;
      for (int node : {e.from, e.to}) {
        if (on_table[node]) line = true;
        if (on_table[node] && base_index[group[node]] >= 0 &&
            std::find(unknowns.begin(), unknowns.end(), base_index[group[node]]) == unknowns.end())
          for (int k = 0; k < 6; ++k) unknowns.push_back(base_index[group[node]] + k);
        if (index[node] < 0) continue;
        const int count = on_table[node] ? 1 : 6;
        for (int k = 0; k < count; ++k) unknowns.push_back(index[node] + k);
      }
      if (line)
        for (int k = 0; k < 4; ++k) unknowns.push_back(k);
      const Vector6d r = pose_graph_error(pose(s, e.from), pose(s, e.to), e.measurement);
      Eigen::MatrixXd J(6, unknowns.size());
      Eigen::VectorXd x = Eigen::VectorXd::Zero(dim);
      for (std::size_t c = 0; c < unknowns.size(); ++c) {
        x(unknowns[c]) = h;
        const TurntableState sp = apply(s, x);
        x(unknowns[c]) = -h;
        const TurntableState sm = apply(s, x);
        x(unknowns[c]) = 0;
        J.col(c) = (pose_graph_error(pose(sp, e.from), pose(sp, e.to), e.measurement) -
                    pose_graph_error(pose(sm, e.from), pose(sm, e.to), e.measurement)) /
                   (2 * h);
      }
      const Eigen::MatrixXd JtO = J.transpose() * e.information;
      const Eigen::MatrixXd Hl = JtO * J;
      const Eigen::VectorXd gl = JtO * r;
      for (std::size_t a = 0; a < unknowns.size(); ++a) {
        g(unknowns[a]) += gl(a);
        for (std::size_t b = 0; b < unknowns.size(); ++b) H(unknowns[a], unknowns[b]) += Hl(a, b);
      }
    }
    // Unknowns no edge reaches stay where they are (as in optimize_pose_graph).
    const double ridge = 1e-12 * (H.trace() / dim + 1.0);
    for (int i = 0; i < dim; ++i) H(i, i) += (H(i, i) == 0 ? 1.0 : ridge);
    const Eigen::VectorXd dx = H.ldlt().solve(-g);
    if (!dx.allFinite()) break;
    const TurntableState next = apply(s, dx);
    const double next_cost = total_cost(next);
    res.iterations = it + 1;
    if (next_cost > cost * (1 + 1e-12) + 1e-300) {
      res.converged = true;
      break;
    }
    s = next;
    cost = next_cost;
    if (dx.cwiseAbs().maxCoeff() < params.tolerance) {
      res.converged = true;
      break;
    }
  }
  res.final_cost = cost;
  for (int i = 0; i < n; ++i) poses[i] = pose(s, i);
  edge_diagnostics(poses, edges, res);
  res.poses = std::move(poses);
  if (model) {
    model->direction = s.d;
    // The point nearest the gauge view's scanner origin, as fit_turntable_axis does.
    model->point = s.p - s.d * s.d.dot(s.p);
    model->angles_rad.assign(n, std::numeric_limits<double>::quiet_NaN());
    for (int i = 0; i < n; ++i)
      if (on_table[i]) model->angles_rad[i] = s.angle[i];
  }
  return res;
}

}  // namespace station
