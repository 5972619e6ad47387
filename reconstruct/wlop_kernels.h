#pragma once
// Internal to reconstruct/: the inner sums of WLOP (methods.md section 1) over a
// RadiusGrid's points within h of a query, in double precision, eight lanes at
// a time. theta(r) = exp(-r^2 / (h/4)^2) (eq. 8). The lanes are summed in a fixed
// order, so a result depends on the grid and the query alone (not on the CPU's
// vector width: every ISA runs the same eight-lane arithmetic).
#include "core/geometry.h"
#include "reconstruct/radius_grid.h"

namespace station::detail {

/// A weighted sum over neighbours p: w = sum a_p, d = sum a_p (p - q).
struct KernelSums {
  double w = 0;
  Vec3d d = Vec3d::Zero();
};

/// Shared constants of one radius h.
struct KernelShape {
  double h2 = 0;      ///< h^2: only points with |p - q|^2 < h^2 count
  double inv_s2 = 0;  ///< 1 / (h/4)^2
  double eps2 = 0;    ///< attraction leaves out |p - q|^2 <= eps2 (alpha is singular at 0)
};

/// w = sum theta(|p - q|) over all grid points within h (q itself included when in
/// the grid). d is left zero. Eqs. 6-7 with the self term as the "1 +".
KernelSums density_sum(const RadiusGrid& grid, const Vec3d& q, const KernelShape& k);

/// a_p = theta(r) / r * weight[p] (weight by sorted position; eq. 2's alpha_ij / v_j
/// with weight = 1 / v_j), over eps2 < r^2 < h^2.
KernelSums attraction_sum(const RadiusGrid& grid, const double* weight, const Vec3d& q,
                          const KernelShape& k);

/// a_p = theta(r) * weight[p] (eq. 3's w_r |beta_ir| with weight = w_r) over r^2 < h^2,
/// leaving out sorted position `self`.
KernelSums repulsion_sum(const RadiusGrid& grid, const double* weight, const Vec3d& q,
                         const KernelShape& k, int self);

/// The attraction sum over n points given as offsets (dx, dy, dz) from q with
/// squared lengths r2, in contiguous arrays: a_p = theta(r) / r * weight[p] over
/// eps2 < r^2 < h^2. Each array must hold n + RadiusGrid::kPad readable entries.
KernelSums attraction_sum(const double* dx, const double* dy, const double* dz, const double* r2,
                          const double* weight, int n, const KernelShape& k);

/// One copy of the edge variant's upsampling (eqs. 13-15) for the n neighbours of
/// x_i at offsets (dx, dy, dz) (squared lengths r2): with a the unit axis from c_i
/// to x_i, the copy is shifted so that x_i lies Dt from c_i and inverted with the
/// radius that keeps x'_i at Q from c_i. Writes each neighbour's offset from x'_i
/// to (ux, uy, uz) and its squared length to ur2, and returns how many of those
/// are below h2. Inputs need n + kPad readable entries, outputs n + kPad writable.
int invert_copy(const double* dx, const double* dy, const double* dz, const double* r2, int n,
                double Dt, double Q, const Vec3d& a, double h2, double* ux, double* uy,
                double* uz, double* ur2);

/// The edge variant's density weights 1 / v'_k = 1 / (1 + (v_k - 1) S_k) for n
/// neighbours with (unit, any sign) normals (nx, ny, nz) and input densities v, where
/// S_k = sum_t 1 / (g_t sqrt(1 + (g_t^2 - 1) (n_k . a)^2)) over the copies' lateral
/// scales g (K of them). Arrays need n + kPad entries (w: writable).
void edge_weights(const double* nx, const double* ny, const double* nz, const double* v, int n,
                  const Vec3d& a, const double* g, int K, double* w);

}  // namespace station::detail
