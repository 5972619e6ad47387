#pragma once
// Turntable axis from rigid motions between views.
//
// Every view of a turntable session is the same object turned about one line
// (the axis) seen by a fixed scanner, so the motion taking view b's scanner-frame
// points into view a's (X_a^-1 X_b for poses X, or a pairwise ICP result) is a
// rotation by -(angle_b - angle_a) about that line. The fit:
//  - direction: principal eigenvector of sum_k w_k omega_k omega_k^T, omega_k the
//    axis-angle vector of motion k (sign from the commanded angles: positive
//    angles turn counter-clockwise about the direction, docs/session-format.md);
//  - point: least squares of (I - R_k) p = t_k over all motions (the fixed points
//    of each rotation), plus one row fixing the free position along the axis.
// Residuals per motion say how well a pure turntable explains each: the
// angle about the axis against the commanded one, the tilt (rotation off the
// axis: wobble or a bad pose) and the translation not explained by the axis.
#include <Eigen/Core>
#include <optional>
#include <string>
#include <vector>

#include "core/camera.h"

namespace station {

/// An angle in degrees wrapped into (-180, 180].
double wrap_angle_deg(double a);

/// One measured motion between two views of a turntable session.
struct AxisMotion {
  /// Maps view b's scanner-frame points into view a's scanner frame.
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  /// angle_b - angle_a, degrees (commanded); wrapped into (-180, 180] internally.
  double angle_deg = 0;
  double weight = 1;
};

struct AxisFitParams {
  /// Where along the axis the returned point lies: the foot of the perpendicular
  /// from this point (scanner frame). Empty: from the scanner origin.
  std::optional<Vec3d> point_near;
  /// Motions whose wrapped commanded angle is within this of 180 degrees are
  /// skipped (their rotation sense is ambiguous), degrees.
  double ambiguous_margin_deg = 10;
};

/// Residuals of one motion against the fitted axis.
struct AxisResidual {
  double angle_deg = 0;    ///< measured rotation about the axis minus the commanded angle
  double tilt_deg = 0;     ///< rotation component off the axis
  double translation = 0;  ///< the poses' units, |(I - R) p - t| (0 for a pure rotation about the axis)
  bool used = false;       ///< entered the fit
};

struct AxisFitResult {
  TurntableAxis axis;
  bool ok = false;          ///< enough non-degenerate motions (at least one of 5+ degrees)
  std::string message;      ///< why not
  std::vector<AxisResidual> residuals;  ///< one per input motion
  double rms_angle_deg = 0;
  double rms_tilt_deg = 0;
  double rms_translation = 0;  ///< the poses' units
};

/// Fits the axis to measured motions (see the file comment).
AxisFitResult fit_turntable_axis(const std::vector<AxisMotion>& motions,
                                 const AxisFitParams& params = {});

/// Turntable calibration from a registered session: `poses[i]` (object <- scanner)
/// and `angles_deg[i]` of each view (same length; non-finite poses are skipped).
/// Motions are taken relative to the first usable view; residuals are one per
/// view (the reference view's all zero). The result is what `turntable_axis`
/// in a session manifest holds.
AxisFitResult calibrate_axis(const std::vector<Eigen::Matrix4d>& poses,
                             const std::vector<double>& angles_deg,
                             const AxisFitParams& params = {});

}  // namespace station
