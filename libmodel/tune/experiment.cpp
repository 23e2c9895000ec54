#include "libmodel/tune/experiment.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <limits>
#include <sstream>
#include <string>

namespace orthosim::tune {

// ---- targets ------------------------------------------------------------------

std::vector<double> Target::values() const {
  if (biphasic) return {k1_pa, turning_strain, k2_pa};
  return {k_pa};
}

std::vector<std::string> Target::keys() const {
  if (biphasic) return {"k1_kpa", "turning_strain", "k2_kpa"};
  return {"k_kpa"};
}

Target target_of(const Tissue& t) {
  Target q;
  switch (t.mechanics.model) {
    case Mechanics::Model::biphasic:
      q.biphasic = true;
      q.k1_pa = t.mechanics.k1_pa;
      q.turning_strain = t.mechanics.turning_strain;
      q.k2_pa = t.mechanics.k2_pa;
      break;
    case Mechanics::Model::linear:
      q.biphasic = false;
      q.k_pa = t.mechanics.k_pa;
      break;
    case Mechanics::Model::none:
      throw Error("", "tissue '" + t.name + "' has no mechanics to tune");
  }
  q.weights = t.mechanics.weights;
  if (q.weights.empty()) q.weights.assign(q.biphasic ? 3 : 1, 1.0);
  return q;
}

void validate(const Target& q) {
  // kMinModulusKpa .. kMaxModulusKpa (tissues.h), 1 Pa .. 1 TPa; beyond, a unit
  // slip (k 1e30 kPa was tuned and reported 100 % off with exit 0)
  auto modulus = [&](double v, const char* name) {
    // (a table's 1e308 kPa overflows to inf in Pa: out of range, not "not positive")
    if (!(v > 0)) throw Error("", std::string("target ") + name + " must be a positive modulus");
    if (!std::isfinite(v))
      throw Error("", std::string("target ") + name +
                          " overflows a double in Pa: it is outside a tissue's range, 1e-3 .. 1e9 kPa (a unit slip?)");
    if (v < 1e3 * kMinModulusKpa || v > 1e3 * kMaxModulusKpa)
      throw Error("", std::string("target ") + name + " = " + (std::ostringstream() << std::setprecision(10) << v / 1e3).str() +
                          " kPa is outside a tissue's range, 1e-3 .. 1e9 kPa (a unit slip?)");
  };
  if (q.biphasic) {
    modulus(q.k1_pa, "K1");
    modulus(q.k2_pa, "K2");
    if (q.k2_pa < q.k1_pa) throw Error("", "target K2 must not be smaller than K1");
    if (!(std::isfinite(q.turning_strain) && q.turning_strain > 0 && q.turning_strain < 1))
      throw Error("", "target turning strain must lie in (0, 1)");
  } else {
    modulus(q.k_pa, "K");
  }
  const std::size_t n = q.biphasic ? 3 : 1;
  if (q.weights.size() != n) throw Error("", "target needs " + std::to_string(n) + " weights");
  double sum = 0;
  for (double w : q.weights) {
    if (!(std::isfinite(w) && w >= 0)) throw Error("", "weights must be finite and >= 0");
    sum += w;
  }
  if (!(sum > 0)) throw Error("", "all weights are zero: nothing to tune");
}

double objective(const Target& q, const std::vector<double>& p) {
  const std::vector<double> v = q.values();
  if (p.size() != v.size()) return kFailedPsi;
  // The weights count relative to the largest (Eq. 1's minimiser does not
  // depend on their scale; Psi must not either): weights of 1e8 put every
  // Psi above kFailedPsi, the failed experiments' value, and the search saw a
  // flat landscape (the skin stayed untuned, 41 % off). Tables whose largest
  // weight is 1 (the samples') give the same Psi, bit for bit.
  double wmax = 0;
  for (double w : q.weights) wmax = std::max(wmax, w);
  double psi = 0;
  for (std::size_t i = 0; i < v.size(); ++i) {
    const double r = (p[i] - v[i]) / v[i];
    psi += (q.weights[i] / wmax) * r * r;
  }
  return std::isfinite(psi) ? std::min(psi, kFailedPsi) : kFailedPsi;
}

double max_relative_error(const Target& q, const std::vector<double>& p) {
  const std::vector<double> v = q.values();
  if (p.size() != v.size()) return std::numeric_limits<double>::infinity();
  double m = 0;
  for (std::size_t i = 0; i < v.size(); ++i)
    if (q.weights[i] > 0) m = std::max(m, std::abs(p[i] - v[i]) / v[i]);
  return std::isfinite(m) ? m : std::numeric_limits<double>::infinity();
}

// ---- specimen and loading --------------------------------------------------------

void validate(const ExperimentOptions& o) {
  if (o.kind != "tetra" && o.kind != "lattice") throw Error("", "specimen kind must be tetra or lattice, not '" + o.kind + "'");
  for (int k = 0; k < 3; ++k) {
    if (o.cells[static_cast<std::size_t>(k)] < 1 || o.cells[static_cast<std::size_t>(k)] > 64)
      throw Error("", "specimen cells must be in 1..64");
    if (!(o.cell_m[static_cast<std::size_t>(k)] > 0 && std::isfinite(o.cell_m[static_cast<std::size_t>(k)])))
      throw Error("", "specimen cell size must be > 0");
  }
  if (o.kind == "tetra" && o.cells[2] != 1) throw Error("", "a tetra specimen is one prism layer thick (cells z = 1)");
  if (o.axis < 0 || o.axis > 2) throw Error("", "load axis must be 0, 1 or 2");
  if (o.steps_below < 2 || o.steps_below > 500) throw Error("", "steps below the turning strain must be in 2..500");
  if (!(o.stretch > 1 && o.stretch <= 3)) throw Error("", "stretch (largest strain / turning strain) must be in (1, 3]");
  if (o.linear_steps < 1 || o.linear_steps > 1000) throw Error("", "linear_steps must be in 1..1000");
  if (!(o.linear_strain > 0 && o.linear_strain <= 0.2)) throw Error("", "linear_strain must be in (0, 0.2]");
  if (!(o.lattice_min_weight >= 0 && o.lattice_min_weight < 1)) throw Error("", "lattice_min_weight must be in [0, 1)");
  if (!(o.volume_ratio >= 0 && o.volume_ratio < 1e6)) throw Error("", "volume_ratio must be in [0, 1e6)");
  if (!(o.volume_group >= 0 && o.volume_group <= 64)) throw Error("", "volume_group must be in 0..64");
}

std::vector<double> strain_schedule(const Target& q, const ExperimentOptions& o) {
  std::vector<double> e;
  if (q.biphasic) {
    const double d = q.turning_strain / (o.steps_below + 0.5);
    const int n = static_cast<int>(std::floor(o.stretch * (o.steps_below + 0.5) + 1e-9));
    for (int i = 1; i <= n; ++i) e.push_back(d * i);
  } else {
    for (int i = 1; i <= o.linear_steps; ++i) e.push_back(o.linear_strain * i / o.linear_steps);
  }
  return e;
}

msm::Specimen make_tissue_specimen(const ExperimentOptions& o) {
  validate(o);
  msm::SpecimenOptions so;
  so.kind = o.kind;
  so.cells = o.cells;
  so.cell_m = o.cell_m;
  so.body_diagonals = o.body_diagonals;
  so.lattice_min_weight = o.lattice_min_weight;
  so.lattice_axis_correction = o.axis_correction;
  so.volume_ratio = o.volume_ratio;
  so.volume_group = o.volume_group;
  so.tetra_grid_prisms = o.kind == "tetra" && o.tetra_grid_prisms;
  if (o.kind == "tetra" && o.axis_correction) {
    so.tetra_axis_factors =
        msm::tetra_layer_axes(o.cell_m, so.volume_ratio, so.volume_group, so.tetra_grid_prisms).factors;
    so.tetra_alternate_diagonals = true;
  }
  return msm::make_specimen(so);
}

Grips sliding_grips(const msm::Specimen& s, int axis) {
  if (axis < 0 || axis > 2) throw Error("", "load axis must be 0, 1 or 2");
  const int l1 = (axis + 1) % 3, l2 = (axis + 2) % 3;
  const MatX3d& X = s.network.nodes;
  const auto size = [&](int k) { return s.size_m[static_cast<std::size_t>(k)]; };
  const double L = size(axis);
  const double tol = 1e-9 * std::max({size(0), size(1), size(2)});
  Grips g;
  g.axis = axis;
  std::vector<int> lo;
  for (Eigen::Index i = 0; i < X.rows(); ++i) {
    const int n = static_cast<int>(i);
    if (std::abs(X(i, axis)) < tol) {
      lo.push_back(n);
      g.nodes.push_back(n);
      g.lever_m.push_back(0.0);
    } else if (std::abs(X(i, axis) - L) < tol) {
      g.nodes.push_back(n);
      g.lever_m.push_back(L);
      g.measured.push_back(n);
    }
  }
  if (lo.empty() || g.measured.empty()) throw Error("", "the specimen has no loaded faces");
  auto corner = [&](double w1, double w2) {
    int best = lo.front();
    double bd = std::numeric_limits<double>::infinity();
    for (int n : lo) {
      const double d = std::abs(X(n, l1) - w1) + std::abs(X(n, l2) - w2);
      if (d < bd) bd = d, best = n;
    }
    return best;
  };
  const int c0 = corner(0, 0), c1 = corner(size(l1), 0);
  g.held = {3 * static_cast<std::int64_t>(c0) + l1, 3 * static_cast<std::int64_t>(c0) + l2,
            3 * static_cast<std::int64_t>(c1) + l2};
  g.area_m2 = size(l1) * size(l2);
  return g;
}

Curve tension_test(const msm::SpringNetwork& net, const Grips& g, const std::vector<double>& strains,
                   const msm::StaticOptions& solver) {
  if (g.axis < 0 || g.axis > 2) throw Error("", "tension_test: axis must be 0, 1 or 2");
  if (g.nodes.size() != g.lever_m.size()) throw Error("", "tension_test: one lever per gripped node");
  if (g.nodes.empty() || g.measured.empty()) throw Error("", "tension_test: no gripped or measured nodes");
  if (!(g.area_m2 > 0)) throw Error("", "tension_test: the cross-section must be > 0");
  const Eigen::Index nn = net.nodes.rows();
  for (int n : g.nodes)
    if (n < 0 || n >= nn) throw Error("", "tension_test: gripped node out of range");
  for (int n : g.measured)
    if (n < 0 || n >= nn) throw Error("", "tension_test: measured node out of range");
  for (auto d : g.held)
    if (d < 0 || d >= 3 * nn) throw Error("", "tension_test: held dof out of range");
  const int ax = g.axis;

  std::vector<std::int64_t> dofs;
  for (int n : g.nodes) dofs.push_back(3 * static_cast<std::int64_t>(n) + ax);
  dofs.insert(dofs.end(), g.held.begin(), g.held.end());
  std::vector<double> disp(dofs.size(), 0.0);

  Curve out;
  MatX3d x = net.nodes, x_prev = net.nodes;
  double e_prev = 0, e_prev2 = 0;
  for (std::size_t k = 0; k < strains.size(); ++k) {
    const double e = strains[k];
    for (std::size_t i = 0; i < g.nodes.size(); ++i) disp[i] = e * g.lever_m[i];
    // predictor: the previous equilibrium extrapolated linearly in strain;
    // from rest, the affine stretch along the axis
    MatX3d guess;
    if (k == 0) {
      guess = net.nodes;
      guess.col(ax) += e * (net.nodes.col(ax).array() - net.nodes.col(ax).minCoeff()).matrix();
    } else {
      const double r = (e - e_prev) / (e_prev - e_prev2);
      guess = x + r * (x - x_prev);
    }
    msm::StaticResult res;
    try {
      res = msm::solve_static(net, dofs, disp, &guess, solver);
      if (!res.converged && k > 0) {
        // extrapolation past a kink can mislead Newton: retry from the previous state
        MatX3d plain = x;
        plain.col(ax) += (e - e_prev) * (net.nodes.col(ax).array() - net.nodes.col(ax).minCoeff()).matrix();
        msm::StaticResult again = msm::solve_static(net, dofs, disp, &plain, solver);
        out.newton_iterations += res.iterations;
        res = std::move(again);
      }
    } catch (const Error& err) {
      out.converged = false;
      out.failure = err.message();
      return out;
    }
    out.newton_iterations += res.iterations;
    if (!res.converged) {
      out.converged = false;
      out.failure = "no equilibrium at strain " + std::to_string(e) + " after " + std::to_string(res.iterations) +
                    " Newton iterations";
      return out;
    }
    double F = 0;
    for (int n : g.measured) F += res.reaction(3 * static_cast<Eigen::Index>(n) + ax);
    out.strain.push_back(e);
    out.stress_pa.push_back(F / g.area_m2);
    out.max_residual_n = std::max(out.max_residual_n, res.residual);
    x_prev = x;
    x = std::move(res.x);
    e_prev2 = e_prev;
    e_prev = e;
  }
  return out;
}

// ---- per-class laws ------------------------------------------------------------------

SpringParams rule_params(const Target& q) {
  ClassLaw law;
  if (q.biphasic) law = {q.k1_pa, q.turning_strain, q.k2_pa};
  else law = {q.k_pa, 0.0, q.k_pa};
  SpringParams p;
  p.fill(law);
  return p;
}

void apply_params(msm::Specimen& s, const SpringParams& p) {
  msm::SpringNetwork& n = s.network;
  const Eigen::Index m = n.springs.rows();
  n.k1.resize(m), n.k2.resize(m), n.turning_length.resize(m);
  for (Eigen::Index i = 0; i < m; ++i) {
    const int c = s.spring_class(i);
    if (c < 0 || c >= kSpringClasses) throw Error("", "specimen spring with an unknown class");
    const ClassLaw& l = p[static_cast<std::size_t>(c)];
    n.k1(i) = l.k1_pa * s.k_per_pa(i);
    n.k2(i) = std::max(l.k2_pa, l.k1_pa) * s.k_per_pa(i);
    n.turning_length(i) = n.rest_length(i) * (1 + l.turning_strain);
  }
  // the volume term follows the structural class's K1, as build's and tune's layers do
  n.tet_k = VecXd::Constant(n.n_volume_groups(), s.options.volume_ratio * p[0].k1_pa);
}

std::vector<SpringClass> classes_of(const msm::Specimen& s) {
  std::vector<SpringClass> out;
  for (int c = 0; c < kSpringClasses; ++c)
    if ((s.spring_class.array() == static_cast<std::uint8_t>(c)).any()) out.push_back(static_cast<SpringClass>(c));
  return out;
}

// ---- measurement -------------------------------------------------------------------------

Measurement measure(const msm::Specimen& s, const Grips& g, const Target& q, const ExperimentOptions& o) {
  Measurement m;
  m.curve = tension_test(s.network, g, strain_schedule(q, o), o.solver);
  if (!m.curve.converged) {
    m.failure = m.curve.failure;
    return m;
  }
  if (q.biphasic) {
    m.fit = fit_bilinear(m.curve.strain, m.curve.stress_pa, o.weighting);
    m.p = {m.fit.k1_pa, m.fit.turning_strain, m.fit.k2_pa};
  } else {
    m.p = {fit_linear(m.curve.strain, m.curve.stress_pa)};
  }
  for (double v : m.p)
    if (!std::isfinite(v)) {
      m.failure = "the fit is not finite";
      m.p.clear();
      break;
    }
  return m;
}

}  // namespace orthosim::tune
