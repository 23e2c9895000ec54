// Test and benchmark models built in code: a layered lattice block like the
// paper's 39 x 9 grid with 4 layers, written as model-file `Layer`s.
//
// Geometry: `nu` x `nv` nodes per sheet (x along u, z along v), `layers`
// sheets along +y with the skin sheet at y = 0 and the bone sheet deepest.
// Layer i (order i, 0 = skin) owns sheet i's nodes, the springs inside sheet
// i and the springs between sheets i and i + 1; the last layer ("bone") owns
// only its sheet. Cells between sheets i and i + 1 carry tissue i.
//
// Springs: every hexahedral cell adds k = c E V / l^2 to its 12 edges
// (c = 1/10) and 12 face diagonals (c = 2/5), V its volume and l the
// spring's rest length: for cubic cells this is the isotropic assembly
// k_edge = E a / 10, k_face = E a / 5 per cell (nu = 1/4; see
// ../shared/reference/lattice-elasticity.md). A biphasic tissue (E2 > E)
// gives its springs k2 from E2 and turning length (1 + turning_strain) L0;
// contributions add. Damping c = 2 zeta sqrt(k1 mu), mu the reduced mass
// of the two ends. Masses: density x cell volume / 8 to each corner.
//
// Node sets: "fixed" (the bone sheet), "skin" (sheet 0), "layer_<name>".
// These are test fixtures with documented, not tuned, tissue values.
#pragma once

#include "libmodel/format/model.h"
#include "runtime/model.h"
#include "runtime/types.h"

#include <map>
#include <span>
#include <string>
#include <utility>
#include <vector>

namespace orthosim::runtime::testing {

struct LayeredBlockOptions {
  int nu = 39, nv = 9, layers = 4;        // nodes per sheet along x and z; sheets
  Real spacing_u = 4e-3, spacing_v = 4e-3;  // m
  // one value per cell layer (layers - 1), skin first
  std::vector<Real> thickness{2e-3, 5e-3, 10e-3};    // m
  std::vector<Real> youngs{0.118e6, 2.3e3, 3e3};     // Pa, first phase (dermis K1 of the paper's Table 1, read as MPa)
  std::vector<Real> youngs2{18.51e6, 2.3e3, 3e3};    // Pa, second phase; == youngs for a linear tissue
  std::vector<Real> turning_strain{0.41, 0, 0};      // strain where the second phase starts
  std::vector<Real> density{1090, 950, 1050};        // kg/m^3
  std::vector<std::string> names{"dermis", "hypodermis", "muscle", "bone"};  // one per sheet
  Real damping_ratio = 0.02;  // zeta of each spring
  // Pa per cell layer, or empty: a layer with a value > 0 gets a volume term
  // (Layer::volume_modulus) on its cells, each split into the 6 tetrahedra
  // of the Kuhn triangulation (around the cell's diagonal from corner (i, j,
  // s) to (i+1, j+1, s+1)), positively oriented
  std::vector<Real> volume_modulus;
  // the volume term's groups (Layer::volume_group): 1, a term per
  // tetrahedron, as build gives a tetra layer; 6, one per cell, as build
  // gives a lattice layer
  int volume_group = 1;
  // Pa per cell layer, or empty: a layer with a value > 0 gets the inversion
  // guard (Layer::guard_modulus) on the same 6 tetrahedra per cell, at
  // guard_ratio (Layer::guard_ratio)
  std::vector<Real> guard_modulus;
  Real guard_ratio = 0.5;
};

struct LayeredBlock {
  std::vector<std::pair<std::string, Layer>> layers;
  std::map<std::string, VecXi> sets;
  LayeredBlockOptions options;
  std::int64_t n_nodes = 0;
};

// Throws Error("", ...) on inconsistent options.
LayeredBlock make_layered_block(const LayeredBlockOptions& o);
// The paper-sized block with a given grid.
LayeredBlock make_layered_block(int nu, int nv, int layers);

// Writes the block as a model file. With `extras`, also a small /volume,
// /surfaces/skin, /quads/skin, a /vessels/artery tree and /tuning, so
// lazy-loading tests can check they are not read.
void write_model_file(const std::string& path, const LayeredBlock& b, bool extras = false);

// The springs' pull (N) on the nodes a State holds fixed (inverse mass 0),
// summed: at rest, what the fixed nodes carry of the loads on the free ones
// (their springs' elastic forces at x; tension-only springs count only
// stretched; damping and the volume term left out).
Vec3 fixed_reaction(const Model& m, std::span<const Real> x, std::span<const Real> inv_mass);

}  // namespace orthosim::runtime::testing
