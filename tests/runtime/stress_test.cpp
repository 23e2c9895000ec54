// The stability stress test, small: dt x K2/K1 x neighbour mass ratio x
// degenerate springs, for each integrator mode. No NaN ever reaches the
// state; implicit Euler stays bounded at dt = 1/30 s; automatic substeps
// never fail. The large sweep and the docs table: tests/bench/runtime_bench.cpp.
#include "runtime/obstacles.h"
#include "runtime/solver.h"
#include "runtime/testing/lattice.h"
#include "runtime/testing/stress.h"
#include "tests/runtime/runtime_test_util.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <map>
#include <random>

namespace orthosim::runtime::testing {
namespace {

TEST(Stress, SmallSweepNeverProducesNaN) {
  StressSize size;
  size.nu = 4, size.nv = 3, size.layers = 3;
  size.steps = 8;
  size.max_substeps = 1 << 15;
  std::map<std::string, std::map<std::string, int>> table;  // mode -> verdict -> cells
  double wall = 0;
  for (StressMode mode : {StressMode::symplectic_auto, StressMode::symplectic_fixed, StressMode::implicit})
    for (Real dt : {1e-5, 1e-3, 1.0 / 30})
      for (Real kr : {1.0, 1e2, 1e4})
        for (Real mr : {1.0, 1e2, 1e4})
          for (Degenerate d : {Degenerate::none, Degenerate::zero, Degenerate::near_zero}) {
            StressCase c{dt, kr, mr, d, mode};
            const auto r = run_stress_case(c, size);
            wall += r.wall_s;
            SCOPED_TRACE(std::string(to_string(mode)) + " dt " + std::to_string(dt) + " K2/K1 " + std::to_string(kr) +
                         " mass ratio " + std::to_string(mr) + " degenerate " + to_string(d));
            EXPECT_FALSE(r.nan_seen);
            if (mode == StressMode::implicit) {
              EXPECT_TRUE(r.bounded) << "max displacement " << r.max_displacement << " m";
              EXPECT_EQ(r.counters.failed, 0);
            }
            if (mode == StressMode::symplectic_auto) {
              EXPECT_EQ(r.counters.failed, 0) << r.verdict();
            }
            ++table[to_string(mode)][r.verdict()];
          }
  for (const auto& [mode, counts] : table) {
    std::printf("%-28s", mode.c_str());
    for (const char* v : {"stable", "recovered", "failed"}) std::printf(" %s %d", v, counts.count(v) ? counts.at(v) : 0);
    std::printf("\n");
  }
  std::printf("sweep wall time %.2f s\n", wall);
}

// A two-sided square 0.1 m a side about c, spanned by the unit vectors t1, t2.
ObstacleMesh two_sided_square(const Vec3& c, const Vec3& t1, const Vec3& t2) {
  ObstacleMesh m;
  for (Real a : {-0.05, 0.05})
    for (Real b : {-0.05, 0.05}) {
      const Vec3 q = c + a * t1 + b * t2;
      m.vertices.insert(m.vertices.end(), {q.x, q.y, q.z});
    }
  m.triangles = {0, 1, 3, 0, 3, 2};
  m.two_sided = true;
  return m;
}

// A collider's stress path: pressed to `up` by t_up, dragged to `dragged` and
// turned by `turn` rad about z (its pivot) over 0.1 s, back to where it
// started 0.05 s later.
Path press_drag_turn(Real t_up, const Vec3& up, const Vec3& dragged, Real turn) {
  Path path;
  path.t = {0, t_up, t_up + 0.1, t_up + 0.15};
  path.p = {0, 0, 0, up.x, up.y, up.z, dragged.x, dragged.y, dragged.z, 0, 0, 0};
  path.r = {0, 0, 0, 0, 0, 0, 0, 0, turn, 0, 0, 0};
  return path;
}

// The colliders' stress runs' solver: light damping, room to subdivide.
SolverOptions collider_stress_options(Integrator integ) {
  SolverOptions o;
  o.integrator = integ;
  o.mass_damping = 2;
  o.max_substeps = 1 << 14;
  return o;
}

// The colliders' stress trials: 12 random trials on both integrators, dt
// 1/240 and 1/30 s in turn, each on the 8 x 4 x 4 block hanging from its
// bone sheet (x 0..28 mm, z 0..12 mm, y 0 (skin) .. 17 mm (fixed));
// trial(rng, integrator, dt, model, state) sets the colliders and runs it.
template <class Trial>
void collider_trials(std::uint64_t seed, Trial&& trial) {
  std::mt19937_64 rng(seed);
  for (int k = 0; k < 12; ++k)
    for (Integrator integ : {Integrator::implicit_euler, Integrator::symplectic_euler}) {
      const Real dt = k % 2 ? 1.0 / 30 : 1.0 / 240;
      const auto b = make_layered_block(8, 4, 4);
      const Model m = model_from_layers(b.layers, b.sets);
      State s = make_state(m);
      fix_nodes(m, s, m.set("fixed"));
      SCOPED_TRACE("trial " + std::to_string(k) + " " + to_string(integ) + " dt " + std::to_string(dt));
      trial(rng, integ, dt, m, s);
    }
}

// Static colliders under stress: a hanging block (8 x 4 x 4) over a table,
// with a two-sided square wall standing through it, and a grasper dragging
// skin nodes down through the table and across the wall along a random path
// (up to 0.5 m/s), for random table heights, wall angles and paths, both
// integrators, dt 1/30 and 1/240 s. No NaN ever; no failed step; no free
// node below the table after any step; no free node changes sides of the
// wall (where it is inside the square's extent).
TEST(Stress, CollidersNeverLetANodeThroughNorProduceNaN) {
  std::uniform_real_distribution<Real> u(0, 1);
  int cases = 0;
  long contacts = 0;
  collider_trials(20261128, [&](std::mt19937_64& rng, Integrator integ, Real dt, const Model& m, State& s) {
      const Real table = -u(rng) * 2e-3;
      const Real angle = (u(rng) - 0.5) * 0.6;  // the wall's tilt about z
      const Vec3 wall_n{std::cos(angle), std::sin(angle), 0};
      const Vec3 wall_p{0.010 + 0.008 * u(rng), 0, 0};
      auto ob = std::make_shared<Obstacles>();
      add_obstacle_plane(*ob, {{0, table, 0}, {0, 1, 0}, 0.3 * u(rng), 0.8 * u(rng)});
      {
        // a square 0.1 m a side in the wall's plane, about wall_p
        ObstacleMesh wall = two_sided_square(wall_p, {-wall_n.y, wall_n.x, 0}, {0, 0, 1});
        wall.friction = 0.5 * u(rng);
        add_obstacle_mesh(*ob, std::move(wall));
      }
      s.obstacles = ob;
      // the grasper: the skin nodes within 4 mm of a skin point, dragged down and across
      const auto& skin = m.set("skin");
      const Vec3 c0{0.004 + 0.02 * u(rng), 0, 0.006};
      Attachment a;
      for (auto i : skin) {
        const Vec3 r = load3(m.rest_x.data(), i);
        if (norm(r - c0) > 4e-3) continue;
        a.nodes.push_back(i);
        a.offset.insert(a.offset.end(), {r.x - c0.x, r.y - c0.y, r.z - c0.z});
      }
      ASSERT_FALSE(a.nodes.empty());
      const Vec3 c1 = c0 + Vec3{(u(rng) - 0.5) * 0.04, -0.004 - 0.006 * u(rng), (u(rng) - 0.5) * 0.01};
      a.path.t = {0, 0.1};
      a.path.p = {c0.x, c0.y, c0.z, c1.x, c1.y, c1.z};
      attach(m, s, a);
      auto side = [&](const State& st, std::int32_t i) {  // +1 / -1 of the wall, 0 outside its square
        const Vec3 r = load3(st.x.data(), i) - wall_p;
        const Vec3 t1{-wall_n.y, wall_n.x, 0};
        if (std::abs(dot(r, t1)) > 0.05 || std::abs(r.z) > 0.05) return 0;
        return dot(r, wall_n) >= 0 ? 1 : -1;
      };
      std::vector<int> side0(static_cast<std::size_t>(m.n_nodes));
      for (std::int32_t i = 0; i < m.n_nodes; ++i) side0[static_cast<std::size_t>(i)] = side(s, i);
      SolverOptions o;
      o.integrator = integ;
      o.mass_damping = 2;
      o.max_substeps = 1 << 14;
      int through_table = 0, through_wall = 0;
      bool finite = true;
      for (Real t = 0; t < 0.2; t += dt) {
        step(m, s, dt, o);
        for (std::int32_t i = 0; i < m.n_nodes; ++i) {
          if (s.pin[static_cast<std::size_t>(i)] != Pin::free) continue;
          const Vec3 r = load3(s.x.data(), i);
          finite = finite && std::isfinite(r.x) && std::isfinite(r.y) && std::isfinite(r.z);
          through_table += r.y < table;
          const int now = side(s, i), then = side0[static_cast<std::size_t>(i)];
          through_wall += now != 0 && then != 0 && now != then;
        }
      }
      EXPECT_TRUE(finite);
      EXPECT_EQ(s.counters.nonfinite, 0);
      EXPECT_EQ(s.counters.failed, 0);
      EXPECT_EQ(through_table, 0) << "node-steps below the table";
      EXPECT_EQ(through_wall, 0) << "node-steps on the other side of the wall";
      contacts += s.counters.obstacle_contacts;
      ++cases;
  });
  std::printf("%d cases, %ld node-substeps in contact\n", cases, contacts);
  EXPECT_GT(contacts, 0);
}

// Moving colliders: a plate under the hanging block's skin (a two-sided
// square 0.1 m a side, wider than the block and its drag, so that no node can
// go around it; tilted by up to 0.3 rad) is driven into the skin along its
// normal from 2 mm below it to 1-5 mm into it at 0.05-1.4 m/s, dragged
// sideways by up to 10 mm while turned about its centre by up to 0.15 rad,
// and withdrawn, for random tilts, depths, speeds,
// drags, frictions and restitutions, both integrators, dt 1/30 and 1/240 s.
// No NaN ever; no failed step; no free node behind the plate where it is
// after any step.
TEST(Stress, MovingCollidersNeverLetANodeThroughNorProduceNaN) {
  std::uniform_real_distribution<Real> u(0, 1);
  int cases = 0;
  long contacts = 0;
  collider_trials(20261129, [&](std::mt19937_64& rng, Integrator integ, Real dt, const Model& m, State& s) {
      const Real tilt = (u(rng) - 0.5) * 0.6;
      const Vec3 n{-std::sin(tilt), std::cos(tilt), 0}, t1{std::cos(tilt), std::sin(tilt), 0}, t2{0, 0, 1};
      const Real cx = 0.014;
      const Vec3 c{cx, -(0.002 + std::abs(std::sin(tilt)) * 0.014) / std::cos(tilt), 0.006};  // 2 mm below the skin at least
      auto ob = std::make_shared<Obstacles>();
      {
        ObstacleMesh plate = two_sided_square(c, t1, t2);
        plate.friction = 0.8 * u(rng);
        plate.restitution = 0.3 * u(rng);
        plate.pivot = c;
        add_obstacle_mesh(*ob, std::move(plate));
      }
      s.obstacles = ob;
      Real gap = HUGE_VAL;  // the skin's least distance ahead of the plate at rest
      for (std::int32_t i = 0; i < m.n_nodes; ++i) gap = std::min(gap, dot(n, load3(m.rest_x.data(), i) - c));
      ASSERT_GE(gap, 0.002 - 1e-12);
      const Real rise = gap + 0.001 + 0.004 * u(rng);       // 1-5 mm into the skin
      const Real t_up = rise / (0.05 + 1.35 * u(rng));       // at 0.05 .. 1.4 m/s
      const Vec3 up = rise * n, dragged = up + ((u(rng) - 0.5) * 0.02) * t1;
      // and turned about its centre by up to 0.15 rad each way while pressed
      const Real turn = (u(rng) - 0.5) * 0.3;
      const Path path = press_drag_turn(t_up, up, dragged, turn);
      s.obstacle_paths = {path};
      const SolverOptions o = collider_stress_options(integ);
      int through = 0;
      bool finite = true;
      Real deepest = 0;
      for (Real t = 0; t < t_up + 0.2; t += dt) {
        step(m, s, dt, o);
        const Vec3 d = path.at(s.time), nt = path_rotation(path, s.time)(n);
        for (std::int32_t i = 0; i < m.n_nodes; ++i) {
          if (s.pin[static_cast<std::size_t>(i)] != Pin::free) continue;
          const Vec3 r = load3(s.x.data(), i);
          finite = finite && std::isfinite(r.x) && std::isfinite(r.y) && std::isfinite(r.z);
          const Real ahead = dot(nt, r - c - d);
          through += ahead < -1e-9;
          deepest = std::min(deepest, ahead);
        }
      }
      EXPECT_TRUE(finite);
      EXPECT_EQ(s.counters.nonfinite, 0);
      EXPECT_EQ(s.counters.failed, 0);
      EXPECT_EQ(through, 0) << "node-steps behind the plate, the deepest " << deepest << " m";
      EXPECT_GT(s.counters.obstacle_contacts, 0) << "the plate met the skin";
      contacts += s.counters.obstacle_contacts;
      ++cases;
  });
  std::printf("%d cases, %ld node-substeps in contact\n", cases, contacts);
}

// Thin probes under stress: a rod 0.5-2 mm across (under the block's 4 mm
// node spacing), its tip 2 mm under the skin of an 8 x 8 x 4 block hanging
// from its bone sheet (28 x 28 mm), between nodes at random within 4 mm of
// the centre; pushed 1-5 mm into the skin at 0.05-1.4 m/s, then dragged up
// to 3 mm each way along x and turned up to 0.15 rad each way about its tip
// while pressed, then withdrawn; random friction; its edges sampled at the
// default spacing. 8 trials on both integrators, dt 1/240 and 1/30 s in
// turn. No NaN, no failed step, and no point of the rod behind the skin face
// over it, nor inside the skin (behind the face over it, and away from
// every face), after any step by more than 10^-6 m. (The block's sides have no
// faces: a rod that reached one would enter the tissue there, so the rod
// stays in the middle.)
// (the trials, for rods w_min .. w_min + w_span wide)
void probe_trials(Real w_min, Real w_span, Preconditioner pc = Preconditioner::automatic) {
  std::uniform_real_distribution<Real> u(0, 1);
  std::mt19937_64 rng(20261130);
  const auto b = make_layered_block(8, 8, 4);
  const Model m = model_from_layers(b.layers, b.sets);
  const std::vector<std::int32_t> skin_quads = test::top_sheet_quads(m);  // the skin sheet's quads
  ASSERT_EQ(skin_quads.size(), 4u * 7 * 7);
  const Real spacing = default_edge_spacing(m.quads, m.rest_x);
  int cases = 0;
  long faces = 0;
  Real worst = -HUGE_VAL, worst_face = -HUGE_VAL;
  for (int k = 0; k < 8; ++k)
    for (Integrator integ : {Integrator::implicit_euler, Integrator::symplectic_euler}) {
      const Real dt = k % 2 ? 1.0 / 30 : 1.0 / 240;
      SCOPED_TRACE("trial " + std::to_string(k) + " " + to_string(integ) + " dt " + std::to_string(dt));
      State s = make_state(m);
      fix_nodes(m, s, m.set("fixed"));
      const Real w = w_min + w_span * u(rng);
      const Vec3 tip{0.01 + 0.008 * u(rng), -0.002, 0.01 + 0.008 * u(rng)};
      auto ob = std::make_shared<Obstacles>();
      {
        ObstacleMesh rod = test::box_mesh({tip.x - w / 2, tip.y - 0.02, tip.z - w / 2}, {tip.x + w / 2, tip.y, tip.z + w / 2});
        rod.friction = 0.8 * u(rng);
        rod.pivot = tip;
        add_obstacle_mesh(*ob, std::move(rod));
        sample_obstacle_edges(ob->meshes[0], spacing);
      }
      s.obstacles = ob;
      const Real rise = 0.003 + 0.004 * u(rng);        // 1-5 mm into the skin
      const Real t_up = rise / (0.05 + 1.35 * u(rng));  // at 0.05 .. 1.4 m/s
      const Real drag = (u(rng) - 0.5) * 0.006, turn = (u(rng) - 0.5) * 0.3;
      const Path path = press_drag_turn(t_up, {0, rise, 0}, {drag, rise, 0}, turn);
      s.obstacle_paths = {path};
      SolverOptions o = collider_stress_options(integ);
      o.preconditioner = pc;
      bool finite = true;
      Real behind = -HUGE_VAL, behind_face = -HUGE_VAL;
      std::vector<Real> points(ob->meshes[0].samples.size());
      for (Real t = 0; t < t_up + 0.2; t += dt) {
        step(m, s, dt, o);
        const Vec3 d = path.at(s.time);
        const Rot3 r = path_rotation(path, s.time);
        for (std::size_t j = 0; 3 * j < points.size(); ++j) {
          const Vec3 p = r(load3(ob->meshes[0].samples.data(), static_cast<std::int64_t>(j)) - tip) + tip + d;
          points[3 * j] = p.x, points[3 * j + 1] = p.y, points[3 * j + 2] = p.z;
        }
        const test::SkinDepth sd = test::depth_behind_skin(points, {}, skin_quads, s.x);
        behind = std::max(behind, sd.behind);
        behind_face = std::max(behind_face, sd.behind_face);
        for (Real xi : s.x) finite = finite && std::isfinite(xi);
      }
      EXPECT_TRUE(finite);
      EXPECT_EQ(s.counters.nonfinite, 0);
      EXPECT_EQ(s.counters.failed, 0);
      EXPECT_LE(behind_face, 1e-6) << "a point of the rod behind a skin face";
      EXPECT_LE(behind, 1e-6) << "a point of the rod inside the skin";
      EXPECT_GT(s.counters.face_contacts, 0) << "the rod met the skin";
      if (integ == Integrator::implicit_euler && pc == Preconditioner::cholesky) {
        EXPECT_GT(s.counters.factorizations, 0) << "the factor preconditioned the solves";
      }
      std::printf("  %s dt %.4f: w %.2f mm, rise %.1f mm at %.2f m/s, behind a face %.3g m, inside %.3g m, %lld face contacts\n",
                  to_string(integ), dt, 1e3 * w, 1e3 * rise, rise / t_up, behind_face, behind, static_cast<long long>(s.counters.face_contacts));
      worst = std::max(worst, behind);
      worst_face = std::max(worst_face, behind_face);
      faces += s.counters.face_contacts;
      ++cases;
    }
  std::printf("%d cases, %ld sample-substeps meeting a face; the deepest behind a face %.3g m, inside the skin %.3g m\n", cases, faces,
              worst_face, worst);
}
TEST(Stress, ThinProbesPressTheSkinWithoutPassingIt) { probe_trials(0.0005, 0.0015); }

// The same trials with probes 4-12 mm wide, wider than the node spacing: the
// rows of the implicit solve's faces meet many samples at once. Until
// 2026-11-29 (2) a 5.6 mm probe pressed 5 mm at 0.3 m/s in 1/30 s steps failed
// 5 steps here: hundreds of candidate rows came up in one step, samples that
// had not touched the skin yet, and about 60 of them were taken against one
// another (impulses of 10^3-10^4 N s); now only samples on the surface are
// candidates.
TEST(Stress, WideProbesPressTheSkinWithoutPassingIt) { probe_trials(0.004, 0.008); }

// The wide probes' trials with the sparse factor as the implicit solve's
// preconditioner: it preconditions the faces' rows too (by Woodbury, since
// 2026-11-29; before, a solve with rows fell back to block Jacobi).
TEST(Stress, WideProbesOnTheSparseFactor) { probe_trials(0.004, 0.008, Preconditioner::cholesky); }
}  // namespace
}  // namespace orthosim::runtime::testing
