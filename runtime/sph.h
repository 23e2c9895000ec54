// Weakly compressible SPH blood (issue 9): what the paper hands to the PhysX
// PPU next to the mass-spring tissue (§4.2), emulated on the CPU.
//
//   FluidParams p;                        // SI, defaults = blood (1060 kg/m^3, 3 cP)
//   p.spacing = 0.002;
//   Fluid fluid = make_fluid(p);          // validates; immutable derived constants
//   FluidBoundaries b = make_box_boundaries({0, 0, 0}, {0.1, 0.1, 0.1});
//   FluidState s = make_fluid_state();
//   fill_box(fluid, s, {0, 0, 0}, {0.05, 0.05, 0.05});
//   s.emitters.push_back(emitter); s.drains.push_back(drain);   // inputs, between steps
//   FluidStepInfo info = fluid_step(fluid, s, 1.0 / 60, b);     // substeps inside
//
// Model apart from state, as in the mass-spring runtime: Fluid (from
// FluidParams) and FluidBoundaries are immutable; FluidState holds the
// particles (structure of arrays), the inputs a caller changes between steps
// (emitters, drains, moving surfaces) and the counters. fluid_step never
// throws and never leaves a NaN in the state: a particle whose position or
// velocity is not finite is removed and counted; an invalid dt is refused
// and counted.
//
// Method (docs/sph.md):
// - density by summation, rho_i = sum_j m W_ij + wall part, Wendland C2
//   kernel with support H = support_ratio * spacing;
// - pressure from a Tait or linear equation of state with speed of sound c0
//   (physical: c0 = 10 max_speed, density variation ~1 %; PhysX-compatible:
//   the paper's "stiffness 20" mapped to c0, see physx_stiffness_to_sound_speed);
// - momentum: symmetric pressure gradient (Monaghan 1992), laminar viscosity
//   of Morris, Fox & Zhu (1997), Monaghan's artificial viscosity;
// - symplectic Euler with CFL, force and viscous substep limits;
// - walls (box faces, half-spaces, static triangle meshes, moving triangle
//   surfaces with two-way coupling) by semi-analytic wall integrals
//   (Kulasegaram et al. 2004; Ferrand et al. 2013) plus a projection with
//   restitution and friction;
// - neighbours by a flat uniform cell grid rebuilt every substep by counting
//   sort, all particle arrays permuted into cell order.
// Determinism: every per-particle sum is a gather in a fixed order and the
// only reductions are maxima, so a step is bitwise identical for any number
// of threads. The loops run in the caller's TBB task arena.
#pragma once

#include "runtime/types.h"

#include <array>
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <utility>
#include <vector>

namespace orthosim::runtime {

// ---- kernels: pure functions (support radius H, q = r / H) --------------------

// Wendland C2 in 3-D (Wendland, Adv. Comput. Math. 4, 1995; Dehnen & Aly,
// MNRAS 425, 2012: no pairing instability at any neighbour number):
//   W(r) = 21 / (2 pi H^3) (1 - q)^4 (1 + 4 q),  q < 1;  0 beyond
//   grad_i W(r_ij) = -210 / (pi H^5) (1 - q)^3 r_ij   (r_ij = x_i - x_j)
// The gradient is a polynomial times r_ij: no division, zero at r = 0.
inline Real wendland_w(Real r, Real H) {
  const Real q = r / H;
  if (!(q < 1)) return 0;
  const Real t = 1 - q;
  return Real(21) / (2 * M_PI * H * H * H) * (t * t) * (t * t) * (1 + 4 * q);
}
// The factor g with grad_i W = -g r_ij (1/m^5).
inline Real wendland_grad_factor(Real r, Real H) {
  const Real q = r / H;
  if (!(q < 1)) return 0;
  const Real t = 1 - q;
  return Real(210) / (M_PI * H * H * H * H * H) * t * t * t;
}

// Mueller, Charypar & Gross, SCA 2003 (the kernels of PhysX 2.x fluids), for
// reference and the kernel tests; the solver uses Wendland C2.
//   poly6:   W = 315 / (64 pi H^9) (H^2 - r^2)^3
//   spiky:   grad W = -45 / (pi H^6) (H - r)^2 r_vec / r
//   viscosity: lap W = 45 / (pi H^6) (H - r)
inline Real poly6_w(Real r, Real H) {
  if (!(r < H)) return 0;
  const Real d = H * H - r * r;
  return Real(315) / (64 * M_PI * std::pow(H, 9)) * d * d * d;
}
inline Vec3 spiky_grad(const Vec3& r_vec, Real H) {
  const Real r = norm(r_vec);
  if (!(r < H) || !(r > 0)) return {};
  const Real d = H - r;
  return (-Real(45) / (M_PI * std::pow(H, 6)) * d * d / r) * r_vec;
}
inline Real viscosity_laplacian(Real r, Real H) { return r < H ? Real(45) / (M_PI * std::pow(H, 6)) * (H - r) : 0; }

// ---- equation of state --------------------------------------------------------

enum class Eos : std::uint8_t {
  tait,    // p = B ((rho / rho0)^gamma - 1), B = rho0 c0^2 / gamma (Monaghan 1994; Becker & Teschner 2007)
  linear,  // p = c0^2 (rho - rho0)   (the gas-constant form of Mueller 2003 and PhysX, k = c0^2)
};
const char* to_string(Eos e);  // "tait" | "linear"

// Pressure (Pa) of density rho (kg/m^3). gamma: the Tait exponent (integer).
inline Real eos_pressure(Eos e, Real rho, Real rho0, Real c0, int gamma) {
  if (e == Eos::linear) return c0 * c0 * (rho - rho0);
  const Real x = rho / rho0;
  Real xp = 1;
  for (int k = 0; k < gamma; ++k) xp *= x;
  return rho0 * c0 * c0 / gamma * (xp - 1);
}
// Density at pressure p (the inverse), for tests and the hydrostatic rule.
Real eos_density(Eos e, Real p, Real rho0, Real c0, int gamma);

// PhysX 2.x fluid stiffness k (NxFluidDesc::stiffness, default 20; the paper's
// "20 N") against the speed of sound. PhysX evaluates p = k (rho - rho0) in a
// space rescaled to 10 particles per unit length; lengths there are physical
// lengths divided by s = 10 * spacing, time is physical, and the density scale
// cancels in grad p / rho, so c0^2 = k s^2:
//   c0 = 10 * spacing * sqrt(k),   k = (c0 / (10 * spacing))^2.
// Default PhysX (50 particles per metre, k = 20): c0 = 0.89 m/s.
Real physx_stiffness_to_sound_speed(Real stiffness, Real spacing);
Real sound_speed_to_physx_stiffness(Real sound_speed, Real spacing);

// Poiseuille's law: volume flow (m^3/s) of a vessel of radius r (m) and length
// L (m) under a pressure drop dp (Pa) with dynamic viscosity mu (Pa s):
//   Q = pi r^4 dp / (8 mu L).
Real poiseuille_flow_rate(Real radius, Real pressure_drop, Real viscosity, Real length);

// ---- parameters and the immutable fluid -----------------------------------------

// Shear-thinning blood (Carreau; Cho & Kensey, Biorheology 28, 1991; reference/tissues.md):
//   mu(g) = mu_inf + (mu0 - mu_inf) [1 + (lambda g)^2]^((n - 1) / 2),  g the shear rate (1/s)
struct Carreau {
  Real mu0 = 0.056;       // Pa s, zero-shear viscosity
  Real mu_inf = 0.00345;  // Pa s, infinite-shear viscosity, 0 <= mu_inf <= mu0
  Real lambda = 3.313;    // s, relaxation time, >= 0
  Real n = 0.3568;        // power index, (0, 1]
};
Real carreau_viscosity(const Carreau& c, Real shear_rate);
// Shear rate g >= 0 with carreau_viscosity(c, g) g = stress (monotone for n > 0).
Real carreau_shear_rate(const Carreau& c, Real stress);
// Steady flow rate (m^3/s) of a Carreau fluid through a pipe of radius r and
// length L under a pressure drop dp: the wall stress dp r / (2L) falls linearly
// to the axis, Q = pi integral_0^r s^2 g(dp s / 2L) ds (Rabinowitsch-Mooney).
// For n = 1 or lambda = 0 it is Poiseuille's law with mu0.
Real carreau_pipe_flow_rate(Real radius, Real pressure_drop, Real length, const Carreau& c);

enum class Rheology { newtonian, carreau };
const char* to_string(Rheology r);

// How the pressure is found:
// - eos: weakly compressible SPH, p from the equation of state; the substep
//   is bound by the sound speed, cfl h / (c0 + |v|max);
// - pcisph: predictive-corrective incompressible SPH (Solenthaler & Pajarola
//   2009). Each substep starts from p = 0 and iterates: predict every
//   particle's position from its current accelerations, sum the density
//   there (over the substep's lists, walls included), raise its pressure by
//   delta (rho* - rho0) (clamped at 0), recompute the accelerations; until the
//   largest predicted compression rho*/rho0 - 1 is at most pcisph_tolerance
//   (and at least pcisph_min_iterations corrections). delta is
//   rho0^2 / (2 h^2 m^2 gradient_scale sum |grad W|^2) over the rest lattice.
//   The sound speed leaves the CFL limit, cfl h / |v|max; the substep also
//   follows the solver: a solve that does not converge in
//   pcisph_max_iterations is redone at half the substep, unless the fluid was
//   compressed already (its worst particle at the substep's start, or the
//   compression predicted without pressure no longer shrinks): then the solve
//   is taken as it is and counted. Nor is it halved below the substep the
//   EOS would take at the same c0, cfl h / (c0 + |v|max) (there one EOS pass
//   is the cheaper solver; an unreachable tolerance ratcheted the substep
//   down without end before, each redo's h starting the next substep, and
//   the corrections over a vanishing substep threw particles out); the next
//   substep is not sized below it either. A solve that cycles between two states
//   (a particle beside walls whose response to its own pressure is more than
//   twice delta overshoots; with the clamp at 0 it flips back and forth) stops
//   after pcisph_stall_repeats repeats and is treated as one not converged.
//   The next substep is sized for about
//   pcisph_target_iterations corrections. c0 still sets the artificial
//   viscosity. The pressures are a partly converged
//   iterate: their noise is about delta rho0 tolerance (docs/sph.md).
enum class PressureSolver { eos, pcisph };
const char* to_string(PressureSolver p);

struct FluidParams {
  Real rest_density = 1060;   // kg/m^3, rho0 (blood, reference/tissues.md)
  Real viscosity = 0.003;     // Pa s, dynamic viscosity mu (3 cP, the paper), >= 0; newtonian rheology
  // carreau: each particle's viscosity follows its shear rate sqrt(2 D:D), D the
  // strain rate from the velocity gradient (renormalised SPH gradient, exact for a
  // linear field); pairs use mu_i + mu_j in place of 2 mu, walls the particle's mu.
  // `viscosity` is then unused by the forces; the viscous substep limit uses mu0.
  Rheology rheology = Rheology::newtonian;
  Carreau carreau;
  Real spacing = 0.002;       // m, rest particle spacing dx (PhysX: 1 / restParticlesPerMeter)
  Real support_ratio = 2.0;   // kernel support radius H / spacing, [1.5, 4]; 2: ~33 neighbours
  std::array<Real, 3> gravity{0, -9.81, 0};  // m/s^2, any body acceleration
  // Equation of state, physical mode (physx_stiffness == 0):
  Eos eos = Eos::tait;
  int tait_gamma = 7;         // [1, 7]
  Real sound_speed = 0;       // m/s, c0; 0 = 10 * max_speed
  Real max_speed = 1.0;       // m/s, largest expected speed (flow, or sqrt(2 g depth) for a pool)
  // PhysX-compatible mode (> 0): linear EOS with c0 = physx_stiffness_to_sound_speed(physx_stiffness, spacing);
  // sound_speed must then be 0. The paper's value is 20.
  Real physx_stiffness = 0;
  // Pressure solver (see PressureSolver); pcisph needs the physical mode
  // (physx_stiffness == 0).
  PressureSolver pressure_solver = PressureSolver::eos;
  Real pcisph_tolerance = 0.01;    // largest predicted rho*/rho0 - 1 a substep accepts, (0, 0.5]
  int pcisph_min_iterations = 3;   // [1, pcisph_max_iterations]
  int pcisph_target_iterations = 20;  // corrections the substep is sized for, [1, pcisph_max_iterations]
  int pcisph_max_iterations = 100; // [1, 1000]; beyond, the solve is redone at half the substep
  // A solve whose largest predicted compression repeats the one two corrections
  // before (within 1e-3 of itself) this many times in a row cycles: it stops
  // (counted as stalled) and is redone at half the substep like one that ran
  // out of corrections; [0, 1000], 0 = never (it runs to pcisph_max_iterations).
  int pcisph_stall_repeats = 4;
  Real artificial_viscosity = 0.02;  // alpha of Monaghan (1992), [0, 1]; 0 = physical viscosity only
  Real damping = 0;           // 1/s, velocity damping v /= 1 + damping h per substep (settling), >= 0
  bool clamp_negative_pressure = true;  // p = max(p, 0): no tension at free surfaces
  Real collision_distance = 0.25;  // fraction of spacing: walls project particles to at least this distance
  // Substep limits: h <= cfl (H/2) / (c0 + v_max), force_cfl sqrt((H/2) / a_max),
  // viscous_cfl (H/2)^2 / nu, max_substep (0 = none).
  Real cfl = 0.4;
  Real force_cfl = 0.25;
  Real viscous_cfl = 0.125;
  Real max_substep = 0;       // s
  int max_substeps = 4096;    // per step; beyond, the rest of the step is skipped and counted
  // Work savers for moving triangle surfaces; both leave every result
  // unchanged (tests compare them bitwise with the plain path):
  // a surface's triangle grid bins each vertex with its box over the step
  // grown by surface_grid_slack H, and later steps keep it while every vertex
  // stays in its box, [0, 1] (0: rebuilt whenever a vertex has moved);
  Real surface_grid_slack = 0.125;
  // the density pass reads the triangle contacts the drift's collision tests
  // found at the same position and time (false: it queries again).
  bool reuse_wall_contacts = true;
  // Verlet neighbour lists: the lists are built out to (1 + neighbour_skin) H
  // and kept through later substeps (and steps) while no particle has moved
  // more than neighbour_skin H / 2 since, and the particles are the same ones
  // in the same order; [0, 1], 0 = rebuilt every substep. The same pairs
  // within H as a fresh build, summed in another order, and the force pass's
  // float positions are relative to the build's grid origin: its pair terms
  // round differently (~1e-7 of themselves, as for any other origin). A build
  // lists without the skin where it cannot pay: right after particles were
  // added or removed (an active emitter, a drain: the next substep rebuilds
  // anyway), or where the fastest particle moved more than a quarter of the
  // skin over the last substep (a jet in the soft PhysX fluid, whose CFL
  // substep lets it move ~0.2 H).
  Real neighbour_skin = 0.1;
};

// Wall sums for a particle at distance d = q H from a plane wall, tabulated
// at make_fluid for q in [0, 1] (n + 1 entries, linear interpolation): sums
// over the sites of the particle's rest lattice that lie beyond the wall
// (lateral offsets (i, j) dx, normal distances d + dx/2 + k dx), each of
// volume V = m / rho0, so that a rest lattice beside a wall has rho = rho0
// and is in balance under a uniform pressure (semi-analytic walls in the
// spirit of Kulasegaram et al. 2004 and Ferrand et al. 2013, summed rather
// than integrated):
//   f0(q) = V sum W                                     (wall share of the kernel sum, ~1/2 at q = 0)
//   g0(q) = gradient_scale V sum (-grad W).n   * H      (= -gradient_scale d f0 / dq)
//   g1(q) = gradient_scale V sum z (-grad W).n          (z = normal distance to the site)
//   vm(q) = viscous_scale V sum beta (r.grad W) / (r^2 + eta^2) * H^2, beta = min(2, 1 + d'/d)
//           (Morris et al. 1997 extrapolated no-slip velocity, d' = the site's depth beyond the wall;
//           their cap of 1.5 leaves a slip of ~0.18 dx at H = 2 dx)
//   av(q) = gradient_scale V sum g z^2 / (r^2 + eta^2) * H^2 (the artificial viscosity of the
//           mirrored sites, whose velocity is the particle's reflected in the wall)
struct WallTables {
  int n = 0;
  std::vector<Real> f0, g0, g1, vm, av;
  // value at q (clamped to [0, 1])
  static Real at(const std::vector<Real>& t, int n, Real q);
};

struct Fluid {
  FluidParams params;  // as given (validated)
  Real H = 0;          // m, kernel support radius
  Real h = 0;          // m, smoothing length H / 2 (the substep limits use it)
  Real mass = 0;       // kg per particle: rho0 / (lattice kernel sum), so a rest lattice has rho = rho0 exactly
  Real volume = 0;     // m^3 per particle, mass / rho0 (~ spacing^3)
  Real c0 = 0;         // m/s, speed of sound
  Real physx_stiffness = 0;  // the PhysX stiffness equivalent to c0 at this spacing
  Eos eos = Eos::tait; // linear in PhysX-compatible mode
  Real nu = 0;         // m^2/s, kinematic viscosity mu / rho0
  Real expected_density_variation = 0;  // (max_speed / c0)^2, the EOS's dynamic compression
  Real lattice_sum = 0;  // 1/m^3, sum of W over the rest cubic lattice
  // Lattice calibration of the pair forces (a scalar form of the gradient
  // correction of Bonet & Lok 1999): the pressure and artificial-viscosity
  // terms are multiplied by gradient_scale = 1 / (V sum_j g_ij x_ij^2) and
  // the Morris viscosity by viscous_scale = 1 / (V sum_j g_ij r^2 x^2 / (r^2 + eta^2))
  // over the rest lattice, so a linear pressure field and a quadratic
  // velocity field are differentiated exactly there. Symmetric in (i, j):
  // momentum is still conserved.
  Real gradient_scale = 1;
  Real viscous_scale = 1;
  Real viscous_limit = 0;  // s, viscous_cfl h^2 / nu (inf when nu = 0)
  Real lattice_grad2 = 0;  // 1/m^8, sum |grad W|^2 over the rest lattice (pcisph's delta)
  WallTables walls;
};

// Validates p and derives the constants. Throws Error("", "fluid: <what>") on
// the first invalid value.
Fluid make_fluid(const FluidParams& p);
void validate(const FluidParams& p);

// ---- boundaries (immutable) -------------------------------------------------------

// How a wall treats particles: pressure and no-slip viscosity from the wall
// integrals, and a projection to collision_distance with restitution e
// (normal velocity -> -e v_n) and Coulomb friction (tangential change at most
// friction * (1 + e) |v_n|, never reversing).
struct WallParams {
  Real restitution = 0;  // [0, 1]
  Real friction = 0;     // >= 0
  bool slip = false;     // true: no viscous wall term (free slip)
};

enum class Face : std::uint8_t { wall, open, periodic };

// A half-space wall: fluid where normal . (x - point) >= 0.
struct FluidPlane {
  std::array<Real, 3> point{0, 0, 0};
  std::array<Real, 3> normal{0, 1, 0};  // normalised by add_plane
  WallParams wall;
};

// A uniform grid of triangles (bounding boxes inflated by a margin), built in
// O(n) by counting sort: cell c lists items [start[c], start[c + 1]).
struct TriangleCells {
  Real margin = 0;                  // m, every triangle within margin of a cell's point is listed in it
  std::array<Real, 3> origin{0, 0, 0};
  Real cell = 1;
  std::array<std::int32_t, 3> dims{0, 0, 0};
  std::vector<std::int32_t> start;  // (n_cells + 1)
  std::vector<std::int32_t> items;  // triangle ids
};

// Two levels over the same triangles: margin H (any contact) and H / 2 (a
// query that already has a contact that near reads a few candidates only).
// Each vertex has the box it was binned with (its positions over the build's
// step, grown by a slack); a later step reuses the grid while every vertex
// stays in its box and the triangles and their listing are unchanged.
struct TriangleGrid {
  std::array<TriangleCells, 2> level;
  std::vector<std::uint8_t> listed;      // (n_triangles) 1 where the triangle is in the grid (valid, not degenerate)
  std::vector<Real> vertex_box;          // (n_vertices x 6) m, lo xyz, hi xyz: the boxes the vertices were binned with
  std::vector<std::int32_t> triangles;   // (n_triangles x 3) the triangles binned
  std::int64_t builds = 0, reuses = 0;   // counters: grids built, steps that reused one
};

// A static triangle mesh wall (a tray, a bone). One-sided meshes keep fluid on
// the side of the counter-clockwise normal (closed surfaces oriented
// outward); two-sided meshes keep each particle on the side it came from.
struct FluidMesh {
  std::vector<Real> vertices;           // (n_vertices x 3) m
  std::vector<std::int32_t> triangles;  // (n_triangles x 3)
  WallParams wall;
  bool two_sided = false;
  TriangleGrid grid;                    // built by add_mesh
};

struct FluidBoundaries {
  std::array<Real, 3> lo{-1, -1, -1}, hi{1, 1, 1};  // m, the domain; particles outside are removed
  std::array<Face, 6> faces{Face::wall, Face::wall, Face::wall, Face::wall, Face::wall, Face::wall};  // -x +x -y +y -z +z
  WallParams box_wall;                  // the faces that are walls
  std::vector<FluidPlane> planes;       // further half-space walls
  std::vector<FluidMesh> meshes;        // static triangle walls
};

// A closed box [lo, hi], every face a wall (set faces[k] to open or periodic after).
FluidBoundaries make_box_boundaries(const std::array<Real, 3>& lo, const std::array<Real, 3>& hi);
void add_plane(FluidBoundaries& b, FluidPlane plane);  // normalises the normal; throws Error on a zero normal
// Validates the mesh (indices, finite coordinates) and builds its grid for the
// fluid's support radius. Throws Error("", "fluid mesh: ...").
void add_mesh(FluidBoundaries& b, FluidMesh mesh, const Fluid& fluid);
// Throws Error("", "<what>: ...") unless vertices and triangles are (n x 3)
// arrays, the coordinates finite and every index a vertex.
void validate_triangle_mesh(std::span<const Real> vertices, std::span<const std::int32_t> triangles, const char* what);
// The grid of a static triangle set, as add_mesh builds a FluidMesh's with
// margin = the fluid's H: for other queries of the same kind of walls (the
// tissue's obstacles, runtime/obstacles.h). Indices must be valid; degenerate
// triangles are left out (TriangleGrid::listed).
void build_static_triangle_grid(std::span<const Real> vertices, std::span<const std::int32_t> triangles, Real margin,
                                TriangleGrid& g);
// [begin, end) of g.items: the triangles listed in the cell of p (every
// triangle within g.margin of p is among them); empty outside the grid.
std::pair<std::int32_t, std::int32_t> cell_candidates(const TriangleCells& g, const Vec3& p);
// The point of triangle abc closest to p (Ericson 2005, 5.1.5).
Vec3 closest_point_on_triangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c);
// Throws Error("", "fluid boundaries: ...") for an empty box, periodic faces
// not in pairs, or a periodic length below 3 H.
void validate(const FluidBoundaries& b, const Fluid& fluid);

// ---- inputs a caller changes between steps ---------------------------------------

enum class EmitterProfile : std::uint8_t { plug, parabolic };

// A disc emitting particles along `direction` at volume flow `flow_rate`.
// Law: the disc carries a square lattice of spacing dx; lattice point k moves
// at u_k (plug: Q / (pi r^2); parabolic: 2 Q / (pi r^2) (1 - rho_k^2 / r^2),
// rescaled so sum u_k = n Q / (pi r^2)) and emits a particle each time it has
// travelled l = n V / (pi r^2) (V the particle volume), at the distance it has
// travelled beyond the disc, with velocity u_k direction. The emitted volume
// per second is n V sum(u_k) / (n l) = Q exactly in the mean.
struct FluidEmitter {
  std::array<Real, 3> center{0, 0, 0};     // m
  std::array<Real, 3> direction{0, 1, 0};  // jet direction (normalised when used)
  Real radius = 0.002;                     // m, > 0
  Real flow_rate = 0;                      // m^3/s, Q >= 0 (poiseuille_flow_rate gives it from a pressure drop)
  EmitterProfile profile = EmitterProfile::plug;
  Real start = 0;                          // s, active for start <= t < end
  Real end = std::numeric_limits<Real>::infinity();
  bool enabled = true;
  // state
  std::vector<Real> travelled;             // (n_points) m since each point's last particle
  std::int64_t emitted = 0;                // particles
  Real emitted_volume = 0;                 // m^3
};

// A sphere removing the particles inside it (the paper's draining tool).
struct FluidDrain {
  std::array<Real, 3> center{0, 0, 0};  // m, may move between steps
  Real radius = 0.005;                  // m
  bool enabled = true;
  std::int64_t drained = 0;             // particles removed, accumulated
  Real drained_volume = 0;              // m^3 (particles * rest volume)
};

// A triangle surface moved by the caller (the tissue skin): set x and v before
// each step; the fluid treats it as a wall moving at v through the step
// (vertex at x + v t) and returns in `force` the mean force the fluid
// exerted on each vertex over the step (N): the reaction to every wall
// acceleration and collision impulse it gave particles, split by the
// barycentric weights of the contact point. Equal and opposite: the
// particles' momentum change from the surface is -sum(force) dt.
struct FluidSurface {
  std::vector<std::int32_t> triangles;  // (n_triangles x 3), fixed topology
  std::vector<Real> x;                  // (n_vertices x 3) m, at the step's start (input)
  std::vector<Real> v;                  // (n_vertices x 3) m/s, through the step (input; empty = at rest)
  WallParams wall;
  bool two_sided = false;
  std::vector<Real> force;              // (n_vertices x 3) N, output of the last step
  TriangleGrid grid;                    // scratch, rebuilt when the surface has left it (TriangleGrid)
};

// ---- neighbour grid (shared with the surface extraction and the tests) ------------

// A flat uniform cell grid over points, built by counting sort (count, prefix
// sum, fill). Cells are at least `radius` wide, so the neighbours of a point
// lie in its cell and the 26 around it; x varies fastest, so the three cells
// (cx-1..cx+1) of a row are contiguous in sorted order. On periodic axes the
// grid spans [lo, hi) exactly and neighbours wrap with a shift of the period.
struct NeighbourGrid {
  std::array<Real, 3> origin{}, cell{};
  std::array<std::int32_t, 3> dims{};
  std::array<Real, 3> period{};        // m, > 0 on periodic axes
  std::vector<std::int32_t> start;     // (n_cells + 1) first sorted slot of each cell
  std::vector<std::int32_t> order;     // (n) sorted slot -> input index
  std::vector<std::int32_t> occupied;  // non-empty cells, ascending
  // the occupied cells' sorted slots in pieces of at most kPieceSlots, in
  // slot order: the SPH passes' work items, so that a crowded cell (a pool
  // of soft blood holds hundreds of particles a cell) is shared among tasks
  struct Piece {
    std::int32_t cell, begin, end;
  };
  static constexpr std::int32_t kPieceSlots = 32;
  std::vector<Piece> pieces;
  std::vector<std::int32_t> point_cell;  // (n) scratch: cell of each input point
  std::int64_t n_cells() const { return static_cast<std::int64_t>(dims[0]) * dims[1] * dims[2]; }
  std::int32_t cell_of(Real x, Real y, Real z) const;  // clamped into the grid
};

// Builds the grid over (x[i], y[i], z[i]), i < n. Periodic axes (lo[a] < hi[a]
// with periodic[a]) need hi - lo >= 3 radius. The number of cells is kept
// below max(4 n, 4096) by widening cells on non-periodic axes.
void build_neighbour_grid(const Real* x, const Real* y, const Real* z, std::int64_t n, Real radius,
                          const std::array<Real, 3>& lo, const std::array<Real, 3>& hi,
                          const std::array<bool, 3>& periodic, NeighbourGrid& g);

// A contiguous run of sorted slots [begin, end) whose points are offset by
// `shift` (the periodic image) as seen from the querying cell.
struct NeighbourRun {
  std::int32_t begin, end;
  Real sx, sy, sz;
};
// The runs covering the 27 cells around `cell` (at most 27, 9 without wrap
// in x). Returns their number.
int neighbour_runs(const NeighbourGrid& g, std::int32_t cell, NeighbourRun* runs /* [27] */);

// ---- state -------------------------------------------------------------------------

struct FluidCounters {
  std::int64_t steps = 0;            // fluid_step calls that ran
  std::int64_t substeps = 0;
  std::int64_t emitted = 0;          // particles
  std::int64_t left_domain = 0;      // removed: outside the domain box or deep inside an open face
  std::int64_t drained = 0;          // removed by drains
  std::int64_t nonfinite = 0;        // removed: NaN or Inf position / velocity
  std::int64_t collisions = 0;       // wall projections
  std::int64_t truncated_steps = 0;  // steps that hit max_substeps (the rest of the step skipped)
  std::int64_t invalid_steps = 0;    // refused: dt not finite or <= 0
  std::int64_t contacts_reused = 0;  // particle-substeps whose density pass read the drift's triangle contacts
  std::int64_t list_builds = 0;      // substeps that sorted the particles and built the neighbour lists
  std::int64_t list_reuses = 0;      // substeps that kept the last lists (neighbour_skin)
  std::int64_t pressure_solves = 0;       // pcisph: solves, the redone ones included
  std::int64_t pressure_iterations = 0;   // pcisph: corrections, all substeps
  std::int64_t pressure_unconverged = 0;  // pcisph: solves taken unconverged (after 10 halvings, at the EOS substep, or where halving cannot help)
  std::int64_t pressure_retries = 0;      // pcisph: solves redone at half the substep (not converged)
  std::int64_t pressure_stalled = 0;      // pcisph: solves stopped early, cycling between two states (then redone or taken)
  // substeps by the limit that set their length (fluid_step spreads the rest
  // of a step evenly, so a substep is shorter than the limit, never longer):
  // [0] none (the rest of the step fits), [1] CFL, sound and flow speed
  // (cfl h / (c0 + |v|max)), [2] force (force_cfl sqrt(h / |a|max)),
  // [3] viscous (viscous_limit), [4] max_substep,
  // [5] pressure (pcisph: the length its solver asked for, or a halving)
  std::array<std::int64_t, 6> substep_limit{};
  // Wall time (s) of fluid_step's phases, all steps (steady clock, read
  // around each phase of each substep): [0] prepare (sort, neighbour grid and
  // lists, the walls' triangle grid), [1] density (with the walls' share),
  // [2] forces (with the walls'), [3] pressure (pcisph's corrections),
  // [4] integrate (with the collisions against the walls), [5] emit and
  // compact. Names: fluid_phase_name.
  std::array<double, 6> phase_s{};
  Real emitted_volume = 0;           // m^3
  Real drained_volume = 0;           // m^3
  Real lost_volume = 0;              // m^3, left the domain or non-finite
};

// What one step did.
// Names of FluidCounters::substep_limit's entries: "step", "cfl", "force", "viscous", "max_substep", "pressure".
const char* substep_limit_name(int k);
// Names of FluidCounters::phase_s's entries: "prepare", "density", "forces", "pressure", "integrate", "emit".
const char* fluid_phase_name(int k);

struct FluidStepInfo {
  int substeps = 0;
  bool truncated = false;
  Real min_substep = 0, max_substep = 0;  // s
  Real max_compression = 0;   // max (rho / rho0 - 1) over particles and substeps
  Real max_predicted_compression = 0;  // pcisph: the largest last predicted rho*/rho0 - 1 of the substeps
  std::int64_t pressure_iterations = 0;  // pcisph: corrections in this step
  Real mean_neighbours = 0;   // particles within H, self included, last substep
  Real max_speed = 0;         // m/s, at the end
  std::int64_t removed = 0;   // particles removed in this step
  std::int64_t emitted = 0;
};

// Per-substep scratch (never read across steps).
struct FluidScratch {
  NeighbourGrid grid;                   // of the last sort; particles are in its sorted order
  std::array<std::vector<Real>, 6> perm; // (6)(n) permutation buffers of x and v
  std::vector<std::int64_t> tmp_id;     // (n)
  std::array<std::vector<Real>, 3> a;   // (3)(n) m/s^2, particle forces / mass
  std::array<std::vector<Real>, 3> aw;  // (3)(n) m/s^2, of which from walls
  std::array<std::vector<Real>, 3> pred; // (3)(n) m, pcisph: predicted positions
  std::vector<Real> pred_sum;           // (n) pcisph: kernel sums there
  std::vector<std::uint8_t> near;       // (n) 1 where a wall may be within H
  std::vector<Real> psum;               // (n) Pa, the walls' Shepard pressure sums (where near)
  std::vector<Real> inv_rho;            // (n) 1 / rho
  std::vector<Real> mu;                 // (n) Pa s, per-particle viscosity (carreau rheology only)
  std::vector<Real> neighbours;         // (n) particles within H, self included
  std::vector<Real> ksum;               // (n) kernel sum (the walls' Shepard pressure sums are taken on demand)
  std::vector<float> pack;              // (n x 8) x, y, z (- grid origin), p / rho^2, vx, vy, vz, 1 / rho in
                                        // single precision: the force pass's gathers
  std::array<std::vector<float>, 3> xf; // (3)(n + 8) m, positions relative to the grid origin in single
                                        // precision: the neighbour search and the force pass's pack
  std::vector<std::int32_t> list;       // (n x 100) neighbour lists of the density pass
  std::vector<std::int32_t> count;      // (n) their lengths
  // the lists' build (FluidParams::neighbour_skin): the positions and ids
  // then, the kernel support and the skin (m) they were built for; reusable
  // is false where none may be kept (no skin, a list overflowed)
  std::array<std::vector<Real>, 3> list_x;
  std::vector<std::int64_t> list_id;
  Real list_H = 0, list_skin = 0;
  bool list_reusable = false;
  bool set_changed = false;             // particles were added or removed since the last build
  Real substep_motion = 0;              // m, |v|max h of the last substep (its force pass's top speed)
  std::vector<std::uint8_t> dead;       // (n) removal reason, 0 = alive
  std::vector<std::int32_t> wall_hint;  // (n x triangle walls) each particle's closest triangle at its last
                                        // collision test, or -1: the next query's first guess (speed only)
  std::vector<std::int32_t> tmp_hint;   // (n x triangle walls) permutation buffer
  std::vector<Real> reactions;          // surface reaction records of the substep
};

struct FluidState {
  Real time = 0;                          // s
  std::array<std::vector<Real>, 3> x;     // (3)(n) m, positions, component-major: x[0][i] is x of particle i
  std::array<std::vector<Real>, 3> v;     // (3)(n) m/s, velocities
  std::vector<Real> rho;                  // (n) kg/m^3, density of the last substep
  std::vector<Real> p;                    // (n) Pa, pressure of the last substep
  Real pressure_substep = 0;              // s, pcisph: the substep its solver asked for last (0: none yet)
  std::vector<std::int64_t> id;           // (n) stable particle ids (the order may change at any substep)
  std::int64_t next_id = 0;
  std::vector<FluidEmitter> emitters;
  // Emitters stop at this many particles, within a substep (0 = no cap); a
  // point of an emitter that is held back keeps at most one particle due.
  std::int64_t max_particles = 0;
  std::vector<FluidDrain> drains;
  std::vector<FluidSurface> surfaces;
  FluidCounters counters;
  FluidStepInfo last;
  FluidScratch scratch;
  std::int64_t size() const { return static_cast<std::int64_t>(id.size()); }
};

FluidState make_fluid_state();

// Appends particles at xyz (n x 3, interleaved) with velocities vel (n x 3 or
// empty = at rest). Their density is rho0 until the next step.
void add_particles(const Fluid& f, FluidState& s, std::span<const Real> xyz, std::span<const Real> vel = {});
// Fills [lo, hi] with a cubic lattice of spacing dx at (i + 1/2) dx from lo.
// Returns the number of particles added.
std::int64_t fill_box(const Fluid& f, FluidState& s, const std::array<Real, 3>& lo, const std::array<Real, 3>& hi,
                      const std::array<Real, 3>& velocity = {0, 0, 0});

// Fills the ball of radius r about c with the cubic lattice at c + (i + 1/2) a,
// at rest; a = lattice (0: the fluid's spacing; smaller: compressed). Returns
// the number of particles added: none for a negative or non-finite radius or
// one of 10^4 spacings or more.
std::int64_t fill_ball(const Fluid& f, FluidState& s, const std::array<Real, 3>& c, Real r, Real lattice = 0);

// Advances the state by dt (s) with substeps inside; never throws.
FluidStepInfo fluid_step(const Fluid& f, FluidState& s, Real dt, const FluidBoundaries& b);

// Sorts the particles into cell order and computes rho and p without moving
// anything (diagnostics, tests, a first frame's output).
void fluid_update_density(const Fluid& f, FluidState& s, const FluidBoundaries& b);

// Largest substep the limits allow now (s); runs the density and force passes.
Real fluid_substep_limit(const Fluid& f, FluidState& s, const FluidBoundaries& b);

// ---- diagnostics ---------------------------------------------------------------------

std::vector<Real> fluid_positions(const FluidState& s);  // (n x 3) interleaved, m
std::uint64_t fluid_state_hash(const FluidState& s);     // FNV-1a of time, x, v, id
std::array<Real, 3> fluid_momentum(const Fluid& f, const FluidState& s);  // kg m/s
Real fluid_kinetic_energy(const Fluid& f, const FluidState& s);           // J
Real fluid_volume(const Fluid& f, const FluidState& s);                   // m^3, n * rest volume

}  // namespace orthosim::runtime
