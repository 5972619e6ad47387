#include "reconstruct/detail/wlop_kernels.h"

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#ifdef __x86_64__
#include <immintrin.h>
#endif

// Vector loops written once with GCC/Clang vector extensions and instantiated at
// the CPU's native width: 8 doubles (AVX-512), 4 (AVX2) or 2 (SSE2, the x86-64
// baseline and the fallback elsewhere), picked once at run time; floats twice
// that. Every set gives the same bits, on any machine (docs/determinism.md):
// - sums run over one logical width of 8 doubles (16 floats) on every set. A set
//   narrower than that keeps 8 / W accumulators and hands a run's consecutive
//   blocks to them in turn, so logical lane L always sums the candidates at L,
//   L + 8, L + 16, ... of each run, in the same order, and the lanes are added up
//   in the same order at the end (a skipped block only adds zeros);
// - no hardware estimates (their bits differ between ISAs and between vendors);
// - no FMA contraction (the build has -ffp-contract=off; AVX-512 implies FMA).
// Non-native vector widths would cost lanes at every run's tail. Vector
// comparisons are avoided: GCC turns them into scalar code whenever the mask has
// to live in a register. Masks are made from sign bits instead (a < b <=> a - b <
// 0 for finite doubles) and applied with AND, which also zeroes whatever NaN or
// infinity a masked-out lane computed.
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
// The eight records (8 floats each) at rec + 8 * pos[0..8), transposed: field f of
// record l goes to lane l of out[f].
__attribute__((target("avx2"))) inline void load_records8(const float* rec, const int* pos,
                                                         __m256 out[8]) {
  __m256 r[8];
  for (int l = 0; l < 8; ++l) r[l] = _mm256_loadu_ps(rec + 8 * std::size_t(pos[l]));
  __m256 t[8], u[8];
  for (int i = 0; i < 4; ++i) {
    t[2 * i] = _mm256_unpacklo_ps(r[2 * i], r[2 * i + 1]);
    t[2 * i + 1] = _mm256_unpackhi_ps(r[2 * i], r[2 * i + 1]);
  }
  for (int i = 0; i < 2; ++i) {
    u[4 * i + 0] = _mm256_shuffle_ps(t[4 * i], t[4 * i + 2], _MM_SHUFFLE(1, 0, 1, 0));
    u[4 * i + 1] = _mm256_shuffle_ps(t[4 * i], t[4 * i + 2], _MM_SHUFFLE(3, 2, 3, 2));
    u[4 * i + 2] = _mm256_shuffle_ps(t[4 * i + 1], t[4 * i + 3], _MM_SHUFFLE(1, 0, 1, 0));
    u[4 * i + 3] = _mm256_shuffle_ps(t[4 * i + 1], t[4 * i + 3], _MM_SHUFFLE(3, 2, 3, 2));
  }
  for (int f = 0; f < 4; ++f) {
    out[f] = _mm256_permute2f128_ps(u[f], u[f + 4], 0x20);
    out[f + 4] = _mm256_permute2f128_ps(u[f], u[f + 4], 0x31);
  }
}
#endif

// The logical widths of every kernel set (see the top of this file).
constexpr int kDoubleLanes = 8;
constexpr int kFloatLanes = 16;

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
  // vector sqrt and divide, and the same bits on every ISA (a hardware estimate
  // is not). Garbage (possibly NaN) for x = 0; masked by callers.
  static STATION_INLINE V rsqrt_positive(V x) {
    const V half = x * 0.5;
    V y = (V)((U{} + 0x5fe6eb50c7b537a9ULL) - ((U)x >> 1));
    for (int i = 0; i < 4; ++i) y = y * (1.5 - half * y * y);
    return y;
  }

  struct Acc {
    V w{}, x{}, y{}, z{};
  };
  // Accumulators that make up the logical width (see the top of this file).
  static constexpr int kSets = kDoubleLanes / W;
  static_assert(kSets * W == kDoubleLanes, "the native width must divide the logical one");
  // Logical lanes 0, 1, ..., kDoubleLanes - 1 of field m, added up in that order.
  static STATION_INLINE double lane_sum(const Acc* acc, V Acc::*m) {
    double s = 0;
    for (int a = 0; a < kSets; ++a)
      for (int l = 0; l < W; ++l) s += (acc[a].*m)[l];
    return s;
  }

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

  template <Mode mode>
  static STATION_INLINE KernelSums sums(const RadiusGrid& grid, const double* weight, const Vec3d& q,
                                        const KernelShape& k, int self) {
    const double *xs = grid.xs(), *ys = grid.ys(), *zs = grid.zs();
    const V qx = splat(q.x()), qy = splat(q.y()), qz = splat(q.z());
    Acc acc[kSets];
    RadiusGrid::Run runs[RadiusGrid::kMaxRuns];
    const int count = grid.runs(q, runs);
    for (int run = 0; run < count; ++run) {
      const int b = runs[run].begin, e = runs[run].end;
      int p = b, set = 0;
      for (; p + W <= e; p += W) {
        block<mode, false>(xs, ys, zs, weight, qx, qy, qz, k, p, W, self, acc[set]);
        if constexpr (kSets > 1) set = set + 1 == kSets ? 0 : set + 1;
      }
      if (p < e) block<mode, true>(xs, ys, zs, weight, qx, qy, qz, k, p, e - p, self, acc[set]);
    }
    KernelSums out;
    out.w = lane_sum(acc, &Acc::w);
    if (mode != Mode::kDensity)
      out.d = Vec3d(lane_sum(acc, &Acc::x), lane_sum(acc, &Acc::y), lane_sum(acc, &Acc::z));
    return out;
  }
};

// The edge variant's inverted-space sums (invert_copy, the Jacobian weights and the
// attraction over the copies) in single precision, twice the lanes of the double
// kernels. Every quantity in them is an offset from x_i or x'_i of order h (or a
// ratio of such), so float keeps them to about 1e-7 h relative to h; the sums are
// taken per lane in float (at most a few hundred terms a lane) and across lanes in
// double. This part of the edge variant is bound by the arithmetic per neighbour
// and copy (a reciprocal square root twice, an exponential once), which float
// halves per lane and shortens (a degree-7 polynomial, three Newton steps).
template <int W>
struct FloatLanes {
  typedef float V __attribute__((vector_size(4 * W)));
  typedef unsigned U __attribute__((vector_size(4 * W)));
};

template <int W>
struct FloatKernels {
  using V = typename FloatLanes<W>::V;
  using U = typename FloatLanes<W>::U;
  static_assert(kFloatPad >= W, "float padding must cover a lane block");

  static STATION_INLINE V load(const float* p) {
    V v;
    std::memcpy(&v, p, sizeof v);
    return v;
  }
  static STATION_INLINE void store(float* p, V v) { std::memcpy(p, &v, sizeof v); }
  static STATION_INLINE V splat(float x) { return V{} + x; }
  // Accumulators that make up the logical width, as in Kernels: block j of a loop
  // over p = 0, W, 2W, ... adds into accumulator j mod kSets.
  static constexpr int kSets = kFloatLanes / W;
  static_assert(kSets * W == kFloatLanes, "the native width must divide the logical one");
  static STATION_INLINE int next(int set) {
    if constexpr (kSets == 1) return 0;
    return set + 1 == kSets ? 0 : set + 1;
  }
  static STATION_INLINE double lane_sum(const V* v) {
    double s = 0;
    for (int a = 0; a < kSets; ++a)
      for (int l = 0; l < W; ++l) s += double(v[a][l]);
    return s;
  }
  static STATION_INLINE U negative(V v) { return U{} - ((U)v >> 31); }
  static STATION_INLINE V keep(V v, U mask) { return (V)((U)v & mask); }
  static STATION_INLINE V lanes() {
    V lane;
    for (int l = 0; l < W; ++l) lane[l] = float(l);
    return lane;
  }

  // exp(x) for -87 < x <= 0 to about 1 ulp (float): Cody-Waite reduction as in the
  // double kernels, e^r by its degree-7 Taylor polynomial (|r| <= ln2/2: remainder
  // < 2e-8 relative). Garbage below -87; callers mask those lanes (x < -16 there).
  static STATION_INLINE V exp_nonpositive(V x) {
    const V shifter = splat(12582912.0f);  // 1.5 * 2^23
    const V t = x * 1.44269504f + shifter;
    const V n = t - shifter;
    const V r = x - n * 0.693145752f - n * 1.42860677e-6f;
    V p = splat(1.0f / 5040.0f);
    p = p * r + 1.0f / 720.0f;
    p = p * r + 1.0f / 120.0f;
    p = p * r + 1.0f / 24.0f;
    p = p * r + 1.0f / 6.0f;
    p = p * r + 0.5f;
    p = p * r + 1.0f;
    p = p * r + 1.0f;
    const U bits = (((U)t - (U)shifter) + 127u) << 23;
    return p * (V)bits;
  }

  // 1 / sqrt(x) for x > 0, float precision: the bit-level guess and three Newton
  // steps (the same bits on every ISA; the CPU's estimate is 12 bits with SSE and
  // AVX, 14 with AVX-512, and differs between vendors). Garbage for x = 0; masked
  // by callers.
  static STATION_INLINE V rsqrt_positive(V x) {
    V y;
    y = (V)((U{} + 0x5f375a86u) - ((U)x >> 1));
    for (int i = 0; i < 3; ++i) y = y * (1.5f - (x * 0.5f) * y * y);
    return y;
  }

  // See invert_copy in the header; the arithmetic of the double version, with
  // e = l2 / (d + A) instead of d - A (no cancellation in float).
  static STATION_INLINE int invert_copy(const float* dxs, const float* dys, const float* dzs,
                                        const float* r2s, int n, double Dt, double Q,
                                        const Vec3d& a, double h2, float* ux, float* uy,
                                        float* uz, float* ur2) {
    const V lane = lanes();
    const float axf = float(a.x()), ayf = float(a.y()), azf = float(a.z());
    const float dt = float(Dt), q = float(Q), hh = float(h2);
    V inside{};
    for (int p = 0; p < n; p += W) {
      const V dx = load(dxs + p), dy = load(dys + p), dz = load(dzs + p);
      const V z = dx * axf + dy * ayf + dz * azf;
      V l2 = load(r2s + p) - z * z;
      l2 = keep(l2, ~negative(l2));  // rounding can make it slightly negative
      const V A = dt + z;
      const V dd = A * A + l2;
      const V inv_d = rsqrt_positive(dd);
      const V e = l2 / (dd * inv_d + A);
      const V g = (q - z - e) * inv_d;
      const V ax = -z - e - g * e;
      const V along = ax - g * z;
      store(ux + p, along * axf + g * dx);
      store(uy + p, along * ayf + g * dy);
      store(uz + p, along * azf + g * dz);
      const V d2 = ax * ax + g * g * l2;
      store(ur2 + p, d2);
      inside += keep(splat(1.0f), negative(d2 - hh) & negative(lane - float(n - p)));
    }
    int count = 0;  // whole numbers: exact in any order
    for (int l = 0; l < W; ++l) count += int(inside[l]);
    return count;
  }

  static STATION_INLINE void edge_weights(const float* nxs, const float* nys, const float* nzs,
                                          const float* vs, int n, const Vec3d& a, const double* g,
                                          int K, float* w) {
    const float axf = float(a.x()), ayf = float(a.y()), azf = float(a.z());
    for (int p = 0; p < n; p += W) {
      const V c = load(nxs + p) * axf + load(nys + p) * ayf + load(nzs + p) * azf;
      const V c2 = c * c;
      V S{};
      for (int t = 0; t < K; ++t) {
        const float g2 = float(g[t] * g[t]);
        S += rsqrt_positive(g2 * (1.0f + (g2 - 1.0f) * c2));
      }
      store(w + p, 1.0f / (1.0f + (load(vs + p) - 1.0f) * S));
    }
  }

  // Index of the smallest of r2[0..n) (the first on ties); n > 0.
  static STATION_INLINE int nearest(const float* r2, int n) {
    const V lane = lanes();
    V best = splat(std::numeric_limits<float>::infinity()), at = splat(-1.0f);
    for (int p = 0; p < n; p += W) {
      // Past-the-end lanes read as +inf; a strictly smaller value replaces.
      const U valid = negative(lane - float(n - p));
      const V r = (V)(((U)load(r2 + p) & valid) | (~valid & (U)splat(std::numeric_limits<float>::infinity())));
      const U smaller = negative(r - best);
      best = (V)(((U)r & smaller) | ((U)best & ~smaller));
      at = (V)(((U)(lane + float(p)) & smaller) | ((U)at & ~smaller));
    }
    float b = best[0];
    float idx = at[0];
    for (int l = 1; l < W; ++l)
      if (best[l] < b || (best[l] == b && at[l] < idx)) {
        b = best[l];
        idx = at[l];
      }
    return int(idx);
  }

  // Fields 0..6 of the records of pos[0..W) (see EdgeRecord in the header), one
  // vector per field.
  static STATION_INLINE void load_records(const float* rec, const int* pos, V out[7]) {
#if defined(__x86_64__) && defined(__GNUC__)
    if constexpr (W == 8) {
      __m256 f[8];
      load_records8(rec, pos, f);
      for (int k = 0; k < 7; ++k) out[k] = (V)f[k];
      return;
    } else if constexpr (W == 16) {
      __m256 lo[8], hi[8];
      load_records8(rec, pos, lo);
      load_records8(rec, pos + 8, hi);
      for (int k = 0; k < 7; ++k) {
        std::memcpy(&out[k], &lo[k], sizeof lo[k]);
        std::memcpy(reinterpret_cast<char*>(&out[k]) + sizeof lo[k], &hi[k], sizeof hi[k]);
      }
      return;
    }
#endif
    float fields[7][W];
    for (int l = 0; l < W; ++l) {
      const float* r = rec + 8 * std::size_t(pos[l]);
      for (int k = 0; k < 7; ++k) fields[k][l] = r[k];
    }
    for (int k = 0; k < 7; ++k) std::memcpy(&out[k], fields[k], sizeof out[k]);
  }

  // Eq. 10's signed normal sum; see signed_normal_sum in the header.
  static STATION_INLINE Vec3d signed_normal_sum(const int* pos, int n, const float* rec,
                                                const float* ref, bool oriented, float* nx,
                                                float* ny, float* nz, float* v) {
    const V lane = lanes();
    V sx[kSets] = {}, sy[kSets] = {}, sz[kSets] = {};
    for (int p = 0, set = 0; p < n; p += W, set = next(set)) {
      V f[7];
      load_records(rec, pos + p, f);
      const V dot = f[3] * ref[0] + f[4] * ref[1] + f[5] * ref[2];
      // sign = -1 where dot < 0: flip the sign bit of the normal's components.
      const U flip = oriented ? U{} : (negative(dot) << 31);
      const V fx = (V)((U)f[0] ^ flip), fy = (V)((U)f[1] ^ flip), fz = (V)((U)f[2] ^ flip);
      store(nx + p, fx);
      store(ny + p, fy);
      store(nz + p, fz);
      store(v + p, f[6]);
      const U valid = negative(lane - float(n - p));
      sx[set] += keep(fx, valid);
      sy[set] += keep(fy, valid);
      sz[set] += keep(fz, valid);
    }
    return Vec3d(lane_sum(sx), lane_sum(sy), lane_sum(sz));
  }

  static STATION_INLINE KernelSums attraction(const float* dx, const float* dy, const float* dz,
                                              const float* r2s, const float* weight, int n,
                                              const KernelShape& k) {
    const V lane = lanes();
    const float h2 = float(k.h2), eps2 = float(k.eps2), inv_s2 = float(k.inv_s2);
    V w[kSets] = {}, x[kSets] = {}, y[kSets] = {}, z[kSets] = {};
    for (int p = 0, set = 0; p < n; p += W, set = next(set)) {
      const V r2 = load(r2s + p);
      const U inside = negative(r2 - h2) & negative(eps2 - r2) & negative(lane - float(n - p));
      const V a = keep(exp_nonpositive(r2 * -inv_s2) * rsqrt_positive(r2) * load(weight + p), inside);
      w[set] += a;
      x[set] += a * load(dx + p);
      y[set] += a * load(dy + p);
      z[set] += a * load(dz + p);
    }
    KernelSums out;
    out.w = lane_sum(w);
    out.d = Vec3d(lane_sum(x), lane_sum(y), lane_sum(z));
    return out;
  }
};

// gather_run (see the header). Scalar: every candidate is written and only the
// ones inside are kept (no branch on the unpredictable comparison).
int gather_run_scalar(const double* xs, const double* ys, const double* zs, int b, int e,
                      const Vec3d& q, double h2, int n, int* pos, float* dx, float* dy, float* dz,
                      float* r2) {
  for (int p = b; p < e; ++p) {
    const double x = xs[p] - q.x(), y = ys[p] - q.y(), z = zs[p] - q.z();
    const double d2 = x * x + y * y + z * z;
    pos[n] = p;
    dx[n] = float(x);
    dy[n] = float(y);
    dz[n] = float(z);
    r2[n] = float(d2);
    n += d2 < h2;
  }
  return n;
}

#ifdef STATION_X86_DISPATCH
// Left-packing eight candidates at a time: for each 8-bit mask of the lanes inside,
// the permutation that moves them to the front, in order.
struct PackTable {
  alignas(32) int index[256][8];
  constexpr PackTable() : index{} {
    for (int m = 0; m < 256; ++m) {
      int k = 0;
      for (int l = 0; l < 8; ++l)
        if (m & (1 << l)) index[m][k++] = l;
      for (; k < 8; ++k) index[m][k] = 0;
    }
  }
};
constexpr PackTable kPack;

// The same candidates kept in the same order as the scalar loop, with the same
// double arithmetic for the test (every CPU with AVX2 has POPCNT); eight at a time, left-packed with one permutation
// per array. Reads up to 7 entries past e (the grid's padding covers the last run)
// and writes up to 8 past the new n.
__attribute__((target("avx2,popcnt"))) int gather_run_avx2(const double* xs, const double* ys,
                                                   const double* zs, int b, int e, const Vec3d& q,
                                                   double h2, int n, int* pos, float* dx,
                                                   float* dy, float* dz, float* r2) {
  const __m256d qx = _mm256_set1_pd(q.x()), qy = _mm256_set1_pd(q.y()), qz = _mm256_set1_pd(q.z());
  const __m256d hh = _mm256_set1_pd(h2);
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  for (int p = b; p < e; p += 8) {
    __m128 fx[2], fy[2], fz[2], f2[2];
    int mask = 0;
    for (int half = 0; half < 2; ++half) {
      const int o = p + 4 * half;
      const __m256d x = _mm256_sub_pd(_mm256_loadu_pd(xs + o), qx);
      const __m256d y = _mm256_sub_pd(_mm256_loadu_pd(ys + o), qy);
      const __m256d z = _mm256_sub_pd(_mm256_loadu_pd(zs + o), qz);
      // No FMA contraction: the same roundings as the scalar x*x + y*y + z*z.
      const __m256d d2 = _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(x, x), _mm256_mul_pd(y, y)),
                                       _mm256_mul_pd(z, z));
      mask |= _mm256_movemask_pd(_mm256_cmp_pd(d2, hh, _CMP_LT_OQ)) << (4 * half);
      fx[half] = _mm256_cvtpd_ps(x);
      fy[half] = _mm256_cvtpd_ps(y);
      fz[half] = _mm256_cvtpd_ps(z);
      f2[half] = _mm256_cvtpd_ps(d2);
    }
    if (e - p < 8) mask &= (1 << (e - p)) - 1;
    const __m256i perm = _mm256_load_si256(reinterpret_cast<const __m256i*>(kPack.index[mask]));
    // (A loop, not a lambda: a lambda would not inherit the target attribute.)
    float* const outs[4] = {dx, dy, dz, r2};
    const __m128* const ins[4] = {fx, fy, fz, f2};
    for (int a = 0; a < 4; ++a) {
      const __m256 all = _mm256_set_m128(ins[a][1], ins[a][0]);
      _mm256_storeu_ps(outs[a] + n, _mm256_permutevar8x32_ps(all, perm));
    }
    const __m256i ids = _mm256_add_epi32(_mm256_set1_epi32(p), lane);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(pos + n), _mm256_permutevar8x32_epi32(ids, perm));
    n += __builtin_popcount(unsigned(mask));
  }
  return n;
}
#endif

struct Table {
  KernelSums (*density)(const RadiusGrid&, const Vec3d&, const KernelShape&);
  KernelSums (*attraction)(const RadiusGrid&, const double*, const Vec3d&, const KernelShape&);
  KernelSums (*repulsion)(const RadiusGrid&, const double*, const Vec3d&, const KernelShape&, int);
  KernelSums (*array_attraction_f)(const float*, const float*, const float*, const float*,
                                   const float*, int, const KernelShape&);
  int (*invert_copy_f)(const float*, const float*, const float*, const float*, int, double,
                       double, const Vec3d&, double, float*, float*, float*, float*);
  void (*edge_weights_f)(const float*, const float*, const float*, const float*, int,
                         const Vec3d&, const double*, int, float*);
  int (*nearest)(const float*, int);
  Vec3d (*signed_normal_sum)(const int*, int, const float*, const float*, bool, float*, float*,
                             float*, float*);
  int (*gather_run)(const double*, const double*, const double*, int, int, const Vec3d&, double,
                    int, int*, float*, float*, float*, float*);
};

#define STATION_KERNEL_TABLE(NAME, W, WF, GATHER, TARGET)                                                  \
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
  TARGET KernelSums NAME##_array_f(const float* dx, const float* dy, const float* dz,          \
                                   const float* r2, const float* w, int n, const KernelShape& k) { \
    return FloatKernels<WF>::attraction(dx, dy, dz, r2, w, n, k);                               \
  }                                                                                             \
  TARGET int NAME##_invert_f(const float* dx, const float* dy, const float* dz, const float* r2, \
                             int n, double Dt, double Q, const Vec3d& a, double h2, float* ux,  \
                             float* uy, float* uz, float* ur2) {                                \
    return FloatKernels<WF>::invert_copy(dx, dy, dz, r2, n, Dt, Q, a, h2, ux, uy, uz, ur2);     \
  }                                                                                             \
  TARGET void NAME##_weights_f(const float* nx, const float* ny, const float* nz, const float* v, \
                               int n, const Vec3d& a, const double* g, int K, float* w) {       \
    FloatKernels<WF>::edge_weights(nx, ny, nz, v, n, a, g, K, w);                               \
  }                                                                                             \
  TARGET int NAME##_nearest(const float* r2, int n) { return FloatKernels<WF>::nearest(r2, n); } \
  TARGET Vec3d NAME##_normal_sum(const int* pos, int n, const float* rec, const float* ref,     \
                                 bool o, float* nx, float* ny, float* nz, float* v) {           \
    return FloatKernels<WF>::signed_normal_sum(pos, n, rec, ref, o, nx, ny, nz, v);            \
  }                                                                                             \
  const Table NAME##_table{NAME##_density,  NAME##_attraction, NAME##_repulsion, NAME##_array_f, \
                           NAME##_invert_f, NAME##_weights_f,  NAME##_nearest,   NAME##_normal_sum, \
                           GATHER};

STATION_KERNEL_TABLE(base, 2, 4, gather_run_scalar, )
#ifdef STATION_X86_DISPATCH
STATION_KERNEL_TABLE(avx2, 4, 8, gather_run_avx2, __attribute__((target("avx2"))))
STATION_KERNEL_TABLE(avx512, 8, 16, gather_run_avx2, __attribute__((target("avx512f,avx512dq"))))
#endif

struct Variant {
  const char* name;
  const Table* table;
};

// The kernel sets this CPU can run, the default first: AVX2 before AVX-512. With
// the same bits on every set, AVX-512 gains nothing: without its 14-bit 1/sqrt
// estimate and FMA its eight-lane blocks waste more lanes at the grid runs' short
// tails, and on the Xeon of 2026-12-03 it was 7-8 % slower than AVX2 (plain WLOP
// 0.46 against 0.43 s of iterations, edge-WLOP 0.63 against 0.58 s,
// docs/determinism.md).
const std::vector<Variant>& variants() {
  static const std::vector<Variant> all = [] {
    std::vector<Variant> v;
#ifdef STATION_X86_DISPATCH
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx2")) v.push_back({"avx2", &avx2_table});
    if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq"))
      v.push_back({"avx512", &avx512_table});
#endif
    v.push_back({"base", &base_table});
    return v;
  }();
  return all;
}

// The default set, or the one STATION_WLOP_KERNELS names (all sets give the same
// bits; the variable is there to show that on a whole run, and to time them).
const Table* initial_table() {
  const char* want = std::getenv("STATION_WLOP_KERNELS");
  if (!want || !*want) return variants().front().table;
  std::string have;
  for (const Variant& v : variants()) {
    if (v.name == std::string(want)) return v.table;
    have += std::string(have.empty() ? "" : ", ") + v.name;
  }
  std::fprintf(stderr, "warning: STATION_WLOP_KERNELS=%s is not a kernel set of this CPU (%s); using %s\n",
               want, have.c_str(), variants().front().name);
  return variants().front().table;
}

std::atomic<const Table*>& current() {
  static std::atomic<const Table*> chosen{initial_table()};
  return chosen;
}

const Table& table() { return *current().load(std::memory_order_relaxed); }

}  // namespace

std::vector<std::string> kernel_variants() {
  std::vector<std::string> names;
  for (const Variant& v : variants()) names.emplace_back(v.name);
  return names;
}

void use_kernel_variant(const std::string& name) {
  for (const Variant& v : variants())
    if (name == v.name) {
      current().store(v.table);
      return;
    }
  throw std::invalid_argument("no WLOP kernel variant '" + name + "' on this CPU");
}

KernelSums attraction_sum(const float* dx, const float* dy, const float* dz, const float* r2,
                          const float* weight, int n, const KernelShape& k) {
  return table().array_attraction_f(dx, dy, dz, r2, weight, n, k);
}

void edge_weights(const float* nx, const float* ny, const float* nz, const float* v, int n,
                  const Vec3d& a, const double* g, int K, float* w) {
  table().edge_weights_f(nx, ny, nz, v, n, a, g, K, w);
}

int invert_copy(const float* dx, const float* dy, const float* dz, const float* r2, int n,
                double Dt, double Q, const Vec3d& a, double h2, float* ux, float* uy, float* uz,
                float* ur2) {
  return table().invert_copy_f(dx, dy, dz, r2, n, Dt, Q, a, h2, ux, uy, uz, ur2);
}

int nearest(const float* r2, int n) { return table().nearest(r2, n); }

int gather_run(const double* xs, const double* ys, const double* zs, int b, int e, const Vec3d& q,
               double h2, int n, int* pos, float* dx, float* dy, float* dz, float* r2) {
  return table().gather_run(xs, ys, zs, b, e, q, h2, n, pos, dx, dy, dz, r2);
}

Vec3d signed_normal_sum(const int* pos, int n, const float* records, const float* ref,
                        bool oriented, float* nx, float* ny, float* nz, float* v) {
  return table().signed_normal_sum(pos, n, records, ref, oriented, nx, ny, nz, v);
}

KernelSums density_sum(const RadiusGrid& grid, const Vec3d& q, const KernelShape& k) {
  return table().density(grid, q, k);
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
