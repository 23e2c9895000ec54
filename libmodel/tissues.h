// The tissue table (tissues.json): one file shared by segment, build and tune.
//
// File format (JSON, units in the keys; see docs/tissues.md):
// {
//   "format": "orthosim-tissues/1",
//   "tissues": [
//     { "name": "skin", "label": 1, "rgb": [[205, 160, 140]], "density_kg_m3": 1090,
//       "layer": "tetra", "inside": null,
//       "mechanics": {"model": "biphasic", "k1_kpa": 0.1, "turning_strain": 0.4,
//                     "k2_kpa": 18.8, "weights": [1, 1, 1]},
//       "source": "..." }, ... ] }
//
// In memory everything is SI (Pa, kg/m^3).
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace orthosim {

// A tissue's range of moduli, kPa: softer than any tissue (brain, fat: ~0.1 kPa)
// to stiffer than cortical bone (~2e7 kPa) by decades; beyond, a unit slip. The
// table parser and tune's targets (tune::validate) both keep to it.
inline constexpr double kMinModulusKpa = 1e-3, kMaxModulusKpa = 1e9;

struct Mechanics {
  enum class Model { none, linear, biphasic };
  Model model = Model::none;
  double k_pa = 0;            // linear: modulus (Pa)
  double k1_pa = 0;           // biphasic: low-strain modulus (Pa)
  double turning_strain = 0;  // biphasic: strain where the second phase starts
  double k2_pa = 0;           // biphasic: high-strain modulus (Pa)
  std::vector<double> weights;  // Eq. 1 weights: 3 for biphasic (K1, turning, K2), 1 for linear
};

struct Tissue {
  std::string name;
  std::uint8_t label = 0;                          // 1..255; 0 is background
  std::vector<std::array<std::uint8_t, 3>> rgb;    // colour prototypes (sRGB)
  double density_kg_m3 = 0;
  std::string layer;                               // tetra | lattice | rigid | vessel | none
  std::string inside;                              // the tissue that encloses this one ("" = none)
  Mechanics mechanics;
  std::string source;                              // where the numbers come from
};

struct TissueTable {
  std::string path;  // file it came from (for messages)
  std::string background_name = "background";
  std::vector<std::array<std::uint8_t, 3>> background_rgb;  // embedding colour prototypes
  std::vector<Tissue> tissues;

  const Tissue* find(const std::string& name) const;
  const Tissue* by_label(int label) const;
  // label_names()[v] names label value v ("" where no tissue has it).
  std::vector<std::string> label_names() const;
  // Depth of nesting: 0 for a tissue with no "inside", 1 + depth(inside).
  int depth(const Tissue& t) const;
};

// Parses and validates. Throws Error(path, ...) on unknown keys, values of the
// wrong type, duplicate names or labels, out-of-range or inconsistent values
// (K2 < K1, turning strain <= 0 or >= 1, negative density), unknown "inside"
// or cycles (a tissue inside itself included), and one colour prototype
// given to two tissues (or a tissue and the background). "background" and its
// "rgb" are optional here (build and tune use no colours); segmentation
// requires the background's colour (require_background_colour).
TissueTable parse_tissue_table(const std::string& json_text, const std::string& path);
TissueTable load_tissue_table(const std::string& path);
// Segmentation needs the embedding medium's colour (background.rgb): without
// it every pixel is some tissue, and the background normalisation, the hole
// filling and the body's outline have nothing to work from. Throws
// Error(table.path, ...) when the table has none.
void require_background_colour(const TissueTable& table);
std::string to_json(const TissueTable& table);  // kPa in the file, as read

}  // namespace orthosim
