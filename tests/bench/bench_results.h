// Shared plumbing of the benchmark programs in tests/bench (issue 10):
// the options every program takes, timing with repeats and alternation, and
// the results rows `orthosim bench` merges into results.json / results.csv.
//
//   <prog> --results=FILE.json [--quick]
// runs the program's fixed harness workloads (small ones with --quick) and
// writes FILE.json atomically:
//   {"stage": "...", "program": "...", "quick": bool, "rows": [ROW...], "notes": ["..."]}
// ROW (every key always present; null where not measured):
//   stage, workload, setting        what ran (setting: the value swept, e.g. "39x9" or "dt=0.001")
//   repeats                         timed runs after one warm-up
//   time_median_s, time_min_s, time_max_s   wall time of one run (spread: min and max)
//   error_metric, error_value       the accuracy measure of this workload and its value
//   goal, goal_met                  "<= 0.5" / ">= 0.97" (null: informational) and whether met
//   peer, peer_time_median_s, peer_time_min_s, peer_time_max_s, peer_error_value
//   ratio                           peer median / ours median, timed in alternation in the same run
//   x                               the workload's size (nodes, particles, voxels...) for plots
//   extra                           anything else (an object)
// Without --results the programs behave as before (tables, Google Benchmark).
#pragma once

#include "libmodel/format/atomic.h"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <functional>
#include <string>
#include <vector>

namespace orthosim::bench {

// The options every bench program understands; the rest go to the program.
struct CommonArgs {
  std::string results;  // --results=FILE.json
  bool quick = false;   // --quick
  std::vector<char*> rest;
};

// Takes --results=FILE and --quick out of argv; rest keeps argv[0] and the others.
inline CommonArgs parse_common(int argc, char** argv) {
  CommonArgs a;
  for (int i = 0; i < argc; ++i) {
    if (i > 0 && std::strncmp(argv[i], "--results=", 10) == 0) a.results = argv[i] + 10;
    else if (i > 0 && std::strcmp(argv[i], "--quick") == 0) a.quick = true;
    else a.rest.push_back(argv[i]);
  }
  return a;
}

// Takes `--name=VALUE` out of rest (in place); true when found.
inline bool take_flag(std::vector<char*>& rest, const char* name, std::string* value) {
  const std::size_t n = std::strlen(name);
  for (std::size_t i = 1; i < rest.size(); ++i) {
    const char* a = rest[i];
    if (std::strncmp(a, name, n) == 0 && (a[n] == '=' || (a[n] == 0 && !value))) {
      if (value) *value = a[n] == '=' ? a + n + 1 : "";
      rest.erase(rest.begin() + static_cast<std::ptrdiff_t>(i));
      return true;
    }
  }
  return false;
}

inline double now_s() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

inline double median(std::vector<double> v) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const std::size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

// Wall seconds of `f`, run `repeats` times after `warmup` untimed runs.
inline std::vector<double> time_runs(int repeats, const std::function<void()>& f, int warmup = 1) {
  for (int i = 0; i < warmup; ++i) f();
  std::vector<double> s;
  for (int i = 0; i < repeats; ++i) {
    const double t0 = now_s();
    f();
    s.push_back(now_s() - t0);
  }
  return s;
}

// Ours and a peer timed in alternation (ours, peer, ours, peer...) after one
// warm-up of each, so both see the same machine load.
inline void time_alternating(int repeats, const std::function<void()>& ours, const std::function<void()>& peer,
                             std::vector<double>* ours_s, std::vector<double>* peer_s, int warmup = 1) {
  for (int i = 0; i < warmup; ++i) ours(), peer();
  for (int i = 0; i < repeats; ++i) {
    double t0 = now_s();
    ours();
    ours_s->push_back(now_s() - t0);
    t0 = now_s();
    peer();
    peer_s->push_back(now_s() - t0);
  }
}

// One results row (see the file comment). Fill it, then Results::add.
struct Row {
  std::string workload, setting;
  std::vector<double> seconds;  // ours, per run
  std::string error_metric;     // empty: none
  double error_value = NAN;
  std::string goal_op;  // "<=", ">=" or empty (informational)
  double goal = NAN;
  std::string peer;
  std::vector<double> peer_seconds;
  double peer_error = NAN;
  double x = NAN;
  nlohmann::json extra = nlohmann::json::object();

  Row& error(std::string metric, double value, std::string op = "", double target = NAN) {
    error_metric = std::move(metric), error_value = value, goal_op = std::move(op), goal = target;
    return *this;
  }
};

class Results {
 public:
  Results(std::string stage, std::string program, bool quick) : stage_(std::move(stage)), program_(std::move(program)), quick_(quick) {}

  void add(const Row& r) {
    using nlohmann::json;
    auto num = [](double v) { return std::isfinite(v) ? json(v) : json(nullptr); };
    json j;
    j["stage"] = stage_;
    j["workload"] = r.workload;
    j["setting"] = r.setting;
    j["repeats"] = r.seconds.size();
    j["time_median_s"] = num(median(r.seconds));
    j["time_min_s"] = r.seconds.empty() ? json(nullptr) : json(*std::min_element(r.seconds.begin(), r.seconds.end()));
    j["time_max_s"] = r.seconds.empty() ? json(nullptr) : json(*std::max_element(r.seconds.begin(), r.seconds.end()));
    j["error_metric"] = r.error_metric.empty() ? json(nullptr) : json(r.error_metric);
    j["error_value"] = num(r.error_value);
    if (r.goal_op.empty() || !std::isfinite(r.goal)) {
      j["goal"] = nullptr;
      j["goal_met"] = nullptr;
    } else {
      char g[64];
      std::snprintf(g, sizeof g, "%s %.6g", r.goal_op.c_str(), r.goal);
      j["goal"] = g;
      const bool met = std::isfinite(r.error_value) &&
                       (r.goal_op == "<=" ? r.error_value <= r.goal : r.error_value >= r.goal);
      j["goal_met"] = met;
      if (!met) ++missed_;
    }
    j["peer"] = r.peer.empty() ? json(nullptr) : json(r.peer);
    j["peer_time_median_s"] = num(median(r.peer_seconds));
    j["peer_time_min_s"] =
        r.peer_seconds.empty() ? json(nullptr) : json(*std::min_element(r.peer_seconds.begin(), r.peer_seconds.end()));
    j["peer_time_max_s"] =
        r.peer_seconds.empty() ? json(nullptr) : json(*std::max_element(r.peer_seconds.begin(), r.peer_seconds.end()));
    j["peer_error_value"] = num(r.peer_error);
    j["ratio"] = r.peer_seconds.empty() || r.seconds.empty() ? json(nullptr) : num(median(r.peer_seconds) / median(r.seconds));
    j["x"] = num(r.x);
    j["extra"] = r.extra;
    rows_.push_back(j);
    std::printf("bench row: %s / %s / %s: %.4g s", stage_.c_str(), r.workload.c_str(), r.setting.c_str(), median(r.seconds));
    if (!r.error_metric.empty()) std::printf(", %s = %.4g", r.error_metric.c_str(), r.error_value);
    if (!r.goal_op.empty()) std::printf(" (goal %s %.4g)", r.goal_op.c_str(), r.goal);
    if (!r.peer.empty()) std::printf(", %s %.4g s", r.peer.c_str(), median(r.peer_seconds));
    std::printf("\n");
    std::fflush(stdout);
  }
  void note(const std::string& text) { notes_.push_back(text); }
  int missed() const { return missed_; }

  // Writes the file atomically (`orthosim bench` reads goal_met from the rows).
  void write(const std::string& path) const {
    nlohmann::json j;
    j["stage"] = stage_;
    j["program"] = program_;
    j["quick"] = quick_;
    j["rows"] = rows_;
    j["notes"] = notes_;
    write_text_file(path, j.dump(1) + "\n");
  }

 private:
  std::string stage_, program_;
  bool quick_;
  nlohmann::json rows_ = nlohmann::json::array();
  std::vector<std::string> notes_;
  int missed_ = 0;
};

}  // namespace orthosim::bench
