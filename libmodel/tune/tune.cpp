#include "libmodel/tune/tune.h"

#include "libmodel/provenance.h"

#include "libmodel/msm/biphasic.h"

#include <nlopt.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>

namespace orthosim::tune {

namespace {

using Clock = std::chrono::steady_clock;

// search ranges (natural logarithms of the ratio to the target)
const double kModulusRange = std::log(4.0);          // biphasic k1, k2: a factor 4 either way
const double kTurnLo = std::log(0.5), kTurnHi = std::log(3.0);
const double kLinearRange = std::log(5.0);           // linear k

double from_unit(double u, double lo, double hi) { return lo + std::clamp(u, 0.0, 1.0) * (hi - lo); }
double to_unit(double v, double lo, double hi) { return (v - lo) / (hi - lo); }

const std::map<std::string, nlopt::algorithm>& nlopt_global() {
  static const std::map<std::string, nlopt::algorithm> m = {
      {"crs2", nlopt::GN_CRS2_LM}, {"isres", nlopt::GN_ISRES}, {"direct-l", nlopt::GN_DIRECT_L}, {"esch", nlopt::GN_ESCH}};
  return m;
}
const std::map<std::string, nlopt::algorithm>& nlopt_local() {
  static const std::map<std::string, nlopt::algorithm> m = {{"bobyqa", nlopt::LN_BOBYQA},
                                                            {"sbplx", nlopt::LN_SBPLX},
                                                            {"neldermead", nlopt::LN_NELDERMEAD},
                                                            {"cobyla", nlopt::LN_COBYLA}};
  return m;
}

// Every evaluation of every method: runs the experiment, keeps the best, the
// trace and the stopping target.
struct Evaluator {
  msm::Specimen& specimen;
  const Grips& grips;
  const Target& target;
  const ExperimentOptions& experiment;
  const Space& space;
  double tolerance;
  Clock::time_point start = Clock::now();

  Evaluator(msm::Specimen& s, const Grips& g, const Target& q, const ExperimentOptions& e, const Space& sp, double tol)
      : specimen(s), grips(g), target(q), experiment(e), space(sp), tolerance(tol) {}

  std::int64_t evaluations = 0;
  double experiment_seconds = 0;
  double best_psi = std::numeric_limits<double>::infinity();
  std::vector<double> best_x;
  SpringParams best_params{};
  Measurement best_measurement;
  bool reached = false;
  std::vector<TracePoint> trace;

  double seconds() const { return std::chrono::duration<double>(Clock::now() - start).count(); }

  double operator()(const std::vector<double>& x) {
    const SpringParams params = space.params(x, target);
    apply_params(specimen, params);
    const auto t0 = Clock::now();
    Measurement m;
    try {
      m = measure(specimen, grips, target, experiment);
    } catch (const Error& e) {
      m.p.clear();
      m.failure = e.message();
    }
    experiment_seconds += std::chrono::duration<double>(Clock::now() - t0).count();
    ++evaluations;
    const double psi = objective(target, m.p);
    if (psi < best_psi) {
      best_psi = psi;
      best_x = x;
      best_params = params;
      best_measurement = std::move(m);
      trace.push_back({evaluations, seconds(), psi});
      if (max_relative_error(target, best_measurement.p) <= tolerance) reached = true;
    }
    return psi;
  }
};

std::string nlopt_reason(nlopt::result r) {
  switch (r) {
    case nlopt::SUCCESS: return "success";
    case nlopt::STOPVAL_REACHED: return "stopval";
    case nlopt::FTOL_REACHED: return "ftol";
    case nlopt::XTOL_REACHED: return "xtol";
    case nlopt::MAXEVAL_REACHED: return "evaluations";
    case nlopt::MAXTIME_REACHED: return "budget";
    default: return "nlopt-" + std::to_string(static_cast<int>(r));
  }
}

// one NLopt run on the unit box from x (updated to NLopt's result); returns why it stopped
std::string run_nlopt(nlopt::algorithm alg, Evaluator& ev, std::vector<double>& x, std::int64_t max_evals,
                      double seconds, std::uint64_t seed, double initial_step) {
  const unsigned n = static_cast<unsigned>(x.size());
  nlopt::opt opt(alg, n);
  opt.set_lower_bounds(std::vector<double>(n, 0.0));
  opt.set_upper_bounds(std::vector<double>(n, 1.0));
  struct Data {
    Evaluator* ev;
    nlopt::opt* opt;
  } data{&ev, &opt};
  opt.set_min_objective(
      [](unsigned, const double* xv, double*, void* d) {
        auto* dd = static_cast<Data*>(d);
        const double psi = (*dd->ev)(std::vector<double>(xv, xv + dd->opt->get_dimension()));
        if (dd->ev->reached) dd->opt->force_stop();
        return psi;
      },
      &data);
  if (max_evals > 0) opt.set_maxeval(static_cast<int>(std::min<std::int64_t>(max_evals, 2'000'000'000)));
  opt.set_maxtime(std::max(seconds, 1e-3));
  opt.set_xtol_rel(0);
  opt.set_ftol_abs(0);
  opt.set_stopval(0);
  if (initial_step > 0) opt.set_initial_step(initial_step);
  if (alg == nlopt::GN_CRS2_LM || alg == nlopt::GN_ISRES || alg == nlopt::GN_ESCH)
    opt.set_population(0);  // NLopt's default population for the dimension
  nlopt::srand(static_cast<unsigned long>(seed));
  for (double& v : x) v = std::clamp(v, 0.0, 1.0);
  double f = 0;
  try {
    const nlopt::result r = opt.optimize(x, f);
    return nlopt_reason(r);
  } catch (const nlopt::forced_stop&) {
    return "target";
  } catch (const nlopt::roundoff_limited&) {
    return "roundoff";
  } catch (const std::runtime_error& e) {
    return std::string("nlopt: ") + e.what();
  }
}

}  // namespace

// ---- space ----------------------------------------------------------------------------

Space make_space(const Target& q, const std::vector<SpringClass>& classes, bool tied) {
  if (classes.empty()) throw Error("", "the specimen has no springs to tune");
  Space s;
  s.biphasic = q.biphasic;
  s.tied = tied;
  s.classes = classes;
  s.base = rule_params(q);
  return s;
}

SpringParams Space::params(const std::vector<double>& x, const Target& q) const {
  if (static_cast<int>(x.size()) != dims()) throw Error("", "tune: wrong number of variables");
  SpringParams p = base;
  for (std::size_t c = 0; c < classes.size(); ++c) {
    ClassLaw& l = p[static_cast<std::size_t>(classes[c])];
    const std::size_t i = tied ? 0 : c;  // the law's variables
    if (biphasic) {
      l.k1_pa = q.k1_pa * std::exp(from_unit(x[3 * i], -kModulusRange, kModulusRange));
      l.turning_strain = q.turning_strain * std::exp(from_unit(x[3 * i + 1], kTurnLo, kTurnHi));
      l.k2_pa = std::max(l.k1_pa, q.k2_pa * std::exp(from_unit(x[3 * i + 2], -kModulusRange, kModulusRange)));
    } else {
      l.k1_pa = l.k2_pa = q.k_pa * std::exp(from_unit(x[i], -kLinearRange, kLinearRange));
      l.turning_strain = 0;
    }
  }
  return p;
}

std::vector<double> Space::start(const Target&) const {
  std::vector<double> x;
  for (int i = 0; i < laws(); ++i) {
    if (biphasic) {
      x.push_back(to_unit(0.0, -kModulusRange, kModulusRange));
      x.push_back(to_unit(0.0, kTurnLo, kTurnHi));
      x.push_back(to_unit(0.0, -kModulusRange, kModulusRange));
    } else {
      x.push_back(to_unit(0.0, -kLinearRange, kLinearRange));
    }
  }
  return x;
}

// ---- options -----------------------------------------------------------------------------

AnnealOptions default_anneal() {
  AnnealOptions a;
  a.walk_sweeps = 100;
  return a;
}

std::vector<std::string> methods() {
  std::vector<std::string> m = {"sa"};
  for (const auto& [k, v] : nlopt_global()) m.push_back(k);
  for (const auto& [k, v] : nlopt_local()) m.push_back(k);
  return m;
}

bool is_method(const std::string& name) {
  const auto m = methods();
  return std::find(m.begin(), m.end(), name) != m.end();
}

bool is_global_method(const std::string& name) { return nlopt_global().count(name) > 0; }

void validate(const TuneOptions& o) {
  if (!is_method(o.method)) {
    std::string list;
    for (const auto& m : methods()) list += (list.empty() ? "" : ", ") + m;
    throw Error("", "unknown method '" + o.method + "' (one of " + list + ")");
  }
  if (o.polish != "none" && !nlopt_local().count(o.polish))
    throw Error("", "unknown polish '" + o.polish + "' (bobyqa, sbplx, neldermead, cobyla or none)");
  if (!(o.polish_share >= 0 && o.polish_share < 1)) throw Error("", "polish share must be in [0, 1)");
  if (!(std::isfinite(o.budget_s) && o.budget_s > 0)) throw Error("", "budget must be > 0 seconds");
  if (o.max_evaluations < 0) throw Error("", "max evaluations must be >= 0");
  if (!(o.tolerance > 0 && o.tolerance < 0.5)) throw Error("", "tolerance must be in (0, 0.5)");
}

// ---- tuning --------------------------------------------------------------------------------

TuneResult tune_specimen(msm::Specimen& specimen, const Target& target, const ExperimentOptions& experiment,
                         const TuneOptions& o) {
  validate(target);
  validate(experiment);
  validate(o);
  const Grips grips = sliding_grips(specimen, experiment.axis);
  const Space space = make_space(target, classes_of(specimen), !o.per_class);

  TuneResult r;
  r.method = o.method;
  r.seed = o.seed;
  r.target = target;
  r.classes = space.classes;
  apply_params(specimen, space.base);
  r.untuned = measure(specimen, grips, target, experiment);

  Evaluator ev{specimen, grips, target, experiment, space, o.tolerance};
  const std::vector<double> x0 = space.start(target);
  if (o.method == "sa") {
    AnnealOptions a = o.anneal;
    a.seed = o.seed;
    a.max_evaluations = o.max_evaluations;
    a.budget_s = o.budget_s;
    const AnnealResult ar = anneal([&](const std::vector<double>& x) { return std::log(ev(x) + 1e-16); }, x0, a,
                                   [&](double) { return ev.reached; });
    r.stop = ar.stop;
  } else if (nlopt_local().count(o.method)) {
    std::vector<double> x = x0;
    ev(x);  // the rule itself, as every method sees it first
    // the rule's evaluation counts against the budget (sbplx --max-evaluations 5 ran 6)
    if (ev.reached) r.stop = "target";
    else if (o.max_evaluations == 1) r.stop = "evaluations";
    else
      r.stop = run_nlopt(nlopt_local().at(o.method), ev, x, o.max_evaluations > 0 ? o.max_evaluations - 1 : 0,
                         o.budget_s, o.seed, 0.1);
  } else {
    // global stage, then a local polish from its best point with what is left
    const double share = o.polish == "none" ? 0.0 : o.polish_share;
    std::vector<double> x = x0;
    const std::int64_t global_evals =
        o.max_evaluations > 0 ? std::max<std::int64_t>(1, static_cast<std::int64_t>((1 - share) * o.max_evaluations)) : 0;
    r.stop = run_nlopt(nlopt_global().at(o.method), ev, x, global_evals, (1 - share) * o.budget_s, o.seed, 0);
    if (!ev.reached && o.polish != "none" && !ev.best_x.empty()) {
      const std::int64_t left = o.max_evaluations > 0 ? o.max_evaluations - ev.evaluations : 0;
      const double time_left = o.budget_s - ev.seconds();
      if ((o.max_evaluations == 0 || left > 0) && time_left > 0) {
        r.method += "+" + o.polish;  // only when it runs (crs2 --max-evaluations 1 said "crs2+bobyqa")
        x = ev.best_x;
        r.stop = run_nlopt(nlopt_local().at(o.polish), ev, x, left, time_left, o.seed, 0.02);
      }
    }
    if (ev.reached) r.stop = "target";
  }

  r.params = ev.best_params;
  r.measured = ev.best_measurement;
  r.psi = ev.best_psi;
  r.max_error = max_relative_error(target, r.measured.p);
  r.evaluations = ev.evaluations;
  r.seconds = ev.seconds();
  r.seconds_per_experiment = ev.evaluations ? ev.experiment_seconds / static_cast<double>(ev.evaluations) : 0;
  r.reached = ev.reached;
  r.trace = std::move(ev.trace);
  apply_params(specimen, r.params);
  // the other axes, which the search does not see
  for (int ax = 0; ax < 3; ++ax) {
    Measurement m;
    if (ax == experiment.axis) {
      m = r.measured;
    } else {
      try {
        m = measure(specimen, sliding_grips(specimen, ax), target, experiment);
      } catch (const Error&) {
        m.p.clear();
      }
    }
    r.axis_ratio[static_cast<std::size_t>(ax)] =
        m.p.empty() ? std::numeric_limits<double>::quiet_NaN() : m.p[0] / target.values()[0];
  }
  return r;
}

TuneResult tune_target(const Target& target, const ExperimentOptions& experiment, const TuneOptions& options) {
  validate(target);
  msm::Specimen s = make_tissue_specimen(experiment);
  return tune_specimen(s, target, experiment, options);
}

// ---- the model ----------------------------------------------------------------------------

double layer_volume_ratio(const Layer& l) {
  if (!(l.volume_modulus > 0)) return 0;
  if (l.spring_law.size() != 3 * kSpringClasses)
    throw Error("", "layer '" + l.tissue + "' has a volume_modulus but no spring_law to relate it to K1");
  return l.volume_modulus / l.spring_law[0];
}

ExperimentOptions experiment_for_layer(const Layer& layer, const Layer& below, const ExperimentOptions& defaults) {
  if (layer.kind != "tetra" && layer.kind != "lattice")
    throw Error("", "layer '" + layer.tissue + "' is " + layer.kind + ", not a tetra or lattice layer");
  if (layer.quads.rows() == 0) throw Error("", "layer '" + layer.tissue + "' has no top quads");
  const MatX4i local = layer.quads.array() - static_cast<std::int32_t>(layer.node_offset);
  const Eigen::Index ng = static_cast<Eigen::Index>(local.maxCoeff()) + 1;
  if (local.minCoeff() < 0 || ng > layer.nodes.rows() || ng > below.nodes.rows())
    throw Error("", "layer '" + layer.tissue + "': top quads do not index its own grid");
  // mean edge along u and v, as the lattice rule's equivalent box, and the thickness
  const auto [a, b, h] = msm::mean_cell_shape(layer.nodes.topRows(ng), below.nodes.topRows(ng), local);
  if (!(a > 0 && b > 0 && h > 0)) throw Error("", "layer '" + layer.tissue + "' has degenerate cells");
  ExperimentOptions o = defaults;
  o.kind = layer.kind;
  o.volume_ratio = layer_volume_ratio(layer);
  o.volume_group = o.volume_ratio > 0 ? layer.volume_group : 0;
  o.tetra_grid_prisms = o.volume_ratio > 0 && layer.kind == "tetra" && layer.volume_tets.rows() > 0;
  if (layer.kind == "tetra") {
    o.cells[2] = 1;
    o.cell_m = {a, b, h};
  } else {
    const Eigen::Index through = (layer.nodes.rows() - ng) / ng + 1;
    o.cell_m = {a, b, h / static_cast<double>(through)};
  }
  return o;
}

SpringParams current_params(const Layer& l, const Tuning* record, const Target& table) {
  if (l.spring_law.size() == 3 * kSpringClasses) {
    SpringParams p;
    for (int c = 0; c < kSpringClasses; ++c)
      p[static_cast<std::size_t>(c)] = {l.spring_law[3 * c], l.spring_law[3 * c + 1], l.spring_law[3 * c + 2]};
    return p;
  }
  return record ? params_of(*record) : rule_params(table);
}

std::vector<double> law_values(const SpringParams& p) {
  std::vector<double> v;
  for (const ClassLaw& c : p) v.insert(v.end(), {c.k1_pa, c.turning_strain, std::max(c.k2_pa, c.k1_pa)});
  return v;
}

void check_layer_law(const Layer& l, const SpringParams& current) {
  const Eigen::Index n = l.springs.rows();
  if (l.spring_class.size() != n || l.k1.size() != n || l.k2.size() != n || l.turning_length.size() != n ||
      l.rest_length.size() != n || l.damping.size() != n)
    throw Error("", "layer '" + l.tissue + "' has inconsistent spring arrays");
  const bool recorded = l.spring_law.size() == 3 * kSpringClasses;
  for (Eigen::Index s = 0; s < n; ++s) {
    const int c = l.spring_class(s);
    if (c < 0 || c >= kSpringClasses) throw Error("", "layer '" + l.tissue + "' has a spring of unknown class");
    const ClassLaw& cur = current[static_cast<std::size_t>(c)];
    if (!(cur.k1_pa > 0)) throw Error("", "layer '" + l.tissue + "': no current law for its spring class " + std::to_string(c));
    // a NaN passed the law's comparisons below (false either way) and came out of
    // the tuning as more NaN (its k2, lin_k, lin_damping), exit 0
    const auto bad = [&](const char* what, double v, bool ok) {
      if (!std::isfinite(v) || !ok)
        throw Error("", "layer '" + l.tissue + "': spring " + std::to_string(s) + " has " +
                            (std::isfinite(v) ? "a non-physical " : "a non-finite ") + what + " (" + std::to_string(v) +
                            ")");
    };
    bad("k1", l.k1(s), l.k1(s) > 0);
    bad("k2", l.k2(s), l.k2(s) > 0);
    bad("rest_length", l.rest_length(s), l.rest_length(s) > 0);
    bad("turning_length", l.turning_length(s), l.turning_length(s) > 0);
    bad("damping", l.damping(s), l.damping(s) >= 0);
    const double k_per_pa = l.k1(s) / cur.k1_pa;
    // the layer must follow the law it is said to carry
    const double k2_expected = cur.k2_pa * k_per_pa, lt_expected = l.rest_length(s) * (1 + cur.turning_strain);
    if (std::abs(l.k2(s) - k2_expected) > 1e-6 * std::abs(k2_expected) + 1e-300 ||
        std::abs(l.turning_length(s) - lt_expected) > 1e-9 * l.rest_length(s))
      throw Error("", "layer '" + l.tissue + "': its springs do not follow " +
                          (recorded ? std::string("the law recorded with it (spring_law)")
                                    : std::string("the tissue table's law (a model written before layers recorded their "
                                                  "law: was it built with another tissue table? build it again)")) +
                          " (spring " + std::to_string(s) + ")");
  }
}

void apply_to_layer(Layer& l, const SpringParams& current, const SpringParams& tuned) {
  check_layer_law(l, current);
  const Eigen::Index n = l.springs.rows();
  for (Eigen::Index s = 0; s < n; ++s) {
    const int c = l.spring_class(s);
    const ClassLaw& cur = current[static_cast<std::size_t>(c)];
    const ClassLaw& t = tuned[static_cast<std::size_t>(c)];
    // the same law: the spring stays bit for bit (the round trip k1 / law x law moved
    // 613 of the sample skin's k2 by an ulp when a tune was run again)
    if (t.k1_pa == cur.k1_pa && t.k2_pa == cur.k2_pa && t.turning_strain == cur.turning_strain) continue;
    const double k_per_pa = l.k1(s) / cur.k1_pa;
    const double k1_new = t.k1_pa * k_per_pa;
    if (l.k1(s) > 0) l.damping(s) *= std::sqrt(k1_new / l.k1(s));
    l.k1(s) = k1_new;
    l.k2(s) = std::max(t.k2_pa, t.k1_pa) * k_per_pa;
    l.turning_length(s) = l.rest_length(s) * (1 + t.turning_strain);
  }
  // the volume term keeps its ratio to the structural class's K1 (build's --poisson-ratio)
  if (l.volume_modulus > 0 && current[0].k1_pa > 0) l.volume_modulus *= tuned[0].k1_pa / current[0].k1_pa;
  // so does the inversion guard's (the bulk modulus, build's --inversion-guard)
  if (l.guard_modulus > 0 && current[0].k1_pa > 0) l.guard_modulus *= tuned[0].k1_pa / current[0].k1_pa;
  l.spring_law = law_values(tuned);
  msm::decompose_biphasic(l);
}

Tuning tuning_record(const TuneResult& r) {
  Tuning t;
  t.method = r.method;
  t.seed = static_cast<std::int64_t>(r.seed);
  t.psi = r.psi;
  t.evaluations = r.evaluations;
  t.seconds = reproducible_run() ? 0 : r.seconds;  // (SOURCE_DATE_EPOCH: the same bytes each run)
  const auto q = r.target.values();
  t.target = Eigen::Map<const VecXd>(q.data(), static_cast<Eigen::Index>(q.size()));
  t.weights = Eigen::Map<const VecXd>(r.target.weights.data(), static_cast<Eigen::Index>(r.target.weights.size()));
  t.achieved = VecXd::Constant(static_cast<Eigen::Index>(q.size()), std::numeric_limits<double>::quiet_NaN());
  for (std::size_t i = 0; i < r.measured.p.size() && i < q.size(); ++i) t.achieved(static_cast<Eigen::Index>(i)) = r.measured.p[i];
  t.spring_params.resize(3 * kSpringClasses);
  for (int c = 0; c < kSpringClasses; ++c) {
    const ClassLaw& l = r.params[static_cast<std::size_t>(c)];
    t.spring_params.segment<3>(3 * c) << l.k1_pa, l.turning_strain, l.k2_pa;
  }
  return t;
}

SpringParams params_of(const Tuning& t) {
  if (t.spring_params.size() != 3 * kSpringClasses)
    throw Error("", "/tuning spring_params must hold 3 values for each of the 4 spring classes");
  SpringParams p;
  for (int c = 0; c < kSpringClasses; ++c)
    p[static_cast<std::size_t>(c)] = {t.spring_params(3 * c), t.spring_params(3 * c + 1), t.spring_params(3 * c + 2)};
  return p;
}

}  // namespace orthosim::tune
