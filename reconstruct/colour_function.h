#pragma once
// The MPU colour function (Fujimoto, Itoh, Nakata, Kitagawa, Oka, Tanaka,
// "Implicit surface reconstruction with color distribution using MPU implicits";
// shared/seeds/colour-mpu_fujimoto.txt, methods.md section 3; docs/colour.md).
//
// Colours are fitted in CIE L*a*b* (reconstruct/lab.h) on an adaptive octree of
// the same kind as MPU's (reconstruct/mpu.h: same normalised frame, root cell,
// support balls R = alpha * d grown by lambda R to n_min points, weights
// w_k(x) = b2(3 |x - o_k| / (2 R_k))) and blended as
//
//   f(x) = sum_k w_k(x) Q_k(x) / sum_k w_k(x)      (one Q_k per leaf, 3 channels)
//
// Each leaf is Type A (a weighted least-squares bivariate quadratic per channel in
// the cell's tangent frame) or Type B (the ball's points split into colour
// clusters, each interpolated by a compactly supported RBF, joined by RBF boundary
// functions), so colour boundaries stay sharp. By default (ColourParams::side_consensus)
// the leaves at x first vote on x's side (colour class) and only that side's
// predictions are blended, so neighbouring leaves never mix the two colours.
#include <array>
#include <memory>
#include <vector>

#include "core/geometry.h"
#include "reconstruct/implicit.h"
#include "reconstruct/lab.h"

namespace station {

struct ColourParams {
  // ---- octree and weights (as MpuParams; the paper uses MPU's values) ----------
  /// Support radius R = alpha * (cell diagonal). Paper: 0.75.
  double alpha = 0.75;
  /// A ball with fewer than n_min points grows R <- R + lambda R until it holds n_min;
  /// such a leaf is not split further. Paper: 0.1 and 15.
  double lambda = 0.1;
  int n_min = 15;
  /// Margin of the root cell around the points' bounding cube (as MpuParams), so the
  /// octree is the MPU surface's twin for the same points.
  double root_margin = 0.1;
  /// Deepest level (root = 0); a cell there is kept whatever its error.
  int max_depth = 12;
  /// A Type A cell failing eq. 4 is split only when its ball holds at least this many
  /// points (0: always, as the paper). Not in the paper: on fine texture the split goes on
  /// until the children's balls must grow to n_min points, many large overlapping
  /// balls that cost time and barely help (docs/colour.md).
  int split_min_points = 30;
  /// Eq. 4 measures each point's residual beyond its own quantisation: how far the
  /// colour its 8-bit value stands for can lie from it (half a step in each sRGB
  /// channel, in L*a*b*: 0.10-0.26 for L*, 0.15-0.77 for a*, 0.16-0.71 for b*). Not in the paper; the
  /// paper's epsilon_col (0.1 L*) is below that, so on 8-bit texture a cell's fit
  /// fails eq. 4 on quantisation alone and splits down to split_min_points
  /// (docs/colour.md). false: the paper's test.
  bool quantisation_tolerance = true;

  // ---- the paper's cell test ------------------------------------------------------
  /// N_max: a ball holding more points is split before any colour test. Paper: 200
  /// (150-225 best); Type-A-only runs in the paper use 2000.
  int n_max = 200;
  /// gamma: a ball whose largest colour difference max |c_i - c_j| (L*a*b*, CIE76)
  /// exceeds this holds a colour boundary: Type B. Paper: 40.
  double gamma = 40;
  /// epsilon_col: Type A is accepted when max |Q(p_i) - c_i| / r * phi(p_i) is below
  /// it for every channel (eq. 4; r = 100 for L*, 255 for a*, b*), over the points
  /// within alpha * d of the centre; else the cell is split. Paper: 1e-3.
  double epsilon_col = 1e-3;
  /// Type B RBF support radius as a fraction of the cell's R_k. Paper: 0.4.
  double rbf_radius_factor = 0.4;
  /// false: Type A everywhere (the paper's Table 1 baseline, there with n_max = 2000).
  bool type_b = true;
  /// A cluster with fewer points gets a constant colour (its mean) instead of an RBF;
  /// the cell stays Type B. Bad-input guard (issue 7: "fewer than four points").
  int min_rbf_points = 4;

  // ---- blending (beyond the paper, on by default) --------------------------------
  /// Where Type B leaves cover x, decide the side (colour class) at x once and blend
  /// only predictions for that side. The leaves' colour predictions at x (each Type B
  /// cluster's RBF, each Type A quadratic) are grouped into classes (within gamma / 2);
  /// every leaf votes with its weight: a Type B leaf its boundary function for each of
  /// its clusters' classes (b and -b, or b_c one-vs-rest, clamped to [-1, 1]), a Type A
  /// leaf +1 for its class, -1 for classes a leaf does not have; the best class wins and
  /// only the leaves' predictions in it are blended. false: the paper, every leaf blends
  /// the colour of its own side, so leaves whose boundaries disagree slightly, and
  /// one-colour leaves whose balls reach over the boundary, mix the two colours in a band
  /// about two grid cells wide on a mesh finer than the sampling (docs/colour.md). Where
  /// no Type B leaf covers x both are the same.
  bool side_consensus = true;

  /// A two-cluster cell whose clusters a straight line separates in the cell's tangent
  /// plane gets that line as its boundary function instead of the RBF: the widest
  /// empty strip between the clusters (the perpendicular bisector of the closest points
  /// of their convex hulls), b = +-1 at the strip's edges. The RBF's zero set runs
  /// midway between neighbouring samples of the two colours, so where the sampling
  /// leaves a gap along the boundary it strays into the gap by up to a spacing; the
  /// line is held by every sample along the cell's stretch of boundary. Cells whose
  /// clusters no line separates (curved or interleaved boundaries) keep the RBF. Both
  /// classify every input point alike, so e_col at the input points is unchanged.
  bool linear_boundary = true;

  // ---- beyond the paper (each off by default = the paper's method) --------------
  /// (a) Three or more colours in a cell: up to max_clusters clusters (farthest-point
  /// seeds in L*a*b* while the next seed is more than gamma from all others), each with
  /// its own RBF, joined by one-vs-rest boundary functions (the largest wins).
  bool multi_colour = false;
  int max_clusters = 4;
  /// (b) Colour noise: a cell is Type B only when every cluster holds at least
  /// noise_min_fraction of the ball's points (and min_rbf_points) and every pair of
  /// clusters is separated: |mean_1 - mean_2| > noise_separation * (s_1 + s_2) with s
  /// the clusters' RMS colour spread; else Type A. Type A then also accepts a fit whose
  /// weighted RMS residual is below noise_accept_rms (L*a*b* units) where eq. 4 fails.
  bool noise_robust = false;
  double noise_min_fraction = 0.1;
  double noise_separation = 2.0;
  double noise_accept_rms = 14.0;

  /// Evaluate e_col on the input points after the fit (ColourDiagnostics::e_col; about a
  /// quarter of the total time). false: e_col stays 0.
  bool compute_e_col = true;
  /// e_col over at most this many of the input points, evenly strided (0: all of them).
  /// The mean over 50,000 of 100,000 clean mustard samples is within 1 % of the whole
  /// cloud's; evaluating every point of a 1 M cloud took 1.5 s of a 27 s surface stage.
  std::size_t e_col_max_points = 0;
  /// Threads for the build and batched evaluation (0 = all cores). The result does not
  /// depend on it.
  int threads = 0;
};

/// Leaf types.
enum class ColourCellType { kA = 0, kB = 1 };

struct ColourDiagnostics {
  std::size_t input_points = 0;
  std::size_t cells = 0;   ///< octree nodes, internal and leaves
  std::size_t leaves = 0;
  std::size_t empty_cells = 0;  ///< cells without a point in their ball: no local function
  std::array<std::size_t, 2> leaves_by_type{};              ///< [ColourCellType]
  std::vector<std::array<std::size_t, 2>> leaves_by_depth;  ///< [depth][type]
  std::size_t grown_leaves = 0;       ///< ball grown to n_min (not split further)
  std::size_t unconverged_leaves = 0; ///< Type A leaves failing eq. 4 (grown or max depth)
  std::size_t multi_colour_leaves = 0;///< Type B leaves with three or more clusters
  std::size_t constant_clusters = 0;  ///< clusters below min_rbf_points (constant colour)
  std::size_t linear_boundaries = 0;  ///< Type B leaves whose boundary is a line (linear_boundary)
  std::size_t rejected_type_b = 0;    ///< gamma exceeded but rejected by noise_robust
  std::size_t fallback_type_a = 0;    ///< Type B systems that failed to solve -> Type A
  /// e_col on the input points (the paper's: mean over points of |dR|+|dG|+|dB|, sRGB
  /// channels in [0, 1], the function's colour unquantised vs the point's colour).
  double e_col = 0;
  std::size_t e_col_points = 0;  ///< the input points e_col was taken over
  double fit_seconds = 0;   ///< building the octree and the local functions
  double e_col_seconds = 0; ///< evaluating e_col
};

/// The fitted colour function. Cheap to copy (shares immutable state); queries are
/// const and thread-safe and take input (world) units.
class ColourFunction {
 public:
  /// f_L, f_a, f_b at x (blend of the leaves whose ball holds x). Where no ball holds
  /// x: the colour of the nearest input point. With a surface (set_surface), x is
  /// first projected onto its zero set.
  Lab lab(const Vec3d& x) const;
  /// sRGB in [0, 1], unquantised (clamped).
  std::array<double, 3> srgb(const Vec3d& x) const;
  /// 8-bit sRGB.
  Rgb rgb(const Vec3d& x) const;
  /// Batched rgb (parallel, same results).
  std::vector<Rgb> rgbs(const std::vector<Vec3f>& xs) const;
  /// Batched lab (parallel on `threads`, 0 = all cores; the same values as lab, bit for
  /// bit): nearby points share one walk of the octree.
  std::vector<Lab> labs(const std::vector<Vec3f>& xs, int threads = 0) const;

  /// (c) Colour off the surface: when set, queries are evaluated at the projection of x
  /// onto f = 0 (Newton steps x <- x - f grad f / |grad f|^2, at most `steps`, stopping
  /// below tolerance 1e-6 of the bounding diagonal), so offsets of the surface take the
  /// colour of the nearest surface part. The function must outlive this object (and its
  /// copies). nullptr switches it off.
  void set_surface(const ImplicitFunction* surface, int steps = 4);

  /// Type of the leaf that contributes most (largest weight) at x; kA where none.
  ColourCellType dominant_type(const Vec3d& x) const;

  /// e_col over a coloured cloud (the paper's metric; see ColourDiagnostics::e_col).
  double e_col(const Cloud& coloured, int threads = 0) const;

  const ColourDiagnostics& diagnostics() const;
  const ColourParams& params() const;

  struct Impl;

 private:
  friend ColourFunction fit_colour(const Cloud&, const ColourParams&);
  std::shared_ptr<const Impl> impl_;
  const ImplicitFunction* surface_ = nullptr;
  int projection_steps_ = 4;
};

/// Fits the colour function to a coloured cloud. Normals are optional (the cells'
/// tangent frames then come from the points' PCA); when present they give the frame
/// as in the paper (weighted mean normal). Deterministic for any params.threads.
/// InvalidInput when the cloud has no colours ("colour_function: the cloud has no
/// colours", which the CLI turns into a notice), is empty, has non-finite coordinates,
/// inconsistent attributes, all points equal, or a parameter out of range.
ColourFunction fit_colour(const Cloud& coloured_points, const ColourParams& params = {});

/// Sets mesh.colours from f at the vertices (parallel; 0 = all cores).
void colour_mesh(Mesh& mesh, const ColourFunction& f, int threads = 0);

/// The same, except at vertices where `surface` is not trusted (no data near, e.g.
/// a closed underside the scanner never saw): there the local fits would only
/// extrapolate (quadratics drift to colours the object does not have), so those
/// vertices take the inverse-distance mean of the 4 nearest input colours
/// (reconstruct/colour_transfer.h). Returns how many vertices did. On the demo's
/// mustard bottle e_col against the true texture goes 0.114 -> 0.091 (k-NN alone: 0.093).
std::size_t colour_mesh(Mesh& mesh, const ColourFunction& f, const ImplicitFunction& surface,
                        const Cloud& coloured_points, int threads = 0);

}  // namespace station
