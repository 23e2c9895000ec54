// tune (issue 7): the virtual experiment against analytic lattices
// (shared/reference/lattice-elasticity.md), the bilinear fit on synthetic
// curves, the annealer, the tuner's accuracy on Table 1 dermis, the sample
// tissue table and scaled targets, determinism, the model-layer round trip
// and bad input. Every tuning run is bounded by evaluations, never by wall
// time, so the results are the same on every machine.
#include "libmodel/msm/biphasic.h"
#include "libmodel/msm/lattice.h"
#include "libmodel/tissues.h"
#include "libmodel/tune/tune.h"

#include <gtest/gtest.h>

#include <cmath>
#include <string>

using namespace orthosim;
using namespace orthosim::tune;

namespace {

Target biphasic(double k1_pa, double turning, double k2_pa) {
  Target q;
  q.biphasic = true;
  q.k1_pa = k1_pa, q.turning_strain = turning, q.k2_pa = k2_pa;
  q.weights = {1, 1, 1};
  return q;
}

Target linear(double k_pa) {
  Target q;
  q.biphasic = false;
  q.k_pa = k_pa;
  q.weights = {1};
  return q;
}

// Table 1 dermis: K1 0.1 kPa, turning strain 0.4, K2 18.8 kPa
Target dermis() { return biphasic(100, 0.4, 18800); }

// a deterministic run: bounded by evaluations, never by wall time
TuneOptions sa(std::int64_t evaluations, std::uint64_t seed = 1) {
  TuneOptions o;
  o.method = "sa";
  o.seed = seed;
  o.budget_s = 1e6;
  o.max_evaluations = evaluations;
  return o;
}

void expect_within(const Target& q, const TuneResult& r, double tol, const std::string& what) {
  const auto v = q.values();
  const auto keys = q.keys();
  ASSERT_EQ(r.measured.p.size(), v.size()) << what << ": " << r.measured.failure;
  for (std::size_t i = 0; i < v.size(); ++i)
    EXPECT_LE(std::abs(r.measured.p[i] - v[i]) / v[i], tol)
        << what << " " << keys[i] << ": achieved " << r.measured.p[i] << ", target " << v[i] << " (" << r.evaluations
        << " evaluations, stop " << r.stop << ")";
}

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.message();
  }
  return "";
}

}  // namespace

// ---- the bilinear and linear fits ------------------------------------------------

TEST(TuneFit, RecoversBilinearParametersFromSyntheticCurves) {
  struct Case {
    double k1, b, k2;
    int n;
    double emax;
  };
  // turning strain between samples, on a sample, near the first and last sample
  for (const Case& c : {Case{100, 0.4, 18800, 13, 0.8}, Case{100, 0.4, 18800, 8, 0.8}, Case{3e5, 0.05, 9e5, 20, 0.2},
                        Case{1, 0.11, 50, 12, 0.6}, Case{2.5e3, 0.52, 2.6e3, 9, 0.9}}) {
    std::vector<double> e, s;
    for (int i = 1; i <= c.n; ++i) {
      const double x = c.emax * i / c.n;
      e.push_back(x);
      s.push_back(x < c.b ? c.k1 * x : c.k1 * c.b + c.k2 * (x - c.b));
    }
    for (FitWeighting w : {FitWeighting::relative, FitWeighting::absolute}) {
      const BilinearFit f = fit_bilinear(e, s, w);
      EXPECT_NEAR(f.k1_pa, c.k1, 1e-9 * c.k1) << c.k1 << " " << c.b << " " << c.k2;
      EXPECT_NEAR(f.turning_strain, c.b, 1e-9 * c.b) << c.k1 << " " << c.b << " " << c.k2;
      EXPECT_NEAR(f.k2_pa, c.k2, 1e-9 * c.k2) << c.k1 << " " << c.b << " " << c.k2;
      EXPECT_LE(f.rms_pa, 1e-9 * c.k2 * c.emax);
    }
  }
}

TEST(TuneFit, LeastSquaresOnNoisyCurveAndLinearFit) {
  // symmetric +-1 % noise on a bilinear curve: the fit stays within a few %
  std::vector<double> e, s;
  for (int i = 1; i <= 16; ++i) {
    const double x = 0.05 * i;
    e.push_back(x);
    s.push_back((x < 0.4 ? 100 * x : 40 + 18800 * (x - 0.4)) * (1 + (i % 2 ? 0.01 : -0.01)));
  }
  const BilinearFit f = fit_bilinear(e, s);
  EXPECT_NEAR(f.k1_pa, 100, 3);
  EXPECT_NEAR(f.turning_strain, 0.4, 0.01);
  EXPECT_NEAR(f.k2_pa, 18800, 400);
  EXPECT_DOUBLE_EQ(fit_linear({0.1, 0.2, 0.3}, {230, 460, 690}), 2300);
  EXPECT_NE(error_of([] { fit_bilinear({0.1, 0.2}, {1, 2}); }).find("at least 3"), std::string::npos);
  EXPECT_NE(error_of([] { fit_bilinear({0.1, 0.1, 0.3}, {1, 2, 3}); }).find("increasing"), std::string::npos);
  EXPECT_NE(error_of([] { fit_linear({0.1}, {NAN}); }).find("non-finite"), std::string::npos);
}

// ---- the virtual experiment against analytic lattices ------------------------------

// The linear modulus a lattice specimen of `cells` box cells of `cell_m`
// measures along `axis` at a small strain, with the rule's springs for q.
namespace {
Measurement small_strain_lattice(std::array<int, 3> cells, std::array<double, 3> cell_m, int axis, const Target& q) {
  ExperimentOptions o;
  o.kind = "lattice";
  o.cells = cells;
  o.cell_m = cell_m;
  o.axis = axis;
  o.linear_strain = 1e-6;
  o.linear_steps = 2;
  msm::Specimen s = make_tissue_specimen(o);
  apply_params(s, rule_params(q));
  return measure(s, sliding_grips(s, axis), q, o);
}
}  // namespace

// A cubic lattice (edges + face diagonals, per-cell k_e = E a / 10, k_f = E a / 5)
// is isotropic with modulus E exactly (Cauchy-Born); at a small strain the
// measured modulus is E to O(strain).
TEST(TuneExperiment, LinearLatticeModulusIsTheAnalyticValue) {
  const Target q = linear(2300);
  for (int axis : {0, 1, 2}) {
    const Measurement m = small_strain_lattice({3, 2, 2}, {1e-3, 1e-3, 1e-3}, axis, q);
    ASSERT_EQ(m.p.size(), 1u) << m.failure;
    EXPECT_NEAR(m.p[0], 2300, 2300 * 1e-5) << "axis " << axis;
  }
}

// The cells of a coarse grid's layer are far from cubic (the phantom's fat at
// 15 x 5: 9.6 x 23.4 x 4.1 mm), where the unconstrained rule dropped whole
// spring families and left a mechanism. With the rule's floor the specimen is
// rigid on every axis and its modulus is the Cauchy-Born prediction of the
// rule's weights (the affine field is exact for a block of box cells): with
// the axis correction (the specimen's default, as build's) E on every axis.
TEST(TuneExperiment, FlatLatticeCellsAreRigidAndHaveTheRulesModuli) {
  const Target q = linear(2300);
  const std::array<double, 3> cell{9.634779061042022e-3, 23.432936673436475e-3, 4.088599158621684e-3};
  const msm::CellRule rule = msm::cell_rule(cell[0], cell[1], cell[2], false, 0.01, true);
  const auto E = msm::axis_moduli(msm::box_stiffness(cell[0], cell[1], cell[2], rule));
  for (int axis : {0, 1, 2}) {
    const Measurement m = small_strain_lattice({2, 2, 1}, cell, axis, q);
    ASSERT_EQ(m.p.size(), 1u) << "axis " << axis << ": " << m.failure;
    EXPECT_NEAR(m.p[0] / (2300 * E[static_cast<std::size_t>(axis)]), 1.0, 1e-4) << "axis " << axis;
  }
}

// shared/reference/lattice-elasticity.md, "An exactly bilinear case": a 2-D
// triangular lattice of bilinear springs pulled along a bond axis is exactly
// bilinear with E1 = 2 k1 / (sqrt(3) t), E2 = 2 k2 / (sqrt(3) t) and the
// springs' turning strain, at any strain (the +-60 degree bonds keep their
// length). msm::make_specimen builds only the model's cubic lattice and tetra
// prism cells, so the network is made here and run through the same
// experiment (tension_test on the target's strain schedule, then the fit).
TEST(TuneExperiment, TriangularLatticeIsExactlyBilinear) {
  const int nx = 6, ny = 5;  // bonds per row, rows of nodes
  const double a = 1e-3, t = 0.5e-3, k1 = 0.2, k2 = 30, eps_t = 0.3;
  const double h = a * std::sqrt(3.0) / 2;
  msm::Specimen s;
  std::vector<Eigen::Vector3d> X;
  std::vector<std::array<int, 2>> bonds;
  Grips g;
  g.axis = 0;
  auto id = [&](int i, int j) { return j * (nx + 1) + i; };
  for (int j = 0; j < ny; ++j)
    for (int i = 0; i <= nx; ++i) X.emplace_back((i + 0.5 * (j % 2)) * a, j * h, 0.0);
  for (int j = 0; j < ny; ++j)
    for (int i = 0; i <= nx; ++i) {
      if (i < nx) bonds.push_back({id(i, j), id(i + 1, j)});
      if (j + 1 < ny) {
        // the two bonds up: to (i, j+1) and to its left or right neighbour
        bonds.push_back({id(i, j), id(i, j + 1)});
        const int o = j % 2 ? i + 1 : i - 1;
        if (o >= 0 && o <= nx) bonds.push_back({id(i, j), id(o, j + 1)});
      }
    }
  const Eigen::Index nn = static_cast<Eigen::Index>(X.size()), ns = static_cast<Eigen::Index>(bonds.size());
  s.network.nodes.resize(nn, 3);
  for (Eigen::Index n = 0; n < nn; ++n) s.network.nodes.row(n) = X[static_cast<std::size_t>(n)].transpose();
  s.network.springs.resize(ns, 2);
  s.network.rest_length.resize(ns), s.network.k1.resize(ns), s.network.k2.resize(ns);
  s.network.turning_length.resize(ns);
  for (Eigen::Index b = 0; b < ns; ++b) {
    s.network.springs.row(b) << bonds[static_cast<std::size_t>(b)][0], bonds[static_cast<std::size_t>(b)][1];
    s.network.rest_length(b) = a;
    s.network.k1(b) = k1, s.network.k2(b) = k2;
    s.network.turning_length(b) = a * (1 + eps_t);
  }
  // each row's two end nodes are gripped at their own abscissa (the rows are
  // staggered), so every row is stretched by the same nominal strain; the
  // plane's z dofs and one y dof are held
  for (int j = 0; j < ny; ++j) {
    g.nodes.push_back(id(0, j)), g.lever_m.push_back(X[static_cast<std::size_t>(id(0, j))].x());
    g.nodes.push_back(id(nx, j)), g.lever_m.push_back(X[static_cast<std::size_t>(id(nx, j))].x());
    g.measured.push_back(id(nx, j));
  }
  for (Eigen::Index n = 0; n < nn; ++n) g.held.push_back(3 * n + 2);
  g.held.push_back(3 * id(0, 0) + 1);
  g.area_m2 = ny * h * t;  // each row carries a strip of width h

  const Target q = biphasic(1, eps_t, 2);  // only the turning strain sets the schedule
  ExperimentOptions o;
  const Measurement m = measure(s, g, q, o);
  ASSERT_EQ(m.p.size(), 3u) << m.failure;
  const double E1 = 2 * k1 / (std::sqrt(3.0) * t), E2 = 2 * k2 / (std::sqrt(3.0) * t);
  // a 1e-9 Newton tolerance on the forces: the fit to ~1e-8
  EXPECT_NEAR(m.p[0], E1, 1e-7 * E1);
  EXPECT_NEAR(m.p[1], eps_t, 1e-7 * eps_t);
  EXPECT_NEAR(m.p[2], E2, 1e-7 * E2);
  EXPECT_LT(m.fit.rms_pa, 1e-7 * E2);
  EXPECT_GT(m.curve.strain.back(), 1.5 * eps_t);
}

TEST(TuneExperiment, StrainScheduleStraddlesTheTurningStrain) {
  const ExperimentOptions o;
  const auto e = strain_schedule(dermis(), o);
  ASSERT_GE(e.size(), 10u);
  EXPECT_NEAR(e[6] - 0.4, 0.4 - e[5], 1e-12);  // T half-way between two samples
  EXPECT_LE(e.back(), o.stretch * 0.4 + 1e-12);
  EXPECT_GT(e.back(), 1.8 * 0.4);
}

// ---- the annealer ----------------------------------------------------------------------

TEST(TuneAnneal, FindsTheMinimumOfAMultimodalFunctionReproducibly) {
  // Rastrigin-like in 3-D, minimum 0 at (0.3, 0.6, 0.8), local minima 0.1 apart
  const std::vector<double> c = {0.3, 0.6, 0.8};
  auto f = [&](const std::vector<double>& x) {
    double v = 0;
    for (std::size_t i = 0; i < x.size(); ++i) {
      const double d = 10 * (x[i] - c[i]);
      v += d * d + 3 * (1 - std::cos(2 * M_PI * d));
    }
    return v;
  };
  AnnealOptions o;
  o.seed = 7;
  o.max_evaluations = 30000;
  o.walk_sweeps = 1000;
  const AnnealResult a = anneal(f, {0.5, 0.5, 0.5}, o, [](double best) { return best < 1e-3; });
  const AnnealResult b = anneal(f, {0.5, 0.5, 0.5}, o, [](double best) { return best < 1e-3; });
  EXPECT_EQ(a.stop, "target");
  for (std::size_t i = 0; i < 3; ++i) EXPECT_NEAR(a.x[i], c[i], 1e-3);
  EXPECT_EQ(a.x, b.x);
  EXPECT_EQ(a.evaluations, b.evaluations);
  EXPECT_NE(error_of([&] { anneal(f, {1.5, 0.5, 0.5}, o); }).find("unit box"), std::string::npos);
}

// ---- tuning ----------------------------------------------------------------------------------

// Table 1 dermis: each parameter within 1 % (the paper: 18 %, 2.5 %, 1.5 %).
TEST(Tune, DermisWithinOnePercent) {
  const TuneResult r = tune_target(dermis(), ExperimentOptions{}, sa(4000));
  expect_within(dermis(), r, 0.01, "dermis");
  EXPECT_TRUE(r.reached) << r.stop;
  EXPECT_EQ(r.stop, "target");
  EXPECT_LE(r.max_error, 1e-3);  // the default stopping target
  EXPECT_EQ(r.classes.size(), 3u);  // structural, shear, inter-layer springs of the tetra prism
  // the untuned rule is not already there: the tuner did the work
  EXPECT_GT(max_relative_error(dermis(), r.untuned.p), 0.1);
  ASSERT_FALSE(r.trace.empty());
  for (std::size_t i = 1; i < r.trace.size(); ++i) EXPECT_LT(r.trace[i].best, r.trace[i - 1].best);
}

// Eq. 1's minimiser does not depend on the weights' scale, and neither does
// the tuning: weights of 1e8 put every Psi above the failed experiments' value
// (1e6), the landscape was flat, and the dermis stayed at its untuned rule
// (41 % off). Now it tunes to the same result as with weights of 1.
TEST(Tune, WeightsCountRelativeToEachOther) {
  Target big = dermis();
  big.weights = {1e8, 1e8, 1e8};
  EXPECT_EQ(objective(big, {150, 0.3, 20000}), objective(dermis(), {150, 0.3, 20000}));
  Target mixed = dermis();
  mixed.weights = {2e8, 1e8, 1e8};
  Target half = dermis();
  half.weights = {1, 0.5, 0.5};
  EXPECT_EQ(objective(mixed, {150, 0.3, 20000}), objective(half, {150, 0.3, 20000}));
  const TuneResult r = tune_target(big, ExperimentOptions{}, sa(4000));
  const TuneResult ref = tune_target(dermis(), ExperimentOptions{}, sa(4000));
  expect_within(big, r, 0.01, "dermis, weights 1e8");
  EXPECT_TRUE(r.reached) << r.stop;
  EXPECT_EQ(r.measured.p, ref.measured.p) << "the same search, bit for bit";
  EXPECT_EQ(r.evaluations, ref.evaluations);
}

// Every tissue with mechanics in data-samples/tissues.json, on its layer kind.
TEST(Tune, SampleTissueTableWithinTwoPercent) {
  const TissueTable t = load_tissue_table(std::string(ORTHOSIM_SOURCE_DIR) + "/data-samples/tissues.json");
  int tuned = 0;
  for (const Tissue& tissue : t.tissues) {
    if (tissue.mechanics.model == Mechanics::Model::none) continue;
    const Target q = target_of(tissue);
    ExperimentOptions o;
    o.kind = tissue.layer == "lattice" ? "lattice" : "tetra";
    const TuneResult r = tune_target(q, o, sa(4000));
    expect_within(q, r, 0.02, tissue.name);
    ++tuned;
  }
  EXPECT_EQ(tuned, 3);  // skin (biphasic, tetra), fat and muscle (linear, lattice)
}

// Targets of the same kind that the tuner was not set up on: stiffness x 1000
// and other turning strains, on the tetra prism.
TEST(Tune, ScaledTargetsWithinTwoPercent) {
  for (const Target& q : {biphasic(1e5, 0.25, 1.88e7), biphasic(1e5, 0.6, 1.88e7), biphasic(5e3, 0.15, 6e4)}) {
    const TuneResult r = tune_target(q, ExperimentOptions{}, sa(4000));
    expect_within(q, r, 0.02, "K1 " + std::to_string(q.k1_pa) + " T " + std::to_string(q.turning_strain));
  }
}

// The experiment loads one axis. With a law per spring class the search had
// more variables than the target has values, and the seed chose the stiffness
// across the load: the sample table's muscle lattice tuned with seeds 1 and 3
// came out 0.2x and 4.8x the rule's across, 0.1 % off along (sweep of
// 2026-11-27). One law for every class (the default) keeps the rule's ratio
// of the two axes; the seed changes only the last digits.
double modulus_along(int axis, const Target& q, ExperimentOptions o, const SpringParams& params) {
  o.axis = axis;
  msm::Specimen s = make_tissue_specimen(o);
  apply_params(s, params);
  const Measurement m = measure(s, sliding_grips(s, axis), q, o);
  EXPECT_FALSE(m.p.empty()) << m.failure;
  return m.p.empty() ? 0.0 : m.p[0];  // K (linear) or K1 (biphasic)
}

TEST(Tune, TheStiffnessAcrossTheLoadDoesNotDependOnTheSeed) {
  const TissueTable t = load_tissue_table(std::string(ORTHOSIM_SOURCE_DIR) + "/data-samples/tissues.json");
  for (const char* name : {"muscle", "skin"}) {
    const Tissue* tissue = nullptr;
    for (const Tissue& x : t.tissues)
      if (x.name == name) tissue = &x;
    ASSERT_NE(tissue, nullptr) << name;
    const Target q = target_of(*tissue);
    ExperimentOptions o;
    o.kind = tissue->layer == "lattice" ? "lattice" : "tetra";
    // the sample model's cells (tune --model's report): long along the limb (v)
    o.cells = {2, 2, 1};
    o.cell_m = o.kind == "lattice" ? std::array<double, 3>{3.1e-3, 11.8e-3, 12.3e-3}
                                   : std::array<double, 3>{4.1e-3, 11.8e-3, 1.96e-3};
    const SpringParams rule = rule_params(q);
    // the rule's anisotropy: across / along
    const double rule_ratio = modulus_along(1, q, o, rule) / modulus_along(0, q, o, rule);
    std::vector<double> across;
    for (std::uint64_t seed : {1, 3}) {
      const TuneResult r = tune_target(q, o, sa(4000, seed));
      expect_within(q, r, 0.01, std::string(name) + " seed " + std::to_string(seed));
      across.push_back(modulus_along(1, q, o, r.params));
      const double ratio = across.back() / r.measured.p[0];
      EXPECT_NEAR(ratio / rule_ratio, 1, 0.02) << name << " seed " << seed << ": across / along " << ratio
                                               << ", the rule's " << rule_ratio;
    }
    EXPECT_NEAR(across[1] / across[0], 1, 0.02) << name << ": across the load, seeds 1 and 3";
  }
}

// The search loads one axis; the result says what the tuned specimen does
// along the other two. A lattice of cubic cells, 2 x 2 cells in plane: u and v
// are the same by symmetry; through the single cell layer it differs.
TEST(Tune, TheOtherAxesAreMeasured) {
  ExperimentOptions o;
  o.kind = "lattice";
  const TuneResult r = tune_target(linear(3000), o, sa(400));
  ASSERT_EQ(r.measured.p.size(), 1u);
  EXPECT_DOUBLE_EQ(r.axis_ratio[0], r.measured.p[0] / 3000);
  EXPECT_NEAR(r.axis_ratio[1], r.axis_ratio[0], 1e-9 * r.axis_ratio[0]);
  EXPECT_TRUE(std::isfinite(r.axis_ratio[2]));
  EXPECT_GT(r.axis_ratio[2], 0);
}

// The experiment loads u only; the rule's axis correction (docs/msm.md) is
// what gives the tuned layer the target along v and through it too. Lattice
// cells are affine: the tuned block has the target on every axis (without
// the correction 1.45x along v on the paper's 39 x 9 limb cells). Tetra
// prisms: the small-strain moduli of the tuned block are the target on every
// axis (within the 2 x 2 block's free-edge effect, 4 %); at the experiment's
// 1 % strain the block stiffens along the cells' long side (v), 1.33x here,
// against 2.02x with the trace rule alone (docs/msm.md).
TEST(Tune, TheTunedSpecimenHasTheTargetAlongEveryAxis) {
  const Target q = linear(3000);
  for (const char* kind : {"tetra", "lattice"}) {
    const bool tetra = std::string(kind) == "tetra";
    ExperimentOptions o;
    o.kind = kind;
    o.cells = tetra ? std::array<int, 3>{2, 2, 1} : std::array<int, 3>{2, 2, 2};
    o.cell_m = {4.4e-3, 16e-3, 5e-3};
    double off[2][3] = {};
    for (const bool corrected : {true, false}) {
      o.axis_correction = corrected;
      msm::Specimen s = make_tissue_specimen(o);
      const TuneResult r = tune_specimen(s, q, o, sa(400));
      ASSERT_TRUE(r.reached) << kind;
      for (int a = 0; a < 3; ++a) off[corrected ? 0 : 1][a] = std::abs(r.axis_ratio[static_cast<std::size_t>(a)] - 1);
      RecordProperty(std::string(kind) + (corrected ? "" : "_uncorrected") + "_axis_ratio_v_w",
                     std::to_string(r.axis_ratio[1]) + " " + std::to_string(r.axis_ratio[2]));
      if (!corrected || !tetra) continue;
      for (int a = 0; a < 3; ++a) {
        msm::UniaxialOptions u;
        u.axis = a;
        const double E = msm::uniaxial_test(s, {1e-4}, u).stress_pa[0] / 1e-4;
        EXPECT_NEAR(E / 3000, 1.0, 0.05) << "tetra small strain, axis " << a;
      }
    }
    if (tetra) {
      for (int a = 1; a < 3; ++a) EXPECT_LT(off[0][a], off[1][a]) << "tetra axis " << a;
    } else {
      for (int a = 0; a < 3; ++a) EXPECT_LT(off[0][a], 0.01) << "lattice axis " << a;
      EXPECT_GT(std::max(off[1][1], off[1][2]), 0.2) << "lattice without the correction";
    }
  }
}

TEST(Tune, SameSeedSameResult) {
  TuneOptions o = sa(400, 5);
  o.tolerance = 1e-6;  // stops on evaluations
  const TuneResult a = tune_target(dermis(), ExperimentOptions{}, o);
  const TuneResult b = tune_target(dermis(), ExperimentOptions{}, o);
  EXPECT_EQ(a.stop, "evaluations");
  EXPECT_EQ(a.evaluations, 400);
  EXPECT_EQ(a.psi, b.psi);
  EXPECT_EQ(a.measured.p, b.measured.p);
  for (int c = 0; c < kSpringClasses; ++c) {
    EXPECT_EQ(a.params[static_cast<std::size_t>(c)].k1_pa, b.params[static_cast<std::size_t>(c)].k1_pa);
    EXPECT_EQ(a.params[static_cast<std::size_t>(c)].turning_strain, b.params[static_cast<std::size_t>(c)].turning_strain);
    EXPECT_EQ(a.params[static_cast<std::size_t>(c)].k2_pa, b.params[static_cast<std::size_t>(c)].k2_pa);
  }
  ASSERT_EQ(a.trace.size(), b.trace.size());
  for (std::size_t i = 0; i < a.trace.size(); ++i) EXPECT_EQ(a.trace[i].evaluations, b.trace[i].evaluations);
  // another seed walks elsewhere
  o.seed = 6;
  const TuneResult c = tune_target(dermis(), ExperimentOptions{}, o);
  EXPECT_NE(a.psi, c.psi);
}

TEST(Tune, NloptGlobalThenPolishImprovesOnTheRule) {
  TuneOptions o = sa(300);
  o.method = "crs2";
  o.polish = "bobyqa";
  const TuneResult r = tune_target(dermis(), ExperimentOptions{}, o);
  EXPECT_EQ(r.method, "crs2+bobyqa");
  EXPECT_LE(r.evaluations, 300);
  EXPECT_LT(r.psi, objective(dermis(), r.untuned.p));
}

// A local method counts the rule's own evaluation against max_evaluations
// (sbplx, neldermead, cobyla ran max_evaluations + 1 experiments).
TEST(Tune, LocalMethodsKeepToTheEvaluationBound) {
  for (const char* method : {"bobyqa", "sbplx", "neldermead", "cobyla"})
    for (const std::int64_t n : {1, 5, 12}) {
      TuneOptions o = sa(n);
      o.method = method;
      o.tolerance = 1e-9;  // never reached: the bound stops the run
      const TuneResult r = tune_target(dermis(), ExperimentOptions{}, o);
      EXPECT_LE(r.evaluations, n) << method;
      EXPECT_GE(r.evaluations, 1) << method;
      EXPECT_EQ(r.stop, "evaluations") << method << " " << n;
    }
}

// ---- the model layer and the /tuning record ----------------------------------------------------

TEST(Tune, AppliesTunedLawsToALayerAndRoundTripsTheRecord) {
  // a layer carrying the rule (every class the tissue's law), made from a specimen
  const Target q = dermis();
  msm::Specimen s = make_tissue_specimen(ExperimentOptions{});
  const SpringParams rule = rule_params(q);
  apply_params(s, rule);
  Layer l;
  l.tissue = "skin";
  l.kind = "tetra";
  l.nodes = s.network.nodes;
  l.springs = s.network.springs;
  l.rest_length = s.network.rest_length;
  l.spring_class = s.spring_class;
  l.k1 = s.network.k1, l.k2 = s.network.k2, l.turning_length = s.network.turning_length;
  l.damping = 0.01 * s.network.k1.cwiseSqrt();
  SpringParams tuned = rule;
  tuned[0] = {150, 0.35, 20000};
  tuned[1] = {80, 0.3, 15000};
  Layer m = l;
  apply_to_layer(m, rule, tuned);
  for (Eigen::Index i = 0; i < l.springs.rows(); ++i) {
    const ClassLaw& t = tuned[l.spring_class(i)];
    EXPECT_NEAR(m.k1(i), t.k1_pa * s.k_per_pa(i), 1e-12 * m.k1(i) + 1e-300);
    EXPECT_NEAR(m.k2(i), t.k2_pa * s.k_per_pa(i), 1e-12 * m.k2(i) + 1e-300);
    EXPECT_NEAR(m.turning_length(i), l.rest_length(i) * (1 + t.turning_strain), 1e-15);
    if (l.k1(i) > 0) {
      EXPECT_NEAR(m.damping(i), l.damping(i) * std::sqrt(m.k1(i) / l.k1(i)), 1e-12 * l.damping(i));
    }
  }
  EXPECT_GT(m.lin_springs.rows(), 0);  // the linear decomposition was redone
  // tuning twice from the recorded laws gives the same layer as once
  Layer twice = l;
  apply_to_layer(twice, rule, tuned);
  apply_to_layer(twice, tuned, tuned);
  EXPECT_TRUE(twice.k1.isApprox(m.k1, 1e-12));
  // a layer built with another law is refused
  EXPECT_NE(error_of([&] { Layer x = l; apply_to_layer(x, rule_params(biphasic(100, 0.3, 18800)), tuned); })
                .find("do not follow"),
            std::string::npos);

  TuneResult r;
  r.method = "sa";
  r.seed = 3;
  r.target = q;
  r.params = tuned;
  r.measured.p = {101, 0.401, 18700};
  r.psi = 1e-5;
  r.evaluations = 42;
  const Tuning rec = tuning_record(r);
  EXPECT_EQ(rec.target.size(), 3);
  EXPECT_EQ(rec.achieved(1), 0.401);
  EXPECT_EQ(rec.seed, 3);
  const SpringParams back = params_of(rec);
  for (int c = 0; c < kSpringClasses; ++c) {
    EXPECT_EQ(back[static_cast<std::size_t>(c)].k1_pa, tuned[static_cast<std::size_t>(c)].k1_pa);
    EXPECT_EQ(back[static_cast<std::size_t>(c)].turning_strain, tuned[static_cast<std::size_t>(c)].turning_strain);
    EXPECT_EQ(back[static_cast<std::size_t>(c)].k2_pa, tuned[static_cast<std::size_t>(c)].k2_pa);
  }
}

// ---- bad input ---------------------------------------------------------------------------------

TEST(Tune, RejectsTargetsOutOfPhysicalRangeAndBadOptions) {
  auto bad = [](Target q) { return error_of([&] { validate(q); }); };
  EXPECT_NE(bad(biphasic(-1, 0.4, 18800)).find("K1"), std::string::npos);
  EXPECT_NE(bad(biphasic(100, 0.4, 50)).find("K2 must not be smaller"), std::string::npos);
  EXPECT_NE(bad(biphasic(100, 0, 18800)).find("turning strain"), std::string::npos);
  EXPECT_NE(bad(biphasic(100, 1.0, 18800)).find("turning strain"), std::string::npos);
  EXPECT_NE(bad(linear(0)).find("K must be"), std::string::npos);
  // beyond a tissue's decades (k 1e30 kPa was tuned, 100 % off, exit 0)
  EXPECT_NE(bad(linear(1e33)).find("target K = 1e+30 kPa is outside a tissue's range, 1e-3 .. 1e9 kPa"), std::string::npos);
  EXPECT_NE(bad(linear(1e-27)).find("outside a tissue's range"), std::string::npos);
  EXPECT_NE(bad(biphasic(100, 0.4, 1e303)).find("target K2 = "), std::string::npos);
  EXPECT_EQ(bad(linear(1)), "");
  EXPECT_EQ(bad(linear(2e10)), "");  // cortical bone
  Target z = dermis();
  z.weights = {0, 0, 0};
  EXPECT_NE(bad(z).find("all weights are zero"), std::string::npos);
  z.weights = {1, -1, 1};
  EXPECT_NE(bad(z).find(">= 0"), std::string::npos);
  EXPECT_EQ(bad(dermis()), "");

  auto bad_options = [](TuneOptions o) { return error_of([&] { validate(o); }); };
  TuneOptions o;
  o.budget_s = 0;
  EXPECT_NE(bad_options(o).find("budget"), std::string::npos);
  o = TuneOptions{};
  o.method = "gradient-descent";
  EXPECT_NE(bad_options(o).find("unknown method"), std::string::npos);
  o = TuneOptions{};
  o.polish = "newton";
  EXPECT_NE(bad_options(o).find("unknown polish"), std::string::npos);
  EXPECT_EQ(bad_options(TuneOptions{}), "");
  // a tissue without mechanics has no target
  Tissue bone;
  bone.name = "bone";
  EXPECT_NE(error_of([&] { target_of(bone); }).find("no mechanics"), std::string::npos);
}
