// orthosim pipeline --stack DIR --tissues tissues.json --spacing X,Y,Z (mm)
//   [--scene scene.json] [--grid 39x9] [--work DIR] --out model.h5 [--report r.json]
// One command from a colour stack to a scene-ready model: segment -> surface
// -> remesh -> build -> tune -> vessels, each stage run in this process as
// its own subcommand (same flags, same one-line errors, prefixed with the
// stage's name) and cached in the work folder (libmodel/pipeline/cache.h):
// a second run with nothing changed does no work, and a changed parameter
// re-runs only the stages downstream of it. With --scene, only what the
// scene uses is built: no vessel trees for a scene without vessels, and only
// the tissues of the scene's layers are tuned. docs/pipeline.md.
#include "libmodel/format/atomic.h"
#include "libmodel/pipeline/cache.h"
#include "libmodel/provenance.h"
#include "libmodel/tissues.h"
#include "tools/common.h"

#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <set>
#include <sstream>

namespace orthosim::cli {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

struct Args {
  std::string stack, tissues, spacing, origin = "0,0,0", scene, grid = "39x9", work, out;
  bool texture = true, tune = true;
  double tune_budget_s = 30;
  std::uint64_t seed = 1;
  CommonOptions common;
};

std::string join(const std::vector<std::string>& v, const std::string& sep = ",") {
  std::string s;
  for (const auto& x : v) s += (s.empty() ? "" : sep) + x;
  return s;
}

void copy_file(const std::string& from, const std::string& to) {
  std::error_code ec;
  fs::copy_file(from, to, fs::copy_options::overwrite_existing, ec);
  if (ec) throw Error(to, "cannot copy " + from + ": " + ec.message());
}

// What a scene file asks of the model (only the keys the pipeline needs).
struct SceneNeeds {
  bool given = false;
  std::vector<std::string> layers;   // empty: every layer
  std::vector<std::string> vessels;  // empty: none
};

SceneNeeds read_scene(const std::string& path) {
  SceneNeeds n;
  if (path.empty()) return n;
  n.given = true;
  std::ifstream in(path);
  if (!in) throw Error(path, "cannot read the scene file");
  json j;
  try {
    j = json::parse(in);
  } catch (const json::exception& e) {
    throw Error(path, std::string("invalid JSON: ") + e.what());
  }
  auto names = [&](const char* key) {
    std::vector<std::string> v;
    if (!j.contains(key)) return v;
    if (!j[key].is_array()) throw Error(path, std::string(key) + " must be a list of names");
    for (const auto& e : j[key]) {
      if (!e.is_string()) throw Error(path, std::string(key) + " must be a list of names");
      v.push_back(e.get<std::string>());
    }
    return v;
  };
  n.layers = names("layers");
  n.vessels = names("vessels");
  return n;
}

class Runner {
 public:
  Runner(const Args& a, Report& report) : a_(a), report_(report) {}

  // Runs (or reuses) one stage: `args` are the subcommand's, with paths in
  // `dir`; `prepare` copies the stage's input model into dir first.
  pipeline::CacheEntry stage(const std::string& name, const std::vector<std::string>& key_parts,
                             const std::function<std::vector<std::string>(const std::string& dir)>& make_args,
                             const std::vector<std::string>& outputs,
                             const std::function<void(const std::string& dir)>& prepare = {}) {
    std::vector<std::string> parts = key_parts;
    parts.push_back(version_string());
    const auto key = pipeline::stage_key(name, parts);
    auto e = pipeline::open_entry(a_.work, name, key);
    json rec = {{"stage", name}, {"key", key}, {"dir", e.dir}};
    const auto t0 = std::chrono::steady_clock::now();
    if (e.hit) {
      rec["ran"] = false;
      rec["why"] = "cached";
    } else {
      rec["ran"] = true;
      rec["why"] = e.reason;
      if (prepare) prepare(e.dir);
      auto args = make_args(e.dir);
      args.push_back("--report");
      args.push_back(e.dir + "/report.json");
      args.push_back("--quiet");
      if (!a_.common.quiet) std::cerr << "pipeline: " << name << " (" << e.reason << ")\n";
      const std::string saved = command_line();
      command_line() = "orthosim " + join(args, " ");
      const int code = run_command(args);
      command_line() = saved;
      if (code != 0) {
        // the stage printed its one-line error; the cache entry stays without a manifest
        failed_code_ = code;
        throw StageFailed{name};
      }
      std::vector<std::string> outs = outputs;
      outs.push_back("report.json");
      pipeline::commit_entry(e, outs);
    }
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    rec["seconds"] = s;
    report_.phase(name, s);
    report_.json()["stages"].push_back(rec);
    if (!a_.common.quiet && e.hit) std::cerr << "pipeline: " << name << " (cached)\n";
    return e;
  }

  void skip(const std::string& name, const std::string& why) {
    report_.json()["stages"].push_back({{"stage", name}, {"ran", false}, {"why", why}});
    if (!a_.common.quiet) std::cerr << "pipeline: " << name << " skipped: " << why << "\n";
  }

  struct StageFailed {
    std::string stage;
  };
  int failed_code() const { return failed_code_; }

 private:
  const Args& a_;
  Report& report_;
  int failed_code_ = 0;
};

// Returns 0, or the exit code of the stage that failed (it printed its error).
int run_pipeline(Args a) {
  Report report("pipeline");
  report.json()["stages"] = json::array();
  if (a.out.empty()) throw UsageError("--out: a model file path is required");
  if (a.work.empty()) a.work = a.out + ".work";
  if (!(a.tune_budget_s > 0)) throw UsageError("--tune-budget-s must be > 0");
  parse_size(a.grid, 2, "--grid");
  parse_list(a.spacing, 3, "--spacing", true);
  parse_list(a.origin, 3, "--origin", false);
  std::error_code ec;
  if (!fs::is_directory(a.stack, ec)) throw Error(a.stack, "not a folder of slices");
  if (fs::is_directory(a.out, ec)) throw Error(a.out, "is a folder; --out names a model file");
  const TissueTable table = load_tissue_table(a.tissues);
  const SceneNeeds scene = read_scene(a.scene);
  report.input(a.stack);
  report.input(a.tissues);
  if (!a.scene.empty()) report.input(a.scene);
  report.parameters() = {{"grid", a.grid}, {"spacing_mm", a.spacing}, {"origin_mm", a.origin},
                         {"work", a.work}, {"texture", a.texture}, {"tune", a.tune},
                         {"tune_budget_s", a.tune_budget_s}, {"seed", a.seed}};

  // tissues of the layers (table order is outer to inner) and of the vessels
  std::vector<std::string> layered, vessels;
  // The stack ends at the first rigid tissue: what lies inside it (marrow in
  // bone) moves with it and adds no layer.
  bool floor = false;
  for (const auto& t : table.tissues) {
    if (!floor && (t.layer == "tetra" || t.layer == "lattice" || t.layer == "rigid")) layered.push_back(t.name);
    floor = floor || t.layer == "rigid";
    if (t.layer == "vessel") vessels.push_back(t.name);
  }
  if (layered.size() < 2) throw Error(a.tissues, "the pipeline needs at least two layered tissues (tetra, lattice or rigid)");
  for (const auto& l : scene.layers)
    if (std::find(layered.begin(), layered.end(), l) == layered.end())
      throw Error(a.scene, "layer '" + l + "' is not a layered tissue of " + a.tissues);
  for (const auto& v : scene.vessels)
    if (std::find(vessels.begin(), vessels.end(), v) == vessels.end())
      throw Error(a.scene, "vessel '" + v + "' is not a vessel tissue of " + a.tissues);

  const std::string stack_hash = hash_path(a.stack), table_hash = hash_path(a.tissues);
  Runner run(a, report);
  try {
    // 1. segment
    const auto seg = run.stage(
        "segment", {stack_hash, table_hash, a.spacing, a.origin},
        [&](const std::string& d) {
          return std::vector<std::string>{"segment", "--stack", a.stack, "--tissues", a.tissues, "--spacing",
                                          a.spacing, "--origin", a.origin, "--out", d + "/labels.h5"};
        },
        {"labels.h5"});
    const std::string labels = seg.dir + "/labels.h5";

    // 2. surface: the layered tissues
    const auto surf = run.stage(
        "surface", {seg.key, join(layered)},
        [&](const std::string& d) {
          return std::vector<std::string>{"surface", "--labels", labels, "--out", d, "--tissues", join(layered)};
        },
        [&] {
          std::vector<std::string> o;
          for (const auto& t : layered) o.push_back(t + ".stl");
          return o;
        }());

    // 3. remesh: corresponding quad layers (+ the skin's texture)
    const auto rem = run.stage(
        "remesh", {surf.key, seg.key, a.grid, a.texture ? stack_hash : "no-texture"},
        [&](const std::string& d) {
          std::vector<std::string> inner;
          for (std::size_t i = 1; i < layered.size(); ++i) inner.push_back(surf.dir + "/" + layered[i] + ".stl");
          std::vector<std::string> args{"remesh", "--surface", surf.dir + "/" + layered[0] + ".stl", "--inner",
                                        join(inner), "--grid", a.grid, "--out", d + "/quads", "--model",
                                        d + "/model.h5"};
          if (a.texture) args.insert(args.end(), {"--stack", a.stack, "--texture"});
          return args;
        },
        {"model.h5", "quads"}, [&](const std::string& d) { copy_file(labels, d + "/model.h5"); });

    // 4. build: the multilayer mass-spring model
    const auto bld = run.stage(
        "build", {rem.key, table_hash},
        [&](const std::string& d) {
          return std::vector<std::string>{"build", "--model", d + "/model.h5", "--tissues", a.tissues};
        },
        {"model.h5"}, [&](const std::string& d) { copy_file(rem.dir + "/model.h5", d + "/model.h5"); });
    std::string last = bld.dir + "/model.h5";
    std::string last_key = bld.key;

    // 5. tune: the tissues the scene loads (all without a scene)
#ifdef ORTHOSIM_HAVE_TUNE
    if (a.tune) {
      std::vector<std::string> tuned;
      for (const auto& t : layered) {
        const Tissue* ti = table.find(t);
        if (ti->layer == "rigid" || ti->mechanics.model == Mechanics::Model::none) continue;
        if (!scene.layers.empty() && std::find(scene.layers.begin(), scene.layers.end(), t) == scene.layers.end()) continue;
        tuned.push_back(t);
      }
      if (tuned.empty()) {
        run.skip("tune", "the scene loads no tissue with mechanics to tune");
      } else {
        const std::string from = last;
        const auto tun = run.stage(
            "tune", {last_key, table_hash, join(tuned), std::to_string(a.seed), std::to_string(a.tune_budget_s)},
            [&](const std::string& d) {
              std::vector<std::string> args{"tune",     "--tissues", a.tissues, "--model", d + "/model.h5", "--seed",
                                            std::to_string(a.seed), "--budget-s", std::to_string(a.tune_budget_s),
                                            "--out", d + "/tuned_tissues.json"};
              for (const auto& t : tuned) args.insert(args.end(), {"--tissue", t});
              return args;
            },
            {"model.h5", "tuned_tissues.json"}, [&](const std::string& d) { copy_file(from, d + "/model.h5"); });
        last = tun.dir + "/model.h5";
        last_key = tun.key;
      }
    } else {
      run.skip("tune", "--no-tune");
    }
#else
    run.skip("tune", "this build has no tune stage");
#endif

    // 6. vessels: only when the scene uses them (all vessel tissues without a scene)
#ifdef ORTHOSIM_HAVE_VESSELS
    const std::vector<std::string> want = scene.given ? scene.vessels : vessels;
    if (want.empty()) {
      run.skip("vessels", scene.given ? "the scene uses no vessels" : "the tissue table has no vessel tissue");
    } else {
      const std::string from = last;
      const auto ves = run.stage(
          "vessels", {last_key, seg.key, join(want)},
          [&](const std::string& d) {
            std::vector<std::string> args{"vessels", "--labels", labels, "--model", d + "/model.h5"};
            for (const auto& v : want) args.insert(args.end(), {"--tissue", v});
            return args;
          },
          {"model.h5"}, [&](const std::string& d) { copy_file(from, d + "/model.h5"); });
      last = ves.dir + "/model.h5";
    }
#else
    run.skip("vessels", "this build has no vessels stage");
#endif

    // the model, atomically
    {
      AtomicFile f(a.out);
      copy_file(last, f.temp());
      f.commit();
    }
    report.output(a.out);
  } catch (const Runner::StageFailed& f) {
    // the stage printed its one-line error; the previous --out and the cache stay intact
    report.json()["failed_stage"] = f.stage;
    return run.failed_code();
  }
  int ran = 0;
  for (const auto& s : report.json()["stages"]) ran += s.value("ran", false) ? 1 : 0;
  report.metrics()["stages_run"] = ran;
  report.write(a.common.report);
  if (!a.common.quiet) std::cout << "pipeline: wrote " << a.out << " (" << ran << " stages run)\n";
  return 0;
}

}  // namespace

void add_pipeline_command(CLI::App& app) {
  auto* sub = app.add_subcommand("pipeline",
                                 "colour stack to a scene-ready model in one command: segment, surface, remesh, "
                                 "build, tune, vessels, cached in a work folder");
  static Args a;
  sub->add_option("--stack", a.stack, "folder of colour slices")->required();
  sub->add_option("--tissues", a.tissues, "tissue table (tissues.json)")->required();
  sub->add_option("--spacing", a.spacing, "voxel size in mm, X,Y,Z")->required();
  sub->add_option("--origin", a.origin, "position of voxel (0,0,0) in mm, X,Y,Z")->capture_default_str();
  sub->add_option("--scene", a.scene, "scene file: build only what it uses");
  sub->add_option("--grid", a.grid, "quad grid NUxNV")->capture_default_str();
  sub->add_option("--work", a.work, "cache folder (default: <out>.work)");
  sub->add_option("--out", a.out, "model file to write")->required();
  sub->add_flag("!--no-texture", a.texture, "skip the skin texture");
  sub->add_flag("!--no-tune", a.tune, "skip spring tuning");
  sub->add_option("--tune-budget-s", a.tune_budget_s, "wall-clock budget per tuned tissue (s)")->capture_default_str();
  sub->add_option("--seed", a.seed, "seed of the tuning")->capture_default_str();
  add_common_options(sub, a.common);
  sub->callback([] {
    int stage_code = 0;
    const int code = guarded("pipeline", [&] { stage_code = run_pipeline(a); });
    exit_code() = code != 0 ? code : stage_code;
  });
}

}  // namespace orthosim::cli
