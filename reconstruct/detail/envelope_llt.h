#pragma once
// Cholesky factorisation of a symmetric positive definite matrix stored by its row
// envelope: row i holds A(i, first[i] .. i), the entries left of first[i] are zero.
// The factor L keeps the envelope (no fill outside it), so the work is sum_i w_i^2 / 2
// for row widths w_i instead of n^3 / 6. Used for the colour function's RBF systems
// (docs/colour.md): nodes sorted by one tangent coordinate and a compactly supported
// psi make every row's nonzeros a window of about a quarter of the nodes.

#include <cmath>
#include <cstddef>
#include <vector>

namespace station::detail {

// sum_k a[k] b[k] in four interleaved partial sums (the dependent chain of a single sum
// is what bounds the factorisation's speed).
inline double envelope_dot(const double* a, const double* b, int n) {
  double s0 = 0, s1 = 0, s2 = 0, s3 = 0;
  int k = 0;
  for (; k + 4 <= n; k += 4) {
    s0 += a[k] * b[k];
    s1 += a[k + 1] * b[k + 1];
    s2 += a[k + 2] * b[k + 2];
    s3 += a[k + 3] * b[k + 3];
  }
  for (; k < n; ++k) s0 += a[k] * b[k];
  return (s0 + s1) + (s2 + s3);
}

class EnvelopeLlt {
 public:
  /// Starts a matrix of n rows; then set row i (in order) with begin_row / the returned
  /// pointer, then factor().
  void reset(int n) {
    n_ = n;
    first_.assign(std::size_t(n), 0);
    inv_diag_.assign(std::size_t(n), 0.0);
    offset_.assign(std::size_t(n) + 1, 0);
    values_.clear();
  }
  /// Row i's entries A(i, first .. i) (i - first + 1 of them, the diagonal last), to be
  /// written by the caller. Rows must be begun in order 0, 1, ...; `first` at most i.
  double* begin_row(int i, int first) {
    first_[std::size_t(i)] = first;
    offset_[std::size_t(i)] = values_.size();
    values_.resize(values_.size() + std::size_t(i - first + 1), 0.0);
    offset_[std::size_t(i) + 1] = values_.size();
    return values_.data() + offset_[std::size_t(i)];
  }

  /// In place; false when the matrix is not (numerically) positive definite.
  bool factor() {
    for (int i = 0; i < n_; ++i) {
      const int fi = first_[std::size_t(i)];
      double* li = row(i);  // li[k - fi] = L(i, k)
      for (int j = fi; j < i; ++j) {
        const int fj = first_[std::size_t(j)];
        const double* lj = row(j);
        const int k0 = fi > fj ? fi : fj;
        const double s = li[j - fi] - envelope_dot(li + (k0 - fi), lj + (k0 - fj), j - k0);
        li[j - fi] = s * inv_diag_[std::size_t(j)];
      }
      const double d = li[i - fi] - envelope_dot(li, li, i - fi);
      if (!(d > 0) || !std::isfinite(d)) return false;
      li[i - fi] = std::sqrt(d);
      inv_diag_[std::size_t(i)] = 1 / li[i - fi];
    }
    return true;
  }

  /// Solves A x = b in place for `cols` right-hand sides stored column after column
  /// (x[c * stride + i]).
  void solve(double* x, int cols, std::ptrdiff_t stride) const {
    for (int c = 0; c < cols; ++c) {
      double* v = x + c * stride;
      for (int i = 0; i < n_; ++i) {  // L y = b
        const int fi = first_[std::size_t(i)];
        const double* li = row(i);
        v[i] = (v[i] - envelope_dot(li, v + fi, i - fi)) * inv_diag_[std::size_t(i)];
      }
      for (int i = n_ - 1; i >= 0; --i) {  // L^T x = y
        const int fi = first_[std::size_t(i)];
        const double* li = row(i);
        const double xi = v[i] * inv_diag_[std::size_t(i)];
        v[i] = xi;
        for (int k = 0; k < i - fi; ++k) v[fi + k] -= li[k] * xi;
      }
    }
  }

  int size() const { return n_; }
  std::size_t stored() const { return values_.size(); }

 private:
  double* row(int i) { return values_.data() + offset_[std::size_t(i)]; }
  const double* row(int i) const { return values_.data() + offset_[std::size_t(i)]; }

  int n_ = 0;
  std::vector<int> first_;
  std::vector<std::size_t> offset_;
  std::vector<double> values_;
  std::vector<double> inv_diag_;  // 1 / L(i, i)
};

}  // namespace station::detail
