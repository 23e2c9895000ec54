// orthosim tune --tissues tissues.json [--tissue NAME ...] [--model model.h5] [--seed N] [--budget-s T]
//   [--max-evaluations N] [--method sa|crs2|isres|direct-l|esch|bobyqa|sbplx|...] [--polish bobyqa|sbplx|none]
//   [--tolerance X] [--per-class] [--out tuned.json] [--plot DIR]
// Tunes the spring parameters of each tissue with mechanics (paper §4.1,
// Eq. 1) against its tissue-table values (libmodel/tune/tune.h,
// docs/tune.md). Without --model the specimen is a 2 x 2 cell block of 1 mm
// cells of the tissue's layer kind; with --model it has the cell size of the
// tissue's built layer in /layers, the tuned laws are applied to that layer
// and /tuning/<tissue> is written into the model. --out writes the tissue
// table with a "tuned" object in each tuned tissue's mechanics; --plot one
// stress-strain PNG per tissue.
#include "libmodel/format/atomic.h"
#include "libmodel/format/model.h"
#include "libmodel/provenance.h"
#include "libmodel/tissues.h"
#include "libmodel/tune/plot.h"
#include "libmodel/tune/tune.h"
#include "tools/common.h"

#include <tbb/parallel_for.h>

#include <chrono>
#include <exception>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <map>
#include <numeric>
#include <optional>
#include <sstream>

namespace orthosim::cli {
namespace {

using nlohmann::json;

const char* const kClassNames[tune::kSpringClasses] = {"structural", "shear", "inter_layer", "body"};

// values in the tissue table's units and keys: kPa for moduli, 1 for strains
json values_json(const tune::Target& q, const std::vector<double>& v) {
  json j = json::object();
  const auto keys = q.keys();
  for (std::size_t i = 0; i < keys.size() && i < v.size(); ++i)
    j[keys[i]] = keys[i] == "turning_strain" ? v[i] : v[i] * 1e-3;
  return j;
}

json params_json(const tune::TuneResult& r) {
  json j = json::array();
  for (SpringClass c : r.classes) {
    const tune::ClassLaw& l = r.params[static_cast<std::size_t>(c)];
    json e = {{"class", kClassNames[static_cast<int>(c)]}, {"code", static_cast<int>(c)}};
    if (r.target.biphasic) {
      e["k1_kpa"] = l.k1_pa * 1e-3;
      e["turning_strain"] = l.turning_strain;
      e["k2_kpa"] = l.k2_pa * 1e-3;
    } else {
      e["k_kpa"] = l.k1_pa * 1e-3;
    }
    j.push_back(e);
  }
  return j;
}

json result_json(const std::string& name, const tune::TuneResult& r) {
  json j = {{"name", name},
          {"target", values_json(r.target, r.target.values())},
          {"weights", r.target.weights},
          {"achieved", values_json(r.target, r.measured.p)},
          {"untuned", values_json(r.target, r.untuned.p)},
          {"psi", r.psi},
          {"max_relative_error", r.max_error},
          {"evaluations", r.evaluations},
          {"seconds", r.seconds},
          {"seconds_per_experiment", r.seconds_per_experiment},
          {"reached", r.reached},
          {"stop", r.stop},
          {"method", r.method},
          {"seed", r.seed},
          {"spring_params", params_json(r)}};
  // the tuned specimen along each axis (TuneResult::axis_ratio; null: the experiment failed)
  json ax = json::object();
  const char* names[3] = {"u", "v", "w"};
  for (std::size_t k = 0; k < 3; ++k) ax[names[k]] = std::isfinite(r.axis_ratio[k]) ? json(r.axis_ratio[k]) : json(nullptr);
  j["axis_ratio"] = ax;
  return j;
}

json experiment_json(const tune::ExperimentOptions& e) {
  return {{"kind", e.kind},
          {"cells", e.cells},
          {"cell_m", e.cell_m},
          {"axis", e.axis},
          {"steps_below", e.steps_below},
          {"stretch", e.stretch},
          {"linear_steps", e.linear_steps},
          {"linear_strain", e.linear_strain},
          {"body_diagonals", e.body_diagonals},
          {"lattice_min_weight", e.lattice_min_weight},
          {"axis_correction", e.axis_correction},
          {"volume_ratio", e.volume_ratio},
          {"volume_group", e.volume_group},
          {"tetra_grid_prisms", e.tetra_grid_prisms},
          {"force_tolerance", e.solver.force_tolerance},
          {"newton_iterations", e.solver.max_iterations}};
}

// One tissue to tune: its target, the specimen, and with --model its layer.
struct Job {
  std::string tissue;
  tune::Target target;
  tune::ExperimentOptions experiment;
  std::string layer_name;  // with --model
  Layer layer;
  tune::SpringParams current{};  // the laws the layer carries now
  tune::TuneResult result;
};

// The tissue's built layer and the one below it (its bottom grid).
void find_layer(const ModelReader& m, Job& job) {
  std::map<int, std::pair<std::string, Layer>> by_order;
  std::int64_t n_global = 0;  // node ids are global: a layer's springs may end on its neighbours'
  for (const auto& name : m.names("/layers")) {
    if (!m.h5().is_group("/layers/" + name) || name == "sets") continue;
    Layer l = m.layer_fields(name, {"nodes"});
    const int order = l.order;
    n_global = std::max(n_global, l.node_offset + static_cast<std::int64_t>(l.nodes.rows()));
    if (const auto seen = by_order.find(order); seen != by_order.end())
      throw Error(m.path(), "layers '" + seen->second.first + "' and '" + name + "' have the same order " + std::to_string(order));
    by_order[order] = {name, std::move(l)};
  }
  for (const auto& [order, named] : by_order) {
    if (named.second.tissue != job.tissue) continue;
    if (named.second.kind != "tetra" && named.second.kind != "lattice")
      throw Error(m.path(), "tissue '" + job.tissue + "' is built as a " + named.second.kind +
                                " layer: only tetra and lattice layers have springs to tune");
    const auto below = by_order.find(order + 1);
    if (below == by_order.end())
      throw Error(m.path(), "layer '" + named.first + "' has no layer below it to give its thickness");
    job.layer_name = named.first;
    job.layer = m.layer(named.first);
    // tune rewrites these springs: a corrupt end would be written back as it came
    const std::string g = "/layers/" + named.first;
    check_index_range(job.layer.springs, n_global, m.path(), g + "/springs");
    check_index_range(job.layer.lin_springs, n_global, m.path(), g + "/lin_springs");
    // the specimen's cells as the build made the layer's (a specimen without
    // the body diagonals measured another rule than the layer's)
    tune::ExperimentOptions defaults;
    const auto prov = m.provenance();
    if (const auto b = prov.find("build"); b != prov.end()) {
      const json p = json::parse(b->second.parameters_json, nullptr, false);
      if (p.is_object()) {
        if (p.contains("body_diagonals") && p["body_diagonals"].is_boolean()) defaults.body_diagonals = p["body_diagonals"].get<bool>();
        if (p.contains("lattice_min_weight") && p["lattice_min_weight"].is_number())
          defaults.lattice_min_weight = p["lattice_min_weight"].get<double>();
        // built before the axis correction (2026-11-27, night), or without it
        defaults.axis_correction = p.contains("axis_correction") && p["axis_correction"].is_boolean() &&
                                   p["axis_correction"].get<bool>();
      }
    }
    job.experiment = tune::experiment_for_layer(job.layer, below->second.second, defaults);
    // the laws the springs carry: recorded with the layer (any table may then
    // retarget it), else as before 2026-11-27; checked before any tuning
    std::optional<Tuning> record;
    if (m.has("/tuning/" + job.tissue)) record = m.tuning(job.tissue);
    job.current = tune::current_params(job.layer, record ? &*record : nullptr, job.target);
    tune::check_layer_law(job.layer, job.current);
    return;
  }
  throw Error(m.path(), "no built layer for tissue '" + job.tissue + "' in /layers: run orthosim build first");
}

}  // namespace

void add_tune_command(CLI::App& app) {
  auto* sub = app.add_subcommand("tune", "tune spring parameters against the tissue table (simulated annealing, Eq. 1)");
  static std::string tissues_path, model, out, plot_dir;
  static std::vector<std::string> names;
  static tune::TuneOptions opt;
  static CommonOptions common;
  sub->add_option("--tissues", tissues_path, "tissue table (tissues.json)")->required();
  sub->add_option("--tissue", names, "tissue to tune (repeatable; default: every tissue with mechanics)");
  sub->add_option("--model", model,
                  "built model: specimens take its layers' cell sizes; the tuned laws and /tuning/<tissue> are written "
                  "into it");
  sub->add_option("--seed", opt.seed, "random seed")
      ->check(seed_check())->capture_default_str();
  sub->add_option("--budget-s", opt.budget_s,
                  "wall-clock budget per tissue (s): a safety net; a run it stops depends on the machine's speed")
      ->capture_default_str();
  sub->add_option("--max-evaluations", opt.max_evaluations,
                  "virtual experiments per tissue (0: no limit); a run bounded by this, not by time, is reproducible")
      // (1e20 was read as 2^63 - 1, silently)
      ->check(CLI::Range(std::int64_t{0}, std::int64_t{1'000'000'000'000}))
      ->capture_default_str();
  sub->add_option("--method", opt.method, "sa, an NLopt global algorithm (crs2, isres, direct-l, esch) or an NLopt "
                                          "local one (bobyqa, sbplx, neldermead, cobyla)")
      ->capture_default_str();
  CLI::Option* const polish =
      sub->add_option("--polish", opt.polish, "local polish after an NLopt global method: bobyqa, sbplx or none")
          ->capture_default_str();
  sub->add_option("--tolerance", opt.tolerance, "stop when every weighted parameter is within this relative error")
      ->capture_default_str();
  sub->add_flag("--per-class", opt.per_class,
               "each spring class its own law (default: one law for every class, which keeps the cell's isotropy; "
               "per class, the stiffness across the load axis is left to the seed)");
  sub->add_option("--out", out, "tuned tissue table (JSON)");
  sub->add_option("--plot", plot_dir, "directory for one stress-strain PNG per tissue");
  add_common_options(sub, common);
  on_run(sub, "tune", common, [polish] {
    Report report("tune");
    try {
      tune::validate(opt);
    } catch (const Error& e) {
      throw UsageError(e.message());
    }
    // a polish follows a global method only: given with sa or a local method it was ignored
    if (polish->count() > 0 && !tune::is_global_method(opt.method))
      throw UsageError("--polish follows an NLopt global method (crs2, isres, direct-l, esch), not --method " +
                       opt.method);
    const TissueTable table = load_tissue_table(tissues_path);
    report.input(tissues_path);

    // the tissues and their targets, all checked before any work
    std::vector<Job> jobs;
    // rigid layers and vessels have no springs: their mechanics are unused
    auto springless = [](const Tissue& t) { return t.layer == "rigid" || t.layer == "vessel"; };
    auto add = [&](const Tissue& t) {
      if (springless(t))
        throw Error(tissues_path, "tissue '" + t.name + "' is a " + t.layer + " tissue: it has no springs to tune");
      Job j;
      j.tissue = t.name;
      try {
        j.target = tune::target_of(t);
        tune::validate(j.target);
      } catch (const Error& e) {
        throw Error(tissues_path, "tissue '" + t.name + "': " + e.message());
      }
      j.experiment.kind = t.layer == "lattice" ? "lattice" : "tetra";
      jobs.push_back(std::move(j));
    };
    if (names.empty()) {
      for (const Tissue& t : table.tissues)
        if (t.mechanics.model != Mechanics::Model::none && !springless(t)) add(t);
      if (jobs.empty()) throw Error(tissues_path, "no tissue has mechanics to tune");
    } else {
      for (const auto& n : names) {
        const Tissue* t = table.find(n);
        if (!t) throw Error(tissues_path, "unknown tissue '" + n + "'");
        for (const Job& j : jobs)
          if (j.tissue == n) throw UsageError("--tissue '" + n + "' given twice");
        add(*t);
      }
    }
    if (!model.empty()) {
      ModelReader m(model);
      if (!m.has("/layers")) throw Error(model, "no /layers in the model: run orthosim build first");
      report.input(model);
      // without --tissue, a tissue the build made rigid (the fixed bottom of a
      // model without a rigid tissue) is not tuned (it was an error)
      if (names.empty()) {
        std::map<std::string, std::string> kind;
        for (const auto& name : m.names("/layers"))
          if (m.h5().is_group("/layers/" + name) && name != "sets") {
            const Layer l = m.layer_fields(name, {});
            kind[l.tissue] = l.kind;
          }
        // nor one the model has no layer for (built with --layers without it, or
        // listed in the table but absent from the data): "run orthosim build first"
        // was wrong advice for a model built with that table
        std::erase_if(jobs, [&](const Job& j) {
          const auto k = kind.find(j.tissue);
          if (k == kind.end()) {
            std::cerr << "tune: note: " << model << ": '" << j.tissue << "' has no layer in the model: not tuned\n";
            return true;
          }
          if (k->second != "rigid") return false;
          std::cerr << "tune: note: " << model << ": '" << j.tissue << "' is built as a rigid layer: not tuned\n";
          return true;
        });
        if (jobs.empty()) throw Error(model, "no tissue with mechanics has a tetra or lattice layer in the model");
      }
      for (Job& j : jobs) {
        try {
          find_layer(m, j);
        } catch (const Error& e) {
          if (!e.file().empty()) throw;
          throw Error(model, e.message());
        }
      }
    }
    // outputs: checked before any work, so that a bad path does not fail
    // after the model was updated
    if (!out.empty()) check_output_file(out);
    if (!plot_dir.empty() && std::filesystem::exists(plot_dir) && !std::filesystem::is_directory(plot_dir))
      throw Error(plot_dir, "--plot must name a directory");
    if (!plot_dir.empty()) check_output_dir(plot_dir);
    // a plot's own name taken by a folder failed at the end, after the model had been
    // updated; checked again, with every other entry, when the plots are committed
    if (!plot_dir.empty())
      for (const Job& j : jobs) {
        const std::filesystem::path png = std::filesystem::path(plot_dir) / (j.tissue + ".png");
        if (std::filesystem::is_directory(png)) throw Error(png.string(), "a folder is in the way of the plot");
      }

    json params = {{"method", opt.method},         {"polish", opt.polish},       {"polish_share", opt.polish_share},
                   {"seed", opt.seed},             {"budget_s", opt.budget_s},   {"max_evaluations", opt.max_evaluations},
                   {"tolerance", opt.tolerance},   {"walk_sweeps", opt.anneal.walk_sweeps},
                   {"per_class", opt.per_class},
                   {"tissues", json::array()}};
    for (const Job& j : jobs) params["tissues"].push_back({{"name", j.tissue}, {"experiment", experiment_json(j.experiment)}});
    report.parameters() = params;

    // tune: the tissues are independent, so they are tuned side by side,
    // each with its own annealer seeded by --seed (a tissue's result does not
    // depend on the others or on the order they finish in). The first failing
    // tissue in table order is the one reported.
    std::vector<std::exception_ptr> failed(jobs.size());
    std::vector<double> seconds(jobs.size(), 0.0);
    tbb::parallel_for(std::size_t{0}, jobs.size(), [&](std::size_t i) {
      const auto t0 = std::chrono::steady_clock::now();
      try {
        jobs[i].result = tune::tune_target(jobs[i].target, jobs[i].experiment, opt);
      } catch (...) {
        failed[i] = std::current_exception();
      }
      seconds[i] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    });
    for (std::size_t i = 0; i < jobs.size(); ++i) {
      if (!failed[i]) continue;
      try {
        std::rethrow_exception(failed[i]);
      } catch (const Error& e) {
        if (!e.file().empty()) throw;
        throw Error(tissues_path, "tissue '" + jobs[i].tissue + "': " + e.message());
      }
    }
    // a tissue none of whose experiments could be measured has no tuned laws:
    // an error, not a model left silently untuned
    for (const Job& j : jobs)
      if (j.result.evaluations == 0)  // (it said "none converged" of the experiments that never ran)
        throw UsageError("tissue '" + j.tissue + "': --budget-s " + (std::ostringstream() << opt.budget_s).str() +
                         " ended before the first virtual experiment ran");
      else if (j.result.measured.p.empty())
        throw Error(model.empty() ? tissues_path : model,
                    "tissue '" + j.tissue + "': no virtual experiment could be measured (" +
                        (j.result.untuned.failure.empty() ? "none converged" : j.result.untuned.failure) + ")");
    for (std::size_t i = 0; i < jobs.size(); ++i) {
      Job& j = jobs[i];
      report.phase("tune." + j.tissue, seconds[i]);
      if (j.result.stop == "budget")  // even with -q: the output is no longer reproducible
        std::cerr << "tune: warning: " << j.tissue << " stopped on the wall-clock budget (--budget-s) after "
                  << j.result.evaluations << " experiments: the result depends on this machine's speed; bound it by "
                  << "--max-evaluations for a reproducible one\n";
      if (!j.result.reached)  // even with -q (the pipeline runs it so): the springs miss the table
        std::cerr << "tune: warning: " << j.tissue << " missed its tolerance (" << 100 * opt.tolerance
                  << " %): max error " << std::setprecision(3) << 100 * j.result.max_error << " % after "
                  << j.result.evaluations << " experiments (stop: " << j.result.stop
                  << "); more experiments (--max-evaluations, the pipeline's --tune-evaluations) or another --method\n";
      if (!j.layer_name.empty()) tune::apply_to_layer(j.layer, j.current, j.result.params);
      if (!common.quiet) {
        const auto& r = j.result;
        const auto q = r.target.values();
        const auto keys = r.target.keys();
        std::cout << "tune: " << j.tissue << " (" << r.method << ", seed " << r.seed << "):";
        for (std::size_t i = 0; i < keys.size(); ++i) {
          const double s = keys[i] == "turning_strain" ? 1.0 : 1e-3;
          std::cout << " " << keys[i] << " " << std::setprecision(5) << (i < r.measured.p.size() ? r.measured.p[i] * s : 0)
                    << " (target " << q[i] * s << ")";
        }
        std::cout << ", max error " << std::setprecision(3) << 100 * r.max_error << " %, psi " << r.psi << ", "
                  << r.evaluations << " experiments, " << std::setprecision(3) << r.seconds << " s"
                  << (r.reached ? "" : " (tolerance not reached: " + r.stop + ")") << "\n";
        // the target is isotropic, the search loads one axis (the specimen's u)
        std::cout << "tune: " << j.tissue << ": " << keys[0] << " along u, v, through the layer: " << std::setprecision(3);
        for (std::size_t k = 0; k < 3; ++k)
          std::cout << (k ? ", " : "") << (std::isfinite(r.axis_ratio[k]) ? (std::ostringstream() << r.axis_ratio[k]).str()
                                                                          : std::string("(failed)"));
        std::cout << " x the target (the search loads u)\n";
      }
    }

    // outputs, each atomic: all written to their temporaries first, then
    // committed together (a plot folder that could not be made failed after the
    // model had been updated and the table written)
    {
      Phase p(report, "write");
      std::optional<AtomicDir> plots;
      if (!plot_dir.empty()) {
        plots.emplace(plot_dir);
        for (const Job& j : jobs) {
          tune::PlotOptions po;
          po.title = j.tissue;
          tune::write_curve_png((std::filesystem::path(plots->temp()) / (j.tissue + ".png")).string(), j.result, po);
        }
      }
      std::optional<AtomicFile> table;
      if (!out.empty()) {
        std::ifstream in(tissues_path);
        std::stringstream text;
        text << in.rdbuf();
        json t = json::parse(text.str());
        for (json& e : t["tissues"]) {
          bool tuned_now = false;
          for (const Job& j : jobs) {
            if (e.value("name", "") != j.tissue) continue;
            tuned_now = true;
            json tuned = result_json(j.tissue, j.result);
            tuned.erase("name");  // (its target stays: a later run tells a stale block by it)
            // wall times stay in the report: the same table, options and seed give
            // the same file byte for byte (they made it differ in two fields)
            tuned.erase("seconds");
            tuned.erase("seconds_per_experiment");
            e["mechanics"]["tuned"] = tuned;
          }
          // a tissue not tuned now keeps an earlier run's block only while the
          // table still holds the targets it was tuned to (a block for k_kpa
          // 2.3 stood next to k_kpa 10, 'reached': true)
          if (!tuned_now && e.contains("mechanics") && e["mechanics"].is_object() && e["mechanics"].contains("tuned")) {
            json& mech = e["mechanics"];
            const json& target = mech["tuned"].is_object() && mech["tuned"].contains("target") ? mech["tuned"]["target"] : json();
            bool same = target.is_object();
            if (same)
              for (const auto& [k, v] : target.items())
                same = same && v.is_number() && mech.contains(k) && mech[k].is_number() &&
                       std::abs(mech[k].get<double>() - v.get<double>()) <= 1e-9 * std::abs(v.get<double>());
            if (!same) {
              mech.erase("tuned");
              std::cerr << "tune: warning: " << tissues_path << ": tissue '" << e.value("name", "")
                        << "': its 'tuned' block was for other targets (or names none); not copied to " << out << "\n";
            }
          }
        }
        table.emplace(out);
        std::ofstream o(table->temp());
        o << t.dump(2) << "\n";
        if (!o) throw Error(out, "could not write the tuned tissue table");
      }
      std::optional<ModelWriter> w;
      if (!model.empty()) {
        w.emplace(model, ModelWriter::Start::update);
        for (const Job& j : jobs) {
          w->remove("/layers/" + j.layer_name);
          w->write_layer(j.layer_name, j.layer);
          w->remove("/tuning/" + j.tissue);
          w->write(j.tissue, tune::tuning_record(j.result));
        }
        w->write("tune", make_provenance(command_line(), report.json()["inputs"].dump(), params.dump(),
                                         static_cast<std::int64_t>(opt.seed),
                                         std::accumulate(seconds.begin(), seconds.end(), 0.0)));
      }
      // the plots first: their folder is merged into one that may hold anything
      // (AtomicDir::commit checks every entry before it moves one); the model and
      // the table are single renames onto paths checked before the work
      if (plots) plots->commit(), report.output(plot_dir);
      if (w) w->commit(), report.output(model);
      if (table) table->commit(), report.output(out);
    }
    report.metrics()["tissues"] = json::array();
    for (const Job& j : jobs) report.metrics()["tissues"].push_back(result_json(j.tissue, j.result));
    report.write(common.report);
  });
}

}  // namespace orthosim::cli
