// orthosim vessels --labels labels.h5 --tissue artery [--tissue vein] [--root X,Y,Z] --model model.h5
//   [--out DIR] [--tolerance MM]
// Extracts each vessel tissue's tree from the label volume (/volume of
// --labels): centreline graph, Bezier tree and closed tube mesh
// (libmodel/vessels/vessels.h, docs/vessels.md). Writes /vessels/<tissue>
// into --model (created if absent, else the groups are added to it), with
// --out also DIR/<tissue>_tube.stl, DIR/<tissue>_tube.obj and
// DIR/<tissue>_centreline.obj.
#include "libmodel/format/model.h"
#include "libmodel/provenance.h"
#include "libmodel/vessels/vessels.h"
#include "tools/common.h"

#include <tbb/global_control.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iomanip>
#include <iostream>
#include <memory>
#include <optional>
#include <sstream>

namespace orthosim::cli {
namespace {

using nlohmann::json;

json point_json(const Eigen::Vector3d& p) { return {p.x(), p.y(), p.z()}; }

json metrics_json(const VesselMetrics& m) {
  int open = 0, closed = 0;
  json ends = json::array();
  for (const VesselEnd& e : m.ends) {
    (e.open ? open : closed) += 1;
    ends.push_back({{"position_m", point_json(e.position_m)},
                    {"radius_m", e.radius_m},
                    {"branch", e.branch},
                    {"root", e.root},
                    {"open", e.open}});
  }
  json cuts = json::array();
  for (const VesselCut& c : m.cuts)
    cuts.push_back({{"kind", c.kind}, {"position_m", point_json(c.position_m)}, {"radius_m", c.radius_m}});
  return {{"label", m.label},
          {"voxels", m.voxels},
          {"skeleton_voxels", m.skeleton_voxels},
          {"trees", m.trees},
          {"branches", m.branches},
          {"bifurcations", m.bifurcations},
          {"trifurcations", m.trifurcations},
          {"open_ends", open},
          {"closed_ends", closed},
          {"ends", ends},
          {"spurs_pruned", m.spurs_pruned},
          {"children_pruned", m.children_pruned},
          {"pruned_length_m", m.pruned_length_m},
          {"loops_broken", m.loops_broken},
          {"contacts_cut", m.contacts_cut},
          {"components_dropped", m.components_dropped},
          {"thin_components_dropped", m.thin_components_dropped},
          {"cuts", cuts},
          {"roots_used", m.roots_used},
          {"radius_min_m", m.radius_min_m},
          {"radius_max_m", m.radius_max_m},
          {"length_m", m.length_m},
          {"bezier",
           {{"pieces", m.bezier_pieces}, {"tolerance_m", m.tolerance_m}, {"max_deviation_m", m.bezier_max_deviation_m}}},
          {"tube",
           {{"vertices", m.tube_vertices},
            {"quads", m.tube_quads},
            {"triangles", m.tube_tris},
            {"closed", m.tube_closed},
            {"manifold", m.tube_manifold},
            {"oriented", m.tube_oriented},
            {"components", m.tube_components},
            {"self_intersections", m.self_intersections}}},
          {"tube_to_label_boundary_m",
           {{"mean", m.boundary_mean_m}, {"p95", m.boundary_p95_m}, {"max", m.boundary_max_m}}},
          {"phases_s",
           {{"distance", m.distance_s},
            {"thinning", m.thinning_s},
            {"graph", m.graph_s},
            {"centreline", m.centreline_s},
            {"fit", m.fit_s},
            {"tube", m.tube_s},
            {"check", m.check_s}}}};
}

std::string mm(const Eigen::Vector3d& p) {
  std::ostringstream s;
  s << std::fixed << std::setprecision(2) << 1e3 * p.x() << "," << 1e3 * p.y() << "," << 1e3 * p.z();
  return s.str();
}

}  // namespace

void add_vessels_command(CLI::App& app) {
  auto* sub = app.add_subcommand(
      "vessels", "extract vessel trees (centreline, Bezier tree, tube mesh) from a label volume into /vessels");
  struct Args {
    std::string labels, model, out;
    std::vector<std::string> tissues, roots;
    double tolerance_mm = 0;
    double min_radius_voxels = VesselOptions{}.min_radius_voxels;
    double spur_ratio = VesselOptions{}.spur_ratio;
    int ring_vertices = 24, threads = 0, max_children = 3;
    bool no_self_intersection_check = false, refuse_excess_children = false, skip_unformed = false;
    CommonOptions common;
  };
  static Args a;
  sub->add_option("--labels", a.labels, "model file with the label volume /volume (orthosim segment, phantom truth.h5)")
      ->required();
  sub->add_option("--tissue", a.tissues, "vessel tissue to extract (repeat, or comma-separated)")
      ->required()
      ->delimiter(',');
  sub->add_option("--root", a.roots,
                  "X,Y,Z in mm: the vessel end nearest to it becomes its tree's root (repeat for several trees); "
                  "default: each tree's widest end");
  sub->add_option("--model", a.model, "model file to write /vessels/<tissue> into (created if absent)")->required();
  sub->add_option("--out", a.out, "also write DIR/<tissue>_tube.stl, _tube.obj and _centreline.obj");
  sub->add_option("--tolerance", a.tolerance_mm,
                  "largest Bezier-to-centreline distance in mm (0: a quarter of the smallest voxel size)")
      ->capture_default_str();
  sub->add_option("--ring-vertices", a.ring_vertices, "vertices around each tube ring, a multiple of 4 in 8..256 "
                                                      "(and of 6 for trifurcations)")
      ->capture_default_str();
  sub->add_option("--max-children", a.max_children,
                  "most children a junction may have, 2..4 (4 needs --ring-vertices a multiple of 8)")
      ->capture_default_str();
  sub->add_option("--min-radius-voxels", a.min_radius_voxels,
                  "drop as noise a piece of vessel label whose largest inscribed radius is below this many of the "
                  "smallest voxel spacing where a thicker piece exists (0.75: nowhere more than 2 voxels across), >= 0 (0: keep them)")
      ->capture_default_str();
  sub->add_option("--spur-ratio", a.spur_ratio,
                  "remove as a spur a skeleton branch from a junction to an end that is shorter than this many inscribed "
                  "radii at its junction (raise it for noisy labels: docs/vessels.md), > 0")
      ->capture_default_str();
  sub->add_flag("--refuse-excess-children", a.refuse_excess_children,
                "refuse a junction with more children instead of dropping its shortest leaf children");
  sub->add_flag("--skip-unformed", a.skip_unformed,
                "leave out, with a warning, a tissue whose voxels form no vessel (every piece too short for its "
                "radius) instead of failing; the others are written");
  sub->add_flag("--no-self-intersection-check", a.no_self_intersection_check,
                "skip counting the tube's self-intersections (CGAL)");
  sub->add_option("--threads", a.threads, "worker threads (0: all cores)")->capture_default_str();
  add_common_options(sub, a.common);

  on_run(sub, "vessels", a.common, [] {
    // ---- flags, before any work -------------------------------------------------
    VesselOptions o;
    if (!std::isfinite(a.tolerance_mm) || a.tolerance_mm < 0) throw UsageError("--tolerance: must be >= 0 (mm)");
    o.tolerance_m = a.tolerance_mm * 1e-3;
    o.ring_vertices = a.ring_vertices;
    o.max_children = a.max_children;
    if (!std::isfinite(a.min_radius_voxels) || a.min_radius_voxels < 0)
      throw UsageError("--min-radius-voxels: must be a number >= 0");
    o.min_radius_voxels = a.min_radius_voxels;
    if (!std::isfinite(a.spur_ratio) || !(a.spur_ratio > 0)) throw UsageError("--spur-ratio: must be a number > 0");
    o.spur_ratio = a.spur_ratio;
    o.prune_excess_children = !a.refuse_excess_children;
    o.check_self_intersections = !a.no_self_intersection_check;
    for (const std::string& r : a.roots) {
      const std::vector<double> p = parse_list(r, 3, "--root", false);
      o.roots_m.emplace_back(p[0] * 1e-3, p[1] * 1e-3, p[2] * 1e-3);
    }
    try {
      validate(o);
    } catch (const Error& e) {
      std::string m = e.message();
      if (m.rfind("ring_vertices", 0) == 0) m = "--ring-vertices" + m.substr(13);
      if (m.rfind("max_children", 0) == 0) m = "--max-children" + m.substr(12);
      throw UsageError(m);
    }
    if (a.threads < 0) throw UsageError("--threads: must be >= 0");
    std::vector<std::string> tissues;
    for (const std::string& t : a.tissues) {
      if (t.empty()) throw UsageError("--tissue: empty tissue name");
      if (std::find(tissues.begin(), tissues.end(), t) == tissues.end()) tissues.push_back(t);
    }
    std::unique_ptr<tbb::global_control> threads;
    if (a.threads > 0)
      threads = std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism, a.threads);

    // ---- inputs and outputs are checked before anything is written ----------------
    {
      std::error_code ec;
      if (!std::filesystem::exists(a.labels, ec)) throw Error(a.labels, "no such file");
    }
    check_output_file(a.model);
    if (std::filesystem::exists(a.model)) ModelReader check(a.model);  // an existing model must be ours
    if (!a.out.empty()) check_output_dir(a.out);

    Report report("vessels");
    report.parameters() = json::parse(vessel_parameters_json(o));
    report.parameters()["tissues"] = tissues;
    report.parameters()["threads"] = a.threads;
    Volume v;
    {
      Phase p(report, "read");
      ModelReader in(a.labels);
      v = in.volume();
    }
    report.input(a.labels);
    // the volume's frame: roots outside it are a mistake, not an empty match
    for (std::size_t i = 0; i < o.roots_m.size(); ++i) {
      const int n[3] = {v.nx, v.ny, v.nz};
      for (int d = 0; d < 3; ++d) {
        const double lo = v.origin_m[d] - 0.5 * v.spacing_m[d], hi = v.origin_m[d] + (n[d] - 0.5) * v.spacing_m[d];
        if (o.roots_m[i](d) < lo || o.roots_m[i](d) > hi)
          throw UsageError("--root " + a.roots[i] + ": outside the volume of " + a.labels + " (" +
                           mm(Eigen::Vector3d(v.origin_m[0], v.origin_m[1], v.origin_m[2])) + " to " +
                           mm(v.position(v.nx - 1, v.ny - 1, v.nz - 1)) + " mm)");
      }
    }

    // ---- every tissue, all before any output ---------------------------------------
    std::vector<VesselResult> results;
    std::vector<char> root_used(o.roots_m.size(), 0);
    json left_out = json::array();
    std::vector<std::string> unformed;
    for (const std::string& t : tissues) {
      Phase p(report, "extract." + t);
      try {
        results.push_back(extract_vessels(v, t, o));
      } catch (const NoVesselError& e) {
        if (!a.skip_unformed) throw Error(a.labels, e.message());
        left_out.push_back({{"tissue", t}, {"why", e.message()}});
        unformed.push_back(t);
        std::cerr << "orthosim vessels: warning: " << a.labels << ": " << e.message() << "; it is left out\n";
        continue;
      } catch (const Error& e) {
        if (!e.file().empty()) throw;
        throw Error(a.labels, e.message());
      }
      for (int i : results.back().metrics.roots_used) root_used[static_cast<std::size_t>(i)] = 1;
    }
    for (const std::string& t : unformed) tissues.erase(std::find(tissues.begin(), tissues.end(), t));
    for (std::size_t i = 0; i < o.roots_m.size(); ++i)
      if (!root_used[i]) {
        // the nearest vessel end, to say how far off the point is
        double best = 1e300;
        Eigen::Vector3d at(0, 0, 0);
        const VesselEnd* nearest = nullptr;
        for (const VesselResult& r : results)
          for (const VesselEnd& e : r.metrics.ends)
            if ((e.position_m - o.roots_m[i]).norm() < best)
              best = (e.position_m - o.roots_m[i]).norm(), at = e.position_m, nearest = &e;
        const double voxel = std::max({v.spacing_m[0], v.spacing_m[1], v.spacing_m[2]});
        std::ostringstream m;
        m << std::fixed << std::setprecision(2) << "--root " << a.roots[i];
        if (nearest && best <= 3 * nearest->radius_m + 2 * voxel)
          // in reach, so its tree took another root (it said "no end within reach, 0.03 mm away")
          m << ": the vessel end at " << mm(at) << " mm (" << 1e3 * best
            << " mm away) is on a tree another --root has rooted already: one root per tree";
        else
          m << ": no vessel end of " << json(tissues).dump() << " within reach (3 radii + 2 voxels); the nearest end is at "
            << mm(at) << " mm, " << 1e3 * best << " mm away";
        throw UsageError(m.str());
      }

    // ---- outputs: the directory, then the model -------------------------------------
    {
      Phase p(report, "write");
      std::optional<AtomicDir> dir;
      if (!a.out.empty()) {
        dir.emplace(a.out);
        for (std::size_t i = 0; i < tissues.size(); ++i) {
          write_tube_stl(dir->temp_path(tissues[i] + "_tube.stl"), results[i].tree);
          write_tube_obj(dir->temp_path(tissues[i] + "_tube.obj"), results[i].tree);
          write_centreline_obj(dir->temp_path(tissues[i] + "_centreline.obj"), results[i].tree);
        }
      }
      ModelWriter w(a.model, ModelWriter::Start::update);
      double wall = 0;
      for (std::size_t i = 0; i < tissues.size(); ++i) {
        w.write(tissues[i], results[i].tree);
        const VesselMetrics& m = results[i].metrics;
        wall += m.distance_s + m.thinning_s + m.graph_s + m.centreline_s + m.fit_s + m.tube_s + m.check_s;
      }
      w.write("vessels", make_provenance(command_line(), report.json()["inputs"].dump(),
                                         report.parameters().dump(), 0, wall));
      if (dir) dir->commit();
      w.commit();
    }
    if (!a.out.empty())
      for (const std::string& t : tissues)
        for (const char* s : {"_tube.stl", "_tube.obj", "_centreline.obj"}) report.output(a.out + "/" + t + s);
    report.output(a.model);

    // ---- report and summary ---------------------------------------------------------
    json& j = report.metrics();
    j["volume"] = {{"size", {v.nx, v.ny, v.nz}},
                   {"spacing_m", {v.spacing_m[0], v.spacing_m[1], v.spacing_m[2]}}};
    j["tissues"] = json::object();
    j["left_out"] = left_out;
    for (std::size_t i = 0; i < tissues.size(); ++i) j["tissues"][tissues[i]] = metrics_json(results[i].metrics);
    report.write(a.common.report);
    for (std::size_t i = 0; i < tissues.size(); ++i) {
      const VesselMetrics& m = results[i].metrics;
      if (m.children_pruned > 0)  // even with --quiet: the tree lost branches the labels show
        std::cerr << "orthosim vessels: warning: " << a.labels << ": " << tissues[i] << ": dropped "
                  << m.children_pruned << " leaf branch(es), " << std::fixed << std::setprecision(1)
                  << 1e3 * m.pruned_length_m << " mm in all, at junctions with more than " << a.max_children
                  << " children (--refuse-excess-children refuses instead)\n";
      if (m.self_intersections > 0)  // even with --quiet: a tube that cuts itself misleads collisions and rendering
        std::cerr << "orthosim vessels: warning: " << a.labels << ": " << tissues[i] << ": the tube has "
                  << m.self_intersections << " self-intersecting face pair(s) (" << m.trees << " tree(s), "
                  << m.branches << " branches, from " << m.voxels
                  << " voxels): branches short or sharply bent against their radius, or touching or noisy "
                     "vessel labels (the segment report's vessel Dice and islands)\n";
    }
    if (!a.common.quiet) {
      for (std::size_t i = 0; i < tissues.size(); ++i) {
        const VesselMetrics& m = results[i].metrics;
        int open = 0;
        for (const VesselEnd& e : m.ends) open += e.open;
        std::cout << std::fixed << std::setprecision(3) << "vessels: " << tissues[i] << ": " << m.trees
                  << (m.trees == 1 ? " tree, " : " trees, ") << m.branches << " branches, " << m.bifurcations
                  << " bifurcations";
        if (m.trifurcations) std::cout << ", " << m.trifurcations << " trifurcations";
        std::cout << ", " << m.ends.size() << " ends (" << open << " open at the border), " << m.loops_broken
                  << " loops broken, " << m.contacts_cut << " contacts cut; Bezier " << m.bezier_pieces
                  << " pieces, max deviation " << 1e3 * m.bezier_max_deviation_m << " mm; tube " << m.tube_quads
                  << " quads, " << (m.tube_closed && m.tube_manifold ? "closed manifold" : "NOT closed/manifold");
        if (m.self_intersections >= 0) std::cout << ", " << m.self_intersections << " self-intersections";
        std::cout << ", to the label boundary mean " << 1e3 * m.boundary_mean_m << " max " << 1e3 * m.boundary_max_m
                  << " mm; " << std::setprecision(0)
                  << 1e3 * (m.distance_s + m.thinning_s + m.graph_s + m.centreline_s + m.fit_s + m.tube_s + m.check_s)
                  << " ms\n";
      }
      std::cout << "vessels: wrote " << a.model;
      if (!a.out.empty()) std::cout << " and " << a.out << "/";
      std::cout << "\n";
    }
  });
}

}  // namespace orthosim::cli
