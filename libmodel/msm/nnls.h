// Lawson-Hanson non-negative least squares for small fixed-size systems
// (the lattice rule's 6 x 7, lattice.cpp): no heap, normal equations on the
// passive set (well conditioned at such sizes when the caller scales the
// columns to comparable norms).
#pragma once

#include <Eigen/Dense>

#include <algorithm>
#include <type_traits>

namespace orthosim::msm {

// min |A x - b| over x >= 0, using the first n columns of A (the others stay 0).
template <int Rows, int Cols>
Eigen::Matrix<double, Cols, 1> nnls(const Eigen::Matrix<double, Rows, Cols>& A,
                                    const std::type_identity_t<Eigen::Matrix<double, Rows, 1>>& b, int n) {
  using VecC = Eigen::Matrix<double, Cols, 1>;
  using Small = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, Cols, Cols>;
  using SmallVec = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, Cols, 1>;
  VecC x = VecC::Zero();
  bool passive[Cols] = {};
  const Eigen::Matrix<double, Cols, Cols> AtA = A.transpose() * A;
  const VecC Atb = A.transpose() * b;
  const double tol = 1e-12 * std::max(1.0, A.norm() * b.norm());
  auto solve_passive = [&](VecC& s) {
    int P[Cols], m = 0;
    for (int i = 0; i < n; ++i)
      if (passive[i]) P[m++] = i;
    Small M(m, m);
    SmallVec r(m);
    for (int i = 0; i < m; ++i) {
      r(i) = Atb(P[i]);
      for (int j = 0; j < m; ++j) M(i, j) = AtA(P[i], P[j]);
    }
    const SmallVec y = M.ldlt().solve(r);
    s.setZero();
    for (int i = 0; i < m; ++i) s(P[i]) = y(i);
  };
  for (int outer = 0; outer < 3 * n + 10; ++outer) {
    const VecC w = Atb - AtA * x;
    int j = -1;
    double best = tol;
    for (int i = 0; i < n; ++i)
      if (!passive[i] && w(i) > best) best = w(i), j = i;
    if (j < 0) break;
    passive[j] = true;
    for (int inner = 0; inner < 3 * n + 10; ++inner) {
      VecC s;
      solve_passive(s);
      bool positive = true;
      for (int i = 0; i < n; ++i)
        if (passive[i] && !(s(i) > 0)) positive = false;
      if (positive) {
        x = s;
        break;
      }
      double alpha = 1;
      for (int i = 0; i < n; ++i)
        if (passive[i] && !(s(i) > 0)) alpha = std::min(alpha, x(i) / (x(i) - s(i)));
      x += alpha * (s - x);
      for (int i = 0; i < n; ++i)
        if (passive[i] && x(i) <= 1e-15) passive[i] = false, x(i) = 0;
    }
  }
  return x;
}

}  // namespace orthosim::msm
