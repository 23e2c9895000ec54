// Accuracy, conservation and determinism of the mass-spring solver.
#include "runtime/cut.h"
#include "runtime/kernels.h"
#include "runtime/obstacles.h"
#include "runtime/solver.h"
#include "runtime/testing/lattice.h"
#include "runtime/testing/newton.h"
#include "tests/runtime/runtime_test_util.h"

#include <Eigen/Core>
#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include <cmath>
#include <random>

namespace orthosim::runtime {
namespace {

using test::all_finite;
using test::box_mesh;
using test::displacement_path;
using test::make_model;
using test::max_node_distance;
using testing::make_layered_block;

SolverOptions no_gravity(Integrator i) {
  SolverOptions o;
  o.integrator = i;
  o.gravity = {0, 0, 0};
  return o;
}

// ---- biphasic oscillator against its analytic solution -----------------------

// A mass m on a biphasic spring (k1 below the turning extension xt, total
// slope k2 above), released at rest from extension x0 > xt. Piecewise
// harmonic: above xt, x = xc + (x0 - xc) cos(w2 t) about xc = (k2 - k1) xt / k2;
// below, x = xt cos(w1 s) + (v1 / w1) sin(w1 s) from the crossing.
struct Biphasic {
  Real m, k1, k2, xt, x0;
  Real w1() const { return std::sqrt(k1 / m); }
  Real w2() const { return std::sqrt(k2 / m); }
  Real xc() const { return (k2 - k1) * xt / k2; }
  Real t1() const { return std::acos((xt - xc()) / (x0 - xc())) / w2(); }
  Real v1() const { return -(x0 - xc()) * w2() * std::sin(w2() * t1()); }
  Real amp1() const { return std::sqrt(xt * xt + (v1() / w1()) * (v1() / w1())); }
  Real tau1() const { return (2 * M_PI - 2 * std::acos(xt / amp1())) / w1(); }
  Real period() const { return 2 * t1() + tau1(); }
  Real x(Real t) const {
    t = std::fmod(t, period());
    if (t < t1()) return xc() + (x0 - xc()) * std::cos(w2() * t);
    if (t < t1() + tau1()) {
      const Real s = t - t1();
      return xt * std::cos(w1() * s) + (v1() / w1()) * std::sin(w1() * s);
    }
    return xc() + (x0 - xc()) * std::cos(w2() * (period() - t));
  }
};

// max |x_sim - x_exact| over two periods
Real oscillator_error(const Biphasic& b, Real L0, Integrator integ, Real dt) {
  const Real Lt = L0 + b.xt;
  Model m = make_model({0, 0, 0, L0 + b.x0, 0, 0}, {1.0, b.m},
                       {{0, 1, L0, b.k1, 0, false}, {0, 1, Lt, b.k2 - b.k1, 0, true}});
  State s = make_state(m);
  fix_nodes(m, s, std::vector<std::int32_t>{0});
  SolverOptions o = no_gravity(integ);
  o.substeps = 1;
  o.cg_tolerance = 1e-12;
  const long n = std::lround(2 * b.period() / dt);
  Real err = 0;
  for (long k = 1; k <= n; ++k) {
    step(m, s, dt, o);
    err = std::max(err, std::abs((s.x[3] - L0) - b.x(s.time)));
  }
  EXPECT_EQ(s.counters.events, 0);
  return err;
}

TEST(Solver, BiphasicOscillatorMatchesAnalyticSolution) {
  const Biphasic b{0.01, 100, 1000, 0.01, 0.015};
  const Real L0 = 0.1;
  ASSERT_GT(b.x0, b.xt);
  ASSERT_LT(b.amp1(), L0);  // never compressed through zero length
  const Real amp = b.amp1();
  const Real e5 = oscillator_error(b, L0, Integrator::symplectic_euler, 1e-5);
  const Real e4 = oscillator_error(b, L0, Integrator::symplectic_euler, 1e-4);
  EXPECT_LT(e5, 2e-3 * amp) << "symplectic Euler, dt 1e-5";
  EXPECT_GT(e4 / e5, 4) << "first-order convergence expected";
  const Real i5 = oscillator_error(b, L0, Integrator::implicit_euler, 1e-5);
  EXPECT_LT(i5, 2e-2 * amp) << "implicit Euler, dt 1e-5 (numerical damping)";
}

TEST(Solver, TensionOnlySpringIsSlackWhenShort) {
  // only the tension-only spring: at rest shorter than its rest length, nothing moves
  Model m = make_model({0, 0, 0, 0.05, 0, 0}, {1.0, 0.1}, {{0, 1, 0.1, 1000, 0, true}});
  State s = make_state(m);
  fix_nodes(m, s, std::vector<std::int32_t>{0});
  step(m, s, 0.01, no_gravity(Integrator::symplectic_euler));
  EXPECT_EQ(s.x[3], 0.05);
  EXPECT_EQ(s.v[3], 0.0);
}

// ---- hanging block: static equilibrium against a direct Newton solve ------------

TEST(Solver, HangingBlockEquilibriumMatchesNewton) {
  const auto block = make_layered_block(8, 4, 4);
  Model m = model_from_layers(block.layers, block.sets);
  State s0 = make_state(m);
  fix_nodes(m, s0, m.set("fixed"));

  testing::NewtonOptions no;
  no.gravity = {0, -9.81, 0};
  const auto ref = testing::solve_static(m, s0, no);
  ASSERT_TRUE(ref.converged) << "Newton residual " << ref.residual;
  const Real sag = max_node_distance(ref.x, m.rest_x);
  ASSERT_GT(sag, 1e-4) << "the block should sag visibly";

  {  // implicit Euler, large steps, mass damping: converges to the equilibrium
    State s = s0;
    SolverOptions o;
    o.integrator = Integrator::implicit_euler;
    o.mass_damping = 20;
    o.cg_tolerance = 1e-10;
    o.cg_max_iterations = 2000;
    for (int k = 0; k < 60; ++k) step(m, s, 1.0 / 30, o);
    const Real err = max_node_distance(s.x, ref.x);
    EXPECT_LT(err, 1e-3 * sag) << "implicit: error " << err << " m, sag " << sag << " m";
    EXPECT_EQ(s.counters.events, 0);
  }
  {  // symplectic Euler with automatic substeps and mass damping
    State s = s0;
    SolverOptions o;
    o.mass_damping = 80;
    for (int k = 0; k < 30; ++k) step(m, s, 1.0 / 60, o);
    const Real err = max_node_distance(s.x, ref.x);
    EXPECT_LT(err, 1e-3 * sag) << "symplectic: error " << err << " m, sag " << sag << " m";
    EXPECT_EQ(s.counters.events, 0);
  }
}

// ---- short trajectory against a small-step RK4 reference ----------------------

// independent reference: straightforward AoS forces, classic RK4
struct Rk4 {
  const Model& m;
  const State& s0;
  Eigen::Vector3d g;
  void accel(const std::vector<Eigen::Vector3d>& x, const std::vector<Eigen::Vector3d>& v,
             std::vector<Eigen::Vector3d>& a) const {
    const std::size_t n = x.size();
    std::vector<Eigen::Vector3d> f(n, Eigen::Vector3d::Zero());
    for (std::int32_t q = 0; q < m.n_springs; ++q) {
      const auto i = m.spring_a[q], j = m.spring_b[q];
      const Eigen::Vector3d d = x[j] - x[i];
      const double L = d.norm();
      if (L == 0) continue;
      const Eigen::Vector3d nrm = d / L;
      if (m.spring_tension[q] && L < m.spring_rest[q]) continue;
      const Eigen::Vector3d fa = (m.spring_k[q] * (L - m.spring_rest[q]) + m.spring_c[q] * (v[j] - v[i]).dot(nrm)) * nrm;
      f[i] += fa;
      f[j] -= fa;
    }
    a.assign(n, Eigen::Vector3d::Zero());
    for (std::size_t i = 0; i < n; ++i)
      if (s0.inv_mass[i] > 0) a[i] = f[i] * s0.inv_mass[i] + g;
  }
  std::vector<Real> run(Real T, Real h) const {
    const std::size_t n = static_cast<std::size_t>(m.n_nodes);
    std::vector<Eigen::Vector3d> x(n), v(n), k1x, k1v, k2x, k2v, k3x, k3v, k4x, k4v, xt(n), vt(n);
    for (std::size_t i = 0; i < n; ++i) {
      x[i] = Eigen::Vector3d(s0.x[3 * i], s0.x[3 * i + 1], s0.x[3 * i + 2]);
      v[i] = Eigen::Vector3d(s0.v[3 * i], s0.v[3 * i + 1], s0.v[3 * i + 2]);
    }
    const long steps = std::lround(T / h);
    for (long k = 0; k < steps; ++k) {
      k1x = v;
      accel(x, v, k1v);
      for (std::size_t i = 0; i < n; ++i) xt[i] = x[i] + 0.5 * h * k1x[i], vt[i] = v[i] + 0.5 * h * k1v[i];
      k2x = vt;
      accel(xt, vt, k2v);
      for (std::size_t i = 0; i < n; ++i) xt[i] = x[i] + 0.5 * h * k2x[i], vt[i] = v[i] + 0.5 * h * k2v[i];
      k3x = vt;
      accel(xt, vt, k3v);
      for (std::size_t i = 0; i < n; ++i) xt[i] = x[i] + h * k3x[i], vt[i] = v[i] + h * k3v[i];
      k4x = vt;
      accel(xt, vt, k4v);
      for (std::size_t i = 0; i < n; ++i) {
        x[i] += h / 6 * (k1x[i] + 2 * k2x[i] + 2 * k3x[i] + k4x[i]);
        v[i] += h / 6 * (k1v[i] + 2 * k2v[i] + 2 * k3v[i] + k4v[i]);
      }
    }
    std::vector<Real> out(3 * n);
    for (std::size_t i = 0; i < n; ++i)
      for (int k = 0; k < 3; ++k) out[3 * i + k] = x[i][k];
    return out;
  }
};

TEST(Solver, ShortTrajectoryConvergesToRk4) {
  testing::LayeredBlockOptions bo;
  bo.nu = 5, bo.nv = 3, bo.layers = 3;
  bo.thickness = {3e-3, 4e-3};
  bo.youngs = {50e3, 10e3};
  bo.youngs2 = bo.youngs;
  bo.turning_strain = {0, 0};
  bo.density = {1000, 1000};
  bo.names = {"a", "b", "c"};
  const auto block = make_layered_block(bo);
  Model m = model_from_layers(block.layers, block.sets);
  State s0 = make_state(m);
  fix_nodes(m, s0, m.set("fixed"));
  // a lateral kick on the skin so the motion is not purely along gravity
  for (auto i : m.set("skin")) s0.v[3 * static_cast<std::size_t>(i)] = 0.05;
  const Real T = 0.01;
  Rk4 rk{m, s0, Eigen::Vector3d(0, -9.81, 0)};
  const auto ref = rk.run(T, 1e-6);
  const Real motion = max_node_distance(ref, s0.x);
  ASSERT_GT(motion, 1e-5);

  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    // implicit Euler damps the stiff modes: it reaches the asymptotic regime at smaller steps
    const std::vector<Real> ladder = integ == Integrator::symplectic_euler ? std::vector<Real>{4e-5, 2e-5, 1e-5}
                                                                          : std::vector<Real>{1e-5, 5e-6, 2.5e-6};
    std::vector<Real> err;
    for (Real h : ladder) {
      State s = s0;
      SolverOptions o;
      o.integrator = integ;
      o.substeps = 1;
      o.cg_tolerance = 1e-12;
      o.cg_max_iterations = 1000;
      const long n = std::lround(T / h);
      for (long k = 0; k < n; ++k) step(m, s, h, o);
      EXPECT_EQ(s.counters.events, 0);
      err.push_back(max_node_distance(s.x, ref));
    }
    SCOPED_TRACE(to_string(integ));
    EXPECT_LT(err[2], 2e-2 * motion) << "error at dt " << ladder[2] << ": " << err[2] << " m of " << motion << " m motion";
    EXPECT_GT(err[0] / err[1], 1.6) << "first order: halving dt halves the error";
    EXPECT_GT(err[1] / err[2], 1.6);
    EXPECT_LT(err[1] / err[2], 2.6);
  }
}

// ---- conservation -------------------------------------------------------------

Model random_free_network(int n, int n_springs, std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<Real> u(-0.05, 0.05), km(50, 500), mm(0.01, 0.1), cm(0, 0.05);
  std::vector<Real> x(3 * static_cast<std::size_t>(n)), mass(static_cast<std::size_t>(n));
  for (auto& v : x) v = u(rng);
  for (auto& v : mass) v = mm(rng);
  std::vector<test::SpringSpec> sp;
  std::uniform_int_distribution<int> pick(0, n - 1);
  for (int q = 0; q < n_springs; ++q) {
    int a = pick(rng), b = pick(rng);
    if (a == b) b = (a + 1) % n;
    const Real L = std::sqrt((x[3 * a] - x[3 * b]) * (x[3 * a] - x[3 * b]) + (x[3 * a + 1] - x[3 * b + 1]) * (x[3 * a + 1] - x[3 * b + 1]) +
                             (x[3 * a + 2] - x[3 * b + 2]) * (x[3 * a + 2] - x[3 * b + 2]));
    sp.push_back({a, b, L * (0.8 + 0.4 * (q % 5) / 4.0), km(rng), cm(rng), q % 7 == 0});
  }
  return make_model(x, mass, sp);
}

TEST(Solver, FreeSpringsConserveMomentum) {
  Model m = random_free_network(30, 90, 7);
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    State s = make_state(m);
    std::mt19937 rng(3);
    std::uniform_real_distribution<Real> u(-0.5, 0.5);
    for (auto& v : s.v) v = u(rng);
    SolverOptions o = no_gravity(integ);
    o.cg_tolerance = 1e-12;
    o.cg_max_iterations = 1000;
    const auto p0 = momentum(m, s);
    Real scale = 0, lscale = 0;
    for (std::int32_t i = 0; i < m.n_nodes; ++i) {
      scale += m.mass[i] * norm(load3(s.v.data(), i));
      lscale += m.mass[i] * norm(load3(s.v.data(), i)) * norm(load3(s.x.data(), i));
    }
    for (int k = 0; k < 200; ++k) step(m, s, 1e-3, o);
    const auto p1 = momentum(m, s);
    SCOPED_TRACE(to_string(integ));
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(p1[c], p0[c], 1e-11 * scale) << "linear momentum " << c;
    if (integ == Integrator::symplectic_euler) {  // central forces: exact for symplectic Euler
      for (int c = 3; c < 6; ++c) EXPECT_NEAR(p1[c], p0[c], 1e-10 * lscale) << "angular momentum " << c - 3;
    }
    EXPECT_EQ(s.counters.events, 0);
  }
}

TEST(Solver, SymplecticEnergyDriftIsBoundedOver1e5Steps) {
  testing::LayeredBlockOptions bo;
  bo.nu = 3, bo.nv = 3, bo.layers = 2;
  bo.thickness = {4e-3};
  bo.youngs = {20e3};
  bo.youngs2 = bo.youngs;
  bo.turning_strain = {0};
  bo.density = {1000};
  bo.names = {"a", "b"};
  bo.damping_ratio = 0;
  const auto block = make_layered_block(bo);
  Model m = model_from_layers(block.layers, block.sets);
  State s = make_state(m);
  std::mt19937 rng(11);
  std::uniform_real_distribution<Real> u(-2e-4, 2e-4);
  for (auto& x : s.x) x += u(rng);  // a free, undamped, perturbed block
  SolverOptions o = no_gravity(Integrator::symplectic_euler);
  const Real h = 0.1 * symplectic_step_limit(m, s, o);
  o.substeps = 1;
  const Real e0 = energies(m, s, o).total();
  ASSERT_GT(e0, 0);
  const long n = 100000;
  Real dev = 0, first = 0, last = 0;
  int n_first = 0, n_last = 0;
  for (long k = 1; k <= n; ++k) {
    step(m, s, h, o);
    if (k % 50 == 0) {
      const Real e = energies(m, s, o).total();
      dev = std::max(dev, std::abs(e - e0) / e0);
      if (k <= n / 10) first += e, ++n_first;
      if (k > n - n / 10) last += e, ++n_last;
    }
  }
  const Real drift = std::abs(last / n_last - first / n_first) / e0;
  EXPECT_LT(dev, 0.05) << "energy oscillation bounded";
  EXPECT_LT(drift, 2e-3) << "no secular drift over 1e5 steps";
  EXPECT_EQ(s.counters.events, 0);
}

// State::spring_energy is the elastic energy at the start of the step's last
// substep with either integrator (the symplectic one computed it in the
// first substep only, so a run report read 0 whenever a step had several).
TEST(Solver, SpringEnergyIsThatOfTheLastSubstep) {
  const auto block = make_layered_block(6, 3, 3);
  const Model m = model_from_layers(block.layers, block.sets);
  SolverOptions o;
  o.integrator = Integrator::symplectic_euler;
  o.gravity = {0, -9.81, 0};
  State s = make_state(m);
  fix_nodes(m, s, m.set("fixed"));
  State r = s;  // the same steps one substep at a time
  const Real dt = 4 * 0.5 * symplectic_step_limit(m, s, o);
  o.substeps = 4;
  SolverOptions o1 = o;
  o1.substeps = 1;
  for (int k = 0; k < 5; ++k) {
    step(m, s, dt, o);
    for (int j = 0; j < 4; ++j) {
      if (j == 3) {
        const Real expected = energies(m, r, o).elastic;
        EXPECT_GT(expected, 0);
        // r and s are the same substeps: the energy pass sums in another order
        step(m, r, dt / 4, o1);
        EXPECT_NEAR(s.spring_energy, expected, 1e-9 * expected) << "step " << k;
      } else {
        step(m, r, dt / 4, o1);
      }
    }
    EXPECT_EQ(s.x, r.x) << "step " << k;
  }
  EXPECT_EQ(s.counters.events, 0);
}

// ---- determinism ------------------------------------------------------------------

std::uint64_t run_hash(Integrator integ, int threads, Preconditioner pc = Preconditioner::block_jacobi) {
  auto bo = make_layered_block(20, 9, 4).options;
  bo.youngs2 = bo.youngs;  // linear: fewer substeps, same code paths
  bo.youngs2[0] = 3 * bo.youngs[0];
  bo.turning_strain[0] = 0.01;
  bo.volume_modulus = {16 * bo.youngs[0]};  // the skin's volume term: 912 tetrahedra in 15 chunks
  const auto block = testing::make_layered_block(bo);
  Model m = model_from_layers(block.layers, block.sets);
  EXPECT_GT(m.n_tet_chunks, 1);
  State s = make_state(m);
  fix_nodes(m, s, m.set("fixed"));
  Attachment a;
  const auto& skin = m.set("skin");
  for (std::size_t j = 0; j < skin.size(); j += 7) {
    a.nodes.push_back(skin[j]);
    for (int k = 0; k < 3; ++k) a.offset.push_back(0);
  }
  for (std::size_t j = 0; j < a.nodes.size(); ++j)
    for (int k = 0; k < 3; ++k) a.offset[3 * j + k] = m.rest_x[3 * static_cast<std::size_t>(a.nodes[j]) + k];
  a.path.t = {0, 0.1};
  a.path.p = {0, 0, 0, 0, -0.004, 0.001};
  attach(m, s, a);
  SolverOptions o;
  o.integrator = integ;
  o.mass_damping = 1;
  o.preconditioner = pc;
  tbb::task_arena arena(threads);
  arena.execute([&] {
    for (int k = 0; k < (integ == Integrator::implicit_euler ? 30 : 10); ++k) step(m, s, 1.0 / 120, o);
  });
  EXPECT_TRUE(all_finite(s));
  return state_hash(s);
}

TEST(Solver, DeterministicAcrossRunsAndThreadCounts) {
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    const auto h1 = run_hash(integ, 1);
    EXPECT_EQ(run_hash(integ, 1), h1) << "same thread count, same hash";
    EXPECT_EQ(run_hash(integ, 2), h1) << "two threads, same hash";
  }
  // the sparse factor (the cholesky preconditioner) too
  const auto c1 = run_hash(Integrator::implicit_euler, 1, Preconditioner::cholesky);
  EXPECT_EQ(run_hash(Integrator::implicit_euler, 2, Preconditioner::cholesky), c1);
  EXPECT_NE(c1, run_hash(Integrator::implicit_euler, 1)) << "another preconditioner, another rounding";
}

// The PCG stops relative to the size of the right-hand side's terms (momentum,
// spring, gravity and external forces), not to the right-hand side itself,
// which vanishes at equilibrium where the terms cancel. A block at rest in its
// static equilibrium then needs no iterations and stays put; a test relative
// to |b| would iterate on round-off.
TEST(Solver, PcgAtEquilibriumDoesNotIterateOnRoundOff) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  State s = make_state(m);
  fix_nodes(m, s, m.set("fixed"));
  const State rest = s;
  SolverOptions settle;
  settle.integrator = Integrator::implicit_euler;
  settle.cg_tolerance = 1e-12;
  settle.cg_max_iterations = 1000;
  settle.mass_damping = 50;  // 1/s: with implicit Euler's own damping, at rest well within the 10 s
  for (int k = 0; k < 600; ++k) step(m, s, 1.0 / 60, settle);
  std::fill(s.v.begin(), s.v.end(), 0.0);
  std::fill(s.warm.begin(), s.warm.end(), 0.0);
  const Real sag = max_node_distance(s.x, rest.x);
  ASSERT_GT(sag, 1e-5);
  const State settled = s;
  SolverOptions o;  // the defaults
  o.integrator = Integrator::implicit_euler;
  const auto c0 = s.counters;
  for (int k = 0; k < 10; ++k) step(m, s, 1.0 / 60, o);
  const Real its = static_cast<Real>(s.counters.cg_iterations - c0.cg_iterations) / 10;
  EXPECT_LE(its, 2) << "iterations a step at rest in equilibrium";
  EXPECT_EQ(s.counters.cg_unconverged, c0.cg_unconverged);
  EXPECT_LT(max_node_distance(s.x, settled.x), 1e-6 * sag) << "the equilibrium is kept";
}

// A solve stopped at cg_max_iterations is redone with shorter substeps
// (redo_unconverged): a block whose skin cells are 0.1 mm thick under 4 mm
// squares (the lattice of `build --through-cells 64`) needs far more PCG
// iterations than the cap at dt = 1/60 s. Without the redo it drifts away
// from the converged motion; with it every kept solve converges and the
// motion is that of the converged solves at the substeps chosen.
TEST(Solver, UnconvergedSolvesAreRedoneWithShorterSubsteps) {
  testing::LayeredBlockOptions bo;
  bo.nu = 13, bo.nv = 5, bo.layers = 4;
  bo.thickness = {0.1e-3, 5e-3, 10e-3};
  const auto b = make_layered_block(bo);
  const Model m = model_from_layers(b.layers, b.sets);
  auto run = [&](int cap, bool redo, int substeps) {
    State s = make_state(m);
    fix_nodes(m, s, m.set("fixed"));
    SolverOptions o;
    o.integrator = Integrator::implicit_euler;
    o.mass_damping = 5;
    o.cg_max_iterations = cap;
    o.redo_unconverged = redo;
    o.substeps = substeps;
    o.preconditioner = Preconditioner::block_jacobi;  // (auto would switch to the factor at the first capped solve)
    int most = 0;
    for (int k = 0; k < 30; ++k) most = std::max(most, step(m, s, 1.0 / 60, o).substeps);
    return std::make_pair(s, most);
  };
  const auto [plain, plain_sub] = run(20, false, 0);
  const auto [redone, sub] = run(20, true, 0);
  EXPECT_GT(plain.counters.cg_unconverged, 0) << "the cap binds: the test needs it to";
  EXPECT_EQ(redone.counters.cg_unconverged, 0);
  EXPECT_GT(redone.counters.cg_redos, 0);
  EXPECT_EQ(redone.counters.events, 0) << "a redo for the solver is not a stability event";
  ASSERT_GT(sub, 1);
  // the reference: converged solves at the most substeps the redo chose
  const auto [ref, ref_sub] = run(100000, false, sub);
  EXPECT_EQ(ref.counters.cg_unconverged, 0);
  const State rest = make_state(m);
  const Real sag = max_node_distance(ref.x, rest.x);
  ASSERT_GT(sag, 1e-5);
  const Real err_redo = max_node_distance(redone.x, ref.x), err_plain = max_node_distance(plain.x, ref.x);
  std::printf("sag %.3g mm; substeps %d; off the converged motion: redone %.3g mm, plain %.3g mm\n", 1e3 * sag, sub,
              1e3 * err_redo, 1e3 * err_plain);
  EXPECT_LT(err_redo, 0.05 * sag);
  EXPECT_GT(err_plain, err_redo);
  (void)plain_sub;
  (void)ref_sub;
}

// ---- pins and attachments ----------------------------------------------------------

TEST(Solver, FixedAndKinematicNodes) {
  const auto block = make_layered_block(6, 3, 3);
  Model m = model_from_layers(block.layers, block.sets);
  State s = make_state(m);
  fix_nodes(m, s, m.set("fixed"));
  Attachment a;
  a.nodes = {m.set("skin")[4]};
  a.offset = {0, 0, 0};
  a.path.t = {0, 0.1};
  a.path.p = {0, 0, 0, 0.002, -0.003, 0};
  for (int k = 0; k < 3; ++k) a.path.p[k] = m.rest_x[3 * static_cast<std::size_t>(a.nodes[0]) + k];
  for (int k = 0; k < 3; ++k) a.path.p[3 + k] += m.rest_x[3 * static_cast<std::size_t>(a.nodes[0]) + k];
  attach(m, s, a);
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    State t = s;
    SolverOptions o;
    o.integrator = integ;
    for (int k = 0; k < 12; ++k) step(m, t, 0.01, o);
    const auto g = static_cast<std::size_t>(a.nodes[0]);
    EXPECT_NEAR(t.x[3 * g], a.path.p[3], 1e-12);
    EXPECT_NEAR(t.x[3 * g + 1], a.path.p[4], 1e-12);
    for (auto i : m.set("fixed"))
      for (int k = 0; k < 3; ++k) EXPECT_EQ(t.x[3 * static_cast<std::size_t>(i) + k], m.rest_x[3 * static_cast<std::size_t>(i) + k]);
    // released, the node moves again
    detach(m, t, 0);
    const Real before = t.x[3 * g + 1];
    for (int k = 0; k < 5; ++k) step(m, t, 0.01, o);
    EXPECT_NE(t.x[3 * g + 1], before);
  }
}

// ---- stability: detection and redo --------------------------------------------------

TEST(Solver, TooLargeFixedSubstepIsDetectedAndRedone) {
  const auto block = make_layered_block(6, 3, 3);
  Model m = model_from_layers(block.layers, block.sets);
  State s = make_state(m);
  fix_nodes(m, s, m.set("fixed"));
  SolverOptions o;
  const Real limit = symplectic_step_limit(m, s, o);
  o.substeps = 1;  // told otherwise: no automatic substeps
  const Real dt = 64 * limit;
  for (int k = 0; k < 20; ++k) {
    const auto info = step(m, s, dt, o);
    ASSERT_TRUE(all_finite(s)) << "step " << k;
    EXPECT_FALSE(info.failed);
  }
  EXPECT_GT(s.counters.events, 0);
  EXPECT_GT(s.counters.recovered, 0);
  EXPECT_EQ(s.counters.failed, 0);

  // without redos the step fails: the state is restored, at rest, finite
  State t = make_state(m);
  fix_nodes(m, t, m.set("fixed"));
  o.max_retries = 0;
  Real last_time = 0;
  for (int k = 0; k < 30; ++k) {
    step(m, t, dt, o);
    ASSERT_TRUE(all_finite(t));
    last_time = t.time;
  }
  EXPECT_GT(t.counters.failed, 0);
  EXPECT_NEAR(last_time, 30 * dt, 1e-12);
}

// The damped oscillator's limit (2 / omega)(sqrt(1 + z^2) - z), z = gamma / (2 omega),
// tends to 2 / gamma for heavy damping; it was computed as 0 for z > ~1e8 (read as no
// limit: one substep a step, a blow-up, no word), and a node of 1e-300 kg made it
// "no limit" too.
TEST(Solver, TheStabilityLimitHoldsForHeavyDampingAndTinyMasses) {
  for (const Real z : {0.0, 1e-3, 1.0, 1e4, 1e8, 1e12, 1e200}) {
    const Real omega = 50, gamma = 2 * z * omega;
    const Real exact = z < 1e4 ? (2 / omega) * (std::sqrt(1 + z * z) - z) : (2 / omega) / (2 * z) * (1 - 1 / (4 * z * z));
    EXPECT_NEAR(symplectic_limit(omega, gamma) / exact, 1.0, 1e-12) << "z = " << z;
  }
  const auto block = make_layered_block(6, 3, 3);
  Model m = model_from_layers(block.layers, block.sets);
  SolverOptions o;
  {
    State s = make_state(m);
    fix_nodes(m, s, m.set("fixed"));
    const Real light = symplectic_step_limit(m, s, o);
    for (auto& g : m.gamma) g *= 1e12;  // damping 1e12 times the model's
    s.step_limit = 0;
    const Real damped = symplectic_step_limit(m, s, o);
    EXPECT_GT(damped, 0);
    EXPECT_LT(damped, 1e-6 * light);
    const auto info = step(m, s, 1.0 / 60, o);
    EXPECT_EQ(info.substeps, o.max_substeps) << "a heavily damped model needs more substeps than allowed";
  }
  Model tiny = model_from_layers(block.layers, block.sets);
  for (std::int32_t i = 0; i < tiny.n_nodes; ++i) tiny.omega2[i] = HUGE_VAL;  // k / m of a 1e-300 kg node
  State t = make_state(tiny);
  fix_nodes(tiny, t, tiny.set("fixed"));
  EXPECT_GT(symplectic_step_limit(tiny, t, o), 0);
  EXPECT_LT(symplectic_step_limit(tiny, t, o), 1e-300);
}

TEST(Solver, AutomaticSubstepsFollowTheStabilityLimit) {
  const auto block = make_layered_block(6, 3, 3);
  Model m = model_from_layers(block.layers, block.sets);
  State s = make_state(m);
  fix_nodes(m, s, m.set("fixed"));
  SolverOptions o;
  const Real limit = symplectic_step_limit(m, s, o);
  const auto info = step(m, s, 1.0 / 60, o);
  EXPECT_EQ(info.substeps, static_cast<int>(std::ceil((1.0 / 60) / (o.safety * limit))));
  EXPECT_EQ(info.retries, 0);
}

// ---- the volume term (Model::tet) ---------------------------------------------------

// A two-sheet block (one cell layer 4 mm thick, 4 mm cells) whose cells carry
// a volume term of modulus kv (6 Kuhn tetrahedra each), undamped springs of
// modulus E, the second sheet rigid ("fixed"); group: one term per
// tetrahedron (1, a tetra layer's) or per cell (6, a lattice layer's).
testing::LayeredBlock volume_block(Real kv, Real E, int nu = 4, int nv = 3, int group = 1) {
  testing::LayeredBlockOptions bo;
  bo.nu = nu, bo.nv = nv, bo.layers = 2;
  bo.thickness = {4e-3};
  bo.youngs = {E};
  bo.youngs2 = bo.youngs;
  bo.turning_strain = {0};
  bo.density = {1000};
  bo.names = {"a", "b"};
  bo.damping_ratio = 0;
  bo.volume_modulus = {kv};
  bo.volume_group = group;
  return make_layered_block(bo);
}

Real max_abs(const std::vector<Real>& v) {
  Real r = 0;
  for (Real x : v) r = std::max(r, std::abs(x));
  return r;
}

// The force the solver applies at s.x (one symplectic substep of 1e-14 s,
// no gravity) against central differences of the elastic energy it
// reports; returns the force.
std::vector<Real> expect_force_is_minus_the_energy_gradient(const Model& m, State s) {
  SolverOptions o = no_gravity(Integrator::symplectic_euler);
  o.substeps = 1;
  const std::vector<Real> x0 = s.x;
  step(m, s, 1e-14, o);  // s.f: the forces at x0
  const std::vector<Real> f = s.f;
  Real err = 0;
  for (std::size_t d = 0; d < x0.size(); ++d) {
    const Real eps = 1e-7 * 4e-3;
    State p = s, q = s;
    p.x = x0, q.x = x0;
    p.x[d] += eps, q.x[d] -= eps;
    const Real grad = (energies(m, p, o).elastic - energies(m, q, o).elastic) / (2 * eps);
    err = std::max(err, std::abs(f[d] + grad));
  }
  EXPECT_GT(max_abs(f), 0);
  EXPECT_LT(err, 1e-6 * max_abs(f));
  return f;
}

std::vector<Real> tet_volumes(const Model& m, const std::vector<Real>& x) {
  std::vector<Real> v;
  for (std::int32_t t = 0; t < m.n_tets; ++t) {
    const std::int32_t* c = &m.tet[4 * static_cast<std::size_t>(t)];
    v.push_back(tet_gradient(load3(x.data(), c[0]), load3(x.data(), c[1]), load3(x.data(), c[2]), load3(x.data(), c[3])).volume);
  }
  return v;
}

// The force the solver applies is minus the gradient of the energy it
// reports (energies().elastic), by central differences at a deformed state:
// the volume term's force, energy and their bookkeeping per corner agree.
// Both for a term per tetrahedron and one per cell (a group of 6).
TEST(VolumeTerm, TheForceIsMinusTheGradientOfTheEnergy) {
 for (const int group : {1, 6}) {
  SCOPED_TRACE(group);
  const auto block = volume_block(1e5, 2e3, 4, 3, group);
  const Model m = model_from_layers(block.layers, block.sets);
  ASSERT_EQ(m.n_tets, 3 * 2 * 6);
  ASSERT_EQ(m.n_groups, 3 * 2 * 6 / group);
  State s = make_state(m);
  std::mt19937 rng(5);
  std::uniform_real_distribution<Real> u(-4e-4, 4e-4);  // 10 % of a cell
  for (auto& x : s.x) x += u(rng);
  const std::vector<Real> x0 = s.x;
  SolverOptions o = no_gravity(Integrator::symplectic_euler);
  o.substeps = 1;
  const std::vector<Real> f = expect_force_is_minus_the_energy_gradient(m, s);
  const Real fmax = max_abs(f);
  // and most of it is the volume term's: without it the forces differ
  auto springs_only = block;
  springs_only.layers[0].second.volume_modulus = 0;
  const Model m0 = model_from_layers(springs_only.layers, springs_only.sets);
  EXPECT_EQ(m0.n_tets, 0);
  State s0 = make_state(m0);
  s0.x = x0;
  step(m0, s0, 1e-14, o);
  EXPECT_GT(max_node_distance(s0.f, f), 0.5 * fmax);
 }
}

// The inversion guard (Layer::guard_modulus, guard_ratio; docs/msm.md, "The
// inversion guard") does nothing until a tetrahedron has lost 1 - a of its
// volume: a block squashed to 70 % of its thickness has the springs' energy
// alone, to 30 % the springs' plus (k/2) (0.3 - a)^2 |V0| per tetrahedron
// (0.5 here), also with the tetrahedra written the other way round (a
// negative V0); and its force is minus the gradient of that energy where some
// tetrahedra are past the ratio and some are not.
TEST(VolumeTerm, TheGuardActsOnlyBelowItsRatio) {
  constexpr Real kGuard = 1e5, kE = 2e3;
  auto guarded = volume_block(0, kE, 4, 3);
  guarded.options.guard_modulus = {kGuard};
  guarded = testing::make_layered_block(guarded.options);
  const auto plain = volume_block(0, kE, 4, 3);
  auto flipped = guarded;
  for (Eigen::Index t = 0; t < flipped.layers[0].second.tets.rows(); ++t)
    std::swap(flipped.layers[0].second.tets(t, 2), flipped.layers[0].second.tets(t, 3));
  const Model m = model_from_layers(guarded.layers, guarded.sets), mf = model_from_layers(flipped.layers, flipped.sets),
              m0 = model_from_layers(plain.layers, plain.sets);
  ASSERT_EQ(m.n_tets, 3 * 2 * 6);
  ASSERT_EQ(m.n_groups, m.n_tets);
  ASSERT_EQ(m0.n_tets, 0);
  EXPECT_EQ(m.flat_guards_skipped, 0);
  {
    // a tetrahedron flat at rest (four nodes of the top sheet) has no
    // orientation to guard: left out and counted, the model still loads
    auto flat = guarded;
    Layer& l = flat.layers[0].second;
    l.tets.conservativeResize(l.tets.rows() + 1, 4);
    const VecXi& top = flat.sets.at("skin");
    l.tets.row(l.tets.rows() - 1) << top(0), top(1), top(2), top(3);
    const Model mflat = model_from_layers(flat.layers, flat.sets);
    EXPECT_EQ(mflat.n_tets, m.n_tets);
    EXPECT_EQ(mflat.flat_guards_skipped, 1);
  }
  for (Real v : mf.tet_rest_volume) ASSERT_LT(v, 0);
  const Real block_volume = 12e-3 * 8e-3 * 4e-3;
  const SolverOptions o = no_gravity(Integrator::symplectic_euler);
  // the top sheet (y = 0) moved towards the bottom one (y = 4 mm): every
  // tetrahedron keeps the fraction f of its volume
  auto squashed = [&](const Model& mm, Real f) {
    State s = make_state(mm);
    for (std::int32_t i : mm.set("skin")) s.x[3 * static_cast<std::size_t>(i) + 1] = 4e-3 * (1 - f);
    return s;
  };
  for (const Model* g : {&m, &mf}) {
    EXPECT_EQ(energies(*g, make_state(*g), o).elastic, 0);
    const Real e70 = energies(*g, squashed(*g, 0.7), o).elastic, s70 = energies(m0, squashed(m0, 0.7), o).elastic;
    EXPECT_GT(s70, 0);
    EXPECT_EQ(e70, s70);
    const Real e30 = energies(*g, squashed(*g, 0.3), o).elastic, s30 = energies(m0, squashed(m0, 0.3), o).elastic;
    EXPECT_NEAR(e30 - s30, 0.5 * kGuard * 0.2 * 0.2 * block_volume, 1e-9 * e30);
  }
  // force against energy, squashed to 45 % and shaken by 10 % of a cell
  State s = squashed(m, 0.45);
  std::mt19937 rng(7);
  std::uniform_real_distribution<Real> u(-4e-4, 4e-4);
  for (auto& x : s.x) x += u(rng);
  const auto v = tet_volumes(m, s.x);
  int below = 0;
  for (std::int32_t t = 0; t < m.n_tets; ++t) below += v[t] < 0.5 * m.tet_rest_volume[t];
  ASSERT_GT(below, 0);
  ASSERT_LT(below, m.n_tets);
  expect_force_is_minus_the_energy_gradient(m, s);
}

// The solver visits a node's guard corners only where one of its guards acts
// (Model::tet_guard_begin: finalize puts each node's volume-term corners
// first, then its guards'). The order the groups come in is no part of the
// physics: the block with its guards written before its terms steps as the
// one with them after, from a squashed state where some guards act and some
// do not.
TEST(VolumeTerm, GuardsAndTermsInAnyOrderStepAlike) {
  auto bo = volume_block(2e4, 2e3, 4, 3, 6).options;
  bo.guard_modulus = {1e5};
  const auto block = testing::make_layered_block(bo);
  const Model m = model_from_layers(block.layers, block.sets);
  Model r = m;  // the same groups, the guards' first
  r.tet.clear(), r.tet_k.clear(), r.tet_guard.clear(), r.tet_group_first.assign(1, 0);
  for (const bool guards : {true, false})
    for (std::int32_t g = 0; g < m.n_groups; ++g) {
      const std::int32_t t0 = m.tet_group_first[g], t1 = m.tet_group_first[g + 1];
      if ((m.tet_guard[t0] > 0) != guards) continue;
      r.tet.insert(r.tet.end(), m.tet.begin() + 4 * t0, m.tet.begin() + 4 * t1);
      r.tet_k.insert(r.tet_k.end(), m.tet_k.begin() + t0, m.tet_k.begin() + t1);
      r.tet_guard.insert(r.tet_guard.end(), m.tet_guard.begin() + t0, m.tet_guard.begin() + t1);
      r.tet_group_first.push_back(static_cast<std::int32_t>(r.tet_k.size()));
    }
  r.finalize();
  ASSERT_EQ(r.n_groups, m.n_groups);
  ASSERT_EQ(r.n_tets, m.n_tets);
  for (const Model* mm : {&m, static_cast<const Model*>(&r)}) {
    int terms = 0, guards = 0;
    for (std::int32_t i = 0; i < mm->n_nodes; ++i) {
      const auto* c = mm->tet_corner.data();
      const std::int32_t q0 = mm->tet_first[i], qg = mm->tet_guard_begin[i], q1 = mm->tet_first[i + 1];
      ASSERT_LE(q0, qg);
      ASSERT_LE(qg, q1);
      for (std::int32_t q = q0; q < qg; ++q, ++terms) EXPECT_EQ(mm->tet_guard[c[q] >> 2], 0);
      for (std::int32_t q = qg; q < q1; ++q, ++guards) EXPECT_GT(mm->tet_guard[c[q] >> 2], 0);
      EXPECT_TRUE(std::is_sorted(c + q0, c + qg) && std::is_sorted(c + qg, c + q1)) << i;
    }
    EXPECT_EQ(terms + guards, 4 * mm->n_tets);
    EXPECT_GT(terms, 0);
    EXPECT_GT(guards, 0);
  }
  // the top sheet squashed to 40 % of the layer and shaken by 10 % of a cell
  State a = make_state(m), b = make_state(r);
  for (std::int32_t i : m.set("skin")) a.x[3 * static_cast<std::size_t>(i) + 1] = 4e-3 * 0.6;
  std::mt19937 rng(11);
  std::uniform_real_distribution<Real> u(-4e-4, 4e-4);
  for (std::int32_t i : m.set("skin"))
    for (int d = 0; d < 3; ++d) a.x[3 * static_cast<std::size_t>(i) + static_cast<std::size_t>(d)] += u(rng);
  b.x = a.x;
  const auto v = tet_volumes(m, a.x);
  int acting = 0, guarded = 0;
  for (std::int32_t t = 0; t < m.n_tets; ++t)
    if (m.tet_guard[t] > 0) ++guarded, acting += v[t] / m.tet_rest_volume[t] < m.tet_guard[t];
  ASSERT_GT(acting, 0);
  ASSERT_LT(acting, guarded);
  fix_nodes(m, a, m.set("fixed"));
  fix_nodes(r, b, r.set("fixed"));
  SolverOptions o = no_gravity(Integrator::implicit_euler);
  o.mass_damping = 20;
  for (int k = 0; k < 30; ++k) {
    step(m, a, 1e-3, o);
    step(r, b, 1e-3, o);
  }
  EXPECT_EQ(a.counters.events, 0);
  EXPECT_EQ(b.counters.events, 0);
  EXPECT_GT(max_node_distance(a.x, make_state(m).x), 1e-4);
  // each node adds the same corners in the same order (its terms', then its
  // guards'), and a group's pressure does not depend on where it is listed
  EXPECT_EQ(max_node_distance(a.x, b.x), 0);
}

// Central springs do not resist a layer turned inside out: its mirror image
// through the sheet below has every spring at its rest length. The volume
// term does, and so does the inversion guard alone: with either the layer
// unfolds to its rest shape, without them the mirrored layer is an
// equilibrium and stays.
TEST(VolumeTerm, AMirroredLayerUnfoldsOnlyWithIt) {
  // group 0: no volume term, the inversion guard alone (at its modulus kv)
  for (const auto& [kv, group] : {std::pair<Real, int>{0.0, 1}, {2e4, 1}, {2e4, 6}, {2e4, 0}}) {
    SCOPED_TRACE(std::to_string(kv) + " group " + std::to_string(group));
    auto block = volume_block(group == 0 ? 0 : kv, 2e3, 6, 4, std::max(group, 1));
    if (group == 0) {
      block.options.guard_modulus = {kv};
      block = testing::make_layered_block(block.options);
    }
    const Model m = model_from_layers(block.layers, block.sets);
    State s = make_state(m);
    fix_nodes(m, s, m.set("fixed"));
    // the top sheet (y = 0) mirrored through the bottom one (y = 4 mm)
    for (std::int32_t i : m.set("skin")) s.x[3 * static_cast<std::size_t>(i) + 1] = 8e-3;
    ASSERT_EQ(inverted_columns(m, s.x).at(0).inverted, 6 * 4);
    SolverOptions o = no_gravity(Integrator::implicit_euler);
    o.mass_damping = 20;
    for (int k = 0; k < 500; ++k) step(m, s, 1e-3, o);
    EXPECT_EQ(s.counters.events, 0);
    const auto inv = inverted_columns(m, s.x).at(0);
    if (kv == 0) {
      EXPECT_EQ(inv.inverted, 6 * 4) << "springs alone: the mirror image is at rest";
    } else {
      EXPECT_EQ(inv.inverted, 0);
      EXPECT_LT(max_node_distance(s.x, m.rest_x), 1e-5) << "back at rest";
      const auto v = tet_volumes(m, s.x);
      for (std::int32_t t = 0; t < m.n_tets; ++t) EXPECT_GT(v[t] / m.tet_rest_volume[t], 0.99) << t;
    }
  }
}

// A squeezed block released: symplectic Euler with automatic substeps stays
// stable with a volume term 50 times the springs' modulus (the Gershgorin
// bound counts it), its energy bounded at that step and kept at a tenth of
// it; implicit Euler settles at the rest volume.
TEST(VolumeTerm, BothIntegratorsAreStableWithAStiffVolumeTerm) {
 for (const int group : {1, 6}) {
  SCOPED_TRACE(group);
  const auto block = volume_block(1e6, 2e4, 4, 3, group);
  const Model m = model_from_layers(block.layers, block.sets);
  const auto loose = volume_block(0, 2e4);
  const Model m0 = model_from_layers(loose.layers, loose.sets);
  {
    State s = make_state(m), s0 = make_state(m0);
    EXPECT_LT(symplectic_step_limit(m, s, SolverOptions{}), 0.5 * symplectic_step_limit(m0, s0, SolverOptions{}))
        << "the stiffer term shortens the stability limit";
  }
  int auto_substeps = 0;
  for (int run = 0; run < 3; ++run) {
    const Integrator integ = run < 2 ? Integrator::symplectic_euler : Integrator::implicit_euler;
    SCOPED_TRACE(std::string(to_string(integ)) + (run == 1 ? ", ten times the substeps" : ""));
    State s = make_state(m);
    fix_nodes(m, s, m.set("fixed"));
    for (std::int32_t i : m.set("skin")) s.x[3 * static_cast<std::size_t>(i) + 1] += 8e-4;  // 20 % thinner
    SolverOptions o = no_gravity(integ);
    if (run == 1) o.substeps = 10 * auto_substeps;
    if (run == 2) o.mass_damping = 50;
    const Real e0 = energies(m, s, o).total();
    ASSERT_GT(e0, 0);
    Real dev = 0;
    for (int k = 0; k < 300; ++k) {
      const StepInfo info = step(m, s, 1e-3, o);
      if (run == 0) auto_substeps = info.substeps;
      ASSERT_TRUE(all_finite(s));
      dev = std::max(dev, std::abs(energies(m, s, o).total() - e0) / e0);
    }
    EXPECT_EQ(s.counters.events, 0);
    if (run == 0) {
      EXPECT_GT(auto_substeps, 1);
      EXPECT_LT(dev, 0.5) << "energy bounded";
    } else if (run == 1) {
      EXPECT_LT(dev, 0.03) << "energy kept";
    } else {
      Real v = 0, v0 = 0;
      for (Real x : tet_volumes(m, s.x)) v += x;
      for (Real x : m.tet_rest_volume) v0 += x;
      EXPECT_GT(v0, 0);
      EXPECT_NEAR(v / v0, 1, 1e-4);
      EXPECT_EQ(s.counters.cg_unconverged, 0);
    }
  }
 }
}

// The cholesky preconditioner (SolverOptions::preconditioner) on a stiff,
// nearly incompressible skin (a volume term 16 times its springs' modulus, the
// default nu = 0.49, over a 50 times softer fat): the same motion as block
// Jacobi within the solves' tolerance in a few iterations where block Jacobi
// takes hundreds, "auto" switching to it after block Jacobi's first
// unconverged solve; and a State's copy, sharing its factor, steps exactly as
// the original.
TEST(Solver, TheCholeskyPreconditionerSolvesStiffVolumeTerms) {
  auto bo = make_layered_block(15, 5, 4).options;
  bo.volume_modulus = {16 * bo.youngs[0]};
  const auto block = testing::make_layered_block(bo);
  const Model m = model_from_layers(block.layers, block.sets);
  struct Run {
    State s;
    std::vector<Real> x;
  };
  auto run = [&](Preconditioner pc) {
    State s = make_state(m);
    fix_nodes(m, s, m.set("fixed"));
    SolverOptions o;
    o.integrator = Integrator::implicit_euler;
    o.preconditioner = pc;
    o.cg_tolerance = 1e-8;
    o.cg_max_iterations = 2000;  // block Jacobi converges too, given the iterations
    o.redo_unconverged = false;
    for (int k = 0; k < 20; ++k) step(m, s, 1.0 / 60, o);
    return s;
  };
  const State bj = run(Preconditioner::block_jacobi), ch = run(Preconditioner::cholesky);
  EXPECT_EQ(bj.counters.events + ch.counters.events, 0);
  EXPECT_EQ(bj.counters.cg_unconverged + ch.counters.cg_unconverged, 0);
  EXPECT_LT(max_node_distance(bj.x, ch.x), 1e-6 * m.extent) << "the same solution";
  Real moved = max_node_distance(ch.x, m.rest_x);
  EXPECT_GT(moved, 1e-4) << "the block sagged";
  EXPECT_GT(ch.counters.factorizations, 0);
  EXPECT_LT(ch.counters.cg_iterations * 10, bj.counters.cg_iterations)
      << "cholesky " << ch.counters.cg_iterations << ", block Jacobi " << bj.counters.cg_iterations;
  RecordProperty("cg_iterations_block_jacobi", std::to_string(bj.counters.cg_iterations));
  RecordProperty("cg_iterations_cholesky", std::to_string(ch.counters.cg_iterations));
  RecordProperty("factorizations", std::to_string(ch.counters.factorizations));

  // auto: block Jacobi stops at the default 200 iterations, switches, and the step is redone
  State a = make_state(m);
  fix_nodes(m, a, m.set("fixed"));
  SolverOptions o;
  o.integrator = Integrator::implicit_euler;
  EXPECT_EQ(o.preconditioner, Preconditioner::automatic);
  for (int k = 0; k < 20; ++k) step(m, a, 1.0 / 60, o);
  EXPECT_TRUE(a.cholesky_on);
  EXPECT_GT(a.counters.factorizations, 0);
  EXPECT_EQ(a.counters.cg_unconverged, 0);
  EXPECT_LT(max_node_distance(a.x, ch.x), 1e-4 * m.extent);

  // a copy shares the factor and steps bit for bit as the original
  State b = a;
  ASSERT_EQ(b.factor, a.factor);
  for (int k = 0; k < 10; ++k) {
    step(m, a, 1.0 / 60, o);
    step(m, b, 1.0 / 60, o);
  }
  EXPECT_EQ(state_hash(a), state_hash(b));
  EXPECT_EQ(a.counters.factorizations, b.counters.factorizations);
}


// ---- static obstacles (runtime/obstacles.h) ------------------------------------

// A square [-1, 1] m in x and z at height y, two triangles counter-clockwise
// seen from +y (the front of a one-sided mesh).
ObstacleMesh square_at(Real y, Real friction, Real restitution = 0, bool two_sided = false) {
  ObstacleMesh m;
  m.vertices = {-1, y, -1, 1, y, -1, 1, y, 1, -1, y, 1};
  m.triangles = {0, 2, 1, 0, 3, 2};
  m.friction = friction;
  m.restitution = restitution;
  m.two_sided = two_sided;
  return m;
}

// One free node on a table (y = 0), with a fixed node 1 m away so that the
// model has an extent (the stability check's energy budget scales with it).
Model node_on_table() { return make_model({0, 0, 0, 1, 0, 0}, {0.01, 0}, {}); }

// A node sliding at v0 on a table under gravity stops after v0^2 / (2 mu g)
// (Coulomb friction: mu g of deceleration), with the table as a plane or a
// mesh, for both integrators; the discrete sum differs from the integral by
// less than one substep's travel, v0 h. (Symplectic: each substep's contact
// takes g h of normal velocity and at most mu g h of tangential. Implicit:
// the node is held on the table and its friction is a damper mu N / |v_t|
// in the solve, mu N / creep_speed below creep_speed, which stops it.)
TEST(Obstacles, ASlidingNodeStopsWhereCoulombFrictionSays) {
  const Real v0 = 0.5, mu = 0.4, g = 9.81, h = 1e-3;
  const Real expected = v0 * v0 / (2 * mu * g);  // 31.9 mm, after v0 / (mu g) = 0.127 s
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler})
    for (bool as_mesh : {false, true}) {
      SCOPED_TRACE(std::string(to_string(integ)) + (as_mesh ? ", mesh" : ", plane"));
      const Model m = node_on_table();
      State s = make_state(m);
      s.v = {v0, 0, 0, 0, 0, 0};
      auto ob = std::make_shared<Obstacles>();
      if (as_mesh) add_obstacle_mesh(*ob, square_at(0, mu));
      else add_obstacle_plane(*ob, {{0, 0, 0}, {0, 2, 0}, 0, mu});  // (a normal of any length)
      s.obstacles = ob;
      SolverOptions o;
      o.integrator = integ;
      o.substeps = 1;
      Real lowest = 0;
      for (int k = 0; k < 300; ++k) {
        step(m, s, h, o);
        lowest = std::min(lowest, s.x[1]);
      }
      EXPECT_NEAR(s.x[0], expected, v0 * h) << "stopping distance";
      if (integ == Integrator::symplectic_euler) EXPECT_EQ(s.v[0], 0) << "at rest: friction stops it, never reverses it";
      else EXPECT_LT(std::abs(s.v[0]), 1e-9 * v0) << "at rest: below creep_speed the damper takes the speed to zero";
      EXPECT_GE(s.v[0], -o.cg_tolerance * g * h) << "never reversed (the implicit solve: within its tolerance)";
      EXPECT_GE(lowest, 0) << "never below the table";
      EXPECT_LT(s.x[1], 1e-8) << "on it";
      EXPECT_EQ(s.counters.obstacle_contacts, 300) << "in contact every substep";
      EXPECT_EQ(s.counters.events, 0);
    }
}

// Coulomb's law under a steady tangential pull F on a node resting on a
// table: inside the friction cone (F = mu m g / 2) it stays (the implicit
// solve's smoothed friction lets it creep at most creep_speed); outside (F =
// 2 mu m g) it slides with acceleration (F - mu m g) / m = mu g. Both
// integrators, a plane table.
TEST(Obstacles, APulledNodeSticksInsideTheFrictionConeAndSlidesOutside) {
  const Real mu = 0.4, g = 9.81, mass = 0.01, h = 1e-3;
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    SolverOptions o;
    o.integrator = integ;
    o.substeps = 1;
    auto pull = [&](Real F, int steps) {
      const Model m = node_on_table();
      State s = make_state(m);
      auto ob = std::make_shared<Obstacles>();
      add_obstacle_plane(*ob, {{0, 0, 0}, {0, 1, 0}, 0, mu});
      s.obstacles = ob;
      s.f_ext = {F, 0, 0, 0, 0, 0};
      std::vector<Real> vx;
      for (int k = 0; k < steps; ++k) {
        step(m, s, h, o);
        vx.push_back(s.v[0]);
      }
      EXPECT_EQ(s.counters.events, 0);
      EXPECT_GE(s.x[1], 0);
      return std::pair{s.x[0], vx};
    };
    // inside the cone, 1 s
    const auto [x_in, v_in] = pull(0.5 * mu * mass * g, 1000);
    // (symplectic: each substep meets the table 10^-9 m below its start, after
    // a sliver of the substep's motion: 0.2 micrometres in 1 s)
    if (integ == Integrator::symplectic_euler) EXPECT_LT(x_in, 1e-6) << "it sticks";
    else EXPECT_LE(x_in, 0.5 * o.friction_creep_speed * 1.0) << "it creeps at most F / (mu N) creep_speed";
    EXPECT_GE(x_in, 0);
    // outside, 0.2 s: the acceleration over the last 0.1 s
    const auto [x_out, v_out] = pull(2 * mu * mass * g, 200);
    const Real a = (v_out[199] - v_out[99]) / (100 * h);
    EXPECT_NEAR(a, mu * g, 0.01 * mu * g) << "kinetic friction mu m g";
    EXPECT_GT(x_out, 0);
  }
}

// A mesh stops a node however fast it comes (the crossing is found along its
// motion, not at its end): 100 m/s at a zero-thickness square, 10 cm a
// substep. It slides on (the tangential motion of the substep is kept
// without friction), bounces with restitution, and a one-sided mesh lets a
// node through from behind while a two-sided one does not.
TEST(Obstacles, AFastNodeDoesNotTunnelThroughAThinMesh) {
  const Real h = 1e-3;
  SolverOptions o;
  o.gravity = {0, 0, 0};
  o.substeps = 1;
  auto shoot = [&](ObstacleMesh mesh, Real y0, Real vy) {
    const Model m = make_model({0, y0, 0}, {0.01}, {});
    State s = make_state(m);
    s.v = {0.3, vy, 0.2};
    auto ob = std::make_shared<Obstacles>();
    add_obstacle_mesh(*ob, std::move(mesh));
    s.obstacles = ob;
    step(m, s, h, o);
    return s;
  };
  {  // from the front, no friction, no restitution: on the square, sliding
    const State s = shoot(square_at(0, 0), 0.05, -100);
    EXPECT_GT(s.x[1], 0);
    EXPECT_LT(s.x[1], 1e-8);
    EXPECT_DOUBLE_EQ(s.x[0], 0.3 * h);
    EXPECT_DOUBLE_EQ(s.x[2], 0.2 * h);
    EXPECT_EQ(s.v[1], 0);
    EXPECT_DOUBLE_EQ(s.v[0], 0.3);
    EXPECT_EQ(s.counters.obstacle_contacts, 1);
  }
  {  // restitution 0.5: it leaves at half the speed it came with
    const State s = shoot(square_at(0, 0, 0.5), 0.05, -100);
    EXPECT_DOUBLE_EQ(s.v[1], 50);
  }
  {  // from behind a one-sided square: through; a two-sided one stops it below
    const State one = shoot(square_at(0, 0), -0.05, 100);
    EXPECT_NEAR(one.x[1], 0.05, 1e-12);
    EXPECT_EQ(one.counters.obstacle_contacts, 0);
    const State two = shoot(square_at(0, 0, 0, true), -0.05, 100);
    EXPECT_LT(two.x[1], 0);
    EXPECT_GT(two.x[1], -1e-8);
    EXPECT_EQ(two.v[1], 0);
  }
  {  // past the square's edge: nothing to cross
    ObstacleMesh small = square_at(0, 0);
    for (std::size_t k = 0; k < small.vertices.size(); k += 3) small.vertices[k] = 0.5 + 0.01 * small.vertices[k];
    const State s = shoot(std::move(small), 0.05, -100);
    EXPECT_NEAR(s.x[1], 0.05 - 100 * h, 1e-12);
  }
}

// The paper's block (13 x 5 x 4, fixed at its top sheet) hangs under gravity;
// a table under its skin, at a third of its sag without one, holds it: no node goes
// below the table, the skin rests on it, and a plane and a mesh in the same
// place give the same state (the mesh keeps nodes 1e-9 m in front of it), for
// both integrators, without a stability event.
TEST(Obstacles, ATableHoldsASaggingBlock) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  Real rest_low = HUGE_VAL;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) rest_low = std::min(rest_low, m.rest_x[3 * static_cast<std::size_t>(i) + 1]);
  // (the implicit solve with block Jacobi and with the sparse factor, which
  // does not know the holds: they filter its output)
  for (const auto& [integ, pc] : {std::pair{Integrator::implicit_euler, Preconditioner::block_jacobi},
                                  std::pair{Integrator::implicit_euler, Preconditioner::cholesky},
                                  std::pair{Integrator::symplectic_euler, Preconditioner::automatic}}) {
    SCOPED_TRACE(std::string(to_string(integ)) + " " + to_string(pc));
    SolverOptions o;
    o.integrator = integ;
    o.preconditioner = pc;
    o.mass_damping = 20;
    auto hang = [&](std::shared_ptr<const Obstacles> ob, Real* lowest) {
      State s = make_state(m);
      fix_nodes(m, s, m.set("fixed"));
      s.obstacles = std::move(ob);
      *lowest = HUGE_VAL;
      for (int k = 0; k < 40; ++k) {
        step(m, s, 1.0 / 60, o);
        for (std::int32_t i = 0; i < m.n_nodes; ++i) *lowest = std::min(*lowest, s.x[3 * static_cast<std::size_t>(i) + 1]);
      }
      EXPECT_EQ(s.counters.events, 0);
      EXPECT_TRUE(all_finite(s));
      return s;
    };
    auto end_low = [&](const State& s) {
      Real low = HUGE_VAL;
      for (std::int32_t i = 0; i < m.n_nodes; ++i) low = std::min(low, s.x[3 * static_cast<std::size_t>(i) + 1]);
      return low;
    };
    Real free_low = 0;
    const Real sag = rest_low - end_low(hang(nullptr, &free_low));
    ASSERT_GT(sag, 1e-4) << "the block should sag visibly";
    const Real table = rest_low - sag / 3;
    auto plane = std::make_shared<Obstacles>();
    add_obstacle_plane(*plane, {{0, table, 0}, {0, 1, 0}, 0, 0.5});
    auto mesh = std::make_shared<Obstacles>();
    add_obstacle_mesh(*mesh, square_at(table, 0.5));
    Real low_plane = 0, low_mesh = 0;
    const State on_plane = hang(plane, &low_plane), on_mesh = hang(mesh, &low_mesh);
    EXPECT_GE(low_plane, table) << "below the plane";
    EXPECT_GE(low_mesh, table) << "below the mesh";
    EXPECT_GT(on_plane.counters.obstacle_contacts, 0);
    // the skin rests on the table: its lowest node is on it
    EXPECT_LT(end_low(on_plane) - table, 1e-8);
    EXPECT_LT(end_low(on_mesh) - table, 1e-8);
    EXPECT_LT(max_node_distance(on_plane.x, on_mesh.x), 1e-6) << "plane and mesh in one place";
  }
}

// A free block (13 x 5 x 4, nothing fixed) dropped on a table comes to rest
// there, and the table carries its weight: the contact forces on its nodes
// (State::contact_force) add up to (0, M g, 0) within 0.01 %, with the table a
// plane or a mesh, for both integrators. (Implicit: the holds' normal forces
// and friction; symplectic: each substep's contact impulses over h.)
TEST(Obstacles, TheTableCarriesTheWeightOfABlockAtRest) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  Real low = HUGE_VAL;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) low = std::min(low, m.rest_x[3 * static_cast<std::size_t>(i) + 1]);
  const Real g = 9.81, weight = m.total_mass * g;
  for (Integrator integ : {Integrator::implicit_euler, Integrator::symplectic_euler})
    for (bool as_mesh : {false, true}) {
      SCOPED_TRACE(std::string(to_string(integ)) + (as_mesh ? ", mesh" : ", plane"));
      State s = make_state(m);
      auto ob = std::make_shared<Obstacles>();
      const Real table = low - 1e-3;  // it drops 1 mm
      if (as_mesh) add_obstacle_mesh(*ob, square_at(table, 0.5));
      else add_obstacle_plane(*ob, {{0, table, 0}, {0, 1, 0}, 0, 0.5});
      s.obstacles = ob;
      SolverOptions o;
      o.integrator = integ;
      o.mass_damping = 20;
      for (int k = 0; k < 60; ++k) step(m, s, 1.0 / 60, o);
      Real f[3] = {0, 0, 0};
      for (std::int32_t i = 0; i < m.n_nodes; ++i)
        for (int a = 0; a < 3; ++a) f[a] += s.contact_force[3 * static_cast<std::size_t>(i) + a];
      std::printf("  %s, %s: the table carries %.6g N of the block's %.6g N (%+.3g %%), sideways %.3g N; %lld factors\n",
                  to_string(integ), as_mesh ? "mesh" : "plane", f[1], weight, 100 * (f[1] / weight - 1), std::hypot(f[0], f[2]),
                  static_cast<long long>(s.counters.factorizations));
      EXPECT_NEAR(f[1], weight, 1e-4 * weight) << "the table carries the block's weight, " << weight << " N";
      EXPECT_LT(std::hypot(f[0], f[2]), 1e-4 * weight) << "and no sideways force";
      EXPECT_EQ(s.counters.events, 0);
      Real lowest = HUGE_VAL;
      for (std::int32_t i = 0; i < m.n_nodes; ++i) lowest = std::min(lowest, s.x[3 * static_cast<std::size_t>(i) + 1]);
      EXPECT_GE(lowest, table);
      EXPECT_LT(lowest - table, 1e-8) << "it rests on the table";
    }
}

// The sparse factor (the cholesky preconditioner) of a system with nodes held
// on a table is the held system's, so it solves it in a few iterations and is
// not rebuilt every substep. (A factor of the unheld matrix stayed above
// refactor_after however fresh, and was rebuilt every substep: 59 factors
// here; the runtime benchmark's free-lattice rows, BENCHMARKS.md.)
TEST(Obstacles, HeldNodesDoNotRebuildTheSparseFactorEverySubstep) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  Real low = HUGE_VAL;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) low = std::min(low, m.rest_x[3 * static_cast<std::size_t>(i) + 1]);
  State s = make_state(m);
  auto ob = std::make_shared<Obstacles>();
  add_obstacle_plane(*ob, {{0, low - 1e-3, 0}, {0, 1, 0}, 0, 0.5});
  s.obstacles = ob;
  SolverOptions o;
  o.integrator = Integrator::implicit_euler;
  o.preconditioner = Preconditioner::cholesky;
  o.mass_damping = 20;
  for (int k = 0; k < 60; ++k) step(m, s, 1.0 / 60, o);
  EXPECT_GT(s.counters.obstacle_contacts, 0);
  EXPECT_LE(static_cast<double>(s.counters.cg_iterations) / static_cast<double>(s.counters.cg_solves), 3)
      << "iterations a solve with the held system's factor";
  EXPECT_LE(s.counters.factorizations, 5) << "of 60 substeps";
  EXPECT_EQ(s.counters.events, 0);
}

// Contact is resolved node by node, so the result is bitwise the same for
// any thread count.
TEST(Obstacles, DeterministicAcrossThreadCounts) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  auto ob = std::make_shared<Obstacles>();
  add_obstacle_mesh(*ob, square_at(-2e-4, 0.5));
  add_obstacle_plane(*ob, {{0.03, 0, 0}, {-1, 0, 0}, 0.2, 0.3});  // a wall the block's free end presses on
  auto run = [&](Integrator integ, int threads) {
    State s = make_state(m);
    fix_nodes(m, s, m.set("fixed"));
    s.obstacles = ob;
    SolverOptions o;
    o.integrator = integ;
    o.mass_damping = 5;
    o.gravity = {3, -9.81, 0};
    tbb::task_arena arena(threads);
    arena.execute([&] {
      for (int k = 0; k < 20; ++k) step(m, s, 1.0 / 120, o);
    });
    EXPECT_GT(s.counters.obstacle_contacts, 0);
    return state_hash(s);
  };
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    EXPECT_EQ(run(integ, 1), run(integ, 2));
  }
}

// Bad obstacles are refused with one line.
TEST(Obstacles, BadObstaclesAreRefused) {
  Obstacles ob;
  auto refused = [&](auto&& add, const std::string& what) {
    try {
      add();
      ADD_FAILURE() << "accepted: " << what;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  };
  refused([&] { add_obstacle_plane(ob, {{0, 0, 0}, {0, 0, 0}}); }, "normal must be non-zero");
  refused([&] { add_obstacle_plane(ob, {{0, NAN, 0}, {0, 1, 0}}); }, "the point finite");
  refused([&] { add_obstacle_plane(ob, {{0, 0, 0}, {0, 1, 0}, 1.5, 0}); }, "restitution must be in [0, 1]");
  refused([&] { add_obstacle_mesh(ob, square_at(0, -1)); }, "friction must be finite and >= 0");
  ObstacleMesh bad = square_at(0, 0);
  bad.triangles[4] = 9;
  refused([&] { add_obstacle_mesh(ob, bad); }, "triangle index 9 out of range (4 vertices)");
  ObstacleMesh flat = square_at(0, 0);
  flat.triangles = {0, 1, 1};
  refused([&] { add_obstacle_mesh(ob, flat); }, "no triangle with an area");
  EXPECT_TRUE(ob.empty());
}


// ---- moving obstacles (State::obstacle_paths) -------------------------------------


// The square_at(y) turned over: its front (one-sided) faces -y.
ObstacleMesh square_facing_down(Real y, Real friction) {
  ObstacleMesh m = square_at(y, friction);
  m.triangles = {0, 1, 2, 0, 2, 3};
  return m;
}

// A table rising at u under a node lifts it at u: the node never goes below
// the table where it is at that time, rests on it, moves up at u, and the
// table carries its weight m g (no acceleration), with the table a plane or a
// mesh, for both integrators.
TEST(MovingObstacles, ARisingTableLiftsANodeAtItsSpeed) {
  const Real u = 0.1, g = 9.81, mass = 0.01, h = 1e-3;
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler})
    for (bool as_mesh : {false, true}) {
      SCOPED_TRACE(std::string(to_string(integ)) + (as_mesh ? ", mesh" : ", plane"));
      const Model m = node_on_table();
      State s = make_state(m);
      auto ob = std::make_shared<Obstacles>();
      if (as_mesh) add_obstacle_mesh(*ob, square_at(0, 0.5));
      else add_obstacle_plane(*ob, {{0, 0, 0}, {0, 1, 0}, 0, 0.5});
      s.obstacles = ob;
      s.obstacle_paths = {displacement_path({{0, 0, 0, 0}, {1, 0, u, 0}})};
      SolverOptions o;
      o.integrator = integ;
      o.substeps = 1;
      Real worst = HUGE_VAL;  // the node's height over the table, the least over the steps
      for (int k = 0; k < 500; ++k) {
        step(m, s, h, o);
        worst = std::min(worst, s.x[1] - u * s.time);
      }
      EXPECT_GE(worst, -1e-12) << "never below the table where it is";
      EXPECT_LT(s.x[1] - u * s.time, 1e-8) << "on it";
      EXPECT_NEAR(s.v[1], u, 1e-9) << "lifted at the table's speed";
      EXPECT_NEAR(s.contact_force[1], mass * g, 1e-6 * mass * g) << "the table carries the node's weight";
      EXPECT_EQ(s.counters.obstacle_contacts, 500);
      EXPECT_EQ(s.counters.events, 0);
    }
}

// A table that starts sliding at u under a node drags it by friction: the
// node accelerates at mu g (kinetic friction on the relative velocity) until
// it moves with the table at u after u / (mu g), then sticks (the implicit
// solve: within the creep speed). Both integrators, a plane table.
TEST(MovingObstacles, ASlidingTableDragsANodeByFriction) {
  const Real u = 0.2, mu = 0.4, g = 9.81, h = 1e-3;
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    const Model m = node_on_table();
    State s = make_state(m);
    auto ob = std::make_shared<Obstacles>();
    add_obstacle_plane(*ob, {{0, 0, 0}, {0, 1, 0}, 0, mu});
    s.obstacles = ob;
    s.obstacle_paths = {displacement_path({{0, 0, 0, 0}, {10, 10 * u, 0, 0}})};
    SolverOptions o;
    o.integrator = integ;
    o.substeps = 1;
    std::vector<Real> vx;
    for (int k = 0; k < 300; ++k) {
      step(m, s, h, o);
      vx.push_back(s.v[0]);
      EXPECT_GE(s.x[1], 0) << "at step " << k;
    }
    // while it slides (t < u / (mu g) = 51 ms): the acceleration over 10 .. 40 ms
    const Real a = (vx[39] - vx[9]) / (30 * h);
    EXPECT_NEAR(a, mu * g, 0.01 * mu * g) << "kinetic friction mu g";
    EXPECT_NEAR(vx.back(), u, o.friction_creep_speed) << "it moves with the table";
    // (the implicit solve: within its tolerance, as in ASlidingNodeStopsWhereCoulombFrictionSays)
    const Real over = integ == Integrator::implicit_euler ? o.cg_tolerance * g * h : 1e-12;
    EXPECT_LE(vx.back(), u + over) << "friction never drives it past the table, by " << vx.back() - u;
    EXPECT_EQ(s.counters.events, 0);
  }
}

// A probe pressed into a node held by a spring (k, rest 0.1 m, fixed at the
// origin) to a depth d stops there, and the contact force on the node is the
// spring's, k d; withdrawn, it lets go of the node, which springs back to
// rest with no force left. Both integrators, the probe a one-sided mesh
// facing the node.
TEST(MovingObstacles, AProbePressedIntoASpringMeetsItsStiffness) {
  const Real k = 100, d = 0.01, h = 1e-3;
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    const Model m = make_model({0, 0, 0, 0, 0.1, 0}, {0, 0.01}, {{0, 1, 0.1, k, 0}});
    State s = make_state(m);
    auto ob = std::make_shared<Obstacles>();
    add_obstacle_mesh(*ob, square_facing_down(0.12, 0.3));
    s.obstacles = ob;
    // down 2 cm + d in 0.5 s, held 1 s, back up in 0.5 s
    s.obstacle_paths = {displacement_path({{0, 0, 0, 0}, {0.5, 0, -0.02 - d, 0}, {1.5, 0, -0.02 - d, 0}, {2, 0, 0, 0}})};
    SolverOptions o;
    o.integrator = integ;
    o.substeps = 1;
    o.gravity = {0, 0, 0};
    o.mass_damping = 20;
    Real worst = -HUGE_VAL;  // the node's height over the probe's face, the most over the steps
    int k_step = 0;
    for (; k_step < 1500; ++k_step) {
      step(m, s, h, o);
      worst = std::max(worst, s.x[4] - (0.12 + s.obstacle_paths[0].at(s.time).y));
    }
    EXPECT_LE(worst, 1e-12) << "never past the probe's face";
    EXPECT_NEAR(s.x[4], 0.1 - d, 1e-8) << "pressed to the depth";
    EXPECT_NEAR(s.contact_force[4], -k * d, 1e-4 * k * d) << "the spring's force k d";
    EXPECT_EQ(s.contact_obstacle[1], 0);
    for (; k_step < 3000; ++k_step) step(m, s, h, o);
    EXPECT_NEAR(s.x[4], 0.1, 1e-6) << "back at rest";
    EXPECT_EQ(s.contact_obstacle[1], -1) << "let go";
    EXPECT_EQ(s.contact_force[4], 0);
    EXPECT_EQ(s.counters.events, 0);
  }
}

// A probe moving at 50 m/s (5 cm a substep) through a free node does not pass
// it: the node is caught on its face and carried at its speed. A two-sided
// square, no gravity, both integrators.
TEST(MovingObstacles, AFastProbeDoesNotPassThroughANode) {
  const Real h = 1e-3;
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    const Model m = make_model({0, 0, 0}, {0.01}, {});
    State s = make_state(m);
    auto ob = std::make_shared<Obstacles>();
    add_obstacle_mesh(*ob, square_at(0, 0, 0, true));
    s.obstacles = ob;
    s.obstacle_paths = {displacement_path({{0, 0, 0.03, 0}, {0.002, 0, -0.07, 0}})};
    SolverOptions o;
    o.integrator = integ;
    o.substeps = 1;
    o.gravity = {0, 0, 0};
    step(m, s, h, o);
    EXPECT_LT(s.x[1], -0.02) << "caught and carried";
    EXPECT_GT(s.x[1], -0.02 - 1e-8);
    step(m, s, h, o);
    EXPECT_LT(s.x[1], -0.07);
    EXPECT_GT(s.x[1], -0.07 - 1e-8) << "on the probe's face where it stops";
    EXPECT_NEAR(s.v[1], -50, 1e-9);
    EXPECT_EQ(s.counters.events, 0);
  }
}

// The free block (13 x 5 x 4, nothing fixed) on a table, pushed along it by a
// wall moving at 0.3 m/s: no stability event (the wall's work is in the
// step's energy budget), no node behind the wall or below the table, the
// block carried along with the wall, and the same state bit for bit on one
// thread and two.
TEST(MovingObstacles, PushingABlockIsStableAndDeterministic) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  Real right = -HUGE_VAL, low = HUGE_VAL;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    right = std::max(right, m.rest_x[3 * static_cast<std::size_t>(i)]);
    low = std::min(low, m.rest_x[3 * static_cast<std::size_t>(i) + 1]);
  }
  auto ob = std::make_shared<Obstacles>();
  add_obstacle_plane(*ob, {{0, low, 0}, {0, 1, 0}, 0, 0.3});            // the table, at rest
  add_obstacle_plane(*ob, {{right + 1e-3, 0, 0}, {-1, 0, 0}, 0, 0.3});  // the wall
  const Real u = 0.3;
  auto run = [&](Integrator integ, int threads) {
    State s = make_state(m);
    s.obstacles = ob;
    s.obstacle_paths = {Path{}, displacement_path({{0, 0, 0, 0}, {1, -u, 0, 0}})};
    SolverOptions o;
    o.integrator = integ;
    o.mass_damping = 5;
    Real past = -HUGE_VAL, below = HUGE_VAL;
    tbb::task_arena arena(threads);
    arena.execute([&] {
      for (int k = 0; k < 30; ++k) {
        step(m, s, 1.0 / 120, o);
        const Real wall = right + 1e-3 - u * s.time;
        for (std::int32_t i = 0; i < m.n_nodes; ++i) {
          past = std::max(past, s.x[3 * static_cast<std::size_t>(i)] - wall);
          below = std::min(below, s.x[3 * static_cast<std::size_t>(i) + 1] - low);
        }
      }
    });
    EXPECT_LE(past, 1e-12) << "no node behind the wall";
    EXPECT_GE(below, -1e-12) << "no node below the table";
    Real rightmost = -HUGE_VAL;
    for (std::int32_t i = 0; i < m.n_nodes; ++i) rightmost = std::max(rightmost, s.x[3 * static_cast<std::size_t>(i)]);
    EXPECT_LT(right + 1e-3 - u * s.time - rightmost, 1e-8) << "the block is carried along with the wall";
    EXPECT_EQ(s.counters.events, 0);
    EXPECT_TRUE(all_finite(s));
    return state_hash(s);
  };
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    EXPECT_EQ(run(integ, 1), run(integ, 2));
  }
}

// A table tilting about its pivot (0.4 rad about z in 1 s, friction 2 >
// tan 0.4) carries a node resting on it round the pivot: the node stays
// where it sat on the table, never goes behind it, and the table carries its
// weight (and the small centripetal force). The implicit solve lets the node
// creep at most creep_speed along the table. Both integrators.
TEST(MovingObstacles, ATiltingTableCarriesAStuckNodeRoundItsPivot) {
  const Real h = 1e-3, theta = 0.4, mass = 0.01, g = 9.81;
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    const Model m = make_model({0.1, 0, 0, 1, 0, 0}, {mass, 0}, {});
    State s = make_state(m);
    auto ob = std::make_shared<Obstacles>();
    add_obstacle_plane(*ob, {{0, 0, 0}, {0, 1, 0}, 0, 2.0, {0, 0, 0}});
    s.obstacles = ob;
    Path path = displacement_path({{0, 0, 0, 0}, {1, 0, 0, 0}});
    path.r = {0, 0, 0, 0, 0, theta};
    s.obstacle_paths = {path};
    SolverOptions o;
    o.integrator = integ;
    o.substeps = 1;
    Real behind = 0;
    for (int k = 0; k < 1000; ++k) {
      step(m, s, h, o);
      const Real a = theta * s.time;  // the table's angle now: its normal (-sin a, cos a, 0)
      behind = std::min(behind, -std::sin(a) * s.x[0] + std::cos(a) * s.x[1]);
    }
    EXPECT_GE(behind, -1e-12) << "never behind the table";
    const Real dx = s.x[0] - 0.1 * std::cos(theta), dy = s.x[1] - 0.1 * std::sin(theta);
    const Real off = std::hypot(dx, dy);
    // (symplectic: a stuck node moves on a straight line at the table's
    // velocity through each substep, so it drifts outward by the chord,
    // r (w h)^2 / 2 a substep: r w^2 h T / 2 = 8 um in all, an O(h) error)
    const Real w = theta / 1.0;
    if (integ == Integrator::implicit_euler) EXPECT_LT(off, o.friction_creep_speed * 1.0) << "creeps at most v_eps T";
    else EXPECT_LT(off, 0.1 * w * w * h * 1.0) << "where it sat, but for the chords";
    // the table's force: the weight, and the centripetal m w^2 r (1.6e-3 of it) toward the pivot
    EXPECT_NEAR(s.contact_force[0], -mass * w * w * 0.1 * std::cos(theta), 2e-3 * mass * g);
    EXPECT_NEAR(s.contact_force[1], mass * g - mass * w * w * 0.1 * std::sin(theta), 2e-3 * mass * g);
    EXPECT_EQ(s.counters.events, 0);
  }
}

// A door (a two-sided square hinged on the y axis) swung at 50 rad/s, its
// edge at 5 m/s, 5 mm a substep, through a free node: the node is caught on
// the face it meets and carried, never passing to the other side. Both
// integrators, no gravity, no friction.
TEST(MovingObstacles, ASwingingDoorDoesNotPassANode) {
  const Real h = 1e-3;
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    const Model m = make_model({0.1 * std::cos(0.5), 0, -0.1 * std::sin(0.5)}, {0.01}, {});
    State s = make_state(m);
    auto ob = std::make_shared<Obstacles>();
    ObstacleMesh door;
    door.vertices = {0, -0.1, 0, 0.2, -0.1, 0, 0.2, 0.1, 0, 0, 0.1, 0};
    door.triangles = {0, 1, 2, 0, 2, 3};
    door.two_sided = true;
    door.friction = 0;
    add_obstacle_mesh(*ob, std::move(door));
    s.obstacles = ob;
    Path path = displacement_path({{0, 0, 0, 0}, {0.02, 0, 0, 0}});
    path.r = {0, 0, 0, 0, 1.0, 0};  // about +y: the door's +x edge swings toward -z
    s.obstacle_paths = {path};
    SolverOptions o;
    o.integrator = integ;
    o.substeps = 1;
    o.gravity = {0, 0, 0};
    Real worst = -HUGE_VAL;  // the node's side of the door, in the door's frame (negative: the side it came from)
    for (int k = 0; k < 20; ++k) {
      step(m, s, h, o);
      const Real a = 50 * s.time;
      worst = std::max(worst, std::sin(a) * s.x[0] + std::cos(a) * s.x[2]);  // z in the door's frame
    }
    EXPECT_LE(worst, 1e-12) << "it never passes the door";
    EXPECT_GT(worst, -1e-8) << "it is on the door's face";
    EXPECT_GT(std::hypot(s.x[0], s.x[2]), 0.1 - 1e-9) << "swept round (it slides outward, frictionless)";
    EXPECT_EQ(s.counters.events, 0);
  }
}

// ---- a mesh's edges against the tissue's faces -----------------------------

// One triangle pair of free nodes (a unit square at y = 0, its outside -y)
// moving out at 1 m/s and along x at 0.3 m/s meets a sample 0.5 mm in front
// of its centre in a 1 ms substep: the two nodes of the diagonal under it
// (weights 1/2, 1/2) move back so that the point under it ends on it, 0.5 m/s
// slower, and friction 0.2 takes 0.2 x 0.5 m/s of their 0.3 m/s along it
// (Coulomb). The impulse is their momentum change.
TEST(FaceContacts, TheLawOnOneFace) {
  // the samples: a box's 8 corners, and points along its 12 edges and 6 face diagonals
  Obstacles o;
  add_obstacle_mesh(o, box_mesh({0.4, -0.1, 0.4}, {0.6, 0.1, 0.6}));
  sample_obstacle_edges(o.meshes[0], 1.0);
  EXPECT_EQ(o.meshes[0].samples.size(), 3u * 8) << "edges shorter than the spacing: the corners";
  sample_obstacle_edges(o.meshes[0], 0.05);
  EXPECT_EQ(o.meshes[0].samples.size(), 3u * (8 + 12 * 3 + 6 * 5)) << "0.2 m edges in 4, 0.28 m diagonals in 6";
  sample_obstacle_edges(o.meshes[0], 0);
  EXPECT_TRUE(o.meshes[0].samples.empty()) << "spacing 0: none";
  try {
    sample_obstacle_edges(o.meshes[0], 1e-9);
    ADD_FAILURE() << "10^8 points";
  } catch (const Error& e) {
    EXPECT_NE(e.message().find("edge samples 1e-09 m apart would be more than 10^7 points"), std::string::npos) << e.message();
  }
  // a box whose one corner over the square is (0.5, -0.0005, 0.5)
  Obstacles o1;
  ObstacleMesh one = box_mesh({0.5, -0.0015, 0.5}, {1.5, -0.0005, 1.5});
  one.friction = 0.2;
  add_obstacle_mesh(o1, std::move(one));
  sample_obstacle_edges(o1.meshes[0], 2.0);
  const std::vector<std::int32_t> quads = {0, 1, 2, 3};  // (0,0,0) (1,0,0) (1,0,1) (0,0,1): counter-clockwise from -y
  const std::vector<Real> x = {0, 0, 0, 1, 0, 0, 1, 0, 1, 0, 0, 1};
  std::vector<Real> v;
  for (int k = 0; k < 4; ++k) v.insert(v.end(), {0.2, -1, 0.2});  // out, and along the diagonal under the sample
  const std::vector<Real> v_in = v;
  const std::vector<Real> inv_mass(4, 1.0);
  std::vector<Real> impulse(3, 0);
  FaceScratch sc;
  const Real h = 1e-3;
  const FaceContacts c = resolve_face_contacts(o1, {}, quads, x, v, inv_mass, h, impulse, sc);
  EXPECT_EQ(c.contacts, 1) << "the corner over the square's centre (the one under it is in front)";
  EXPECT_EQ(c.work, 0) << "a mesh at rest does no work";
  // at the end the square has moved 0.2 mm along the diagonal: the sample is at 0.4998 of it
  const Real w0 = 0.5002, w2 = 0.4998;
  auto at_point = [&](const std::vector<Real>& a, int k) { return w0 * a[k] + w2 * a[6 + k]; };
  // the point under it ends on it, 10^-9 m (the standoff) behind it (deeper: +y)
  const Real standoff = 1e-9;
  EXPECT_NEAR(at_point(x, 1) + h * at_point(v, 1), -0.0005 + standoff, 1e-15);
  const Real dvn = (0.0005 + standoff) / h;  // its normal change: 0.5 m/s slower out
  EXPECT_NEAR(at_point(v, 1), -1 + dvn, 1e-12);
  // Coulomb: 0.2 x that off its 0.283 m/s along the diagonal, not turned
  EXPECT_NEAR(std::hypot(at_point(v, 0), at_point(v, 2)), std::hypot(0.2, 0.2) - 0.2 * dvn, 1e-12);
  EXPECT_NEAR(at_point(v, 0), at_point(v, 2), 1e-15);
  // the nodes' shares: w_j / sum w^2 of the point's change each
  const Real W = w0 * w0 + w2 * w2;
  for (int k = 0; k < 3; ++k) EXPECT_NEAR((v[k] - v_in[k]) / w0, (v[6 + k] - v_in[6 + k]) / w2, 1e-9) << k;
  EXPECT_NEAR((at_point(v, 1) - at_point(v_in, 1)), (v[1] - v_in[1]) * W / w0, 1e-9);
  for (int i : {1, 3})
    for (int k = 0; k < 3; ++k) EXPECT_EQ(v[3 * i + k], v_in[3 * i + k]) << "off the diagonal: untouched";
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(impulse[k], v[k] - v_in[k] + v[6 + k] - v_in[6 + k], 1e-12) << "the momentum change";
  // fixed nodes do not move; a free one takes it all
  std::vector<Real> v2(12);
  for (int k = 0; k < 4; ++k) v2[3 * k + 1] = -1;
  std::vector<Real> im2 = {0, 1, 0, 0};
  std::vector<Real> imp2(3, 0);
  EXPECT_EQ(resolve_face_contacts(o1, {}, quads, x, v2, im2, h, imp2, sc).contacts, 0) << "the diagonal's nodes are fixed";
  // already behind the face at the start (inside the tissue): left alone
  std::vector<Real> x3 = x;
  for (int k = 0; k < 4; ++k) x3[3 * k + 1] = -0.001;
  std::vector<Real> v3(12, 0);
  EXPECT_EQ(resolve_face_contacts(o1, {}, quads, x3, v3, inv_mass, h, imp2, sc).contacts, 0);
}

// A probe narrower than the skin's 4 mm node spacing, pushed 5 mm into the
// layered block between its nodes: a 1 mm rod tip first, and a 1 mm bar
// lying across the skin whose vertices all lie beyond the block (only its
// edges' samples meet the faces). With the edge samples the skin is pressed:
// no sample of the probe gets behind a skin face, the face under it is on it,
// and the probe's force on the tissue is what the fixed bone carries. With
// them off (spacing 0) the probe passes through the skin. Both integrators,
// 1 and 2 threads the same.
TEST(FaceContacts, AThinProbePressesTheSkinBetweenNodes) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  ASSERT_GT(m.n_quads, 0);
  const std::vector<std::int32_t> skin_quads = test::top_sheet_quads(m);  // the skin sheet's quads
  ASSERT_EQ(skin_quads.size(), 4u * 12 * 4);
  const Real spacing = default_edge_spacing(m.quads, m.rest_x);
  EXPECT_NEAR(spacing, 2e-3, 1e-12) << "half the 4 mm edges";
  const Real push = 5e-3;
  struct Result {
    Real behind = -HUGE_VAL;  // the most a sample is behind the skin face over (under) it, over the steps
    Real gap = HUGE_VAL;      // at the end: the least distance from a sample to the face under it
    Vec3 force, bone;         // at the end: the probe's force on the tissue; the fixed nodes' reaction
    std::int64_t events = 0, faces = 0;
    std::uint64_t hash = 0;
  };
  auto press = [&](const ObstacleMesh& probe_mesh, Real edge_spacing, Integrator integ, int threads) {
    auto ob = std::make_shared<Obstacles>();
    add_obstacle_mesh(*ob, probe_mesh);
    sample_obstacle_edges(ob->meshes[0], edge_spacing);
    State s = make_state(m);
    fix_nodes(m, s, m.set("fixed"));
    s.obstacles = ob;
    s.obstacle_paths = {displacement_path({{0, 0, 0, 0}, {0.25, 0, push, 0}})};
    SolverOptions o;
    o.integrator = integ;
    o.gravity = {0, 0, 0};
    o.mass_damping = 20;
    Result r;
    // the probe's points at the default spacing (whether or not the solve
    // uses them) in space, and how far each is behind the skin under it (y: deeper)
    ObstacleMesh points = probe_mesh;
    sample_obstacle_edges(points, spacing);
    auto measure = [&](bool end) {
      const test::SkinDepth sd = test::depth_behind_skin(points.samples, s.obstacle_paths[0].at(s.time), skin_quads, s.x);
      r.behind = std::max(r.behind, sd.behind);
      if (end) r.gap = sd.gap;
    };
    tbb::task_arena arena(threads);
    arena.execute([&] {
      for (int k = 0; k < 60; ++k) {
        step(m, s, 1.0 / 120, o);
        measure(k == 59);
      }
    });
    r.force = load3(s.face_force.data(), 0);
    r.bone = testing::fixed_reaction(m, s.x, s.inv_mass);
    r.events = s.counters.events;
    r.faces = s.counters.face_contacts;
    r.hash = state_hash(s);
    EXPECT_TRUE(all_finite(s));
    return r;
  };
  // between the nodes at x = 20, 24 mm and z = 4, 8 mm: a rod, tip up at y = -1 mm; a bar along z across the block
  const ObstacleMesh rod = box_mesh({0.0215, -0.02, 0.0055}, {0.0225, -0.001, 0.0065});
  const ObstacleMesh bar = box_mesh({0.0215, -0.002, -0.01}, {0.0225, -0.001, 0.026});
  for (const auto& [name, probe] : {std::pair{"rod", rod}, std::pair{"bar", bar}}) {
    Real symplectic_force = 0;
    for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
      SCOPED_TRACE(std::string(name) + ", " + to_string(integ));
      const Result r = press(probe, spacing, integ, 1);
      std::printf("  %s, %s: force %.6f N (the bone %.6f N), deepest sample %.3g m, gap %.3g m, %lld face contacts\n", name,
                  to_string(integ), r.force.y, r.bone.y, r.behind, r.gap, static_cast<long long>(r.faces));
      EXPECT_LE(r.behind, 1e-9) << "no sample behind the skin";
      EXPECT_LT(r.gap, 1e-6) << "the skin pressed is on the probe";
      EXPECT_GT(r.force.y, 0) << "the probe pushes the skin in";
      EXPECT_NEAR(r.bone.y, r.force.y, 0.02 * r.force.y) << "at rest, the bone carries the push";
      // the implicit solve holds the point the probe presses, not its whole
      // triangle: its force is the symplectic run's (until 2026-11-29 it held
      // the triangle's corners, +4 % for the rod). Within 2 %: with friction
      // the two integrators' paths stick and slip differently (frictionless,
      // the bar's agree within 2e-4)
      if (integ == Integrator::symplectic_euler) symplectic_force = r.force.y;
      else EXPECT_NEAR(r.force.y, symplectic_force, 0.02 * symplectic_force) << "the implicit's force is the symplectic's";
      EXPECT_GT(r.faces, 0);
      EXPECT_EQ(r.events, 0);
      EXPECT_EQ(press(probe, spacing, integ, 2).hash, r.hash) << "threads";
      const Result off = press(probe, 0, integ, 1);
      EXPECT_GT(off.behind, 2e-3) << "without the samples it passes through the skin";
      EXPECT_EQ(off.faces, 0);
    }
  }
}

// A rod pressed 1.5 mm into the skin between nodes and then slid 30 mm
// sideways, off the block's edge (frictionless, at the same depth), lets the
// skin go: once it has left, no face row remains (implicit), and the
// skin comes back to rest. Both integrators. (Pressed deeper than the 2 mm
// skin layer, the implicit run folds the layer, which central springs do not
// unfold: docs/runtime.md, "Inverted layers"; so the press stays shallower.)
TEST(FaceContacts, ARodSlidOffLetsTheSkinGo) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  for (Integrator integ : {Integrator::symplectic_euler, Integrator::implicit_euler}) {
    SCOPED_TRACE(to_string(integ));
    auto ob = std::make_shared<Obstacles>();
    ObstacleMesh rod = box_mesh({0.0215, -0.02, 0.0055}, {0.0225, -0.001, 0.0065});
    rod.friction = 0;
    add_obstacle_mesh(*ob, std::move(rod));
    sample_obstacle_edges(ob->meshes[0], default_edge_spacing(m.quads, m.rest_x));
    State s = make_state(m);
    fix_nodes(m, s, m.set("fixed"));
    s.obstacles = ob;
    s.obstacle_paths = {displacement_path({{0, 0, 0, 0}, {0.2, 0, 0.0025, 0}, {0.3, 0, 0.0025, 0}, {0.6, 0.03, 0.0025, 0}})};
    SolverOptions o;
    o.integrator = integ;
    o.gravity = {0, 0, 0};
    o.mass_damping = 20;
    Real pressed = 0;  // the skin's deepest node while the rod is in it
    for (int k = 0; k < 36; ++k) {
      step(m, s, 1.0 / 120, o);
      for (std::int32_t i : m.set("skin")) pressed = std::max(pressed, s.x[3 * static_cast<std::size_t>(i) + 1]);
    }
    EXPECT_GT(pressed, 0.001) << "the rod pressed the skin";
    EXPECT_GT(s.counters.face_contacts, 0);
    for (int k = 0; k < 120; ++k) step(m, s, 1.0 / 120, o);  // the rod off the block from 0.6 s
    EXPECT_TRUE(s.face_rows.empty()) << "no face held";
    EXPECT_LT(max_node_distance(s.x, m.rest_x), 1e-4) << "the skin back at rest";
    for (const auto& ic : inverted_columns(m, s.x)) EXPECT_EQ(ic.inverted, 0) << ic.layer;
    EXPECT_EQ(s.counters.events, 0);
  }
}

// A rod pressed 1.5 mm into the skin between nodes and dragged 10 mm along it
// with friction, towards the block's open side, in the demo's steps of 1/60 s
// (implicit), keeps its contact: its force changes smoothly from step to step
// (falling from 0.10 to 0.04 N as the skin nears the side; no step gives up the contact
// and the next takes it back: until 2026-11-29 the drag alternated 0.002 and
// 0.066 N from step to step in the demo's rod scene, as the rod's edge point
// slid off the face it held onto one it did not yet touch), the skin does not
// fold, and no point of the rod gets behind the skin.
TEST(FaceContacts, ARodDraggedAlongTheSkinKeepsItsContact) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  const std::vector<std::int32_t> skin_quads = test::top_sheet_quads(m);
  const Real spacing = default_edge_spacing(m.quads, m.rest_x);
  auto ob = std::make_shared<Obstacles>();
  ObstacleMesh rod = box_mesh({0.0215, -0.02, 0.0055}, {0.0225, -0.001, 0.0065});
  rod.friction = 0.3;
  add_obstacle_mesh(*ob, rod);
  sample_obstacle_edges(ob->meshes[0], spacing);
  ObstacleMesh points = rod;
  sample_obstacle_edges(points, spacing);
  State s = make_state(m);
  fix_nodes(m, s, m.set("fixed"));
  s.obstacles = ob;
  // down 2.5 mm (1.5 mm into the skin) over 0.3 s, then along z 10 mm over 0.6 s
  s.obstacle_paths = {displacement_path({{0, 0, 0, 0}, {0.3, 0, 0.0025, 0}, {0.9, 0, 0.0025, 0.01}})};
  SolverOptions o;
  o.integrator = Integrator::implicit_euler;
  o.gravity = {0, 0, 0};
  o.mass_damping = 5;
  std::vector<Real> fy;
  Real behind = -HUGE_VAL;
  for (int k = 0; k < 54; ++k) {
    step(m, s, 1.0 / 60, o);
    fy.push_back(load3(s.face_force.data(), 0).y);
    behind = std::max(behind, test::depth_behind_skin(points.samples, s.obstacle_paths[0].at(s.time), skin_quads, s.x).behind);
    for (const auto& ic : inverted_columns(m, s.x)) EXPECT_EQ(ic.inverted, 0) << ic.layer << " at step " << k;
  }
  // the drag: from one step after it starts to its end
  Real lo = HUGE_VAL, hi = 0, worst = 1;
  for (int k = 19; k < 54; ++k) {
    lo = std::min(lo, fy[k]), hi = std::max(hi, fy[k]);
    worst = std::min(worst, fy[k] / fy[k - 1]);
  }
  std::printf("  the drag's force %.4f - %.4f N, the least step-to-step ratio %.3f, deepest point %.3g m\n", lo, hi, worst, behind);
  EXPECT_GT(worst, 0.8) << "no step lets the skin go (the force falls towards the block's side smoothly)";
  EXPECT_LE(behind, 1e-9) << "no point of the rod behind the skin";
  EXPECT_EQ(s.counters.events, 0);
}

// The 1 mm rod of the tests below (x 21.5-22.5 mm, z 5.5-6.5 mm, its tip 1 mm
// above the skin, between the nodes at x 20, 24 and z 4, 8 mm), its edges
// sampled at the default spacing, on a fresh State of the block m (bone
// fixed) that pushes it `push` into the skin over 0.25 s; implicit, no
// gravity, mass damping 20.
struct PressingRod {
  State s;
  SolverOptions o;
};
PressingRod pressing_rod(const Model& m, Real push, Real friction) {
  auto ob = std::make_shared<Obstacles>();
  ObstacleMesh rod = box_mesh({0.0215, -0.02, 0.0055}, {0.0225, -0.001, 0.0065});
  rod.friction = friction;
  add_obstacle_mesh(*ob, rod);
  sample_obstacle_edges(ob->meshes[0], default_edge_spacing(m.quads, m.rest_x));
  PressingRod r{make_state(m), {}};
  fix_nodes(m, r.s, m.set("fixed"));
  r.s.obstacles = ob;
  r.s.obstacle_paths = {displacement_path({{0, 0, 0, 0}, {0.25, 0, push, 0}})};
  r.o.integrator = Integrator::implicit_euler;
  r.o.gravity = {0, 0, 0};
  r.o.mass_damping = 20;
  return r;
}

// A caller that cuts a Model itself (cut_model, as Scene::cut does) while a
// rod presses the skin, and steps on: the rows of the last substep name
// triangles of the quads before the cut, which removes the quads it crosses
// and renumbers the rest. The solve holds a row whose corners are still a
// face (renumbered: the rod keeps its hold through a cut beside it) and
// drops one whose face the cut removed (its nodes may be the wound's sides):
// the step is the one from rows made on the cut model, renumbered or gone. (Until
// 2026-11-29 the solve held every row's nodes for a substep, faces the cut
// had opened too, and Scene::cut cleared all rows.) Cuts under the rod and
// beside it.
TEST(FaceContacts, ACutKeepsTheRowsOfFacesItLeaves) {
  const auto b = make_layered_block(13, 5, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  auto [s, o] = pressing_rod(m, 0.003, 0.3);
  for (int k = 0; k < 30; ++k) step(m, s, 1.0 / 120, o);  // the rod 2 mm into the skin
  ASSERT_FALSE(s.face_rows.empty()) << "the rod holds the skin";
  for (const FaceRow& r : s.face_rows) ASSERT_TRUE(face_row_current(m.quads, r)) << "rows of the model they were made on";
  // the rod spans x 21.5-22.5 mm, z 5.5-6.5 mm, between the nodes at x 20, 24 and z 4, 8 mm
  std::int64_t renumbered_all = 0, removed_all = 0;
  for (Real z : {0.002, 0.006, 0.010}) {
    SCOPED_TRACE("a cut along x at z = " + std::to_string(z));
    Model cut = m;
    CutDef def;
    def.polyline = {Vec3{0.010, -5e-4, z}, Vec3{0.034, -5e-4, z}};
    def.direction = {0, 1, 0};
    def.depth = 0.004;  // the skin under the rod is 2 mm down
    ASSERT_GT(cut_model(cut, s.x, def).springs_cut, 0);
    ASSERT_LT(cut.n_quads, m.n_quads) << "the cut removed quads";
    State expected = s;  // as if the rows had been made on the cut model: renumbered, or gone with their face
    for (FaceRow& r : expected.face_rows) r.triangle = test::face_with_corners(cut, r);
    std::erase_if(expected.face_rows, [&](const FaceRow& r) { return r.triangle < 0; });
    std::int64_t renumbered = 0, removed = 0;
    for (const FaceRow& r : s.face_rows) {
      const bool face = test::face_with_corners(cut, r) >= 0;
      renumbered += face && !face_row_current(cut.quads, r);
      removed += !face && r.impulse > 0;
    }
    renumbered_all += renumbered, removed_all += removed;
    std::printf("  z = %.3f: %zu rows, %lld renumbered, %lld pushing on removed faces\n", z, s.face_rows.size(),
                static_cast<long long>(renumbered), static_cast<long long>(removed));
    State held = s;
    step(cut, held, 1.0 / 120, o);
    step(cut, expected, 1.0 / 120, o);
    EXPECT_EQ(state_hash(held), state_hash(expected)) << "the rows of removed faces are not held, the others are";
    for (int k = 0; k < 10; ++k) step(cut, held, 1.0 / 120, o);
    EXPECT_TRUE(all_finite(held));
    EXPECT_EQ(held.counters.failed, s.counters.failed);
    for (const FaceRow& r : held.face_rows) EXPECT_TRUE(face_row_current(cut.quads, r));
  }
  EXPECT_GT(renumbered_all, 0) << "a cut before the rod renumbers its faces";
  EXPECT_GT(removed_all, 0) << "a cut under it removes the faces it pushed";
}

// A thin rod pressed into a stiff, nearly incompressible skin (the block's
// 0.118 MPa dermis with a volume term of 16 E, nu about 0.49), where block
// Jacobi cannot see the incompressible modes and the sparse factor is the
// preconditioner that works (docs/BENCHMARKS.md, "the volume term"): the
// factor preconditions the faces' rows too, by Woodbury (G - G J^T S^-1 J G,
// G = F^-1 between the holds' filters), and the force is block Jacobi's.
// Until 2026-11-29 a solve with rows fell back to block Jacobi: the same
// iterations as block Jacobi's (its PCG stopped at its cap and the steps were
// redone with more substeps: the demo's rod and spatula on the limb with its
// dermis in MPa ran at 11-14 steps/s with 127 and 131 steps redone; 7.2x
// and 5.7x faster now: docs/BENCHMARKS.md).
TEST(FaceContacts, TheSparseFactorPreconditionsTheRows) {
  testing::LayeredBlockOptions bo;
  bo.nu = 13, bo.nv = 5;
  bo.volume_modulus = {16 * bo.youngs[0], 0, 0};
  const auto b = make_layered_block(bo);
  const Model m = model_from_layers(b.layers, b.sets);
  ASSERT_GT(m.n_tets, 0);
  struct Result {
    Real force = 0;
    double its = 0;  // PCG iterations a solve
    std::int64_t factors = 0, redos = 0, resolves = 0;
    std::uint64_t hash = 0;
  };
  auto press = [&](Preconditioner pc, int threads) {
    auto [s, o] = pressing_rod(m, 0.004, ObstacleMesh{}.friction);
    o.preconditioner = pc;
    o.cg_max_iterations = 5000;  // block Jacobi converges, slowly
    tbb::task_arena(threads).execute([&] {
      for (int k = 0; k < 40; ++k) step(m, s, 1.0 / 120, o);
    });
    EXPECT_TRUE(all_finite(s));
    EXPECT_EQ(s.counters.failed, 0);
    EXPECT_FALSE(s.face_rows.empty()) << "the rod holds the skin";
    return Result{load3(s.face_force.data(), 0).y,
                  static_cast<double>(s.counters.cg_iterations) / static_cast<double>(s.counters.cg_solves),
                  s.counters.factorizations, s.counters.cg_redos, s.counters.face_resolves, state_hash(s)};
  };
  const Result bj = press(Preconditioner::block_jacobi, 1), f = press(Preconditioner::cholesky, 1);
  std::printf("  block Jacobi: %.6f N, %.1f PCG a solve, %lld resolves; factor: %.6f N, %.1f PCG a solve, %lld factors, %lld resolves\n",
              bj.force, bj.its, static_cast<long long>(bj.resolves), f.force, f.its, static_cast<long long>(f.factors),
              static_cast<long long>(f.resolves));
  EXPECT_GT(f.force, 0);
  EXPECT_NEAR(f.force, bj.force, 1e-4 * bj.force) << "the same solve";
  EXPECT_LT(f.its, bj.its / 5) << "the factor's iterations, not block Jacobi's";
  EXPECT_LT(f.factors, 10) << "the rows do not make the factor stale";
  EXPECT_EQ(f.redos, 0);
  EXPECT_EQ(press(Preconditioner::cholesky, 2).hash, f.hash) << "threads";
}

}  // namespace
}  // namespace orthosim::runtime
