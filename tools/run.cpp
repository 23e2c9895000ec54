// orthosim run SCENE.json: loads the scene's model lazily, simulates it and
// writes its ParaView series; the report gives the speed and the stability
// events. Everything is validated before the first step.
#include "libmodel/format/atomic.h"
#include "runtime/scene.h"
#include "tools/common.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <iterator>
#include <map>
#include <set>
#include <iomanip>
#include <sstream>
#include <vector>

namespace orthosim::cli {

namespace {

// " 'name'" for a named tool in a message, "" for an unnamed one
std::string quoted(const std::string& name) { return name.empty() ? std::string() : " '" + name + "'"; }

// the fluid's substeps by the limit that set their length
nlohmann::json substep_limits(const runtime::FluidCounters& c) {
  nlohmann::json j = nlohmann::json::object();
  for (std::size_t k = 0; k < c.substep_limit.size(); ++k) j[runtime::substep_limit_name(static_cast<int>(k))] = c.substep_limit[k];
  return j;
}

// triangle grids built for the fluid's moving surfaces (the other steps reused one)
std::int64_t surface_grid_builds(const runtime::FluidState& fs) {
  std::int64_t n = 0;
  for (const auto& sf : fs.surfaces) n += sf.grid.builds;
  return n;
}
}  // namespace

void add_run_command(CLI::App& app) {
  auto* sub = app.add_subcommand("run", "simulate a scene: lazy model loading, mass-spring solver, ParaView output");
  static std::string scene_file, model_override, out_override;
  static long steps = 0;
  static int threads = 0;
  static bool no_output = false;
  static CommonOptions common;
  sub->add_option("scene", scene_file, "scene file (.json); see docs/runtime.md")->required();
  CLI::Option* const steps_flag =
      sub->add_option("--steps", steps, "number of steps of the scene's dt, >= 1 (default: duration / dt)");
  CLI::Option* const threads_flag =
      sub->add_option("--threads", threads, "worker threads (default: the scene's, 0 = all cores)");
  sub->add_option("--model", model_override, "model file, instead of the scene's");
  sub->add_option("--out", out_override, "output directory, instead of the scene's");
  sub->add_flag("--no-output", no_output, "write no ParaView series");
  add_common_options(sub, common);
  on_run(sub, "run", common, [steps_flag, threads_flag] {
    Report report("run");
    const bool steps_given = steps_flag->count() > 0;
    // 1e9 steps: a day at 10^4 steps/s; beyond, a count that overflowed or a
    // dt far too small for the duration (dt 1e-20 over 1 s ran "1 steps")
    constexpr long kMaxSteps = 1000000000;
    if (steps_given && (steps < 1 || steps > kMaxSteps))
      throw UsageError("--steps must be in 1..1e9, got " + std::to_string(steps) +
                       " (leave it out to run the scene's duration)");
    // (-1 was the "not given" value, so --threads -1 ran with the scene's threads)
    const bool threads_given = threads_flag->count() > 0;
    if (threads_given && (threads < 0 || threads > 1024))
      throw UsageError("--threads must be in 0..1024, got " + std::to_string(threads));
    // (both ran with no output and no word)
    if (no_output && !out_override.empty()) throw UsageError("--no-output and --out contradict each other: give one");
    runtime::SceneDef def = runtime::parse_scene_file(scene_file);
    if (!model_override.empty()) def.model = model_override;
    if (!out_override.empty()) {
      def.output.enabled = true;
      def.output.dir = out_override;
    }
    if (no_output) def.output.enabled = false;
    if (threads_given) def.threads = threads;
    if (!steps_given && !(def.duration / def.dt <= kMaxSteps))
      throw Error(scene_file, "duration / dt = " + (std::ostringstream() << def.duration / def.dt).str() +
                                  " steps, more than 1e9: a larger dt or a shorter duration (or --steps)");
    const long n_steps = steps_given ? steps : std::max(1L, std::lround(def.duration / def.dt));
    const double last_start = static_cast<double>(n_steps - 1) * def.dt;  // the last step starts here
    auto never_acts = [&](const runtime::ToolDef& t) { return t.start > last_start * (1 + 1e-12) + 1e-15; };

    // a --report among the series' files would replace one (tissue.pvd held the
    // JSON report, the series broken, exit 0), or be removed as a stale frame
    if (def.output.enabled && !common.report.empty()) {
      namespace fs = std::filesystem;
      const fs::path r = fs::weakly_canonical(common.report), dir = fs::weakly_canonical(def.output.dir);
      // (only the series' own names: tissue_report.json is fine)
      if (r.parent_path() == dir && runtime::is_series_file(def.output.name, r.filename().string()))
        throw Error(common.report, "--report names a file of the output series (" + def.output.name + "* in " +
                                       def.output.dir + "): the report would replace it; name another file");
    }
    report.input(scene_file);  // before the load: refuses a --report that names the scene's model
    if (std::filesystem::exists(def.model)) report.input(def.model);
    std::unique_ptr<runtime::Scene> scene;
    {
      Phase p(report, "load");
      scene = std::make_unique<runtime::Scene>(def);
    }
    // what the scene asks for that this run will not do (even with --quiet); after
    // the load, so that a scene the load refuses gets its one error line alone
    if (!steps_given && def.duration < 0.5 * def.dt)
      std::cerr << "orthosim run: warning: " << scene_file << ": duration " << def.duration
                << " s is under half a step (dt = " << def.dt << " s); one step is run\n";
    if (def.fluid.enabled && def.vessels.empty())
      for (const auto& t : def.tools)
        if (t.type == runtime::ToolType::cut) {
          std::cerr << "orthosim run: warning: " << scene_file << ": the scene has blood and a cut"
                    << quoted(t.name)
                    << " but loads no vessel tree, so nothing can bleed (name the trees in \"vessels\")\n";
          break;
        }
    for (const auto& t : def.tools)
      if (never_acts(t))
        std::cerr << "orthosim run: warning: " << scene_file << ": the " << runtime::to_string(t.type) << " tool"
                  << quoted(t.name) << " starts at t = " << t.start
                  << " s, after the run's last step starts (t = " << last_start << " s, " << n_steps
                  << " steps of " << def.dt << " s): it never acts\n";

    const runtime::Model& m0 = scene->model();  // a cut replaces the model: not used after the steps
    // what a tool will not do (even with --quiet):
    // - a pull, hook or pressure tool whose nodes are all fixed already moves
    //   nothing (a pull on the "fixed" set ran as if it were not there);
    // - a drain that cannot reach the blood's domain never drains (a centre 100 m
    //   off ran with 0 drained and nothing said);
    // - a cut polyline snapped farther than its depth lay off the skin (5 m off a
    //   7 cm limb was snapped onto it and cut, silently)
    const runtime::FluidBoundaries* const fb = scene->fluid_boundaries();
    std::set<std::string> outside_domain;  // drains warned of here (not again after the run)
    for (std::size_t k = 0; k < def.tools.size(); ++k) {
      const runtime::ToolDef& t = def.tools[k];
      const int id = static_cast<int>(k);
      if (t.type == runtime::ToolType::pull || t.type == runtime::ToolType::hook || t.type == runtime::ToolType::pressure) {
        const auto& nodes = scene->tool_nodes(id);
        bool all_fixed = !nodes.empty();
        for (auto i : nodes) all_fixed = all_fixed && scene->state().pin[static_cast<std::size_t>(i)] == runtime::Pin::fixed;
        if (all_fixed)
          std::cerr << "orthosim run: warning: " << scene_file << ": the " << runtime::to_string(t.type) << " tool"
                    << quoted(t.name) << " takes only the " << nodes.size()
                    << " fixed node(s) it found: it does nothing (its nodes or centre?)\n";
      } else if (t.type == runtime::ToolType::drain && fb) {
        const auto c = scene->tool_center(id);
        double d2 = 0;  // from the centre to the domain box
        for (std::size_t a = 0; a < 3; ++a) {
          const double e = std::max({fb->lo[a] - c[a], 0.0, c[a] - fb->hi[a]});
          d2 += e * e;
        }
        if (std::sqrt(d2) > t.radius) {
          outside_domain.insert(t.name);
          std::cerr << "orthosim run: warning: " << scene_file << ": the drain" << quoted(t.name) << " lies "
                    << std::sqrt(d2) - t.radius
                    << " m outside the blood's domain (the loaded tissue's box grown by fluid.margin): it never "
                       "drains\n";
        }
      } else if (t.type == runtime::ToolType::cut && scene->tool_snap_distance(id) > t.depth) {
        std::cerr << "orthosim run: warning: " << scene_file << ": the cut" << quoted(t.name)
                  << "'s polyline lies off its nodes: the snap moved a point " << scene->tool_snap_distance(id)
                  << " m, more than the cut's depth (" << t.depth << " m); check its points (or \"snap\": false)\n";
      }
    }
    // - a collider the blood's domain does not reach never acts; a plane with
    //   the whole domain behind it pushes every particle out of the domain
    if (fb) {
      // (the boundaries' planes and meshes are the colliders', in the scene's order)
      std::size_t plane = 0, mesh = 0;
      for (const runtime::ColliderDef& c : def.colliders) {
        if (!c.blood || !c.path.t.empty()) continue;  // (a moving one is a moving wall, not in the boundaries)
        if (c.kind == runtime::ColliderDef::Kind::plane) {
          const runtime::FluidPlane& pl = fb->planes[plane++];
          int ahead = 0;
          for (int k = 0; k < 8; ++k) {
            double d = 0;
            for (std::size_t a = 0; a < 3; ++a) d += pl.normal[a] * ((k >> a & 1 ? fb->hi[a] : fb->lo[a]) - pl.point[a]);
            ahead += d > 0;
          }
          if (ahead == 8)
            std::cerr << "orthosim run: warning: " << scene_file << ": the collider" << quoted(c.name)
                      << " (a plane) lies outside the blood's domain: it never acts\n";
          else if (ahead == 0)
            std::cerr << "orthosim run: warning: " << scene_file << ": the collider" << quoted(c.name)
                      << " (a plane) has the blood's whole domain behind it: it pushes all the blood out (its normal?)\n";
        } else {
          const runtime::FluidMesh& m = fb->meshes[mesh++];
          bool overlaps = false;  // a triangle's box meets the domain box
          for (std::size_t t = 0; 3 * t < m.triangles.size() && !overlaps; ++t) {
            bool meets = true;
            for (std::size_t a = 0; a < 3; ++a) {
              double lo = HUGE_VAL, hi = -HUGE_VAL;
              for (std::size_t k = 0; k < 3; ++k) {
                const double x = m.vertices[3 * static_cast<std::size_t>(m.triangles[3 * t + k]) + a];
                lo = std::min(lo, x), hi = std::max(hi, x);
              }
              meets = meets && hi >= fb->lo[a] && lo <= fb->hi[a];
            }
            overlaps = meets;
          }
          if (!overlaps)
            std::cerr << "orthosim run: warning: " << scene_file << ": the collider" << quoted(c.name) << " ("
                      << c.stl << ") lies outside the blood's domain: it never acts (its units or frame?)\n";
        }
      }
    }
    // - tissue behind a collider at rest: a plane pushes those nodes onto itself
    //   in the first step (a jolt, when many); a one-sided mesh cannot tell
    //   them from nodes inside it and leaves them there
    if (const runtime::Obstacles* ob = scene->obstacles()) {
      const runtime::Model& m = scene->model();
      std::vector<std::int32_t> free_nodes;
      for (std::int32_t i = 0; i < m.n_nodes; ++i)
        if (scene->state().inv_mass[static_cast<std::size_t>(i)] > 0) free_nodes.push_back(i);
      // (the moving colliders where they are at the start)
      std::vector<runtime::ObstacleFrame> frames;
      runtime::obstacle_frames(*ob, scene->state().obstacle_paths, scene->time(), 0, frames);
      const std::vector<std::int64_t> behind =
          runtime::obstacle_nodes_behind(*ob, scene->positions(), free_nodes, runtime::ObstacleMotion{frames});
      // the loaded nodes' rest box grown by its largest side: a mesh beyond it
      // meets the tissue only if the tissue moves farther than its own size
      const auto [rlo, rhi] = runtime::rest_box(m);
      const double lo[3] = {rlo.x, rlo.y, rlo.z}, hi[3] = {rhi.x, rhi.y, rhi.z};
      const double grow = std::max({hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]});
      std::size_t plane = 0, mesh = 0;  // (behind: the planes' counts, then the meshes', in the scene's order)
      // the tissue's node spacing: the median spring rest length
      double spacing = 0;
      if (m.n_springs > 0) {
        std::vector<double> rest(m.spring_rest.begin(), m.spring_rest.end());
        std::nth_element(rest.begin(), rest.begin() + static_cast<std::ptrdiff_t>(rest.size() / 2), rest.end());
        spacing = rest[rest.size() / 2];
      }
      for (const runtime::ColliderDef& c : def.colliders) {
        if (!c.tissue) continue;
        if (c.kind == runtime::ColliderDef::Kind::mesh) {
          // its bounding box, and (turning) its radius about its pivot
          const runtime::ObstacleMesh& om = ob->meshes[mesh];
          double mlo[3] = {HUGE_VAL, HUGE_VAL, HUGE_VAL}, mhi[3] = {-HUGE_VAL, -HUGE_VAL, -HUGE_VAL}, r2 = 0;
          for (std::size_t v = 0; 3 * v < om.vertices.size(); ++v) {
            for (int a = 0; a < 3; ++a) mlo[a] = std::min(mlo[a], om.vertices[3 * v + a]), mhi[a] = std::max(mhi[a], om.vertices[3 * v + a]);
            const runtime::Vec3 d = runtime::load3(om.vertices.data(), static_cast<std::int64_t>(v)) - om.pivot;
            r2 = std::max(r2, runtime::dot(d, d));
          }
          // - a moving mesh narrower than the tissue's node spacing whose edges
          //   do not meet the tissue's faces (edge_spacing 0, or no quads): only
          //   nodes collide, so it can pass between them (a probe through the skin)
          double ext[3] = {mhi[0] - mlo[0], mhi[1] - mlo[1], mhi[2] - mlo[2]};
          std::sort(ext, ext + 3);
          if (!c.path.t.empty() && ext[1] < spacing && om.samples.empty())
            std::cerr << "orthosim run: warning: " << scene_file << ": the moving collider" << quoted(c.name) << " (" << c.stl
                      << ") is " << ext[1] << " m across, less than the tissue's node spacing (" << spacing
                      << " m, the median spring): only nodes collide, so it can pass between them\n";
          // - a mesh farther from the tissue than the tissue's size (with blood
          //   and static: the domain's check above); a moving one: the box it
          //   sweeps along its path (turning, of the ball about its pivot that holds it)
          if (!(c.blood && fb) || !c.path.t.empty()) {
            bool meets = true;
            const double piv[3] = {om.pivot.x, om.pivot.y, om.pivot.z};
            for (int a = 0; a < 3 && meets; ++a) {
              double blo = mlo[a], bhi = mhi[a], dlo = 0, dhi = 0;
              if (!c.path.r.empty()) blo = piv[a] - std::sqrt(r2), bhi = piv[a] + std::sqrt(r2);
              for (std::size_t w = 0; w < c.path.t.size(); ++w)
                dlo = std::min(dlo, c.path.p[3 * w + a]), dhi = std::max(dhi, c.path.p[3 * w + a]);
              meets = bhi + dhi >= lo[a] - grow && blo + dlo <= hi[a] + grow;
            }
            if (!meets)
              std::cerr << "orthosim run: warning: " << scene_file << ": the collider" << quoted(c.name) << " (" << c.stl
                        << ") lies farther from the tissue than the tissue's own size (" << grow
                        << " m): it never meets it (its units or frame?)\n";
          }
        }
        const std::int64_t n =
            behind[c.kind == runtime::ColliderDef::Kind::plane ? plane++ : ob->planes.size() + mesh++];
        if (n == 0) continue;
        if (c.kind == runtime::ColliderDef::Kind::plane)
          std::cerr << "orthosim run: warning: " << scene_file << ": the collider" << quoted(c.name) << " (a plane) has " << n
                    << " of the tissue's " << free_nodes.size()
                    << " free nodes behind it at rest: the first step puts them on it (its point or normal?)\n";
        else
          std::cerr << "orthosim run: warning: " << scene_file << ": the collider" << quoted(c.name) << " (" << c.stl << ") has "
                    << n << " of the tissue's free nodes just behind its faces at rest: a one-sided mesh leaves them "
                    << "there (its placement, units or orientation?)\n";
      }
    }
    // - two tools that hold the same nodes at the same time do not add up: a hook
    //   fixes them, and a pull that moves them overrides another (a hook and a
    //   pull on one grip left it still; of two pulls only the later acted). Spring
    //   pulls (stiffness > 0) add their forces: no warning for two of them.
    auto holds = [](const runtime::ToolDef& t) {
      return t.type == runtime::ToolType::hook || t.type == runtime::ToolType::pull;
    };
    for (std::size_t a = 0; a < def.tools.size(); ++a)
      for (std::size_t b = a + 1; b < def.tools.size(); ++b) {
        const runtime::ToolDef &ta = def.tools[a], &tb = def.tools[b];
        if (!holds(ta) || !holds(tb) || !(ta.start < tb.end && tb.start < ta.end)) continue;
        if (ta.type == runtime::ToolType::pull && tb.type == runtime::ToolType::pull && ta.stiffness > 0 && tb.stiffness > 0)
          continue;
        auto na = scene->tool_nodes(static_cast<int>(a)), nb = scene->tool_nodes(static_cast<int>(b));
        std::sort(na.begin(), na.end());
        std::sort(nb.begin(), nb.end());
        std::vector<std::int32_t> shared;
        std::set_intersection(na.begin(), na.end(), nb.begin(), nb.end(), std::back_inserter(shared));
        if (shared.empty()) continue;
        std::cerr << "orthosim run: warning: " << scene_file << ": the " << runtime::to_string(ta.type) << " tool"
                  << quoted(ta.name) << " and the " << runtime::to_string(tb.type) << " tool" << quoted(tb.name)
                  << " hold " << shared.size() << " of the same node(s) at the same time (from "
                  << std::max(ta.start, tb.start) << " s): they do not add up (a hook fixes its nodes; of two pulls "
                     "that move nodes, the later one listed moves them)\n";
      }
    auto& par = report.parameters();
    par["model"] = def.model;
    par["layers"] = def.layers;
    par["integrator"] = runtime::to_string(def.solver.integrator);
    par["dt_s"] = def.dt;
    par["steps"] = n_steps;
    par["substeps"] = def.solver.substeps == 0 ? nlohmann::json("auto") : nlohmann::json(def.solver.substeps);
    par["threads"] = def.threads;
    par["gravity"] = def.solver.gravity;
    par["mass_damping"] = def.solver.mass_damping;
    par["output"] = def.output.enabled ? def.output.dir : "";
    if (!common.quiet)
      std::cerr << "run: " << m0.n_nodes << " nodes (" << m0.n_anchors << " anchors), " << m0.n_springs
                << " linear springs, " << m0.n_tets << " volume tetrahedra, " << n_steps << " steps of " << def.dt << " s, "
                << runtime::to_string(def.solver.integrator) << "\n";

    Progress progress("run", n_steps, common.quiet);
    runtime::RunSummary r;
    // layers turned inside out, per step (runtime::inverted_columns; cheap:
    // one dot product per grid column and layer)
    struct Inversion {
      std::int32_t columns = 0, max = 0, end = 0;
      long first_step = -1;
    };
    std::map<std::string, Inversion> inversion;
    auto check_inversion = [&](long step) {
      for (const auto& c : runtime::inverted_columns(scene->model(), scene->positions())) {
        Inversion& v = inversion[c.layer];
        v.columns = c.columns;
        v.max = std::max(v.max, c.inverted);
        v.end = c.inverted;
        if (c.inverted > 0 && v.first_step < 0) v.first_step = step;
      }
    };
    // the colliders' forces on the tissue: the largest over the steps
    std::vector<double> max_force(def.colliders.size(), 0.0);
    std::vector<long> max_force_step(def.colliders.size(), -1);
    auto track_forces = [&](long step) {
      if (!scene->obstacles()) return;
      const auto f = scene->collider_forces();
      for (std::size_t k = 0; k < f.size(); ++k) {
        const double mag = std::sqrt(f[k][0] * f[k][0] + f[k][1] * f[k][1] + f[k][2] * f[k][2]);
        if (mag > max_force[k]) max_force[k] = mag, max_force_step[k] = step;
      }
    };
    {
      Phase p(report, "simulate");
      r = runtime::run(*scene, n_steps, [&](long done) {
        check_inversion(done);
        track_forces(done);
        progress.update(done);
      });
    }
    const auto& c = scene->counters();
    const runtime::Model& m = scene->model();  // after the cuts
    auto& met = report.metrics();
    const auto& st = scene->read_stats();
    met["nodes"] = m.n_nodes;
    met["anchors"] = m.n_anchors;
    met["springs"] = m.n_springs;
    met["volume_tets"] = m.n_tets;
    met["flat_guards_skipped"] = m.flat_guards_skipped;
    met["layers_loaded"] = m.layers.size();
    met["vessels_loaded"] = m.vessels.size();
    met["datasets_read"] = st.datasets_read;
    met["bytes_read"] = st.bytes_read;
    met["steps"] = r.steps;
    met["simulated_s"] = r.simulated_s;
    met["wall_s"] = r.wall_s;
    met["step_wall_s"] = r.step_wall_s;
    met["output_wall_s"] = r.output_wall_s;
    met["steps_per_second"] = r.step_wall_s > 0 ? static_cast<double>(r.steps) / r.step_wall_s : 0.0;
    met["simulated_seconds_per_wall_second"] = r.step_wall_s > 0 ? r.simulated_s / r.step_wall_s : 0.0;
    met["substeps"] = c.substeps;
    met["substeps_per_step"] = r.steps > 0 ? static_cast<double>(c.substeps) / static_cast<double>(r.steps) : 0.0;
    met["substeps_per_second"] = r.step_wall_s > 0 ? static_cast<double>(c.substeps) / r.step_wall_s : 0.0;
    met["symplectic_step_limit_s"] = scene->step_limit();
    // node-substeps in contact with the static colliders (null without a collider on the tissue)
    met["obstacle_contacts"] = scene->obstacles() ? nlohmann::json(c.obstacle_contacts) : nlohmann::json(nullptr);
    met["face_contacts"] = scene->obstacles() ? nlohmann::json(c.face_contacts) : nlohmann::json(nullptr);
    // each collider's force on the tissue (N): at the end, and the largest
    // over the steps with its time (null for a collider off the tissue)
    met["colliders"] = nlohmann::json::array();
    {
      const auto f = scene->collider_forces();
      const auto blood = scene->collider_blood_forces();
      for (std::size_t k = 0; k < def.colliders.size(); ++k) {
        const auto& cd = def.colliders[k];
        nlohmann::json e = {{"name", cd.name}, {"tissue", cd.tissue}, {"blood", cd.blood}};
        // a moving collider's force from the blood (its moving wall's reaction), at the end
        if (const auto& fb = blood[k]) e["blood_force_n"] = {(*fb)[0], (*fb)[1], (*fb)[2]};
        else e["blood_force_n"] = nullptr;
        if (cd.tissue && scene->obstacles()) {
          e["tissue_force_n"] = {f[k][0], f[k][1], f[k][2]};
          e["max_tissue_force_n"] = max_force[k];
          e["max_tissue_force_t_s"] = max_force_step[k] < 0 ? nlohmann::json(nullptr) : nlohmann::json(max_force_step[k] * def.dt);
        } else {
          e["tissue_force_n"] = nullptr;
          e["max_tissue_force_n"] = nullptr;
          e["max_tissue_force_t_s"] = nullptr;
        }
        met["colliders"].push_back(e);
      }
    }
    met["inverted_columns"] = nlohmann::json::object();
    for (const auto& [layer, v] : inversion) {
      met["inverted_columns"][layer] = {{"columns", v.columns}, {"max", v.max}, {"end", v.end},
                                        {"first_t_s", v.first_step < 0 ? nlohmann::json(nullptr)
                                                                       : nlohmann::json(v.first_step * def.dt)}};
      if (v.max > 0)  // even with --quiet: the result is not a tissue
        std::cerr << "orthosim run: warning: " << scene_file << ": layer '" << layer << "' turned inside out in "
                  << v.max << " of its " << v.columns << " grid columns (" << v.end << " at the end, the first at "
                  << v.first_step * def.dt << " s): its top passed its bottom (docs/runtime.md, Inverted layers: "
                     "build's volume term (--poisson-ratio, --lattice-volume-term) and inversion guard (--inversion-guard) "
                     "resist it)\n";
    }
    met["stability"] = {{"events", c.events},       {"nonfinite", c.nonfinite},
                        {"blowups", c.blowups},     {"recovered_steps", c.recovered},
                        {"failed_steps", c.failed}, {"substeps_redone", c.substeps_redone}};
    if (def.solver.integrator == runtime::Integrator::implicit_euler)
      met["cg"] = {{"solves", c.cg_solves},
                   {"iterations", c.cg_iterations},
                   {"mean_iterations", c.cg_solves ? static_cast<double>(c.cg_iterations) / static_cast<double>(c.cg_solves) : 0.0},
                   {"max_iterations", c.cg_max_iterations},
                   {"unconverged", c.cg_unconverged},
                   {"redos", c.cg_redos},
                   {"factorizations", c.factorizations},
                   {"face_resolves", c.face_resolves}};
    if (const runtime::FluidState* fs = scene->fluid_state()) {
      const auto f = scene->fluid_summary();
      const runtime::Fluid& fl = *scene->fluid();
      met["fluid"] = {{"particles", f.particles},
                      {"particles_emitted", f.emitted},
                      {"particles_drained", f.drained},
                      {"particles_left_domain", f.left_domain},
                      {"particles_nonfinite", f.nonfinite},
                      {"emitted_volume_m3", f.emitted_volume},
                      {"drained_volume_m3", f.drained_volume},
                      {"bleeding_vessels", f.emitters},
                      {"bleeding_flow_m3_s", f.flow_rate},
                      {"emitter_paused_steps", f.paused_steps},
                      {"emitter_outside_steps", f.emitter_outside_steps},
                      {"max_compression", f.max_compression},
                      {"substeps", fs->counters.substeps},
                      {"substeps_set_by", substep_limits(fs->counters)},
                      {"collisions", fs->counters.collisions},
                      {"contacts_reused", fs->counters.contacts_reused},
                      {"neighbour_lists_kept", fs->counters.list_reuses},
                      {"pressure_solver", runtime::to_string(fl.params.pressure_solver)},
                      {"pressure_solves", fs->counters.pressure_solves},
                      {"pressure_iterations", fs->counters.pressure_iterations},
                      {"pressure_retries", fs->counters.pressure_retries},
                      {"pressure_unconverged", fs->counters.pressure_unconverged},
                      {"pressure_stalled", fs->counters.pressure_stalled},
                      {"truncated_steps", fs->counters.truncated_steps},
                      {"surface_grid_builds", surface_grid_builds(*fs)},
                      {"spacing_m", fl.params.spacing},
                      {"sound_speed_m_s", fl.c0},
                      {"physx_stiffness", fl.physx_stiffness},
                      {"wall_s", f.wall_s}};
      for (int k = 0; k < static_cast<int>(fs->counters.phase_s.size()); ++k)
        met["fluid"]["phases_s"][runtime::fluid_phase_name(k)] = fs->counters.phase_s[static_cast<std::size_t>(k)];
      met["particles_emitted"] = f.emitted;
      met["particles_drained"] = f.drained;
      if (!common.quiet)
        std::cerr << "run: blood: " << f.emitters << " wound(s) in the vessels bleeding, " << f.emitted << " particles emitted, "
                  << f.drained << " drained, " << f.left_domain << " left the domain, " << f.particles
                  << " in the scene; fluid " << f.wall_s << " s of the steps\n";
      // what sets the fluid's substeps: the largest share (the steps' last substeps aside)
      const auto& lim = fs->counters.substep_limit;
      std::int64_t set = 0;
      std::size_t top = 1;
      for (std::size_t k = 1; k < lim.size(); ++k) {
        set += lim[k];
        if (lim[k] > lim[top]) top = k;
      }
      if (!common.quiet && r.steps > 0 && set > 0)
        std::cerr << "run: fluid: " << static_cast<double>(fs->counters.substeps) / static_cast<double>(r.steps)
                  << " substeps per step, limited by " << runtime::substep_limit_name(static_cast<int>(top)) << " ("
                  << std::lround(100.0 * static_cast<double>(lim[top]) / static_cast<double>(set))
                  << " % of the limited ones; metrics.fluid.substeps_set_by)\n";
    }
    met["cuts"] = nlohmann::json::array();
    // without surface quads loaded a cut removes none, and the count is null
    for (const auto& c : scene->cuts())
      met["cuts"].push_back({{"springs_cut", c.springs_cut}, {"tets_cut", c.tets_cut},
                             {"quads_removed", c.quads_loaded ? nlohmann::json(c.quads_removed) : nlohmann::json()},
                             {"detached_nodes", c.detached.size()}, {"vessel_hits", c.vessel_hits.size()},
                             {"vessel_edges_open_already", c.vessel_edges_open_already},
                             {"columns_opened", c.columns_opened},
                             {"columns_severed", c.columns_severed}});
    met["frames"] = r.frames;
    met["kinetic_energy_j"] = scene->state().kinetic_energy;
    met["elastic_energy_j"] = scene->state().spring_energy;
    if (scene->output()) {
      report.output(scene->output()->pvd_path());
      met["output_bytes"] = scene->output()->bytes_written();
    }
    if (!common.quiet)
      std::cerr << "run: " << r.steps << " steps in " << r.step_wall_s << " s ("
                << met["steps_per_second"].get<double>() << " steps/s, " << c.substeps << " substeps, "
                << c.events << " stability events, " << c.failed << " failed"
                << (c.cg_redos > 0 ? ", " + std::to_string(c.cg_redos) +
                                         " implicit steps redone with more substeps: PCG stopped at cg_max_iterations"
                                   : std::string())
                << ")"
                << (scene->output() ? ", series " + scene->output()->pvd_path() : std::string()) << "\n";
    if (scene->fluid_state()) {
      const auto f = scene->fluid_summary();
      if (f.emitters > 0 && f.emitted == 0 && !(f.flow_rate > 0))  // bleed_pressure 0 ("takes inf s")
        std::cerr << "orthosim run: warning: " << scene_file << ": " << f.emitters
                  << " wound(s) in the vessels, but bleed_pressure is 0: nothing flows\n";
      // (where the steps were truncated, the blood's clock lagged: the truncation's
      // warning below says why, and this advice would point the wrong way)
      else if (f.emitters > 0 && f.emitted == 0 && scene->fluid_state()->counters.truncated_steps == 0)  // a warning even with --quiet: the bleeding the scene asks for shows nothing
        std::cerr << "orthosim run: warning: " << scene_file << ": " << f.emitters << " cut vessel(s) bleed "
                  << f.flow_rate << " m^3/s in all, but no particle was emitted: one particle ("
                  << f.particle_volume << " m^3) takes " << f.particle_volume / f.flow_rate
                  << " s of that flow; a finer fluid spacing or a higher bleed_pressure shows it\n";
    }
    if (scene->fluid_state() && scene->fluid_summary().emitter_outside_steps > 0)  // even with --quiet: the blood is thrown away
      std::cerr << "orthosim run: warning: " << scene_file << ": a wound's emitter, moved with the tissue, lay outside the "
                << "blood's domain in " << scene->fluid_summary().emitter_outside_steps << " step(s), so its blood was emitted "
                << "outside it (" << scene->fluid_summary().left_domain << " of " << scene->fluid_summary().emitted
                << " particles left the domain); a larger fluid.margin keeps it inside (the domain is the tissue's rest "
                   "box grown by it)\n";
    if (const runtime::FluidState* fs = scene->fluid_state(); fs && scene->fluid_summary().emitted > 0) {
      // a drain that removed nothing while blood was emitted never met it (a warning even with
      // --quiet: the drained count the scene is for reads 0); drains are in the order of their tools
      std::size_t k = 0;
      for (const auto& t : def.tools) {
        if (t.type != runtime::ToolType::drain) continue;
        // (not a drain already warned of: outside the domain, or starting after the last step)
        if (k < fs->drains.size() && fs->drains[k].drained == 0 && !outside_domain.count(t.name) &&
            !never_acts(t))
          std::cerr << "orthosim run: warning: " << scene_file << ": the drain" << quoted(t.name)
                    << " removed no blood of the " << scene->fluid_summary().emitted
                    << " particles emitted: the blood never reached it (inside closed tissue, away from the wound, "
                       "or active only while none was there)\n";
        ++k;
      }
    }
    if (scene->fluid_state() && !scene->model().vessels.empty() && !scene->cuts().empty()) {
      std::size_t hits = 0;
      for (const auto& cr : scene->cuts()) hits += cr.vessel_hits.size();
      if (hits == 0) {  // even with --quiet: the bleeding the scene is built for cannot start
        // the blade's direction too: aimed off the limb's axis, a cut runs along the skin
        // beside the vessels, and the advice blamed the vessels (sweep of 2026-11-27)
        std::ostringstream blades;
        for (const auto& cr : scene->cuts())
          blades << (blades.tellp() > 0 ? "; " : "") << (cr.tool.empty() ? std::string("cut") : "'" + cr.tool + "'")
                 << " along (" << std::setprecision(3)
                 << cr.direction.x << ", " << cr.direction.y << ", " << cr.direction.z << ")";
        std::cerr << "orthosim run: warning: " << scene_file << ": " << scene->cuts().size()
                  << " cut(s) crossed none of the " << scene->model().vessels.size()
                  << " loaded vessel tree(s), so nothing bled (blade " << blades.str()
                  << ": is the vessel where the cut is, within its depth and ahead of its blade (a cut's \"direction\")? "
                     "the model's vessels may be shorter than the tissue's: see its vessels report)\n";
      }
    }
    for (const auto& cr : scene->cuts())
      if (cr.springs_cut == 0 && cr.quads_removed == 0)  // even with --quiet: the incision the scene asks for is not there
        std::cerr << "orthosim run: warning: " << scene_file << ": the cut"
                  << quoted(cr.tool) << " at t = " << cr.time
                  << " s cut nothing: its polyline, swept along the blade to its depth, crosses no spring of the model\n";
    if (def.solver.integrator == runtime::Integrator::implicit_euler && c.cg_unconverged > 0)  // even with --quiet
      std::cerr << "orthosim run: warning: " << scene_file << ": " << c.cg_unconverged << " of " << c.cg_solves
                << " implicit solves stopped unconverged at cg_max_iterations (" << def.solver.cg_max_iterations
                << ") in the kept steps, after " << c.cg_redos
                << " redos with more substeps: the tissue is stiff for this dt (a smaller dt, a higher "
                   "cg_max_iterations, or cg_tolerance)\n";
    if (const runtime::FluidState* fs = scene->fluid_state(); fs && fs->counters.truncated_steps > 0)  // even with --quiet
      std::cerr << "orthosim run: warning: " << scene_file << ": the blood reached its limit of "
                << scene->fluid()->params.max_substeps << " substeps in " << fs->counters.truncated_steps
                << " step(s); the rest of those steps' fluid time was skipped, so the blood lags the tissue (its "
                   "sound speed or spacing asks for substeps far below dt; metrics.fluid.truncated_steps)\n";
    if (const runtime::FluidState* fs = scene->fluid_state(); fs && fs->counters.pressure_unconverged > 0)
      std::cerr << "orthosim run: warning: " << scene_file << ": " << fs->counters.pressure_unconverged << " of "
                << fs->counters.pressure_solves
                << " PCISPH pressure solves were taken unconverged (after halving the substep, at most down to the "
                   "EOS's own at the same sound speed, or where halving cannot help): the blood is compressed "
                   "beyond pcisph_tolerance there (more pcisph_max_iterations or a larger pcisph_tolerance; "
                   "metrics.fluid.pressure_unconverged)\n";
    report.write(common.report);
    if (c.failed > 0) {
      // the run went to the end (outputs and report written; a failed step ends at rest, never
      // NaN), but the solver gave up on steps: the scene is beyond its stability
      std::cerr << "orthosim run: error: " << scene_file << ": " << c.failed << " of " << r.steps
                << " steps failed (the solver gave up on them after up to " << def.solver.max_retries
                << " retries, halving the substep down to 1/" << def.solver.max_substeps
                << " of the step at most; metrics.stability in the report)";
      // the symplectic stability limit beyond max_substeps: the cause, not a blow-up
      // (a 1e12 N/m grip needed 2.5e6 substeps a step; the message spoke of retries only)
      const double limit = scene->step_limit();
      if (def.solver.integrator == runtime::Integrator::symplectic_euler && def.solver.substeps == 0 && limit > 0 &&
          def.dt / limit > def.solver.max_substeps)
        std::cerr << ": the symplectic stability limit is " << limit << " s, " << def.dt / limit
                  << " substeps a step, more than max_substeps (" << def.solver.max_substeps
                  << "): a stiffer (or more heavily damped) spring or grip than the step allows (the implicit integrator, a smaller dt or "
                     "a softer grip)";
      std::cerr << "\n";
      exit_code() = 3;
    }
  });
}

}  // namespace orthosim::cli
