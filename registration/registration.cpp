#include "registration/registration.h"

#include <tbb/parallel_for.h>
#include <yaml-cpp/yaml.h>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <chrono>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <cmath>
#include <set>
#include <iomanip>
#include <sstream>
#include <tuple>
#include <utility>

#include "core/camera.h"
#include "core/threads.h"
#include "registration/axis_calibration.h"
#include "registration/axis_consensus.h"
#include "registration/free_space.h"
#include "registration/pose_graph.h"
#include "registration/prior_check.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/kdtree.h"
#include "core/normals.h"
#include "core/union_find.h"

namespace station {

const char* to_string(InitialPoseSource s) {
  switch (s) {
    case InitialPoseSource::kInitialPose: return "initial_pose";
    case InitialPoseSource::kTurntableAxis: return "turntable_axis";
    case InitialPoseSource::kEstimatedAxis: return "estimated_axis";
    case InitialPoseSource::kGlobal: return "global_features";
    case InitialPoseSource::kNone: return "none";
  }
  return "none";
}

const char* to_string(PriorUse u) {
  switch (u) {
    case PriorUse::kNone: return "none";
    case PriorUse::kUsed: return "used";
    case PriorUse::kCorrected: return "corrected";
    case PriorUse::kRejected: return "rejected";
    case PriorUse::kIgnored: return "ignored";
  }
  return "none";
}

const char* to_string(RigidTurntable r) {
  switch (r) {
    case RigidTurntable::kOff: return "off";
    case RigidTurntable::kOn: return "on";
    case RigidTurntable::kAuto: return "auto";
  }
  return "auto";
}

RigidTurntable parse_rigid_turntable(const std::string& name) {
  if (name == "off") return RigidTurntable::kOff;
  if (name == "on") return RigidTurntable::kOn;
  if (name == "auto") return RigidTurntable::kAuto;
  throw InvalidInput("rigid turntable: '" + name + "' is not off, on or auto");
}

std::pair<double, double> relative_pose_error(const Eigen::Matrix4d& A0, const Eigen::Matrix4d& A,
                                              const Eigen::Matrix4d& B0, const Eigen::Matrix4d& B) {
  const Eigen::Matrix4d ra = rigid_inverse(A0) * A;
  const Eigen::Matrix4d rb = rigid_inverse(B0) * B;
  const double rot = rotation_angle_deg(rigid_inverse(ra) * rb);
  const double trans = (ra.block<3, 1>(0, 3) - rb.block<3, 1>(0, 3)).norm();
  return {rot, trans};
}

namespace {

using Clock = std::chrono::steady_clock;

// Global registration against a model (docs/registration.md, "Hand-held
// views"). Poses within kTie of the best overlap are told apart by colour. For
// a single view, a pose whose mean colour difference to the model (per channel,
// 0-255) is at least kColourDisagrees gives way to one with at least
// kColourOverlapShare of the best overlap and at most kColourBetter times its
// colour difference, and such a view is not settled (more starts are refined).
constexpr double kTie = 0.03;
// place_on_table_axis: a view keeps to the turntable line most views share when
// within kAxisSlack times the rigid turntable's bounds (rigid_max_deviation_*);
// a view off it is swept about the line in kAxisSweepDeg steps, ICP from the
// kAxisStarts best turns.
constexpr double kAxisSlack = 0.4;
constexpr double kAxisSweepDeg = 5;
constexpr std::size_t kAxisStarts = 4;
constexpr double kAxisSameTurnDeg = 5;
// A turntable prior edge the solved graph turns more than this many of its sigmas
// (prior_angle_sigma_deg) from is dropped (refine).
constexpr double kPriorOutlierSigmas = 2;
// A pose near the turn a view's neighbours' angles expect is chosen over the best when
// the best is turned more than kTwinTurnDeg from it and it overlaps at least this share
// of the best's (global_align, expected_).
constexpr double kExpectedShare = 0.5;
constexpr double kTwinTurnDeg = 120;
// A view whose commanded angle looks wrong (check_angles) is expected within this many
// degrees of it by the same rule: an angle a little off (the issue's 11 degrees) must not
// hand the view to the half-turned twin of a near-symmetric shape.
constexpr double kSuspectNearDeg = 45;
// A group registered as a whole (place_unlinked_groups) whose pose turned by half a
// turn overlaps the others at least this share of its own is named as ambiguous (a
// near-symmetric object's right place overlaps less than its twin's, which sees only
// what other views saw: the bottle knocked 90 deg, 0.53 against 0.97).
constexpr double kTwinOverlapShare = 0.5;
// ...and at least this overlap, at the twin and where it is: a view or run that hardly
// overlaps the others anywhere says nothing about which place is right.
constexpr double kTwinMinOverlap = 0.2;
// Every warning about a half-turned twin says this (the comparison of the runs looks
// for it in the runs it passes over).
constexpr const char* kHalfTurn = "turned by half a turn";
// ...and where the colours chose the place, one of these.
constexpr const char* kColoursChose = "the colours chose between the two";
constexpr const char* kColoursFavour = "the colours favour that place";
// Views placed where they overlap and their colours differ (a pair the chain would
// refute: kChainColourRefutes) are named with this.
constexpr const char* kColoursDiffer = "views overlap where their colours differ";
constexpr double kPairColourOverMedian = 5;
constexpr double kColourDisagrees = 15;
// ...or, where the model's own views disagree more among themselves (light and
// shading that change from view to view on a real scanner), this many times
// their median pair difference.
constexpr double kColourDisagreesOverViews = 2.5;
constexpr double kColourOverlapShare = 0.7;
constexpr double kColourBetter = 0.5;
// A single view no angle placed (colour_twins) that fits the views the angles placed
// turned by half a turn too goes there when its colours there differ by at most this
// share of where it is. Measured on the sim tests' everyday sessions (the bottle with
// and without colours and the coloured cube, knocked -30 to 135 deg): the coloured
// bottle's views on the twin 0.51 and 0.53 (the
// shapes favouring the twin, 1.0 against 0.70 overlap); the other views whose turned
// place fitted too came to 0.78 and over.
constexpr double kColourTwinView = 0.6;
// The colour comparison's gain (one for all channels) stays within [1/this, this].
constexpr double kColourMaxGain = 3;
// Turned starts refined first (all of them when those leave no pose that
// overlaps enough and agrees in colour).
constexpr std::size_t kSpunRefined = 4;
// A chain's pair (pair_align) whose colours differ by this many times the colour
// bound (kColourDisagrees: a single view has no views of its own to calibrate it)
// is refuted by them: the second chain runs, takes no such fit at once and prefers
// any other. At the bound alone, the bottle's half-turned twin at 200x150 (15 per
// channel) was refuted too, and the second chain, taking none of its four views at
// once, joined them wrong and won. (Its right poses, 90 deg apart, read 41 and 47,
// refuted even so: the first chain takes the nearest fit whatever its colours.)
constexpr double kChainColourRefutes = 2;
// A chain's target view's colours (own_colours) are thinned to about this many points.
constexpr std::size_t kOwnColoursPoints = 100000;
// The final ICP distance is never under this share of the median point spacing
// (final_distance).
constexpr double kEndPerSpacing = 2.0 / 3.0;
// A view still not settled after every start: each distinct converged pose is
// slid along the translation its ICP system constrains least, in steps of
// kSlideStep ICP start distances out to kSlideReach of the session size either
// way; at each place the overlap and the colours are compared (at the ICP start
// distance), and ICP goes on from the kSlideRefined best-coloured places of
// each pose.
constexpr double kSlideStep = 0.6;
constexpr double kSlideReach = 0.25;
constexpr std::size_t kSlideRefined = 2;
// A pose against a model is refused when more than this share of the view's
// points lie where a model view with a known sensor saw through: in front of
// what that view saw along the same line of sight (free space; a near-symmetric
// shape fitted turned puts part of the view outside the object)...
constexpr double kSeenThrough = 0.2;
// A run whose every view puts at most this share there (right poses: 0-6 %) is
// clear of what the views saw; one with a view above kRunSeenThrough is not
// (register_views_checked). Lower than kSeenThrough: in a run, a wrong view's own
// sight also sees through the right views it contradicts, so the shares spread
// (the run without angles of the issue's session turned -30 deg: the wrong view
// 10 %, right ones up to 16 %; right runs 0-6 %).
constexpr double kSeenClear = 0.1;
constexpr double kRunSeenThrough = 0.15;
// ...by more than kSeenMargin registration voxels or kSeenNoise times the
// median ICP point-to-plane RMS of the view's converged poses, whichever is
// larger: a real depth camera's noise (test
// KinectFrames.ARightPoseIsNotSeenThroughAndATurnedOneIs).
constexpr double kSeenMargin = 3;
constexpr double kSeenNoise = 3;
// Only the view's points within this share of the session size of the model's
// bounding box count (a hand or a stand in a hand-held view is not the object).
constexpr double kSeenGrow = 0.1;

double median_of(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const std::size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

// Per centre: finite and within `diagonal` of the median of the finite centres (the
// views of one object on the table, against views lying elsewhere).
std::vector<bool> views_at_table(const std::vector<Vec3d>& c, double diagonal) {
  std::vector<double> xs[3];
  for (const Vec3d& x : c)
    if (x.allFinite())
      for (int a = 0; a < 3; ++a) xs[a].push_back(x[a]);
  std::vector<bool> out(c.size(), false);
  if (xs[0].empty()) return out;
  const Vec3d median(median_of(xs[0]), median_of(xs[1]), median_of(xs[2]));
  for (std::size_t i = 0; i < c.size(); ++i) out[i] = c[i].allFinite() && (c[i] - median).norm() <= diagonal;
  return out;
}

Eigen::Matrix3d skew(const Vec3d& a) {
  Eigen::Matrix3d m;
  m << 0, -a.z(), a.y(), a.z(), 0, -a.x(), -a.y(), a.x(), 0;
  return m;
}

Vec3d centroid(const std::vector<Vec3f>& pts) {
  Vec3d c = Vec3d::Zero();
  for (const Vec3f& p : pts) c += p.cast<double>();
  return pts.empty() ? c : Vec3d(c / double(pts.size()));
}

std::string view_name(const SessionManifest& m, std::size_t i) {
  return "views[" + std::to_string(i) + "] (" + m.views[i].file + ")";
}

struct HessianAnalysis {
  double ratio = 1;         // smallest / largest eigenvalue
  bool about_axis = false;  // the weakest direction is a rotation about the axis
};

// The ICP Hessian is for motions about the target frame's origin, in radians
// and metres; moved to the overlap's centroid and scaled by the object size,
// its eigenvalues compare rotations and translations fairly.
HessianAnalysis analyse_hessian(const Matrix6d& H, const Vec3d& c, double scale,
                                const std::optional<Vec3d>& axis_dir) {
  HessianAnalysis a;
  Matrix6d A = Matrix6d::Identity();
  A.block<3, 3>(3, 0) = skew(c);
  Matrix6d D = Matrix6d::Identity();
  D.block<3, 3>(0, 0) *= 1.0 / std::max(scale, 1e-9);
  const Matrix6d Hn = D * A.transpose() * H * A * D;
  Eigen::SelfAdjointEigenSolver<Matrix6d> es(Hn);
  const double top = es.eigenvalues()(5);
  if (!(top > 0)) return a;
  a.ratio = std::max(0.0, es.eigenvalues()(0)) / top;
  const Vector6d v = es.eigenvectors().col(0);
  if (axis_dir) a.about_axis = std::abs(v.head<3>().dot(*axis_dir)) > 0.7 * v.norm();
  return a;
}

struct Pair {
  int from, to;
  bool loop;
};

/// RMS point-to-plane distance of b's registration points to a's (see
/// PairResidual), with b moved into a's frame by Ta^-1 Tb.
std::pair<double, std::size_t> pair_plane_rmse(const PreparedView& a, const PreparedView& b,
                                               const Eigen::Matrix4d& Ta, const Eigen::Matrix4d& Tb,
                                               double max_distance, double min_normal_dot) {
  if (!a.index || a.points.empty()) return {0.0, 0};
  const Eigen::Matrix4d T = rigid_inverse(Ta) * Tb;
  const Eigen::Matrix3d R = T.block<3, 3>(0, 0);
  const Eigen::Vector3d t = T.block<3, 1>(0, 3);
  double ss = 0;
  std::size_t n = 0;
  for (std::size_t k = 0; k < b.points.size(); ++k) {
    const Eigen::Vector3d p = R * b.points[k].cast<double>() + t;
    const auto [j, d] = a.index->nearest_within(p.cast<float>(), float(max_distance));
    if (j < 0 || d > max_distance) continue;
    const Eigen::Vector3d nq = a.normals[j].cast<double>();
    if ((R * b.normals[k].cast<double>()).dot(nq) < min_normal_dot) continue;
    const double r = (p - a.points[j].cast<double>()).dot(nq);
    ss += r * r;
    ++n;
  }
  return {n ? std::sqrt(ss / double(n)) : 0.0, n};
}

class Registrar {
 public:
  // `moved_from`: the first view of a second run the prior check found (the
  // object turned on the table before it; its angles are corrected already), or -1.
  Registrar(const std::vector<Cloud>& clouds, const SessionManifest& m, const RegistrationParams& p,
            const RegistrationCallback& cb, int moved_from = -1)
      : clouds_(clouds), m_(m), p_(p), cb_(cb), moved_from_(moved_from) {}

  /// A run with the angles corrected (a convention, a move): `given` is the manifest
  /// as the user gave it, whose angles the warnings quote as commanded.
  Registrar& as_given(const SessionManifest& given) {
    given_ = &given;
    return *this;
  }

  /// A run without the session's axis (the run without angles): the calibrated axis
  /// it was given, for place_on_table_axis alone (a line the views' poses can be
  /// checked against, not a prior).
  Registrar& with_calibrated_axis(const std::optional<TurntableAxis>& axis) {
    calibrated_ = axis;
    return *this;
  }

  RegistrationResult run() {
    const auto t_total = Clock::now();
    const std::size_t n = m_.views.size();
    res_.mm_per_unit = mm_per_unit(m_);
    res_.poses.assign(n, Eigen::Matrix4d::Identity());
    res_.views.resize(n);
    auto t0 = Clock::now();
    prepare();
    res_.seconds_prepare = seconds_since(t0);
    t0 = Clock::now();
    const State start = state();
    initial_poses();
    res_.seconds_initial = seconds_since(t0);
    t0 = Clock::now();
    std::size_t warned = res_.warnings.size();
    refine();
    const double initial_seconds = res_.seconds_initial;
    retry_chain(start, warned);
    if (!split_.found) place_on_table_axis(warned);
    res_.seconds_initial = initial_seconds;  // (the second chain's is in the refinement's)
    // Two runs on the table (the object moved, or was turned over for a second
    // pass): the refinement placed the second run from the angles, which the
    // move made wrong; register it to the first as a whole, then refine again
    // (its word on the rigid turntable replaces the first one's). A run the
    // prior check found by its shared angle error counts too: its corrected
    // angles turn it right, but the move across the table is left, and the pairs
    // across it fail, so the refinement alone does not see it.
    if (!split_.found && moved_from_ > 0) {
      // The first view of the run that regroup() takes (usable, its angle kept).
      const auto takes = [&](int j) { return usable_[std::size_t(j)] && placed_by_angle(j); };
      int first = moved_from_;
      while (first < int(n) && !takes(first)) ++first;
      for (int j = std::min(first, int(n)) - 1; first < int(n) && j >= 0; --j)
        if (takes(j)) {
          split_.found = true;
          split_.last_before = j;
          split_.first_after = first;
          break;
        }
    }
    std::size_t last_refine_words = warned;  // where the last refinement's warnings start
    if (split_.found) {
      const std::vector<std::string> first_words(res_.warnings.begin() + std::ptrdiff_t(warned), res_.warnings.end());
      res_.warnings.resize(warned);
      if (regroup()) {
        res_.pairs.clear();
        last_refine_words = res_.warnings.size();  // (after regroup's own warning)
        refine();
      } else {
        // (regroup's word on a twin, where it said one, stays before the refinement's.)
        const std::size_t said = res_.warnings.size() - warned;
        res_.warnings.insert(res_.warnings.end(), first_words.begin(), first_words.end());
        last_refine_words = warned + said;
        refine_words_ = {refine_words_.first + said, refine_words_.second + said};
      }
    }
    if (p_.place_unlinked && p_.global_registration) place_unlinked_groups(last_refine_words);
    if (p_.global_registration) {
      settle_view_twins();
      settle_runs_twin();
    }
    name_pairs_whose_colours_differ();
    res_.seconds_refine = seconds_since(t0);
    t0 = Clock::now();
    finish();
    res_.seconds_merge = seconds_since(t0);
    res_.seconds_total = seconds_since(t_total);
    return std::move(res_);
  }

 private:
  void report(const std::string& stage, int done, int total) {
    if (cb_) cb_({stage, done, total});
  }

  void fail(std::size_t i, const std::string& why) {
    usable_[i] = false;
    res_.views[i].registered = false;
    if (res_.views[i].message.empty()) res_.views[i].message = view_name(m_, i) + ": " + why;
  }

  // The final ICP max correspondence distance: icp_end_rel of the session size,
  // but never under two thirds of the registration copies' median point spacing.
  // A sparse scan of a small object (a Rubik's cube at 320x240: 1.4 mm between
  // points, 0.5 mm icp_end) finds a neighbour in reach for one point in eight on
  // the very same surface, so every pair read as no overlap (fitness 0.12 under
  // 0.15) and the angles were taken unchecked. Dense views are voxelled to about
  // icp_end already (spacing 1.1-1.5 times it), so the floor leaves them as they were.
  double final_distance() const {
    std::vector<double> spacings;
    for (std::size_t i = 0; i < views_.size(); ++i)
      if (usable_[i] && views_[i].points.size() >= 2) spacings.push_back(median_spacing(views_[i].points));
    const double spacing = spacings.empty() ? 0.0 : median_of(spacings);
    // (Never beyond the first round's start distance: ICP's distance shrinks.)
    const double end = p_.icp_end_rel * diag_;
    return std::max(end, std::min(kEndPerSpacing * spacing, std::max(end, p_.icp_start_rel * diag_)));
  }

  void prepare() {
    const std::size_t n = m_.views.size();
    usable_.assign(n, true);
    // Session size first (median view diagonal): the voxel and ICP distances follow it.
    std::vector<double> diags;
    for (std::size_t i = 0; i < n; ++i) {
      std::vector<Vec3f> finite;
      for (const Vec3f& q : clouds_[i].points)
        if (q.allFinite()) finite.push_back(q);
      if (!finite.empty()) diags.push_back(bounding_box(finite).diagonal());
    }
    diag_ = median_of(diags);
    res_.diagonal = diag_;
    warn_units();
    PrepareParams pp;
    pp.voxel_size = p_.voxel_rel * diag_;
    pp.outlier_neighbors = p_.outlier_neighbors;
    pp.outlier_std_ratio = p_.outlier_std_ratio;
    pp.normal_neighbors = p_.normal_neighbors;
    // The merge's normals, from the outlier removal's search (no second one over every point).
    pp.full_normal_neighbors = p_.merge_normals ? p_.normal_neighbors : 0;
    pp.intensity = p_.icp.objective == IcpObjective::kColoured || p_.final_objective == IcpObjective::kColoured;
    views_.resize(n);
    feats_.resize(n);
    report("prepare", 0, int(n));
    {
      // The views side by side: each one's index builds and copies are serial.
      std::mutex progress;
      int done = 0;
      tbb::parallel_for(std::size_t(0), n, [&](std::size_t i) {
        views_[i] = prepare_view(clouds_[i], pp);
        const std::lock_guard<std::mutex> lock(progress);
        report("prepare", ++done, int(n));
      });
    }
    for (std::size_t i = 0; i < n; ++i) {
      ViewDiagnostics& d = res_.views[i];
      d.input_points = clouds_[i].size();
      d.points = views_[i].full.size();
      d.registration_points = views_[i].points.size();
      d.viewpoint_estimated = !views_[i].viewpoint_at_origin;
      d.grazing_origin = views_[i].grazing_origin;
      if (clouds_[i].empty()) fail(i, "empty view");
      else if (views_[i].full.empty()) fail(i, "no finite points");
      else if (views_[i].points.size() < std::size_t(std::max(p_.icp.min_correspondences, 6)))
        fail(i, "too few points (" + std::to_string(views_[i].points.size()) + ")");
    }
    if (std::none_of(usable_.begin(), usable_.end(), [](bool b) { return b; }))
      throw InvalidInput("registration: no usable view (all empty or non-finite)");
    icp_end_ = final_distance();

    warn_estimated_viewpoints();
    if (pp.intensity) warn_missing_colours();
  }

  // Units the views' size contradicts: a turntable object spans centimetres to a
  // metre or two; a median view 20 "m" across is millimetres, one under a
  // "millimetre" is metres. Said, not changed (the axis and poses are in the same
  // units as the manifest says, and only the user knows which is wrong).
  void warn_units() {
    if (!(diag_ > 0)) return;
    char buf[320];
    if (m_.units == "m" && diag_ > 20)
      std::snprintf(buf, sizeof buf,
                    "the views are %.4g m across (median view diagonal) while the session says units: m: are "
                    "they in millimetres? (the turntable axis and poses must be in the same units as the views)",
                    diag_);
    else if (m_.units == "mm" && diag_ < 1)
      std::snprintf(buf, sizeof buf,
                    "the views are %.3g mm across (median view diagonal) while the session says units: mm: are "
                    "they in metres? (the turntable axis and poses must be in the same units as the views)",
                    diag_);
    else
      return;
    res_.warnings.push_back(buf);
  }

  // Coloured ICP asked for, views without colours: their pairs are matched on the
  // geometry alone (the objective falls back pair by pair), said once.
  void warn_missing_colours() {
    std::vector<std::size_t> bare;
    std::size_t usable = 0;
    for (std::size_t i = 0; i < views_.size(); ++i) {
      if (!usable_[i]) continue;
      ++usable;
      if (!views_[i].full.has_colours()) bare.push_back(i);
    }
    if (bare.empty()) return;
    std::string w = "the coloured ICP objective needs colours, and ";
    if (bare.size() == usable) {
      w += "no view has any: every pair is matched on its geometry alone (point-to-plane)";
    } else {
      w += std::to_string(bare.size()) + (bare.size() == 1 ? " view has" : " views have") + " none (" +
           view_name(m_, bare[0]) + (bare.size() > 1 ? ", ..." : "") +
           "): the pairs with them are matched on their geometry alone (point-to-plane)";
    }
    res_.warnings.push_back(w);
  }

  // One note for the views whose normals cannot face the scanner-frame origin.
  void warn_estimated_viewpoints() {
    std::vector<std::size_t> moved;
    double lo = 1, hi = 0;
    for (std::size_t i = 0; i < res_.views.size(); ++i)
      if (res_.views[i].viewpoint_estimated) {
        moved.push_back(i);
        lo = std::min(lo, res_.views[i].grazing_origin);
        hi = std::max(hi, res_.views[i].grazing_origin);
      }
    if (moved.empty()) return;
    std::ostringstream w;
    w << std::fixed << std::setprecision(0);
    w << moved.size() << " of " << res_.views.size() << (moved.size() == 1 ? " view is" : " views are")
      << " not stored in their scanner frame (from the origin " << 100 * lo << "-" << 100 * hi
      << " % of their points would be seen edge-on): their normals face a viewpoint estimated from the view";
    res_.notes.push_back(w.str());
  }

  // Runs ICP on each pair (view `to` onto view `from`) from the current poses
  // or the given initial relative motions.
  std::vector<IcpResult> run_pairs(const std::vector<Pair>& pairs,
                                   const std::vector<Eigen::Matrix4d>& initial, double start,
                                   double end, std::optional<IcpObjective> objective = {},
                                   double convergence_scale = 1.0) {
    IcpParams ip = p_.icp;
    ip.convergence_rotation *= convergence_scale;
    ip.convergence_translation *= convergence_scale;
    if (objective) ip.objective = *objective;
    ip.max_distance_start = start;
    ip.max_distance_end = end;
    std::vector<IcpResult> out(pairs.size());
    tbb::parallel_for(std::size_t(0), pairs.size(), [&](std::size_t k) {
      out[k] = icp_point_to_plane(views_[pairs[k].to], views_[pairs[k].from], initial[k], ip);
    });
    return out;
  }

  // The usable views in turntable order: capture order, or the order of their
  // turns where place_on_table_axis found them (ring_order_; views not in it after).
  std::vector<int> ring() const {
    std::vector<int> r;
    for (int i : ring_order_)
      if (usable_[std::size_t(i)]) r.push_back(i);
    for (std::size_t i = 0; i < usable_.size(); ++i)
      if (usable_[i] && std::find(ring_order_.begin(), ring_order_.end(), int(i)) == ring_order_.end())
        r.push_back(int(i));
    return r;
  }

  bool has_angle(int i) const { return m_.views[i].angle_deg.has_value(); }
  // View i's angle as the refinement uses it: the commanded one, turned by the
  // move of the object where a run of views was registered to the others as a
  // whole (the move's turn about the table: the later views' angles are all off by it).
  double angle_of(int i) const {
    return *m_.views[std::size_t(i)].angle_deg + (angle_shift_.empty() ? 0.0 : angle_shift_[std::size_t(i)]);
  }
  // After `group` was moved by G (world frame): their angles turned by G's turn
  // about the table, so that the prior between consecutive views and the axis fit
  // agree with the moved poses. The turn's sign is the one under which the motion
  // from `anchor` (a view not moved) to the group's first view is what the
  // angles say (the poses' frame need not be the table's).
  // A move that is no turn about the table (turned over: half a turn about a level
  // axis) leaves the angles as they are: no shift of them describes it.
  void shift_angles(const std::vector<int>& group, const Eigen::Matrix4d& G, int anchor,
                    const std::optional<std::pair<Vec3d, Vec3d>>& table) {
    if (!res_.axis || !table || group.empty() || anchor < 0 || !has_angle(anchor)) return;
    const Eigen::AngleAxisd turn(Eigen::Matrix3d(G.block<3, 3>(0, 0)));
    constexpr double kDegree = M_PI / 180;
    if (turn.angle() > 2 * kDegree && std::abs(turn.axis().dot(table->second.normalized())) < std::cos(10 * kDegree))
      return;
    if (angle_shift_.empty()) angle_shift_.assign(m_.views.size(), 0.0);
    const double theta = turn.angle() * 180.0 / M_PI;
    int b = -1;
    for (int j : group)
      if (has_angle(j)) {
        b = j;
        break;
      }
    if (b < 0) return;
    const Eigen::Matrix4d measured = rigid_inverse(res_.poses[std::size_t(anchor)]) * res_.poses[std::size_t(b)];
    double best = std::numeric_limits<double>::infinity(), shift = 0;
    for (double s : {-theta, theta}) {
      const Eigen::Matrix4d said = rigid_inverse(turntable_pose(*res_.axis, angle_of(anchor))) *
                                   turntable_pose(*res_.axis, angle_of(b) + s);
      const double off = rotation_angle_deg(rigid_inverse(measured) * said);
      if (off < best) best = off, shift = s;
    }
    for (int j : group)
      if (has_angle(j)) angle_shift_[std::size_t(j)] += shift;
  }

  // Axis unknown, angles known: pairwise ICP of consecutive views from axis
  // hypotheses, then the axis that best explains the converged pair motions.
  void estimate_axis(const std::vector<int>& with_angle) {
    const int m = int(with_angle.size());
    if (m < 2) return;
    report("axis", 0, 2);
    Vec3d c = Vec3d::Zero();
    for (int i : with_angle) c += centroid(views_[i].points);
    c /= double(m);
    std::vector<Pair> pairs;
    for (int k = 0; k + 1 < m || (m > 2 && k + 1 == m); ++k)
      pairs.push_back({with_angle[k], with_angle[(k + 1) % m], k + 1 == m});
    const auto motions_for = [&](const TurntableAxis& axis, const std::vector<Pair>& ps) {
      std::vector<Eigen::Matrix4d> init;
      for (const Pair& pr : ps)
        init.push_back(rigid_inverse(turntable_pose(axis, *m_.views[pr.from].angle_deg)) *
                       turntable_pose(axis, *m_.views[pr.to].angle_deg));
      return init;
    };
    // Direction hypotheses: the scanner's up (-y) first, then the other signed
    // axes, scored on a few pairs by the overlap ICP reaches.
    const Vec3d dirs[6] = {-Vec3d::UnitY(), Vec3d::UnitY(), -Vec3d::UnitZ(),
                           Vec3d::UnitZ(),  -Vec3d::UnitX(), Vec3d::UnitX()};
    std::vector<Pair> probe;
    for (int k : {0, int(pairs.size()) / 3, 2 * int(pairs.size()) / 3})
      if (std::none_of(probe.begin(), probe.end(), [&](const Pair& q) { return q.from == pairs[k].from; }))
        probe.push_back(pairs[k]);
    TurntableAxis best;
    double best_score = -1;
    const double start = p_.axis_search_start_rel * diag_;
    const double end = icp_end_;
    for (const Vec3d& d : dirs) {
      TurntableAxis axis;
      axis.direction = d;
      axis.point = c;
      const auto r = run_pairs(probe, motions_for(axis, probe), start, end, std::nullopt,
                               p_.early_convergence_scale);
      double score = 0;
      for (const IcpResult& x : r) score += x.converged ? x.fitness : 0.0;
      if (score > best_score + 1e-9) {
        best_score = score;
        best = axis;
      }
      if (best_score > 0.5 * double(probe.size())) break;  // clearly right: skip the rest
    }
    // Two fits: the second starts from the first fitted axis.
    for (int pass = 0; pass < 2; ++pass) {
      const auto r = run_pairs(pairs, motions_for(best, pairs), pass == 0 ? start : 2 * end, end,
                               std::nullopt, p_.early_convergence_scale);
      std::vector<AxisMotion> motions(pairs.size());
      for (std::size_t k = 0; k < pairs.size(); ++k) {
        motions[k].transform = r[k].transform;
        motions[k].angle_deg = *m_.views[pairs[k].to].angle_deg - *m_.views[pairs[k].from].angle_deg;
        motions[k].weight = r[k].converged ? r[k].fitness : 0.0;
      }
      AxisFitParams fp;
      fp.point_near = c;
      AxisFitResult fit = fit_turntable_axis(motions, fp);
      if (!fit.ok) break;
      best = fit.axis;
      res_.axis_fit = fit;
      report("axis", pass + 1, 2);
    }
    if (res_.axis_fit) res_.axis = best;
  }

  void initial_poses() {
    const std::size_t n = m_.views.size();
    if (m_.axis) res_.axis = m_.axis;
    std::vector<int> need_axis;
    for (int i : ring())
      if (!m_.views[i].initial_pose && has_angle(i)) need_axis.push_back(i);
    if (!m_.axis && !need_axis.empty()) estimate_axis(need_axis);
    for (std::size_t i = 0; i < n; ++i) {
      ViewDiagnostics& d = res_.views[i];
      const ViewRecord& v = m_.views[i];
      if (v.initial_pose) {
        res_.poses[i] = *v.initial_pose;
        d.initial = InitialPoseSource::kInitialPose;
      } else if (v.angle_deg && res_.axis) {
        res_.poses[i] = turntable_pose(*res_.axis, *v.angle_deg);
        d.initial = m_.axis ? InitialPoseSource::kTurntableAxis : InitialPoseSource::kEstimatedAxis;
      } else if (usable_[i] && !p_.global_registration) {
        fail(i, v.angle_deg ? "turntable axis could not be estimated"
                            : "no initial pose and no turntable angle (global registration disabled)");
      }
    }
    if (p_.global_registration) {
      if (p_.check_angles) check_angles();
      global_poses();
    }
  }

  bool posed(std::size_t i) const {
    return usable_[i] && res_.views[i].initial != InitialPoseSource::kNone;
  }

  // Scale 0: the FPFH radius of p_.global; 1, 2, ...: p_.global_extra_radii.
  GlobalRegistrationParams global_params(std::size_t scale = 0) const {
    GlobalRegistrationParams gp = p_.global;
    gp.voxel_size = p_.global_voxel_rel * diag_;
    if (scale > 0) gp.feature_radius_voxels = p_.global_extra_radii.at(scale - 1);
    return gp;
  }
  std::size_t feature_scales() const { return 1 + p_.global_extra_radii.size(); }
  // ICP from a global registration's pose: from twice its inlier distance (at least the
  // refinement's final distance) down to that final distance.
  IcpParams refine_params() const {
    const GlobalRegistrationParams gp = global_params();
    IcpParams ip = p_.icp;
    ip.max_distance_start = std::max(2.0 * gp.inlier_distance_voxels * gp.voxel_size, icp_end_);
    ip.max_distance_end = icp_end_;
    return ip;
  }

  const FeatureView& features_of(int i, std::size_t scale = 0) {
    std::vector<std::unique_ptr<FeatureView>>& f = feats_[i];
    if (f.size() < feature_scales()) f.resize(feature_scales());
    if (!f[scale]) f[scale] = std::make_unique<FeatureView>(
                        make_feature_view(views_[i].full.points, views_[i].viewpoint, global_params(scale)));
    return *f[scale];
  }
  // A view's features at the first scale with its colours' chromaticities (colour-gated
  // matches: FeatureView::chroma), made once.
  const FeatureView& colour_features_of(int i) {
    colour_feats_.resize(views_.size());
    std::unique_ptr<FeatureView>& f = colour_feats_[std::size_t(i)];
    if (!f) f = std::make_unique<FeatureView>(with_colours(features_of(i), views_[i].full));
    return *f;
  }
  // A view's features at every scale (the multi-start path).
  std::vector<const FeatureView*> all_features_of(int i) {
    std::vector<const FeatureView*> out;
    for (std::size_t s = 0; s < feature_scales(); ++s) out.push_back(&features_of(i, s));
    return out;
  }
  // A merged model's features (points with oriented normals) at every scale.
  std::vector<FeatureView> model_features(const PreparedView& model) const {
    std::vector<FeatureView> out(feature_scales());
    for (std::size_t s = 0; s < out.size(); ++s) out[s] = make_feature_view(model.points, model.normals, global_params(s));
    return out;
  }
  static std::vector<const FeatureView*> pointers(const std::vector<FeatureView>& f) {
    std::vector<const FeatureView*> out;
    for (const FeatureView& x : f) out.push_back(&x);
    return out;
  }

  // The registration copies of `members` moved by their current poses, as one
  // target view (points, normals, index).
  PreparedView model_of(const std::vector<int>& members) const {
    PreparedView mv;
    for (int j : members) {
      const Eigen::Matrix3f R = res_.poses[j].block<3, 3>(0, 0).cast<float>();
      const Vec3f t = res_.poses[j].block<3, 1>(0, 3).cast<float>();
      for (std::size_t k = 0; k < views_[j].points.size(); ++k) {
        mv.points.push_back(R * views_[j].points[k] + t);
        mv.normals.push_back(R * views_[j].normals[k]);
      }
    }
    mv.index = std::make_shared<PointIndex>(mv.points);
    mv.graph = neighbour_graph(*mv.index);
    return mv;
  }

  // Fraction of (up to ~1000 of) `src`'s registration points that `X` brings
  // within `dist` of the target.
  static double overlap(const PreparedView& src, const PreparedView& target, const Eigen::Matrix4d& X,
                        double dist) {
    const std::vector<Vec3f>& sp = src.points;
    if (sp.empty() || !target.index) return 0;
    const std::size_t stride = std::max<std::size_t>(1, sp.size() / 1000);
    const Eigen::Matrix4f Xf = X.cast<float>();
    std::size_t near = 0, total = 0;
    for (std::size_t q = 0; q < sp.size(); q += stride, ++total) {
      const Vec3f y = Xf.block<3, 3>(0, 0) * sp[q] + Xf.block<3, 1>(0, 3);
      if (target.index->nearest(y).second < float(dist)) ++near;
    }
    return double(near) / double(std::max<std::size_t>(total, 1));
  }

  // How close `X` brings (up to ~1000 of) `src`'s registration points to the
  // target: the mean of 1 - d / dist over them (0 beyond dist). Unlike overlap(),
  // which saturates at 1 over a wide range of poses near a good one, it peaks
  // where the points fit best.
  static double closeness(const PreparedView& src, const PreparedView& target, const Eigen::Matrix4d& X,
                          double dist) {
    const std::vector<Vec3f>& sp = src.points;
    if (sp.empty() || !target.index) return 0;
    const std::size_t stride = std::max<std::size_t>(1, sp.size() / 1000);
    const Eigen::Matrix4f Xf = X.cast<float>();
    double sum = 0;
    std::size_t total = 0;
    for (std::size_t q = 0; q < sp.size(); q += stride, ++total) {
      const Vec3f y = Xf.block<3, 3>(0, 0) * sp[q] + Xf.block<3, 1>(0, 3);
      const auto [j, d] = target.index->nearest_within(y, float(dist));
      if (j >= 0 && d < dist) sum += 1 - d / dist;
    }
    return sum / double(std::max<std::size_t>(total, 1));
  }

  // A chain's global fit taken at once (the view waits for a better one otherwise).
  static constexpr double kConfidentFitness = 0.3;

  struct GlobalAlign {
    bool ok = false;
    Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();  // target <- source
    double fitness = 0;
    std::string message;
    bool colour_disagrees = false;  // the pose's colours disagree with the target's (colour given)
    double colour = std::numeric_limits<double>::infinity();  // its colour_error (colour given)
    bool colour_refuted = false;  // a chain's pair (pair_align): colour >= kChainColourRefutes bounds
    bool by_colour = false;       // a chain's pair: found by features matched where colours agree
  };

  // Free space as the model's views saw it (registration/free_space.h): the
  // member views whose sensor is the scanner-frame origin (not estimated from
  // the normals). Null without any.
  std::unique_ptr<FreeSpace> free_space_of(const std::vector<int>& members) const {
    auto fs = std::make_unique<FreeSpace>();
    for (int j : members)
      if (views_[j].viewpoint_at_origin) fs->add(views_[j].points, res_.poses[j]);
    if (fs->empty()) return nullptr;
    return fs;
  }

  // The coloured points of the posed views, thinned, for telling apart poses that
  // fit the shape equally well (a near-symmetric object turned half way: the
  // mustard bottle's front and back) by the colours they bring together.
  struct ColourModel {
    std::vector<Rgb> colours;
    std::unique_ptr<PointIndex> index;
    /// How far a pose's colour difference to this model (colour_error) may go
    /// before the colours disagree: kColourDisagrees, or kColourDisagreesOverViews
    /// times the median difference between consecutive member views at their
    /// poses, whichever is larger.
    double disagrees = kColourDisagrees;
    double views_differ = 0;  ///< that median (0: fewer than two members compared)
  };
  // The members' coloured points placed by their poses, thinned to about
  // `max_points`; null when a member has no colours or nothing is left.
  // `own_frame`: the members' points as they are (a chain's pair target, own_colours).
  std::unique_ptr<ColourModel> placed_colours(const std::vector<int>& members, std::size_t max_points,
                                              bool own_frame = false) const {
    std::size_t total = 0;
    for (int j : members) {
      if (!views_[j].full.has_colours()) return nullptr;
      total += views_[j].full.size();
    }
    const std::size_t stride = std::max<std::size_t>(1, total / max_points);
    auto cm = std::make_unique<ColourModel>();
    std::vector<Vec3f> pts;
    for (int j : members) {
      const Eigen::Matrix4f X = own_frame ? Eigen::Matrix4f::Identity() : Eigen::Matrix4f(res_.poses[j].cast<float>());
      const Cloud& c = views_[j].full;
      for (std::size_t k = 0; k < c.size(); k += stride) {
        pts.push_back(X.block<3, 3>(0, 0) * c.points[k] + X.block<3, 1>(0, 3));
        cm->colours.push_back(c.colours[k]);
      }
    }
    if (pts.empty()) return nullptr;
    cm->index = std::make_unique<PointIndex>(std::move(pts));
    return cm;
  }
  std::unique_ptr<ColourModel> colour_model_of(const std::vector<int>& members) const {
    std::unique_ptr<ColourModel> cm = placed_colours(members, 300000);
    if (!cm) return nullptr;
    // How much right poses disagree here: each member against the next one
    // (capture order: neighbours on the table overlap most).
    std::vector<double> diffs(members.size() > 1 ? members.size() - 1 : 0, std::numeric_limits<double>::infinity());
    tbb::parallel_for(std::size_t(0), diffs.size(), [&](std::size_t k) {
      const std::unique_ptr<ColourModel> next = placed_colours({members[k + 1]}, 20000);
      if (next)
        diffs[k] = colour_error(views_[members[k]].full, *next, res_.poses[members[k]], icp_end_,
                                views_[members[k]].viewpoint);
    });
    diffs.erase(std::remove_if(diffs.begin(), diffs.end(), [](double d) { return !std::isfinite(d); }), diffs.end());
    if (!diffs.empty()) {
      cm->views_differ = median_of(diffs);
      cm->disagrees = std::max(kColourDisagrees, kColourDisagreesOverViews * cm->views_differ);
    }
    return cm;
  }
  // View j's coloured points in its own frame (a chain's pair target), made once;
  // null without colours.
  const ColourModel* own_colours(int j) {
    own_colours_.resize(views_.size());
    std::unique_ptr<ColourModel>& cm = own_colours_[std::size_t(j)];
    // (Thinned as a model is: a 640x480 range image holds 300,000 points.)
    if (!cm) cm = placed_colours({j}, kOwnColoursPoints, true);
    return cm.get();
  }
  // Mean colour difference (0-255, per channel) between the points of `c` moved
  // by X and the model's nearest within `dist`, after one gain on all channels that
  // fits the view's colours to the model's best (least squares, within
  // [1 / kColourMaxGain, kColourMaxGain]: a scanner's exposure changes from view
  // to view; a gain cannot turn one hue into another). With normals, the view's
  // shading too: a lamp on the scanner lights each point by its angle to it
  // (Lambert), a brightness affine in the point's normal n (turned towards the
  // sensor `eye`), which one gain per view cannot undo (docs/registration.md, "Under
  // a lamp"). So the model's colour b is fitted to the view's a as h(n) b with
  // h = h0 + h . n (least squares, the normal terms lightly damped towards one gain),
  // and the difference taken as |a / h(n) - b|, each h within the same bounds.
  // Points without a usable normal take the one gain. Infinity when no point is that
  // near.
  static double colour_error(const Cloud& c, const ColourModel& cm, const Eigen::Matrix4d& X, double dist,
                             const Vec3f& eye = Vec3f::Zero()) {
    if (!c.has_colours() || c.empty()) return std::numeric_limits<double>::infinity();
    const std::size_t stride = std::max<std::size_t>(1, c.size() / 3000);
    const Eigen::Matrix4f Xf = X.cast<float>();
    std::vector<std::pair<Vec3d, Vec3d>> pairs;
    std::vector<Eigen::Vector4d> basis;  // (1, n) at each pair; (0, 0, 0, 0): no normal
    const bool shading = c.has_normals();
    double ab = 0, aa = 0;
    for (std::size_t k = 0; k < c.size(); k += stride) {
      const auto [j, d] = cm.index->nearest(Xf.block<3, 3>(0, 0) * c.points[k] + Xf.block<3, 1>(0, 3));
      if (j < 0 || d > float(dist)) continue;
      const Rgb& a = c.colours[k];
      const Rgb& b = cm.colours[std::size_t(j)];
      pairs.push_back({Vec3d(a.r, a.g, a.b), Vec3d(b.r, b.g, b.b)});
      ab += pairs.back().first.dot(pairs.back().second);
      aa += pairs.back().first.squaredNorm();
      if (shading) {
        Vec3d n = c.normals[k].cast<double>();
        const double len = n.norm();
        if (!(len > 0) || !std::isfinite(len)) {
          basis.push_back(Eigen::Vector4d::Zero());
          continue;
        }
        n /= len;
        if (n.dot((eye - c.points[k]).cast<double>()) < 0) n = -n;
        basis.push_back(Eigen::Vector4d(1, n.x(), n.y(), n.z()));
      }
    }
    if (pairs.empty()) return std::numeric_limits<double>::infinity();
    const double gain = aa > 0 ? std::clamp(ab / aa, 1.0 / kColourMaxGain, kColourMaxGain) : 1.0;
    Eigen::Vector4d h = Eigen::Vector4d::Zero();
    bool fitted = false;
    if (shading) {
      // h(n) b ~ a over the pairs with a normal: sum |b|^2 phi phi^T h = sum (a . b) phi.
      Eigen::Matrix4d A = Eigen::Matrix4d::Zero();
      Eigen::Vector4d rhs = Eigen::Vector4d::Zero();
      double bb = 0;
      for (std::size_t k = 0; k < pairs.size(); ++k) {
        if (basis[k][0] == 0) continue;
        const double s = pairs[k].second.squaredNorm();
        A += s * basis[k] * basis[k].transpose();
        rhs += pairs[k].first.dot(pairs[k].second) * basis[k];
        bb += s;
      }
      // The normal terms damped (1e-3 of the total weight): nearly equal normals
      // leave one gain rather than fit the texture through their noise.
      for (int t = 1; t < 4; ++t) A(t, t) += 1e-3 * bb;
      if (bb > 0) h = A.ldlt().solve(rhs);
      fitted = bb > 0 && h.allFinite();
    }
    double sum = 0;
    for (std::size_t k = 0; k < pairs.size(); ++k) {
      const auto& [a, b] = pairs[k];
      if (fitted && basis[k][0] != 0) {
        const double hk = std::clamp(h.dot(basis[k]), 1.0 / kColourMaxGain, kColourMaxGain);
        sum += (a / hk - b).cwiseAbs().sum() / 3.0;
      } else {
        sum += (gain * a - b).cwiseAbs().sum() / 3.0;
      }
    }
    return sum / double(pairs.size());
  }

  // Feature registration of view `src` onto a target, each hypothesis refined
  // by ICP; the converged one with the best overlap wins. Against a model (the
  // overload taking every feature scale, and regroup(): `multi`) it starts from
  // more places, below; a view onto one other view (the prior-free chain) is
  // pair_align.
  // Against a model (every feature scale; see below).
  GlobalAlign global_align(int src, const PreparedView& target, const std::vector<FeatureView>& target_feats,
                           const ColourModel* colour, const std::optional<std::pair<Vec3d, Vec3d>>& axis,
                           const FreeSpace* free) {
    return global_align(views_[src], all_features_of(src), views_[src].full, target, pointers(target_feats),
                        colour, axis, true, true, free);
  }
  // The same for any source: a view, or a run of views merged (`coloured`: its
  // points with colours, for the colour check). `source_feats` and
  // `target_feats` hold the same scales (the first: p_.global's radius).
  //
  // `multi` (against a model: off-table views, suspect angles, a chain's
  // unplaced views, a second run) starts from more places (issue 26, item 3):
  // given more than one scale, RANSAC with 1 + global_extra_seeds seeds on the
  // first scale's features and once on each further scale's
  // (global_extra_radii), every run's hypotheses pooled and ranked by the
  // overlap they give; twice the ICP candidates; the best pose turned (below);
  // near ties decided by colour. `until_settled` (a view against the model, not
  // a merged run: a second pass whose runs do not overlap would be placed where
  // some turned start happens to fit) refines every turned start, and goes on
  // with ICP that ran out of iterations, while no pose both overlaps enough and
  // agrees in colour. `colour_swap` (a chain's pair: one view against another) makes
  // the same colour swap as `until_settled` without its further starts, and a pose
  // whose colours disagree with nothing better is still taken.
  GlobalAlign global_align(const PreparedView& source, const std::vector<const FeatureView*>& source_feats,
                           const Cloud& coloured, const PreparedView& target,
                           const std::vector<const FeatureView*>& target_feats, const ColourModel* colour,
                           const std::optional<std::pair<Vec3d, Vec3d>>& axis, bool multi = false,
                           bool until_settled = false, const FreeSpace* free = nullptr,
                           bool colour_swap = false) {
    GlobalAlign out;
    GlobalRegistrationParams gp = global_params();
    if (multi) gp.hypotheses = std::max(gp.hypotheses, 2 * p_.global_icp_candidates);
    // The runs: (scale, seed).
    std::vector<std::pair<std::size_t, std::uint64_t>> runs = {{0, gp.seed}};
    if (multi) {
      // Extra seeds only with the extra scales (a merged run against a model
      // gets neither: regroup()).
      const std::size_t scales = std::min(source_feats.size(), target_feats.size());
      if (scales > 1)
        for (int k = 1; k <= p_.global_extra_seeds; ++k) runs.push_back({0, gp.seed + std::uint64_t(k)});
      for (std::size_t s = 1; s < scales; ++s) runs.push_back({s, gp.seed});
    }
    std::vector<GlobalRegistrationResult> found(runs.size());
    tbb::parallel_for(std::size_t(0), runs.size(), [&](std::size_t k) {
      GlobalRegistrationParams q = global_params(runs[k].first);
      q.hypotheses = gp.hypotheses;
      q.seed = runs[k].second;
      found[k] = register_global(*source_feats[runs[k].first], *target_feats[runs[k].first], q);
    });
    GlobalRegistrationResult g;
    for (const GlobalRegistrationResult& f : found) {
      if (!f.success) continue;
      g.success = true;
      g.hypotheses.insert(g.hypotheses.end(), f.hypotheses.begin(), f.hypotheses.end());
    }
    if (!g.success) {
      std::string why = found.front().message;
      for (const GlobalRegistrationResult& f : found)
        if (why.empty()) why = f.message;
      out.message = "global registration failed: " + why;
      return out;
    }
    const IcpParams ip = refine_params();
    // Hypotheses ranked by the overlap they give the registration copies (the
    // fraction of source points within the ICP start distance of the target);
    // only the best `global_icp_candidates` are refined by ICP.
    const std::size_t nh = g.hypotheses.size();
    std::vector<std::pair<double, std::size_t>> rank(nh);
    tbb::parallel_for(std::size_t(0), nh, [&](std::size_t k) {
      rank[k] = {-overlap(source, target, g.hypotheses[k].transform, ip.max_distance_start), k};
    });
    std::sort(rank.begin(), rank.end());
    const int candidates = std::max(1, p_.global_icp_candidates) * (multi ? 2 : 1);
    rank.resize(std::min<std::size_t>(nh, std::size_t(candidates)));
    std::vector<IcpResult> r(rank.size());
    tbb::parallel_for(std::size_t(0), rank.size(), [&](std::size_t k) {
      r[k] = icp_point_to_plane(source, target, g.hypotheses[rank[k].second].transform, ip);
    });
    std::string why;
    // The best converged pose; else, for a single view (`until_settled`), the
    // best that did not converge yet (a partial view sliding on a flat part):
    // the turned starts go from it.
    int best = -1;
    bool best_converged = false;
    for (std::size_t k = 0; k < r.size(); ++k) {
      if (!r[k].converged && why.empty()) why = r[k].message;
      const bool better = best < 0 || (r[k].converged && !best_converged) ||
                          (r[k].converged == best_converged && r[k].fitness > r[best].fitness);
      if (better && (r[k].converged || (until_settled && r[k].fitness > 0))) {
        best = int(k);
        best_converged = r[k].converged;
      }
    }
    // The choice: the best overlap; among near ties (kTie), the best colour
    // agreement. Then, for a single view (`until_settled`), a pose whose colours
    // clearly disagree with the model's (a near-symmetric shape turned: its
    // overlap can exceed the right pose's, which sees a part no other view saw)
    // gives way to the most overlapping pose with at least kColourOverlapShare
    // of the best overlap whose colours agree at least 1 / kColourBetter times
    // better (docs/registration.md, "Hand-held views").
    double chosen_colour = std::numeric_limits<double>::infinity();
    // Each result's colour difference, once (choose runs again as results are
    // added; the best overlap only grows, so a result left out stays out).
    std::vector<std::optional<double>> colour_of;
    // Each converged result's share seen through by the model's views (`free`),
    // once; a result above kSeenThrough is never chosen.
    std::vector<std::optional<double>> seen_of;
    double refused_seen = -1, refused_fit = 0;  // the best-overlapping result refused so
    // The noise the margin allows for: the median ICP residual of the first
    // converged results (not each pose's own: a pose that fits worse would get a
    // wider margin).
    double noise_rms = -1;
    const auto in_free_space = [&](std::size_t k) {
      if (!free) return true;
      seen_of.resize(r.size());
      if (!seen_of[k]) {
        if (noise_rms < 0) {
          std::vector<double> rms;
          for (const IcpResult& x : r)
            if (x.converged) rms.push_back(x.plane_rmse);
          noise_rms = median_of(rms);
        }
        seen_of[k] = seen_share(*free, source.points, r[k].transform, noise_rms);
      }
      if (*seen_of[k] <= kSeenThrough) return true;
      if (r[k].fitness > refused_fit) refused_fit = r[k].fitness, refused_seen = *seen_of[k];
      return false;
    };
    const auto choose = [&] {
      out.fitness = 0;
      out.transform = Eigen::Matrix4d::Identity();
      double best_fit = 0;
      std::vector<char> usable(r.size(), 0);
      for (std::size_t k = 0; k < r.size(); ++k)
        if (r[k].converged && in_free_space(k)) {
          usable[k] = 1;
          best_fit = std::max(best_fit, r[k].fitness);
        }
      // A table view without an angle between views with angles, or one whose angle
      // looks wrong (expected_: check_angles): the
      // best pose half a turn or so from where its neighbours' angles put it, and a
      // pose near there that overlaps at least kExpectedShare of the best: the near
      // one. On a near-symmetric object the twin overlaps better, because the right
      // pose sees a side no posed view saw (the bottle's first four views without
      // angle, the others with: right poses 0.64-0.76, twins 0.95; they came out
      // 178-180 deg off without a warning). A view off the table (from above, in the
      // hand) is far from every table pose but not turned half way from it: left as is.
      if (expected_) {
        const auto turn_from_expected = [&](std::size_t k) {
          return rotation_angle_deg(Eigen::Matrix4d(rigid_inverse(expected_->first) * r[k].transform));
        };
        std::size_t best_k = r.size();
        for (std::size_t k = 0; k < r.size(); ++k)
          if (usable[k] && (best_k == r.size() || r[k].fitness > r[best_k].fitness)) best_k = k;
        std::vector<char> near(r.size(), 0);
        double near_fit = 0;
        for (std::size_t k = 0; k < r.size(); ++k)
          if (usable[k] && turn_from_expected(k) <= expected_->second) {
            near[k] = 1;
            near_fit = std::max(near_fit, r[k].fitness);
          }
        if (best_k < r.size() && turn_from_expected(best_k) > kTwinTurnDeg && near_fit >= p_.global_min_fitness &&
            near_fit >= kExpectedShare * best_fit) {
          best_fit = near_fit;
          for (std::size_t k = 0; k < r.size(); ++k) usable[k] = near[k];
        }
      }
      std::vector<double> err(r.size(), std::numeric_limits<double>::infinity());
      double best_score = std::numeric_limits<double>::infinity();
      for (std::size_t k = 0; k < r.size(); ++k) {
        const IcpResult& x = r[k];
        if (!usable[k]) continue;
        if (!colour) {
          if (x.fitness > out.fitness) {
            out.fitness = x.fitness;
            out.transform = x.transform;
          }
          continue;
        }
        if (x.fitness >= kColourOverlapShare * best_fit) {
          colour_of.resize(r.size());
          if (!colour_of[k]) colour_of[k] = colour_error(coloured, *colour, x.transform, ip.max_distance_end, source.viewpoint);
          err[k] = *colour_of[k];
        }
        if (x.fitness >= best_fit - kTie && (err[k] < best_score || (err[k] == best_score && x.fitness > out.fitness))) {
          best_score = err[k];
          out.fitness = x.fitness;
          out.transform = x.transform;
        }
      }
      chosen_colour = best_score;
      if (!((until_settled || colour_swap) && colour && std::isfinite(best_score) && best_score >= colour->disagrees))
        return;
      double swap_fit = -1;
      for (std::size_t k = 0; k < r.size(); ++k)
        if (usable[k] && err[k] <= kColourBetter * best_score && r[k].fitness >= p_.global_min_fitness &&
            r[k].fitness > swap_fit) {
          swap_fit = r[k].fitness;
          chosen_colour = err[k];
          out.fitness = r[k].fitness;
          out.transform = r[k].transform;
        }
    };
    if (best >= 0 && multi) {
      // More starts from the best pose: turned about the turntable axis in eighths,
      // and about the model's principal axes through the view's centre in quarters
      // (a view upside down, or from the far side, of a shape that looks alike).
      const Eigen::Matrix4d T = r[best].transform;
      std::vector<std::pair<Vec3d, Eigen::Matrix3d>> turns;  // about a point
      // Mean and principal axes (eigenvectors of the scatter) of points moved by X.
      const auto axes_of = [](const std::vector<Vec3f>& pts, const Eigen::Matrix4d& X) {
        std::vector<Vec3d> placed;
        placed.reserve(pts.size());
        for (const Vec3f& q : pts) placed.push_back((X * q.cast<double>().homogeneous()).head<3>());
        Vec3d mean = Vec3d::Zero();
        for (const Vec3d& q : placed) mean += q;
        mean /= double(std::max<std::size_t>(1, placed.size()));
        Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
        for (const Vec3d& q : placed) cov += (q - mean) * (q - mean).transpose();
        return std::make_pair(mean, Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(cov).eigenvectors());
      };
      const auto [model_mean, model_axes] = axes_of(target.points, Eigen::Matrix4d::Identity());
      // About lines through the model's centre (the object need not stand on the axis).
      if (axis)
        for (int k = 1; k < 8; ++k)
          turns.push_back({model_mean, Eigen::AngleAxisd(M_PI * k / 4, axis->second).toRotationMatrix()});
      for (int a = 0; a < 3; ++a)
        for (int k = 1; k < 4; ++k)
          turns.push_back({model_mean, Eigen::AngleAxisd(M_PI * k / 2, model_axes.col(a)).toRotationMatrix()});
      std::vector<std::pair<double, Eigen::Matrix4d>> starts(turns.size());
      tbb::parallel_for(std::size_t(0), turns.size(), [&](std::size_t k) {
        Eigen::Matrix4d S = Eigen::Matrix4d::Identity();
        S.block<3, 3>(0, 0) = turns[k].second;
        S.block<3, 1>(0, 3) = turns[k].first - turns[k].second * turns[k].first;
        starts[k] = {-overlap(source, target, S * T, ip.max_distance_start), S * T};
      });
      std::stable_sort(starts.begin(), starts.end(),
                       [](const auto& a, const auto& b) { return a.first < b.first; });
      if (until_settled) {
        // Turned about the view's own principal axes through its placed centre,
        // in quarters (a partial view of a near-symmetric band fits it upside
        // down or mirrored in place, where turns about the model's centre would
        // carry it elsewhere). Refined only with the rest, when the first
        // starts leave the view not settled.
        const auto [vm, view_axes] = axes_of(source.points, T);
        for (int a = 0; a < 3; ++a)
          for (int k = 1; k < 4; ++k) {
            Eigen::Matrix4d S = Eigen::Matrix4d::Identity();
            S.block<3, 3>(0, 0) = Eigen::AngleAxisd(M_PI * k / 2, view_axes.col(a)).toRotationMatrix();
            S.block<3, 1>(0, 3) = vm - S.block<3, 3>(0, 0) * vm;
            starts.push_back({0.0, S * T});
          }
      }
      // ICP is the cost: the starts with the best overlap are refined, and the
      // others only when no pose is left that both overlaps enough and agrees
      // in colour. The start's overlap ranks poorly: the right pose of the
      // hand-held view from nearly straight below started 10th of 16.
      const auto refine = [&](std::size_t from, std::size_t to) {
        std::vector<IcpResult> spun(to - from);
        tbb::parallel_for(from, to, [&](std::size_t k) {
          spun[k - from] = icp_point_to_plane(source, target, starts[k].second, ip);
        });
        for (IcpResult& x : spun) r.push_back(std::move(x));
        choose();
      };
      // A table view between views with angles (expected_): ICP also starts where its
      // neighbours' angles put it (the fandisk's fourth view without angle: every
      // start converged on the half-turned twin, none near the right pose).
      // (Not for a view whose angle is suspect: its pairs did not converge near its
      // angle's pose, and ICP from there slid the dragon's view 12 degrees off to 18.)
      const bool start_expected = expected_ && !expected_suspect_;
      if (start_expected) starts.insert(starts.begin(), {0.0, expected_->first});
      const std::size_t first = std::min(starts.size(), kSpunRefined + (start_expected ? 1 : 0));
      refine(0, first);
      const auto settled = [&] {
        // A pose whose colours could not be compared (a view without colours, no
        // sample near the model) counts as agreeing.
        return !until_settled || (out.fitness >= p_.global_min_fitness &&
                                  !(colour && std::isfinite(chosen_colour) && chosen_colour >= colour->disagrees));
      };
      if (!settled()) refine(first, starts.size());
      if (!settled()) {
        // ICP that ran out of iterations while still sliding (a view that
        // overlaps the model along a narrow band, a flat part the model lacks):
        // continued at the final distance, the best of them by overlap.
        std::vector<std::size_t> sliding;
        for (std::size_t k = 0; k < r.size(); ++k)
          if (!r[k].converged && r[k].fitness >= p_.global_min_fitness) sliding.push_back(k);
        std::stable_sort(sliding.begin(), sliding.end(),
                         [&](std::size_t a, std::size_t b) { return r[a].fitness > r[b].fitness; });
        sliding.resize(std::min(sliding.size(), std::size_t(2 * kSpunRefined)));
        IcpParams more = ip;
        more.max_distance_start = ip.max_distance_end;
        more.max_iterations = 2 * ip.max_iterations;
        std::vector<IcpResult> cont(sliding.size());
        tbb::parallel_for(std::size_t(0), sliding.size(), [&](std::size_t k) {
          cont[k] = icp_point_to_plane(source, target, r[sliding[k]].transform, more);
        });
        for (IcpResult& x : cont) r.push_back(std::move(x));
        choose();
      }
      if (!settled() && colour && coloured.has_colours()) {
        slide(source, target, coloured, *colour, ip, r);
        choose();
      }
    } else {
      choose();
    }
    out.colour = chosen_colour;
    out.colour_disagrees = colour && std::isfinite(chosen_colour) && chosen_colour >= colour->disagrees;
    if (out.fitness >= p_.global_min_fitness && until_settled && out.colour_disagrees) {
      // Every start tried and the best pose's colours still disagree: a shape
      // that fits turned or slid (a near-symmetric part), not the view's place.
      // A view fails by name rather than land wrong.
      std::ostringstream w;
      w.precision(3);
      w << "global registration found no pose whose colours agree with the model's (the best, overlap "
        << out.fitness << ", differs by " << chosen_colour << " per channel";
      if (colour->views_differ > 0) w << "; the model's views differ by " << colour->views_differ << " among themselves";
      w << ")";
      out.message = w.str();
    } else if (out.fitness >= p_.global_min_fitness) {
      out.ok = true;
    } else if (refused_seen >= 0 && refused_fit >= p_.global_min_fitness) {
      std::ostringstream w;
      w.precision(3);
      w << "global registration found no pose that the model's views do not see through (the best, overlap "
        << refused_fit << ", puts " << 100 * refused_seen << " % of the view where they saw through)";
      out.message = w.str();
    } else {
      out.message = "global registration found no pose with enough overlap (best ICP fitness " +
                    std::to_string(out.fitness) + (why.empty() ? "" : ", " + why) + ")";
    }
    return out;
  }

  // A converged pose may be right but for a slide along a direction the shape
  // leaves almost free (a band of a prism-like part seen from below: ICP stops
  // where the band still half overlaps): each distinct converged pose of `r` is
  // moved along its weakest translation (the smallest eigenvector of its ICP
  // system's translation block) in steps of kSlideStep ICP start distances, out to
  // kSlideReach of the session size either way; the places that overlap at
  // least half as well as the pose itself are ranked by colour agreement, and
  // ICP goes on from the kSlideRefined best of each. The results join `r`.
  void slide(const PreparedView& source, const PreparedView& target, const Cloud& coloured, const ColourModel& colour,
             const IcpParams& ip, std::vector<IcpResult>& r) const {
    Vec3d c = Vec3d::Zero();
    for (const Vec3f& q : source.points) c += q.cast<double>();
    c /= double(std::max<std::size_t>(1, source.points.size()));
    std::vector<Eigen::Matrix4d> poses;
    std::vector<Vec3d> dirs;
    for (const IcpResult& x : r) {
      if (!x.converged || x.fitness < p_.global_min_fitness) continue;
      const Vec3d at = (x.transform * c.homogeneous()).head<3>();
      bool seen = false;
      for (const Eigen::Matrix4d& P : poses)
        seen = seen || (rotation_angle_deg(rigid_inverse(P) * x.transform) < 2 &&
                        ((P * c.homogeneous()).head<3>() - at).norm() < ip.max_distance_end);
      if (seen) continue;
      // The slide is a translation: its information is the system's translation
      // block (sum of n n^T over the correspondences, whatever the rotation's centre).
      const Eigen::Matrix3d Htt = x.hessian.block<3, 3>(3, 3);
      const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(Htt);
      if (es.info() != Eigen::Success || !es.eigenvectors().col(0).allFinite()) continue;
      poses.push_back(x.transform);
      dirs.push_back(es.eigenvectors().col(0));
    }
    const double step = kSlideStep * ip.max_distance_start;
    const int steps = std::max(1, int(kSlideReach * diag_ / step));
    std::vector<Eigen::Matrix4d> starts;
    for (std::size_t k = 0; k < poses.size(); ++k) {
      const double base = overlap(source, target, poses[k], ip.max_distance_start);
      std::vector<std::pair<double, Eigen::Matrix4d>> places(std::size_t(2 * steps));
      tbb::parallel_for(0, 2 * steps, [&](int s) {
        const int o = s < steps ? s - steps : s - steps + 1;  // -steps..-1, 1..steps
        Eigen::Matrix4d X = poses[k];
        X.block<3, 1>(0, 3) += dirs[k] * (o * step);
        const double ov = overlap(source, target, X, ip.max_distance_start);
        const double col = ov >= 0.5 * base ? colour_error(coloured, colour, X, ip.max_distance_start, source.viewpoint)
                                            : std::numeric_limits<double>::infinity();
        places[std::size_t(s)] = {col, X};
      });
      std::stable_sort(places.begin(), places.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
      for (std::size_t j = 0; j < std::min(kSlideRefined, places.size()); ++j)
        if (std::isfinite(places[j].first)) starts.push_back(places[j].second);
    }
    std::vector<IcpResult> slid(starts.size());
    tbb::parallel_for(std::size_t(0), starts.size(), [&](std::size_t k) {
      slid[k] = icp_point_to_plane(source, target, starts[k], ip);
    });
    for (IcpResult& x : slid) r.push_back(std::move(x));
  }

  // Views `group`, merged at their current poses, registered globally onto the
  // model of `base` (one feature scale and seed: a merged run has features enough;
  // with the extra ones, the turned-over blocks' second run (the test
  // ASecondPassTurnedOverIsRegisteredAsTwoTurntableRuns) was placed where the
  // refinement then took five of its views 93.6 deg off). The motion that moves the
  // group (object frame) when it overlaps `base` by at least 0.05 more than where
  // it is; `now` and `then` are those overlaps.
  // The overlap `group`, placed by G onto `base`, gives turned by half a turn about the
  // table's axis through the base's centre (the object's, where its views see it round;
  // the group sees one side of it) and refined by ICP; -1 where that does not converge
  // nearly half a turn away, or where the colours clearly favour G's place. A
  // near-symmetric object (a bottle's front and back) fits both; its right place can
  // overlap less than the turned one, which sees only what the other views saw.
  // About 1,000 coloured points of each of `group`'s views (views without colours left
  // out), placed by X times the view's pose: a group's colours against a model's.
  Cloud coloured_sample(const std::vector<int>& group, const Eigen::Matrix4d& X = Eigen::Matrix4d::Identity()) const {
    Cloud out;
    for (int j : group) {
      const Eigen::Matrix4f P = (X * res_.poses[std::size_t(j)]).cast<float>();
      const Cloud& v = views_[std::size_t(j)].full;
      if (!v.has_colours()) continue;
      const std::size_t stride = std::max<std::size_t>(1, v.size() / 1000);
      for (std::size_t k = 0; k < v.size(); k += stride) {
        out.points.push_back(P.block<3, 3>(0, 0) * v.points[k] + P.block<3, 1>(0, 3));
        out.colours.push_back(v.colours[k]);
      }
    }
    return out;
  }

  // The twin check after `group` was registered onto `base` as a whole (G; `then`: its
  // overlap there): where its place turned by half a turn on the table fits about as
  // well (kTwinOverlapShare) and the colours clearly favour the turned one, G and then
  // become the turned place's (a near-symmetric object with a printed label: +1;
  // with `colours_choose` false, -1 as below).
  // Where it fits and the colours do not decide: -1 (said, not decided: with the
  // move's size unknown, nothing in the scans tells the two apart). 0 otherwise.
  // `twin`: the turned place's overlap (-1: none).
  int settle_twin(const std::vector<int>& base, const std::vector<int>& group, Eigen::Matrix4d& G, double& then,
                  const std::optional<std::pair<Vec3d, Vec3d>>& axis, double& twin, bool colours_choose = true) {
    if (!axis) return 0;
    const Twin t = twin_overlap(base, group, G, *axis);
    twin = t.overlap;
    if (!(t.overlap >= std::max(kTwinOverlapShare * then, kTwinMinOverlap)) || !(then >= kTwinMinOverlap)) return 0;
    if (t.colours > 0) return 0;
    if (t.colours == 0 || !colours_choose) return -1;
    G = t.transform;
    then = t.overlap;
    return 1;
  }
  static constexpr const char* kTwinChosen =
      "; the shapes fit it turned by half a turn too, and the colours chose between the two";  // kColoursChose
  std::string twin_words(const std::vector<int>& group, double twin, double then) const {
    std::ostringstream w;
    w.precision(3);
    w << group_name(group) << " also fit the others " << kHalfTurn << " on the table (overlap " << twin
      << " against " << then << ", and the colours do not favour this place): the object looks alike from both "
      << "sides, so their place may be the turned one; check the merged cloud, or scan with colours or a "
      << "marker on the object";
    return w.str();
  }

  struct Twin {
    double overlap = -1;  // -1: no twin (ICP did not converge nearly half a turn away)
    Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();  // the turned place (object frame)
    int colours = 0;  // +1: they clearly favour G's place, -1: the turned one, 0: neither (or none)
  };
  // (`base_model`, `base_colours`: the base's models where the caller has built them.)
  Twin twin_overlap(const std::vector<int>& base, const std::vector<int>& group, const Eigen::Matrix4d& G,
                    const std::pair<Vec3d, Vec3d>& axis, double better = kColourBetter,
                    const PreparedView* base_model = nullptr, const ColourModel* base_colours = nullptr) {
    Twin t;
    const PreparedView built = base_model ? PreparedView() : model_of(base);
    const PreparedView& first = base_model ? *base_model : built;
    const PreparedView second = model_of(group);
    const IcpResult x =
        icp_point_to_plane(second, first, turn_about_line(centroid(first.points), axis.second, M_PI) * G, refine_params());
    if (!x.converged || rotation_angle_deg(Eigen::Matrix4d(rigid_inverse(G) * x.transform)) < 90) return t;
    t.transform = x.transform;
    const std::unique_ptr<ColourModel> own = base_colours ? nullptr : colour_model_of(base);
    if (const ColourModel* colours = base_colours ? base_colours : own.get()) {
      const Cloud coloured = coloured_sample(group, G);
      const Eigen::Matrix4d turned = x.transform * rigid_inverse(G);  // from G's place
      const double here = colour_error(coloured, *colours, Eigen::Matrix4d::Identity(), icp_end_);
      const double there = colour_error(coloured, *colours, turned, icp_end_);
      if (std::isfinite(here) && std::isfinite(there)) t.colours = here <= better * there ? 1 : there <= better * here ? -1 : 0;
    }
    t.overlap = overlap(second, first, x.transform, 2 * icp_end_);
    return t;
  }

  // Views no angle placed (none given, or found wrong) that fit the views the angles
  // placed (`base`) turned by half a turn about the table's axis about as well as where
  // they are (kTwinOverlapShare): where the colours clearly favour the turned place
  // (kColourTwinView), moved there, the session refined again, and kept when they stay
  // joined to the others by converged pairs. Global registration against the model
  // takes the better overlap, and a near-symmetric object's turned twin can overlap
  // better than its right place (the knocked bottle's first view after the knock, its
  // angle found wrong, 179 deg off, and the view without angle after it). Where the
  // colours do not decide and nothing else holds the view where it is (its angle, or
  // for a view without angle the turn its neighbours expect, within kSuspectNearDeg /
  // expected_pose's tolerance), a warning names it. True when some moved.
  bool settle_view_twins() {
    std::vector<int> base, check;
    for (std::size_t i = 0; i < m_.views.size(); ++i) {
      if (!usable_[i]) continue;
      const int v = int(i);
      if (placed_by_angle(v)) base.push_back(v);
      else if (res_.views[i].initial != InitialPoseSource::kInitialPose) check.push_back(v);  // (a pose given stays)
    }
    if (base.size() < 2 || check.empty()) return false;
    const std::optional<std::pair<Vec3d, Vec3d>> axis = object_axis(base);
    if (!axis) return false;
    const PreparedView first = model_of(base);
    const std::unique_ptr<ColourModel> base_colours = colour_model_of(base);
    State before = state();
    std::vector<int> moved;
    std::vector<std::string> words, doubts;
    for (int v : check) {
      const double now = overlap(model_of({v}), first, Eigen::Matrix4d::Identity(), 2 * icp_end_);
      // (Its angle, or its neighbours' expected turn, holds it: left, whatever the colours.)
      if (!(now >= kTwinMinOverlap) || held_where_it_is(v)) continue;
      const Twin t = twin_overlap(base, {v}, Eigen::Matrix4d::Identity(), *axis, kColourTwinView, &first,
                                  base_colours.get());
      if (!(t.overlap >= std::max(kTwinOverlapShare * now, kTwinMinOverlap)) || t.colours > 0) continue;
      std::ostringstream w;
      w.precision(3);
      if (t.colours == 0) {
        w << view_name(m_, std::size_t(v)) << " also fits the views the angles placed " << kHalfTurn << " on the "
          << "table (overlap " << t.overlap << " against " << now << "), and neither its angle nor its colours "
          << "tell the two apart: its place may be the turned one; check the merged cloud";
        doubts.push_back(w.str());
        continue;
      }
      res_.poses[std::size_t(v)] = t.transform * res_.poses[std::size_t(v)];
      moved.push_back(v);
      w << view_name(m_, std::size_t(v)) << " fit the views the angles placed " << kHalfTurn << " too (overlap "
        << t.overlap << " against " << now << "), and " << kColoursFavour << ": moved there ("
        << rotation_angle_deg(t.transform) << " deg)";
      if (has_angle(v) && std::find(off_table_.begin(), off_table_.end(), v) == off_table_.end())
        w << "; it is now " << rotation_angle_deg(Eigen::Matrix4d(rigid_inverse(turntable_pose(*res_.axis, angle_of(v))) *
                                                                res_.poses[std::size_t(v)]))
          << " deg from its commanded angle (a word above about its angle is from before the move)";
      words.push_back(w.str());
    }
    if (moved.empty()) {
      res_.warnings.insert(res_.warnings.end(), doubts.begin(), doubts.end());
      return false;
    }
    const std::array<std::size_t, 3> score = chain_score();
    refine_again();
    const bool joined = in_main_group(moved, true);
    // Kept when the moved views are joined and the session holds as well (on a
    // near-symmetric object pairs converge on a twin too, so joined alone proves little).
    const std::array<std::size_t, 3> now_score = chain_score();
    if (!joined || now_score[0] < score[0] || now_score[1] < score[1] || (rigid_rejected_ && !before.rigid_rejected)) {
      restore(std::move(before));
      for (int v : moved) {
        std::ostringstream w;
        w << view_name(m_, std::size_t(v)) << " also fits the views the angles placed " << kHalfTurn << " on the "
          << "table, where its colours fit better, but the session did not hold together with it there: its place "
          << "may be the turned one; check the merged cloud";
        doubts.push_back(w.str());
      }
      res_.warnings.insert(res_.warnings.end(), doubts.begin(), doubts.end());
      return false;
    }
    res_.warnings.insert(res_.warnings.end(), words.begin(), words.end());
    res_.warnings.insert(res_.warnings.end(), doubts.begin(), doubts.end());
    return true;
  }
  // Without any angle (the run without angles, or a session of clouds only), where the
  // refinement found the object moved on the table (split_: two runs, each on the one
  // axis): the run after the move, where it is, against its half-turned twin about the
  // table's axis (the axis the first run's poses turn about), as `settle_twin` does for
  // a group (issue 26: every knocked coloured cube kept this run on the twin, unnamed).
  // Where the colours choose the turned place, the run goes there and the session is
  // refined again, kept where it holds as well; where they do not decide, named.
  bool settle_runs_twin() {
    // (Two runs that each fit the one axis: the refinement held them so.)
    if (!split_.found || split_.run_starts.size() != 1 || res_.turntable_groups < 2) return false;
    for (std::size_t i = 0; i < m_.views.size(); ++i)
      if (has_angle(int(i))) return false;
    std::vector<int> before, after;
    bool moved = false;
    for (int i : ring()) {
      if (!usable_[std::size_t(i)] || std::find(off_table_.begin(), off_table_.end(), i) != off_table_.end()) continue;
      moved = moved || i == split_.first_after;
      (moved ? after : before).push_back(i);
    }
    if (before.size() < 3 || after.size() < 2) return false;
    if (std::any_of(after.begin(), after.end(), [&](int j) {
          return res_.views[std::size_t(j)].initial == InitialPoseSource::kInitialPose;  // (a pose given stays)
        }))
      return false;
    std::vector<Eigen::Matrix4d> poses;
    for (int i : before) poses.push_back(res_.poses[std::size_t(i)]);
    const AxisFitResult fit = calibrate_axis(poses, angles_about_common_axis(poses));
    if (!fit.ok) return false;
    const Eigen::Matrix4d& X = res_.poses[std::size_t(before.front())];
    const std::optional<std::pair<Vec3d, Vec3d>> axis = std::make_pair(
        Vec3d((X * fit.axis.point.homogeneous()).head<3>()), Vec3d((X.block<3, 3>(0, 0) * fit.axis.direction).normalized()));
    const double now = overlap(model_of(after), model_of(before), Eigen::Matrix4d::Identity(), 2 * icp_end_);
    double then = now, twin = -1;
    Eigen::Matrix4d G = Eigen::Matrix4d::Identity();
    const int settled = settle_twin(before, after, G, then, axis, twin);
    if (settled < 0) res_.warnings.push_back(twin_words(after, twin, then));
    if (settled <= 0) return false;
    State was = state();
    const std::array<std::size_t, 3> score = chain_score();
    for (int j : after) res_.poses[std::size_t(j)] = G * res_.poses[std::size_t(j)];
    refine_again();
    // Kept where the two runs still each fit the axis, the run moved is joined to the
    // others by converged pairs, and no fewer views are joined or registered.
    const std::array<std::size_t, 3> now_score = chain_score();
    const bool joined = in_main_group(after, false);
    if (!joined || res_.turntable_groups < 2 || now_score[0] < score[0] || now_score[1] < score[1]) {
      restore(std::move(was));
      std::ostringstream w;
      w.precision(3);
      w << group_name(after) << " (after the object moved on the table) also fit the others " << kHalfTurn
        << " on the table, where their colours fit better, but the session did not hold together with them "
        << "there: their place may be the turned one; check the merged cloud";
      res_.warnings.push_back(w.str());
      return false;
    }
    std::ostringstream w;
    w.precision(3);
    w << group_name(after) << " (after the object moved on the table) were " << kHalfTurn
      << " about the table's axis (" << rotation_angle_deg(G) << " deg): the shapes fit both places, and "
      << kColoursChose;
    res_.warnings.push_back(w.str());
    return true;
  }

  // Placed by its commanded angle: it has one, not found wrong, on the table.
  bool placed_by_angle(int i) const {
    return has_angle(i) && !res_.views[std::size_t(i)].angle_rejected &&
           std::find(off_table_.begin(), off_table_.end(), i) == off_table_.end();
  }
  // The session refined again from the poses as they are, the last refinement's words
  // giving way to the new one's.
  void refine_again() {
    const std::size_t from = std::min(refine_words_.first, res_.warnings.size());
    const std::size_t to = std::max(from, std::min(refine_words_.second, res_.warnings.size()));
    res_.warnings.erase(res_.warnings.begin() + std::ptrdiff_t(from), res_.warnings.begin() + std::ptrdiff_t(to));
    res_.pairs.clear();
    refine();
  }
  // Whether `views` (every one, or any one) are in the largest group converged pairs join.
  bool in_main_group(const std::vector<int>& views, bool every) const {
    std::size_t main_group = 0;
    const std::vector<std::vector<int>> groups = linked_groups(&main_group);
    if (groups.empty()) return false;
    const auto in = [&](int v) {
      return std::find(groups[main_group].begin(), groups[main_group].end(), v) != groups[main_group].end();
    };
    return every ? std::all_of(views.begin(), views.end(), in) : std::any_of(views.begin(), views.end(), in);
  }
  // Whether something besides its overlap holds view v where it is: its commanded angle
  // (shifted with its run) within kSuspectNearDeg, or, without angle, the pose its
  // neighbours in capture order expect, within that pose's tolerance.
  bool held_where_it_is(int v) const {
    if (!res_.axis) return false;
    const Eigen::Matrix4d& X = res_.poses[std::size_t(v)];
    if (has_angle(v))
      return rotation_angle_deg(Eigen::Matrix4d(rigid_inverse(turntable_pose(*res_.axis, angle_of(v))) * X)) <
             kSuspectNearDeg;
    const auto e = expected_pose(v);
    return e && rotation_angle_deg(Eigen::Matrix4d(rigid_inverse(e->first) * X)) < e->second;
  }

  std::optional<Eigen::Matrix4d> place_group(const std::vector<int>& base, const std::vector<int>& group,
                                             double& now, double& then,
                                             double max_now = std::numeric_limits<double>::infinity(),
                                             bool free_space = false) {
    const PreparedView first = model_of(base), second = model_of(group);
    const double d = 2 * icp_end_;
    now = overlap(second, first, Eigen::Matrix4d::Identity(), d);
    then = now;
    if (now > max_now) return std::nullopt;  // (before the costly global registration)
    const std::vector<FeatureView> first_feat = {make_feature_view(first.points, first.normals, global_params())};
    const std::vector<FeatureView> second_feat = {make_feature_view(second.points, second.normals, global_params())};
    const std::unique_ptr<ColourModel> colours = colour_model_of(base);
    const Cloud coloured = colours ? coloured_sample(group) : Cloud();
    // (`free_space`: no pose the base's views see through, as for a single view.)
    const std::unique_ptr<FreeSpace> free = free_space ? free_space_of(base) : nullptr;
    const GlobalAlign g = global_align(second, pointers(second_feat), coloured, first, pointers(first_feat),
                                       colours.get(), object_axis(base), true, false, free.get());
    if (!g.ok) return std::nullopt;
    then = overlap(second, first, g.transform, d);
    if (then < now + 0.05) return std::nullopt;
    return g.transform;
  }

  // The run of table views after the move, merged, registered globally onto the
  // run before it (issue 26, item 2); its poses moved when that overlaps the
  // first run clearly better than where they are. True when they moved.
  bool regroup() {
    std::vector<int> before, after;
    bool moved = false;
    for (int i : ring()) {
      if (!usable_[i] || !has_angle(i) || res_.views[i].angle_rejected ||
          std::find(off_table_.begin(), off_table_.end(), i) != off_table_.end())
        continue;
      moved = moved || i == split_.first_after;
      (moved ? after : before).push_back(i);
    }
    if (before.size() < 2 || after.size() < 2) return false;
    double now = 0, then = 0;
    std::optional<Eigen::Matrix4d> G = place_group(before, after, now, then);
    // Where the run stays (its angles, corrected by their shared error, placed it where
    // it overlaps the first run best), it may still be the half-turned twin of a
    // near-symmetric object: the same check there.
    const bool stays = !G;
    if (stays) {
      G = Eigen::Matrix4d::Identity();
      then = now;
    }
    double twin = -1;
    const int settled = settle_twin(before, after, *G, then, object_axis(before), twin);
    if (stays && settled <= 0) {
      if (settled < 0) res_.warnings.push_back(twin_words(after, twin, then));
      return false;
    }
    for (int j : after) res_.poses[j] = *G * res_.poses[j];
    shift_angles(after, *G, before.back(), object_axis(before));
    res_.regrouped_from = split_.first_after;
    std::ostringstream w;
    w.precision(3);
    w << "the views from " << view_name(m_, std::size_t(split_.first_after))
      << " on were registered to the ones before as a whole (the object moved " << rotation_angle_deg(*G)
      << " deg on the table; overlap " << now << " -> " << then << ")";
    if (settled > 0) w << kTwinChosen;
    res_.warnings.push_back(w.str());
    if (settled < 0) res_.warnings.push_back(twin_words(after, twin, then));
    return true;
  }

  // What refine() and global_poses() change, to be put back when a try is not kept.
  struct State {
    RegistrationResult res;
    std::vector<bool> usable;
    TurntableSplit split;
    bool rigid_rejected = false, rigid_used = false;
    std::vector<int> off_table, unplaced;
    std::vector<double> angle_shift;
    std::vector<int> ring_order, chain_missed, table_free;
    std::pair<std::size_t, std::size_t> refine_words;
  };
  State state() const {
    return {res_,         usable_,      split_,         rigid_rejected_, rigid_used_, off_table_,
            unplaced_,    angle_shift_, ring_order_,    chain_missed_,   table_free_, refine_words_};
  }
  void restore(State&& s) {
    res_ = std::move(s.res);
    usable_ = std::move(s.usable);
    split_ = s.split;
    rigid_rejected_ = s.rigid_rejected;
    rigid_used_ = s.rigid_used;
    off_table_ = std::move(s.off_table);
    unplaced_ = std::move(s.unplaced);
    angle_shift_ = std::move(s.angle_shift);
    ring_order_ = std::move(s.ring_order);
    chain_missed_ = std::move(s.chain_missed);
    table_free_ = std::move(s.table_free);
    refine_words_ = s.refine_words;
  }
  // Views the converged pairs join into the largest group, views registered, and
  // the last round's converged pairs: a result is better than another when these
  // are larger, in this order (views placed where they belong overlap more of their
  // neighbours, and more of those pairs converge).
  std::array<std::size_t, 3> chain_score() const {
    std::size_t largest = 0;
    const std::vector<std::vector<int>> groups = linked_groups(&largest);
    const std::size_t joined = groups.empty() ? 0 : groups[largest].size();
    std::size_t converged = 0;
    if (!res_.pairs.empty())
      for (const PairDiagnostics& pd : res_.pairs)
        converged += pd.round == res_.pairs.back().round && pd.converged && usable_[std::size_t(pd.from)] &&
                     usable_[std::size_t(pd.to)];
    return {joined, std::size_t(std::count(usable_.begin(), usable_.end(), true)), converged};
  }

  // The last round's converged pairs whose views' colours, under the poses kept, differ
  // by kChainColourRefutes times the colour bound or more (as a chain's pair is refuted:
  // own_colours). 0 without colours, or with the colour gate off (colour_gate 0).
  std::size_t colour_refuted_pairs() {
    const auto all = pair_colours();
    return std::size_t(std::count_if(all.begin(), all.end(), [](const PairColour& c) { return c.refuted; }));
  }
  // The last round's converged pairs with colours: (from, to), their colour difference
  // under the poses kept (own_colours: the target in its own frame), and whether a
  // chain would refute it. None with the colour gate off.
  struct PairColour {
    int from = 0, to = 0;
    double difference = 0;
    bool refuted = false;
  };
  std::vector<PairColour> pair_colours() {
    std::vector<PairColour> out;
    if (res_.pairs.empty() || !(p_.global.colour_gate > 0)) return out;
    const int round = res_.pairs.back().round;
    for (const PairDiagnostics& pd : res_.pairs) {
      if (pd.round != round || !pd.converged || !usable_[std::size_t(pd.from)] || !usable_[std::size_t(pd.to)]) continue;
      const ColourModel* colours = own_colours(pd.to);
      if (!colours) continue;
      const double e = colour_error(views_[pd.from].full, *colours, rigid_inverse(res_.poses[pd.to]) * res_.poses[pd.from],
                                    icp_end_, views_[pd.from].viewpoint);
      if (std::isfinite(e)) out.push_back({pd.from, pd.to, e, e >= kChainColourRefutes * colours->disagrees});
    }
    return out;
  }
  // Pairs that overlap where their colours differ by kChainColourRefutes times the colour
  // bound and kPairColourOverMedian times the session's median pair (a lamp that lights
  // each view differently raises every pair: right hand-held views under a harsh lamp
  // read up to 30.6, their median 14): named, a near-symmetric object's view may be on
  // a turned twin of its place that no check moved (the coloured cube knocked -30 and
  // 45 deg, 179.9 / 179.6 deg off, silent before: 42.7-49.9 against a median of 5.6).
  void name_pairs_whose_colours_differ() {
    const std::vector<PairColour> all = pair_colours();
    if (all.empty()) return;
    std::vector<double> d;
    for (const PairColour& c : all) d.push_back(c.difference);
    const double bound = std::max(kChainColourRefutes * kColourDisagrees, kPairColourOverMedian * median_of(d));
    std::ostringstream w;
    w.precision(3);
    int named = 0;
    for (const PairColour& c : all)
      if (c.difference >= bound)
        w << (named++ ? "; " : "") << view_name(m_, std::size_t(c.from)) << " and " << view_name(m_, std::size_t(c.to))
          << " (" << c.difference << ")";
    if (named == 0) return;
    std::ostringstream b;
    b.precision(3);
    b << bound;
    res_.warnings.push_back(std::string(kColoursDiffer) + " (mean per channel, 0-255, over " + b.str() + "): " + w.str() +
                            ": one of each pair may be on a turned twin of its place (a near-symmetric object); "
                            "check the merged cloud");
  }
  // When the views were chained (nothing posed) and the chain took a weak fit, or left
  // some views failed or not joined to the others by converged pairs: the second chain
  // (confident fits first, global_poses) from the same start, refined; kept when its
  // chain_score is higher. (The dragon's scans out of turntable order: the first chain
  // joined all 15 views with four of them 103 deg off, by 0.175 and 0.236 fits; the
  // second placed all within 0.36 deg.) `start`: the state before initial_poses;
  // `warned`: where the refinement's warnings start.
  void retry_chain(const State& start, std::size_t& warned) {
    if (!chained_ || confident_chain_) return;
    const std::array<std::size_t, 3> first_score = chain_score();
    const std::size_t usable_at_start = std::size_t(std::count(start.usable.begin(), start.usable.end(), true));
    if (!weak_fit_ && first_score[0] == first_score[1] && first_score[1] == usable_at_start) return;
    State first = state();
    const std::size_t first_warned = warned;
    const std::size_t first_refuted = colour_refuted_pairs();
    restore(State(start));
    confident_chain_ = true;
    initial_poses();
    warned = res_.warnings.size();
    refine();
    // Converged pairs whose colours refute them count against a chain (a cube's
    // quarter-turned twins fit the shapes as well as the right poses do).
    const auto colour_checked = [](std::array<std::size_t, 3> score, std::size_t refuted) {
      score[2] -= std::min(score[2], refuted);
      return score;
    };
    const std::array<std::size_t, 3> second_score = chain_score();
    const std::size_t second_refuted = colour_refuted_pairs();
    const bool second_kept = colour_checked(second_score, second_refuted) > colour_checked(first_score, first_refuted);
    // Where the colours changed which is kept, a note.
    const auto chose = [&](std::size_t kept, std::size_t other) {
      return "the views without angles were placed in two ways that fit the shapes alike (a near-symmetric "
             "object): " + std::string(kColoursChose) + ", the one with " + std::to_string(kept) +
             " overlapping pairs whose colours differ (the other " + std::to_string(other) + ")";
    };
    if (second_kept) {
      if (!(second_score > first_score)) res_.notes.push_back(chose(second_refuted, first_refuted));
      return;
    }
    restore(std::move(first));
    if (second_score > first_score) res_.notes.push_back(chose(first_refuted, second_refuted));
    warned = first_warned;
    confident_chain_ = false;
  }


  // A run without angles (the chain) whose table views refuse one rigid turntable,
  // no move between runs of them found: where most views keep to one turntable
  // line (axis_consensus.h) and some do not, those were placed on a turned twin
  // (a near-symmetric object given out of turntable order: the chain paired views
  // far round it, and the bottle's four front views came out on its back). Each
  // is placed again where a view of that turntable can be: the reference view's
  // pose turned about the line, swept in kAxisSweepDeg steps against the model of
  // the views kept, ICP from the kAxisStarts best peaks of closeness (place_on_line);
  // then all refined in the order of their turns, and kept when the views now fit
  // one rigid turntable, with no fewer registered and joined by converged pairs.
  void place_on_table_axis(std::size_t warned) {
    if (!chained_ || !rigid_rejected_ || p_.rigid_turntable != RigidTurntable::kAuto) return;
    std::vector<int> table;
    for (int i : ring())
      if (!res_.views[i].angle_rejected && std::find(off_table_.begin(), off_table_.end(), i) == off_table_.end())
        table.push_back(i);
    if (table.size() < 4) return;
    std::vector<Eigen::Matrix4d> poses;
    std::vector<Vec3d> centres;
    for (int i : table) {
      poses.push_back(res_.poses[i]);
      centres.push_back(centroid(views_[i].points));
    }
    AxisConsensus c =
        turntable_consensus(poses, centres, kAxisSlack * p_.rigid_max_deviation_deg,
                            kAxisSlack * p_.rigid_max_deviation_rel * diag_, 10.0, kAxisSameTurnDeg);
    // No line three views share at distinct turns (a cube's views stacked by the chain
    // on two turns of a line far off the table's): where the session's turntable is
    // calibrated, the line is known all the same, and every view but the first is
    // placed about it, where its colours agree with the views placed before it.
    const std::optional<TurntableAxis>& calibrated = m_.axis ? m_.axis : calibrated_;
    const bool from_calibrated = !c.found && calibrated;
    if (from_calibrated) c = calibrated_consensus(calibrated->point, calibrated->direction, poses, 0);
    if (!c.found) return;
    // Kept: the inliers, one per turn (the reference first, then the nearest the
    // line); views stacked on a kept view's turn are twins of it, and wait with the
    // views off the line.
    std::vector<int> order = c.inliers;
    std::stable_sort(order.begin(), order.end(), [&](int a, int b) {
      return std::make_pair(a != c.reference, c.deviation_deg[std::size_t(a)]) <
             std::make_pair(b != c.reference, c.deviation_deg[std::size_t(b)]);
    });
    std::vector<int> kept, pending;
    std::vector<double> turns;  // the kept views' turns from the reference's (degrees)
    for (int k : order) {
      const double t = c.turn[std::size_t(k)] * 180.0 / M_PI;
      if (near_a_turn(t, turns, kAxisSameTurnDeg)) continue;
      turns.push_back(t);
      kept.push_back(table[std::size_t(k)]);
    }
    for (int i : table)
      if (std::find(kept.begin(), kept.end(), i) == kept.end()) pending.push_back(i);
    // The views the chain failed or the refinement dropped (their fits were to views on twins) too.
    for (std::size_t i = 0; i < usable_.size(); ++i)
      if (!usable_[i] && (res_.views[i].initial == InitialPoseSource::kGlobal ||
                          std::find(chain_missed_.begin(), chain_missed_.end(), int(i)) != chain_missed_.end()))
        pending.push_back(int(i));
    // (About the calibrated line, the views the chain put against the model too: a run
    // without angles knows no view off the table but by how the chain placed it.)
    if (from_calibrated)
      for (int i : off_table_)
        if (usable_[std::size_t(i)] && std::find(pending.begin(), pending.end(), i) == pending.end()) pending.push_back(i);
    const Eigen::Matrix4d ref = res_.poses[table[std::size_t(c.reference)]];
    State before = state();
    const std::array<std::size_t, 3> before_score = chain_score();
    std::vector<int> moved;
    for (bool placed_some = true; placed_some && !pending.empty();) {
      placed_some = false;
      const PreparedView model = model_of(kept);
      const std::unique_ptr<ColourModel> colours = colour_model_of(kept);
      const std::unique_ptr<FreeSpace> free = free_space_of(kept);
      std::vector<int> still;
      std::vector<std::tuple<double, int, Eigen::Matrix4d>> placed;  // (-fitness, view, pose)
      for (int v : pending) {
        const auto X = place_on_line(v, model, colours.get(), free.get(), c, ref, turns, from_calibrated);
        if (X) placed.push_back({-X->second, v, X->first});
        else still.push_back(v);
      }
      // The best fits first; a view placed on the turn another took in this round waits.
      std::sort(placed.begin(), placed.end(),
                [](const auto& a, const auto& b) { return std::get<0>(a) < std::get<0>(b); });
      for (const auto& [fit, v, X] : placed) {
        const double t = turn_about_axis((X * rigid_inverse(ref)).block<3, 3>(0, 0), c.direction) * 180.0 / M_PI;
        if (near_a_turn(t, turns, kAxisSameTurnDeg)) {
          still.push_back(v);
          continue;
        }
        turns.push_back(t);
        res_.poses[v] = X;
        if (!usable_[std::size_t(v)]) {  // (a view failed before)
          usable_[std::size_t(v)] = true;
          res_.views[std::size_t(v)].message.clear();
          res_.views[std::size_t(v)].initial = InitialPoseSource::kGlobal;
        }
        // Now a table view (the chain may have placed it against the model), in the
        // order of the turns below.
        if (std::find(table.begin(), table.end(), v) == table.end()) table.push_back(v);
        off_table_.erase(std::remove(off_table_.begin(), off_table_.end(), v), off_table_.end());
        kept.push_back(v);
        moved.push_back(v);
        placed_some = true;
      }
      pending = std::move(still);
    }
    if (moved.empty()) return;
    // The ring in the order of the turns (the refinement pairs each view with its
    // neighbours in it): capture order was no turntable order.
    std::vector<std::pair<double, int>> by_turn;
    for (int i : table) {
      double t = turn_about_axis((res_.poses[i] * rigid_inverse(ref)).block<3, 3>(0, 0), c.direction);
      if (!std::isfinite(t)) continue;  // (ring() puts it after the others)
      if (t < 0) t += 2 * M_PI;
      by_turn.push_back({t, i});
    }
    std::sort(by_turn.begin(), by_turn.end());
    ring_order_.clear();
    for (const auto& [t, i] : by_turn) ring_order_.push_back(i);
    res_.warnings.resize(warned);
    res_.pairs.clear();
    refine();
    // (Not on the converged pairs: views on a twin, where others already are, overlap
    // more of them than views spread round the table.)
    const std::array<std::size_t, 3> score = chain_score();
    if (rigid_rejected_ || score[0] < before_score[0] || score[1] < before_score[1]) {
      restore(std::move(before));
      return;
    }
    std::sort(moved.begin(), moved.end());
    std::ostringstream w;
    w << (from_calibrated ? "placed again about the session's calibrated turntable axis" :
                            "placed again about the turntable axis the other views share")
      << " (the run without angles had put them off it, on a near-symmetric shape's turned twin, or failed them):";
    for (int v : moved) w << " " << view_name(m_, std::size_t(v));
    res_.notes.push_back(w.str());
  }

  // View v posed as a view of the turntable `c` can be (its reference view's pose
  // `ref` turned about the line), the turn found by a sweep of the closeness to
  // `model` away from the kept views' `turns`, then ICP from the best peaks; the
  // converged pose with the best overlap (ICP fitness) that the model's views do
  // not see through and that is not at a kept view's turn, near ties by colour (and,
  // with `colour_must_agree`, none whose colours disagree with the model's); with
  // its fitness. None when no such pose overlaps by the global registration's minimum.
  std::optional<std::pair<Eigen::Matrix4d, double>> place_on_line(int v, const PreparedView& model, const ColourModel* colours,
                                               const FreeSpace* free, const AxisConsensus& c,
                                               const Eigen::Matrix4d& ref, const std::vector<double>& turns,
                                               bool colour_must_agree) const {
    const IcpParams ip = refine_params();
    const int steps = int(std::lround(360.0 / kAxisSweepDeg));
    std::vector<Eigen::Matrix4d> start(static_cast<std::size_t>(steps));
    std::vector<double> ov(static_cast<std::size_t>(steps));
    // At a kept view's own turn (within kAxisSameTurnDeg): where that view's twin
    // fits, for it sees what that view saw.
    const auto at_kept_turn = [&](double t) { return near_a_turn(t, turns, kAxisSameTurnDeg); };
    tbb::parallel_for(0, steps, [&](int s) {
      start[std::size_t(s)] = turn_about_line(c.point, c.direction, 2 * M_PI * s / steps) * ref;
      ov[std::size_t(s)] = closeness(views_[v], model, start[std::size_t(s)], ip.max_distance_start);
    });
    // The sweep's peaks (round the circle) away from the kept views' turns, best first.
    std::vector<int> peaks;
    for (int s = 0; s < steps; ++s) {
      const double o = ov[std::size_t(s)];
      if (o > 0 && o >= ov[std::size_t((s + steps - 1) % steps)] && o > ov[std::size_t((s + 1) % steps)] &&
          !at_kept_turn(s * kAxisSweepDeg))
        peaks.push_back(s);
    }
    std::stable_sort(peaks.begin(), peaks.end(),
                     [&](int a, int b) { return ov[std::size_t(a)] > ov[std::size_t(b)]; });
    peaks.resize(std::min(peaks.size(), kAxisStarts));
    std::vector<IcpResult> r(peaks.size());
    tbb::parallel_for(std::size_t(0), peaks.size(), [&](std::size_t k) {
      r[k] = icp_point_to_plane(views_[v], model, start[std::size_t(peaks[k])], ip);
      // ICP that ran out of iterations while still sliding goes on at the final distance.
      if (!r[k].converged && r[k].fitness >= p_.global_min_fitness) {
        IcpParams more = ip;
        more.max_distance_start = ip.max_distance_end;
        more.max_iterations = 2 * ip.max_iterations;
        r[k] = icp_point_to_plane(views_[v], model, r[k].transform, more);
      }
    });
    std::vector<double> rms;
    for (const IcpResult& x : r)
      if (x.converged) rms.push_back(x.plane_rmse);
    const double noise_rms = rms.empty() ? 0.0 : median_of(rms);
    std::vector<char> usable(r.size(), 0), twin(r.size(), 0);
    for (std::size_t k = 0; k < r.size(); ++k) {
      if (!r[k].converged || r[k].fitness < p_.global_min_fitness) continue;
      if (free && seen_share(*free, views_[v].points, r[k].transform, noise_rms) > kSeenThrough) continue;
      usable[k] = 1;
      twin[k] = at_kept_turn(turn_about_axis((r[k].transform * rigid_inverse(ref)).block<3, 3>(0, 0), c.direction) *
                             180.0 / M_PI);
    }
    // Never at a kept view's turn (the view waits for the model to grow, or stays).
    for (std::size_t k = 0; k < r.size(); ++k) usable[k] = usable[k] && !twin[k];
    std::vector<double> err(r.size(), std::numeric_limits<double>::infinity());
    if (colours)
      for (std::size_t k = 0; k < r.size(); ++k)
        if (usable[k])
          err[k] = colour_error(views_[v].full, *colours, r[k].transform, ip.max_distance_end, views_[v].viewpoint);
    // `colour_must_agree`: not where the colours disagree with the model's (a cube's
    // quarter-turned twin, which the shape alone cannot tell: 33-137 per channel where
    // a right pose reads 4-6); the view waits for the model to grow.
    if (colours && colour_must_agree)
      for (std::size_t k = 0; k < r.size(); ++k)
        if (std::isfinite(err[k]) && err[k] >= colours->disagrees) usable[k] = 0;
    double best_fit = 0;
    for (std::size_t k = 0; k < r.size(); ++k)
      if (usable[k]) best_fit = std::max(best_fit, r[k].fitness);
    int best = -1;
    for (std::size_t k = 0; k < r.size(); ++k) {
      if (!usable[k] || r[k].fitness < best_fit - kTie) continue;
      if (best < 0 || err[k] < err[std::size_t(best)] ||
          (err[k] == err[std::size_t(best)] && r[k].fitness > r[std::size_t(best)].fitness))
        best = int(k);
    }
    if (best < 0) return std::nullopt;
    return std::make_pair(r[std::size_t(best)].transform, r[std::size_t(best)].fitness);
  }

  // The groups of usable views that the last round's converged pairs join (in the
  // order of their union-find roots), and which of them is the largest (ties: the
  // first).
  std::vector<std::vector<int>> linked_groups(std::size_t* largest = nullptr) const {
    std::vector<std::vector<int>> out;
    if (largest) *largest = 0;
    if (res_.pairs.empty()) return out;
    const int last = res_.pairs.back().round;
    UnionFind uf(m_.views.size());
    for (const PairDiagnostics& pd : res_.pairs)
      if (pd.round == last && pd.converged && usable_[std::size_t(pd.from)] && usable_[std::size_t(pd.to)])
        uf.unite(pd.from, pd.to);
    std::map<int, std::vector<int>> groups;
    for (std::size_t i = 0; i < m_.views.size(); ++i)
      if (usable_[i]) groups[uf.find(int(i))].push_back(int(i));
    for (auto& [root, g] : groups) out.push_back(std::move(g));
    if (largest)
      for (std::size_t k = 1; k < out.size(); ++k)
        if (out[k].size() > out[*largest].size()) *largest = k;
    return out;
  }

  // Groups of two or more views that no converged pair joins to the largest one
  // and that the turntable angles placed (issue 26: the object moved on the table
  // between two views, and the angles carried the later views along as if it had
  // not, so they overlap nothing where they are): each merged and registered
  // globally onto the largest group. A placement is taken only for a group that
  // overlaps the others at most 0.1 where it is, when it is a move on the table (a
  // turn about the table's axis direction, within 10 degrees, and a slide) that
  // overlaps clearly better; the session is then refined again and kept
  // only if every moved group is joined by converged pairs; the warnings of the
  // refinement before (from `first_refine_words`) are then dropped. True when kept.
  bool place_unlinked_groups(std::size_t first_refine_words, bool colours_choose = true) {
    std::size_t largest = 0;
    const std::vector<std::vector<int>> groups = linked_groups(&largest);
    if (groups.size() < 2 || groups[largest].size() < 2) return false;
    const std::vector<int>& base = groups[largest];
    const std::optional<std::pair<Vec3d, Vec3d>> axis = object_axis(base);
    std::vector<std::vector<int>> moved;
    std::vector<std::string> words;
    State before = state();  // put back whole when the placement is not kept
    bool turned_any = false;
    for (std::size_t k = 0; k < groups.size(); ++k) {
      if (k == largest) continue;
      const std::vector<int>& g = groups[k];
      const bool by_angles = std::any_of(g.begin(), g.end(), [&](int i) { return placed_by_angle(i); });
      // A group that no angle placed (the run without angles: the chain's global
      // registrations put it there, pairs it could not refine): its place is measured
      // by nothing either (the dragon's scans given out of turntable order: two of them
      // 169 deg off, exit 0), so it is tried the same way; a turn about any axis.
      if (g.size() < 2 || (!by_angles && !chained_)) continue;
      // Where the angles put it the group must overlap the others hardly at all (the
      // moved dragon: 0.015). A group that overlaps them there and still joins no
      // pair is a sparse or near-symmetric session (the pipeline tests' 6-view
      // bottle: 0.31, and its global fit is the bottle turned half way).
      double now = 0, then = 0;
      // Not so for a group the features placed: where it is was as much a guess (the
      // shuffled dragon's half-turned pair overlaps the others 0.24-0.27 there).
      std::optional<Eigen::Matrix4d> G =
          place_group(base, g, now, then, by_angles ? 0.1 : std::numeric_limits<double>::infinity());
      if (!G) continue;
      const Eigen::AngleAxisd turn(Eigen::Matrix3d(G->block<3, 3>(0, 0)));
      constexpr double kDegree = M_PI / 180;
      if (by_angles && axis && turn.angle() > 2 * kDegree &&
          std::abs(turn.axis().dot(axis->second)) < std::cos(10 * kDegree))
        continue;
      double twin = -1;
      const int settled = settle_twin(base, g, *G, then, axis, twin, colours_choose);
      turned_any = turned_any || settled > 0;
      for (int j : g) res_.poses[j] = *G * res_.poses[j];
      if (by_angles) {
        int anchor = -1;
        for (int j : base)
          if (has_angle(j) && !res_.views[std::size_t(j)].angle_rejected) anchor = j;
        shift_angles(g, *G, anchor, axis);
      }
      moved.push_back(g);
      std::ostringstream w;
      w.precision(3);
      // The slide at the group (its points' centroid), in the session's units.
      Vec3d c = Vec3d::Zero();
      std::size_t count = 0;
      for (int j : g)
        for (const Vec3f& q : views_[std::size_t(j)].points) {
          c += (res_.poses[j] * q.cast<double>().homogeneous()).head<3>();  // (already moved)
          ++count;
        }
      c /= double(std::max<std::size_t>(count, 1));
      const double slide = (c - (rigid_inverse(*G) * c.homogeneous()).head<3>()).norm();
      if (by_angles)
        w << group_name(g) << ", which the angles placed where they overlap nothing, were registered to the "
          << "others as a whole: the object moved on the table (" << rotation_angle_deg(*G) << " deg, "
          << res_.mm_per_unit * slide << " mm; overlap " << now << " -> " << then << ")";
      else
        w << group_name(g) << ", which their features placed where no pair joins them, were registered to the "
          << "others as a whole (moved " << rotation_angle_deg(*G) << " deg, " << res_.mm_per_unit * slide
          << " mm; overlap " << now << " -> " << then << ")";
      if (settled > 0) w << kTwinChosen;
      words.push_back(w.str());
      if (settled < 0) words.push_back(twin_words(g, twin, then));
    }
    if (moved.empty()) return false;
    // Refined again from the moved poses; kept when every moved group is joined.
    const auto all_joined = [&] {
      std::size_t main_group = 0;
      const std::vector<std::vector<int>> after = linked_groups(&main_group);
      return !after.empty() && std::all_of(moved.begin(), moved.end(), [&](const std::vector<int>& g) {
        const std::vector<int>& joint = after[main_group];
        return std::any_of(g.begin(), g.end(), [&](int i) {
          return std::find(joint.begin(), joint.end(), i) != joint.end();
        });
      });
    };
    res_.warnings.resize(std::min(first_refine_words, res_.warnings.size()));
    const std::size_t kept_words = res_.warnings.size();
    res_.pairs.clear();
    refine();
    if (!all_joined()) {
      restore(std::move(before));
      // Where a group was turned by its colours and the groups then do not all join:
      // every group placed where the shapes fit best instead, a group whose twin fits
      // named as ambiguous (as before the colours chose).
      return turned_any && place_unlinked_groups(first_refine_words, false);
    }
    // Views without an angle that global registration could not place against the
    // model of the misplaced poses: tried again against the corrected one, and kept
    // when the groups stay joined and no more views fail.
    std::vector<int> retry;
    for (int i : unplaced_)
      if (!usable_[std::size_t(i)]) retry.push_back(i);
    if (!retry.empty()) {
      State placed_state = state();
      for (int i : retry) {
        usable_[std::size_t(i)] = true;
        res_.views[std::size_t(i)].message.clear();
      }
      unplaced_.clear();
      global_poses();
      const bool placed = std::any_of(retry.begin(), retry.end(), [&](int i) { return usable_[std::size_t(i)]; });
      if (!placed) {
        restore(std::move(placed_state));
      } else {
        const std::size_t usable_before =
            std::size_t(std::count(placed_state.usable.begin(), placed_state.usable.end(), true));
        res_.warnings.resize(std::min(kept_words, res_.warnings.size()));
        res_.pairs.clear();
        refine();
        if (!all_joined() || std::size_t(std::count(usable_.begin(), usable_.end(), true)) <= usable_before)
          restore(std::move(placed_state));
      }
    }
    replace_feature_placed(moved, all_joined, words, kept_words);
    res_.warnings.insert(res_.warnings.end(), words.begin(), words.end());
    for (const std::vector<int>& g : moved) res_.moved_with_object.insert(res_.moved_with_object.end(), g.begin(), g.end());
    return true;
  }

  // After place_unlinked_groups moved groups: the views global registration had
  // placed against the model of the misplaced poses (an angle found wrong, or
  // none) are placed again, as groups joined by converged pairs among themselves,
  // onto the model of all the others (place_group: where they overlap it clearly
  // better). Kept when the session is then still joined as `joined` asks, no view
  // fewer is registered, and the views contradict what the others saw less than
  // before (the largest seen_through). Only views above kSeenClear are tried.
  // (The issue's own session with the object turned 10 degrees and moved 5 cm on
  // the table, scanned again, run with the corrected angles: the two views whose
  // angles were found wrong and the view without one after them came out 62 deg
  // off, joined to the rest by weak pairs, up to 21 % of a view where the others
  // saw through; placed again, within 0.04 deg and 3 %.)
  template <class Joined>
  void replace_feature_placed(const std::vector<std::vector<int>>& moved, const Joined& joined,
                              std::vector<std::string>& words, std::size_t kept_words) {
    if (chained_) return;
    const std::size_t n = m_.views.size();
    const double seen_before = most_seen_now();
    std::vector<bool> member(n, false);
    for (std::size_t i = 0; i < n; ++i)
      member[i] = usable_[i] && res_.views[i].initial == InitialPoseSource::kGlobal &&
                  res_.views[i].seen_through.value_or(0) > kSeenClear;
    for (const std::vector<int>& g : moved)
      for (int j : g) member[std::size_t(j)] = false;
    if (std::none_of(member.begin(), member.end(), [](bool b) { return b; })) return;
    UnionFind uf(n);
    if (!res_.pairs.empty())
      for (const PairDiagnostics& pd : res_.pairs)
        if (pd.round == res_.pairs.back().round && pd.converged && member[std::size_t(pd.from)] &&
            member[std::size_t(pd.to)])
          uf.unite(pd.from, pd.to);
    std::map<int, std::vector<int>> parts;
    for (std::size_t i = 0; i < n; ++i)
      if (member[i]) parts[uf.find(int(i))].push_back(int(i));
    const std::size_t usable_before = std::size_t(std::count(usable_.begin(), usable_.end(), true));
    State before = state();
    std::vector<std::string> said;
    for (const auto& [root, g] : parts) {
      std::vector<int> base;
      for (std::size_t i = 0; i < n; ++i)
        if (usable_[i] && std::find(g.begin(), g.end(), int(i)) == g.end()) base.push_back(int(i));
      if (base.size() < 2) continue;
      double now = 0, then = 0;
      const std::optional<Eigen::Matrix4d> G =
          place_group(base, g, now, then, std::numeric_limits<double>::infinity(), true);
      if (!G) continue;
      for (int j : g) res_.poses[std::size_t(j)] = *G * res_.poses[std::size_t(j)];
      std::ostringstream w;
      w.precision(3);
      w << group_name(g) << ", placed by global registration before the move was found, "
        << (g.size() > 1 ? "were" : "was") << " placed again against the others (moved " << rotation_angle_deg(*G)
        << " deg; overlap " << now << " -> " << then << ")";
      said.push_back(w.str());
    }
    if (said.empty()) return;
    // (The refinement's warnings replace those of the one before, from `kept_words`.)
    res_.warnings.resize(std::min(kept_words, res_.warnings.size()));
    res_.pairs.clear();
    refine();
    const double seen_after = most_seen_now();
    if (!joined() || std::size_t(std::count(usable_.begin(), usable_.end(), true)) < usable_before ||
        !(seen_after < seen_before)) {
      restore(std::move(before));
      return;
    }
    words.insert(words.end(), said.begin(), said.end());
  }

  // The turntable axis in the object frame (a point on it, its unit direction),
  // from the first of `members` posed by an angle; none without.
  std::optional<std::pair<Vec3d, Vec3d>> object_axis(const std::vector<int>& members) const {
    if (!res_.axis) return std::nullopt;
    for (int j : members) {
      if (!has_angle(j) || res_.views[j].angle_rejected) continue;
      const Eigen::Matrix4d& X = res_.poses[j];
      return std::make_pair(Vec3d((X * res_.axis->point.homogeneous()).head<3>()),
                            Vec3d((X.block<3, 3>(0, 0) * res_.axis->direction).normalized()));
    }
    return std::nullopt;
  }

  // A view without an angle whose nearest views with angles before and after it in
  // capture order (round the end: a turntable session is a ring; a view whose angle
  // was found wrong counts with the turn global registration gave it) are less than
  // half a turn apart, forwards: the pose of the angle interpolated between theirs by its
  // place between them, and a tolerance of one step between views plus 15 degrees.
  // None without a turntable axis or such neighbours. `angle`: that angle.
  std::optional<std::pair<Eigen::Matrix4d, double>> expected_pose(int i, double* angle_out = nullptr) const {
    const int n = int(m_.views.size());
    if (!res_.axis || n < 3) return std::nullopt;
    const auto angled = [&](int j) {
      return usable_[std::size_t(j)] && has_angle(j) && !res_.views[std::size_t(j)].angle_rejected &&
             posed(std::size_t(j));
    };
    // A neighbour's turn: its angle, or where its angle was found wrong and global
    // registration placed it on the table (check_angles), the turn of that pose (the
    // issue's view 11 degrees off, then the view without angle after it: its
    // neighbours with angles 180 degrees apart over four steps expected nothing, and
    // the near-symmetric bottle's view came out 179 degrees off).
    const Eigen::Matrix4d table = table_from_scanner(*res_.axis);
    const auto turn_of = [&](int j) -> std::optional<double> {
      if (angled(j)) return *m_.views[std::size_t(j)].angle_deg;
      const ViewDiagnostics& d = res_.views[std::size_t(j)];
      if (!usable_[std::size_t(j)] || !has_angle(j) || !d.angle_rejected || d.initial != InitialPoseSource::kGlobal)
        return std::nullopt;
      const Eigen::Matrix3d R = (res_.poses[std::size_t(j)] * rigid_inverse(table)).block<3, 3>(0, 0);
      const double t = turn_about_axis(R, Vec3d::UnitZ());
      // On the table: a turn about its axis, hardly tilted.
      const Eigen::Matrix3d rest = Eigen::AngleAxisd(t, Vec3d::UnitZ()).toRotationMatrix().transpose() * R;
      if (Eigen::AngleAxisd(rest).angle() > 10 * M_PI / 180) return std::nullopt;
      return -t * 180 / M_PI;
    };
    int before = -1, after = -1, steps_before = 0, steps_after = 0;
    for (int d = 1; d < n && before < 0; ++d)
      if (turn_of((i - d + n) % n)) before = (i - d + n) % n, steps_before = d;
    for (int d = 1; d < n && after < 0; ++d)
      if (turn_of((i + d) % n)) after = (i + d) % n, steps_after = d;
    if (before < 0 || after < 0 || before == after) return std::nullopt;
    const double a0 = *turn_of(before), a1 = *turn_of(after);
    // The forward span from `before` to `after`, in the direction the angles grow.
    double span = std::fmod(a1 - a0, 360.0);
    if (span < 0) span += 360;
    if (!(span > 0)) return std::nullopt;
    const double step = span / double(steps_before + steps_after);
    if (span >= 180) {
      // Half a turn or more without angles (the first four of eight views): taken
      // when the views with angles step as evenly (within a quarter of their median
      // step between neighbours in capture order).
      std::vector<double> steps;
      for (int j = 0; j < n; ++j)
        if (angled(j) && angled((j + 1) % n)) {
          double d = std::fmod(*m_.views[std::size_t((j + 1) % n)].angle_deg - *m_.views[std::size_t(j)].angle_deg, 360.0);
          if (d < 0) d += 360;
          if (d > 0 && d < 180) steps.push_back(d);
        }
      if (steps.empty()) return std::nullopt;
      const double typical = median_of(steps);
      if (!(std::abs(step - typical) <= 0.25 * typical)) return std::nullopt;
    }
    const double angle = a0 + step * steps_before;
    if (angle_out) *angle_out = angle;
    return std::make_pair(turntable_pose(*res_.axis, angle), step + 15.0);
  }

  // A chain's pair: view `src` against view `j` in j's frame, by global
  // registration with j's colours weighed (colour_swap); where every pose found
  // brings different colours together (a cube's faces alike but for their
  // stickers: the RANSAC poses all land on one turned twin), the multi-start,
  // taken when a pose of it agrees in colour. Made once per pair (the second
  // chain asks again: the views and features do not change).
  const GlobalAlign& pair_align(int src, int j) {
    const auto key = std::make_pair(src, j);
    const auto found = pair_aligns_.find(key);
    if (found != pair_aligns_.end()) return found->second;
    const ColourModel* colours = own_colours(j);
    GlobalAlign a = global_align(views_[src], {&features_of(src)}, views_[src].full, views_[j], {&features_of(j)},
                                 colours, std::nullopt, false, false, nullptr, true);
    if (a.ok && a.colour_disagrees) {
      const GlobalAlign b = global_align(views_[src], all_features_of(src), views_[src].full, views_[j],
                                         all_features_of(j), colours, std::nullopt, true, false, nullptr, true);
      if (b.ok && !b.colour_disagrees && b.colour <= kColourBetter * a.colour) a = b;
    }
    // Still different colours brought together, or no fit at all: the features matched
    // only where their colours agree (FeatureView::chroma), from many starts. A cube's
    // faces are alike but for their stickers, so every face's features match every
    // other's and RANSAC's poses land on quarter-turned twins; the right pose of two
    // views 30 deg apart converged with a better overlap (0.60 against 0.47) but was
    // never proposed.
    if (colours && views_[src].full.has_colours() && p_.global.colour_gate > 0 && (!a.ok || a.colour_disagrees)) {
      GlobalAlign c = global_align(views_[src], {&colour_features_of(src)}, views_[src].full, views_[j],
                                   {&colour_features_of(j)}, colours, std::nullopt, true, false, nullptr, true);
      c.by_colour = a.ok;  // (a pose where the shapes alone found none is no choice between two)
      if (c.ok && !c.colour_disagrees && (!a.ok || c.colour <= kColourBetter * a.colour)) a = c;
    }
    // (Infinite where nothing could be compared, a source view without colours: no word.)
    a.colour_refuted =
        a.ok && colours && std::isfinite(a.colour) && a.colour >= kChainColourRefutes * colours->disagrees;
    return pair_aligns_.emplace(key, std::move(a)).first->second;
  }

  // Views without a pose: chained in capture order when nothing is posed,
  // else registered against the model merged from the posed views.
  void global_poses() {
    const std::size_t n = m_.views.size();
    std::vector<int> todo, have;
    for (std::size_t i = 0; i < n; ++i) {
      if (!usable_[i]) continue;
      if (res_.views[i].initial == InitialPoseSource::kNone) todo.push_back(int(i));
      else have.push_back(int(i));
    }
    if (todo.empty()) return;
    if (have.empty()) {
      // Chain: the first view anchors the object frame; each next view is
      // aligned to the previous registered ones (nearest first, two tried) and taken
      // at the first that fits. The second chain (confident_chain_, tried when the
      // first leaves views failed or groups unjoined) takes a fit there only when it
      // is confident (kConfidentFitness); the others wait, and are then tried against
      // every chained view, again and again while that places some (views given out
      // of turntable order: a view's predecessors are then far round the object, and
      // a weak fit to one of them, 0.175 for two dragon scans 120 deg apart, put four
      // views 103 deg off; neighbours 24 deg apart fit 0.42-0.78). What is still
      // unplaced takes its best fit found (at least the acceptance overlap).
      chained_ = true;
      const int anchor = todo.front();
      res_.poses[anchor] = Eigen::Matrix4d::Identity();
      res_.views[anchor].initial = InitialPoseSource::kGlobal;
      std::vector<int> chain = {anchor};
      std::vector<std::pair<int, std::string>> missed;  // views the chain could not place
      if (todo.size() > 1) report("global", 0, int(todo.size() - 1));
      struct Waiting {
        int view;
        GlobalAlign best;
        int best_to = -1;
        std::string why;
        std::vector<int> tried;
      };
      std::vector<Waiting> waiting;
      const auto attempt = [&](Waiting& w, int j) {
        w.tried.push_back(j);
        const GlobalAlign& a = pair_align(w.view, j);
        // A fit whose colours agree before any that disagree, then the best overlap.
        if (a.ok && (w.best_to < 0 || (w.best.colour_refuted && !a.colour_refuted) ||
                     (w.best.colour_refuted == a.colour_refuted && a.fitness > w.best.fitness))) {
          w.best = a;
          w.best_to = j;
        }
        if (!a.ok && w.why.empty()) w.why = view_name(m_, j) + ": " + a.message;
        return a.ok && !a.colour_refuted && a.fitness >= kConfidentFitness;
      };
      std::vector<int> by_colour;  // placed by a pose the colours chose (pair_align)
      const auto place = [&](const Waiting& w) {
        if (w.best.by_colour) by_colour.push_back(w.view);
        weak_fit_ = weak_fit_ || w.best.fitness < kConfidentFitness || w.best.colour_refuted;
        res_.poses[w.view] = res_.poses[w.best_to] * w.best.transform;
        res_.views[w.view].initial = InitialPoseSource::kGlobal;
        chain.push_back(w.view);
      };
      int done = 0;
      for (std::size_t k = 1; k < todo.size(); ++k) {
        Waiting w;
        w.view = todo[k];
        bool confident = false;
        for (int back = 1; back <= 2 && back <= int(chain.size()) && !confident; ++back) {
          confident = attempt(w, chain[chain.size() - back]);
          // The first chain: the nearest view that fits at all (a weak fit to the view
          // before is right more often than a strong one further off on a near-
          // symmetric object: the bottle's sessions).
          if (!confident_chain_ && w.best_to >= 0) confident = true;
        }
        if (confident) {
          place(w);
          report("global", ++done, int(todo.size() - 1));
        } else {
          waiting.push_back(std::move(w));
        }
      }
      for (bool placed_some = confident_chain_; placed_some && !waiting.empty();) {
        placed_some = false;
        std::vector<Waiting> still;
        for (Waiting& w : waiting) {
          bool confident = false;
          for (std::size_t c = chain.size(); c-- > 0 && !confident;)
            if (std::find(w.tried.begin(), w.tried.end(), chain[c]) == w.tried.end()) confident = attempt(w, chain[c]);
          if (confident) {
            place(w);
            placed_some = true;
            report("global", ++done, int(todo.size() - 1));
          } else {
            still.push_back(std::move(w));
          }
        }
        waiting = std::move(still);
      }
      for (const Waiting& w : waiting) {
        report("global", ++done, int(todo.size() - 1));
        if (w.best_to < 0) {
          missed.push_back({w.view, "global registration against the previous views failed (" + w.why + ")"});
          continue;
        }
        place(w);
      }
      // A view that fits neither of the two before it (a view from above or
      // below among table views, a view after a gap in the ring) gets the
      // multi-start against the model of every chained view, as an off-table
      // view does (issue 26, item 3).
      // One pass: a second one, against the model widened by the first's, placed
      // three of the dragon's views given in a shell glob's order half-turned
      // (168 deg), where one pass leaves them failed by name.
      std::map<int, std::string> against_model;  // each view's word from the model
      if (!missed.empty() && chain.size() >= 2) {
        const PreparedView model = model_of(chain);
        const std::vector<FeatureView> model_feat = model_features(model);
        const std::unique_ptr<ColourModel> colours = colour_model_of(chain);
        const std::unique_ptr<FreeSpace> free = free_space_of(chain);
        std::vector<std::pair<int, std::string>> still;
        for (const auto& [i, why] : missed) {
          const GlobalAlign a = global_align(i, model, model_feat, colours.get(), std::nullopt, free.get());
          if (!a.ok) {
            against_model[i] = "; " + a.message + " against the model of the others";
            still.push_back({i, why});
            continue;
          }
          res_.poses[i] = a.transform;
          res_.views[i].initial = InitialPoseSource::kGlobal;
          off_table_.push_back(i);
        }
        missed = std::move(still);
      }
      for (const auto& [i, why] : missed) {
        fail(i, why + against_model[i]);
        chain_missed_.push_back(i);
      }
      if (!by_colour.empty()) {
        std::sort(by_colour.begin(), by_colour.end());
        res_.notes.push_back(group_name(by_colour) + ": the shapes fit the views before them in other places too "
                             "(a near-symmetric object, turned), where the colours differ; " + kColoursChose +
                             " places");
      }
      return;
    }
    // Off-turntable views: against the model of the posed ones. Table views without
    // an angle between views with angles (expected_pose) go first, the one whose
    // expected turn is nearest a posed view's first, and each placed near its expected
    // pose joins the model for the next: a view far from every posed view overlaps
    // them little (the fandisk's eight views with the first four without angle: the
    // third, 90 deg from the nearest posed view, fitted its half-turned twin better and
    // came out 178 deg off, exit 0, no warning).
    const PreparedView given_model = model_of(have);
    report("global", 0, int(todo.size()));
    const std::vector<FeatureView> given_feat = model_features(given_model);
    const std::unique_ptr<ColourModel> given_colours = colour_model_of(have);
    const std::unique_ptr<FreeSpace> given_free = free_space_of(have);
    const auto axis = object_axis(have);
    std::vector<double> posed_angles;
    for (int j : have)
      // (As given, as expected_pose interpolates them.)
      if (has_angle(j) && !res_.views[std::size_t(j)].angle_rejected) posed_angles.push_back(*m_.views[std::size_t(j)].angle_deg);
    std::map<int, double> expected_angle;
    for (int i : todo) {
      double a = 0;
      if (expected_pose(i, &a)) expected_angle[i] = a;
    }
    const auto gap = [&](int i) {
      double g = 360;
      for (double a : posed_angles) g = std::min(g, std::abs(std::remainder(expected_angle.at(i) - a, 360.0)));
      return g;
    };
    std::vector<int> order;
    for (int i : todo)
      if (!expected_angle.count(i)) order.push_back(i);
    std::vector<int> table_todo;
    for (int i : todo)
      if (expected_angle.count(i)) table_todo.push_back(i);
    std::vector<int> members = have;  // the grown model's views
    std::optional<PreparedView> grown;
    std::vector<FeatureView> grown_feat;
    std::unique_ptr<ColourModel> grown_colours;
    std::unique_ptr<FreeSpace> grown_free;
    std::size_t next_other = 0;  // the next of `order` (after every table view)
    for (std::size_t k = 0; k < todo.size(); ++k) {
      int i;
      const bool table = !table_todo.empty();
      if (table) {
        const auto next = std::min_element(table_todo.begin(), table_todo.end(),
                                           [&](int a, int b) { return gap(a) < gap(b); });
        i = *next;
        table_todo.erase(next);
      } else {
        i = order[next_other++];
      }
      const PreparedView& model = table && grown ? *grown : given_model;
      expected_ = expected_pose(i);
      const GlobalAlign a =
          global_align(i, model, table && grown ? grown_feat : given_feat,
                       table && grown ? grown_colours.get() : given_colours.get(), axis,
                       table && grown ? grown_free.get() : given_free.get());
      const bool near_expected =
          expected_ && a.ok && rotation_angle_deg(Eigen::Matrix4d(rigid_inverse(expected_->first) * a.transform)) <=
                                   expected_->second;
      // ...and on the table's line (a turn of the expected pose about it, within the
      // rigid turntable's bounds): a table view, held on the line by the rigid solve
      // with its own free angle (refine), so that it cannot slide where its pairs
      // barely hold it (the fandisk's view between two posed ones 90 deg apart: 1.07 mm).
      if (near_expected && axis) {
        const Eigen::Matrix4d M = a.transform * rigid_inverse(expected_->first);
        const Eigen::Matrix4d on_line =
            turn_about_line(axis->first, axis->second, turn_about_axis(M.block<3, 3>(0, 0), axis->second));
        const Vec3d at = (expected_->first * centroid(views_[std::size_t(i)].points).homogeneous()).head<3>();
        if (rotation_angle_deg(Eigen::Matrix4d(rigid_inverse(on_line) * M)) <= p_.rigid_max_deviation_deg &&
            ((M - on_line) * at.homogeneous()).head<3>().norm() <= p_.rigid_max_deviation_rel * diag_)
          if (std::find(table_free_.begin(), table_free_.end(), i) == table_free_.end()) table_free_.push_back(i);
      }
      expected_.reset();
      report("global", int(k + 1), int(todo.size()));
      if (!a.ok) {
        fail(i, "no initial pose or angle, and " + a.message + " against the merged model");
        unplaced_.push_back(i);
        continue;
      }
      res_.poses[i] = a.transform;
      res_.views[i].initial = InitialPoseSource::kGlobal;
      off_table_.push_back(i);
      if (table && near_expected && !table_todo.empty()) {
        posed_angles.push_back(expected_angle.at(i));
        members.push_back(i);
        grown = model_of(members);
        grown_feat = model_features(*grown);
        grown_colours = colour_model_of(members);
        grown_free = free_space_of(members);
      }
    }
  }

  // Views posed from a commanded angle: ICP onto the angle neighbours from the
  // prior. A view none of whose neighbour pairs converges near the prior is
  // suspect; it is registered globally against the others, and a pose far
  // from the prior replaces the angle's.
  void check_angles() {
    std::vector<int> a;
    for (int i : ring())
      if (posed(i) && (res_.views[i].initial == InitialPoseSource::kTurntableAxis ||
                       res_.views[i].initial == InitialPoseSource::kEstimatedAxis))
        a.push_back(i);
    const int m = int(a.size());
    if (m < 3) return;
    report("angles", 0, 1);
    std::vector<Pair> pairs;
    std::vector<Eigen::Matrix4d> init;
    for (int k = 0; k < m; ++k) {
      pairs.push_back({a[k], a[(k + 1) % m], k + 1 == m});
      init.push_back(rigid_inverse(res_.poses[a[k]]) * res_.poses[a[(k + 1) % m]]);
    }
    const auto r = run_pairs(pairs, init, p_.icp_start_rel * diag_, icp_end_);
    // good[k]: pair k converged near its prior.
    std::vector<bool> good(m);
    for (int k = 0; k < m; ++k)
      good[k] = r[k].converged && rotation_angle_deg(rigid_inverse(init[k]) * r[k].transform) < p_.wrong_angle_deg;
    std::vector<int> suspects;
    for (int k = 0; k < m; ++k)
      if (!good[k] && !good[(k + m - 1) % m]) suspects.push_back(a[k]);
    report("angles", 1, 1);
    if (suspects.empty() || int(suspects.size()) * 2 >= m) return;  // most fail: not the angles' fault
    std::vector<int> others;
    for (int i : a)
      if (std::find(suspects.begin(), suspects.end(), i) == suspects.end()) others.push_back(i);
    const PreparedView model = model_of(others);
    const std::vector<FeatureView> model_feat = model_features(model);
    const std::unique_ptr<ColourModel> colours = colour_model_of(others);
    const std::unique_ptr<FreeSpace> free = free_space_of(others);
    const auto axis = object_axis(others);
    for (int i : suspects) {
      expected_ = std::make_pair(res_.poses[i], kSuspectNearDeg);
      expected_suspect_ = true;
      const GlobalAlign g = global_align(i, model, model_feat, colours.get(), axis, free.get());
      expected_.reset();
      expected_suspect_ = false;
      if (!g.ok) continue;  // the refinement decides (and fails it if nothing overlaps)
      const double off = rotation_angle_deg(rigid_inverse(res_.poses[i]) * g.transform);
      if (off < p_.wrong_angle_deg) continue;
      std::ostringstream w;
      w.precision(3);
      w << view_name(m_, i) << ": commanded angle ";
      const std::optional<double> as_given = given_ ? given_->views[std::size_t(i)].angle_deg : m_.views[i].angle_deg;
      if (as_given && *as_given != *m_.views[i].angle_deg)
        w << *as_given << " deg (" << *m_.views[i].angle_deg << " corrected)";
      else
        w << *m_.views[i].angle_deg << " deg";
      w << " looks wrong: global registration puts the view " << off
        << " deg from it; the registered pose is used and its angle ignored";
      res_.warnings.push_back(w.str());
      res_.views[i].message = w.str();
      res_.views[i].angle_rejected = true;
      res_.views[i].initial = InitialPoseSource::kGlobal;
      res_.poses[i] = g.transform;
    }
  }

  bool prior_usable(int i) const {
    return res_.axis && has_angle(i) && !res_.views[i].angle_rejected &&
           res_.views[i].initial != InitialPoseSource::kInitialPose &&
           res_.views[i].initial != InitialPoseSource::kGlobal;
  }

  void refine() {
    refine_words_ = {res_.warnings.size(), res_.warnings.size()};
    struct WordsEnd {
      Registrar& self;
      ~WordsEnd() { self.refine_words_.second = self.res_.warnings.size(); }
    } words_end{*this};
    std::vector<int> r = ring();
    const int m = int(r.size());
    if (m < 2) return;
    std::set<std::pair<int, int>> seen;
    std::vector<Pair> pairs;
    for (int k = 0; k < m; ++k)
      for (int s = 1; s <= std::max(1, p_.neighbors); ++s) {
        if (k + s >= m && !p_.loop_closure) continue;
        const int a = r[k], b = r[(k + s) % m];
        if (a == b || seen.count({std::min(a, b), std::max(a, b)})) continue;
        seen.insert({std::min(a, b), std::max(a, b)});
        pairs.push_back({a, b, k + s >= m});
      }
    // Off-turntable views (global against the model) overlap views anywhere
    // in the ring: paired with every other view they overlap by 20 % or more
    // at their global pose. Without any angle, so is a view that overlaps
    // neither neighbour in the list: the capture order need not be the
    // turntable's (files given by a shell glob). (Every view so cost the
    // simulated sessions' prior-free runs 0.07 -> 0.22 mm at the object.)
    std::vector<int> anywhere = off_table_;
    if (m >= 3 && std::none_of(r.begin(), r.end(), [&](int i) { return has_angle(i); })) {
      const double d = 2 * icp_end_;
      const auto overlaps = [&](int a, int b) {
        return overlap(views_[a], views_[b], rigid_inverse(res_.poses[b]) * res_.poses[a], d) >= 0.2;
      };
      for (int k = 0; k < m; ++k) {
        const int i = r[k];
        if (std::find(anywhere.begin(), anywhere.end(), i) != anywhere.end()) continue;
        if (!overlaps(i, r[(k + m - 1) % m]) && !overlaps(i, r[(k + 1) % m])) anywhere.push_back(i);
      }
    }
    for (int i : anywhere)
      for (int j : r) {
        if (i == j || seen.count({std::min(i, j), std::max(i, j)})) continue;
        if (overlap(views_[i], views_[j], rigid_inverse(res_.poses[j]) * res_.poses[i],
                    2 * icp_end_) < 0.2)
          continue;
        seen.insert({std::min(i, j), std::max(i, j)});
        pairs.push_back({j, i, false});
      }
    const double end = icp_end_;
    const double sigma_floor = 0.05 * end;
    std::optional<Vec3d> axis_dir;
    if (res_.axis) axis_dir = res_.axis->direction.normalized();
    std::vector<bool> has_edge(m_.views.size(), false);
    report("refine", 0, std::max(1, p_.rounds));
    for (int round = 0; round < std::max(1, p_.rounds); ++round) {
      std::vector<Eigen::Matrix4d> init;
      for (const Pair& pr : pairs) init.push_back(rigid_inverse(res_.poses[pr.from]) * res_.poses[pr.to]);
      const double start = round == 0 ? p_.icp_start_rel * diag_ : 2 * end;
      const bool last = round + 1 == std::max(1, p_.rounds);
      const std::vector<IcpResult> icp =
          run_pairs(pairs, init, std::max(start, end), end,
                    last ? std::optional<IcpObjective>(p_.final_objective) : std::nullopt,
                    last ? 1.0 : p_.early_convergence_scale);

      std::vector<PoseGraphEdge> edges;
      std::vector<int> edge_pair;  // index into pairs, -1 for prior edges
      const std::size_t first_diag = res_.pairs.size();
      std::fill(has_edge.begin(), has_edge.end(), false);
      for (std::size_t k = 0; k < pairs.size(); ++k) {
        const IcpResult& x = icp[k];
        PairDiagnostics pd;
        pd.from = pairs[k].from;
        pd.to = pairs[k].to;
        pd.round = round;
        pd.loop_closure = pairs[k].loop;
        pd.converged = x.converged;
        pd.fitness = x.fitness;
        pd.inlier_rmse = x.inlier_rmse;
        pd.correspondences = x.correspondences;
        pd.iterations = x.iterations;
        pd.message = x.message;
        if (x.converged) {
          const HessianAnalysis ha =
              analyse_hessian(x.hessian, centroid(views_[pairs[k].from].points), 0.5 * diag_, axis_dir);
          pd.eigen_ratio = ha.ratio;
          pd.degenerate = ha.ratio < p_.degeneracy_ratio && ha.about_axis;
          const double sigma = std::max(x.plane_rmse, sigma_floor);
          PoseGraphEdge e;
          e.from = pairs[k].from;
          e.to = pairs[k].to;
          e.measurement = x.transform;
          e.information = x.hessian / (sigma * sigma);
          edges.push_back(e);
          edge_pair.push_back(int(k));
        }
        res_.pairs.push_back(pd);
      }
      // The turntable prior between consecutive views: weak, it matters only
      // where the shape leaves a direction free.
      if (p_.turntable_prior && res_.axis) {
        Matrix6d info = Matrix6d::Zero();
        const double sa = p_.prior_angle_sigma_deg * M_PI / 180.0;
        const double st = p_.prior_translation_sigma_rel * diag_;
        info.diagonal() << 1 / (sa * sa), 1 / (sa * sa), 1 / (sa * sa), 1 / (st * st), 1 / (st * st),
            1 / (st * st);
        for (int k = 0; k < m; ++k) {
          const int a = r[k], b = r[(k + 1) % m];
          if (a == b || (k + 1 == m && (!p_.loop_closure || m < 3))) continue;
          if (!prior_usable(a) || !prior_usable(b)) continue;
          PoseGraphEdge e;
          e.from = a;
          e.to = b;
          e.measurement = rigid_inverse(turntable_pose(*res_.axis, angle_of(a))) *
                          turntable_pose(*res_.axis, angle_of(b));
          e.information = info;
          edges.push_back(e);
          edge_pair.push_back(-1);
        }
      }
      PoseGraphParams gp;
      gp.fixed_node = r.front();
      // The rigid turntable over the views with an angle (its gauge one of them).
      std::vector<bool> on_table(m_.views.size(), false);
      int table_views = 0;
      // A session without any angle (clouds only) is taken as one turntable
      // ring too: kAuto then keeps the rigid poses only if they fit.
      const bool no_angles = std::none_of(r.begin(), r.end(), [&](int i) { return has_angle(i); });
      if (p_.rigid_turntable != RigidTurntable::kOff)
        for (int i : r)
          if ((has_angle(i) || no_angles) && !res_.views[i].angle_rejected &&
              std::find(off_table_.begin(), off_table_.end(), i) == off_table_.end()) {
            on_table[i] = true;
            if (table_views++ == 0) gp.fixed_node = i;
          }
      const auto solve = [&](const std::vector<PoseGraphEdge>& es) {
        PoseGraphResult free_graph = optimize_pose_graph(res_.poses, es, gp);
        rigid_rejected_ = rigid_used_ = false;
        res_.turntable_groups = 0;
        res_.moved_after_view = -1;
        res_.run_starts.clear();
        split_ = {};
        if (table_views < 3) return free_graph;
        // The rigid solve starts from the free solution and the axis that
        // best explains it (or the session's / estimated axis).
        std::vector<Eigen::Matrix4d> table_poses;
        std::vector<double> table_angles;
        for (int i : r)
          if (on_table[i]) {
            table_poses.push_back(free_graph.poses[i]);
            table_angles.push_back(has_angle(i) ? angle_of(i) : 0.0);
          }
        if (no_angles) table_angles = angles_about_common_axis(table_poses);
        const AxisFitResult fit = calibrate_axis(table_poses, table_angles);
        std::optional<TurntableAxis> start = fit.ok ? std::optional<TurntableAxis>(fit.axis) : res_.axis;
        if (!start) return free_graph;
        // The table views without angle on the line (table_free_) held on it too,
        // each with its own angle; where that does not fit, the angled ones alone.
        std::vector<bool> held = on_table;
        bool with_free = false;
        for (int i : table_free_)
          if (usable_[std::size_t(i)] && !held[std::size_t(i)]) held[std::size_t(i)] = with_free = true;
        // How far a constrained solution moves the `on` views from the free one.
        const auto deviation = [&](const PoseGraphResult& c, const std::vector<bool>& on) {
          double dev_deg = 0, dev = 0;
          for (int i : r) {
            if (!on[i]) continue;
            const Eigen::Matrix4d a = rigid_inverse(free_graph.poses[gp.fixed_node]) * free_graph.poses[i];
            const Eigen::Matrix4d b = rigid_inverse(c.poses[gp.fixed_node]) * c.poses[i];
            dev_deg = std::max(dev_deg, rotation_angle_deg(rigid_inverse(a) * b));
            dev = std::max(dev, ((a - b) * centroid(views_[i].points).homogeneous()).norm());
          }
          return std::make_pair(dev_deg, dev);
        };
        const auto fits = [&](const std::pair<double, double>& d) {
          return d.first <= p_.rigid_max_deviation_deg && d.second <= p_.rigid_max_deviation_rel * diag_;
        };
        PoseGraphResult rigid =
            optimize_turntable_graph(free_graph.poses, es, held, start->point, start->direction, gp);
        auto dev = deviation(rigid, held);
        if (with_free && !fits(dev)) {
          rigid = optimize_turntable_graph(free_graph.poses, es, on_table, start->point, start->direction, gp);
          dev = deviation(rigid, on_table);
        }
        res_.rigid_deviation_deg = dev.first;
        res_.rigid_deviation = dev.second;
        rigid_rejected_ = p_.rigid_turntable == RigidTurntable::kAuto && !fits(dev);
        rigid_used_ = !rigid_rejected_;
        res_.turntable_groups = rigid_used_ ? 1 : 0;
        if (!rigid_rejected_) return rigid;
        // The object moved on the table between two runs of views: each run is
        // held on the one axis with its own base pose, when that fits.
        std::vector<int> order;
        for (int i : r)
          if (on_table[i]) order.push_back(i);
        // Three runs (knocked twice) only where the angles say how each run turns: without
        // them (the turns measured from the free poses themselves) a third base fits the
        // free poses' own errors (the dragon moved twice, registered without angles:
        // 0.44 -> 0.76 deg against the clean session).
        split_ = find_turntable_split(free_graph.poses, order, table_angles, 1e-3 * diag_, no_angles ? 2 : 3);
        if (!split_.found) return free_graph;
        std::vector<int> group(m_.views.size(), 0);
        int run = 0;
        for (int i : order) {
          if (std::find(split_.run_starts.begin(), split_.run_starts.end(), i) != split_.run_starts.end()) ++run;
          group[i] = run;
        }
        PoseGraphResult runs = optimize_turntable_graph(free_graph.poses, es, on_table, start->point,
                                                        start->direction, gp, nullptr, group);
        if (!fits(deviation(runs, on_table))) return free_graph;
        res_.turntable_groups = run + 1;
        res_.moved_after_view = split_.first_after;
        res_.run_starts = split_.run_starts;
        return runs;
      };
      PoseGraphResult g = solve(edges);
      // Edges the optimised graph disagrees with strongly are wrong matches
      // (a symmetric part aligned the wrong way): drop them and solve again.
      // So are turntable prior edges it disagrees with by more than kPriorOutlierSigmas
      // times their sigma, between views that converged pairs hold (an angle a few
      // degrees off, under the wrong-angle check: 6 deg pulled the bottle's eight
      // views 0.49 deg off).
      // (Held: joined by consistent, non-degenerate converged pairs, so that the
      // prior was no group's only link to the others, nor what fixed a slide.)
      UnionFind pair_held(m_.views.size());
      for (std::size_t e = 0; e < edges.size(); ++e)
        if (edge_pair[e] >= 0 && g.edge_rotation_deg[e] <= 2.0 && g.edge_translation[e] <= 3 * end &&
            !res_.pairs[first_diag + std::size_t(edge_pair[e])].degenerate)
          pair_held.unite(edges[e].from, edges[e].to);
      std::vector<PoseGraphEdge> kept;
      std::vector<int> kept_pair;
      for (std::size_t e = 0; e < edges.size(); ++e) {
        if (edge_pair[e] < 0 && g.edge_rotation_deg[e] > kPriorOutlierSigmas * p_.prior_angle_sigma_deg &&
            pair_held.find(edges[e].from) == pair_held.find(edges[e].to))
          continue;
        const bool bad = edge_pair[e] >= 0 &&
                         (g.edge_rotation_deg[e] > 2.0 || g.edge_translation[e] > 3 * end);
        if (bad) {
          PairDiagnostics& pd = res_.pairs[first_diag + edge_pair[e]];
          pd.converged = false;
          pd.message = "inconsistent with the other pairs (" + std::to_string(g.edge_rotation_deg[e]) +
                       " deg, " + std::to_string(res_.mm_per_unit * g.edge_translation[e]) + " mm)";
          continue;
        }
        kept.push_back(edges[e]);
        kept_pair.push_back(edge_pair[e]);
      }
      if (kept.size() != edges.size()) g = solve(kept);
      res_.poses = g.poses;
      res_.rigid_turntable = rigid_used_;
      for (std::size_t e = 0; e < kept.size(); ++e) {
        if (kept_pair[e] < 0) continue;
        PairDiagnostics& pd = res_.pairs[first_diag + kept_pair[e]];
        pd.graph_rotation_deg = g.edge_rotation_deg[e];
        pd.graph_translation = g.edge_translation[e];
        has_edge[kept[e].from] = has_edge[kept[e].to] = true;
      }
      report("refine", round + 1, std::max(1, p_.rounds));
    }
    if (rigid_rejected_) {
      std::ostringstream w;
      w.precision(3);
      w << "the views do not fit one rigid turntable (the rigid solution moves a view " << res_.rigid_deviation_deg
        << " deg / " << res_.mm_per_unit * res_.rigid_deviation << " mm from the free one: did the object shift on the table?); ";
      // Where the object moved: "views[5] (...) and views[6] (...)", and each further move.
      std::string between;
      for (std::size_t k = 0; split_.found && k < split_.run_starts.size(); ++k)
        between += std::string(k ? ", and between " : "") + view_name(m_, std::size_t(split_.run_ends[k])) + " and " +
                   view_name(m_, std::size_t(split_.run_starts[k]));
      const bool several = split_.run_starts.size() > 1;
      if (res_.turntable_groups >= 2)
        w << "the object moved between " << between << ": the views before and after " << (several ? "each move " : "")
          << "are held on the one axis, each run with its own place on the table";
      else if (split_.found)
        w << "the object moved on the table between " << between
          << ": the views before and after each turn about one axis (unexplained motion "
          << res_.mm_per_unit * split_.parts_misfit << " mm RMS) but not together (" << res_.mm_per_unit * split_.whole_misfit
          << " mm), and not as " << split_.run_starts.size() + 1 << " runs on one axis either; the free poses are used";
      else
        w << "the free poses are used";
      res_.warnings.push_back(w.str());
    }
    for (const PairDiagnostics& pd : res_.pairs)
      if (pd.degenerate && pd.round == p_.rounds - 1) res_.degenerate = true;
    if (res_.degenerate) {
      res_.degeneracy_message =
          "shape leaves the rotation about the turntable axis unconstrained (" +
          std::string(p_.turntable_prior && res_.axis ? "held by the turntable angles"
                                                      : "no turntable prior: rotation about it is arbitrary") +
          ")";
    }
    // No pair converged at all: the views overlap nowhere, or too little for ICP. A
    // sparse session (four views 90 degrees apart): each view the turntable placed
    // (the session's or the estimated axis, its commanded angle) stays there, held by
    // its angle alone, where two or more such views land among the others' (within
    // the session size of their median centre); failing them made the run without
    // angles the one kept, which had put two of four views half a turn off by their
    // features. Otherwise the first stays, alone, as the partial result (issue 26's
    // bad input, views 1 m apart: every other view named, exit 3), rather than
    // nothing. Where some pair converged, a view none joins fails (held, a wrong
    // angle or junk would be hidden from the prior check's runs).
    const bool converged_any = std::any_of(r.begin(), r.end(), [&](int i) { return bool(has_edge[i]); });
    std::vector<bool> held(m_.views.size(), false);
    if (!converged_any) {
      std::vector<Vec3d> placed;
      for (int i : r)
        placed.push_back((res_.poses[std::size_t(i)] * centroid(views_[std::size_t(i)].points).homogeneous()).head<3>());
      const std::vector<bool> among = views_at_table(placed, diag_);
      for (std::size_t k = 0; k < r.size(); ++k) held[std::size_t(r[k])] = among[k] && prior_usable(r[k]);
      if (std::count(held.begin(), held.end(), true) < 2) std::fill(held.begin(), held.end(), false);
    }
    const bool none = !converged_any && std::none_of(held.begin(), held.end(), [](bool h) { return h; });
    for (int i : r)
      if (!has_edge[i] && !held[std::size_t(i)] && !(none && i == r.front()))
        fail(i, "no overlap with its neighbouring views (every ICP pair failed)");
    if (none && r.size() > 1)
      res_.warnings.push_back("no two views overlap: the result is " + view_name(m_, std::size_t(r.front())) +
                              " alone");
  }

  // Views by name: each of a group of up to six, else the first five and how many
  // more ("views[4] (...) to views[11] (...) (2 views)" read as a range of eight).
  std::string group_name(const std::vector<int>& g) const {
    if (g.size() == 1) return view_name(m_, std::size_t(g.front()));
    std::string out;
    const std::size_t shown = g.size() <= 6 ? g.size() : 5;
    for (std::size_t k = 0; k < shown; ++k) {
      if (k > 0) out += k + 1 == g.size() ? " and " : ", ";
      out += view_name(m_, std::size_t(g[k]));
    }
    if (shown < g.size()) out += " and " + std::to_string(g.size() - shown) + " more";
    return out + " (" + std::to_string(g.size()) + " views)";
  }

  // Registered views that no converged pair of the last round joins to the
  // largest group: their place relative to it rests on the turntable angles
  // alone (or, without angles, on nothing measured between them). Said, per
  // group, so that a coverage gap is not mistaken for a measured fit.
  void warn_unlinked() {
    std::size_t largest = 0;
    const std::vector<std::vector<int>> groups = linked_groups(&largest);
    if (groups.size() < 2) return;
    for (std::size_t k = 0; k < groups.size(); ++k) {
      if (k == largest) continue;
      const std::vector<int>& g = groups[k];
      const bool angles = std::all_of(g.begin(), g.end(), [&](int i) {
        return has_angle(i) && !res_.views[std::size_t(i)].angle_rejected;
      });
      std::ostringstream w;
      w << group_name(g) << " overlap none of the other views: "
        << (angles ? "held to them by the turntable angles alone (a gap in the coverage?)"
                   : "their place relative to them is not measured");
      res_.warnings.push_back(w.str());
      res_.unlinked_views += int(g.size());
    }
  }

  /// PairResidual for the last round's converged pairs, under the refined
  /// poses and, where both views have one, under the reference poses.
  void pair_residuals() {
    if (res_.pairs.empty()) return;
    const int last = res_.pairs.back().round;
    const double max_distance = icp_end_;
    const double min_dot = std::cos(p_.icp.max_normal_angle_deg * M_PI / 180.0);
    std::vector<const PairDiagnostics*> pairs;
    for (const PairDiagnostics& pd : res_.pairs)
      if (pd.round == last && pd.converged && usable_[pd.from] && usable_[pd.to]) pairs.push_back(&pd);
    res_.pair_residuals.resize(pairs.size());
    tbb::parallel_for(std::size_t(0), pairs.size(), [&](std::size_t k) {
      const PairDiagnostics& pd = *pairs[k];
      PairResidual& out = res_.pair_residuals[k];
      out.from = pd.from;
      out.to = pd.to;
      const PreparedView& a = views_[pd.from];
      const PreparedView& b = views_[pd.to];
      std::tie(out.rmse, out.matches) =
          pair_plane_rmse(a, b, res_.poses[pd.from], res_.poses[pd.to], max_distance, min_dot);
      const auto& ra = m_.views[pd.from].reference_pose;
      const auto& rb = m_.views[pd.to].reference_pose;
      if (ra && rb) out.reference_rmse = pair_plane_rmse(a, b, *ra, *rb, max_distance, min_dot).first;
    });
    if (res_.pair_residuals.empty()) return;
    double ours = 0, reference = 0;
    bool all_reference = true;
    for (const PairResidual& pr : res_.pair_residuals) {
      ours += pr.rmse;
      if (pr.reference_rmse) reference += *pr.reference_rmse;
      else all_reference = false;
    }
    const double n = double(res_.pair_residuals.size());
    res_.mean_pair_rmse = ours / n;
    if (all_reference) res_.mean_reference_pair_rmse = reference / n;
  }

  // The share of `points`, moved by X, where `free`'s sights saw through, beyond the
  // margin for `noise_rms` (kSeenMargin registration voxels or kSeenNoise times the
  // noise, whichever is larger); `skip`: a sight left out (FreeSpace::seen_through).
  double seen_share(const FreeSpace& free, const std::vector<Vec3f>& points, const Eigen::Matrix4d& X,
                    double noise_rms, int skip = -1) const {
    const double voxel = std::max(p_.voxel_rel, 1e-4) * diag_;
    return free.seen_through(points, X, std::max(kSeenMargin * voxel, kSeenNoise * noise_rms), voxel,
                             kSeenGrow * diag_, skip);
  }

  // Each registered view (sensor known) against the free space of the other
  // registered views under the current poses: ViewDiagnostics::seen_through.
  // Returns the largest (0 where none is known).
  double most_seen_now() {
    const std::size_t n = m_.views.size();
    for (ViewDiagnostics& v : res_.views) v.seen_through.reset();
    FreeSpace free;
    std::vector<int> sight(n, -1);
    for (std::size_t i = 0; i < n; ++i)
      if (usable_[i] && views_[i].viewpoint_at_origin) sight[i] = free.add(views_[i].points, res_.poses[i]);
    if (free.empty()) return 0;
    std::vector<double> rms;
    for (const PairDiagnostics& pd : res_.pairs)
      if (pd.converged && pd.round == res_.pairs.back().round) rms.push_back(pd.inlier_rmse);
    const double noise_rms = rms.empty() ? 0.0 : median_of(rms);
    std::vector<std::size_t> todo;
    for (std::size_t i = 0; i < n; ++i)
      if (sight[i] >= 0) todo.push_back(i);
    tbb::parallel_for(std::size_t(0), todo.size(), [&](std::size_t k) {
      const std::size_t i = todo[k];
      res_.views[i].seen_through = seen_share(free, views_[i].points, res_.poses[i], noise_rms, sight[i]);
    });
    double most = 0;
    for (std::size_t i : todo) most = std::max(most, *res_.views[i].seen_through);
    return most;
  }

  void finish() {
    const std::size_t n = m_.views.size();
    for (std::size_t i = 0; i < n; ++i) {
      if (usable_[i]) res_.views[i].registered = true;
      else res_.failed_views.push_back(int(i));
    }
    warn_unlinked();
    most_seen_now();
    // Errors against the reference poses, relative to the first registered view with one.
    int anchor = -1;
    for (std::size_t i = 0; i < n && anchor < 0; ++i)
      if (usable_[i] && m_.views[i].reference_pose) anchor = int(i);
    std::vector<double> rot, trans, object_trans;
    if (anchor >= 0) {
      for (std::size_t i = 0; i < n; ++i) {
        if (!usable_[i] || !m_.views[i].reference_pose) continue;
        const auto [er, et] = relative_pose_error(res_.poses[anchor], res_.poses[i],
                                                  *m_.views[anchor].reference_pose,
                                                  *m_.views[i].reference_pose);
        res_.views[i].rotation_error_deg = er;
        res_.views[i].translation_error = et;
        rot.push_back(er);
        trans.push_back(et);
        const Eigen::Vector4d c = centroid(views_[i].points).homogeneous();
        const Eigen::Matrix4d ra = rigid_inverse(res_.poses[anchor]) * res_.poses[i];
        const Eigen::Matrix4d rb = rigid_inverse(*m_.views[anchor].reference_pose) * *m_.views[i].reference_pose;
        const double eo = ((ra - rb) * c).norm();
        res_.views[i].object_translation_error = eo;
        object_trans.push_back(eo);
      }
    }
    res_.views_with_reference = int(rot.size());
    if (!rot.empty()) {
      res_.max_rotation_error_deg = *std::max_element(rot.begin(), rot.end());
      res_.max_translation_error = *std::max_element(trans.begin(), trans.end());
      res_.median_rotation_error_deg = median_of(rot);
      res_.median_translation_error = median_of(trans);
      res_.max_object_translation_error = *std::max_element(object_trans.begin(), object_trans.end());
      res_.median_object_translation_error = median_of(object_trans);
    }
    pair_residuals();
    const int to_merge = int(std::count(usable_.begin(), usable_.end(), true));
    int merged = 0;
    report("merge", 0, to_merge);
    // Merge: colours only when every merged view has them (a cloud's colours are all or none).
    bool colours = true;
    for (std::size_t i = 0; i < n; ++i)
      if (usable_[i] && !views_[i].full.has_colours()) colours = false;
    std::vector<std::size_t> merging;
    for (std::size_t i = 0; i < n; ++i)
      if (usable_[i]) merging.push_back(i);
    std::vector<Cloud> moved(merging.size());
    std::vector<double> spacings(p_.fuse && !(p_.fuse_distance > 0) ? merging.size() : 0);
    std::mutex progress;
    // The views side by side (each one's index build is serial), in their order in `moved`.
    tbb::parallel_for(std::size_t(0), merging.size(), [&](std::size_t m) {
      const std::size_t i = merging[m];
      Cloud c = std::move(views_[i].full);  // not needed after the merge: no second copy of every view
      if (!spacings.empty()) spacings[m] = median_spacing(c.points);
      if (!colours) c.colours.clear();
      if (!c.has_normals() && p_.merge_normals) {
        if (views_[i].full_normals.size() == c.size() && !c.empty()) {
          c.normals = std::move(views_[i].full_normals);
          orient_normals_towards(c.points, c.normals, views_[i].viewpoint, true);
        } else {
          const PointIndex index(c.points);
          c.normals = pca_normals(index, p_.normal_neighbors, views_[i].viewpoint);
        }
      } else if (c.has_normals()) {
        // The view's own normals, turned to face the sensor (outwards for a single view).
        const Vec3f& eye = views_[i].viewpoint;
        for (std::size_t k = 0; k < c.size(); ++k)
          if (c.normals[k].dot(eye - c.points[k]) < 0) c.normals[k] = -c.normals[k];
      }
      transform_cloud(c, res_.poses[i]);
      moved[m] = std::move(c);
      const std::lock_guard<std::mutex> lock(progress);
      report("merge", ++merged, to_merge);
    });
    // Concatenation, or fusion of the overlaps; either way attributes are kept
    // only when every view has them.
    if (p_.fuse) res_.fuse_distance = p_.fuse_distance > 0 ? p_.fuse_distance : median_of(spacings);
    res_.merged = fuse_clouds(moved, res_.fuse_distance, p_.fuse ? &res_.fuse : nullptr);
  }

  const std::vector<Cloud>& clouds_;
  const SessionManifest& m_;
  const SessionManifest* given_ = nullptr;  // as_given
  std::optional<TurntableAxis> calibrated_;  // with_calibrated_axis
  const RegistrationParams& p_;
  const RegistrationCallback& cb_;
  RegistrationResult res_;
  std::vector<PreparedView> views_;
  std::vector<std::vector<std::unique_ptr<FeatureView>>> feats_;  // per view, per feature scale
  std::vector<int> off_table_;  // posed by global registration against the model
  std::vector<std::unique_ptr<FeatureView>> colour_feats_;  // colour_features_of
  bool confident_chain_ = false;  // global_poses' second chain (see there)
  // While global_poses aligns a view without an angle that sits between views with
  // angles in capture order: the pose its angle would give, interpolated from theirs,
  // and how far (degrees) a pose may turn from it to count as near (expected_pose).
  // While check_angles aligns a view whose angle looks wrong: its angle's pose, and
  // kSuspectNearDeg.
  std::optional<std::pair<Eigen::Matrix4d, double>> expected_;
  bool expected_suspect_ = false;  // expected_ is a suspect angle's pose (check_angles)
  bool chained_ = false;          // global_poses chained the views (nothing was posed)
  bool weak_fit_ = false;         // and took some view at a fit below kConfidentFitness
  std::vector<int> unplaced_;   // views without an angle that global registration could not place
  // Where the last refine()'s warnings are in res_.warnings (first, one past the last).
  std::pair<std::size_t, std::size_t> refine_words_{0, 0};
  int moved_from_ = -1;
  std::vector<double> angle_shift_;  // per view, degrees (angle_of): empty until a run is moved
  std::vector<int> ring_order_;      // ring()'s order where not the capture order (place_on_table_axis)
  std::vector<int> chain_missed_;    // views the prior-free chain failed (global_poses)
  std::vector<int> table_free_;      // table views without angle on the table's line (global_poses)
  bool rigid_rejected_ = false;  // kAuto kept the free poses in the last solve
  bool rigid_used_ = false;      // the last solve's poses are the rigid ones
  TurntableSplit split_;  // the last solve's split of the table views into two runs (found: a move)
  std::vector<bool> usable_;
  double diag_ = 0;
  std::vector<std::unique_ptr<ColourModel>> own_colours_;  // own_colours
  std::map<std::pair<int, int>, GlobalAlign> pair_aligns_;  // pair_align
  double icp_end_ = 0;  // final ICP max correspondence distance (final_distance)
};

}  // namespace

namespace {

// Registered views among those that can be the object on the table: a view
// whose points lie further than the session size from the others' (the median
// centroid, in the scanner frame, where a turntable keeps the object) may align
// as a shape without angles, but is no view of this bench's object.
int registered_count(const RegistrationResult& r, const std::vector<bool>& at_table) {
  int n = 0;
  for (std::size_t i = 0; i < r.views.size(); ++i) n += r.views[i].registered && at_table[i];
  return n;
}

// Registered views (at the table) in the largest group that the last round's
// converged pairs join: the views whose places relative to each other are
// measured, not held by the angles alone (warn_unlinked names the rest).
std::vector<int> linked_group(const RegistrationResult& r, const std::vector<bool>& at_table) {
  std::map<int, std::vector<int>> groups;
  const int last = r.pairs.empty() ? -1 : r.pairs.back().round;
  UnionFind uf(r.views.size());
  for (const PairDiagnostics& pd : r.pairs)
    if (pd.round == last && pd.converged && r.views[std::size_t(pd.from)].registered &&
        r.views[std::size_t(pd.to)].registered)
      uf.unite(pd.from, pd.to);
  std::vector<int> best;
  for (std::size_t i = 0; i < r.views.size(); ++i)
    if (r.views[i].registered && at_table[i]) {
      std::vector<int>& g = groups[uf.find(int(i))];
      g.push_back(int(i));
      if (g.size() > best.size()) best = g;
    }
  return best;
}

// Whether run `b` places the views of `group` where run `a` does, relative to
// each other: within kAgreeDeg, and within kAgreeAtObject of the session size
// at each view's centroid (`centres`, in its scanner frame).
constexpr double kAgreeDeg = 2.0;
constexpr double kAgreeAtObject = 0.02;
// The largest share of a registered view's points that its pose puts where the
// other views saw through (ViewDiagnostics::seen_through); 0 where none is known.
double most_seen_through(const RegistrationResult& r) {
  double most = 0;
  for (const ViewDiagnostics& v : r.views)
    if (v.registered && v.seen_through) most = std::max(most, *v.seen_through);
  return most;
}

// "views[1] (a.ply), views[4] (b.ply)": the views named, in the given order.
std::string view_list(const SessionManifest& m, const std::vector<int>& views) {
  std::string out;
  for (std::size_t k = 0; k < views.size(); ++k) out += (k ? ", " : "") + view_name(m, std::size_t(views[k]));
  return out;
}

// A warning naming the registered views over kRunSeenThrough with their shares,
// where there are any: their poses may be on a near twin of their place. `when`:
// which runs said so.
void name_seen_through(RegistrationResult& r, const SessionManifest& m, const char* when) {
  std::string names;
  for (std::size_t i = 0; i < r.views.size(); ++i)
    if (r.views[i].registered && r.views[i].seen_through.value_or(0) > kRunSeenThrough)
      names += (names.empty() ? "" : ", ") + view_name(m, i) + " (" +
               std::to_string(std::lround(100 * *r.views[i].seen_through)) + " %)";
  if (!names.empty())
    r.warnings.push_back(names + ": placed where the other views saw through, " + when +
                         "; their poses may be wrong (a near twin of their place?)");
}

bool runs_agree(const RegistrationResult& a, const RegistrationResult& b, const std::vector<int>& group,
                const std::vector<Vec3d>& centres) {
  if (group.empty()) return true;
  const int g0 = group.front();
  if (!b.views[std::size_t(g0)].registered) return false;
  for (int i : group) {
    if (!b.views[std::size_t(i)].registered) return false;
    const Eigen::Matrix4d ra = rigid_inverse(a.poses[std::size_t(g0)]) * a.poses[std::size_t(i)];
    const Eigen::Matrix4d rb = rigid_inverse(b.poses[std::size_t(g0)]) * b.poses[std::size_t(i)];
    if (rotation_angle_deg(rigid_inverse(ra) * rb) > kAgreeDeg) return false;
    const Vec3d& c = centres[std::size_t(i)];
    if (c.allFinite() && ((ra - rb) * c.homogeneous()).norm() > kAgreeAtObject * a.diagonal) return false;
  }
  return true;
}

int linked_count(const RegistrationResult& r, const std::vector<bool>& at_table) {
  return int(linked_group(r, at_table).size());
}

// Each view's centroid of its finite points, in its scanner frame (NaN for a
// view without any).
std::vector<Vec3d> view_centres(const std::vector<Cloud>& clouds) {
  std::vector<Vec3d> c(clouds.size(), Vec3d::Constant(std::nan("")));
  for (std::size_t i = 0; i < clouds.size(); ++i) {
    Vec3d sum = Vec3d::Zero();
    std::size_t k = 0;
    for (const Vec3f& p : clouds[i].points)
      if (p.allFinite()) sum += p.cast<double>(), ++k;
    if (k) c[i] = sum / double(k);
  }
  return c;
}


// Signs that the prior misled the run: the views refused one rigid turntable, a
// view with points failed, or a commanded angle was rejected.
bool prior_suspect(const RegistrationResult& r, const RegistrationParams& p, const std::vector<bool>& at_table) {
  if (p.rigid_turntable == RigidTurntable::kAuto && !r.rigid_turntable && r.rigid_deviation_deg > 0) return true;
  for (const ViewDiagnostics& v : r.views)
    if (v.angle_rejected) return true;
  for (std::size_t i = 0; i < r.views.size(); ++i)
    if (!r.views[i].registered && r.views[i].registration_points >= 6 && at_table[i]) return true;
  return false;
}

std::string run_summary(const char* name, const RegistrationResult& r, const std::vector<bool>& at_table) {
  std::ostringstream o;
  o.precision(3);
  const int reg = registered_count(r, at_table), linked = linked_count(r, at_table);
  o << name << ": " << reg << " of " << r.views.size() << " views";
  if (linked < reg) o << " (" << linked << " joined by pairs)";
  o << ", pair residual " << r.mm_per_unit * r.mean_pair_rmse << " mm";
  const double seen = most_seen_through(r);
  if (seen > kSeenClear) o << ", a view " << std::lround(100 * seen) << " % where the others saw through";
  return o.str();
}

}  // namespace

namespace {

// The views with a wrong angle at the end of the session (capture order, among
// the views with an angle and a prior-free pose: at least three, up to the last
// one) that share one error within `tolerance_deg` of the last one's: the object
// turned on the table before them (a second pass), not that many wrong angles.
// Only a run to the end: a move leaves every later view moved, so a run that an
// agreeing view follows is wrong angles (regroup() would move the views after
// it too). Its error is the mean of theirs.
struct MovedRun {
  std::vector<int> views;  // ascending
  double error_deg = 0;
};
MovedRun moved_run(const AnglePriorFit& fit, const SessionManifest& manifest, double tolerance_deg) {
  const auto wrap = [](double a) { return a - 360.0 * std::round(a / 360.0); };
  MovedRun out;
  std::vector<int> run;
  double last = 0;
  for (std::size_t k = manifest.views.size(); k-- > 0;) {
    if (!manifest.views[k].angle_deg || !fit.residual_deg[k]) continue;
    const bool wrong = std::find(fit.wrong.begin(), fit.wrong.end(), int(k)) != fit.wrong.end();
    if (!wrong) break;
    if (run.empty()) last = *fit.residual_deg[k];
    else if (std::abs(wrap(*fit.residual_deg[k] - last)) > tolerance_deg) break;
    run.push_back(int(k));
  }
  if (run.size() < 3) return out;
  double sum = 0;
  for (int i : run) sum += wrap(*fit.residual_deg[std::size_t(i)] - last);
  out.views.assign(run.rbegin(), run.rend());
  out.error_deg = wrap(last + sum / double(run.size()));
  return out;
}

}  // namespace

double mm_per_unit(const SessionManifest& manifest) { return manifest.units == "mm" ? 1.0 : 1000.0; }

RegistrationParams in_session_units(const RegistrationParams& params, const SessionManifest& manifest) {
  RegistrationParams p = params;
  const double per_metre = 1000 / mm_per_unit(manifest);  // session units in a metre
  p.fuse_distance *= per_metre;
  p.icp.coloured_reference_distance *= per_metre;
  p.icp.convergence_translation *= per_metre;
  p.icp.units_per_metre *= per_metre;
  return p;
}

namespace {

// Views whose points are the same as an earlier view's (a scan copied under another
// name, recorded twice): one warning per earlier view that has copies. Said, not
// refused (import does the same): the user may mean it.
std::vector<std::string> same_scans(const std::vector<Cloud>& clouds, const SessionManifest& manifest) {
  std::vector<std::string> out;
  std::vector<bool> copy(clouds.size(), false);
  for (std::size_t j = 0; j < clouds.size(); ++j) {
    if (copy[j] || clouds[j].empty()) continue;
    std::vector<std::size_t> same;
    for (std::size_t i = j + 1; i < clouds.size(); ++i)
      if (!copy[i] && clouds[i].points.size() == clouds[j].points.size() && clouds[i].points == clouds[j].points) {
        copy[i] = true;
        same.push_back(i);
      }
    if (same.empty()) continue;
    std::string w;
    for (std::size_t k = 0; k < same.size(); ++k)
      w += (k == 0 ? "" : k + 1 == same.size() ? " and " : ", ") + view_name(manifest, same[k]);
    w += (same.size() == 1 ? " has" : " have") + std::string(" the same points as ") + view_name(manifest, j) +
         ": the same scan recorded twice?";
    out.push_back(std::move(w));
  }
  return out;
}

}  // namespace

// register_views without the same-scan warnings.
// Views registered in both runs that `b` places more than 90 deg from where `a`
// does, the two runs' frames matched at the view that agrees with the most others
// (within 10 deg).
static std::vector<int> half_turn_apart(const RegistrationResult& a, const RegistrationResult& b) {
  const std::size_t n = std::min(a.poses.size(), b.poses.size());
  std::vector<int> both;
  for (std::size_t i = 0; i < n && i < a.views.size() && i < b.views.size(); ++i)
    if (a.views[i].registered && b.views[i].registered) both.push_back(int(i));
  const auto turn = [&](int anchor, int j) {
    const Eigen::Matrix4d ra = rigid_inverse(a.poses[std::size_t(anchor)]) * a.poses[std::size_t(j)];
    const Eigen::Matrix4d rb = rigid_inverse(b.poses[std::size_t(anchor)]) * b.poses[std::size_t(j)];
    return rotation_angle_deg(Eigen::Matrix4d(rigid_inverse(ra) * rb));
  };
  int best = -1;
  std::size_t agree_best = 0;
  for (int k : both) {
    std::size_t agree = 0;
    for (int j : both) agree += turn(k, j) < 10;
    if (agree > agree_best) agree_best = agree, best = k;
  }
  std::vector<int> out;
  if (best < 0) return out;
  for (int j : both)
    if (turn(best, j) > 90) out.push_back(j);
  return out;
}

static RegistrationResult register_views_checked(const std::vector<Cloud>& clouds, const SessionManifest& manifest,
                                                 const RegistrationParams& given,
                                                 const RegistrationCallback& progress) {
  // The profile's absolute lengths are in metres; the views in the session's units.
  const RegistrationParams params = in_session_units(given, manifest);
  if (clouds.size() != manifest.views.size())
    throw InvalidInput("registration: " + std::to_string(clouds.size()) + " clouds for " +
                       std::to_string(manifest.views.size()) + " views");
  if (manifest.views.empty()) throw InvalidInput("registration: the session has no views");
  if (params.global_extra_seeds < 0) throw InvalidInput("registration: global_extra_seeds must be >= 0");
  for (double r : params.global_extra_radii)
    if (!(r > 0) || !std::isfinite(r))
      throw InvalidInput("registration: global_extra_radii must be positive and finite");
  const std::size_t n = manifest.views.size();
  RegistrationResult with = Registrar(clouds, manifest, params, progress).run();
  for (std::size_t i = 0; i < n; ++i)
    if (manifest.views[i].angle_deg && !manifest.views[i].initial_pose)
      with.views[i].prior = with.views[i].angle_rejected ? PriorUse::kRejected : PriorUse::kUsed;
  const int with_angles = int(std::count_if(manifest.views.begin(), manifest.views.end(),
                                            [](const ViewRecord& v) { return v.angle_deg.has_value(); }));
  if (!params.prior_check || with_angles < 2 || !params.global_registration) {
    name_seen_through(with, manifest, "with no other run to compare");
    return with;
  }
  const std::vector<Vec3d> centres = view_centres(clouds);
  const std::vector<bool> at_table = views_at_table(centres, with.diagonal);
  // Views held to the rest by the angles alone: a gap in the coverage, or the
  // object moved where no angle check could see it (a whole run of views moved
  // together agrees with itself). Only the run without angles tells which; such
  // a run alone is compared by the rule below (joined views), nothing else.
  // (So is a run that puts a view where the others saw through.)
  const bool suspect = prior_suspect(with, params, at_table) || most_seen_through(with) > kRunSeenThrough;
  const bool only_unlinked = !suspect && with.unlinked_views > 0;
  if (!suspect && !only_unlinked) return with;

  // The same views without any angle (or axis): what the data says alone.
  SessionManifest bare = manifest;
  bare.axis.reset();
  for (ViewRecord& v : bare.views) v.angle_deg.reset();
  // The extra runs report their stages under their own names ("without angles:
  // prepare", ...): a progress display sees each stage once.
  const auto named = [&](const char* run) -> RegistrationCallback {
    if (!progress) return {};
    return [&progress, run](const RegistrationProgress& p) {
      RegistrationProgress q = p;
      q.stage = std::string(run) + ": " + p.stage;
      progress(q);
    };
  };
  const RegistrationCallback free_progress = named("without angles");
  RegistrationResult free = Registrar(clouds, bare, params, free_progress).with_calibrated_axis(manifest.axis).run();
  std::vector<bool> reg(n);
  for (std::size_t i = 0; i < n; ++i) reg[i] = free.views[i].registered;
  const std::optional<Vec3d> known =
      manifest.axis ? std::optional<Vec3d>(manifest.axis->direction) : std::nullopt;
  const AnglePriorFit fit = fit_angle_prior(free.poses, reg, manifest, params.wrong_angle_deg, known);

  // The prior corrected by the fit: the session-wide convention fixed, the
  // views whose angle disagrees registered without it.
  std::optional<RegistrationResult> corrected;
  // (Nothing new when the only wrong angles are those the run with the prior
  // rejected already.)
  const bool news = std::any_of(fit.wrong.begin(), fit.wrong.end(), [&](int i) { return !with.views[i].angle_rejected; });
  if (!only_unlinked && fit.ok && (news || !fit.convention.empty())) {
    const MovedRun moved = moved_run(fit, manifest, params.wrong_angle_deg);
    SessionManifest m = manifest;
    for (std::size_t i = 0; i < n; ++i) {
      ViewRecord& v = m.views[i];
      if (!v.angle_deg) continue;
      // Every angled view from the run's first on (those between without a
      // prior-free pose included: the object had moved for them too).
      const bool in_run = !moved.views.empty() && int(i) >= moved.views.front();
      if (in_run) v.angle_deg = fit.sign * fit.scale * *v.angle_deg + moved.error_deg;
      else if (std::find(fit.wrong.begin(), fit.wrong.end(), int(i)) != fit.wrong.end()) v.angle_deg.reset();
      else v.angle_deg = fit.sign * fit.scale * *v.angle_deg;
    }
    const RegistrationCallback corrected_progress = named("corrected angles");
    corrected = Registrar(clouds, m, params, corrected_progress, moved.views.empty() ? -1 : moved.views.front())
                    .as_given(manifest)
                    .run();
    if (!moved.views.empty()) {
      std::ostringstream w;
      w.precision(3);
      w << "the angles of " << view_name(manifest, std::size_t(moved.views.front())) << " to "
        << view_name(manifest, std::size_t(moved.views.back())) << " share one error of " << moved.error_deg
        << " deg: the object turned on the table before them; their angles were corrected by it";
      corrected->warnings.push_back(w.str());
    }
    for (std::size_t i = 0; i < n; ++i) {
      if (!manifest.views[i].angle_deg || manifest.views[i].initial_pose) continue;
      ViewDiagnostics& d = corrected->views[i];
      const bool in_run = !moved.views.empty() && int(i) >= moved.views.front();
      d.prior = !m.views[i].angle_deg || d.angle_rejected ? PriorUse::kRejected
                : fit.convention.empty() && !in_run        ? PriorUse::kUsed
                                                           : PriorUse::kCorrected;
    }
  }

  // Never worse than no prior: more registered views first, then the pair residual.
  // `by_links`: then more views joined by converged pairs (linked_group), before the
  // residual, which over fewer pairs is no measure.
  const auto better = [&](const RegistrationResult& a, const RegistrationResult& b, double slack,
                          bool by_links = false) {
    const int ca = registered_count(a, at_table), cb = registered_count(b, at_table);
    if (ca != cb) return ca > cb;
    if (by_links) {
      const int la = linked_count(a, at_table), lb = linked_count(b, at_table);
      if (la != lb) return la > lb;
    }
    return a.mean_pair_rmse <= slack * b.mean_pair_rmse;
  };
  // Where the run without angles fits the angles nowhere, it may be the wrong one (on
  // a near-symmetric object without colours its chain lands groups of views on turned
  // twins: the fandisk's eight views with angles of the wrong sign, five of them 99 deg
  // off): the conventions a commanded list is mistaken in (the opposite sign, step
  // indices for degrees) are tried as hypotheses, each a run of its own, the best
  // kept as the corrected prior if it beats the run as given (below), in turn; the
  // first that joins every view by pairs ends the search.
  if (!corrected && !only_unlinked && !fit.ok) {
    const std::vector<double> signs = manifest.axis ? std::vector<double>{1.0, -1.0} : std::vector<double>{1.0};
    // Every view at the table that could register at all joined: nothing to gain.
    int could = 0;
    for (std::size_t i = 0; i < n; ++i) could += at_table[i] && with.views[i].registration_points >= 6;
    const auto all_joined = [&] { return corrected && linked_count(*corrected, at_table) >= could; };
    std::string name;
    for (double sign : signs) {
      for (double scale : angle_scales(manifest)) {
        if (sign == 1 && scale == 1) continue;
        SessionManifest hm = manifest;
        for (ViewRecord& v : hm.views)
          if (v.angle_deg) v.angle_deg = sign * scale * *v.angle_deg;
        const char* run = sign < 0 && scale != 1 ? "angles of the opposite sign as steps"
                          : sign < 0             ? "angles of the opposite sign"
                                                 : "angles as steps";
        RegistrationResult h = Registrar(clouds, hm, params, named(run)).as_given(manifest).run();
        // Taken only where the angles so fit the poses registered with them as
        // they are (a run that registers more views with angles still wrong is no
        // convention found).
        std::vector<bool> h_reg(n);
        for (std::size_t i = 0; i < n; ++i) h_reg[i] = h.views[i].registered;
        const AnglePriorFit own = fit_angle_prior(h.poses, h_reg, hm, params.wrong_angle_deg, known);
        if (!own.ok || !own.convention.empty()) continue;
        if (!better(h, corrected ? *corrected : with, 0.95, true)) continue;
        corrected = std::move(h);
        name = convention_name(sign, scale);
        for (std::size_t i = 0; i < n; ++i)
          if (manifest.views[i].angle_deg && !manifest.views[i].initial_pose)
            corrected->views[i].prior = corrected->views[i].angle_rejected ? PriorUse::kRejected : PriorUse::kCorrected;
        if (all_joined()) break;
      }
      if (all_joined()) break;
    }
    if (corrected)
      corrected->warnings.push_back("the commanded angles fit the scans with " + name + " (tried as a hypothesis: " +
                                    run_summary("corrected", *corrected, at_table) + "; " +
                                    run_summary("as given", with, at_table) + ")");
  }
  RegistrationResult* prior_best = &with;
  // The corrected prior replaces the given one when it registers more views, joins
  // more of them by pairs, or fits clearly better (5 %): where both agree, the run as
  // given is kept. (The bottle's eight views with angles of the wrong sign: the run
  // as given held half of them by the angles alone, 0.342 mm over its few pairs; the
  // corrected run joined all eight at 0.344 mm, and the run as given was kept, four
  // views 90-180 deg off.) Not so against the run without angles: that one may join
  // more views by placing some on a near-symmetric object's turned twin (below).
  // Where the angles fit only under a convention (step indices, the opposite sign),
  // every angle as given is wrong: the corrected run is kept unless the run as given
  // registers or joins more, or fits clearly better. (The fandisk's 24 views with step
  // indices: the run as given, its wrong angles pulling, bent half the ring 2.5 deg
  // off and refused one rigid turntable, 0.395 mm; the corrected run 0.397 mm.)
  const bool convention = fit.ok && !fit.convention.empty();
  // What the views saw comes first: a run that puts a view where the others saw
  // through (ViewDiagnostics::seen_through over kRunSeenThrough) loses to one that
  // puts none of them near it (kSeenClear), whatever it registers or joins.
  // (The issue's own session with the object turned on the table and scanned
  // again: runs that join every view by pairs, two views half turned on the
  // fandisk's near twin, against a run whose views all agree with each other.)
  // (A run that registers fewer than half the other's views is no measure: with few
  // views there is little to contradict.)
  const auto overrules = [&](const RegistrationResult& a, const RegistrationResult& b) {
    return most_seen_through(a) <= kSeenClear && most_seen_through(b) > kRunSeenThrough &&
           2 * registered_count(a, at_table) >= registered_count(b, at_table);
  };
  if (corrected && (overrules(*corrected, with) ||
                    (!overrules(with, *corrected) &&
                     (convention ? !better(with, *corrected, 0.95, true) : better(*corrected, with, 0.95, true)))))
    prior_best = &*corrected;
  // A run without angles that joins, by converged pairs, more views than the
  // prior's does: the prior held views apart from the rest where the data joins
  // them (the object moved, more than once perhaps). Where the data joins no
  // more (a gap in the coverage), the prior's run is compared as before.
  // ...and that agrees with the prior's run where that one measured (its joined
  // views): a run without angles that links more views by placing some of them
  // wrong (a half turn of a near-symmetric object) contradicts the pairs the
  // prior's run did converge.
  // The free run's joined group must hold the prior's: a larger group of views
  // elsewhere (joined among themselves, placed wrong as a whole) is no measure.
  const std::vector<int> prior_linked = linked_group(*prior_best, at_table);
  const std::vector<int> free_linked = linked_group(free, at_table);
  const bool holds = std::includes(free_linked.begin(), free_linked.end(), prior_linked.begin(), prior_linked.end());
  // (Two views joined by one pair are no measure against the turntable: on a sparse
  // session of a near-symmetric object that pair converges half a turn off.)
  // (Nor where the run without angles confirms every commanded angle, as given: it
  // joined the views where the angles had put them, and the run as given stands. The bottle's four views 90 deg apart, placed about the calibrated
  // axis without their angles: within 0.14 deg of them, and the run as given, held by
  // the angles where no pair converged, is the more accurate.)
  // (Each view with an angle fitted within the tolerance, and the run with the angles
  // placing the views the run without them joined where that one does: a slide on the
  // table fits every angle, and shows there.)
  bool angles_confirmed = fit.ok && fit.convention.empty() && fit.wrong.empty();
  for (std::size_t i = 0; i < n && angles_confirmed; ++i) {
    const ViewRecord& v = manifest.views[i];
    if (!v.angle_deg || !std::isfinite(*v.angle_deg) || v.initial_pose) continue;
    angles_confirmed = i < fit.residual_deg.size() && fit.residual_deg[i] &&
                       std::abs(*fit.residual_deg[i]) <= params.wrong_angle_deg;
  }
  angles_confirmed = angles_confirmed && runs_agree(*prior_best, free, free_linked, centres);
  const bool free_links_more = free_linked.size() > prior_linked.size() && free_linked.size() >= 3 && holds &&
                               runs_agree(*prior_best, free, prior_linked, centres) && !angles_confirmed;
  // Views with an angle that the run without angles could not place (too little
  // overlap to find from scratch), where it is kept for joining more views, are
  // placed from the angles of registered neighbours that bracket them and turn
  // as their angles say (the object may have moved between runs of views;
  // within one, the angles hold), and the run is made again from those poses.
  // Kept when it registers more views and agrees with the run without angles
  // where that one joined views by pairs.
  std::string free_summary = run_summary("without angles", free, at_table);
  std::vector<int> filled;
  if (free_links_more) {
    SessionManifest fm = bare;
    for (std::size_t i = 0; i < n; ++i) {
      if (free.views[i].registered) {
        fm.views[i].initial_pose = free.poses[i];
        continue;
      }
      const auto X = pose_from_neighbours_angles(free.poses, reg, manifest, int(i), fit.ok ? fit.scale : 1.0,
                                                 params.wrong_angle_deg, free.diagonal);
      if (X) fm.views[i].initial_pose = *X, filled.push_back(int(i));
    }
    if (!filled.empty()) {
      RegistrationResult again = Registrar(clouds, fm, params, named("the failed views from their neighbours' angles")).run();
      const std::vector<int> now = linked_group(again, at_table);
      if (registered_count(again, at_table) > registered_count(free, at_table) &&
          std::includes(now.begin(), now.end(), free_linked.begin(), free_linked.end()) &&
          runs_agree(free, again, free_linked, centres)) {
        // The views it had placed keep their own initial source.
        for (std::size_t i = 0; i < n; ++i)
          if (free.views[i].registered) again.views[i].initial = free.views[i].initial;
        filled.erase(std::remove_if(filled.begin(), filled.end(),
                                    [&](int i) { return !again.views[std::size_t(i)].registered; }),
                     filled.end());
        free = std::move(again);
        free_summary += " (" + std::to_string(filled.size()) + " more from their neighbours' angles)";
      } else {
        filled.clear();
      }
    }
  }
  // Never fewer registered views than the prior's run for joining more.
  bool keep_free =
      overrules(free, *prior_best) ||
      (!overrules(*prior_best, free) &&
       ((free_links_more && registered_count(free, at_table) >= registered_count(*prior_best, at_table)) ||
        (!only_unlinked && !better(*prior_best, free, 1.05))));
  // The rules above compare two runs at a time: where the run they keep has a view
  // over kRunSeenThrough, a clear run that another comparison passed over (the run
  // with the angles clear, the corrected one at 12 % kept against it, the one
  // without angles at 18 %) is taken instead, the one registering the most views.
  if (most_seen_through(keep_free ? free : *prior_best) > kRunSeenThrough) {
    RegistrationResult* clear = nullptr;
    for (RegistrationResult* r : {&with, corrected ? &*corrected : nullptr, &free})
      if (r && overrules(*r, keep_free ? free : *prior_best) &&
          (!clear || registered_count(*r, at_table) > registered_count(*clear, at_table)))
        clear = r;
    if (clear == &free) {
      keep_free = true;
    } else if (clear) {
      keep_free = false;
      prior_best = clear;
    }
  }
  if (!keep_free) filled.clear();
  // A session suspect only for its unlinked views, where the run without angles
  // joins no more of them: a gap in the coverage; the run as given stands as it was.
  if (only_unlinked && !keep_free) return with;
  const std::string comparison = run_summary("with the angles", with, at_table) + "; " +
                                 (corrected ? run_summary("corrected angles", *corrected, at_table) + "; " : std::string()) +
                                 free_summary;
  RegistrationResult& chosen = keep_free ? free : *prior_best;
  // A run made again from the kept run's poses (below) keeps what that run said
  // and found: its angles' use and the views' initial sources, its warnings, its
  // axis and the moves it found; the poses, the pairs and the merged cloud are its
  // own. `as_was`: views whose diagnostics are taken whole (taken out, not back).
  const auto carry_over = [&](RegistrationResult& again, RegistrationResult& from, const std::vector<bool>& as_was) {
    for (std::size_t i = 0; i < n; ++i) {
      if (as_was[i]) {
        again.views[i] = from.views[i];
        continue;
      }
      again.views[i].prior = from.views[i].prior;
      again.views[i].angle_rejected = from.views[i].angle_rejected;
      if (from.views[i].registered) again.views[i].initial = from.views[i].initial;
    }
    again.warnings.swap(from.warnings);
    again.axis = from.axis;
    again.axis_fit = from.axis_fit;
    again.turntable_groups = from.turntable_groups;
    again.moved_after_view = from.moved_after_view;
    again.run_starts = from.run_starts;
    again.regrouped_from = from.regrouped_from;
    again.moved_with_object = from.moved_with_object;
  };
  // Where no run is clear of what the views saw, the kept run's views over
  // kRunSeenThrough (and their converged pairs' partners over kSeenClear: two
  // views on a near twin hold each other there) are taken out, and the session is
  // made again from the other views' poses; taken when that is clear and places
  // them as the kept run did. The views taken out fail by name (a partial result,
  // never a view silently half turned). (The issue's session turned 90 deg: every
  // run had two views 170 deg off, 15-18 % of them seen through, the others 0-1 %.)
  std::vector<int> dropped;
  std::vector<Cloud> kept_clouds;  // the clouds without the views taken out
  if (most_seen_through(chosen) > kRunSeenThrough) {
    std::vector<bool> out_of(n, false);
    for (std::size_t i = 0; i < n; ++i)
      out_of[i] = chosen.views[i].registered && chosen.views[i].seen_through.value_or(0) > kRunSeenThrough;
    std::vector<bool> partner(n, false);
    if (!chosen.pairs.empty())
      for (const PairDiagnostics& pd : chosen.pairs) {
        if (pd.round != chosen.pairs.back().round || !pd.converged) continue;
        for (const auto& [a, b] : {std::make_pair(pd.from, pd.to), std::make_pair(pd.to, pd.from)})
          if (out_of[std::size_t(a)] && chosen.views[std::size_t(b)].seen_through.value_or(0) > kSeenClear)
            partner[std::size_t(b)] = true;
      }
    SessionManifest fm = bare;
    std::vector<int> out, rest;
    std::vector<bool> as_was(n, false);
    for (std::size_t i = 0; i < n; ++i) {
      as_was[i] = out_of[i] || partner[i];
      if (as_was[i]) out.push_back(int(i));
      else if (chosen.views[i].registered) rest.push_back(int(i)), fm.views[i].initial_pose = chosen.poses[i];
    }
    std::vector<Cloud> without;
    RegistrationResult again;
    if (rest.size() >= 2) {
      without = clouds;
      for (int i : out) without[std::size_t(i)] = Cloud();
      again = Registrar(without, fm, params, named("without the views the others saw through")).run();
    }
    if (rest.size() >= 2 && runs_agree(chosen, again, rest, centres) && most_seen_through(again) <= kSeenClear) {
      dropped = std::move(out);
      kept_clouds = std::move(without);
      carry_over(again, chosen, as_was);
      for (int d : dropped) {
        // The view as it was (its points, its angle's use), not registered.
        const std::size_t i = std::size_t(d);
        const double seen = again.views[i].seen_through.value_or(0);
        again.views[i].registered = false;
        again.views[i].rotation_error_deg.reset();
        again.views[i].translation_error.reset();
        again.views[i].object_translation_error.reset();
        again.views[i].message = view_name(manifest, i) + ": its pose put " + std::to_string(std::lround(100 * seen)) +
                                 " % of it where the other views saw through, and no run was clear of that (a "
                                 "near twin of its place?)";
      }
      chosen = std::move(again);
    }
  }
  const std::vector<Cloud>& clouds_now = dropped.empty() ? clouds : kept_clouds;
  // Views the kept run could not place, where its views all agree with what the
  // others saw: another run that placed one of them, there clear of what its own
  // views saw too, gives it a start (its pose relative to a view both runs placed,
  // a converged pair's partner where it has one), and the session is made again
  // from the kept poses and those (no angles: every view posed). Taken when that
  // registers more views, its views still agree with what the others saw, and it
  // places the kept run's views as that did. (The issue's session with the object
  // turned 45 deg on the table and scanned again: the run kept placed seven views,
  // the run without angles all ten, five of them half turned.)
  std::vector<int> brought;
  if (!chosen.failed_views.empty() && most_seen_through(chosen) <= kSeenClear) {
    const std::vector<int> chosen_placed = [&] {
      std::vector<int> v;
      for (std::size_t i = 0; i < n; ++i)
        if (chosen.views[i].registered) v.push_back(int(i));
      return v;
    }();
    SessionManifest fm = bare;
    for (int i : chosen_placed) fm.views[std::size_t(i)].initial_pose = chosen.poses[std::size_t(i)];
    std::vector<const RegistrationResult*> sources = {&free, &with};
    if (corrected) sources.push_back(&*corrected);
    for (int v : chosen.failed_views) {
      for (const RegistrationResult* src : sources) {
        if (src == &chosen || !src->views[std::size_t(v)].registered ||
            !(src->views[std::size_t(v)].seen_through.value_or(1.0) <= kSeenClear))
          continue;
        int anchor = -1;
        if (!src->pairs.empty())
          for (const PairDiagnostics& pd : src->pairs) {
            if (pd.round != src->pairs.back().round || !pd.converged || (pd.from != v && pd.to != v)) continue;
            const int other = pd.from == v ? pd.to : pd.from;
            if (chosen.views[std::size_t(other)].registered && src->views[std::size_t(other)].registered) {
              anchor = other;
              break;
            }
          }
        for (std::size_t a = 0; a < n && anchor < 0; ++a)
          if (chosen.views[a].registered && src->views[a].registered) anchor = int(a);
        if (anchor < 0) continue;
        fm.views[std::size_t(v)].initial_pose = chosen.poses[std::size_t(anchor)] *
                                                rigid_inverse(src->poses[std::size_t(anchor)]) *
                                                src->poses[std::size_t(v)];
        brought.push_back(v);
        break;
      }
    }
    RegistrationResult again;
    if (!brought.empty()) {
      // (A view taken out above comes back where another run placed it clear.)
      std::vector<Cloud> back;
      for (int v : brought)
        if (std::find(dropped.begin(), dropped.end(), v) != dropped.end()) {
          if (back.empty()) back = clouds_now;
          back[std::size_t(v)] = clouds[std::size_t(v)];
        }
      again = Registrar(back.empty() ? clouds_now : back, fm, params, named("the failed views from another run")).run();
    }
    const bool made = !brought.empty() && registered_count(again, at_table) > registered_count(chosen, at_table) &&
                      most_seen_through(again) <= kSeenClear && runs_agree(chosen, again, chosen_placed, centres) &&
                      std::any_of(brought.begin(), brought.end(),
                                  [&](int i) { return again.views[std::size_t(i)].registered; });
    if (!made) {
      brought.clear();
    } else {
      brought.erase(std::remove_if(brought.begin(), brought.end(),
                                   [&](int i) { return !again.views[std::size_t(i)].registered; }),
                    brought.end());
      std::vector<bool> as_was(n, false);  // taken out above and not back: its message stays
      for (int i : dropped) as_was[std::size_t(i)] = !again.views[std::size_t(i)].registered;
      carry_over(again, chosen, as_was);
      again.warnings.push_back(view_list(manifest, brought) +
                               (brought.size() > 1 ? ", which this run could not place, were" :
                                                     ", which this run could not place, was") +
                               " placed from another run's pose and registered with the others");
      chosen = std::move(again);
    }
  }
  // Where no run was clear and none could be made so: the views over
  // kRunSeenThrough, named (registered as they are).
  if (dropped.empty()) name_seen_through(chosen, manifest, "in every run tried");
  // The views taken out that no other run brought back.
  std::vector<int> left_out;
  for (int i : dropped)
    if (!chosen.views[std::size_t(i)].registered) left_out.push_back(i);
  if (!left_out.empty())
    chosen.warnings.push_back(view_list(manifest, left_out) + (left_out.size() > 1 ? " were" : " was") +
                              " placed where the other views saw through, in every run tried: not registered");
  const bool kept_given = !keep_free && prior_best == &with;
  std::vector<bool> rejected_before(n);
  for (std::size_t i = 0; i < n; ++i) rejected_before[i] = with.views[i].angle_rejected;
  // A run passed over that found a half-turned twin fitting too (its warnings say so)
  // and that places views about half a turn from where the kept run does: the runs
  // disagree where the shapes cannot tell, which is named (the coloured bottle knocked
  // 45 deg: the run with the angles put the views after the knock where the colours
  // say, and joined one view fewer than the run without angles, kept on the twin).
  std::string twin_doubt;
  {
    const RegistrationResult& kept = keep_free ? free : *prior_best;
    // (Not where the kept run's own colours chose a place: the bottle with colours
    // knocked -30 deg, right, and a run passed over with a view on its twin.)
    const auto colours_chose = [](const std::vector<std::string>& words) {
      return std::any_of(words.begin(), words.end(), [](const std::string& w) {
        return w.find(kColoursChose) != std::string::npos || w.find(kColoursFavour) != std::string::npos;
      });
    };
    const bool kept_by_colours = colours_chose(kept.warnings) || colours_chose(kept.notes);
    for (const RegistrationResult* r : {&with, corrected ? &*corrected : nullptr, &free}) {
      if (kept_by_colours) break;
      if (!r || r == &kept) continue;
      if (std::none_of(r->warnings.begin(), r->warnings.end(), [](const std::string& w) {
            return w.find(kHalfTurn) != std::string::npos;
          }))
        continue;
      const std::vector<int> apart = half_turn_apart(kept, *r);
      if (apart.empty()) continue;
      std::ostringstream d;
      d << "the run " << (r == &with ? "with the angles" : r == &free ? "without angles" : "with the corrected angles")
        << " found that the object fits turned by half a turn too, and places ";
      for (std::size_t k = 0; k < apart.size(); ++k) d << (k ? ", " : "") << "views[" << apart[k] << "]";
      d << " half a turn from the poses kept: the object looks alike from both sides, so their place may be the "
           "turned one; check the merged cloud";
      twin_doubt = d.str();
      break;
    }
  }
  RegistrationResult out = std::move(keep_free ? free : *prior_best);
  out.prior_kept = keep_free ? "no prior" : kept_given ? "prior" : "corrected prior";
  if (keep_free) {
    // The turntable axis for what follows (the report's up, the table plane): the
    // prior-free poses are in the first view's scanner frame, where the session's
    // axis holds; without one, the axis the registered poses turn about.
    out.axis = manifest.axis;
    if (!out.axis) {
      std::vector<Eigen::Matrix4d> ps;
      for (std::size_t i = 0; i < n; ++i)
        if (out.views[i].registered) ps.push_back(out.poses[i]);
      if (ps.size() >= 3) {
        const AxisFitResult a = calibrate_axis(ps, angles_about_common_axis(ps));
        if (a.ok) out.axis = a.axis;
      }
    }
  }
  out.prior_comparison = comparison;
  // The angle error column is the kept poses' turn against the commanded angles: the
  // run without angles is what judged the angles, but where another run is kept it
  // may have placed views elsewhere (a group it could not join, 100 deg off).
  // (The kept run without angles may also hold views filled in from their neighbours'
  // angles since `fit` was taken: measured again on the poses kept.) Where a run with
  // the angles is kept, a view no converged pair joins to the rest was placed by its
  // angle alone: its error would be 0 by construction, so none is shown.
  std::vector<bool> kept_registered(n);
  for (std::size_t i = 0; i < n; ++i) kept_registered[i] = out.views[i].registered;
  // Where the kept poses hold a move of the object (two turntable runs, or groups
  // registered to the others as a whole), each part turns as its own angles say
  // and is off from the others by the move: the angles are fitted to each part
  // alone (one fit over all would call the views of one part wrong by the move's
  // turn, or those of the other when the parts are as large), and the fit of the
  // run without angles (one offset for the whole session) names no view.
  std::vector<int> part(n, 0);
  for (std::size_t i = 0; i < n; ++i) {
    for (int start : out.run_starts)
      if (out.turntable_groups >= 2 && int(i) >= start) ++part[i];
    // A run registered as a whole that the runs' pose graph did not hold (turned over:
    // it turns about the table's axis the other way in the object's frame).
    if (out.turntable_groups < 2 && out.regrouped_from >= 0 && int(i) >= out.regrouped_from) part[i] = 1;
    if (std::find(out.moved_with_object.begin(), out.moved_with_object.end(), int(i)) != out.moved_with_object.end())
      part[i] = int(out.run_starts.size()) + 2;
  }
  const bool moved_parts = std::any_of(part.begin(), part.end(), [](int k) { return k != 0; });
  AnglePriorFit shown = fit_angle_prior(out.poses, kept_registered, manifest, params.wrong_angle_deg, known);
  if (moved_parts) {
    const AnglePriorFit whole = shown;
    shown.wrong.clear();
    shown.ok = false;
    const auto wrap = [](double a) { return a - 360.0 * std::round(a / 360.0); };
    for (int k = 0; k <= int(out.run_starts.size()) + 2; ++k) {
      SessionManifest only = manifest;
      std::vector<int> members;
      for (std::size_t i = 0; i < n; ++i)
        if (part[i] != k) only.views[i].angle_deg.reset();
        else if (manifest.views[i].angle_deg) members.push_back(int(i));
      if (members.empty()) continue;
      const AnglePriorFit f = fit_angle_prior(out.poses, kept_registered, only, params.wrong_angle_deg, known);
      if (f.ok) {
        for (int i : members) shown.residual_deg[std::size_t(i)] = f.residual_deg[std::size_t(i)];
        shown.wrong.insert(shown.wrong.end(), f.wrong.begin(), f.wrong.end());
        shown.ok = true;
        continue;
      }
      // Too few views to fit alone (under three): the whole fit's residuals with
      // the part's own mean turn taken out (the move's), when the whole fit had its
      // sign and step. (A larger part whose angles fit nowhere shows none.)
      for (int i : members) shown.residual_deg[std::size_t(i)].reset();
      if (members.size() >= 3) continue;
      std::vector<double> res;
      for (int i : members)
        if (whole.residual_deg[std::size_t(i)]) res.push_back(*whole.residual_deg[std::size_t(i)]);
      if (res.empty() || !whole.ok) continue;
      double mean = 0;
      for (double e : res) mean += wrap(e - res.front());
      mean = res.front() + mean / double(res.size());
      for (int i : members) {
        const std::optional<double>& e = whole.residual_deg[std::size_t(i)];
        if (!e) continue;
        shown.residual_deg[std::size_t(i)] = wrap(*e - mean);
        shown.ok = true;
        if (std::abs(wrap(*e - mean)) > params.wrong_angle_deg) shown.wrong.push_back(i);
      }
    }
    std::sort(shown.wrong.begin(), shown.wrong.end());
  }
  const std::vector<int> joined = linked_group(out, at_table);
  const auto measured = [&](std::size_t i) {
    return keep_free || std::find(joined.begin(), joined.end(), int(i)) != joined.end();
  };
  for (std::size_t i = 0; i < n; ++i) {
    out.views[i].angle_error_deg = measured(i) ? shown.residual_deg[i] : std::nullopt;
    if (keep_free && manifest.views[i].angle_deg) out.views[i].prior = PriorUse::kIgnored;
  }
  for (int i : filled) {
    if (!out.views[std::size_t(i)].registered) continue;
    out.views[std::size_t(i)].prior = PriorUse::kUsed;
    out.views[std::size_t(i)].initial = InitialPoseSource::kTurntableAxis;
  }
  std::vector<std::string> notes;
  std::ostringstream w;
  w.precision(3);
  if (out.prior_kept != "prior") {
    w << "the turntable prior misled the registration (" << out.prior_comparison << "): "
      << (keep_free ? "the poses registered without angles are kept" : "the poses of the corrected angles are kept");
    notes.push_back(w.str());
    w.str("");
  }
  if (fit.ok && !fit.convention.empty()) {
    w << "the commanded angles fit the scans with " << fit.convention << " (" << fit.agreeing << " of "
      << fit.views << " views within " << params.wrong_angle_deg << " deg)";
    notes.push_back(w.str());
    w.str("");
  }
  const std::vector<std::vector<int>> passes =
      keep_free && free_links_more
          ? agreeing_runs(fit, manifest, params.wrong_angle_deg, std::max(15.0, 2 * params.wrong_angle_deg))
          : std::vector<std::vector<int>>{};
  if (!fit.ok && passes.size() >= 2) {
    // Not a turntable that did not turn: the pairs joined the passes, each turning
    // as its angles say.
    w << "the commanded angles fit " << passes.size() << " runs of views apart (";
    for (std::size_t k = 0; k < passes.size(); ++k)
      w << (k ? ", " : "") << "views[" << passes[k].front() << "]-views[" << passes[k].back() << "]";
    w << "), each turning as its angles say but off from the runs beside it: the object moved on the table "
         "between them";
    notes.push_back(w.str());
    w.str("");
  } else if (!fit.ok && !shown.ok && fit.views >= 3 && 2 * fit.agreeing < fit.views) {
    w << "the commanded angles fit the registered poses nowhere (" << fit.agreeing << " of " << fit.views
      << " views agree within " << params.wrong_angle_deg << " deg of any one turning): did the turntable turn, "
      << "and are the views of one object?";
    notes.push_back(w.str());
    w.str("");
  }
  // Wrong angles: as the kept poses show them (the column above), and as the run
  // without angles found them (the kept run's angle prior may have pulled such a view
  // back towards its angle, or the corrected run registered it without).
  std::vector<int> wrong;
  if (shown.ok)
    for (int i : shown.wrong)
      if (measured(std::size_t(i))) wrong.push_back(i);
  if (fit.ok && !moved_parts) wrong.insert(wrong.end(), fit.wrong.begin(), fit.wrong.end());
  std::sort(wrong.begin(), wrong.end());
  wrong.erase(std::unique(wrong.begin(), wrong.end()), wrong.end());
  for (int i : wrong) {
    const bool seen_kept = shown.ok && measured(std::size_t(i)) &&
                           std::find(shown.wrong.begin(), shown.wrong.end(), i) != shown.wrong.end();
    const double off = std::abs(*(seen_kept ? shown : fit).residual_deg[i]);
    if (kept_given && rejected_before[i]) continue;  // warned about already
    // (The object turned when it moved: a moved part's angles are off together,
    // which the warning about the move explains; each part's own fit above takes
    // that turn out, so what is left is a view wrong within its part.)
    w << view_name(manifest, std::size_t(i)) << ": commanded angle " << *manifest.views[i].angle_deg << " deg is "
      << off << " deg off what the other views and the scans say; "
      << (out.views[i].prior == PriorUse::kUsed || out.views[i].prior == PriorUse::kCorrected
              ? "the refinement moved the view off it"
              : "registered without it");
    notes.push_back(w.str());
    if (out.views[i].message.empty() && out.views[i].registered) out.views[i].message = w.str();
    w.str("");
  }
  if (!filled.empty()) {
    w << filled.size() << " view" << (filled.size() == 1 ? "" : "s") << " that the run without angles could not place ("
      << view_name(manifest, std::size_t(filled.front())) << (filled.size() > 1 ? ", ..." : "")
      << ") started from the angles of neighbours that turn as their angles say";
    notes.push_back(w.str());
    w.str("");
  }
  if (!twin_doubt.empty()) notes.push_back(twin_doubt);
  out.warnings.insert(out.warnings.begin(), notes.begin(), notes.end());
  return out;
}

RegistrationResult register_views(const std::vector<Cloud>& clouds, const SessionManifest& manifest,
                                  const RegistrationParams& given, const RegistrationCallback& progress) {
  RegistrationResult r = register_views_checked(clouds, manifest, given, progress);
  const std::vector<std::string> same = same_scans(clouds, manifest);
  r.warnings.insert(r.warnings.begin(), same.begin(), same.end());
  return r;
}

RegistrationResult register_session(const Session& session, const RegistrationParams& params,
                                    const RegistrationCallback& progress) {
  const SessionManifest& m = session.manifest();
  std::vector<Cloud> clouds(m.views.size());
  std::vector<std::string> unreadable(m.views.size());
  for (std::size_t i = 0; i < m.views.size(); ++i) {
    try {
      clouds[i] = session.load_view(i);
    } catch (const Error& e) {
      // An unreadable view is a failed view, not a failed session.
      unreadable[i] = e.what();
    }
  }
  RegistrationResult r = register_views(clouds, m, params, progress);
  for (std::size_t i = 0; i < m.views.size(); ++i)
    if (!unreadable[i].empty()) r.views[i].message = view_name(m, i) + ": " + unreadable[i];
  return r;
}

std::string poses_to_yaml(const RegistrationResult& result, const SessionManifest& manifest) {
  YAML::Emitter out;
  out.SetDoublePrecision(17);
  out << YAML::BeginMap;
  out << YAML::Key << "format" << YAML::Value << "station-poses";
  out << YAML::Key << "version" << YAML::Value << 1;
  if (result.axis) {
    out << YAML::Key << "turntable_axis" << YAML::Value << YAML::Flow << YAML::BeginMap;
    out << YAML::Key << "point" << YAML::Value << YAML::Flow << YAML::BeginSeq << result.axis->point.x()
        << result.axis->point.y() << result.axis->point.z() << YAML::EndSeq;
    out << YAML::Key << "direction" << YAML::Value << YAML::Flow << YAML::BeginSeq
        << result.axis->direction.x() << result.axis->direction.y() << result.axis->direction.z()
        << YAML::EndSeq;
    out << YAML::EndMap;
  }
  out << YAML::Key << "degenerate" << YAML::Value << result.degenerate;
  out << YAML::Key << "prior_kept" << YAML::Value << result.prior_kept;
  if (!result.prior_comparison.empty())
    out << YAML::Key << "prior_comparison" << YAML::Value << YAML::DoubleQuoted << result.prior_comparison;
  out << YAML::Key << "views" << YAML::Value << YAML::BeginSeq;
  for (std::size_t i = 0; i < result.poses.size(); ++i) {
    const ViewDiagnostics& v = result.views[i];
    out << YAML::BeginMap;
    out << YAML::Key << "file" << YAML::Value << YAML::DoubleQuoted << manifest.views[i].file;
    out << YAML::Key << "registered" << YAML::Value << v.registered;
    out << YAML::Key << "initial" << YAML::Value << to_string(v.initial);
    if (v.prior != PriorUse::kNone) out << YAML::Key << "prior" << YAML::Value << to_string(v.prior);
    if (v.angle_error_deg) out << YAML::Key << "angle_error_deg" << YAML::Value << *v.angle_error_deg;
    out << YAML::Key << "pose" << YAML::Value << YAML::Flow << YAML::BeginMap << YAML::Key << "matrix"
        << YAML::Value << YAML::Flow << YAML::BeginSeq;
    for (int r = 0; r < 4; ++r)
      for (int c = 0; c < 4; ++c) out << result.poses[i](r, c);
    out << YAML::EndSeq << YAML::EndMap;
    if (!v.message.empty()) out << YAML::Key << "message" << YAML::Value << YAML::DoubleQuoted << v.message;
    if (v.rotation_error_deg) out << YAML::Key << "rotation_error_deg" << YAML::Value << *v.rotation_error_deg;
    if (v.translation_error) out << YAML::Key << "translation_error" << YAML::Value << *v.translation_error;
    if (v.object_translation_error)
      out << YAML::Key << "object_translation_error" << YAML::Value << *v.object_translation_error;
    out << YAML::EndMap;
  }
  out << YAML::EndSeq << YAML::EndMap;
  return std::string(out.c_str()) + "\n";
}

void write_poses_yaml(const std::filesystem::path& path, const RegistrationResult& result,
                      const SessionManifest& manifest) {
  write_file_atomic(path, poses_to_yaml(result, manifest));
}

}  // namespace station
