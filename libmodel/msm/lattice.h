// Lattice layers: hexahedral cells between corresponding quad grids, springs
// on the cell edges and face diagonals (and optionally body diagonals), and
// the rule that sets each spring's stiffness from the tissue's modulus.
//
// Stiffness rule (docs/msm.md derives and verifies it). Each cell adds to each
// of its springs
//     k = beta * E * V / l^2                                   (N/m)
// where V is the cell's volume, l the spring's rest length and beta a
// dimensionless weight per spring group of the cell: edges along u, v, w and
// face diagonals in the uv, vw and uw faces (body diagonals when enabled).
// The betas make the Cauchy-Born stiffness of the cell's equivalent box
// (a x b x c = mean edge lengths along u, v, w),
//     C_ijkl = (1/V) sum_springs k l^2 n_i n_j n_k n_l = E sum beta n_i n_j n_k n_l,
// equal to the isotropic tensor of modulus E and Poisson's ratio 1/4 (the
// only isotropic tensor a central-spring lattice can have: Cauchy relation
// C12 = C44). Closed form, exact whenever every edge weight is >= 0:
//     beta_uv = (a^2 + b^2)^2 / (10 a^2 b^2)                     (and cyclically)
//     beta_u  = (3 - a^2/b^2 - a^2/c^2) / 10                     (and cyclically)
// For a cube: beta_edge = 1/10, beta_face = 2/5, i.e. k_e = E a / 10 and
// k_f = E a / 5 per cell, the reference's per-element assembly
// (../shared/reference/lattice-elasticity.md), E = 5 k / (2 a) in the bulk.
// Elongated cells (a^2/b^2 + a^2/c^2 > 3 for some axis) cannot be isotropic:
// the betas are then the least-squares fit of the six orthotropic constants,
// each relative to its target, with every edge and face-diagonal weight at
// least min_weight times its cube value (1/10, 2/5). Without that floor the
// fit can drop whole families and leave a mechanism: a 2.4 : 5.7 : 1 cell
// (the phantom's fat at a 15 x 5 grid) loses its v edges and vw diagonals,
// and its vw faces shear freely. Any positive floor makes every cell rigid;
// 1 % costs at most a few per cent of misfit. RuleStats reports
// the residual and the moduli the cell will actually have.
#pragma once

#include "libmodel/msm/cells.h"

#include <Eigen/Core>

#include <array>

namespace orthosim::msm {

// Weights of one cell. k = beta * E * V / l^2 for each spring of the group.
struct CellRule {
  std::array<double, 3> edge{0, 0, 0};  // edges along u, v, w
  std::array<double, 3> face{0, 0, 0};  // face diagonals in the uv, vw, uw faces
  double body = 0;                      // body diagonals (only with body_diagonals)
  double residual = 0;                  // relative RMS misfit of the six constants (0 = exact), before the axis correction
  bool exact = true;
  // the axis correction (equal_moduli): every spring scaled by
  // sum_a s_a n_a^2 (n its unit direction in the cell's u, v, w frame)
  std::array<double, 3> axis_factors{1, 1, 1};
  // the volume term's modulus over E the axis correction allowed for (0:
  // none): cell_stiffness adds it to the normal block
  double volume_ratio = 0;
};

// Weights for a box cell a x b x c (m, each > 0). Edge and face-diagonal
// weights are at least min_weight (in [0, 1)) times their cube values.
// equal_moduli: where the fit is not exact, each spring's weight is then
// scaled by sum_a s_a n_a^2 with the axis factors s_u, s_v, s_w that make the
// cell's three Young's moduli exactly E (the least-squares fit leaves an
// elongated cell up to 1.45x stiffer along one axis; docs/msm.md). The
// shears and Poisson's ratios stay the fit's.
// volume_ratio: the cell's volume term (Layer::volume_modulus over E, one per
// hexahedron; docs/msm.md "The volume term"), whose Cauchy-Born stiffness
// volume_ratio delta_ij delta_kl adds to the springs'. With equal_moduli the
// axis factors then make the moduli of springs and term together E, for
// exact cells too (springs alone would leave them 1.19x stiff at
// volume_ratio 16).
CellRule cell_rule(double a, double b, double c, bool body_diagonals, double min_weight = 0.01,
                   bool equal_moduli = false, double volume_ratio = 0);

// The Cauchy-Born stiffness per unit E (Voigt 6x6, order 11 22 33 23 13 12)
// of an infinite lattice of a x b x c boxes with these weights.
Eigen::Matrix<double, 6, 6> box_stiffness(double a, double b, double c, const CellRule& r);

// box_stiffness plus the rule's volume term (r.volume_ratio on the normal
// block: C11..C33 and C12, C13, C23).
Eigen::Matrix<double, 6, 6> cell_stiffness(double a, double b, double c, const CellRule& r);

// Young's moduli along the three axes of a Voigt stiffness (1 / S_ii).
std::array<double, 3> axis_moduli(const Eigen::Matrix<double, 6, 6>& C);

struct LatticeOptions {
  int through_cells = 1;        // cells through the layer's thickness, [1, 64]; interior grids interpolate linearly
  bool body_diagonals = false;  // add the 4 body diagonals of each cell (docs/msm.md: they do not help)
  double min_weight = 0.01;     // floor of edge/face weights, times their cube values: no cell is a mechanism
  double inverted_ratio = 1e-9; // a cell whose Jacobian falls below this fraction of the mean cell volume is inverted
  bool axis_correction = true;  // cell_rule's equal_moduli: each cell's Young's moduli along u, v, w exactly E
  // the volume term's modulus over E (msm::volume_ratio of Poisson's ratio;
  // 0: none). > 0: the axis correction allows for it (cell_rule), and
  // LayerCells::tets holds each hexahedron's 6 tetrahedra (positively
  // oriented, in cell order: one volume term per 6, Layer::volume_group)
  double volume_ratio = 0;
  // LayerCells::tets also without a volume term (for the inversion guard,
  // Layer::guard_modulus): each hexahedron's 6 tetrahedra as above
  bool tets = false;
};

// Smallest Jacobian of the trilinear map of the hexahedron from the unit cube
// (volume units, = its volume for a box) over its 8 corners and its centre,
// the hexahedron "Jacobian" of the Verdict library (Knupp 2000; VTK's
// vtkMeshQuality). T = the top (outer) quad q0..q3, counter-clockwise seen
// from outside; B = the quad below it. <= 0: the cell is inverted there.
double hex_min_jacobian(const Eigen::Vector3d T[4], const Eigen::Vector3d B[4]);

// The cells of a lattice layer between `top` and `bottom` grids (same rows,
// same `quads`, outward counter-clockwise). Interior grids (through_cells-1 of
// them) are created at blocks.created + (k-1)*n_grid. Each hexahedron is cut
// into 6 tetrahedra (two prisms over the triangles q0q1q2, q0q2q3, side
// faces cut from the smaller id) for its volume, lumped V/8 per corner; it is
// inverted where hex_min_jacobian <= inverted_ratio x the mean cell volume (a
// sheared but valid hexahedron may have a sub-tetrahedron of negative volume:
// the split is a quadrature, the cell is the element).
LayerCells lattice_cells(const MatX3d& top, const MatX3d& bottom, const MatX4i& quads, const NodeBlocks& blocks,
                         const LatticeOptions& options);

}  // namespace orthosim::msm
