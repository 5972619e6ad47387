#include "registration/axis_consensus.h"

#include <Eigen/Geometry>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <limits>

#include "registration/icp.h"

namespace station {
namespace {

struct Line {
  Vec3d point, direction;
};

// The screw axis of motion M as a line: its rotation axis, through the point
// (nearest the origin) that the rotation leaves where it is; the motion's slide
// along the axis is left out. Stacked for several motions (all about one line).
Line line_of(const std::vector<Eigen::Matrix4d>& motions, const Vec3d& direction) {
  Eigen::MatrixXd A(3 * motions.size(), 3);
  Eigen::VectorXd b(3 * motions.size());
  for (std::size_t k = 0; k < motions.size(); ++k) {
    const Eigen::Matrix3d R = motions[k].block<3, 3>(0, 0);
    const Vec3d t = motions[k].block<3, 1>(0, 3);
    A.block<3, 3>(3 * k, 0) = Eigen::Matrix3d::Identity() - R;
    b.segment<3>(3 * long(k)) = t - t.dot(direction) * direction;
  }
  // (I - R) c = t has a line of solutions along the axis: the least-norm one.
  Vec3d c = A.jacobiSvd(Eigen::ComputeThinU | Eigen::ComputeThinV).solve(b);
  c -= c.dot(direction) * direction;
  return {c, direction};
}

}  // namespace

double turn_about_axis(const Eigen::Matrix3d& R, const Vec3d& d) {
  const Vec3d v(R(2, 1) - R(1, 2), R(0, 2) - R(2, 0), R(1, 0) - R(0, 1));
  return std::atan2(d.dot(v), R.trace() - d.dot(R * d));
}

bool near_a_turn(double t_deg, const std::vector<double>& turns_deg, double tolerance_deg) {
  return std::any_of(turns_deg.begin(), turns_deg.end(),
                     [&](double u) { return std::abs(std::remainder(t_deg - u, 360.0)) < tolerance_deg; });
}

Eigen::Matrix4d turn_about_line(const Vec3d& point, const Vec3d& direction, double angle) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d R = Eigen::AngleAxisd(angle, direction.normalized()).toRotationMatrix();
  T.block<3, 3>(0, 0) = R;
  T.block<3, 1>(0, 3) = point - R * point;
  return T;
}

AxisConsensus calibrated_consensus(const Vec3d& axis_point, const Vec3d& axis_direction,
                                   const std::vector<Eigen::Matrix4d>& poses, int reference) {
  AxisConsensus c;
  const std::size_t n = poses.size();
  c.deviation_deg.assign(n, std::numeric_limits<double>::infinity());
  c.deviation.assign(n, std::numeric_limits<double>::infinity());
  c.turn.assign(n, 0.0);
  if (reference < 0 || std::size_t(reference) >= n || !poses[std::size_t(reference)].allFinite() ||
      !axis_point.allFinite() || !(axis_direction.norm() > 0))
    return c;
  const Eigen::Matrix4d& P = poses[std::size_t(reference)];
  c.direction = (P.block<3, 3>(0, 0) * axis_direction).normalized();
  c.point = (P * axis_point.homogeneous()).head<3>();
  c.reference = reference;
  c.inliers = {reference};
  c.deviation_deg[std::size_t(reference)] = c.deviation[std::size_t(reference)] = 0;
  c.distinct_turns = 1;
  c.found = true;
  return c;
}

AxisConsensus turntable_consensus(const std::vector<Eigen::Matrix4d>& poses, const std::vector<Vec3d>& centres,
                                  double max_deg, double max_shift, double min_turn_deg, double same_turn_deg) {
  const int n = int(poses.size());
  AxisConsensus best;
  best.deviation_deg.assign(std::size_t(n), std::numeric_limits<double>::infinity());
  best.deviation.assign(std::size_t(n), std::numeric_limits<double>::infinity());
  best.turn.assign(std::size_t(n), 0.0);
  std::vector<bool> finite(poses.size());
  for (int k = 0; k < n; ++k) finite[std::size_t(k)] = poses[std::size_t(k)].allFinite();
  double best_sum = std::numeric_limits<double>::infinity();
  // Every view's deviation from the line turned from `ref`; the inliers and their summed deviation.
  const auto evaluate = [&](const Line& L, int ref, AxisConsensus& out, double& sum) {
    out.point = L.point;
    out.direction = L.direction;
    out.reference = ref;
    out.inliers.clear();
    out.deviation_deg.assign(std::size_t(n), std::numeric_limits<double>::infinity());
    out.deviation.assign(std::size_t(n), std::numeric_limits<double>::infinity());
    out.turn.assign(std::size_t(n), 0.0);
    sum = 0;
    const Eigen::Matrix4d& Pr = poses[std::size_t(ref)];
    for (int k = 0; k < n; ++k) {
      if (!finite[std::size_t(k)]) continue;
      const Eigen::Matrix4d M = poses[std::size_t(k)] * rigid_inverse(Pr);
      const double phi = turn_about_axis(M.block<3, 3>(0, 0), L.direction);
      const Eigen::Matrix4d Mphi = turn_about_line(L.point, L.direction, phi);
      const Vec3d y = (Pr * centres[std::size_t(k)].homogeneous()).head<3>();
      const double dev_deg = rotation_angle_deg(rigid_inverse(Mphi) * M);
      const double dev = ((M - Mphi) * y.homogeneous()).head<3>().norm();
      out.deviation_deg[std::size_t(k)] = dev_deg;
      out.deviation[std::size_t(k)] = dev;
      out.turn[std::size_t(k)] = phi;
      if (dev_deg <= max_deg && dev <= max_shift) {
        out.inliers.push_back(k);
        sum += dev_deg / max_deg + dev / max_shift;
      }
    }
  };
  // The inliers' turns that differ from every other counted one by same_turn_deg.
  const auto distinct = [&](const AxisConsensus& c) {
    std::vector<double> seen;
    for (int k : c.inliers) {
      const double t = c.turn[std::size_t(k)] * 180.0 / M_PI;
      if (!near_a_turn(t, seen, same_turn_deg)) seen.push_back(t);
    }
    return int(seen.size());
  };
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) {
      if (i == j || !finite[std::size_t(i)] || !finite[std::size_t(j)]) continue;
      const Eigen::Matrix4d M = poses[std::size_t(j)] * rigid_inverse(poses[std::size_t(i)]);
      const Eigen::AngleAxisd aa(Eigen::Matrix3d(M.block<3, 3>(0, 0)));
      const double turn_deg = aa.angle() * 180.0 / M_PI;
      if (turn_deg < min_turn_deg || turn_deg > 180.0 - min_turn_deg / 4) continue;
      AxisConsensus c;
      double sum = 0;
      evaluate(line_of({M}, aa.axis().normalized()), i, c, sum);
      // Refitted over its inliers (their motions from the reference), twice.
      for (int round = 0; round < 2 && c.inliers.size() >= 2; ++round) {
        std::vector<Eigen::Matrix4d> motions;
        Vec3d d = Vec3d::Zero();
        for (int k : c.inliers) {
          if (k == i) continue;
          const Eigen::Matrix4d Mk = poses[std::size_t(k)] * rigid_inverse(poses[std::size_t(i)]);
          const Eigen::AngleAxisd ak(Eigen::Matrix3d(Mk.block<3, 3>(0, 0)));
          if (ak.angle() * 180.0 / M_PI < min_turn_deg / 2) continue;
          motions.push_back(Mk);
          // Each axis signed along the line's and weighted by how well its turn defines it.
          const Vec3d a = ak.axis().dot(c.direction) < 0 ? Vec3d(-ak.axis()) : Vec3d(ak.axis());
          d += std::sin(0.5 * ak.angle()) * a;
        }
        if (motions.empty() || !(d.norm() > 0)) break;
        AxisConsensus r;
        double rsum = 0;
        evaluate(line_of(motions, d.normalized()), i, r, rsum);
        if (r.inliers.size() < c.inliers.size()) break;
        c = std::move(r);
        sum = rsum;
      }
      c.distinct_turns = distinct(c);
      if (c.distinct_turns > best.distinct_turns ||
          (c.distinct_turns == best.distinct_turns &&
           (c.inliers.size() > best.inliers.size() || (c.inliers.size() == best.inliers.size() && sum < best_sum)))) {
        best = std::move(c);
        best_sum = sum;
      }
    }
  best.found = best.distinct_turns >= 3;
  return best;
}

}  // namespace station
