#pragma once
// Colour for ICP (Park, Zhou & Koltun 2017, "Colored point cloud registration
// revisited", ICCV): per registration point an intensity and its gradient in
// the tangent plane. The joint objective itself is IcpObjective::kColored in
// capture/icp.h:
//   E = (1 - lambda) sum r_C^2 + lambda sum r_G^2,
//   r_G = n_q . (p - q)                         (point-to-plane),
//   r_C = C_q(p') - C(s), C_q(x) = C(q) + d_q . (x - q), p' = p projected on q's plane,
// with p the moved source point s, q its nearest target point, d_q the target's
// intensity gradient. lambda = IcpParams::colored_lambda (the paper's 0.968).
#include <vector>

#include "core/geometry.h"

namespace station {

class PointIndex;

/// Intensity in [0, 1] (mean of R, G, B) of each colour.
std::vector<float> intensities(const std::vector<Rgb>& colours);

/// Intensity of each of `points`: the mean over the points of `cloud_points`
/// (with `cloud_intensity`) within `radius` of it, or of the nearest one when
/// none is that close. `cloud_index` indexes cloud_points.
std::vector<float> sample_intensity(const std::vector<Vec3f>& points, const PointIndex& cloud_index,
                                    const std::vector<float>& cloud_intensity, double radius);

/// Tangent-plane intensity gradient of every point of `index` (Park et al.
/// 2017, sec. 3): least squares over its k nearest points q of
/// C(p) + d . (q' - p) = C(q), q' = q projected on p's tangent plane, with
/// d . n = 0 enforced by a heavily weighted extra row. Zero where the
/// neighbourhood is degenerate. InvalidInput on a size mismatch.
std::vector<Vec3f> intensity_gradients(const PointIndex& index, const std::vector<Vec3f>& normals,
                                       const std::vector<float>& intensity, int k = 16);

}  // namespace station
