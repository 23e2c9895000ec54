// The runtime's mutable state: everything a step reads and writes, apart
// from the immutable Model (runtime/model.h). Copying a State snapshots a
// simulation; two States can step one Model side by side.
//
// Arrays are (n_nodes x 3) flat, node i at [3i, 3i+3), SI units, the model
// file's physical frame. Inputs a caller sets between steps (external
// forces, pins, attachments) live here too, like MuJoCo's mjData holds ctrl
// and xfrc_applied.
#pragma once

#include "runtime/model.h"
#include "runtime/types.h"

#include <array>
#include <cstdint>
#include <memory>
#include <span>
#include <vector>

namespace orthosim::runtime {

// A piecewise-linear path of a point: times ascending (s), points (m). Held at
// the first point before t[0] and at the last after t[n-1].
struct Path {
  std::vector<Real> t;  // (n) s
  std::vector<Real> p;  // (n x 3) m
  std::vector<Real> r{};  // (n x 3) rad, rotation vectors (axis x angle) at the waypoints, or empty: none
                          // (moving colliders turn about their pivot; runtime/obstacles.h, path_rotation)
  Vec3 at(Real time) const;
  Real max_speed() const;  // m/s, largest segment speed
};

// Where obstacle k is over a substep (a moving collider): its rigid motion
// from its geometry as given, x -> R (x - pivot) + pivot + d, with d going
// from d0 to d1 linearly and R(s) = r0 exp(s [w]) over the fraction s of the
// substep (w a rotation vector in the obstacle's own frame; rotates false:
// R = I throughout).
struct ObstacleFrame {
  Vec3 d0, d1;  // m
  bool rotates = false;
  Vec3 pivot;   // m, in the obstacle's own coordinates
  Rot3 r0, r1;  // the rotation at the substep's start and end (r1 = r0 exp([w]))
  Vec3 w;       // rad over the substep
};

// Nodes attached to a moving point: node j follows path(t) + offset_j.
// stiffness == 0: kinematic grip (positions prescribed, the node's pin is
// kinematic); stiffness > 0: each node is pulled toward its target by a
// spring of that stiffness (N/m) and stays free.
struct Attachment {
  std::vector<std::int32_t> nodes;  // local ids
  std::vector<Real> offset;         // (n x 3) m
  Path path;
  Real stiffness = 0;  // N/m per node, 0 = kinematic
};

// Pin of a node: free, fixed in place, or moved kinematically by an attachment.
enum class Pin : std::uint8_t { free = 0, fixed = 1, kinematic = 2 };

// Stability and solver counters, accumulated over the State's life.
struct Counters {
  std::int64_t steps = 0;             // completed steps (calls of step())
  std::int64_t substeps = 0;          // integrator substeps of completed steps (redone work not counted)
  std::int64_t substeps_redone = 0;   // substeps thrown away by redos
  std::int64_t events = 0;            // detections: non-finite values or energy blow-up
  std::int64_t nonfinite = 0;         //   of which NaN or Inf
  std::int64_t blowups = 0;           //   of which energy growth or runaway motion
  std::int64_t recovered = 0;         // steps that succeeded after at least one redo
  std::int64_t failed = 0;            // steps that failed max_retries times (state restored, velocities zeroed)
  std::int64_t cg_solves = 0;         // implicit: linear solves
  std::int64_t cg_iterations = 0;     // implicit: PCG iterations, all solves
  std::int64_t cg_max_iterations = 0; // implicit: most iterations in one solve
  std::int64_t cg_unconverged = 0;    // implicit: solves stopped at the iteration cap, in accepted attempts
  std::int64_t cg_redos = 0;          // implicit: attempts redone because a solve stopped at the cap
  std::int64_t factorizations = 0;    // implicit, cholesky preconditioner: sparse factors built
  std::int64_t obstacle_contacts = 0; // node-substeps that touched an obstacle (State::obstacles), in accepted attempts
  std::int64_t face_contacts = 0;     // mesh edge samples that met a tissue face, summed over the substeps of accepted attempts
  std::int64_t face_resolves = 0;     // implicit: solves run again for the faces' rows (one let go, or one taken), all attempts
};

// A tissue face held by a mesh's edge sample (resolve_face_contacts): the
// sample met or touched the face's triangle in the last substep, or lies in
// front of it within its motion (a candidate). The implicit solve keeps the
// triangle's point under the sample from moving out past it: one constraint
// row on sum_j w_j v_j . n (runtime/solver.cpp, "the faces' rows", which takes
// the point again under the sample where the mesh puts it at the substep's
// end; docs/runtime.md, Thin instruments). Sorted by (obstacle, sample,
// triangle).
struct FaceRow {
  std::int32_t obstacle = -1;          // the mesh, indexed as ObstacleContact::obstacle
  std::int32_t sample = -1;            // its edge sample (ObstacleMesh::samples)
  std::int32_t triangle = -1;          // the face: triangle t of quad t / 2, (q0, q1, q2) or (q0, q2, q3)
  std::array<std::int32_t, 3> node{};  // the triangle's corners
  std::array<Real, 3> w{};             // the point's barycentric weights, clamped to the triangle (sum 1), as the face pass found it
  Vec3 n{};                            // unit: the normal the sample pushes the face along (into the tissue), as found
  Real impulse = 0;                    // N s: the normal impulse on the face in the last substep (bounds its friction)
  bool candidate = false;              // the sample in front of the face, neither meeting nor touching it, but
                                       // within the triangle's motion over the substep: a contact the solve may make
  std::array<std::int32_t, 3> key() const { return {obstacle, sample, triangle}; }  // the rows' order
};

// Scratch of resolve_face_contacts (runtime/obstacles.h).
struct FaceScratch {
  std::vector<Real> body0, body1;     // (n_nodes x 3) m: the nodes at the substep's start and end, in a mesh's frame
  std::vector<std::int32_t> hits;     // (n x 2) sample, triangle
  std::vector<std::array<std::int32_t, 2>> order;  // the hits sorted
  std::vector<std::uint8_t> met;      // (a mesh's samples) which met the faces in the last substep
  std::vector<std::int32_t> row_of;   // (order) the row a meeting's first sweep added (-1: none)
};

// Scratch the solver resizes on demand (never read across steps).
struct Scratch {
  std::vector<Real> fs;        // (n_springs x 3) N: per-spring force on end a / PCG products
  std::vector<Real> offdiag;   // (n_entries x 6) implicit matrix: coupling block of each node-neighbour entry
  std::vector<Real> diag;      // (n_nodes x 6) implicit matrix: diagonal blocks
  std::vector<Real> precond;   // (n_nodes x 6) inverse diagonal blocks (or inverse diagonals)
  std::vector<Real> rhs, r, z, p, p_next, q, vnew;  // (n_nodes x 3)
  std::vector<Real> x0, v0;    // (n_nodes x 3) step start, for redo
  std::vector<Real> partial;   // (n_chunks x 4) per-chunk partial sums
  std::vector<Real> attach_k;  // (n_nodes) N/m: spring-attachment stiffness per node
  std::vector<Real> attach_f;  // (n_nodes x 3) N: spring-attachment forces of the substep (implicit)
  std::vector<Real> spring_block;  // (n_springs x 6) implicit: each spring's matrix block, computed at its end a
  std::vector<Real> force_sq;      // (n_nodes) implicit: sum of |f|^2 over a node's springs (the residual's scale)
  // volume term (Model::tet)
  std::vector<Real> tet_g;         // (n_tets x 4 x 3) m^2: dV/dx of each corner at the substep's start
  std::vector<Real> tet_p;         // (n_tets) Pa: k (V - V0) / |V0|, the force on corner c being -tet_p g_c
  std::vector<Real> tet_c;         // (n_tets) implicit: h^2 k / |V0|, the Gauss-Newton block h^2 (k/|V0|) g g^T
  std::vector<Real> tet_s;         // (n_tets) implicit: tet_c g.p of the PCG product (0 for a guard that does not act)
  std::vector<std::uint8_t> guard_acts;  // (n_nodes) implicit: node i has a corner in an acting inversion guard
  std::vector<Real> tet_partial;   // (n_tet_chunks) per-chunk energy sums
  // implicit, with obstacles: the unit normal of each node's hold in this
  // substep's solve (zero: none), the filter I - n n^T
  std::vector<Real> constraint;    // (n_nodes x 3)
  bool constrained = false;        // some node is held
  std::vector<std::int32_t> contact0;  // (n_nodes) State::contact_obstacle at the step's start, for redo
  std::vector<Real> force0;            // (n_nodes x 3) State::contact_force at the step's start, for redo
  std::vector<Real> friction_c;        // (n_nodes) N s/m: the friction damper of each held node in this substep
  std::vector<Real> friction_f;        // (n_nodes x 3) N: the Coulomb force of each held node sliding in this substep (else zero)
  std::vector<ObstacleFrame> obstacle_frames;  // where each moving obstacle is over the substep (runtime/obstacles.h)
  FaceScratch faces;                           // the meshes' edges against the tissue's faces
  std::vector<Real> face_force0;               // State::face_force at the step's start, for redo
  std::vector<FaceRow> face_rows0;             // State::face_rows at the step's start, for redo
  std::vector<FaceRow> face_rows_new;          // implicit: the rows the face pass finds for the next substep
  std::vector<std::int32_t> face_slot;         // (n_nodes) implicit: a node's index among the solve's rows' nodes, or -1
  std::vector<std::uint8_t> face_met0;         // State::face_met at the step's start, for redo
};

// The cholesky preconditioner's factor (runtime/solver.cpp): immutable once
// built, so copies of a State share it and step exactly as the original.
struct SparseFactor;

// Static obstacles of the free nodes (runtime/obstacles.h).
struct Obstacles;

struct State {
  Real time = 0;                   // s
  std::vector<Real> x;             // (n_nodes x 3) m, positions
  std::vector<Real> v;             // (n_nodes x 3) m/s, velocities
  std::vector<Real> f;             // (n_nodes x 3) N, total force on each node in the last substep
  std::vector<Real> f_ext;         // (n_nodes x 3) N, external force applied through each step (input)
  std::vector<Pin> pin;            // (n_nodes)
  std::vector<Real> inv_mass;      // (n_nodes) 1/kg, effective: 0 where pinned
  std::vector<Real> warm;          // (n_nodes x 3) m/s, implicit: last velocity change (PCG warm start)
  std::vector<Attachment> attachments;
  // static obstacles the free nodes cannot pass (runtime/obstacles.h), or
  // none; immutable and shared by copies of the State
  std::shared_ptr<const Obstacles> obstacles;
  // moving obstacles (an instrument): obstacle k (index as
  // ObstacleContact::obstacle) is displaced from its geometry by
  // obstacle_paths[k].at(t) at time t (m); an obstacle without a path, or
  // with an empty one, stays where it is. An input like the attachments'
  // paths: a caller may change it between steps.
  std::vector<Path> obstacle_paths;
  // the obstacle each node rested on after the last substep (index as
  // ObstacleContact::obstacle, -1: none); sized by the solver
  std::vector<std::int32_t> contact_obstacle;
  // (n_nodes x 3) N: the force of that contact on the node in the last
  // substep, normal and friction (the implicit solve's hold and friction
  // damper, or the contact's impulse over the substep; zero: none). Its
  // normal part bounds the next substep's friction.
  std::vector<Real> contact_force;
  // (obstacles x 3) N: each mesh's force on the tissue's surface faces in the
  // last substep, through its edges (resolve_face_contacts; not in
  // contact_force, which is the nodes'); sized by the solver
  std::vector<Real> face_force;
  // implicit: the faces the meshes' edge samples hold (FaceRow), found in the last substep
  std::vector<FaceRow> face_rows;
  // (all meshes' edge samples, in order) 1 where the sample met or touched a
  // tissue face in the last substep (resolve_face_contacts); sized by the solver
  std::vector<std::uint8_t> face_met;

  Real kinetic_energy = 0;  // J, after the last substep
  Real spring_energy = 0;   // J, at the start of the last substep
  Real step_limit = 0;      // s, cached symplectic stability limit; 0 = recompute (pins changed)
  Counters counters;
  Scratch scratch;
  // implicit, cholesky preconditioner (SolverOptions::preconditioner): the
  // factor in use, whether the next substep rebuilds it, and (automatic)
  // whether the solves have switched to it
  std::shared_ptr<const SparseFactor> factor;
  bool refactor = true;
  int factor_first_iterations = -1;  // PCG iterations of the first solve with the current factor (-1: none yet)
  bool cholesky_on = false;
};

// A State at rest at the model's rest positions, anchors fixed.
State make_state(const Model& m);

// Fixes nodes in place (velocity zero) or releases them. Anchors stay fixed.
void fix_nodes(const Model& m, State& s, std::span<const std::int32_t> nodes);
void release_nodes(const Model& m, State& s, std::span<const std::int32_t> nodes);

// Adds an attachment; kinematic ones pin their nodes. Returns its index.
int attach(const Model& m, State& s, Attachment a);
// Removes an attachment's effect: its nodes become free (unless fixed elsewhere).
void detach(const Model& m, State& s, int index);

// Order-sensitive 64-bit hash (FNV-1a) of time, positions and velocities:
// equal bits give equal hashes. For determinism tests.
std::uint64_t state_hash(const State& s);

}  // namespace orthosim::runtime
