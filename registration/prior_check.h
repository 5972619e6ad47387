#pragma once
// The turntable prior as a hypothesis (docs/registration.md, "A wrong prior"):
// the commanded angles of a session checked against poses registered without
// them. The angles are fitted as measured = sign * scale * commanded + offset
// (sign: the opposite turning sense; scale: step indices given for degrees;
// offset: the gauge, or a table that was not at zero), by a one-point consensus
// over the views; a view whose angle disagrees with the consensus by more than
// the tolerance has a wrong angle.
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "capture/session.h"

namespace station {

/// Each pose's rotation from the first, signed about `direction` (degrees, the
/// commanded-angle convention: X_0^-1 X_i turns by -angle_i about it). Without a
/// direction, the direction most of those rotations share (its sign arbitrary).
std::vector<double> angles_about_common_axis(const std::vector<Eigen::Matrix4d>& poses,
                                             const std::optional<Vec3d>& direction = {});

struct AnglePriorFit {
  bool ok = false;            ///< at least three views with an angle were fitted, half of them agree
  double sign = 1;            ///< -1: the angles turn the other way
  double scale = 1;           ///< degrees per commanded unit (1, or 360/N for step indices)
  double offset_deg = 0;
  int views = 0;              ///< views with an angle and a registered pose
  int agreeing = 0;           ///< of them, within the tolerance
  /// Per view of the manifest: measured minus fitted commanded angle (degrees);
  /// none where the view has no angle or no registered pose.
  std::vector<std::optional<double>> residual_deg;
  std::vector<int> wrong;     ///< views whose |residual| exceeds the tolerance
  /// "" when the angles are as given, else what was corrected ("the opposite sign",
  /// "steps of 30 degrees, not degrees").
  std::string convention;
};

/// Fits the manifest's commanded angles to `poses` (registered[i]: pose i is a
/// registration result). With `known_direction` (the session's calibrated axis,
/// in the scanner frame of the poses' first view... any frame the poses share)
/// the turning sense can be told; without it the sign is the axis's and is
/// fixed to +1.
AnglePriorFit fit_angle_prior(const std::vector<Eigen::Matrix4d>& poses, const std::vector<bool>& registered,
                              const SessionManifest& manifest, double tolerance_deg,
                              const std::optional<Vec3d>& known_direction = {});

/// The scales fit_angle_prior tries for the manifest's commanded angles: 1 (degrees),
/// and for angles that look like step indices (all integers, 2 to 63 at most) 360 /
/// (largest + 1) and 360 / largest.
std::vector<double> angle_scales(const SessionManifest& manifest);

/// How a convention reads in a warning ("the opposite sign", "steps of 45 degrees,
/// not degrees"); "" for sign 1, scale 1.
std::string convention_name(double sign, double scale);

/// Where an object moved on the table: the split of the ordered views `order`
/// (indices into poses, each with its angle in `angles_deg`) into two runs (or,
/// where no two fit and `max_runs` allows, three), each at least three views, that each turn about one
/// axis while all of them do not
/// (the RMS translation a turntable leaves unexplained over the motions between
/// consecutive views, fit_turntable_axis: the whole's at least 3x the worse
/// part's, and above `min_misfit` metres).
struct TurntableSplit {
  bool found = false;
  int last_before = -1, first_after = -1;  ///< views either side of the (first) move
  /// Every move: the first view of each run after the first (first_after first).
  /// Two runs where two fit; three (the object knocked twice) only where no two do.
  std::vector<int> run_starts;
  std::vector<int> run_ends;  ///< the last view of the run before each of run_starts
  double whole_misfit = 0;                  ///< metres, RMS over the whole
  double parts_misfit = 0;                  ///< metres, the worse part's RMS
};
TurntableSplit find_turntable_split(const std::vector<Eigen::Matrix4d>& poses, const std::vector<int>& order,
                                    const std::vector<double>& angles_deg, double min_misfit, int max_runs = 3);

/// Runs of consecutive views (capture order, among those with an angle and a
/// prior-free pose) whose angles are off by one amount: each within
/// `tolerance_deg` of the run's first view. Where the object moved on the table
/// between passes, each pass turns as its angles say and is off from the others by
/// the move's turn. Only runs of three views or more, whose angles span a turn of
/// at least `min_turn_deg` (a table that did not turn drifts by its step from view
/// to view and fits no such run), and only when they hold at least half the views
/// with a residual; else none.
std::vector<std::vector<int>> agreeing_runs(const AnglePriorFit& fit, const SessionManifest& manifest,
                                            double tolerance_deg, double min_turn_deg);

/// T^s for a rigid motion T that turns about one line (a turntable's motion between
/// two views, with any slide along the axis scaled too).
Eigen::Matrix4d screw_power(const Eigen::Matrix4d& T, double s);

/// Where the angles place view `j`, which a run did not register (poses[i] and
/// registered[i] per view of `m`; `diagonal` the session's size): from two
/// registered views k < j < l with angles that bracket it in capture order (the
/// nearest one or two on each side), whose motion T = P_k^-1 P_l turns by what
/// their angles say (`scale` x the difference, within `tol_deg`; at least 15 deg
/// and twice `tol_deg`, and at most 180 less twice `tol_deg`) about a line with no
/// slide along it (under 2 % of `diagonal`), so that the object did not move
/// between them, and about the same line in the same sense (within `tol_deg`) as the
/// pair beside it (the nearest registered view with an angle before k, with k; else
/// l with the nearest after l; when that pair turns as its angles say): a move that
/// turned the object by minus twice the step between k and l turns it by the right
/// amount the wrong way. T taken to the fraction of its turn that j's angle is
/// (between 0 and 1). None when no such pair is found. Without a pair beside it the
/// sense is not checked.
std::optional<Eigen::Matrix4d> pose_from_neighbours_angles(const std::vector<Eigen::Matrix4d>& poses,
                                                            const std::vector<bool>& registered,
                                                            const SessionManifest& m, int j, double scale,
                                                            double tol_deg, double diagonal);

}  // namespace station
