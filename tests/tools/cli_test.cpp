// The CLI conventions: --version, --help, one-line errors with exit 2,
// inspect on good and bad files, nothing written on failure.
#include "libmodel/format/model.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <filesystem>

using namespace orthosim;

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
  Surface s;
  s.vertices = MatX3d::Zero(4, 3);
  s.faces.resize(4, 3);
  s.faces << 0, 1, 2, 0, 2, 3, 0, 3, 1, 1, 3, 2;
  w.write("skin", s);
  w.write("test", make_provenance_for_test());
  w.commit();
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
