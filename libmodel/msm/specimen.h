// The virtual experiment shared by build's tests and by tune (issue 7): a
// block of a layer made by the same cell builders and spring classes as the
// real model, its static equilibrium under prescribed displacements, and a
// uniaxial stretch test that records nominal stress against strain.
//
//   auto s = msm::make_specimen(msm::SpecimenOptions{});     // 4x4x4 cubic lattice cells of 1 mm
//   msm::apply_law(s, {k1_pa, k2_pa, turning_strain});       // the tissue's moduli through the rule
//   auto curve = msm::uniaxial_test(s, {0.01, 0.02, ...}, {});
//
// Static solve: Newton's method on the total spring energy with the exact
// tangent (a modified tangent with compressive geometric terms dropped where
// the exact one is not positive definite), sparse LDL^T (Eigen
// SimplicialLDLT) on the free degrees of freedom, Armijo backtracking on the
// energy. Converged when every free component of the residual force is below
// force_tolerance x the largest spring force, or below the round-off floor
// 256 eps max(k L) of the force evaluation; not a dynamic relaxation that may
// stop early.
#pragma once

#include "libmodel/format/model.h"
#include "libmodel/msm/biphasic.h"
#include "libmodel/msm/lattice.h"
#include "libmodel/msm/tetra.h"

#include <array>
#include <cstdint>
#include <string>
#include <vector>

namespace orthosim::msm {

// A network of biphasic springs (k2 == k1 and turning_length == rest_length
// for linear ones), positions at rest.
struct SpringNetwork {
  MatX3d nodes;           // (n_nodes x 3) m
  MatX2i springs;         // (n_springs x 2) node ids
  VecXd rest_length;      // (n_springs) m
  VecXd k1;               // (n_springs) N/m
  VecXd k2;               // (n_springs) N/m, total slope past the turning length
  VecXd turning_length;   // (n_springs) m
  // the volume term (Layer::volume_modulus), one per group of consecutive
  // tetrahedra (a tetra layer's each tetrahedron, a lattice layer's the 6 of
  // each hexahedron; Layer::volume_group): group g
  // adds (tet_k(g) / 2) (V - V0)^2 / |V0| with V, V0 the sums of its
  // tetrahedra's volumes; empty tets: none
  MatX4i tets;            // (n_tets x 4) node ids
  VecXd tet_rest_volume;  // (n_tets) m^3, signed rest volume of each tetrahedron
  VecXi tet_group_first;  // (n_groups + 1) the groups' first tetrahedra; empty: one group per tetrahedron
  VecXd tet_k;            // (n_groups) Pa
  Eigen::Index n_volume_groups() const { return tet_group_first.size() ? tet_group_first.size() - 1 : tets.rows(); }
};

// The volume term of one tetrahedron, V = det[b-a, c-a, d-a] / 6: its
// energy (k/2)(V - V0)^2/|V0| (J), the gradient (4 x 3, N: row c is dE/dx_c)
// and the Hessian (12 x 12, corners a, b, c, d), exact: (k/|V0|) g g^T +
// k (V - V0)/|V0| d2V, with g = dV/dx (4 x 3). `gauss_newton` drops the second
// term, which is indefinite (the positive semi-definite part alone).
struct TetVolumeTerm {
  double energy = 0, volume = 0;
  Eigen::Matrix<double, 4, 3> gradient;
  Eigen::Matrix<double, 12, 12> hessian;
};
TetVolumeTerm tet_volume_term(const Eigen::Matrix<double, 4, 3>& x, double rest_volume, double k, bool gauss_newton = false);

// The same for group g of a network (SpringNetwork::tet_group_first): its
// distinct nodes, and the energy, gradient (3 per node, in `nodes` order) and
// Hessian (exact, or its Gauss-Newton part) of its one volume term. At most
// kMaxGroupNodes nodes (a hexahedron's 8; more is an Error), so that the
// static solver's many calls allocate nothing.
inline constexpr int kMaxGroupNodes = 8;
struct GroupVolumeTerm {
  Eigen::Matrix<int, Eigen::Dynamic, 1, 0, kMaxGroupNodes, 1> nodes;
  double energy = 0, volume = 0, rest_volume = 0;
  Eigen::Matrix<double, Eigen::Dynamic, 1, 0, 3 * kMaxGroupNodes, 1> gradient;
  Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 3 * kMaxGroupNodes, 3 * kMaxGroupNodes> hessian;
};
GroupVolumeTerm group_volume_term(const SpringNetwork& net, const MatX3d& x, Eigen::Index group, bool gauss_newton,
                                  bool want_hessian);

// The volume term's modulus over K1 for a tissue of Poisson's ratio nu
// (docs/msm.md, "The volume term"): the bulk modulus K = E / (3 (1 - 2 nu))
// less the 2 E / 3 that central springs of Poisson's ratio 1/4 carry,
// 1 / (3 (1 - 2 nu)) - 2 / 3; 0 at nu = 1/4, 16 at nu = 0.49. Throws Error
// unless 1/4 <= nu < 1/2.
double volume_ratio(double poisson_ratio);
// The bulk modulus over K1, 1 / (3 (1 - 2 nu)): the inversion guard's modulus
// (Layer::guard_modulus). Throws Error unless 1/4 <= nu < 1/2.
double bulk_ratio(double poisson_ratio);

struct StaticOptions {
  double force_tolerance = 1e-10;  // relative to the largest spring force, (0, 1e-3]
  int max_iterations = 60;
};

struct StaticResult {
  MatX3d x;               // (n_nodes x 3) m, equilibrium positions
  VecXd reaction;         // (3 n_nodes) N: force the constraints exert, non-zero at prescribed dofs only
  int iterations = 0;
  double residual = 0;    // largest free residual force (N)
  double force_scale = 0; // largest spring force (N)
  bool converged = false;
};

// Equilibrium with the dofs `prescribed` (3*node + axis) displaced by
// `displacement` (m) from the rest positions and every other dof free of
// external force. `start`: an initial guess (positions), or null for the rest
// state. Throws Error("", ...) if the free part of the network is a mechanism
// (singular stiffness) or the arguments are inconsistent. Deterministic.
StaticResult solve_static(const SpringNetwork& net, const std::vector<std::int64_t>& prescribed,
                          const std::vector<double>& displacement, const MatX3d* start,
                          const StaticOptions& options);

struct SpecimenOptions {
  std::string kind = "lattice";          // "lattice" | "tetra"
  std::array<int, 3> cells{4, 4, 4};     // along x, y, z in 1..200; tetra: one prism layer, cells[2] sets its height
  std::array<double, 3> cell_m{1e-3, 1e-3, 1e-3};  // cell size along x, y, z (m), > 0
  bool body_diagonals = false;           // lattice only
  double lattice_min_weight = 0.01;      // lattice only: the rule's floor (LatticeOptions::min_weight)
  ProjectionOptions projection;          // tetra only
  bool lattice_axis_correction = true;   // lattice only: LatticeOptions::axis_correction
  std::array<double, 3> tetra_axis_factors{1, 1, 1};  // tetra only: TetraOptions::axis_factors
  bool tetra_alternate_diagonals = false;  // tetra only: TetraOptions::alternate_diagonals
  // the volume term's modulus over the law's K1 (volume_ratio; 0: none);
  // apply_law sets network.tet_k to volume_ratio x K1. One term per
  // tetrahedron of a tetra layer, per hexahedron of a lattice layer (whose
  // axis correction allows for it), as build writes them
  double volume_ratio = 0;
  // tetrahedra per volume term (Layer::volume_group); 0: as build writes
  // them (tetra 1, lattice 6); a tetra layer's kTetsPerPrism is one term per
  // prism (docs/msm.md, "The volume term": it does not lock in bending, but
  // the layer loses its Poisson's ratio). The inversion guard is not
  // modelled: it does nothing until a tetrahedron has lost 1 - guard_ratio
  // of its volume, far beyond the specimens' strains.
  int volume_group = 0;
  // tetra only: the volume term over the layer's grid prisms and their caps
  // (grid_prism_tets: groups of kGridPrismTets, two a prism, each at
  // volume_ratio x K1, so volume_ratio is kGridPrismShare of the tissue's)
  // instead of over its cells' tetrahedra, as build writes it with
  // BuildOptions::tetra_volume_term "prisms" (docs/msm.md, "The volume term")
  bool tetra_grid_prisms = false;
};

// A block [0, X] x [0, Y] x [0, Z]: the top grid at z = Z, the bottom at z = 0,
// as a layer between two flat corresponding grids (u along x, v along y).
struct Specimen {
  SpecimenOptions options;
  SpringNetwork network;                // stiffness for E = 1 Pa until apply_law
  VecXd k_per_pa;                       // (n_springs) m: the rule's stiffness per unit modulus
  VecXu8 spring_class;                  // (n_springs) SpringClass
  VecXi cells;                          // (n_springs) cells sharing each spring (per-cell assembly: k = cells x k_cell)
  std::array<double, 3> size_m{0, 0, 0};
  double volume_m3 = 0;                 // sum of the cell volumes
  std::int64_t tets = 0;                // tetra: tetrahedra (7 per prism)
};

Specimen make_specimen(const SpecimenOptions& options);

// Sets k1, k2 and turning lengths from a tissue law through the rule:
// k1 = K1 k_per_pa, k2 = K2 k_per_pa, Lt = L0 (1 + turning strain), and the
// volume term's modulus to options.volume_ratio x K1. A linear law: k2_pa ==
// k1_pa, turning_strain = 0.
void apply_law(Specimen& s, const SpringLaw& law);

// The tetra axis factors (TetraOptions::axis_factors) that give a tetra
// specimen of these options (kind "tetra"; its tetra_axis_factors ignored)
// equal small-strain Young's moduli along x (u), y (v) and z (through the
// layer), each E: Broyden's method on log E_a(log s) from the fixed point's
// Jacobian (s_a <- s_a E / E_a), three linear uniaxial tests (strain 1e-4,
// sliding clamps) per iteration, until every modulus is within `tolerance`
// of E. The trace rule alone leaves the moduli
// of realistic prisms 0.57-1.6 E and unequal (docs/msm.md). Throws Error if
// it does not converge in max_iterations. Deterministic.
struct AxisCalibration {
  std::array<double, 3> factors{1, 1, 1};
  std::array<double, 3> moduli_before{0, 0, 0};  // E_u, E_v, E_w / E of the trace rule
  std::array<double, 3> moduli_after{0, 0, 0};   // with the factors
  int iterations = 0;
};
AxisCalibration calibrate_tetra_axes(SpecimenOptions options, double tolerance = 1e-3, int max_iterations = 60);

// The calibration build and tune both use for a tetra layer of mean cell
// a x b x h (m; mean_cell_shape): a flat specimen of kTetraCalibrationCells
// prisms of that shape with alternating diagonals. The same cell shape gives
// the same factors in both.
inline constexpr std::array<int, 3> kTetraCalibrationCells{6, 6, 1};
// volume_ratio: the layer's volume term (SpecimenOptions::volume_ratio), which
// the factors then account for.
// grid_prisms: the term over the grid prisms (SpecimenOptions::tetra_grid_prisms).
AxisCalibration tetra_layer_axes(const std::array<double, 3>& cell_m, double volume_ratio = 0, int volume_group = 0,
                                 bool grid_prisms = false);

// A layer's mean cell: the mean top-quad edge along u (q0q1, q3q2) and v
// (q1q2, q0q3), and the mean distance between corresponding top and bottom
// grid vertices (m). `quads` index both grids' rows.
std::array<double, 3> mean_cell_shape(const MatX3d& top, const MatX3d& bottom, const MatX4i& quads);

enum class Clamp {
  sliding,  // the two loaded faces keep their normal displacement only; lateral motion free (uniaxial stress)
  full,     // the two loaded faces are held in every direction (the ends cannot contract)
};

struct UniaxialOptions {
  int axis = 0;                  // load axis: 0 x, 1 y, 2 z
  Clamp clamp = Clamp::sliding;
  StaticOptions solver;
};

struct UniaxialCurve {
  std::vector<double> strain;          // nominal strain of each step
  std::vector<double> stress_pa;       // nominal stress: reaction on the moving face / initial area
  std::vector<double> lateral_strain;  // 2 per step: mean strain along the two other axes (from the side faces)
  std::vector<int> iterations;         // Newton iterations per step
  double max_residual = 0;             // largest final residual over the steps (N)
  double seconds = 0;
};

// Stretches the specimen along `axis` through the strain steps in order (each
// solve starts from the previous one). Throws Error if a step does not converge.
UniaxialCurve uniaxial_test(const Specimen& s, const std::vector<double>& strains, const UniaxialOptions& options);

}  // namespace orthosim::msm
