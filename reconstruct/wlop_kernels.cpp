#include "reconstruct/wlop_kernels.h"

#include <cstring>

#ifdef __x86_64__
#include <immintrin.h>
#endif

// Vector loops written once with GCC/Clang vector extensions and instantiated at
// the CPU's native width: 8 doubles (AVX-512), 4 (AVX2) or 2 (SSE2, the x86-64
// baseline and the fallback elsewhere), picked once at run time. Non-native widths
// are not an option, and neither are vector comparisons: GCC turns them into
// scalar code whenever the mask has to live in a register. Masks are made from
// sign bits instead (a < b <=> a - b < 0 for finite doubles) and applied with AND,
// which also zeroes whatever NaN or infinity a masked-out lane computed.
#pragma GCC diagnostic ignored "-Wpsabi"

#if defined(__x86_64__) && defined(__GNUC__)
#define STATION_X86_DISPATCH 1
#endif
#define STATION_INLINE __attribute__((always_inline)) inline

namespace station::detail {

namespace {

template <int W>
struct Lanes {
  typedef double V __attribute__((vector_size(8 * W)));
  typedef unsigned long long U __attribute__((vector_size(8 * W)));
  typedef long long M __attribute__((vector_size(8 * W)));  // comparison results
};

enum class Mode { kDensity, kAttraction, kRepulsion };

#if defined(__x86_64__) && defined(__GNUC__)
// AVX-512's 14-bit reciprocal square root estimate: two Newton steps then give
// full precision, against four from the bit-level guess. Only ever inlined into
// the AVX-512 kernels.
__attribute__((target("avx512f"))) inline Lanes<8>::V rsqrt14(Lanes<8>::V x) {
  return (Lanes<8>::V)_mm512_maskz_rsqrt14_pd(__mmask8(0xFF), (__m512d)x);
}
#endif

template <int W>
struct Kernels {
  using V = typename Lanes<W>::V;
  using U = typename Lanes<W>::U;
  static_assert(RadiusGrid::kPad >= W, "grid padding must cover a lane block");

  static STATION_INLINE V load(const double* p) {
    V v;
    std::memcpy(&v, p, sizeof v);
    return v;
  }
  static STATION_INLINE V splat(double x) { return V{} + x; }
  static STATION_INLINE double lane_sum(V v) {
    double s = 0;
    for (int l = 0; l < W; ++l) s += v[l];
    return s;
  }

  // All ones where v < 0 (sign bit set), else zero.
  static STATION_INLINE U negative(V v) { return U{} - ((U)v >> 63); }
  static STATION_INLINE V keep(V v, U mask) { return (V)((U)v & mask); }

  // exp(x) for -708 < x <= 0 to about 1 ulp: x = n ln2 + r with |r| <= ln2/2
  // (Cody-Waite split of ln2), e^r by its degree-12 Taylor polynomial (remainder
  // < 2e-16), 2^n put straight into the exponent bits. Garbage below -708; the
  // callers mask those lanes (r > h, where x < -16) away.
  static STATION_INLINE V exp_nonpositive(V x) {
    const V shifter = splat(6755399441055744.0);  // 1.5 * 2^52: adding it rounds to integer
    const V t = x * 1.4426950408889634 + shifter;
    const V n = t - shifter;
    const V r = x - n * 0.6931471803691238 - n * 1.9082149292705877e-10;
    V p = splat(1.0 / 479001600.0);
    p = p * r + 1.0 / 39916800.0;
    p = p * r + 1.0 / 3628800.0;
    p = p * r + 1.0 / 362880.0;
    p = p * r + 1.0 / 40320.0;
    p = p * r + 1.0 / 5040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * r + 1.0;
    p = p * r + 1.0;
    // t's low mantissa bits hold n (two's complement): the exponent field of 2^n.
    const U bits = (((U)t - (U)shifter) + 1023) << 52;
    return p * (V)bits;
  }

  // 1 / sqrt(x) for x > 0 to about 1 ulp: the bit-level first guess (relative
  // error < 3.5 %) and four Newton steps, each squaring the error. Cheaper than a
  // vector sqrt and divide. Garbage (possibly NaN) for x = 0; masked by callers.
  static STATION_INLINE V rsqrt_positive(V x) {
    const V half = x * 0.5;
#if defined(__x86_64__) && defined(__GNUC__)
    if constexpr (W == 8) {
      V y = rsqrt14(x);
      for (int i = 0; i < 2; ++i) y = y * (1.5 - half * y * y);
      return y;
    }
#endif
    V y = (V)((U{} + 0x5fe6eb50c7b537a9ULL) - ((U)x >> 1));
    for (int i = 0; i < 4; ++i) y = y * (1.5 - half * y * y);
    return y;
  }

  struct Acc {
    V w{}, x{}, y{}, z{};
  };

  // One block of W lanes starting at sorted position p; `valid` lanes from the
  // first are in the run (W for full blocks).
  template <Mode mode, bool tail>
  static STATION_INLINE void block(const double* xs, const double* ys, const double* zs,
                                   const double* weight, const V& qx, const V& qy, const V& qz,
                                   const KernelShape& k, int p, int valid, int self, Acc& acc) {
    const V dx = load(xs + p) - qx, dy = load(ys + p) - qy, dz = load(zs + p) - qz;
    const V r2 = dx * dx + dy * dy + dz * dz;
    U inside = negative(r2 - k.h2);  // r2 < h2
    V a = exp_nonpositive(r2 * -k.inv_s2);
    if (mode == Mode::kAttraction) {
      inside &= negative(k.eps2 - r2);  // r2 > eps2
      a = a * rsqrt_positive(r2) * load(weight + p);
    } else if (mode == Mode::kRepulsion) {
      a = a * load(weight + p);
    }
    if (tail || mode == Mode::kRepulsion) {
      V lane;
      for (int l = 0; l < W; ++l) lane[l] = l;
      if (tail) inside &= negative(lane - double(valid));  // lane < valid
      if (mode == Mode::kRepulsion) {
        const V off = lane - double(self - p);
        inside &= ~negative(off * off - 0.25);  // lane != self - p
      }
    }
    a = keep(a, inside);
    acc.w += a;
    if (mode != Mode::kDensity) {
      acc.x += a * dx;
      acc.y += a * dy;
      acc.z += a * dz;
    }
  }

  // Attraction over contiguous arrays of offsets (the edge variant's inverted
  // neighbourhood): the same lane arithmetic as block().
  static STATION_INLINE KernelSums array_attraction(const double* dx, const double* dy,
                                                    const double* dz, const double* r2s,
                                                    const double* weight, int n,
                                                    const KernelShape& k) {
    Acc acc;
    V lane;
    for (int l = 0; l < W; ++l) lane[l] = l;
    for (int p = 0; p < n; p += W) {
      const V r2 = load(r2s + p);
      U inside = negative(r2 - k.h2) & negative(k.eps2 - r2) & negative(lane - double(n - p));
      V a = exp_nonpositive(r2 * -k.inv_s2) * rsqrt_positive(r2) * load(weight + p);
      a = keep(a, inside);
      acc.w += a;
      acc.x += a * load(dx + p);
      acc.y += a * load(dy + p);
      acc.z += a * load(dz + p);
    }
    KernelSums out;
    out.w = lane_sum(acc.w);
    out.d = Vec3d(lane_sum(acc.x), lane_sum(acc.y), lane_sum(acc.z));
    return out;
  }

  // See invert_copy in the header. With z the axial and l2 the squared lateral
  // offset of a neighbour, A = Dt + z its shifted axial distance from c_i and
  // d = |p + t l - c_i|: e = d - A, the inverted distance from c_i is Q - z - e,
  // the lateral scale g = (Q - z - e) / d and the axial offset from x'_i is
  // -z - e - g e; the lateral offset, g (p - x_i - z a). (d - A loses about
  // eps * A / e of e's relative precision, absolute error ~1e-16 A: no need for the
  // division of l2 / (d + A).)
  static STATION_INLINE int invert_copy(const double* dxs, const double* dys, const double* dzs,
                                        const double* r2s, int n, double Dt, double Q,
                                        const Vec3d& a, double h2, double* ux, double* uy,
                                        double* uz, double* ur2) {
    V lane;
    for (int l = 0; l < W; ++l) lane[l] = l;
    V inside{};
    for (int p = 0; p < n; p += W) {
      const V dx = load(dxs + p), dy = load(dys + p), dz = load(dzs + p);
      const V z = dx * a.x() + dy * a.y() + dz * a.z();
      V l2 = load(r2s + p) - z * z;
      l2 = keep(l2, ~negative(l2));  // rounding can make it slightly negative
      const V A = Dt + z;
      const V dd = A * A + l2;
      const V inv_d = rsqrt_positive(dd);
      const V e = dd * inv_d - A;
      const V g = (Q - z - e) * inv_d;
      const V ax = -z - e - g * e;
      const V along = ax - g * z;  // the axial part of g (p - x_i) is g z
      const V ox = along * a.x() + g * dx, oy = along * a.y() + g * dy, oz = along * a.z() + g * dz;
      const V d2 = ax * ax + g * g * l2;
      std::memcpy(ux + p, &ox, sizeof ox);
      std::memcpy(uy + p, &oy, sizeof oy);
      std::memcpy(uz + p, &oz, sizeof oz);
      std::memcpy(ur2 + p, &d2, sizeof d2);
      inside += keep(splat(1.0), negative(d2 - h2) & negative(lane - double(n - p)));
    }
    return int(lane_sum(inside));
  }

  static STATION_INLINE void edge_weights(const double* nxs, const double* nys, const double* nzs,
                                          const double* vs, int n, const Vec3d& a, const double* g,
                                          int K, double* w) {
    for (int p = 0; p < n; p += W) {
      const V c = load(nxs + p) * a.x() + load(nys + p) * a.y() + load(nzs + p) * a.z();
      const V c2 = c * c;
      V S{};
      // 1 / (g sqrt(1 + (g^2 - 1) c^2)) = rsqrt(g^2 (1 + (g^2 - 1) c^2))
      for (int t = 0; t < K; ++t) S += rsqrt_positive(g[t] * g[t] * (1.0 + (g[t] * g[t] - 1.0) * c2));
      const V out = 1.0 / (1.0 + (load(vs + p) - 1.0) * S);
      std::memcpy(w + p, &out, sizeof out);
    }
  }

  template <Mode mode>
  static STATION_INLINE KernelSums sums(const RadiusGrid& grid, const double* weight, const Vec3d& q,
                                        const KernelShape& k, int self) {
    const double *xs = grid.xs(), *ys = grid.ys(), *zs = grid.zs();
    const V qx = splat(q.x()), qy = splat(q.y()), qz = splat(q.z());
    Acc acc;
    RadiusGrid::Run runs[RadiusGrid::kMaxRuns];
    const int count = grid.runs(q, runs);
    for (int run = 0; run < count; ++run) {
      const int b = runs[run].begin, e = runs[run].end;
      int p = b;
      for (; p + W <= e; p += W)
        block<mode, false>(xs, ys, zs, weight, qx, qy, qz, k, p, W, self, acc);
      if (p < e) block<mode, true>(xs, ys, zs, weight, qx, qy, qz, k, p, e - p, self, acc);
    }
    KernelSums out;
    out.w = lane_sum(acc.w);
    if (mode != Mode::kDensity) out.d = Vec3d(lane_sum(acc.x), lane_sum(acc.y), lane_sum(acc.z));
    return out;
  }
};

struct Table {
  KernelSums (*density)(const RadiusGrid&, const Vec3d&, const KernelShape&);
  KernelSums (*attraction)(const RadiusGrid&, const double*, const Vec3d&, const KernelShape&);
  KernelSums (*repulsion)(const RadiusGrid&, const double*, const Vec3d&, const KernelShape&, int);
  KernelSums (*array_attraction)(const double*, const double*, const double*, const double*,
                                 const double*, int, const KernelShape&);
  int (*invert_copy)(const double*, const double*, const double*, const double*, int, double,
                     double, const Vec3d&, double, double*, double*, double*, double*);
  void (*edge_weights)(const double*, const double*, const double*, const double*, int,
                       const Vec3d&, const double*, int, double*);
};

#define STATION_KERNEL_TABLE(NAME, W, TARGET)                                                    \
  TARGET KernelSums NAME##_density(const RadiusGrid& g, const Vec3d& q, const KernelShape& k) { \
    return Kernels<W>::template sums<Mode::kDensity>(g, nullptr, q, k, -1);                     \
  }                                                                                             \
  TARGET KernelSums NAME##_attraction(const RadiusGrid& g, const double* w, const Vec3d& q,     \
                                      const KernelShape& k) {                                   \
    return Kernels<W>::template sums<Mode::kAttraction>(g, w, q, k, -1);                        \
  }                                                                                             \
  TARGET KernelSums NAME##_repulsion(const RadiusGrid& g, const double* w, const Vec3d& q,      \
                                     const KernelShape& k, int self) {                          \
    return Kernels<W>::template sums<Mode::kRepulsion>(g, w, q, k, self);                       \
  }                                                                                             \
  TARGET KernelSums NAME##_array(const double* dx, const double* dy, const double* dz,           \
                                 const double* r2, const double* w, int n, const KernelShape& k) { \
    return Kernels<W>::array_attraction(dx, dy, dz, r2, w, n, k);                               \
  }                                                                                             \
  TARGET int NAME##_invert(const double* dx, const double* dy, const double* dz, const double* r2, \
                           int n, double Dt, double Q, const Vec3d& a, double h2, double* ux,   \
                           double* uy, double* uz, double* ur2) {                               \
    return Kernels<W>::invert_copy(dx, dy, dz, r2, n, Dt, Q, a, h2, ux, uy, uz, ur2);           \
  }                                                                                             \
  TARGET void NAME##_weights(const double* nx, const double* ny, const double* nz,              \
                             const double* v, int n, const Vec3d& a, const double* g, int K,     \
                             double* w) {                                                        \
    Kernels<W>::edge_weights(nx, ny, nz, v, n, a, g, K, w);                                     \
  }                                                                                             \
  const Table NAME##_table{NAME##_density, NAME##_attraction, NAME##_repulsion, NAME##_array,  \
                           NAME##_invert, NAME##_weights};

STATION_KERNEL_TABLE(base, 2, )
#ifdef STATION_X86_DISPATCH
STATION_KERNEL_TABLE(avx2, 4, __attribute__((target("avx2"))))
STATION_KERNEL_TABLE(avx512, 8, __attribute__((target("avx512f,avx512dq"))))
#endif

const Table& table() {
  static const Table& chosen = [&]() -> const Table& {
#ifdef STATION_X86_DISPATCH
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq")) return avx512_table;
    if (__builtin_cpu_supports("avx2")) return avx2_table;
#endif
    return base_table;
  }();
  return chosen;
}

}  // namespace

KernelSums attraction_sum(const double* dx, const double* dy, const double* dz, const double* r2,
                          const double* weight, int n, const KernelShape& k) {
  return table().array_attraction(dx, dy, dz, r2, weight, n, k);
}

KernelSums density_sum(const RadiusGrid& grid, const Vec3d& q, const KernelShape& k) {
  return table().density(grid, q, k);
}

void edge_weights(const double* nx, const double* ny, const double* nz, const double* v, int n,
                  const Vec3d& a, const double* g, int K, double* w) {
  table().edge_weights(nx, ny, nz, v, n, a, g, K, w);
}

int invert_copy(const double* dx, const double* dy, const double* dz, const double* r2, int n,
                double Dt, double Q, const Vec3d& a, double h2, double* ux, double* uy,
                double* uz, double* ur2) {
  return table().invert_copy(dx, dy, dz, r2, n, Dt, Q, a, h2, ux, uy, uz, ur2);
}

KernelSums attraction_sum(const RadiusGrid& grid, const double* weight, const Vec3d& q,
                          const KernelShape& k) {
  return table().attraction(grid, weight, q, k);
}

KernelSums repulsion_sum(const RadiusGrid& grid, const double* weight, const Vec3d& q,
                         const KernelShape& k, int self) {
  return table().repulsion(grid, weight, q, k, self);
}

}  // namespace station::detail
