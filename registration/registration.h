#pragma once
// Registration of a scan session into one cloud (issue #3; method and measured
// accuracy in docs/registration.md).
//
// Pipeline (register_session):
//  1. per view (capture/icp.h): non-finite points dropped, statistical outlier
//     removal, a voxel-downsampled copy for registration, PCA normals facing
//     the sensor;
//  2. initial poses, per view in this order: the view's initial_pose; the
//     turntable prior from its angle and the session's axis; its angle with the
//     axis estimated from pairwise ICP of neighbouring views
//     (capture/axis_calibration.h); views with none of these go through
//     global registration by features (FPFH + RANSAC, then ICP): chained in
//     capture order when no view has a pose, else against the model merged
//     from the posed views; views with a commanded angle that ICP contradicts
//     are checked the same way (a wrong angle is replaced, with a warning);
//  3. rounds of pairwise point-to-plane ICP between neighbouring views (ring
//     order plus the loop closure last -> first, and optionally skip-one pairs),
//     each followed by a pose-graph optimisation (capture/pose_graph.h) weighted
//     by the ICP Hessians, with the turntable angles as weak prior edges;
//  4. degeneracy about the turntable axis (a bottle, a vase) detected from the
//     smallest eigenvector of each pair's ICP Hessian, and reported; the prior
//     edges then hold the angle;
//  5. merge: every registered view's full cloud (outliers removed) moved into
//     the object frame, normals (the view's own or PCA) facing the sensor, that
//     is outwards, colours kept.
// Poses follow the session convention: object frame <- scanner frame.
#include <Eigen/Core>
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "registration/axis_calibration.h"
#include "registration/fuse.h"
#include "registration/global_registration.h"
#include "registration/icp.h"
#include "capture/session.h"

namespace station {

/// Where a view's initial pose came from.
enum class InitialPoseSource {
  kInitialPose,    ///< the view's initial_pose
  kTurntableAxis,  ///< angle + the session's axis
  kEstimatedAxis,  ///< angle + an axis estimated from pairwise alignments
  kGlobal,         ///< global registration by features (capture/global_registration.h)
  kNone,           ///< nothing usable (the view fails)
};
const char* to_string(InitialPoseSource s);

/// How the pose graph treats the views on the turntable (RegistrationParams).
enum class RigidTurntable { kOff, kOn, kAuto };
const char* to_string(RigidTurntable r);
/// "off", "on" or "auto"; InvalidInput otherwise.
RigidTurntable parse_rigid_turntable(const std::string& name);

struct RegistrationParams {
  /// IcpParams with the registration's choices: coarse iterations on every
  /// 4th source point (the dragon's poses unchanged to 1e-4 degree, the
  /// initial stage 1.7x faster).
  static IcpParams default_icp() {
    IcpParams p;
    p.coarse_stride = 4;
    return p;
  }

  /// Lengths below are relative to the session size: the median bounding-box
  /// diagonal of the views (scanner frame).
  double voxel_rel = 0.004;           ///< voxel edge of the registration copy (0: no downsampling)
  double icp_start_rel = 0.03;        ///< first ICP max correspondence distance, first round
  double icp_end_rel = 0.004;         ///< final ICP max correspondence distance
  double axis_search_start_rel = 0.1; ///< first max distance when searching the unknown axis
  int outlier_neighbors = 16;         ///< statistical outlier removal k (0: off)
  double outlier_std_ratio = 3.0;     ///< ... and its alpha
  int normal_neighbors = 10;          ///< PCA normal neighbourhood (small: less bias on sparse views)
  IcpParams icp = default_icp();      ///< iteration count, guards; distances are set from the above
  /// The ICP runs whose poses are refined again later (axis estimation, every
  /// round but the last) stop at this many times icp's convergence thresholds:
  /// the last round converges fully from wherever they stop. (10: the dragon's
  /// poses unchanged to 1e-5 degree, refinement 1.6x faster.)
  double early_convergence_scale = 10.0;
  /// Each view is paired with the next `neighbors` views in capture order
  /// (1: ring only; 2: also skip-one pairs).
  int neighbors = 2;
  bool loop_closure = true;           ///< pair the last view with the first
  int rounds = 3;                     ///< ICP + pose-graph rounds
  /// Objective of the last round (the earlier ones use icp.objective). Point-to-
  /// point here matches Stanford's dragon alignment slightly better but is
  /// biased on partial overlaps (tests/capture/icp_test.cpp); see docs/registration.md.
  IcpObjective final_objective = IcpObjective::kPointToPlane;
  /// Turntable prior edges between consecutive views (when angles and an axis
  /// are known or estimated): the regulariser for degenerate shapes.
  bool turntable_prior = true;
  double prior_angle_sigma_deg = 2.0;        ///< trust in the commanded angles
  double prior_translation_sigma_rel = 0.02; ///< trust in the axis position
  /// Hold the views with a commanded angle on one rigid turntable in the
  /// pose-graph solves (capture/pose_graph.h optimize_turntable_graph: X_i =
  /// X_0 Rot(axis, phi_i), the axis and the angles unknown), so a view cannot
  /// slide along a face its pairs barely hold. Views without an angle, and
  /// those whose angle was found wrong, stay free. kAuto solves both ways and
  /// keeps the rigid poses only when no view moves further from the free ones
  /// than the tolerances below (an object that shifted on the table between
  /// views, or a wobbling table, fails that and is warned about).
  RigidTurntable rigid_turntable = RigidTurntable::kAuto;
  double rigid_max_deviation_deg = 0.75;  ///< kAuto: largest rotation from the free poses
  double rigid_max_deviation_rel = 0.01;  ///< kAuto: largest shift at the object, relative to the session size
  /// A pair is degenerate when the smallest eigenvalue of its (scale-normalised)
  /// ICP Hessian is below this fraction of the largest.
  double degeneracy_ratio = 2e-3;
  bool merge_normals = true;          ///< give the merged cloud normals (PCA when views have none)
  /// Fuse overlapping points of different views in the merge
  /// (capture/fuse.h): a point within fuse_distance of a point kept from an
  /// earlier view is averaged into it. Off by default: the merged cloud then
  /// keeps every measured point (WLOP, the next stage, evens it out anyway).
  bool fuse = false;
  double fuse_distance = 0;           ///< metres; 0: the median point spacing of the views
  /// Global registration by FPFH features + RANSAC (capture/global_registration.h)
  /// for views with neither an initial pose nor a usable angle: when no view
  /// has a pose, each view is aligned to the previous registered one in capture
  /// order (chain); otherwise against the model merged from the posed views.
  /// Also the recovery for views whose commanded angle is wrong.
  bool global_registration = true;
  double global_voxel_rel = 0.02;     ///< feature voxel, relative to the session size
  GlobalRegistrationParams global;    ///< RANSAC settings (voxel_size is set from global_voxel_rel)
  /// A global pose is kept only when its ICP refinement overlaps at least this
  /// much (0.15 = the ICP guard; 0.3 lost the dragon's views 48 degrees apart).
  double global_min_fitness = 0.15;
  /// RANSAC hypotheses refined by ICP (the best by overlap first; the best ICP
  /// fitness wins). 2 put one of three angle-less views of the simulated
  /// fandisk session 33 degrees off (a near-symmetric fit), 4 or more found it.
  /// Against the model of the posed views (off-table views, suspect angles)
  /// twice as many, plus the best pose turned about the turntable axis in
  /// eighths and about the model's principal axes in quarters (through the
  /// model's centre; the 4 of those with the best overlap); among poses within 0.03 of the best overlap the one whose
  /// colours agree best with the model's wins. A single view whose chosen pose
  /// overlaps too little or whose colours disagree with the model's (15 per
  /// channel) is not settled: every turned start is refined, then ICP runs that
  /// ran out of iterations go on, and a pose with 0.7 of the best overlap and
  /// half the colour difference may replace it (docs/registration.md,
  /// "Hand-held views").
  int global_icp_candidates = 6;
  /// Against a model (the multi-start path above; issue 26, item 3): RANSAC
  /// runs with this many more seeds on the same features, and once at each of
  /// these further FPFH radii (voxels, besides global.feature_radius_voxels);
  /// all their hypotheses are pooled and ranked by overlap. The extra seeds run
  /// only with extra radii (empty global_extra_radii: one run). A merged run
  /// registered onto another (a second pass) uses neither, but gets the other
  /// more starts (12 hypotheses, the turned starts, colour for near ties).
  int global_extra_seeds = 1;
  std::vector<double> global_extra_radii = {8.0};
  /// Wrong-angle check (views posed from angle + axis): a view whose ICP onto
  /// both angle neighbours fails, or lands more than `wrong_angle_deg` from
  /// the prior, is registered globally against the others; when that pose is
  /// more than wrong_angle_deg from the prior it replaces it, with a warning.
  bool check_angles = true;
  double wrong_angle_deg = 8.0;
  /// The prior as a hypothesis (docs/registration.md, "A wrong prior"): when the
  /// run with the angles shows trouble (the views do not fit one rigid turntable,
  /// a view with points failed, an angle was rejected), the session is registered
  /// again without any angle; the commanded angles are fitted to those poses
  /// (registration/prior_check.h: sign, steps for degrees, offset, views off by
  /// more than wrong_angle_deg), registered once more with the corrected prior,
  /// and the result kept is the one with more registered views, then the lower
  /// mean pair residual (a prior-based one only when within 5 % of the
  /// prior-free one's).
  bool prior_check = true;
  /// Groups of two or more views that the turntable angles placed where no pair
  /// joins them to the others (the object moved on the table between two views)
  /// are registered to the others as a whole when that is a move on the table that
  /// overlaps clearly better, and kept when their pairs then join (issue 26).
  bool place_unlinked = true;
};

struct RegistrationProgress {
  /// "prepare", "axis", "global", "angles", "refine" (ICP and pose graph, a step per
  /// round), "merge". Each stage reports done = 0 before its work starts, then after
  /// each step, so the time from a stage's first report to the next stage's is its own.
  /// The prior check's extra runs (RegistrationParams::prior_check) prefix theirs:
  /// "without angles: prepare", "corrected angles: refine", ...
  std::string stage;
  int done = 0;
  int total = 0;
};

/// One registered pair (view `to` aligned onto view `from`).
struct PairDiagnostics {
  int from = 0, to = 0;
  int round = 0;
  bool loop_closure = false;
  bool converged = false;
  double fitness = 0;
  double inlier_rmse = 0;    ///< session units (metres or millimetres: RegistrationResult::mm_per_unit)
  std::size_t correspondences = 0;
  int iterations = 0;
  bool degenerate = false;   ///< rotation about the turntable axis unconstrained
  double eigen_ratio = 0;    ///< smallest / largest eigenvalue of the normalised Hessian
  double graph_rotation_deg = 0;  ///< disagreement with the optimised poses
  double graph_translation = 0;   ///< session units
  std::string message;       ///< why it failed
};

/// What became of a view's commanded angle.
enum class PriorUse {
  kNone,       ///< the view has no angle
  kUsed,       ///< as commanded
  kCorrected,  ///< with the session-wide correction (sign, steps for degrees)
  kRejected,   ///< found wrong: the view was registered without it
  kIgnored,    ///< the poses kept were registered without any angle
};
const char* to_string(PriorUse u);

struct ViewDiagnostics {
  std::size_t input_points = 0;
  std::size_t points = 0;               ///< after non-finite and outlier removal
  std::size_t registration_points = 0;  ///< downsampled copy
  /// The scanner-frame origin failed the sensor check (registration/viewpoint.h:
  /// an imported view stored in another frame); its normals face an estimated viewpoint.
  bool viewpoint_estimated = false;
  double grazing_origin = 0;  ///< share of its points the origin would see beyond 80 degrees
  InitialPoseSource initial = InitialPoseSource::kNone;
  bool registered = false;
  bool angle_rejected = false;          ///< its commanded angle was found wrong (pose from global registration)
  PriorUse prior = PriorUse::kNone;
  /// Registered angle minus the (corrected) commanded one, when the prior was
  /// checked against prior-free poses (degrees).
  std::optional<double> angle_error_deg;
  std::string message;                  ///< why it failed ("views[3] (view_003.ply): ...")
  /// Against reference_pose, both relative to the first registered view with a
  /// reference (view 0 normally): angle of R_est^T R_ref, degrees, and |t_est - t_ref|, session units.
  std::optional<double> rotation_error_deg;
  std::optional<double> translation_error;
  /// The same error measured where the object is: how far the view's
  /// centroid lands from where the reference puts it, session units. The scanner-frame
  /// translation above also carries the rotation error times the lever arm from
  /// the scanner origin (0.45 m on the simulated bench: 0.08 mm per 0.01 deg).
  std::optional<double> object_translation_error;
  /// Share of the view's registration points (up to about 1,000) that its pose
  /// puts where the other registered views saw through (registration/free_space.h:
  /// in front of what they saw, by more than the noise), under the poses kept.
  /// Right poses put 0-6 % there; views on a near-symmetric object's turned twin
  /// 10-58 % in the runs measured (docs/registration.md). None for a view whose
  /// sensor is not known or that was not registered, except a view taken out for
  /// it (registration failed by name): its share where it was.
  std::optional<double> seen_through;
};

/// How well one refined pair's views agree under a set of poses: the RMS
/// point-to-plane distance of the later view's registration points to the
/// earlier view's (nearest neighbour within the final ICP distance, normals
/// within IcpParams::max_normal_angle_deg), in session units.
struct PairResidual {
  int from = 0, to = 0;
  std::size_t matches = 0;            ///< under the refined poses
  double rmse = 0;                    ///< under the refined poses
  std::optional<double> reference_rmse;  ///< under the reference poses, when both views have one
};

struct RegistrationResult {
  std::vector<Eigen::Matrix4d> poses;   ///< per view, object <- scanner (the prior for failed views)
  std::vector<ViewDiagnostics> views;
  std::vector<PairDiagnostics> pairs;   ///< every pair of every round
  std::vector<int> failed_views;
  std::optional<TurntableAxis> axis;    ///< the session's or the estimated one
  std::optional<AxisFitResult> axis_fit;  ///< when the axis was estimated
  /// The last round's poses of the turntable views lie on one rigid turntable
  /// (RegistrationParams::rigid_turntable).
  bool rigid_turntable = false;
  /// Rigid turntable runs the table views were held on, last round: 1 (one
  /// turntable, rigid_turntable), 2 or 3 (the object moved between runs of views,
  /// once or twice: each run on the one axis with its own base pose), 0 (free poses).
  int turntable_groups = 0;
  int moved_after_view = -1;  ///< turntable_groups >= 2: the first view of the second run
  /// turntable_groups >= 2: the first view of each run after the first (the object
  /// moved on the table before each; run_starts[0] == moved_after_view).
  std::vector<int> run_starts;
  /// The first view of a run that was registered to the views before it as a whole
  /// (the object moved, or was turned over, for a second pass), or -1.
  int regrouped_from = -1;
  /// Views that the angles had placed where no pair joined them and that were
  /// registered to the others as a group (the object moved on the table:
  /// RegistrationParams::place_unlinked); their angles are off by the move.
  std::vector<int> moved_with_object;
  /// Largest difference between the rigid and the free solution over the
  /// turntable views, last round (when both were solved): degrees, and session units
  /// at the view's centroid.
  double rigid_deviation_deg = 0;
  double rigid_deviation = 0;
  bool degenerate = false;              ///< some pair is degenerate about the axis
  std::string degeneracy_message;
  /// Which poses were kept (RegistrationParams::prior_check): "prior" (the angles
  /// as given; also when they were not checked), "corrected prior" or "no prior".
  std::string prior_kept = "prior";
  /// The three runs' registered views and mean pair residuals, when compared.
  std::string prior_comparison;
  /// Things the caller should show (a wrong commanded angle, ...), each naming the view.
  std::vector<std::string> warnings;
  /// What was done that the caller may want to know, not a problem (views stored
  /// outside their scanner frame, their sensor estimated).
  std::vector<std::string> notes;
  Cloud merged;
  FuseStats fuse;              ///< when RegistrationParams::fuse (else zeros)
  double fuse_distance = 0;    ///< session units, the distance used (0: not fused)
  /// Over views with errors (see ViewDiagnostics); 0 when no reference.
  int views_with_reference = 0;
  /// Registered views outside the largest group that the last round's
  /// converged pairs join (each such group named in `warnings`).
  int unlinked_views = 0;
  double max_rotation_error_deg = 0, median_rotation_error_deg = 0;
  double max_translation_error = 0, median_translation_error = 0;
  double max_object_translation_error = 0, median_object_translation_error = 0;
  /// Data consistency of the poses, per refined pair (last round's pairs that
  /// converged) and averaged: lets a user see whether the refined poses or the
  /// reference poses fit the scans better (a reference is an estimate too).
  std::vector<PairResidual> pair_residuals;
  double mean_pair_rmse = 0;
  std::optional<double> mean_reference_pair_rmse;  ///< over the same pairs, when all have one
  double diagonal = 0;  ///< session size used for the relative lengths (session units)
  /// Millimetres in one unit of the session (its manifest's `units`: 1000 for m, 1 for
  /// mm). Every length here (poses, errors, residuals, deviations, fuse_distance) is in
  /// the session's units; multiply by this to show millimetres.
  double mm_per_unit = 1000;
  double seconds_prepare = 0, seconds_initial = 0, seconds_refine = 0, seconds_merge = 0,
         seconds_total = 0;
};

/// Progress. Called one call at a time, but not always on the caller's thread: the
/// views are prepared and merged in parallel, and those steps report from the worker
/// that finished a view (under a lock; the callback must not wait on the registration's
/// own parallel work).
using RegistrationCallback = std::function<void(const RegistrationProgress&)>;

/// Registers every view of `session` (see the file comment). Views that cannot
/// be read, are empty or all non-finite, or do not overlap their neighbours
/// are listed in failed_views with a message naming them; the others are still
/// registered and merged. InvalidInput only when fewer than one view is usable.
RegistrationResult register_session(const Session& session, const RegistrationParams& params = {},
                                    const RegistrationCallback& progress = {});

/// The same on clouds in memory: `clouds[i]` is `manifest.views[i]`'s cloud.
/// RegistrationParams' absolute lengths (fuse_distance, the ICP's coloured reference
/// distance and convergence step) are in metres and are taken into the session's units.
RegistrationResult register_views(const std::vector<Cloud>& clouds, const SessionManifest& manifest,
                                  const RegistrationParams& params = {},
                                  const RegistrationCallback& progress = {});

/// Millimetres in one unit of the session: 1000 for `units: m`, 1 for `units: mm`.
double mm_per_unit(const SessionManifest& manifest);
/// `params` with its absolute lengths (metres) in the session's units.
RegistrationParams in_session_units(const RegistrationParams& params, const SessionManifest& manifest);

/// YAML of the result: per view file, pose (the session's `matrix` form),
/// registered or failed with its message, errors when known; the axis used.
std::string poses_to_yaml(const RegistrationResult& result, const SessionManifest& manifest);
/// Writes poses_to_yaml atomically.
void write_poses_yaml(const std::filesystem::path& path, const RegistrationResult& result,
                      const SessionManifest& manifest);

/// Rotation (degrees) and translation (metres) between two poses, each taken
/// relative to its own anchor: A0^-1 A against B0^-1 B.
std::pair<double, double> relative_pose_error(const Eigen::Matrix4d& A0, const Eigen::Matrix4d& A,
                                              const Eigen::Matrix4d& B0, const Eigen::Matrix4d& B);

}  // namespace station
