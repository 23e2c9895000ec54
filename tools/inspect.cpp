// orthosim inspect FILE.h5: summarises any orthosim model file: groups,
// datasets with shape, type and unit, group attributes, provenance.
#include "libmodel/format/model.h"
#include "tools/common.h"

#include <array>
#include <cmath>
#include <iostream>
#include <sstream>

namespace orthosim::cli {
namespace {

using nlohmann::json;

json describe_group(const ModelReader& m, const std::string& group) {
  const h5::File& f = m.h5();
  json g = json::object();
  for (const auto& name : f.children(group)) {
    const std::string path = (group == "/" ? "" : group) + "/" + name;
    if (f.is_group(path)) {
      g[name] = describe_group(m, path);
      continue;
    }
    json d;
    d["shape"] = f.dims(path);
    d["dtype"] = h5::dtype_name(f.dtype(path));
    if (f.has_attr(path, "unit")) d["unit"] = f.attr_string(path, "unit");
    g[name] = d;
  }
  return g;
}

json group_attrs(const ModelReader& m, const std::string& group, const std::vector<std::string>& names) {
  json a = json::object();
  const h5::File& f = m.h5();
  for (const auto& n : names) {
    if (!f.has_attr(group, n)) continue;
    try {
      a[n] = f.attr_string(group, n);
    } catch (const Error&) {
      try {
        auto v = f.attr_doubles(group, n);
        // whole numbers (grid sizes, node offsets: int64 in the file) as integers, not "39.0"
        json arr = json::array();
        for (double x : v)
          arr.push_back(std::isfinite(x) && x == std::floor(x) && std::abs(x) < 9e15 ? json(static_cast<std::int64_t>(x)) : json(x));
        a[n] = v.size() == 1 ? arr[0] : arr;
      } catch (const Error&) {
        a[n] = f.attr_strings(group, n);
      }
    }
  }
  return a;
}

json summarise(const ModelReader& m) {
  json s;
  s["file"] = m.path();
  s["orthosim_format"] = m.version();
  if (m.h5().has_attr("/", "units")) s["units"] = m.h5().attr_string("/", "units");
  s["tree"] = describe_group(m, "/");
  json counts = json::object();
  if (m.has("/volume")) {
    auto d = m.h5().dims("/volume/labels");
    counts["volume"] = {{"nz", d[0]}, {"ny", d[1]}, {"nx", d[2]},
                        {"attributes", group_attrs(m, "/volume", {"spacing_m", "origin_m", "stack_offset_voxels", "stack_shape_voxels", "label_names"})}};
    // what every stage that reads the volume refuses, without reading the voxels
    // (a NaN spacing printed as null, as if the file were fine; sweep of 2026-11-27)
    const json& at = counts["volume"]["attributes"];
    std::string problem;
    if (!at.contains("spacing_m") || !at.contains("origin_m") || !at["spacing_m"].is_array() ||
        !at["origin_m"].is_array() || at["spacing_m"].size() != 3 || at["origin_m"].size() != 3) {
      problem = "spacing_m and origin_m need 3 values";
    } else {
      std::array<double, 3> sp{}, org{};
      for (std::size_t k = 0; k < 3; ++k) {
        sp[k] = at["spacing_m"][k].is_number() ? at["spacing_m"][k].get<double>() : std::nan("");
        org[k] = at["origin_m"][k].is_number() ? at["origin_m"][k].get<double>() : std::nan("");
      }
      problem = voxel_geometry_problem(sp, org);
    }
    try {
      if (m.h5().dtype("/volume/labels") != h5::dtype_of<std::uint8_t>())
        problem += std::string(problem.empty() ? "" : "; ") + "labels are " +
                   h5::dtype_name(m.h5().dtype("/volume/labels")) + ", not uint8";
    } catch (const Error& e) {  // an element type the format has no name for
      problem += std::string(problem.empty() ? "" : "; ") + e.message();
    }
    if (!problem.empty()) counts["volume"]["problem"] = problem;
  }
  for (const char* kind : {"surfaces", "quads", "layers", "vessels", "tuning"}) {
    const std::string g = std::string("/") + kind;
    if (!m.has(g)) continue;
    json k = json::object();
    for (const auto& name : m.names(g)) {
      const std::string p = g + "/" + name;
      if (!m.h5().is_group(p)) continue;
      json e = group_attrs(m, p, {"tissue", "kind", "order", "node_offset", "volume_modulus", "volume_group", "guard_modulus", "guard_ratio", "nu", "nv", "method", "psi",
                                  "evaluations", "seed", "seconds"});
      for (const auto& ds : m.h5().children(p))
        if (!m.h5().is_group(p + "/" + ds)) e["n_" + ds] = m.h5().dims(p + "/" + ds)[0];
      k[name] = e;
    }
    counts[kind] = k;
  }
  s["summary"] = counts;
  if (m.has("/provenance")) {
    json p = json::object();
    for (const auto& [stage, pr] : m.provenance())
      p[stage] = {{"tool_version", pr.tool_version}, {"command_line", pr.command_line},
                  {"time_utc", pr.time_utc}, {"seed", pr.seed}, {"wall_s", pr.wall_s},
                  {"inputs", json::parse(pr.inputs_json, nullptr, false)}};
    s["provenance"] = p;
  }
  return s;
}

void print_text(const json& s, std::ostream& out) {
  out << s["file"].get<std::string>() << ": orthosim model, format " << s["orthosim_format"].get<std::string>()
      << "\n";
  if (s.contains("units")) out << "  units: " << s["units"].get<std::string>() << "\n";
  const json& c = s["summary"];
  if (c.contains("volume")) {
    const json& v = c["volume"];
    out << "  /volume: " << v["nx"] << " x " << v["ny"] << " x " << v["nz"] << " voxels";
    if (v["attributes"].contains("spacing_m")) out << ", spacing_m " << v["attributes"]["spacing_m"].dump();
    // a region of the stack (segment --roi, --slices): where it lies in the slice files
    if (const auto& off = v["attributes"].value("stack_offset_voxels", json());
        off.is_array() && off != json::array({0, 0, 0}))
      out << ", from the stack's voxel " << off.dump();
    if (const auto& sh = v["attributes"].value("stack_shape_voxels", json()); sh.is_array())
      out << ", stack " << sh.dump();
    if (v["attributes"].contains("label_names")) {
      // the named labels only (a table with labels 200 and 255 printed 256 names, most "")
      const json& names = v["attributes"]["label_names"];
      out << ", labels";
      if (names.is_array()) {
        const char* sep = " ";
        for (std::size_t l = 0; l < names.size(); ++l)
          if (names[l].is_string() && !names[l].get<std::string>().empty())
            out << sep << l << " " << names[l].get<std::string>(), sep = ", ";
      } else {
        out << " " << names.dump();
      }
    }
    out << "\n";
    if (v.contains("problem")) out << "  /volume: invalid: " << v["problem"].get<std::string>() << "\n";
  }
  for (const char* kind : {"surfaces", "quads", "layers", "vessels", "tuning"}) {
    if (!c.contains(kind)) continue;
    for (auto it = c[kind].begin(); it != c[kind].end(); ++it) {
      out << "  /" << kind << "/" << it.key() << ":";
      for (auto f = it.value().begin(); f != it.value().end(); ++f) out << " " << f.key() << "=" << f.value().dump();
      out << "\n";
    }
  }
  if (s.contains("provenance"))
    for (auto it = s["provenance"].begin(); it != s["provenance"].end(); ++it)
      out << "  /provenance/" << it.key() << ": orthosim " << it.value()["tool_version"].get<std::string>()
          << " at " << it.value()["time_utc"].get<std::string>() << ", " << it.value()["wall_s"] << " s\n";
}

}  // namespace

void add_inspect_command(CLI::App& app) {
  auto* sub = app.add_subcommand("inspect", "summarise an orthosim model file (groups, counts, units, provenance)");
  static std::string file;
  static bool as_json = false;
  static CommonOptions common;
  sub->add_option("file", file, "model file (.h5)")->required();
  sub->add_flag("--json", as_json, "print the summary as JSON");
  add_common_options(sub, common);
  on_run(sub, "inspect", common, [] {
    Report report("inspect");
    ModelReader m(file);
    report.input(file);
    json s = summarise(m);
    report.metrics() = s["summary"];
    if (as_json)
      std::cout << s.dump(2) << "\n";
    else if (!common.quiet)
      print_text(s, std::cout);
    report.write(common.report);
  });
}

}  // namespace orthosim::cli
