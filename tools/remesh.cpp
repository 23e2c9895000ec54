// orthosim remesh --surface skin.stl [--inner fat.stl,muscle.stl,bone.stl]
//   --grid 39x9 --out DIR [--model model.h5] [--stack DIR --texture]
// Re-parameterises the tissue surfaces into corresponding nu x nv quad grids
// (docs/remesh.md), writes DIR/<tissue>_quads.obj for every layer, with
// --texture the skin's texture (OBJ + MTL + PNG, glTF), with --model the
// grids into /quads/<tissue>.
#include "libmodel/provenance.h"
#include "libmodel/remesh/remesh.h"
#include "libmodel/remesh/texture.h"
#include "libmodel/segment/segment.h"
#include "tools/common.h"

#include <tbb/parallel_for.h>

#include <cctype>
#include <cmath>
#include <exception>
#include <filesystem>
#include <iomanip>
#include <iostream>
#include <optional>
#include <sstream>

namespace orthosim::cli {

namespace {

using nlohmann::json;

std::vector<std::string> split_commas(const std::string& text) {
  std::vector<std::string> out;
  std::stringstream s(text);
  std::string part;
  while (std::getline(s, part, ','))
    if (!part.empty()) out.push_back(part);
  return out;
}

json quality_json(const QuadQuality& q) {
  return {{"min_angle_deg", q.min_angle_deg}, {"max_angle_deg", q.max_angle_deg}, {"max_aspect", q.max_aspect},
          {"mean_aspect", q.mean_aspect},     {"min_edge_m", q.min_edge_m},       {"max_edge_m", q.max_edge_m},
          {"mean_edge_m", q.mean_edge_m},     {"max_warp_deg", q.max_warp_deg},   {"flipped", q.flipped},
          {"degenerate", q.degenerate}};
}

json distance_json(const SurfaceDistance& d) {
  return {{"hausdorff_m", d.hausdorff_m},
          {"mean_m", d.mean_m},
          {"quad_to_input_max_m", d.quad_to_input_max_m},
          {"quad_to_input_mean_m", d.quad_to_input_mean_m},
          {"input_to_quad_max_m", d.input_to_quad_max_m},
          {"input_to_quad_mean_m", d.input_to_quad_mean_m},
          {"compared_input_area_m2", d.compared_input_area_m2}};
}

}  // namespace

void add_remesh_command(CLI::App& app) {
  auto* sub = app.add_subcommand(
      "remesh", "re-parameterise tissue surfaces (STL) into corresponding nu x nv quad grids, optionally textured");
  struct Args {
    std::string surface, inner, names, grid = "39x9", out, model, stack, spacing, origin, around = "arc";
    bool texture = false, uniform = false;
    double texel_mm = 0, depth_mm = -1;
    int bit_depth = 16;            // segment's --bit-depth, for 16-bit slices
    CLI::Option* depth = nullptr;  // given or not (absent: one voxel)
    int arc_window = RemeshOptions{}.arc_window;
    std::string ends = "crease";
    CommonOptions common;
  };
  static Args a;
  sub->add_option("--surface", a.surface, "outer closed surface (STL, metres), one tube-like component")->required();
  sub->add_option("--inner", a.inner, "inner surfaces, outer to inner, comma-separated (STL); may have several components");
  static CLI::Option* names_flag =
      sub->add_option("--names", a.names, "tissue names of the surfaces, comma-separated (default: the file stems)");
  sub->add_option("--grid", a.grid, "NUxNV: points around each ring x rings along the axis, each 3..10000 x 2..10000")
      ->capture_default_str();
  sub->add_option("--out", a.out, "output directory: <tissue>_quads.obj, and with --texture the textured skin")
      ->required();
  sub->add_option("--model", a.model, "model file to write /quads/<tissue> into (replaces /quads)");
  sub->add_option("--around", a.around, "ring sampling: arc (equal arc length) or angle (equal angles)")
      ->capture_default_str();
  sub->add_option("--arc-window", a.arc_window,
                  "arc sampling: measure each section's length smoothed over 2N+1 of its vertices (0..64; 0: raw)")
      ->capture_default_str();
  sub->add_option("--ends", a.ends,
                  "end rings of flat caps: crease (past the wall faces touching the cap) or rim (on the cap's rim)")
      ->capture_default_str();
  sub->add_flag("--uniform", a.uniform, "rings at equal arc length (default: more where the surface bends along the axis)");
  sub->add_option("--stack", a.stack, "colour slice directory (DIR/slices/*.png or DIR/*.png) for --texture");
  sub->add_flag("--texture", a.texture, "bake the outer surface's texture from --stack: OBJ + MTL + PNG and glTF");
  sub->add_option("--spacing", a.spacing, "voxel size of the stack in mm, X,Y,Z (default: the model's /volume)");
  sub->add_option("--origin", a.origin, "centre of voxel (0,0,0) in mm, X,Y,Z (default: the model's /volume, else 0,0,0)");
  sub->add_option("--texel", a.texel_mm, "texel size in mm (default: the in-plane voxel size)");
  a.depth = sub->add_option("--texture-depth", a.depth_mm, "sample the colour this far inside the surface, mm (default: one voxel)");
  sub->add_option("--bit-depth", a.bit_depth,
                  "significant bits of 16-bit slices, as segment's --bit-depth (12: a 12-bit camera's data in 16-bit files)")
      ->check(CLI::Range(8, 16))
      ->capture_default_str();
  add_common_options(sub, a.common);

  on_run(sub, "remesh", a.common, [] {
    // ---- flags, before any work -----------------------------------------------
    RemeshOptions o;
    {
      std::vector<int> g;
      try {
        g = parse_size(a.grid, 2, "--grid");
      } catch (const UsageError&) {
        throw UsageError("--grid: expected NUxNV with NU in 3..10000 and NV in 2..10000, got '" + a.grid + "'");
      }
      o.nu = g[0], o.nv = g[1];
    }
    o.adaptive = !a.uniform;
    if (a.arc_window < 0 || a.arc_window > 64)
      throw UsageError("--arc-window: expected 0..64 section vertices, got " + std::to_string(a.arc_window));
    o.arc_window = a.arc_window;
    if (a.ends == "crease")
      o.ends = EndRings::crease;
    else if (a.ends == "rim")
      o.ends = EndRings::rim;
    else
      throw UsageError("--ends: expected crease or rim, got '" + a.ends + "'");
    if (a.around == "arc")
      o.around = RingSampling::arc_length;
    else if (a.around == "angle")
      o.around = RingSampling::angle;
    else
      throw UsageError("--around: expected arc or angle, got '" + a.around + "'");
    try {
      validate(o);
    } catch (const Error& e) {
      throw UsageError("--" + e.message());
    }
    std::vector<std::string> files{a.surface};
    for (const auto& f : split_commas(a.inner)) files.push_back(f);
    std::vector<std::string> names;
    if (names_flag->count() > 0 && a.names.empty()) throw UsageError("--names: empty (give one name per surface)");
    if (!a.names.empty()) {
      names = split_commas(a.names);
      if (names.size() != files.size())
        throw UsageError("--names: " + std::to_string(files.size()) + " names needed, got " + std::to_string(names.size()));
    } else {
      for (const auto& f : files) names.push_back(std::filesystem::path(f).stem().string());
    }
    // names become files (<name>_quads.obj) and model groups (/quads/<name>):
    // the tissue table's rule ("sk/in" failed after all the work naming a
    // temporary path, ".." wrote a hidden file and a group /quads/..)
    for (std::size_t i = 0; i < names.size(); ++i) {
      const std::string& n = names[i];
      bool ok = !n.empty() && n.size() <= 64;
      for (const char c : n) ok = ok && (std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-');
      if (!ok)
        throw UsageError((a.names.empty() ? "the surface " + files[i] + " gives the tissue name '" + n + "'"
                                          : "--names: '" + n + "'") +
                         ": tissue names have 1 to 64 letters, digits, '_' or '-'" +
                         (a.names.empty() ? " (name it with --names)" : ""));
      for (std::size_t j = 0; j < i; ++j)
        if (n == names[j]) throw UsageError("two surfaces are named '" + n + "': use --names");
    }
    if (a.texture && a.stack.empty()) throw UsageError("--texture needs --stack DIR");
    if (!(a.texel_mm >= 0)) throw UsageError("--texel must be >= 0");
    if (a.depth->count() > 0 && !(a.depth_mm >= 0 && std::isfinite(a.depth_mm)))
      throw UsageError("--texture-depth must be >= 0 mm (inside the surface), got " + a.depth->as<std::string>());
    check_output_dir(a.out);
    if (!a.model.empty()) check_output_file(a.model);

    Report report("remesh");
    report.parameters() = {{"grid", {o.nu, o.nv}},
                           {"around", a.around},
                           {"arc_window", o.arc_window},
                           {"ends", a.ends},
                           {"adaptive", o.adaptive},
                           {"max_spacing_ratio", o.max_spacing_ratio},
                           {"axis_sections", o.axis_sections},
                           {"axis_iterations", o.axis_iterations},
                           {"end_area_fraction", o.end_area_fraction},
                           {"cap_angle_deg", o.cap_angle_deg},
                           {"names", names},
                           {"texture", a.texture}};

    // ---- read and remesh (validates everything) --------------------------------
    std::vector<NamedSurface> in;
    {
      Phase p(report, "read");
      // the files side by side (a 256^3 stack's four took 4.4 s one after
      // another); a bad file is reported as before: the first in order
      std::vector<Surface> read(files.size());
      std::vector<std::exception_ptr> failed(files.size());
      tbb::parallel_for(std::size_t{0}, files.size(), [&](std::size_t i) {
        try {
          read[i] = read_stl(files[i]);
        } catch (...) {
          failed[i] = std::current_exception();
        }
      });
      for (const auto& e : failed)
        if (e) std::rethrow_exception(e);
      for (std::size_t i = 0; i < files.size(); ++i) {
        in.push_back({names[i], std::move(read[i])});
        report.input(files[i]);
      }
    }
    RemeshResult r;
    try {
      r = remesh_layers(in, o);
    } catch (const Error& e) {
      // name the file rather than the tissue
      for (std::size_t i = 0; i < names.size(); ++i)
        if (e.file() == names[i]) throw Error(files[i], e.message());
      throw;
    }
    // check and axis run side by side (remesh.h): the report's phases stay
    // disjoint (remesh = their wall time), the split is in the metrics
    report.phase("remesh", r.total_s);
    RemeshEvaluation ev;
    {
      Phase p(report, "evaluate");
      ev = evaluate_remesh(r, in);
    }

    // ---- texture -----------------------------------------------------------------
    TextureImage tex;
    std::vector<std::string> stale;  // model groups built from the quads this run replaces
    if (a.texture) {
      Phase p(report, "texture");
      std::array<double, 3> spacing{0, 0, 0}, origin{0, 0, 0};
      std::array<int, 3> offset{0, 0, 0};  // the volume's voxel (0,0,0) in the stack (segment --roi, --slices)
      std::array<int, 3> volume_n{0, 0, 0};
      std::vector<double> stack_shape;  // the slice files segment read (/volume@stack_shape_voxels), if said
      int volume_nz = 0;
      bool have_spacing = false;
      if (!a.model.empty() && std::filesystem::exists(a.model)) {
        ModelReader m(a.model);
        if (m.has("/volume")) {
          const Volume v = m.volume();
          spacing = v.spacing_m, volume_nz = v.nz;
          volume_n = {v.nx, v.ny, v.nz};
          if (m.h5().has_attr("/volume", "stack_shape_voxels")) {
            stack_shape = m.h5().attr_doubles("/volume", "stack_shape_voxels");
            if (stack_shape.size() != 3) throw Error(a.model, "/volume@stack_shape_voxels must hold 3 numbers");
          }
          if (m.h5().has_attr("/volume", "stack_offset_voxels")) {
            const std::vector<double> off = m.h5().attr_doubles("/volume", "stack_offset_voxels");
            if (off.size() != 3) throw Error(a.model, "/volume@stack_offset_voxels must hold 3 numbers");
            for (std::size_t k = 0; k < 3; ++k) {
              if (!(off[k] >= 0 && off[k] <= 1e9) || off[k] != std::floor(off[k]))
                throw Error(a.model, "/volume@stack_offset_voxels must hold whole numbers >= 0");
              offset[k] = static_cast<int>(off[k]);
            }
          }
          // the stack's pixel (0,0) of its first slice, where the texture's lookup starts
          for (std::size_t k = 0; k < 3; ++k) origin[k] = v.origin_m[k] - offset[k] * v.spacing_m[k];
          have_spacing = true;
        }
      }
      if (!a.spacing.empty()) {
        const auto s = parse_list(a.spacing, 3, "--spacing", true);
        for (int k = 0; k < 3; ++k) spacing[k] = s[k] * 1e-3;
        have_spacing = true;
      }
      if (!a.origin.empty()) {
        const auto s = parse_list(a.origin, 3, "--origin", false);
        for (int k = 0; k < 3; ++k) origin[k] = s[k] * 1e-3;
      }
      if (!have_spacing) throw UsageError("--texture needs the voxel size: --spacing X,Y,Z (mm) or a --model with /volume");
      ColourStack st = open_colour_stack(a.stack, spacing, origin);
      st.bit_depth = a.bit_depth;
      // the model's labels place the slices: only their part (and 2 px
      // around) is read, as segment --roi read it (read_slice's region)
      if (volume_n[0] > 0 && a.spacing.empty() && a.origin.empty()) {
        const int x0 = std::max(0, offset[0] - 2), y0 = std::max(0, offset[1] - 2);
        const int x1 = std::min(st.nx, offset[0] + volume_n[0] + 2), y1 = std::min(st.ny, offset[1] + volume_n[1] + 2);
        if (x1 > x0 && y1 > y0 && (x1 - x0 < st.nx || y1 - y0 < st.ny)) st.region = {x0, y0, x1 - x0, y1 - y0};
      }
      // the model's labels were segmented from slice files of a known shape:
      // another stack (a neighbouring block of the same size, the stack before
      // a crop) would texture the surface with colours that are not its own
      // and say nothing. An explicit --spacing says the stack is another
      // sampling of the same body, and only its extent is checked then.
      if (volume_n[0] > 0) {
        const std::array<double, 3> got{static_cast<double>(st.nx), static_cast<double>(st.ny),
                                        static_cast<double>(st.files.size())};
        auto shape = [](const std::array<double, 3>& d) {
          std::ostringstream s;
          s << d[0] << " x " << d[1] << " px, " << d[2] << " slices";
          return s.str();
        };
        if (a.spacing.empty() && stack_shape.size() == 3 &&
            (got[0] != stack_shape[0] || got[1] != stack_shape[1] || got[2] != stack_shape[2]))
          throw Error(a.stack, "has " + shape(got) + ", but " + a.model + "'s labels were segmented from " +
                                   shape({stack_shape[0], stack_shape[1], stack_shape[2]}) +
                                   " (/volume@stack_shape_voxels): not the stack segment read");
        if (a.spacing.empty())
          for (std::size_t k = 0; k < 3; ++k)
            if (offset[k] + volume_n[k] > got[k])
              throw Error(a.stack, "has " + shape(got) + ", but " + a.model + "'s labels reach its " +
                                       std::string(k == 0 ? "column " : k == 1 ? "row " : "slice ") +
                                       std::to_string(offset[k] + volume_n[k] - 1) + ": not the stack segment read");
      }
      // a registered segmentation moved its slices: the texture's colours move with them
      if (!a.model.empty() && std::filesystem::exists(a.model)) {
        ModelReader m(a.model);
        if (m.h5().exists("/volume/slice_shift_px")) {
          std::vector<std::uint64_t> d;
          const auto sh = m.h5().read<std::int32_t>("/volume/slice_shift_px", &d);
          // one row per segmented slice: the stack's offset[2] .. offset[2] + rows - 1
          if (d.size() != 2 || d[1] != 2 || d[0] != static_cast<std::uint64_t>(volume_nz))
            throw Error(a.model, "/volume/slice_shift_px has " + std::to_string(d.empty() ? 0 : d[0]) +
                                     " rows, but /volume has " + std::to_string(volume_nz) + " slices");
          if (offset[2] + d[0] > st.files.size())
            throw Error(a.model, "/volume's slices " + std::to_string(offset[2]) + ".." +
                                     std::to_string(offset[2] + d[0] - 1) + " reach beyond --stack " + a.stack +
                                     ", which has " + std::to_string(st.files.size()) + " slices");
          st.shift.assign(st.files.size(), {0, 0});
          for (std::size_t k = 0; k < d[0]; ++k) st.shift[offset[2] + k] = {sh[2 * k], sh[2 * k + 1]};
        }
      }
      // the slices the texture reads: the labels' (and one each side) when the
      // model places them, else the stack's (hash_stack: not every file in the folder)
      const std::string slices = std::filesystem::path(st.files[0]).parent_path().string();  // DIR or DIR/slices
      const bool placed = volume_n[0] > 0 && a.spacing.empty() && a.origin.empty();
      report.input(a.stack, placed ? hash_stack(slices, std::max(0, offset[2] - 1), offset[2] + volume_n[2])
                                   : hash_stack(slices));
      TextureOptions to;
      to.texel_m = a.texel_mm * 1e-3;
      to.depth_m = a.depth->count() > 0 ? a.depth_mm * 1e-3 : -1;
      tex = bake_texture(in[0].surface, r.sweep, o.around, o.arc_window, st, to, names[0]);
      report.metrics()["texture"] = {{"width", tex.width}, {"height", tex.height}, {"outside", tex.outside}, {"side_loops", tex.side_loops}};
      // a texture sampled off the stack is one flat colour (an --origin of
      // 1000 mm wrote it, exit 0, nothing said): refused when all of it is,
      // said when much of it is
      const double texels = static_cast<double>(tex.width) * tex.height;
      if (texels > 0 && static_cast<double>(tex.outside) >= texels)
        throw Error(a.stack, "every texel of the texture samples outside the stack: --spacing and --origin (or the "
                             "model's /volume) do not place the slices around the surface");
      if (texels > 0 && static_cast<double>(tex.outside) > 0.1 * texels)
        std::cerr << "orthosim remesh: warning: " << a.stack << ": " << std::fixed << std::setprecision(0)
                  << 100.0 * static_cast<double>(tex.outside) / texels
                  << " % of the texture samples outside the stack (clamped to its edge): check --spacing, --origin "
                     "and --texture-depth\n";
    }

    // ---- outputs: the directory, then the model ------------------------------------
    {
      Phase p(report, "write");
      AtomicDir dir(a.out);
      for (std::size_t l = 0; l < r.layers.size(); ++l) {
        const std::string& n = names[l];
        if (l == 0 && a.texture) {
          write_texture_png(dir.temp_path(n + "_texture.png"), tex);
          write_mtl(dir.temp_path(n + "_quads.mtl"), n, n + "_texture.png");
          write_quad_obj(dir.temp_path(n + "_quads.obj"), r.layers[l], n + "_quads.mtl", n);
          write_gltf(dir.temp_path(n + ".gltf"), r.layers[l], n + "_texture.png", n);
        } else {
          write_quad_obj(dir.temp_path(n + "_quads.obj"), r.layers[l]);
        }
      }
      std::optional<ModelWriter> w;
      if (!a.model.empty()) {
        w.emplace(a.model, ModelWriter::Start::update);
        w->remove("/quads");
        // what was built and tuned from the old quads describes another mesh
        // (a 15x5 /quads beside 39x9 /layers and their /tuning, exit 0)
        for (const char* g : {"/layers", "/tuning", "/provenance/build", "/provenance/tune"})
          if (w->h5().exists(g)) {
            w->remove(g);
            stale.push_back(g);
          }
        for (std::size_t l = 0; l < r.layers.size(); ++l) w->write(names[l], r.layers[l]);
        w->write("remesh", make_provenance(command_line(), report.json()["inputs"].dump(),
                                           report.parameters().dump(), 0, r.total_s));
      }
      dir.commit();
      if (w) w->commit();
    }
    if (!stale.empty() && !a.common.quiet) {
      std::string list;
      for (const auto& g : stale) list += (list.empty() ? "" : ", ") + g;
      std::cerr << "remesh: removed " << list << " from " << a.model
                << ": they were built from the quads it replaced (run build, and tune, again)\n";
    }
    report.metrics()["removed_groups"] = stale;
    for (const auto& n : names) report.output(a.out + "/" + n + "_quads.obj");
    if (!a.model.empty()) report.output(a.model);

    // ---- metrics and summary ---------------------------------------------------------
    json& m = report.metrics();
    m["sweep"] = {{"length_m", r.sweep.length_m},
                  {"flat_cap", {r.sweep.flat_cap[0], r.sweep.flat_cap[1]}},
                  {"uncovered_m2", {r.sweep.uncovered_m2[0], r.sweep.uncovered_m2[1]}},
                  {"cap_inset_m", {r.sweep.cap_inset_m[0], r.sweep.cap_inset_m[1]}},
                  {"plane_turn", r.sweep.plane_turn},
                  {"normal_window_m", r.sweep.normal_window_m},
                  {"side_loops", r.side_loops},
                  {"stations_m", std::vector<double>(r.stations_m.data(), r.stations_m.data() + r.stations_m.size())}};
    // wall time of remesh's own phases; check (topology, containment) and
    // axis (axis, sweep, stations) overlap
    m["remesh_phases_s"] = {{"check", r.check_s}, {"axis", r.axis_s}, {"rings", r.rings_s}, {"total", r.total_s}};
    m["layers"] = json::array();
    for (std::size_t l = 0; l < r.layers.size(); ++l)
      m["layers"].push_back({{"name", names[l]},
                             {"components", r.stats[l].components},
                             {"hit", r.stats[l].hit},
                             {"bridged", r.stats[l].bridged},
                             {"filled", r.stats[l].filled},
                             {"normal_blend", r.stats[l].normal_blend},
                             {"quality", quality_json(ev.quality[l])},
                             {"distance", distance_json(ev.distance[l])}});
    m["alignment"] = json::array();
    for (const auto& al : ev.alignment)
      m["alignment"].push_back({{"outer", al.outer},
                                {"inner", al.inner},
                                {"max_normal_angle_deg", al.max_normal_angle_deg},
                                {"mean_normal_angle_deg", al.mean_normal_angle_deg},
                                {"max_lateral_m", al.max_lateral_m},
                                {"max_lateral_rel", al.max_lateral_rel},
                                {"ray_in_quad", al.ray_in_quad},
                                {"max_ray_miss_m", al.max_ray_miss_m}});
    m["worst_misalignment"] = {{"lateral_m", ev.worst_lateral_m},
                               {"lateral_rel", ev.worst_lateral_rel},
                               {"ray_miss_m", ev.worst_ray_miss_m}};
    if (!a.common.quiet) {
      std::cout << std::fixed << std::setprecision(3);
      std::cout << "remesh: " << o.nu << "x" << o.nv << " grid, axis " << r.sweep.length_m * 1e3 << " mm, ends "
                << (r.sweep.flat_cap[0] ? "flat cap" : "trimmed") << " / " << (r.sweep.flat_cap[1] ? "flat cap" : "trimmed")
                << ", " << r.total_s * 1e3 << " ms\n";
      for (std::size_t l = 0; l < r.layers.size(); ++l) {
        const auto& q = ev.quality[l];
        const auto& d = ev.distance[l];
        std::cout << "  " << names[l] << ": hausdorff " << d.hausdorff_m * 1e3 << " mm, mean " << d.mean_m * 1e3
                  << " mm, angles " << std::setprecision(1) << q.min_angle_deg << ".." << q.max_angle_deg
                  << " deg, aspect <= " << q.max_aspect << ", flipped " << q.flipped << ", degenerate "
                  << q.degenerate << std::setprecision(3);
        if (l > 0) std::cout << ", bridged " << r.stats[l].bridged << ", filled " << r.stats[l].filled;
        std::cout << "\n";
      }
      for (const auto& al : ev.alignment)
        std::cout << "  " << al.outer << " -> " << al.inner << ": lateral offset <= " << al.max_lateral_m * 1e3
                  << " mm (" << al.max_lateral_rel << " of a quad), off the normal <= " << std::setprecision(1)
                  << al.max_normal_angle_deg << " deg, normal rays in quad (i,j) "
                  << std::setprecision(1) << 100 * al.ray_in_quad << " %" << std::setprecision(3) << "\n";
    }
    report.write(a.common.report);
  });
}

}  // namespace orthosim::cli
