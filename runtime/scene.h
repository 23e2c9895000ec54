// Scenes: what to simulate (a JSON scene file or a SceneDef built in code)
// and the Scene that runs it, in the spirit of PhysX's PxScene:
//
//   auto def = parse_scene_file("pull_skin.json");  // or default_scene_def()
//   Scene scene(def);               // loads only what def names; throws Error before any step
//   for (...) {
//     scene.add_force(node, {0, 0, 1});  // between steps: forces, tool targets, pins
//     scene.simulate(1.0 / 60);
//     scene.fetch_results();
//     read scene.positions();
//   }
//
// simulate(dt) advances by dt with the scene's integrator and substeps
// (runtime/solver.h) on the scene's own TBB arena of `threads` threads;
// fetch_results() completes the step and publishes its results. The step is
// computed synchronously inside simulate() today; the split keeps callers
// written for an asynchronous step (issue 9's fluid may overlap the two).
// Calls that change the scene are refused between simulate() and
// fetch_results().
//
// Scene file format: docs/runtime.md. Units SI; relative paths are relative
// to the scene file's directory.
#pragma once

#include "libmodel/format/h5file.h"
#include "runtime/cut.h"
#include "runtime/model.h"
#include "runtime/solver.h"
#include "runtime/state.h"
#include "runtime/vtk.h"

#include <array>
#include <functional>
#include <limits>
#include <memory>
#include <span>
#include <string>
#include <vector>

namespace orthosim::runtime {

enum class ToolType { pull, pressure, hook, cut };
const char* to_string(ToolType t);

// A tool. Its nodes are chosen once, when the scene is created, at rest
// positions: the nodes of `nodes` (a node set; empty = every free node of the
// loaded layers) within `radius` of `center` (no radius = the whole set).
struct ToolDef {
  std::string name;
  ToolType type = ToolType::pull;
  std::string nodes;                     // node set the tool may take; "" = all free loaded nodes
  std::array<Real, 3> center{0, 0, 0};   // m, the tool point at rest
  bool has_center = false;               // false: the set's centroid, and every node of the set
  // When set, center is this point of the candidates' rest bounding box, as
  // fractions of its size per axis ([0.5, 0, 0.5]: middle of the low-y face),
  // so a scene can name a place on a model it has no coordinates for.
  bool center_relative = false;
  std::array<Real, 3> center_fraction{0.5, 0.5, 0.5};
  Real radius = 0;                       // m, > 0 when has_center
  // pull: displacement of the tool point from center over time (s, m);
  // held before the first and after the last time. Empty: stays at center.
  Path path;
  Real stiffness = 0;                    // pull: N/m per node; 0 = kinematic grip
  Real pressure = 0;                     // pressure: Pa; total force pressure * pi radius^2, shared equally
  std::array<Real, 3> direction{0, 0, 0};  // pressure: direction of the force (normalised)
  // cut: the incision polyline (n x 3) m, or, with polyline_relative, as
  // fractions of the candidates' rest bounding box; with snap, each point
  // moves to the nearest candidate node at its rest position (the polyline
  // then lies on the tissue surface). The blade goes `depth` m along
  // `direction` (zero: towards the model's axis, runtime/cut.h) at `start`.
  std::vector<Real> polyline;
  bool polyline_relative = false;
  bool snap = true;
  Real depth = 0;
  Real start = 0;                        // s: taken at the first step starting at or after start
  Real end = std::numeric_limits<Real>::infinity();  // s: released at the first step starting at or after end
};

struct OutputDef {
  bool enabled = false;
  std::string dir;            // created after validation
  std::string name = "tissue";
  int every = 1;              // write every K steps (and the last)
  VtkOptions vtk;
};

struct SceneDef {
  std::string file;                   // the scene file ("" for scenes built in code)
  std::string model;                  // model file
  std::vector<std::string> layers;    // empty = every layer
  std::vector<std::string> vessels;   // vessel trees to load (static until issue 9)
  std::vector<std::string> fixed;     // node sets fixed from the start
  std::vector<std::string> sets;      // further node sets to load (for the API: Model::set)
  bool couple_unloaded = true;        // see LoadRequest
  SolverOptions solver;
  Real dt = 1.0 / 60;                 // s per step
  Real duration = 1.0;                // s
  int threads = 0;                    // 0 = all cores
  std::vector<ToolDef> tools;
  OutputDef output;
};

SceneDef default_scene_def();

// Parses a scene file (JSON). Relative paths are resolved against the file's
// directory. Throws Error(path, what) on unreadable JSON, unknown keys, wrong
// types and invalid numbers.
SceneDef parse_scene_file(const std::string& path);
// Parses JSON text; `file` names it in errors and anchors relative paths.
SceneDef parse_scene(const std::string& json_text, const std::string& file);

// Checks numbers and names that need no model. Throws Error(def.file, ...).
void validate(const SceneDef& def);

// What run() did.
struct RunSummary {
  long steps = 0;
  double wall_s = 0;          // whole loop
  double step_wall_s = 0;     // inside simulate/fetch_results
  double output_wall_s = 0;   // writing frames
  Real simulated_s = 0;
  int frames = 0;
};

class Scene;
// Runs `steps` steps of def().dt, writing a frame before the first step,
// every output.every steps and after the last (when output is enabled).
// `progress(done)` is called after each step when given.
RunSummary run(Scene& scene, long steps, const std::function<void(long)>& progress = {});

class Scene {
 public:
  // Opens def.model, loads what def names and validates everything against
  // it (layers, node sets, vessels, tools' nodes, output directory) before
  // the first step. Throws Error(file, what).
  explicit Scene(const SceneDef& def);
  // A scene over an in-memory model (tests, benchmarks); def.model is ignored.
  Scene(Model model, const SceneDef& def);
  ~Scene();
  Scene(const Scene&) = delete;
  Scene& operator=(const Scene&) = delete;

  // ---- stepping
  void simulate(Real dt);          // dt > 0 and finite, else Error
  StepInfo fetch_results();        // completes the step; returns what it did
  bool in_step() const { return in_step_; }

  // ---- results (valid after fetch_results)
  const Model& model() const { return *model_; }
  const State& state() const { return state_; }
  std::span<const Real> positions() const { return state_.x; }  // (n_nodes x 3) m
  Real time() const { return state_.time; }
  const Counters& counters() const { return state_.counters; }
  const SceneDef& def() const { return def_; }
  const h5::ReadStats& read_stats() const { return stats_; }  // what loading read from the model file
  Real step_limit();               // s, symplectic stability limit now

  // ---- between steps
  void add_force(std::int32_t node, const std::array<Real, 3>& f);  // N, through the next step only
  int tool(const std::string& name) const;                            // index, -1 if absent
  // The tool point moves in a straight line to p over the next step, then stays.
  void move_tool(int tool, const std::array<Real, 3>& p);
  void fix(std::span<const std::int32_t> nodes);
  void release(std::span<const std::int32_t> nodes);
  const std::vector<std::int32_t>& tool_nodes(int tool) const;
  // Cuts the tissue now (between steps), as a cut tool would; returns what it did.
  CutReport cut(const CutDef& def);
  // Every cut made so far, in order (the cut tools' and cut()'s).
  const std::vector<CutReport>& cuts() const { return cuts_; }

  // ---- output
  // Writes a frame if output is enabled (the CLI calls it every K steps).
  void write_frame();
  const VtkSeries* output() const { return vtk_.get(); }

 private:
  void init(const std::string& model_file);
  void update_tools(Real t);
  CutReport apply_cut(const CutDef& def);
  void check_mutable(const char* what) const;

  SceneDef def_;
  std::shared_ptr<const Model> model_;
  State state_;
  h5::ReadStats stats_;
  struct ToolRun {
    ToolDef def;
    std::vector<std::int32_t> nodes;
    bool active = false, done = false;
    int attachment = -1;
  };
  std::vector<ToolRun> tools_;
  std::vector<CutReport> cuts_;
  std::vector<Real> user_force_;  // (n_nodes x 3) N, for the next step
  bool user_force_set_ = false;
  bool in_step_ = false;
  StepInfo last_;
  struct Arena;
  std::unique_ptr<Arena> arena_;
  std::unique_ptr<VtkSeries> vtk_;
};

}  // namespace orthosim::runtime
