#pragma once
// Global (initial-pose-free) registration of two views by local features:
// FPFH descriptors (capture/features.h) matched by nearest descriptor, then a
// RANSAC-style consensus over triples of matches with prerejection (in the
// manner of PCL's SampleConsensusPrerejective and Open3D's correspondence
// checkers): a sampled triple is discarded before any fitting when its edge
// lengths in the source and in the target differ by more than a factor
// `edge_similarity`, or when the normals of a match disagree after the
// triple's rigid fit. Surviving hypotheses are scored by the number of matches
// they bring within `inlier_distance`. The best distinct hypotheses are
// returned for the caller to refine by ICP (registration.cpp keeps the one ICP
// gives the best overlap). Deterministic for a given seed.
#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "registration/features.h"
#include "core/geometry.h"

namespace station {

class PointIndex;

/// A view reduced for feature matching.
struct FeatureView {
  std::vector<Vec3f> points;
  std::vector<Vec3f> normals;  ///< unit, consistently oriented
  std::vector<FpfhDescriptor> features;
  std::shared_ptr<PointIndex> index;  ///< over points
  /// Optional, one per point (with_colours): the point's chromaticity, rgb / max(r + g + b,
  /// kChromaDark), so hues compare whatever the exposure and dark points stay near zero.
  /// Where both views carry them, a feature match must agree in it (colour_gate).
  std::vector<Vec3f> chroma;
};

struct GlobalRegistrationParams {
  /// Voxel edge of the feature cloud, the clouds' units (> 0).
  double voxel_size = 0.005;
  /// Neighbours for the PCA normals (make_feature_view from bare points).
  int normal_neighbors = 16;
  /// FPFH radius, in voxels.
  double feature_radius_voxels = 5.0;
  int max_feature_neighbors = 100;
  /// A match is an inlier of a hypothesis when the moved source point is
  /// within this many voxels of its matched target point.
  double inlier_distance_voxels = 1.5;
  /// Prerejection: ratio of corresponding edge lengths of a sampled triple.
  double edge_similarity = 0.9;
  /// Prerejection: matched normals must agree within this angle after the
  /// triple's fit, degrees (0 disables the check).
  double normal_angle_deg = 45.0;
  int max_iterations = 200000;
  /// Stop once a hypothesis would have been found with this probability.
  double confidence = 0.9999;
  /// Hypotheses returned (distinct: > 5 degrees or 2 voxels apart), best first.
  int hypotheses = 6;
  /// Fewer inlier matches than this is a failure.
  int min_inliers = 8;
  std::uint64_t seed = 42;
  /// Where both views carry chromaticities (FeatureView::chroma), a descriptor match is
  /// only made between points whose chromaticities are within this distance: on a
  /// shape that looks alike turned (a cube's faces), the shape's features alone match
  /// every face to every other, and RANSAC's best pose lands on a turned twin.
  double colour_gate = 0.08;
  /// ...looked for among this many nearest descriptors (nearest_descriptors_gated).
  int colour_candidates = 32;
};

struct GlobalHypothesis {
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();  ///< target <- source
  int inliers = 0;
  double inlier_rmse = 0;  ///< the clouds' units, over the inlier matches
};

struct GlobalRegistrationResult {
  bool success = false;
  Eigen::Matrix4d transform = Eigen::Matrix4d::Identity();  ///< the best hypothesis
  std::vector<GlobalHypothesis> hypotheses;                  ///< best first
  std::size_t matches = 0;      ///< descriptor matches sampled from
  int iterations = 0;
  int prerejected = 0;          ///< triples rejected before scoring
  std::string message;          ///< why it failed
};

/// Voxel-downsamples `points` (scanner frame), estimates PCA normals facing
/// `viewpoint` and computes FPFH. Empty input gives an empty view.
FeatureView make_feature_view(const std::vector<Vec3f>& points, const Vec3f& viewpoint,
                              const GlobalRegistrationParams& params);
/// The same for points that carry oriented normals already (e.g. a merged
/// model): downsampled, each kept point takes the normal of its nearest input point.
FeatureView make_feature_view(const std::vector<Vec3f>& points, const std::vector<Vec3f>& normals,
                              const GlobalRegistrationParams& params);

/// Chromaticities are rgb / max(r + g + b, this): darker points tend to zero.
inline constexpr float kChromaDark = 90;
/// `view` with chroma from `coloured`'s colours (each feature point takes its nearest
/// point's; the same frame). `view` unchanged where `coloured` has no colours.
FeatureView with_colours(FeatureView view, const Cloud& coloured);

/// Aligns `source` onto `target` without an initial pose. InvalidInput on
/// non-positive voxel size or edge_similarity outside (0, 1].
GlobalRegistrationResult register_global(const FeatureView& source, const FeatureView& target,
                                         const GlobalRegistrationParams& params = {});

}  // namespace station
