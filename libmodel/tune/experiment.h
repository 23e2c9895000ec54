// The virtual experiment of spring tuning (paper §4.1; docs/tune.md): a small
// specimen of a tissue's layer, made by the model builder's own cell builders
// and spring classes (msm::make_specimen), is clamped on one face and
// stretched on the opposite face in strain steps to well past the turning
// point; each step is a quasi-static equilibrium solved by Newton's method
// with a sparse LDL^T factorisation (msm::solve_static, to its relative force
// tolerance); the nominal stress (reaction on the moving face / initial area)
// against the nominal strain is fitted with the tissue's law (fit.h).
//
//   Target q = target_of(tissue);                         // K1, turning strain, K2 (or K) and weights
//   auto s = make_tissue_specimen(options);               // e.g. a 2 x 2 tetra prism slab
//   apply_params(s, params);                              // per spring class laws
//   Measurement m = measure(s, q, options);               // the curve and p = (K1, turning strain, K2)
//   double psi = objective(q, m.p);                       // Eq. 1, relative terms
//
// Units SI: Pa, m. Deterministic.
#pragma once

#include "libmodel/format/model.h"
#include "libmodel/msm/specimen.h"
#include "libmodel/tissues.h"
#include "libmodel/tune/fit.h"

#include <array>
#include <cstdint>
#include <string>
#include <vector>

namespace orthosim::tune {

// ---- the tissue's data-book values ------------------------------------------

// What a tissue should do macroscopically, in SI.
struct Target {
  bool biphasic = true;
  double k1_pa = 0;           // biphasic: low-strain modulus K1 (Pa), > 0
  double turning_strain = 0;  // biphasic: turning strain, in (0, 1)
  double k2_pa = 0;           // biphasic: high-strain modulus K2 (Pa), >= K1
  double k_pa = 0;            // linear: modulus K (Pa), > 0
  std::vector<double> weights;  // Eq. 1 weights w_i >= 0, not all 0: 3 (K1, turning strain, K2) or 1 (K)

  // q: (K1 Pa, turning strain, K2 Pa) or (K Pa), the order of the weights.
  std::vector<double> values() const;
  // Names of the values in reports and in the tissue table: k1_kpa, turning_strain, k2_kpa / k_kpa.
  std::vector<std::string> keys() const;
};

// The tissue's mechanics as a target. Throws Error("", ...) if it has none.
Target target_of(const Tissue& tissue);
// Throws Error("", one line) for targets out of physical range: a modulus
// <= 0 or not finite, K2 < K1, a turning strain outside (0, 1), a negative
// weight, all weights 0, or the wrong number of weights.
void validate(const Target& target);

// Eq. 1 with relative terms: psi = sum_i w_i ((p_i - q_i) / q_i)^2. A failed
// experiment (empty p) counts as kFailedPsi.
inline constexpr double kFailedPsi = 1e6;
double objective(const Target& target, const std::vector<double>& p);
// The largest relative error |p_i - q_i| / q_i over the parameters with w_i > 0.
double max_relative_error(const Target& target, const std::vector<double>& p);

// ---- the specimen and its loading -------------------------------------------

struct ExperimentOptions {
  std::string kind = "tetra";               // the layer kind: "tetra" | "lattice"
  std::array<int, 3> cells{2, 2, 1};        // cells along x, y, z (tetra: one prism layer, cells[2] = 1)
  std::array<double, 3> cell_m{1e-3, 1e-3, 1e-3};  // cell size (m); tetra: cell_m[2] is the layer thickness
  int axis = 0;                             // load axis: 0 x (the grid's u), 1 y (v), 2 z (through the layer)
  int steps_below = 6;                      // biphasic: strain steps below the target turning strain, >= 2
  double stretch = 2.0;                     // biphasic: largest strain / target turning strain, (1, 3]
  int linear_steps = 2;                     // strain steps of a linear experiment, >= 1
  double linear_strain = 0.01;              // largest strain of a linear experiment, (0, 0.2]
  FitWeighting weighting = FitWeighting::relative;
  msm::StaticOptions solver{1e-9, 60};      // Newton: relative force tolerance, iterations per step
  // lattice cells as the model's build made them (its --body-diagonals and
  // --lattice-min-weight; tune --model reads them from /provenance/build)
  bool body_diagonals = false;
  double lattice_min_weight = 0.01;
  // the rule's axis correction (build --no-axis-correction turns it off;
  // models built before 2026-11-27, night have none): lattice cells with equal
  // moduli along u, v, w, tetra prisms with the factors of
  // msm::tetra_layer_axes for this cell shape
  bool axis_correction = true;
  // the layer's volume term over its K1 (msm::volume_ratio;
  // experiment_for_layer reads it from the layer's volume_modulus): the
  // specimen's tetrahedra (tetra) or hexahedra (lattice) carry it at every
  // candidate K1
  double volume_ratio = 0;
  // tetrahedra per volume term (experiment_for_layer: the layer's
  // volume_group); 0: as build writes them (msm::SpecimenOptions::volume_group)
  int volume_group = 0;
  // a tetra layer's term over its grid prisms (Layer::volume_tets;
  // msm::SpecimenOptions::tetra_grid_prisms)
  bool tetra_grid_prisms = false;
};
// Throws Error("", ...) for out-of-range options.
void validate(const ExperimentOptions& options);

// The strain steps for a target. Biphasic: equal increments d = T / (steps_below
// + 1/2) up to stretch x T (T: the target turning strain), so that T lies
// half-way between two samples: near the solution the kink of the curve
// never crosses a sample, and the fitted turning strain moves smoothly with
// the spring parameters. Linear: linear_steps equal increments up to
// linear_strain.
std::vector<double> strain_schedule(const Target& target, const ExperimentOptions& options);

// The specimen block (msm::make_specimen) for these options.
msm::Specimen make_tissue_specimen(const ExperimentOptions& options);

// How a network is stretched. The `axis` component of each gripped node is
// prescribed, u = strain x lever_m; every other dof is free except `held`
// (3 node + axis, kept at rest). The nominal stress is the sum of the
// reactions along `axis` on the `measured` nodes over `area_m2`.
struct Grips {
  int axis = 0;
  std::vector<int> nodes;               // gripped nodes
  std::vector<double> lever_m;          // one per gripped node (m)
  std::vector<int> measured;            // the moving face
  std::vector<std::int64_t> held;       // rigid-body and out-of-plane dofs held at rest
  double area_m2 = 0;                   // initial cross-section (m^2)
};

// The sliding clamp of msm::uniaxial_test: the face at the axis minimum is
// held (lever 0), the face at the maximum moves (lever = the specimen's
// length); lateral motion of both faces is free; the corner at the lateral
// minimum of the held face keeps both lateral dofs and the corner at (max
// l1, min l2) keeps l2, which removes the rigid-body modes.
Grips sliding_grips(const msm::Specimen& specimen, int axis);

struct Curve {
  std::vector<double> strain;       // nominal strain of each step
  std::vector<double> stress_pa;    // nominal stress (Pa)
  int newton_iterations = 0;        // over all steps
  double max_residual_n = 0;        // largest final free residual force (N)
  bool converged = true;            // false: a step did not converge; the curve stops before it
  std::string failure;              // why, when not converged
};

// Stretches the network through the strain steps in order, each solve
// starting from the previous equilibrium extrapolated linearly in strain (the
// first from the affine stretch of the rest state). Never throws for a step
// that does not converge (Curve::converged); throws Error for inconsistent
// grips or a mechanism.
Curve tension_test(const msm::SpringNetwork& network, const Grips& grips, const std::vector<double>& strains,
                   const msm::StaticOptions& solver);

// ---- spring parameters per class ----------------------------------------------

// The law of one spring class, as moduli that the stiffness rule turns into
// springs: k1 = k1_pa x k_per_pa, k2 = k2_pa x k_per_pa, turning length =
// rest length x (1 + turning_strain). A linear class has k2_pa == k1_pa and
// turning_strain 0.
struct ClassLaw {
  double k1_pa = 0, turning_strain = 0, k2_pa = 0;
};
inline constexpr int kSpringClasses = 4;  // SpringClass codes 0..3
using SpringParams = std::array<ClassLaw, kSpringClasses>;

// The untuned rule: every class carries the tissue's own law.
SpringParams rule_params(const Target& target);
// Sets the specimen's springs from per-class laws.
void apply_params(msm::Specimen& specimen, const SpringParams& params);
// The classes present in a specimen, ascending.
std::vector<SpringClass> classes_of(const msm::Specimen& specimen);

// ---- one measurement -------------------------------------------------------------

struct Measurement {
  std::vector<double> p;   // measured (K1 Pa, turning strain, K2 Pa) or (K Pa); empty if the experiment failed
  Curve curve;
  BilinearFit fit;         // biphasic
  std::string failure;     // why p is empty
};

// Runs the experiment on a specimen whose springs are set, on the target's
// strain schedule, and fits the target's law.
Measurement measure(const msm::Specimen& specimen, const Grips& grips, const Target& target,
                    const ExperimentOptions& options);

}  // namespace orthosim::tune
