#include "runtime/testing/newton.h"

#include "runtime/kernels.h"

#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>

#include <cmath>

namespace orthosim::runtime::testing {

namespace {

// residual on free dofs at x with load factor lambda
Eigen::VectorXd residual(const Model& m, const State& s, const std::vector<int>& dof, const std::vector<Real>& x,
                         const NewtonOptions& o, Real lambda, int n_dof) {
  Eigen::VectorXd r = Eigen::VectorXd::Zero(n_dof);
  for (std::int32_t q = 0; q < m.n_springs; ++q) {
    const auto a = m.spring_a[q], b = m.spring_b[q];
    const Vec3 d = load3(x.data(), b) - load3(x.data(), a);
    const Vec3 f = spring_force_elastic(d, m.spring_rest[q], m.spring_k[q], m.spring_tension[q] != 0).f;
    if (dof[a] >= 0) r.segment<3>(dof[a]) += Eigen::Vector3d(f.x, f.y, f.z);
    if (dof[b] >= 0) r.segment<3>(dof[b]) -= Eigen::Vector3d(f.x, f.y, f.z);
  }
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    if (dof[i] < 0) continue;
    for (int k = 0; k < 3; ++k) r[dof[i] + k] += lambda * (m.mass[i] * o.gravity[k] + s.f_ext[3 * i + k]);
  }
  return r;
}

}  // namespace

NewtonResult solve_static(const Model& m, const State& s, const NewtonOptions& o) {
  NewtonResult res;
  res.x = s.x;
  std::vector<int> dof(static_cast<std::size_t>(m.n_nodes), -1);
  int n_dof = 0;
  Real load = 0;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    if (s.inv_mass[i] == 0) continue;
    dof[i] = n_dof;
    n_dof += 3;
    for (int k = 0; k < 3; ++k) load += std::abs(m.mass[i] * o.gravity[k] + s.f_ext[3 * i + k]);
  }
  if (n_dof == 0) {
    res.converged = true;
    return res;
  }
  const Real tol = o.tolerance * std::max<Real>(load, 1e-300);
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt;
  bool analysed = false;
  for (int ls = 1; ls <= o.load_steps; ++ls) {
    const Real lambda = static_cast<Real>(ls) / o.load_steps;
    Eigen::VectorXd r = residual(m, s, dof, res.x, o, lambda, n_dof);
    for (int it = 0; it < o.max_iterations; ++it) {
      res.residual = r.norm();
      if (res.residual <= tol) break;
      // tangent
      std::vector<Eigen::Triplet<double>> trip;
      trip.reserve(static_cast<std::size_t>(m.n_springs) * 36);
      for (std::int32_t q = 0; q < m.n_springs; ++q) {
        const auto a = m.spring_a[q], b = m.spring_b[q];
        const Vec3 d = load3(res.x.data(), b) - load3(res.x.data(), a);
        const Real len = norm(d);
        if (!(len > kTinyLength) || (m.spring_tension[q] && len < m.spring_rest[q])) continue;
        const Eigen::Vector3d n(d.x / len, d.y / len, d.z / len);
        const Real k = m.spring_k[q];
        const Eigen::Matrix3d K =
            k * (n * n.transpose()) + k * (1 - m.spring_rest[q] / len) * (Eigen::Matrix3d::Identity() - n * n.transpose());
        const int da = dof[a], db = dof[b];
        for (int u = 0; u < 3; ++u)
          for (int v = 0; v < 3; ++v) {
            if (da >= 0) trip.emplace_back(da + u, da + v, K(u, v));
            if (db >= 0) trip.emplace_back(db + u, db + v, K(u, v));
            if (da >= 0 && db >= 0) {
              trip.emplace_back(da + u, db + v, -K(u, v));
              trip.emplace_back(db + u, da + v, -K(u, v));
            }
          }
      }
      Eigen::SparseMatrix<double> A(n_dof, n_dof);
      A.setFromTriplets(trip.begin(), trip.end());
      if (!analysed) {
        ldlt.analyzePattern(A);
        analysed = true;
      }
      ldlt.factorize(A);
      if (ldlt.info() != Eigen::Success) return res;
      const Eigen::VectorXd dx = ldlt.solve(r);
      // backtracking on |r|
      Real step = 1;
      std::vector<Real> trial = res.x;
      Eigen::VectorXd r_new;
      for (int bt = 0; bt < 30; ++bt) {
        trial = res.x;
        for (std::int32_t i = 0; i < m.n_nodes; ++i)
          if (dof[i] >= 0)
            for (int k = 0; k < 3; ++k) trial[3 * i + k] += step * dx[dof[i] + k];
        r_new = residual(m, s, dof, trial, o, lambda, n_dof);
        if (r_new.norm() < res.residual) break;
        step *= 0.5;
      }
      res.x = trial;
      r = r_new;
      ++res.iterations;
    }
    res.residual = r.norm();
  }
  res.converged = res.residual <= tol;
  return res;
}

}  // namespace orthosim::runtime::testing
