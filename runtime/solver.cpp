#include "runtime/solver.h"

#include "runtime/kernels.h"
#include "runtime/obstacles.h"

#include <Eigen/Cholesky>
#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <cstring>

namespace orthosim::runtime {

const char* to_string(Integrator i) { return i == Integrator::implicit_euler ? "implicit" : "symplectic"; }
const char* to_string(Preconditioner p) {
  switch (p) {
    case Preconditioner::jacobi: return "jacobi";
    case Preconditioner::block_jacobi: return "block_jacobi";
    case Preconditioner::cholesky: return "cholesky";
    case Preconditioner::automatic: return "auto";
  }
  return "?";
}
bool parse_preconditioner(std::string_view s, Preconditioner& p) {
  for (const Preconditioner q : {Preconditioner::automatic, Preconditioner::cholesky, Preconditioner::block_jacobi,
                                 Preconditioner::jacobi})
    if (s == to_string(q)) {
      p = q;
      return true;
    }
  return false;
}

// The cholesky preconditioner: an LDL^T factor (Eigen's SimplicialLDLT, AMD
// ordering) of the implicit matrix M + h C + h^2 K on the free nodes, the
// volume term by its Gauss-Newton blocks, as assembled at the substep that
// built it, with the nodes then held on obstacles held (build_factor).
// Immutable: a State's copies share it.
struct SparseFactor {
  std::int32_t n_nodes = 0, n_springs = 0, n_tets = 0;
  std::size_t n_entries = 0;
  std::vector<std::int32_t> free_of;  // node -> its free index (dofs 3f .. 3f+2), -1 where pinned
  std::int32_t n_free = 0;
  std::vector<int> outer, inner;  // the lower triangle's pattern (column-major)
  // the fill-reducing ordering (AMD) of that pattern, kept while it holds:
  // the factor is of P A P^T
  Eigen::PermutationMatrix<Eigen::Dynamic, Eigen::Dynamic, int> perm, perm_inv;
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>, Eigen::Lower, Eigen::NaturalOrdering<int>> ldlt;
  bool ok = false;  // factorised and positive definite
};

void validate(const SolverOptions& o) {
  for (Real g : o.gravity)
    if (!std::isfinite(g)) throw Error("", "gravity must be finite");
  if (!(std::isfinite(o.mass_damping) && o.mass_damping >= 0)) throw Error("", "mass damping must be finite and >= 0");
  if (o.substeps < 0) throw Error("", "substeps must be >= 0 (0 = automatic)");
  if (!(o.safety > 0 && o.safety <= 1)) throw Error("", "safety must be in (0, 1]");
  if (o.max_substeps < 1) throw Error("", "max_substeps must be >= 1");
  if (o.max_retries < 0 || o.max_retries > 30) throw Error("", "max_retries must be in [0, 30]");
  if (!(std::isfinite(o.energy_growth) && o.energy_growth > 1)) throw Error("", "energy_growth must be > 1");
  if (!(std::isfinite(o.cg_tolerance) && o.cg_tolerance > 0 && o.cg_tolerance < 1))
    throw Error("", "cg_tolerance must be in (0, 1)");
  if (o.cg_max_iterations < 1) throw Error("", "cg_max_iterations must be >= 1");
  if (o.refactor_after < 1) throw Error("", "refactor_after must be >= 1");
  if (!(std::isfinite(o.friction_creep_speed) && o.friction_creep_speed > 0))
    throw Error("", "friction_creep_speed must be finite and > 0");
}

namespace {

constexpr int kPad = 8;  // partial sums per chunk, one cache line apart

// body(c) for each of nc work chunks, in parallel (TBB, the caller's arena)
template <class F>
void for_each_chunk(int nc, F&& body) {
  if (nc <= 1) {
    if (nc == 1) body(0);
    return;
  }
  tbb::parallel_for(tbb::blocked_range<int>(0, nc, 1), [&](const tbb::blocked_range<int>& r) {
    for (int c = r.begin(); c != r.end(); ++c) body(c);
  });
}
// the node chunks, and the volume term's chunks of tetrahedra
template <class F>
void for_chunks(const Model& m, F&& body) {
  for_each_chunk(m.n_chunks, body);
}
template <class F>
void for_tet_chunks(const Model& m, F&& body) {
  for_each_chunk(m.n_tet_chunks, body);
}

inline std::int32_t chunk_begin(const Model& m, int c) { return c * m.chunk; }
inline std::int32_t chunk_end(const Model& m, int c) { return std::min(m.n_nodes, (c + 1) * m.chunk); }

Real partial_sum(const Model& m, const Scratch& sc, int k) {
  Real s = 0;
  for (int c = 0; c < m.n_chunks; ++c) s += sc.partial[static_cast<std::size_t>(c * kPad + k)];
  return s;
}
Real partial_max(const Model& m, const Scratch& sc, int k) {
  Real s = 0;
  for (int c = 0; c < m.n_chunks; ++c) s = std::max(s, sc.partial[static_cast<std::size_t>(c * kPad + k)]);
  return s;
}

void ensure_scratch(const Model& m, State& s, bool implicit) {
  Scratch& sc = s.scratch;
  const auto n3 = 3 * static_cast<std::size_t>(m.n_nodes);
  const auto ns = static_cast<std::size_t>(m.n_springs);
  if (sc.fs.size() != 3 * ns) sc.fs.assign(3 * ns, 0);
  if (sc.partial.size() != static_cast<std::size_t>(m.n_chunks * kPad)) sc.partial.assign(static_cast<std::size_t>(m.n_chunks * kPad), 0);
  if (sc.x0.size() != n3) sc.x0.assign(n3, 0);
  if (sc.v0.size() != n3) sc.v0.assign(n3, 0);
  if (sc.attach_k.size() != n3 / 3) sc.attach_k.assign(n3 / 3, 0);
  if (s.f.size() != n3) s.f.assign(n3, 0);
  if (s.warm.size() != n3) s.warm.assign(n3, 0);
  const auto nt = static_cast<std::size_t>(m.n_tets);
  if (sc.tet_g.size() != 12 * nt) sc.tet_g.assign(12 * nt, 0);
  for (auto* v : {&sc.tet_p, &sc.tet_c, &sc.tet_s})
    if (v->size() != nt) v->assign(nt, 0);
  if (sc.guard_acts.size() != n3 / 3) sc.guard_acts.assign(n3 / 3, 0);
  if (sc.tet_partial.size() != static_cast<std::size_t>(m.n_tet_chunks)) sc.tet_partial.assign(static_cast<std::size_t>(m.n_tet_chunks), 0);
  if (s.obstacles) {
    if (s.contact_obstacle.size() != n3 / 3) s.contact_obstacle.assign(n3 / 3, -1);
    if (s.contact_force.size() != n3) s.contact_force.assign(n3, 0);
    const auto nf = 3 * static_cast<std::size_t>(obstacle_count(*s.obstacles));
    if (s.face_force.size() != nf) s.face_force.assign(nf, 0);
    std::size_t samples = 0;
    for (const ObstacleMesh& om : s.obstacles->meshes) samples += om.samples.size() / 3;
    if (s.face_met.size() != samples) s.face_met.assign(samples, 0);
    if (implicit && sc.friction_c.size() != n3 / 3) sc.friction_c.assign(n3 / 3, 0);
    if (implicit && sc.friction_f.size() != n3) sc.friction_f.assign(n3, 0);
    if (implicit && sc.constraint.size() != n3) sc.constraint.assign(n3, 0);
  }
  sc.constrained = false;
  if (implicit) {
    const auto ne = m.nbr.size();
    if (sc.offdiag.size() != 6 * ne) sc.offdiag.assign(6 * ne, 0);
    if (sc.diag.size() != 2 * n3) sc.diag.assign(2 * n3, 0);
    if (sc.precond.size() != 2 * n3) sc.precond.assign(2 * n3, 0);
    if (sc.attach_f.size() != n3) sc.attach_f.assign(n3, 0);
    if (sc.spring_block.size() != 6 * ns) sc.spring_block.assign(6 * ns, 0);
    if (sc.force_sq.size() != n3 / 3) sc.force_sq.assign(n3 / 3, 0);
    for (auto* v : {&sc.rhs, &sc.r, &sc.z, &sc.p, &sc.p_next, &sc.q, &sc.vnew})
      if (v->size() != n3) v->assign(n3, 0);
  }
}

// What the stability check compares against during one step.
struct Budget {
  Real ke0 = 0;      // J, kinetic energy at the step's start
  Real u0 = -1;      // J, elastic energy at the step's start (-1: not yet known)
  Real scale = 0;    // J, bound of the work of gravity, external forces and tools
  Real w_tool = 0;   // J, work done by kinematic attachments so far in this attempt
};

struct Check {
  Real ke = 0, u = 0, vmax2 = 0;
  Real contacts = 0;  // nodes that touched an obstacle in the substep
  Real faces = 0;     // mesh edge samples that met a tissue face in the substep
};

enum class Verdict { ok, nonfinite, blowup };

Verdict judge(const Model& m, const Check& c, const Budget& b, Real h, const SolverOptions& o) {
  if (!std::isfinite(c.ke) || !std::isfinite(c.u) || !std::isfinite(c.vmax2)) return Verdict::nonfinite;
  if (c.ke > o.energy_growth * (b.ke0 + std::max<Real>(b.u0, 0) + b.scale + std::max<Real>(b.w_tool, 0)))
    return Verdict::blowup;
  if (m.extent > 0 && c.vmax2 * h * h > m.extent * m.extent) return Verdict::blowup;
  return Verdict::ok;
}

// ---- shared passes ---------------------------------------------------------

// Spring attachments: adds k (target(t) - x) to f of each attached node.
void attachment_forces(State& s, Real t) {
  for (const auto& a : s.attachments) {
    if (a.stiffness == 0 || a.nodes.empty()) continue;
    const Vec3 p = a.path.at(t);
    for (std::size_t j = 0; j < a.nodes.size(); ++j) {
      const auto i = a.nodes[j];
      if (s.inv_mass[i] == 0) continue;
      const Vec3 target = p + load3(a.offset.data(), static_cast<std::int64_t>(j));
      store3(s.f.data(), i, load3(s.f.data(), i) + a.stiffness * (target - load3(s.x.data(), i)));
    }
  }
}

// Kinematic attachments: moves their nodes to target(t1) with the matching
// velocity; returns the work done on the tissue (J) against the forces in s.f.
Real move_kinematic(State& s, Real t1, Real h) {
  Real work = 0;
  for (const auto& a : s.attachments) {
    if (a.stiffness != 0 || a.nodes.empty()) continue;
    const Vec3 p = a.path.at(t1);
    for (std::size_t j = 0; j < a.nodes.size(); ++j) {
      const auto i = a.nodes[j];
      if (s.pin[i] != Pin::kinematic) continue;
      const Vec3 target = p + load3(a.offset.data(), static_cast<std::int64_t>(j));
      const Vec3 dx = target - load3(s.x.data(), i);
      work -= dot(load3(s.f.data(), i), dx);
      store3(s.v.data(), i, (1 / h) * dx);
      store3(s.x.data(), i, target);
    }
  }
  return work;
}

// The obstacles' motion over the substep [t, t + h] (State::obstacle_paths),
// held in the scratch; empty (at rest) when no obstacle has a path.
ObstacleMotion obstacle_motion(State& s, Real t, Real h) {
  if (!s.obstacles) return {};
  obstacle_frames(*s.obstacles, s.obstacle_paths, t, h, s.scratch.obstacle_frames);
  return {s.scratch.obstacle_frames};
}

// The meshes' edges against the tissue's faces (resolve_face_contacts) over
// the substep: changes v (the substep's velocities, x + h v its end), sets
// State::face_force and adds the moving meshes' work to *tool_work. Returns
// the meetings (0 without edge samples or quads).
// With rows (the implicit solve's), the meetings, touches and candidates it
// finds go to Scratch::face_rows_new (FaceRow), the next substep's rows.
Real face_pass(const Model& m, State& s, const ObstacleMotion& mo, std::span<Real> v, Real h, Real* tool_work,
               bool rows = false) {
  if (!s.obstacles || m.n_quads == 0 || !has_edge_samples(*s.obstacles)) return 0;
  std::fill(s.face_force.begin(), s.face_force.end(), 0);
  const FaceContacts c = resolve_face_contacts(*s.obstacles, mo, m.quads, s.x, v, s.inv_mass, h, s.face_force, s.scratch.faces,
                                               rows ? &s.scratch.face_rows_new : nullptr, s.face_met);
  for (Real& f : s.face_force) f /= h;  // the impulses over the substep: forces
  *tool_work += c.work;
  return static_cast<Real>(c.contacts);
}

// ---- the volume term ------------------------------------------------------

// Per group of tetrahedra at the current positions: each tetrahedron's
// corners' dV/dx (tet_g), the group's pressure k (V - V0)/|V0| (tet_p of each
// of its tetrahedra) and h2 k/|V0| (tet_c, for the implicit matrix); returns
// the energy sum (k/2)(V - V0)^2/|V0|, added per chunk of groups in chunk
// order (the same for any thread count). An inversion guard's group (guard
// ratio a > 0) has s V - a |V0| (s the sign of V0) in place of V - V0 where
// that is negative, and neither pressure nor stiffness above it.
Real tet_pass(const Model& m, State& s, Real h2) {
  if (m.n_tets == 0) return 0;
  Scratch& sc = s.scratch;
  const Real* x = s.x.data();
  Real* tg = sc.tet_g.data();
  for_tet_chunks(m, [&](int ch) {
    Real u = 0;
    for (std::int32_t g = ch * m.tet_chunk, ge = std::min(m.n_groups, (ch + 1) * m.tet_chunk); g < ge; ++g) {
      const std::int32_t t0 = m.tet_group_first[g], t1 = m.tet_group_first[g + 1];
      Real V = 0;
      for (std::int32_t t = t0; t < t1; ++t) {
        const std::int32_t* c = &m.tet[4 * static_cast<std::size_t>(t)];
        const TetGradient G = tet_gradient(load3(x, c[0]), load3(x, c[1]), load3(x, c[2]), load3(x, c[3]));
        for (int j = 0; j < 4; ++j) store3(tg, 4 * static_cast<std::int64_t>(t) + j, G.g[j]);
        V += G.volume;
      }
      const Real v0 = m.group_rest_volume[static_cast<std::size_t>(g)], k = m.tet_k[t0], av0 = std::abs(v0);
      // a guard: sgn V below a |V0|, sgn the sign of V0 (a tetrahedron at rest is either way round)
      const Real a = m.tet_guard[t0], sgn = v0 > 0 ? 1 : -1;
      const Real strain = a > 0 ? sgn * std::min<Real>(0, (sgn * V - a * av0) / av0) : (V - v0) / av0;
      const Real c = a > 0 && strain == 0 ? 0 : h2 * k / av0;
      for (std::int32_t t = t0; t < t1; ++t) {
        sc.tet_p[t] = k * strain;
        sc.tet_c[t] = c;
        if (c == 0) sc.tet_s[t] = 0;  // the PCG product leaves such groups out
      }
      u += Real(0.5) * k * av0 * strain * strain;
    }
    sc.tet_partial[static_cast<std::size_t>(ch)] = u;
  });
  Real u = 0;
  for (Real p : sc.tet_partial) u += p;
  return u;
}

// The volume term's force on node i, -sum over its corners of p_t g_tc, and
// (implicit) the Gauss-Newton diagonal block, the sum over its groups of
// tet_c G G^T with G the node's summed corner gradients in the group, and
// sum |f|^2 per group. A node's corners are the volume terms' then the
// guards', each in ascending tetrahedron order, so each group's come
// together. A guard that does not act (p = 0, and c = 0) adds nothing and is
// skipped; guard_acts says whether any of the node's acts.
struct TetNodeTerms {
  Vec3 f;
  Sym3 block;
  Real f2 = 0;
  bool guard_acts = false;
};
template <bool kImplicit>
TetNodeTerms tet_node_terms(const Model& m, const Scratch& sc, std::int32_t i) {
  TetNodeTerms out;
  Vec3 G{};
  std::int32_t group = -1, last_t = -1;
  auto flush = [&] {
    if (group < 0) return;
    const Vec3 f = -sc.tet_p[last_t] * G;
    out.f += f;
    if constexpr (kImplicit) {
      out.f2 += dot(f, f);
      out.block += outer(sc.tet_c[last_t], G);
    }
  };
  for (std::int32_t q = m.tet_first[i], qg = m.tet_guard_begin[i], qe = m.tet_first[i + 1]; q < qe; ++q) {
    const std::int32_t e = m.tet_corner[static_cast<std::size_t>(q)], t = e >> 2;
    if (q >= qg) {
      if (sc.tet_p[t] == 0) continue;
      out.guard_acts = true;
    }
    if (m.tet_group[t] != group) {
      flush();
      group = m.tet_group[t];
      G = Vec3{};
    }
    G += load3(sc.tet_g.data(), e);
    last_t = t;
  }
  flush();
  return out;
}

// ---- symplectic Euler ------------------------------------------------------

// pass 1 of symplectic Euler: forces of the springs each node is the first
// end of, stored per spring for the gather; elastic energy when kEnergy
template <bool kEnergy>
void symplectic_spring_pass(const Model& m, State& s) {
  Scratch& sc = s.scratch;
  const Real* x = s.x.data();
  const Real* v = s.v.data();
  Real* f = s.f.data();
  Real* fs = sc.fs.data();
  const std::int32_t* a_first = m.a_first.data();
  const std::int32_t* sb = m.spring_b.data();
  const Real* rest = m.spring_rest.data();
  const Real* k = m.spring_k.data();
  const Real* c = m.spring_c.data();
  const std::uint8_t* ten = m.spring_tension.data();
  Real* partial = sc.partial.data();
  for_chunks(m, [&](int ch) {
    Real u = 0;
    for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
      const Vec3 xi = load3(x, i), vi = load3(v, i);
      Vec3 fi{};
      std::int32_t prev_b = -1;
      SpringGeometry geo{};
      for (std::int32_t q = a_first[i], qe = a_first[i + 1]; q < qe; ++q) {
        const std::int32_t b = sb[q];
        if (b != prev_b) {  // springs are sorted by (a, b): a biphasic pair shares its geometry
          geo = spring_geometry(load3(x, b) - xi, load3(v, b) - vi);
          prev_b = b;
        }
        const Vec3 fq = spring_force(geo, rest[q], k[q], c[q], ten[q] != 0);
        store3(fs, q, fq);
        fi += fq;
        if constexpr (kEnergy) {
          const Real stretch = geo.len - rest[q];
          u += static_cast<Real>(!ten[q] | (stretch >= 0)) * Real(0.5) * k[q] * stretch * stretch;
        }
      }
      store3(f, i, fi);
    }
    partial[ch * kPad] = u;
  });
}

Check symplectic_substep(const Model& m, State& s, Real t, Real h, const SolverOptions& o, Real* tool_work,
                         bool energy) {
  Scratch& sc = s.scratch;
  const Real* fs = sc.fs.data();
  Real* f = s.f.data();
  Real* partial = sc.partial.data();
  if (energy) symplectic_spring_pass<true>(m, s);
  else symplectic_spring_pass<false>(m, s);
  const Real u_tets = tet_pass(m, s, 0);
  attachment_forces(s, t);

  // pass 2: gather second ends, external forces, integrate free nodes
  Real* xw = s.x.data();
  Real* vw = s.v.data();
  const Real* fext = s.f_ext.data();
  const Real* w = s.inv_mass.data();
  const Real* mass = m.mass.data();
  const std::int32_t* b_first = m.b_first.data();
  const std::int32_t* b_spring = m.b_spring.data();
  const Vec3 g{o.gravity[0], o.gravity[1], o.gravity[2]};
  const Real alpha = o.mass_damping;
  const bool has_tets = m.n_tets > 0;
  const Obstacles* obs = s.obstacles && !s.obstacles->empty() ? s.obstacles.get() : nullptr;
  const ObstacleMotion mo = obs ? obstacle_motion(s, t, h) : ObstacleMotion{};
  // the meshes' edges against the tissue's faces: after every node's new
  // velocity and before the nodes' contacts, in a second pass
  const bool faces = obs && m.n_quads > 0 && has_edge_samples(*obs);
  struct Sums {
    Real ke = 0, vmax2 = 0, contacts = 0, work = 0;
  };
  // a free node's move with its new velocity: its contacts, and the sums
  auto finish = [&](std::int32_t i, Vec3 vi, Sums& sum) {
    const Vec3 x0i = load3(xw, i);
    Vec3 xi = x0i + h * vi;
    if (obs) {
      const Vec3 v_before = vi;
      const std::int32_t k = resolve_obstacle_contact(*obs, x0i, xi, vi, h, mo).obstacle;
      s.contact_obstacle[static_cast<std::size_t>(i)] = k;
      const Vec3 fc = k >= 0 ? (mass[i] / h) * (vi - v_before) : Vec3{};
      store3(s.contact_force.data(), i, fc);
      sum.contacts += k >= 0;
      if (mo.moving()) sum.work += h * dot(fc, mo.velocity(k, xi, 1, h));  // a moving obstacle's work on the node
    }
    store3(vw, i, vi);
    store3(xw, i, xi);
    const Real v2 = dot(vi, vi);
    sum.ke += mass[i] * v2;
    sum.vmax2 = std::max(sum.vmax2, v2);
  };
  auto store_sums = [&](int ch, const Sums& sum) {
    partial[ch * kPad + 1] = Real(0.5) * sum.ke;
    partial[ch * kPad + 2] = sum.vmax2;
    partial[ch * kPad + 4] = sum.contacts;
    partial[ch * kPad + 5] = sum.work;
  };
  for_chunks(m, [&](int ch) {
    Sums sum;
    for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
      Vec3 fi = load3(f, i) + load3(fext, i);
      for (std::int32_t q = b_first[i], qe = b_first[i + 1]; q < qe; ++q) fi -= load3(fs, b_spring[q]);
      if (has_tets) fi += tet_node_terms<false>(m, sc, i).f;
      store3(f, i, fi);
      const Real wi = w[i];
      if (wi > 0) {
        Vec3 vi = load3(vw, i);
        vi += h * (wi * fi + g - alpha * vi);
        if (faces) store3(vw, i, vi);
        else finish(i, vi, sum);
      }
    }
    store_sums(ch, sum);
  });
  Real face_meetings = 0;
  if (faces) {
    face_meetings = face_pass(m, s, mo, s.v, h, tool_work);
    for_chunks(m, [&](int ch) {
      Sums sum;
      for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i)
        if (w[i] > 0) finish(i, load3(vw, i), sum);
      store_sums(ch, sum);
    });
  }
  if (mo.moving()) *tool_work += partial_sum(m, sc, 5);
  *tool_work += move_kinematic(s, t + h, h);
  return {partial_sum(m, sc, 1), energy ? partial_sum(m, sc, 0) + u_tets : Real(0), partial_max(m, sc, 2),
          obs ? partial_sum(m, sc, 4) : Real(0), face_meetings};
}

// ---- implicit Euler --------------------------------------------------------

inline Sym3 sym_at(const Real* a, std::int64_t k) {
  const Real* b = a + 6 * k;
  return {b[0], b[1], b[2], b[3], b[4], b[5]};
}
inline void sym_store(Real* a, std::int64_t k, const Sym3& s) {
  Real* b = a + 6 * k;
  b[0] = s.xx, b[1] = s.yy, b[2] = s.zz, b[3] = s.xy, b[4] = s.xz, b[5] = s.yz;
}
inline void sym_add(Real* a, std::int64_t k, const Sym3& s) {
  Real* b = a + 6 * k;
  b[0] += s.xx, b[1] += s.yy, b[2] += s.zz, b[3] += s.xy, b[4] += s.xz, b[5] += s.yz;
}

// A contact constraint's filter I - n n^T (Baraff & Witkin 1998, 5.3): the
// part of a node's vector along the obstacle's surface (n unit, or zero for
// no constraint: a unchanged).
inline Vec3 filter(const Vec3& a, const Vec3& n) { return a - dot(a, n) * n; }
// Whether a hold's normal n (Scratch::constraint) holds its node (zero: no hold).
inline bool holds(const Vec3& n) { return n.x != 0 || n.y != 0 || n.z != 0; }

// ---- the faces' rows in the implicit solve ---------------------------------
//
// Each FaceRow of the last substep (a mesh's edge sample that met or touched
// a tissue face, or a candidate in front of one) is one constraint row on
// the solve's velocities. Its point is the triangle's (at the substep's
// start) under the sample where the mesh puts it at the substep's end,
// clamped to the triangle; to first order the sample's distance to the face
// changes with that point's velocity along the face's normal n (into the
// tissue), sum_j w_j v_j . n = J v, and the row asks J v >= c = (standoff -
// gap) / h, gap the sample's distance in front of the point were the face to
// stay: the face does not pass the sample over the substep. A row whose
// sample has left its triangle (not within its extent, nor in the wedge behind
// its edge) or was behind it at the start (inside the tissue) is not made.
// The solve holds J v = c as a stiff compliant constraint: the energy it
// minimises gains (J v - c)^2 / (2 eps), the row's impulse on the face is
// lambda = (c - J v) / eps, eps = kappa (J Q J^T)_rr (kappa = kFaceCompliance;
// Q the block-Jacobi inverse, filtered where a node is held): the row gives
// way by kappa of the velocity change its impulse would make on its own (the
// face pass after the solve mends it where it would leave the face past the
// sample; else the next substep's row asks it back, the gap being less than
// the standoff), and rows that say the same (more samples on a face than it
// has corners) stay solvable. (The forces hardly
// depend on kappa: the benchmark rod's within 1.4e-4 for kappa 1e-8 .. 1e-2,
// its PCG iterations a solve 66, 55, 47, 42 for 1e-8, 1e-6, 1e-4, 1e-2:
// docs/BENCHMARKS.md.) The preconditioner is the inverse of (Q^-1 + J^T J /
// eps), by Woodbury: Q - Q J^T S^-1 J Q, S = eps + J Q J^T (a sparse LDL^T,
// rows x rows, once a solve), so the stiff rows cost no more iterations than
// the tissue; with the sparse factor F (the cholesky preconditioner) the same
// with G = F^-1 between the holds' filters in place of Q (G J^T a factor solve
// per row, once a substep; S dense). Rows push, never pull: an active set. Rows that met or touched
// start active, as do candidates (samples on the surface in front of another
// face within its motion: resolve_face_contacts) that pushed in the last substep; after a
// solve, an active row that pulls is let go, a candidate whose face the solve
// passes its sample with is taken, and a row whose impulse outgrows
// kFaceConflict times the step's momentum terms and its own need is dropped
// (it is held against rows it cannot meet together), and the solve is run
// again from there, kFaceActiveSetPasses solves at most
// (Counters::face_resolves). A row's friction is a damper on its corners (c
// w_j (I - n n^T) each, c = mu N / max(|v_t|, friction_creep_speed), N its
// normal impulse of the last substep over h), or Coulomb's force when the
// point slides too fast for one substep's friction to stop it, as a held
// node's.
constexpr Real kFaceCompliance = 1e-4;
constexpr int kFaceActiveSetPasses = 4;
constexpr Real kFaceConflict = 1e3;

struct FaceSolve {
  struct Row {
    std::int32_t src = -1;       // its FaceRow (State::face_rows)
    std::int32_t obstacle = -1;  // the mesh
    std::int32_t node[3]{};      // the triangle's corners
    Real wa[3]{};                // the point's weights (barycentric, clamped to the triangle)
    Real w[3]{};                 // the weights of its free corners (0 at a fixed one)
    Real gap = 0;                // m, how far the sample is in front of the point at the substep's end, were the face to stay
    Real standoff = 0;           // m, obstacle_standoff there
    bool candidate = false;      // FaceRow::candidate: starts inactive (unless below)
    bool pushed = false;         // its impulse in the last substep was > 0
    Real d = 0;                  // kg^-1, (J Q J^T)_rr: its velocity change per unit impulse, alone
    Real need = 0;               // m/s, |c - J v| at the substep's start velocities: what it asks of the face
    bool usable = false;         // can hold (some free corner, finite)
    Vec3 n{};                    // unit, into the tissue
    Vec3 u{};                    // m/s, the mesh's velocity at the sample at the substep's start
    Real c = 0;                  // m/s: J v >= c
    Real eps = 0;                // 1/kg, the compliance
    Real lambda = 0;             // N s, its impulse on the face along n
    Vec3 force{};                // N, its force on the tissue in the solve (normal and friction)
    Real cf = 0;                 // N s/m, its friction damper
    Vec3 f_slide{};              // N, a sliding point's Coulomb force (else zero)
    bool active = false;
  };
  std::vector<Row> rows;
  std::vector<std::int32_t> nodes;   // the free nodes the rows touch, ascending (Scratch::face_slot: node -> index)
  std::vector<Real> node_D;          // (nodes x 6) the rows' friction dampers h c w_j (I - n n^T)
  std::vector<Real> node_b;          // (nodes x 3) friction's part of b
  std::vector<Real> acc;             // (nodes x 3) J^T y
  std::vector<Real> rhs0;            // (nodes x 3) b without the rows
  std::vector<std::int32_t> index;   // (rows) a row's index among the active ones, -1: inactive
  std::int32_t n_active = 0;
  std::vector<std::int32_t> active;  // (n_active) the active rows, by index
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> S;
  Eigen::VectorXd t, y;
  // With the sparse factor F (the cholesky preconditioner) in place of Q:
  // per row, G J_r^T with G = Pi F^-1 Pi (Pi the held nodes' filter), (n_nodes
  // x 3), made once a substep when the row is first active; S = eps + J G J^T
  // is then dense
  const SparseFactor* F = nullptr;
  std::vector<std::vector<Real>> W;
  Eigen::LDLT<Eigen::MatrixXd> S_dense;
  bool any() const { return n_active > 0; }
};

inline Real row_dot(const FaceSolve::Row& r, const Real* p) {
  Real s = 0;
  for (int j = 0; j < 3; ++j)
    if (r.w[j] != 0) s += r.w[j] * dot(r.n, load3(p, r.node[j]));
  return s;
}

// How apply_matrix reads its vector: p itself, or the PCG direction update
// p_next = z + beta p fused into the read (beta == 0: z alone).
enum class Read { plain, fused_first, fused };

// y = A p on the free nodes (constrained rows zero), one pass over the
// node-neighbour rows: y_i = D_i p_i - sum_j O_ij p_j. The fused modes also
// write p_next for each node. Returns p.y (of p_next when fused).
template <Read kRead>
Real apply_matrix(const Model& m, State& s, const Real* p, const Real* z, Real beta, Real* p_next, Real* y,
                  const FaceSolve* fs = nullptr) {
  Scratch& sc = s.scratch;
  const Real* D = sc.diag.data();
  const Real* O = sc.offdiag.data();
  const std::int32_t* nbr_first = m.nbr_first.data();
  const std::int32_t* nbr = m.nbr.data();
  const Real* w = s.inv_mass.data();
  Real* partial = sc.partial.data();
  const bool constrained = sc.constrained;
  const Real* cn = sc.constraint.data();
  const std::uint8_t* acts = sc.guard_acts.data();
  auto dir = [&](std::int32_t j) {
    if constexpr (kRead == Read::plain) return load3(p, j);
    else if constexpr (kRead == Read::fused_first) return load3(z, j);
    else return load3(z, j) + beta * load3(p, j);
  };
  // the volume term, matrix-free: s = h^2 (k/|V0|) sum over the group's
  // corners of g_c . p_c per group, then y_i += s g_c at each corner (the same
  // direction values as the node pass reads)
  const bool has_tets = m.n_tets > 0;
  if (has_tets) {
    const Real* tg = sc.tet_g.data();
    for_tet_chunks(m, [&](int ch) {
      for (std::int32_t g = ch * m.tet_chunk, ge = std::min(m.n_groups, (ch + 1) * m.tet_chunk); g < ge; ++g) {
        const std::int32_t t0 = m.tet_group_first[g], t1 = m.tet_group_first[g + 1];
        if (sc.tet_c[t0] == 0) continue;  // an inversion guard above its ratio (tet_pass set its tet_s to 0)
        Real gp = 0;
        for (std::int32_t t = t0; t < t1; ++t) {
          const std::int32_t* c = &m.tet[4 * static_cast<std::size_t>(t)];
          for (int j = 0; j < 4; ++j) gp += dot(load3(tg, 4 * static_cast<std::int64_t>(t) + j), dir(c[j]));
        }
        for (std::int32_t t = t0; t < t1; ++t) sc.tet_s[t] = sc.tet_c[t] * gp;  // the group's, at each of its tetrahedra
      }
    });
  }
  for_chunks(m, [&](int ch) {
    Real pq = 0;
    for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
      const Vec3 pi = dir(i);
      if constexpr (kRead != Read::plain) store3(p_next, i, pi);
      if (w[i] == 0) {
        store3(y, i, Vec3{});
        continue;
      }
      Vec3 yi = sym_at(D, i) * pi;
      for (std::int32_t k = nbr_first[i], ke = nbr_first[i + 1]; k < ke; ++k) yi -= sym_at(O, k) * dir(nbr[k]);
      if (has_tets)  // the volume terms' corners, and the guards' where one acts
        for (std::int32_t q = m.tet_first[i], qe = acts[i] ? m.tet_first[i + 1] : m.tet_guard_begin[i]; q < qe; ++q) {
          const std::int32_t e = m.tet_corner[static_cast<std::size_t>(q)];
          yi += sc.tet_s[e >> 2] * load3(sc.tet_g.data(), e);
        }
      if (constrained) yi = filter(yi, load3(cn, i));
      store3(y, i, yi);
      pq += dot(pi, yi);
    }
    partial[ch * kPad + 3] = pq;
  });
  Real pq = partial_sum(m, sc, 3);
  // the faces' rows: J^T (J p) / eps (filtered where a node is held), after
  // the nodes' pass (serial: rows share nodes)
  if (fs && fs->any()) {
    const Real* d = kRead == Read::plain ? p : p_next;
    for (const FaceSolve::Row& r : fs->rows) {
      if (!r.active) continue;
      const Real jp = row_dot(r, d), coef = jp / r.eps;
      for (int j = 0; j < 3; ++j) {
        if (r.w[j] == 0) continue;
        Vec3 a = (coef * r.w[j]) * r.n;
        if (constrained) a = filter(a, load3(cn, r.node[j]));
        store3(y, r.node[j], load3(y, r.node[j]) + a);
      }
      pq += jp * coef;
    }
  }
  return pq;
}

inline Vec3 apply_precond(const Real* P, std::int32_t i, const Vec3& r) { return sym_at(P, i) * r; }

// Q a at node i: the block-Jacobi inverse, between the filters of a held node
inline Vec3 q_apply(const Real* P, const Real* cn, bool constrained, std::int32_t i, Vec3 a) {
  if (!constrained) return apply_precond(P, i, a);
  const Vec3 n = load3(cn, i);
  return filter(apply_precond(P, i, filter(a, n)), n);
}

// The rows of State::face_rows for this substep's solve and their friction
// (FaceSolve::node_D, node_b, for the nodes' pass); the velocities v at the
// substep's start.
void face_rows_begin(const Model& m, State& s, const ObstacleMotion& mo, Real h, const SolverOptions& o, FaceSolve& fs) {
  fs.rows.clear();
  fs.nodes.clear();
  fs.n_active = 0;
  fs.F = nullptr;
  fs.W.clear();
  if (s.face_rows.empty()) return;
  Scratch& sc = s.scratch;
  if (sc.face_slot.size() != static_cast<std::size_t>(m.n_nodes)) sc.face_slot.assign(static_cast<std::size_t>(m.n_nodes), -1);
  const Obstacles& obs = *s.obstacles;
  const auto np = static_cast<std::int32_t>(obs.planes.size());
  // A cut (cut_model) removes quads and renumbers the rest, and the rows name
  // triangles of the quads before it: a row whose triangle no longer has its
  // corners is held if they are still a face, and dropped if the cut removed
  // it (its nodes may lie on the wound's sides; the face pass finds the
  // contact again). The faces' corners, sorted, at the first such row.
  std::vector<std::array<std::int32_t, 3>> faces;
  auto still_a_face = [&](const FaceRow& fr) {
    if (face_row_current(m.quads, fr)) return true;
    if (faces.empty()) {
      const auto nt = static_cast<std::int32_t>(m.quads.size() / 2);
      for (std::int32_t t = 0; t < nt; ++t) faces.push_back(quad_triangle(m.quads, t));
      std::sort(faces.begin(), faces.end());
    }
    return std::binary_search(faces.begin(), faces.end(), fr.node);
  };
  for (std::size_t q = 0; q < s.face_rows.size(); ++q) {
    const FaceRow& fr = s.face_rows[q];
    if (!still_a_face(fr)) continue;
    FaceSolve::Row r;
    r.src = static_cast<std::int32_t>(q);
    r.obstacle = fr.obstacle;
    r.candidate = fr.candidate;
    r.pushed = fr.impulse > 0;
    // the point of the triangle (at the substep's start) under the sample
    // where the mesh puts it at the substep's end, clamped to the triangle:
    // to first order, the face's distance to the sample moves with that
    // point's velocity along the normal
    const ObstacleMesh& mesh = obs.meshes[static_cast<std::size_t>(fr.obstacle - np)];
    const Vec3 ps = load3(mesh.samples.data(), fr.sample);
    const Vec3 p0 = mo.to_world(fr.obstacle, ps, 0), p1 = mo.to_world(fr.obstacle, ps, 1);
    Vec3 y[3];
    for (int j = 0; j < 3; ++j) y[j] = load3(s.x.data(), r.node[j] = fr.node[static_cast<std::size_t>(j)]);
    const Vec3 nrm = cross(y[1] - y[0], y[2] - y[0]);
    const Real n2 = dot(nrm, nrm);
    if (!(n2 > 0)) continue;
    TriangleProjection pr = triangle_projection(p1, y[0], y[1], y[2], nrm, n2);
    r.n = (-1 / std::sqrt(n2)) * nrm;
    // as the face pass meets it: the sample within the triangle's extent,
    // or behind its plane and beyond its edge by no more than that (the
    // wedge); else it has left this face (a neighbour's row may hold it)
    if (!pr.inside) {
      const Real d_end = dot(p1 - y[0], -1 * r.n);  // < 0: behind the plane
      if (!(d_end < 0 && near_edge(p1, y[0], y[1], y[2], d_end))) continue;
    }
    Real* wa = pr.w;
    Real ws = 0;
    for (int j = 0; j < 3; ++j) ws += (wa[j] = std::max<Real>(wa[j], 0));
    if (!(ws > 0)) continue;
    Real winv = 0;  // sum w^2 / m over the free corners: the point's inverse mass
    Vec3 vp{}, xp{};
    for (int j = 0; j < 3; ++j) {
      r.wa[j] = wa[j] / ws;
      const Real im = s.inv_mass[static_cast<std::size_t>(r.node[j])];
      r.w[j] = im > 0 ? r.wa[j] : 0;
      winv += r.w[j] * r.w[j] * im;
      vp += r.wa[j] * load3(s.v.data(), r.node[j]);
      xp += r.wa[j] * y[j];
    }
    if (!(winv > 0)) continue;  // all its corners fixed
    r.gap = dot(xp - p1, r.n);  // the sample in front of the point, were the face to stay
    // the sample in front of the face (or on it) at the substep's start, as
    // the face pass asks of a meeting: one behind it is inside the tissue
    if (!(dot(y[0] - p0, r.n) >= -obstacle_reach(p0))) continue;
    r.standoff = obstacle_standoff(p1);
    r.u = mo.velocity(fr.obstacle, p0, 0, h);
    const Vec3 vt = filter(vp - r.u, r.n);
    const Real mu_n = obstacle_friction_coefficient(obs, fr.obstacle) * std::max<Real>(0, fr.impulse) / h, st = norm(vt);
    if (mu_n > 0) {
      if (mu_n * h * winv < st) r.f_slide = (-mu_n / st) * vt;  // mu N h < m |v_t|: sliding
      else r.cf = mu_n / std::max(st, o.friction_creep_speed);
    }
    for (int j = 0; j < 3; ++j)
      if (r.w[j] != 0) fs.nodes.push_back(r.node[j]);
    fs.rows.push_back(r);
  }
  std::sort(fs.nodes.begin(), fs.nodes.end());
  fs.nodes.erase(std::unique(fs.nodes.begin(), fs.nodes.end()), fs.nodes.end());
  for (std::size_t k = 0; k < fs.nodes.size(); ++k) sc.face_slot[static_cast<std::size_t>(fs.nodes[k])] = static_cast<std::int32_t>(k);
  fs.node_D.assign(6 * fs.nodes.size(), 0);
  fs.node_b.assign(3 * fs.nodes.size(), 0);
  fs.acc.assign(3 * fs.nodes.size(), 0);
  fs.W.resize(fs.rows.size());
  for (const FaceSolve::Row& r : fs.rows)
    for (int j = 0; j < 3; ++j) {
      if (r.w[j] == 0) continue;
      const std::int32_t k = sc.face_slot[static_cast<std::size_t>(r.node[j])];
      Vec3 b = (h * r.w[j]) * r.f_slide;
      if (r.cf > 0) {
        const Real a = h * r.cf * r.w[j];
        sym_add(fs.node_D.data(), k, Sym3{a * (1 - r.n.x * r.n.x), a * (1 - r.n.y * r.n.y), a * (1 - r.n.z * r.n.z),
                                         -a * r.n.x * r.n.y, -a * r.n.x * r.n.z, -a * r.n.y * r.n.z});
        b += a * filter(r.u, r.n);
      }
      store3(fs.node_b.data(), k, load3(fs.node_b.data(), k) + b);
    }
}

void factor_solve(const SparseFactor& f, const Model& m, const Real* r, Real* z);

// With the sparse factor (FaceSolve::F): each active row's G J_r^T, made where
// the substep has not yet, and S = eps + J G J^T, dense.
void face_rows_factor_dense(const Model& m, const State& s, FaceSolve& fs) {
  const Scratch& sc = s.scratch;
  const Real* cn = sc.constraint.data();
  const bool constrained = sc.constrained;
  const auto n3 = 3 * static_cast<std::size_t>(m.n_nodes);
  // the rows new to the factor this substep, their solves side by side (each
  // its own: the same for any thread count)
  std::vector<std::int32_t> fresh;
  for (const std::int32_t q : fs.active)
    if (fs.W[static_cast<std::size_t>(q)].empty()) fresh.push_back(q);
  tbb::parallel_for(std::size_t(0), fresh.size(), [&](std::size_t k) {
    const std::int32_t q = fresh[k];
    const FaceSolve::Row& r = fs.rows[static_cast<std::size_t>(q)];
    std::vector<Real> a(n3, 0);
    for (int j = 0; j < 3; ++j)
      if (r.w[j] != 0) {
        Vec3 aj = r.w[j] * r.n;
        if (constrained) aj = filter(aj, load3(cn, r.node[j]));
        store3(a.data(), r.node[j], load3(a.data(), r.node[j]) + aj);
      }
    std::vector<Real>& Wq = fs.W[static_cast<std::size_t>(q)];
    Wq.resize(n3);
    factor_solve(*fs.F, m, a.data(), Wq.data());
    if (constrained)
      for (std::int32_t i = 0; i < m.n_nodes; ++i) store3(Wq.data(), i, filter(load3(Wq.data(), i), load3(cn, i)));
  });
  const Eigen::Index na = fs.n_active;
  Eigen::MatrixXd S(na, na);
  for (Eigen::Index i = 0; i < na; ++i)
    for (Eigen::Index k = 0; k < na; ++k)
      S(i, k) = row_dot(fs.rows[static_cast<std::size_t>(fs.active[static_cast<std::size_t>(i)])],
                        fs.W[static_cast<std::size_t>(fs.active[static_cast<std::size_t>(k)])].data());
  S = (0.5 * (S + S.transpose())).eval();  // (J G J^T is symmetric but for round-off)
  for (Eigen::Index i = 0; i < na; ++i) S(i, i) += fs.rows[static_cast<std::size_t>(fs.active[static_cast<std::size_t>(i)])].eps;
  fs.S_dense.compute(S);
  if (fs.S_dense.info() != Eigen::Success || !(fs.S_dense.vectorD().minCoeff() > 0)) {
    for (FaceSolve::Row& r : fs.rows) r.active = false;
    fs.n_active = 0;
    fs.active.clear();
  }
}

// The active rows' S = eps + J Q J^T, factorised (rows that cannot hold, or
// a factor that fails, leave the rows inactive); with the sparse factor F,
// S = eps + J G J^T (face_rows_factor_dense).
void face_rows_factor(const Model& m, const State& s, FaceSolve& fs) {
  const Scratch& sc = s.scratch;
  const Real* P = sc.precond.data();
  const Real* cn = sc.constraint.data();
  const bool constrained = sc.constrained;
  fs.index.assign(fs.rows.size(), -1);
  fs.active.clear();
  fs.n_active = 0;
  for (std::size_t q = 0; q < fs.rows.size(); ++q)
    if (fs.rows[q].active) {
      fs.index[q] = fs.n_active++;
      fs.active.push_back(static_cast<std::int32_t>(q));
    }
  fs.t.resize(fs.n_active);
  if (fs.n_active == 0) return;
  if (fs.F) {
    face_rows_factor_dense(m, s, fs);
    fs.t.resize(fs.n_active);
    return;
  }
  // per node, its rows' entries w_j n and Q (w_j n)
  struct Entry {
    std::int32_t slot, row;
    Vec3 a, qa;
  };
  std::vector<Entry> e;
  for (std::size_t q = 0; q < fs.rows.size(); ++q) {
    const FaceSolve::Row& r = fs.rows[q];
    if (!r.active) continue;
    for (int j = 0; j < 3; ++j)
      if (r.w[j] != 0) {
        const Vec3 a = r.w[j] * r.n;
        e.push_back({sc.face_slot[static_cast<std::size_t>(r.node[j])], fs.index[q], a, q_apply(P, cn, constrained, r.node[j], a)});
      }
  }
  std::stable_sort(e.begin(), e.end(), [](const Entry& a, const Entry& b) { return a.slot < b.slot; });
  std::vector<Eigen::Triplet<double>> tr;
  for (std::size_t q = 0; q < fs.rows.size(); ++q)
    if (fs.index[q] >= 0) tr.emplace_back(fs.index[q], fs.index[q], fs.rows[q].eps);
  for (std::size_t b = 0; b < e.size();) {
    std::size_t end = b;
    while (end < e.size() && e[end].slot == e[b].slot) ++end;
    for (std::size_t i = b; i < end; ++i)
      for (std::size_t j = b; j < end; ++j) tr.emplace_back(e[i].row, e[j].row, dot(e[i].a, e[j].qa));
    b = end;
  }
  Eigen::SparseMatrix<double> S(fs.n_active, fs.n_active);
  S.setFromTriplets(tr.begin(), tr.end());
  fs.S.compute(S);
  if (fs.S.info() != Eigen::Success) {
    for (FaceSolve::Row& r : fs.rows) r.active = false;
    fs.n_active = 0;
    fs.active.clear();
  }
  fs.t.resize(fs.n_active);
}

// y = S^-1 t (t set for the active rows), and at each of the rows' nodes
// (FaceSolve::acc) Q (J^T y): the move the rows' impulses y make there
void face_rows_spread(const State& s, FaceSolve& fs) {
  fs.y = fs.S.solve(fs.t);
  const Scratch& sc = s.scratch;
  std::fill(fs.acc.begin(), fs.acc.end(), 0);
  for (std::size_t q = 0; q < fs.rows.size(); ++q) {
    if (fs.index[q] < 0) continue;
    const FaceSolve::Row& r = fs.rows[q];
    const Real yq = fs.y(fs.index[q]);
    for (int j = 0; j < 3; ++j)
      if (r.w[j] != 0) {
        const std::int32_t k = sc.face_slot[static_cast<std::size_t>(r.node[j])];
        store3(fs.acc.data(), k, load3(fs.acc.data(), k) + (yq * r.w[j]) * r.n);
      }
  }
  for (std::size_t k = 0; k < fs.nodes.size(); ++k)
    store3(fs.acc.data(), static_cast<std::int64_t>(k),
           q_apply(sc.precond.data(), sc.constraint.data(), sc.constrained, fs.nodes[k], load3(fs.acc.data(), static_cast<std::int64_t>(k))));
}

// z -= Q J^T S^-1 J z (z = Q r: then z = (Q^-1 + J^T J / eps)^-1 r); *ez
// changes by the mass norm's change. Returns t . y, by which r . z falls.
Real face_rows_precondition(const Model& m, const State& s, FaceSolve& fs, Real* z, Real* ez) {
  for (std::size_t q = 0; q < fs.rows.size(); ++q)
    if (fs.index[q] >= 0) fs.t(fs.index[q]) = row_dot(fs.rows[q], z);
  face_rows_spread(s, fs);
  for (std::size_t k = 0; k < fs.nodes.size(); ++k) {
    const std::int32_t i = fs.nodes[k];
    const Vec3 zi = load3(z, i);
    const Vec3 zn = zi - load3(fs.acc.data(), static_cast<std::int64_t>(k));
    *ez += m.mass[static_cast<std::size_t>(i)] * (dot(zn, zn) - dot(zi, zi));
    store3(z, i, zn);
  }
  return fs.t.dot(fs.y);
}

// With the sparse factor: z -= G J^T S^-1 J z (z = G r: then z is M^-1 r,
// M = G^-1 + J^T J / eps, by Woodbury), over all nodes (G J^T reaches them);
// *ez changes by the mass norm's change. Returns t . y, by which r . z falls.
Real face_rows_precondition_factor(const Model& m, State& s, FaceSolve& fs, Real* z, Real* ez) {
  const auto na = static_cast<std::size_t>(fs.n_active);
  for (std::size_t k = 0; k < na; ++k) fs.t(static_cast<Eigen::Index>(k)) = row_dot(fs.rows[static_cast<std::size_t>(fs.active[k])], z);
  fs.y = fs.S_dense.solve(fs.t);
  Real* partial = s.scratch.partial.data();
  const Real* mass = m.mass.data();
  for_chunks(m, [&](int ch) {
    Real de = 0;
    for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
      const Vec3 zi = load3(z, i);
      Vec3 zn = zi;
      for (std::size_t k = 0; k < na; ++k) zn -= fs.y(static_cast<Eigen::Index>(k)) * load3(fs.W[static_cast<std::size_t>(fs.active[k])].data(), i);
      de += mass[i] * (dot(zn, zn) - dot(zi, zi));
      store3(z, i, zn);
    }
    partial[ch * kPad + 5] = de;
  });
  *ez += partial_sum(m, s.scratch, 5);
  return fs.t.dot(fs.y);
}

// b at the rows' nodes: b0 (without the rows) + J^T c / eps of the active rows
void face_rows_rhs(const FaceSolve& fs, Real* rhs) {
  for (std::size_t k = 0; k < fs.nodes.size(); ++k) store3(rhs, fs.nodes[k], load3(fs.rhs0.data(), static_cast<std::int64_t>(k)));
  for (const FaceSolve::Row& r : fs.rows) {
    if (!r.active) continue;
    for (int j = 0; j < 3; ++j)
      if (r.w[j] != 0) store3(rhs, r.node[j], load3(rhs, r.node[j]) + (r.c / r.eps * r.w[j]) * r.n);
  }
}

// After the nodes' pass (the preconditioner, holds and fixed velocities
// known): each row's c and eps, the factor of S, and J^T c / eps in b.
void face_rows_constrain(State& s, Real h, FaceSolve& fs) {
  if (fs.rows.empty()) return;
  Scratch& sc = s.scratch;
  const Real* vnew = sc.vnew.data();
  for (FaceSolve::Row& r : fs.rows) {
    Real fixed_v = 0;  // the fixed corners' part of J v (their velocities are set)
    Real d = 0;        // (J Q J^T)_rr
    for (int j = 0; j < 3; ++j) {
      if (r.w[j] == 0) fixed_v += r.wa[j] * dot(r.n, load3(vnew, r.node[j]));
      else d += r.w[j] * r.w[j] * dot(r.n, q_apply(sc.precond.data(), sc.constraint.data(), sc.constrained, r.node[j], r.n));
    }
    r.c = (r.standoff - r.gap) / h - fixed_v;
    r.need = std::abs(r.c - row_dot(r, s.v.data()));
    r.eps = kFaceCompliance * d;
    r.usable = d > 0 && std::isfinite(r.c);
    r.d = d;
    // a candidate starts active where it pushed in the last substep (its
    // face drawn off the sample since by the mesh's motion, which it follows)
    r.active = r.usable && (!r.candidate || r.pushed);
  }
  fs.rhs0.resize(3 * fs.nodes.size());
  for (std::size_t k = 0; k < fs.nodes.size(); ++k) store3(fs.rhs0.data(), static_cast<std::int64_t>(k), load3(sc.rhs.data(), fs.nodes[k]));
}

// After the solve: each row's impulse lambda = (c - J v) / eps and its force
// on the tissue (normal and friction) at the solve's velocities v.
void face_rows_forces(FaceSolve& fs, const Real* v, Real h) {
  for (FaceSolve::Row& r : fs.rows) {
    r.lambda = r.active ? (r.c - row_dot(r, v)) / r.eps : 0;
    r.force = Vec3{};
    if (!r.active) continue;
    Real wf = 0;  // the free corners' weight
    for (int j = 0; j < 3; ++j) {
      if (r.w[j] == 0) continue;
      wf += r.w[j];
      if (r.cf > 0) r.force -= (r.cf * r.w[j]) * filter(load3(v, r.node[j]) - r.u, r.n);
    }
    r.force += (wf * r.lambda / h) * r.n + wf * r.f_slide;
  }
}

// After the face pass: the solve's rows' forces added to State::face_force
// and their work (at the meshes' velocities at the substep's end) to
// *tool_work; the rows the face pass found (Scratch::face_rows_new) become
// State::face_rows, each with the impulse of its row in this solve added
// (the next substep's friction bound); the node slots cleared.
void face_rows_end(State& s, const ObstacleMotion& mo, Real h, FaceSolve& fs, Real* tool_work) {
  Scratch& sc = s.scratch;
  if (!fs.rows.empty()) {
    const Obstacles& obs = *s.obstacles;
    const auto np = static_cast<std::int32_t>(obs.planes.size());
    std::vector<FaceRow>& next = sc.face_rows_new;
    for (const FaceSolve::Row& r : fs.rows) {
      if (!r.active) continue;
      const FaceRow& fr = s.face_rows[static_cast<std::size_t>(r.src)];
      store3(s.face_force.data(), r.obstacle, load3(s.face_force.data(), r.obstacle) + r.force);
      if (mo.moving()) {
        const ObstacleMesh& mesh = obs.meshes[static_cast<std::size_t>(fr.obstacle - np)];
        const Vec3 p1 = mo.to_world(fr.obstacle, load3(mesh.samples.data(), fr.sample), 1);
        *tool_work += h * dot(r.force, mo.velocity(fr.obstacle, p1, 1, h));
      }
      const auto it = std::lower_bound(next.begin(), next.end(), fr.key(), [](const FaceRow& a, const std::array<std::int32_t, 3>& k) { return a.key() < k; });
      if (it != next.end() && it->key() == fr.key()) it->impulse += std::max<Real>(0, r.lambda);
      // a sample whose row pushed is on the surface, as one the face pass
      // met (State::face_met): the next face pass may make it a candidate
      if (r.lambda > 0) {
        std::size_t first = 0;
        for (std::int32_t j = np; j < fr.obstacle; ++j) first += obs.meshes[static_cast<std::size_t>(j - np)].samples.size() / 3;
        const std::size_t id = first + static_cast<std::size_t>(fr.sample);
        if (id < s.face_met.size()) s.face_met[id] = 1;
      }
    }
    for (const std::int32_t i : fs.nodes) sc.face_slot[static_cast<std::size_t>(i)] = -1;
  }
  s.face_rows.swap(sc.face_rows_new);
}

// ---- the cholesky preconditioner -------------------------------------------

bool factor_matches(const SparseFactor& f, const Model& m, const State& s) {
  if (f.n_nodes != m.n_nodes || f.n_springs != m.n_springs || f.n_tets != m.n_tets || f.n_entries != m.nbr.size())
    return false;
  for (std::int32_t i = 0; i < m.n_nodes; ++i)
    if ((s.inv_mass[i] > 0) != (f.free_of[static_cast<std::size_t>(i)] >= 0)) return false;
  return true;
}

// The factor of the matrix the substep has assembled (Scratch::diag without
// the volume term, offdiag, tet_g, tet_c), its lower triangle built column
// by column on the free nodes (node pairs from the spring rows and the
// tetrahedra).
std::shared_ptr<const SparseFactor> build_factor(const Model& m, const State& s, const SparseFactor* previous) {
  const Scratch& sc = s.scratch;
  auto f = std::make_shared<SparseFactor>();
  f->n_nodes = m.n_nodes, f->n_springs = m.n_springs, f->n_tets = m.n_tets, f->n_entries = m.nbr.size();
  f->free_of.assign(static_cast<std::size_t>(m.n_nodes), -1);
  for (std::int32_t i = 0; i < m.n_nodes; ++i)
    if (s.inv_mass[i] > 0) f->free_of[static_cast<std::size_t>(i)] = f->n_free++;
  const auto N = static_cast<Eigen::Index>(3 * f->n_free);
  std::vector<int>& outer = f->outer;
  std::vector<int>& inner = f->inner;
  outer.assign(1, 0);
  std::vector<double> values;
  std::vector<std::int32_t> mark(static_cast<std::size_t>(m.n_nodes), -1), row;
  std::vector<std::array<double, 9>> blk;  // (j, i) blocks of the column node i, row-major in (q, p)
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    const std::int32_t fi = f->free_of[static_cast<std::size_t>(i)];
    if (fi < 0) continue;
    row.clear();
    row.push_back(i);
    for (std::int32_t k = m.nbr_first[i]; k < m.nbr_first[i + 1]; ++k) {
      const std::int32_t j = m.nbr[static_cast<std::size_t>(k)];
      if (j > i && s.inv_mass[j] > 0) row.push_back(j);
    }
    for (std::int32_t q = m.tet_first[i]; q < m.tet_first[i + 1]; ++q) {
      const std::int32_t g = m.tet_group[m.tet_corner[static_cast<std::size_t>(q)] >> 2];
      for (std::int32_t t = m.tet_group_first[g]; t < m.tet_group_first[g + 1]; ++t)
        for (int d = 0; d < 4; ++d) {
          const std::int32_t j = m.tet[4 * static_cast<std::size_t>(t) + d];
          if (j > i && s.inv_mass[j] > 0) row.push_back(j);
        }
    }
    std::sort(row.begin() + 1, row.end());
    row.erase(std::unique(row.begin() + 1, row.end()), row.end());
    blk.assign(row.size(), std::array<double, 9>{});
    for (std::size_t r = 0; r < row.size(); ++r) mark[static_cast<std::size_t>(row[r])] = static_cast<std::int32_t>(r);
    const Sym3 Di = sym_at(sc.diag.data(), i);
    blk[0] = {Di.xx, Di.xy, Di.xz, Di.xy, Di.yy, Di.yz, Di.xz, Di.yz, Di.zz};
    for (std::int32_t k = m.nbr_first[i]; k < m.nbr_first[i + 1]; ++k) {
      const std::int32_t j = m.nbr[static_cast<std::size_t>(k)];
      if (j <= i || s.inv_mass[j] == 0) continue;
      const Sym3 O = sym_at(sc.offdiag.data(), k);
      const double o9[9] = {O.xx, O.xy, O.xz, O.xy, O.yy, O.yz, O.xz, O.yz, O.zz};
      auto& b = blk[static_cast<std::size_t>(mark[static_cast<std::size_t>(j)])];
      for (int e = 0; e < 9; ++e) b[static_cast<std::size_t>(e)] -= o9[e];
    }
    // each group of node i: G_i, its summed corner gradients, then every
    // corner d of the group's tetrahedra adds tet_c g_d G_i^T at its node
    for (std::int32_t q = m.tet_first[i]; q < m.tet_first[i + 1];) {
      const std::int32_t g = m.tet_group[m.tet_corner[static_cast<std::size_t>(q)] >> 2];
      Vec3 Gi{};
      for (; q < m.tet_first[i + 1] && m.tet_group[m.tet_corner[static_cast<std::size_t>(q)] >> 2] == g; ++q)
        Gi += load3(sc.tet_g.data(), m.tet_corner[static_cast<std::size_t>(q)]);
      const double gi3[3] = {Gi.x, Gi.y, Gi.z};
      const std::int32_t t0 = m.tet_group_first[g];
      for (std::int32_t t = t0; t < m.tet_group_first[g + 1]; ++t)
        for (int d = 0; d < 4; ++d) {
          const std::int32_t j = m.tet[4 * static_cast<std::size_t>(t) + d];
          if (j < i || s.inv_mass[j] == 0) continue;
          const Vec3 gj = load3(sc.tet_g.data(), 4 * static_cast<std::int64_t>(t) + d);
          const double gj3[3] = {gj.x, gj.y, gj.z};
          auto& b = blk[static_cast<std::size_t>(mark[static_cast<std::size_t>(j)])];
          for (int qq = 0; qq < 3; ++qq)
            for (int pp = 0; pp < 3; ++pp) b[static_cast<std::size_t>(3 * qq + pp)] += sc.tet_c[t0] * gj3[qq] * gi3[pp];
        }
    }
    // nodes held on obstacles (Scratch::constraint): the factor is of the
    // held system, S A S + d n n^T at each held node (S = I - n n^T there, d
    // its diagonal's mean), so that on the held subspace it inverts what the
    // filtered PCG solves
    if (sc.constrained) {
      const Vec3 ni = load3(sc.constraint.data(), i);
      for (std::size_t r = 0; r < row.size(); ++r) {
        const Vec3 nj = load3(sc.constraint.data(), row[r]);
        const bool hi = holds(ni), hj = holds(nj);
        if (!hi && !hj) continue;
        auto& bk = blk[r];  // B[q][p] = bk[3 q + p]: q the row node j's dof, p the column node i's
        const double a[3] = {nj.x, nj.y, nj.z}, c[3] = {ni.x, ni.y, ni.z};
        const double d = r == 0 ? (bk[0] + bk[4] + bk[8]) / 3 : 0;
        if (hj)  // S_j B: B - n_j (n_j^T B)
          for (int p = 0; p < 3; ++p) {
            const double col = a[0] * bk[static_cast<std::size_t>(p)] + a[1] * bk[static_cast<std::size_t>(3 + p)] +
                               a[2] * bk[static_cast<std::size_t>(6 + p)];
            for (int q = 0; q < 3; ++q) bk[static_cast<std::size_t>(3 * q + p)] -= a[q] * col;
          }
        if (hi)  // (.) S_i: X - (X n_i) n_i^T
          for (int q = 0; q < 3; ++q) {
            const double rw = bk[static_cast<std::size_t>(3 * q)] * c[0] + bk[static_cast<std::size_t>(3 * q + 1)] * c[1] +
                              bk[static_cast<std::size_t>(3 * q + 2)] * c[2];
            for (int p = 0; p < 3; ++p) bk[static_cast<std::size_t>(3 * q + p)] -= rw * c[p];
          }
        if (r == 0 && hi)
          for (int q = 0; q < 3; ++q)
            for (int p = 0; p < 3; ++p) bk[static_cast<std::size_t>(3 * q + p)] += d * c[q] * c[p];
      }
    }
    for (int p = 0; p < 3; ++p) {
      for (std::size_t r = 0; r < row.size(); ++r) {
        const std::int32_t fj = f->free_of[static_cast<std::size_t>(row[r])];
        for (int q = r == 0 ? p : 0; q < 3; ++q) {
          inner.push_back(3 * fj + q);
          values.push_back(blk[r][static_cast<std::size_t>(3 * q + p)]);
        }
      }
      outer.push_back(static_cast<int>(inner.size()));
    }
    for (std::int32_t j : row) mark[static_cast<std::size_t>(j)] = -1;
  }
  if (N == 0) return f;
  const Eigen::Map<const Eigen::SparseMatrix<double>> A(N, N, static_cast<Eigen::Index>(values.size()), outer.data(),
                                                        inner.data(), values.data());
  if (previous && previous->outer == outer && previous->inner == inner) {
    f->perm = previous->perm, f->perm_inv = previous->perm_inv;
  } else {
    const Eigen::SparseMatrix<double> full = A.selfadjointView<Eigen::Lower>();
    Eigen::AMDOrdering<int> amd;
    amd(full, f->perm_inv);
    f->perm = f->perm_inv.inverse();
  }
  Eigen::SparseMatrix<double> PAP(N, N);
  PAP.selfadjointView<Eigen::Lower>() = A.selfadjointView<Eigen::Lower>().twistedBy(f->perm);
  f->ldlt.compute(PAP);
  f->ok = f->ldlt.info() == Eigen::Success && f->ldlt.vectorD().allFinite() && f->ldlt.vectorD().minCoeff() > 0;
  return f;
}

// z = A^-1 r on the free nodes (zero where pinned), through the factor
void factor_solve(const SparseFactor& f, const Model& m, const Real* r, Real* z) {
  const auto N = static_cast<Eigen::Index>(3 * f.n_free);
  Eigen::VectorXd b(N);
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    const std::int32_t fi = f.free_of[static_cast<std::size_t>(i)];
    if (fi >= 0) b.segment<3>(3 * fi) << r[3 * i], r[3 * i + 1], r[3 * i + 2];
  }
  const Eigen::VectorXd x = f.perm_inv * f.ldlt.solve(f.perm * b).eval();
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    const std::int32_t fi = f.free_of[static_cast<std::size_t>(i)];
    store3(z, i, fi >= 0 ? Vec3{x(3 * fi), x(3 * fi + 1), x(3 * fi + 2)} : Vec3{});
  }
}

Check implicit_substep(const Model& m, State& s, Real t, Real h, const SolverOptions& o, Real* tool_work,
                       int* iterations, bool* cg_converged) {
  Scratch& sc = s.scratch;
  const Real* x = s.x.data();
  Real* f = s.f.data();
  Real* partial = sc.partial.data();
  Real* vnew = sc.vnew.data();

  // spring attachments, implicit in x: k (target(t+h) - x) - h^2 k v' (stiffness in the diagonal)
  for (const auto& a : s.attachments) {
    if (a.stiffness == 0 || a.nodes.empty()) continue;
    const Vec3 p = a.path.at(t + h);
    for (std::size_t j = 0; j < a.nodes.size(); ++j) {
      const auto i = a.nodes[j];
      const Vec3 target = p + load3(a.offset.data(), static_cast<std::int64_t>(j));
      store3(sc.attach_f.data(), i, load3(sc.attach_f.data(), i) + a.stiffness * (target - load3(x, i)));
    }
  }
  // prescribed velocities of kinematic nodes
  for (const auto& a : s.attachments) {
    if (a.stiffness != 0 || a.nodes.empty()) continue;
    const Vec3 p = a.path.at(t + h);
    for (std::size_t j = 0; j < a.nodes.size(); ++j) {
      const auto i = a.nodes[j];
      if (s.pin[i] != Pin::kinematic) continue;
      store3(vnew, i, (1 / h) * (p + load3(a.offset.data(), static_cast<std::int64_t>(j)) - load3(x, i)));
    }
  }

  // Two passes over the nodes. The first takes each spring once, at its end
  // a: its elastic force, energy and block (the geometry shared by a
  // biphasic pair), kept per spring, and node a's share of its row; the
  // second gathers the springs at their end b and completes each row, the
  // right-hand side, preconditioner and initial guess. Each spring was
  // computed at both ends until 2026-11-26 (the same d = x_b - x_a, so the
  // same values); every sum is taken in the same order as then, so the
  // results are bitwise those of before.
  const std::int32_t* a_first = m.a_first.data();
  const std::int32_t* b_first = m.b_first.data();
  const std::int32_t* b_spring = m.b_spring.data();
  const std::int32_t* sb = m.spring_b.data();
  const std::int32_t* slot_a = m.slot_a.data();
  const std::int32_t* slot_b = m.slot_b.data();
  const std::int32_t* nbr_first = m.nbr_first.data();
  const Real* rest = m.spring_rest.data();
  const Real* k = m.spring_k.data();
  const Real* c = m.spring_c.data();
  const std::uint8_t* ten = m.spring_tension.data();
  const Real* fext = s.f_ext.data();
  const Real* fatt = sc.attach_f.data();
  const Real* w = s.inv_mass.data();
  const Real* mass = m.mass.data();
  const Real* v = s.v.data();
  const Real* warm = s.warm.data();
  const Real* attach_k = sc.attach_k.data();
  Real* rhs = sc.rhs.data();
  Real* D = sc.diag.data();
  Real* O = sc.offdiag.data();
  Real* P = sc.precond.data();
  Real* fs = sc.fs.data();          // (n_springs x 3) force on end a
  Real* blk = sc.spring_block.data();  // (n_springs x 6) block
  Real* fsq = sc.force_sq.data();   // (n_nodes) sum |f|^2 of the node's springs so far
  const Vec3 g{o.gravity[0], o.gravity[1], o.gravity[2]};
  const Real damp = 1 + h * o.mass_damping;
  const bool block = o.preconditioner != Preconditioner::jacobi;  // (and the cholesky solves' fallback)
  const bool use_warm = o.warm_start;
  const Obstacles* obs = s.obstacles && !s.obstacles->empty() ? s.obstacles.get() : nullptr;
  const ObstacleMotion mo = obs ? obstacle_motion(s, t, h) : ObstacleMotion{};
  // the tissue's faces meet the meshes' edges, and the solve holds those
  // they met in the last substep (FaceSolve)
  const bool faced = obs && m.n_quads > 0 && has_edge_samples(*obs);
  FaceSolve faces;
  if (faced) face_rows_begin(m, s, mo, h, o, faces);
  const bool face_rows = !faces.rows.empty();
  const std::int32_t* face_slot = sc.face_slot.data();
  Real* cn = sc.constraint.data();
  for_chunks(m, [&](int ch) {
    Real u = 0;
    for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
      const Vec3 xi = load3(x, i);
      Vec3 fi{};
      Real fs2 = 0;
      Sym3 Di;
      for (std::int32_t kk = nbr_first[i]; kk < nbr_first[i + 1]; ++kk) sym_store(O, kk, Sym3{});
      // springs are sorted by (a, b): a biphasic pair is adjacent and shares its geometry
      std::int32_t prev = -1;
      SpringGeometry geo{};
      for (std::int32_t q = a_first[i], qe = a_first[i + 1]; q < qe; ++q) {
        if (sb[q] != prev) {
          prev = sb[q];
          geo = spring_geometry(load3(x, prev) - xi, Vec3{});
        }
        const SpringForceBlock sf = spring_force_block(geo, rest[q], k[q], c[q], ten[q] != 0, h);
        store3(fs, q, sf.f);
        sym_store(blk, q, sf.block);
        fi += sf.f;
        fs2 += dot(sf.f, sf.f);
        u += sf.energy;
        Di += sf.block;
        sym_add(O, slot_a[q], sf.block);
      }
      store3(f, i, fi);
      fsq[i] = fs2;
      sym_store(D, i, Di);
    }
    partial[ch * kPad] = u;
  });
  const Real u_tets = tet_pass(m, s, h * h);
  const bool has_tets = m.n_tets > 0;
  for_chunks(m, [&](int ch) {
    Real b2 = 0, t2 = 0, tw = 0, held = 0;
    for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
      Vec3 fi = load3(f, i);
      Real fs2 = fsq[i];
      Sym3 Di = sym_at(D, i);
      for (std::int32_t qq = b_first[i], qe = b_first[i + 1]; qq < qe; ++qq) {
        const std::int32_t q = b_spring[qq];
        const Vec3 fq = load3(fs, q);
        const Sym3 bq = sym_at(blk, q);
        fi -= fq;
        fs2 += dot(fq, fq);
        Di += bq;
        sym_add(O, slot_b[q], bq);
      }
      // the volume term: its force, and its diagonal block for the
      // preconditioner (apply_matrix applies the term itself)
      Sym3 Dt;
      if (has_tets) {
        const TetNodeTerms tt = tet_node_terms<true>(m, sc, i);
        sc.guard_acts[i] = tt.guard_acts;
        fi += tt.f;
        fs2 += tt.f2;
        Dt = tt.block;
      }
      fi += load3(fext, i);
      if (w[i] == 0) {
        if (obs) store3(cn, i, Vec3{});
        store3(f, i, fi);
        store3(rhs, i, Vec3{});
        sym_store(P, i, Sym3{});
        sym_store(D, i, Di);
        if (s.pin[i] != Pin::kinematic) store3(vnew, i, Vec3{});
        continue;
      }
      fi += mass[i] * g + load3(fatt, i);
      store3(f, i, fi);
      const Real md = damp * mass[i] + h * h * attach_k[i];
      Di.xx += md, Di.yy += md, Di.zz += md;
      const Vec3 vi = load3(v, i);
      Vec3 ni{};  // the hold's normal (zero: none)
      Vec3 ui{};  // the velocity of the obstacle holding it (a moving one)
      Vec3 b_friction{};  // friction's part of b: h times the sliding force, or h c (u - n n^T u)
      Vec3 f_slide{};     // a sliding node's Coulomb force, -mu N t (explicit)
      if (obs) {
        // a node resting on an obstacle (put on it by the last substep, or
        // held there with the hold pushing: below) moves only along its
        // surface in this solve: its normal velocity is held at the
        // obstacle's, u . n (zero for one at rest; the constraint filters
        // every PCG vector, Baraff & Witkin 1998, 5.3, the first guess holds
        // u . n). Its friction is a tangential damper in the matrix on the
        // velocity relative to the obstacle, c = mu N /
        // max(|v_t - u_t|, v_eps), N the hold's normal force of the last substep:
        // against a node at rest a damper that lets it creep at most v_eps
        // (friction_creep_speed) under any force inside the friction cone
        // (lagged, smoothed Coulomb friction, as IPC's eps_v: Li et al. 2020).
        // A node sliding too fast for one substep's friction impulse to stop
        // it (mu N h < m |v_t - u_t|) gets Coulomb's force itself, -mu N along
        // its relative tangential velocity, in b: the damper's force there is
        // c |v'_t - u_t|, short of mu N by the substep's change of the relative
        // speed (4 % under a node dragged by a table, 1 ms substeps, until
        // 2026-11-28: MovingObstacles.ASlidingTableDragsANodeByFriction).
        const std::int32_t k = s.contact_obstacle[static_cast<std::size_t>(i)];
        Real cf = 0;
        ObstacleContact c;
        const Vec3 xi = load3(x, i);
        if (k >= 0) c = rests_on(*obs, k, xi, mo);
        const Real* last_force = s.contact_force.data();
        {
          if (c.obstacle >= 0) {
            ni = c.n;
            ui = mo.velocity(k, xi, 0, h);
            const Vec3 vt = filter(vi - ui, ni);
            const Real n_prev = std::max(Real(0), dot(load3(last_force, i), ni));  // N of the last substep
            const Real mu_n = obstacle_friction_coefficient(*obs, k) * n_prev, st = norm(vt);
            if (mu_n * h < mass[i] * st) {
              f_slide = (-mu_n / st) * vt;
              b_friction = h * f_slide;
            } else {
              cf = mu_n / std::max(st, o.friction_creep_speed);
              Sym3 t;  // h c (I - n n^T)
              t.xx = h * cf * (1 - ni.x * ni.x), t.yy = h * cf * (1 - ni.y * ni.y), t.zz = h * cf * (1 - ni.z * ni.z);
              t.xy = -h * cf * ni.x * ni.y, t.xz = -h * cf * ni.x * ni.z, t.yz = -h * cf * ni.y * ni.z;
              Di += t;
              if (mo.moving()) b_friction = (h * cf) * filter(ui, ni);
            }
          }
        }
        store3(cn, i, ni);
        sc.friction_c[static_cast<std::size_t>(i)] = cf;
        store3(sc.friction_f.data(), i, f_slide);
      }
      // the faces' rows' friction at their corners
      if (face_rows)
        if (const std::int32_t k = face_slot[i]; k >= 0) {
          Di += sym_at(faces.node_D.data(), k);
          b_friction += load3(faces.node_b.data(), k);
        }
      sym_store(D, i, Di);
      Di += Dt;  // the whole diagonal block from here on
      Sym3 inv;
      if (block) {
        inv = inverse(Di);
      } else {
        inv.xx = 1 / Di.xx, inv.yy = 1 / Di.yy, inv.zz = 1 / Di.zz;
      }
      sym_store(P, i, inv);
      const Vec3 bi = mass[i] * vi + h * fi + b_friction;
      store3(rhs, i, bi);
      b2 += dot(bi, bi);
      // the size of the terms that make up b_i: momentum, each spring's force, the
      // external, attachment and gravity forces
      const Vec3 mv = mass[i] * vi, fe = load3(fext, i), fa = load3(fatt, i), mg = mass[i] * g;
      const Real ti2 = dot(mv, mv) + h * h * (fs2 + dot(fe, fe) + dot(fa, fa) + dot(mg, mg));
      t2 += ti2;
      // the same terms as the velocity change they would make at this node
      // (over its diagonal), in the mass norm: the scale of the energy test
      const Real pi = 3 / (Di.xx + Di.yy + Di.zz);
      tw += mass[i] * pi * pi * ti2;
      Vec3 guess = use_warm ? vi + load3(warm, i) : vi;
      if (holds(ni)) {
        guess = filter(guess, ni) + dot(ui, ni) * ni;
        held += 1;
      }
      store3(vnew, i, guess);
    }
    partial[ch * kPad + 1] = b2;
    partial[ch * kPad + 2] = t2;
    partial[ch * kPad + 3] = tw;
    partial[ch * kPad + 4] = held;
  });
  sc.constrained = obs && partial_sum(m, sc, 4) > 0;
  const bool constrained = sc.constrained;
  if (face_rows) face_rows_constrain(s, h, faces);
  const Real rhs2 = partial_sum(m, sc, 1);
  const Real terms2 = partial_sum(m, sc, 2);
  const Real termsw = partial_sum(m, sc, 3);
  for (const auto& a : s.attachments)
    if (a.stiffness > 0)
      for (auto i : a.nodes) store3(sc.attach_f.data(), i, Vec3{});

  // the preconditioner: block Jacobi (P), or the sparse factor, built here
  // from this substep's matrix when due (SolverOptions::preconditioner)
  const SparseFactor* F = nullptr;
  if (o.preconditioner == Preconditioner::cholesky || (o.preconditioner == Preconditioner::automatic && s.cholesky_on)) {
    if (s.refactor || !s.factor || !factor_matches(*s.factor, m, s)) {
      s.factor = build_factor(m, s, s.factor.get());
      s.refactor = false;
      s.factor_first_iterations = -1;
      ++s.counters.factorizations;
    }
    if (s.factor->ok) F = s.factor.get();  // (not positive definite: block Jacobi this time)
  }
  // the faces' rows: S with the preconditioner chosen (Q's or the factor's), J^T c / eps in b
  if (face_rows) {
    faces.F = F;
    face_rows_factor(m, s, faces);
    face_rows_rhs(faces, sc.rhs.data());
  }
  Real* r = sc.r.data();
  Real* z = sc.z.data();
  Real* q = sc.q.data();
  // with the factor: z = F^-1 r over all nodes at once, then r.z and the mass norm of z
  auto factor_pass = [&](Real* rz_out, Real* ez_out) {
    factor_solve(*F, m, r, z);
    for_chunks(m, [&](int ch) {
      Real rz_c = 0, ez_c = 0;
      for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
        if (w[i] == 0) continue;
        Vec3 zi = load3(z, i);
        if (constrained) {
          zi = filter(zi, load3(cn, i));
          store3(z, i, zi);
        }
        rz_c += dot(load3(r, i), zi);
        ez_c += mass[i] * dot(zi, zi);
      }
      partial[ch * kPad + 1] = rz_c;
      partial[ch * kPad + 3] = ez_c;
    });
    *rz_out = partial_sum(m, sc, 1);
    *ez_out = partial_sum(m, sc, 3);
  };

  // PCG on the free nodes, from the initial guess in vnew; the iterations
  // add to it, converged says the last solve's verdict. (The guess is not
  // moved onto the faces' rows first: that move, v += Q J^T S^-1 (c - J v),
  // gives each row the impulse that would move its point alone, and the
  // warm start's impulse, which the tissue carries, is lost: 2.4e11 times
  // the residual test's bound at the start of a solve of the benchmark rod
  // at rest. Without it the solves take 41.7 PCG iterations against 45.5;
  // a new row's residual goes in the first iterations, the preconditioner
  // holding the rows exactly.)
  int it = 0;
  int its_most = 0;  // the most iterations of one solve (the faces' rows' active set may solve again)
  bool converged = false;
  FaceSolve* rows = face_rows ? &faces : nullptr;
  // z_i = P r_i (filtered where the node is held), adding its r.z and mass-norm terms
  auto precondition = [&](std::int32_t i, const Vec3& ri, Real& rz_c, Real& ez_c) {
    Vec3 zi = apply_precond(P, i, ri);
    if (constrained) zi = filter(zi, load3(cn, i));
    store3(z, i, zi);
    rz_c += dot(ri, zi);
    ez_c += mass[i] * dot(zi, zi);
  };
  // a chunk's, and then all chunks' sums r.z, |r|^2 and z's mass norm (z by
  // the factor, or corrected for the faces' rows)
  auto put_sums = [&](int ch, Real rz_c, Real rr_c, Real ez_c) {
    partial[ch * kPad + 1] = rz_c;
    partial[ch * kPad + 2] = rr_c;
    partial[ch * kPad + 3] = ez_c;
  };
  auto sums = [&](Real* rz, Real* rr, Real* ez) {
    *rz = partial_sum(m, sc, 1);
    *rr = partial_sum(m, sc, 2);
    *ez = partial_sum(m, sc, 3);
    if (F) factor_pass(rz, ez);
    if (rows && rows->any()) *rz -= F ? face_rows_precondition_factor(m, s, *rows, z, ez) : face_rows_precondition(m, s, *rows, z, ez);
  };
  auto pcg = [&] {
    apply_matrix<Read::plain>(m, s, vnew, nullptr, 0, nullptr, q, rows);
    for_chunks(m, [&](int ch) {
      Real rz = 0, rr = 0, ez = 0;
      for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
        Vec3 ri = w[i] == 0 ? Vec3{} : load3(rhs, i) - load3(q, i);
        if (constrained) ri = filter(ri, load3(cn, i));
        store3(r, i, ri);
        rr += dot(ri, ri);
        if (!F) precondition(i, ri, rz, ez);
      }
      put_sums(ch, rz, rr, ez);
    });
    Real rz, rr, ez;
    sums(&rz, &rr, &ez);
    // Stop at |r| <= tol x the size of b's terms (root sum of squares), not of b
    // itself: near equilibrium the terms cancel, |b| -> 0, and a test relative to
    // |b| iterates on round-off (139 iterations a step for a block at rest in its
    // equilibrium, now 0-2). A poor first guess (|r0| larger than both) sets the scale.
    //
    // And stop only once the velocity error the preconditioner reads off the
    // residual (z = P r), in the mass norm, is below tol x the same terms as
    // velocity changes (each over its node's diagonal). The first test alone
    // let a stiff spring grip (1e9 N/m) set the scale: its force, h k x the
    // lag, outweighed every free node's terms by 1e8, and the free nodes
    // stopped far from their solution (the demo's pull_skin with that grip: 70
    // stability events, 12 % too much elastic energy). Over its diagonal h^2 k,
    // the grip's force is the velocity of its lag (the lag over h), a velocity
    // like the others.
    const Real thresh = o.cg_tolerance * o.cg_tolerance * std::max({terms2, rhs2, rr});
    const Real thresh_e = o.cg_tolerance * o.cg_tolerance * std::max(termsw, ez);
    int its = 0;
    converged = rr <= thresh && ez <= thresh_e;
    Real beta = 0;
    while (!converged && its < o.cg_max_iterations) {
      const Real pq = its == 0 ? apply_matrix<Read::fused_first>(m, s, sc.p.data(), z, 0, sc.p_next.data(), q, rows)
                               : apply_matrix<Read::fused>(m, s, sc.p.data(), z, beta, sc.p_next.data(), q, rows);
      sc.p.swap(sc.p_next);
      ++its;
      if (!(pq > 0) || !std::isfinite(pq)) break;  // not positive definite or not finite: stop here
      const Real alpha = rz / pq;
      const Real* p = sc.p.data();
      for_chunks(m, [&](int ch) {
        Real rz_c = 0, rr_c = 0, ez_c = 0;
        for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
          if (w[i] == 0) continue;
          store3(vnew, i, load3(vnew, i) + alpha * load3(p, i));
          const Vec3 ri = load3(r, i) - alpha * load3(q, i);
          store3(r, i, ri);
          rr_c += dot(ri, ri);
          if (!F) precondition(i, ri, rz_c, ez_c);
        }
        put_sums(ch, rz_c, rr_c, ez_c);
      });
      Real rz_new;
      sums(&rz_new, &rr, &ez);
      converged = rr <= thresh && ez <= thresh_e;
      beta = rz > 0 ? rz_new / rz : 0;
      rz = rz_new;
    }
    it += its;
    its_most = std::max(its_most, its);
  };
  pcg();
  // the faces' rows push, never pull: a row that pulls is let go, a
  // candidate the solve's face would pass is taken, and the solve run again
  // from here (an active set, kFaceActiveSetPasses solves at most)
  for (int pass = 1; rows && pass < kFaceActiveSetPasses; ++pass) {
    bool changed = false;
    for (FaceSolve::Row& fr : rows->rows) {
      if (!fr.usable) continue;
      // a row whose impulse outgrows kFaceConflict times the step's momentum
      // terms and its own need is held against rows it cannot meet together
      // (the compliance lets lambda grow as 1 / eps): it is let go
      const Real jv = row_dot(fr, vnew);
      if (fr.active && (fr.c - jv) / fr.eps > kFaceConflict * (std::sqrt(terms2) + fr.need / fr.d)) {
        fr.active = fr.usable = false, changed = true;
        continue;
      }
      const bool pulls = fr.active && jv > fr.c;
      const bool passes = !fr.active && jv < fr.c;
      if (pulls || passes) fr.active = !fr.active, changed = true;
    }
    if (!changed) break;
    face_rows_factor(m, s, *rows);
    face_rows_rhs(*rows, rhs);
    ++s.counters.face_resolves;
    pcg();
  }
  if (rows) face_rows_forces(*rows, vnew, h);
  // a slow solve: the factor has drifted from the matrix (rebuild it next
  // substep), or (automatic) block Jacobi is not enough for this model
  // (With nodes held on obstacles the factor is of the held system as it was
  // when built; where the holds change every substep a fresh factor may not
  // bring a solve under refactor_after, so there a rebuild is due only when
  // the solves have also doubled since the factor's first. Before the factor
  // knew the holds, a free block resting on a table got a new factor every
  // substep.)
  if (F) {
    if (s.factor_first_iterations < 0) s.factor_first_iterations = its_most;
    const int limit = constrained ? std::max(o.refactor_after, 2 * s.factor_first_iterations) : o.refactor_after;
    if (its_most > limit) s.refactor = true;
  }
  if (o.preconditioner == Preconditioner::automatic && !s.cholesky_on && !converged) {
    s.cholesky_on = true;
    s.refactor = true;
  }
  *iterations = it;
  *cg_converged = converged;
  ++s.counters.cg_solves;
  s.counters.cg_iterations += it;
  s.counters.cg_max_iterations = std::max<std::int64_t>(s.counters.cg_max_iterations, it);

  // the holds' impulses: (A v' - b) at each held node, of the unfiltered
  // product (one more product, only where a node is held), for their forces
  // and their release
  if (constrained) {
    sc.constrained = false;
    apply_matrix<Read::plain>(m, s, vnew, nullptr, 0, nullptr, q, rows);
    sc.constrained = true;
  }

  // the meshes' edges against the tissue's faces: on the solve's velocities,
  // before the nodes' contacts (which then keep every node off the obstacles)
  Real face_meetings = 0;
  if (obs) face_meetings = face_pass(m, s, mo, std::span<Real>(sc.vnew), h, tool_work, faced);

  // update: v = v', x += h v' (kinematic nodes land exactly on their targets)
  Real* xw = s.x.data();
  Real* vw = s.v.data();
  Real* warmw = s.warm.data();
  for_chunks(m, [&](int ch) {
    Real ke = 0, vmax2 = 0, contacts = 0, work = 0;
    for (std::int32_t i = chunk_begin(m, ch), e = chunk_end(m, ch); i < e; ++i) {
      if (w[i] == 0) continue;
      Vec3 vi = load3(vnew, i);
      store3(warmw, i, vi - load3(vw, i));  // the solve's own change (the next solve's first guess)
      // a held node: the hold's impulse (A v' - b)_i . n over h is its normal
      // force. Pushing (> 0), the hold stays and the force sets the next
      // substep's friction; pulling, the node is let go. The obstacle's force
      // on the node is that normal force and the damper's -c v'_t.
      bool keep = false;
      Vec3 hold_force{};
      if (constrained) {
        const Vec3 ni = load3(cn, i);
        if (holds(ni)) {
          const Real normal_force = dot(load3(q, i) - load3(rhs, i), ni) / h;
          keep = normal_force > 0;
          const Vec3 ui = mo.velocity(s.contact_obstacle[static_cast<std::size_t>(i)], load3(xw, i), 0, h);
          hold_force = normal_force * ni - sc.friction_c[static_cast<std::size_t>(i)] * filter(vi - ui, ni) +
                       load3(sc.friction_f.data(), i);
        }
      }
      const Vec3 x0i = load3(xw, i);
      Vec3 xi = x0i + h * vi;
      if (obs) {
        const Vec3 v_before = vi;
        const ObstacleContact c = resolve_obstacle_contact(*obs, x0i, xi, vi, h, mo);
        std::int32_t k = c.obstacle;
        Vec3 fc{};
        if (k >= 0) {
          // put on an obstacle: the contact's velocity change is the impulse
          // m dv of a force m dv / h over the substep
          fc = (mass[i] / h) * (vi - v_before);
        } else if (keep) {
          k = s.contact_obstacle[static_cast<std::size_t>(i)];  // held on it by the solve
          fc = hold_force;
        }
        store3(s.contact_force.data(), i, fc);
        s.contact_obstacle[static_cast<std::size_t>(i)] = k;
        contacts += k >= 0;
        if (mo.moving()) work += h * dot(fc, mo.velocity(k, xi, 1, h));  // a moving obstacle's work on the node
      }
      store3(vw, i, vi);
      store3(xw, i, xi);
      const Real v2 = dot(vi, vi);
      ke += mass[i] * v2;
      vmax2 = std::max(vmax2, v2);
    }
    partial[ch * kPad + 1] = Real(0.5) * ke;
    partial[ch * kPad + 2] = vmax2;
    partial[ch * kPad + 4] = contacts;
    partial[ch * kPad + 5] = work;
  });
  // the faces' rows: their forces on the tissue are the meshes'; the rows
  // the face pass found hold the faces in the next substep
  if (faced) face_rows_end(s, mo, h, faces, tool_work);
  Check out{partial_sum(m, sc, 1), partial_sum(m, sc, 0) + u_tets, partial_max(m, sc, 2),
            obs ? partial_sum(m, sc, 4) : Real(0), face_meetings};
  if (mo.moving()) *tool_work += partial_sum(m, sc, 5);
  *tool_work += move_kinematic(s, t + h, h);
  return out;
}

}  // namespace

Real symplectic_step_limit(const Model& m, State& s, const SolverOptions& o) {
  if (s.step_limit > 0) return s.step_limit;
  // stiffness of spring attachments per node
  std::vector<Real> extra(static_cast<std::size_t>(m.n_nodes), 0);
  for (const auto& a : s.attachments)
    if (a.stiffness > 0)
      for (auto i : a.nodes) extra[static_cast<std::size_t>(i)] += a.stiffness;
  Real w2 = 0, gam = 0;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    if (s.inv_mass[i] == 0) continue;
    w2 = std::max(w2, m.omega2[i] + extra[static_cast<std::size_t>(i)] * m.inv_mass[i]);
    gam = std::max(gam, m.gamma[i]);
  }
  gam += o.mass_damping;
  s.step_limit = symplectic_limit(std::sqrt(w2), gam);
  // a limit that underflows (omega^2 = k / m overflowing for a node of
  // 1e-300 kg) is the smallest step, never "no limit": the substeps then
  // reach max_substeps and the run says why
  if (!(s.step_limit > 0)) s.step_limit = std::numeric_limits<Real>::min();
  return s.step_limit;
}

StepInfo step(const Model& m, State& s, Real dt, const SolverOptions& o) {
  StepInfo info;
  const bool implicit = o.integrator == Integrator::implicit_euler;
  ensure_scratch(m, s, implicit);
  Scratch& sc = s.scratch;
  if (!(dt > 0) || !std::isfinite(dt) || m.n_nodes == 0) {
    s.time += (dt > 0 && std::isfinite(dt)) ? dt : 0;
    ++s.counters.steps;
    return info;
  }

  // substeps
  long n_sub = o.substeps;
  if (n_sub == 0) {
    if (implicit) {
      n_sub = 1;
    } else {
      const Real h_max = o.safety * symplectic_step_limit(m, s, o);
      const Real want = std::ceil(dt / h_max);
      n_sub = want >= o.max_substeps ? o.max_substeps : std::max<long>(1, static_cast<long>(want));
    }
  }
  n_sub = std::min<long>(n_sub, o.max_substeps);

  // spring-attachment stiffness per node (implicit diagonal)
  bool has_spring_attach = false;
  for (const auto& a : s.attachments)
    if (a.stiffness > 0)
      for (auto i : a.nodes) {
        sc.attach_k[static_cast<std::size_t>(i)] += a.stiffness;
        has_spring_attach = true;
      }

  // the step's energy budget (see solver.h)
  Budget budget;
  {
    const Real M = m.total_mass;
    const Real gmag = std::sqrt(o.gravity[0] * o.gravity[0] + o.gravity[1] * o.gravity[1] + o.gravity[2] * o.gravity[2]);
    Real fext = 0;
    for (std::int32_t i = 0; i < m.n_nodes; ++i)
      if (s.inv_mass[i] > 0) fext += norm(load3(s.f_ext.data(), i));
    Real v_tool = 0, e_tool = 0;
    // moving obstacles: their speed, and a turning one's at the farthest node
    if (s.obstacles)
      for (std::size_t k = 0; k < s.obstacle_paths.size() && k < static_cast<std::size_t>(obstacle_count(*s.obstacles)); ++k) {
        const Path& p = s.obstacle_paths[k];
        Real speed = p.max_speed();
        if (const Real w = path_max_angular_speed(p); w > 0) {
          const std::size_t np = s.obstacles->planes.size();
          const Vec3 c = (k < np ? s.obstacles->planes[k].pivot : s.obstacles->meshes[k - np].pivot) + p.at(s.time);
          Real r2 = 0;
          for (std::int32_t i = 0; i < m.n_nodes; ++i)
            if (s.inv_mass[i] > 0) r2 = std::max(r2, dot(load3(s.x.data(), i) - c, load3(s.x.data(), i) - c));
          speed += w * std::sqrt(r2);
        }
        v_tool = std::max(v_tool, speed);
      }
    for (const auto& a : s.attachments) {
      if (a.nodes.empty()) continue;
      const Real speed = a.path.max_speed();
      v_tool = std::max(v_tool, speed);
      if (a.stiffness > 0) {
        const Vec3 p = a.path.at(s.time);
        for (std::size_t j = 0; j < a.nodes.size(); ++j) {
          const Real gap = norm(p + load3(a.offset.data(), static_cast<std::int64_t>(j)) - load3(s.x.data(), a.nodes[j])) +
                           speed * dt;
          e_tool += Real(0.5) * a.stiffness * gap * gap;
        }
      }
    }
    const Real v_char = m.extent / 1.0;  // m/s: the model crossing its own size in a second
    budget.scale = Real(0.5) * M * (v_char * v_char + v_tool * v_tool) + M * gmag * m.extent + fext * m.extent + e_tool;
    Real ke = 0;
    for (std::int32_t i = 0; i < m.n_nodes; ++i)
      if (s.inv_mass[i] > 0) {
        const Vec3 vi = load3(s.v.data(), i);
        ke += Real(0.5) * m.mass[i] * dot(vi, vi);
      }
    budget.ke0 = ke;
  }

  // attempts: redo from the step's start with twice the substeps
  const Real t0 = s.time;
  std::memcpy(sc.x0.data(), s.x.data(), s.x.size() * sizeof(Real));
  std::memcpy(sc.v0.data(), s.v.data(), s.v.size() * sizeof(Real));
  std::vector<Real> warm0;
  if (implicit) warm0 = s.warm;
  if (!s.contact_obstacle.empty()) sc.contact0 = s.contact_obstacle, sc.force0 = s.contact_force, sc.face_force0 = s.face_force;
  if (!s.face_rows.empty()) sc.face_rows0 = s.face_rows;
  else sc.face_rows0.clear();
  if (!s.face_met.empty()) sc.face_met0 = s.face_met;
  bool ok = false;
  Check last;
  for (int attempt = 0; attempt <= o.max_retries; ++attempt) {
    const Real h = dt / static_cast<Real>(n_sub);
    budget.w_tool = 0;
    int cg_its = 0;
    long done = 0, unconverged = 0;
    Real contacts = 0, faces = 0;
    Verdict verdict = Verdict::ok;
    for (long k = 0; k < n_sub; ++k) {
      const Real t = t0 + h * static_cast<Real>(k);
      int its = 0;
      bool converged = true;
      last = implicit ? implicit_substep(m, s, t, h, o, &budget.w_tool, &its, &converged)
                      : symplectic_substep(m, s, t, h, o, &budget.w_tool, budget.u0 < 0 || k == n_sub - 1);
      cg_its += its;
      unconverged += !converged;
      contacts += last.contacts;
      faces += last.faces;
      ++done;
      if (budget.u0 < 0) budget.u0 = std::isfinite(last.u) ? last.u : 0;
      verdict = judge(m, last, budget, h, o);
      if (verdict != Verdict::ok) break;
    }
    // A solve stopped at cg_max_iterations leaves a velocity off by its
    // residual, and the next solves start from there: a stiff model (thin
    // lattice cells: 1 566 iterations at 64 cells through a layer) drifts
    // into a tangle. Shorter substeps condition M + h^2 K better (about h
    // times fewer iterations each), so such a step is redone like a blow-up;
    // the last attempt is kept as it is, its unconverged solves counted.
    const bool redo_for_cg = verdict == Verdict::ok && unconverged > 0 && attempt < o.max_retries &&
                             n_sub < o.max_substeps && o.redo_unconverged;
    if (verdict == Verdict::ok && !redo_for_cg) {
      ok = true;
      info.substeps = static_cast<int>(n_sub);
      info.retries = attempt;
      info.cg_iterations = cg_its;
      s.counters.substeps += n_sub;
      s.counters.cg_unconverged += unconverged;
      s.counters.obstacle_contacts += static_cast<std::int64_t>(contacts);
      s.counters.face_contacts += static_cast<std::int64_t>(faces);
      break;
    }
    // detected: count, restore, refine
    if (redo_for_cg) {
      ++s.counters.cg_redos;
    } else {
      ++s.counters.events;
      if (verdict == Verdict::nonfinite) ++s.counters.nonfinite;
      else ++s.counters.blowups;
    }
    s.counters.substeps_redone += done;
    std::memcpy(s.x.data(), sc.x0.data(), s.x.size() * sizeof(Real));
    std::memcpy(s.v.data(), sc.v0.data(), s.v.size() * sizeof(Real));
    if (implicit) s.warm = warm0;
    if (!s.contact_obstacle.empty()) s.contact_obstacle = sc.contact0, s.contact_force = sc.force0, s.face_force = sc.face_force0;
    s.face_rows = sc.face_rows0;
    if (!s.face_met.empty()) s.face_met = sc.face_met0;
    info.retries = attempt + 1;
    if (n_sub >= o.max_substeps) break;
    n_sub = std::min<long>(2 * n_sub, o.max_substeps);
  }
  if (ok) {
    if (info.retries > 0) ++s.counters.recovered;
  } else {
    // give up: the step's start, at rest (never a NaN in the state)
    ++s.counters.failed;
    info.failed = true;
    std::fill(s.v.begin(), s.v.end(), 0);
    std::fill(s.warm.begin(), s.warm.end(), 0);
    if (!s.contact_obstacle.empty()) s.contact_obstacle = sc.contact0, s.contact_force = sc.force0, s.face_force = sc.face_force0;
    s.face_rows = sc.face_rows0;
    if (!s.face_met.empty()) s.face_met = sc.face_met0;
    for (std::int32_t i = 0; i < m.n_nodes; ++i)
      if (!std::isfinite(s.f[3 * i]) || !std::isfinite(s.f[3 * i + 1]) || !std::isfinite(s.f[3 * i + 2]))
        store3(s.f.data(), i, Vec3{});
    last = Check{0, budget.u0 > 0 ? budget.u0 : 0, 0};
    // kinematic nodes still go where their tools are
    for (const auto& a : s.attachments) {
      if (a.stiffness != 0 || a.nodes.empty()) continue;
      const Vec3 p = a.path.at(t0 + dt);
      for (std::size_t j = 0; j < a.nodes.size(); ++j)
        if (s.pin[a.nodes[j]] == Pin::kinematic)
          store3(s.x.data(), a.nodes[j], p + load3(a.offset.data(), static_cast<std::int64_t>(j)));
    }
  }
  if (has_spring_attach)
    for (const auto& a : s.attachments)
      if (a.stiffness > 0)
        for (auto i : a.nodes) sc.attach_k[static_cast<std::size_t>(i)] = 0;
  s.kinetic_energy = last.ke;
  s.spring_energy = last.u;
  s.time = t0 + dt;
  ++s.counters.steps;
  return info;
}

Energies energies(const Model& m, const State& s, const SolverOptions& o) {
  Energies e;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    if (s.inv_mass[i] == 0) continue;
    const Vec3 vi = load3(s.v.data(), i);
    e.kinetic += Real(0.5) * m.mass[i] * dot(vi, vi);
    e.gravity -= m.mass[i] * (o.gravity[0] * s.x[3 * i] + o.gravity[1] * s.x[3 * i + 1] + o.gravity[2] * s.x[3 * i + 2]);
  }
  for (std::int32_t q = 0; q < m.n_springs; ++q) {
    const Vec3 d = load3(s.x.data(), m.spring_b[q]) - load3(s.x.data(), m.spring_a[q]);
    e.elastic += spring_force_elastic(d, m.spring_rest[q], m.spring_k[q], m.spring_tension[q] != 0).energy;
  }
  for (std::int32_t g = 0; g < m.n_groups; ++g) {
    Real V = 0;
    for (std::int32_t t = m.tet_group_first[g]; t < m.tet_group_first[g + 1]; ++t) {
      const std::int32_t* c = &m.tet[4 * static_cast<std::size_t>(t)];
      V += tet_gradient(load3(s.x.data(), c[0]), load3(s.x.data(), c[1]), load3(s.x.data(), c[2]), load3(s.x.data(), c[3])).volume;
    }
    const Real v0 = m.group_rest_volume[static_cast<std::size_t>(g)], a = m.tet_guard[m.tet_group_first[g]];
    const Real d = a > 0 ? std::min<Real>(0, (v0 > 0 ? V : -V) - a * std::abs(v0)) : V - v0;
    e.elastic += Real(0.5) * m.tet_k[m.tet_group_first[g]] * d * d / std::abs(v0);
  }
  return e;
}

std::array<Real, 6> momentum(const Model& m, const State& s) {
  std::array<Real, 6> p{};
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    if (s.inv_mass[i] == 0) continue;
    const Vec3 x = load3(s.x.data(), i), v = m.mass[i] * load3(s.v.data(), i);
    p[0] += v.x, p[1] += v.y, p[2] += v.z;
    p[3] += x.y * v.z - x.z * v.y;
    p[4] += x.z * v.x - x.x * v.z;
    p[5] += x.x * v.y - x.y * v.x;
  }
  return p;
}

}  // namespace orthosim::runtime
