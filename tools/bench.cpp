// orthosim bench [--quick] [--only STAGE,...] [--out DIR] [--bench-dir DIR]:
// runs every stage's benchmark program (tests/bench, built with the tests)
// on its fixed harness workloads and gathers run time against error, side by
// side with the peers, into one report (issue 10; docs/BENCHMARKS.md).
//
// Each stage's program runs as `<program> --results=FILE.json [--quick]`
// (tests/bench/bench_results.h documents the rows and the workloads are
// listed at the top of each program). This command merges the rows, adds
// the machine, and writes atomically into DIR (default out/bench):
//   results.json   {"machine": {...}, "quick", "stages": [{stage, program, status, seconds, note}],
//                   "rows": [ROW...], "notes": [...], "goals": {"checked", "met"}}
//   results.csv    one line per row, the ROW columns (extra as JSON text)
//   summary.md     a table per stage, the machine, what was skipped
//   logs/<stage>.txt   each program's output
//   *.png          plots by scripts/plot_bench.py (when python3 with matplotlib is there)
// A program that is not built is skipped with a note (not an error). Exit
// status: 0 when every program that ran succeeded and every accuracy goal
// was met; 1 otherwise (the report is still written); 2 for bad usage.
// --report FILE.json gets the usual summary (parameters, --out, goals).
#include "libmodel/format/atomic.h"
#include "tools/common.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <sstream>
#include <thread>

namespace fs = std::filesystem;
using nlohmann::json;

namespace orthosim::cli {
namespace {

struct Stage {
  const char* name;
  const char* program;
  const char* what;
};

// The stages in pipeline order, their program, and what the rows measure.
const std::vector<Stage> kStages = {
    {"segment", "segment_bench", "phantom stack: voxels/s against Dice (min over tissues)"},
    {"surface", "surface_bench", "phantom tissues: time and faces against distance to the analytic interface; VTK flying edges"},
    {"remesh", "remesh_bench", "bent elliptic tube: Hausdorff distance against grid"},
    {"build", "msm_bench", "limb stack, 4 layers: build time against grid size (mass error)"},
    {"vessels", "vessels_bench", "phantom and analytic vessels: time against centreline error; CGAL MCF skeleton"},
    {"tune", "tune_bench", "Table 1 dermis: time against parameter error, SA against NLopt"},
    {"runtime", "runtime_bench",
     "mass-spring: integrator error against time and dt, time per step against grid (Fig. 3a), stability matrix, "
     "Bullet btSoftBody"},
    {"sph", "sph_bench", "SPH: time per step against particles (Fig. 3b), dam-break front error against resolution"},
    {"scene", "orthosim",
     "the integrated scenes on the demo model (pipeline on data-samples/phantom, 39x9): steps/s and simulated "
     "seconds per wall second of pull_skin.json and bleeding.json"},
};

std::string stage_names() {
  std::string s;
  for (const Stage& st : kStages) {
    if (!s.empty()) s += ',';
    s += st.name;
  }
  return s;
}

std::string read_text(const std::string& path) {
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::string trim(std::string s) {
  while (!s.empty() && std::isspace(static_cast<unsigned char>(s.back()))) s.pop_back();
  std::size_t i = 0;
  while (i < s.size() && std::isspace(static_cast<unsigned char>(s[i]))) ++i;
  return s.substr(i);
}

std::string first_field(const std::string& file, const std::string& key, char sep) {
  std::ifstream in(file);
  for (std::string line; std::getline(in, line);)
    if (line.rfind(key, 0) == 0) {
      const auto p = line.find(sep);
      if (p != std::string::npos) return trim(line.substr(p + 1));
    }
  return "";
}

// the 1, 5 and 15 minute load averages
std::string load_average() {
  std::istringstream in(read_text("/proc/loadavg"));
  std::string a, b, c;
  in >> a >> b >> c;
  return a + " " + b + " " + c;
}

std::string shell(const std::string& cmd) {
  std::string out;
  if (FILE* p = ::popen(cmd.c_str(), "r")) {
    char buf[256];
    while (std::fgets(buf, sizeof buf, p)) out += buf;
    ::pclose(p);
  }
  return trim(out);
}

std::string self_dir() {
  std::error_code ec;
  const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
  return ec ? std::string(".") : exe.parent_path().string();
}

json machine(const std::string& bench_dir) {
  json m;
  m["cpu"] = first_field("/proc/cpuinfo", "model name", ':');
  m["cores"] = std::thread::hardware_concurrency();
  const std::string mem = first_field("/proc/meminfo", "MemTotal", ':');
  m["memory_gib"] = mem.empty() ? json(nullptr) : json(std::round(std::stod(mem) / (1024.0 * 1024.0) * 10) / 10);
#if defined(__clang__)
  m["compiler"] = std::string("Clang ") + __clang_version__;
#elif defined(__GNUC__)
  m["compiler"] = std::string("GCC ") + __VERSION__;
#else
  m["compiler"] = "unknown";
#endif
  const std::string cache = (fs::path(bench_dir).parent_path() / "CMakeCache.txt").string();
  std::string type = first_field(cache, "CMAKE_BUILD_TYPE:", '=');
#ifdef NDEBUG
  if (type.empty()) type = "unknown (NDEBUG)";
#else
  if (type.empty()) type = "unknown (assertions on)";
#endif
  m["build_type"] = type;
  std::string source = first_field(cache, "CMAKE_HOME_DIRECTORY:", '=');
  if (source.empty()) source = fs::path(self_dir()).parent_path().parent_path().string();
  std::string commit = shell("git -C '" + source + "' rev-parse --short=12 HEAD 2>/dev/null");
  if (!commit.empty() && !shell("git -C '" + source + "' status --porcelain --untracked-files=no 2>/dev/null").empty())
    commit += " (with uncommitted changes)";
  m["commit"] = commit.empty() ? json(nullptr) : json(commit);
  m["version"] = ORTHOSIM_VERSION;
  m["load_average_before"] = load_average();
  char date[32];
  const std::time_t t = std::time(nullptr);
  std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&t));
  m["date"] = date;
  return m;
}

// Runs argv with stdout and stderr to `log`; kills it after `limit_s`.
// Returns the exit status, -1 for a timeout, -2 when it could not start.
int run_program(const std::vector<std::string>& argv, const std::string& log, double limit_s, double* seconds) {
  const auto t0 = std::chrono::steady_clock::now();
  const pid_t pid = ::fork();
  if (pid < 0) return -2;
  if (pid == 0) {
    sigset_t none;  // (this process blocks the interrupts but in its signal thread, tools/main.cpp)
    sigemptyset(&none);
    ::sigprocmask(SIG_SETMASK, &none, nullptr);
    ::setpgid(0, 0);
    const int fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd >= 0) ::dup2(fd, 1), ::dup2(fd, 2), ::close(fd);
    std::vector<char*> args;
    for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);
    ::execv(args[0], args.data());
    ::_exit(127);
  }
  int status = 0;
  bool timed_out = false;
  for (;;) {
    const pid_t r = ::waitpid(pid, &status, WNOHANG);
    if (r == pid) break;
    *seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (!timed_out && *seconds > limit_s) {
      ::kill(-pid, SIGKILL);
      timed_out = true;
    }
    ::usleep(20000);
  }
  *seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (timed_out) return -1;
  if (WIFEXITED(status)) return WEXITSTATUS(status);
  return 128 + (WIFSIGNALED(status) ? WTERMSIG(status) : 0);
}

json row_template(const std::string& stage) {
  json r;
  for (const char* c : {"workload", "setting", "error_metric", "error_value", "goal", "goal_met", "peer", "peer_time_median_s",
                        "peer_time_min_s", "peer_time_max_s", "peer_error_value", "ratio", "x", "time_median_s",
                        "time_min_s", "time_max_s"})
    r[c] = nullptr;
  r["stage"] = stage;
  r["repeats"] = 0;
  r["extra"] = json::object();
  return r;
}

void set_times(json& r, std::vector<double> s) {
  std::sort(s.begin(), s.end());
  r["repeats"] = s.size();
  if (s.empty()) return;
  const std::size_t n = s.size();
  r["time_median_s"] = n % 2 ? s[n / 2] : 0.5 * (s[n / 2 - 1] + s[n / 2]);
  r["time_min_s"] = s.front();
  r["time_max_s"] = s.back();
}

// The "scene" stage, run by this executable: builds the demo model with
// `orthosim pipeline` (timed: the cold pipeline), then runs the sample scenes
// with --no-output for a fixed number of steps (quick: 30 and 20 steps; full:
// 120 and 150, the pull scene 3 times). Error = failed steps + non-finite
// particles (goal 0). Returns {"rows", "notes"}; throws std::runtime_error
// with the failing command.
json run_scene(const std::string& source, const std::string& scratch, const std::string& log_dir, bool quick, double limit) {
  json part = {{"rows", json::array()}, {"notes", json::array()}};
  const std::string exe = (fs::path(self_dir()) / "orthosim").string();
  const std::string sample = source + "/data-samples/phantom";
  if (!fs::exists(sample + "/slices")) throw std::runtime_error(sample + "/slices not found");
  const std::string model = scratch + "/model.h5";
  auto run = [&](const std::vector<std::string>& argv, const std::string& log) {
    double s = 0;
    const int rc = run_program(argv, log_dir + "/" + log, limit, &s);
    if (rc != 0) throw std::runtime_error(argv[1] + " failed (exit " + std::to_string(rc) + ", see logs/" + log + ")");
    return s;
  };
  json row = row_template("scene");
  row["workload"] = "orthosim pipeline on data-samples/phantom (cold, 39x9): the demo model";
  row["setting"] = "cold";
  const std::string pipeline_report = scratch + "/pipeline.json";
  set_times(row, {run({exe, "pipeline", "--stack", sample + "/slices", "--tissues", sample + "/tissues.json", "--spacing",
                       "0.45,0.45,1.5", "--grid", "39x9", "--work", scratch + "/work", "--out", model, "--report",
                       pipeline_report, "--quiet"},
                      "scene_pipeline.txt")});
  part["rows"].push_back(row);
  struct Scene {
    const char* file;
    int steps, repeats;
  };
  const std::vector<Scene> scenes = {{"pull_skin.json", quick ? 30 : 120, quick ? 1 : 3},
                                     {"bleeding.json", quick ? 20 : 150, 1}};
  for (const Scene& sc : scenes) {
    const std::string file = source + "/data-samples/scenes/" + sc.file;
    if (!fs::exists(file)) {
      part["notes"].push_back(file + " not found: scene skipped");
      continue;
    }
    json r = row_template("scene");
    r["workload"] = std::string("integrated scene ") + sc.file + " on the demo model, no output";
    r["setting"] = std::to_string(sc.steps) + " steps";
    std::vector<double> step_s;
    json met;
    for (int k = 0; k < sc.repeats; ++k) {
      const std::string report = scratch + "/run.json";
      run({exe, "run", file, "--model", model, "--steps", std::to_string(sc.steps), "--no-output", "--report", report,
           "--quiet"},
          std::string("scene_") + sc.file + ".txt");
      met = json::parse(read_text(report))["metrics"];
      step_s.push_back(met.value("wall_s", 0.0) > 0 ? met["step_wall_s"].get<double>() : 0.0);
    }
    set_times(r, step_s);
    const json stab = met.value("stability", json::object());
    double bad = stab.value("failed_steps", 0.0) + stab.value("nonfinite", 0.0);
    if (met.contains("fluid")) bad += met["fluid"].value("particles_nonfinite", 0.0);
    r["error_metric"] = "failed steps + non-finite values";
    r["error_value"] = bad;
    r["goal"] = "<= 0";
    r["goal_met"] = bad <= 0;
    r["x"] = met.value("nodes", 0.0);
    const double median = r["time_median_s"].is_null() ? 0.0 : r["time_median_s"].get<double>();
    r["extra"] = {{"steps_per_s", median > 0 ? sc.steps / median : 0.0},
                  {"simulated_s_per_wall_s", median > 0 ? met.value("simulated_s", 0.0) / median : 0.0},
                  {"nodes", met.value("nodes", 0)}, {"springs", met.value("springs", 0)},
                  {"substeps_per_step", met.value("substeps_per_step", 0.0)}};
    if (met.contains("fluid")) {
      r["extra"]["particles_emitted"] = met["fluid"].value("particles_emitted", 0);
      r["extra"]["particles_drained"] = met["fluid"].value("particles_drained", 0);
      r["extra"]["fluid_wall_s"] = met["fluid"].value("wall_s", 0.0);
    }
    part["rows"].push_back(r);
  }
  return part;
}

const char* kColumns[] = {"stage",      "workload",   "setting",        "repeats",         "time_median_s",
                          "time_min_s", "time_max_s", "error_metric",   "error_value",     "goal",
                          "goal_met",   "peer",       "peer_time_median_s", "peer_time_min_s", "peer_time_max_s",
                          "peer_error_value", "ratio", "x",             "extra"};

std::string csv_field(const json& v) {
  std::string s;
  if (v.is_null()) return "";
  if (v.is_string()) s = v.get<std::string>();
  else if (v.is_number_float()) {
    std::ostringstream o;
    o << std::setprecision(9) << v.get<double>();
    s = o.str();
  } else s = v.dump();
  if (s.find_first_of(",\"\n") == std::string::npos) return s;
  std::string q = "\"";
  for (char c : s) q += c == '"' ? std::string("\"\"") : std::string(1, c);
  return q + "\"";
}

std::string to_csv(const json& rows) {
  std::ostringstream o;
  for (std::size_t i = 0; i < std::size(kColumns); ++i) o << (i ? "," : "") << kColumns[i];
  o << "\n";
  for (const json& r : rows) {
    for (std::size_t i = 0; i < std::size(kColumns); ++i) o << (i ? "," : "") << csv_field(r.value(kColumns[i], json()));
    o << "\n";
  }
  return o.str();
}

std::string fmt(const json& v, const char* f = "%.4g") {
  if (v.is_null()) return "";
  if (v.is_boolean()) return v.get<bool>() ? "yes" : "**no**";
  if (v.is_number()) {
    char b[64];
    std::snprintf(b, sizeof b, f, v.get<double>());
    return b;
  }
  if (v.is_string()) return v.get<std::string>();
  return v.dump();
}

std::string time_cell(json r, const char* med, const char* mn, const char* mx) {  // (a copy: [] of a missing key)
  if (r.value(med, json()).is_null()) return "";
  const double m = r[med].get<double>();
  const char* unit = m < 1e-3 ? "us" : m < 1 ? "ms" : "s";
  const double k = m < 1e-3 ? 1e6 : m < 1 ? 1e3 : 1;
  char b[96];
  if (!r.value(mn, json()).is_null() && r.value("repeats", 0) > 1)
    std::snprintf(b, sizeof b, "%.3g %s (%.3g-%.3g)", m * k, unit, r[mn].get<double>() * k, r[mx].get<double>() * k);
  else std::snprintf(b, sizeof b, "%.3g %s", m * k, unit);
  return b;
}

// a few figures of `extra` worth a glance (rates, sizes)
std::string highlights(const json& extra) {
  static const std::vector<std::pair<const char*, const char*>> keys = {
      {"voxels_per_s", "voxels/s"}, {"steps_per_s", "steps/s"}, {"sim_s_per_wall_s", "sim s / wall s"},
      {"simulated_s_per_wall_s", "sim s / wall s"}, {"nodes", "nodes"}, {"particles", "particles"},
      {"particles_end", "particles"}, {"faces", "faces"}, {"peer_faces", "peer faces"}, {"evaluations", "evaluations"},
      {"peer_evaluations", "peer evaluations"}, {"stable", "stable"}, {"recovered", "recovered"}, {"failed", "failed"}};
  std::string out;
  if (!extra.is_object()) return out;
  for (const auto& [k, label] : keys)
    if (extra.contains(k) && extra[k].is_number()) out += (out.empty() ? "" : ", ") + fmt(extra[k]) + " " + label;
  return out;
}

// A copy, and no const: operator[] of a const json on a missing key is
// undefined (a results.json without "memory_gib" crashed --render); on a
// mutable one it is null, which fmt() writes as an empty cell.
std::string summary(json j) {
  std::ostringstream o;
  json& m = j["machine"];
  o << "# orthosim bench" << (j["quick"].get<bool>() ? " --quick" : "") << "\n\n"
    << "Machine: " << fmt(m["cpu"]) << ", " << fmt(m["cores"]) << " cores, " << fmt(m["memory_gib"]) << " GiB; "
    << fmt(m["compiler"]) << ", " << fmt(m["build_type"]) << "; commit " << fmt(m["commit"]) << "; " << fmt(m["date"])
    << "; load average before / after: " << fmt(m["load_average_before"]) << " / " << fmt(m["load_average_after"])
    << ". Total " << fmt(j["seconds"], "%.0f") << " s.\n\n"
    << "Times: median of the repeats (min-max in brackets). Ratio: peer median / ours, timed in alternation in the "
       "same run (> 1: ours faster). Goal: the accuracy goal of the error metric.\n\n";
  json& g = j["goals"];
  o << "Accuracy goals met: " << g["met"].get<int>() << " of " << g["checked"].get<int>() << ".\n\n";
  for (json& st : j["stages"]) {
    const std::string name = st["stage"];
    o << "## " << name << "\n\n" << fmt(st["what"]) << " (`" << fmt(st["program"]) << "`, " << fmt(st["status"]);
    if (!st["seconds"].is_null()) o << ", " << fmt(st["seconds"], "%.1f") << " s";
    o << ")\n\n";
    if (!st["note"].is_null()) o << "Note: " << fmt(st["note"]) << "\n\n";
    // one table per workload, in the order the workloads first appear (a
    // program may interleave them, e.g. Fig. 3(a)'s two integrators per grid)
    std::vector<std::string> workloads;
    for (json& r : j["rows"])
      if (r["stage"] == name && std::find(workloads.begin(), workloads.end(), r["workload"]) == workloads.end())
        workloads.push_back(r["workload"]);
    const bool any = !workloads.empty();
    for (std::size_t w = 0; w < workloads.size(); ++w) {
      o << (w ? "\n" : "") << "**" << workloads[w] << "**\n\n"
        << "| setting | time | error metric | value | goal | met | peer | peer time | peer error | ratio | also |\n"
        << "|---|---|---|---|---|---|---|---|---|---|---|\n";
      for (json& r : j["rows"]) {
        if (r["stage"] != name || r["workload"] != workloads[w]) continue;
        o << "| " << fmt(r["setting"]) << " | " << time_cell(r, "time_median_s", "time_min_s", "time_max_s") << " | "
          << fmt(r["error_metric"]) << " | " << fmt(r["error_value"]) << " | " << fmt(r["goal"]) << " | "
          << fmt(r["goal_met"]) << " | " << fmt(r["peer"]) << " | "
          << time_cell(r, "peer_time_median_s", "peer_time_min_s", "peer_time_max_s") << " | " << fmt(r["peer_error_value"])
          << " | " << (r["ratio"].is_null() ? "" : fmt(r["ratio"], "%.2fx")) << " | " << highlights(r["extra"]) << " |\n";
      }
    }
    if (any) o << "\n";
    for (const json& n : st.value("notes", json::array())) o << "- " << n.get<std::string>() << "\n";
    if (!st.value("notes", json::array()).empty()) o << "\n";
  }
  if (!j["notes"].empty()) {
    o << "## Notes\n\n";
    for (const json& n : j["notes"]) o << "- " << n.get<std::string>() << "\n";
  }
  return o.str();
}

}  // namespace

void add_bench_command(CLI::App& app) {
  auto* sub = app.add_subcommand(
      "bench", "run every stage's benchmark (tests/bench) and write results.json, results.csv, summary.md and plots");
  struct Args {
    bool quick = false;
    std::string only;
    std::string out = "out/bench";
    std::string bench_dir;
    std::string plot_script;
    bool no_plots = false;
    double limit_s = 0;
    std::string render;
    CommonOptions common;
  };
  static Args a;
  sub->add_flag("--quick", a.quick, "small workloads, fewer repeats: a smoke test of every workload and accuracy goal");
  sub->add_option("--only", a.only, "comma-separated stages to run (" + stage_names() + ")");
  sub->add_option("--out", a.out, "output directory")->capture_default_str();
  sub->add_option("--bench-dir", a.bench_dir, "where the bench programs are (default: the build's tests/ folder)");
  sub->add_option("--plot-script", a.plot_script, "plot script (default: scripts/plot_bench.py of the source tree)");
  sub->add_flag("--no-plots", a.no_plots, "do not call the plot script");
  sub->add_option("--limit", a.limit_s, "seconds allowed per program (default 300 with --quick, 1200 without)");
  sub->add_option("--render", a.render,
                  "run nothing: write results.csv and summary.md into --out from an earlier run's results.json "
                  "(plots: scripts/plot_bench.py RESULTS.json DIR)");
  add_common_options(sub, a.common);

  // like on_run, but a run with a failed program or a missed goal exits 1
  static bool bench_failed = false;
  sub->callback([sub] {
    bench_failed = false;
    const int rc = guarded("bench", [sub] {
    check_common_options(a.common);
    // (--render prev.json --report prev.json replaced the results it rendered, exit 0)
    check_operands(sub, a.common.report);
    Report report("bench");
    if (!a.render.empty()) {
      json j;
      try {
        j = json::parse(read_text(a.render));
        if (!j.contains("rows") || !j.contains("stages") || !j.contains("goals") || !j.contains("machine"))
          throw Error(a.render, "not the results.json of an orthosim bench run");
      } catch (const json::exception& e) {
        throw Error(a.render, std::string("invalid JSON: ") + e.what());
      }
      // rendered before anything is written: a file with the keys but not
      // their contents was an "internal error" (a JSON type error)
      std::string csv, md;
      try {
        csv = to_csv(j["rows"]);
        md = summary(j);
      } catch (const json::exception& e) {
        throw Error(a.render, std::string("not the results.json of an orthosim bench run: ") + e.what());
      }
      AtomicDir out(a.out);
      write_text_file(out.temp_path("results.json"), j.dump(1) + "\n");
      write_text_file(out.temp_path("results.csv"), csv);
      write_text_file(out.temp_path("summary.md"), md);
      out.commit();
      report.input(a.render);
      report.parameters() = {{"render", a.render}};
      report.output(a.out);
      report.write(a.common.report);
      return;
    }
    std::vector<const Stage*> stages;
    if (a.only.empty()) {
      for (const Stage& s : kStages) stages.push_back(&s);
    } else {
      std::stringstream ss(a.only);
      for (std::string name; std::getline(ss, name, ',');) {
        name = trim(name);
        if (name.empty()) continue;
        const Stage* found = nullptr;
        for (const Stage& s : kStages)
          if (name == s.name) found = &s;
        if (!found) throw UsageError("--only: unknown stage '" + name + "' (stages: " + stage_names() + ")");
        if (std::find(stages.begin(), stages.end(), found) == stages.end()) stages.push_back(found);
      }
      if (stages.empty()) throw UsageError("--only: no stage given (stages: " + stage_names() + ")");
    }
    std::string bench_dir = a.bench_dir;
    if (bench_dir.empty()) bench_dir = (fs::path(self_dir()).parent_path() / "tests").string();
    if (!fs::is_directory(bench_dir)) throw Error(bench_dir, "bench directory not found (build with ORTHOSIM_BUILD_BENCH or give --bench-dir)");
    if (a.limit_s < 0) throw UsageError("--limit: must be positive");
    const double limit = a.limit_s > 0 ? a.limit_s : a.quick ? 300 : 1200;

    AtomicDir out(a.out);
    fs::create_directories(out.temp_path("logs"));
    const auto t0 = std::chrono::steady_clock::now();
    json j;
    j["command"] = command_line();
    j["quick"] = a.quick;
    j["machine"] = machine(bench_dir);
    j["stages"] = json::array();
    j["rows"] = json::array();
    j["notes"] = json::array();
    bool failed = false;
    for (const Stage* s : stages) {
      json st = {{"stage", s->name}, {"program", s->program}, {"what", s->what}, {"seconds", nullptr}, {"note", nullptr},
                 {"notes", json::array()}};
      if (std::string(s->name) == "scene") {
        std::string source = first_field((fs::path(bench_dir).parent_path() / "CMakeCache.txt").string(), "CMAKE_HOME_DIRECTORY:", '=');
        if (source.empty()) source = fs::path(self_dir()).parent_path().parent_path().string();
        if (!a.common.quiet) std::cout << "bench: scene (orthosim pipeline, orthosim run) ..." << std::flush;
        const auto ts = std::chrono::steady_clock::now();
        const std::string scratch = out.temp_path(".scene");
        try {
          fs::create_directories(scratch);
          const json part = run_scene(source, scratch, out.temp_path("logs"), a.quick, limit);
          for (const json& r : part["rows"]) j["rows"].push_back(r);
          st["notes"] = part["notes"];
          st["status"] = "ok";
        } catch (const std::exception& e) {
          failed = true;
          st["status"] = "failed";
          st["note"] = e.what();
          j["notes"].push_back(std::string("scene: ") + e.what());
        }
        std::error_code ec;
        fs::remove_all(scratch, ec);
        st["seconds"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - ts).count();
        if (!a.common.quiet) {
          std::cout << " " << st["status"].get<std::string>() << " in " << std::fixed << std::setprecision(1)
                    << st["seconds"].get<double>() << " s\n";
          if (!st["note"].is_null()) std::cout << "bench: scene: " << st["note"].get<std::string>() << "\n";
        }
        j["stages"].push_back(st);
        continue;
      }
      const std::string exe = (fs::path(bench_dir) / s->program).string();
      if (::access(exe.c_str(), X_OK) != 0) {
        st["status"] = "skipped";
        st["note"] = std::string(s->program) + " is not built (" + exe + "): stage skipped";
        j["notes"].push_back(std::string(s->name) + ": " + st["note"].get<std::string>());
        if (!a.common.quiet) std::cout << "bench: " << s->name << ": " << st["note"].get<std::string>() << "\n";
        j["stages"].push_back(st);
        continue;
      }
      const std::string rows_file = out.temp_path(std::string(".") + s->name + ".json");
      const std::string log = out.temp_path(std::string("logs/") + s->name + ".txt");
      std::vector<std::string> argv = {exe, "--results=" + rows_file};
      if (a.quick) argv.push_back("--quick");
      if (!a.common.quiet) std::cout << "bench: " << s->name << " (" << s->program << (a.quick ? " --quick" : "") << ") ..." << std::flush;
      double seconds = 0;
      const int rc = run_program(argv, log, limit, &seconds);
      st["seconds"] = seconds;
      json part;
      if (fs::exists(rows_file)) {
        try {
          part = json::parse(read_text(rows_file));
        } catch (const json::exception& e) {
          st["note"] = std::string("unreadable results: ") + e.what();
        }
        fs::remove(rows_file);
      }
      if (rc == 0 && part.is_object()) {
        st["status"] = "ok";
        for (const json& r : part["rows"]) j["rows"].push_back(r);
        st["notes"] = part.value("notes", json::array());
      } else {
        failed = true;
        st["status"] = "failed";
        std::string why = rc == -1 ? "killed after " + std::to_string(static_cast<int>(limit)) + " s"
                          : rc == -2 ? std::string("could not start")
                          : rc == 0  ? std::string("no results written")
                                     : "exit status " + std::to_string(rc);
        st["note"] = std::string(s->program) + " failed: " + why + " (see logs/" + s->name + ".txt)";
        j["notes"].push_back(std::string(s->name) + ": " + st["note"].get<std::string>());
        if (part.is_object())
          for (const json& r : part["rows"]) j["rows"].push_back(r);
      }
      if (!a.common.quiet) {
        std::cout << " " << st["status"].get<std::string>() << " in " << std::fixed << std::setprecision(1) << seconds << " s\n";
        if (!st["note"].is_null()) std::cout << "bench: " << s->name << ": " << st["note"].get<std::string>() << "\n";
      }
      j["stages"].push_back(st);
    }
    int checked = 0, met = 0;
    for (const json& r : j["rows"]) {
      if (r.value("goal_met", json()).is_null()) continue;
      ++checked;
      if (r["goal_met"].get<bool>()) ++met;
      else if (!a.common.quiet)
        std::cout << "bench: goal missed: " << r["stage"].get<std::string>() << " / " << r["workload"].get<std::string>()
                  << " / " << r["setting"].get<std::string>() << ": " << r["error_metric"].get<std::string>() << " = "
                  << fmt(r["error_value"]) << ", goal " << r["goal"].get<std::string>() << "\n";
    }
    j["goals"] = {{"checked", checked}, {"met", met}};
    j["machine"]["load_average_after"] = load_average();
    j["seconds"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

    write_text_file(out.temp_path("results.json"), j.dump(1) + "\n");
    write_text_file(out.temp_path("results.csv"), to_csv(j["rows"]));

    // plots: optional, never fatal
    if (!a.no_plots) {
      std::string script = a.plot_script;
      if (script.empty()) {
        std::string source = first_field((fs::path(bench_dir).parent_path() / "CMakeCache.txt").string(), "CMAKE_HOME_DIRECTORY:", '=');
        script = (fs::path(source) / "scripts" / "plot_bench.py").string();
      }
      std::string note;
      if (!fs::exists(script)) note = "plots: " + script + " not found";
      else if (::access("/usr/bin/python3", X_OK) != 0) note = "plots: /usr/bin/python3 not found";
      else {
        double s = 0;
        const int rc = run_program({"/usr/bin/python3", script, out.temp_path("results.json"), out.temp()},
                                   out.temp_path("logs/plots.txt"), 300, &s);
        if (rc != 0) note = "plots: " + script + " failed (exit " + std::to_string(rc) + ", see logs/plots.txt)";
      }
      if (!note.empty()) j["notes"].push_back(note);
    }
    write_text_file(out.temp_path("results.json"), j.dump(1) + "\n");
    write_text_file(out.temp_path("summary.md"), summary(j));
    out.commit();

    const bool goals_ok = met == checked;
    if (!a.common.quiet)
      std::cout << "bench: " << j["rows"].size() << " rows, accuracy goals met " << met << "/" << checked << ", "
                << std::fixed << std::setprecision(0) << j["seconds"].get<double>() << " s; wrote " << a.out
                << "/{results.json,results.csv,summary.md}\n";
    bench_failed = failed || !goals_ok;
    // --report: the run's summary (results.json in --out has everything)
    report.parameters() = {{"quick", a.quick}, {"only", a.only}, {"limit_s", limit}};
    report.output(a.out);
    report.metrics() = {{"rows", j["rows"].size()}, {"goals", j["goals"]}, {"programs_failed", failed}};
    report.write(a.common.report);
    });
    exit_code() = rc != 0 ? rc : bench_failed ? 1 : 0;
  });
}

}  // namespace orthosim::cli
