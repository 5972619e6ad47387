#pragma once
// Vertex colours for a reconstructed mesh from the coloured input cloud: the
// inverse-distance weighted mean of the k nearest input colours. The surface
// stage's `colour_method: nearest` (reconstruct/surface.h), and the colour
// function's fallback where it is not trusted (reconstruct/colour_function.h); it
// blurs colour boundaries by about the input spacing.
#include "core/geometry.h"

namespace station {

struct ColourTransferParams {
  int neighbours = 4;  ///< k nearest input points per vertex
  int threads = 0;     ///< 0 = all cores; the result does not depend on it
};

/// Sets mesh.colours (one per vertex). InvalidInput when the cloud has no colours
/// or is empty.
void transfer_colours(Mesh& mesh, const Cloud& coloured, const ColourTransferParams& params = {});

}  // namespace station
