#include "runtime/testing/stress.h"

#include "runtime/testing/lattice.h"

#include <chrono>
#include <cmath>

namespace orthosim::runtime::testing {

const char* to_string(Degenerate d) {
  switch (d) {
    case Degenerate::none: return "none";
    case Degenerate::zero: return "zero";
    case Degenerate::near_zero: return "near_zero";
  }
  return "?";
}

const char* to_string(StressMode m) {
  switch (m) {
    case StressMode::symplectic_auto: return "symplectic (auto substeps)";
    case StressMode::symplectic_fixed: return "symplectic (1 substep)";
    case StressMode::implicit: return "implicit";
  }
  return "?";
}

std::string StressResult::verdict() const {
  if (counters.failed > 0) return "failed";
  if (counters.events > 0) return "recovered";
  return "stable";
}

namespace {

Model stress_model(const StressCase& c, const StressSize& size) {
  LayeredBlockOptions o;
  o.nu = size.nu, o.nv = size.nv, o.layers = size.layers;
  o.spacing_u = o.spacing_v = 1e-2;
  const auto nc = static_cast<std::size_t>(size.layers - 1);
  o.thickness.assign(nc, 1e-2);
  o.youngs.assign(nc, 10e3);
  o.youngs2 = o.youngs;
  o.turning_strain.assign(nc, 0);
  o.youngs2[0] = c.stiffness_ratio * o.youngs[0];
  o.turning_strain[0] = 0.02;
  o.density.assign(nc, 1000);
  o.names.clear();
  // (appended, not "l" + std::to_string(s): GCC 12 warns -Wrestrict on that
  // operator+, a false positive, GCC bug 105329)
  for (int s = 0; s < size.layers; ++s) o.names.push_back(std::string("l").append(std::to_string(s)));
  o.damping_ratio = 0.02;
  const LayeredBlock b = make_layered_block(o);

  // flatten, then edit masses and add degenerate springs
  ModelSource src;
  src.layers = b.layers;
  src.node_sets = b.sets;
  Model m = assemble_model(src);
  const Real root = std::sqrt(c.mass_ratio);
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    const int parity = (i % size.nu + (i / size.nu) % size.nv + i / (size.nu * size.nv)) % 2;
    m.mass[i] *= parity ? root : 1 / root;
  }
  if (c.degenerate != Degenerate::none) {
    const Real rest = c.degenerate == Degenerate::zero ? 0 : 1e-9;
    const auto skin = m.set("skin");
    Real kmax = 0;
    for (Real k : m.spring_k) kmax = std::max(kmax, k);
    for (std::size_t j = 0; j < skin.size(); ++j) {
      const std::int32_t i = skin[j];
      const std::int32_t twin = m.n_nodes++;
      for (int k = 0; k < 3; ++k) m.rest_x.push_back(m.rest_x[3 * static_cast<std::size_t>(i) + k]);
      m.mass.push_back(m.mass[i]);
      m.file_id.push_back(-1);
      m.node_layer.push_back(0);
      auto add = [&](std::int32_t a, std::int32_t bb, Real r) {
        m.spring_a.push_back(a);
        m.spring_b.push_back(bb);
        m.spring_rest.push_back(r);
        m.spring_k.push_back(kmax);
        m.spring_c.push_back(0);
        m.spring_tension.push_back(0);
        ++m.n_springs;
      };
      add(i, twin, rest);
      add(twin, skin[(j + 1) % skin.size()], 0);
    }
  }
  m.inv_mass.clear();
  m.omega2.clear();
  m.gamma.clear();
  m.shortest_spring.clear();
  m.finalize();
  return m;
}

}  // namespace

StressResult run_stress_case(const StressCase& c, const StressSize& size) {
  const auto t0 = std::chrono::steady_clock::now();
  const Model m = stress_model(c, size);
  State s = make_state(m);
  fix_nodes(m, s, m.set("fixed"));
  // pull the middle of the skin outward (-y) by half the skin thickness x 3
  Attachment a;
  const auto& skin = m.set("skin");
  const std::int32_t mid = skin[skin.size() / 2];
  a.nodes = {mid};
  a.offset = {0, 0, 0};
  const Real T = c.dt * size.steps;
  a.path.t = {0, T / 2};
  const Vec3 p = load3(m.rest_x.data(), mid);
  a.path.p = {p.x, p.y, p.z, p.x, p.y - 0.03, p.z};
  attach(m, s, a);

  SolverOptions o;
  o.mass_damping = 0;
  o.max_substeps = size.max_substeps;
  o.cg_max_iterations = 200;
  o.cg_tolerance = 1e-6;
  switch (c.mode) {
    case StressMode::symplectic_auto: o.integrator = Integrator::symplectic_euler; break;
    case StressMode::symplectic_fixed:
      o.integrator = Integrator::symplectic_euler;
      o.substeps = 1;
      break;
    case StressMode::implicit: o.integrator = Integrator::implicit_euler; break;
  }
  StressResult r;
  r.extent = m.extent;
  for (int k = 0; k < size.steps; ++k) {
    step(m, s, c.dt, o);
    for (std::size_t i = 0; i < s.x.size(); ++i)
      if (!std::isfinite(s.x[i]) || !std::isfinite(s.v[i])) r.nan_seen = true;
    for (std::int32_t i = 0; i < m.n_nodes; ++i) {
      const Real d = norm(load3(s.x.data(), i) - load3(m.rest_x.data(), i));
      if (std::isfinite(d)) r.max_displacement = std::max(r.max_displacement, d);
    }
  }
  r.bounded = r.max_displacement <= 10 * m.extent;
  r.counters = s.counters;
  r.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return r;
}

}  // namespace orthosim::runtime::testing
