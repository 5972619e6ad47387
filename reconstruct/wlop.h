#pragma once
// Consolidation (`station consolidate`): turns a merged, uneven, noisy cloud into
// a thinner, even set of points on the surface.
//
// Method (../shared/docs/methods.md section 1; equation numbers are those of the
// paper ../shared/seeds/edge-preserving-wlop_awano.txt, Awano 2013, which restates
// WLOP, Huang et al. 2009, as eqs. 1-9):
//
//   x_i <- E1 + mu E2                                                     (eq. 1)
//   E1 = sum_j p_j (alpha_ij / v_j) / sum_j (alpha_ij / v_j)              (eq. 2)
//   E2 = sum_r (x_i - x_r) w_r beta_ir / sum_r w_r beta_ir                (eq. 3)
//   alpha_ij = theta(|x_i - p_j|) / |x_i - p_j|                           (eq. 4)
//   beta_ir = theta(|x_i - x_r|) eta(|x_i - x_r|) / |x_i - x_r|           (eq. 5)
//   v_j = 1 + sum_{j' != j} theta(|p_j - p_j'|)     input density, once   (eq. 6)
//   w_i = 1 + sum_{r != i} theta(|x_i - x_r|)       every iteration       (eq. 7)
//   theta(r) = exp(-r^2 / (h/4)^2)                                        (eq. 8)
//   eta(r) = -r                                                           (eq. 9)
//
// Every sum runs over the points strictly within h (theta(h) = e^-16 ~ 1e-7):
// fixed-radius queries on a grid over the input built once and a grid over the
// projected set rebuilt each iteration. Updates are Jacobi style (every x_i from
// the previous iterate) and each point's sums run in a fixed order, so the output
// depends on the input, the parameters and the seed only, not on the thread count
// (on one machine: the vector width the kernels pick, AVX-512, AVX2 or SSE2, and
// fused multiply-adds can change the last bits between CPUs). Positions, kernels
// and sums are double; theta and 1/r come from our own vector exp and rsqrt
// (about 1 ulp). The edge variant's sums over its inverted neighbourhood (and the
// offsets gathered for them) are float, about 1e-7 relative to h: offsets of
// order h need no more, and they run twice the lanes.
//
// beta_ir: eq. 5 as printed gives theta(r) eta(r) / r = -theta(r). WLOP's own
// definition (Lipman et al. 2007, Huang et al. 2009), which eq. 5 restates, is
// theta(r) |eta'(r)| / r = theta(r) / r. The two differ: with -theta a neighbour's
// push on x_i shrinks with its distance, so close pairs barely separate and points
// pair up once h/4 exceeds the output spacing. We use theta / r by default
// (RepulsionWeight; docs/consolidation.md has the measurements) and keep the
// printed form selectable.
//
// Conventions the equations leave open (docs/consolidation.md says why):
// - A pair closer than 1e-9 h is left out of E1 (alpha is singular there; the
//   initial x_i coincide with input points), and of E2 with beta = theta / r.
// - A point with no input point within h keeps its position for that iteration
//   (neither E1 nor E2 is defined for it); WlopResult::isolated_points counts them.
// - Without projected neighbours E2 = 0.
//
// Edge-preserving variant (Awano 2013, section 3), for each x_i and iteration:
//   c_i = x_i + d_bb sum_l n_l / (2 k_h)                                  (eq. 10)
//   n_l: the "simple normal" of input point p_l (eqs. 11-12; simple_normal in
//   core/normals.h): the plane through the centroid of p_l's neighbours
//   within h (at most 32 of them, evenly strided) with the least sum of absolute
//   distances. Signs are made consistent around x_i through the PCA normals
//   (smooth across edges): each n_l is flipped to agree with the PCA normal of the
//   input point nearest x_i. Where the n_l cancel (|sum| < 0.2 k_h) plain E1 is used.
//   Inversion f(p, c, r): the point at distance 2r - |p - c| from c along the ray
//   c -> p (eq. 13 gives it relative to c; it is its own inverse).
//   Upsampling (eqs. 14-15): copy t = 0, 1, ... of the neighbours is shifted by
//   t l (l along c_i -> x_i, |l| = R / m) and inverted with radius R + t |l| / 2,
//   until the copies put at least k_h points within h of x'_i = f(x_i, c_i, R).
//   (Eq. 15 prints (1 + |l|/2) R; R + t|l|/2 keeps each point's inverted distance
//   from c_i, so the copies only differ in lateral scale and stack on x'_i.)
//   E1' (eqs. 16-18) is E1 taken over the copies around x'_i; E1 = f(E1', c_i, R) (eq. 19).
//   v'_s of eq. 18 is by default carried over from v_j through the inversion's
//   Jacobian (InvertedDensity), and E2 loses its component along c_i -> x_i
//   (EdgeRepulsion); both are our decisions, explained there.
#include <cstddef>
#include <functional>
#include <vector>

#include "core/geometry.h"

namespace station {

enum class WlopMethod {
  kWlop,      ///< WLOP, eqs. 1-9
  kEdgeWlop,  ///< edge-preserving WLOP: E1 through spherical inversion, eqs. 10-19
};

/// The input density weights v_j of E1 (eq. 6).
enum class InputDensity {
  kComputed,  ///< eq. 6, computed once for every input point: O(|J| k) setup
  /// v_j = 1 for all j (plain LOP attraction): what CGAL's WLOP does unless asked for
  /// require_uniform_sampling. Skips the setup sum, which dominates when the input
  /// is dense relative to h (1M points at a 100k-point radius: ~4400 neighbours each).
  kUniform,
};

/// Normals that place the inversion centre c_i (eq. 10) of the edge variant.
enum class EdgeNormals {
  kSimple,  ///< eqs. 11-12 on the input (L1 plane fits), whatever the input carries
  kInput,   ///< the input's normals (assumed consistently oriented) when it has them, else kSimple
};

/// The repulsion E2 of the edge variant's update x_i <- E1 + mu E2 (eq. 1).
enum class EdgeRepulsion {
  /// E2 without its component along the inversion axis a (c_i -> x_i). In the
  /// inverted space, where the paper takes E1 because the neighbourhood is smooth
  /// there, the neighbourhood lies across a and WLOP's repulsion is tangential; in
  /// the original space E2's part along a pushes points off a sharp edge (the
  /// neighbours on both faces lie below the crease), which plain WLOP's rounded E1
  /// happens to offset. Measured on a 90-degree crease (16k points to 3200, h = 0.08,
  /// tests/reconstruct/wlop_test.cpp): mean distance to the surface of the points
  /// within h/4 of the crease 0.0032 with kFull, 0.0008 with kTangential (plain
  /// WLOP 0.0015). Away from edges it also stops WLOP's drift off the surface.
  kTangential,
  kFull,  ///< E2 whole, as in eq. 1
};

/// The repulsion weight beta_ir of E2 (eqs. 3 and 5), for both methods.
enum class RepulsionWeight {
  /// beta = theta(r) |eta'(r)| / r = theta(r) / r (eta(r) = -r): WLOP's repulsion
  /// weight as Lipman et al. 2007 derive it and Huang et al. 2009 use it. Each
  /// neighbour within reach pushes x_i away with a weight that does not vanish as
  /// the pair closes, so close pairs separate. The default.
  kOriginal,
  /// beta = theta(r) eta(r) / r = -theta(r): eq. 5 as printed in the restatement
  /// (the sign cancels in E2's normalisation). A neighbour's push shrinks with its
  /// distance: on the fandisk at the benchmark's radius (h = 8 x the input spacing)
  /// the output's uniformity is 0.51 here against 0.62 with kOriginal, on the
  /// literal blade setting 0.36 against 0.54 for the edge variant.
  kPrinted,
};

/// The repulsion E2 of plain WLOP's update x_i <- E1 + mu E2 (eq. 1).
enum class WlopRepulsion {
  kFull,  ///< E2 whole, as in eq. 1
  /// E2 without its component along the local normal at x_i (the direction of least
  /// spread of the projected points within h, unweighted PCA; left whole where fewer
  /// than 3 are within h). Not in the paper: wherever the neighbours are not coplanar
  /// (noise, curvature) E2 has a part along the normal, and it feeds back into the
  /// drift off the surface that CGAL's users report (docs/consolidation.md,
  /// "Behaviour worth knowing"); the edge variant's kTangential removes it the same
  /// way along its inversion axis. Costs one more pass over the projected neighbours
  /// and a 3x3 eigen-solve per point and iteration. The default (issue 30: it beat CGAL
  /// on accuracy and speed).
  kTangential,
};

/// The attraction of the update (both methods).
enum class WlopAttraction {
  /// Not in the paper (issue 30; docs/consolidation.md "Projection" has the measurements
  /// and says why). Each iteration, for every x_i:
  ///   fit: the input points within r_f of x_i, weighted by the biweight
  ///        (1 - r^2 / r_f^2)^2 of their distance along the plane of the iteration
  ///        before (of the 3-D distance the first time) and by 1 / v_j (eq. 6): their
  ///        weighted centroid c_i and least-spread direction n_i (PCA);
  ///   x_i <- x_i + ((c_i - x_i) . n_i) n_i      onto the plane,
  ///          + pull                             the centroid's offset along the plane,
  ///                                             beyond a dead zone of 0.4 standard
  ///                                             deviations of the weights (0.3
  ///                                             where the edge variant fits two
  ///                                             or more faces),
  ///          + mu E2_t                          E2 (eq. 3) without its part along n_i,
  /// E2 and w_i (eq. 7) with theta over a radius of 2.6 output spacings (from the area
  /// the projected points cover, WlopResult::repulsion_radius) instead of h. After the
  /// last iteration every point goes onto its plane once more. Inputs with normals
  /// (taken as oriented, as scans' are) fit each point to the neighbours facing its way,
  /// which keeps the two faces of a part thinner than r_f apart, and the fits' 1 / v_j
  /// then count the neighbours facing the same way only; so does the area, measured
  /// again after the 6th iteration (each face is even by then).
  /// The iterations start from a spread-out subset of the input (dart throwing in a
  /// seeded random order, a maximal Poisson-disk sample sized to |I|) instead of
  /// initial_subset's random one, whose clumps E2 evens out only slowly.
  /// The edge variant at a crease (two or more faces found): E2 counts each neighbour
  /// at |t| + |a|, t and a its offset's parts along and across the point's face (its
  /// distance over the surface across a right-angled crease), with beta = theta / r
  /// whatever repulsion_weight says: with straight distances the points left a gap on
  /// both sides of every edge.
  /// The edge variant: where fewer than 90 % of the weight has a simple normal (eqs.
  /// 11-12, over r_f) within 35 degrees of n_i, up to three faces are fitted, each to the
  /// neighbours whose simple normal lies within 35 degrees of a face normal (the
  /// candidates: strided neighbours' normals, the best supported first), and x_i goes
  /// onto the nearest face plane: a crease stays a crease.
  /// r_f is WlopParams::fit_radius; by default sized to the input's spacing and noise.
  /// It denoises (a fit averages tens of points, where eq. 2's singular alpha keeps x_i
  /// on the input point it started from) and evens (the motion along the surface is
  /// E2's, no longer held by eq. 2 to input points).
  kProjection,
  /// Eq. 2 (plain WLOP) or eq. 19 (the edge variant) as printed: x_i <- E1 + mu E2.
  kL1,
};

/// Density weights v'_s of the inverted, upsampled neighbourhood (eq. 18).
enum class InvertedDensity {
  /// v'_s = 1 + (v_j - 1) sum_t 1/sigma_t(j): the input density of the point p_j that
  /// u_s copies, divided by the area scale sigma_t of the inversion of copy t
  /// (summed over the copies that overlap there). O(k_h) per point and iteration.
  kJacobian,
  /// Eq. 18 literally, over all pairs of the upsampled set. O(k_h^2) per point and
  /// iteration: tens of times slower; kept to check kJacobian against.
  kExact,
};

struct WlopParams {
  WlopMethod method = WlopMethod::kWlop;
  /// |I|, the number of output points. 0: round(ratio * |J|) (at least 1).
  /// More than the input holds: clamped to |J| (the whole input is projected;
  /// WlopResult::clamped says so).
  std::size_t target_points = 0;
  /// |I| / |J| when target_points is 0; in (0, 1].
  double ratio = 0.2;
  /// With target_points 0: |I| is kept within [min(min_points, |J|), max_points]
  /// (0: no bound on that side), e.g. the profile's `points: auto`.
  std::size_t min_points = 0, max_points = 0;
  /// k, iterations of eq. 1 (>= 0). 35 is CGAL's default for
  /// wlop_simplify_and_regularize_point_set and what the benchmark compares at;
  /// the paper runs 100 "to be sure of convergence".
  int iterations = 35;
  /// h, the support radius of theta (absolute, input units). 0: 4 d_bb / sqrt(|J|),
  /// which is the paper's 4 sqrt(d_bb / |J|) for its d_bb = 1 (it normalises the
  /// model), made scale-invariant.
  double radius = 0;
  /// mu, weight of the repulsion E2 (eq. 1); in [0, 0.5) per Huang et al.
  double mu = 0.45;
  InputDensity input_density = InputDensity::kComputed;
  /// The attraction (both methods).
  WlopAttraction attraction = WlopAttraction::kProjection;
  /// r_f, the radius of kProjection's plane fits (absolute). 0: max(1.5 h_0, 4.5 sigma)
  /// with h_0 = 4 d_bb / sqrt(|J|) (the default h, whatever `radius` is) and sigma the
  /// input's noise estimate (WlopResult::noise).
  double fit_radius = 0;
  /// Plain WLOP's E2 with attraction kL1 (the edge variant has edge_repulsion;
  /// kProjection's E2 is always tangential to its fit).
  WlopRepulsion repulsion = WlopRepulsion::kTangential;
  /// beta_ir of E2 (both methods).
  RepulsionWeight repulsion_weight = RepulsionWeight::kOriginal;
  /// Seed of the initial subset (initial_subset's draw; kProjection's dart order).
  unsigned seed = 1;
  /// When the input is a part of a larger cloud (a block, reconstruct/blocks.h): the
  /// whole cloud's d_bb and |J|. The defaults of h and r_f and the edge variant's
  /// eq. 10 then take them instead of the part's, so every part works at the whole
  /// cloud's scale. 0: the input's own.
  double frame_diagonal = 0;
  std::size_t frame_points = 0;
  /// Worker threads (0 = all cores). The output does not depend on it.
  int threads = 0;
  /// Called after every iteration with (iterations done, iterations in all).
  std::function<void(int, int)> progress;

  // ---- edge variant (method == kEdgeWlop) ----
  /// R, the inversion radius, in units of d_bb (> 0.25). The paper only asks for
  /// R >> h; but eq. 10 puts c_i D = d_bb |mean n| / 2 from x_i, and f maps
  /// distance d from c_i to 2R - d, a bijection on the neighbourhood only while
  /// 2R > D + h: the bound is set by d_bb, not h. What R controls is the lateral
  /// magnification g = (2R - D) / D of the inverted neighbourhood, i.e. how much
  /// the inversion flattens an edge (and narrows the attraction kernel). 0.6 gives
  /// g = 1.4 on flat parts and 2.4 on a right-angled edge with 2-3 copies; 1.0
  /// (g = 3 and 4.7) needs about 7 copies and was no better in our tests
  /// (docs/consolidation.md). Clamped per point to at least D + h.
  double inversion_radius = 0.6;
  /// m: the shift per copy is |l| = R / m (eq. 15; the paper finds m > 10 equivalent).
  int shift_divisions = 20;
  /// Upper bound on the number of copies K (eq. 14) when k'_h stays below k_h; in [1, 64].
  int max_copies = 64;
  EdgeNormals edge_normals = EdgeNormals::kSimple;
  InvertedDensity inverted_density = InvertedDensity::kJacobian;
  EdgeRepulsion edge_repulsion = EdgeRepulsion::kTangential;

  // ---- output attributes ----
  /// Estimate output normals (PCA over the normal_neighbours nearest output points,
  /// itself included) and orient them: to agree with the input's normals when it has
  /// them (orient_normals_to, 8 nearest input points), else by propagation over a
  /// minimum spanning tree from the highest point, made to point up
  /// (orient_normals_mst): outwards for a closed object. core/normals.h.
  bool estimate_normals = true;
  int normal_neighbours = 12;
};

struct WlopResult {
  /// |I| points (float), in the order of their initial input points (initial_subset,
  /// or kProjection's spread-out subset, both in input order). Colours when the input has
  /// them: each the mean of the input colours within h of the final point weighted
  /// like plain E1 (alpha_ij / v_j, for both methods), in 8-bit sRGB, rounded (the
  /// nearest input point's colour when none is within h). Normals when
  /// params.estimate_normals: unit, oriented outwards.
  Cloud cloud;
  /// The same points in double (|I| x 3), as computed.
  std::vector<Vec3d> positions;

  std::size_t input_points = 0;      ///< |J|
  std::size_t requested_points = 0;  ///< |I| asked for (target_points or ratio * |J|)
  /// Requested more than |J|, or than the input's distinct positions when the initial
  /// subset had to avoid duplicates (see consolidate); |I| is then that count.
  bool clamped = false;
  std::size_t output_points = 0;     ///< |I|
  int iterations = 0;                ///< iterations run
  double radius = 0;                 ///< h used (absolute)
  /// kProjection: the input's noise estimate sigma (median RMS residual of plane fits
  /// over the k nearest points, k = 16, 64 or 256, the smallest whose neighbourhood is 4
  /// times as wide as its residual; curvature adds to it) and the fit radius r_f used.
  double noise = 0;
  double fit_radius = 0;
  /// kProjection: the input points the fits use (all of them, or a seeded random subset
  /// holding about 96 within r_f where the input is denser).
  std::size_t fit_points = 0;
  /// kProjection: the surface area estimated from the projected points (each standing
  /// for pi rho^2 / 15, rho the distance to its 16th nearest, itself counted; with
  /// oriented normals, the 16th facing its way, measured again after the 6th
  /// iteration) and the radius of E2 and w_i: 2.6 x the output's spacing on that area,
  /// sqrt(2 A / (sqrt 3 |I|)). kL1: h.
  double area = 0;
  double repulsion_radius = 0;
  double bbox_diagonal = 0;          ///< d_bb of the input
  /// Points left where they were in the last iteration for want of input points
  /// within h.
  std::size_t isolated_points = 0;
  /// Edge variant, last iteration: mean number of copies K per point, and the
  /// points that fell back to plain E1 (normals cancelling, |sum n_l| < 0.2 k_h).
  double mean_copies = 0;
  std::size_t plain_fallbacks = 0;

  double seconds = 0;             ///< whole call
  double seconds_setup = 0;       ///< input grid, densities v_j (and simple normals)
  double seconds_iterations = 0;  ///< the k iterations
  double seconds_attributes = 0;  ///< colours and normals
};

/// Consolidates `input` (|J| points; colours and normals optional) into
/// |I| points by WLOP or its edge-preserving variant. See the file comment.
/// InvalidInput on an empty cloud, non-finite coordinates, inconsistent
/// attributes, a zero-size bounding box (all points identical), or a bad
/// parameter (ratio outside (0, 1], iterations < 0, radius < 0 or non-finite,
/// mu outside [0, 0.5), threads < 0, inversion_radius <= 0.25,
/// shift_divisions < 1, max_copies outside [1, 64], normal_neighbours < 3).
WlopResult consolidate(const Cloud& input, const WlopParams& params = {});

/// |I| asked for from an n-point input: target_points, or round(ratio * n) (at least
/// 1) within [min(min_points, n), max_points]; WlopResult::requested_points. The
/// output holds min(this, n).
std::size_t wlop_requested_points(std::size_t n, const WlopParams& params);

/// InvalidInput ("consolidate: radius 10 is larger than the cloud itself ...") when
/// params.radius or params.fit_radius exceeds `diagonal`, the cloud's bounding box
/// diagonal: consolidate() and the blocked run refuse such a radius alike.
void check_radii_within(const WlopParams& params, double diagonal);

/// The initial projected set: `count` distinct indices into an n-point input,
/// drawn by a partial Fisher-Yates shuffle driven by std::mt19937_64(seed) and
/// returned sorted. Same n, count and seed, same subset, on any platform.
/// count is clamped to n.
std::vector<int> initial_subset(std::size_t n, std::size_t count, unsigned seed);

}  // namespace station
