#pragma once
// Marching-cubes case table, derived programmatically (no pasted table).
// Corner c of a cell sits at offset (c & 1, (c >> 1) & 1, (c >> 2) & 1); edge e joins
// mc_edge_corner[e][0] and [1] along axis e / 4. For each of the 256 sign
// configurations (bit c set: corner c inside, f < iso) the table lists triangles as
// triples of edge indices, counter-clockwise seen from outside.
#include <array>
#include <cstdint>
#include <vector>

namespace station::mc {

/// Corners joined by each of the 12 edges; edges 4a..4a+3 run along axis a.
const std::array<std::array<int, 2>, 12>& edge_corners();
/// Triangles (edge-index triples) of each configuration.
const std::array<std::vector<std::array<int, 3>>, 256>& triangle_table();
/// Per configuration: bit 2a + side set when the cell's face (axis a, side) has a sign
/// change (a surface walk crosses it).
const std::array<std::uint8_t, 256>& crossed_faces();

}  // namespace station::mc
