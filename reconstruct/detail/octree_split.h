#pragma once
// Private to reconstruct/: the split of an adaptive octree's cell, as the MPU surface
// (mpu.cpp) and the colour function (colour_function.cpp) build theirs breadth-first.
#include <vector>

#include "core/geometry.h"

namespace station::detail {

/// Appends the eight children of nodes[id] (half its size, at its octants, one level
/// deeper than `depth`) to `nodes`, links them as its children and queues their
/// indices in `next`. NodeT has center (Vec3d), half, depth and first_child.
template <class NodeT>
void split_cell(std::vector<NodeT>& nodes, int id, int depth, std::vector<int>& next) {
  const int first = int(nodes.size());
  nodes[std::size_t(id)].first_child = first;
  const NodeT parent = nodes[std::size_t(id)];
  for (int c = 0; c < 8; ++c) {
    NodeT ch;
    ch.half = parent.half / 2;
    ch.center = parent.center + ch.half * Vec3d(c & 1 ? 1 : -1, c & 2 ? 1 : -1, c & 4 ? 1 : -1);
    ch.depth = depth + 1;
    nodes.push_back(ch);
    next.push_back(first + c);
  }
}

}  // namespace station::detail
