// The CLI conventions: --version, --help, one-line errors with exit 2,
// inspect on good and bad files, nothing written on failure: a bad --report
// path fails every subcommand before any work, and segment checks its
// --truth and the table's background colour before writing.
#include "libmodel/format/model.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <filesystem>

using namespace orthosim;
namespace fs = std::filesystem;

namespace {
Provenance make_provenance_for_test() {
  Provenance p;
  p.tool_version = "0.1.0";
  p.command_line = "unit test";
  p.inputs_json = "{}";
  p.parameters_json = "{}";
  p.time_utc = "2026-01-01T00:00:00Z";
  return p;
}

// a degenerate (zero-size) tetrahedron as /surfaces/skin, the provenance, and the commit
void write_skin_and_commit(ModelWriter& w) {
  Surface s;
  s.vertices = MatX3d::Zero(4, 3);
  s.faces.resize(4, 3);
  s.faces << 0, 1, 2, 0, 2, 3, 0, 3, 1, 1, 3, 2;
  w.write("skin", s);
  w.write("test", make_provenance_for_test());
  w.commit();
}

std::string make_model(const test::TempDir& dir) {
  const std::string p = dir / "m.h5";
  ModelWriter w(p, ModelWriter::Start::fresh);
  Volume v;
  v.nx = 2;
  v.ny = 2;
  v.nz = 2;
  v.labels.assign(8, 1);
  v.label_names = {"background", "skin"};
  w.write(v);
  write_skin_and_commit(w);
  return p;
}
// a valid model file with a surface and no /volume
std::string make_model_without_volume(const test::TempDir& dir) {
  const std::string p = dir / "novol.h5";
  ModelWriter w(p, ModelWriter::Start::fresh);
  write_skin_and_commit(w);
  return p;
}
}  // namespace

TEST(Cli, VersionAndHelp) {
  auto r = test::run_cli("--version");
  EXPECT_EQ(r.code, 0);
  EXPECT_NE(r.out.find("orthosim 0."), std::string::npos) << r.out;
  r = test::run_cli("inspect --help");
  EXPECT_EQ(r.code, 0);
  EXPECT_NE(r.out.find("--json"), std::string::npos);
}

TEST(Cli, UnknownCommandAndFlagAreOneLineExit2) {
  auto r = test::run_cli("frobnicate");
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  r = test::run_cli("inspect --bogus x");
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_EQ(r.err.rfind("orthosim inspect: error: ", 0), 0u) << r.err;
}

// A seed outside 64 bits is refused: "-1" wrapped to 2^64 - 1 and 2^64 was
// clamped to it, silently (recorded so in the provenance).
TEST(Cli, SeedsAreSixtyFourBitIntegers) {
  test::TempDir d("cli-seed");
  const std::vector<std::string> cmds = {"phantom --out " + (d / "ph") + " --size 16x16x2", "tune --tissues x.json",
                                         "pipeline --stack x --tissues x.json --spacing 1,1,1 --out " + (d / "m.h5")};
  for (const std::string& cmd : cmds)
    for (const std::string seed : {"-1", "18446744073709551616", "1.5"}) {
      SCOPED_TRACE(cmd + " --seed " + seed);
      const auto r = test::run_cli(cmd + " --seed " + seed);
      EXPECT_EQ(r.code, 2);
      EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
      EXPECT_NE(r.err.find("--seed: a seed is an integer in 0..18446744073709551615, got '" + seed + "'"),
                std::string::npos)
          << r.err;
    }
  EXPECT_FALSE(fs::exists(d / "ph"));
  EXPECT_EQ(test::run_cli("phantom -q --out " + (d / "ph") + " --size 16x16x2 --seed 18446744073709551615").code, 0);
}

TEST(Cli, InspectSummarisesAModel) {
  test::TempDir dir("cli");
  auto p = make_model(dir);
  auto r = test::run_cli("inspect " + p + " --json --report " + (dir / "r.json"));
  ASSERT_EQ(r.code, 0) << r.err;
  auto j = nlohmann::json::parse(r.out);
  EXPECT_EQ(j["orthosim_format"], format_version());
  EXPECT_EQ(j["summary"]["surfaces"]["skin"]["n_faces"], 4);
  EXPECT_EQ(j["summary"]["volume"]["nx"], 2);
  EXPECT_EQ(j["tree"]["surfaces"]["skin"]["vertices"]["unit"], "m");
  EXPECT_EQ(j["provenance"]["test"]["command_line"], "unit test");
  auto rep = nlohmann::json::parse(test::read_file(dir / "r.json"));
  EXPECT_EQ(rep["command"], "inspect");
  EXPECT_EQ(rep["inputs"][p].get<std::string>().rfind("xxh3:", 0), 0u);
  r = test::run_cli("inspect " + p);
  EXPECT_EQ(r.code, 0);
  EXPECT_NE(r.out.find("/surfaces/skin"), std::string::npos) << r.out;
  // whole-number attributes are integers (a grid printed as nu=39.0, node_offset=975.0)
  {
    ModelWriter w(p, ModelWriter::Start::update);
    w.h5().make_groups("/quads/skin");
    w.h5().set_attr("/quads/skin", "nu", std::int64_t{39});
    w.h5().set_attr("/quads/skin", "nv", std::int64_t{9});
    w.h5().set_attr("/quads/skin", "psi", 0.25);
    w.commit();
  }
  r = test::run_cli("inspect " + p + " --json");
  ASSERT_EQ(r.code, 0) << r.err;
  j = nlohmann::json::parse(r.out);
  EXPECT_TRUE(j["summary"]["quads"]["skin"]["nu"].is_number_integer()) << j["summary"]["quads"].dump();
  EXPECT_EQ(j["summary"]["quads"]["skin"]["nu"], 39);
  EXPECT_EQ(j["summary"]["quads"]["skin"]["psi"], 0.25);
  r = test::run_cli("inspect " + p);
  EXPECT_NE(r.out.find("nu=39"), std::string::npos) << r.out;
  EXPECT_EQ(r.out.find("nu=39.0"), std::string::npos) << r.out;
  // the named labels only, and a volume every stage refuses is said to be invalid
  // (a NaN spacing printed as null as if the file were fine; sweep of 2026-11-27)
  EXPECT_NE(r.out.find("labels 0 background, 1 skin\n"), std::string::npos) << r.out;
  EXPECT_EQ(r.out.find("invalid"), std::string::npos) << r.out;
  {
    ModelWriter w(p, ModelWriter::Start::update);
    w.h5().set_attr("/volume", "spacing_m", std::vector<double>{std::nan(""), 1e-3, 1e-3});
    w.commit();
  }
  r = test::run_cli("inspect " + p);
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("  /volume: invalid: spacing along x is nan m"), std::string::npos) << r.out;
  r = test::run_cli("inspect " + p + " --json");
  EXPECT_NE(nlohmann::json::parse(r.out)["summary"]["volume"]["problem"].get<std::string>().find("spacing along x is nan"),
            std::string::npos);
}

TEST(Cli, InspectBadInputsAreOneLineExit2) {
  test::TempDir dir("cli");
  auto good = make_model(dir);
  test::write_file(dir / "text.h5", "plain text");
  std::string bytes = test::read_file(good);
  test::write_file(dir / "trunc.h5", bytes.substr(0, bytes.size() / 3));
  { h5::File f(dir / "plain.h5", h5::File::Mode::create); }
  std::filesystem::copy_file(good, dir / "newer.h5");
  {
    h5::File f(dir / "newer.h5", h5::File::Mode::read_write);
    f.set_attr("/", "orthosim_format", "9.0");
  }
  test::write_file(dir / "unreadable.h5", bytes);
  std::filesystem::permissions(dir / "unreadable.h5", std::filesystem::perms::none);
  for (const std::string name : {"missing.h5", "text.h5", "trunc.h5", "plain.h5", "newer.h5", "unreadable.h5"}) {
    if (name == "unreadable.h5" && ::geteuid() == 0) continue;  // root reads anything
    auto r = test::run_cli("inspect " + (dir / name));
    EXPECT_EQ(r.code, 2) << name << ": " << r.err;
    EXPECT_EQ(test::count_lines(r.err), 1) << name << ": " << r.err;
    EXPECT_NE(r.err.find(dir / name), std::string::npos) << r.err;
  }
}

namespace {

// A small phantom stack with its truth and table (made once) in `dir`.
struct PhantomStack {
  test::TempDir dir{"cli-ph"};
  std::string slices = dir / "ph/slices", tissues = dir / "ph/tissues.json", truth = dir / "ph/truth.h5";
  PhantomStack() {
    const auto r = test::run_cli("phantom --out " + (dir / "ph") + " --size 64x64x8 --spacing 1,1,2 --seed 3 --quiet");
    EXPECT_EQ(r.code, 0) << r.err;
  }
};
const PhantomStack& phantom_stack() {
  static PhantomStack s;
  return s;
}

// exit 2, one line naming `file` and saying `what`
void expect_refused(const test::RunResult& r, const std::string& file, const std::string& what) {
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find(file + ": " + what), std::string::npos) << r.err;
}

}  // namespace

// --report into a folder that does not exist: every subcommand says so before
// doing any work, so nothing else is written (segment, phantom and pipeline
// did all their work, wrote --out, and only then failed).
TEST(Cli, ReportPathIsCheckedBeforeAnyWork) {
  const PhantomStack& ph = phantom_stack();
  test::TempDir d("cli-report");
  const std::string report = d / "nodir/r.json";
  const std::string what = "output directory " + (d / "nodir") + " does not exist";
  const std::string stack = " --stack " + ph.slices + " --tissues " + ph.tissues + " --spacing 1,1,2";
  const std::vector<std::pair<std::string, std::string>> cases = {
      // good inputs: each would write its outputs (the second string) without the check
      {"phantom --out " + (d / "ph") + " --size 16x16x4", d / "ph"},
      {"segment" + stack + " --out " + (d / "labels.h5"), d / "labels.h5"},
      {"pipeline" + stack + " --out " + (d / "model.h5"), d / "model.h5.work"},
      {"surface --labels " + ph.truth + " --out " + (d / "surfaces") + " --tissues skin", d / "surfaces"},
      {"vessels --labels " + ph.truth + " --tissue artery --model " + (d / "vessels.h5"), d / "vessels.h5"},
      {"inspect " + ph.truth, ""},
      // inputs that are bad too: the report is the first thing checked
      {"remesh --surface " + (d / "none.stl") + " --out " + (d / "quads"), d / "quads"},
      {"build --model " + (d / "none.h5") + " --tissues " + ph.tissues, ""},
      {"tune --tissues " + ph.tissues + " --out " + (d / "tuned.json"), d / "tuned.json"},
      {"run " + (d / "none.json") + " --out " + (d / "series"), d / "series"},
      {"bench --render " + (d / "none.json") + " --out " + (d / "bench"), d / "bench"},
  };
  for (const auto& [args, out] : cases) {
    SCOPED_TRACE(args);
    const auto r = test::run_cli(args + " --quiet --report " + report);
    expect_refused(r, report, what);
    EXPECT_EQ(r.err.rfind("orthosim " + args.substr(0, args.find(' ')) + ": error: ", 0), 0u) << r.err;
    if (!out.empty()) {
      EXPECT_FALSE(fs::exists(out)) << out;
    }
  }
  EXPECT_FALSE(fs::exists(d / "model.h5"));
  EXPECT_FALSE(fs::exists(d / "nodir"));
}

// --report naming a file the command reads or writes: refused before any work,
// the file untouched (run --report MODEL replaced a 13 MB model by its report,
// exit 0; so did tune, and run --report SCENE the scene). Also where the scene's
// own "model" key names it.
TEST(Cli, ReportNeverReplacesAnOperand) {
  const PhantomStack& ph = phantom_stack();
  test::TempDir d("cli-report-operand");
  const std::string model = make_model(d), bytes = test::read_file(model);
  const std::string scene = d / "s.json";
  test::write_file(scene, R"({"model": ")" + model + R"(", "dt": 0.001, "duration": 0.002})");
  const std::string scene_bytes = test::read_file(scene);
  const std::vector<std::tuple<std::string, std::string, std::string>> cases = {
      {"run --no-output " + scene + " --model " + model, model, "--report names the same file as --model " + model},
      {"run --no-output " + scene + " --model " + model, scene,
       "--report names the same file as the argument " + scene},
      {"run --no-output " + scene, model, "--report names the input " + model},
      {"tune --tissues " + ph.tissues + " --model " + model, model, "--report names the same file as --model " + model},
      {"inspect " + model, model, "--report names the same file as the argument " + model},
      {"segment --stack " + ph.slices + " --tissues " + ph.tissues + " --spacing 1,1,2 --out " + (d / "l.h5"),
       d / "l.h5", "--report names the same file as --out " + (d / "l.h5")},
  };
  for (const auto& [args, report, what] : cases) {
    SCOPED_TRACE(args + " --report " + report);
    const auto r = test::run_cli(args + " --quiet --report " + report);
    expect_refused(r, report, what);
    EXPECT_EQ(test::read_file(model), bytes);
    EXPECT_EQ(test::read_file(scene), scene_bytes);
  }
  EXPECT_FALSE(fs::exists(d / "l.h5"));
}

// An output naming an input or another output: refused before any work, the
// files untouched (segment --out TABLE turned the tissue table into HDF5,
// --out X --nrrd X left an NRRD for the model, --out STACK/slice.png replaced
// a slice, pipeline --out TABLE; all exit 0 until 2026-11-27).
TEST(Cli, OutputsNeverReplaceInputs) {
  const PhantomStack& ph = phantom_stack();
  test::TempDir d("cli-output-input");
  const std::string table_bytes = test::read_file(ph.tissues);
  const std::string slice = ph.slices + "/" + fs::directory_iterator(ph.slices)->path().filename().string();
  const std::string slice_bytes = test::read_file(slice);
  const std::string seg = "segment --stack " + ph.slices + " --tissues " + ph.tissues + " --spacing 1,1,2 --quiet";
  fs::create_directories(d / "exp");
  fs::create_directories(d / "plots");  // a second run's: the report's folder exists
  const std::vector<std::tuple<std::string, std::string, std::string>> cases = {
      {seg + " --out " + ph.tissues, ph.tissues, "--out names the same file as --tissues " + ph.tissues},
      {seg + " --out " + (d / "l.h5") + " --nrrd " + ph.tissues, ph.tissues, "--nrrd names the same file as --tissues"},
      {seg + " --out " + slice, slice, "--out lies in the --stack folder " + ph.slices},
      {seg + " --out " + (ph.slices + "/new.h5"), ph.slices + "/new.h5", "--out lies in the --stack folder " + ph.slices},
      {seg + " --out " + (d / "r.h5") + " --report " + slice, slice, "--report lies in the --stack folder " + ph.slices},
      {seg + " --out " + (d / "x.h5") + " --nrrd " + (d / "x.h5"), d / "x.h5", "--out and --nrrd name the same file"},
      {"pipeline --stack " + ph.slices + " --tissues " + ph.tissues + " --spacing 1,1,2 --quiet --out " + ph.tissues,
       ph.tissues, "--out names the same file as --tissues"},
      // a file of a kind a folder output writes, in that folder (the STL became the report)
      {"tune --tissues " + ph.tissues + " --plot " + (d / "plots") + " --report " + (d / "plots/skin.png"), d / "plots/skin.png",
       "--report lies in the --plot folder " + (d / "plots") + " under a kind of name it writes (.png)"},
      // an entry the export writes (the model was replaced by the exported labels)
      {"pipeline --stack " + ph.slices + " --tissues " + ph.tissues + " --spacing 1,1,2 --quiet --export " + (d / "exp") +
           " --out " + (d / "exp/labels.h5"),
       d / "exp/labels.h5", "--out names 'labels.h5' of the --export folder " + (d / "exp")},
  };
  for (const auto& [args, file, what] : cases) {
    SCOPED_TRACE(args);
    const auto r = test::run_cli(args);
    expect_refused(r, file, what);
    EXPECT_EQ(test::read_file(ph.tissues), table_bytes);
    EXPECT_EQ(test::read_file(slice), slice_bytes);
  }
  EXPECT_FALSE(fs::exists(d / "l.h5"));
  EXPECT_FALSE(fs::exists(d / "x.h5"));
  EXPECT_FALSE(fs::exists(ph.slices + "/new.h5"));
  EXPECT_FALSE(fs::exists(d / "exp/labels.h5"));
  EXPECT_TRUE(fs::is_empty(d / "plots"));
  // bench: the report over the results it renders (replaced, exit 0, until
  // 2026-11-27), or over a file its --out folder writes
  const std::string prev = d / "prev.json",
                    prev_bytes = R"({"command": "orthosim bench", "quick": true, "seconds": 0, "rows": [], "stages": [],
                                    "goals": {"checked": 0, "met": 0}, "notes": [], "machine": {"cpu": "test", "cores": 2}})";
  test::write_file(prev, prev_bytes);
  fs::create_directories(d / "bo");  // a second run's: the report's folder exists
  expect_refused(test::run_cli("bench --render " + prev + " --out " + (d / "bo") + " --report " + prev), prev,
                 "--report names the same file as --render " + prev);
  expect_refused(test::run_cli("bench --render " + prev + " --out " + (d / "bo") + " --report " + (d / "bo/summary.md")),
                 d / "bo/summary.md", "--report lies in the --out folder " + (d / "bo") + " under a name it writes (summary.md)");
  EXPECT_EQ(test::read_file(prev), prev_bytes);
  EXPECT_TRUE(fs::is_empty(d / "bo"));
  // (a report beside them is fine)
  const auto ok = test::run_cli("bench --render " + prev + " --out " + (d / "bo") + " --report " + (d / "bo/report.json"));
  EXPECT_EQ(ok.code, 0) << ok.err;
  EXPECT_TRUE(fs::exists(d / "bo/summary.md"));
  EXPECT_TRUE(fs::exists(d / "bo/report.json"));
  // a file with the keys but not their contents: one line naming it (it was an "internal error")
  test::write_file(d / "mangled.json", R"({"rows": [], "stages": [], "goals": [], "machine": {}})");
  expect_refused(test::run_cli("bench --render " + (d / "mangled.json") + " --out " + (d / "bo2")), d / "mangled.json",
                 "not the results.json of an orthosim bench run: ");
  EXPECT_FALSE(fs::exists(d / "bo2"));
}

// --truth of another size than the stack: refused before --out is written
// (segment wrote --out, then failed on the Dice).
TEST(Cli, SegmentChecksTheTruthBeforeWriting) {
  const PhantomStack& ph = phantom_stack();
  test::TempDir d("cli-truth");
  ASSERT_EQ(test::run_cli("phantom --out " + (d / "other") + " --size 48x64x8 --spacing 1,1,2 --quiet").code, 0);
  const std::string truth = d / "other/truth.h5";
  const std::string args = "segment --stack " + ph.slices + " --tissues " + ph.tissues + " --spacing 1,1,2 --quiet --out " +
                           (d / "labels.h5") + " --nrrd " + (d / "labels.nrrd") + " --report " + (d / "r.json");
  auto r = test::run_cli(args + " --truth " + truth);
  expect_refused(r, truth, "truth volume is 48x64x8 voxels, the stack " + ph.slices + " is 64x64x8");
  for (const char* f : {"labels.h5", "labels.nrrd", "r.json"}) EXPECT_FALSE(fs::exists(d / f)) << f;
  // a model file without a volume is no truth either
  r = test::run_cli(args + " --truth " + make_model_without_volume(d));
  expect_refused(r, d / "novol.h5", "missing dataset /volume/labels");
  for (const char* f : {"labels.h5", "labels.nrrd", "r.json"}) EXPECT_FALSE(fs::exists(d / f)) << f;
  // the right size: the Dice is reported
  r = test::run_cli(args + " --truth " + ph.truth);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(nlohmann::json::parse(test::read_file(d / "r.json"))["metrics"].contains("dice"));
}

// Segmentation needs the background's colour: a table without it is refused
// by segment and pipeline before any work (it classified the embedding
// medium as tissue).
TEST(Cli, SegmentNeedsTheBackgroundColour) {
  const PhantomStack& ph = phantom_stack();
  test::TempDir d("cli-bg");
  auto table = nlohmann::json::parse(test::read_file(ph.tissues));
  for (const bool entry : {false, true}) {
    SCOPED_TRACE(entry ? "background without rgb" : "no background");
    if (entry) table["background"] = {{"name", "gel"}};
    else table.erase("background");
    const std::string t = d / "t.json";
    test::write_file(t, table.dump(1));
    const std::string common = " --stack " + ph.slices + " --tissues " + t + " --spacing 1,1,2 --quiet";
    auto r = test::run_cli("segment" + common + " --out " + (d / "labels.h5"));
    expect_refused(r, t, "no background colour: segmentation needs \"background\": {\"rgb\"");
    EXPECT_FALSE(fs::exists(d / "labels.h5"));
    r = test::run_cli("pipeline" + common + " --out " + (d / "model.h5"));
    expect_refused(r, t, "no background colour");
    EXPECT_FALSE(fs::exists(d / "model.h5"));
    EXPECT_FALSE(fs::exists(d / "model.h5.work"));
  }
}

// An interrupted run (SIGTERM, Ctrl-C's SIGINT) leaves no temporary output
// behind and ends by that signal: a build stopped by `timeout` left a 300 MB
// ".model.h5.tmp-*" beside the model until 2026-11-27. The phantom's slices
// go to a temporary folder from the start, so it is interrupted mid-work.
TEST(Cli, AnInterruptedRunLeavesNoTemporaryFiles) {
  for (const int sig : {SIGTERM, SIGINT}) {
    SCOPED_TRACE(sig == SIGTERM ? "SIGTERM" : "SIGINT");
    test::TempDir d("cli-interrupt");
    const std::string out = d / "ph";
    std::vector<std::string> args{ORTHOSIM_BINARY, "phantom", "--out", out, "--size", "384x384x256", "--quiet"};
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    pid_t pid = 0;
    ASSERT_EQ(posix_spawn(&pid, argv[0], nullptr, nullptr, argv.data(), environ), 0);
    // until its temporary folder holds a slice (or 60 s)
    auto temporaries = [&] {
      std::vector<std::string> t;
      for (const auto& e : fs::directory_iterator(d.path))
        if (e.path().filename().string().rfind(".ph.tmp-", 0) == 0) t.push_back(e.path().string());
      return t;
    };
    bool started = false;
    for (int k = 0; k < 600 && !started; ++k) {
      for (const auto& t : temporaries()) {
        std::error_code ec;
        if (fs::exists(t + "/slices/slice_0000.png", ec)) started = true;
      }
      if (!started) ::usleep(100000);
    }
    ASSERT_TRUE(started) << "the phantom never wrote a slice";
    ASSERT_EQ(::kill(pid, sig), 0);
    int status = 0;
    ASSERT_EQ(::waitpid(pid, &status, 0), pid);
    EXPECT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == sig) << "status " << status;
    EXPECT_TRUE(temporaries().empty()) << temporaries().front();
    EXPECT_FALSE(fs::exists(out));
  }
}
