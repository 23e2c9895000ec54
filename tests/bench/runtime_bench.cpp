// Runtime benchmarks (issue 8). Google Benchmark timings plus tables:
//   runtime_bench                                  all timings
//   runtime_bench --benchmark_filter=Paper         the 39x9x4 lattice
//   runtime_bench --tables=DIR [--quick]           write DIR/runtime_tables.md: the run-time
//                                                  against error table, the stress sweep, the Bullet
//                                                  comparison (when built with ORTHOSIM_WITH_BULLET_PEER)
//   runtime_bench --cg-tolerance                   the PCG's stopping tolerance against its solve error
//                                                  and the integrator's (39x9x4 lattice settling, 1 thread)
//   runtime_bench --results=FILE.json [--quick]    the harness rows (orthosim bench, tests/bench/bench_results.h):
//     - integrator error against dt: 13x5x4 block pulled for 0.05 s, error = max position error / max
//       motion against symplectic Euler at 2e-6 s (full: 1e-7 s); goal <= 0.2 for symplectic with
//       automatic substeps and implicit Euler (first-order error at dt <= 1/30 s); a single symplectic
//       substep is informational (it is meant to fail beyond its limit)
//     - the paper's Fig. 3(a): time per step against grid (15x5 ... 400x100, 4 layers; quick up to
//       100x25): one symplectic substep and one implicit Euler step at 1/60 s, 2 threads; error =
//       stability events (goal 0)
//     - the stability matrix: stable / recovered / failed runs per integrator x dt x K2/K1 (9 runs per
//       cell: mass ratio x degenerate springs); error = runs with a non-finite state (goal 0)
//     - static sag of the 39x9x4 lattice against Newton, ours (implicit, 1/60 s) and Bullet btSoftBody
//       (10 iterations) timed in alternation; error = relative sag error (goal <= 1e-3 for ours)
//     a free lattice resting on a table (a plane, a 2-triangle mesh): the table's force against the
//       weight (goal <= 1e-4)
// Timings are medians of repetitions when run with --benchmark_repetitions.
#include "runtime/obstacles.h"
#include "runtime/solver.h"
#include "runtime/testing/lattice.h"
#include "runtime/testing/newton.h"
#include "runtime/testing/stress.h"
#include "tests/bench/bench_results.h"
#include "tests/runtime/runtime_test_util.h"

#include <benchmark/benchmark.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/partitioner.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#ifdef ORTHOSIM_HAVE_BULLET
#include <BulletSoftBody/btSoftBody.h>
#include <BulletSoftBody/btSoftBodyHelpers.h>
#include <BulletSoftBody/btSoftBodyRigidBodyCollisionConfiguration.h>
#include <BulletSoftBody/btSoftRigidDynamicsWorld.h>
#include <btBulletDynamicsCommon.h>
#endif

namespace rt = orthosim::runtime;
using rt::Real;

namespace {

using clock_type = std::chrono::steady_clock;
double seconds_since(clock_type::time_point t0) { return std::chrono::duration<double>(clock_type::now() - t0).count(); }

// ---- shared fixtures ---------------------------------------------------------

struct Lattice {
  rt::Model model;
  rt::State rest;
};

// The paper-sized block (or larger), bone fixed. Cached per size.
const Lattice& lattice(int nu, int nv, int layers) {
  static std::map<std::array<int, 3>, std::unique_ptr<Lattice>> cache;
  auto& slot = cache[{nu, nv, layers}];
  if (!slot) {
    const auto b = rt::testing::make_layered_block(nu, nv, layers);
    slot = std::make_unique<Lattice>();
    slot->model = rt::model_from_layers(b.layers, b.sets);
    slot->rest = rt::make_state(slot->model);
    rt::fix_nodes(slot->model, slot->rest, slot->model.set("fixed"));
  }
  return *slot;
}

// Minimum memory traffic of one symplectic step (bytes): per spring, pass 1
// reads the second end, rest, k, c, tension flag and writes the force; pass 2
// reads the spring id and force again. Per node: positions, velocities,
// forces, external force, masses, offsets (neighbours' x, v assumed cached).
double symplectic_step_bytes(const rt::Model& m) {
  const double per_spring = 4 + 3 * 8 + 1 + 3 * 8 + 4 + 3 * 8;
  const double per_node = (6 * 8 + 4 + 3 * 8) + (3 * 8 + 3 * 8 + 4 + 8 + 8 + 2 * 6 * 8);
  return per_spring * m.n_springs + per_node * m.n_nodes;
}

// ---- STREAM-like triad: the machine's memory bandwidth -------------------------

void BM_StreamTriad(benchmark::State& state) {
  const int threads = static_cast<int>(state.range(0));
  const std::size_t n = std::size_t(1) << 23;  // 8 Mi doubles per array, 3 x 64 MiB
  static std::vector<double> a(n, 1.0), b(n, 2.0), c(n, 0.5);
  tbb::task_arena arena(threads);
  const double s = 3.0;
  for (auto _ : state) {
    arena.execute([&] {
      tbb::parallel_for(tbb::blocked_range<std::size_t>(0, n, n / 64), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t i = r.begin(); i < r.end(); ++i) a[i] = b[i] + s * c[i];
      }, tbb::static_partitioner());
    });
    benchmark::ClobberMemory();
  }
  state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations()) * static_cast<std::int64_t>(3 * n * sizeof(double)));
  state.counters["GBps"] = benchmark::Counter(static_cast<double>(3 * n * sizeof(double)) * 1e-9,
                                              benchmark::Counter::kIsIterationInvariantRate);
}
BENCHMARK(BM_StreamTriad)->Arg(1)->Arg(2)->UseRealTime()->Unit(benchmark::kMillisecond);

// ---- symplectic Euler: integrator steps per second ----------------------------------

void symplectic_steps(benchmark::State& state, int nu, int nv) {
  const int threads = static_cast<int>(state.range(0));
  const Lattice& L = lattice(nu, nv, 4);
  rt::State s = L.rest;
  rt::SolverOptions o;
  o.substeps = 1;
  const Real h = o.safety * rt::symplectic_step_limit(L.model, s, o);
  tbb::task_arena arena(threads);
  for (auto _ : state) arena.execute([&] { rt::step(L.model, s, h, o); });
  if (s.counters.events != 0) state.SkipWithError("stability events in a stable run");
  state.counters["steps_per_s"] = benchmark::Counter(1, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["ns_per_spring"] = benchmark::Counter(1e9 / L.model.n_springs, benchmark::Counter::kIsIterationInvariantRate |
                                                                                   benchmark::Counter::kInvert);
  state.counters["springs"] = L.model.n_springs;
  state.counters["nodes"] = L.model.n_nodes;
  state.counters["h_s"] = h;
  const double bytes = symplectic_step_bytes(L.model);
  state.counters["GBps"] = benchmark::Counter(bytes * 1e-9, benchmark::Counter::kIsIterationInvariantRate);
}

void BM_Paper_Symplectic(benchmark::State& state) { symplectic_steps(state, 39, 9); }
BENCHMARK(BM_Paper_Symplectic)->Arg(1)->Arg(2)->UseRealTime()->Unit(benchmark::kMicrosecond);

void BM_Large_Symplectic(benchmark::State& state) { symplectic_steps(state, 400, 100); }
BENCHMARK(BM_Large_Symplectic)->Arg(1)->Arg(2)->UseRealTime()->Unit(benchmark::kMillisecond);

// One frame of 1/60 s with automatic substeps (what a 60 Hz scene costs).
void BM_Paper_SymplecticFrame60(benchmark::State& state) {
  const int threads = static_cast<int>(state.range(0));
  const Lattice& L = lattice(39, 9, 4);
  rt::State s = L.rest;
  rt::SolverOptions o;
  tbb::task_arena arena(threads);
  long substeps = 0;
  for (auto _ : state) arena.execute([&] { substeps += rt::step(L.model, s, 1.0 / 60, o).substeps; });
  state.counters["frames_per_s"] = benchmark::Counter(1, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["sim_s_per_wall_s"] = benchmark::Counter(1.0 / 60, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["substeps_per_frame"] = static_cast<double>(substeps) / static_cast<double>(state.iterations());
}
BENCHMARK(BM_Paper_SymplecticFrame60)->Arg(2)->UseRealTime()->Unit(benchmark::kMillisecond);

// ---- implicit Euler ------------------------------------------------------------------

void implicit_steps(benchmark::State& state, int nu, int nv) {
  const int threads = static_cast<int>(state.range(0));
  const Real dt = 1.0 / static_cast<Real>(state.range(1));
  const Lattice& L = lattice(nu, nv, 4);
  rt::State s = L.rest;
  rt::SolverOptions o;
  o.integrator = rt::Integrator::implicit_euler;
  o.cg_tolerance = 1e-4;
  o.mass_damping = 1;
  tbb::task_arena arena(threads);
  for (int k = 0; k < 5; ++k) arena.execute([&] { rt::step(L.model, s, dt, o); });  // warm start
  const auto c0 = s.counters;
  for (auto _ : state) arena.execute([&] { rt::step(L.model, s, dt, o); });
  state.counters["steps_per_s"] = benchmark::Counter(1, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["sim_s_per_wall_s"] = benchmark::Counter(dt, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["cg_its"] = static_cast<double>(s.counters.cg_iterations - c0.cg_iterations) /
                             static_cast<double>(std::max<std::int64_t>(1, s.counters.cg_solves - c0.cg_solves));
  state.counters["dt_s"] = dt;
}
void BM_Paper_Implicit(benchmark::State& state) { implicit_steps(state, 39, 9); }
BENCHMARK(BM_Paper_Implicit)->Args({1, 1000})->Args({2, 1000})->Args({2, 60})->UseRealTime()->Unit(benchmark::kMicrosecond);
// The paper's block with (range 1 = 1) or without (0) the skin's volume term
// of build's default (nu = 0.49: 16 K1, the block's dermis 0.118 MPa, so 1.9
// MPa over a 50 times softer fat), implicit at 1/60 s: block Jacobi (range 0
// = 0) against the sparse Cholesky factor (1), 2 threads (docs/runtime.md,
// Preconditioners).
void BM_Paper_VolumeTermImplicit(benchmark::State& state) {
  static const std::array<Lattice, 2> lattices = [] {
    std::array<Lattice, 2> out;
    for (int term = 0; term < 2; ++term) {
      auto bo = rt::testing::make_layered_block(39, 9, 4).options;
      if (term) bo.volume_modulus = {16 * bo.youngs[0]};
      const auto b = rt::testing::make_layered_block(bo);
      out[static_cast<std::size_t>(term)].model = rt::model_from_layers(b.layers, b.sets);
      Lattice& l = out[static_cast<std::size_t>(term)];
      l.rest = rt::make_state(l.model);
      rt::fix_nodes(l.model, l.rest, l.model.set("fixed"));
    }
    return out;
  }();
  const Lattice& L = lattices[state.range(1) == 1 ? 1 : 0];
  rt::State s = L.rest;
  rt::SolverOptions o;
  o.integrator = rt::Integrator::implicit_euler;
  o.mass_damping = 1;
  o.preconditioner = state.range(0) == 1 ? rt::Preconditioner::cholesky : rt::Preconditioner::block_jacobi;
  tbb::task_arena arena(2);
  for (int k = 0; k < 5; ++k) arena.execute([&] { rt::step(L.model, s, 1.0 / 60, o); });
  const auto c0 = s.counters;
  for (auto _ : state) arena.execute([&] { rt::step(L.model, s, 1.0 / 60, o); });
  state.counters["steps_per_s"] = benchmark::Counter(1, benchmark::Counter::kIsIterationInvariantRate);
  state.counters["cg_its"] = static_cast<double>(s.counters.cg_iterations - c0.cg_iterations) /
                             static_cast<double>(std::max<std::int64_t>(1, s.counters.cg_solves - c0.cg_solves));
  state.counters["substeps"] = static_cast<double>(s.counters.substeps - c0.substeps) / static_cast<double>(state.iterations());
  state.counters["factorizations"] = static_cast<double>(s.counters.factorizations - c0.factorizations);
  state.counters["tets"] = L.model.n_tets;
}
BENCHMARK(BM_Paper_VolumeTermImplicit)->ArgsProduct({{0, 1}, {0, 1}})->UseRealTime()->Unit(benchmark::kMillisecond)->Iterations(60);
void BM_Large_Implicit(benchmark::State& state) { implicit_steps(state, 400, 100); }
BENCHMARK(BM_Large_Implicit)->Args({2, 1000})->Args({2, 60})->UseRealTime()->Unit(benchmark::kMillisecond)->Iterations(5);

// ---- static sag: ours and Bullet's against Newton -----------------------------------

// Mean displacement of the skin along gravity at equilibrium.
Real skin_sag(const rt::Model& m, const std::vector<Real>& x) {
  Real s = 0;
  const auto& skin = m.set("skin");
  for (auto i : skin) s += m.rest_x[3 * static_cast<std::size_t>(i) + 1] - x[3 * static_cast<std::size_t>(i) + 1];
  return s / static_cast<Real>(skin.size());
}

Real newton_sag(const Lattice& L) {
  static std::map<const Lattice*, Real> cache;
  auto it = cache.find(&L);
  if (it != cache.end()) return it->second;
  rt::testing::NewtonOptions no;
  const auto r = rt::testing::solve_static(L.model, L.rest, no);
  return cache[&L] = skin_sag(L.model, r.x);
}

// Our integrators at dt: time per step while settling, and the sag error after settling.
void BM_Paper_SagOurs(benchmark::State& state) {
  const bool implicit = state.range(0) == 1;
  const Real dt = 1.0 / static_cast<Real>(state.range(1));
  const Lattice& L = lattice(39, 9, 4);
  rt::SolverOptions o;
  o.integrator = implicit ? rt::Integrator::implicit_euler : rt::Integrator::symplectic_euler;
  o.mass_damping = 20;
  o.cg_tolerance = 1e-4;
  tbb::task_arena arena(2);
  const Real ref = newton_sag(L);
  Real err = 0;
  for (auto _ : state) {
    state.PauseTiming();
    rt::State s = L.rest;
    state.ResumeTiming();
    arena.execute([&] {
      for (int k = 0; k < static_cast<int>(2.0 / dt); ++k) rt::step(L.model, s, dt, o);  // 2 s of settling
    });
    state.PauseTiming();
    err = std::abs(skin_sag(L.model, s.x) - ref) / ref;
    state.ResumeTiming();
  }
  const double steps = 2.0 / dt;
  state.counters["us_per_step"] = benchmark::Counter(steps * 1e-6, benchmark::Counter::kIsIterationInvariantRate |
                                                                     benchmark::Counter::kInvert);
  state.counters["sag_error"] = err;
  state.counters["newton_sag_m"] = ref;
}
BENCHMARK(BM_Paper_SagOurs)->Args({1, 60})->Args({1, 30})->Args({0, 60})->UseRealTime()->Unit(benchmark::kMillisecond)->Iterations(1);

#ifdef ORTHOSIM_HAVE_BULLET
// Bullet's btSoftBody on the same nodes (fixed nodes mass 0) and the same
// always-active springs as links with full linear stiffness (kLST = 1),
// one position iteration, in a btSoftRigidDynamicsWorld.
struct BulletLattice {
  std::unique_ptr<btSoftBodyRigidBodyCollisionConfiguration> config;
  std::unique_ptr<btCollisionDispatcher> dispatcher;
  std::unique_ptr<btDbvtBroadphase> broadphase;
  std::unique_ptr<btSequentialImpulseConstraintSolver> solver;
  std::unique_ptr<btSoftRigidDynamicsWorld> world;
  btSoftBody* body = nullptr;
  BulletLattice(const Lattice& L, int iterations, Real kLST) {
    config = std::make_unique<btSoftBodyRigidBodyCollisionConfiguration>();
    dispatcher = std::make_unique<btCollisionDispatcher>(config.get());
    broadphase = std::make_unique<btDbvtBroadphase>();
    solver = std::make_unique<btSequentialImpulseConstraintSolver>();
    world = std::make_unique<btSoftRigidDynamicsWorld>(dispatcher.get(), broadphase.get(), solver.get(), config.get());
    world->setGravity(btVector3(0, -9.81f, 0));
    auto& wi = world->getWorldInfo();
    wi.m_gravity = btVector3(0, -9.81f, 0);
    wi.m_sparsesdf.Initialize();
    const rt::Model& m = L.model;
    std::vector<btVector3> x(static_cast<std::size_t>(m.n_nodes));
    std::vector<btScalar> mass(static_cast<std::size_t>(m.n_nodes));
    for (std::int32_t i = 0; i < m.n_nodes; ++i) {
      x[i] = btVector3(btScalar(m.rest_x[3 * i]), btScalar(m.rest_x[3 * i + 1]), btScalar(m.rest_x[3 * i + 2]));
      mass[i] = L.rest.inv_mass[i] > 0 ? btScalar(m.mass[i]) : btScalar(0);
    }
    body = new btSoftBody(&wi, m.n_nodes, x.data(), mass.data());
    btSoftBody::Material* mat = body->appendMaterial();
    mat->m_kLST = btScalar(kLST);
    for (std::int32_t q = 0; q < m.n_springs; ++q)
      if (!m.spring_tension[q]) body->appendLink(m.spring_a[q], m.spring_b[q], mat);
    body->m_cfg.piterations = iterations;
    body->m_cfg.kDP = btScalar(0.01);
    body->m_cfg.collisions = 0;
    for (std::int32_t i = 0; i < m.n_nodes; ++i)
      if (L.rest.inv_mass[i] == 0) body->setMass(i, 0);
    world->addSoftBody(body);
  }
  ~BulletLattice() {
    world->removeSoftBody(body);
    delete body;
  }
  std::vector<Real> positions() const {
    std::vector<Real> x(static_cast<std::size_t>(3 * body->m_nodes.size()));
    for (int i = 0; i < body->m_nodes.size(); ++i)
      for (int k = 0; k < 3; ++k) x[3 * static_cast<std::size_t>(i) + k] = body->m_nodes[i].m_x[k];
    return x;
  }
};

void BM_Paper_SagBullet(benchmark::State& state) {
  const int iterations = static_cast<int>(state.range(0));
  const Real dt = 1.0 / 60;
  const Lattice& L = lattice(39, 9, 4);
  const Real ref = newton_sag(L);
  Real err = 0, sag = 0;
  for (auto _ : state) {
    state.PauseTiming();
    BulletLattice b(L, iterations, 1.0);
    state.ResumeTiming();
    for (int k = 0; k < static_cast<int>(2.0 / dt); ++k) b.world->stepSimulation(btScalar(dt), 0);
    state.PauseTiming();
    sag = skin_sag(L.model, b.positions());
    err = std::abs(sag - ref) / ref;
    state.ResumeTiming();
  }
  state.counters["us_per_step"] = benchmark::Counter((2.0 / dt) * 1e-6, benchmark::Counter::kIsIterationInvariantRate |
                                                                           benchmark::Counter::kInvert);
  state.counters["sag_error"] = err;
  state.counters["sag_fraction"] = sag / ref;
}
BENCHMARK(BM_Paper_SagBullet)->Arg(1)->Arg(10)->UseRealTime()->Unit(benchmark::kMillisecond)->Iterations(1);
#endif

// ---- tables ----------------------------------------------------------------------------

// The run-time-against-error workload: a 13 x 5 x 4 block, bone fixed, the
// middle skin node pulled 4 mm down over T = 0.05 s, under gravity.
struct PullBlock {
  rt::Model m;
  rt::State s0;
  Real T = 0.05;
};
PullBlock pull_block() {
  rt::testing::LayeredBlockOptions bo;
  bo.nu = 13, bo.nv = 5;
  const auto b = rt::testing::make_layered_block(bo);
  PullBlock w{rt::model_from_layers(b.layers, b.sets), {}, 0.05};
  w.s0 = rt::make_state(w.m);
  rt::fix_nodes(w.m, w.s0, w.m.set("fixed"));
  rt::Attachment a;
  const auto& skin = w.m.set("skin");
  a.nodes = {skin[skin.size() / 2]};
  a.offset = {0, 0, 0};
  const rt::Vec3 p = rt::load3(w.m.rest_x.data(), a.nodes[0]);
  a.path.t = {0, w.T};
  a.path.p = {p.x, p.y, p.z, p.x, p.y - 0.004, p.z};
  rt::attach(w.m, w.s0, a);
  return w;
}

// Run-time against error: a 13 x 5 x 4 block, gravity and a pull, T = 0.05 s,
// against symplectic Euler at 1e-7 s (converged to the RK4 solution within
// the first-order error of that step).
std::string error_table(bool quick) {
  PullBlock w = pull_block();
  rt::Model& m = w.m;
  const rt::State& s0 = w.s0;
  const Real T = w.T;
  auto simulate = [&](rt::SolverOptions o, Real dt, double* wall, rt::Counters* c) {
    rt::State s = s0;
    tbb::task_arena arena(1);
    const auto t0 = clock_type::now();
    const long n = std::lround(T / dt);
    arena.execute([&] {
      for (long k = 0; k < n; ++k) rt::step(m, s, dt, o);
    });
    *wall = seconds_since(t0);
    *c = s.counters;
    return s.x;
  };
  rt::SolverOptions ro;
  ro.substeps = 1;
  double wref = 0;
  rt::Counters cref;
  const Real href = quick ? 2e-6 : 1e-7;
  const auto ref = simulate(ro, href, &wref, &cref);
  Real motion = 0;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) motion = std::max(motion, rt::norm(rt::load3(ref.data(), i) - rt::load3(s0.x.data(), i)));
  std::ostringstream out;
  out << "| integrator | dt (s) | substeps/step | wall s per simulated s | max position error / max motion | stability events (failed) |\n"
      << "|---|---|---|---|---|---|\n";
  struct Mode {
    const char* name;
    rt::Integrator integ;
    int substeps;
  };
  for (const Mode& md : {Mode{"symplectic, 1 substep", rt::Integrator::symplectic_euler, 1},
                         Mode{"symplectic, auto substeps", rt::Integrator::symplectic_euler, 0},
                         Mode{"implicit, 1 Newton step", rt::Integrator::implicit_euler, 0}}) {
    for (Real dt : {1e-5, 1e-4, 1e-3, 1e-2, 1.0 / 30}) {
      rt::SolverOptions o;
      o.integrator = md.integ;
      o.substeps = md.substeps;
      o.cg_tolerance = 1e-6;
      double wall = 0;
      rt::Counters c;
      const auto x = simulate(o, dt, &wall, &c);
      Real err = 0;
      for (std::int32_t i = 0; i < m.n_nodes; ++i) err = std::max(err, rt::norm(rt::load3(x.data(), i) - rt::load3(ref.data(), i)));
      char line[256];
      std::snprintf(line, sizeof line, "| %s | %.3g | %.1f | %.3g | %.2e | %lld (%lld) |\n", md.name, dt,
                    static_cast<double>(c.substeps) / std::max<double>(1, static_cast<double>(c.steps)), wall / T,
                    err / motion, static_cast<long long>(c.events), static_cast<long long>(c.failed));
      out << line;
    }
  }
  char foot[256];
  std::snprintf(foot, sizeof foot, "\nReference: symplectic Euler at %.0e s (%.1f s wall); max motion %.3g m; %d nodes, %d springs, 1 thread.\n",
                href, wref, motion, m.n_nodes, m.n_springs);
  out << foot;
  return out.str();
}

// The stability sweep's workload, one definition for the table and the
// harness rows: block size and steps, dt x K2/K1 x mass ratio.
struct StressGrid {
  rt::testing::StressSize size;
  std::vector<Real> dts{1e-5, 1e-4, 1e-3, 1e-2, 1.0 / 30};
  std::vector<Real> krs{1, 10, 1e2, 1e3, 1e4};
  std::vector<Real> mrs{1, 1e2, 1e4};
};
StressGrid stress_grid(bool quick) {
  StressGrid g;
  g.size.nu = quick ? 4 : 8, g.size.nv = quick ? 3 : 5, g.size.layers = 4;
  g.size.steps = quick ? 6 : 12;
  g.size.max_substeps = quick ? 1 << 14 : 1 << 16;
  return g;
}

std::string stress_table(bool quick) {
  using namespace rt::testing;
  const StressGrid g = stress_grid(quick);
  const StressSize& size = g.size;
  const std::vector<Real>&dts = g.dts, &krs = g.krs, &mrs = g.mrs;
  std::ostringstream out;
  out << "Cells: dt x K2/K1; each cell counts stable/recovered/failed over mass ratio {1, 1e2, 1e4} x degenerate springs {none, zero, near-zero} (9 runs).\n\n";
  long nan_runs = 0, runs = 0, unbounded_implicit = 0;
  double wall = 0;
  for (StressMode mode : {StressMode::symplectic_auto, StressMode::symplectic_fixed, StressMode::implicit}) {
    out << "\n**" << to_string(mode) << "**\n\n| dt (s) |";
    for (Real kr : krs) out << " K2/K1 = " << kr << " |";
    out << "\n|---|";
    for (std::size_t i = 0; i < krs.size(); ++i) out << "---|";
    out << "\n";
    for (Real dt : dts) {
      char head[32];
      std::snprintf(head, sizeof head, "| %.3g |", dt);
      out << head;
      for (Real kr : krs) {
        int st = 0, rc = 0, fl = 0;
        for (Real mr : mrs)
          for (Degenerate d : {Degenerate::none, Degenerate::zero, Degenerate::near_zero}) {
            const auto r = run_stress_case(StressCase{dt, kr, mr, d, mode}, size);
            wall += r.wall_s;
            ++runs;
            nan_runs += r.nan_seen;
            if (mode == StressMode::implicit && !r.bounded) ++unbounded_implicit;
            const auto v = r.verdict();
            (v == "stable" ? st : v == "recovered" ? rc : fl)++;
          }
        out << " " << st << "/" << rc << "/" << fl << " |";
      }
      out << "\n";
    }
  }
  char foot[256];
  std::snprintf(foot, sizeof foot,
                "\n%ld runs, %ld with a non-finite value in the state, %ld implicit runs unbounded; block %dx%dx%d, %d steps per run, "
                "at most %d substeps per step; %.1f s.\n",
                runs, nan_runs, unbounded_implicit, size.nu, size.nv, size.layers, size.steps, size.max_substeps, wall);
  out << foot;
  return out.str();
}

// ---- harness rows (orthosim bench) -----------------------------------------------------

namespace ob = orthosim::bench;

void integrator_rows(ob::Results& out, bool quick) {
  PullBlock w = pull_block();
  rt::Model& m = w.m;
  const rt::State& s0 = w.s0;
  const Real T = w.T;
  tbb::task_arena arena(1);
  auto simulate = [&](const rt::SolverOptions& o, Real dt, rt::Counters* c) {
    rt::State s = s0;
    const long n = std::lround(T / dt);
    arena.execute([&] {
      for (long k = 0; k < n; ++k) rt::step(m, s, dt, o);
    });
    if (c) *c = s.counters;
    return s.x;
  };
  rt::SolverOptions ro;
  ro.substeps = 1;
  const Real href = quick ? 2e-6 : 1e-7;
  const auto ref = simulate(ro, href, nullptr);
  Real motion = 0;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) motion = std::max(motion, rt::norm(rt::load3(ref.data(), i) - rt::load3(s0.x.data(), i)));
  struct Mode {
    const char* name;
    rt::Integrator integ;
    int substeps;
    bool goal;
  };
  const std::vector<Real> dts = quick ? std::vector<Real>{1e-4, 1e-3, 1e-2, 1.0 / 30} : std::vector<Real>{1e-5, 1e-4, 1e-3, 1e-2, 1.0 / 30};
  for (const Mode& md : {Mode{"symplectic, 1 substep", rt::Integrator::symplectic_euler, 1, false},
                         Mode{"symplectic, auto substeps", rt::Integrator::symplectic_euler, 0, true},
                         Mode{"implicit Euler, 1 Newton step", rt::Integrator::implicit_euler, 0, true}}) {
    for (Real dt : dts) {
      if (quick && md.substeps == 1 && dt < 1e-3) continue;
      rt::SolverOptions o;
      o.integrator = md.integ;
      o.substeps = md.substeps;
      o.cg_tolerance = 1e-6;
      rt::Counters c;
      std::vector<Real> x;
      ob::Row row;
      row.workload = std::string("integrator error against dt (13x5x4 block, pull, 0.05 s): ") + md.name;
      char set[32];
      std::snprintf(set, sizeof set, "dt=%.3g", dt);
      row.setting = set;
      row.seconds = ob::time_runs(quick ? 1 : 3, [&] { x = simulate(o, dt, &c); }, 0);
      Real err = 0;
      bool finite = true;
      for (std::int32_t i = 0; i < m.n_nodes; ++i) {
        const Real e = rt::norm(rt::load3(x.data(), i) - rt::load3(ref.data(), i));
        finite = finite && std::isfinite(e);
        err = std::max(err, e);
      }
      const double rel = finite ? err / motion : INFINITY;
      if (md.goal) row.error("max position error / max motion", rel, "<=", 0.2);
      else row.error("max position error / max motion", rel);
      row.x = dt;
      row.extra = {{"integrator", md.name}, {"dt_s", dt}, {"wall_s_per_simulated_s", ob::median(row.seconds) / T},
                   {"substeps_per_step", static_cast<double>(c.substeps) / std::max<double>(1, static_cast<double>(c.steps))},
                   {"events", c.events}, {"failed_steps", c.failed}, {"reference_dt_s", href}, {"nodes", m.n_nodes}};
      out.add(row);
    }
  }
}

// the paper's Fig. 3(a): time per step against grid size, 4 layers
void grid_rows(ob::Results& out, bool quick) {
  std::vector<std::pair<int, int>> grids = {{15, 5}, {18, 5}, {39, 9}, {60, 15}, {100, 25}};
  if (!quick) grids.insert(grids.end(), {{200, 50}, {400, 100}});
  tbb::task_arena arena(2);
  const double batch_s = quick ? 0.03 : 0.2;
  for (auto [nu, nv] : grids) {
    const Lattice& L = lattice(nu, nv, 4);
    for (bool implicit : {false, true}) {
      rt::State s = L.rest;
      rt::SolverOptions o;
      Real dt = 1.0 / 60;
      if (implicit) {
        o.integrator = rt::Integrator::implicit_euler;
        o.cg_tolerance = 1e-4;
        o.mass_damping = 1;
      } else {
        o.substeps = 1;
        dt = o.safety * rt::symplectic_step_limit(L.model, s, o);
      }
      auto one = [&] { arena.execute([&] { rt::step(L.model, s, dt, o); }); };
      for (int k = 0; k < 3; ++k) one();  // warm start
      long n = 1;
      for (double t = 0; (t = ob::now_s(), one(), ob::now_s() - t) * static_cast<double>(n) < batch_s && n < 100000;) n *= 2;
      ob::Row row;
      row.workload = implicit ? "time per step against grid (Fig. 3a), implicit Euler dt 1/60 s, 2 threads"
                              : "time per step against grid (Fig. 3a), symplectic substep, 2 threads";
      row.setting = std::to_string(nu) + "x" + std::to_string(nv);
      const auto c0 = s.counters;
      for (int r = 0; r < (quick ? 3 : 5); ++r) {
        const double t0 = ob::now_s();
        for (long k = 0; k < n; ++k) one();
        row.seconds.push_back((ob::now_s() - t0) / static_cast<double>(n));
      }
      row.error("stability events", static_cast<double>(s.counters.events - c0.events), "<=", 0);
      row.x = L.model.n_nodes;
      row.extra = {{"nu", nu}, {"nv", nv}, {"layers", 4}, {"nodes", L.model.n_nodes}, {"springs", L.model.n_springs},
                   {"dt_s", dt}, {"steps_per_batch", n}, {"integrator", implicit ? "implicit" : "symplectic"},
                   {"steps_per_s", 1 / ob::median(row.seconds)}};
      if (implicit)
        row.extra["sim_s_per_wall_s"] = dt / ob::median(row.seconds);
      out.add(row);
    }
  }
}

void stability_rows(ob::Results& out, bool quick) {
  using namespace rt::testing;
  const StressGrid g = stress_grid(quick);
  const StressSize& size = g.size;
  const std::vector<Real>&dts = g.dts, &krs = g.krs, &mrs = g.mrs;
  for (StressMode mode : {StressMode::symplectic_auto, StressMode::symplectic_fixed, StressMode::implicit})
    for (Real dt : dts)
      for (Real kr : krs) {
        int st = 0, rc = 0, fl = 0, nan = 0, unbounded = 0;
        double wall = 0;
        for (Real mr : mrs)
          for (Degenerate d : {Degenerate::none, Degenerate::zero, Degenerate::near_zero}) {
            const auto r = run_stress_case(StressCase{dt, kr, mr, d, mode}, size);
            wall += r.wall_s;
            nan += r.nan_seen;
            unbounded += !r.bounded;
            const auto v = r.verdict();
            (v == "stable" ? st : v == "recovered" ? rc : fl)++;
          }
        ob::Row row;
        row.workload = std::string("stability matrix: ") + to_string(mode);
        char set[64];
        std::snprintf(set, sizeof set, "dt=%.3g K2/K1=%g", dt, kr);
        row.setting = set;
        row.seconds = {wall};
        row.error("runs with a non-finite state", nan, "<=", 0);
        row.x = dt;
        row.extra = {{"integrator", to_string(mode)}, {"dt_s", dt}, {"stiffness_ratio", kr}, {"stable", st},
                     {"recovered", rc}, {"failed", fl}, {"runs", st + rc + fl}, {"unbounded", unbounded},
                     {"block", std::to_string(size.nu) + "x" + std::to_string(size.nv) + "x4"}, {"steps", size.steps}};
        out.add(row);
      }
}

void sag_rows(ob::Results& out, bool quick) {
  const Lattice& L = lattice(39, 9, 4);
  const Real ref = newton_sag(L);
  const Real dt = 1.0 / 60;
  const int steps = static_cast<int>(2.0 / dt);
  tbb::task_arena arena(2);
  Real ours_sag = 0;
  auto ours = [&] {
    rt::SolverOptions o;
    o.integrator = rt::Integrator::implicit_euler;
    o.mass_damping = 20;
    o.cg_tolerance = 1e-4;
    rt::State s = L.rest;
    arena.execute([&] {
      for (int k = 0; k < steps; ++k) rt::step(L.model, s, dt, o);
    });
    ours_sag = skin_sag(L.model, s.x);
  };
  ob::Row row;
  row.workload = "static sag of the 39x9x4 lattice under gravity, 2 s of 1/60 s steps, against Newton";
  row.setting = "implicit, 120 steps";
  row.x = L.model.n_nodes;
#ifdef ORTHOSIM_HAVE_BULLET
  Real bullet_sag = 0;
  auto peer = [&] {
    BulletLattice b(L, 10, 1.0);
    for (int k = 0; k < steps; ++k) b.world->stepSimulation(btScalar(dt), 0);
    bullet_sag = skin_sag(L.model, b.positions());
  };
  ob::time_alternating(quick ? 1 : 3, ours, peer, &row.seconds, &row.peer_seconds);
  row.peer = "Bullet btSoftBody, 10 iterations";
  row.peer_error = std::abs(bullet_sag - ref) / ref;
#else
  row.seconds = ob::time_runs(quick ? 1 : 3, ours);
  out.note("Bullet btSoftBody peer not built (configure with -DORTHOSIM_WITH_BULLET_PEER=ON)");
#endif
  row.error("relative sag error", std::abs(ours_sag - ref) / ref, "<=", 1e-3);
  row.extra = {{"newton_sag_m", ref}, {"nodes", L.model.n_nodes}, {"springs", L.model.n_springs}};
  out.add(row);
}

// Static colliders on the tissue: the paper-sized lattice, free (nothing
// fixed), dropped 1 mm on to a table and left to rest, 2 s of 1/60 s implicit
// steps; error = the table's force on it (State::contact_force summed)
// against its weight M g. The table as a plane and as a 2-triangle mesh; and
// a moving collider: the plane rising at u = 0.05 m/s from the start, which
// lifts the lattice at u once it rests on it, its force then M (g + alpha u)
// (the weight and the mass damping -alpha m v of the lattice moving at u).
void contact_rows(ob::Results& out, bool quick) {
  const Lattice& L = lattice(39, 9, 4);
  Real low = HUGE_VAL;
  for (std::int32_t i = 0; i < L.model.n_nodes; ++i) low = std::min(low, L.model.rest_x[3 * static_cast<std::size_t>(i) + 1]);
  const Real table = low - 1e-3, weight = L.model.total_mass * 9.81;
  const Real alpha = 20, rise = 0.05;  // 1/s, m/s
  for (int variant = 0; variant < 3; ++variant) {
    const bool as_mesh = variant == 1, rising = variant == 2;
    const Real expected = rising ? L.model.total_mass * (9.81 + alpha * rise) : weight;
    auto ob = std::make_shared<rt::Obstacles>();
    if (as_mesh) {
      rt::ObstacleMesh m;
      m.vertices = {-1, table, -1, 1, table, -1, 1, table, 1, -1, table, 1};
      m.triangles = {0, 2, 1, 0, 3, 2};
      m.friction = 0.5;
      rt::add_obstacle_mesh(*ob, std::move(m));
    } else {
      rt::add_obstacle_plane(*ob, {{0, table, 0}, {0, 1, 0}, 0, 0.5});
    }
    Real fy = 0, fside = 0, its = 0;
    std::int64_t contacts = 0, factors = 0;
    tbb::task_arena arena(2);
    auto ours = [&] {
      rt::State s = rt::make_state(L.model);
      s.obstacles = ob;
      if (rising) {
        s.obstacle_paths.resize(1);
        s.obstacle_paths[0].t = {0, 10};
        s.obstacle_paths[0].p = {0, 0, 0, 0, 10 * rise, 0};
      }
      rt::SolverOptions o;
      o.integrator = rt::Integrator::implicit_euler;
      o.mass_damping = alpha;
      arena.execute([&] {
        for (int k = 0; k < 120; ++k) rt::step(L.model, s, 1.0 / 60, o);
      });
      Real f[3] = {0, 0, 0};
      for (std::size_t i = 0; i < s.contact_force.size(); ++i) f[i % 3] += s.contact_force[i];
      fy = f[1], fside = std::hypot(f[0], f[2]), contacts = s.counters.obstacle_contacts;
      its = static_cast<Real>(s.counters.cg_iterations) / static_cast<Real>(std::max<std::int64_t>(1, s.counters.cg_solves));
      factors = s.counters.factorizations;
    };
    ob::Row row;
    row.workload = rising ? std::string("a free 39x9x4 lattice lifted by a table rising at 0.05 m/s (a moving plane), 2 s of "
                                        "1/60 s steps: the table's force against M (g + alpha u)")
                          : std::string("a free 39x9x4 lattice resting on a table (") + (as_mesh ? "2-triangle STL" : "plane") +
                                "), 2 s of 1/60 s steps: the table's force against the weight";
    row.setting = "implicit, 120 steps, 2 threads";
    row.x = L.model.n_nodes;
    row.seconds = ob::time_runs(quick ? 1 : 3, ours);
    row.error(rising ? "relative force error" : "relative weight error", std::abs(fy - expected) / expected, "<=", 1e-4);
    row.extra = {{"weight_n", weight}, {"expected_force_y_n", expected}, {"table_force_y_n", fy}, {"sideways_n", fside},
                 {"contacts", contacts}, {"pcg_iterations_per_solve", its}, {"sparse_factors", factors}};
    out.add(row);
  }
}

// A thin probe on the tissue: a 1 mm rod, narrower than the skin's 4 mm node
// spacing, pushed 5 mm into the paper-sized lattice (bone fixed, no gravity)
// between nodes over 0.25 s and held, 2 s of 1/60 s implicit steps; its edges
// meet the skin's faces (resolve_face_contacts). Error: its force on the
// tissue at the end against what the fixed bone carries (at rest they are
// equal). Beside it, the same run with the edge samples off (only nodes
// collide: the rod passes through the skin, and carries nothing; the tissue
// at rest takes far fewer PCG iterations, so the time ratio is mostly the
// pressed tissue's solves, not the faces' pass).
void thin_probe_rows(ob::Results& out, bool quick) {
  const Lattice& L = lattice(39, 9, 4);
  // the rod's tip 1 mm under the skin (y = 0) in the middle of a quad near the lattice's middle
  const Real cx = 0.5 * 0.004 * 19 + 0.002, cz = 0.5 * 0.004 * 8 + 0.002, push = 0.005;
  const rt::ObstacleMesh rod = rt::test::box_mesh({cx - 0.0005, -0.021, cz - 0.0005}, {cx + 0.0005, -0.001, cz + 0.0005});
  struct Result {
    rt::Vec3 force, bone;
    std::int64_t faces = 0;
    double its = 0;  // PCG iterations per solve
    std::int64_t resolves = 0;
  };
  auto run = [&](Real spacing, Result& r) {
    auto ob = std::make_shared<rt::Obstacles>();
    rt::add_obstacle_mesh(*ob, rod);
    rt::sample_obstacle_edges(ob->meshes[0], spacing);
    rt::State s = L.rest;
    s.obstacles = ob;
    s.obstacle_paths.resize(1);
    s.obstacle_paths[0].t = {0, 0.25};
    s.obstacle_paths[0].p = {0, 0, 0, 0, push, 0};
    rt::SolverOptions o;
    o.integrator = rt::Integrator::implicit_euler;
    o.gravity = {0, 0, 0};
    o.mass_damping = 20;
    tbb::task_arena arena(2);
    arena.execute([&] {
      for (int k = 0; k < 120; ++k) rt::step(L.model, s, 1.0 / 60, o);
    });
    r.force = rt::load3(s.face_force.data(), 0);
    r.bone = rt::testing::fixed_reaction(L.model, s.x, s.inv_mass);
    r.faces = s.counters.face_contacts;
    r.resolves = s.counters.face_resolves;
    r.its = static_cast<double>(s.counters.cg_iterations) / static_cast<double>(std::max<std::int64_t>(1, s.counters.cg_solves));
  };
  const Real spacing = rt::default_edge_spacing(L.model.quads, L.model.rest_x);
  Result with, without;
  std::vector<double> off_s;
  ob::Row row;
  row.workload = "a 1 mm rod pushed 5 mm into the 39x9x4 lattice's skin between nodes (4 mm apart), 2 s of 1/60 s steps: its "
                 "force on the tissue against the fixed bone's reaction";
  row.setting = "implicit, 120 steps, 2 threads, edge samples " + std::to_string(1e3 * spacing).substr(0, 4) + " mm apart";
  row.x = L.model.n_nodes;
  ob::time_alternating(quick ? 1 : 3, [&] { run(spacing, with); }, [&] { run(0, without); }, &row.seconds, &off_s);
  row.error("relative force error", std::abs(with.bone.y - with.force.y) / with.force.y, "<=", 1e-3);
  row.extra = {{"force_y_n", with.force.y},
               {"bone_reaction_y_n", with.bone.y},
               {"face_contacts", with.faces},
               {"seconds_nodes_only_median", ob::median(off_s)},
               {"ratio_to_nodes_only", ob::median(row.seconds) / ob::median(off_s)},
               {"nodes_only_force_y_n", without.bone.y},
               {"pcg_iterations_per_solve", with.its},
               {"face_resolves", with.resolves},
               {"nodes_only_pcg_iterations_per_solve", without.its}};
  out.add(row);
}

void results(const std::string& path, bool quick) {
  ob::Results out("runtime", "runtime_bench", quick);
  integrator_rows(out, quick);
  grid_rows(out, quick);
  sag_rows(out, quick);
  contact_rows(out, quick);
  thin_probe_rows(out, quick);
  stability_rows(out, quick);
  out.write(path);
}

// The implicit solve's error against the integrator's: the 39x9x4 lattice
// released under gravity for 0.5 s, 1 thread. Solve error: positions at the
// end against the same dt solved to 1e-12; integrator error: that run against
// dt = 0.125 ms; both over the largest motion.
void print_cg_tolerance_table() {
  const Lattice& L = lattice(39, 9, 4);
  const Real T = 0.5;
  struct Run {
    std::vector<Real> x;
    double its = 0, us = 0;
  };
  auto run = [&](Real dt, Real tol) {
    rt::State s = L.rest;
    rt::SolverOptions o;
    o.integrator = rt::Integrator::implicit_euler;
    o.cg_tolerance = tol;
    o.cg_max_iterations = 2000;
    o.gravity = {0, 9.81, 0};
    tbb::task_arena arena(1);
    const long n = std::lround(T / dt);
    const auto t0 = std::chrono::steady_clock::now();
    for (long k = 0; k < n; ++k) arena.execute([&] { rt::step(L.model, s, dt, o); });
    const double w = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return Run{s.x, static_cast<double>(s.counters.cg_iterations) / static_cast<double>(s.counters.cg_solves),
               1e6 * w / static_cast<double>(n)};
  };
  auto dist = [](const std::vector<Real>& a, const std::vector<Real>& b) {
    Real e = 0;
    for (std::size_t i = 0; i + 2 < a.size(); i += 3)
      e = std::max(e, std::hypot(a[i] - b[i], a[i + 1] - b[i + 1], a[i + 2] - b[i + 2]));
    return e;
  };
  const Run ref = run(0.125e-3, 1e-12);
  const Real motion = dist(ref.x, L.rest.x);
  std::printf("39x9x4 lattice under gravity for %.1f s, 1 thread; errors over the largest motion (%.3g m)\n", T, motion);
  std::printf("%10s %10s %16s %12s %12s %14s\n", "dt s", "tolerance", "iterations/step", "us/step", "solve error", "integ. error");
  for (Real dt : {1.0 / 60, 1e-3, 0.5e-3}) {
    const Run tight = run(dt, 1e-12);
    const Real integ = dist(tight.x, ref.x) / motion;
    for (Real tol : {1e-3, 1e-4, 1e-5, 1e-6}) {
      const Run r = run(dt, tol);
      std::printf("%10.3g %10.0e %16.2f %12.1f %12.2e %14.2e\n", dt, tol, r.its, r.us, dist(r.x, tight.x) / motion, integ);
    }
  }
}

}  // namespace

int main(int argc, char** argv) {
  ob::CommonArgs common = ob::parse_common(argc, argv);
  if (!common.results.empty()) {
    results(common.results, common.quick);
    return 0;
  }
  std::string tables;
  const bool quick = common.quick;
  std::vector<char*> args;
  for (char* arg : common.rest) {
    if (std::strncmp(arg, "--tables=", 9) == 0) tables = arg + 9;
    else if (std::strcmp(arg, "--cg-tolerance") == 0) {
      print_cg_tolerance_table();
      return 0;
    } else args.push_back(arg);
  }
  if (!tables.empty()) {
    std::ostringstream md;
    md << "# runtime tables (generated by runtime_bench --tables)\n\n## Run time against error\n\n"
       << error_table(quick) << "\n## Stability stress sweep (stable/recovered/failed)\n\n" << stress_table(quick);
    std::ofstream(tables + "/runtime_tables.md") << md.str();
    std::fputs(md.str().c_str(), stdout);
    return 0;
  }
  int n = static_cast<int>(args.size());
  benchmark::Initialize(&n, args.data());
  if (benchmark::ReportUnrecognizedArguments(n, args.data())) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
