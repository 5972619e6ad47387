#pragma once
// Evaluation metrics between two clouds or meshes (`station eval A B`). Every
// later stage is judged with these. Distances are in the inputs' units.
#include <functional>
#include <optional>
#include <variant>

#include "core/geometry.h"

namespace station {

struct EvalParams {
  /// Points sampled uniformly (by area) on each mesh's faces; a cloud is used as is.
  int mesh_samples = 200000;
  /// Seed of the sampler: same inputs and seed, same result.
  unsigned seed = 1;
  /// Threads for the distance queries (0 = all cores).
  int threads = 0;
  /// Colour of mesh A / mesh B at a surface point (face index, barycentrics u, v
  /// with point = (1-u-v) a + u b + v c), e.g. from a texture (core/texture.h
  /// surface_color). When set, it replaces the mesh's vertex colours and makes the
  /// mesh count as coloured; ignored for clouds. Must be thread-safe.
  std::function<Rgb(int face, double u, double v)> a_surface_colour, b_surface_colour;
};

struct DirectedStats {
  double mean = 0, rms = 0, p95 = 0, max = 0;
  std::size_t count = 0;
};

/// Either a cloud or a mesh.
using Shape = std::variant<Cloud, Mesh>;

struct EvalResult {
  DirectedStats a_to_b, b_to_a;
  double chamfer = 0;    ///< (a_to_b.mean + b_to_a.mean) / 2
  double hausdorff = 0;  ///< max(a_to_b.max, b_to_a.max)
  double p95 = 0;        ///< max(a_to_b.p95, b_to_a.p95)
  /// Mean |n_a . n_b| over nearest pairs, both directions; empty when a side lacks normals
  /// (a mesh always has them: face normals at the sample or closest point). The two
  /// directions' means are averaged; zero-length normals are left out.
  std::optional<double> normal_consistency;
  /// Colour error e_col (methods.md, colour paper): mean of |dR|+|dG|+|dB| (channels in
  /// [0,1]) against A's colour at the nearest point; empty unless both carry colour.
  /// Directed, and taken over B's points (B's cloud points, or B's samples with their
  /// interpolated colours), not A's: the paper evaluates "at every input point" the
  /// reconstructed colour, so with A = the reconstruction and B = the reference input
  /// (`station eval RESULT REFERENCE`) this is the paper's e_col. A's colour at a point:
  /// a mesh's vertex colours interpolated at the closest point, a cloud's nearest point.
  std::optional<double> colour_error;
};

/// Distances from A's points (or samples) to B's surface (B a mesh: exact point-to-
/// triangle distance; B a cloud: nearest point), and the same from B to A.
/// By convention A is the result being judged and B the reference (see color_error,
/// the one directed metric). A mesh without faces is taken as the cloud of its
/// vertices (with their normals and colours). p95 is the nearest-rank percentile.
/// Results are identical for any params.threads.
/// InvalidInput ("A: empty", "B: non-finite coordinates", ...) on an empty shape,
/// non-finite coordinates, inconsistent attributes, a mesh of zero total area, or
/// mesh_samples <= 0 / threads < 0.
EvalResult evaluate(const Shape& a, const Shape& b, const EvalParams& params = {});

/// Area-uniform samples on the faces, with face normals and (when the mesh has
/// vertex colours) interpolated colours. Deterministic for a seed.
/// InvalidInput on a mesh without faces or of zero area, or a negative count.
Cloud sample_mesh(const Mesh& mesh, int count, unsigned seed);

/// The colour transition of a mesh across a known sharp two-colour boundary (issue 7's
/// measure, used by the colour tests and bench/surface_bench.cpp): per vertex, t = the
/// projection of its colour on the a -> b colour axis (0 = a, 1 = b) and s = its signed
/// distance to the boundary (> 0 on b's side).
struct ColourTransition {
  double width = 0;           ///< 2 x the 95th percentile of |s| over vertices with 0.1 < t < 0.9
  double max_band = 0;        ///< largest |s| of a vertex with 0.1 < t < 0.9
  std::size_t band = 0;       ///< vertices with 0.1 < t < 0.9
  std::size_t wrong = 0;      ///< vertices on the wrong side (t > 0.5 with s < 0 or t < 0.5 with s > 0)
  std::size_t wrong_far = 0;  ///< ... more than `cell` from the boundary
  double max_wrong = 0;       ///< largest |s| of a wrong-side vertex
  std::size_t vertices = 0;   ///< coloured vertices measured
};
ColourTransition measure_colour_transition(const Mesh& mesh,
                                           const std::function<double(const Vec3d&)>& signed_distance,
                                           const Rgb& a, const Rgb& b, double cell);

}  // namespace station
