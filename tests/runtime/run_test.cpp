// `orthosim run`: a scene on a generated model, the report, and bad input.
#include "runtime/testing/lattice.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>

#include <array>
#include <nlohmann/json.hpp>

#include <cstdio>
#include <cmath>
#include <filesystem>
#include <set>

namespace orthosim {
namespace {

namespace fs = std::filesystem;
using test::run_cli;

// A run that succeeds with exactly one warning line holding `text`.
void expect_one_warning(const test::RunResult& r, const std::string& text) {
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find(text), std::string::npos) << r.err;
}

// A run that succeeds without a word on stderr.
void expect_silent(const test::RunResult& r) {
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err, "");
}

struct RunCli : ::testing::Test {
  test::TempDir dir{"runcli"};
  std::string model = dir / "model.h5";
  void SetUp() override { runtime::testing::write_model_file(model, runtime::testing::make_layered_block(39, 9, 4)); }
  std::string scene(const std::string& json) {
    const std::string p = dir / "scene.json";
    test::write_file(p, json);
    return p;
  }
  // The block with its artery (written here), cut across the artery at t = 0
  // so it bleeds 500 Pa; `fluid` and `tools` add keys to those blocks.
  std::string bleeding_scene(const std::string& duration, const std::string& fluid, const std::string& tools = "") {
    runtime::testing::write_model_file(model, runtime::testing::make_layered_block(39, 9, 4), true);
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "gravity": [0, 9.81, 0], "integrator": "implicit",
      "dt": 0.005, "duration": )" + duration + R"(, "vessels": ["artery"],
      "fluid": {"spacing": 0.002, "sound_speed": 3, "bleed_pressure": 500, "margin": 0.01)" + fluid + R"(},
      "tools": [{"name": "scalpel", "type": "cut", "polyline": [[0.0, 0, 0.01], [0.03, 0, 0.01]], "depth": 0.008,
                 "direction": [0, 1, 0], "snap": false, "start": 0})" + tools + R"(]
    })");
  }
};

TEST_F(RunCli, PullsTheSkinAndReports) {
  const auto s = scene(R"({
    "model": "model.h5", "fixed": ["fixed"], "gravity": [0, -9.81, 0], "damping": {"mass": 5},
    "integrator": "symplectic", "dt": 0.01, "duration": 0.2,
    "tools": [{"name": "grasper", "type": "pull", "nodes": "skin", "center": [0.076, 0, 0.016], "radius": 0.006,
               "path": [[0, 0, 0, 0], [0.2, 0, -0.01, 0]]}],
    "output": {"dir": "series", "every": 5}
  })");
  const auto r = run_cli("run " + s + " --report " + (dir / "r.json") + " --threads 2 --quiet");
  ASSERT_EQ(r.code, 0) << r.err;
  const auto j = nlohmann::json::parse(test::read_file(dir / "r.json"));
  const auto& m = j["metrics"];
  EXPECT_EQ(m["steps"], 20);
  EXPECT_GT(m["steps_per_second"].get<double>(), 0);
  EXPECT_GT(m["simulated_seconds_per_wall_second"].get<double>(), 0);
  EXPECT_GE(m["substeps"].get<long>(), 20);
  EXPECT_EQ(m["stability"]["events"], 0);
  EXPECT_EQ(m["stability"]["failed_steps"], 0);
  EXPECT_EQ(m["nodes"], 39 * 9 * 4);
  EXPECT_EQ(m["frames"], 5);
  EXPECT_TRUE(fs::exists(dir / "series/tissue.pvd"));
  EXPECT_TRUE(fs::exists(dir / "series/tissue_000004.vtu"));

  // --steps, --no-output, implicit
  const auto s2 = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.0333})");
  const auto r2 = run_cli("run " + s2 + " --steps 7 --no-output --report " + (dir / "r2.json") + " --quiet");
  ASSERT_EQ(r2.code, 0) << r2.err;
  const auto j2 = nlohmann::json::parse(test::read_file(dir / "r2.json"));
  EXPECT_EQ(j2["metrics"]["steps"], 7);
  EXPECT_GT(j2["metrics"]["cg"]["iterations"].get<long>(), 0);
}

// A layer pressed through itself: central springs let a column's top pass
// its bottom, and the run said nothing (the demo's pull scene turns 149 of
// its skin's 351 columns inside out under gravity within 0.05 s; found
// 2026-11-27, night). A grasper pushes the skin 12 mm into the block, through
// the 2 mm dermis and the 5 mm hypodermis under it: the report counts the
// inverted columns per layer and one warning says so; the same scene pushing
// 1 mm inverts none and is silent.
TEST_F(RunCli, ALayerTurnedInsideOutIsCountedAndAWarning) {
  auto push = [&](const std::string& depth) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "damping": {"mass": 5}, "integrator": "implicit",
      "dt": 0.01, "duration": 0.3,
      "tools": [{"name": "grasper", "type": "pull", "nodes": "skin", "center": [0.076, 0, 0.016], "radius": 0.006,
                 "path": [[0, 0, 0, 0], [0.2, 0, )" + depth + R"(, 0]]}]
    })");
  };
  const auto deep = run_cli("run " + push("0.012") + " --no-output --report " + (dir / "r.json") + " --quiet");
  expect_one_warning(deep, "turned inside out");
  const auto j = nlohmann::json::parse(test::read_file(dir / "r.json"));
  const auto& inv = j["metrics"]["inverted_columns"];
  ASSERT_TRUE(inv.contains("dermis") && inv.contains("hypodermis") && inv.contains("muscle")) << inv.dump();
  EXPECT_EQ(inv["dermis"]["columns"], 39 * 9);
  std::int64_t total = 0;
  for (const auto& [layer, v] : inv.items()) total += v["max"].get<std::int64_t>();
  EXPECT_GT(total, 0) << inv.dump();
  const auto shallow = run_cli("run " + push("0.001") + " --no-output --report " + (dir / "r2.json") + " --quiet");
  expect_silent(shallow);
  const auto j2 = nlohmann::json::parse(test::read_file(dir / "r2.json"));
  for (const auto& [layer, v] : j2["metrics"]["inverted_columns"].items()) {
    EXPECT_EQ(v["max"], 0) << layer;
    EXPECT_TRUE(v["first_t_s"].is_null()) << layer;
  }
}

// A cut across the model's artery bleeds; the report counts the blood and
// says which limit set the fluid's substeps, with either pressure solver.
TEST_F(RunCli, BleedsAndReportsTheFluid) {
  runtime::testing::write_model_file(model, runtime::testing::make_layered_block(39, 9, 4), true);  // with the artery
  long eos_substeps = 0;
  long uncut_springs = 0, uncut_anchors = 0;
  {
    const auto r = run_cli("run " + scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005})") +
                           " --steps 1 --no-output --report " + (dir / "r0.json") + " --quiet");
    ASSERT_EQ(r.code, 0) << r.err;
    const auto j = nlohmann::json::parse(test::read_file(dir / "r0.json"));
    uncut_springs = j["metrics"]["springs"].get<long>();
    uncut_anchors = j["metrics"]["anchors"].get<long>();
    ASSERT_GT(uncut_springs, 0);
  }
  for (const std::string solver : {"eos", "pcisph"}) {
    SCOPED_TRACE(solver);
    const auto s = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "gravity": [0, 9.81, 0], "integrator": "implicit",
      "dt": 0.005, "duration": 0.06, "vessels": ["artery"],
      "fluid": {"spacing": 0.002, "sound_speed": 3, "bleed_pressure": 500, "margin": 0.01, "pressure_solver": ")" +
                         solver + R"("},
      "tools": [{"name": "scalpel", "type": "cut", "polyline": [[0.0, 0, 0.01], [0.03, 0, 0.01]], "depth": 0.008,
                 "direction": [0, 1, 0], "snap": false, "start": 0}]
    })");
    const auto r = run_cli("run " + s + " --report " + (dir / "r.json") + " --threads 2 --no-output --quiet");
    ASSERT_EQ(r.code, 0) << r.err;
    const auto j = nlohmann::json::parse(test::read_file(dir / "r.json"));
    const auto& f = j["metrics"]["fluid"];
    EXPECT_GE(f["bleeding_vessels"].get<int>(), 1);
    EXPECT_GT(f["particles_emitted"].get<long>(), 0);
    // the cut opened tissue columns to the blood (runtime/cut.h, WoundColumns)
    EXPECT_GT(j["metrics"]["cuts"][0]["columns_opened"].get<int>(), 0) << j["metrics"]["cuts"].dump();
    long sum = 0;
    for (const char* k : {"step", "cfl", "force", "viscous", "max_substep", "pressure"}) sum += f["substeps_set_by"][k].get<long>();
    EXPECT_EQ(sum, f["substeps"].get<long>());
    EXPECT_GE(f["substeps"].get<long>(), 12);  // at least one a step
    // the work savers' counts: a grid for the first step at least, at most one a step
    EXPECT_GE(f["surface_grid_builds"].get<long>(), 1);
    EXPECT_LE(f["surface_grid_builds"].get<long>(), 12);
    EXPECT_GT(f["contacts_reused"].get<long>(), 0) << f.dump();
    EXPECT_GE(f["neighbour_lists_kept"].get<long>(), 0);
    EXPECT_LT(f["neighbour_lists_kept"].get<long>(), f["substeps"].get<long>());  // the first substep builds
    EXPECT_EQ(f["pressure_solver"], solver);
    // where the fluid's time went: six phases, inside the fluid's wall time
    double phases = 0;
    for (const char* k : {"prepare", "density", "forces", "pressure", "integrate", "emit"}) {
      ASSERT_TRUE(f["phases_s"][k].is_number()) << k << " " << f.dump();
      EXPECT_GE(f["phases_s"][k].get<double>(), 0) << k;
      phases += f["phases_s"][k].get<double>();
    }
    EXPECT_GT(f["phases_s"]["density"].get<double>(), 0);
    EXPECT_GT(phases, 0);
    EXPECT_LE(phases, f["wall_s"].get<double>() * 1.0001) << f.dump();
    if (solver == "eos") {
      EXPECT_EQ(f["phases_s"]["pressure"].get<double>(), 0);
    }
    if (solver == "eos") {
      eos_substeps = f["substeps"].get<long>();
      EXPECT_EQ(f["pressure_iterations"].get<long>(), 0);
    } else {  // the corrections are counted (none before the cut emits), and the sound speed no longer sets the substeps
      EXPECT_GT(f["pressure_iterations"].get<long>(), 0);
      EXPECT_TRUE(f["pressure_retries"].is_number_integer() && f["pressure_unconverged"].is_number_integer()) << f.dump();
      EXPECT_LT(f["substeps"].get<long>(), eos_substeps);
    }
    EXPECT_EQ(j["metrics"]["stability"]["failed_steps"], 0);
    EXPECT_EQ(f["particles_nonfinite"].get<long>(), 0);
    // the counts of the model as the cut left it (the cut replaces the model: they were read from the freed one)
    const auto& m = j["metrics"];
    EXPECT_EQ(m["nodes"].get<long>(), 39 * 9 * 4) << m.dump();
    EXPECT_EQ(m["layers_loaded"].get<long>(), 4);
    EXPECT_EQ(m["vessels_loaded"].get<long>(), 1);
    EXPECT_EQ(m["anchors"].get<long>(), uncut_anchors);
    EXPECT_GT(m["springs"].get<long>(), 0.9 * uncut_springs);
    EXPECT_LT(m["springs"].get<long>(), uncut_springs) << "the cut removed springs";
  }
}

// What the scene asks for and the run will not do is named in a warning (it
// was silent): a tool that starts after the last step starts, a duration
// under half a step (one step is run).
TEST_F(RunCli, WhatTheRunWillNotDoIsAWarning) {
  auto with_start = [&](const std::string& start, const std::string& duration) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": )" + duration + R"(,
      "tools": [{"name": "scalpel", "type": "cut", "polyline": [[0.0, 0, 0.01], [0.03, 0, 0.01]], "depth": 0.008,
                 "direction": [0, 1, 0], "snap": false, "start": )" + start + R"(}]
    })");
  };
  // 4 steps of 5 ms: the last starts at 15 ms
  const auto late = with_start("0.02", "0.02");
  expect_one_warning(run_cli("run " + late + " --no-output --quiet --report " + (dir / "late.json")),
                     "orthosim run: warning: " + late + ": the cut tool 'scalpel' starts at t = 0.02 s, after the "
                       "run's last step starts (t = 0.015 s, 4 steps of 0.005 s): it never acts");
  const auto j = nlohmann::json::parse(test::read_file(dir / "late.json"));
  EXPECT_TRUE(j["metrics"]["cuts"].empty()) << j["metrics"]["cuts"].dump();
  // starting with the last step: it acts, no warning
  expect_silent(run_cli("run " + with_start("0.015", "0.02") + " --no-output --quiet --report " + (dir / "last.json")));
  EXPECT_EQ(nlohmann::json::parse(test::read_file(dir / "last.json"))["metrics"]["cuts"].size(), 1u);
  // --steps decides the run's length: the same check against it
  expect_silent(run_cli("run " + late + " --steps 5 --no-output --quiet"));
  // blood and a cut, but no vessel tree loaded: nothing can bleed
  const auto dry = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "fluid": {"spacing": 0.002, "sound_speed": 3, "margin": 0.01},
      "tools": [{"name": "scalpel", "type": "cut", "polyline": [[0.0, 0, 0.01], [0.03, 0, 0.01]], "depth": 0.008,
                 "direction": [0, 1, 0], "snap": false, "start": 0}]
    })");
  expect_one_warning(run_cli("run " + dry + " --no-output --quiet --report " + (dir / "dry.json")),
                     "orthosim run: warning: " + dry + ": the scene has blood and a cut 'scalpel' but loads no "
                        "vessel tree, so nothing can bleed");
  // with the fluid the surface is loaded and the cut's quads are counted; without it (and
  // without output) they are not loaded, and the count is null, not 0
  EXPECT_GT(nlohmann::json::parse(test::read_file(dir / "dry.json"))["metrics"]["cuts"][0]["quads_removed"].get<int>(), 0);
  EXPECT_TRUE(nlohmann::json::parse(test::read_file(dir / "last.json"))["metrics"]["cuts"][0]["quads_removed"].is_null());
  // a collider the blood never meets, and a plane turned away from the blood
  auto collider = [&](const std::string& c) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "fluid": {"spacing": 0.002, "sound_speed": 3, "margin": 0.01, "colliders": [)" + c + R"(]}})");
  };
  test::write_file(dir / "far.stl", "solid far\nfacet normal 0 1 0\nouter loop\nvertex 5 5 5\nvertex 5 5 6\n"
                                    "vertex 6 5 5\nendloop\nendfacet\nendsolid far\n");
  const auto far = collider(R"({"name": "tray", "type": "mesh", "stl": "far.stl"})");
  expect_one_warning(run_cli("run " + far + " --no-output --quiet"),
                     "orthosim run: warning: " + far + ": the collider 'tray' (" + (dir / "far.stl") +
                         ") lies outside the blood's domain: it never acts (its units or frame?)");
  const auto above = collider(R"({"name": "sky", "type": "plane", "point": [0, 9, 0], "normal": [0, -1, 0]})");
  expect_one_warning(run_cli("run " + above + " --no-output --quiet"),
                     "orthosim run: warning: " + above + ": the collider 'sky' (a plane) lies outside the blood's domain: "
                                                         "it never acts");
  const auto behind = collider(R"({"name": "table", "type": "plane", "point": [0, -9, 0], "normal": [0, -1, 0]})");
  expect_one_warning(run_cli("run " + behind + " --no-output --quiet"),
                     "orthosim run: warning: " + behind + ": the collider 'table' (a plane) has the blood's whole domain "
                                                          "behind it: it pushes all the blood out (its normal?)");
  expect_silent(run_cli("run " + collider(R"({"type": "plane", "point_in_box": [0.5, 0, 0.5], "normal": [0, 1, 0]})") +
                        " --no-output --quiet"));
  // tissue behind a collider at rest: a plane between the skin (y = 0) and the
  // next sheet (y = 2 mm) has the skin's 351 nodes behind it; a one-sided mesh there, the same
  const auto shelf = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "colliders": [{"name": "shelf", "type": "plane", "point": [0, 0.001, 0], "normal": [0, 1, 0]}]})");
  expect_one_warning(run_cli("run " + shelf + " --no-output --quiet"),
                     "orthosim run: warning: " + shelf + ": the collider 'shelf' (a plane) has 351 of the tissue's 1053 free "
                                                         "nodes behind it at rest: the first step puts them on it (its point or normal?)");
  test::write_file(dir / "shelf.stl", "solid shelf\nfacet normal 0 1 0\nouter loop\nvertex -10 1 -10\nvertex 200 1 200\n"
                                      "vertex 200 1 -10\nendloop\nendfacet\nfacet normal 0 1 0\nouter loop\nvertex -10 1 -10\n"
                                      "vertex -10 1 200\nvertex 200 1 200\nendloop\nendfacet\nendsolid shelf\n");  // mm
  const auto shelf_mesh = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "colliders": [{"name": "shelf", "type": "mesh", "stl": "shelf.stl", "units": "mm"}]})");
  expect_one_warning(run_cli("run " + shelf_mesh + " --no-output --quiet"),
                     "orthosim run: warning: " + shelf_mesh + ": the collider 'shelf' (" + (dir / "shelf.stl") +
                         ") has 351 of the tissue's free nodes just behind its faces at rest");
  // a mesh in millimetres read as metres lies far from the tissue (no blood: the tissue's check)
  const auto far_mesh = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "colliders": [{"name": "tray", "type": "mesh", "stl": "far.stl"}]})");
  expect_one_warning(run_cli("run " + far_mesh + " --no-output --quiet"),
                     "orthosim run: warning: " + far_mesh + ": the collider 'tray' (" + (dir / "far.stl") +
                         ") lies farther from the tissue than the tissue's own size (0.152 m): it never meets it "
                         "(its units or frame?)");
  // under the tissue: silent, and the series has the collider though the scene has no blood
  const auto floor = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "colliders": [{"name": "floor", "type": "plane", "point_in_box": [0.5, 0, 0.5], "normal": [0, 1, 0]}]})");
  expect_silent(run_cli("run " + floor + " --out " + (dir / "floor") + " --quiet --report " + (dir / "floor.json")));
  EXPECT_TRUE(std::filesystem::is_regular_file(dir / "floor/tissue_colliders.vtp"));
  {
    const auto fm = nlohmann::json::parse(test::read_file(dir / "floor.json"))["metrics"];
    EXPECT_TRUE(fm["obstacle_contacts"].is_number_integer());
    ASSERT_EQ(fm["colliders"].size(), 1u) << fm.dump();
    const auto& fc = fm["colliders"][0];
    EXPECT_EQ(fc["name"], "floor");
    ASSERT_EQ(fc["tissue_force_n"].size(), 3u) << fc.dump();
    EXPECT_GE(fc["max_tissue_force_n"].get<double>(), std::hypot(fc["tissue_force_n"][0].get<double>(), fc["tissue_force_n"][1].get<double>(),
                                                                 fc["tissue_force_n"][2].get<double>()));
  }
  EXPECT_TRUE(nlohmann::json::parse(test::read_file(dir / "dry.json"))["metrics"]["obstacle_contacts"].is_null());
  // a moving mesh narrower than the tissue's node spacing whose edges do not
  // meet the tissue's faces can pass between the nodes: a 1 mm rod pushed up
  // into the skin with "edge_spacing": 0 is a warning; by default its edges
  // meet the faces (silent, and it presses the skin), and a 20 mm plate is silent
  auto box = [&](const std::string& file, double w, double h) {  // w x h x w m, its top face at y = -0.002
    test::write_file(dir / file, test::box_stl({0.02 - w / 2, -0.002 - h, 0.008 - w / 2}, {0.02 + w / 2, -0.002, 0.008 + w / 2}));
  };
  box("rod.stl", 0.001, 0.02);
  box("plate.stl", 0.02, 0.001);
  auto pushed = [&](const std::string& stl, const std::string& more) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.05,
      "colliders": [{"name": "probe", "type": "mesh", "stl": ")" + stl + R"(", "path": [[0, 0, 0, 0], [0.05, 0, 0.003, 0]])" + more + "}]}");
  };
  const auto rod = pushed("rod.stl", R"(, "edge_spacing": 0)");
  const auto rod_run = run_cli("run " + rod + " --no-output --quiet");
  expect_one_warning(rod_run, "orthosim run: warning: " + rod + ": the moving collider 'probe' (" + (dir / "rod.stl") + ") is 0.001 m across");
  EXPECT_NE(rod_run.err.find("only nodes collide, so it can pass between them"), std::string::npos) << rod_run.err;
  expect_silent(run_cli("run " + pushed("rod.stl", "") + " --no-output --quiet --report " + (dir / "rod.json")));
  {
    // pushed 3 mm up in 0.05 s, its top 2 mm under the skin at the start: it presses the skin 1 mm
    const auto rm = nlohmann::json::parse(test::read_file(dir / "rod.json"))["metrics"];
    EXPECT_GT(rm["face_contacts"].get<long long>(), 0) << rm.dump();
    EXPECT_GT(rm["colliders"][0]["tissue_force_n"][1].get<double>(), 0) << rm.dump();
  }
  expect_silent(run_cli("run " + pushed("plate.stl", "") + " --no-output --quiet"));
  // the far mesh brought to the tissue by its path is not far: the box it sweeps meets the tissue
  const auto brought = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "colliders": [{"name": "tray", "type": "mesh", "stl": "far.stl", "path": [[0, 0, 0, 0], [10, -5, -5, -5]]}]})");
  const auto brought_run = run_cli("run " + brought + " --no-output --quiet");
  EXPECT_EQ(brought_run.err.find("lies farther from the tissue"), std::string::npos) << brought_run.err;
  // a duration under half a step
  const auto shortrun = with_start("0", "0.002");
  const auto r2 = run_cli("run " + shortrun + " --no-output --quiet");
  ASSERT_EQ(r2.code, 0) << r2.err;
  EXPECT_EQ(test::count_lines(r2.err), 1) << r2.err;
  EXPECT_NE(r2.err.find("orthosim run: warning: " + shortrun + ": duration 0.002 s is under half a step (dt = 0.005 s); "
                        "one step is run"),
            std::string::npos)
      << r2.err;
}

// PCISPH solves taken unconverged are named in a warning (the report counted
// them, the run said nothing).
TEST_F(RunCli, UnconvergedPressureSolvesAreAWarning) {
  auto bleed = [&](const std::string& extra) {
    return bleeding_scene("0.1", R"(, "pressure_solver": "pcisph")" + extra);
  };
  const auto tight = bleed(R"(, "pcisph_tolerance": 1e-3, "pcisph_max_iterations": 3, "pcisph_target_iterations": 3)");
  const auto r = run_cli("run " + tight + " --no-output --quiet --threads 2 --report " + (dir / "p.json"));
  ASSERT_EQ(r.code, 0) << r.err;
  const auto f = nlohmann::json::parse(test::read_file(dir / "p.json"))["metrics"]["fluid"];
  ASSERT_GT(f["pressure_unconverged"].get<long>(), 0) << f.dump();
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("orthosim run: warning: " + tight + ": " + std::to_string(f["pressure_unconverged"].get<long>()) +
                       " of " + std::to_string(f["pressure_solves"].get<long>()) +
                       " PCISPH pressure solves were taken unconverged"),
            std::string::npos)
      << r.err;
  // the defaults converge: no warning
  const auto ok = run_cli("run " + bleed("") + " --no-output --quiet --threads 2 --report " + (dir / "q.json"));
  ASSERT_EQ(ok.code, 0) << ok.err;
  EXPECT_EQ(nlohmann::json::parse(test::read_file(dir / "q.json"))["metrics"]["fluid"]["pressure_unconverged"], 0);
  EXPECT_EQ(ok.err, "");
}

// A fluid whose substeps hit max_substeps skips the rest of the step: counted
// in the report and one warning line (sound speed 1e5 m/s: nothing said, and
// the only warning blamed the emitter, until 2026-11-27).
TEST_F(RunCli, FluidStepsCutAtMaxSubstepsAreAWarning) {
  runtime::testing::write_model_file(model, runtime::testing::make_layered_block(39, 9, 4), true);
  const auto s = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.01, "duration": 0.02,
      "vessels": ["artery"], "fluid": {"spacing": 0.002, "sound_speed": 100000, "margin": 0.01}
    })");
  expect_one_warning(run_cli("run " + s + " --no-output --quiet --report " + (dir / "t.json")),
                     "orthosim run: warning: " + s + ": the blood reached its limit of 4096 substeps in 2 step(s)");
  const auto f = nlohmann::json::parse(test::read_file(dir / "t.json"))["metrics"]["fluid"];
  EXPECT_EQ(f["truncated_steps"].get<long>(), 2) << f.dump();
}

// Cuts that cross none of the loaded vessels are named in a warning: a
// bleeding scene on a model whose segmentation lost most of its vessels ran
// with nothing bleeding and said nothing.
TEST_F(RunCli, CutsThatMissEveryVesselAreAWarning) {
  runtime::testing::write_model_file(model, runtime::testing::make_layered_block(39, 9, 4), true);  // artery at x = 10 mm
  auto cut_from = [&](const std::string& x0, const std::string& x1) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "vessels": ["artery"], "fluid": {"spacing": 0.002, "sound_speed": 3, "margin": 0.01},
      "tools": [{"name": "scalpel", "type": "cut", "polyline": [[)" + x0 + R"(, 0, 0.01], [)" + x1 + R"(, 0, 0.01]],
                 "depth": 0.008, "direction": [0, 1, 0], "snap": false, "start": 0}]
    })");
  };
  const auto away = cut_from("0.1", "0.13");
  const auto r = run_cli("run " + away + " --no-output --quiet --report " + (dir / "away.json"));
  ASSERT_EQ(r.code, 0) << r.err;
  const auto j = nlohmann::json::parse(test::read_file(dir / "away.json"));
  ASSERT_GT(j["metrics"]["cuts"][0]["springs_cut"].get<int>(), 0) << "the cut opens the tissue";
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("orthosim run: warning: " + away + ": 1 cut(s) crossed none of the 1 loaded vessel tree(s), so "
                       "nothing bled (blade 'scalpel' along ("),
            std::string::npos)
      << r.err;
  // across the artery: it bleeds, no warning
  expect_silent(run_cli("run " + cut_from("0.0", "0.03") + " --no-output --quiet"));
}

// A cut that misses the model is named in a warning (it cut nothing, silently).
TEST_F(RunCli, ACutThatMissesTheModelIsAWarning) {
  auto cut_at = [&](const std::string& z) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "tools": [{"name": "scalpel", "type": "cut", "polyline": [[0.0, 0, )" + z + R"(], [0.03, 0, )" + z + R"(]], "depth": 0.008,
                 "direction": [0, 1, 0], "snap": false, "start": 0}]
    })");
  };
  const auto s = cut_at("0.5");  // half a metre off the block
  expect_one_warning(run_cli("run " + s + " --no-output --quiet --report " + (dir / "miss.json")),
                     "orthosim run: warning: " + s + ": the cut 'scalpel' at t = 0 s cut nothing");
  const auto j = nlohmann::json::parse(test::read_file(dir / "miss.json"));
  EXPECT_EQ(j["metrics"]["cuts"][0]["springs_cut"], 0);
  expect_silent(run_cli("run " + cut_at("0.01") + " --no-output --quiet"));
}

// A cut vessel whose flow is too small to emit one particle in the run is
// named in a warning (it bled nothing, silently); the report has the flow.
TEST_F(RunCli, ABleedingTooSmallToShowIsAWarning) {
  runtime::testing::write_model_file(model, runtime::testing::make_layered_block(39, 9, 4), true);  // with the artery
  auto bleed = [&](const std::string& pressure) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.03,
      "vessels": ["artery"], "fluid": {"spacing": 0.002, "sound_speed": 3, "bleed_pressure": )" + pressure + R"(, "margin": 0.01},
      "tools": [{"name": "scalpel", "type": "cut", "polyline": [[0.0, 0, 0.01], [0.03, 0, 0.01]], "depth": 0.008,
                 "direction": [0, 1, 0], "snap": false, "start": 0}]
    })");
  };
  const auto s = bleed("1e-6");
  const auto r = run_cli("run " + s + " --no-output --quiet --report " + (dir / "tiny.json"));
  expect_one_warning(r, "orthosim run: warning: " + s + ": ");
  EXPECT_NE(r.err.find(" cut vessel(s) bleed "), std::string::npos) << r.err;
  const auto j = nlohmann::json::parse(test::read_file(dir / "tiny.json"));
  EXPECT_EQ(j["metrics"]["fluid"]["particles_emitted"], 0);
  EXPECT_GT(j["metrics"]["fluid"]["bleeding_flow_m3_s"].get<double>(), 0);
  // a bleeding that shows: no warning
  expect_silent(run_cli("run " + bleed("500") + " --no-output --quiet"));
  // bleed_pressure 0: nothing flows, said so (it said "takes inf s of that flow")
  const auto zero = bleed("0");
  const auto z = run_cli("run " + zero + " --no-output --quiet");
  ASSERT_EQ(z.code, 0) << z.err;
  EXPECT_EQ(test::count_lines(z.err), 1) << z.err;
  EXPECT_EQ(z.err.rfind("orthosim run: warning: " + zero + ": ", 0), 0u) << z.err;
  EXPECT_NE(z.err.find(" wound(s) in the vessels, but bleed_pressure is 0: nothing flows"), std::string::npos) << z.err;
}

// A pull whose nodes are all fixed does nothing: a warning (it ran as if it
// were not there, silently).
TEST_F(RunCli, AToolOnFixedNodesIsAWarning) {
  const auto s = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "tools": [{"name": "grasper", "type": "pull", "nodes": "fixed", "center_in_box": [0.5, 0.5, 0.5], "radius": 0.001,
                 "nearest": true, "path": [[0, 0, 0, 0], [0.01, 0, 0.001, 0]]}]
    })");
  expect_one_warning(run_cli("run " + s + " --no-output --quiet"),
                     "orthosim run: warning: " + s +
                         ": the pull tool 'grasper' takes only the 1 fixed node(s) it found: it does nothing");
  // a pressure tool on fixed nodes likewise (no warning until 2026-11-27; the state was
  // bitwise that of a run without it)
  const auto p = scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "tools": [{"name": "press", "type": "pressure", "nodes": "fixed", "center_in_box": [0.5, 0.5, 0.5], "radius": 0.001,
                 "nearest": true, "pressure": 1e5, "direction": [0, 1, 0]}]
    })");
  expect_one_warning(run_cli("run " + p + " --no-output --quiet"),
                     "orthosim run: warning: " + p +
                         ": the pressure tool 'press' takes only the 1 fixed node(s) it found: it does nothing");
}

// Two tools holding the same nodes at the same time do not add up: a hook and a
// pull on one grip left it still, of two pulls only the later acted, silently
// (until 2026-11-27). Two spring pulls add their forces: no warning.
TEST_F(RunCli, ToolsHoldingTheSameNodesAreAWarning) {
  auto grip = [&](const std::string& first, const std::string& second) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "tools": [)" + first + ", " + second + R"(]
    })");
  };
  const std::string where = R"("nodes": "skin", "center_in_box": [0.5, 0, 0.5], "radius": 0.001, "nearest": true)";
  const std::string hook = R"({"name": "h", "type": "hook", )" + where + "}";
  const std::string pull = R"({"name": "g", "type": "pull", )" + where + R"(, "path": [[0, 0, 0, 0], [0.01, 0, 0.001, 0]]})";
  const std::string pull2 = R"({"name": "g2", "type": "pull", )" + where + R"(, "path": [[0, 0, 0, 0], [0.01, 0, -0.001, 0]]})";
  const auto a = grip(hook, pull);
  expect_one_warning(run_cli("run " + a + " --no-output --quiet"),
                     "orthosim run: warning: " + a + ": the hook tool 'h' and the pull tool 'g' hold 1 of the same node(s) "
                     "at the same time (from 0 s): they do not add up");
  const auto b = grip(pull, pull2);
  expect_one_warning(run_cli("run " + b + " --no-output --quiet"),
                     "orthosim run: warning: " + b + ": the pull tool 'g' and the pull tool 'g2' hold 1 of the same node(s)");
  // spring pulls add up; tools at different times do not meet
  std::string spring = pull, spring2 = pull2;
  spring.insert(spring.size() - 1, R"(, "stiffness": 100)");
  spring2.insert(spring2.size() - 1, R"(, "stiffness": 100)");
  expect_silent(run_cli("run " + grip(spring, spring2) + " --no-output --quiet"));
  std::string early = pull, later = pull2;
  early.insert(early.size() - 1, R"(, "end": 0.005)");
  later.insert(later.size() - 1, R"(, "start": 0.005)");
  expect_silent(run_cli("run " + grip(early, later) + " --no-output --quiet"));
}

// An output block without "dir" takes --out's (it was refused, "output: missing
// dir", though a scene with no output block at all ran with --out); without
// --out it is refused naming the scene.
TEST_F(RunCli, OutGivesAnOutputBlockItsDir) {
  const auto s = scene(R"({"model": "model.h5", "fixed": ["fixed"], "dt": 0.005, "duration": 0.01,
                           "output": {"every": 1, "name": "limb"}})");
  const auto r = run_cli("run " + s + " --quiet --out " + (dir / "given"));
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(fs::exists(dir / "given/limb.pvd"));
  const auto bad = run_cli("run " + s + " --quiet");
  EXPECT_EQ(bad.code, 2);
  EXPECT_EQ(bad.err, "orthosim run: error: " + s + ": output: dir is required (in the scene's output block, or orthosim run --out)\n");
}

// A --report among the series' own files replaced one: tissue.pvd then held
// the JSON report and the series was broken, exit 0. Refused before any work;
// a report beside the series under another name is fine.
TEST_F(RunCli, AReportAmongTheSeriesFilesIsRefused) {
  const auto s = scene(R"({"model": "model.h5", "fixed": ["fixed"], "dt": 0.005, "duration": 0.01,
                           "output": {"every": 1, "name": "limb"}})");
  const std::string out = dir / "series";
  // a report beside the series under another name is fine
  const auto ok = run_cli("run " + s + " --quiet --out " + out);
  ASSERT_EQ(ok.code, 0) << ok.err;
  ASSERT_EQ(run_cli("run " + s + " --quiet --out " + out + " --report " + out + "/report.json").code, 0);
  const std::string pvd = test::read_file(out + "/limb.pvd"), frame = test::read_file(out + "/limb_000001.vtu");
  ASSERT_NE(pvd.find("VTKFile"), std::string::npos);
  for (const std::string f : {"limb.pvd", "limb_000001.vtu"}) {
    const auto r = run_cli("run " + s + " --quiet --out " + out + " --report " + out + "/" + f);
    EXPECT_EQ(r.code, 2) << f;
    EXPECT_EQ(r.err, "orthosim run: error: " + out + "/" + f + ": --report names a file of the output series (limb* in " + out +
                         "): the report would replace it; name another file\n");
  }
  EXPECT_EQ(test::read_file(out + "/limb.pvd"), pvd);
  EXPECT_EQ(test::read_file(out + "/limb_000001.vtu"), frame);
  // names that only start like the series' are reports like any other
  for (const std::string f : {"limb_report.json", "limbreport.json"})
    EXPECT_EQ(run_cli("run " + s + " --quiet --out " + out + " --report " + out + "/" + f).code, 0) << f;
}

// --threads -1 was the "not given" value: it ran with the scene's threads.
TEST_F(RunCli, ThreadsOutOfRangeAreRefused) {
  const auto s = scene(R"({"model": "model.h5", "fixed": ["fixed"], "dt": 0.005, "duration": 0.01})");
  for (const char* t : {"-1", "-5", "1025"}) {
    const auto r = run_cli("run " + s + " --no-output --quiet --threads " + t);
    EXPECT_EQ(r.code, 2) << t;
    EXPECT_EQ(r.err, std::string("orthosim run: error: --threads must be in 0..1024, got ") + t + "\n");
  }
  expect_silent(run_cli("run " + s + " --no-output --quiet --threads 0"));
  // more threads than cores run on the cores, without TBB's own warning line
  expect_silent(run_cli("run " + s + " --no-output --quiet --threads 1024"));
}

// A drain that cannot reach the blood's domain is a warning (0 drained, silently).
TEST_F(RunCli, ADrainOutsideTheBloodIsAWarning) {
  auto drain_at = [&](const std::string& c) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "fluid": {"spacing": 0.002, "sound_speed": 3, "margin": 0.01},
      "tools": [{"name": "suction", "type": "drain", "center": )" + c + R"(, "radius": 0.01}]
    })");
  };
  const auto far = drain_at("[1, 0, 0]");
  expect_one_warning(run_cli("run " + far + " --no-output --quiet"),
                     "orthosim run: warning: " + far + ": the drain 'suction' lies ");
  expect_silent(run_cli("run " + drain_at("[0.01, 0, 0.01]") + " --no-output --quiet"));
}

// A drain the blood never reaches (in the closed tissue far from the wound)
// drained 0 of the emitted particles without a word; now a warning names it.
// One at the wound drains, silently.
TEST_F(RunCli, ADrainTheBloodNeverReachesIsAWarning) {
  auto bleed_with_drain_at = [&](const std::string& c) {
    return bleeding_scene("0.06", "", R"(, {"name": "suction", "type": "drain", "center": )" + c + R"(, "radius": 0.004})");
  };
  // in the muscle, 10 cm along the limb from the cut: inside the domain, never opened
  const auto deep = bleed_with_drain_at("[0.13, 0.012, 0.02]");
  const auto r = run_cli("run " + deep + " --no-output --quiet --report " + (dir / "deep.json"));
  expect_one_warning(r, "orthosim run: warning: " + deep + ": the drain 'suction' removed no blood of the ");
  EXPECT_GT(nlohmann::json::parse(test::read_file(dir / "deep.json"))["metrics"]["fluid"]["particles_emitted"].get<long>(), 0);
  expect_silent(run_cli("run " + bleed_with_drain_at("[0.015, 0.004, 0.01]") + " --no-output --quiet"));
  // a drain that starts after the last step is warned of once, for that (it was also said to
  // have "removed no blood ... the blood never reached it")
  const auto late = bleeding_scene("0.06", "", R"(, {"name": "suction", "type": "drain", "center": [0.015, 0.004, 0.01], "radius": 0.004, "start": 1})");
  expect_one_warning(run_cli("run " + late + " --no-output --quiet"), "the drain tool 'suction' starts at t = 1 s");
}

// A cut polyline the snap moved farther than the cut's depth lay off the
// skin: a warning (5 m off a 7 cm limb was snapped on and cut, silently).
TEST_F(RunCli, ACutSnappedFromFarOffIsAWarning) {
  auto cut_at = [&](const std::string& y) {
    return scene(R"({
      "model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005, "duration": 0.01,
      "tools": [{"name": "scalpel", "type": "cut", "nodes": "skin", "polyline": [[0.005, )" + y + R"(, 0.01], [0.03, )" + y +
                 R"(, 0.01]], "depth": 0.004, "direction": [0, 1, 0]}]
    })");
  };
  const auto far = cut_at("-0.5");
  expect_one_warning(run_cli("run " + far + " --no-output --quiet"),
                     "orthosim run: warning: " + far +
                         ": the cut 'scalpel''s polyline lies off its nodes: the snap moved a point 0.5");
  expect_silent(run_cli("run " + cut_at("0") + " --no-output --quiet"));
}

TEST_F(RunCli, BadScenesExitTwoWithOneLine) {
  const std::vector<std::pair<std::string, std::string>> cases{
      {R"({"model": "missing.h5"})", "does not exist"},
      {R"({"model": "model.h5", "layers": ["skin"]})", "no layer 'skin'"},
      {R"({"model": "model.h5", "fixed": ["bone_surface"]})", "no node set 'bone_surface'"},
      {R"({"model": "model.h5", "tools": [{"type": "pull", "center": [1, 1, 1], "radius": 0.001}]})", "takes no node"},
      {R"({"model": "model.h5", "dt": 0})", "dt must be"},
      {R"({"model": "model.h5", "duration": "long"})", "duration must be a number"},
      // a tool that never acts was warned of before the load's error: two lines for one bad scene
      {R"({"model": "model.h5", "dt": 0.01, "duration": 0.02, "tools": [{"type": "pull", "center": [1, 1, 1], "radius": 0.001, "start": 5}]})",
       "takes no node"},
  };
  for (const auto& [json, expect] : cases) {
    const auto s = scene(json);
    const auto r = run_cli("run " + s + " --out " + (dir / "never"));
    EXPECT_EQ(r.code, 2) << json << " -> " << r.err;
    EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
    EXPECT_NE(r.err.find("orthosim run: error: "), std::string::npos) << r.err;
    EXPECT_NE(r.err.find(expect), std::string::npos) << r.err;
    EXPECT_FALSE(fs::exists(dir / "never"));
  }
  const auto r = run_cli("run " + (dir / "nothing.json"));
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("scene file not found"), std::string::npos) << r.err;
  const auto ok = scene(R"({"model": "model.h5"})");
  EXPECT_EQ(run_cli("run " + ok + " --steps -3").code, 2);
  // --steps 0 is a usage error (it ran the scene's whole duration)
  const auto z = run_cli("run " + ok + " --steps 0 --out " + (dir / "never") + " --report " + (dir / "never.json"));
  EXPECT_EQ(z.code, 2) << z.err;
  EXPECT_EQ(test::count_lines(z.err), 1) << z.err;
  EXPECT_NE(z.err.find("orthosim run: error: --steps must be in 1..1e9, got 0"), std::string::npos) << z.err;
  EXPECT_FALSE(fs::exists(dir / "never"));
  EXPECT_FALSE(fs::exists(dir / "never.json"));
  // more than 1e9 steps: --steps 1e20 was clamped to 2^63 - 1 and hung; dt 1e-20
  // over 1 s overflowed the count and ran "1 steps" (2026-11-27)
  const auto big = run_cli("run " + ok + " --steps 99999999999999999999");
  EXPECT_EQ(big.code, 2) << big.err;
  EXPECT_NE(big.err.find("--steps must be in 1..1e9"), std::string::npos) << big.err;
  const auto tiny = scene(R"({"model": "model.h5", "dt": 1e-20, "duration": 1})");
  const auto t = run_cli("run " + tiny + " --no-output");
  EXPECT_EQ(t.code, 2) << t.err;
  EXPECT_EQ(test::count_lines(t.err), 1) << t.err;
  EXPECT_NE(t.err.find(tiny + ": duration / dt = 1e+20 steps, more than 1e9"), std::string::npos) << t.err;
  const auto help = run_cli("run --help");
  EXPECT_NE(help.out.find(">= 1"), std::string::npos) << help.out;
}

// A run whose steps fail (the solver gives up: gravity 10^5 g with one retry)
// goes to the end, writes its report, and exits 3 with one line (it exited 0).
TEST_F(RunCli, FailedStepsExitThree) {
  const auto s = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "symplectic", "dt": 0.01,
                           "substeps": 1, "gravity": [0, -1e6, 0], "stability": {"max_retries": 1}})");
  const auto r = run_cli("run " + s + " --steps 3 --no-output --report " + (dir / "failed.json"));
  EXPECT_EQ(r.code, 3) << r.err;
  EXPECT_NE(r.err.find("orthosim run: error: " + s + ": 3 of 3 steps failed"), std::string::npos) << r.err;
  const auto j = nlohmann::json::parse(test::read_file(dir / "failed.json"));
  EXPECT_EQ(j["metrics"]["stability"]["failed_steps"], 3);
  EXPECT_TRUE(std::isfinite(j["metrics"]["kinetic_energy_j"].get<double>()));
  EXPECT_EQ(r.err.find("symplectic stability limit"), std::string::npos) << r.err;  // a blow-up, not the limit
  // the same scene at 1 g: 0
  const auto ok = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "symplectic", "dt": 0.01})");
  EXPECT_EQ(run_cli("run " + ok + " --steps 3 --no-output --quiet").code, 0);
  // automatic substeps whose stability limit needs more than max_substeps: the message says
  // so (it spoke of retries only; a 1e12 N/m grip needed 2.5e6 substeps a step)
  const auto capped = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "symplectic", "dt": 0.01,
                                "gravity": [0, -100, 0], "stability": {"max_substeps": 2, "max_retries": 1}})");
  const auto rc = run_cli("run " + capped + " --steps 3 --no-output --quiet");
  EXPECT_EQ(rc.code, 3) << rc.err;
  EXPECT_NE(rc.err.find("substeps a step, more than max_substeps (2): a stiffer (or more heavily damped) spring or grip than the step allows"),
            std::string::npos)
      << rc.err;
}

// Implicit solves stopped at their iteration cap are named in a warning line
// (the summary said "0 stability events, 0 failed" with 60 of 60 unconverged).
// Block Jacobi throughout: "auto" would switch to the sparse factor at the
// first capped solve.
TEST_F(RunCli, UnconvergedSolvesAreAWarning) {
  const auto s = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.01,
                           "implicit": {"cg_tolerance": 1e-12, "cg_max_iterations": 1, "redo_unconverged": false,
                                        "preconditioner": "block_jacobi"}})");
  const auto r = run_cli("run " + s + " --steps 3 --no-output --quiet");
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("orthosim run: warning: " + s + ": 3 of 3 implicit solves stopped unconverged"), std::string::npos)
      << r.err;
  // redone (the default) 8 times a step, each with twice the substeps: the
  // last attempt's 256 solves a step are kept and counted
  const auto d = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.01,
                           "implicit": {"cg_tolerance": 1e-12, "cg_max_iterations": 1, "preconditioner": "block_jacobi"}})");
  const auto rd = run_cli("run " + d + " --steps 3 --no-output --quiet");
  EXPECT_EQ(rd.code, 0) << rd.err;
  EXPECT_EQ(test::count_lines(rd.err), 1) << rd.err;
  EXPECT_NE(rd.err.find(": 768 of 1533 implicit solves stopped unconverged at cg_max_iterations (1) in the kept steps, "
                        "after 24 redos"),
            std::string::npos)
      << rd.err;
  // the summary (without --quiet) counts the redos too
  const auto rs = run_cli("run " + d + " --steps 3 --no-output");
  EXPECT_NE(rs.err.find(", 24 implicit steps redone with more substeps: PCG stopped at cg_max_iterations)"),
            std::string::npos)
      << rs.err;
  const auto ok = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.01})");
  const auto q = run_cli("run " + ok + " --steps 3 --no-output --quiet");
  EXPECT_EQ(q.code, 0) << q.err;
  EXPECT_EQ(q.err, "");
}

// A second run into the same folder with fewer frames leaves only its own
// frames: the earlier run's later ones go, files of other names stay.
TEST_F(RunCli, ARerunRemovesTheEarlierRunsStaleFrames) {
  const auto s = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.01,
                           "output": {"dir": "series"}})");
  ASSERT_EQ(run_cli("run " + s + " --steps 6 --quiet").code, 0);
  ASSERT_TRUE(fs::exists(dir / "series/tissue_000006.vtu"));
  // other files in the folder: none of them is a frame of the series
  const std::vector<std::string> others = {"tissue_notes.vtu", "tissue_000009.vtp", "other_000009.vtu", "tissue_12a.vtu",
                                           "tissue_.vtu", "xtissue_000009.vtu", "notes.txt"};
  test::write_file(dir / "series/tissue_blood_3.vtp", "stale");  // the blood series of the name goes too
  for (const auto& f : others) test::write_file(dir / ("series/" + f), "keep");
  const auto r = run_cli("run " + s + " --steps 2 --quiet");
  ASSERT_EQ(r.code, 0) << r.err;
  for (int k = 0; k <= 6; ++k) {
    char f[32];
    std::snprintf(f, sizeof f, "series/tissue_%06d.vtu", k);
    EXPECT_EQ(fs::exists(dir / f), k <= 2) << f;
  }
  const std::string pvd = test::read_file(dir / "series/tissue.pvd");
  EXPECT_NE(pvd.find("tissue_000002.vtu"), std::string::npos) << pvd;
  EXPECT_EQ(pvd.find("tissue_000003.vtu"), std::string::npos) << pvd;
  for (const auto& f : others) EXPECT_EQ(test::read_file(dir / ("series/" + f)), "keep") << f;

  // the blood series likewise (its frames are numbered with six digits, as
  // the tissue's: they were not padded until 2026-11-27, and stale frames
  // numbered either way go)
  const auto b = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.005,
                           "fluid": {"spacing": 0.002, "sound_speed": 3}, "output": {"dir": "series"}})");
  test::write_file(dir / "series/tissue_blood_7.vtp", "stale");
  test::write_file(dir / "series/tissue_blood_000008.vtp", "stale");
  test::write_file(dir / "series/tissue_blood.pvd", "stale");
  const auto rb = run_cli("run " + b + " --steps 1 --quiet");
  ASSERT_EQ(rb.code, 0) << rb.err;
  EXPECT_FALSE(fs::exists(dir / "series/tissue_blood_7.vtp"));
  EXPECT_FALSE(fs::exists(dir / "series/tissue_blood_000008.vtp"));
  EXPECT_TRUE(fs::exists(dir / "series/tissue_blood_000000.vtp"));
  EXPECT_TRUE(fs::exists(dir / "series/tissue_blood_000001.vtp"));
  EXPECT_FALSE(fs::exists(dir / "series/tissue_blood_1.vtp"));
  EXPECT_EQ(test::read_file(dir / "series/tissue_blood.pvd").find("tissue_blood_7"), std::string::npos);
  EXPECT_FALSE(fs::exists(dir / "series/tissue_000002.vtu")) << "the tissue frames of the run before";
  EXPECT_FALSE(fs::exists(dir / "series/tissue_blood_3.vtp")) << "a blood frame of the run before";
  EXPECT_EQ(test::read_file(dir / "series/other_000009.vtu"), "keep");
  EXPECT_EQ(test::read_file(dir / "series/tissue_notes.vtu"), "keep");

  // a run without a fluid removes the blood and particle series of the run
  // before too (they stayed beside its tissue series until 2026-11-27)
  test::write_file(dir / "series/tissue_particles_000004.vtp", "stale");
  test::write_file(dir / "series/tissue_particles.pvd", "stale");
  const auto dry = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.01,
                             "output": {"dir": "series"}})");  // (scene() rewrote s's file for b)
  ASSERT_EQ(run_cli("run " + dry + " --steps 1 --quiet").code, 0);
  for (const char* f : {"tissue_blood_000000.vtp", "tissue_blood_000001.vtp", "tissue_blood.pvd",
                        "tissue_particles_000004.vtp", "tissue_particles.pvd"})
    EXPECT_FALSE(fs::exists(dir / (std::string("series/") + f))) << f;
  EXPECT_TRUE(fs::exists(dir / "series/tissue_000001.vtu"));
  EXPECT_EQ(test::read_file(dir / "series/other_000009.vtu"), "keep");
}

// A long series name: every frame its own file (a char[64] cut names over 52
// characters, so every frame overwrote one file and the .pvd listed it three
// times, exit 0); --no-output with --out is a contradiction, not a silent no-op.
TEST_F(RunCli, LongSeriesNamesKeepEveryFrame) {
  const std::string name(190, 'y');
  const auto s = scene(R"({"model": "model.h5", "fixed": ["fixed"], "integrator": "implicit", "dt": 0.01,
                           "output": {"dir": "long", "name": ")" + name + R"("}})");
  const auto r = run_cli("run " + s + " --steps 2 --quiet");
  ASSERT_EQ(r.code, 0) << r.err;
  std::set<std::string> frames;
  for (const auto& e : fs::directory_iterator(dir / "long")) frames.insert(e.path().filename().string());
  EXPECT_EQ(frames, (std::set<std::string>{name + "_000000.vtu", name + "_000001.vtu", name + "_000002.vtu", name + ".pvd"}));
  const std::string pvd = test::read_file(dir / ("long/" + name + ".pvd"));
  for (int k = 0; k <= 2; ++k) EXPECT_NE(pvd.find(name + "_00000" + std::to_string(k) + ".vtu"), std::string::npos) << k;
  const auto c = run_cli("run " + s + " --steps 1 --no-output --out " + (dir / "other") + " --quiet");
  EXPECT_EQ(c.code, 2) << c.err;
  EXPECT_NE(c.err.find("--no-output and --out contradict each other"), std::string::npos) << c.err;
  EXPECT_FALSE(fs::exists(dir / "other"));
}

}  // namespace
}  // namespace orthosim
