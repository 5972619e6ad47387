#pragma once
// Internal to reconstruct/: the inner sums of WLOP (methods.md section 1) over a
// RadiusGrid's points within h of a query, in double precision, eight lanes at
// a time. theta(r) = exp(-r^2 / (h/4)^2) (eq. 8). The lanes are summed in a fixed
// order, so a result depends on the grid and the query alone, not on the CPU:
// every kernel set runs the same eight-lane (double) and sixteen-lane (float)
// arithmetic, with no hardware estimates and no FMA contraction, and gives the
// same bits (docs/determinism.md; tests/reconstruct/wlop_kernels_test.cpp checks).
#include <string>
#include <vector>

#include "core/geometry.h"
#include "reconstruct/detail/radius_grid.h"

namespace station::detail {

/// The kernel sets this CPU can run, the default first ("avx2", "avx512", "base":
/// AVX2 is the faster of the two where both run). They differ in speed only, never
/// in a bit of the results. The first is used unless the environment variable
/// STATION_WLOP_KERNELS names another (a name this CPU lacks gets a warning on
/// stderr and the first) or use_kernel_variant picks one (for tests: every set can
/// then be checked on one machine; not to be called while kernels run).
/// use_kernel_variant throws std::invalid_argument for a name not in the list.
std::vector<std::string> kernel_variants();
void use_kernel_variant(const std::string& name);

/// Readable (and, for outputs, writable) entries past the end that the float
/// kernels below need: one lane block of the widest ISA.
constexpr int kFloatPad = 16;

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
/// with weight = 1 / v_j, or eq. 3's w_r beta_ir with beta = theta / r and weight =
/// w_r), over eps2 < r^2 < h^2.
KernelSums attraction_sum(const RadiusGrid& grid, const double* weight, const Vec3d& q,
                          const KernelShape& k);

/// a_p = theta(r) * weight[p] (eq. 3's w_r |beta_ir| with eq. 5's printed beta = -theta
/// and weight = w_r) over r^2 < h^2, leaving out sorted position `self`.
KernelSums repulsion_sum(const RadiusGrid& grid, const double* weight, const Vec3d& q,
                         const KernelShape& k, int self);

// The edge variant's sums over its gathered, inverted neighbourhood, in single
// precision (twice the lanes of the double kernels): every quantity is an offset
// of order h from x_i or x'_i, kept to about 1e-7 relative; sums across lanes in
// double. Arrays need n + kFloatPad readable entries (outputs: writable).

/// The attraction sum over n points given as offsets (dx, dy, dz) from q with
/// squared lengths r2, in contiguous arrays: a_p = theta(r) / r * weight[p] over
/// eps2 < r^2 < h^2.
KernelSums attraction_sum(const float* dx, const float* dy, const float* dz, const float* r2,
                          const float* weight, int n, const KernelShape& k);

/// One copy of the edge variant's upsampling (eqs. 13-15) for the n neighbours of
/// x_i at offsets (dx, dy, dz) (squared lengths r2): with a the unit axis from c_i
/// to x_i, the copy is shifted so that x_i lies Dt from c_i and inverted with the
/// radius that keeps x'_i at Q from c_i. Writes each neighbour's offset from x'_i
/// to (ux, uy, uz) and its squared length to ur2, and returns how many of those
/// are below h2.
int invert_copy(const float* dx, const float* dy, const float* dz, const float* r2, int n,
                double Dt, double Q, const Vec3d& a, double h2, float* ux, float* uy, float* uz,
                float* ur2);

/// The edge variant's density weights 1 / v'_k = 1 / (1 + (v_k - 1) S_k) for n
/// neighbours with (unit, any sign) normals (nx, ny, nz) and input densities v, where
/// S_k = sum_t 1 / (g_t sqrt(1 + (g_t^2 - 1) (n_k . a)^2)) over the copies' lateral
/// scales g (K of them).
void edge_weights(const float* nx, const float* ny, const float* nz, const float* v, int n,
                  const Vec3d& a, const double* g, int K, float* w);

/// Appends to (pos, dx, dy, dz, r2)[n..] the points of sorted positions [b, e) of a
/// grid's coordinate arrays (xs, ys, zs) strictly within h of q (|p - q|^2 < h2 in
/// double): position, offset p - q and its squared length, as float, in order.
/// Returns the new count. Reads up to 7 entries past e (a RadiusGrid's padding
/// covers them) and may write up to 8 entries past the returned count: the outputs
/// need room for n + (e - b) + 8 entries.
int gather_run(const double* xs, const double* ys, const double* zs, int b, int e, const Vec3d& q,
               double h2, int n, int* pos, float* dx, float* dy, float* dz, float* r2);

/// Index of the smallest of r2[0..n) (the first on ties); n > 0. r2 needs n + kFloatPad
/// readable entries.
int nearest(const float* r2, int n);

/// The edge variant's per-point record, 8 floats by the input grid's sorted
/// position: the simple normal n (unit), the PCA normal m that orients it, v_j, and
/// one float of padding (one aligned load reads a record).
enum EdgeRecord { kNx, kNy, kNz, kMx, kMy, kMz, kV, kRecordFloats = 8 };

/// Eq. 10's sum for the neighbours at sorted positions pos[0..n): each one's simple
/// normal with the sign of m . ref (flipped where that is negative, unless
/// `oriented`: the input's own normals, never flipped), written to (nx, ny, nz) with
/// its v_j to v, and summed. pos needs n + kFloatPad readable entries, each a valid
/// record index (gather_run leaves positions below the grid size + 8 past its count;
/// pad the records accordingly); outputs n + kFloatPad writable.
Vec3d signed_normal_sum(const int* pos, int n, const float* records, const float* ref,
                        bool oriented, float* nx, float* ny, float* nz, float* v);

}  // namespace station::detail
