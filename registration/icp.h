#pragma once
// Per-view preparation for registration and pairwise point-to-plane ICP.
//
// Preparation (`prepare_view`): non-finite points dropped, statistical outlier
// removal (Rusu et al. 2008, "Towards 3D point cloud based object maps for
// household environments", sec. 4), a voxel-grid downsampled copy for
// registration only (voxel centroids), and PCA normals oriented towards the
// sensor: the scanner-frame origin, checked (registration/viewpoint.h).
//
// ICP (`icp_point_to_plane`): Chen & Medioni 1992 point-to-plane error, each
// step the linearised 6x6 normal equations (Low 2004, "Linear least-squares
// optimization for point-to-plane ICP surface registration"), with a maximum
// correspondence distance shrinking geometrically from a coarse to a fine value
// (as in Rusinkiewicz & Levoy 2001's distance rejection), normal-compatibility
// rejection, and a Huber weight. Correspondence search runs in parallel (TBB)
// over a PointIndex of the target; results are deterministic for a given input.
//
// Guards: fewer than `min_correspondences` matches, or a final overlap (fitness)
// below `min_fitness`, or a non-finite/ill-posed system, is reported as a
// failure (`converged = false`, `message` says why), never as a pose that only
// looks converged.
#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/geometry.h"

namespace station {

class PointIndex;

/// 6x6 matrices in the (rotation, translation) order used throughout
/// registration: a small motion x = (w, v) moves a point p to p + w x p + v.
using Matrix6d = Eigen::Matrix<double, 6, 6>;
using Vector6d = Eigen::Matrix<double, 6, 1>;

struct PrepareParams {
  /// Voxel edge for the registration copy, the clouds' units; 0: no downsampling.
  double voxel_size = 0.0;
  /// Statistical outlier removal: neighbours per point (k), 0 disables it.
  int outlier_neighbors = 16;
  /// A point is an outlier when its mean distance to its k neighbours exceeds
  /// mean + outlier_std_ratio * standard deviation over the view (Rusu's alpha).
  double outlier_std_ratio = 3.0;
  /// Neighbours for the PCA normal of each registration point.
  int normal_neighbors = 16;
  /// Intensity and its gradient per registration point, for coloured ICP
  /// (only when the cloud has colours).
  bool intensity = false;
  /// PCA normals (unoriented) of the full cloud's points over this many neighbours
  /// (the point itself included, as estimate_normals), for a merge: 0 none. Only for
  /// clouds without normals; the outlier removal's own search gives the neighbours
  /// where it found enough.
  int full_normal_neighbors = 0;
};

/// Each point's kNeighbours nearest other points (UINT32_MAX past the last) and
/// `reach`, how near any other point can be (the next one's distance; infinity when
/// the list holds all the others). A query x whose nearest among a point q and q's
/// list is q itself, at d with 2 d < reach(q), has q for its nearest point of all:
/// any point q' off the list has |x - q'| >= |q - q'| - d >= reach - d > d.
struct NeighbourGraph {
  static constexpr int kNeighbours = 8;
  std::vector<std::uint32_t> neighbours;  ///< kNeighbours per point
  std::vector<float> reach;
  bool empty() const { return reach.empty(); }
};
NeighbourGraph neighbour_graph(const PointIndex& index);

/// A view ready for registration. Scanner frame throughout.
struct PreparedView {
  Cloud full;                        ///< outliers and non-finite points removed (attributes kept)
  std::vector<Vec3f> points;         ///< downsampled registration points, N
  std::vector<Vec3f> normals;        ///< N unit normals facing the sensor (`viewpoint`)
  /// The sensor: the scanner-frame origin, or where the view's normals say it is
  /// when the origin fails registration/viewpoint.h's check (imported views).
  Vec3f viewpoint = Vec3f::Zero();
  bool viewpoint_at_origin = true;
  double grazing_origin = 0;  ///< share of points seen beyond 80 degrees from the origin
  std::shared_ptr<PointIndex> index; ///< over `points`
  /// The registration points' neighbour graph (neighbour_graph; empty: not computed):
  /// ICP finds a point's nearest from its last correspondence without a search where
  /// the graph proves it.
  NeighbourGraph graph;
  /// Only with PrepareParams::intensity and a cloud with colours (else empty): intensity in [0, 1] of each
  /// registration point (mean over its voxel's neighbourhood) and its
  /// tangent-plane gradient (capture/coloured_icp.h), for IcpObjective::kColored.
  std::vector<float> intensity;
  std::vector<Vec3f> intensity_gradient;
  std::size_t dropped_nonfinite = 0;
  std::size_t dropped_outliers = 0;
  /// With PrepareParams::full_normal_neighbors: `full`'s points' PCA normals,
  /// unoriented (estimate_normals' over `full` alone); empty otherwise.
  std::vector<Vec3f> full_normals;
};

/// PCA normals (smallest eigenvector of the k-neighbour covariance), oriented
/// towards `viewpoint` (the sensor; the scanner-frame origin for raw views): core/normals.h's
/// estimate_normals, with the direction to the viewpoint where a neighbourhood is degenerate.
std::vector<Vec3f> pca_normals(const PointIndex& index, int k, const Vec3f& viewpoint);


/// Runs the preparation above. Never throws on empty input: an empty view gives
/// an empty PreparedView (the caller reports it).
PreparedView prepare_view(const Cloud& cloud, const PrepareParams& params);

/// Error minimised by ICP.
enum class IcpObjective {
  kPointToPlane,  ///< (p - q) . n_q (Chen & Medioni 1992)
  kSymmetric,     ///< (p - q) . (n_p + n_q), linearised (Rusinkiewicz 2019, "A symmetric objective function for ICP")
  kPointToPoint,  ///< |p - q|^2 (Besl & McKay 1992), same linearised solver
  /// Point-to-plane + photometric term (Park, Zhou & Koltun 2017, "Colored
  /// point cloud registration revisited"; capture/coloured_icp.h). Needs
  /// `intensity` on both views and `intensity_gradient` on the target; without
  /// them it runs as point-to-plane.
  kColoured,
  /// Generalized ICP (Segal, Haehnel & Thrun 2009, "Generalized-ICP"): the
  /// plane-to-plane Mahalanobis distance r^T (C_q + R C_p R^T)^-1 r with
  /// plane-like covariances I - (1 - eps) n n^T from the views' normals
  /// (IcpParams::gicp_epsilon), solved by the same Gauss-Newton steps.
  kGeneralized,
};

struct IcpParams {
  IcpObjective objective = IcpObjective::kPointToPlane;
  /// Maximum correspondence distance of the first iteration, the clouds' units.
  double max_distance_start = 0.01;
  /// Final maximum correspondence distance, the clouds' units (reached by shrinking).
  double max_distance_end = 0.002;
  /// Factor applied to the maximum distance after each iteration (in (0, 1]).
  double shrink = 0.85;
  int max_iterations = 60;
  /// Stop (at the final distance) when an update is smaller than this (radians, the clouds' units).
  double convergence_rotation = 1e-6;
  double convergence_translation = 1e-6;
  /// Units of the clouds in a metre (1 for metres, 1000 for millimetres): the paper's
  /// coloured_lambda balances residuals in metres (the colour term's weight is scaled
  /// by its square), and the fixed thresholds inside (an exhausted budget still counts
  /// as converged below 1e-5 m of step) are in metres. Every length here
  /// (coloured_reference_distance included) is in the clouds' units as given.
  double units_per_metre = 1;
  /// Correspondences whose normals differ by more than this are dropped, degrees.
  double max_normal_angle_deg = 60.0;
  /// Huber threshold on point-to-plane residuals, as a fraction of the current
  /// maximum distance (robust weighting; 0 disables it).
  double huber_fraction = 0.3;
  /// kColored: weight lambda of the geometric term, (1 - lambda) on the colour
  /// term (the paper's and Open3D's 0.968; residuals in metres and in [0, 1] intensity).
  double coloured_lambda = 0.968;
  /// kColored: the final distance at which lambda keeps the paper's balance. The
  /// colour term is weighted (1 - lambda) (max_distance_end / this)^2, so the balance
  /// does not depend on the object's size (an intensity gradient is per metre).
  /// 0.04 m: the first (coarsest) of Park et al.'s (and Open3D's) 4 / 2 / 1 cm
  /// schedule, where lambda is first applied; of the three, the one that registered
  /// the simulated bottle best (docs/registration.md). 0 keeps the weight 1 - lambda
  /// at every scale.
  double coloured_reference_distance = 0.04;
  /// kGeneralized: covariance eigenvalue along the normal (the others are 1),
  /// Segal's epsilon (0.001, as in the paper and PCL).
  double gicp_epsilon = 1e-3;
  /// Guards: at least this many correspondences ...
  int min_correspondences = 50;
  /// ... and at least this fraction of source points matched at the end.
  double min_fitness = 0.15;
  /// While the correspondence distance is still above max_distance_end, use
  /// every coarse_stride-th source point only (1: all); the iterations at the
  /// final distance and the diagnostics always use all of them.
  int coarse_stride = 1;
};

/// ICP outcome. `transform` maps source points onto the target:
/// q_target = transform * p_source.
struct IcpResult {
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();
  bool converged = false;       ///< the guards passed and the update became small
  int iterations = 0;
  std::size_t correspondences = 0;  ///< inliers at max_distance_end
  double fitness = 0;           ///< correspondences / source points
  double inlier_rmse = 0;       ///< Euclidean distance of inlier pairs, the clouds' units
  double plane_rmse = 0;        ///< point-to-plane distance of inlier pairs, the clouds' units
  /// J^T J of the final point-to-plane system (rotation about the target-frame
  /// origin, then translation); the information of the estimate for a pose graph.
  /// kColored: the joint system divided by lambda (geometric part + the colour
  /// part weighted (1 - lambda) / lambda).
  Matrix6d hessian = Matrix6d::Zero();
  std::string message;          ///< why it failed (empty when converged)
  /// Nearest-point queries over all passes, and how many of them the target's
  /// neighbour graph answered without a tree search.
  std::size_t queries = 0, graph_answers = 0;
};

/// Point-to-plane ICP of `source` (points + normals) onto `target` (points,
/// normals and index), starting from `initial` (target <- source).
IcpResult icp_point_to_plane(const PreparedView& source, const PreparedView& target,
                             const Eigen::Matrix4d& initial, const IcpParams& params = {});

/// Rotation angle of a rigid transform's 3x3 block, degrees.
double rotation_angle_deg(const Eigen::Matrix4d& T);
/// exp of a small motion x = (w, v): [Rodrigues(w) | v].
Eigen::Matrix4d motion_exp(const Vector6d& x);
/// Inverse of a rigid transform.
Eigen::Matrix4d rigid_inverse(const Eigen::Matrix4d& T);

}  // namespace station
