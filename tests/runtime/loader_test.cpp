// Lazy loading: only what a scene names is read from the model file.
#include "runtime/loader.h"
#include "runtime/testing/lattice.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>

#include <algorithm>

namespace orthosim::runtime {
namespace {

using testing::make_layered_block;
using testing::write_model_file;

bool read_any(const h5::ReadStats& st, const std::string& prefix) {
  return std::any_of(st.paths_read.begin(), st.paths_read.end(),
                     [&](const std::string& p) { return p.rfind(prefix, 0) == 0; });
}

// Loading the file fails with one line holding `want`.
void expect_load_refused(const std::string& file, const std::string& want) {
  try {
    ModelReader r(file);
    load_model(r, {});
    ADD_FAILURE() << want;
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find(want), std::string::npos) << e.what();
    EXPECT_EQ(std::string(e.what()).find('\n'), std::string::npos);
  }
}

struct LoaderTest : ::testing::Test {
  orthosim::test::TempDir dir{"loader"};
  std::string file = dir / "model.h5";
  testing::LayeredBlock block = make_layered_block(6, 4, 4);
  void SetUp() override { write_model_file(file, block, /*extras=*/true); }
  // The block spoiled by `spoil`, written as `name`, is refused in one line
  // that begins with the file and holds `want`.
  template <class Spoil>
  void expect_spoiled_refused(const char* name, Spoil&& spoil, const std::string& want) {
    auto bad = block;
    spoil(bad);
    const std::string f2 = dir / name;
    write_model_file(f2, bad);
    ModelReader r(f2);
    try {
      load_model(r, LoadRequest{});
      ADD_FAILURE() << want << ": accepted";
    } catch (const Error& e) {
      EXPECT_EQ(std::string(e.what()).rfind(f2 + ": ", 0), 0u) << e.what();
      EXPECT_NE(std::string(e.what()).find(want), std::string::npos) << e.what();
      EXPECT_EQ(std::string(e.what()).find('\n'), std::string::npos) << e.what();
    }
  }
};

TEST_F(LoaderTest, SceneWithoutVesselsNeverReadsThem) {
  ModelReader r(file);
  LoadRequest req;
  req.node_sets = {"fixed", "skin"};
  Model m = load_model(r, req);
  const auto& st = r.h5().stats();
  EXPECT_FALSE(read_any(st, "/vessels"));
  EXPECT_FALSE(read_any(st, "/volume"));
  EXPECT_FALSE(read_any(st, "/surfaces"));
  EXPECT_FALSE(read_any(st, "/quads"));
  EXPECT_FALSE(read_any(st, "/tuning"));
  // 4 layers x (nodes, masses, 5 lin_* fields) + 2 node sets; nothing else
  EXPECT_EQ(st.datasets_read, 4 * 7 + 2);
  for (const auto& p : st.paths_read) {
    EXPECT_TRUE(p.find("/k1") == std::string::npos && p.find("/springs") == std::string::npos &&
                p.find("/quads") == std::string::npos && p.find("/tets") == std::string::npos)
        << p << " should not be read";
  }
  EXPECT_EQ(m.n_nodes, 6 * 4 * 4);
  EXPECT_EQ(m.n_anchors, 0);
  EXPECT_TRUE(m.vessels.empty());
}

// A layer's tets are read only when it has a volume term (Layer::
// volume_modulus), then all of them whose corners the model holds; a volume
// term without tets is a one-line error.
TEST_F(LoaderTest, TetsAreReadForAVolumeTermOnly) {
  {
    ModelReader r(file);
    EXPECT_EQ(load_model(r, {}).n_tets, 0);
    EXPECT_FALSE(read_any(r.h5().stats(), "/layers/dermis/tets"));
  }
  auto o = block.options;
  o.volume_modulus = {2e6};
  const auto with = testing::make_layered_block(o);
  const std::string f2 = dir / "volume.h5";
  write_model_file(f2, with);
  {
    ModelReader r(f2);
    const Model m = load_model(r, {});
    EXPECT_TRUE(read_any(r.h5().stats(), "/layers/dermis/tets"));
    ASSERT_EQ(m.n_tets, 5 * 3 * 6);
    for (Real k : m.tet_k) EXPECT_EQ(k, 2e6);
    Real v = 0;
    for (Real x : m.tet_rest_volume) v += x;
    EXPECT_NEAR(std::abs(v), 5 * 3 * 16e-6 * 2e-3, 1e-15) << "the cells' volume, 4 x 4 x 2 mm each";
  }
  {
    // the skin alone: its tets reach the next sheet through anchors
    ModelReader r(f2);
    LoadRequest req;
    req.layers = {"dermis"};
    const Model m = load_model(r, req);
    EXPECT_EQ(m.n_tets, 5 * 3 * 6);
    EXPECT_GT(m.n_anchors, 0);
  }
  auto broken = with;
  broken.layers[0].second.tets.resize(0, 4);
  const std::string f3 = dir / "broken.h5";
  write_model_file(f3, broken);
  expect_load_refused(f3, "volume_modulus but no tets");
  // a lattice layer's term, one per cell of 6 (attribute volume_group)
  o.volume_group = 6;
  const auto cells = testing::make_layered_block(o);
  const std::string f4 = dir / "cells.h5";
  write_model_file(f4, cells);
  {
    ModelReader r(f4);
    EXPECT_EQ(r.layer("dermis").volume_group, 6);
    const Model m = load_model(r, {});
    EXPECT_EQ(m.n_tets, 5 * 3 * 6);
    EXPECT_EQ(m.n_groups, 5 * 3);
    EXPECT_NEAR(std::abs(m.group_rest_volume[0]), 16e-6 * 2e-3, 1e-15) << "a cell's volume";
  }
  {
    ModelReader r(f2);
    EXPECT_EQ(r.layer("dermis").volume_group, 1) << "absent: 1";
    EXPECT_EQ(load_model(r, {}).n_groups, 5 * 3 * 6);
  }
  // tets that are not whole groups, and a bad attribute: one line each
  {
    h5::File f(f4, h5::File::Mode::read_write);
    f.set_attr("/layers/dermis", "volume_group", static_cast<std::int64_t>(4));
  }
  for (const char* want : {"not groups of volume_group 4", "volume_group must be in 1..64"}) {
    if (std::string(want).find("1..64") != std::string::npos) {
      h5::File f(f4, h5::File::Mode::read_write);
      f.set_attr("/layers/dermis", "volume_group", static_cast<std::int64_t>(0));
    }
    expect_load_refused(f4, want);
  }
}

// A layer's own tetrahedra for its volume term (Layer::volume_tets, a tetra
// layer's grid prisms): the term's groups come from them, the guard's from
// `tets`; ids out of range and rows that are not whole groups are one-line
// errors.
TEST_F(LoaderTest, TheVolumeTermsOwnTetsAreReadWhereTheLayerHasThem) {
  auto o = block.options;
  o.volume_modulus = {2e6};
  o.guard_modulus = {3e5};
  o.guard_ratio = 0.5;
  auto with = testing::make_layered_block(o);
  Layer& l = with.layers[0].second;
  // the term over the cells' first 4 tetrahedra, twice over, in groups of 4
  const Eigen::Index nc = l.tets.rows() / 6;
  l.volume_tets.resize(2 * 4 * nc, 4);
  for (Eigen::Index c = 0; c < nc; ++c)
    for (int k = 0; k < 8; ++k) l.volume_tets.row(8 * c + k) = l.tets.row(6 * c + k % 4);
  l.volume_group = 4;
  const std::string f1 = dir / "own.h5";
  write_model_file(f1, with);
  {
    ModelReader r(f1);
    const Model m = load_model(r, {});
    EXPECT_TRUE(read_any(r.h5().stats(), "/layers/dermis/volume_tets"));
    ASSERT_EQ(m.n_tets, 8 * nc + 6 * nc);
    ASSERT_EQ(m.n_groups, 2 * nc + 6 * nc);
    for (std::int32_t g = 0; g < m.n_groups; ++g) {
      const std::int32_t t0 = m.tet_group_first[g];
      EXPECT_EQ(m.tet_group_first[g + 1] - t0, g < 2 * nc ? 4 : 1) << g;
      EXPECT_EQ(m.tet_k[t0], g < 2 * nc ? 2e6 : 3e5) << g;
      EXPECT_EQ(m.tet_guard[t0], g < 2 * nc ? 0 : 0.5) << g;
    }
    // a group's rest volume: its 4 tetrahedra's
    Real v = 0;
    for (int t = 0; t < 4; ++t) v += m.tet_rest_volume[static_cast<std::size_t>(t)];
    EXPECT_NEAR(m.group_rest_volume[0], v, 1e-15);
    EXPECT_NEAR(m.group_rest_volume[0], m.group_rest_volume[1], 1e-15) << "the same tetrahedra twice";
  }
  {
    h5::File f(f1, h5::File::Mode::read_write);
    f.set_attr("/layers/dermis", "volume_group", static_cast<std::int64_t>(7));
  }
  ASSERT_NE(8 * nc % 7, 0);
  expect_load_refused(f1, std::to_string(8 * nc) + " volume_tets are not groups of volume_group 7");
  l.volume_tets(5, 2) = 1 << 30;
  const std::string f2 = dir / "own_bad.h5";
  write_model_file(f2, with);
  expect_load_refused(f2, "volume_tets");
}

// The inversion guard (Layer::guard_modulus, guard_ratio): its attributes
// round-trip, its tets are read for it alone (one group each, at the ratio),
// after the volume term's where both are set; a guard without tets or with a
// ratio outside (0, 1) is a one-line error.
TEST_F(LoaderTest, TheInversionGuardIsReadWithItsTets) {
  auto o = block.options;
  o.guard_modulus = {3e5};
  o.guard_ratio = 0.4;
  const std::string f1 = dir / "guard.h5";
  write_model_file(f1, testing::make_layered_block(o));
  {
    ModelReader r(f1);
    const Layer l = r.layer("dermis");
    EXPECT_EQ(l.guard_modulus, 3e5);
    EXPECT_EQ(l.guard_ratio, 0.4);
    EXPECT_EQ(l.volume_modulus, 0);
    const Model m = load_model(r, {});
    EXPECT_TRUE(read_any(r.h5().stats(), "/layers/dermis/tets"));
    ASSERT_EQ(m.n_tets, 5 * 3 * 6);
    EXPECT_EQ(m.n_groups, m.n_tets);
    for (std::int32_t t = 0; t < m.n_tets; ++t) {
      EXPECT_EQ(m.tet_k[t], 3e5);
      EXPECT_EQ(m.tet_guard[t], 0.4);
    }
  }
  o.volume_modulus = {2e6};
  o.volume_group = 6;
  const std::string f2 = dir / "guard_and_term.h5";
  write_model_file(f2, testing::make_layered_block(o));
  {
    ModelReader r(f2);
    const Model m = load_model(r, {});
    ASSERT_EQ(m.n_tets, 2 * 5 * 3 * 6);
    EXPECT_EQ(m.n_groups, 5 * 3 + 5 * 3 * 6);
    EXPECT_EQ(m.tet_guard[0], 0);
    EXPECT_EQ(m.tet_k[0], 2e6);
    EXPECT_EQ(m.tet_guard[static_cast<std::size_t>(m.n_tets - 1)], 0.4);
    EXPECT_EQ(m.tet_k[static_cast<std::size_t>(m.n_tets - 1)], 3e5);
  }
  for (const double ratio : {0.0, 1.0}) {
    {
      h5::File f(f1, h5::File::Mode::read_write);
      f.set_attr("/layers/dermis", "guard_ratio", std::vector<double>{ratio});
    }
    expect_load_refused(f1, "guard_ratio must be one value in (0, 1)");
  }
  o.volume_modulus.clear();
  auto bare = testing::make_layered_block(o);
  bare.layers[0].second.tets.resize(0, 4);
  const std::string f3 = dir / "guard_no_tets.h5";
  EXPECT_THROW(write_model_file(f3, bare), Error) << "the writer refuses a guard without tets";
}

TEST_F(LoaderTest, VesselsAndSurfacesAreReadWhenNamed) {
  ModelReader r(file);
  LoadRequest req;
  req.vessels = {"artery"};
  req.surface = true;
  Model m = load_model(r, req);
  const auto& st = r.h5().stats();
  EXPECT_TRUE(read_any(st, "/vessels/artery/nodes"));
  EXPECT_FALSE(read_any(st, "/vessels/artery/tube_vertices")) << "only what the runtime uses";
  EXPECT_FALSE(read_any(st, "/volume"));
  ASSERT_EQ(m.vessels.size(), 1u);
  EXPECT_EQ(m.vessels[0].radii.size(), 3u);
  EXPECT_EQ(m.n_quads, 4 * 5 * 3);
}

TEST_F(LoaderTest, OneLayerAnchorsItsNeighbours) {
  const std::int32_t per_sheet = 6 * 4;
  {
    ModelReader r(file);
    LoadRequest req;
    req.layers = {"dermis"};
    Model m = load_model(r, req);
    EXPECT_EQ(m.n_nodes - m.n_anchors, per_sheet);
    EXPECT_EQ(m.n_anchors, per_sheet) << "the next sheet's nodes anchor the inter-layer springs";
    for (std::int32_t i = m.n_nodes - m.n_anchors; i < m.n_nodes; ++i) EXPECT_EQ(m.inv_mass[i], 0);
    const auto& st = r.h5().stats();
    EXPECT_FALSE(read_any(st, "/layers/muscle/lin_k")) << "muscle springs do not reach the dermis";
    EXPECT_TRUE(read_any(st, "/layers/hypodermis/nodes")) << "anchor positions";
    EXPECT_FALSE(read_any(st, "/layers/hypodermis/masses"));
  }
  {
    ModelReader r(file);
    LoadRequest req;
    req.layers = {"hypodermis"};
    Model m = load_model(r, req);
    EXPECT_EQ(m.n_anchors, 2 * per_sheet) << "dermis-owned springs reach down, own springs reach the muscle";
    EXPECT_TRUE(read_any(r.h5().stats(), "/layers/dermis/lin_k"));
  }
  {  // uncoupled: exactly the layer's seven datasets and its own anchors
    ModelReader r(file);
    LoadRequest req;
    req.layers = {"hypodermis"};
    req.couple_unloaded = false;
    Model m = load_model(r, req);
    EXPECT_EQ(r.h5().stats().datasets_read, 7 + 1);  // + muscle nodes for the anchors
    EXPECT_EQ(m.n_anchors, per_sheet);
  }
}

TEST_F(LoaderTest, MissingNamesAreOneLineErrors) {
  ModelReader r(file);
  auto expect_error = [&](const LoadRequest& req, const std::string& what) {
    try {
      load_model(r, req);
      FAIL() << "expected an error containing " << what;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
      EXPECT_EQ(std::string(e.what()).find('\n'), std::string::npos);
    }
  };
  LoadRequest a;
  a.layers = {"epidermis"};
  expect_error(a, "no layer 'epidermis' in the model (layers: bone, dermis, hypodermis, muscle)");
  LoadRequest b;
  b.node_sets = {"clamp"};
  expect_error(b, "no node set 'clamp'");
  LoadRequest c;
  c.vessels = {"vein"};
  expect_error(c, "no vessel tree 'vein'");
}

TEST_F(LoaderTest, InvalidSpringDataIsRejected) {
  auto bad = block;
  bad.layers[1].second.lin_k[0] = -5;
  const std::string f2 = dir / "bad.h5";
  write_model_file(f2, bad);
  ModelReader r(f2);
  try {
    load_model(r, LoadRequest{});
    FAIL() << "negative stiffness accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("stiffness"), std::string::npos) << e.what();
  }
}

// Found by corrupting the demo's model one field at a time (2026-11-28):
// these three loaded and ran, exit 0. A lin_slack of 7 acted as 1; a layer
// kind no reader knows and two layers stacked at one order were taken as
// they came (the wound's columns follow the order).
TEST_F(LoaderTest, SlackKindAndOrderAreChecked) {
  auto refused = [&](const char* name, auto&& spoil, const std::string& want) { expect_spoiled_refused(name, spoil, want); };
  const std::string g = "/layers/" + block.layers[1].first + ": ";
  refused("slack.h5", [](auto& b) { b.layers[1].second.lin_slack[3] = 7; },
          g + "linear spring 3 has lin_slack 7 (0: always acts, 1: acts when longer than its rest length)");
  refused("kind.h5", [](auto& b) { b.layers[1].second.kind = "jelly"; },
          g + "attribute kind must be tetra, lattice or rigid, not 'jelly'");
  refused("order.h5", [](auto& b) { b.layers[2].second.order = b.layers[1].second.order; },
          "have the same order");
  refused("negative_order.h5", [](auto& b) { b.layers[2].second.order = -1; }, "attribute order must be in 0..1000000, not -1");
  // the block as written loads (the spoils above are what is refused)
  ModelReader r(file);
  EXPECT_NO_THROW(load_model(r, LoadRequest{}));
}

// Finite but absurd: a node at 1e300 m or a rest length of 1e300 m (their
// squares overflow) made every step non-finite and wrote inf strains into the
// series; refused naming the file, the layer and the node or spring.
TEST_F(LoaderTest, CoordinatesAndLengthsBeyondAMillionMetresAreRejected) {
  auto expect_refused = [&](const char* name, auto&& spoil, const std::string& what) { expect_spoiled_refused(name, spoil, what); };
  expect_refused("far.h5", [](auto& b) { b.layers[1].second.nodes(5, 1) = 1e300; },
                 "has a non-finite position or one beyond 1e6 m");
  expect_refused("long.h5", [](auto& b) { b.layers[1].second.lin_rest_length[0] = 1e300; },
                 "linear spring 0 has an invalid rest length (negative, non-finite or beyond 1e6 m)");
  // a kilometre is still a (strange) model
  auto ok = block;
  ok.layers[1].second.nodes(5, 1) += 1e3;
  write_model_file(dir / "km.h5", ok);
  ModelReader r(dir / "km.h5");
  EXPECT_NO_THROW(load_model(r, LoadRequest{}));
}

TEST_F(LoaderTest, VesselTubesAreReadOnRequestAndChecked) {
  {
    ModelReader r(file);
    LoadRequest req;
    req.vessels = {"artery"};
    req.vessel_tubes = true;
    Model m = load_model(r, req);
    EXPECT_TRUE(read_any(r.h5().stats(), "/vessels/artery/tube_vertices"));
    ASSERT_EQ(m.vessels.size(), 1u);
    EXPECT_EQ(m.vessels[0].tube_vertices.size(), 12u * 3);
    // quads split as (a, b, c), (a, c, d): the first quad of the test tube is (0, 1, 5, 4)
    const std::vector<std::int32_t> first(m.vessels[0].tube_triangles.begin(), m.vessels[0].tube_triangles.begin() + 6);
    EXPECT_EQ(first, (std::vector<std::int32_t>{0, 1, 5, 0, 5, 4}));
  }
  // a tube face naming a vertex that is not there
  {
    VesselTree t;
    t.nodes.resize(2, 3);
    t.nodes << 0, 0, 0, 0, 0, 0.01;
    t.radii.resize(2);
    t.radii << 1e-3, 1e-3;
    t.edges.resize(1, 2);
    t.edges << 0, 1;
    t.tube_vertices.resize(3, 3);
    t.tube_vertices << 0, 0, 0, 1e-3, 0, 0, 0, 1e-3, 0;
    t.tube_tris.resize(1, 3);
    t.tube_tris << 0, 1, 3;
    ModelWriter w(file, ModelWriter::Start::update);
    w.write("bad", t);
    w.commit();
  }
  ModelReader r(file);
  LoadRequest req;
  req.vessels = {"bad"};
  EXPECT_NO_THROW(load_model(r, req)) << "the tube is not read without vessel_tubes";
  req.vessel_tubes = true;
  try {
    load_model(r, req);
    FAIL() << "out-of-range tube id accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("/vessels/bad: a tube face has a vertex id out of range"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace orthosim::runtime
