#include "libmodel/tissues.h"

#include "libmodel/format/json.h"
#include "libmodel/format/types.h"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <map>
#include <set>
#include <sstream>

namespace orthosim {

using nlohmann::json;

const Tissue* TissueTable::find(const std::string& name) const {
  for (const auto& t : tissues)
    if (t.name == name) return &t;
  return nullptr;
}

const Tissue* TissueTable::by_label(int label) const {
  for (const auto& t : tissues)
    if (t.label == label) return &t;
  return nullptr;
}

std::vector<std::string> TissueTable::label_names() const {
  int top = 0;
  for (const auto& t : tissues) top = std::max(top, static_cast<int>(t.label));
  std::vector<std::string> names(static_cast<std::size_t>(top) + 1);
  names[0] = background_name;
  for (const auto& t : tissues) names[t.label] = t.name;
  return names;
}

int TissueTable::depth(const Tissue& t) const {
  int d = 0;
  const Tissue* cur = &t;
  while (cur && !cur->inside.empty() && d <= static_cast<int>(tissues.size())) {
    cur = find(cur->inside);
    ++d;
  }
  return d;
}

namespace {

void check_keys(const json& j, const std::set<std::string>& allowed, const std::string& path,
                const std::string& where) {
  for (auto it = j.begin(); it != j.end(); ++it)
    if (!allowed.count(it.key())) throw Error(path, where + ": unknown key '" + it.key() + "'");
}

double number(const json& j, const char* key, const std::string& path, const std::string& where) {
  if (!j.contains(key)) throw Error(path, where + ": missing '" + key + "'");
  if (!j[key].is_number()) throw Error(path, where + ": '" + key + "' must be a number");
  double v = j[key].get<double>();
  if (!std::isfinite(v)) throw Error(path, where + ": '" + key + "' must be finite");
  return v;
}

std::vector<std::array<std::uint8_t, 3>> colours(const json& j, const std::string& path, const std::string& where) {
  if (!j.is_array() || j.empty()) throw Error(path, where + ": 'rgb' must be a non-empty list of [r,g,b]");
  // accept a single [r,g,b] too
  json list = j[0].is_number() ? json::array({j}) : j;
  std::vector<std::array<std::uint8_t, 3>> out;
  for (const auto& c : list) {
    if (!c.is_array() || c.size() != 3) throw Error(path, where + ": each rgb prototype needs 3 values");
    std::array<std::uint8_t, 3> rgb{};
    for (int k = 0; k < 3; ++k) {
      // read as 64 bits: an int read wrapped 4294967522 to 226, which was taken
      if (!c[k].is_number_integer() || (c[k].is_number_unsigned() && c[k].get<std::uint64_t>() > 255) ||
          c[k].get<std::int64_t>() < 0 || c[k].get<std::int64_t>() > 255)
        throw Error(path, where + ": rgb values must be integers in 0..255, not " + c[k].dump());
      rgb[k] = static_cast<std::uint8_t>(c[k].get<std::int64_t>());
    }
    out.push_back(rgb);
  }
  return out;
}

// kMinModulusKpa .. kMaxModulusKpa, tune's range too: build used a k of 1e30 kPa
// (springs of 1.7e31 N/m, exit 0) that tune then refused. (kPa as the table
// gives it: 1e308 kPa is infinite in Pa)
void modulus_range(double kpa, const char* key, const std::string& path, const std::string& where) {
  if (kpa < kMinModulusKpa || kpa > kMaxModulusKpa)
    throw Error(path, where + ": " + key + " = " + (std::ostringstream() << std::setprecision(10) << kpa).str() +
                          " is outside a tissue's range, 1e-3 .. 1e9 kPa (a unit slip?)");
}

Mechanics parse_mechanics(const json& m, const std::string& path, const std::string& where) {
  Mechanics out;
  if (!m.is_object()) throw Error(path, where + ": 'mechanics' must be an object");
  if (!m.contains("model")) throw Error(path, where + ": mechanics needs a 'model'");
  if (!m["model"].is_string()) throw Error(path, where + ": mechanics 'model' must be \"linear\" or \"biphasic\", not " + m["model"].dump());
  const std::string model = m["model"];
  const std::string w = where + " mechanics";
  if (model == "biphasic") {
    check_keys(m, {"model", "k1_kpa", "turning_strain", "k2_kpa", "weights", "note", "tuned"}, path, w);
    out.model = Mechanics::Model::biphasic;
    const double k1_kpa = number(m, "k1_kpa", path, w), k2_kpa = number(m, "k2_kpa", path, w);
    out.k1_pa = k1_kpa * 1e3;
    out.turning_strain = number(m, "turning_strain", path, w);
    out.k2_pa = k2_kpa * 1e3;
    if (!(out.k1_pa > 0)) throw Error(path, w + ": k1_kpa must be > 0");
    if (!(out.k2_pa > 0)) throw Error(path, w + ": k2_kpa must be > 0");
    modulus_range(k1_kpa, "k1_kpa", path, w);
    modulus_range(k2_kpa, "k2_kpa", path, w);
    if (out.k2_pa < out.k1_pa) throw Error(path, w + ": k2_kpa must not be smaller than k1_kpa");
    // one stiffness on both sides of the turning strain is a linear law, whose
    // turning strain no experiment can find (tune ended 12 % off after 4000)
    if (out.k2_pa == out.k1_pa)
      throw Error(path, w + ": k2_kpa equals k1_kpa: the law is linear (write \"model\": \"linear\" with k_kpa)");
    if (!(out.turning_strain > 0 && out.turning_strain < 1))
      throw Error(path, w + ": turning_strain must lie in (0, 1)");
    out.weights = {1, 1, 1};
  } else if (model == "linear") {
    check_keys(m, {"model", "k_kpa", "weights", "note", "tuned"}, path, w);
    out.model = Mechanics::Model::linear;
    const double k_kpa = number(m, "k_kpa", path, w);
    out.k_pa = k_kpa * 1e3;
    if (!(out.k_pa > 0)) throw Error(path, w + ": k_kpa must be > 0");
    modulus_range(k_kpa, "k_kpa", path, w);
    out.weights = {1};
  } else {
    throw Error(path, w + ": model must be 'biphasic' or 'linear', not '" + model + "'");
  }
  if (m.contains("weights")) {
    if (!m["weights"].is_array() || m["weights"].size() != out.weights.size())
      throw Error(path, w + ": 'weights' needs " + std::to_string(out.weights.size()) + " numbers");
    double sum = 0;
    for (std::size_t i = 0; i < out.weights.size(); ++i) {
      if (!m["weights"][i].is_number()) throw Error(path, w + ": weights must be numbers");
      out.weights[i] = m["weights"][i].get<double>();
      if (!(out.weights[i] >= 0) || !std::isfinite(out.weights[i])) throw Error(path, w + ": weights must be >= 0");
      sum += out.weights[i];
    }
    if (!(sum > 0)) throw Error(path, w + ": at least one weight must be positive");
  }
  return out;
}

}  // namespace

TissueTable parse_tissue_table(const std::string& text, const std::string& path) {
  json j;
  std::string twice;
  try {
    j = parse_json_noting_repeats(text, twice);
  } catch (const json::exception& e) {  // parse errors, and numbers beyond double's range (1e400)
    std::string what = e.what();
    for (auto& c : what)
      if (c == '\n') c = ' ';
    throw Error(path, "not valid JSON: " + what);
  }
  if (!twice.empty()) throw Error(path, "not valid JSON: the key '" + twice + "' appears twice in one object");
  if (!j.is_object()) throw Error(path, "tissue table must be a JSON object");
  check_keys(j, {"format", "note", "units", "background", "tissues"}, path, "top level");
  // the keys carry their units (k1_kpa, density_kg_m3): a "units" block that says
  // otherwise is a table written for other units ("moduli": "MPa" was read as kPa)
  if (j.contains("units")) {
    const json& u = j["units"];
    if (!u.is_object()) throw Error(path, "'units' must be an object like {\"moduli\": \"kPa\"}");
    auto lower = [](std::string x) {
      for (auto& c : x) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
      x.erase(std::remove(x.begin(), x.end(), ' '), x.end());
      return x;
    };
    struct Unit {
      const char* key;
      std::vector<std::string> spellings;  // lower case, no spaces
      const char* keys_are;
    };
    // a key it does not know ("colour": "linear") was ignored: refused like any other
    check_keys(u, {"moduli", "density", "rgb"}, path, "units");
    const Unit known[] = {{"moduli", {"kpa"}, "kPa (k1_kpa, k2_kpa, k_kpa)"},
                          {"density", {"kg/m^3", "kg/m3", "kgm^-3"}, "kg/m^3 (density_kg_m3)"},
                          {"rgb", {"srgb0..255", "srgb", "0..255", "srgb(0..255)"}, "8-bit sRGB 0..255"}};
    for (const Unit& k : known) {
      if (!u.contains(k.key)) continue;
      const std::string v = u[k.key].is_string() ? lower(u[k.key].get<std::string>()) : std::string();
      if (std::find(k.spellings.begin(), k.spellings.end(), v) == k.spellings.end())
        throw Error(path, std::string("units: ") + k.key + " is " + u[k.key].dump() + ", but the table's " + k.key +
                              " keys are in " + k.keys_are + ": convert the values and say so");
    }
  }
  if (!j.contains("format") || j["format"] != "orthosim-tissues/1")
    throw Error(path, "missing or unsupported 'format' (expected \"orthosim-tissues/1\")");
  TissueTable t;
  t.path = path;
  if (j.contains("background")) {
    const auto& b = j["background"];
    if (!b.is_object()) throw Error(path, "'background' must be an object like {\"rgb\": [[r, g, b]]}");
    check_keys(b, {"name", "rgb", "note"}, path, "background");
    if (b.contains("name")) {
      if (!b["name"].is_string() || b["name"].get<std::string>().empty())
        throw Error(path, "background: 'name' must be a non-empty string");
      t.background_name = b["name"].get<std::string>();
    }
    if (b.contains("rgb")) t.background_rgb = colours(b["rgb"], path, "background");
  }
  if (!j.contains("tissues") || !j["tissues"].is_array() || j["tissues"].empty())
    throw Error(path, "'tissues' must be a non-empty list");
  std::set<std::string> names;
  std::set<int> labels;
  static const std::set<std::string> layers = {"tetra", "lattice", "rigid", "vessel", "none"};
  for (const auto& e : j["tissues"]) {
    if (!e.is_object()) throw Error(path, "each tissue must be an object");
    if (!e.contains("name") || !e["name"].is_string() || e["name"].get<std::string>().empty())
      throw Error(path, "a tissue has no name");
    Tissue ts;
    ts.name = e["name"];
    // names become file names (surfaces/<name>.stl, plots/<name>.png) and HDF5 groups
    if (ts.name.size() > 64)
      throw Error(path, "tissue '" + ts.name.substr(0, 32) + "...': names may be at most 64 characters long (this one has " +
                            std::to_string(ts.name.size()) + ")");
    // /layers/sets holds the model's node sets: a tissue named so had its layer merged into them
    if (ts.name == "sets") throw Error(path, "tissue 'sets': the name is reserved (the model's node sets); rename the tissue");
    if (ts.name == t.background_name)
      throw Error(path, "tissue '" + ts.name + "' has the background's name (label 0 is the background; rename the tissue)");
    const std::string where = "tissue '" + ts.name + "'";
    check_keys(e, {"name", "label", "rgb", "density_kg_m3", "layer", "inside", "mechanics", "source", "note"},
               path, where);
    for (char c : ts.name)
      if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-'))
        throw Error(path, where + ": names may use letters, digits, '_' and '-' only");
    if (!names.insert(ts.name).second) throw Error(path, "duplicate tissue name '" + ts.name + "'");
    if (!e.contains("label")) throw Error(path, where + ": missing 'label'");
    if (!e["label"].is_number_integer())
      throw Error(path, where + ": 'label' must be an integer in 1..255, not " + e["label"].dump());
    const std::int64_t label = e["label"].get<std::int64_t>();
    if (label < 1 || label > 255) throw Error(path, where + ": label must be in 1..255 (0 is background)");
    if (!labels.insert(static_cast<int>(label)).second) throw Error(path, "duplicate label " + std::to_string(label));
    ts.label = static_cast<std::uint8_t>(label);
    if (!e.contains("rgb")) throw Error(path, where + ": missing 'rgb'");
    ts.rgb = colours(e["rgb"], path, where);
    ts.density_kg_m3 = number(e, "density_kg_m3", path, where);
    if (!(ts.density_kg_m3 > 0)) throw Error(path, where + ": density_kg_m3 must be > 0");
    // No tissue lies outside [100, 22 600] kg/m^3: a tenth of water's (inflated
    // lung, the lightest, is ~250) up to osmium's, the densest element's. A
    // value outside is a unit slip (1.09: g/cm^3) that would make every node's
    // mass 1000x off, silently.
    if (!(ts.density_kg_m3 >= 100 && ts.density_kg_m3 <= 22600)) {
      std::ostringstream m;
      m << where << ": density_kg_m3 " << ts.density_kg_m3
        << " is no tissue's (100 to 22 600 kg/m^3, a tenth of water's up to osmium's)";
      if (ts.density_kg_m3 >= 0.1 && ts.density_kg_m3 < 22.6)
        m << "; " << ts.density_kg_m3 << " g/cm^3 is " << ts.density_kg_m3 * 1000 << " kg/m^3";
      throw Error(path, m.str());
    }
    if (!e.contains("layer") || !e["layer"].is_string() || !layers.count(e["layer"].get<std::string>()))
      throw Error(path, where + ": 'layer' must be one of tetra, lattice, rigid, vessel, none");
    ts.layer = e["layer"];
    if (e.contains("inside") && !e["inside"].is_null()) {
      if (!e["inside"].is_string()) throw Error(path, where + ": 'inside' must be a tissue name");
      ts.inside = e["inside"];
    }
    if (e.contains("mechanics")) ts.mechanics = parse_mechanics(e["mechanics"], path, where);
    if ((ts.layer == "tetra" || ts.layer == "lattice") && ts.mechanics.model == Mechanics::Model::none)
      throw Error(path, where + ": a " + ts.layer + " layer needs 'mechanics'");
    if (e.contains("source") && e["source"].is_string()) ts.source = e["source"];
    t.tissues.push_back(ts);
  }
  for (const auto& ts : t.tissues) {
    if (ts.inside == ts.name) throw Error(path, "tissue '" + ts.name + "': 'inside' names the tissue itself (a cycle)");
    if (!ts.inside.empty() && !t.find(ts.inside))
      throw Error(path, "tissue '" + ts.name + "': 'inside' names unknown tissue '" + ts.inside + "'");
    if (t.depth(ts) > static_cast<int>(t.tissues.size()))
      throw Error(path, "tissue '" + ts.name + "': 'inside' forms a cycle");
  }
  // a colour prototype belongs to one tissue (or the background): the same
  // colour under two names would split that tissue's voxels between them
  std::map<std::array<std::uint8_t, 3>, std::pair<std::string, std::string>> owner;  // colour -> name, "tissue 'x'"
  auto claim = [&](const std::array<std::uint8_t, 3>& c, const std::string& name, const std::string& what) {
    const auto [it, fresh] = owner.emplace(c, std::make_pair(name, what));
    if (!fresh && it->second.first != name)
      throw Error(path, it->second.second + " and " + what + " have the same colour prototype [" + std::to_string(c[0]) +
                            ", " + std::to_string(c[1]) + ", " + std::to_string(c[2]) +
                            "]: each colour must belong to one tissue");
  };
  for (const auto& c : t.background_rgb) claim(c, t.background_name, "background '" + t.background_name + "'");
  for (const auto& ts : t.tissues)
    for (const auto& c : ts.rgb) claim(c, ts.name, "tissue '" + ts.name + "'");
  return t;
}

TissueTable load_tissue_table(const std::string& path) {
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec)) throw Error(path, "is a folder, not a tissue table (tissues.json)");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path, "cannot open tissue table (missing or unreadable)");
  std::stringstream s;
  s << in.rdbuf();
  return parse_tissue_table(s.str(), path);
}

void require_background_colour(const TissueTable& table) {
  if (table.background_rgb.empty())
    throw Error(table.path,
                "no background colour: segmentation needs \"background\": {\"rgb\": [[r, g, b], ...]}, the colour of the "
                "embedding medium around the body");
}

std::string to_json(const TissueTable& table) {
  json j;
  j["format"] = "orthosim-tissues/1";
  j["units"] = {{"density", "kg/m^3"}, {"moduli", "kPa"}, {"rgb", "sRGB 0..255"}};
  json bg;
  bg["name"] = table.background_name;
  if (!table.background_rgb.empty()) bg["rgb"] = table.background_rgb;
  j["background"] = bg;
  j["tissues"] = json::array();
  for (const auto& t : table.tissues) {
    json e;
    e["name"] = t.name;
    e["label"] = t.label;
    e["rgb"] = t.rgb;
    e["density_kg_m3"] = t.density_kg_m3;
    e["layer"] = t.layer;
    e["inside"] = t.inside.empty() ? json(nullptr) : json(t.inside);
    if (t.mechanics.model == Mechanics::Model::biphasic) {
      e["mechanics"] = {{"model", "biphasic"},
                        {"k1_kpa", t.mechanics.k1_pa / 1e3},
                        {"turning_strain", t.mechanics.turning_strain},
                        {"k2_kpa", t.mechanics.k2_pa / 1e3},
                        {"weights", t.mechanics.weights}};
    } else if (t.mechanics.model == Mechanics::Model::linear) {
      e["mechanics"] = {{"model", "linear"}, {"k_kpa", t.mechanics.k_pa / 1e3}, {"weights", t.mechanics.weights}};
    }
    if (!t.source.empty()) e["source"] = t.source;
    j["tissues"].push_back(e);
  }
  return j.dump(2) + "\n";
}

}  // namespace orthosim
