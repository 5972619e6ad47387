#include "reconstruct/detail/envelope_llt.h"

#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <random>

namespace station::detail {
namespace {

// Points along a line with a compactly supported kernel: row i's nonzeros are a window
// ending at the diagonal, as the colour function's RBF systems are with nodes sorted by u.
Eigen::MatrixXd windowed_spd(int n, double support, std::mt19937& rng, std::vector<int>& first) {
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<double> x(static_cast<std::size_t>(n));
  for (double& v : x) v = u(rng);
  std::sort(x.begin(), x.end());
  Eigen::MatrixXd a = Eigen::MatrixXd::Zero(n, n);
  first.assign(static_cast<std::size_t>(n), 0);
  for (int i = 0; i < n; ++i) {
    a(i, i) = 1 + 1e-6;
    int f = i;
    for (int j = i - 1; j >= 0 && x[i] - x[j] < support; --j) {
      const double t = 1 - (x[i] - x[j]) / support;
      a(i, j) = a(j, i) = t * t * t * t * (4 * (x[i] - x[j]) / support + 1);  // Wendland, PD
      f = j;
    }
    first[static_cast<std::size_t>(i)] = f;
  }
  return a;
}

TEST(EnvelopeLlt, SolvesLikeADenseCholeskyAndStoresOnlyTheEnvelope) {
  std::mt19937 rng(3);
  for (int n : {1, 2, 7, 60, 200}) {
    std::vector<int> first;
    const Eigen::MatrixXd a = windowed_spd(n, 0.4, rng, first);
    EnvelopeLlt llt;
    llt.reset(n);
    std::size_t expected_stored = 0;
    for (int i = 0; i < n; ++i) {
      double* row = llt.begin_row(i, first[static_cast<std::size_t>(i)]);
      for (int j = first[static_cast<std::size_t>(i)]; j <= i; ++j) row[j - first[static_cast<std::size_t>(i)]] = a(i, j);
      expected_stored += static_cast<std::size_t>(i - first[static_cast<std::size_t>(i)] + 1);
    }
    ASSERT_TRUE(llt.factor()) << n;
    EXPECT_EQ(llt.stored(), expected_stored);
    if (n >= 60) {
      EXPECT_LT(double(llt.stored()), 0.5 * n * (n + 1) / 2.0) << "the window should be narrow";
    }
    const Eigen::MatrixXd b = Eigen::MatrixXd::Random(n, 3);
    Eigen::MatrixXd x = b;
    llt.solve(x.data(), 3, x.rows());
    const Eigen::MatrixXd ref = a.llt().solve(b);
    EXPECT_LT((x - ref).norm(), 1e-9 * (1 + ref.norm())) << n;
    EXPECT_LT((a * x - b).norm(), 1e-9 * (1 + b.norm())) << n;
  }
}

TEST(EnvelopeLlt, RefusesAMatrixThatIsNotPositiveDefinite) {
  EnvelopeLlt llt;
  llt.reset(2);
  double* r0 = llt.begin_row(0, 0);
  r0[0] = 1;
  double* r1 = llt.begin_row(1, 0);
  r1[0] = 2;  // [[1, 2], [2, 1]]: eigenvalues 3 and -1
  r1[1] = 1;
  EXPECT_FALSE(llt.factor());
}

}  // namespace
}  // namespace station::detail
