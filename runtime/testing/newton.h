// Reference static solver for tests and benchmarks: the equilibrium of a
// spring network under gravity and external forces by Newton's method with
// a direct sparse factorisation (Eigen SimplicialLDLT), independent of the
// runtime's integrators.
//
//   r(x) = sum_s f_s(x) + m g + f_ext = 0 on the free nodes,
//   K(x) dx = r(x),  K = sum_s k [ n n^T + (1 - L0/L) (I - n n^T) ]  (full
//   tangent, geometric term not clamped), with a backtracking line search on
//   |r| and optional load stepping (gravity and f_ext ramped in steps).
#pragma once

#include "runtime/model.h"
#include "runtime/state.h"

#include <array>
#include <vector>

namespace orthosim::runtime::testing {

struct NewtonOptions {
  std::array<Real, 3> gravity{0, -9.81, 0};  // m/s^2
  int load_steps = 4;        // gravity and f_ext ramped in this many increments
  int max_iterations = 60;   // Newton iterations per load step
  Real tolerance = 1e-11;    // converged when |r| <= tolerance * (|m g| + |f_ext|) summed over free nodes
};

struct NewtonResult {
  std::vector<Real> x;  // (n_nodes x 3) m, equilibrium positions
  int iterations = 0;   // total
  Real residual = 0;    // N, final |r|
  bool converged = false;
};

// Nodes with s.inv_mass == 0 (fixed, kinematic, anchors) are held at s.x;
// the solve starts from s.x and uses s.f_ext.
NewtonResult solve_static(const Model& m, const State& s, const NewtonOptions& o);

}  // namespace orthosim::runtime::testing
