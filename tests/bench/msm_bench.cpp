// orthosim build (libmodel/msm) speed: the paper's 39x9 grid and 400x100,
// 4 surfaces (skin:tetra, fat:lattice, muscle:lattice over a rigid bone), on a
// limb-like analytic stack. Goals (issue 5): < 100 ms and < 2 s.
//   build-msm/tests/msm_bench --benchmark_repetitions=5 --benchmark_report_aggregates_only=true
//   msm_bench --results=FILE.json [--quick]   the harness rows (orthosim bench): build time
//       against grid size 15x5 ... 400x100 (quick: up to 100x25), error = the
//       largest relative mass error of a layer (goal <= 1e-6), with the
//       mesh counts and quality counters (inverted tets, fallbacks) in extra.
#include "libmodel/msm/build.h"
#include "libmodel/msm/specimen.h"
#include "libmodel/tissues.h"
#include "tests/bench/bench_results.h"
#include "tests/libmodel/msm_fixtures.h"

#include <benchmark/benchmark.h>

using namespace orthosim;

namespace {

void build(benchmark::State& state, bool intersections, bool axis_correction = true) {
  const int nu = static_cast<int>(state.range(0)), nv = static_cast<int>(state.range(1));
  const auto surfaces = test::limb_stack(nu, nv);
  const auto table = parse_tissue_table(test::msm_tissue_table(), "tissues.json");
  const std::vector<msm::LayerSpec> specs = {{"skin", "tetra"}, {"fat", "lattice"}, {"muscle", "lattice"}};
  msm::BuildOptions o;
  o.check_intersections = intersections;
  o.axis_correction = axis_correction;
  msm::BuildReport r;
  for (auto _ : state) {
    auto m = msm::build_layers(surfaces, specs, table, o);
    r = m.report;
    benchmark::DoNotOptimize(m.layers.data());
  }
  state.counters["nodes"] = static_cast<double>(r.nodes);
  state.counters["springs"] = static_cast<double>(r.springs);
  state.counters["lin_springs"] = static_cast<double>(r.lin_springs);
  state.counters["tets"] = static_cast<double>(r.tets);
  state.counters["fallbacks"] = static_cast<double>(r.projection_fallbacks);
  for (const auto& [phase, s] : r.phases_s) state.counters["s_" + phase] = s;
}

void BM_Build(benchmark::State& state) { build(state, true); }
void BM_BuildNoIntersectionCheck(benchmark::State& state) { build(state, false); }
// the rules alone (build --no-axis-correction): the axis correction's cost
void BM_BuildNoAxisCorrection(benchmark::State& state) { build(state, true, false); }

// one virtual experiment of the tuner: a 6x6x6 lattice block, 10 strain steps to 0.6
void BM_UniaxialLattice(benchmark::State& state) {
  msm::SpecimenOptions so;
  so.cells = {6, 6, 6};
  auto s = msm::make_specimen(so);
  msm::apply_law(s, {100, 18800, 0.4});
  std::vector<double> strains;
  for (int k = 1; k <= 10; ++k) strains.push_back(0.06 * k);
  int iterations = 0;
  for (auto _ : state) {
    auto c = msm::uniaxial_test(s, strains, {});
    iterations = 0;
    for (int i : c.iterations) iterations += i;
    benchmark::DoNotOptimize(c.stress_pa.data());
  }
  state.counters["springs"] = static_cast<double>(s.network.springs.rows());
  state.counters["newton_iterations"] = iterations;
}

}  // namespace

BENCHMARK(BM_Build)->Args({39, 9})->Args({400, 100})->Unit(benchmark::kMillisecond)->MeasureProcessCPUTime()->UseRealTime();
BENCHMARK(BM_BuildNoIntersectionCheck)->Args({39, 9})->Args({400, 100})->Unit(benchmark::kMillisecond)->MeasureProcessCPUTime()->UseRealTime();
BENCHMARK(BM_BuildNoAxisCorrection)->Args({39, 9})->Args({400, 100})->Unit(benchmark::kMillisecond)->MeasureProcessCPUTime()->UseRealTime();
BENCHMARK(BM_UniaxialLattice)->Unit(benchmark::kMillisecond)->MeasureProcessCPUTime()->UseRealTime();

namespace {

void results(const std::string& path, bool quick) {
  bench::Results out("build", "msm_bench", quick);
  std::vector<std::pair<int, int>> grids = {{15, 5}, {39, 9}, {100, 25}};
  if (!quick) grids = {{15, 5}, {18, 5}, {39, 9}, {60, 15}, {100, 25}, {200, 50}, {400, 100}};
  const auto table = parse_tissue_table(test::msm_tissue_table(), "tissues.json");
  const std::vector<msm::LayerSpec> specs = {{"skin", "tetra"}, {"fat", "lattice"}, {"muscle", "lattice"}};
  for (auto [nu, nv] : grids) {
    const auto surfaces = test::limb_stack(nu, nv);
    msm::BuildReport r;
    bench::Row row;
    row.workload = "limb stack, 4 surfaces (skin:tetra, fat:lattice, muscle:lattice, bone rigid)";
    row.setting = std::to_string(nu) + "x" + std::to_string(nv);
    row.seconds = bench::time_runs(quick ? 3 : 5, [&] { r = msm::build_layers(surfaces, specs, table, {}).report; });
    row.error("max relative layer mass error", r.max_mass_error, "<=", 1e-6);
    row.x = static_cast<double>(r.nodes);
    row.extra = {{"nu", nu}, {"nv", nv}, {"nodes", r.nodes}, {"springs", r.springs}, {"tets", r.tets},
                 {"inverted_tets", r.inverted_tets}, {"projection_fallbacks", r.projection_fallbacks},
                 {"components", r.components}, {"surface_intersections", r.surface_intersections}};
    out.add(row);
  }
  out.write(path);
}

}  // namespace

int main(int argc, char** argv) {
  bench::CommonArgs a = bench::parse_common(argc, argv);
  if (!a.results.empty()) {
    results(a.results, a.quick);
    return 0;
  }
  int n = static_cast<int>(a.rest.size());
  benchmark::Initialize(&n, a.rest.data());
  if (benchmark::ReportUnrecognizedArguments(n, a.rest.data())) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
