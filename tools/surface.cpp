// orthosim surface --labels labels.h5 --out DIR: one closed, outward triangle
// surface per tissue from the label volume (/volume), as DIR/<tissue>.stl
// and, with --model, /surfaces/<tissue> (libmodel/surface/surface.h,
// docs/surface.md).
#include "libmodel/provenance.h"
#include "libmodel/remesh/remesh.h"
#include "libmodel/surface/surface.h"
#include "tools/common.h"

#include <tbb/global_control.h>
#include <tbb/parallel_for.h>
#include <tbb/task_group.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <iomanip>
#include <iostream>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <sstream>

namespace orthosim::cli {

namespace {

std::vector<std::string> split_commas(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream in(s);
  std::string item;
  while (std::getline(in, item, ','))
    if (!item.empty()) out.push_back(item);
  return out;
}

}  // namespace

void add_surface_command(CLI::App& app) {
  auto* sub = app.add_subcommand("surface", "closed triangle surfaces of the tissues of a label volume (STL, /surfaces)");
  struct Args {
    std::string labels, out, model, tissues, tissue_table, decimation = "lindstrom-turk";
    std::int64_t target_faces = 0;
    int smooth_iterations = 10, threads = 0;
    double sigma = 0.7, lambda = 0.5, mu = -0.53, nest_clearance = 0.1,
           nest_gap = SurfaceOptions{}.nest_gap_vox, min_component_voxels = SurfaceOptions{}.min_component_voxels;
    bool no_fill_holes = false, no_self_check = false;
    CommonOptions common;
  };
  static Args a;
  sub->add_option("--labels", a.labels, "model file with the label volume (/volume)")->required();
  sub->add_option("--out", a.out, "output directory: <tissue>.stl (binary, metres)")->required();
  sub->add_option("--model", a.model, "also write /surfaces/<tissue> into this model file (created or updated)");
  sub->add_option("--tissues", a.tissues, "comma-separated tissue names (default: every label with voxels)");
  sub->add_option("--tissue-table", a.tissue_table,
                  "tissues.json whose 'inside' gives the nesting (default: inferred from the volume)");
  sub->add_option("--target-faces", a.target_faces, "decimate each surface to at most N faces (0: no decimation)")
      ->capture_default_str();
  sub->add_option("--smooth-iterations", a.smooth_iterations, "Taubin lambda|mu iterations (0: none)")
      ->capture_default_str();
  sub->add_option("--sigma", a.sigma, "Gaussian smoothing of the indicator, voxels along each axis (0: none)")
      ->capture_default_str();
  sub->add_option("--taubin-lambda", a.lambda, "Taubin lambda, in (0, 1)")->capture_default_str();
  sub->add_option("--taubin-mu", a.mu, "Taubin mu, in (-1, -lambda)")->capture_default_str();
  sub->add_option("--decimation", a.decimation, "edge-collapse cost: lindstrom-turk or garland-heckbert")
      ->capture_default_str();
  sub->add_option("--nest-clearance", a.nest_clearance,
                  "keep each nested surface this far inside its parent's, in voxels of the smallest spacing")
      ->capture_default_str();
  sub->add_option("--nest-gap", a.nest_gap,
                  "where a nested tissue reaches its parent's outside (a shell the voxels lost), draw its surface this "
                  "far inside the parent's, in voxels, [0, 0.5] (0: off)")
      ->capture_default_str();
  sub->add_flag("--no-fill-holes", a.no_fill_holes, "keep pockets the tissue encloses out of its solid");
  sub->add_option("--min-component-voxels", a.min_component_voxels,
                  "drop surface components enclosing fewer voxels (noise specks; the largest is kept; 0: keep all)")
      ->capture_default_str();
  sub->add_flag("--no-self-intersection-check", a.no_self_check, "skip the CGAL self-intersection count (and so the untangling of the outermost surfaces)");
  sub->add_option("--threads", a.threads, "worker threads (0: all cores)")->capture_default_str();
  add_common_options(sub, a.common);

  on_run(sub, "surface", a.common, [] {
    // ---- flags -----------------------------------------------------------------------
    SurfaceOptions o;
    o.sigma_vox = a.sigma;
    o.smooth_iterations = a.smooth_iterations;
    o.taubin_lambda = a.lambda;
    o.taubin_mu = a.mu;
    o.target_faces = a.target_faces;
    o.fill_holes = !a.no_fill_holes;
    o.check_self_intersections = !a.no_self_check;
    o.nest_clearance_vox = a.nest_clearance;
    o.nest_gap_vox = a.nest_gap;
    o.min_component_voxels = a.min_component_voxels;
    if (a.decimation == "lindstrom-turk") o.decimation = DecimationCost::lindstrom_turk;
    else if (a.decimation == "garland-heckbert") o.decimation = DecimationCost::garland_heckbert;
    else throw UsageError("--decimation: expected lindstrom-turk or garland-heckbert, got '" + a.decimation + "'");
    try {
      validate(o);
    } catch (const Error& e) {
      throw UsageError("--" + e.message());
    }
    if (a.threads < 0) throw UsageError("--threads: must be >= 0");
    std::unique_ptr<tbb::global_control> threads;
    if (a.threads > 0)
      threads = std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism, a.threads);

    // ---- inputs first: nothing is written unless all of them are good ------------------
    check_output_dir(a.out);
    if (!a.model.empty()) {
      check_output_file(a.model);
      if (std::filesystem::exists(a.model)) ModelReader check(a.model);  // refuse a file that is not ours
    }
    Report report("surface");
    Volume v;
    {
      Phase p(report, "read");
      ModelReader in(a.labels);
      v = in.volume();
      report.input(a.labels);
    }
    std::vector<int> parents;
    if (!a.tissue_table.empty()) {
      const TissueTable table = load_tissue_table(a.tissue_table);
      report.input(a.tissue_table);
      parents = label_parents(v, table);
    } else {
      parents = label_parents(v);
    }
    std::vector<std::int64_t> count(256, 0);
    for (std::uint8_t l : v.labels) ++count[l];
    if (count[0] == static_cast<std::int64_t>(v.labels.size()))
      throw Error(a.labels, "nothing is segmented: every voxel of /volume is background");
    std::vector<std::string> names;
    if (!a.tissues.empty()) {
      names = split_commas(a.tissues);
      if (names.empty()) throw UsageError("--tissues: no tissue names");
    } else {
      for (std::size_t l = 1; l < v.label_names.size() && l < 256; ++l)
        if (!v.label_names[l].empty() && count[l] > 0) names.push_back(v.label_names[l]);
    }
    std::vector<std::vector<int>> solids;
    for (std::size_t i = 0; i < names.size(); ++i) {
      for (std::size_t j = 0; j < i; ++j)
        if (names[i] == names[j]) throw UsageError("--tissues: '" + names[i] + "' is listed twice");
      try {
        solids.push_back(solid_label_set(v, names[i], parents));
      } catch (const Error& e) {
        throw Error(a.labels, e.message());
      }
      if (count[static_cast<std::size_t>(v.label_of(names[i]))] == 0)
        throw Error(a.labels, "tissue '" + names[i] + "' has no voxels");
    }
    report.parameters() = nlohmann::json::parse(surface_parameters_json(o));
    report.parameters()["tissues"] = names;
    report.parameters()["nesting"] = a.tissue_table.empty() ? "inferred" : "tissue table";
    report.parameters()["threads"] = a.threads;

    // ---- surfaces ---------------------------------------------------------------------------
    // The surface each tissue must stay inside: the nearest enclosing label
    // that has a surface here (none: names.size()).
    const std::size_t none = names.size();
    std::vector<std::size_t> outer(names.size(), none);
    for (std::size_t i = 0; i < names.size(); ++i) {
      int pl = parents[static_cast<std::size_t>(v.label_of(names[i]))];
      while (pl > 0 && outer[i] == none) {
        for (std::size_t j = 0; j < names.size(); ++j)
          if (v.label_of(names[j]) == pl) outer[i] = j;
        if (outer[i] == none) pl = parents[static_cast<std::size_t>(pl)];
      }
    }

    // The tissues are independent until nesting: they are extracted side by
    // side (each extraction is parallel inside too; TBB shares the threads),
    // every result in its own slot, so the output does not depend on the
    // order they finish in. The first failing tissue in --tissues order is
    // the one reported. A nested surface is checked for self-intersections
    // once, after nesting has moved it (not also before).
    std::vector<SurfaceResult> results(names.size());
    {
      Progress bar("surface", static_cast<long>(names.size()), a.common.quiet);
      std::vector<std::string> failed(names.size());
      std::atomic<long> done{0};
      std::mutex bar_mutex;
      tbb::parallel_for(std::size_t{0}, names.size(), [&](std::size_t i) {
        SurfaceOptions oi = o;
        if (outer[i] != none) oi.check_self_intersections = false;
        try {
          results[i] = extract_surface(v, solids[i], oi, outer[i] != none ? solids[outer[i]] : std::vector<int>{});
        } catch (const Error& e) {
          failed[i] = names[i] + ": " + e.message();
        }
        const std::lock_guard<std::mutex> lock(bar_mutex);
        bar.update(++done);
      });
      for (const auto& f : failed)
        if (!f.empty()) throw Error(a.labels, f);
      for (const auto& r : results) {
        const SurfaceMetrics& m = r.metrics;
        report.phase("solid", m.solid_s);
        report.phase("field", m.field_s);
        report.phase("extract", m.extract_s);
        report.phase("smooth", m.smooth_s);
        report.phase("decimate", m.decimate_s);
        report.phase("check", m.check_s);
      }
    }

    // ---- untangling the outermost surfaces -----------------------------------------------------
    // Nothing nests them, so nothing else relaxes their folds (a thin, torn
    // skin). Found by the extraction's own self-intersection test, so a surface
    // without folds costs nothing here (with --no-self-intersection-check none is
    // looked for, so none is untangled).
    // A surface that changed after extraction is checked again (its extraction
    // figures kept).
    auto check = [&](std::size_t i) {
      const auto t0 = std::chrono::steady_clock::now();
      const SurfaceMetrics before = results[i].metrics;
      SurfaceMetrics m = check_surface(results[i].surface, o.check_self_intersections);
      m.extracted_faces = before.extracted_faces;
      m.solid_voxels = before.solid_voxels;
      m.filled_voxels = before.filled_voxels;
      m.smooth_volume_change = before.smooth_volume_change;
      m.clamped_to_caps = before.clamped_to_caps;
      m.dropped_components = before.dropped_components;
      m.gap_samples = before.gap_samples;
      m.dropped_volume_m3 = before.dropped_volume_m3;
      m.solid_s = before.solid_s, m.field_s = before.field_s, m.extract_s = before.extract_s;
      m.smooth_s = before.smooth_s, m.decimate_s = before.decimate_s;
      m.check_s = before.check_s + std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      results[i].metrics = m;
    };
    const std::vector<CapPlane> caps = cap_planes(v, o);
    std::vector<FoldsResult> unfolded(names.size());
    {
      Phase p(report, "untangle");
      tbb::parallel_for(std::size_t{0}, names.size(), [&](std::size_t i) {
        if (outer[i] != none || results[i].metrics.self_intersections <= 0) return;
        unfolded[i] = untangle_surface(results[i].surface, caps, &results[i].intersecting_pairs);
        check(i);
      });
    }

    // ---- nesting: each surface strictly inside its parent's, outermost first ----------------------
    // Nesting is a chain (muscle inside the final fat, fat inside the final
    // skin), but a surface that nesting does not move is final as extracted.
    // So every tissue is first nested, side by side, against its parent as
    // extracted; then, outermost first, a result stands when the parent did
    // not change (no vertex moved in, no fold relaxed) and is recomputed
    // against the changed parent otherwise: the same surfaces as the plain
    // chain, in one parallel round when nothing changes.
    // A tissue's surface is final once nested, so its checks run in a task
    // while the tissues inside it are settled (both only read it).
    std::vector<NestingResult> nesting(names.size());
    {
      Phase p(report, "nesting");
      auto depth = [&](int l) {
        int d = 0;
        while (l > 0 && d < 256) l = parents[static_cast<std::size_t>(l)], ++d;
        return d;
      };
      std::vector<std::size_t> order(names.size());
      for (std::size_t i = 0; i < order.size(); ++i) order[i] = i;
      std::stable_sort(order.begin(), order.end(), [&](std::size_t x, std::size_t y) {
        return depth(v.label_of(names[x])) < depth(v.label_of(names[y]));
      });
      const double clearance = o.nest_clearance_vox * std::min({v.spacing_m[0], v.spacing_m[1], v.spacing_m[2]});
      tbb::task_group checks;
      std::vector<Surface> nested(names.size());
      // each parent's mesh and search trees once for all its children (the
      // muscle's three: bone and the two vessels), one parent's at a time per thread
      std::vector<std::size_t> parents_used;
      for (std::size_t i = 0; i < names.size(); ++i)
        if (outer[i] != none && std::find(parents_used.begin(), parents_used.end(), outer[i]) == parents_used.end())
          parents_used.push_back(outer[i]);
      tbb::parallel_for(std::size_t{0}, parents_used.size(), [&](std::size_t k) {
        const std::size_t q = parents_used[k];
        const auto index = make_nesting_index(results[q].surface, caps);
        std::vector<std::size_t> children;
        for (std::size_t i = 0; i < names.size(); ++i)
          if (outer[i] == q) children.push_back(i);
        tbb::parallel_for(std::size_t{0}, children.size(), [&](std::size_t j) {
          const std::size_t i = children[j];
          nested[i] = results[i].surface;
          nesting[i] = enforce_nesting(nested[i], *index, clearance);
        });
      });
      // a changed parent's final surface, indexed once for all its children
      std::map<std::size_t, std::shared_ptr<const NestingIndex>> final_index;
      try {
        for (std::size_t i : order) {
          if (outer[i] == none) continue;
          if (nesting[outer[i]].moved > 0 || nesting[outer[i]].untangle_rounds > 0) {  // the parent changed: nest against its final surface
            auto& index = final_index[outer[i]];
            if (!index) index = make_nesting_index(results[outer[i]].surface, caps);
            nesting[i] = enforce_nesting(results[i].surface, *index, clearance);
          } else {
            results[i].surface = std::move(nested[i]);
          }
          if (nesting[i].still_outside > 0)
            throw Error(a.labels, names[i] + ": " + std::to_string(nesting[i].still_outside) +
                                      " vertices stay outside the surface of " + names[outer[i]] +
                                      (clearance > 0 ? " (a shell thinner than --nest-clearance?)"
                                                     : " (with --nest-clearance 0 a vertex on the surface may count as outside: "
                                                       "give a clearance > 0)"));
          checks.run([&check, i] { check(i); });
        }
      } catch (...) {
        checks.wait();  // a task group is waited for before it goes
        throw;
      }
      checks.wait();
    }

    // an outermost tissue's untangling is reported where a nested one's is
    for (std::size_t i = 0; i < names.size(); ++i)
      if (outer[i] == none)
        nesting[i].folds = unfolded[i].folds, nesting[i].untangle_rounds = unfolded[i].untangle_rounds,
        nesting[i].folds_left = unfolded[i].folds_left;

    // ---- outputs: the directory, then the model ------------------------------------------------
    {
      Phase p(report, "write");
      AtomicDir dir(a.out);
      for (std::size_t i = 0; i < names.size(); ++i) write_stl(dir.temp_path(names[i] + ".stl"), results[i].surface);
      std::optional<ModelWriter> w;
      if (!a.model.empty()) {
        w.emplace(a.model, ModelWriter::Start::update);
        for (std::size_t i = 0; i < names.size(); ++i) w->write(names[i], results[i].surface);
        double secs = 0;
        for (const auto& r : results) secs += r.metrics.total_s();
        w->write("surface", make_provenance(command_line(), report.json()["inputs"].dump(), report.parameters().dump(), 0, secs));
      }
      dir.commit();
      if (w) w->commit();
    }
    // DIR holds this run's surfaces: the STL of another tissue of the volume's
    // table is an earlier run's, of another volume or selection, and goes (a
    // marrow.stl of a volume without marrow stood beside the new surfaces;
    // sweep of 2026-11-27)
    std::vector<std::string> removed;
    for (const std::string& t : v.label_names) {
      if (t.empty() || std::find(names.begin(), names.end(), t) != names.end()) continue;
      const std::filesystem::path stale = std::filesystem::path(a.out) / (t + ".stl");
      std::error_code ec;
      if (std::filesystem::is_regular_file(stale, ec) && std::filesystem::remove(stale, ec)) removed.push_back(stale.string());
    }
    if (!removed.empty()) {
      report.metrics()["removed_stale"] = removed;
      if (!a.common.quiet)
        for (const auto& r : removed) std::cerr << "surface: removed " << r << ": an earlier run's, not written by this one\n";
    }
    for (const auto& n : names) report.output(a.out + "/" + n + ".stl");
    if (!a.model.empty()) report.output(a.model);

    // ---- metrics and summary -------------------------------------------------------------------
    nlohmann::json& j = report.metrics();
    j["size"] = {v.nx, v.ny, v.nz};
    j["spacing_m"] = v.spacing_m;
    j["tissues"] = nlohmann::json::object();
    for (std::size_t i = 0; i < names.size(); ++i) {
      const SurfaceMetrics& m = results[i].metrics;
      std::vector<std::string> labels;
      for (int l : solids[i]) labels.push_back(v.label_names[static_cast<std::size_t>(l)]);
      j["tissues"][names[i]] = {{"solid_labels", labels},
                                {"solid_voxels", m.solid_voxels},
                                {"filled_voxels", m.filled_voxels},
                                {"extracted_faces", m.extracted_faces},
                                {"faces", m.faces},
                                {"vertices", m.vertices},
                                {"volume_m3", m.volume_m3},
                                {"area_m2", m.area_m2},
                                {"smooth_volume_change", m.smooth_volume_change},
                                {"clamped_to_caps", m.clamped_to_caps},
                                {"euler", m.euler},
                                {"components", m.components},
                                {"dropped_components", m.dropped_components},
                                {"gap_samples", m.gap_samples},
                                {"dropped_volume_m3", m.dropped_volume_m3},
                                {"closed", m.closed},
                                {"manifold", m.manifold},
                                {"outward", m.outward},
                                {"self_intersections", m.self_intersections},
                                {"nesting", {{"moved", nesting[i].moved}, {"outside", nesting[i].outside},
                                             {"max_move_m", nesting[i].max_move_m}, {"on_cap", nesting[i].on_cap},
                                             {"moved_again", nesting[i].moved_again}, {"folds", nesting[i].folds},
                                             {"untangle_rounds", nesting[i].untangle_rounds},
                                             {"folds_left", nesting[i].folds_left}}},
                                {"seconds",
                                 {{"solid", m.solid_s},
                                  {"field", m.field_s},
                                  {"extract", m.extract_s},
                                  {"smooth", m.smooth_s},
                                  {"decimate", m.decimate_s},
                                  {"check", m.check_s}}}};
    }
    report.write(a.common.report);
    // what the surfaces do not promise, even with --quiet (a noisy segmentation's
    // fat passed with a handle and 5 self-intersecting face pairs, silently)
    for (std::size_t i = 0; i < names.size(); ++i) {
      const SurfaceMetrics& m = results[i].metrics;
      const int handles = m.components - m.euler / 2;  // the genus summed over the components
      if (m.self_intersections > 0 || handles > 0)
        std::cerr << "orthosim surface: warning: " << a.labels << ": " << names[i] << ": the surface has "
                  << (m.self_intersections > 0 ? std::to_string(m.self_intersections) + " self-intersecting face pair(s)"
                                                 : std::string())
                  << (m.self_intersections > 0 && handles > 0 ? " and " : "")
                  << (handles > 0 ? std::to_string(handles) + " handle(s) (Euler characteristic " +
                                        std::to_string(m.euler) + ", " + std::to_string(m.components) +
                                        " component(s))"
                                  : std::string())
                  << ": noise or misclassified voxels in the labels (the segment report's Dice), a tissue only a "
                     "few voxels thin at this spacing, or slices off each other (segment --register); remesh refuses "
                     "handles in the outermost layer (the skin)\n";
    }
    if (!a.common.quiet) {
      std::cout << std::fixed;
      std::cout << "surface: wrote " << names.size() << " surface" << (names.size() == 1 ? "" : "s") << " to " << a.out
                << " in " << std::setprecision(2) << report.json()["wall_s"].get<double>() << " s\n";
      for (std::size_t i = 0; i < names.size(); ++i) {
        const SurfaceMetrics& m = results[i].metrics;
        std::cout << "  " << std::left << std::setw(8) << names[i] << std::right << " " << m.faces << " faces (of "
                  << m.extracted_faces << "), volume " << std::setprecision(2) << m.volume_m3 * 1e6 << " cm^3, euler "
                  << m.euler << ", self-intersections " << (m.self_intersections < 0 ? std::string("not checked") : std::to_string(m.self_intersections)) << ", " << std::setprecision(0)
                  << m.total_s() * 1e3 << " ms\n";
      }
    }
  });
}

}  // namespace orthosim::cli
