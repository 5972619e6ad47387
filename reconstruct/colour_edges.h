#pragma once
// Sharp colour edges on a vertex-coloured mesh (beyond the colour paper).
//
// A mesh coloured at its vertices (colour_mesh) blends colours linearly over each
// triangle, so a colour boundary that crosses a triangle is smeared over the whole
// triangle, whatever the colour function knows: on the two-colour sphere of the
// benchmark that smear is all of the mesh's colour error at the input points.
// sharpen_colour_edges splits every mesh edge whose two end colours differ by more
// than a threshold at the colour change, found by bisection on the colour function,
// inserting one vertex on each side of it (each with the colour function's colour
// there), and re-triangulates the faces around them so that a triangle no longer
// spans the boundary except inside a strip 2^-steps of an edge wide. The geometry is
// unchanged (new vertices lie on the old edges; faces keep their orientation), the
// mesh stays watertight (a split edge's vertices are shared by both its faces), and no
// face is degenerate (new vertices lie strictly inside their edges).
#include <cstddef>
#include <functional>

#include "core/geometry.h"
#include "reconstruct/colour_function.h"

namespace station {

struct ColourEdgeParams {
  /// An edge is split when the colours of its ends differ by more than this (CIE76
  /// distance in L*a*b*). 0: the colour function's gamma (ColourParams::gamma, 40 by
  /// default), the difference at which it calls a cell a colour boundary.
  double min_difference = 0;
  /// Bisection steps along a split edge: the colour change is located within
  /// 2^-steps of the edge's length (the width of the strip left blended). In [1, 20].
  int steps = 4;
  /// An end is used only where the mesh's colour there is the colour function's
  /// (within this CIE76 distance); ends coloured otherwise (colour_mesh's nearest-
  /// sample colours where the surface is not trusted) are left alone.
  double end_tolerance = 3;
  /// Threads for the bisections (0 = all cores). The result does not depend on it.
  int threads = 0;
  /// Edges (by their end vertices) never split: a block's edges on a face it shares
  /// with another block (reconstruct/blocks.h). Empty: none.
  std::function<bool(int a, int b)> keep_edge;
};

struct ColourEdgeStats {
  std::size_t candidate_edges = 0;  ///< edges whose end colours differ by more than the threshold
  std::size_t split_edges = 0;      ///< of them, split (the others: ends not the function's colour)
  std::size_t new_vertices = 0;
  std::size_t faces_before = 0, faces_after = 0;
  /// Faces with all three edges split (three colours meet): fanned around a new
  /// vertex at their centroid, so one of their colours is still blended over part.
  std::size_t three_way_faces = 0;
};

/// Splits the mesh's colour-boundary edges in place (see the file comment). A mesh
/// without vertex colours, or with none above the threshold, is left as it is.
/// New vertices are appended (their normals interpolated and normalised when the
/// mesh has normals); faces not touching a split edge keep their index order.
/// InvalidInput on inconsistent attributes or a parameter out of range.
ColourEdgeStats sharpen_colour_edges(Mesh& mesh, const ColourFunction& f, const ColourEdgeParams& params = {});

}  // namespace station
