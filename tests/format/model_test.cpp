#include "libmodel/format/model.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <map>
#include <random>
#include <tuple>

using namespace orthosim;

namespace {

// Serialises every declared field of a group struct: equality driven by the
// same declaration that drives the file format.
struct Collect {
  std::map<std::string, std::string> bytes;
  template <class M>
  void operator()(const M& m, const char* name, const char*, const char*, const char*) {
    std::string b(reinterpret_cast<const char*>(m.data()), sizeof(typename M::Scalar) * m.size());
    bytes[name] = std::to_string(m.rows()) + ":" + b;
  }
};
template <class S> std::map<std::string, std::string> collect(S s) {
  Collect c;
  s.fields(c);
  return c.bytes;
}

// Fills every field of a group struct with `rows_for(count)` random rows.
struct Fill {
  std::mt19937 rng{42};
  std::map<std::string, int> counts;
  template <class M>
  void operator()(M& m, const char*, const char* count, const char*, const char*) {
    if (!counts.count(count)) counts[count] = 3 + static_cast<int>(counts.size());
    m.resize(counts[count], M::ColsAtCompileTime);
    for (Eigen::Index i = 0; i < m.size(); ++i)
      m.data()[i] = static_cast<typename M::Scalar>(rng() % 3);  // small: valid as ids too
  }
};
template <class S> S filled() {
  S s;
  Fill f;
  s.fields(f);
  return s;
}

// a layer of random rows whose kind a reader knows
Layer filled_layer() {
  auto l = filled<Layer>();
  l.kind = "lattice";
  return l;
}

Volume small_volume() {
  Volume v;
  v.nx = 4;
  v.ny = 3;
  v.nz = 2;
  v.spacing_m = {0.3e-3, 0.3e-3, 1e-3};
  v.origin_m = {-1e-3, 2e-3, 0};
  v.labels.resize(24);
  for (int i = 0; i < 24; ++i) v.labels[i] = static_cast<std::uint8_t>(i % 4);
  v.label_names = {"background", "skin", "fat", "muscle"};
  return v;
}

}  // namespace

TEST(ModelFile, EveryGroupRoundTrips) {
  test::TempDir dir("model");
  const std::string p = dir / "m.h5";
  Volume vol = small_volume();
  auto surf = filled<Surface>();
  auto quads = filled<QuadSurface>();
  quads.nu = 1;
  quads.nv = static_cast<int>(quads.vertices.rows());
  quads.uv = quads.uv.cwiseMin(1.0);  // texture coordinates lie in [0, 1]
  auto layer = filled<Layer>();
  layer.tissue = "fat";
  layer.kind = "lattice";
  layer.order = 1;
  layer.node_offset = 12;
  auto tree = filled<VesselTree>();
  auto tuning = filled<Tuning>();
  tuning.method = "sa";
  tuning.seed = 9;
  tuning.psi = 1e-5;
  tuning.evaluations = 321;
  tuning.seconds = 1.5;
  VecXi set(3);
  set << 0, 5, 7;
  Provenance prov;
  prov.tool_version = "0.1.0";
  prov.command_line = "orthosim build";
  prov.inputs_json = R"({"a":"xxh3:0"})";
  prov.seed = 4;
  prov.wall_s = 0.25;
  {
    ModelWriter w(p, ModelWriter::Start::fresh);
    w.write(vol);
    w.write("skin", surf);
    w.write("skin", quads);
    w.write_layer("fat", layer);
    w.write_node_set("fixed", set);
    w.write("artery", tree);
    w.write("skin", tuning);
    w.write("build", prov);
    w.commit();
  }
  ModelReader r(p);
  EXPECT_EQ(r.version(), format_version());
  Volume v2 = r.volume();
  EXPECT_EQ(v2.labels, vol.labels);
  EXPECT_EQ(v2.nx, 4);
  EXPECT_EQ(v2.nz, 2);
  EXPECT_EQ(v2.spacing_m, vol.spacing_m);
  EXPECT_EQ(v2.origin_m, vol.origin_m);
  EXPECT_EQ(v2.label_names, vol.label_names);
  EXPECT_EQ(v2.at(3, 2, 1), vol.labels[(1 * 3 + 2) * 4 + 3]);
  EXPECT_EQ(collect(r.surface("skin")), collect(surf));
  auto q2 = r.quads("skin");
  EXPECT_EQ(collect(q2), collect(quads));
  EXPECT_EQ(q2.nv, quads.nv);
  auto l2 = r.layer("fat");
  EXPECT_EQ(collect(l2), collect(layer));
  EXPECT_EQ(l2.tissue, "fat");
  EXPECT_EQ(l2.kind, "lattice");
  EXPECT_EQ(l2.order, 1);
  EXPECT_EQ(l2.node_offset, 12);
  EXPECT_EQ(r.node_set("fixed"), set);
  EXPECT_EQ(collect(r.vessels("artery")), collect(tree));
  auto t2 = r.tuning("skin");
  EXPECT_EQ(collect(t2), collect(tuning));
  EXPECT_EQ(t2.method, "sa");
  EXPECT_EQ(t2.evaluations, 321);
  auto pr = r.provenance();
  ASSERT_EQ(pr.count("build"), 1u);
  EXPECT_EQ(pr["build"].command_line, "orthosim build");
  EXPECT_EQ(pr["build"].seed, 4);
  // every dataset carries a unit
  for (const auto& name : r.h5().children("/layers/fat"))
    EXPECT_TRUE(r.h5().has_attr("/layers/fat/" + name, "unit")) << name;
}

TEST(ModelFile, LazyReadTouchesOnlyWhatIsAsked) {
  test::TempDir dir("model");
  const std::string p = dir / "m.h5";
  {
    ModelWriter w(p, ModelWriter::Start::fresh);
    w.write(small_volume());
    w.write_layer("skin", filled_layer());
    w.write("artery", filled<VesselTree>());
    w.commit();
  }
  ModelReader r(p);
  auto l = r.layer_fields("skin", {"nodes", "masses"});
  EXPECT_GT(l.nodes.rows(), 0);
  EXPECT_EQ(l.springs.rows(), 0);
  EXPECT_EQ(r.h5().stats().datasets_read, 2);
  for (const auto& path : r.h5().stats().paths_read) EXPECT_EQ(path.rfind("/layers/skin/", 0), 0u) << path;
}

TEST(ModelFile, UpdateAddsGroupsAndKeepsOthers) {
  test::TempDir dir("model");
  const std::string p = dir / "m.h5";
  {
    ModelWriter w(p, ModelWriter::Start::fresh);
    w.write(small_volume());
    w.commit();
  }
  {
    ModelWriter w(p, ModelWriter::Start::update);
    w.write("skin", filled<Surface>());
    w.commit();
  }
  ModelReader r(p);
  EXPECT_TRUE(r.has("/volume/labels"));
  EXPECT_TRUE(r.has("/surfaces/skin/faces"));
}

TEST(ModelFile, FailedWriteLeavesExistingFileUntouched) {
  test::TempDir dir("model");
  const std::string p = dir / "m.h5";
  {
    ModelWriter w(p, ModelWriter::Start::fresh);
    w.write(small_volume());
    w.commit();
  }
  const std::string before = test::read_file(p);
  try {
    ModelWriter w(p, ModelWriter::Start::update);
    w.write("skin", filled<Surface>());
    Surface bad = filled<Surface>();
    bad.faces(0, 0) = 999;  // out of range: the stage fails mid-way
    w.write("fat", bad);
    w.commit();
    FAIL() << "expected an error";
  } catch (const Error&) {
  }
  EXPECT_EQ(test::read_file(p), before);
  // and no temporary file is left behind
  int files = 0;
  for (auto& e : std::filesystem::directory_iterator(dir.path)) files += e.is_regular_file();
  EXPECT_EQ(files, 1);
}

// Layer::volume_tets, the volume term's own tetrahedra (a tetra layer's grid
// prisms): an optional dataset, read whole or by name, absent in older files
// (read empty), written only with a volume_modulus and in whole groups.
TEST(ModelFile, VolumeTetsAreOptional) {
  test::TempDir dir("model");
  Layer l = filled_layer();
  l.kind = "tetra";
  l.volume_modulus = 800;
  l.volume_group = 4;
  l.volume_tets.resize(8, 4);
  for (Eigen::Index i = 0; i < l.volume_tets.size(); ++i) l.volume_tets.data()[i] = static_cast<std::int32_t>(i % 3);
  Layer plain = filled_layer();
  {
    ModelWriter w(dir / "m.h5", ModelWriter::Start::fresh);
    w.write_layer("skin", l);
    w.write_layer("fat", plain);
    w.commit();
  }
  ModelReader r(dir / "m.h5");
  const Layer a = r.layer("skin");
  EXPECT_EQ(a.volume_tets, l.volume_tets);
  EXPECT_EQ(a.volume_group, 4);
  EXPECT_EQ(r.layer_fields("skin", {"volume_tets"}).volume_tets, l.volume_tets);
  EXPECT_EQ(r.layer_fields("skin", {"tets"}).volume_tets.rows(), 0);  // only what is asked
  EXPECT_TRUE(r.h5().has_attr("/layers/skin/volume_tets", "unit"));
  EXPECT_EQ(r.layer("fat").volume_tets.rows(), 0);
  EXPECT_FALSE(r.h5().exists("/layers/fat/volume_tets"));
  // not in whole groups, or without a term: refused, the file untouched
  for (const auto& [modulus, rows, what] : std::vector<std::tuple<double, int, std::string>>{
           {800.0, 7, "groups of volume_group"}, {0.0, 8, "without a volume_modulus"}}) {
    Layer bad = l;
    bad.volume_modulus = modulus;
    bad.volume_tets.conservativeResize(rows, 4);
    ModelWriter w(dir / "m.h5", ModelWriter::Start::update);
    try {
      w.write_layer("skin", bad);
      ADD_FAILURE() << what;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  }
  EXPECT_EQ(ModelReader(dir / "m.h5").layer("skin").volume_tets, l.volume_tets);
}

TEST(ModelFile, CountMismatchIsRejectedOnWrite) {
  test::TempDir dir("model");
  Layer l = filled_layer();
  l.masses.resize(l.nodes.rows() + 1);
  ModelWriter w(dir / "m.h5", ModelWriter::Start::fresh);
  try {
    w.write_layer("skin", l);
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("n_nodes"), std::string::npos) << e.what();
  }
}

TEST(ModelFile, BadFilesFailWithClearMessages) {
  test::TempDir dir("model");
  const std::string good = dir / "good.h5";
  {
    ModelWriter w(good, ModelWriter::Start::fresh);
    w.write(small_volume());
    w.write_layer("skin", filled_layer());
    w.commit();
  }
  auto expect_error = [](const std::function<void()>& f, const std::string& needle) {
    try {
      f();
      ADD_FAILURE() << "expected an error containing '" << needle << "'";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  expect_error([&] { ModelReader r(dir / "nope.h5"); }, "missing or unreadable");
  test::write_file(dir / "text.h5", "not hdf5");
  expect_error([&] { ModelReader r(dir / "text.h5"); }, "not an HDF5 file");
  // truncated: the first half of a valid file
  std::string bytes = test::read_file(good);
  test::write_file(dir / "trunc.h5", bytes.substr(0, bytes.size() / 2));
  expect_error(
      [&] {
        ModelReader r(dir / "trunc.h5");
        r.layer("skin");
        r.volume();
      },
      "");
  // plain HDF5, not ours
  { h5::File f(dir / "plain.h5", h5::File::Mode::create); }
  expect_error([&] { ModelReader r(dir / "plain.h5"); }, "not an orthosim model file");
  // newer major version
  std::filesystem::copy_file(good, dir / "new.h5");
  {
    h5::File f(dir / "new.h5", h5::File::Mode::read_write);
    f.set_attr("/", "orthosim_format", "2.0");
  }
  expect_error([&] { ModelReader r(dir / "new.h5"); }, "newer");
  // missing dataset, wrong shape, wrong dtype
  std::filesystem::copy_file(good, dir / "broken.h5");
  {
    h5::File f(dir / "broken.h5", h5::File::Mode::read_write);
    f.remove("/layers/skin/k1");
    std::vector<double> x(8);
    f.write<double>("/layers/skin/nodes", x.data(), {4, 2}, "m");
    std::vector<float> y(3);
    f.write<float>("/layers/skin/masses", y.data(), {3}, "kg");
  }
  ModelReader broken(dir / "broken.h5");
  expect_error([&] { broken.layer_fields("skin", {"k1"}); }, "missing dataset /layers/skin/k1");
  expect_error([&] { broken.layer_fields("skin", {"nodes"}); }, "expected (n x 3)");
  expect_error([&] { broken.layer_fields("skin", {"masses"}); }, "float32");
  expect_error([&] { broken.layer("fat"); }, "missing group /layers/fat");
  ModelReader ok(good);
  expect_error([&] { ok.vessels("artery"); }, "missing group");
  // values no writer makes (a corrupted model's, 2026-11-28): read as they came before
  std::filesystem::copy_file(good, dir / "values.h5");
  {
    ModelWriter w(dir / "values.h5", ModelWriter::Start::update);
    auto q = filled<QuadSurface>();
    q.nu = 1, q.nv = static_cast<int>(q.vertices.rows());
    q.uv = q.uv.cwiseMin(1.0);
    q.uv(2, 1) = -0.5;
    w.write("skin", q);
    auto l = filled_layer();
    l.kind = "jelly";
    w.write_layer("fat", l);
    w.commit();
  }
  ModelReader values(dir / "values.h5");
  expect_error([&] { values.quads("skin"); }, "/quads/skin/uv: vertex 2 has a texture coordinate outside [0, 1] (-0.5");
  expect_error([&] { values.layer("fat"); }, "/layers/fat: attribute kind must be tetra, lattice or rigid, not 'jelly'");
}

// Every label with voxels needs a name: surface crashed (SIGSEGV, after its
// output folder was committed) on labels past label_names, and left out an
// unnamed label silently (sweep of 2026-11-27). Labels without voxels may
// stay unnamed (a table with labels 200 and 255 names 256 entries, most "").
TEST(ModelFile, EveryLabelWithVoxelsHasAName) {
  test::TempDir dir("model-labels");
  auto volume_of = [&](const std::string& name, const std::vector<std::string>& names) {
    Volume v = small_volume();
    v.label_names = names;
    const std::string p = dir / name;
    ModelWriter w(p, ModelWriter::Start::fresh);
    w.write(v);
    w.commit();
    return p;
  };
  auto error_of = [](const std::string& p) {
    try {
      ModelReader(p).volume();
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  const std::string shortp = volume_of("short.h5", {"background", "skin"});
  EXPECT_EQ(error_of(shortp), shortp + ": /volume/labels holds label 2 but label_names has 2 entries");
  const std::string empty = volume_of("empty.h5", {"background", "skin", "", "muscle"});
  EXPECT_EQ(error_of(empty), empty + ": /volume/labels holds label 2, which label_names leaves unnamed");
  std::vector<std::string> sparse(256);
  sparse[0] = "background", sparse[1] = "skin", sparse[2] = "fat", sparse[3] = "muscle";
  EXPECT_EQ(error_of(volume_of("sparse.h5", sparse)), "");
}
