#pragma once
// Point-set thinning shared by the stages: voxel-grid downsampling and statistical
// outlier removal.
#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/geometry.h"

namespace station {

/// Voxel-grid downsampling: one point per occupied voxel (the centroid of its
/// points), in a deterministic order. `voxel_size` <= 0 returns the points as they are.
std::vector<Vec3f> voxel_downsample(const std::vector<Vec3f>& points, double voxel_size);

/// Indices of the points kept by statistical outlier removal (Rusu et al. 2008).
/// With `neighbours`, each point's k + 1 nearest (itself first, closest first) are
/// left there, k + 1 entries per point (UINT32_MAX past the last found), for the
/// caller's own use of the same search (registration/icp.h: the views' normals).
std::vector<std::size_t> statistical_inliers(const std::vector<Vec3f>& points, int k, double std_ratio,
                                             std::vector<std::uint32_t>* neighbours = nullptr);

}  // namespace station
