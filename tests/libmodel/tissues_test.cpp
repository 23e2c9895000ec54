#include "libmodel/tissues.h"
#include "libmodel/format/types.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>

using namespace orthosim;

namespace {
const char* kGood = R"({
  "format": "orthosim-tissues/1",
  "background": {"rgb": [[90, 110, 140]]},
  "tissues": [
    {"name": "skin", "label": 1, "rgb": [[205, 160, 140]], "density_kg_m3": 1090, "layer": "tetra",
     "mechanics": {"model": "biphasic", "k1_kpa": 0.1, "turning_strain": 0.4, "k2_kpa": 18.8, "weights": [1, 2, 1]},
     "source": "paper Table 1"},
    {"name": "fat", "label": 2, "rgb": [230, 200, 120], "density_kg_m3": 950, "layer": "lattice", "inside": "skin",
     "mechanics": {"model": "linear", "k_kpa": 2.3}},
    {"name": "bone", "label": 4, "rgb": [[230, 225, 210]], "density_kg_m3": 1920, "layer": "rigid", "inside": "fat"}
  ]})";

std::string replace(std::string s, const std::string& a, const std::string& b) {
  auto k = s.find(a);
  EXPECT_NE(k, std::string::npos) << a;
  return s.replace(k, a.size(), b);
}

void expect_error(const std::string& text, const std::string& needle) {
  try {
    parse_tissue_table(text, "t.json");
    ADD_FAILURE() << "expected error with '" << needle << "'";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    EXPECT_EQ(std::string(e.what()).rfind("t.json: ", 0), 0u) << e.what();
  }
}
}  // namespace

TEST(Tissues, ParsesInSiUnits) {
  auto t = parse_tissue_table(kGood, "t.json");
  ASSERT_EQ(t.tissues.size(), 3u);
  const Tissue* skin = t.find("skin");
  ASSERT_NE(skin, nullptr);
  EXPECT_EQ(skin->mechanics.model, Mechanics::Model::biphasic);
  EXPECT_DOUBLE_EQ(skin->mechanics.k1_pa, 100.0);
  EXPECT_DOUBLE_EQ(skin->mechanics.k2_pa, 18800.0);
  EXPECT_DOUBLE_EQ(skin->mechanics.turning_strain, 0.4);
  EXPECT_EQ(skin->mechanics.weights, (std::vector<double>{1, 2, 1}));
  EXPECT_DOUBLE_EQ(t.find("fat")->mechanics.k_pa, 2300.0);
  EXPECT_EQ(t.find("fat")->rgb.size(), 1u);  // a single [r,g,b] is accepted
  EXPECT_EQ(t.depth(*t.find("bone")), 2);
  auto names = t.label_names();
  ASSERT_EQ(names.size(), 5u);
  EXPECT_EQ(names[4], "bone");
  EXPECT_EQ(names[3], "");
  EXPECT_EQ(t.by_label(2)->name, "fat");
}

TEST(Tissues, JsonRoundTrip) {
  auto t = parse_tissue_table(kGood, "t.json");
  auto t2 = parse_tissue_table(to_json(t), "t2.json");
  EXPECT_EQ(to_json(t), to_json(t2));
  EXPECT_DOUBLE_EQ(t2.find("skin")->mechanics.k2_pa, 18800.0);
}

TEST(Tissues, RejectsBadTables) {
  expect_error("{", "not valid JSON");
  expect_error(replace(kGood, "\"density_kg_m3\": 950", "\"density_kg_m3\": -950"), "density_kg_m3 must be > 0");
  // an rgb value beyond 32 bits was read wrapped (4294967522 -> 226) and taken; a tissue could take the background's name
  expect_error(replace(kGood, "[230, 200, 120]", "[4294967526, 200, 120]"), "rgb values must be integers in 0..255, not 4294967526");
  expect_error(replace(kGood, "[230, 200, 120]", "[-1, 200, 120]"), "rgb values must be integers in 0..255");
  expect_error(replace(kGood, "\"name\": \"fat\"", "\"name\": \"background\""), "tissue 'background' has the background's name");
  // /layers/sets holds the node sets: build merged a tissue named so into them (sweep of 2026-11-27)
  expect_error(replace(replace(kGood, "\"name\": \"fat\"", "\"name\": \"sets\""), "\"inside\": \"fat\"", "\"inside\": \"sets\""),
               "tissue 'sets': the name is reserved");
  // tune's range: build made springs of 1.7e31 N/m from 1e30 kPa that tune then refused as a unit slip
  expect_error(replace(kGood, "\"k_kpa\": 2.3", "\"k_kpa\": 1e30"),
               "tissue 'fat' mechanics: k_kpa = 1e+30 is outside a tissue's range, 1e-3 .. 1e9 kPa (a unit slip?)");
  expect_error(replace(kGood, "\"k1_kpa\": 0.1", "\"k1_kpa\": 1e-30"), "k1_kpa = 1e-30 is outside a tissue's range");
  EXPECT_NO_THROW(parse_tissue_table(replace(kGood, "\"k_kpa\": 2.3", "\"k_kpa\": 1e9"), "t.json"));
  // K2 = K1 is a linear law: its turning strain cannot be tuned (12 % off after 4000 experiments)
  expect_error(replace(kGood, "\"k2_kpa\": 18.8", "\"k2_kpa\": 0.1"), "k2_kpa equals k1_kpa: the law is linear");
  EXPECT_NO_THROW(parse_tissue_table(replace(kGood, "\"k1_kpa\": 0.1", "\"k1_kpa\": 1e-3"), "t.json"));
  expect_error(replace(kGood, "\"model\": \"linear\"", "\"model\": 3"), "mechanics 'model' must be \"linear\" or \"biphasic\", not 3");
  // a unit slip (g/cm^3) and impossible densities were taken, making every node's mass 1000x off
  expect_error(replace(kGood, "\"density_kg_m3\": 950", "\"density_kg_m3\": 0.95"),
               "tissue 'fat': density_kg_m3 0.95 is no tissue's (100 to 22 600 kg/m^3, a tenth of water's up to osmium's); "
               "0.95 g/cm^3 is 950 kg/m^3");
  expect_error(replace(kGood, "\"density_kg_m3\": 950", "\"density_kg_m3\": 0.001"), "density_kg_m3 0.001 is no tissue's");
  expect_error(replace(kGood, "\"density_kg_m3\": 950", "\"density_kg_m3\": 1e6"), "density_kg_m3 1e+06 is no tissue's");
  EXPECT_NO_THROW(parse_tissue_table(replace(kGood, "\"density_kg_m3\": 950", "\"density_kg_m3\": 250"), "t.json"))
      << "inflated lung";
  expect_error(replace(kGood, "\"k2_kpa\": 18.8", "\"k2_kpa\": 0.05"), "k2_kpa must not be smaller");
  expect_error(replace(kGood, "\"turning_strain\": 0.4", "\"turning_strain\": 0"), "turning_strain");
  expect_error(replace(kGood, "\"label\": 2", "\"label\": 1"), "duplicate label 1");
  expect_error(replace(kGood, "\"name\": \"fat\"", "\"name\": \"skin\""), "duplicate tissue name");
  expect_error(replace(kGood, "\"layer\": \"tetra\"", "\"layer\": \"tetra\", \"colour\": 1"), "unknown key 'colour'");
  expect_error(replace(kGood, "\"inside\": \"skin\"", "\"inside\": \"liver\""), "unknown tissue 'liver'");
  expect_error(replace(kGood, "\"weights\": [1, 2, 1]", "\"weights\": [0, 0, 0]"), "at least one weight");
  expect_error(replace(kGood, "\"k_kpa\": 2.3", "\"k_kpa\": -1"), "k_kpa must be > 0");
  expect_error(replace(kGood, "\"label\": 4", "\"label\": 0"), "label must be in 1..255");
  expect_error(replace(kGood, "orthosim-tissues/1", "other/2"), "format");
  expect_error(replace(kGood, "[[230, 225, 210]]", "[[230, 225, 300]]"), "0..255");
  // a units block other than the keys' units (its moduli in MPa were read as kPa)
  expect_error(replace(kGood, "\"format\": \"orthosim-tissues/1\",", "\"format\": \"orthosim-tissues/1\", \"units\": {\"moduli\": \"MPa\"},"),
               "units: moduli is \"MPa\", but the table's moduli keys are in kPa (k1_kpa, k2_kpa, k_kpa)");
  expect_error(replace(kGood, "\"format\": \"orthosim-tissues/1\",", "\"format\": \"orthosim-tissues/1\", \"units\": {\"density\": \"g/cm^3\"},"),
               "units: density is \"g/cm^3\"");
  EXPECT_NO_THROW(parse_tissue_table(replace(kGood, "\"format\": \"orthosim-tissues/1\",",
                                             "\"format\": \"orthosim-tissues/1\", \"units\": {\"moduli\": \"kPa\", \"density\": \"kg/m3\", \"rgb\": \"sRGB 0..255\"},"),
                                     "t.json"));
  // colours in other units, and a unit the table does not know, were accepted and ignored
  expect_error(replace(kGood, "\"format\": \"orthosim-tissues/1\",", "\"format\": \"orthosim-tissues/1\", \"units\": {\"rgb\": \"sRGB 0..1\"},"),
               "units: rgb is \"sRGB 0..1\", but the table's rgb keys are in 8-bit sRGB 0..255");
  expect_error(replace(kGood, "\"format\": \"orthosim-tissues/1\",", "\"format\": \"orthosim-tissues/1\", \"units\": {\"length\": \"mm\"},"),
               "units: unknown key 'length'");
  // a key twice (the last won, silently)
  expect_error(replace(kGood, "\"density_kg_m3\": 950,", "\"density_kg_m3\": 950, \"density_kg_m3\": 900,"),
               "the key 'density_kg_m3' appears twice in one object");
  // an inside cycle
  expect_error(replace(replace(kGood, "\"layer\": \"tetra\",", "\"layer\": \"tetra\", \"inside\": \"bone\","),
                       "\"inside\": \"fat\"", "\"inside\": \"skin\""),
               "cycle");
}

TEST(Tissues, WrongTypesSayWhatIsExpected) {
  // a label given as a string is there, just of the wrong type
  expect_error(replace(kGood, "\"label\": 2", "\"label\": \"2\""), "tissue 'fat': 'label' must be an integer in 1..255, not \"2\"");
  expect_error(replace(kGood, "\"label\": 2", "\"label\": 2.5"), "'label' must be an integer");
  expect_error(replace(kGood, "\"label\": 2, ", ""), "tissue 'fat': missing 'label'");
  expect_error(replace(kGood, "\"background\": {\"rgb\"", "\"background\": {\"name\": 7, \"rgb\""),
               "background: 'name' must be a non-empty string");
  expect_error(replace(kGood, "\"background\": {\"rgb\": [[90, 110, 140]]}", "\"background\": [90, 110, 140]"),
               "'background' must be an object");
}

TEST(Tissues, RejectsATissueInsideItself) {
  expect_error(replace(kGood, "\"inside\": \"skin\"", "\"inside\": \"fat\""),
               "tissue 'fat': 'inside' names the tissue itself");
}

TEST(Tissues, RejectsOneColourForTwoTissues) {
  // the same prototype on two tissues, among others of theirs
  expect_error(replace(kGood, "\"rgb\": [[230, 225, 210]]", "\"rgb\": [[1, 2, 3], [205, 160, 140]]"),
               "tissue 'skin' and tissue 'bone' have the same colour prototype [205, 160, 140]");
  // a tissue with the background's colour
  expect_error(replace(kGood, "\"rgb\": [230, 200, 120]", "\"rgb\": [90, 110, 140]"),
               "background 'background' and tissue 'fat' have the same colour prototype [90, 110, 140]");
  // the same colour twice in one tissue splits nothing: accepted
  EXPECT_NO_THROW(parse_tissue_table(replace(kGood, "\"rgb\": [[230, 225, 210]]", "\"rgb\": [[230, 225, 210], [230, 225, 210]]"),
                                     "t.json"));
}

// The background and its colour are optional in the table (build and tune
// use no colours); orthosim segment requires the colour (cli_test).
TEST(Tissues, BackgroundIsOptionalInTheTable) {
  const auto t = parse_tissue_table(replace(kGood, "\"background\": {\"rgb\": [[90, 110, 140]]},", ""), "t.json");
  EXPECT_TRUE(t.background_rgb.empty());
  EXPECT_EQ(t.background_name, "background");
  try {
    require_background_colour(t);
    ADD_FAILURE() << "segmentation without a background colour";
  } catch (const Error& e) {
    EXPECT_EQ(std::string(e.what()).rfind("t.json: no background colour: segmentation needs", 0), 0u) << e.what();
  }
  EXPECT_NO_THROW(require_background_colour(parse_tissue_table(kGood, "t.json")));
}

TEST(Tissues, MissingFileIsAClearError) {
  try {
    load_tissue_table("/nonexistent/tissues.json");
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.file(), "/nonexistent/tissues.json");
  }
  // a folder (it said "not valid JSON")
  try {
    load_tissue_table("/tmp");
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(std::string(e.what()), "/tmp: is a folder, not a tissue table (tissues.json)");
  }
}
