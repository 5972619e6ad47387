#pragma once
// Fusion of overlapping points when registered views are merged (issue #3,
// item 6; docs/registration.md "Merge").
//
// Where two views saw the same surface, concatenating them doubles the point
// density there and keeps both views' noise side by side (a rough, doubled
// skin). Fusion averages a point into a point kept from an earlier view when
// it lies within `distance` of it; points of the same view are never fused
// with each other (a view's own sampling is kept), and a kept point takes at
// most one point from each later view: of the points whose nearest kept point
// it is, the nearest; the others are kept as new points.
#include <cstddef>
#include <vector>

#include "core/geometry.h"

namespace station {

struct FuseStats {
  std::size_t input = 0;   ///< points over all clouds
  std::size_t output = 0;  ///< points in the fused cloud
  std::size_t fused = 0;   ///< points averaged into an earlier view's point
};

/// Fuses clouds that are already in one frame, in the given order (see the
/// file comment). Positions, normals and colours are the plain means of the
/// points fused into each output point; a normal pointing against the kept
/// point's is flipped before it is added. Attributes are kept only when every
/// non-empty cloud has them. `distance` <= 0 (or not finite) concatenates.
/// Non-finite points are dropped. Deterministic: the result depends only on
/// the input and its order, not on the thread count.
Cloud fuse_clouds(const std::vector<Cloud>& clouds, double distance, FuseStats* stats = nullptr);

/// Median distance from a point to its nearest neighbour, over at most
/// `samples` points spread evenly through the cloud (0 for fewer than 2 points).
double median_spacing(const std::vector<Vec3f>& points, std::size_t samples = 2000);

}  // namespace station
