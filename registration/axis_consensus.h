#pragma once
// The turntable line most of a session's free poses share (docs/registration.md,
// "Views off the turntable's axis"). On a turntable the scanner stands still and
// the object turns, so every view's pose (object <- scanner) is one base pose
// turned about one line of the object frame: P_k = Rot_L(phi_k) * P_ref. A view
// that a registration without angles placed on a turned twin of a near-symmetric
// object (the bottle's back for its front, the anchor on its side) keeps its
// overlap with its neighbours but leaves that line. The consensus is found by
// RANSAC over the pairs of views: each pair's relative motion is a screw whose
// axis is a candidate line; the line the most views keep to (within a rotation
// and a shift) at distinct turns wins, refitted over them.
#include <vector>

#include <Eigen/Core>

#include "core/geometry.h"

namespace station {

struct AxisConsensus {
  bool found = false;       ///< at least three views keep to one line
  Vec3d point = Vec3d::Zero();      ///< a point of the line (the poses' frame)
  Vec3d direction = Vec3d::UnitZ();  ///< its unit direction
  int reference = -1;       ///< the view the others are turned from (an inlier)
  std::vector<int> inliers;  ///< the views within the bounds, ascending
  /// Per view: how far the nearest pose turned from the reference's about the line
  /// is from the view's own (degrees, and the shift of its centre in the poses' units).
  std::vector<double> deviation_deg, deviation;
  /// Per view: the turn about the line from the reference's pose (radians).
  std::vector<double> turn;
  /// The inliers' distinct turns: a turntable takes each view at its own angle, so
  /// inliers within `same_turn_deg` of one another count once (views stacked on one
  /// turn are twins of each other, not a ring).
  int distinct_turns = 0;
};

/// `poses[k]`: object <- scanner of each view (non-finite ones are left out);
/// `centres[k]`: each view's centre in its own (scanner) frame. A view is an
/// inlier when its deviation is within `max_deg` and `max_shift`. Pairs whose
/// motion turns less than `min_turn_deg` give no line (their axis is noise). The
/// line with the most distinct turns wins, then the most inliers, then the
/// smallest summed deviation.
AxisConsensus turntable_consensus(const std::vector<Eigen::Matrix4d>& poses, const std::vector<Vec3d>& centres,
                                  double max_deg, double max_shift, double min_turn_deg = 10.0,
                                  double same_turn_deg = 5.0);

/// The consensus a calibrated turntable gives without any fit: the axis (the
/// scanner frame's line, `TurntableAxis`: a point, a direction) as view `reference`'s
/// pose (`poses[reference]`, object <- scanner) puts it into the poses' frame, that
/// view its one inlier at turn 0 (found, one distinct turn; the other views'
/// deviations infinite: not measured). Not found for a reference out of range or a
/// non-finite pose.
AxisConsensus calibrated_consensus(const Vec3d& axis_point, const Vec3d& axis_direction,
                                   const std::vector<Eigen::Matrix4d>& poses, int reference);

/// The signed turn (radians) about unit `direction` of the rotation about it
/// nearest R (the one maximising trace(Rot(turn)^T R)).
double turn_about_axis(const Eigen::Matrix3d& R, const Vec3d& direction);

/// Whether turn `t_deg` lies within `tolerance_deg` of one of `turns_deg` (round
/// the circle).
bool near_a_turn(double t_deg, const std::vector<double>& turns_deg, double tolerance_deg);

/// The rigid motion turning by `angle` (radians, right-handed about `direction`)
/// about the line through `point`.
Eigen::Matrix4d turn_about_line(const Vec3d& point, const Vec3d& direction, double angle);

}  // namespace station
