// Shared plumbing for the orthosim subcommands: the JSON report, phase
// timers, a progress bar and the error-to-exit-code policy.
//
// Every subcommand file defines `void add_<name>_command(CLI::App& app)`
// which registers the subcommand and its callback; the callback parses flags
// into the stage's options struct, calls the library and fills a Report.
// Exit codes: 0 success, 2 bad usage or bad input (orthosim::Error,
// UsageError), 1 internal error. Errors print one line:
//   orthosim <cmd>: error: <file>: <what is wrong>
#pragma once

#include "libmodel/format/types.h"

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <chrono>
#include <functional>
#include <string>

namespace orthosim {
struct SegmentOptions;
}

namespace orthosim::cli {

// Bad flag values: printed like Error, exit 2.
class UsageError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// A library options check's message ("damping_ratio must be in [0, 10]") as
// the command line's error: the first word's underscores made dashes and
// "--" before it ("--damping-ratio must be in [0, 10]").
UsageError flag_error(const Error& e);

// Options every subcommand has.
struct CommonOptions {
  std::string report;  // --report FILE.json
  bool quiet = false;  // --quiet
};
void add_common_options(CLI::App* sub, CommonOptions& o);
// Throws Error(report, ...) when --report names a file that cannot be written
// (its folder missing, or a folder itself). on_run calls it before the body,
// so a bad report path fails before any work and any output.
void check_common_options(const CommonOptions& o);

// The machine-readable summary written by --report: command, version,
// inputs with their hashes, parameters, per-phase wall times, metrics.
class Report {
 public:
  explicit Report(std::string command);
  void input(const std::string& path);  // records the path and its xxh3 hash (files or directories)
  // records the path with a hash made otherwise (a slice stack's: hash_stack,
  // the files read, not every file in the folder)
  void input(const std::string& path, const std::string& hash);
  void output(const std::string& path);
  nlohmann::json& parameters() { return j_["parameters"]; }
  nlohmann::json& metrics() { return j_["metrics"]; }
  void phase(const std::string& name, double seconds);
  nlohmann::json& json() { return j_; }
  // Atomically writes the report if `path` is non-empty. Adds total wall time.
  void write(const std::string& path);

 private:
  nlohmann::json j_;
  std::chrono::steady_clock::time_point start_;
};

// Times a phase into a report: `{ Phase p(report, "segment"); ... }`.
class Phase {
 public:
  Phase(Report& r, std::string name);
  ~Phase();
  double seconds() const;

 private:
  Report& r_;
  std::string name_;
  std::chrono::steady_clock::time_point t0_;
};

// A progress bar on stderr, shown only when stderr is a terminal, not quiet,
// and the work has run for more than ~1 s.
class Progress {
 public:
  Progress(std::string label, long total, bool quiet);
  ~Progress();
  void update(long done);

 private:
  std::string label_;
  long total_;
  bool enabled_;
  bool shown_ = false;
  std::chrono::steady_clock::time_point t0_;
};

// Runs a subcommand body with the exit-code policy above. Returns the code.
int guarded(const std::string& command, const std::function<void()>& body);
// The process exit code main() returns (set by on_run).
int& exit_code();
// The message of the last error guarded() printed, without its "orthosim
// <command>: error: " prefix ("" when none): the pipeline's report names a
// failed stage's error with it.
std::string& last_error();
// `path` relative to `folder` where it lies in it (both weakly canonical:
// links and ".." resolved), "." for the folder itself; empty where it lies
// outside or either cannot be resolved.
std::filesystem::path path_within(const std::string& path, const std::string& folder);

// Refuses (Error naming the file) a --report naming any operand, and an
// output option (--out, --nrrd, --export, --plot, --work) naming an input
// (--stack and files in it, --tissues, --tissue-table, --labels, --truth,
// --surface, --scene, --model) or another output. on_run calls it; a command
// with its own callback (pipeline) calls it before any work.
void check_operands(const CLI::App* sub, const std::string& report);
// Registers `body` as the subcommand's callback, run through guarded()
// after check_common_options(common):
//   on_run(sub, "phantom", a.common, [&] { ... });
// `common` must outlive the app (the subcommands keep theirs static).
void on_run(CLI::App* sub, const std::string& command, const CommonOptions& common, std::function<void()> body);

// Parses "AxBxC" (e.g. "256x256x128") into n positive integers.
std::vector<int> parse_size(const std::string& text, int n, const std::string& flag);
// Parses "a,b,c" into n finite numbers; `positive` requires each > 0.
std::vector<double> parse_list(const std::string& text, int n, const std::string& flag, bool positive);
// Parses "a,b,c" into n integers, each >= min_value (UsageError naming the flag).
std::vector<int> parse_ints(const std::string& text, int n, const std::string& flag, int min_value);
// --roi X,Y,W,H (px) and --slices FIRST,LAST (0-based, inclusive; LAST -1:
// to the last) of segment and pipeline into o's roi_px, first_slice and
// last_slice; an empty flag leaves its fields as they are (everything).
void parse_roi_flags(const std::string& roi, const std::string& slices, SegmentOptions& o);
// --spacing X,Y,Z and --origin X,Y,Z (mm) within the voxel geometry every
// stage takes (voxel_geometry_problem): UsageError naming the flag otherwise.
void check_voxel_flags(const std::vector<double>& spacing_mm, const std::vector<double>& origin_mm);
// What a segment report's "separations" (SegmentMetrics::separations) say of
// a tissue lost in segmentation: where its colour lies within one standard
// deviation of a pixel's colour of another tissue's (delta < 1: colour alone
// mixes their voxels more than 3 times in 10), ", and its colour is within
// ... of '<other>''s: colour alone cannot tell them apart ..."; else "".
std::string colour_noise_note(const nlohmann::json& separations, const std::string& tissue);

// A CLI11 check for seeds: decimal digits only, within 64 bits ("-1" wrapped to
// 2^64 - 1 and 2^64 was clamped, silently).
CLI::Validator seed_check();

// Registers every subcommand this build has on `app` (tools/main.cpp).
void register_commands(CLI::App& app);
// Runs one subcommand in this process, as `orthosim args...` would
// (`orthosim pipeline` chains the stages this way); returns its exit code.
// Parse errors print one line, like main(), and return 2.
int run_command(const std::vector<std::string>& args);

// The command line as typed, for provenance.
std::string& command_line();

}  // namespace orthosim::cli
