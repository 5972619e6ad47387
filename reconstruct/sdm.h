#pragma once
// Self-organizing Deformable Model (Morooka & Nagahashi 2005, "A method for
// projecting mesh model of 3D object onto arbitrary surface"; summarised in
// shared/docs/methods.md section 5; decisions and measurements in docs/sdm.md).
//
// A template mesh of known topology (an icosphere, or any closed genus-0 mesh) is
// deformed onto a target surface given as control points with outward normals,
// keeping its connectivity:
//   phase 1, competitive learning (SOM, paper eqs. 8-18): a random control point p
//     pulls its winner vertex (smallest non-negative signed distance, see
//     SdmParams) and the winner's edge-hop neighbourhood towards it;
//   phase 2, energy minimisation (eqs. 12, 19-21): every vertex tries the moves
//     v + w (p_j - v) towards its own control points and keeps the one with the
//     least sum of squared point-to-triangle distances over its faces, until the
//     mean distance falls under theta_e.
// The result is watertight, keeps the template's vertex numbering (so two fits of
// the same template correspond vertex by vertex) and closes parts of the target
// that were never scanned (the underside of a turntable object).
#include <functional>
#include <string>
#include <vector>

#include "core/geometry.h"

namespace station {

/// A pinned pair (paper section 3.4): whenever `point` is drawn in phase 1, vertex
/// `vertex` of the template is its winner; in phase 2 the vertex is held on `point`.
struct Landmark {
  int vertex = -1;
  Vec3f point = Vec3f::Zero();
};

struct SdmParams {
  // ---- phase 1: competitive learning --------------------------------------
  /// T_c, the number of SOM steps (control points drawn). 0 = 8 x template vertices.
  int som_iterations = 0;
  /// Phase 1 runs on at most this many control points, a seeded random subset (0 = 8 x
  /// template vertices): the SOM only learns the coarse shape, and its cost grows with
  /// the points' density through the anchor projection. Phase 2 uses all points.
  /// tau and the selection weights refer to this subset.
  int som_points = 0;
  /// epsilon_s, epsilon_f: learning rate at the start and the end (eq. 16). The paper
  /// gives no values; these are the usual SOM ones (Fritzsche 1997, its ref. 4).
  float eps_start = 0.3f, eps_final = 0.02f;
  /// sigma_s, sigma_f: neighbourhood width in edge hops at the start and the end
  /// (eqs. 17-18). sigma_start 0 = sqrt(template vertices) / 8 (about 6 hops for a
  /// level-4 icosphere, 12 for level 5).
  float sigma_start = 0.f, sigma_final = 0.6f;
  /// lambda(i|k) below this is treated as zero (the neighbourhood is cut there, at
  /// L = sigma sqrt(-2 ln cutoff) hops).
  float lambda_cutoff = 0.1f;
  /// alpha of eq. 10: how much a free vertex keeps its offset from the winner
  /// (0: pulled straight to p; 1: translated with the winner).
  float alpha = 0.5f;
  /// tau = tau_factor x control-point spacing (mean nearest-neighbour distance) is the
  /// distance under which a vertex is labelled anchor (paper: twice the spacing).
  float tau_factor = 2.f;
  /// Selection probabilities of the control points (paper section 3.4): empty =
  /// uniform (the paper's default), or one non-negative weight per control point.
  std::vector<float> selection_weights;
  /// When > 0 and selection_weights is empty: weight = 1 + curvature_gain x (surface
  /// variation / its mean), surface variation = smallest / sum of the PCA eigenvalues
  /// over 12 neighbours: more samples (hence more vertices) where the surface is
  /// complex.
  float curvature_gain = 0.f;
  /// Probability that a SOM step draws a landmark (when there are any) instead of an
  /// ordinary control point (the default T_c grows to keep as many ordinary draws).
  /// High, so that the landmarks' neighbourhoods have followed them before phase 2
  /// pins them (a landmark far from where phase 1 left its vertex folds the faces
  /// around it).
  float landmark_probability = 0.3f;
  /// Scale the template (per axis) so that its bounding box is the target's bounding
  /// box enlarged by template_margin, centred on it. The paper's initial shape is
  /// arbitrary; a template around the target keeps the winner rule (vertices on the
  /// outer side of p) meaningful from the first step. Off: the template is used as is.
  bool place_template = true;
  float template_margin = 1.15f;

  // ---- phase 2: energy minimisation ----------------------------------------
  /// theta_e of eq. 21, relative to the mesh's mean edge length after phase 1 (the
  /// paper gives no value): phase 2 stops when the mean point-to-mesh distance
  /// D(M, Psi) falls below it. Relative to the edge length so that a finer template is
  /// held to a finer fit.
  float theta_e = 0.05f;
  /// At most this many phase-2 rounds; two rounds in a row that improve D by less
  /// than min_improvement (relative) also end it. The best state seen is kept.
  int max_energy_rounds = 30;
  float min_improvement = 0.05f;
  /// A vertex whose control points lie on average within theta_e / 2 of its faces is
  /// taken as fitted and skips the energy moves (relaxation still applies).
  /// w of eq. 19: the step lengths tried towards each control point.
  std::vector<float> steps = {0.25f, 0.5f, 1.f};
  /// At most this many control points of a vertex are tried as p_j (evenly spread over
  /// its Omega_i), plus their centroid. The energy is summed over at most 12 of them.
  int max_candidates = 6;
  /// Tangential relaxation (not in the paper): after its energy move, a vertex moves
  /// this fraction of the way to its neighbours' centroid within its tangent plane.
  /// Keeps triangles well shaped and undoes folds left by phase 1.
  float relax = 0.25f;
  /// Vertices that own no control point (holes, the unseen underside) move this
  /// fraction of the way to their neighbours' centroid (a membrane over the hole).
  float membrane = 0.5f;
  /// Fold repair (not in the paper): before and after every phase-2 round, the
  /// vertices around folded faces (see count_folded_faces) are smoothed towards their
  /// neighbours' centroid, at most this many passes; the energy moves then bring them
  /// back onto the target.
  int repair_iterations = 10;
  /// At the end, intersecting faces (count_self_intersections) and two rings around
  /// them are smoothed likewise, at most repair_iterations rounds (not in the paper).

  // ---- general ----------------------------------------------------------------
  /// Neighbours for normal estimation when the target has none (core/normals.h).
  int normal_k = 12;
  /// Fewer control points than max(min_control_points, template vertices / 4) is
  /// refused.
  int min_control_points = 50;
  unsigned seed = 1;
  /// Worker threads (0 = all cores). Phase 1 is sequential (each step depends on the
  /// last); phase 2 runs in parallel over independent vertex sets. The result does not
  /// depend on the thread count.
  int threads = 0;
};


struct SdmDiagnostics {
  int template_vertices = 0, template_faces = 0, control_points = 0;
  bool normals_estimated = false;  ///< the target had no normals
  float spacing = 0;               ///< phase-1 control points' mean nearest-neighbour distance
  float tau = 0;                   ///< anchor threshold
  float diagonal = 0;              ///< target bounding-box diagonal
  int som_iterations = 0;          ///< phase-1 steps run
  int som_skipped = 0;             ///< steps whose control point found no winner
  int anchors = 0;                 ///< vertices labelled anchor at the end of phase 1
  int energy_rounds = 0;           ///< phase-2 rounds run
  int colours = 0;                 ///< independent vertex sets of phase 2
  double distance_after_som = 0;   ///< D(M, Psi) after phase 1
  double mean_distance = 0;        ///< D(M, Psi) at the end: mean control-point-to-mesh distance
  int flipped_faces = 0;           ///< faces folded over their neighbours (see count_folded_faces)
  int self_intersections = 0;      ///< intersecting face pairs left (see count_self_intersections)
  double seconds_som = 0, seconds_energy = 0, seconds_total = 0;
};

struct SdmResult {
  Mesh mesh;  ///< the template's vertices moved; same faces, vertex normals filled
  SdmDiagnostics diagnostics;
};

/// Called now and then with the phase ("som", "energy") and its completed fraction.
using SdmProgress = std::function<void(const std::string& phase, double fraction)>;

/// Fits `template_mesh` to the target's points. The template must be a closed,
/// connected, consistently oriented genus-0 manifold (the target's genus cannot be
/// read off a cloud; a genus-0 template gives a genus-0 surface whatever the target,
/// see docs/sdm.md). Target normals must point outwards; when absent they are
/// estimated (PCA over normal_k neighbours) and oriented (core/normals.h).
/// InvalidInput ("template: ...", "target: ...", "landmark 3: ...") on a template of
/// other topology, too few or non-finite control points, bad landmarks or parameters.
SdmResult fit_sdm(const Mesh& template_mesh, const Cloud& target, const SdmParams& params = {},
                  const std::vector<Landmark>& landmarks = {}, const SdmProgress& progress = {});

/// fit_sdm with make_icosphere_template(level), coarse to fine as in the paper
/// (section 4.1: the fitted level-4 SDM subdivided into level 5 and deformed again):
/// above coarse_level, the icosphere of coarse_level is fitted (both phases), then
/// subdivided one level at a time (edge midpoints: the same connectivity and vertex
/// numbering as make_icosphere_template(level)) and polished by phase 2 alone.
/// Landmarks on vertices that do not exist at a level wait for the level that has
/// them. Diagnostics: phase 1 of the coarse fit, phase 2 summed, the finest level's
/// distances and counts.
SdmResult fit_sdm_icosphere(int level, const Cloud& target, const SdmParams& params = {},
                            const std::vector<Landmark>& landmarks = {},
                            const SdmProgress& progress = {}, int coarse_level = 4);

/// Unit icosphere (an icosahedron subdivided `level` times, 10 * 4^level + 2
/// vertices: level 4 = 2,562, level 5 = 10,242), counter-clockwise outward faces.
/// InvalidInput unless 0 <= level <= 7.
Mesh make_icosphere_template(int level);


/// Landmarks from a text file: one "vertex_index x y z" per line; blank lines and
/// lines starting with '#' are skipped. IoError when unreadable, FormatError
/// ("PATH:LINE: ...") on a malformed line.
std::vector<Landmark> read_landmarks(const std::string& path);

/// Simple surfaces of the paper's Fig. 6.
enum class SimpleSurface {
  kPlane,     ///< the unit disc in z = 0; the mesh must be a disc (one boundary loop)
  kSphere,    ///< the unit sphere; the mesh must be closed genus 0
  kCylinder,  ///< the closed cylinder x^2 + y^2 = 1, |z| <= 1 with both caps; genus 0
};

struct ParameterisationResult {
  Mesh mesh;                ///< the input's connectivity, vertices on the surface
  std::vector<Vec2f> uv;    ///< one per vertex, in [0, 1]^2
  SdmDiagnostics diagnostics;
};

/// Maps `mesh` onto a simple surface with the SDM (control points sampled on the
/// surface, `control_points` of them, 0 = 4 x vertices) and reads UVs off it:
/// plane: (x + 1) / 2, (y + 1) / 2 (boundary loop pinned to the unit circle by arc
/// length); sphere: longitude / 2 pi, colatitude / pi; cylinder: angle / 2 pi and
/// the arc length along the profile (bottom cap centre 0, rims 1/4 and 3/4, top cap
/// centre 1). Mesh has no UV field, so they are returned beside it. `progress` as for
/// fit_sdm.
ParameterisationResult sdm_parameterise(const Mesh& mesh, SimpleSurface surface,
                                        const SdmParams& params = {}, int control_points = 0,
                                        const SdmProgress& progress = {});

}  // namespace station
