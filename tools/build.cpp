// orthosim build --model model.h5 --tissues tissues.json [--layers skin:tetra,fat:lattice,muscle:lattice]
// Reads the corresponding quad surfaces /quads/<tissue> (outer skin to bone)
// and writes the multilayer mass-spring model: /layers/<tissue> and the node
// sets /layers/sets/{fixed, skin, layer_<tissue>, surface_<tissue>}.
// docs/msm.md describes the model; libmodel/msm/build.h the library.
#include "libmodel/format/model.h"
#include "libmodel/msm/build.h"
#include "libmodel/provenance.h"
#include "libmodel/tissues.h"
#include "tools/common.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <iostream>

namespace orthosim::cli {
namespace {

using nlohmann::json;

json projection_json(const msm::ProjectionCounts& p) {
  return {{"rays", p.rays},           {"hits", p.hits},   {"fallbacks", p.fallbacks()},
          {"fallback_miss", p.miss},  {"fallback_backface", p.backface},
          {"fallback_other_cell", p.other_cell}, {"near_edge_clamped", p.near_edge}};
}

json report_json(const msm::BuildReport& r) {
  json j;
  j["nodes"] = r.nodes;
  j["springs"] = r.springs;
  j["lin_springs"] = r.lin_springs;
  j["tets"] = r.tets;
  j["components"] = r.components;
  j["duplicate_springs"] = r.duplicate_springs;
  j["zero_length_springs"] = r.zero_length_springs;
  j["inverted_tets"] = r.inverted_tets;
  j["projection_fallbacks"] = r.projection_fallbacks;
  j["surface_intersections"] = r.surface_intersections;
  j["spring_ratio"] = r.spring_ratio;
  j["mass_kg"] = r.mass_kg;
  j["layer_mass_kg"] = r.layer_mass_kg;
  j["max_mass_error"] = r.max_mass_error;
  j["layers"] = json::array();
  for (const auto& l : r.layers) {
    json e = {{"name", l.name},
              {"tissue", l.tissue},
              {"kind", l.kind},
              {"order", l.order},
              {"node_offset", l.node_offset},
              {"nodes", l.nodes},
              {"springs", l.springs},
              {"lin_springs", l.lin_springs},
              {"tets", l.tets},
              {"density_kg_m3", l.density_kg_m3}};
    if (l.kind != "rigid") {
      e["cells"] = l.cells;
      e["interface_springs"] = l.interface_springs;
      e["zero_stiffness_dropped"] = l.zero_stiffness_dropped;
      e["volume_modulus_pa"] = l.volume_modulus_pa;
      e["volume_group"] = l.volume_group;
      e["volume_tets"] = l.volume_tets;
      e["guard_modulus_pa"] = l.guard_modulus_pa;
      e["guard_ratio"] = l.guard_ratio;
      e["springs_by_class"] = l.springs_by_class;
      e["k1_pa"] = l.k1_pa;
      e["k2_pa"] = l.k2_pa;
      e["turning_strain"] = l.turning_strain;
      e["volume_m3"] = l.volume_m3;
      e["reference_volume_m3"] = l.reference_volume_m3;
      e["mass_kg"] = l.mass_kg;
      e["mass_error"] = l.mass_error;
      e["thickness_min_m"] = l.thickness_min_m;
      e["thickness_mean_m"] = l.thickness_mean_m;
      e["spring_min_m"] = l.spring_min_m;
      e["spring_max_m"] = l.spring_max_m;
      e["min_tet_volume_m3"] = l.min_tet_volume_m3;
      e["inverted_tets"] = l.inverted;
      if (l.kind == "tetra") {
        e["projection"] = projection_json(l.projection);
        e["mean_cell_m_uvw"] = l.mean_cell_m;
        e["axis_factors_uvw"] = l.axes.factors;
        // the trace rule's moduli / E before the factors, and with them (on
        // the calibration specimen); null without the axis correction
        const bool calibrated = l.axes.moduli_before[0] > 0;
        e["trace_rule_modulus_ratio_uvw"] = calibrated ? json(l.axes.moduli_before) : json(nullptr);
        e["modulus_ratio_uvw"] = calibrated ? json(l.axes.moduli_after) : json(nullptr);
      }
      if (l.kind == "lattice")
        e["stiffness_rule"] = {{"cells", l.rule.cells},
                               {"exact_cells", l.rule.exact},
                               {"max_relative_residual", l.rule.max_residual},
                               {"mean_modulus_ratio_uvw", l.rule.mean_modulus_ratio},
                               {"mean_shear_ratio_vw_uw_uv", l.rule.mean_shear_ratio},
                               {"mean_cell_m_uvw", l.rule.mean_cell_m}};
    }
    j["layers"].push_back(e);
  }
  return j;
}

}  // namespace

void add_build_command(CLI::App& app) {
  auto* sub = app.add_subcommand("build", "build the multilayer mass-spring model from the layered quad surfaces");
  static std::string model, tissues_path, layers_text;
  static msm::BuildOptions opt;
  static double min_thickness_mm = opt.min_thickness_m * 1e3;
  static bool no_intersection_check = false;
  static CommonOptions common;
  sub->add_option("--model", model, "model file with /quads/<tissue> (from orthosim remesh); /layers is written into it")
      ->required();
  sub->add_option("--tissues", tissues_path, "tissue table (tissues.json)")->required();
  sub->add_option("--layers", layers_text,
                  "layers outer to inner as tissue:kind, kind tetra|lattice (default: from the tissue table)");
  sub->add_option("--through-cells", opt.through_cells, "lattice cells through each lattice layer (1..64)")
      ->capture_default_str();
  sub->add_flag("--body-diagonals", opt.body_diagonals, "add lattice body diagonals (off: docs/msm.md)");
  sub->add_option("--lattice-min-weight", opt.lattice_min_weight,
                  "lattice rule floor: edge and face-diagonal weights at least this times their cube values, in [0, 1) "
                  "(0 lets the fit drop a family, which can leave a mechanism)")
      ->capture_default_str();
  sub->add_flag("!--no-axis-correction", opt.axis_correction,
                "leave each layer's rule as it is: no equal Young's moduli along u, v and through (docs/msm.md)");
  sub->add_option("--poisson-ratio", opt.poisson_ratio,
                  "Poisson's ratio of the layers, in [0.25, 0.5): a volume term per tetrahedron of a tetra layer, and "
                  "with --lattice-volume-term per hexahedron of a lattice layer (0.25: none; docs/msm.md, The volume term)")
      ->capture_default_str();
  sub->add_option("--tetra-volume-term", opt.tetra_volume_term,
                  "where a tetra layer's volume term acts: tets (one per cell tetrahedron; locks in bending) or prisms "
                  "(one per grid prism: keeps the grid's volume without locking; docs/msm.md, The volume term)")
      ->check(CLI::IsMember({"tets", "prisms"}))
      ->capture_default_str();
  sub->add_option("--inversion-guard", opt.inversion_guard,
                  "every tetrahedron of a layer without a volume term of its own (the lattices') resists being pressed "
                  "below this fraction of its rest volume with the tissue's bulk modulus, in [0, 1) (0: none; "
                  "docs/msm.md, The inversion guard)")
      ->capture_default_str();
  sub->add_flag("--lattice-volume-term", opt.lattice_volume_term,
                "give the lattice layers a volume term per hexahedron too (off: in cells far from cubes it buckles the "
                "springs' weak shear under a few per cent of tension; docs/msm.md, The volume term)");
  sub->add_option("--damping-ratio", opt.damping_ratio, "damping ratio of each spring with its end masses")
      ->capture_default_str();
  sub->add_option("--min-thickness-mm", min_thickness_mm, "thinner layers are an error (mm)")->capture_default_str();
  sub->add_flag("--no-intersection-check", no_intersection_check,
                "skip the exact surface-surface intersection test (the thickness and inversion checks remain)");
  add_common_options(sub, common);
  on_run(sub, "build", common, [] {
    Report report("build");
    if (!(min_thickness_mm >= 0 && std::isfinite(min_thickness_mm)))  // (inf: "thinner than inf m")
      throw UsageError("--min-thickness-mm must be >= 0 and finite");
    opt.min_thickness_m = min_thickness_mm * 1e-3;
    opt.check_intersections = !no_intersection_check;
    // a flag out of range is the command line's error (it named the model file, and the
    // option's internal name): "--damping-ratio must be in [0, 10]"
    try {
      msm::check_build_options(opt);
    } catch (const Error& e) {
      throw flag_error(e);
    }
    std::vector<msm::LayerSpec> requested;
    if (!layers_text.empty()) {
      try {
        requested = msm::parse_layer_specs(layers_text);
      } catch (const Error& e) {
        throw UsageError(e.message());
      }
    }
    const TissueTable table = load_tissue_table(tissues_path);
    msm::BuiltModel built;
    msm::Stack stack;
    std::string fixed_bottom;  // a layered tissue made the fixed bottom (no rigid one)
    {
      ModelReader m(model);
      if (!m.has("/quads"))
        throw Error(model, "no /quads in the model: run orthosim remesh --model first");
      std::vector<std::string> present;
      for (const auto& n : m.names("/quads"))
        if (m.h5().is_group("/quads/" + n)) present.push_back(n);
      report.input(model);
      report.input(tissues_path);
      try {
        stack = msm::resolve_stack(requested, present, table);
        // no rigid tissue below the layers: the innermost layered one is the fixed bottom
        if (!stack.layered_bottom.empty()) {
          fixed_bottom = stack.layered_bottom;
          std::cerr << "orthosim build: warning: " << model << ": no rigid tissue among /quads: '" << fixed_bottom
                    << "' (" << table.find(fixed_bottom)->layer << " in " << tissues_path
                    << ") is the model's fixed bottom (its surface, every node fixed), not a layer\n";
        }
        std::vector<std::pair<std::string, QuadSurface>> surfaces;
        {
          Phase p(report, "read");
          for (const auto& s : stack.surfaces) surfaces.emplace_back(s, m.quads(s));
        }
        Phase p(report, "build");
        built = msm::build_layers(surfaces, stack.layers, table, opt);
      } catch (const Error& e) {
        if (!e.file().empty()) throw;
        throw Error(model, e.message());
      }
    }
    report.parameters() = json::parse(msm::build_parameters_json(opt, stack));
    for (const auto& [name, s] : built.report.phases_s) report.phase("build." + name, s);
    {
      Phase p(report, "write");
      ModelWriter w(model, ModelWriter::Start::update);
      w.remove("/layers");
      // an earlier tune's records describe the springs just replaced (a later
      // tune read them as the springs' laws, and inspect called the model tuned)
      w.remove("/tuning");
      w.remove("/provenance/tune");
      for (std::size_t l = 0; l < built.layers.size(); ++l) w.write_layer(built.names[l], built.layers[l]);
      for (const auto& [name, ids] : built.node_sets) w.write_node_set(name, ids);
      w.write("build", make_provenance(command_line(), report.json()["inputs"].dump(),
                                       msm::build_parameters_json(opt, stack), 0,
                                       report.json()["phases_s"].value("build", 0.0)));
      w.commit();
    }
    report.output(model);
    report.metrics() = report_json(built.report);
    if (!fixed_bottom.empty()) report.metrics()["fixed_bottom"] = fixed_bottom;
    if (!common.quiet) {
      const auto& r = built.report;
      std::cout << "build: " << r.nodes << " nodes, " << r.springs << " springs (" << r.lin_springs
                << " linear), " << r.tets << " tets, mass " << std::setprecision(4) << r.mass_kg << " kg, "
                << r.projection_fallbacks << " projection fallbacks\n";
      for (const auto& l : r.layers) {
        std::cout << "  " << l.order << " " << l.name << " (" << l.kind << "): " << l.nodes << " nodes";
        if (l.kind != "rigid")
          std::cout << ", " << l.springs << " springs, mass " << l.mass_kg << " kg (error "
                    << 100 * l.mass_error << " %)";
        std::cout << "\n";
      }
    }
    report.write(common.report);
  });
}

}  // namespace orthosim::cli
