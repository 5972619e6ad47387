#pragma once
// Normals for point clouds: PCA estimation, the "simple normals" of the
// edge-preserving WLOP paper (Awano 2013, eqs. 11-12), and consistent
// orientation (Hoppe et al. 1992's propagation over a minimum spanning tree, or
// agreement with reference normals). Used by consolidate (reconstruct/wlop.h)
// and by the next stage, MPU, which needs outward normals.
#include <vector>

#include "core/geometry.h"

namespace station {

class PointIndex;

/// Unit normal of the least-squares plane through points[0..n) (PCA: the
/// eigenvector of the smallest eigenvalue of their covariance). Arbitrary sign;
/// zero when n < 3 or the points do not span a plane's worth of directions
/// (all equal).
Vec3d pca_normal(const Vec3d* points, int n);

/// The paper's simple normal (eqs. 11-12): the unit n minimising
/// sum_l |n . ((p_l - p_j) - q_j)|, q_j the mean of p_l - p_j, i.e. the plane
/// through the centroid with the least sum of absolute distances. Eq. 11 prints
/// neither a square (that would be PCA, which the paper contrasts it with) nor an
/// absolute value (without one the sum is identically zero); we read it as the L1
/// fit, which at a sharp edge leans further than PCA towards the face holding most
/// of the points (not all the way: the plane is held to the centroid, q_j). Solved
/// by iteratively reweighted PCA
/// (weights 1 / max(|n . y_l|, 1e-3 rms spread)) from the PCA normal, `iterations`
/// times. Arbitrary sign; zero as pca_normal. With `pca`, the PCA normal it started
/// from (pca_normal's, bit for bit) is stored there too.
Vec3d simple_normal(const Vec3d* points, int n, int iterations = 6, Vec3d* pca = nullptr);

/// True when some normal has a length of at least 1e-6 and is finite (the test MPU
/// applies to each point's): a cloud whose normals are all zero has none to use.
bool any_usable_normal(const std::vector<Vec3f>& normals);

/// PCA normals of every point over its k nearest points (itself included; k >= 3).
/// Unit length, arbitrary sign; zero where the neighbourhood is degenerate.
/// Parallel over points; the result does not depend on `threads` (0 = all cores).
std::vector<Vec3f> estimate_normals(const std::vector<Vec3f>& points, int k, int threads = 0);

/// The same over an index of the points already built (its points, in its order).
std::vector<Vec3f> estimate_normals(const PointIndex& index, int k, int threads = 0);

/// Orients `normals` (one per point, any signs) consistently by propagation over a
/// minimum spanning tree of the symmetric k-nearest-neighbour graph with edge cost
/// 1 - |n_a . n_b| (Hoppe et al. 1992): a normal is flipped when it disagrees with
/// the one it is reached from. Each connected component starts at its highest point
/// (max z), whose normal is made to point up (+z): outwards for a closed surface, or
/// an open scan of an object on a turntable. Zero normals are left zero (and passed
/// through). Ties broken by index: deterministic.
void orient_normals_mst(const std::vector<Vec3f>& points, std::vector<Vec3f>& normals, int k = 12);

/// Orients each normal towards a sensor at `viewpoint`: flipped when n . (viewpoint - p)
/// < 0. A zero normal stays zero, or with `zero_faces_viewpoint` becomes the unit
/// direction to the viewpoint (registration's fallback).
void orient_normals_towards(const std::vector<Vec3f>& points, std::vector<Vec3f>& normals, const Vec3f& viewpoint,
                            bool zero_faces_viewpoint = false);

/// Orients each normal to agree with the reference normals near its point: flipped
/// when n . (sum of the k nearest reference points' normals) < 0; left as is when
/// that sum is zero. Reference normals are assumed consistently oriented.
void orient_normals_to(const std::vector<Vec3f>& points, std::vector<Vec3f>& normals,
                       const std::vector<Vec3f>& reference_points,
                       const std::vector<Vec3f>& reference_normals, int k = 8, int threads = 0);

}  // namespace station
