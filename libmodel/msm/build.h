// The multilayer mass-spring model (paper §3, §4.1): corresponding quad
// surfaces, outer skin to bone, become layers of springs and lumped masses.
//
//   surfaces:  S0 (skin) S1 (fat) S2 (muscle) S3 (bone)   nu x nv grids, vertex (i, j) of each under (i, j) of S0
//   layers:    L0 = skin:tetra between S0 and S1, L1 = fat:lattice between S1 and S2, L2 = muscle:lattice
//              between S2 and S3, and the rigid bottom L3 = bone (the nodes of S3, node set "fixed").
//
// Ownership: a layer owns its top grid, then the nodes it creates (a tetra
// layer's projected centroids, a lattice layer's interior grids); its bottom
// grid is the next layer's top. Global ids run layer by layer in that order:
// layer l owns node_offset .. node_offset + n_nodes - 1 and its springs and
// tets may use the next layer's top grid. Each layer emits the springs of its
// own cells, so an in-surface spring of an interface (both ends on the grid
// between two layers) appears once in each of the two layers: two tissues'
// springs in parallel, each with its own law. Node masses are lumped from
// density x cell volume of every layer touching the node.
//
// Stiffness: lattice.h (a per-cell Cauchy-Born rule) and tetra.h (a per-tet
// trace rule) give each spring k_per_pa (m); the tissue law then gives
// k1 = K1 k_per_pa, k2 = K2 k_per_pa, Lt = L0 (1 + turning strain) for a
// biphasic tissue, k1 = k2 = K k_per_pa, Lt = L0 for a linear one, and
// biphasic.h the linear decomposition stored beside it. Damping per spring:
// c = 2 zeta sqrt(k1 m_a m_b / (m_a + m_b)).
#pragma once

#include "libmodel/format/model.h"
#include "libmodel/msm/cells.h"
#include "libmodel/msm/project.h"
#include "libmodel/msm/specimen.h"
#include "libmodel/tissues.h"

#include <array>
#include <cstdint>
#include <map>
#include <string>
#include <utility>
#include <vector>

namespace orthosim::msm {

struct LayerSpec {
  std::string tissue;  // the layer's top surface is /quads/<tissue>; also its name and tissue
  std::string kind;    // "tetra" | "lattice"
};

// "skin:tetra,fat:lattice,muscle:lattice" -> specs. Throws Error("", ...) on
// a malformed item or an unknown kind.
std::vector<LayerSpec> parse_layer_specs(const std::string& text);

// The surfaces and layers to build, outer to inner.
struct Stack {
  std::vector<std::string> surfaces;  // layers.size() + 1 tissue names; the last is the fixed bottom
  std::vector<LayerSpec> layers;
  // Without requested layers and without a rigid tissue among the present
  // ones: the innermost tetra or lattice tissue, whose surface became the
  // fixed bottom instead of a layer (build and the pipeline warn); else "".
  std::string layered_bottom;
};

// Chooses the stack from the tissues that have quad surfaces (`present`) and
// the tissue table. With no `requested` layers: every present tissue whose
// table layer is tetra or lattice, ordered by nesting depth ("inside"), down
// to the first rigid one (or the innermost present surface), which becomes
// the fixed bottom. With requested layers: those, which must be present,
// listed outer to inner (strictly increasing depth), over the next present
// surface below the last one. Throws Error("", ...) for a tissue missing
// from the table, layers out of order, or no surface below the last layer.
Stack resolve_stack(const std::vector<LayerSpec>& requested, const std::vector<std::string>& present,
                    const TissueTable& tissues);

struct BuildOptions {
  int through_cells = 1;          // lattice cells through each lattice layer's thickness, 1..64
  bool body_diagonals = false;    // lattice body diagonals (docs/msm.md shows they do not help; off)
  double lattice_min_weight = 0.01;  // lattice rule: edge/face weights >= this x their cube values (msm/lattice.h), [0, 1)
  double damping_ratio = 0.1;     // zeta of each spring with its end masses, [0, 10]
  double min_thickness_m = 1e-5;  // a layer thinner than this at any grid vertex is an error (m), >= 0
  ProjectionOptions projection;   // centroid rays of tetra layers
  double max_spring_ratio = 1e3;  // longest / shortest spring above this is an error, > 1
  double mass_tolerance = 0.01;   // |cell mass - density x layer volume| / that, per layer, (0, 1)
  double inverted_ratio = 1e-9;   // a cell tetrahedron below this fraction of the mean volume is inverted
  bool check_intersections = true;  // exact triangle-triangle test between consecutive surfaces (CGAL)
  // Equal Young's moduli along u, v and through each layer (docs/msm.md, "The
  // axis correction"): lattice cells by their rule (LatticeOptions), tetra
  // layers by the axis factors calibrated on their mean cell
  // (msm::tetra_layer_axes). Off: the rules alone.
  bool axis_correction = true;
  // Poisson's ratio of the layers' tissue, [1/4, 1/2): a volume term of
  // modulus volume_ratio(nu) x K1 (Layer::volume_modulus; docs/msm.md, "The
  // volume term") on each tetrahedron of a tetra layer, and with
  // lattice_volume_term on each hexahedron of a lattice layer, which the axis
  // correction accounts for, so E along u, v and w stays the table's. 1/4:
  // none (central springs alone, the rules before 2026-11-28). Soft tissue is
  // nearly incompressible (0.45-0.499 in the literature).
  double poisson_ratio = 0.49;
  // Where a tetra layer's volume term acts (docs/msm.md, "The volume term"):
  // "tets", one term per cell tetrahedron (14 a quad: the layer locks in
  // bending, 13.9x stiffer at nu = 0.49 than at 1/4), or "prisms", one per
  // grid prism (grid_prism_tets: the 6 grid nodes under each triangle, 2 a
  // quad; Layer::volume_tets) with a cap that keeps the projected centroid on
  // the surface below, which keeps the grid's volume without locking (1.14x)
  // at 0.62-0.78x the speed (docs/msm.md, "The term over the grid prisms").
  std::string tetra_volume_term = "tets";
  // The lattice layers' volume term (one per hexahedron), off by default:
  // it keeps a lattice from folding through itself, but in cells far from
  // cubes (the rule's shear moduli 1-3 % of E) its pressure buckles the
  // springs' weak shear under a few per cent of tension (docs/msm.md, "The
  // volume term": the demo's fat cells lose 29 % of their modulus at 3 %)
  bool lattice_volume_term = false;
  // The inversion guard (Layer::guard_modulus, guard_ratio; docs/msm.md, "The
  // inversion guard"), in (0, 1), 0: none. Every tetrahedron of a layer whose
  // tetrahedra have no volume term of their own (a lattice layer's 6 per
  // hexahedron; a tetra layer's 14 per quad at poisson_ratio 1/4) resists
  // being pressed below this fraction of its rest volume with the tissue's
  // bulk modulus K1 / (3 (1 - 2 nu)); above it the guard does nothing, so the
  // moduli the axis correction and tune calibrate are not changed.
  double inversion_guard = 0.5;
};

// Per-layer figures, in the report and in BENCHMARKS.md.
struct LayerReport {
  std::string name, tissue, kind;
  int order = 0;
  std::int64_t node_offset = 0, nodes = 0, springs = 0, lin_springs = 0, tets = 0, cells = 0;
  std::int64_t interface_springs = 0;             // springs also present in the layer above (shared surface)
  std::int64_t zero_stiffness_dropped = 0;        // cell springs whose rule weight is 0 in every cell (not emitted)
  std::map<std::string, std::int64_t> springs_by_class;
  double density_kg_m3 = 0, k1_pa = 0, k2_pa = 0, turning_strain = 0;
  double volume_m3 = 0;            // sum of cell volumes
  double reference_volume_m3 = 0;  // between the faceted top and bottom surfaces (cells.h layer_volume)
  double mass_kg = 0;              // density x cell volume: this layer's share of the node masses
  double mass_error = 0;           // |mass - density x reference volume| / (density x reference volume)
  double thickness_min_m = 0, thickness_mean_m = 0;
  double spring_min_m = 0, spring_max_m = 0;
  double min_tet_volume_m3 = 0;
  std::int64_t inverted = 0;
  ProjectionCounts projection;     // tetra layers
  RuleStats rule;                  // lattice layers
  // tetra layers: the mean cell (u, v, thickness; m) and, with the axis
  // correction, its calibration (factors 1 and moduli 0 without)
  std::array<double, 3> mean_cell_m{0, 0, 0};
  AxisCalibration axes;
  double volume_modulus_pa = 0;    // Layer::volume_modulus (0: none)
  int volume_group = 1;            // Layer::volume_group: tetrahedra per volume term (tetra 1, or 4 over volume_tets; lattice 6)
  std::int64_t volume_tets = 0;    // Layer::volume_tets rows (a tetra layer's grid prisms and caps: 16 a quad; 0: the term is over tets)
  double guard_modulus_pa = 0;     // Layer::guard_modulus (0: none)
  double guard_ratio = 0;          // Layer::guard_ratio
};

struct BuildReport {
  std::vector<LayerReport> layers;  // the rigid bottom last
  std::int64_t nodes = 0, springs = 0, lin_springs = 0, tets = 0;
  std::int64_t components = 0;            // connected components of the whole network (must be 1)
  std::int64_t duplicate_springs = 0;     // pairs repeated within a layer or across non-interface layers (must be 0)
  std::int64_t zero_length_springs = 0;   // must be 0
  std::int64_t inverted_tets = 0;         // must be 0
  std::int64_t projection_fallbacks = 0;  // all tetra layers
  std::int64_t surface_intersections = 0; // triangle pairs of consecutive surfaces that intersect (must be 0)
  double spring_ratio = 0;                // longest / shortest rest length
  double mass_kg = 0;                     // sum of node masses
  double layer_mass_kg = 0;               // sum over layers of density x cell volume
  double max_mass_error = 0;
  std::map<std::string, double> phases_s; // wall time per phase
};

struct BuiltModel {
  std::vector<std::string> names;                       // layer names (= tissues), outer to inner, rigid bottom last
  std::vector<Layer> layers;                            // same order
  std::vector<std::pair<std::string, VecXi>> node_sets; // "fixed", "skin", "layer_<name>", "surface_<tissue>"
  BuildReport report;
};

// Throws Error("", "<option> must be ...") for an option out of its range
// (build_layers checks them too; a CLI checks them first, to name its flag).
void check_build_options(const BuildOptions& o);

// Builds the layers. surfaces: (tissue, quads) outer to inner, one more than
// layers; every grid has the same nu, nv and quads, counter-clockwise seen
// from outside. Validates everything first and throws Error("", one line)
// for: a tissue missing from the table or without mechanics, grids that do
// not match, degenerate or inward-facing grids, layers out of order or
// intersecting, a layer thinner than min_thickness_m; and after building, for
// any violated quality check (zero-length or duplicate springs, inverted
// cells, more than one connected component, mass error above tolerance,
// spring length ratio above max_spring_ratio). Deterministic.
BuiltModel build_layers(const std::vector<std::pair<std::string, QuadSurface>>& surfaces,
                        const std::vector<LayerSpec>& layers, const TissueTable& tissues,
                        const BuildOptions& options);

// The options as a JSON object (for provenance and reports).
std::string build_parameters_json(const BuildOptions& o, const Stack& stack);

}  // namespace orthosim::msm
