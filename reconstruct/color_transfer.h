#pragma once
// Vertex colours for a reconstructed mesh from the coloured input cloud: the
// inverse-distance weighted mean of the k nearest input colours. A plain
// stand-in until the MPU colour function (issue 7) lands; it blurs colour
// boundaries by about the input spacing.
#include "core/geometry.h"

namespace station {

struct ColorTransferParams {
  int neighbours = 4;  ///< k nearest input points per vertex
  int threads = 0;     ///< 0 = all cores; the result does not depend on it
};

/// Sets mesh.colors (one per vertex). InvalidInput when the cloud has no colours
/// or is empty.
void transfer_colors(Mesh& mesh, const Cloud& coloured, const ColorTransferParams& params = {});

}  // namespace station
