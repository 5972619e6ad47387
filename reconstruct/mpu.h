#pragma once
// Multi-level Partition of Unity implicit surface (Ohtake, Belyaev, Alexa, Turk,
// Seidel 2003, "Multi-level partition of unity implicits"; summarised in
// shared/seeds/colour-mpu_fujimoto.txt section 2.2 and shared/docs/methods.md
// section 2). An adaptive octree of local quadratic fits Q_k blended as
//
//   f(x) = sum_k w_k(x) Q_k(x) / sum_k w_k(x),  w_k(x) = b2(3 |x - o_k| / (2 R_k))   (MPU eq. 1)
//
// with b2 the quadratic B-spline (support |t| < 3/2, so w_k vanishes outside the
// ball of radius R_k around the cell centre o_k).
//
// Sign convention: f < 0 inside, f > 0 outside (as a signed distance; the DMC
// paper's convention; the colour paper uses the opposite). Input normals must
// point outwards. f is returned in the input's units (approximately a signed
// distance near the surface); internally everything is fitted in the normalised
// frame where the points' bounding cube has diagonal 1.
#include <array>
#include <memory>
#include <vector>

#include "core/geometry.h"
#include "reconstruct/implicit.h"

namespace station {

/// Local shape function of a leaf cell (Ohtake 2003, section 3).
enum class MpuFitType {
  kBivariate,  ///< height function w = h(u, v) over the tangent plane (normals agree)
  kQuadric,    ///< general 3-D quadric with auxiliary off-surface points (normals spread)
  kEdge,       ///< max/min of two bivariate quadratics (sharp edge, two normal clusters)
  kCorner,     ///< max/min of three bivariate quadratics (sharp corner, three clusters)
};

/// MpuParams::sparse_trust from this local spacing over the median (core/kdtree.h's
/// sparse_allowance; the rims' trim to the scans starts at 1.5). The trust fills
/// surface between points, so it waits for sparser data: on the real dragon session
/// (holes kept, 509 cells) mesh -> scans mean / p95 0.21 / 0.40 mm without it (458,607
/// vertices), 0.217 / 0.432 from 1.5 (476,032), 0.212 / 0.415 from 2 (472,360), 0.207 /
/// 0.402 from 2.5 (467,657); scans -> mesh 0.0715, 0.0694, 0.0696, 0.0702 mm; on the
/// Kinect scene (537 cells) scans -> mesh 1.0197 mm without it, 0.9840 / 0.9843 /
/// 0.9873 mm.
inline constexpr double kSparseTrustFrom = 2.0;

struct MpuParams {
  /// alpha: support radius R = alpha * (cell diagonal). Paper: 0.75.
  double alpha = 0.75;
  /// lambda: a ball with fewer than n_min points is grown R <- R + lambda R until it
  /// holds n_min. Paper: 0.1.
  double lambda = 0.1;
  /// N_min: points needed in a cell's ball. Paper: 15.
  int n_min = 15;
  /// A cell is split only when its ball (before growth) holds at least this many
  /// points. Not in the paper (0: split whenever the error asks for it). With noise,
  /// raising n_min (e.g. 30) is what removes small spurious bubbles (docs/mpu.md).
  int split_min_points = 0;
  /// Ridge (relative to the normal matrix's trace) on the curvature terms of bivariate
  /// fits in grown balls, whose n_min points sit on the rim far from the cell: large
  /// values flatten them towards planes. Not in the paper; 0.1 cuts the spurious
  /// bubbles on noisy input ~10x but costs accuracy on sparse clean input (docs/mpu.md).
  double grown_curvature_ridge = 1e-6;
  /// Balls holding more points are fitted (and their error measured) on an evenly
  /// spread subset of this size (0 = all). Only coarse cells are affected; they are
  /// split anyway unless the subset already fits within epsilon0. Not in the paper.
  int max_fit_points = 1000;
  /// epsilon_0: Taubin error max |Q(p)| / |grad Q(p)| over the ball's points above
  /// which a cell is subdivided; relative to the normalised size (bounding-cube
  /// diagonal 1). Paper: 1e-4.
  double epsilon0 = 1e-4;
  /// Deepest octree level (root = 0); a cell there is kept whatever its error.
  int max_depth = 10;
  /// Bivariate fit when every ball normal n_i has n_i . n_mean > this (paper: angle
  /// below pi/2, i.e. 0); else a general quadric (or a sharp fit).
  double bivariate_min_cos = 0.0;
  /// Weight of the normal constraints grad Q(p_i) = n_i in the quadric fit, as a
  /// length relative to R (the residual |grad Q - n| is scaled by this * R). Not in
  /// the paper (which uses auxiliary points only); keeps Q from degenerating where
  /// no auxiliary point qualifies.
  double quadric_normal_weight = 0.1;
  /// Total weight of the auxiliary-point rows against the ball points' rows (paper: 1,
  /// equal totals). The auxiliary distances are tangent-plane estimates, far off at the
  /// cell corners: on 40 exact sphere samples the quadric's Taubin error is 5.8e-2 at
  /// 1, 2e-4 at 1e-3, 2e-5 at 1e-4, 1e-8 at 0. The normal rows fix the scale, so the
  /// auxiliaries only need to break ties.
  double quadric_aux_weight = 1e-4;
  /// Sharp-feature fits (Ohtake section 3.3): the ball's normals are clustered when
  /// two of them differ by more than sharp_angle_deg; each cluster must lie within
  /// cluster_angle_deg of its mean.
  bool sharp_features = true;
  double sharp_angle_deg = 60.0;
  double cluster_angle_deg = 20.0;
  /// Margin of the root cell around the points' bounding cube (fraction of its side),
  /// so that the surface can close just outside the data.
  double root_margin = 0.1;
  /// "Where there is no data": x is trusted when its nearest input point lies within
  /// trust_factor x the mean point spacing (mean nearest-neighbour distance).
  double trust_factor = 4.0;
  /// Where the points are sparse (sparse_allowance, core/kdtree.h: a local spacing
  /// kSparseTrustFrom times their median or more), a point's trust reaches that many
  /// times further, at most 4: x is trusted when some point p lies within trust_factor x
  /// mean spacing x p's allowance. A depth camera's far field is sampled several times
  /// more sparsely than its near field, and a trust distance from the mean spacing alone
  /// cut holes there (docs/run.md, "Holes kept: sparse data trusted").
  bool sparse_trust = false;
  /// Threads for the build and batched evaluation (0 = all cores). The result does
  /// not depend on it.
  int threads = 0;
  /// When valid: the normalised frame (and so the octree's root cell and what epsilon0
  /// measures) from this box instead of the points' bounding box. A part of a cloud fit
  /// in the whole cloud's frame shares the whole fit's octree cells and tolerance (the
  /// blocks of reconstruct/blocks.h). Must be finite, of positive size and hold the
  /// points with usable normals (InvalidInput otherwise). Left as Aabb{}: unset.
  Aabb frame;
  /// The mean spacing behind trust_factor, in input units; 0: the points' own (mean
  /// nearest-neighbour distance).
  double mean_spacing = 0;
  /// The median sample spacing that sparse_trust's allowances are measured against, in
  /// input units; 0: the points' own (MpuDiagnostics::sample_spacing). A block of a
  /// larger cloud takes the whole cloud's (reconstruct/blocks.h).
  double median_spacing = 0;
};

/// Per-build diagnostics (cf. the colour paper's Table 3).
struct MpuDiagnostics {
  std::size_t input_points = 0;
  std::size_t dropped_points = 0;  ///< zero or non-finite normals (left out of the fit)
  std::size_t cells = 0;           ///< octree nodes, internal and leaves
  std::size_t leaves = 0;
  std::array<std::size_t, 4> leaves_by_type{};  ///< indexed by MpuFitType
  std::vector<std::size_t> leaves_by_depth;     ///< [depth]
  std::size_t grown_leaves = 0;     ///< leaves whose ball had to grow to reach n_min
  std::size_t unconverged_leaves = 0;  ///< leaves at max_depth with error > epsilon0
  double max_leaf_error = 0;       ///< largest Taubin error among the leaves (normalised)
  double mean_spacing = 0;         ///< mean nearest-neighbour distance (input units)
  /// The sample spacing 1 / sqrt(density) (input units): the median over the points of
  /// r_8 sqrt(pi / 8), r_8 the distance to the 8th nearest neighbour. Unlike the nearest
  /// neighbour's distance it does not depend on how the samples are placed: a grid of
  /// step s gives 0.89 s (its nearest neighbour s), an even (blue-noise) sample 0.93 of
  /// its nearest neighbour, area-uniform random samples twice their mean nearest
  /// neighbour (which is 0.5 / sqrt(density)). The automatic resolution follows it.
  double sample_spacing = 0;
  double fit_seconds = 0;
};

/// The fitted MPU function. Cheap to copy (shares immutable state); every query is
/// const and thread-safe. Queries take and return input (world) units.
class MpuSurface : public ImplicitFunction {
 public:
  /// f(x) (MPU eq. 1), in input units. Visits only the leaves whose support ball
  /// holds x (octree walk). Outside every support (far beyond the data): the distance
  /// to the root cell's centre, positive.
  double value(const Vec3d& x) const override;
  /// grad f(x), analytic: (sum(grad w Q + w grad Q) W - sum(w Q) grad W) / W^2.
  Vec3d gradient(const Vec3d& x) const override;
  /// f and grad f from one walk.
  double value_gradient(const Vec3d& x, Vec3d& grad) const;
  /// Batched versions (parallel, same results as one by one).
  std::vector<double> values(const std::vector<Vec3d>& xs) const;
  std::vector<Vec3d> gradients(const std::vector<Vec3d>& xs) const;

  /// sum_k w_k(x): zero outside every support ball.
  double weight_sum(const Vec3d& x) const;
  /// Distance from x to the nearest input point (input units).
  double nearest_point_distance(const Vec3d& x) const;
  /// nearest_point_distance(x) <= trust_factor * mean spacing (MpuParams); with
  /// sparse_trust, some point within that times its allowance.
  bool trusted(const Vec3d& x) const override;
  /// Some point within the trust distance (times its allowance, with sparse_trust)
  /// plus `radius`: trusted(y) can hold for a y within `radius` of x.
  bool may_be_trusted_near(const Vec3d& x, double radius) const override;
  /// Some input point within `distance` of x (input units), times that point's
  /// allowance with sparse_trust (MpuParams): "near the data" on the data's own scale.
  bool near_points(const Vec3d& x, double distance) const;
  /// Whether a leaf with a sharp fit (edge or corner, MpuParams::sharp_features) has
  /// its support ball within `radius` of x: elsewhere f is a blend of smooth
  /// quadratics and has no crease.
  bool may_be_sharp(const Vec3d& x, double radius) const override;
  /// value() at each point, bit for bit, with one octree walk for all (the leaves whose
  /// support reaches the points' bounding ball, in the walk's order).
  void values_near(const Vec3d* xs, int n, double* out) const override;
  /// gradient() at each point, bit for bit, from one octree walk for all.
  void gradients_near(const Vec3d* xs, int n, Vec3d* out) const override;
  /// Both, bit for bit, from one octree walk.
  void values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const override;

  /// Normalised frame: y = (x - center()) * scale(); the bounding cube of the input
  /// points (of MpuParams::frame when set) has diagonal 1 there, and epsilon0 is
  /// measured in it.
  Vec3d center() const;
  double scale() const;
  /// Bounding box of the input points (input units) and the points themselves.
  Aabb bounds() const;
  const std::vector<Vec3f>& points() const;
  const MpuDiagnostics& diagnostics() const;
  const MpuParams& params() const;

  struct Impl;

 private:
  friend MpuSurface fit_mpu(const Cloud&, const MpuParams&);
  std::shared_ptr<const Impl> impl_;
};

/// Fits the MPU implicit to points with outward unit normals (methods.md section 2).
/// Deterministic: the same input gives the same surface for any params.threads.
/// Points whose normal is zero or non-finite are left out (counted in the
/// diagnostics). InvalidInput when the cloud has no normals ("estimate and orient
/// them first: core/normals.h"), has non-finite coordinates, fewer than
/// n_min usable points, all points equal, or when a parameter is out of range.
MpuSurface fit_mpu(const Cloud& points_with_normals, const MpuParams& params = {});

/// An epsilon0 suited to the cloud's noise: factor x the median, over up to 5000
/// evenly spread points, of the RMS residual of a quadratic height fit (over the plane
/// normal to the neighbours' mean normal, or their PCA plane without normals) to a
/// point's k nearest neighbours, in the normalised frame of fit_mpu;
/// never below 1e-4
/// (the paper's value, right for clean data). docs/mpu.md: with 0.5 % noise, epsilon0
/// near the noise level gives one clean surface where 1e-4 gives hundreds of bubbles.
/// InvalidInput on fewer than k points or non-finite coordinates.
double suggest_epsilon0(const Cloud& cloud, int k = 50, double factor = 4.0);

}  // namespace station
