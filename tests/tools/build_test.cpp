// orthosim build on a model file with analytic /quads: the layers, node sets
// and report it writes, and bad input (one line, exit 2, file untouched).
#include "libmodel/format/model.h"
#include "libmodel/msm/tetra.h"
#include "libmodel/provenance.h"
#include "tests/libmodel/msm_fixtures.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <map>

using namespace orthosim;

namespace {

std::string write_model(const test::TempDir& dir, const std::vector<std::pair<std::string, QuadSurface>>& s,
                        const std::string& name = "m.h5") {
  const std::string p = dir / name;
  ModelWriter w(p, ModelWriter::Start::fresh);
  for (const auto& [tissue, q] : s) w.write(tissue, q);
  w.commit();
  return p;
}

std::string write_table(const test::TempDir& dir, bool with_fat = true) {
  const std::string p = dir / (with_fat ? "tissues.json" : "tissues_nofat.json");
  test::write_file(p, test::msm_tissue_table(with_fat));
  return p;
}

void expect_refused(const std::string& args, const std::string& model, const std::string& needle) {
  const std::string before = hash_path(model);
  auto r = test::run_cli(args);
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find(needle), std::string::npos) << r.err;
  EXPECT_EQ(r.err.rfind("orthosim build: error: ", 0), 0u) << r.err;
  EXPECT_EQ(hash_path(model), before) << "the model file changed";
}

}  // namespace

TEST(BuildCli, WritesLayersSetsAndReport) {
  test::TempDir dir("build");
  const std::string model = write_model(dir, test::cylinder_stack(39, 9));
  const std::string tissues = write_table(dir);
  auto r = test::run_cli("build --model " + model + " --tissues " + tissues +
                         " --layers skin:tetra,fat:lattice,muscle:lattice --report " + (dir / "r.json"));
  ASSERT_EQ(r.code, 0) << r.err;
  ModelReader m(model);
  EXPECT_EQ(m.names("/layers"), (std::vector<std::string>{"bone", "fat", "muscle", "sets", "skin"}));
  const Layer skin = m.layer("skin");
  EXPECT_EQ(skin.kind, "tetra");
  EXPECT_EQ(skin.node_offset, 0);
  EXPECT_EQ(skin.tets.rows(), 39 * 8 * 2 * 7);
  EXPECT_EQ(m.layer("bone").kind, "rigid");
  EXPECT_EQ(m.node_set("fixed").size(), 39 * 9);
  EXPECT_EQ(m.node_set("skin").size(), 39 * 9);
  EXPECT_TRUE(m.has("/layers/sets/layer_muscle"));
  EXPECT_TRUE(m.has("/provenance/build"));
  EXPECT_TRUE(m.has("/quads/skin"));  // the input is still there
  auto rep = nlohmann::json::parse(test::read_file(dir / "r.json"));
  EXPECT_EQ(rep["metrics"]["components"], 1);
  EXPECT_EQ(rep["metrics"]["projection_fallbacks"], 0);
  EXPECT_EQ(rep["metrics"]["layers"].size(), 4u);
  EXPECT_LT(rep["metrics"]["max_mass_error"].get<double>(), 1e-9);
  // default stack from the tissue table gives the same layers; a rebuild replaces /layers
  r = test::run_cli("build --model " + model + " --tissues " + tissues + " --quiet");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(ModelReader(model).layer("skin").springs, skin.springs);
  // inspect summarises the layers
  r = test::run_cli("inspect " + model);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("/layers/skin"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("kind=\"tetra\""), std::string::npos) << r.out;
}

// Without a rigid tissue among the surfaces the innermost layered one is the
// fixed bottom: said on stderr and in the report (it was silent; the pipeline's
// tune then failed on it against a cache path).
TEST(BuildCli, ALayeredFixedBottomIsAWarning) {
  test::TempDir dir("build-nobone");
  const std::string model = write_model(dir, test::cylinder_stack(16, 5, 0.12, {0.030, 0.028, 0.022}));
  const std::string tissues = write_table(dir);
  auto r = test::run_cli("build --model " + model + " --tissues " + tissues + " --report " + (dir / "r.json"));
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("orthosim build: warning: " + model + ": no rigid tissue among /quads: 'muscle' (lattice in " + tissues +
                       ") is the model's fixed bottom"),
            std::string::npos)
      << r.err;
  EXPECT_EQ(nlohmann::json::parse(test::read_file(dir / "r.json"))["metrics"]["fixed_bottom"], "muscle");
  EXPECT_EQ(ModelReader(model).layer("muscle").kind, "rigid");
  // with the bone: no warning
  const std::string full = write_model(dir, test::cylinder_stack(16, 5), "full.h5");
  r = test::run_cli("build --model " + full + " --tissues " + tissues + " --quiet");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err, "");
}

TEST(BuildCli, BadInputOneLineExit2NoOutput) {
  test::TempDir dir("build-bad");
  const auto good = test::cylinder_stack(16, 5);
  const std::string tissues = write_table(dir), nofat = write_table(dir, false);
  const std::string model = write_model(dir, good);
  expect_refused("build --model " + model + " --tissues " + nofat, model, "missing from the tissue table");
  expect_refused("build --model " + model + " --tissues " + tissues + " --layers fat:lattice,skin:tetra", model,
                 "out of order");
  expect_refused("build --model " + model + " --tissues " + tissues + " --layers skin:cube", model, "tetra or lattice");
  // a flag out of range is the command line's error (it named the model file, and
  // the option's internal name, "damping_ratio")
  for (const auto& [flag, text] : std::vector<std::pair<std::string, std::string>>{
           {"--damping-ratio -1", "orthosim build: error: --damping-ratio must be in [0, 10]\n"},
           {"--through-cells 0", "orthosim build: error: --through-cells must be in 1..64\n"},
           {"--lattice-min-weight 1", "orthosim build: error: --lattice-min-weight must be in [0, 1)\n"},
           {"--poisson-ratio 0.5", "orthosim build: error: --poisson-ratio must be in [0.25, 0.5)\n"},
           {"--poisson-ratio 0.2", "orthosim build: error: --poisson-ratio must be in [0.25, 0.5)\n"},
           // (inf ran and said "thinner than inf m"; sweep of 2026-11-27)
           {"--min-thickness-mm inf", "orthosim build: error: --min-thickness-mm must be >= 0 and finite\n"}}) {
    expect_refused("build --model " + model + " --tissues " + tissues + " " + flag, model, "");
    EXPECT_EQ(test::run_cli("build --model " + model + " --tissues " + tissues + " " + flag).err, text);
  }
  {
    expect_refused("build --model " + model + " --tissues " + tissues + " --tetra-volume-term cells", model, "");
    const auto r = test::run_cli("build --model " + model + " --tissues " + tissues + " --tetra-volume-term cells");
    EXPECT_NE(r.err.find("--tetra-volume-term"), std::string::npos) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    // and prisms without a term (nu 1/4) asks for nothing: refused, not ignored
    expect_refused("build --model " + model + " --tissues " + tissues + " --tetra-volume-term prisms --poisson-ratio 0.25",
                   model, "--tetra-volume-term prisms needs a volume term: a Poisson's ratio above 0.25");
  }
  auto swapped = good;
  std::swap(swapped[0].second, swapped[1].second);
  const std::string m2 = write_model(dir, swapped, "swapped.h5");
  expect_refused("build --model " + m2 + " --tissues " + tissues, m2, "out of order or intersecting");
  auto mismatch = good;
  mismatch[2].second = test::cylinder(16, 6, 0.12, 0.022);
  const std::string m3 = write_model(dir, mismatch, "mismatch.h5");
  expect_refused("build --model " + m3 + " --tissues " + tissues, m3, "grids do not match");
  auto thin = good;
  thin[1].second = test::cylinder(16, 5, 0.12, 0.030 - 1e-6);
  const std::string m4 = write_model(dir, thin, "thin.h5");
  expect_refused("build --model " + m4 + " --tissues " + tissues, m4, "thinner than");
  // a model that already has layers keeps them when a rebuild fails
  ASSERT_EQ(test::run_cli("build --model " + model + " --tissues " + tissues + " --quiet").code, 0);
  expect_refused("build --model " + model + " --tissues " + nofat, model, "missing from the tissue table");
  EXPECT_TRUE(ModelReader(model).has("/layers/skin"));
}

// The soft skin of the paper's Table 1 (dermis K1 = 0.1 kPa) hangs under
// gravity and folds through the fat below it with central springs alone (the
// demo's pull scene: 149 of 351 skin columns inside out within 0.05 s;
// --poisson-ratio 0.25 --inversion-guard 0 here: 152 skin columns). The
// inversion guard alone (docs/msm.md, "The inversion guard"; --poisson-ratio
// 0.25, so its modulus is the bulk modulus of such a compressible tissue,
// 2/3 K1) leaves 8; the default (nu = 0.49: the tetra layer's term per
// tetrahedron, which makes its guard redundant, and the lattices' guard at
// 16.7 K1) keeps every column right way out.
TEST(BuildCli, TheVolumeTermKeepsASoftSkinRightWayOut) {
  test::TempDir dir("build-volume");
  const std::string tissues = write_table(dir);
  std::map<std::string, std::int64_t> inverted;
  const std::int64_t skin_tets = 39 * 8 * 2 * 7, lattice_tets = 2 * 39 * 8 * 6;
  const std::int64_t prism_tets = 39 * 8 * 2 * 2 * msm::kGridPrismTets;  // 2 groups a prism, 2 prisms a quad
  for (const std::string run : {"springs", "guard", "default", "prisms"}) {
    SCOPED_TRACE(run);
    const std::string opts = run == "springs" ? " --poisson-ratio 0.25 --inversion-guard 0"
                             : run == "guard" ? " --poisson-ratio 0.25"
                             : run == "prisms" ? " --tetra-volume-term prisms"
                                              : "";
    // the skin's guard only where its tetrahedra have no term of their own
    const bool prisms = run == "prisms", term = run == "default" || prisms, guard = run != "springs",
               skin_guard = run == "guard" || prisms;
    const std::string model = write_model(dir, test::cylinder_stack(39, 9), "m" + run + ".h5");
    const auto b = test::run_cli("build --model " + model + " --tissues " + tissues +
                                 " --layers skin:tetra,fat:lattice,muscle:lattice" + opts +
                                 " --quiet --report " + (dir / ("b" + run + ".json")));
    ASSERT_EQ(b.code, 0) << b.err;
    const auto br = nlohmann::json::parse(test::read_file(dir / ("b" + run + ".json")));
    // (over the grid prisms: two groups a prism at half the modulus each)
    EXPECT_NEAR(br["metrics"]["layers"][0]["volume_modulus_pa"].get<double>(), term ? (prisms ? 800.0 : 1600.0) : 0.0, 1e-9);
    EXPECT_EQ(br["metrics"]["layers"][0]["volume_group"].get<int>(), prisms ? msm::kGridPrismTets : 1);
    EXPECT_EQ(br["metrics"]["layers"][0]["volume_tets"].get<std::int64_t>(), prisms ? prism_tets : 0);
    // the guard: the bulk modulus K1 / (3 (1 - 2 nu)) at half the rest volume
    const double bulk = term ? 100.0 / (3 * (1 - 2 * 0.49)) : 100.0 / 1.5;
    EXPECT_NEAR(br["metrics"]["layers"][0]["guard_modulus_pa"].get<double>(), skin_guard ? bulk : 0.0, 1e-9);
    EXPECT_EQ(br["metrics"]["layers"][0]["guard_ratio"].get<double>(), skin_guard ? 0.5 : 0.0);
    EXPECT_NEAR(br["metrics"]["layers"][1]["guard_modulus_pa"].get<double>(), guard ? 23 * bulk : 0.0, 1e-6);
    EXPECT_EQ(br["metrics"]["tets"].get<std::int64_t>(), skin_tets + (guard ? lattice_tets : 0));
    // inspect shows the layer's attributes (absent without a term or a guard)
    const auto in = test::run_cli("inspect " + model + " --json");
    ASSERT_EQ(in.code, 0) << in.err;
    const auto summary = nlohmann::json::parse(in.out);
    const auto& skin = summary["summary"]["layers"]["skin"];
    EXPECT_EQ(skin.contains("volume_modulus"), term) << skin.dump();
    EXPECT_EQ(skin.contains("guard_modulus"), skin_guard) << skin.dump();
    if (term) {
      EXPECT_NEAR(skin["volume_modulus"].get<double>(), prisms ? 800.0 : 1600.0, 1e-9) << skin.dump();
    }
    EXPECT_EQ(skin.contains("n_volume_tets") ? skin["n_volume_tets"].get<std::int64_t>() : 0, prisms ? prism_tets : 0)
        << skin.dump();
    if (guard) {
      EXPECT_NEAR(summary["summary"]["layers"]["fat"]["guard_modulus"].get<double>(), 2300.0 * bulk / 100.0, 1e-9);
    }
    const std::string scene = dir / ("s" + run + ".json");
    test::write_file(scene, R"({"model": "m)" + run + R"(.h5", "fixed": ["fixed"], "integrator": "implicit",
                               "dt": 0.01, "duration": 0.3, "damping": {"mass": 5}})");
    const auto r = test::run_cli("run " + scene + " --no-output --quiet --report " + (dir / ("r" + run + ".json")));
    ASSERT_EQ(r.code, 0) << r.err;
    const auto j = nlohmann::json::parse(test::read_file(dir / ("r" + run + ".json")));
    // the runtime's tetrahedra: the term's and the guard's (one group each)
    EXPECT_EQ(j["metrics"]["volume_tets"].get<std::int64_t>(),
              (term || skin_guard ? skin_tets : 0) + (prisms ? prism_tets : 0) + (guard ? lattice_tets : 0));
    for (int l = 1; l < 3; ++l) EXPECT_EQ(br["metrics"]["layers"][l]["volume_modulus_pa"].get<double>(), 0.0) << "lattices: opt-in";
    inverted[run] = 0;
    for (const char* layer : {"skin", "fat", "muscle"}) {
      inverted[run] += j["metrics"]["inverted_columns"][layer]["max"].get<std::int64_t>();
      RecordProperty(run + "_" + layer, std::to_string(j["metrics"]["inverted_columns"][layer]["max"].get<std::int64_t>()));
    }
    EXPECT_EQ(r.err.find("turned inside out") != std::string::npos, inverted[run] > 0) << r.err;
  }
  EXPECT_GT(inverted["springs"], 100) << "central springs alone fold the soft skin";
  EXPECT_LT(inverted["guard"], inverted["springs"] / 10);
  EXPECT_EQ(inverted["default"], 0);
  EXPECT_EQ(inverted["prisms"], 0);
  // a guard ratio outside [0, 1) is refused
  const std::string bad = write_model(dir, test::cylinder_stack(39, 9), "bad.h5");
  for (const char* g : {"1", "-0.1", "nan"})
    expect_refused("build --model " + bad + " --tissues " + tissues + " --inversion-guard " + g, bad, "inversion");
  // --lattice-volume-term: the fat's and muscle's hexahedra too, 6 tetrahedra a term
  const std::string model = write_model(dir, test::cylinder_stack(39, 9), "lat.h5");
  const auto b = test::run_cli("build --model " + model + " --tissues " + tissues +
                               " --layers skin:tetra,fat:lattice,muscle:lattice --lattice-volume-term --quiet --report " +
                               (dir / "blat.json"));
  ASSERT_EQ(b.code, 0) << b.err;
  const auto br = nlohmann::json::parse(test::read_file(dir / "blat.json"));
  EXPECT_EQ(br["metrics"]["tets"].get<std::int64_t>(), 39 * 8 * 2 * 7 + 2 * 39 * 8 * 6);
  for (int l = 1; l < 3; ++l) {
    EXPECT_NEAR(br["metrics"]["layers"][l]["volume_modulus_pa"].get<double>(), 16 * (l == 1 ? 2300.0 : 3000.0), 1e-6);
    EXPECT_EQ(br["metrics"]["layers"][l]["volume_group"].get<int>(), 6);
  }
  const auto in = test::run_cli("inspect " + model + " --json");
  ASSERT_EQ(in.code, 0) << in.err;
  const auto summary = nlohmann::json::parse(in.out);
  EXPECT_EQ(summary["summary"]["layers"]["fat"]["volume_group"].get<int>(), 6) << summary["summary"]["layers"]["fat"].dump();
}
