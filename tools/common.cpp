#include "tools/common.h"

#include "libmodel/format/atomic.h"
#include "libmodel/format/model.h"
#include "libmodel/provenance.h"
#include "libmodel/segment/segment.h"

#include <charconv>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <map>
#include <sstream>

namespace orthosim::cli {

std::string& command_line() {
  static std::string line;
  return line;
}

int& exit_code() {
  static int code = 0;
  return code;
}

std::string& last_error() {
  static std::string message;
  return message;
}

void add_common_options(CLI::App* sub, CommonOptions& o) {
  sub->add_option("--report", o.report, "write a JSON summary (inputs, parameters, timings, metrics)");
  sub->add_flag("--quiet,-q", o.quiet, "no progress or summary on stderr/stdout");
}

void check_common_options(const CommonOptions& o) {
  if (!o.report.empty()) check_output_file(o.report);
}

namespace {

// The --report of the command running now ("" when none): Report::input
// refuses to record it as an input (a scene's "model" key can name it).
std::string& current_report() {
  static std::string path;
  return path;
}

// Whether two paths name one file: the same inode where both exist, else
// the same normalised absolute path.
bool same_file(const std::string& a, const std::string& b) {
  namespace fs = std::filesystem;
  std::error_code e1, e2;
  if (fs::exists(a, e1) && fs::exists(b, e2)) return fs::equivalent(a, b, e1);
  const fs::path ca = fs::weakly_canonical(a, e1), cb = fs::weakly_canonical(b, e2);
  return !e1 && !e2 && ca == cb;
}

// --report naming a file the command reads or writes would replace it with
// the report (a model overwritten by a 2 KB JSON): refused before any work.
void check_report_is_not_an_operand(const CLI::App* sub, const std::string& report) {
  if (report.empty()) return;
  for (const CLI::Option* opt : sub->get_options()) {
    if (opt->get_name() == "--report" || opt->count() == 0) continue;
    for (const std::string& v : opt->results()) {
      if (v.empty() || !same_file(v, report)) continue;
      const std::string name = opt->get_name().empty() || opt->get_name()[0] != '-' ? "the argument " + v
                                                                                     : opt->get_name() + " " + v;
      throw Error(report, "--report names the same file as " + name + ": the report would replace it");
    }
  }
}

}  // namespace

std::filesystem::path path_within(const std::string& path, const std::string& folder) {
  namespace fs = std::filesystem;
  std::error_code e1, e2;
  const fs::path p = fs::weakly_canonical(path, e1), dir = fs::weakly_canonical(folder, e2);
  if (e1 || e2) return {};
  const fs::path rel = p.lexically_relative(dir);
  return rel.empty() || *rel.begin() == ".." ? fs::path() : rel;
}

namespace {

// An output option naming an input (or another output) would replace it:
// `segment --out tissues.json` turned the tissue table into HDF5, `--out x.h5
// --nrrd x.h5` left an NRRD where the model was, `--out stack/slice_0003.png`
// replaced a slice; all exit 0. Refused before any work. (--report: above.)
void check_outputs_are_not_inputs(const CLI::App* sub) {
  static const std::vector<std::string> outputs{"--out", "--nrrd", "--export", "--plot", "--work", "--report"};
  static const std::vector<std::string> inputs{"--stack", "--tissues", "--tissue-table", "--labels", "--truth",
                                               "--surface", "--scene", "--model", "--plot-script", "--render"};
  auto given = [&](const std::vector<std::string>& names) {
    std::vector<std::pair<std::string, std::string>> v;
    for (const CLI::Option* opt : sub->get_options())
      if (opt->count() > 0 && std::find(names.begin(), names.end(), opt->get_name()) != names.end())
        for (const std::string& x : opt->results())
          if (!x.empty()) v.emplace_back(opt->get_name(), x);
    return v;
  };
  const auto outs = given(outputs), ins = given(inputs);
  namespace fs = std::filesystem;
  // A folder output's writer replaces files of its kinds in it: another output
  // there under such a name was replaced (surface --out S --report S/fat.stl,
  // tune --plot P --report P/fat.png, vessels --out V --model V/artery_tube.obj;
  // exit 0). Those names are refused; a report.json beside a run's series stays
  // allowed.
  {
    // the kinds of file each folder output writes (the command's --out, tune's
    // --plot): ".ext" a kind of name, anything else one exact name
    static const std::map<std::string, std::vector<std::string>> out_writes{
        {"surface", {".stl"}},
        {"remesh", {".obj", ".mtl", ".png", ".gltf", ".glb", ".bin"}},
        {"vessels", {".stl", ".obj"}},
        {"phantom", {".png", ".h5"}},
        {"bench", {"results.json", "results.csv", "summary.md", ".png"}}};  // (run checks its series' own names: vtk.h, is_series_file)
    auto all = outs;
    for (const auto& m : given({"--model"})) all.push_back(m);
    const auto cmd = out_writes.find(sub->get_name());
    static const std::vector<std::string> none, png{".png"};
    for (const auto& [fname, folder] : outs) {
      const std::vector<std::string>& written =
          fname == "--plot" ? png : fname == "--out" && cmd != out_writes.end() ? cmd->second : none;
      if (written.empty()) continue;
      for (const auto& [oname, o] : all) {
        if (oname == fname) continue;
        const fs::path rel = path_within(o, folder);
        if (rel.empty() || rel == ".") continue;
        std::string ext = rel.extension().string();
        for (auto& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
        if (std::find(written.begin(), written.end(), ext) != written.end())
          throw Error(o, oname + " lies in the " + fname + " folder " + folder + " under a kind of name it writes (" + ext +
                             "): one would replace the other");
        if (std::find(written.begin(), written.end(), rel.string()) != written.end())
          throw Error(o, oname + " lies in the " + fname + " folder " + folder + " under a name it writes (" + rel.string() +
                             "): one would replace the other");
      }
    }
  }
  for (std::size_t a = 0; a < outs.size(); ++a) {
    const auto& [oname, o] = outs[a];
    for (std::size_t b = a + 1; b < outs.size(); ++b)
      if (same_file(o, outs[b].second))
        throw Error(o, oname + " and " + outs[b].first + " name the same file: one would replace the other");
    for (const auto& [iname, i] : ins) {
      // (an output naming --model is the same file twice: no command takes both)
      if (same_file(o, i))
        throw Error(o, oname + " names the same file as " + iname + " " + i + ": writing it would replace the input");
      // a file written into the slice folder becomes (or replaces) a slice
      std::error_code ec;
      if (iname == "--stack" && fs::is_directory(i, ec)) {
        const fs::path rel = path_within(o, i);
        if (!rel.empty() && rel != ".")
          throw Error(o, oname + " lies in the --stack folder " + i + ": that folder holds the slices (an image written "
                             "there becomes one, or replaces one)");
      }
    }
  }
}

}  // namespace

Report::Report(std::string command) : start_(std::chrono::steady_clock::now()) {
  j_["command"] = std::move(command);
  j_["version"] = version_string();
  j_["command_line"] = command_line();
  j_["time_utc"] = now_utc();
  j_["inputs"] = nlohmann::json::object();
  j_["outputs"] = nlohmann::json::array();
  j_["parameters"] = nlohmann::json::object();
  j_["phases_s"] = nlohmann::json::object();
  j_["metrics"] = nlohmann::json::object();
}

void Report::input(const std::string& path) { input(path, ""); }
void Report::input(const std::string& path, const std::string& hash) {
  if (!current_report().empty() && same_file(path, current_report()))
    throw Error(current_report(), "--report names the input " + path + ": the report would replace it");
  j_["inputs"][path] = hash.empty() ? hash_path(path) : hash;
}
void Report::output(const std::string& path) { j_["outputs"].push_back(path); }

void Report::phase(const std::string& name, double seconds) {
  auto& p = j_["phases_s"];
  p[name] = p.contains(name) ? p[name].get<double>() + seconds : seconds;
}

void Report::write(const std::string& path) {
  j_["wall_s"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  if (!path.empty()) write_text_file(path, j_.dump(2) + "\n");
}

Phase::Phase(Report& r, std::string name)
    : r_(r), name_(std::move(name)), t0_(std::chrono::steady_clock::now()) {}
Phase::~Phase() { r_.phase(name_, seconds()); }
double Phase::seconds() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0_).count();
}

Progress::Progress(std::string label, long total, bool quiet)
    : label_(std::move(label)), total_(total), enabled_(!quiet && ::isatty(2)),
      t0_(std::chrono::steady_clock::now()) {}

Progress::~Progress() {
  if (shown_) std::cerr << "\r\033[K" << std::flush;
}

void Progress::update(long done) {
  if (!enabled_ || total_ <= 0) return;
  double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0_).count();
  if (t < 1.0) return;
  shown_ = true;
  int width = 30;
  int fill = static_cast<int>(width * std::min(1.0, static_cast<double>(done) / total_));
  std::cerr << "\r" << label_ << " [" << std::string(fill, '#') << std::string(width - fill, ' ') << "] "
            << done << "/" << total_ << std::flush;
}

int guarded(const std::string& command, const std::function<void()>& body) {
  auto print = [&](const char* kind, const std::string& message) {
    last_error() = message;
    std::cerr << "orthosim " << command << ": " << kind << ": " << message << "\n";
  };
  try {
    body();
    return 0;
  } catch (const UsageError& e) {
    print("error", e.what());
    return 2;
  } catch (const Error& e) {
    print("error", e.what());
    return 2;
  } catch (const std::bad_alloc&) {
    print("error", "out of memory");
    return 1;
  } catch (const std::exception& e) {
    print("internal error", e.what());
    return 1;
  }
}

void check_operands(const CLI::App* sub, const std::string& report) {
  check_report_is_not_an_operand(sub, report);
  check_outputs_are_not_inputs(sub);
}

void on_run(CLI::App* sub, const std::string& command, const CommonOptions& common, std::function<void()> body) {
  sub->callback([sub, command, &common, body = std::move(body)] {
    exit_code() = 0;  // the body may set a code of its own (run: 3, steps failed)
    // the pipeline runs its stages in this process: each restores the outer one's
    struct Current {
      std::string saved = current_report();
      ~Current() { current_report() = saved; }
    } current;
    const int code = guarded(command, [&] {
      check_common_options(common);  // before any work: a run never ends on an unwritable report
      check_operands(sub, common.report);
      current_report() = common.report;
      body();
    });
    if (code != 0) exit_code() = code;
  });
}

CLI::Validator seed_check() {
  return CLI::Validator(
      [](std::string& v) -> std::string {
        const bool digits = !v.empty() && v.find_first_not_of("0123456789") == std::string::npos;
        if (digits && (v.size() < 20 || (v.size() == 20 && v <= "18446744073709551615"))) return "";
        return "a seed is an integer in 0..18446744073709551615, got '" + v + "'";
      },
      "UINT64");
}

std::vector<int> parse_ints(const std::string& text, int n, const std::string& flag, int min_value) {
  const std::vector<double> v = parse_list(text, n, flag, false);
  std::vector<int> out;
  for (double x : v) {
    if (x != std::floor(x) || x < min_value || x > 2147483647.0)
      throw UsageError(flag + ": expected " + std::to_string(n) + " whole numbers >= " + std::to_string(min_value) +
                       ", got '" + text + "'");
    out.push_back(static_cast<int>(x));
  }
  return out;
}

void parse_roi_flags(const std::string& roi, const std::string& slices, SegmentOptions& o) {
  if (!roi.empty()) {
    const std::vector<int> v = parse_ints(roi, 4, "--roi", 0);
    if (v[2] < 1 || v[3] < 1) throw UsageError("--roi: width and height must be >= 1 px, got '" + roi + "'");
    o.roi_px = {v[0], v[1], v[2], v[3]};
  }
  if (!slices.empty()) {
    const std::vector<int> v = parse_ints(slices, 2, "--slices", -1);
    if (v[0] < 0) throw UsageError("--slices: the first slice must be >= 0, got '" + slices + "'");
    if (v[1] != -1 && v[1] < v[0])
      throw UsageError("--slices: the last slice must be >= the first (or -1: to the last), got '" + slices + "'");
    o.first_slice = v[0], o.last_slice = v[1];
  }
}

UsageError flag_error(const Error& e) {
  std::string m = e.message();
  const std::size_t sp = m.find(' ');
  std::replace(m.begin(), m.begin() + static_cast<std::ptrdiff_t>(sp == std::string::npos ? 0 : sp), '_', '-');
  return UsageError("--" + m);
}

std::vector<int> parse_size(const std::string& text, int n, const std::string& flag) {
  std::vector<int> out;
  std::stringstream s(text);
  std::string part;
  while (std::getline(s, part, 'x')) {
    try {
      std::size_t used = 0;
      long v = std::stol(part, &used);
      if (used != part.size()) throw std::invalid_argument("junk");
      if (v <= 0 || v > 100000) throw UsageError(flag + ": each size must be in 1..100000, got '" + text + "'");
      out.push_back(static_cast<int>(v));
    } catch (const UsageError&) {
      throw;
    } catch (...) {
      throw UsageError(flag + ": expected sizes like " + (n == 2 ? "39x9" : "256x256x128") + ", got '" + text + "'");
    }
  }
  if (static_cast<int>(out.size()) != n)
    throw UsageError(flag + ": expected " + std::to_string(n) + " sizes separated by 'x', got '" + text + "'");
  return out;
}

std::string colour_noise_note(const nlohmann::json& separations, const std::string& tissue) {
  if (!separations.is_array()) return "";
  for (const auto& s : separations) {  // sorted: the first naming the tissue is its nearest
    const auto& t = s.at("tissues");
    if (t.at(0) != tissue && t.at(1) != tissue) continue;
    const double delta = s.at("delta").get<double>();
    if (!(delta < 1)) return "";
    std::ostringstream out;
    out.precision(2);
    out << ", and its colour is within " << delta << " standard deviations of a pixel's colour of '"
        << (t.at(0) == tissue ? t.at(1) : t.at(0)).get<std::string>()
        << "''s: colour alone cannot tell them apart in this stack (noise, or a tissue this varied; the segment "
           "report's 'separations')";
    return out.str();
  }
  return "";
}

void check_voxel_flags(const std::vector<double>& spacing_mm, const std::vector<double>& origin_mm) {
  std::array<double, 3> s{}, o{};
  for (std::size_t k = 0; k < 3; ++k) s[k] = spacing_mm.at(k) * 1e-3, o[k] = origin_mm.at(k) * 1e-3;
  const std::string why = voxel_geometry_problem(s, o);
  if (!why.empty()) throw UsageError((why.rfind("spacing", 0) == 0 ? "--spacing: " : "--origin: ") + why);
}

std::vector<double> parse_list(const std::string& text, int n, const std::string& flag, bool positive) {
  std::vector<double> out;
  std::stringstream s(text);
  std::string part;
  // decimal numbers only: std::stod took hexadecimal, and the typo 0x8 for 0.8
  // became 8 mm silently; a trailing comma was dropped (sweep of 2026-11-27)
  if (!text.empty() && text.back() == ',')
    throw UsageError(flag + ": expected " + std::to_string(n) + " numbers like 0.3,0.3,1.0, got '" + text + "'");
  while (std::getline(s, part, ',')) {
    try {
      const auto b = part.find_first_not_of(" \t"), e = part.find_last_not_of(" \t");
      if (b == std::string::npos) throw std::invalid_argument("empty");
      const char* first = part.data() + b;
      const char* last = part.data() + e + 1;
      if (*first == '+') ++first;
      double v = 0;
      const auto [ptr, ec] = std::from_chars(first, last, v, std::chars_format::general);
      if (ec != std::errc() || ptr != last) throw std::invalid_argument("junk");
      if (!std::isfinite(v)) throw std::invalid_argument("inf");
      if (positive && !(v > 0)) throw UsageError(flag + ": values must be positive, got '" + text + "'");
      out.push_back(v);
    } catch (const UsageError&) {
      throw;
    } catch (...) {
      throw UsageError(flag + ": expected " + std::to_string(n) + " numbers like 0.3,0.3,1.0, got '" + text + "'");
    }
  }
  if (static_cast<int>(out.size()) != n)
    throw UsageError(flag + ": expected " + std::to_string(n) + " comma-separated numbers, got '" + text + "'");
  return out;
}

}  // namespace orthosim::cli
