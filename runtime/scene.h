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
#include "runtime/obstacles.h"
#include "runtime/solver.h"
#include "runtime/sph.h"
#include "runtime/state.h"
#include "runtime/vtk.h"

#include <array>
#include <functional>
#include <optional>
#include <limits>
#include <memory>
#include <span>
#include <string>
#include <vector>

namespace orthosim::runtime {

enum class ToolType { pull, pressure, hook, cut, drain };
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
  // With a center: when no candidate node lies within radius, take the
  // nearest one instead of failing (a grasper closing on the surface), so a
  // scene with center_in_box also fits coarser models (a 15 x 5 grid).
  bool nearest = false;
  // pull: displacement of the tool point from center over time (s, m);
  // held before the first and after the last time. Empty: stays at center.
  Path path;
  Real stiffness = 0;                    // pull: N/m per node; 0 = kinematic grip
  Real pressure = 0;                     // pressure: Pa; total force pressure * pi radius^2, shared equally
  std::array<Real, 3> direction{0, 0, 0};  // pressure: direction of the force (normalised)
  // cut: the incision polyline (n x 3) m, or, with polyline_relative, as
  // fractions of the candidates' rest bounding box; with snap, each point
  // moves to the nearest candidate node at its rest position (the polyline
  // then lies on the tissue surface), and the cut, at `start`, runs through
  // those nodes where they are then (without snap the points stay where they
  // are in space, wherever the tissue has moved). The blade goes `depth` m along
  // `direction` (zero: towards the model's axis, runtime/cut.h) at `start`.
  std::vector<Real> polyline;
  bool polyline_relative = false;
  bool snap = true;
  Real depth = 0;
  Real node_snap = 0.25;  // cut: CutDef::node_snap, [0, 0.5)
  // drain (needs the scene's fluid): removes the blood particles within
  // `radius` of the tool point (center, or center_in_box over every loaded
  // node; `path` moves it as for pull) and counts the drained volume.
  Real start = 0;                        // s: taken at the first step starting at or after start
  Real end = std::numeric_limits<Real>::infinity();  // s: released at the first step starting at or after end
};

// Blood (issue 9; docs/runtime.md "Bleeding"): weakly compressible SPH
// (runtime/sph.h) in a box around the loaded tissue, colliding with the
// loaded layers' surface quads (two-sided walls that move with the nodes),
// which it pushes back (two-way coupling, one step lagged). A cut that
// crosses a loaded vessel becomes an emitter at the crossing, jetting out of
// the wound (against the blade direction) with the Poiseuille flow of the
// vessel's radius (bleeding_flow_rate: Poiseuille, capped by the orifice) and
// the exit profile of the limit that binds (bleeding_profile).
// A collider (issue 9's "static collision meshes"): an operating table, a
// tray, a retractor blade, a bone taken as rigid; or, with a path, an
// instrument moved through the scene. Nothing pushes back on it. The blood collides with it as with the
// tissue (the wall integrals, restitution and friction); the tissue's free
// nodes cannot pass it (runtime/obstacles.h: node contact with the same
// restitution and friction). A scene's top-level "colliders" act on both by
// default ("tissue": false or "blood": false leaves one out); the older
// "fluid": {"colliders": ...} act on the blood alone.
struct ColliderDef {
  enum class Kind { plane, mesh };
  std::string name;
  Kind kind = Kind::plane;
  // plane: the half-space normal . (x - point) >= 0 holds the blood; with
  // point_relative, point is fractions of the loaded nodes' rest bounding box
  // (as a drain's center_in_box), so the scene fits other models
  std::array<Real, 3> point{0, 0, 0};
  bool point_relative = false;
  std::array<Real, 3> normal{0, 1, 0};
  // mesh: a binary or ASCII STL file (resolved against the scene file), its
  // coordinates times `scale` metres in the model's frame (1: metres, as
  // orthosim surface writes them; 1e-3: millimetres). One-sided meshes keep
  // the blood on the side of the outward (counter-clockwise) normal,
  // two-sided ones each particle on the side it came from.
  std::string stl;
  Real scale = 1;
  bool two_sided = false;
  // with place_relative, the STL's origin goes to `place`, fractions of the
  // loaded nodes' rest bounding box (an instrument modelled about its tip,
  // placed on any model)
  std::array<Real, 3> place{0, 0, 0};
  bool place_relative = false;
  // mesh, on the tissue: its edges meet the tissue's surface faces through
  // points at most this far apart along them (m; obstacles.h,
  // resolve_face_contacts); -1: half the median edge of the loaded quads at
  // rest; 0: none, only the tissue's nodes meet it
  Real edge_spacing = -1;
  WallParams wall{0.0, 0.2, false};
  bool tissue = true;  // the tissue's free nodes collide with it
  bool blood = true;   // the blood collides with it (when the scene has blood)
  // a moving collider (an instrument, a retractor blade): its displacement
  // (m) from the geometry above at time t, a list of [t, dx, dy, dz], linear
  // in between, held before the first and after the last waypoint; empty: it
  // does not move. A moving plane acts on the tissue alone.
  Path path;
  // with a path of rotations ([t, dx, dy, dz, rx, ry, rz], rx..rz a rotation
  // vector in radians), the centre it turns about (m; has_pivot false: a
  // plane's point, a mesh's origin, placed by place_in_box)
  std::array<Real, 3> pivot{0, 0, 0};
  bool has_pivot = false;
};

struct FluidDef {
  bool enabled = false;
  FluidParams params;                 // blood by default; gravity is the scene's
  WallParams tissue_wall{0.0, 0.2, false};  // on the tissue surface
  WallParams box_wall{0.0, 0.2, false};     // on the faces of the domain box
  bool couple = true;                 // the blood's wall forces act on the tissue nodes
  Real margin = 0.02;                 // m, the domain: rest bounding box of the loaded nodes grown by this
  bool open_top = true;               // the box face against gravity is open (particles leaving are counted)
  std::int64_t max_particles = 20000; // a cap: emitters stop at this many, within a step (paused steps counted)
  Real bleed_pressure = 1330;         // Pa, pressure drop driving a cut vessel (10 mmHg: venous)
  Real bleed_length = 0.05;           // m, length over which it drops (Poiseuille)
  Real bleed_duration = std::numeric_limits<Real>::infinity();  // s a cut vessel bleeds
  bool surface = true;                // write the blood surface (Eq. 4-6, marching tetrahedra) per frame
  bool particles = false;             // write the particles per frame
  Real surface_cell = 0.5;            // blood surface grid cell / particle spacing
  int surface_volume_passes = 0;      // blood surface: FluidSurfaceOptions::volume_passes
};

// The flow out of a cut vessel of radius r (m) driven by `pressure` (Pa):
// the smaller of the viscous (Poiseuille, over `length` m) and the inertial
// (Bernoulli orifice) limits,
//   Q = min(pi r^4 dp / (8 mu L), pi r^2 sqrt(2 dp / rho))   (m^3/s).
// Poiseuille alone ignores inertia and overestimates the flow of wide
// vessels (r = 2 mm, 10 mmHg, L = 5 cm: a mean speed of 4.4 m/s, against
// 1.6 m/s for the orifice).
Real bleeding_flow_rate(Real radius, Real pressure, Real viscosity, Real length, Real density);
// The same for the fluid's rheology: Newtonian as above with p.viscosity;
// Carreau with its pipe flow (carreau_pipe_flow_rate), capped by the orifice.
Real bleeding_flow_rate(Real radius, Real pressure, const FluidParams& p, Real length);
// The exit profile that goes with it: the law that sets the flow sets the
// profile. Where the orifice (inertial) limit binds, the Bernoulli jet leaves
// the whole orifice at sqrt(2 dp / rho): a plug. Where the viscous limit
// binds, the pipe's parabolic profile (Poiseuille; for Carreau blood an
// approximation of its blunter one). A parabolic profile at the orifice's rate
// would put the centre at twice the Bernoulli speed: four times the kinetic
// energy the pressure can supply.
EmitterProfile bleeding_profile(Real radius, Real pressure, const FluidParams& p, Real length);

// The series a scene writes into `dir`: <name>_NNNNNN.vtu frames and
// <name>.pvd (tissue), with fluid <name>_blood_K.vtp / <name>_blood.pvd and
// <name>_particles_K.vtp / <name>_particles.pvd, and the vessels once
// (<name>_vessels.vtp, <name>_centrelines.vtp). The frames and .pvd of an
// earlier run of the same series in `dir` are removed when the scene is
// created (after validation), so that no stale frame outlives a shorter run.
// The longest name an output series may have (its longest file, name +
// "_particles_000000.vtp", stays well within 255 bytes).
inline constexpr std::size_t kMaxOutputName = 200;

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
  std::vector<ColliderDef> colliders; // static colliders: the top-level list, then fluid.colliders (blood only)
  FluidDef fluid;
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
  double fluid_wall_s = 0;    // of step_wall_s, in the fluid step
};

// The rest bounding box (lo, hi) of all the loaded nodes of m, as the blood's
// domain and point_in_box read it.
std::pair<Vec3, Vec3> rest_box(const Model& m);

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
  // the model as the cuts left it: a cut replaces it (copy on write), so a
  // reference taken before a step may dangle after it; take it anew
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
  int collider(const std::string& name) const;  // index into def().colliders, -1 if absent
  // A moving collider (one with a path; [[0, 0, 0, 0]] holds it where it is
  // given) moves in a straight line from its displacement now to
  // `displacement` (m) over the next step, then stays: an instrument driven
  // from a haptic device step by step. Throws Error for a collider without a
  // path, an index out of range or a non-finite displacement.
  void move_collider(int collider, const std::array<Real, 3>& displacement);
  void fix(std::span<const std::int32_t> nodes);
  void release(std::span<const std::int32_t> nodes);
  // the nodes a tool holds or pushes; of a snapped cut, the node of each polyline point, in order
  const std::vector<std::int32_t>& tool_nodes(int tool) const;
  // m: how far the snap moved the farthest point of a cut tool's polyline onto
  // its nodes (0 for other tools, or without snap)
  Real tool_snap_distance(int tool) const;
  // m: a tool's centre at rest, center_in_box resolved (0, 0, 0 without one)
  std::array<Real, 3> tool_center(int tool) const;
  // Cuts the tissue now (between steps), as a cut tool would; returns what it did.
  CutReport cut(const CutDef& def);
  // Every cut made so far, in order (the cut tools' and cut()'s).
  const std::vector<CutReport>& cuts() const { return cuts_; }

  // ---- blood (null / empty without a fluid)
  const Fluid* fluid() const;
  const FluidState* fluid_state() const;
  const FluidBoundaries* fluid_boundaries() const;
  // ---- the tissue's static obstacles (null without a collider that acts on the tissue)
  // Their planes and meshes are those of def().colliders with tissue set, in order.
  const Obstacles* obstacles() const { return state_.obstacles.get(); }
  // N: the force each of def().colliders exerts on the tissue in the last
  // substep (State::contact_force summed over the nodes in contact with it,
  // plus State::face_force, its edges' on the tissue's faces); zero for a
  // collider that does not act on the tissue
  std::vector<std::array<Real, 3>> collider_forces() const;
  // N: the force the blood exerted on each moving collider that acts on it
  // over the last step (its moving wall's reaction, FluidSurface::force
  // summed); nullopt for the others (the blood's static walls do not record
  // their reaction) and without blood
  std::vector<std::optional<std::array<Real, 3>>> collider_blood_forces() const;
  // What the fluid did over the run: particles emitted, drained, lost, paused emitter steps.
  struct FluidSummary {
    std::int64_t particles = 0, emitted = 0, drained = 0, left_domain = 0, nonfinite = 0, paused_steps = 0;
    // steps in which an emitter, moved with its wound, lay outside the blood's
    // domain (its blood leaves it at once; the domain is the loaded tissue's rest
    // box grown by the margin, and the tissue was carried farther)
    std::int64_t emitter_outside_steps = 0;
    Real emitted_volume = 0, drained_volume = 0;  // m^3
    int emitters = 0;                              // cut vessels bleeding (ever)
    Real flow_rate = 0;                            // m^3/s, their flows (bleeding_flow_rate) summed
    Real particle_volume = 0;                      // m^3, the rest volume of one particle (spacing^3)
    Real max_compression = 0;                      // max rho/rho0 - 1 over steps
    std::int64_t surface_triangles = 0;            // of the last blood surface written
    double wall_s = 0;                             // in fluid steps
  };
  FluidSummary fluid_summary() const;

  // ---- output
  // Writes a frame if output is enabled (the CLI calls it every K steps).
  void write_frame();
  const VtkSeries* output() const { return vtk_.get(); }

 private:
  void init(const std::string& model_file);
  void update_tools(Real t);
  CutReport apply_cut(const CutDef& def);
  void check_mutable(const char* what) const;
  void init_fluid();
  void fluid_step_now(Real dt, std::span<const Real> x_start);
  void update_fluid_surface();
  void write_fluid_frame();
  void write_vessels();  // the loaded vessels' tubes and centrelines, once
  void init_obstacles();   // the tissue's static obstacles (the colliders with tissue)
  void write_colliders();  // the static colliders (planes clipped to the blood's domain or the tissue's box), once
  void write_moving_colliders();  // the moving colliders where they are now, a frame of their series
  std::array<Vec3, 2> collider_box() const;  // the box planes are drawn in

  SceneDef def_;
  std::shared_ptr<const Model> model_;
  State state_;
  h5::ReadStats stats_;
  struct ToolRun {
    ToolDef def;
    std::vector<std::int32_t> nodes;
    bool active = false, done = false;
    int attachment = -1;
    Real snap_m = 0;  // cut: the farthest snap of a polyline point (m)
  };
  std::vector<ToolRun> tools_;
  std::vector<CutReport> cuts_;
  std::vector<Carried> vessel_carry_;  // the vessels' centrelines, carried by the tissue (made at the first cut)
  std::vector<Real> user_force_;  // (n_nodes x 3) N, for the next step
  bool user_force_set_ = false;
  bool in_step_ = false;
  StepInfo last_;
  struct Arena;
  std::unique_ptr<Arena> arena_;
  std::unique_ptr<VtkSeries> vtk_;
  struct FluidRun;
  std::unique_ptr<FluidRun> fluid_;
  // the colliders with a path, their geometry as given (m), for the blood's
  // moving walls and the output series <name>_moving_colliders
  struct MovingCollider {
    std::size_t def = 0;  // index into def_.colliders
    Vec3 point, normal;   // a plane
    Vec3 pivot;           // the centre of its rotations
    std::vector<Real> vertices;
    std::vector<std::int32_t> triangles;  // a mesh
  };
  std::vector<MovingCollider> moving_;
  std::vector<std::pair<Real, std::string>> moving_frames_;
};

}  // namespace orthosim::runtime
