// The mass-spring solver: step(const Model&, State&, dt, options).
//
// Forces per substep (all SI): linear springs with axial damping
// (runtime/kernels.h), gravity m g on free nodes, mass-proportional damping
// -alpha m v, the State's external forces, and spring attachments. Fixed
// nodes do not move; kinematic nodes follow their attachment's path.
//
// Integrators
// - symplectic (semi-implicit) Euler: v += h M^-1 f(x, v); x += h v.
//   Conditionally stable; with automatic substeps h is safety times the
//   stability limit (2/w)(sqrt(1 + z^2) - z) of the stiffest node, where w^2
//   and the damping rate are Gershgorin bounds per node (Model::omega2,
//   Model::gamma), so a light node next to a heavy one and a tension-only
//   spring that may engage are both accounted for.
// - implicit (backward) Euler, one Newton step per substep (Baraff & Witkin
//   1998): (M + h C + h^2 K) v' = M v + h f_elastic(x) + h f_ext, x' = x + h v',
//   solved by preconditioned conjugate gradients (Jacobi or 3x3 block
//   Jacobi), warm-started from v + (last velocity change); pinned nodes are
//   filtered out of the solve with their velocities prescribed.
//
// Obstacles: where the State has static obstacles (State::obstacles,
// runtime/obstacles.h), each free node's update is checked against them in
// the same pass: a motion that crossed one ends on its surface, sliding, with
// restitution and Coulomb friction on the velocity. Nodes are independent
// there, so the rule below holds.
//
// Stability: after every substep the kinetic energy, the largest speed and
// finiteness are checked. A step is redone from its start with twice the
// substeps when a value is NaN or Inf, when the kinetic energy exceeds
// energy_growth times what the step could legitimately reach (kinetic +
// elastic energy at its start + an upper bound of the work of gravity,
// external forces and tools), or when a node would move farther than the
// model's extent in one substep, and (implicit, redo_unconverged) when a
// linear solve stops unconverged at cg_max_iterations (that attempt is kept
// when it is the last). After max_retries redos the state is
// restored to the start of the step with velocities zeroed and the failure is
// counted: a NaN never stays in the State. Every event is counted in
// State::counters.
//
// Determinism: loops run over the Model's fixed node chunks with per-node
// gathers and per-chunk partial sums added in order, so for given inputs
// the result is bitwise identical for any number of threads. The loops use
// TBB in the caller's task arena (Scene runs them in an arena of the
// scene's thread count).
#pragma once

#include "runtime/model.h"
#include "runtime/state.h"

#include <array>
#include <string>
#include <string_view>

namespace orthosim::runtime {

enum class Integrator { symplectic_euler, implicit_euler };
// The implicit solve's preconditioner. block_jacobi: the inverse 3x3
// diagonal blocks. cholesky: a sparse LDL^T factor of the substep's matrix
// (free nodes), kept across substeps and rebuilt from the current matrix when
// a solve took more than refactor_after iterations (the matrix has drifted)
// or the free nodes, springs or tetrahedra changed: stiff, nearly
// incompressible layers (the volume term) that take block Jacobi hundreds of
// iterations take this a few; a soft model whose matrix changes fast is
// cheaper with block Jacobi. automatic: block Jacobi until a solve stops
// unconverged at cg_max_iterations, then cholesky for the State's life (the
// step is redone, redo_unconverged, with the factor).
enum class Preconditioner { jacobi, block_jacobi, cholesky, automatic };

const char* to_string(Integrator i);         // "symplectic" | "implicit"
const char* to_string(Preconditioner p);     // "jacobi" | "block_jacobi" | "cholesky" | "auto"
// The preconditioner to_string names s; false (p unchanged) for any other name.
bool parse_preconditioner(std::string_view s, Preconditioner& p);

struct SolverOptions {
  Integrator integrator = Integrator::symplectic_euler;
  std::array<Real, 3> gravity{0, -9.81, 0};  // m/s^2
  Real mass_damping = 0;   // 1/s, alpha in f = -alpha m v, >= 0
  int substeps = 0;        // substeps per step; 0 = automatic (symplectic: from the stability limit; implicit: 1)
  Real safety = 0.9;       // automatic symplectic substeps use this fraction of the stability limit, (0, 1]
  int max_substeps = 1 << 20;  // cap on substeps per step (automatic or after redos)
  int max_retries = 8;     // redos of one step, each doubling its substeps
  Real energy_growth = 10; // blow-up threshold on kinetic energy (see above), > 1
  Real cg_tolerance = 1e-6;    // implicit: |r| / the size of the right-hand side's terms (docs/runtime.md)
  int cg_max_iterations = 200; // implicit: per solve
  Preconditioner preconditioner = Preconditioner::automatic;
  int refactor_after = 8;   // implicit, cholesky: a solve of more iterations rebuilds the factor next substep, >= 1
  bool warm_start = true;  // implicit: start PCG from v + the last velocity change
  bool redo_unconverged = true;  // implicit: a step with a solve stopped at cg_max_iterations is redone with twice the substeps (up to max_retries)
  // implicit, obstacles: the speed (m/s) below which a resting node's friction
  // is a damper, mu N / creep_speed (smoothed Coulomb friction): a node at
  // rest creeps at most this fast under a tangential force inside the
  // friction cone. > 0. Smaller: less creep, a slower start when pushed past
  // the cone (docs/runtime.md, Static colliders).
  Real friction_creep_speed = 1e-4;
};

// Throws Error("", ...) naming the first invalid option.
void validate(const SolverOptions& o);

// What one step did.
struct StepInfo {
  int substeps = 0;       // substeps of the accepted attempt
  int retries = 0;        // redos before it was accepted (or before giving up)
  bool failed = false;    // true: state restored to the step's start, velocities zeroed
  int cg_iterations = 0;  // implicit: PCG iterations of the accepted attempt
};

// Largest stable symplectic-Euler substep (s) for the model with the State's
// pins and spring attachments, before the safety factor. Cached in
// State::step_limit.
Real symplectic_step_limit(const Model& m, State& s, const SolverOptions& o);

// Advances the State by dt (> 0) seconds. Never throws for numerical
// trouble; see the stability rule above.
StepInfo step(const Model& m, State& s, Real dt, const SolverOptions& o);

// Energies of a State (J): kinetic, elastic (springs), gravitational
// potential (-m g.x over free nodes).
struct Energies {
  Real kinetic = 0, elastic = 0, gravity = 0;
  Real total() const { return kinetic + elastic + gravity; }
};
Energies energies(const Model& m, const State& s, const SolverOptions& o);

// Total linear momentum (kg m/s) and angular momentum about the origin of
// the free nodes.
std::array<Real, 6> momentum(const Model& m, const State& s);

}  // namespace orthosim::runtime
