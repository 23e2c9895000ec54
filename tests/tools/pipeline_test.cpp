// `orthosim pipeline`: a cold run builds a complete model, a warm run does no
// work, a changed grid re-runs only remesh and what follows, a scene without
// vessels skips the vessel stage, a corrupt cache entry is rebuilt, and a
// failing stage reports its own one-line error and leaves the previous model.
#include "libmodel/format/model.h"
#include "libmodel/phantom/phantom.h"
#include "libmodel/pipeline/cache.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <filesystem>
#include <functional>
#include <fstream>

using namespace orthosim;
namespace fs = std::filesystem;

namespace {

struct Sample {
  test::TempDir dir{"pipeline"};
  std::string stack, tissues;
  Sample() {
    const auto r = test::run_cli("phantom --out " + (dir / "ph") + " --size 96x96x32 --spacing 0.75,0.75,3 --seed 3 --quiet");
    EXPECT_EQ(r.code, 0) << r.err;
    stack = dir / "ph/slices";
    tissues = dir / "ph/tissues.json";
  }
  std::string args(const std::string& extra) const {
    return "pipeline --stack " + stack + " --tissues " + tissues + " --spacing 0.75,0.75,3 --work " + (dir / "work") +
           " --out " + (dir / "model.h5") + " --report " + (dir / "r.json") + " --no-texture --tune-budget-s 5 --quiet " + extra;
  }
  nlohmann::json report() const { return nlohmann::json::parse(test::read_file(dir / "r.json")); }
  std::set<std::string> ran() const {
    std::set<std::string> s;
    const nlohmann::json r = report();  // (a range-for over report()["stages"] would dangle)
    for (const auto& st : r["stages"])
      if (st.value("ran", false)) s.insert(st["stage"].get<std::string>());
    return s;
  }
};

const Sample& sample() {
  static Sample s;
  return s;
}

}  // namespace

TEST(PipelineCache, KeysAndManifests) {
  test::TempDir d("cache");
  EXPECT_NE(pipeline::stage_key("a", {"bc"}), pipeline::stage_key("a", {"b", "c"}));
  EXPECT_EQ(pipeline::stage_key("a", {"b"}), pipeline::stage_key("a", {"b"}));
  auto e = pipeline::open_entry(d.path, "s", "k1");
  EXPECT_FALSE(e.hit);
  test::write_file(e.dir + "/out.txt", "hello");
  pipeline::commit_entry(e, {"out.txt"});
  EXPECT_TRUE(pipeline::open_entry(d.path, "s", "k1").hit);
  // a changed output is detected and the entry cleared
  test::write_file(e.dir + "/out.txt", "hellO");
  auto again = pipeline::open_entry(d.path, "s", "k1");
  EXPECT_FALSE(again.hit);
  EXPECT_EQ(again.reason, "out.txt changed");
  EXPECT_FALSE(fs::exists(e.dir + "/out.txt"));
  // no manifest (an interrupted stage) is a miss
  test::write_file(e.dir + "/out.txt", "x");
  EXPECT_FALSE(pipeline::open_entry(d.path, "s", "k1").hit);
}

TEST(Pipeline, ColdWarmAndIncremental) {
  const Sample& s = sample();
  // cold: every stage runs, the model has everything
  auto r = test::run_cli(s.args(""));
  ASSERT_EQ(r.code, 0) << r.err;
  const auto cold = s.ran();
  for (const char* st : {"segment", "surface", "remesh", "build"}) EXPECT_TRUE(cold.count(st)) << st;
  {
    ModelReader m(s.dir / "model.h5");
    EXPECT_TRUE(m.h5().is_group("/volume"));
    EXPECT_TRUE(m.h5().is_group("/quads"));
    EXPECT_TRUE(m.h5().is_group("/layers"));
  }
  // the vessel trees ran in a child process beside surface..tune, and the
  // assembled model holds exactly the trees `orthosim vessels` writes alone
  for (const char* st : {"vessels", "tune", "assemble"}) EXPECT_TRUE(cold.count(st)) << st;
  {
    const nlohmann::json rep = s.report();
    for (const auto& st : rep["stages"])
      if (st["stage"] == "vessels") {
        EXPECT_TRUE(st.value("parallel", false));
      }
    std::string seg_dir, surf_dir;
    for (const auto& st : rep["stages"]) {
      if (st["stage"] == "segment") seg_dir = st["dir"];
      if (st["stage"] == "surface") surf_dir = st["dir"];
    }
    ASSERT_FALSE(seg_dir.empty());
    // the surfaces nest as the table says, not as inferred from the volume
    const auto srep = nlohmann::json::parse(test::read_file(surf_dir + "/report.json"));
    EXPECT_EQ(srep["parameters"]["nesting"], "tissue table");
    const auto alone = test::run_cli("vessels --labels " + seg_dir + "/labels.h5 --tissue artery --tissue vein --model " +
                                     (s.dir / "alone.h5") + " --quiet");
    ASSERT_EQ(alone.code, 0) << alone.err;
    ModelReader a(s.dir / "alone.h5"), m(s.dir / "model.h5");
    ASSERT_EQ(m.names("/vessels"), a.names("/vessels"));
    for (const auto& t : a.names("/vessels")) {
      const VesselTree x = a.vessels(t), y = m.vessels(t);
      EXPECT_GT(x.nodes.rows(), 0) << t;
      EXPECT_TRUE(x.nodes == y.nodes) << t;
      EXPECT_TRUE(x.radii == y.radii) << t;
      EXPECT_TRUE(x.tube_vertices == y.tube_vertices) << t;
      EXPECT_TRUE(x.tube_quads == y.tube_quads) << t;
    }
    // the provenance of every stage that wrote into the model
    for (const char* st : {"segment", "surface", "remesh", "build", "tune", "vessels"})
      EXPECT_TRUE(m.provenance().count(st)) << st;
    EXPECT_TRUE(m.h5().is_group("/surfaces"));
    EXPECT_TRUE(m.h5().is_group("/tuning"));
  }
  const std::string model_hash = test::read_file(s.dir / "model.h5");
  // warm: nothing runs, the same model comes out
  r = test::run_cli(s.args(""));
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(s.ran().empty());
  EXPECT_EQ(test::read_file(s.dir / "model.h5"), model_hash);
  // files segment does not read are no input: a hidden file or a note beside
  // the slices re-ran every stage and changed the model's provenance (the key
  // hashed the whole folder; sweep of 2026-11-27)
  test::write_file(s.stack + "/.DS_Store", "x");
  test::write_file(s.stack + "/notes.txt", "scanned on Tuesday");
  r = test::run_cli(s.args(""));
  fs::remove(s.stack + "/.DS_Store");
  fs::remove(s.stack + "/notes.txt");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(s.ran().empty());
  EXPECT_EQ(test::read_file(s.dir / "model.h5"), model_hash);
  // a new grid: remesh and what follows, not segment or surface
  r = test::run_cli(s.args("--grid 20x6"));
  ASSERT_EQ(r.code, 0) << r.err;
  auto ran = s.ran();
  EXPECT_FALSE(ran.count("segment"));
  EXPECT_FALSE(ran.count("surface"));
  EXPECT_TRUE(ran.count("remesh"));
  EXPECT_TRUE(ran.count("build"));
  // the trees read only the labels: cached, and only re-assembled
  EXPECT_FALSE(ran.count("vessels"));
  EXPECT_TRUE(ran.count("assemble"));
  // a corrupt cache entry is rebuilt, never used
  const auto stages = s.report()["stages"];
  std::string build_dir;
  for (const auto& st : stages)
    if (st["stage"] == "build") build_dir = st["dir"];
  ASSERT_FALSE(build_dir.empty());
  {
    std::ofstream f(build_dir + "/model.h5", std::ios::binary | std::ios::in | std::ios::out);
    f.seekp(1000);
    f.write("garbage", 7);
  }
  r = test::run_cli(s.args("--grid 20x6"));
  ASSERT_EQ(r.code, 0) << r.err;
  ran = s.ran();
  EXPECT_TRUE(ran.count("build"));
  EXPECT_FALSE(ran.count("remesh"));
  {
    // build's --through-cells: the pipeline passes it (a fine grid needs it; it had no such flag)
    ModelReader one(s.dir / "model.h5");
    const std::int64_t nodes1 = one.layer_fields("fat", {"nodes"}).nodes.rows();
    const auto tc = test::run_cli(s.args("--grid 20x6 --through-cells 2"));
    ASSERT_EQ(tc.code, 0) << tc.err;
    const auto ran2 = s.ran();
    EXPECT_FALSE(ran2.count("remesh"));
    EXPECT_TRUE(ran2.count("build"));
    ModelReader two(s.dir / "model.h5");
    EXPECT_EQ(two.layer_fields("fat", {"nodes"}).nodes.rows(), 2 * nodes1) << "a second cell layer of nodes";
  }
  {
    // build's --poisson-ratio: the skin's volume term (16 K1 at the default 0.49, none at 0.25)
    const double k1 = ModelReader(s.dir / "model.h5").layer_fields("skin", {"nodes"}).spring_law.at(0);
    EXPECT_NEAR(ModelReader(s.dir / "model.h5").layer_fields("skin", {"nodes"}).volume_modulus, 16 * k1, 1e-9 * k1);
    const auto off = test::run_cli(s.args("--grid 20x6 --poisson-ratio 0.25"));
    ASSERT_EQ(off.code, 0) << off.err;
    EXPECT_TRUE(s.ran().count("build"));
    EXPECT_EQ(ModelReader(s.dir / "model.h5").layer_fields("skin", {"nodes"}).volume_modulus, 0);
    const auto bad = test::run_cli(s.args("--grid 20x6 --poisson-ratio 0.5"));
    EXPECT_EQ(bad.code, 2) << bad.err;
    EXPECT_EQ(test::count_lines(bad.err), 1) << bad.err;
    EXPECT_NE(bad.err.find("--poisson-ratio"), std::string::npos) << bad.err;
    // --lattice-volume-term: the lattices' term per hexahedron (a build, its own cache key)
    EXPECT_EQ(ModelReader(s.dir / "model.h5").layer_fields("fat", {"nodes"}).volume_modulus, 0);
    const auto lat = test::run_cli(s.args("--grid 20x6 --lattice-volume-term"));
    ASSERT_EQ(lat.code, 0) << lat.err;
    EXPECT_TRUE(s.ran().count("build"));
    const Layer fat = ModelReader(s.dir / "model.h5").layer_fields("fat", {"nodes"});
    EXPECT_NEAR(fat.volume_modulus, 16 * fat.spring_law.at(0), 1e-9 * fat.volume_modulus);
    EXPECT_EQ(fat.volume_group, 6);
    // build's --inversion-guard: the lattices' guard (default 0.5, the bulk modulus;
    // 0: none), its own cache key, the report's parameter; a value outside [0, 1) refused
    EXPECT_NEAR(fat.guard_modulus, fat.spring_law.at(0) / (3 * (1 - 2 * 0.49)), 1e-9 * fat.guard_modulus);
    EXPECT_EQ(fat.guard_ratio, 0.5);
    const auto g = test::run_cli(s.args("--grid 20x6 --inversion-guard 0.7"));
    ASSERT_EQ(g.code, 0) << g.err;
    EXPECT_TRUE(s.ran().count("build"));
    EXPECT_FALSE(s.ran().count("remesh"));
    EXPECT_EQ(ModelReader(s.dir / "model.h5").layer_fields("muscle", {"nodes"}).guard_ratio, 0.7);
    EXPECT_EQ(s.report()["parameters"]["inversion_guard"].get<double>(), 0.7);
    const auto none = test::run_cli(s.args("--grid 20x6 --inversion-guard 0"));
    ASSERT_EQ(none.code, 0) << none.err;
    EXPECT_EQ(ModelReader(s.dir / "model.h5").layer_fields("muscle", {"nodes"}).guard_modulus, 0);
    const auto badg = test::run_cli(s.args("--grid 20x6 --inversion-guard 1"));
    EXPECT_EQ(badg.code, 2) << badg.err;
    EXPECT_EQ(test::count_lines(badg.err), 1) << badg.err;
    EXPECT_NE(badg.err.find("--inversion-guard"), std::string::npos) << badg.err;
    // vessels' --spur-ratio: the vessels stage alone runs again (its own cache key),
    // the report's parameter; a value <= 0 refused in one line
    const auto sr = test::run_cli(s.args("--grid 20x6 --inversion-guard 0 --spur-ratio 4"));
    ASSERT_EQ(sr.code, 0) << sr.err;
    EXPECT_TRUE(s.ran().count("vessels"));
    EXPECT_FALSE(s.ran().count("build"));
    EXPECT_EQ(s.report()["parameters"]["spur_ratio"].get<double>(), 4.0);
    const auto bads = test::run_cli(s.args("--grid 20x6 --spur-ratio 0"));
    EXPECT_EQ(bads.code, 2) << bads.err;
    EXPECT_EQ(test::count_lines(bads.err), 1) << bads.err;
    EXPECT_NE(bads.err.find("--spur-ratio"), std::string::npos) << bads.err;
    // segment's --smoothness: the report's parameter (the default prior); a negative value refused
    EXPECT_EQ(s.report()["parameters"]["smoothness"].get<double>(), 1.0);
    const auto badp = test::run_cli(s.args("--grid 20x6 --smoothness -1"));
    EXPECT_EQ(badp.code, 2) << badp.err;
    EXPECT_EQ(test::count_lines(badp.err), 1) << badp.err;
    EXPECT_NE(badp.err.find("--smoothness"), std::string::npos) << badp.err;
    // segment's --colour-space: the report's parameter (rgb by default); cielab runs segment
    // again (its own cache key); another space refused in one line
    EXPECT_EQ(s.report()["parameters"]["colour_space"], "rgb");
    const auto lab = test::run_cli(s.args("--grid 20x6 --colour-space cielab"));
    ASSERT_EQ(lab.code, 0) << lab.err;
    EXPECT_TRUE(s.ran().count("segment"));
    EXPECT_EQ(s.report()["parameters"]["colour_space"], "cielab");
    const auto badc = test::run_cli(s.args("--grid 20x6 --colour-space hsv"));
    EXPECT_EQ(badc.code, 2) << badc.err;
    EXPECT_EQ(test::count_lines(badc.err), 1) << badc.err;
    EXPECT_NE(badc.err.find("--colour-space"), std::string::npos) << badc.err;
  }
  {
    // build's --no-axis-correction: the pipeline passes it (its own cache key); the
    // build stage's report then has no axis factors on the tetra skin
    auto skin_factors = [&] {
      const nlohmann::json rep = s.report();
      for (const auto& st : rep["stages"])
        if (st["stage"] == "build") {
          const nlohmann::json br = nlohmann::json::parse(test::read_file(st["dir"].get<std::string>() + "/report.json"));
          for (const auto& l : br["metrics"]["layers"])
            if (l["kind"] == "tetra") return l["axis_factors_uvw"].get<std::vector<double>>();
        }
      return std::vector<double>{};
    };
    const auto on = test::run_cli(s.args("--grid 20x6"));
    ASSERT_EQ(on.code, 0) << on.err;
    EXPECT_NE(skin_factors(), std::vector<double>({1.0, 1.0, 1.0}));
    const auto off = test::run_cli(s.args("--grid 20x6 --no-axis-correction"));
    ASSERT_EQ(off.code, 0) << off.err;
    EXPECT_TRUE(s.ran().count("build"));
    EXPECT_FALSE(s.ran().count("remesh"));
    EXPECT_EQ(skin_factors(), std::vector<double>({1.0, 1.0, 1.0}));
    EXPECT_FALSE(s.report()["parameters"]["axis_correction"].get<bool>());
  }
}

// The tuning is bounded by --tune-evaluations, not by the clock: a re-run
// gives the same tuned table (it was cut by --tune-budget-s alone, so two
// runs differed by up to 408 N/m in the skin's k2).
TEST(Pipeline, TuningIsReproducible) {
  const Sample& s = sample();
  auto tune_dir = [&] {
    const nlohmann::json rep = s.report();
    for (const auto& st : rep["stages"])
      if (st["stage"] == "tune") return st["dir"].get<std::string>();
    return std::string();
  };
  // the tuned table without its timings
  auto tuned = [&](const std::string& d) {
    nlohmann::json t = nlohmann::json::parse(test::read_file(d + "/tuned_tissues.json"));
    std::function<void(nlohmann::json&)> strip = [&](nlohmann::json& j) {
      if (j.is_object()) {
        j.erase("seconds");
        j.erase("seconds_per_experiment");
      }
      if (j.is_object() || j.is_array())
        for (auto& e : j) strip(e);
    };
    strip(t);
    return t;
  };
  auto r = test::run_cli(s.args("--tune-evaluations 30"));
  ASSERT_EQ(r.code, 0) << r.err;
  const std::string d = tune_dir();
  ASSERT_FALSE(d.empty());
  EXPECT_TRUE(s.ran().count("tune"));
  const nlohmann::json first = tuned(d);
  const nlohmann::json rep = nlohmann::json::parse(test::read_file(d + "/report.json"));
  ASSERT_FALSE(rep["metrics"]["tissues"].empty());
  for (const auto& t : rep["metrics"]["tissues"]) {
    EXPECT_LE(t["evaluations"].get<long>(), 30 + 1) << t.dump();  // + the untuned measurement
    EXPECT_NE(t["stop"], "budget") << t.dump();
  }
  fs::remove_all(d);  // the cached tuning goes: it runs again
  r = test::run_cli(s.args("--tune-evaluations 30"));
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(s.ran().count("tune"));
  EXPECT_EQ(tuned(tune_dir()), first);
}

// The layers go outer to inner by the table's nesting ('inside'), not by the
// order the table lists them in: bone and marrow listed first was refused
// ("needs at least two layered tissues") and fat before skin failed in remesh.
TEST(Pipeline, LayerOrderFollowsTheNestingNotTheTableOrder) {
  const Sample& s = sample();
  nlohmann::json t = nlohmann::json::parse(test::read_file(s.tissues));
  auto& v = t["tissues"];
  std::stable_partition(v.begin(), v.end(), [](const nlohmann::json& e) {
    return e["name"] == "marrow" || e["name"] == "bone" || e["name"] == "fat";
  });
  ASSERT_EQ(v[0]["name"], "fat");
  const std::string table = s.dir / "reordered.json";
  test::write_file(table, t.dump(2));
  const auto r = test::run_cli("pipeline --stack " + s.stack + " --tissues " + table + " --spacing 0.75,0.75,3 --work " +
                               (s.dir / "work") + " --out " + (s.dir / "reordered.h5") + " --no-texture --no-tune --quiet");
  ASSERT_EQ(r.code, 0) << r.err;
  ModelReader m(s.dir / "reordered.h5");
  for (const char* l : {"skin", "fat", "muscle"}) EXPECT_TRUE(m.h5().is_group(std::string("/layers/") + l)) << l;
}

// A table with tissues the slices do not show (a general table on a crop)
// builds from the tissues they do show: each absent one gets a warning line
// naming the stack and the table, and the report lists them. The surface
// stage refused such a table with "tissue 'tendon' has no voxels" against a
// labels file in the pipeline's cache. A scene that needs an absent layer is
// refused naming it.
TEST(Pipeline, TissuesTheSlicesDoNotShowAreLeftOut) {
  const Sample& s = sample();
  nlohmann::json t = nlohmann::json::parse(test::read_file(s.tissues));
  auto& v = t["tissues"];
  int top = 0;
  for (const auto& e : v) top = std::max(top, e["label"].get<int>());
  nlohmann::json tendon, nerve;
  for (const auto& e : v) {
    if (e["name"] == "muscle") tendon = e;
    if (e["name"] == "vein") nerve = e;
  }
  ASSERT_FALSE(tendon.is_null());
  ASSERT_FALSE(nerve.is_null());
  tendon["name"] = "tendon", tendon["label"] = top + 1, tendon["inside"] = "fat", tendon["rgb"] = {{250, 250, 250}};
  nerve["name"] = "nerve", nerve["label"] = top + 2, nerve["rgb"] = {{10, 250, 10}};
  v.push_back(tendon);
  v.push_back(nerve);
  const std::string table = s.dir / "extra.json", out = s.dir / "extra.h5", rep = s.dir / "extra.json.report";
  test::write_file(table, t.dump(2));
  const std::string base = "pipeline --stack " + s.stack + " --tissues " + table + " --spacing 0.75,0.75,3 --work " +
                           (s.dir / "work") + " --no-texture --no-tune --quiet ";
  const auto r = test::run_cli(base + "--out " + out + " --report " + rep);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 2) << r.err;
  for (const char* name : {"tendon", "nerve"})
    EXPECT_NE(r.err.find("orthosim pipeline: warning: " + s.stack + ": no voxel was segmented as '" + name +
                         "' (no calibration sample and no voxel took its colour: the slices do not show it, or their compression or "
                         "noise changed it; tissue table " + table + "); it is left out"),
              std::string::npos)
        << r.err;
  EXPECT_EQ(nlohmann::json::parse(test::read_file(rep))["metrics"]["absent_tissues"],
            nlohmann::json::array({"tendon", "nerve"}));
  ModelReader m(out);
  for (const char* l : {"skin", "fat", "muscle"}) EXPECT_TRUE(m.h5().is_group(std::string("/layers/") + l)) << l;
  EXPECT_FALSE(m.h5().is_group("/layers/tendon"));
  // a scene that needs the absent layer
  test::write_file(s.dir / "tendon_scene.json", R"({"model": "m.h5", "layers": ["skin", "tendon"]})");
  const auto bad = test::run_cli(base + "--out " + (s.dir / "extra2.h5") + " --scene " + (s.dir / "tendon_scene.json"));
  EXPECT_EQ(bad.code, 2) << bad.err;
  EXPECT_NE(bad.err.find("orthosim pipeline: error: " + (s.dir / "tendon_scene.json") +
                         ": layer 'tendon': no voxel of it was segmented in " + s.stack),
            std::string::npos)
      << bad.err;
  EXPECT_FALSE(fs::exists(s.dir / "extra2.h5"));
  // a tissue whose colour is there but whose voxels the clean-up gave away (marrow put inside
  // the skin: not in contact with it, absorbed by the bone) is an error, not left out: the
  // slices show it (a collapsed segmentation gives the same, and then it was the skin)
  nlohmann::json m2 = nlohmann::json::parse(test::read_file(s.tissues));
  for (auto& e : m2["tissues"])
    if (e["name"] == "marrow") e["inside"] = "skin";
  const std::string moved = s.dir / "marrow_in_skin.json";
  test::write_file(moved, m2.dump(2));
  const auto rm = test::run_cli("pipeline --stack " + s.stack + " --tissues " + moved + " --spacing 0.75,0.75,3 --work " +
                                (s.dir / "work") + " --no-texture --no-tune --quiet --out " + (s.dir / "extra3.h5") +
                                " --report " + (s.dir / "extra3.json"));
  EXPECT_EQ(rm.code, 2) << rm.err;
  // the segment stage's warning (below), then the pipeline's error
  EXPECT_EQ(test::count_lines(rm.err), 2) << rm.err;
  EXPECT_EQ(rm.err.rfind("orthosim segment: warning: " + s.stack + ": no voxel of 'marrow' is left", 0), 0u) << rm.err;
  EXPECT_NE(rm.err.find("\northosim pipeline: error: " + s.stack + ": no voxel of 'marrow' is left after segmentation, though its colour was found ("),
            std::string::npos)
      << rm.err;
  EXPECT_NE(rm.err.find("check its 'inside' in " + moved), std::string::npos) << rm.err;
  EXPECT_FALSE(fs::exists(s.dir / "extra3.h5"));
  // segment alone warns of it (exit 0: the labels are what it made)
  const auto sg = test::run_cli("segment --stack " + s.stack + " --tissues " + moved + " --spacing 0.75,0.75,3 --out " +
                                (s.dir / "marrow_in_skin.h5") + " --quiet");
  EXPECT_EQ(sg.code, 0) << sg.err;
  EXPECT_NE(sg.err.find("orthosim segment: warning: " + s.stack + ": no voxel of 'marrow' is left, though the calibration found its colour ("),
            std::string::npos)
      << sg.err;
  EXPECT_NE(sg.err.find("check its colours and 'inside' in " + moved + ")\n"), std::string::npos) << sg.err;
  // the report is written, naming the stage whose output failed the check (it was not written at all)
  const auto rr = nlohmann::json::parse(test::read_file(s.dir / "extra3.json"));
  EXPECT_EQ(rr["failed_stage"], "segment");
  EXPECT_NE(rr["error"].get<std::string>().find("no voxel of 'marrow' is left"), std::string::npos);
}

TEST(Pipeline, ExportGathersEveryStagesOutputs) {
  const Sample& s = sample();
  const std::string out = s.dir / "export";
  const auto r = test::run_cli(s.args("--export " + out));
  ASSERT_EQ(r.code, 0) << r.err;
  for (const char* f : {"labels.h5", "surfaces/skin.stl", "surfaces/bone.stl", "quads/skin_quads.obj",
                        "vessels/artery_tube.stl", "vessels/vein_centreline.obj", "tuned_tissues.json", "tune/skin.png",
                        "reports/segment.json", "reports/surface.json", "reports/remesh.json", "reports/build.json",
                        "reports/tune.json", "reports/vessels.json"})
    EXPECT_TRUE(fs::is_regular_file(fs::path(out) / f)) << f;
  // the exported labels are the cached ones, byte for byte
  std::string seg_dir;
  const nlohmann::json rep = s.report();
  for (const auto& st : rep["stages"])
    if (st["stage"] == "segment") seg_dir = st["dir"];
  EXPECT_EQ(test::read_file(out + "/labels.h5"), test::read_file(seg_dir + "/labels.h5"));
  // the folder holds one run's outputs: an untuned run after a tuned one left
  // tune/, tuned_tissues.json and reports/tune.json beside the untuned model
  // (sweep of 2026-11-27); other files stay
  test::write_file(out + "/mine.txt", "notes");
  const auto untuned = test::run_cli(s.args("--no-tune --export " + out));
  ASSERT_EQ(untuned.code, 0) << untuned.err;
  for (const char* f : {"tuned_tissues.json", "tune", "reports/tune.json"}) EXPECT_FALSE(fs::exists(fs::path(out) / f)) << f;
  for (const char* f : {"mine.txt", "labels.h5", "surfaces/skin.stl", "reports/build.json"})
    EXPECT_TRUE(fs::exists(fs::path(out) / f)) << f;
  // an --export that names a file is refused before any work
  test::write_file(s.dir / "afile", "x");
  const auto bad = test::run_cli(s.args("--export " + (s.dir / "afile")));
  EXPECT_EQ(bad.code, 2);
  EXPECT_EQ(test::count_lines(bad.err), 1) << bad.err;
}

TEST(Pipeline, SceneWithoutVesselsSkipsThem) {
  const Sample& s = sample();
  test::write_file(s.dir / "scene.json", R"({"model": "model.h5", "layers": ["skin", "fat", "muscle", "bone"]})");
  const auto r = test::run_cli(s.args("--no-tune --scene " + (s.dir / "scene.json")));
  ASSERT_EQ(r.code, 0) << r.err;
  bool skipped = false;
  const nlohmann::json rep = s.report();
  for (const auto& st : rep["stages"])
    if (st["stage"] == "vessels") skipped = !st.value("ran", true) && st["why"] == "the scene uses no vessels";
  EXPECT_TRUE(skipped);
  ModelReader m(s.dir / "model.h5");
  EXPECT_FALSE(m.h5().is_group("/vessels"));
}

// A vein seen on one slice only (26 voxels, a piece shorter than 3 radii)
// forms no vessel: without a scene it is left out with a warning and the
// model has the artery (the vessel stage's error stopped the whole pipeline);
// a scene that uses the vein still fails.
TEST(Pipeline, AVesselTooShortToFormATreeIsLeftOut) {
  const Sample& s = sample();
  const fs::path stack = s.dir / "short_vein";
  fs::create_directories(stack);
  const Volume truth = ModelReader(s.dir / "ph/truth.h5").volume();
  int kept = 0;
  for (int z = 0; z < truth.nz; ++z) {
    char name[32];
    std::snprintf(name, sizeof name, "slice_%04d.png", z);
    cv::Mat im = cv::imread(s.stack + "/" + name, cv::IMREAD_COLOR);
    ASSERT_FALSE(im.empty()) << name;
    for (int y = 0; y < truth.ny; ++y)
      for (int x = 0; x < truth.nx; ++x)
        if (truth.labels[truth.index(x, y, z)] == kPhantomVein) {
          if (z == truth.nz / 2) ++kept;
          else im.at<cv::Vec3b>(y, x) = cv::Vec3b(38, 42, 136);  // the muscle's colour (BGR)
        }
    ASSERT_TRUE(cv::imwrite((stack / name).string(), im));
  }
  ASSERT_GT(kept, 0);
  const std::string base = "pipeline --stack " + stack.string() + " --tissues " + s.tissues + " --spacing 0.75,0.75,3 --work " +
                           (s.dir / "work") + " --no-texture --no-tune --quiet ";
  const auto r = test::run_cli(base + "--out " + (s.dir / "short_vein.h5") + " --report " + (s.dir / "short_vein.json"));
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_EQ(r.err.rfind("orthosim vessels: warning: ", 0), 0u) << r.err;
  EXPECT_NE(r.err.find(": tissue 'vein': its "), std::string::npos) << r.err;
  EXPECT_NE(r.err.find(" voxels form no vessel (every piece is shorter than 3 radii); it is left out\n"), std::string::npos)
      << r.err;
  EXPECT_EQ(nlohmann::json::parse(test::read_file(s.dir / "short_vein.json"))["metrics"]["vessels_left_out"],
            nlohmann::json::array({"vein"}));
  {
    ModelReader m(s.dir / "short_vein.h5");
    EXPECT_EQ(m.names("/vessels"), (std::vector<std::string>{"artery"}));
    for (const char* l : {"skin", "fat", "muscle"}) EXPECT_TRUE(m.h5().is_group(std::string("/layers/") + l)) << l;
  }
  // a scene that uses the vein needs its tree
  test::write_file(s.dir / "vein_scene.json", R"({"model": "m.h5", "layers": ["skin", "fat"], "vessels": ["vein"]})");
  const auto bad = test::run_cli(base + "--out " + (s.dir / "short_vein2.h5") + " --scene " + (s.dir / "vein_scene.json"));
  EXPECT_EQ(bad.code, 2) << bad.err;
  EXPECT_NE(bad.err.find("orthosim vessels: error: "), std::string::npos) << bad.err;
  EXPECT_NE(bad.err.find(" voxels form no vessel"), std::string::npos) << bad.err;
  EXPECT_FALSE(fs::exists(s.dir / "short_vein2.h5"));
}

// --register reaches segment (its shifts in the labels, and the cache keeps
// registered and unregistered labels apart); the model is built from them.
TEST(Pipeline, RegisterMovesTheSlicesBeforeSegmenting) {
  const Sample& s = sample();
  const fs::path stack = s.dir / "jittered";
  fs::create_directories(stack);
  int z = 0;
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(s.stack)) files.push_back(e.path().string());
  std::sort(files.begin(), files.end());
  for (const auto& f : files) {
    const cv::Mat im = cv::imread(f, cv::IMREAD_COLOR);
    ASSERT_FALSE(im.empty()) << f;
    const int dx = (z * 7) % 5 - 2, dy = (z * 3) % 5 - 2;  // up to 2 px a slice
    cv::Mat moved;
    const cv::Mat t = (cv::Mat_<double>(2, 3) << 1, 0, dx, 0, 1, dy);
    cv::warpAffine(im, moved, t, im.size(), cv::INTER_NEAREST, cv::BORDER_REPLICATE);
    ASSERT_TRUE(cv::imwrite((stack / fs::path(f).filename()).string(), moved));
    ++z;
  }
  const std::string base = "pipeline --stack " + stack.string() + " --tissues " + s.tissues + " --spacing 0.75,0.75,3 --work " +
                           (s.dir / "work") + " --no-texture --no-tune --quiet --out " + (s.dir / "registered.h5") +
                           " --export " + (s.dir / "registered_export") + " --report " + (s.dir / "registered.json");
  const auto r = test::run_cli(base + " --register");
  ASSERT_EQ(r.code, 0) << r.err;
  ModelReader labels(s.dir / "registered_export/labels.h5");
  std::vector<std::uint64_t> d;
  const auto shift = labels.h5().read<std::int32_t>("/volume/slice_shift_px", &d);
  ASSERT_EQ(d, (std::vector<std::uint64_t>{static_cast<std::uint64_t>(z), 2}));
  int moved = 0;
  for (auto v : shift) moved += v != 0;
  EXPECT_GT(moved, z / 2) << "most slices were moved back";
  ModelReader m(s.dir / "registered.h5");
  for (const char* l : {"skin", "fat", "muscle"}) EXPECT_TRUE(m.h5().is_group(std::string("/layers/") + l)) << l;
  // without the flag: other labels (another cache entry), no shifts
  const auto plain = test::run_cli(base);
  ASSERT_EQ(plain.code, 0) << plain.err;
  EXPECT_FALSE(ModelReader(s.dir / "registered_export/labels.h5").h5().exists("/volume/slice_shift_px"));
}

// --roi and --slices go to segment (its own cache entry); the labels sit where
// they lie in the stack, and the texture reads the slices there.
TEST(Pipeline, ARegionOfInterestIsSegmentedAndTextured) {
  const Sample& s = sample();
  const std::string base = "pipeline --stack " + s.stack + " --tissues " + s.tissues + " --spacing 0.75,0.75,3 --work " +
                           (s.dir / "work") + " --no-tune --quiet --out " + (s.dir / "roi.h5") + " --export " +
                           (s.dir / "roi_export") + " --report " + (s.dir / "roi.json");
  const auto r = test::run_cli(base + " --roi 6,5,84,86 --slices 1,30");
  ASSERT_EQ(r.code, 0) << r.err;
  ModelReader labels(s.dir / "roi_export/labels.h5");
  EXPECT_EQ(labels.h5().attr_doubles("/volume", "stack_offset_voxels"), (std::vector<double>{6, 5, 1}));
  const Volume v = labels.volume();
  EXPECT_EQ(v.nx, 84);
  EXPECT_EQ(v.ny, 86);
  EXPECT_EQ(v.nz, 30);
  EXPECT_NEAR(v.origin_m[0], 6 * 0.75e-3, 1e-12);
  EXPECT_NEAR(v.origin_m[2], 3e-3, 1e-12);
  ModelReader m(s.dir / "roi.h5");
  for (const char* l : {"skin", "fat", "muscle"}) EXPECT_TRUE(m.h5().is_group(std::string("/layers/") + l)) << l;
  const nlohmann::json rep = nlohmann::json::parse(test::read_file(s.dir / "roi.json"));
  EXPECT_EQ(rep["parameters"]["roi_px"], nlohmann::json({6, 5, 84, 86}));
  EXPECT_EQ(rep["parameters"]["slices"], nlohmann::json({1, 30}));
  int textured = 0;
  for (const auto& st : rep["stages"])
    if (st["stage"] == "remesh") {
      const nlohmann::json rr = nlohmann::json::parse(test::read_file(st["dir"].get<std::string>() + "/report.json"));
      EXPECT_EQ(rr["metrics"]["texture"]["outside"].get<std::int64_t>(), 0) << rr["metrics"]["texture"].dump();
      EXPECT_GT(rr["metrics"]["texture"]["width"].get<std::int64_t>(), 0);
      ++textured;
    }
  EXPECT_EQ(textured, 1);
  // a region beyond the slices: refused before any stage, naming the stack
  const auto bad = test::run_cli(base + " --roi 6,5,91,86");
  EXPECT_EQ(bad.code, 2) << bad.err;
  EXPECT_EQ(test::count_lines(bad.err), 1) << bad.err;
  EXPECT_NE(bad.err.find(s.stack + ": the region of interest (x 6, y 5, 91 x 86 px) reaches beyond the slices, which are "
                                   "96 x 96 px"),
            std::string::npos)
      << bad.err;
  const auto badz = test::run_cli(base + " --slices 0,32");
  EXPECT_EQ(badz.code, 2) << badz.err;
  EXPECT_NE(badz.err.find("the slices 0..32 reach beyond the stack, which has 32 (0..31)"), std::string::npos) << badz.err;
  // The key hashes the slices segment reads (hash_stack's range): a slice
  // outside --slices changed runs nothing, one inside runs segment again (a
  // cached run of a part of a full-body stack hashed every file of it). Bytes
  // after a PNG's IEND chunk change the file, not its pixels. (A copy of the
  // stack: the sample's is shared.)
  const std::string copy = s.dir / "roi_stack";
  fs::create_directories(copy);
  for (const auto& e : fs::directory_iterator(s.stack))
    fs::copy_file(e.path(), copy + "/" + e.path().filename().string(), fs::copy_options::overwrite_existing);
  std::string on_copy = base + " --roi 6,5,84,86 --slices 1,30";
  on_copy.replace(on_copy.find(s.stack), s.stack.size(), copy);
  auto ran = [&] {
    std::set<std::string> out;
    const nlohmann::json rr = nlohmann::json::parse(test::read_file(s.dir / "roi.json"));
    for (const auto& st : rr["stages"])
      if (st.value("ran", false)) out.insert(st["stage"].get<std::string>());
    return out;
  };
  ASSERT_EQ(test::run_cli(on_copy).code, 0);
  EXPECT_TRUE(ran().empty());  // the same files: the same keys
  test::write_file(copy + "/slice_0031.png", test::read_file(copy + "/slice_0031.png") + "outside");
  ASSERT_EQ(test::run_cli(on_copy).code, 0);
  EXPECT_TRUE(ran().empty()) << "a slice outside --slices changed";
  test::write_file(copy + "/slice_0005.png", test::read_file(copy + "/slice_0005.png") + "inside");
  ASSERT_EQ(test::run_cli(on_copy).code, 0);
  EXPECT_TRUE(ran().count("segment")) << "a slice inside --slices changed";
}

TEST(Pipeline, AFailingStageKeepsThePreviousModel) {
  const Sample& s = sample();
  ASSERT_TRUE(fs::exists(s.dir / "model.h5"));
  const std::string before = test::read_file(s.dir / "model.h5");
  // slices of another size in a copy of the stack: segment refuses it
  test::TempDir bad("pipeline-bad");
  fs::create_directories(bad / "slices");
  for (const auto& e : fs::directory_iterator(s.stack)) fs::copy_file(e.path(), bad / ("slices/" + e.path().filename().string()));
  test::write_file(bad / "slices/zz_extra.png", "not an image");
  const auto r = test::run_cli("pipeline --stack " + (bad / "slices") + " --tissues " + s.tissues +
                               " --spacing 0.75,0.75,3 --work " + (s.dir / "work") + " --out " + (s.dir / "model.h5") +
                               " --no-texture --no-tune --quiet --report " + (bad / "r.json"));
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("orthosim segment: error:"), std::string::npos) << r.err;
  EXPECT_EQ(test::read_file(s.dir / "model.h5"), before);
  // the report names the stage and its error (the error was null: only stderr had it)
  const auto rep = nlohmann::json::parse(test::read_file(bad / "r.json"));
  EXPECT_EQ(rep["failed_stage"], "segment");
  ASSERT_TRUE(rep["error"].is_string()) << rep.dump();
  EXPECT_EQ("orthosim segment: error: " + rep["error"].get<std::string>() + "\n", r.err);
}

// A stack of one slice: remesh fails (the limb has no length; its message said
// "R |dn/ds| = inf"), and the report names its error. The vessels, in their
// child process, fail too when they finish first: what they said goes to the
// report's stopped_stages, and the run prints one error line (it printed theirs
// too).
TEST(Pipeline, AOneSliceStackFailsInRemeshAndSaysWhy) {
  const Sample& s = sample();
  test::TempDir one("pipeline-one");
  fs::create_directories(one / "slices");
  std::vector<fs::path> slices;
  for (const auto& e : fs::directory_iterator(s.stack)) slices.push_back(e.path());
  std::sort(slices.begin(), slices.end());
  fs::copy_file(slices[slices.size() / 2], one / "slices/slice_0000.png");
  const auto r = test::run_cli("pipeline --stack " + (one / "slices") + " --tissues " + s.tissues +
                               " --spacing 0.75,0.75,1.2 --work " + (one / "work") + " --out " + (one / "m.h5") +
                               " --no-texture --no-tune --quiet --report " + (one / "r.json"));
  EXPECT_EQ(r.code, 2);
  EXPECT_FALSE(fs::exists(one / "m.h5"));
  EXPECT_EQ(r.err.find("inf"), std::string::npos) << r.err;  // "R |dn/ds| = inf"
  EXPECT_NE(r.err.find("orthosim remesh: error: "), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("R |dn/ds| unbounded, at most 0.5: the surface has no length along it"), std::string::npos) << r.err;
  const auto rep = nlohmann::json::parse(test::read_file(one / "r.json"));
  EXPECT_EQ(rep["failed_stage"], "remesh");
  ASSERT_TRUE(rep["error"].is_string()) << rep.dump();
  EXPECT_NE(r.err.find("orthosim remesh: error: " + rep["error"].get<std::string>() + "\n"), std::string::npos) << r.err;
  EXPECT_EQ(r.err.find("orthosim vessels: error"), std::string::npos) << r.err;
  EXPECT_EQ(r.err.find("error"), r.err.rfind("error")) << "one error line: " << r.err;
}

TEST(Pipeline, BadFlags) {
  const Sample& s = sample();
  auto r = test::run_cli("pipeline --stack " + s.stack + " --tissues " + s.tissues + " --spacing 0,1,1 --out " + (s.dir / "x.h5"));
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_FALSE(fs::exists(s.dir / "x.h5"));
  r = test::run_cli("pipeline --stack " + (s.dir / "nope") + " --tissues " + s.tissues + " --spacing 1,1,1 --out " + (s.dir / "x.h5"));
  EXPECT_EQ(r.code, 2);
  EXPECT_FALSE(fs::exists(s.dir / "x.h5"));
  // a grid the remesh stage refuses, refused before any stage (it failed after segment and surface)
  r = test::run_cli("pipeline --stack " + s.stack + " --tissues " + s.tissues + " --spacing 0.75,0.75,3 --grid 2x9 --work " +
                    (s.dir / "work-grid") + " --out " + (s.dir / "x.h5"));
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(r.err, "orthosim pipeline: error: --grid: nu (points around) must be in 3..10000, got 2\n");
  // the grid's own example (it showed the phantom's 3-D size, 256x256x128)
  r = test::run_cli("pipeline --stack " + s.stack + " --tissues " + s.tissues + " --spacing 0.75,0.75,3 --grid abc --out " +
                    (s.dir / "x.h5"));
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(r.err, "orthosim pipeline: error: --grid: expected sizes like 39x9, got 'abc'\n");
  EXPECT_FALSE(fs::exists(s.dir / "work-grid"));
  // build's options likewise: the grid prisms' term without a term (nu 1/4)
  r = test::run_cli("pipeline --stack " + s.stack + " --tissues " + s.tissues + " --spacing 0.75,0.75,3 --work " +
                    (s.dir / "work-grid") + " --out " + (s.dir / "x.h5") + " --tetra-volume-term prisms --poisson-ratio 0.25");
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(r.err, "orthosim pipeline: error: --tetra-volume-term prisms needs a volume term: a Poisson's ratio above 0.25\n");
  EXPECT_FALSE(fs::exists(s.dir / "work-grid"));
  // a second outermost layered tissue: refused before any stage, naming the table (it failed in
  // the build stage, naming a model file in the cache)
  nlohmann::json t = nlohmann::json::parse(test::read_file(s.tissues));
  for (auto& e : t["tissues"])
    if (e["name"] == "fat") e["inside"] = nullptr;
  const std::string table = s.dir / "two_roots.json";
  test::write_file(table, t.dump(2));
  r = test::run_cli("pipeline --stack " + s.stack + " --tissues " + table + " --spacing 0.75,0.75,3 --work " + (s.dir / "work") +
                    " --out " + (s.dir / "x.h5") + " --no-texture --no-tune --quiet");
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("orthosim pipeline: error: " + table + ": layered tissue 'fat' lies inside none of the layered tissues outside it (skin)"),
            std::string::npos)
      << r.err;
  EXPECT_FALSE(fs::exists(s.dir / "x.h5"));
  // a modulus out of a tissue's range, refused before any stage (segment, surface, remesh and
  // build ran first); 1e308 kPa, infinite in Pa, was "not a positive modulus"
  for (const char* k : {"1e30", "1e308"}) {
    nlohmann::json u = nlohmann::json::parse(test::read_file(s.tissues));
    for (auto& e : u["tissues"])
      if (e["name"] == "fat") e["mechanics"] = nlohmann::json::parse(std::string(R"({"model": "linear", "k_kpa": )") + k + "}");
    const std::string stiff = s.dir / "stiff_fat.json";
    test::write_file(stiff, u.dump(2));
    r = test::run_cli("pipeline --stack " + s.stack + " --tissues " + stiff + " --spacing 0.75,0.75,3 --work " +
                      (s.dir / "work-stiff") + " --out " + (s.dir / "x.h5") + " --no-texture --quiet");
    EXPECT_EQ(r.code, 2) << k;
    EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
    // (the table parser's range since 2026-11-27: build used such a modulus)
    EXPECT_NE(r.err.find("orthosim pipeline: error: " + stiff + ": tissue 'fat' mechanics: k_kpa = 1e+" + (k + 2)), std::string::npos)
        << r.err;
    EXPECT_NE(r.err.find("outside a tissue's range, 1e-3 .. 1e9 kPa"), std::string::npos) << r.err;
    EXPECT_EQ(r.err.find("inf"), std::string::npos) << r.err;
    EXPECT_FALSE(fs::exists(s.dir / "work-stiff")) << k;
  }
}

// The layers nest one in another. An artery made a 'lattice' layer lies in the
// muscle beside the bone: after the bone (the rigid innermost layer) it was
// left out of the model without a word, exit 0; listed before the bone, the two
// were stacked as if the bone lay in the artery and remesh failed ("not inside
// artery") against an STL in the cache. Both are refused once the segmentation
// shows both tissues (a general table may list siblings a stack does not show:
// Pipeline.TissuesTheSlicesDoNotShowAreLeftOut), naming the table; the report
// says why.
TEST(Pipeline, LayersBesideEachOtherAreRefused) {
  const Sample& s = sample();
  auto table_with_artery_layer = [&](bool before_bone) {
    nlohmann::json t = nlohmann::json::parse(test::read_file(s.tissues));
    auto& v = t["tissues"];
    nlohmann::json mech;
    for (const auto& e : v)
      if (e["name"] == "muscle") mech = e["mechanics"];
    auto it = std::find_if(v.begin(), v.end(), [](const nlohmann::json& e) { return e["name"] == "artery"; });
    nlohmann::json artery = *it;
    EXPECT_EQ(artery["inside"], "muscle");
    artery["layer"] = "lattice", artery["mechanics"] = mech;
    v.erase(it);
    auto bone = std::find_if(v.begin(), v.end(), [](const nlohmann::json& e) { return e["name"] == "bone"; });
    v.insert(before_bone ? bone : v.end(), artery);
    const std::string path = s.dir / (before_bone ? "artery_layer_first.json" : "artery_layer.json");
    test::write_file(path, t.dump(2));
    return path;
  };
  for (bool before_bone : {false, true}) {
    const std::string table = table_with_artery_layer(before_bone);
    test::TempDir d("pipeline-nest");
    const auto r = test::run_cli("pipeline --stack " + s.stack + " --tissues " + table + " --spacing 0.75,0.75,3 --work " +
                                 (d / "work") + " --out " + (d / "x.h5") + " --no-texture --no-tune --quiet --report " +
                                 (d / "r.json"));
    EXPECT_EQ(r.code, 2) << r.err;
    EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
    const std::string why = before_bone ? "layered tissue 'bone' (in 'muscle') does not lie in 'artery', the layer just outside it"
                                        : "layered tissue 'artery' (lattice, in 'muscle') lies beside the rigid 'bone', the "
                                          "innermost layer, not in it";
    EXPECT_NE(r.err.find("orthosim pipeline: error: " + table + ": " + why), std::string::npos) << r.err;
    EXPECT_FALSE(fs::exists(d / "x.h5"));
    const auto rep = nlohmann::json::parse(test::read_file(d / "r.json"));
    EXPECT_EQ(rep["failed_stage"], "segment");  // the stage whose output showed them
    EXPECT_EQ(rep["stages"].size(), 1u);
    EXPECT_NE(rep["error"].get<std::string>().find(why), std::string::npos) << rep.dump();
  }
}

// The tool is an input of every stage: a different orthosim executable (here
// the same one with a byte appended, which still runs) reuses no entry.
TEST(Pipeline, ADifferentToolReusesNoEntry) {
  const Sample& s = sample();
  ASSERT_EQ(test::run_cli(s.args("--no-tune")).code, 0);
  EXPECT_FALSE(s.ran().count("segment"));  // warm with this tool
  const std::string other = s.dir / "orthosim-other";
  fs::copy_file(ORTHOSIM_BINARY, other, fs::copy_options::overwrite_existing);
  {
    std::ofstream f(other, std::ios::binary | std::ios::app);
    f << '\n';
  }
  fs::permissions(other, fs::perms::owner_all);
  ASSERT_EQ(std::system((other + " " + s.args("--no-tune") + " 2>/dev/null").c_str()), 0);
  for (const char* st : {"segment", "surface", "remesh", "build"}) EXPECT_TRUE(s.ran().count(st)) << st;
}
