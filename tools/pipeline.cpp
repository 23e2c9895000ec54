// orthosim pipeline --stack DIR --tissues tissues.json --spacing X,Y,Z (mm)
//   [--scene scene.json] [--grid 39x9] [--work DIR] --out model.h5 [--report r.json]
// One command from a colour stack to a scene-ready model: segment -> surface
// -> remesh -> build -> tune -> vessels, each stage run in this process as
// its own subcommand (same flags, same one-line errors, prefixed with the
// stage's name) and cached in the work folder (libmodel/pipeline/cache.h):
// a second run with nothing changed does no work, and a changed parameter
// re-runs only the stages downstream of it. With --scene, only what the
// scene uses is built: no vessel trees for a scene without vessels, and only
// the tissues of the scene's layers are tuned. Independent work runs side by
// side: the vessel trees (which read only the labels) in a child process
// alongside surface -> remesh -> build -> tune, the tissues inside surface
// and tune on TBB's threads; an assemble step then adds the trees to the
// tuned model. --export copies every stage's outputs (STL surfaces, quad
// layers and texture, tube meshes, tuned table, plots) into one folder.
// docs/pipeline.md.
#include "libmodel/format/atomic.h"
#include "libmodel/format/model.h"
#include "libmodel/msm/build.h"
#include "libmodel/pipeline/cache.h"
#include "libmodel/provenance.h"
#include "libmodel/remesh/remesh.h"
#include "libmodel/segment/segment.h"
#include "libmodel/tissues.h"
#include "libmodel/tune/experiment.h"
#include "libmodel/vessels/vessels.h"  // VesselOptions' defaults only (no link)
#include "tools/common.h"

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <array>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <optional>
#include <set>
#include <sstream>

namespace orthosim::cli {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// What --export copies: (stage, its output, the entry in the export folder);
// besides these, surfaces/<tissue>.stl and reports/<stage>.json (kExportFolders).
const std::array<std::array<std::string, 3>, 6> kExportItems = {{{"segment", "labels.h5", "labels.h5"},
                                                                 {"segment", "labels.nrrd", "labels.nrrd"},
                                                                 {"remesh", "quads", "quads"},
                                                                 {"vessels", "meshes", "vessels"},
                                                                 {"tune", "tuned_tissues.json", "tuned_tissues.json"},
                                                                 {"tune", "plots", "tune"}}};
const std::array<std::string, 2> kExportFolders = {"surfaces", "reports"};

struct Args {
  std::string stack, tissues, spacing, origin = "0,0,0", roi, slices, scene, grid = "39x9", work, out, export_dir;
  bool texture = true, tune = true, register_slices = false;
  // virtual experiments per tuned tissue: the bound that keeps the pipeline
  // reproducible; the wall-clock budget is only a safety cap (a run it cuts
  // depends on the machine's speed, and tune warns)
  std::int64_t tune_evaluations = 4000;
  double tune_budget_s = 300;
  std::uint64_t seed = 1;
  int through_cells = 1;  // build's --through-cells (a fine grid's lattice cells need it: 400x100 builds with 4)
  int bit_depth = 16;     // segment's --bit-depth (significant bits of 16-bit slices)
  double smoothness = SegmentOptions{}.smoothness;  // segment's --smoothness (the labels' smoothness prior)
  std::string colour_space = to_string(SegmentOptions{}.colour_space);  // segment's --colour-space
  double poisson_ratio = msm::BuildOptions{}.poisson_ratio;  // build's --poisson-ratio (the layers' volume term)
  bool lattice_volume_term = false;                          // build's --lattice-volume-term
  double inversion_guard = msm::BuildOptions{}.inversion_guard;  // build's --inversion-guard
  std::string tetra_volume_term = msm::BuildOptions{}.tetra_volume_term;  // build's --tetra-volume-term
  double spur_ratio = VesselOptions{}.spur_ratio;                 // vessels' --spur-ratio
  bool axis_correction = true;                               // build's axis correction (--no-axis-correction: off)
  CommonOptions common;
};

// a number as its shortest exact decimal (cache keys and command lines)
std::string exact(double v) {
  std::ostringstream o;
  o.precision(17);
  o << v;
  return o.str();
}

std::string join(const std::vector<std::string>& v, const std::string& sep = ",") {
  std::string s;
  for (const auto& x : v) s += (s.empty() ? "" : sep) + x;
  return s;
}

// Copies a file or a folder (recursively) to `to`, creating its parent.
void copy_path(const fs::path& from, const fs::path& to) {
  std::error_code ec;
  if (!to.parent_path().empty()) fs::create_directories(to.parent_path(), ec);
  if (!ec && fs::is_directory(from, ec)) {
    fs::create_directories(to, ec);
    if (!ec) fs::copy(from, to, fs::copy_options::recursive | fs::copy_options::overwrite_existing, ec);
  } else if (!ec) {
    fs::copy_file(from, to, fs::copy_options::overwrite_existing, ec);
  }
  if (ec) throw Error(to.string(), "cannot copy " + from.string() + ": " + ec.message());
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

// Runs another orthosim process with `args` (this executable, found through
// /proc/self/exe), its stderr written to the file `err` (replayed on ours when
// it ends: replay_stderr). Throws Error when it cannot start.
pid_t spawn_self(const std::vector<std::string>& args, const std::string& err) {
  std::error_code ec;
  const std::string self = fs::read_symlink("/proc/self/exe", ec).string();
  if (ec) throw Error("/proc/self/exe", "cannot find this executable to run a stage in parallel: " + ec.message());
  std::vector<std::string> argv_s{self};
  argv_s.insert(argv_s.end(), args.begin(), args.end());
  std::vector<char*> argv;
  for (auto& x : argv_s) argv.push_back(x.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  posix_spawn_file_actions_addopen(&fa, 2, err.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  pid_t pid = 0;
  // the child starts with no signal blocked (this process blocks the
  // interrupts in all but its signal thread, tools/main.cpp)
  posix_spawnattr_t attr;
  posix_spawnattr_init(&attr);
  sigset_t none;
  sigemptyset(&none);
  posix_spawnattr_setsigmask(&attr, &none);
  posix_spawnattr_setflags(&attr, POSIX_SPAWN_SETSIGMASK);
  const int rc = posix_spawn(&pid, self.c_str(), &fa, &attr, argv.data(), environ);
  posix_spawnattr_destroy(&attr);
  posix_spawn_file_actions_destroy(&fa);
  if (rc != 0) throw Error(self, std::string("cannot start a stage process: ") + std::strerror(rc));
  return pid;
}

// Copies a stage process's stderr file onto ours; returns the message of its
// error line ("orthosim <stage>: error: MESSAGE"), "" when it has none.
std::string replay_stderr(const std::string& err) {
  std::ifstream in(err);
  std::string line, message;
  while (std::getline(in, line)) {
    std::cerr << line << "\n";
    for (const char* kind : {": error: ", ": internal error: "})
      if (const auto at = line.find(kind); line.rfind("orthosim ", 0) == 0 && at != std::string::npos && message.empty())
        message = line.substr(at + std::strlen(kind));
  }
  return message;
}

// Waits for a child; its exit code (1 when it died of a signal).
int wait_child(pid_t pid) {
  int status = 0;
  while (waitpid(pid, &status, 0) < 0)
    if (errno != EINTR) return 1;
  return WIFEXITED(status) ? WEXITSTATUS(status) : 1;
}

class Runner {
 public:
  // The tool is an input of every stage: its version and the content hash of
  // this executable, so a rebuilt orthosim never reuses an older one's entries.
  Runner(const Args& a, Report& report)
      : a_(a), report_(report), tool_(version_string() + " " + hash_path("/proc/self/exe")) {}
  ~Runner() { stop_parallel(); }

  // A stage that failed while a parallel one was running: stop and reap it
  // (its cache entry has no manifest, so it is never used). What it said
  // before it stopped (an error of its own, when it failed too: the one-slice
  // stack's vessels) goes to the report (`stopped_stages`), not to stderr:
  // the failed stage's line is the run's one error line.
  void stop_parallel() {
    for (auto& p : pending_) {
      if (p.pid <= 0) continue;
      kill(p.pid, SIGTERM);
      wait_child(p.pid);
      p.pid = 0;
      std::ifstream in(stderr_file(p));
      std::string line, said;
      while (std::getline(in, line)) said += line + "\n";
      if (!said.empty()) report_.json()["stopped_stages"].push_back({{"stage", p.entry.stage}, {"stderr", said}});
    }
  }

  struct StageFailed {
    std::string stage, error;  // the stage's error message ("" when it printed none)
  };
  // A stage started with start(), finished by finish().
  struct Pending {
    pipeline::CacheEntry entry;
    json rec;
    std::vector<std::string> outputs;
    std::chrono::steady_clock::time_point t0;
    pid_t pid = 0;  // 0: nothing to wait for (a hit)
  };

  // Runs (or reuses) one stage in this process: `body` fills the entry's
  // folder and returns an exit code (0: done). `prepare` runs first.
  pipeline::CacheEntry stage(const std::string& name, const std::vector<std::string>& key_parts,
                             const std::function<int(const std::string& dir)>& body,
                             const std::vector<std::string>& outputs,
                             const std::function<void(const std::string& dir)>& prepare = {}) {
    Pending p = open(name, key_parts, outputs);
    if (!p.entry.hit) {
      if (prepare) prepare(p.entry.dir);
      if (const int code = body(p.entry.dir); code != 0) fail(name, code, last_error());
    }
    return close(std::move(p));
  }

  // The arguments of a subcommand stage: `make_args` plus the report in the
  // entry's folder and --quiet.
  std::function<int(const std::string&)> command(
      const std::function<std::vector<std::string>(const std::string& dir)>& make_args) {
    return [make_args](const std::string& dir) {
      auto args = with_report(make_args(dir), dir);
      const std::string saved = command_line();
      command_line() = "orthosim " + join(args, " ");
      last_error().clear();
      const int code = run_command(args);
      command_line() = saved;
      return code;  // a failed stage printed its one-line error
    };
  }

  // Starts a subcommand stage in a child process, so that it runs alongside
  // the stages that follow in this one; finish() waits for it.
  std::size_t start(const std::string& name, const std::vector<std::string>& key_parts,
                    const std::function<std::vector<std::string>(const std::string& dir)>& make_args,
                    const std::vector<std::string>& outputs) {
    Pending p = open(name, key_parts, outputs);
    p.rec["parallel"] = true;
    if (!p.entry.hit) p.pid = spawn_self(with_report(make_args(p.entry.dir), p.entry.dir), stderr_file(p));
    pending_.push_back(std::move(p));
    return pending_.size() - 1;
  }
  pipeline::CacheEntry finish(std::size_t i) {
    Pending& p = pending_.at(i);
    if (p.pid > 0) {
      const int code = wait_child(p.pid);
      p.pid = 0;
      const std::string error = replay_stderr(stderr_file(p));
      if (code != 0) fail(p.entry.stage, code, error);
    }
    return close(std::move(p));
  }

  void skip(const std::string& name, const std::string& why) {
    report_.json()["stages"].push_back({{"stage", name}, {"ran", false}, {"why", why}});
    if (!a_.common.quiet) std::cerr << "pipeline: " << name << " skipped: " << why << "\n";
  }

  int failed_code() const { return failed_code_; }

 private:
  static std::vector<std::string> with_report(std::vector<std::string> args, const std::string& dir) {
    args.insert(args.end(), {"--report", dir + "/report.json", "--quiet"});
    return args;
  }

  Pending open(const std::string& name, const std::vector<std::string>& key_parts, const std::vector<std::string>& outputs) {
    std::vector<std::string> parts = key_parts;
    parts.push_back(tool_);
    Pending p;
    p.entry = pipeline::open_entry(a_.work, name, pipeline::stage_key(name, parts));
    p.rec = {{"stage", name}, {"key", p.entry.key}, {"dir", p.entry.dir}, {"ran", !p.entry.hit},
             {"why", p.entry.hit ? "cached" : p.entry.reason}};
    p.outputs = outputs;
    p.outputs.push_back("report.json");
    p.t0 = std::chrono::steady_clock::now();
    if (!a_.common.quiet) std::cerr << "pipeline: " << name << " (" << (p.entry.hit ? "cached" : p.entry.reason) << ")\n";
    return p;
  }

  pipeline::CacheEntry close(Pending&& p) {
    if (!p.entry.hit) pipeline::commit_entry(p.entry, p.outputs);
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - p.t0).count();
    p.rec["seconds"] = s;
    report_.phase(p.entry.stage, s);
    report_.json()["stages"].push_back(p.rec);
    return p.entry;
  }

  [[noreturn]] void fail(const std::string& name, int code, const std::string& error) {
    // the stage printed its one-line error; its cache entry stays without a manifest
    failed_code_ = code;
    throw StageFailed{name, error};
  }
  static std::string stderr_file(const Pending& p) { return p.entry.dir + "/stderr.txt"; }

  const Args& a_;
  Report& report_;
  const std::string tool_;
  int failed_code_ = 0;
  std::vector<Pending> pending_;
};

// The pipeline's work (run_pipeline below).
int run_stages(Args a, Report& report) {
  if (a.out.empty()) throw UsageError("--out: a model file path is required");
  if (a.work.empty()) a.work = a.out + ".work";
  if (!(a.tune_budget_s > 0)) throw UsageError("--tune-budget-s must be > 0");
  if (a.tune_evaluations < 1) throw UsageError("--tune-evaluations must be >= 1");
  {
    // the remesh stage's own rule, before any stage runs (--grid 2x9 failed after
    // segment and surface, minutes on a full stack)
    const std::vector<int> g = parse_size(a.grid, 2, "--grid");
    RemeshOptions ro;
    ro.nu = g[0], ro.nv = g[1];
    try {
      validate(ro);
    } catch (const Error& e) {
      throw UsageError("--" + e.message());
    }
  }
  {
    // and build's (--tetra-volume-term prisms at --poisson-ratio 0.25), before any stage runs
    msm::BuildOptions bo;
    bo.poisson_ratio = a.poisson_ratio;
    bo.inversion_guard = a.inversion_guard;
    bo.tetra_volume_term = a.tetra_volume_term;
    try {
      msm::check_build_options(bo);
    } catch (const Error& e) {
      throw flag_error(e);
    }
  }
  check_voxel_flags(parse_list(a.spacing, 3, "--spacing", true), parse_list(a.origin, 3, "--origin", false));
  SegmentOptions region;  // segment's --roi and --slices
  parse_roi_flags(a.roi, a.slices, region);
  std::error_code ec;
  if (!fs::is_directory(a.stack, ec)) throw Error(a.stack, "not a folder of slices");
  if (!a.roi.empty() || !a.slices.empty()) {
    // a region beyond the slices is refused before any stage (reads the first slice's size)
    roi_source(stack_source(a.stack, a.bit_depth), region);
  }
  if (fs::is_directory(a.out, ec)) throw Error(a.out, "is a folder; --out names a model file");
  check_output_file(a.out);
  check_output_dir(a.work);
  if (!a.export_dir.empty()) {
    check_output_dir(a.export_dir);
    // the export's own entries replace what is there: --out EXPORT/labels.h5 was
    // replaced by the labels (exit 0). Other files beside them are fine (the demo
    // keeps the model and the reports in its export folder).
    for (const auto& [flag, path] : {std::pair<std::string, std::string>{"--out", a.out}, {"--report", a.common.report},
                                     {"--work", a.work}}) {
      const fs::path rel = path.empty() ? fs::path() : path_within(path, a.export_dir);
      if (rel.empty()) continue;
      if (rel == ".") throw Error(path, flag + " names the --export folder, which the export replaces");
      const std::string first = rel.begin()->string();
      // (each entry of the export replaces what was there)
      const bool entry = std::find(kExportFolders.begin(), kExportFolders.end(), first) != kExportFolders.end() ||
                         std::any_of(kExportItems.begin(), kExportItems.end(), [&](const auto& it) { return it[2] == first; });
      if (entry)
        throw Error(path, flag + " names '" + first + "' of the --export folder " + a.export_dir + ", which the export replaces");
    }
  }
  const TissueTable table = load_tissue_table(a.tissues);
  require_background_colour(table);  // the segment stage's, before any stage runs
  const SceneNeeds scene = read_scene(a.scene);
  // the slices segment reads, not every file in the folder (a .DS_Store re-ran
  // every stage; a slice outside --slices was read to hash it before each run)
  const std::string stack_hash = hash_stack(a.stack, region.first_slice, region.last_slice),
                    table_hash = hash_path(a.tissues);
  report.input(a.stack, stack_hash);
  report.input(a.tissues, table_hash);
  if (!a.scene.empty()) report.input(a.scene);
  report.parameters() = {{"grid", a.grid}, {"through_cells", a.through_cells}, {"poisson_ratio", a.poisson_ratio}, {"lattice_volume_term", a.lattice_volume_term}, {"inversion_guard", a.inversion_guard}, {"tetra_volume_term", a.tetra_volume_term}, {"spur_ratio", a.spur_ratio}, {"axis_correction", a.axis_correction}, {"bit_depth", a.bit_depth}, {"smoothness", a.smoothness}, {"colour_space", a.colour_space}, {"spacing_mm", a.spacing}, {"origin_mm", a.origin}, {"roi_px", region.roi_px}, {"slices", {region.first_slice, region.last_slice}},
                         {"work", a.work}, {"texture", a.texture}, {"tune", a.tune},
                         {"tune_budget_s", a.tune_budget_s}, {"tune_evaluations", a.tune_evaluations}, {"seed", a.seed}, {"export", a.export_dir}};

  // tissues of the layers (table order is outer to inner) and of the vessels
  std::vector<std::string> layered, vessels;
  std::vector<std::string> beside;  // layered tissues after the floor, not in it (checked once segmented)
  std::string fixed_bottom;         // a layered tissue build makes the fixed bottom (no rigid one segmented)
  // The stack ends at the first rigid tissue: what lies inside it (marrow in
  // bone) moves with it and adds no layer.
  // Outer to inner by the table's nesting ('inside': its depth), ties in table
  // order: a table listing bone first still gives skin, fat, muscle, bone
  // (table order alone refused it: "needs at least two layered tissues").
  std::vector<const Tissue*> by_depth;
  for (const auto& t : table.tissues) by_depth.push_back(&t);
  std::stable_sort(by_depth.begin(), by_depth.end(),
                   [&](const Tissue* a, const Tissue* b) { return table.depth(*a) < table.depth(*b); });
  // does `t` lie, through its 'inside' chain, in the tissue named `outer`?
  auto lies_in = [&](const Tissue& t, const std::string& outer) {
    for (const Tissue* p = table.find(t.inside); p; p = table.find(p->inside))
      if (p->name == outer) return true;
    return false;
  };
  auto in_what = [](const Tissue& t) { return t.inside.empty() ? std::string("in no tissue") : "in '" + t.inside + "'"; };
  auto is_layer = [](const Tissue& t) { return t.layer == "tetra" || t.layer == "lattice" || t.layer == "rigid"; };
  const Tissue* floor = nullptr;  // the first rigid tissue
  for (const Tissue* tp : by_depth) {
    const Tissue& t = *tp;
    if (t.layer == "vessel") vessels.push_back(t.name);
    if (!is_layer(t)) continue;
    if (!floor) {
      layered.push_back(t.name);
      if (t.layer == "rigid") floor = &t;
      continue;
    }
    // after the floor: only what lies in it moves with it; a layered tissue beside
    // it was left out of the model without a word (an artery made 'lattice', in
    // the muscle next to the bone)
    if (!lies_in(t, floor->name)) beside.push_back(t.name);
  }
  if (layered.size() < 2) {
    // a rigid outermost tissue ends the stack at once (the table may list more layered tissues)
    if (layered.size() == 1 && floor)
      throw Error(a.tissues, "the outermost layered tissue '" + layered[0] +
                                 "' is rigid: the layers end at the first rigid tissue, so none is left to build (make it "
                                 "tetra or lattice)");
    throw Error(a.tissues, "the pipeline needs at least two layered tissues (tetra, lattice or rigid)");
  }
  // The layers nest: each layered tissue lies, through its 'inside' chain, in
  // one outside it. A second outermost one ('inside': null) failed in the build
  // with an error against a file in the cache.
  for (std::size_t i = 1; i < layered.size(); ++i) {
    bool nested = false;
    for (std::size_t j = 0; j < i && !nested; ++j) nested = lies_in(*table.find(layered[i]), layered[j]);
    if (!nested)
      throw Error(a.tissues, "layered tissue '" + layered[i] + "' lies inside none of the layered tissues outside it (" +
                                 layered[0] + (i > 1 ? " ... " + layered[i - 1] : std::string()) +
                                 "): the layers nest one in another; give it the tissue it lies in ('inside')");
  }
  // And, among the tissues the slices show, each lies in the layer just outside
  // it, and none lies beside the floor. Checked once segmented: a general table
  // may list side-by-side tissues a stack does not show (a tendon beside the
  // muscle). Two siblings (an artery made 'lattice', and the bone, both in the
  // muscle) failed in remesh ("not inside artery") against the cache's STL; after
  // the bone the artery was left out of the model without a word.
  auto require_layers_nest = [&] {
    for (const auto& name : beside) {
      const Tissue& t = *table.find(name);
      throw Error(a.tissues, "layered tissue '" + t.name + "' (" + t.layer + ", " + in_what(t) + ") lies beside the rigid '" +
                                 floor->name + "', the innermost layer, not in it: the layers nest one in another; make it "
                                 "lie in a layer ('inside') or give it layer vessel or none");
    }
    for (std::size_t i = 1; i < layered.size(); ++i) {
      const Tissue& t = *table.find(layered[i]);
      if (!lies_in(t, layered[i - 1]))
        throw Error(a.tissues, "layered tissue '" + layered[i] + "' (" + in_what(t) + ") does not lie in '" + layered[i - 1] +
                                   "', the layer just outside it: the layers nest one in another; make one of the two lie "
                                   "in the other ('inside') or give it layer vessel or none");
    }
  };
  // the layers and vessels a --scene names must be among them; why(kind, name) says why one is not
  auto require_scene_needs = [&](const std::function<std::string(const std::string&, const std::string&)>& why) {
    for (const auto& l : scene.layers)
      if (std::find(layered.begin(), layered.end(), l) == layered.end()) throw Error(a.scene, why("layer", l));
    for (const auto& v : scene.vessels)
      if (std::find(vessels.begin(), vessels.end(), v) == vessels.end()) throw Error(a.scene, why("vessel", v));
  };
  require_scene_needs([&](const std::string& kind, const std::string& name) {
    return kind + " '" + name + "' is not a " + (kind == "layer" ? "layered" : "vessel") + " tissue of " + a.tissues;
  });

  // the tune stage's check of the tissues it will tune, before any stage runs
  // (a modulus of 1e30 kPa was refused by tune after segment, surface, remesh and build)
  // (the tissues the tune stage takes: layered, not rigid, with mechanics, in the scene's layers)
  auto tunes = [&](const std::string& t) {
    const Tissue* ti = table.find(t);
    return ti->layer != "rigid" && ti->mechanics.model != Mechanics::Model::none &&
           (scene.layers.empty() || std::find(scene.layers.begin(), scene.layers.end(), t) != scene.layers.end());
  };
  if (a.tune)
    for (const auto& t : layered) {
      if (!tunes(t)) continue;
      const Tissue* ti = table.find(t);
      try {
        tune::validate(tune::target_of(*ti));
      } catch (const Error& e) {
        throw Error(a.tissues, "tissue '" + t + "': " + e.message() + " (the tune stage's check; --no-tune skips it)");
      }
    }

  Runner run(a, report);
  try {
    // 1. segment
    const auto seg = run.stage(
        "segment",
        {stack_hash, table_hash, a.spacing, a.origin, a.register_slices ? "registered" : "as-is",
         "bit-depth " + std::to_string(a.bit_depth), "smoothness " + exact(a.smoothness),
         "colour-space " + a.colour_space,
         "roi " + std::to_string(region.roi_px[0]) + "," + std::to_string(region.roi_px[1]) + "," +
             std::to_string(region.roi_px[2]) + "," + std::to_string(region.roi_px[3]) + " slices " +
             std::to_string(region.first_slice) + "," + std::to_string(region.last_slice)},
        run.command([&](const std::string& d) {
          std::vector<std::string> args{"segment", "--stack", a.stack, "--tissues", a.tissues, "--spacing",
                                        a.spacing, "--origin", a.origin, "--out", d + "/labels.h5",
                                        "--nrrd", d + "/labels.nrrd", "--bit-depth", std::to_string(a.bit_depth),
                                        "--smoothness", exact(a.smoothness), "--colour-space", a.colour_space};
          if (a.register_slices) args.push_back("--register");
          if (!a.roi.empty()) args.insert(args.end(), {"--roi", a.roi});
          if (!a.slices.empty()) args.insert(args.end(), {"--slices", a.slices});
          return args;
        }),
        {"labels.h5", "labels.nrrd"});
    const std::string labels = seg.dir + "/labels.h5";

    // Tissues of the table that the stack does not show (a general table on a
    // crop: no artery in it, no marrow in the slices) are left out, each with
    // a warning naming the stack and the table; the surface stage refused
    // them with an error against the cache's labels file. The layers need two.
    {
      const Volume v = ModelReader(labels).volume();
      std::vector<std::int64_t> count(256, 0);
      for (std::uint8_t l : v.labels) ++count[l];
      // the segment stage's calibration samples per tissue: a tissue whose colour
      // was found but has no voxel left lost them to the clean-up (a wrong 'inside')
      std::map<std::string, std::int64_t> samples;
      json disagree, separations;
      try {
        const json rep = json::parse(std::ifstream(seg.dir + "/report.json"));
        for (const auto& pr : rep.at("metrics").at("prototypes")) samples[pr.at("tissue").get<std::string>()] += pr.at("samples").get<std::int64_t>();
        disagree = rep.at("metrics").value("calibration_disagreements", json::array());
        separations = rep.at("metrics").value("separations", json::array());
      } catch (const std::exception&) {
        // a report without prototypes: the warning cannot tell the two causes apart
      }
      // A collapsed calibration (segment's warning: a tissue's share of the voxels
      // 4-fold off its share of the calibration samples; the phantom at noise 32)
      // gives labels no model can be built from: said here, not in surface's
      // nesting a stage later.
      if (disagree.is_array() && !disagree.empty()) {
        const json& d = disagree.front();
        const double vf = d.at("voxel_fraction").get<double>(), sf = d.at("sample_fraction").get<double>();
        // the embedding medium's colour found, its voxels gone (segment's warning says the same)
        const bool enclosed = d.at("tissue").get<std::string>() == table.label_names().at(0) && vf < sf;
        throw Error(a.stack, "the segmentation collapsed: '" + d.at("tissue").get<std::string>() + "' has " +
                                 std::to_string(std::lround(100 * vf)) + " % of the voxels but " +
                                 std::to_string(std::lround(100 * sf)) +
                                 " % of the colour calibration's samples (noise too strong for the tissue table's "
                                 "colours to be told apart, or the table's colours far off: " +
                                 a.tissues + "; the segment report in " + seg.dir + ")" +
                                 (enclosed ? ", or something around the specimen that the table does not name (the "
                                             "photograph's frame, a scale, a label) was taken for tissue: --roi "
                                             "around the specimen"
                                           : ""));
      }
      json absent = json::array();
      auto present = [&](std::vector<std::string>& names) {
        std::vector<std::string> kept;
        for (const auto& t : names) {
          const int l = v.label_of(t);
          if (l > 0 && count[static_cast<std::size_t>(l)] > 0) {
            kept.push_back(t);
            continue;
          }
          // Its colour was found but no voxel is left: the model would lack a tissue the
          // slices show. That is an error (a wrong 'inside', or a segmentation that
          // collapsed: at 8-bit noise 24 the vein's prototype took the gel and the
          // clean-up gave the skin away), not a tissue to leave out.
          const auto found = samples.find(t);
          if (found != samples.end() && found->second > 0)
            throw Error(a.stack, "no voxel of '" + t + "' is left after segmentation, though its colour was found (" +
                                     std::to_string(found->second) +
                                     " calibration samples): the clean-up gave its voxels to the tissues around them; "
                                     "check its 'inside' in " + a.tissues +
                                     " and the segment report (prototypes' shifts, cleanup) in " + seg.dir +
                                     colour_noise_note(separations, t));
          absent.push_back(t);
          std::cerr << "orthosim pipeline: warning: " << a.stack << ": no voxel was segmented as '" << t
                    << "' (no calibration sample and no voxel took its colour: the slices do not show it, or their "
                       "compression or noise changed it; tissue table "
                    << a.tissues << "); it is left out\n";
        }
        names = kept;
      };
      present(layered);
      present(vessels);
      present(beside);
      report.metrics()["absent_tissues"] = absent;
      // Without a rigid tissue the innermost layered one is the model's fixed
      // bottom (build: its surface, every node fixed), not a layer: said, and
      // not tuned (its tune failed on 'built as a rigid layer', a cache path
      // named; with --no-tune the muscle became rigid without a word)
      // (build's rule: msm::resolve_stack over the segmented layered tissues)
      try {
        fixed_bottom = msm::resolve_stack({}, layered, table).layered_bottom;
      } catch (const Error&) {
        // no layer at all: the build stage says so
      }
      if (!fixed_bottom.empty()) {
        std::cerr << "orthosim pipeline: warning: " << a.stack << ": no rigid tissue of " << a.tissues
                  << " was segmented: the innermost layered tissue '" << fixed_bottom << "' ("
                  << table.find(fixed_bottom)->layer << " in the table) becomes the model's fixed bottom, not a layer\n";
      }
      report.metrics()["fixed_bottom"] = fixed_bottom;
      require_layers_nest();
      if (layered.size() < 2)
        throw Error(a.stack, "the segmented stack shows " + std::to_string(layered.size()) +
                                 " layered tissue(s) of " + a.tissues + "; the layers need at least two");
      require_scene_needs([&](const std::string& kind, const std::string& name) {
        return kind + " '" + name + "': no voxel of it was segmented in " + a.stack;
      });
    }

    // 2. vessels: they read only the labels, so they run in a child process
    // alongside surface -> remesh -> build -> tune (only the trees the scene
    // uses; all vessel tissues without a scene)
    std::optional<std::size_t> vessel_job;
#ifdef ORTHOSIM_HAVE_VESSELS
    const std::vector<std::string> want = scene.given ? scene.vessels : vessels;
    if (want.empty()) {
      run.skip("vessels", scene.given ? "the scene uses no vessels" : "the tissue table has no vessel tissue");
    } else {
      vessel_job = run.start(
          "vessels", {seg.key, join(want), scene.given ? "all-required" : "skip-unformed", "spur-ratio " + exact(a.spur_ratio)},
          [&](const std::string& d) {
            std::vector<std::string> args{"vessels", "--labels", labels, "--model", d + "/vessels.h5", "--out",
                                          d + "/meshes", "--spur-ratio", exact(a.spur_ratio)};
            for (const auto& v : want) args.insert(args.end(), {"--tissue", v});
            // without a scene no tree is required: a vessel tissue whose few
            // voxels form no vessel is left out with a warning (it stopped the
            // whole pipeline); a scene's vessels must be there
            if (!scene.given) args.push_back("--skip-unformed");
            return args;
          },
          {"vessels.h5", "meshes"});
    }
#else
    run.skip("vessels", "this build has no vessels stage");
#endif

    // 3. surface: the layered tissues
    const auto surf = run.stage(
        // the nesting is the table's ('inside'), not inferred from the volume:
        // on a real slice where the skin is missing in places (the arm touching
        // the torso) the inference put the skin inside the fat
        "surface", {seg.key, join(layered), table_hash, "table-nesting"}, run.command([&](const std::string& d) {
          return std::vector<std::string>{"surface",   "--labels", labels,           "--out",   d,
                                          "--tissues", join(layered), "--tissue-table", a.tissues, "--model",
                                          d + "/model.h5"};
        }),
        [&] {
          std::vector<std::string> o{"model.h5"};
          for (const auto& t : layered) o.push_back(t + ".stl");
          return o;
        }(),
        [&](const std::string& d) { copy_path(labels, d + "/model.h5"); });

    // 4. remesh: corresponding quad layers (+ the skin's texture)
    const auto rem = run.stage(
        "remesh", {surf.key, seg.key, a.grid, a.texture ? stack_hash : "no-texture"},
        run.command([&](const std::string& d) {
          std::vector<std::string> inner;
          for (std::size_t i = 1; i < layered.size(); ++i) inner.push_back(surf.dir + "/" + layered[i] + ".stl");
          std::vector<std::string> args{"remesh", "--surface", surf.dir + "/" + layered[0] + ".stl", "--inner",
                                        join(inner), "--grid", a.grid, "--out", d + "/quads", "--model",
                                        d + "/model.h5"};
          // (the bit depth is in seg.key, which this stage's key holds)
          if (a.texture) args.insert(args.end(), {"--stack", a.stack, "--texture", "--bit-depth", std::to_string(a.bit_depth)});
          return args;
        }),
        {"model.h5", "quads"}, [&](const std::string& d) { copy_path(surf.dir + "/model.h5", d + "/model.h5"); });

    // 5. build: the multilayer mass-spring model
    const auto bld = run.stage(
        "build", {rem.key, table_hash, "through-cells " + std::to_string(a.through_cells), "poisson-ratio " + exact(a.poisson_ratio),
                  a.lattice_volume_term ? "lattice-volume-term" : "no-lattice-volume-term",
                  a.axis_correction ? "axis-correction" : "no-axis-correction", "inversion-guard " + exact(a.inversion_guard),
                  "tetra-volume-term " + a.tetra_volume_term},
        run.command([&](const std::string& d) {
          std::vector<std::string> args{"build", "--model", d + "/model.h5", "--tissues", a.tissues, "--through-cells",
                                        std::to_string(a.through_cells), "--poisson-ratio", exact(a.poisson_ratio),
                                        "--inversion-guard", exact(a.inversion_guard), "--tetra-volume-term",
                                        a.tetra_volume_term};
          if (a.lattice_volume_term) args.push_back("--lattice-volume-term");
          if (!a.axis_correction) args.push_back("--no-axis-correction");
          return args;
        }),
        {"model.h5"}, [&](const std::string& d) { copy_path(rem.dir + "/model.h5", d + "/model.h5"); });
    std::string last = bld.dir + "/model.h5";
    std::string last_key = bld.key;

    // 6. tune: the tissues the scene loads (all without a scene), side by side
#ifdef ORTHOSIM_HAVE_TUNE
    if (a.tune) {
      std::vector<std::string> tuned;
      for (const auto& t : layered)
        if (tunes(t) && t != fixed_bottom) tuned.push_back(t);
      if (tuned.empty()) {
        run.skip("tune", "the scene loads no tissue with mechanics to tune");
      } else {
        const std::string from = last;
        const auto tun = run.stage(
            "tune", {last_key, table_hash, join(tuned), std::to_string(a.seed), std::to_string(a.tune_budget_s),
                     std::to_string(a.tune_evaluations)},
            run.command([&](const std::string& d) {
              std::vector<std::string> args{"tune",     "--tissues", a.tissues, "--model", d + "/model.h5", "--seed",
                                            std::to_string(a.seed), "--budget-s", std::to_string(a.tune_budget_s),
                                            "--max-evaluations", std::to_string(a.tune_evaluations),
                                            "--out", d + "/tuned_tissues.json", "--plot", d + "/plots"};
              for (const auto& t : tuned) args.insert(args.end(), {"--tissue", t});
              return args;
            }),
            {"model.h5", "tuned_tissues.json", "plots"}, [&](const std::string& d) { copy_path(from, d + "/model.h5"); });
        last = tun.dir + "/model.h5";
        last_key = tun.key;
      }
    } else {
      run.skip("tune", "--no-tune");
    }
#else
    run.skip("tune", "this build has no tune stage");
#endif

    // 7. assemble: the vessel trees join the tuned model
    if (vessel_job) {
      const auto ves = run.finish(*vessel_job);
      {
        json left_out = json::array();
        try {
          const json vr = json::parse(std::ifstream(ves.dir + "/report.json"));
          for (const auto& e : vr["metrics"].value("left_out", json::array())) left_out.push_back(e["tissue"]);
        } catch (const std::exception&) {
          // an entry from before the report listed them: none left out
        }
        report.metrics()["vessels_left_out"] = left_out;
      }
      const std::string from = last;
      const auto asm_entry = run.stage(
          "assemble", {last_key, ves.key},
          [&](const std::string& d) {
            ModelReader trees(ves.dir + "/vessels.h5");
            ModelWriter w(d + "/model.h5", ModelWriter::Start::update);
            for (const auto& t : trees.names("/vessels")) w.write(t, trees.vessels(t));
            for (const auto& [stage, prov] : trees.provenance())
              if (stage == "vessels") w.write(stage, prov);
            w.commit();
            write_text_file(d + "/report.json", json{{"command", "assemble"}, {"vessels", ves.dir + "/vessels.h5"}}.dump(2) + "\n");
            return 0;
          },
          {"model.h5"}, [&](const std::string& d) { copy_path(from, d + "/model.h5"); });
      last = asm_entry.dir + "/model.h5";
    }

    // the model, atomically
    {
      AtomicFile f(a.out);
      copy_path(last, f.temp());
      f.commit();
    }
    report.output(a.out);

    // every stage's outputs in one folder, for people and viewers
    if (!a.export_dir.empty()) {
      AtomicDir out(a.export_dir);
      const fs::path t = out.temp();
      std::map<std::string, std::string> dirs;
      for (const auto& st : report.json()["stages"])
        if (st.contains("dir")) dirs[st["stage"].get<std::string>()] = st["dir"].get<std::string>();
      for (const auto& [stage, from, to] : kExportItems)
        if (dirs.count(stage)) copy_path(fs::path(dirs[stage]) / from, t / to);
      if (dirs.count("surface"))
        for (const auto& tissue : layered) copy_path(fs::path(dirs["surface"]) / (tissue + ".stl"), t / "surfaces" / (tissue + ".stl"));
      for (const auto& [stage, dir] : dirs) copy_path(fs::path(dir) / "report.json", t / "reports" / (stage + ".json"));
      out.commit();
      // the folder holds this run's outputs: the export's own entries that this run
      // did not write are an earlier run's and go (a run with --no-tune after a tuned
      // one left tune/, tuned_tissues.json and reports/tune.json beside the untuned
      // model; sweep of 2026-11-27). Other files stay.
      std::vector<fs::path> stale;
      for (const auto& [stage, from, to] : kExportItems)
        if (!dirs.count(stage)) stale.push_back(fs::path(a.export_dir) / to);
      for (const char* stage : {"segment", "surface", "remesh", "build", "tune", "vessels", "assemble"})
        if (!dirs.count(stage)) stale.push_back(fs::path(a.export_dir) / "reports" / (std::string(stage) + ".json"));
      for (const Tissue& t : table.tissues)
        if (!dirs.count("surface") || std::find(layered.begin(), layered.end(), t.name) == layered.end())
          stale.push_back(fs::path(a.export_dir) / "surfaces" / (t.name + ".stl"));
      for (const fs::path& p : stale) {
        std::error_code ec;
        if (fs::exists(fs::symlink_status(p, ec)) && fs::remove_all(p, ec) > 0) report.metrics()["export_removed"].push_back(p.string());
      }
      report.output(a.export_dir);
    }
  } catch (const Runner::StageFailed& f) {
    // the stage printed its one-line error; the previous --out and the cache stay intact
    run.stop_parallel();
    report.json()["failed_stage"] = f.stage;
    report.json()["error"] = f.error.empty() ? json() : json(f.error);
    report.write(a.common.report);
    return run.failed_code();
  } catch (const Error& e) {
    // the pipeline's own checks between stages (a tissue the clean-up lost, too
    // few layers): the report names the stage whose output failed them (it was
    // not written at all)
    const json& st = report.json()["stages"];
    run.stop_parallel();
    report.json()["failed_stage"] = st.empty() ? json("pipeline") : st.back()["stage"];
    report.json()["error"] = e.what();
    report.write(a.common.report);
    throw;
  }
  int ran = 0;
  for (const auto& s : report.json()["stages"]) ran += s.value("ran", false) ? 1 : 0;
  report.metrics()["stages_run"] = ran;
  report.write(a.common.report);
  if (!a.common.quiet) std::cout << "pipeline: wrote " << a.out << " (" << ran << " stages run)\n";
  return 0;
}

// Returns 0, or the exit code of the stage that failed (it printed its error).
// A run refused before any stage (a table whose layers do not nest) also writes
// its report, naming the error (failed_stage "pipeline").
int run_pipeline(const Args& a) {
  Report report("pipeline");
  report.json()["stages"] = json::array();
  auto failed = [&](const std::string& message) {
    if (report.json().contains("failed_stage")) return;  // the stages' own handler wrote it
    report.json()["failed_stage"] = "pipeline";
    report.json()["error"] = message;
    report.write(a.common.report);
  };
  try {
    return run_stages(a, report);
  } catch (const std::runtime_error& e) {  // Error and UsageError
    failed(e.what());
    throw;
  }
}

// A CLI11 check: a number x with ok(x); `what` names the range ("> 0")
std::function<std::string(const std::string&)> number_check(std::function<bool(double)> ok, std::string what) {
  return [ok = std::move(ok), what = std::move(what)](const std::string& v) -> std::string {
    try {
      return ok(std::stod(v)) ? "" : "must be " + what;
    } catch (...) {
      return "must be a number " + what;
    }
  };
}

// A CLI11 check: a number in [lo, hi)
std::function<std::string(const std::string&)> half_open_range(double lo, double hi) {
  return number_check([lo, hi](double x) { return x >= lo && x < hi; }, "in [" + exact(lo) + ", " + exact(hi) + ")");
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
  sub->add_option("--roi", a.roi,
                  "segment's: only this part of the slices, X,Y,W,H in pixels (default: whole slices); --origin stays "
                  "that of the slice files' pixel (0,0)");
  sub->add_option("--slices", a.slices,
                  "segment's: only the slices FIRST,LAST in natural name order, 0-based, inclusive (LAST -1: to the "
                  "last)");
  sub->add_option("--scene", a.scene, "scene file: build only what it uses");
  sub->add_option("--grid", a.grid, "quad grid NUxNV")->capture_default_str();
  sub->add_option("--bit-depth", a.bit_depth,
                  "significant bits of 16-bit slices, segment's (8..16; 12: a 12-bit camera's data in 16-bit files)")
      ->check(CLI::Range(8, 16))
      ->capture_default_str();
  sub->add_option("--smoothness", a.smoothness,
                  "segment's smoothness prior: nats of colour evidence per unlike face neighbour (0: off, the per-voxel "
                  "rule; docs/segment.md), >= 0")
      ->check(number_check([](double x) { return std::isfinite(x) && x >= 0; }, ">= 0"))
      ->capture_default_str();
  sub->add_option("--colour-space", a.colour_space,
                  "segment's colour space: rgb (the stack's 8-bit values, where sensor noise is) or cielab "
                  "(docs/segment.md)")
      ->check(CLI::IsMember({"rgb", "cielab"}))
      ->capture_default_str();
  sub->add_option("--through-cells", a.through_cells,
                  "lattice cells through each lattice layer, build's (1..64; a fine --grid needs more: 400x100 builds "
                  "with 4)")
      ->check(CLI::Range(1, 64))
      ->capture_default_str();
  sub->add_option("--poisson-ratio", a.poisson_ratio,
                  "Poisson's ratio of the layers' volume term, build's ([0.25, 0.5); 0.25: none)")
      ->check(half_open_range(0.25, 0.5))
      ->capture_default_str();
  sub->add_flag("--lattice-volume-term", a.lattice_volume_term,
                "build's: a volume term per hexahedron of the lattice layers too (docs/msm.md, The volume term)");
  sub->add_option("--tetra-volume-term", a.tetra_volume_term,
                  "build's: where a tetra layer's volume term acts, tets or prisms (docs/msm.md, The volume term)")
      ->check(CLI::IsMember({"tets", "prisms"}))
      ->capture_default_str();
  sub->add_option("--inversion-guard", a.inversion_guard,
                  "build's: the fraction of its rest volume below which a tetrahedron resists with the bulk modulus, "
                  "[0, 1) (0: none; docs/msm.md, The inversion guard)")
      ->check(half_open_range(0, 1))
      ->capture_default_str();
  sub->add_option("--spur-ratio", a.spur_ratio,
                  "vessels': a skeleton branch from a junction to an end shorter than this many junction radii is a "
                  "spur (raise it, e.g. to 4, for noisy labels; docs/vessels.md), > 0")
      ->check(number_check([](double x) { return std::isfinite(x) && x > 0; }, "> 0"))
      ->capture_default_str();
  sub->add_flag("!--no-axis-correction", a.axis_correction,
                "build's: leave each layer's rule as it is, no equal Young's moduli along u, v and through (docs/msm.md)");
  sub->add_option("--work", a.work, "cache folder (default: <out>.work)");
  sub->add_option("--out", a.out, "model file to write")->required();
  sub->add_option("--export", a.export_dir,
                  "also copy every stage's outputs (labels, STL surfaces, quad layers and texture, vessel meshes, "
                  "tuned table and plots, stage reports) into this folder");
  sub->add_flag("!--no-texture", a.texture, "skip the skin texture");
  sub->add_flag("--register", a.register_slices,
                "register the slices before segmentation (segment --register: their jitter undone, the drift kept)");
  sub->add_flag("!--no-tune", a.tune, "skip spring tuning");
  sub->add_option("--tune-evaluations", a.tune_evaluations,
                  "virtual experiments per tuned tissue: the bound that keeps the pipeline reproducible")
      ->capture_default_str();
  sub->add_option("--tune-budget-s", a.tune_budget_s,
                  "wall-clock safety cap per tuned tissue (s); a tuning it cuts depends on the machine's speed")
      ->capture_default_str();
  sub->add_option("--seed", a.seed, "seed of the tuning")
      ->check(seed_check())->capture_default_str();
  add_common_options(sub, a.common);
  sub->callback([sub] {
    int stage_code = 0;
    const int code = guarded("pipeline", [&] {
      check_common_options(a.common);  // before any stage runs
      check_operands(sub, a.common.report);
      stage_code = run_pipeline(a);
    });
    exit_code() = code != 0 ? code : stage_code;
  });
}

}  // namespace orthosim::cli
