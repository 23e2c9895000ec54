// Spring-parameter optimisation against a tissue table (paper §4.1, Eq. 1,
// Table 1; issue 7; docs/tune.md).
//
// For each tissue the microscopic parameters of the spring classes present in
// the tissue's specimen (experiment.h) are optimised until the virtual
// experiment's fitted law matches the tissue's data-book values; one law for
// every class by default, a law per class with TuneOptions::per_class (Space):
//   biphasic: (k1, turning strain, k2), searched as
//             ln(k1 / K1) in [-ln 4, ln 4], ln(t / T) in [ln 0.5, ln 3],
//             ln(k2 / K2) in [-ln 4, ln 4]  (K1, T, K2: the targets; k2 >= k1 enforced;
//             wider boxes hold more local minima pinned on their faces, docs/tune.md)
//   linear:   k, as ln(k / K) in [-ln 5, ln 5]
// k1 and k2 are class moduli that the stiffness rule turns into springs
// (k = modulus x k_per_pa, msm/lattice.h, msm/tetra.h), so they carry over to
// every cell size; the search starts from the untuned rule (every class the
// tissue's own law).
//
// Objective (Eq. 1, relative terms): psi = sum_i w_i ((p_i - q_i) / q_i)^2.
// Stopping target: every parameter with w_i > 0 within `tolerance` of its
// target. Methods: "sa" (anneal.h, on ln(psi + 1e-16)), or an NLopt global
// algorithm ("crs2", "isres", "direct-l", "esch") followed by a local polish
// ("bobyqa" by default, or "sbplx"), or an NLopt local algorithm alone
// ("bobyqa", "sbplx", "neldermead", "cobyla") from the rule.
#pragma once

#include "libmodel/format/model.h"
#include "libmodel/tissues.h"
#include "libmodel/tune/anneal.h"
#include "libmodel/tune/experiment.h"

#include <array>
#include <cstdint>
#include <string>
#include <vector>

namespace orthosim::tune {

// The search space of one target over the spring classes of a specimen.
// Tied (the default): every class carries one law, the search's 3 (biphasic)
// or 1 (linear) variables; the rule's ratios between the classes, which make
// a lattice cell nearly isotropic, are kept. Per class: each class its own law
// (3 or 1 variables a class); the experiment loads one axis only, so the
// other axes' stiffness is then not determined by the target (the sample
// model's muscle lattice tuned with seeds 1 and 3 came out 0.27x and 4.3x the
// rule's across/along ratio, each 0.1 % off along; docs/tune.md).
struct Space {
  bool biphasic = true;
  bool tied = true;
  std::vector<SpringClass> classes;
  SpringParams base;  // the untuned rule; classes outside `classes` keep it

  int laws() const { return tied ? 1 : static_cast<int>(classes.size()); }
  int dims() const { return laws() * (biphasic ? 3 : 1); }
  // x in [0, 1]^dims -> per-class laws (k2 >= k1)
  SpringParams params(const std::vector<double>& x, const Target& target) const;
  // the unit-box point of the untuned rule
  std::vector<double> start(const Target& target) const;
};
Space make_space(const Target& target, const std::vector<SpringClass>& classes, bool tied = true);

// Names accepted by TuneOptions::method.
std::vector<std::string> methods();
bool is_method(const std::string& name);
// An NLopt global method, the only kind TuneOptions::polish follows.
bool is_global_method(const std::string& name);

// The annealer's settings for tuning: AnnealOptions' defaults with a fresh
// walk from a random point every 100 sweeps (docs/tune.md).
AnnealOptions default_anneal();

struct TuneOptions {
  std::string method = "sa";      // methods()
  std::string polish = "bobyqa";  // local polish after an NLopt global method: "bobyqa" | "sbplx" | "none"
  double polish_share = 0.3;      // share of the budget and evaluations kept for the polish, [0, 1)
  std::uint64_t seed = 1;
  // The run stops on the target, on max_evaluations or on budget_s. The
  // defaults are orthosim pipeline's: bounded by the experiments, so the same
  // inputs and seed give the same laws on any machine; the wall-clock budget
  // is a safety net (a run it stops depends on the machine's speed).
  double budget_s = 300;             // wall-clock budget per tissue (s), > 0
  std::int64_t max_evaluations = 4000;  // 0: no limit (then the run stops on the target or the budget)
  double tolerance = 1e-3;        // stopping target: every weighted parameter within this relative error, (0, 0.5)
  bool per_class = false;         // each spring class its own law (Space); default: one law for all
  AnnealOptions anneal = default_anneal();  // "sa"; its seed, max_evaluations and budget_s are set from the fields above
};
// Throws Error("", ...) for bad options (unknown method, budget <= 0, ...).
void validate(const TuneOptions& options);

struct TuneResult {
  std::string method;                // as run, e.g. "sa" or "crs2+bobyqa"
  std::uint64_t seed = 0;
  Target target;
  SpringParams params;               // the best per-class laws
  std::vector<SpringClass> classes;  // the classes that were optimised
  Measurement measured;              // the experiment at the best parameters (p = achieved)
  Measurement untuned;               // the experiment with the rule alone
  double psi = 0;
  double max_error = 0;              // max_relative_error(target, achieved)
  std::int64_t evaluations = 0;
  double seconds = 0;
  double seconds_per_experiment = 0; // mean wall time of one virtual experiment
  bool reached = false;              // the stopping target was met
  std::string stop;                  // "target" | "evaluations" | "budget" | NLopt's reason
  std::vector<TracePoint> trace;     // best psi against evaluations and time
  // The tuned specimen loaded along its other two axes: the first measured
  // value (K1 or K) over the target's, per axis 0 (u), 1 (v), 2 (through the
  // layer); the load axis's own entry is the achieved ratio; NaN where that
  // experiment failed. The target is isotropic and the experiment loads one
  // axis: this says how far the others are from it (docs/tune.md).
  std::array<double, 3> axis_ratio{};
};

// Tunes the spring classes of `specimen` (its springs are overwritten) for
// the target. Deterministic for a given seed when the run stops on the target
// or on max_evaluations.
TuneResult tune_specimen(msm::Specimen& specimen, const Target& target, const ExperimentOptions& experiment,
                         const TuneOptions& options);

// Makes the specimen from `experiment` and tunes it.
TuneResult tune_target(const Target& target, const ExperimentOptions& experiment, const TuneOptions& options);

// ---- the model ----------------------------------------------------------------------

// The specimen geometry of a model layer: its kind, the mean cell edge along
// u and v of its top grid, its thickness (to the next layer's top grid,
// `below`) and, for lattices, the cells through the thickness. The other
// fields of `defaults` are kept.
ExperimentOptions experiment_for_layer(const Layer& layer, const Layer& below, const ExperimentOptions& defaults);

// A layer's volume_modulus over its structural class's K1 (spring_law[0]);
// 0 without a volume term. Throws Error for a volume term without a law.
double layer_volume_ratio(const Layer& layer);

// The laws a layer's springs follow now: its spring_law (written by build and
// tune since 2026-11-27); in older files the /tuning record of an earlier
// tune (`record`, or null), else the tissue table's law (`table`).
SpringParams current_params(const Layer& layer, const Tuning* record, const Target& table);
std::vector<double> law_values(const SpringParams& p);  // Layer::spring_law's 12 values

// Throws Error("", ...) unless every spring of the layer follows `current`
// (its k2 / k1 and turning length those of its class's law): the check
// apply_to_layer makes, to be run before any tuning.
void check_layer_law(const Layer& layer, const SpringParams& current);

// Re-sets a built layer's springs from tuned per-class laws and redoes its
// linear decomposition. Each spring's rule stiffness is recovered from its
// current k1 and its class's current modulus (`current`: the laws the layer
// was built or last tuned with, current_params); damping keeps its ratio (c
// scales with sqrt(k1)); spring_law becomes the tuned laws. Throws Error("",
// ...) if the layer does not match `current`.
void apply_to_layer(Layer& layer, const SpringParams& current, const SpringParams& tuned);

// The /tuning/<tissue> record of a result. spring_params: per class code
// 0..3, (k1 modulus Pa, turning strain, k2 modulus Pa); a spring of the class
// gets k = modulus x its rule stiffness k_per_pa (m), i.e. the values are N/m
// per metre of rule stiffness.
Tuning tuning_record(const TuneResult& result);
// The per-class laws stored in a /tuning record (inverse of tuning_record).
SpringParams params_of(const Tuning& record);

}  // namespace orthosim::tune
