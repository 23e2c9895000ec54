// orthosim vessels on a small phantom label volume written in-process: the
// model groups, the mesh and centreline files, the report, roots, adding to an
// existing model, and bad input (exit 2, one line, nothing written).
#include "libmodel/format/model.h"
#include "libmodel/phantom/phantom.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <filesystem>
#include <sstream>

using namespace orthosim;
namespace fs = std::filesystem;

namespace {

// 96 x 96 x 40 voxels of 0.6 x 0.6 x 1.5 mm: artery (3 branches) and vein
// (1 branch), both cut by the first and last slice.
PhantomOptions small_phantom() {
  PhantomOptions po;
  po.nx = po.ny = 96, po.nz = 40;
  po.spacing_m = {0.6e-3, 0.6e-3, 1.5e-3};
  return po;
}

struct Files {
  test::TempDir d{"vessels-cli"};
  PhantomOptions po = small_phantom();
  std::map<std::string, VesselTree> truth = phantom_vessels(po);
  Files() {
    const Volume v = phantom_labels(po);
    {
      ModelWriter w(d / "labels.h5", ModelWriter::Start::fresh);
      w.write(v);
      w.commit();
    }
    {  // the same label table without any vein voxel
      Volume nv = v;
      std::replace(nv.labels.begin(), nv.labels.end(), std::uint8_t{kPhantomVein}, std::uint8_t{kPhantomMuscle});
      ModelWriter w(d / "no_vein.h5", ModelWriter::Start::fresh);
      w.write(nv);
      w.commit();
    }
    {  // the vein reduced to a speck of 4 voxels: no vessel
      Volume sv = v;
      std::replace(sv.labels.begin(), sv.labels.end(), std::uint8_t{kPhantomVein}, std::uint8_t{kPhantomMuscle});
      for (int i = 0; i < 4; ++i) sv.labels[sv.index(30 + i % 2, 30 + i / 2, 20)] = kPhantomVein;
      ModelWriter w(d / "speck_vein.h5", ModelWriter::Start::fresh);
      w.write(sv);
      w.commit();
    }
    {  // a model file without /volume
      ModelWriter w(d / "empty.h5", ModelWriter::Start::fresh);
      w.commit();
    }
  }
  std::string operator/(const std::string& r) const { return d / r; }
};

std::string mm(const Eigen::Vector3d& p) {
  std::ostringstream s;
  s << 1e3 * p.x() << "," << 1e3 * p.y() << "," << 1e3 * p.z();
  return s.str();
}

std::vector<int> sorted_parents(const VesselTree& t) {
  std::vector<int> p(t.branch_parent.data(), t.branch_parent.data() + t.branch_parent.size());
  std::sort(p.begin(), p.end());
  return p;
}

void expect_error(const test::RunResult& r, const std::string& needle) {
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_EQ(r.err.rfind("orthosim vessels: error: ", 0), 0u) << r.err;
  EXPECT_NE(r.err.find(needle), std::string::npos) << "expected '" << needle << "' in: " << r.err;
}

}  // namespace

TEST(VesselsCli, PhantomTreesIntoANewModelWithFilesAndReport) {
  Files f;
  const std::string model = f / "model.h5", out = f / "out";
  const auto r = test::run_cli("vessels --labels " + f / "labels.h5" + " --tissue artery --tissue vein --model " +
                               model + " --out " + out + " --report " + f / "r.json");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("vessels: artery: 1 tree, 3 branches, 1 bifurcations"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("vessels: vein: 1 tree, 1 branches"), std::string::npos) << r.out;

  ModelReader m(model);
  EXPECT_EQ(m.names("/vessels"), (std::vector<std::string>{"artery", "vein"}));
  EXPECT_TRUE(m.has("/provenance/vessels"));
  const VesselTree art = m.vessels("artery"), vein = m.vessels("vein");
  EXPECT_EQ(sorted_parents(art), (std::vector<int>{-1, 0, 0}));
  EXPECT_EQ(sorted_parents(vein), (std::vector<int>{-1}));
  for (const VesselTree* t : {&art, &vein}) {
    EXPECT_GT(t->nodes.rows(), 20);
    EXPECT_EQ(t->radii.size(), t->nodes.rows());
    EXPECT_EQ((t->bezier_ctrl.rows() - t->branch_parent.size()) % 3, 0);  // 3k+1 per branch
    EXPECT_GT(t->tube_quads.rows(), 100);
    EXPECT_GT(t->radii.minCoeff(), 0.5e-3);
    EXPECT_LT(t->radii.maxCoeff(), 4e-3);
  }

  // files: binary STL of the right size, OBJs with vertices and faces / lines
  for (const char* t : {"artery", "vein"}) {
    const std::string stl = test::read_file(out + "/" + t + "_tube.stl");
    ASSERT_GE(stl.size(), 84u);
    std::uint32_t n = 0;
    std::memcpy(&n, stl.data() + 80, 4);
    EXPECT_EQ(stl.size(), 84u + 50u * n) << t;
    const VesselTree tr = m.vessels(t);
    EXPECT_EQ(n, 2 * tr.tube_quads.rows() + tr.tube_tris.rows());
    const std::string obj = test::read_file(out + "/" + t + "_tube.obj");
    EXPECT_NE(obj.find("\nf "), std::string::npos);
    const std::string cl = test::read_file(out + "/" + t + "_centreline.obj");
    EXPECT_NE(cl.find("\nl "), std::string::npos);
  }

  // the report: counts, open ends, mesh checks, distances, timings
  const auto j = nlohmann::json::parse(test::read_file(f / "r.json"));
  EXPECT_EQ(j["command"], "vessels");
  const auto& a = j["metrics"]["tissues"]["artery"];
  EXPECT_EQ(a["branches"], 3);
  EXPECT_EQ(a["bifurcations"], 1);
  EXPECT_EQ(a["open_ends"], 3);  // the brachial's start and both forearm arteries leave the volume
  EXPECT_EQ(a["loops_broken"], 0);
  EXPECT_TRUE(a["tube"]["closed"].get<bool>());
  EXPECT_TRUE(a["tube"]["manifold"].get<bool>());
  EXPECT_EQ(a["tube"]["self_intersections"], 0);
  EXPECT_LE(a["bezier"]["max_deviation_m"].get<double>(), a["bezier"]["tolerance_m"].get<double>() + 1e-12);
  EXPECT_LT(a["tube_to_label_boundary_m"]["mean"].get<double>(), 0.6e-3);
  EXPECT_GT(a["phases_s"]["thinning"].get<double>(), 0.0);
  const auto& vj = j["metrics"]["tissues"]["vein"];
  EXPECT_EQ(vj["branches"], 1);
  EXPECT_EQ(vj["open_ends"], 2);
  EXPECT_TRUE(j["phases_s"].contains("extract.artery"));
  EXPECT_TRUE(j["inputs"].contains(f / "labels.h5"));

  // quiet: nothing on stdout
  const auto q = test::run_cli("vessels -q --labels " + f / "labels.h5" + " --tissue vein --model " + model);
  ASSERT_EQ(q.code, 0) << q.err;
  EXPECT_TRUE(q.out.empty()) << q.out;
}

// A tube that cuts itself is named in one warning line, even with -q (it was
// written silently).
TEST(VesselsCli, SelfIntersectingTubeIsAWarning) {
  test::TempDir d{"vessels-noisy"};
  const std::string st = d / "stack", labels = d / "labels.h5";
  // the vein segmented at 8-bit noise 24: islands and short branches whose
  // tubes cut each other (the exact labels of a short wide stack did too
  // until 2026-11-27, Vessels.PhantomTreesAtOtherResolutions), segmented with
  // the per-voxel rule (--smoothness 0; the smoothness prior removes them).
  // Seed 2: seeds 1-5 give 0, 299, 135, 0, 188 pairs since the classifier
  // scores pixels against their own mean colours (seed 1 gave some before).
  auto r = test::run_cli("phantom -q --out " + st + " --size 128x128x48 --spacing 0.4,0.4,1.0 --noise 24 --seed 2");
  ASSERT_EQ(r.code, 0) << r.err;
  r = test::run_cli("segment -q --smoothness 0 --stack " + st + "/slices --tissues " + st +
                    "/tissues.json --spacing 0.4,0.4,1.0 --out " + labels);
  ASSERT_EQ(r.code, 0) << r.err;
  r = test::run_cli("vessels -q --labels " + labels + " --tissue vein --model " + (d / "m.h5") + " --report " +
                    (d / "r.json"));
  ASSERT_EQ(r.code, 0) << r.err;
  const auto j = nlohmann::json::parse(test::read_file(d / "r.json"));
  const long n = j["metrics"]["tissues"]["vein"]["tube"]["self_intersections"].get<long>();
  ASSERT_GT(n, 0);
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("orthosim vessels: warning: " + labels + ": vein: the tube has " + std::to_string(n) +
                       " self-intersecting face pair(s)"),
            std::string::npos)
      << r.err;
}

// A vessel tissue whose few voxels form no vessel fails the stage, unless
// --skip-unformed leaves it out with a warning and writes the others (the
// pipeline passes it: a speck of vein stopped the whole pipeline).
TEST(VesselsCli, AnUnformedVesselIsLeftOutOnlyWhenAsked) {
  Files f;
  const std::string labels = f / "speck_vein.h5", model = f / "m.h5", out = f / "out";
  const std::string base = "vessels -q --labels " + labels + " --tissue artery,vein --model " + model + " --out " + out;
  expect_error(test::run_cli(base), "tissue 'vein': its 4 voxels form no vessel");
  EXPECT_FALSE(fs::exists(model));
  EXPECT_FALSE(fs::exists(out));
  const auto r = test::run_cli(base + " --skip-unformed --report " + (f / "r.json"));
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_EQ(r.err.rfind("orthosim vessels: warning: " + labels + ": tissue 'vein': its 4 voxels form no vessel", 0), 0u)
      << r.err;
  EXPECT_NE(r.err.find("; it is left out\n"), std::string::npos) << r.err;
  ModelReader m(model);
  EXPECT_EQ(m.names("/vessels"), (std::vector<std::string>{"artery"}));
  EXPECT_EQ(sorted_parents(m.vessels("artery")), (std::vector<int>{-1, 0, 0}));
  EXPECT_TRUE(fs::exists(out + "/artery_tube.stl"));
  EXPECT_FALSE(fs::exists(out + "/vein_tube.stl"));
  const auto j = nlohmann::json::parse(test::read_file(f / "r.json"));
  ASSERT_EQ(j["metrics"]["left_out"].size(), 1u) << j["metrics"].dump();
  EXPECT_EQ(j["metrics"]["left_out"][0]["tissue"], "vein");
  EXPECT_FALSE(j["metrics"]["tissues"].contains("vein"));
  EXPECT_TRUE(j["metrics"]["tissues"].contains("artery"));
  // every tissue left out: a model with no tree, still written with its provenance
  const auto only = test::run_cli("vessels -q --labels " + labels + " --tissue vein --skip-unformed --model " + (f / "none.h5"));
  ASSERT_EQ(only.code, 0) << only.err;
  ModelReader none(f / "none.h5");
  EXPECT_TRUE(none.names("/vessels").empty());
  EXPECT_TRUE(none.has("/provenance/vessels"));
}

TEST(VesselsCli, AddsToAnExistingModelAndKeepsItsGroups) {
  Files f;
  const std::string model = f / "labels.h5";  // the labels file is the model: /volume stays
  auto r = test::run_cli("vessels -q --labels " + model + " --tissue artery --model " + model);
  ASSERT_EQ(r.code, 0) << r.err;
  r = test::run_cli("vessels -q --labels " + model + " --tissue vein --model " + model + " --tolerance 0.05");
  ASSERT_EQ(r.code, 0) << r.err;
  ModelReader m(model);
  EXPECT_TRUE(m.has("/volume"));
  EXPECT_EQ(m.names("/vessels"), (std::vector<std::string>{"artery", "vein"}));
  EXPECT_EQ(m.vessels("artery").branch_parent.size(), 3);
  const auto prov = m.provenance();
  ASSERT_TRUE(prov.count("vessels"));
  EXPECT_NE(prov.at("vessels").parameters_json.find("\"tolerance_m\":5e-05"), std::string::npos)
      << prov.at("vessels").parameters_json;
}

TEST(VesselsCli, RootPointPicksTheRootEnd) {
  Files f;
  // the radial artery's distal end (truth branch 1's last node) as the root
  const VesselTree& t = f.truth.at("artery");
  const int last = t.branch_nodes(t.branch_offsets(2) - 1);
  const Eigen::Vector3d root = t.nodes.row(last).transpose();
  const std::string model = f / "model.h5";
  const auto r = test::run_cli("vessels -q --labels " + f / "labels.h5" + " --tissue artery --root " + mm(root) +
                               " --model " + model + " --report " + f / "r.json");
  ASSERT_EQ(r.code, 0) << r.err;
  const VesselTree e = ModelReader(model).vessels("artery");
  EXPECT_EQ(sorted_parents(e), (std::vector<int>{-1, 0, 0}));
  const Eigen::Vector3d first = e.nodes.row(e.branch_nodes(0)).transpose();
  EXPECT_LT((first - root).norm(), 3e-3) << "root branch starts at " << mm(first);
  const auto j = nlohmann::json::parse(test::read_file(f / "r.json"));
  EXPECT_EQ(j["metrics"]["tissues"]["artery"]["roots_used"], nlohmann::json::array({0}));
}

TEST(VesselsCli, BadInputIsOneLineExit2AndWritesNothing) {
  Files f;
  const std::string model = f / "model.h5", out = f / "out";
  const std::string tail = " --model " + model + " --out " + out;
  const std::string labels = " --labels " + f / "labels.h5";
  expect_error(test::run_cli("vessels" + labels + " --tissue nerve" + tail), "unknown tissue 'nerve'");
  expect_error(test::run_cli("vessels --labels " + f / "no_vein.h5" + " --tissue artery --tissue vein" + tail),
               "no voxels of tissue 'vein'");
  expect_error(test::run_cli("vessels --labels " + f / "missing.h5" + " --tissue artery" + tail), "missing.h5");
  expect_error(test::run_cli("vessels --labels " + f / "empty.h5" + " --tissue artery" + tail), "/volume");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --root 1,2" + tail), "--root");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --root 1,2,nan" + tail), "--root");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --root 0,0,-500" + tail), "outside the volume");
  // inside the volume but near no end of the vessel (the middle of the brachial artery)
  const VesselTree& t = f.truth.at("artery");
  const Eigen::Vector3d mid = t.nodes.row(t.branch_nodes((t.branch_offsets(0) + t.branch_offsets(1)) / 2)).transpose();
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --root " + mm(mid) + tail), "no vessel end");
  // two roots on one tree: the second is in reach of an end, but its tree is taken
  // (it said "no vessel end ... within reach; the nearest end is ... 0.03 mm away")
  const Eigen::Vector3d tip = t.nodes.row(t.branch_nodes(t.branch_offsets(2) - 1)).transpose();
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --root " + mm(tip) + " --root " + mm(tip) + tail),
               "is on a tree another --root has rooted already: one root per tree");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --tolerance -1" + tail), "--tolerance");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --ring-vertices 10" + tail), "--ring-vertices");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --max-children 5" + tail), "--max-children");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --min-radius-voxels -0.5" + tail), "--min-radius-voxels");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --min-radius-voxels nan" + tail), "--min-radius-voxels");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --spur-ratio 0" + tail), "--spur-ratio");
  expect_error(test::run_cli("vessels" + labels + " --tissue artery --spur-ratio nan" + tail), "--spur-ratio");
  EXPECT_FALSE(fs::exists(model));
  EXPECT_FALSE(fs::exists(out));

  // an existing model is left byte for byte as it was
  ASSERT_EQ(test::run_cli("vessels -q" + labels + " --tissue vein --model " + model).code, 0);
  const std::string before = test::read_file(model);
  expect_error(test::run_cli("vessels" + labels + " --tissue vein --tissue nerve" + tail), "unknown tissue");
  EXPECT_EQ(test::read_file(model), before);
  EXPECT_FALSE(fs::exists(out));
  // a model path that is not an orthosim file is refused before any work
  test::write_file(f / "junk.h5", "not hdf5");
  const auto r = test::run_cli("vessels" + labels + " --tissue vein --model " + f / "junk.h5");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_EQ(test::count_lines(r.err), 1) << r.err;
  EXPECT_EQ(test::read_file(f / "junk.h5"), "not hdf5");
}
