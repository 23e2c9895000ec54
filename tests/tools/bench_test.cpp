// orthosim bench (issue 10): results.json / results.csv / summary.md from a
// real stage, stand-in bench programs for the skipped, failed and goal-missed
// paths, one-line usage errors with exit 2 and nothing written.
#include "tests/test_util.h"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <sys/stat.h>

#include <filesystem>

using namespace orthosim;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

const std::vector<std::string> kColumns = {
    "stage",           "workload",        "setting",        "repeats",          "time_median_s", "time_min_s",
    "time_max_s",      "error_metric",    "error_value",    "goal",             "goal_met",      "peer",
    "peer_time_median_s", "peer_time_min_s", "peer_time_max_s", "peer_error_value", "ratio",       "x",
    "extra"};

std::string header() {
  std::string h;
  for (const auto& c : kColumns) h += (h.empty() ? "" : ",") + c;
  return h;
}

std::vector<std::string> lines(const std::string& text) {
  std::vector<std::string> v;
  std::stringstream s(text);
  for (std::string l; std::getline(s, l);) v.push_back(l);
  return v;
}

// A stand-in bench program: a shell script that writes `rows` (JSON array)
// to --results=FILE and exits with `code`.
void fake_program(const std::string& path, const std::string& rows, int code) {
  test::write_file(path, "#!/bin/sh\nfor a; do case \"$a\" in --results=*) f=\"${a#--results=}\";; esac; done\n"
                         "printf '%s\\n' '{\"stage\": \"build\", \"program\": \"msm_bench\", \"quick\": true, \"rows\": " +
                             rows + ", \"notes\": [\"stand-in\"]}' > \"$f\"\nexit " + std::to_string(code) + "\n");
  ::chmod(path.c_str(), 0755);
}

json row(double error, double goal) {
  json r;
  for (const auto& c : kColumns) r[c] = nullptr;
  r["stage"] = "build", r["workload"] = "w", r["setting"] = "s", r["repeats"] = 1, r["time_median_s"] = 0.5;
  r["error_metric"] = "e", r["error_value"] = error, r["goal"] = "<= " + std::to_string(goal);
  r["goal_met"] = error <= goal;
  r["extra"] = json::object();
  return r;
}

}  // namespace

#ifdef ORTHOSIM_HAVE_MSM_BENCH
TEST(Bench, QuickBuildStageWritesResultsCsvAndSummary) {
  test::TempDir dir("bench");
  const std::string out = dir / "out";
  const auto r = test::run_cli("bench --quick --only build --no-plots --bench-dir " ORTHOSIM_BENCH_DIR " --out " + out);
  ASSERT_EQ(r.code, 0) << r.out << r.err;
  const json j = json::parse(test::read_file(out + "/results.json"));
  for (const char* k : {"cpu", "cores", "compiler", "build_type", "commit", "date", "load_average_before"})
    EXPECT_TRUE(j["machine"].contains(k)) << k;
  EXPECT_GE(j["machine"]["cores"].get<int>(), 1);
  EXPECT_TRUE(j["quick"].get<bool>());
  ASSERT_EQ(j["stages"].size(), 1u);
  EXPECT_EQ(j["stages"][0]["stage"], "build");
  EXPECT_EQ(j["stages"][0]["status"], "ok");
  const json& rows = j["rows"];
  ASSERT_GE(rows.size(), 3u);  // 15x5, 39x9, 100x25
  std::vector<std::string> settings;
  for (const json& x : rows) {
    for (const auto& c : kColumns) EXPECT_TRUE(x.contains(c)) << c;
    EXPECT_EQ(x["stage"], "build");
    EXPECT_GE(x["repeats"].get<int>(), 1);
    EXPECT_GT(x["time_median_s"].get<double>(), 0);
    EXPECT_LE(x["time_min_s"].get<double>(), x["time_median_s"].get<double>());
    EXPECT_GE(x["time_max_s"].get<double>(), x["time_median_s"].get<double>());
    EXPECT_TRUE(x["error_metric"].is_string());
    EXPECT_TRUE(x["goal_met"].get<bool>()) << x.dump();
    EXPECT_GT(x["extra"]["nodes"].get<double>(), 0);
    settings.push_back(x["setting"]);
  }
  EXPECT_NE(std::find(settings.begin(), settings.end(), "39x9"), settings.end());
  EXPECT_EQ(j["goals"]["checked"].get<int>(), static_cast<int>(rows.size()));
  EXPECT_EQ(j["goals"]["met"].get<int>(), static_cast<int>(rows.size()));

  const auto csv = lines(test::read_file(out + "/results.csv"));
  ASSERT_EQ(csv.size(), rows.size() + 1);
  EXPECT_EQ(csv[0], header());
  EXPECT_EQ(csv[1].rfind("build,", 0), 0u) << csv[1];
  const std::string md = test::read_file(out + "/summary.md");
  EXPECT_NE(md.find("## build"), std::string::npos);
  EXPECT_NE(md.find("| 39x9 |"), std::string::npos) << md;
  EXPECT_TRUE(fs::exists(out + "/logs/build.txt"));
  // nothing but the output directory beside it (the temporary one is gone)
  int entries = 0;
  for (const auto& e : fs::directory_iterator(dir.path)) ++entries, (void)e;
  EXPECT_EQ(entries, 1);

  // --render rewrites the same summary and CSV from the results alone
  const std::string again = dir / "again";
  const auto rr = test::run_cli("bench --render " + out + "/results.json --out " + again);
  ASSERT_EQ(rr.code, 0) << rr.err;
  EXPECT_EQ(test::read_file(again + "/summary.md"), md);
  EXPECT_EQ(test::read_file(again + "/results.csv"), test::read_file(out + "/results.csv"));
  // ... and refuses a file that is not a bench run's results, writing nothing
  test::write_file(dir / "not.json", "{\"rows\": []}");
  const auto bad = test::run_cli("bench --render " + (dir / "not.json") + " --out " + (dir / "bad"));
  EXPECT_EQ(bad.code, 2);
  EXPECT_EQ(test::count_lines(bad.err), 1) << bad.err;
  EXPECT_FALSE(fs::exists(dir / "bad"));
}
#endif

TEST(Bench, UnknownStageIsOneLineExit2AndWritesNothing) {
  test::TempDir dir("bench");
  const std::string out = dir / "out";
  auto r = test::run_cli("bench --quick --only build,nosuchstage --out " + out);
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_EQ(r.err.rfind("orthosim bench: error: ", 0), 0u) << r.err;
  EXPECT_NE(r.err.find("nosuchstage"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(out));
  r = test::run_cli("bench --only build --bench-dir " + (dir / "nowhere") + " --out " + out);
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("nowhere"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(out));
  // an existing results directory is left as it was
  fs::create_directories(out);
  test::write_file(out + "/results.json", "old");
  r = test::run_cli("bench --only nosuchstage --out " + out);
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(test::read_file(out + "/results.json"), "old");
}

TEST(Bench, MissingProgramIsSkippedWithANote) {
  test::TempDir dir("bench");
  fs::create_directories(dir / "tests");
  const std::string out = dir / "out";
  const auto r = test::run_cli("bench --quick --only build,sph --no-plots --bench-dir " + (dir / "tests") + " --out " + out);
  EXPECT_EQ(r.code, 0) << r.out << r.err;
  const json j = json::parse(test::read_file(out + "/results.json"));
  ASSERT_EQ(j["stages"].size(), 2u);
  for (const json& s : j["stages"]) {
    EXPECT_EQ(s["status"], "skipped");
    EXPECT_NE(s["note"].get<std::string>().find("not built"), std::string::npos);
  }
  EXPECT_TRUE(j["rows"].empty());
  EXPECT_EQ(lines(test::read_file(out + "/results.csv")).size(), 1u);
  const std::string md = test::read_file(out + "/summary.md");
  EXPECT_NE(md.find("msm_bench is not built"), std::string::npos) << md;
  EXPECT_NE(md.find("sph_bench is not built"), std::string::npos) << md;
}

TEST(Bench, FailedProgramOrMissedGoalExits1WithTheReport) {
  test::TempDir dir("bench");
  fs::create_directories(dir / "tests");
  const std::string prog = dir / "tests/msm_bench";
  const std::string out = dir / "out";

  // the JSON texts built by appends: "[" + std::string raised GCC 12's false -Wrestrict (bug 105329)
  auto rows = [](std::initializer_list<json> rs) {
    std::string t = "[";
    for (const auto& x : rs) {
      if (t.size() > 1) t += ",";
      t += x.dump();
    }
    return t + "]";
  };
  fake_program(prog, rows({row(0.1, 1)}), 0);  // goal met
  auto r = test::run_cli("bench --quick --only build --no-plots --bench-dir " + (dir / "tests") + " --out " + out);
  EXPECT_EQ(r.code, 0) << r.out << r.err;
  json j = json::parse(test::read_file(out + "/results.json"));
  EXPECT_EQ(j["rows"].size(), 1u);
  EXPECT_EQ(j["stages"][0]["notes"][0], "stand-in");

  fake_program(prog, rows({row(0.1, 1), row(2, 1)}), 0);  // one missed
  r = test::run_cli("bench --quick --only build --no-plots --bench-dir " + (dir / "tests") + " --out " + out);
  EXPECT_EQ(r.code, 1);
  EXPECT_NE(r.out.find("goal missed"), std::string::npos) << r.out;
  j = json::parse(test::read_file(out + "/results.json"));
  EXPECT_EQ(j["goals"]["checked"].get<int>(), 2);
  EXPECT_EQ(j["goals"]["met"].get<int>(), 1);
  EXPECT_NE(test::read_file(out + "/summary.md").find("**no**"), std::string::npos);

  fake_program(prog, "[]", 3);  // crashed
  r = test::run_cli("bench --quick --only build --no-plots --bench-dir " + (dir / "tests") + " --out " + out);
  EXPECT_EQ(r.code, 1);
  j = json::parse(test::read_file(out + "/results.json"));
  EXPECT_EQ(j["stages"][0]["status"], "failed");
  EXPECT_NE(j["stages"][0]["note"].get<std::string>().find("exit status 3"), std::string::npos);
  EXPECT_NE(test::read_file(out + "/summary.md").find("failed"), std::string::npos);
}
