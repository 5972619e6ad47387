#pragma once
// Local shape descriptors for global registration: Fast Point Feature
// Histograms (FPFH; Rusu, Blodow & Beetz 2009, "Fast Point Feature Histograms
// (FPFH) for 3D registration", ICRA). Own implementation on core/kdtree.h (PCL's
// headers are not used: they compile very slowly and PCL is not linked by the
// main build; see docs/registration.md).
//
// For a point p with neighbours p_k within `radius`, the simplified point
// feature histogram SPFH(p) bins, for every pair (p, p_k), the three angles of
// the Darboux frame (u = n_s, v = u x (p_t - p_s)/|p_t - p_s|, w = u x v, with
// s the end whose normal makes the smaller angle with the connecting line):
//   alpha = v . n_t, phi = u . (p_t - p_s)/d, theta = atan2(w . n_t, u . n_t),
// 11 bins each (theta over [-pi, pi], alpha and phi over [-1, 1]).
// FPFH(p) = SPFH(p) + 1/k sum_k SPFH(p_k) / |p - p_k|; each 11-bin block is
// normalised to sum 100 (the convention PCL and Open3D use, so distances are
// comparable to theirs).
#include <array>
#include <vector>

#include "core/geometry.h"

namespace station {

class PointIndex;

constexpr int kFpfhBins = 33;
using FpfhDescriptor = std::array<float, kFpfhBins>;

/// FPFH of every point of `index` (normals one per point, unit, consistently
/// oriented). At most `max_neighbors` neighbours (the closest) within `radius`
/// enter each histogram. A point without neighbours gets an all-zero
/// descriptor. Parallel, deterministic. InvalidInput on a size mismatch or a
/// radius <= 0.
std::vector<FpfhDescriptor> compute_fpfh(const PointIndex& index, const std::vector<Vec3f>& normals,
                                         double radius, int max_neighbors = 100);

/// For each query descriptor, the index of the nearest reference descriptor
/// (Euclidean over the 33 bins; brute force, parallel); -1 when `reference` is empty.
std::vector<int> nearest_descriptors(const std::vector<FpfhDescriptor>& query,
                                     const std::vector<FpfhDescriptor>& reference);
/// The same where each descriptor has a colour (a chromaticity, one per descriptor):
/// the nearest reference descriptor among those whose colour is within `gate`
/// (Euclidean) of the query's, looked for among the `candidates` nearest (least
/// distance, then lowest index); -1 where none of them agrees. Below 256 reference
/// descriptors every one is looked at. InvalidInput on a size mismatch.
std::vector<int> nearest_descriptors_gated(const std::vector<FpfhDescriptor>& query, const std::vector<Vec3f>& query_chroma,
                                           const std::vector<FpfhDescriptor>& reference,
                                           const std::vector<Vec3f>& reference_chroma, double gate, int candidates);

}  // namespace station
