#include "runtime/scene.h"

#include "libmodel/format/atomic.h"
#include "libmodel/format/json.h"
#include "libmodel/format/stl.h"
#include "runtime/loader.h"
#include "runtime/sph_surface.h"

#include <nlohmann/json.hpp>
#include <tbb/info.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <cstdio>
#include <chrono>
#include <cmath>
#include <numbers>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <set>
#include <sstream>

namespace fs = std::filesystem;
using nlohmann::json;

namespace orthosim::runtime {

const char* to_string(ToolType t) {
  switch (t) {
    case ToolType::pull: return "pull";
    case ToolType::pressure: return "pressure";
    case ToolType::hook: return "hook";
    case ToolType::cut: return "cut";
    case ToolType::drain: return "drain";
  }
  return "?";
}

SceneDef default_scene_def() { return SceneDef{}; }

// ---- parsing ----------------------------------------------------------------

namespace {

std::string fmt(Real x) {
  std::ostringstream s;
  s << x;
  return s.str();
}

// A message of the SPH library about the scene's fluid, for Error(scene file,
// ...): its validators already say what they are about ("fluid: ...",
// "fluid boundaries: ..."), so "fluid: " is added only to the others.
std::string fluid_message(const std::string& m) { return m.rfind("fluid", 0) == 0 ? m : "fluid: " + m; }

// Reads typed values out of one JSON object, rejecting unknown keys.
class Obj {
 public:
  Obj(const json& j, std::string where, const std::string& file) : j_(j), where_(std::move(where)), file_(file) {
    if (!j.is_object()) fail("must be an object");
  }
  [[noreturn]] void fail(const std::string& what) const { throw Error(file_, where_ + what); }
  bool has(const char* key) {
    seen_.insert(key);
    // null is no value: "fixed": null ran with nothing fixed and the limb fell
    if (j_.contains(key) && j_.at(key).is_null())
      fail(std::string(key) + " is null: give a value, or leave the key out for its default");
    return j_.contains(key);
  }
  const json& at(const char* key) { return j_.at(key); }
  Real number(const char* key, Real fallback, Real lo, Real hi, bool open_lo = false) {
    if (!has(key)) return fallback;
    const json& v = j_.at(key);
    if (!v.is_number()) fail(std::string(key) + " must be a number");
    const Real x = v.get<Real>();
    if (!std::isfinite(x) || x < lo || x > hi || (open_lo && x == lo))
      fail(std::string(key) + " must be a finite number in " + (open_lo ? "(" : "[") + fmt(lo) + ", " + fmt(hi) +
           "] (got " + v.dump() + ")");
    return x;
  }
  long integer(const char* key, long fallback, long lo, long hi) {
    if (!has(key)) return fallback;
    const json& v = j_.at(key);
    const auto range = [&] { return " must be an integer in [" + std::to_string(lo) + ", " + std::to_string(hi) + "] (got " + v.dump() + ")"; };
    // a whole number written as a float (2.0, or beyond 64 bits, which the parser
    // reads as a float: 1e+22 was "not an integer")
    if (v.is_number_float() && std::isfinite(v.get<double>()) && std::floor(v.get<double>()) == v.get<double>()) {
      const double d = v.get<double>();
      if (d < static_cast<double>(lo) || d > static_cast<double>(hi)) fail(std::string(key) + range());
      return static_cast<long>(d);
    }
    if (!v.is_number_integer()) fail(std::string(key) + " must be an integer (got " + v.dump() + ")");
    if (v.is_number_unsigned() && v.get<std::uint64_t>() > static_cast<std::uint64_t>(hi)) fail(std::string(key) + range());
    const long x = v.get<long>();
    if (x < lo || x > hi) fail(std::string(key) + range());
    return x;
  }
  bool boolean(const char* key, bool fallback) {
    if (!has(key)) return fallback;
    if (!j_.at(key).is_boolean()) fail(std::string(key) + " must be true or false");
    return j_.at(key).get<bool>();
  }
  std::string string(const char* key, const std::string& fallback, bool required = false) {
    if (!has(key)) {
      if (required) fail("missing " + std::string(key));
      return fallback;
    }
    if (!j_.at(key).is_string()) fail(std::string(key) + " must be a string");
    std::string s = j_.at(key).get<std::string>();
    if (s.empty()) fail(std::string(key) + " must not be empty");
    return s;
  }
  std::vector<std::string> strings(const char* key) {
    std::vector<std::string> out;
    if (!has(key)) return out;
    const json& v = j_.at(key);
    if (v.is_string()) return {v.get<std::string>()};
    if (!v.is_array()) fail(std::string(key) + " must be a list of names");
    for (const auto& e : v) {
      if (!e.is_string() || e.get<std::string>().empty()) fail(std::string(key) + " must be a list of names");
      out.push_back(e.get<std::string>());
    }
    return out;
  }
  std::array<Real, 3> vec3(const char* key, std::array<Real, 3> fallback) {
    if (!has(key)) return fallback;
    const json& v = j_.at(key);
    if (!v.is_array() || v.size() != 3) fail(std::string(key) + " must be [x, y, z]");
    std::array<Real, 3> out{};
    for (int k = 0; k < 3; ++k) {
      // beyond 1e9 (m, m/s^2, or a direction's components) nothing is physical, and
      // squares overflow past 1e154: gravity -1e200 froze the run, direction 1e200 normalised to 0
      if (!v[k].is_number() || !std::isfinite(v[k].get<Real>()) || std::abs(v[k].get<Real>()) > 1e9)
        fail(std::string(key) + " must be three finite numbers within +-1e9 (got " + v.dump() + ")");
      out[k] = v[k].get<Real>();
    }
    return out;
  }
  void finish() const {
    for (auto it = j_.begin(); it != j_.end(); ++it)
      if (!seen_.count(it.key())) fail("unknown key '" + it.key() + "'");
  }

 private:
  const json& j_;
  std::string where_;
  const std::string& file_;
  std::set<std::string> seen_;
};

// The rest bounding box (lo, hi) of the nodes `ids` of m.
std::pair<Vec3, Vec3> rest_box(const Model& m, const std::vector<std::int32_t>& ids) {
  Vec3 lo{HUGE_VAL, HUGE_VAL, HUGE_VAL}, hi{-HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
  for (auto i : ids) {
    const Vec3 p = load3(m.rest_x.data(), i);
    lo = {std::min(lo.x, p.x), std::min(lo.y, p.y), std::min(lo.z, p.z)};
    hi = {std::max(hi.x, p.x), std::max(hi.y, p.y), std::max(hi.z, p.z)};
  }
  return {lo, hi};
}

}  // namespace

std::pair<Vec3, Vec3> rest_box(const Model& m) {
  std::vector<std::int32_t> all(static_cast<std::size_t>(m.n_nodes));
  for (std::int32_t i = 0; i < m.n_nodes; ++i) all[static_cast<std::size_t>(i)] = i;
  return rest_box(m, all);
}

namespace {

std::string resolve(const std::string& base_dir, const std::string& p) {
  if (p.empty() || fs::path(p).is_absolute() || base_dir.empty()) return p;
  return (fs::path(base_dir) / p).lexically_normal().string();
}

// A direction scaled to unit length (0 stays 0): by its largest component
// first, so tiny components (1e-200) do not underflow to a zero length.
std::array<Real, 3> unit_direction(std::array<Real, 3> d) {
  const Real m = std::max({std::abs(d[0]), std::abs(d[1]), std::abs(d[2])});
  if (!(m > 0)) return {0, 0, 0};
  for (auto& x : d) x /= m;
  const Real n = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  for (auto& x : d) x /= n;
  return d;
}

// A "path": a list of [t, dx, dy, dz] (s, m), times >= 0 and increasing; with
// `rotations`, also [t, dx, dy, dz, rx, ry, rz] (a rotation vector, rad), every
// waypoint the one or the other.
Path parse_path(Obj& o, bool rotations = false) {
  Path path;
  const json& p = o.at("path");
  const char* form = rotations ? "path must be a list of [t, dx, dy, dz] or of [t, dx, dy, dz, rx, ry, rz]"
                               : "path must be a list of [t, dx, dy, dz]";
  if (!p.is_array() || p.empty()) o.fail(form);
  const std::size_t n = p[0].is_array() ? p[0].size() : 0;
  if (n != 4 && !(rotations && n == 7)) o.fail(form);
  for (const auto& e : p) {
    if (!e.is_array() || e.size() != n) o.fail(rotations ? "path waypoints must all be [t, dx, dy, dz] or all [t, dx, dy, dz, rx, ry, rz]" : form);
    for (const auto& x : e)
      // within +-1e9 (s, m) like every other time and vector: a path of 1e155 m
      // overflowed the implicit solve's tolerance and a spring grip did nothing, exit 0
      if (!x.is_number() || !std::isfinite(x.get<Real>()) || std::abs(x.get<Real>()) > 1e9)
        o.fail(rotations ? "path values must be finite numbers within +-1e9 (s, m, rad)"
                         : "path values must be finite numbers within +-1e9 (s, m)");
    const Real tt = e[0].get<Real>();
    if (tt < 0 || (!path.t.empty() && !(tt > path.t.back()))) o.fail("path times must be >= 0 and increasing");
    path.t.push_back(tt);
    for (int k = 1; k < 4; ++k) path.p.push_back(e[k].get<Real>());
    for (std::size_t k = 4; k < n; ++k) path.r.push_back(e[k].get<Real>());
  }
  return path;
}

// A collider of the top-level list (targets: it may say "tissue" and "blood")
// or of fluid.colliders (the blood's alone).
ColliderDef parse_collider(const json& j, std::size_t index, const std::string& file, const std::string& base,
                           const WallParams& wall, bool targets) {
  const std::string where = std::string(targets ? "" : "fluid: ") + "colliders[" + std::to_string(index) + "]: ";
  Obj o(j, where, file);
  ColliderDef c;
  c.name = o.string("name", std::string(targets ? "" : "fluid ") + "collider " + std::to_string(index));
  const std::string type = o.string("type", "", true);
  if (type == "plane") c.kind = ColliderDef::Kind::plane;
  else if (type == "mesh") c.kind = ColliderDef::Kind::mesh;
  else o.fail("type must be plane or mesh (got '" + type + "')");
  auto only = [&](const char* key, const char* kind) {
    if (o.has(key)) o.fail(std::string(key) + " is a " + kind + " collider's key (this one is a " + type + ")");
  };
  if (c.kind == ColliderDef::Kind::plane) {
    for (const char* k : {"stl", "units", "two_sided", "place_in_box", "edge_spacing"}) only(k, "mesh");
    if (o.has("point") == o.has("point_in_box")) o.fail("a plane needs point or point_in_box (one of them)");
    c.point_relative = o.has("point_in_box");
    c.point = o.vec3(c.point_relative ? "point_in_box" : "point", {});
    if (c.point_relative)
      for (Real f : c.point)
        if (f < 0 || f > 1) o.fail("point_in_box fractions must be in [0, 1]");
    if (!o.has("normal")) o.fail("a plane needs a normal");
    c.normal = unit_direction(o.vec3("normal", {}));
    if (c.normal == std::array<Real, 3>{0, 0, 0}) o.fail("normal must not be zero");
  } else {
    for (const char* k : {"point", "point_in_box", "normal"}) only(k, "plane");
    c.stl = resolve(base, o.string("stl", "", true));
    const std::string units = o.string("units", "m");
    if (units == "m") c.scale = 1;
    else if (units == "mm") c.scale = 1e-3;
    else o.fail("units must be m or mm (got '" + units + "')");
    c.two_sided = o.boolean("two_sided", false);
    if (o.has("place_in_box")) {
      c.place_relative = true;
      c.place = o.vec3("place_in_box", {});
      for (Real f : c.place)
        if (f < 0 || f > 1) o.fail("place_in_box fractions must be in [0, 1]");
    }
    if (o.has("edge_spacing")) c.edge_spacing = o.number("edge_spacing", 0, 0, kMaxLength);
  }
  c.wall = wall;  // the fluid's restitution and friction, unless the collider has its own
  c.wall.restitution = o.number("restitution", c.wall.restitution, 0, 1);
  c.wall.friction = o.number("friction", c.wall.friction, 0, 1e3);
  c.wall.slip = o.boolean("slip", c.wall.slip);
  if (targets) {
    c.tissue = o.boolean("tissue", true);
    c.blood = o.boolean("blood", true);
    if (!c.tissue && !c.blood) o.fail("acts on nothing (\"tissue\": false and \"blood\": false)");
  } else {
    c.tissue = false;
  }
  if (o.has("edge_spacing") && !c.tissue) o.fail("edge_spacing is how the tissue meets the mesh, and it does not act on the tissue");
  if (o.has("pivot")) {
    c.pivot = o.vec3("pivot", {});
    c.has_pivot = true;
  }
  if (o.has("path")) {
    c.path = parse_path(o, true);
    if (c.has_pivot && c.path.r.empty()) o.fail("pivot is the centre of a path's rotations, and this path has none");
    // the blood's half-spaces are fixed walls (FluidBoundaries); a moving
    // mesh is a moving wall to it (FluidSurface)
    if (c.kind == ColliderDef::Kind::plane && c.blood)
      o.fail("a moving plane acts on the tissue only: give it \"blood\": false, or make it a mesh");
  }
  if (c.has_pivot && c.path.t.empty()) o.fail("pivot is the centre of a path's rotations, and there is no path");
  o.finish();
  return c;
}

ToolDef parse_tool(const json& j, std::size_t index, const std::string& file) {
  Obj o(j, "tools[" + std::to_string(index) + "]: ", file);
  ToolDef t;
  t.name = o.string("name", "tool" + std::to_string(index));
  const std::string type = o.string("type", "", true);
  if (type == "pull") t.type = ToolType::pull;
  else if (type == "pressure") t.type = ToolType::pressure;
  else if (type == "hook") t.type = ToolType::hook;
  else if (type == "cut") t.type = ToolType::cut;
  else if (type == "drain") t.type = ToolType::drain;
  else o.fail("type must be pull, pressure, hook, cut or drain (got '" + type + "')");
  t.nodes = o.string("nodes", "");
  if (o.has("center") && o.has("center_in_box")) o.fail("give center or center_in_box, not both");
  if (o.has("center") || o.has("center_in_box")) {
    if (o.has("center")) {
      t.center = o.vec3("center", {});
    } else {
      t.center_relative = true;
      t.center_fraction = o.vec3("center_in_box", {});
      for (Real f : t.center_fraction)
        if (f < 0 || f > 1) o.fail("center_in_box fractions must be in [0, 1]");
    }
    t.has_center = true;
    t.radius = o.number("radius", 0, 0, 1e3, true);
    if (!o.has("radius")) o.fail("radius is required with center");
    t.nearest = o.boolean("nearest", false);
  } else {
    if (o.has("radius")) o.fail("radius needs a center");
    if (o.has("nearest")) o.fail("nearest needs a center");
    if (t.nodes.empty() && t.type != ToolType::cut && t.type != ToolType::drain) o.fail("needs a center and radius, or a node set in 'nodes'");
  }
  if (t.type == ToolType::cut) {
    if (t.has_center) o.fail("a cut takes a polyline, not a center");
    if (o.has("polyline") == o.has("polyline_in_box")) o.fail("a cut needs polyline or polyline_in_box (one of them)");
    const char* key = o.has("polyline") ? "polyline" : "polyline_in_box";
    t.polyline_relative = !o.has("polyline");
    const json& p = o.at(key);
    if (!p.is_array() || p.size() < 2) o.fail(std::string(key) + " must be a list of at least 2 [x, y, z]");
    for (const auto& e : p) {
      if (!e.is_array() || e.size() != 3) o.fail(std::string(key) + " must be a list of [x, y, z]");
      for (const auto& x : e) {
        // within +-1e9 m like every other vector (1e300 overflowed the blade's
        // direction and was refused as "a polyline on the model's axis")
        if (!x.is_number() || !std::isfinite(x.get<Real>()) || std::abs(x.get<Real>()) > 1e9)
          o.fail(std::string(key) + " values must be finite numbers within +-1e9");
        if (t.polyline_relative && (x.get<Real>() < 0 || x.get<Real>() > 1)) o.fail("polyline_in_box fractions must be in [0, 1]");
        t.polyline.push_back(x.get<Real>());
      }
    }
    t.depth = o.number("depth", 0, 0, 10, true);
    if (!o.has("depth")) o.fail("depth (m) is required");
    t.direction = unit_direction(o.vec3("direction", {0, 0, 0}));
    t.snap = o.boolean("snap", true);
    t.node_snap = o.number("node_snap", 0.25, 0, 0.5);
    if (!(t.node_snap < 0.5)) o.fail("node_snap must be in [0, 0.5) (a fraction of a node's shortest spring)");
  }
  t.start = o.number("start", 0, 0, 1e9);
  // a cut acts once, at its start: an "end" was ignored
  if (t.type == ToolType::cut && o.has("end")) o.fail("a cut acts once, at its start: it takes no end");
  // a drain removes blood within its radius, whatever the nodes: "nodes" was ignored
  if (t.type == ToolType::drain && !t.nodes.empty()) o.fail("a drain takes no nodes (it removes the blood within its radius)");
  t.end = o.number("end", std::numeric_limits<Real>::infinity(), 0, 1e9);
  if (o.has("end") && !(t.end > t.start)) o.fail("end must be after start");
  if (t.type == ToolType::drain && !t.has_center) o.fail("a drain needs a center (or center_in_box) and a radius");
  if (t.type == ToolType::pull || t.type == ToolType::drain) {
    if (t.type == ToolType::pull) t.stiffness = o.number("stiffness", 0, 0, 1e12);
    if (o.has("path")) {
      t.path = parse_path(o);
      // A pull grips its nodes where they are at its start and moves them by the
      // path's change since then: one waypoint moves nothing (it was run so,
      // the grip held at rest, without a word).
      if (t.type == ToolType::pull && t.path.t.size() == 1)
        o.fail("a pull's path needs at least two waypoints [t, dx, dy, dz]: the grip moves its nodes by the path's "
               "change since the tool's start, so one waypoint moves nothing");
    }
  }
  if (t.type == ToolType::pressure) {
    t.pressure = o.number("pressure", 0, -1e9, 1e9);
    if (!o.has("pressure")) o.fail("pressure (Pa) is required");
    if (!t.has_center) o.fail("a pressure tool needs a center and radius");
    t.direction = unit_direction(o.vec3("direction", {0, 0, 0}));
    if (t.direction == std::array<Real, 3>{0, 0, 0}) o.fail("direction must be a non-zero [x, y, z]");
  }
  o.finish();
  return t;
}

}  // namespace

SceneDef parse_scene(const std::string& text, const std::string& file) {
  json j;
  std::string twice;
  try {
    j = parse_json_noting_repeats(text, twice);
  } catch (const json::exception& e) {
    std::string what = e.what();
    for (auto& c : what)
      if (c == '\n') c = ' ';
    throw Error(file, "invalid JSON: " + what);
  }
  if (!twice.empty()) throw Error(file, "invalid JSON: the key '" + twice + "' appears twice in one object");
  const std::string base = file.empty() ? "" : fs::path(file).parent_path().string();
  SceneDef d = default_scene_def();
  d.file = file;
  Obj o(j, "", file);
  o.string("description", "");
  d.model = resolve(base, o.string("model", "", true));
  d.layers = o.strings("layers");
  if (o.has("layers") && d.layers.empty())  // [] loaded every layer
    o.fail("layers is empty: name the layers to load, or leave the key out (or \"all\") for every layer");
  if (d.layers.size() == 1 && d.layers[0] == "all") d.layers.clear();
  d.vessels = o.strings("vessels");
  // a name twice: each tree would bleed twice; a layer was refused by the
  // loader, naming the model file for the scene's mistake
  for (const auto* names : {&d.layers, &d.vessels})
    for (std::size_t i = 0; i < names->size(); ++i)
      for (std::size_t k = 0; k < i; ++k)
        if ((*names)[i] == (*names)[k])
          o.fail(std::string(names == &d.layers ? "layers" : "vessels") + ": '" + (*names)[i] + "' is named twice");
  std::vector<ColliderDef> fluid_colliders;
  if (o.has("fluid")) {
    Obj f(o.at("fluid"), "fluid: ", file);
    FluidDef& fd = d.fluid;
    fd.enabled = f.boolean("enabled", true);
    FluidParams& p = fd.params;
    p.spacing = f.number("spacing", p.spacing, 0, 1, true);
    p.rest_density = f.number("density", p.rest_density, 0, 1e5, true);
    p.viscosity = f.number("viscosity", p.viscosity, 0, 1e3);
    p.support_ratio = f.number("support_ratio", p.support_ratio, 1.5, 4);
    p.max_speed = f.number("max_speed", p.max_speed, 0, 1e3, true);
    p.sound_speed = f.number("sound_speed", 0, 0, 1e5);
    p.physx_stiffness = f.number("physx_stiffness", 0, 0, 1e6);
    p.artificial_viscosity = f.number("artificial_viscosity", p.artificial_viscosity, 0, 1);
    const std::string eos = f.string("eos", "tait");
    if (eos == "tait") p.eos = Eos::tait;
    else if (eos == "linear") p.eos = Eos::linear;
    else f.fail("eos must be tait or linear (got '" + eos + "')");
    // the PhysX mode's equation of state is linear: a Tait "eos" given with it was ignored
    if (f.has("eos") && p.physx_stiffness > 0 && p.eos != Eos::linear)
      f.fail("eos '" + eos + "' with physx_stiffness: the PhysX mode's equation of state is linear (leave eos out)");
    const std::string solver = f.string("pressure_solver", "eos");
    if (solver == "eos") p.pressure_solver = PressureSolver::eos;
    else if (solver == "pcisph") p.pressure_solver = PressureSolver::pcisph;
    else f.fail("pressure_solver must be eos or pcisph (got '" + solver + "')");
    for (const char* k : {"pcisph_tolerance", "pcisph_target_iterations", "pcisph_max_iterations", "pcisph_stall_repeats"})
      if (f.has(k) && p.pressure_solver != PressureSolver::pcisph) f.fail(std::string(k) + " given with pressure_solver '" + solver + "'");
    p.pcisph_tolerance = f.number("pcisph_tolerance", p.pcisph_tolerance, 0, 0.5, true);
    p.pcisph_max_iterations = static_cast<int>(f.integer("pcisph_max_iterations", p.pcisph_max_iterations, 1, 1000));
    p.pcisph_stall_repeats = static_cast<int>(f.integer("pcisph_stall_repeats", p.pcisph_stall_repeats, 0, 1000));
    p.pcisph_target_iterations =
        static_cast<int>(f.integer("pcisph_target_iterations", p.pcisph_target_iterations, 1, p.pcisph_max_iterations));
    const std::string rheology = f.string("rheology", "newtonian");
    if (rheology == "newtonian") p.rheology = Rheology::newtonian;
    else if (rheology == "carreau") p.rheology = Rheology::carreau;
    else f.fail("rheology must be newtonian or carreau (got '" + rheology + "')");
    if (f.has("carreau")) {
      if (p.rheology != Rheology::carreau) f.fail("carreau parameters given with rheology '" + rheology + "'");
      Obj c(f.at("carreau"), "fluid: carreau: ", file);
      p.carreau.mu0 = c.number("mu0", p.carreau.mu0, 0, 1e6, true);
      p.carreau.mu_inf = c.number("mu_inf", p.carreau.mu_inf, 0, 1e6);
      p.carreau.lambda = c.number("lambda", p.carreau.lambda, 0, 1e6);
      p.carreau.n = c.number("n", p.carreau.n, 0, 1, true);
      c.finish();
    }
    fd.tissue_wall.restitution = f.number("restitution", fd.tissue_wall.restitution, 0, 1);
    fd.tissue_wall.friction = f.number("friction", fd.tissue_wall.friction, 0, 1e3);
    fd.box_wall = fd.tissue_wall;
    fd.couple = f.boolean("couple", fd.couple);
    fd.margin = f.number("margin", fd.margin, 0, 10);
    fd.open_top = f.boolean("open_top", fd.open_top);
    fd.max_particles = f.integer("max_particles", fd.max_particles, 1, 100000000);
    fd.bleed_pressure = f.number("bleed_pressure", fd.bleed_pressure, 0, 1e7);
    fd.bleed_length = f.number("bleed_length", fd.bleed_length, 0, 10, true);
    fd.bleed_duration = f.number("bleed_duration", fd.bleed_duration, 0, 1e9, true);
    fd.surface = f.boolean("surface", fd.surface);
    fd.particles = f.boolean("particles", fd.particles);
    fd.surface_cell = f.number("surface_cell", fd.surface_cell, 0.1, 2);  // (sph_surface.h: no detail finer)
    fd.surface_volume_passes = static_cast<int>(f.integer("surface_volume_passes", fd.surface_volume_passes, 0, 64));
    if (f.has("colliders")) {
      const json& c = f.at("colliders");
      if (!c.is_array()) f.fail("colliders must be a list");
      for (std::size_t i = 0; i < c.size(); ++i) fluid_colliders.push_back(parse_collider(c[i], i, file, base, fd.tissue_wall, false));
    }
    f.finish();
  }
  // static colliders: the top-level list (tissue and blood; the fluid's
  // restitution and friction unless their own), then the fluid's (blood only)
  if (o.has("colliders")) {
    const json& c = o.at("colliders");
    if (!c.is_array()) o.fail("colliders must be a list");
    for (std::size_t i = 0; i < c.size(); ++i) d.colliders.push_back(parse_collider(c[i], i, file, base, d.fluid.tissue_wall, true));
  }
  d.colliders.insert(d.colliders.end(), fluid_colliders.begin(), fluid_colliders.end());
  for (std::size_t i = 0; i < d.colliders.size(); ++i)
    for (std::size_t k = 0; k < i; ++k)
      if (d.colliders[k].name == d.colliders[i].name) o.fail("colliders: '" + d.colliders[i].name + "' is named twice");
  d.fixed = o.strings("fixed");
  d.sets = o.strings("sets");
  for (const auto* names : {&d.fixed, &d.sets})  // (as layers and vessels above; these were accepted)
    for (std::size_t i = 0; i < names->size(); ++i)
      for (std::size_t k = 0; k < i; ++k)
        if ((*names)[i] == (*names)[k])
          o.fail(std::string(names == &d.fixed ? "fixed" : "sets") + ": '" + (*names)[i] + "' is named twice");
  d.couple_unloaded = o.boolean("couple_unloaded_layers", true);
  d.solver.gravity = o.vec3("gravity", d.solver.gravity);
  if (o.has("damping")) {
    Obj dmp(o.at("damping"), "damping: ", file);
    d.solver.mass_damping = dmp.number("mass", 0, 0, 1e6);
    dmp.finish();
  }
  const std::string integ = o.string("integrator", "symplectic");
  if (integ == "symplectic") d.solver.integrator = Integrator::symplectic_euler;
  else if (integ == "implicit") d.solver.integrator = Integrator::implicit_euler;
  else o.fail("integrator must be symplectic or implicit (got '" + integ + "')");
  d.dt = o.number("dt", d.dt, 0, 10, true);
  if (o.has("substeps")) {
    const json& s = o.at("substeps");
    if (s.is_string() && s.get<std::string>() == "auto") d.solver.substeps = 0;
    else d.solver.substeps = static_cast<int>(o.integer("substeps", 0, 1, 1 << 20));
  }
  d.duration = o.number("duration", d.duration, 0, 1e7, true);
  d.threads = static_cast<int>(o.integer("threads", 0, 0, 1024));
  if (o.has("stability")) {
    Obj s(o.at("stability"), "stability: ", file);
    d.solver.safety = s.number("safety", d.solver.safety, 0, 1, true);
    d.solver.max_retries = static_cast<int>(s.integer("max_retries", d.solver.max_retries, 0, 30));
    d.solver.energy_growth = s.number("energy_growth", d.solver.energy_growth, 1, 1e300, true);
    d.solver.max_substeps = static_cast<int>(s.integer("max_substeps", d.solver.max_substeps, 1, 1 << 24));
    s.finish();
  }
  if (o.has("implicit")) {
    // settings the symplectic integrator would ignore: an error, as every ignored key
    if (d.solver.integrator != Integrator::implicit_euler)
      o.fail("implicit: its settings apply to \"integrator\": \"implicit\" only (the scene's is symplectic)");
    Obj s(o.at("implicit"), "implicit: ", file);
    d.solver.cg_tolerance = s.number("cg_tolerance", d.solver.cg_tolerance, 0, 1, true);
    if (!(d.solver.cg_tolerance < 1))  // the solver's range is open at 1 (it said so without the prefix)
      s.fail("cg_tolerance must be a finite number in (0, 1) (got " + fmt(d.solver.cg_tolerance) + ")");
    d.solver.cg_max_iterations = static_cast<int>(s.integer("cg_max_iterations", d.solver.cg_max_iterations, 1, 100000));
    const std::string pc = s.string("preconditioner", "auto");
    if (!parse_preconditioner(pc, d.solver.preconditioner))
      s.fail("preconditioner must be auto, cholesky, block_jacobi or jacobi (got '" + pc + "')");
    d.solver.refactor_after = static_cast<int>(s.integer("refactor_after", d.solver.refactor_after, 1, 100000));
    d.solver.warm_start = s.boolean("warm_start", true);
    d.solver.redo_unconverged = s.boolean("redo_unconverged", true);
    d.solver.friction_creep_speed = s.number("friction_creep_speed", d.solver.friction_creep_speed, 0, 10, true);
    s.finish();
  }
  if (o.has("tools")) {
    const json& t = o.at("tools");
    if (!t.is_array()) o.fail("tools must be a list");
    for (std::size_t i = 0; i < t.size(); ++i) d.tools.push_back(parse_tool(t[i], i, file));
  }
  if (o.has("output")) {
    Obj out(o.at("output"), "output: ", file);
    d.output.enabled = true;
    // no dir: `orthosim run --out` gives it (the Scene refuses an output without one)
    const std::string dir = out.string("dir", "");
    d.output.dir = dir.empty() ? std::string() : resolve(base, dir);
    d.output.name = out.string("name", d.output.name);
    if (d.output.name.find_first_of("/\\") != std::string::npos || d.output.name == "." || d.output.name == "..")
      out.fail("name must be a file name without a folder (got '" + d.output.name + "'): the series goes into dir");
    // the longest frame file is name + "_particles_000000.vtp": within a file
    // name's 255 bytes (a 250-character name failed after loading the model,
    // leaving a frame behind); no control characters (a newline split the
    // one-line messages) and no blank at either end
    if (d.output.name.empty() || d.output.name.size() > kMaxOutputName)
      out.fail("name must have 1 to " + std::to_string(kMaxOutputName) + " characters (got " +
               std::to_string(d.output.name.size()) + ")");
    for (const unsigned char c : d.output.name)
      if (c < 0x20 || c == 0x7f) out.fail("name must not contain control characters (a newline, a tab)");
    if (d.output.name.front() == ' ' || d.output.name.back() == ' ')
      out.fail("name must not begin or end with a blank (got '" + d.output.name + "')");
    d.output.every = static_cast<int>(out.integer("every", 1, 1, 1 << 30));
    const std::string f = out.string("format", "binary");
    if (f == "binary") d.output.vtk.binary = true;
    else if (f == "ascii") d.output.vtk.binary = false;
    else out.fail("format must be binary or ascii (got '" + f + "')");
    d.output.vtk.surface = out.boolean("surface", true);
    d.output.vtk.springs = out.boolean("springs", true);
    out.finish();
  }
  o.finish();
  validate(d);
  return d;
}

SceneDef parse_scene_file(const std::string& path) {
  std::error_code ec;
  if (fs::is_directory(path, ec)) throw Error(path, "is a folder, not a scene file");
  if (!fs::is_regular_file(path, ec)) throw Error(path, "scene file not found");
  std::ifstream in(path, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  if (!in) throw Error(path, "cannot read the scene file");
  return parse_scene(s.str(), path);
}

void validate(const SceneDef& d) {
  auto fail = [&](const std::string& what) { throw Error(d.file, what); };
  if (!(std::isfinite(d.dt) && d.dt > 0)) fail("dt must be a positive finite number (got " + fmt(d.dt) + ")");
  if (!(std::isfinite(d.duration) && d.duration > 0)) fail("duration must be a positive finite number (got " + fmt(d.duration) + ")");
  if (d.threads < 0) fail("threads must be >= 0");
  try {
    validate(d.solver);
  } catch (const Error& e) {
    fail(e.message());
  }
  std::set<std::string> names;
  for (const auto& t : d.tools) {
    if (!names.insert(t.name).second) fail("two tools are named '" + t.name + "'");
    if (t.has_center && !(std::isfinite(t.radius) && t.radius > 0)) fail("tool '" + t.name + "': radius must be > 0");
    if (!t.has_center && t.nodes.empty() && t.type != ToolType::cut && t.type != ToolType::drain) fail("tool '" + t.name + "' needs a center and radius, or a node set");
    if (t.type == ToolType::cut && (t.polyline.size() < 6 || t.polyline.size() % 3 || !(t.depth > 0)))
      fail("tool '" + t.name + "': a cut needs a polyline of at least 2 points and a depth > 0");
    if (!(t.end > t.start)) fail("tool '" + t.name + "': end must be after start");
    if (!(std::isfinite(t.stiffness) && t.stiffness >= 0)) fail("tool '" + t.name + "': stiffness must be >= 0");
    if (!std::isfinite(t.pressure)) fail("tool '" + t.name + "': pressure must be finite");
    if (t.path.p.size() != 3 * t.path.t.size()) fail("tool '" + t.name + "': path points do not match its times");
  }
  for (const auto& t : d.tools) {
    if (t.type == ToolType::drain && !d.fluid.enabled) fail("tool '" + t.name + "': a drain needs the scene's fluid");
    if (t.type == ToolType::drain && !t.has_center) fail("tool '" + t.name + "': a drain needs a center and a radius");
  }
  if (d.fluid.enabled) {
    FluidParams p = d.fluid.params;
    p.gravity = d.solver.gravity;
    try {
      validate(p);
    } catch (const Error& e) {
      fail(fluid_message(e.message()));
    }
  }
}

// ---- Scene ------------------------------------------------------------------

struct Scene::Arena {
  tbb::task_arena arena;
  // at most the cores: more made TBB print its own warning, also under --quiet
  explicit Arena(int threads)
      : arena(threads > 0 ? std::min(threads, tbb::info::default_concurrency()) : tbb::info::default_concurrency()) {}
};

namespace {
// An output needs a folder; a scene file's output block may leave it to `orthosim
// run --out` (it was refused while parsing, before --out could give it).
void require_output_dir(const SceneDef& d) {
  if (d.output.enabled && d.output.dir.empty())
    throw Error(d.file, "output: dir is required (in the scene's output block, or orthosim run --out)");
}
}  // namespace

Scene::Scene(const SceneDef& def) : def_(def) {
  validate(def_);
  require_output_dir(def_);
  std::error_code ec;
  if (def_.model.empty()) throw Error(def_.file, "no model file given");
  if (fs::is_directory(def_.model, ec)) throw Error(def_.file, "model file '" + def_.model + "' is a folder");
  if (!fs::is_regular_file(def_.model, ec)) throw Error(def_.file, "model file '" + def_.model + "' does not exist");
  init(def_.model);
}

Scene::Scene(Model model, const SceneDef& def) : def_(def) {
  validate(def_);
  require_output_dir(def_);
  model_ = std::make_shared<const Model>(std::move(model));
  init("");
}

namespace {
Vec3 collider_point(const ColliderDef& c, const Vec3& lo, const Vec3& hi);
Vec3 collider_pivot(const ColliderDef& c, const Vec3& lo, const Vec3& hi);
void read_collider_mesh(const ColliderDef& c, const Vec3& lo, const Vec3& hi, std::vector<Real>& vertices,
                        std::vector<std::int32_t>& triangles);
}  // namespace

void Scene::init(const std::string& model_file) {
  const std::string& file = def_.file;
  if (!model_) {
    ModelReader reader(model_file);
    LoadRequest req;
    req.layers = def_.layers;
    req.vessels = def_.vessels;
    // the blood collides with the quads; a cut without a direction aims at the axis its quad grids show
    bool aimed_by_quads = false;
    for (const auto& t : def_.tools)
      aimed_by_quads = aimed_by_quads || (t.type == ToolType::cut && t.direction == std::array<Real, 3>{0, 0, 0});
    // and a mesh collider's edges meet the tissue's faces
    const bool faced = std::any_of(def_.colliders.begin(), def_.colliders.end(), [](const ColliderDef& c) {
      return c.tissue && c.kind == ColliderDef::Kind::mesh && c.edge_spacing != 0;
    });
    req.surface = (def_.output.enabled && def_.output.vtk.surface) || def_.fluid.enabled || aimed_by_quads || faced;
    req.vessel_tubes = def_.output.enabled;  // drawn in the output, not simulated
    req.couple_unloaded = def_.couple_unloaded;
    std::set<std::string> sets(def_.fixed.begin(), def_.fixed.end());
    sets.insert(def_.sets.begin(), def_.sets.end());
    for (const auto& t : def_.tools)
      if (!t.nodes.empty()) sets.insert(t.nodes);
    req.node_sets.assign(sets.begin(), sets.end());
    // names the scene uses, checked against the file's structure: scene errors
    const ModelIndex idx = index_model(reader);
    auto list = [](const std::vector<std::string>& v) {
      std::string s;
      for (const auto& x : v) s += (s.empty() ? "" : ", ") + x;
      return s.empty() ? std::string("none") : s;
    };
    for (const auto& name : req.layers)
      if (std::find(idx.layers.begin(), idx.layers.end(), name) == idx.layers.end())
        throw Error(file, "no layer '" + name + "' in " + model_file + " (layers: " + list(idx.layers) + ")");
    for (const auto& name : req.node_sets)
      if (std::find(idx.node_sets.begin(), idx.node_sets.end(), name) == idx.node_sets.end())
        throw Error(file, "no node set '" + name + "' in " + model_file + " (sets: " + list(idx.node_sets) + ")");
    for (const auto& name : req.vessels)
      if (!reader.h5().is_group("/vessels/" + name)) throw Error(file, "no vessel tree '" + name + "' in " + model_file);
    model_ = std::make_shared<const Model>(load_model(reader, req));
    stats_ = reader.h5().stats();
  }
  const Model& m = *model_;
  if (m.n_nodes - m.n_anchors == 0) throw Error(file, "the scene loads no node");

  // fixed sets
  state_ = make_state(m);
  for (const auto& name : def_.fixed) {
    auto it = m.node_sets.find(name);
    if (it == m.node_sets.end()) throw Error(file, "no node set '" + name + "' in the model");
    if (it->second.empty()) throw Error(file, "node set '" + name + "' has no node in the loaded layers");
    fix_nodes(m, state_, it->second);
  }

  // tools: nodes at rest
  for (const auto& t : def_.tools) {
    ToolRun run;
    run.def = t;
    std::vector<std::int32_t> candidates;
    if (!t.nodes.empty()) {
      auto it = m.node_sets.find(t.nodes);
      if (it == m.node_sets.end()) throw Error(file, "tool '" + t.name + "': no node set '" + t.nodes + "' in the model");
      for (auto i : it->second)
        if (m.inv_mass[i] > 0) candidates.push_back(i);
    } else {
      for (std::int32_t i = 0; i < m.n_nodes; ++i)
        if (m.inv_mass[i] > 0) candidates.push_back(i);
    }
    if (t.type == ToolType::cut) {
      if (candidates.empty()) throw Error(file, "tool '" + t.name + "' has no candidate node");
      const auto [lo, hi] = rest_box(m, candidates);
      Real farthest_snap = 0;  // m, the longest way a point was moved by the snap
      for (std::size_t k = 0; 3 * k < t.polyline.size(); ++k) {
        Vec3 p = load3(t.polyline.data(), static_cast<std::int64_t>(k));
        if (t.polyline_relative) p = {lo.x + p.x * (hi.x - lo.x), lo.y + p.y * (hi.y - lo.y), lo.z + p.z * (hi.z - lo.z)};
        if (t.snap) {
          Real best = HUGE_VAL;
          Vec3 q = p;
          std::int32_t node = -1;
          for (auto i : candidates) {
            const Vec3 r = load3(m.rest_x.data(), i);
            if (norm(r - p) < best) best = norm(r - p), q = r, node = i;
          }
          farthest_snap = std::max(farthest_snap, best);
          p = q;
          run.nodes.push_back(node);  // the cut follows it: the polyline is where these nodes are then
        }
        store3(run.def.polyline.data(), static_cast<std::int64_t>(k), p);
      }
      // a polyline whose points all snap to one node (it lies far from the
      // tissue, or is shorter than the node spacing) has no length left
      if (t.snap && t.polyline.size() >= 6) {
        bool one = true;
        for (std::size_t k = 3; k < run.def.polyline.size(); ++k) one = one && run.def.polyline[k] == run.def.polyline[k % 3];
        if (one)
          throw Error(file, "tool '" + t.name + "': every point of the cut's polyline snaps to the same node (at rest " +
                                fmt(run.def.polyline[0]) + ", " + fmt(run.def.polyline[1]) + ", " + fmt(run.def.polyline[2]) +
                                " m; the farthest point moved " + fmt(farthest_snap) +
                                " m): the polyline lies far from the candidate nodes or is shorter than their spacing");
      }
      run.snap_m = farthest_snap;
      CutDef cd;
      for (std::size_t k = 0; 3 * k < run.def.polyline.size(); ++k)
        cd.polyline.push_back(load3(run.def.polyline.data(), static_cast<std::int64_t>(k)));
      cd.depth = t.depth;
      cd.direction = {t.direction[0], t.direction[1], t.direction[2]};
      try {
        run.def.direction = [&] {
          const Vec3 d = cut_direction(m, cd);
          return std::array<Real, 3>{d.x, d.y, d.z};
        }();
      } catch (const Error& e) {
        throw Error(file, "tool '" + t.name + "': " + e.message());
      }
      tools_.push_back(std::move(run));
      continue;
    }
    if (t.has_center && t.center_relative) {
      if (candidates.empty()) throw Error(file, "tool '" + t.name + "' has no candidate node");
      const auto [lo, hi] = rest_box(m, candidates);
      const auto& f = t.center_fraction;
      run.def.center = {lo.x + f[0] * (hi.x - lo.x), lo.y + f[1] * (hi.y - lo.y), lo.z + f[2] * (hi.z - lo.z)};
    }
    if (t.type == ToolType::drain) {
      // a point tool: it takes no node
    } else if (t.has_center) {
      if (candidates.empty()) throw Error(file, "tool '" + t.name + "' has no candidate node");
      const Vec3 c{run.def.center[0], run.def.center[1], run.def.center[2]};
      Real closest = HUGE_VAL;
      std::int32_t nearest = -1;
      for (auto i : candidates) {
        const Real d = norm(load3(m.rest_x.data(), i) - c);
        if (d <= t.radius) run.nodes.push_back(i);
        if (d < closest) closest = d, nearest = i;  // ties: the first candidate (candidates are in index order)
      }
      if (run.nodes.empty() && t.nearest && nearest >= 0) run.nodes.push_back(nearest);
      if (run.nodes.empty())
        throw Error(file, "tool '" + t.name + "' takes no node: no " + (t.nodes.empty() ? "free node" : "node of set '" + t.nodes + "'") +
                              " lies within " + fmt(t.radius) + " m of (" + fmt(c.x) + ", " + fmt(c.y) + ", " + fmt(c.z) +
                              ") (the nearest is " + fmt(closest) + " m away; \"nearest\": true takes it)");
    } else {
      run.nodes = candidates;
      if (run.nodes.empty()) throw Error(file, "tool '" + t.name + "': node set '" + t.nodes + "' has no free node in the loaded layers");
      Vec3 c{};
      for (auto i : run.nodes) c += load3(m.rest_x.data(), i);
      c = (Real(1) / static_cast<Real>(run.nodes.size())) * c;
      run.def.center = {c.x, c.y, c.z};
    }
    // absolute tool-point path
    Path abs;
    const Vec3 c{run.def.center[0], run.def.center[1], run.def.center[2]};
    if (t.path.t.empty()) {
      abs.t = {0};
      abs.p = {c.x, c.y, c.z};
    } else {
      abs.t = t.path.t;
      for (std::size_t k = 0; k < t.path.t.size(); ++k) {
        const Vec3 p = c + load3(t.path.p.data(), static_cast<std::int64_t>(k));
        abs.p.insert(abs.p.end(), {p.x, p.y, p.z});
      }
    }
    run.def.path = abs;
    tools_.push_back(std::move(run));
  }

  // the moving colliders' geometry (for the blood's moving walls and the output)
  for (std::size_t c = 0; c < def_.colliders.size(); ++c) {
    const ColliderDef& cd = def_.colliders[c];
    if (cd.path.t.empty()) continue;
    MovingCollider mc;
    mc.def = c;
    const auto [lo, hi] = rest_box(m);
    mc.pivot = collider_pivot(cd, lo, hi);
    if (cd.kind == ColliderDef::Kind::plane) {
      mc.point = collider_point(cd, lo, hi);
      mc.normal = {cd.normal[0], cd.normal[1], cd.normal[2]};
    } else {
      try {
        read_collider_mesh(cd, lo, hi, mc.vertices, mc.triangles);
        validate_triangle_mesh(mc.vertices, mc.triangles, "mesh");
      } catch (const Error& e) {
        if (!e.file().empty()) throw;
        throw Error(def_.file, "collider '" + cd.name + "': " + e.message());
      }
    }
    moving_.push_back(std::move(mc));
  }
  init_obstacles();
  if (def_.fluid.enabled) init_fluid();

  // output directory, after everything else is known to be valid
  if (def_.output.enabled) {
    check_output_dir(def_.output.dir);
    std::error_code ec;
    fs::create_directories(def_.output.dir, ec);
    if (ec) throw Error(def_.output.dir, "cannot create the output directory: " + ec.message());
    // an earlier run into the same folder under the same name: its frames
    // go, so that the folder holds only this run's (a shorter run would leave
    // the later frames of the earlier one beside the new .pvd)
    const std::string& dir = def_.output.dir;
    const std::string& name = def_.output.name;
    // Every series of the name goes, whether this run writes it or not (a run
    // without particles left an earlier run's particle series beside its own)
    remove_series_frames(dir, name + "_", ".vtu", name + ".pvd");
    remove_series_frames(dir, name + "_blood_", ".vtp", name + "_blood.pvd");
    remove_series_frames(dir, name + "_particles_", ".vtp", name + "_particles.pvd");
    remove_series_frames(dir, name + "_moving_colliders_", ".vtp", name + "_moving_colliders.pvd");
    for (const char* once : {"_vessels.vtp", "_centrelines.vtp", "_colliders.vtp"}) {
      const fs::path p = fs::path(dir) / (name + once);
      if (fs::is_regular_file(p, ec) && !fs::remove(p, ec) && ec)
        throw Error(p.string(), "cannot remove a file of an earlier run: " + ec.message());
    }
    vtk_ = std::make_unique<VtkSeries>(m, def_.output.dir, def_.output.name, def_.output.vtk);
    write_vessels();
    write_colliders();
  }
  user_force_.assign(3 * static_cast<std::size_t>(m.n_nodes), 0);
  arena_ = std::make_unique<Arena>(def_.threads);
}

// ---- blood ---------------------------------------------------------------------

namespace {
// the viscous limit (any law) capped by the inertial one of the orifice
Real capped_by_orifice(Real viscous, Real radius, Real pressure, Real density) {
  return std::min(viscous, Real(M_PI) * radius * radius * std::sqrt(2 * pressure / density));
}
}  // namespace

Real bleeding_flow_rate(Real radius, Real pressure, Real viscosity, Real length, Real density) {
  if (!(radius > 0) || !(pressure > 0)) return 0;
  if (!(viscosity > 0)) return capped_by_orifice(HUGE_VAL, radius, pressure, density);
  return capped_by_orifice(poiseuille_flow_rate(radius, pressure, viscosity, length), radius, pressure, density);
}

Real bleeding_flow_rate(Real radius, Real pressure, const FluidParams& p, Real length) {
  if (p.rheology == Rheology::newtonian) return bleeding_flow_rate(radius, pressure, p.viscosity, length, p.rest_density);
  if (!(radius > 0) || !(pressure > 0)) return 0;
  return capped_by_orifice(carreau_pipe_flow_rate(radius, pressure, length, p.carreau), radius, pressure, p.rest_density);
}

EmitterProfile bleeding_profile(Real radius, Real pressure, const FluidParams& p, Real length) {
  if (!(radius > 0) || !(pressure > 0)) return EmitterProfile::parabolic;  // no flow
  const Real viscous = p.rheology == Rheology::carreau ? carreau_pipe_flow_rate(radius, pressure, length, p.carreau)
                       : p.viscosity > 0                ? poiseuille_flow_rate(radius, pressure, p.viscosity, length)
                                                        : HUGE_VAL;
  return viscous < capped_by_orifice(HUGE_VAL, radius, pressure, p.rest_density) ? EmitterProfile::parabolic
                                                                                  : EmitterProfile::plug;
}

namespace {
// A plane collider's point (m): point_in_box resolved against the loaded
// nodes' rest box [lo, hi].
Vec3 collider_point(const ColliderDef& c, const Vec3& lo, const Vec3& hi) {
  if (!c.point_relative) return {c.point[0], c.point[1], c.point[2]};
  return {lo.x + c.point[0] * (hi.x - lo.x), lo.y + c.point[1] * (hi.y - lo.y), lo.z + c.point[2] * (hi.z - lo.z)};
}
// Where a mesh collider's origin goes: place_in_box's point of the rest box
// [lo, hi], or the origin itself.
Vec3 mesh_origin(const ColliderDef& c, const Vec3& lo, const Vec3& hi) {
  if (!c.place_relative) return {};
  return {lo.x + c.place[0] * (hi.x - lo.x), lo.y + c.place[1] * (hi.y - lo.y), lo.z + c.place[2] * (hi.z - lo.z)};
}
// The centre a collider's rotations turn it about: its pivot, or a plane's
// point, or a mesh's origin (placed by place_in_box).
Vec3 collider_pivot(const ColliderDef& c, const Vec3& lo, const Vec3& hi) {
  if (c.has_pivot) return {c.pivot[0], c.pivot[1], c.pivot[2]};
  if (c.kind == ColliderDef::Kind::plane) return collider_point(c, lo, hi);
  return mesh_origin(c, lo, hi);
}
// A point of a moving collider's geometry where its path puts it at time t.
Vec3 moved(const Path& path, const Vec3& pivot, const Vec3& x, Real t) {
  if (path.r.empty()) return x + path.at(t);
  return path_rotation(path, t)(x - pivot) + pivot + path.at(t);
}

// A mesh collider's STL in metres: vertices (n x 3) and triangles (n x 3),
// with place_in_box its origin moved to that point of the loaded nodes' rest
// box [lo, hi]. Errors name the STL file.
void read_collider_mesh(const ColliderDef& c, const Vec3& lo, const Vec3& hi, std::vector<Real>& vertices,
                        std::vector<std::int32_t>& triangles) {
  const Surface s = read_stl(c.stl);
  const Vec3 shift = mesh_origin(c, lo, hi);
  const Real d[3] = {shift.x, shift.y, shift.z};
  vertices.resize(3 * static_cast<std::size_t>(s.vertices.rows()));
  for (Eigen::Index i = 0; i < s.vertices.rows(); ++i)
    for (int k = 0; k < 3; ++k) vertices[3 * static_cast<std::size_t>(i) + k] = c.scale * s.vertices(i, k) + d[k];
  triangles.assign(s.faces.data(), s.faces.data() + s.faces.size());  // (row-major n x 3)
}
}  // namespace

void Scene::init_obstacles() {
  const Model& m = *model_;
  if (std::none_of(def_.colliders.begin(), def_.colliders.end(), [](const ColliderDef& c) { return c.tissue; })) return;
  const auto [lo, hi] = rest_box(m);
  auto obstacles = std::make_shared<Obstacles>();
  std::vector<Path> plane_paths, mesh_paths;  // the obstacles' order: planes, then meshes
  for (const ColliderDef& c : def_.colliders) {
    if (!c.tissue) continue;
    (c.kind == ColliderDef::Kind::plane ? plane_paths : mesh_paths).push_back(c.path);
    try {
      if (c.kind == ColliderDef::Kind::plane) {
        add_obstacle_plane(*obstacles, {collider_point(c, lo, hi), {c.normal[0], c.normal[1], c.normal[2]},
                                        c.wall.restitution, c.wall.friction, collider_pivot(c, lo, hi)});
      } else {
        ObstacleMesh mesh;
        read_collider_mesh(c, lo, hi, mesh.vertices, mesh.triangles);
        mesh.two_sided = c.two_sided;
        mesh.restitution = c.wall.restitution;
        mesh.friction = c.wall.friction;
        mesh.pivot = collider_pivot(c, lo, hi);
        add_obstacle_mesh(*obstacles, std::move(mesh));
        // its edges against the tissue's faces
        sample_obstacle_edges(obstacles->meshes.back(), c.edge_spacing >= 0 ? c.edge_spacing : default_edge_spacing(m.quads, m.rest_x));
      }
    } catch (const Error& e) {
      if (!e.file().empty()) throw;
      throw Error(def_.file, "collider '" + c.name + "': " + e.message());
    }
  }
  state_.obstacles = std::move(obstacles);
  if (std::any_of(def_.colliders.begin(), def_.colliders.end(), [](const ColliderDef& c) { return c.tissue && !c.path.t.empty(); })) {
    state_.obstacle_paths = std::move(plane_paths);
    state_.obstacle_paths.insert(state_.obstacle_paths.end(), mesh_paths.begin(), mesh_paths.end());
  }
}

std::vector<std::array<Real, 3>> Scene::collider_forces() const {
  std::vector<std::array<Real, 3>> out(def_.colliders.size(), std::array<Real, 3>{0, 0, 0});
  const Obstacles* ob = state_.obstacles.get();
  if (!ob || state_.contact_obstacle.empty()) return out;
  // the obstacles' order: the tissue's planes, then its meshes, each in the colliders' order
  std::vector<std::size_t> of_obstacle;
  for (int kind = 0; kind < 2; ++kind)
    for (std::size_t c = 0; c < def_.colliders.size(); ++c)
      if (def_.colliders[c].tissue && (def_.colliders[c].kind == ColliderDef::Kind::plane) == (kind == 0)) of_obstacle.push_back(c);
  for (std::size_t i = 0; i < state_.contact_obstacle.size(); ++i) {
    const std::int32_t k = state_.contact_obstacle[i];
    if (k < 0 || static_cast<std::size_t>(k) >= of_obstacle.size()) continue;
    for (int a = 0; a < 3; ++a) out[of_obstacle[static_cast<std::size_t>(k)]][static_cast<std::size_t>(a)] += state_.contact_force[3 * i + a];
  }
  // and through its edges on the faces between the nodes
  for (std::size_t k = 0; k < of_obstacle.size() && 3 * k + 2 < state_.face_force.size(); ++k)
    for (std::size_t a = 0; a < 3; ++a) out[of_obstacle[k]][a] += state_.face_force[3 * k + a];
  return out;
}

struct Scene::FluidRun {
  Fluid fluid;
  FluidBoundaries bounds;
  FluidState state = make_fluid_state();
  std::vector<int> drain_of_tool;  // per tool: index into state.drains, -1 for other tools
  std::vector<Real> force;         // (n_nodes x 3) N, the blood's wall forces of the last step
  FluidSummary summary;
  std::vector<std::pair<Real, std::string>> frames;  // blood surface series
  WoundColumns wound;  // the tissue's columns the cuts open (cut.h); not valid: the quads as they are
  Carried emitter_carry;  // the emitters' centres, carried by the tissue (one point per emitter)
  std::vector<std::pair<std::size_t, std::size_t>> moving_walls;  // (index into moving_, into state.surfaces)
};

Scene::~Scene() = default;

std::vector<std::optional<std::array<Real, 3>>> Scene::collider_blood_forces() const {
  std::vector<std::optional<std::array<Real, 3>>> out(def_.colliders.size());
  if (!fluid_) return out;
  for (const auto& [k, si] : fluid_->moving_walls) {
    const FluidSurface& w = fluid_->state.surfaces[si];
    std::array<Real, 3> f{0, 0, 0};
    for (std::size_t i = 0; i < w.force.size(); ++i) f[i % 3] += w.force[i];
    out[moving_[k].def] = f;
  }
  return out;
}

const Fluid* Scene::fluid() const { return fluid_ ? &fluid_->fluid : nullptr; }
const FluidState* Scene::fluid_state() const { return fluid_ ? &fluid_->state : nullptr; }
const FluidBoundaries* Scene::fluid_boundaries() const { return fluid_ ? &fluid_->bounds : nullptr; }

Scene::FluidSummary Scene::fluid_summary() const {
  if (!fluid_) return {};
  FluidSummary r = fluid_->summary;
  const FluidCounters& c = fluid_->state.counters;
  r.particles = fluid_->state.size();
  r.emitted = c.emitted;
  r.drained = c.drained;
  r.left_domain = c.left_domain;
  r.nonfinite = c.nonfinite;
  r.emitted_volume = c.emitted_volume;
  r.drained_volume = c.drained_volume;
  r.emitters = static_cast<int>(fluid_->state.emitters.size());
  for (const FluidEmitter& e : fluid_->state.emitters) r.flow_rate += e.flow_rate;
  r.particle_volume = fluid_->fluid.volume;
  return r;
}

void Scene::init_fluid() {
  const Model& m = *model_;
  const FluidDef& fd = def_.fluid;
  fluid_ = std::make_unique<FluidRun>();
  FluidRun& fr = *fluid_;
  FluidParams p = fd.params;
  p.gravity = def_.solver.gravity;
  try {
    fr.fluid = make_fluid(p);
  } catch (const Error& e) {
    throw Error(def_.file, fluid_message(e.message()));
  }
  // the domain: the loaded nodes' rest bounding box grown by the margin
  const auto [lo, hi] = rest_box(m);
  fr.bounds = make_box_boundaries({lo.x - fd.margin, lo.y - fd.margin, lo.z - fd.margin},
                                  {hi.x + fd.margin, hi.y + fd.margin, hi.z + fd.margin});
  fr.bounds.box_wall = fd.box_wall;
  if (fd.open_top) {
    // the face against gravity's largest component is open
    int axis = 0;
    for (int k = 1; k < 3; ++k)
      if (std::abs(p.gravity[k]) > std::abs(p.gravity[axis])) axis = k;
    if (p.gravity[axis] != 0) fr.bounds.faces[static_cast<std::size_t>(2 * axis + (p.gravity[axis] < 0 ? 1 : 0))] = Face::open;
  }
  // the scene's static walls
  for (const ColliderDef& c : def_.colliders) {
    if (!c.blood || !c.path.t.empty()) continue;  // (a moving one: a moving wall, below)
    const std::string what = "fluid: collider '" + c.name + "': ";
    try {
      if (c.kind == ColliderDef::Kind::plane) {
        FluidPlane pl;
        const Vec3 p = collider_point(c, lo, hi);
        pl.point = {p.x, p.y, p.z};
        pl.normal = c.normal;
        pl.wall = c.wall;
        add_plane(fr.bounds, pl);
      } else {
        FluidMesh mesh;
        read_collider_mesh(c, lo, hi, mesh.vertices, mesh.triangles);
        mesh.wall = c.wall;
        mesh.two_sided = c.two_sided;
        add_mesh(fr.bounds, std::move(mesh), fr.fluid);
      }
    } catch (const Error& e) {
      if (!e.file().empty()) throw;
      throw Error(def_.file, what + e.message());
    }
  }
  try {
    validate(fr.bounds, fr.fluid);
  } catch (const Error& e) {
    throw Error(def_.file, fluid_message(e.message()));
  }
  // the tissue surface: every node a vertex, the loaded layers' quads as
  // two-sided triangles (blood meets the skin outside and the wound inside),
  // closed around the tissue's columns until a cut opens them (WoundColumns)
  fr.wound = wound_columns(m);
  FluidSurface surf;
  surf.two_sided = true;
  surf.wall = fd.tissue_wall;
  surf.x = state_.x;
  fr.state.surfaces.push_back(std::move(surf));
  update_fluid_surface();
  // the moving colliders: walls moved with them (set each step, fluid_step_now)
  for (std::size_t k = 0; k < moving_.size(); ++k) {
    const ColliderDef& c = def_.colliders[moving_[k].def];
    if (!c.blood) continue;  // (a plane with blood and a path is refused by the parser)
    FluidSurface w;
    w.triangles = moving_[k].triangles;
    w.wall = c.wall;
    w.two_sided = c.two_sided;
    w.x = moving_[k].vertices;
    fr.moving_walls.emplace_back(k, fr.state.surfaces.size());
    fr.state.surfaces.push_back(std::move(w));
  }
  fr.force.assign(3 * static_cast<std::size_t>(m.n_nodes), 0);
  // drains, one per drain tool, enabled while the tool is active
  fr.drain_of_tool.assign(tools_.size(), -1);
  for (std::size_t i = 0; i < tools_.size(); ++i) {
    if (tools_[i].def.type != ToolType::drain) continue;
    FluidDrain d;
    const Vec3 c = tools_[i].def.path.at(0);
    d.center = {c.x, c.y, c.z};
    d.radius = tools_[i].def.radius;
    d.enabled = false;
    fr.drain_of_tool[i] = static_cast<int>(fr.state.drains.size());
    fr.state.drains.push_back(d);
  }
}

void Scene::update_fluid_surface() {
  const Model& m = *model_;
  FluidSurface& surf = fluid_->state.surfaces.front();
  if (fluid_->wound.valid()) {
    surf.triangles = wound_wall_triangles(fluid_->wound);
    return;
  }
  surf.triangles.clear();
  surf.triangles.reserve(6 * static_cast<std::size_t>(m.n_quads));
  for (std::int32_t q = 0; q < m.n_quads; ++q) {
    const std::int32_t* v = m.quads.data() + 4 * static_cast<std::size_t>(q);
    surf.triangles.insert(surf.triangles.end(), {v[0], v[1], v[2], v[0], v[2], v[3]});
  }
}

void Scene::fluid_step_now(Real dt, std::span<const Real> x_start) {
  FluidRun& fr = *fluid_;
  const FluidDef& fd = def_.fluid;
  const auto t0 = std::chrono::steady_clock::now();
  // the tissue surface through the step: from its start positions at the mean velocity
  FluidSurface& surf = fr.state.surfaces.front();
  surf.x.assign(x_start.begin(), x_start.end());
  surf.v.resize(surf.x.size());
  for (std::size_t i = 0; i < surf.v.size(); ++i) surf.v[i] = (state_.x[i] - x_start[i]) / dt;
  // the moving colliders through the step: from where they are at its start at their mean velocity
  for (const auto& [k, si] : fr.moving_walls) {
    const Path& path = def_.colliders[moving_[k].def].path;
    FluidSurface& w = fr.state.surfaces[si];
    const std::vector<Real>& rest = moving_[k].vertices;
    w.x.resize(rest.size());
    w.v.resize(rest.size());
    for (std::size_t i = 0; i + 2 < rest.size(); i += 3) {
      const Vec3 p = load3(rest.data(), static_cast<std::int64_t>(i / 3));
      const Vec3 a = moved(path, moving_[k].pivot, p, state_.time - dt), b = moved(path, moving_[k].pivot, p, state_.time);
      const Vec3 u = (1 / dt) * (b - a);
      w.x[i] = a.x, w.x[i + 1] = a.y, w.x[i + 2] = a.z;
      w.v[i] = u.x, w.v[i + 1] = u.y, w.v[i + 2] = u.z;
    }
  }
  // drains follow their tools
  for (std::size_t i = 0; i < tools_.size(); ++i) {
    const int di = fr.drain_of_tool[i];
    if (di < 0) continue;
    FluidDrain& d = fr.state.drains[static_cast<std::size_t>(di)];
    d.enabled = tools_[i].active;
    const Vec3 c = tools_[i].def.path.at(state_.time - dt);
    d.center = {c.x, c.y, c.z};
  }
  // emitters follow their wounds (where the tissue carries them at the step's start)
  if (fr.emitter_carry.rest.size() == 3 * fr.state.emitters.size() && !fr.state.emitters.empty()) {
    const std::vector<Real> at = carried_positions(fr.emitter_carry, *model_, x_start);
    bool outside = false;
    for (std::size_t i = 0; i < fr.state.emitters.size(); ++i) {
      fr.state.emitters[i].center = {at[3 * i], at[3 * i + 1], at[3 * i + 2]};
      const bool live = state_.time - dt >= fr.state.emitters[i].start && state_.time - dt < fr.state.emitters[i].end;
      for (std::size_t a = 0; a < 3; ++a)
        outside = outside || (live && (at[3 * i + a] < fr.bounds.lo[a] || at[3 * i + a] > fr.bounds.hi[a]));
    }
    if (outside) ++fr.summary.emitter_outside_steps;
  }
  // emitters pause while the fluid is full, and stop within the step at the cap
  fr.state.max_particles = fd.max_particles;
  const bool full = fr.state.size() >= fd.max_particles;
  bool any = false;
  for (auto& e : fr.state.emitters) {
    const bool live = state_.time - dt >= e.start && state_.time - dt < e.end;
    any = any || live;
    e.enabled = !full;
  }
  if (full && any) ++fr.summary.paused_steps;
  fr.state.time = state_.time - dt;  // the fluid's clock follows the tissue's
  const FluidStepInfo info = fluid_step(fr.fluid, fr.state, dt, fr.bounds);
  fr.summary.max_compression = std::max(fr.summary.max_compression, info.max_compression);
  if (fd.couple && surf.force.size() == fr.force.size()) fr.force = surf.force;
  fr.summary.wall_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void Scene::write_vessels() {
  if (model_->vessels.empty()) return;
  // once (they do not move): the tube surfaces (<name>_vessels.vtp) and
  // the centrelines, points with their radius (<name>_centrelines.vtp)
  const std::string base = def_.output.dir + "/" + def_.output.name;
  std::vector<double> pts, radius, tube;
  std::vector<std::int32_t> tri;
  for (const auto& v : model_->vessels) {
    pts.insert(pts.end(), v.nodes.begin(), v.nodes.end());
    radius.insert(radius.end(), v.radii.begin(), v.radii.end());
    const auto off = static_cast<std::int32_t>(tube.size() / 3);
    tube.insert(tube.end(), v.tube_vertices.begin(), v.tube_vertices.end());
    for (auto i : v.tube_triangles) tri.push_back(off + i);
  }
  write_vtp(base + "_centrelines.vtp", pts, {}, {VtpArray{"radius", 1, radius}}, def_.output.vtk.binary);
  if (!tri.empty()) write_vtp(base + "_vessels.vtp", tube, tri, {}, def_.output.vtk.binary);
}

namespace {
// A plane (point p0, unit normal n) as the polygon it cuts from the box
// [lo, hi], appended to pts / tri: the crossings of the box's 12 edges, in
// order around their centroid, as a triangle fan. Nothing where the plane
// misses the box (or touches it at an edge).
void append_plane_polygon(const std::array<Real, 3>& lo, const std::array<Real, 3>& hi, const Vec3& p0, const Vec3& n,
                          std::vector<double>& pts, std::vector<std::int32_t>& tri) {
  struct {
    std::array<Real, 3> lo, hi;
  } b{lo, hi};
  auto corner = [&](int c) { return Vec3{c & 1 ? b.hi[0] : b.lo[0], c & 2 ? b.hi[1] : b.lo[1], c & 4 ? b.hi[2] : b.lo[2]}; };
  std::vector<Vec3> poly;
  for (int c = 0; c < 8; ++c)
    for (int k = 0; k < 3; ++k) {
      if (c & (1 << k)) continue;  // each edge once, from its low corner
      const Vec3 a = corner(c), e = corner(c | (1 << k));
      const Real da = dot(n, a - p0), de = dot(n, e - p0);
      if ((da < 0) == (de < 0) && da != 0) continue;
      if (da == de) continue;  // the edge lies in the plane: its ends are other edges' crossings
      poly.push_back(a + (da / (da - de)) * (e - a));
    }
  // a plane through a corner crosses its three edges there: one point
  const Real tiny = 1e-12 * (std::abs(b.hi[0] - b.lo[0]) + std::abs(b.hi[1] - b.lo[1]) + std::abs(b.hi[2] - b.lo[2]));
  std::vector<Vec3> distinct;
  for (const Vec3& q : poly)
    if (std::none_of(distinct.begin(), distinct.end(), [&](const Vec3& d) { return norm(d - q) <= tiny; })) distinct.push_back(q);
  poly = std::move(distinct);
  if (poly.size() < 3) return;
  Vec3 c{0, 0, 0};
  for (const Vec3& q : poly) c = c + q;
  c = (1.0 / static_cast<Real>(poly.size())) * c;
  const Vec3 u0 = poly[0] - c, v0 = cross(n, u0);
  std::sort(poly.begin(), poly.end(), [&](const Vec3& a, const Vec3& q) {
    return std::atan2(dot(a - c, v0), dot(a - c, u0)) < std::atan2(dot(q - c, v0), dot(q - c, u0));
  });
  const auto off = static_cast<std::int32_t>(pts.size() / 3);
  for (const Vec3& q : poly) pts.insert(pts.end(), {q.x, q.y, q.z});
  for (std::int32_t i = 1; i + 1 < static_cast<std::int32_t>(poly.size()); ++i) tri.insert(tri.end(), {off, off + i, off + i + 1});
}
}  // namespace

std::array<Vec3, 2> Scene::collider_box() const {
  // the blood's domain, or without blood the loaded nodes' rest box grown by
  // the fluid's margin (FluidDef::margin)
  if (fluid_) {
    const auto& b = fluid_->bounds;
    return {Vec3{b.lo[0], b.lo[1], b.lo[2]}, Vec3{b.hi[0], b.hi[1], b.hi[2]}};
  }
  const auto [lo, hi] = rest_box(*model_);
  const Real g = def_.fluid.margin;
  return {Vec3{lo.x - g, lo.y - g, lo.z - g}, Vec3{hi.x + g, hi.y + g, hi.z + g}};
}

void Scene::write_colliders() {
  if (def_.colliders.empty()) return;
  const auto [blo, bhi] = collider_box();
  const std::array<Real, 3> box_lo{blo.x, blo.y, blo.z}, box_hi{bhi.x, bhi.y, bhi.z};
  // each collider from the structure that holds it (the tissue's obstacles or
  // the blood's boundaries, whose planes and meshes are the colliders', in order)
  std::vector<const std::vector<Real>*> mesh_vertices;
  std::vector<const std::vector<std::int32_t>*> mesh_triangles;
  std::vector<std::pair<Vec3, Vec3>> planes;  // point, normal
  {
    std::size_t op = 0, om = 0, fp = 0, fm = 0;
    const Obstacles* ob = state_.obstacles.get();
    for (const ColliderDef& c : def_.colliders) {
      const bool from_tissue = c.tissue && ob;
      if (!from_tissue && !(c.blood && fluid_)) continue;
      if (!c.path.t.empty()) {  // a moving one: its own series (write_moving_colliders); not in the blood's boundaries
        if (from_tissue) ++(c.kind == ColliderDef::Kind::plane ? op : om);
        continue;
      }
      if (c.kind == ColliderDef::Kind::plane) {
        if (from_tissue) {
          const ObstaclePlane& pl = ob->planes[op++];
          planes.emplace_back(pl.point, pl.normal);
          if (c.blood && fluid_) ++fp;
        } else {
          const FluidPlane& pl = fluid_->bounds.planes[fp++];
          planes.emplace_back(Vec3{pl.point[0], pl.point[1], pl.point[2]}, Vec3{pl.normal[0], pl.normal[1], pl.normal[2]});
        }
      } else {
        if (from_tissue) {
          mesh_vertices.push_back(&ob->meshes[om].vertices);
          mesh_triangles.push_back(&ob->meshes[om++].triangles);
          if (c.blood && fluid_) ++fm;
        } else {
          mesh_vertices.push_back(&fluid_->bounds.meshes[fm].vertices);
          mesh_triangles.push_back(&fluid_->bounds.meshes[fm++].triangles);
        }
      }
    }
  }
  std::vector<double> pts;
  std::vector<std::int32_t> tri;
  for (std::size_t k = 0; k < mesh_vertices.size(); ++k) {
    const auto off = static_cast<std::int32_t>(pts.size() / 3);
    pts.insert(pts.end(), mesh_vertices[k]->begin(), mesh_vertices[k]->end());
    for (auto i : *mesh_triangles[k]) tri.push_back(off + i);
  }
  for (const auto& [p0, n] : planes) append_plane_polygon(box_lo, box_hi, p0, n, pts, tri);
  if (!tri.empty())
    write_vtp(def_.output.dir + "/" + def_.output.name + "_colliders.vtp", pts, tri, {}, def_.output.vtk.binary);
}

void Scene::write_moving_colliders() {
  if (moving_.empty()) return;
  const auto [blo, bhi] = collider_box();
  const std::array<Real, 3> box_lo{blo.x, blo.y, blo.z}, box_hi{bhi.x, bhi.y, bhi.z};
  std::vector<double> pts;
  std::vector<std::int32_t> tri;
  for (const MovingCollider& mc : moving_) {
    const Path& path = def_.colliders[mc.def].path;
    if (mc.vertices.empty()) {
      const Vec3 n = path.r.empty() ? mc.normal : path_rotation(path, state_.time)(mc.normal);
      append_plane_polygon(box_lo, box_hi, moved(path, mc.pivot, mc.point, state_.time), n, pts, tri);
      continue;
    }
    const auto off = static_cast<std::int32_t>(pts.size() / 3);
    for (std::size_t i = 0; i + 2 < mc.vertices.size(); i += 3) {
      const Vec3 q = moved(path, mc.pivot, load3(mc.vertices.data(), static_cast<std::int64_t>(i / 3)), state_.time);
      pts.insert(pts.end(), {q.x, q.y, q.z});
    }
    for (auto i : mc.triangles) tri.push_back(off + i);
  }
  const std::string& dir = def_.output.dir;
  const std::string& name = def_.output.name;
  char tag[16];
  std::snprintf(tag, sizeof tag, "%06d", static_cast<int>(moving_frames_.size()));
  const std::string file = name + "_moving_colliders_" + tag + ".vtp";
  write_vtp(dir + "/" + file, pts, tri, {}, def_.output.vtk.binary);
  moving_frames_.emplace_back(state_.time, file);
  write_pvd(dir + "/" + name + "_moving_colliders.pvd", moving_frames_);
}

void Scene::write_fluid_frame() {
  FluidRun& fr = *fluid_;
  const std::string& dir = def_.output.dir;
  const std::string& name = def_.output.name;
  const int k = static_cast<int>(fr.frames.size());
  const Real t = state_.time;
  auto pvd = [&](const std::string& series, const std::vector<std::pair<Real, std::string>>& files) {
    write_pvd(dir + "/" + name + "_" + series + ".pvd", files);
  };
  // six digits, as the tissue's frames (name_000012.vtu): listings sort in time order
  char tag_digits[16];
  std::snprintf(tag_digits, sizeof tag_digits, "%06d", k);
  const std::string tag = tag_digits;
  if (def_.fluid.surface) {
    FluidSurfaceOptions so;
    so.cell = def_.fluid.surface_cell;
    so.volume_passes = def_.fluid.surface_volume_passes;
    const FluidSurfaceMesh mesh = extract_fluid_surface(fr.fluid, fr.state, so);
    write_fluid_surface_vtp(dir + "/" + name + "_blood_" + tag + ".vtp", mesh, def_.output.vtk.binary, t);
    fr.summary.surface_triangles = mesh.n_triangles();
  }
  if (def_.fluid.particles) write_fluid_particles_vtp(dir + "/" + name + "_particles_" + tag + ".vtp", fr.state, def_.output.vtk.binary);
  fr.frames.emplace_back(t, tag);
  std::vector<std::pair<Real, std::string>> files;
  if (def_.fluid.surface) {
    for (const auto& [time, f] : fr.frames) files.emplace_back(time, name + "_blood_" + f + ".vtp");
    pvd("blood", files);
  }
  if (def_.fluid.particles) {
    files.clear();
    for (const auto& [time, f] : fr.frames) files.emplace_back(time, name + "_particles_" + f + ".vtp");
    pvd("particles", files);
  }
}

void Scene::check_mutable(const char* what) const {
  if (in_step_) throw Error(def_.file, std::string(what) + " between simulate() and fetch_results()");
}

void Scene::update_tools(Real t) {
  // a cut replaces model_: keep the model of this pass alive (node ids do not change)
  const std::shared_ptr<const Model> hold = model_;
  const Model& m = *hold;
  const Real eps = 1e-9 * def_.dt;
  for (auto& tr : tools_) {
    const ToolDef& d = tr.def;
    if (tr.active && t >= d.end - eps) {
      if (d.type == ToolType::pull) detach(m, state_, tr.attachment);
      if (d.type == ToolType::hook) {
        // release only what this hook fixed and nothing else holds
        std::vector<std::int32_t> rel;
        std::set<std::int32_t> keep;
        for (const auto& name : def_.fixed)
          for (auto i : m.set(name)) keep.insert(i);
        for (const auto& other : tools_)
          if (&other != &tr && other.active && other.def.type == ToolType::hook) keep.insert(other.nodes.begin(), other.nodes.end());
        for (auto i : tr.nodes)
          if (!keep.count(i)) rel.push_back(i);
        release_nodes(m, state_, rel);
      }
      tr.active = false;
      tr.done = true;
    }
    if (!tr.active && !tr.done && t >= d.start - eps && t < d.end - eps) {
      tr.active = true;
      if (d.type == ToolType::pull) {
        Attachment a;
        a.nodes = tr.nodes;
        a.stiffness = d.stiffness;
        a.path = d.path;
        const Vec3 p = d.path.at(t);
        for (auto i : tr.nodes) {
          const Vec3 off = load3(state_.x.data(), i) - p;
          a.offset.insert(a.offset.end(), {off.x, off.y, off.z});
        }
        tr.attachment = attach(m, state_, std::move(a));
      }
      if (d.type == ToolType::hook) fix_nodes(m, state_, tr.nodes);
      if (d.type == ToolType::cut) {
        // a snapped polyline runs through its nodes where they are now (the
        // tissue may have sagged or been pulled since rest: the rest positions
        // put the cut up to 2 cm off the skin the polyline was snapped to in
        // the sample's bleeding scene, cut at 0.1 s); the others are in space
        CutDef cd;
        for (std::size_t k = 0; 3 * k < d.polyline.size(); ++k)
          cd.polyline.push_back(tr.nodes.empty() ? load3(d.polyline.data(), static_cast<std::int64_t>(k))
                                                 : load3(state_.x.data(), tr.nodes[k]));
        cd.depth = d.depth;
        cd.node_snap = d.node_snap;
        cd.direction = {d.direction[0], d.direction[1], d.direction[2]};
        apply_cut(cd);
        cuts_.back().tool = d.name;
        tr.active = false;
        tr.done = true;
      }
    }
  }
}

CutReport Scene::apply_cut(const CutDef& def) {
  // the vessels where the tissue has carried them
  if (vessel_carry_.size() != model_->vessels.size()) {
    vessel_carry_.clear();
    for (const auto& v : model_->vessels) vessel_carry_.push_back(carry_points(*model_, v.nodes));
  }
  std::vector<std::vector<Real>> vessel_x;
  for (const Carried& c : vessel_carry_) vessel_x.push_back(carried_positions(c, *model_, state_.x));
  auto edited = std::make_shared<Model>(*model_);
  CutReport rep = cut_model(*edited, state_.x, def, fluid_ ? &fluid_->wound : nullptr, vessel_x);
  model_ = edited;
  if (!rep.detached.empty()) fix_nodes(*model_, state_, rep.detached);
  state_.step_limit = 0;
  // (the faces' rows name triangles of the quads as they were: the solve
  // holds those whose corners are still a face and drops the others)
  if (vtk_) vtk_->set_topology(*model_);
  if (fluid_) {
    // each cut vessel bleeds: Poiseuille flow of its radius capped by the
    // orifice, with the profile of the limit that binds, out of the wound
    const FluidDef& fd = def_.fluid;
    std::vector<Vec3> disc;  // the emitters' discs: the wound holds them (WoundColumns)
    for (const VesselHit& h : rep.vessel_hits) {
      FluidEmitter e;
      e.center = {h.point.x, h.point.y, h.point.z};
      e.direction = {-rep.direction.x, -rep.direction.y, -rep.direction.z};
      // the jet is at least 1.5 particle spacings wide (a 3 x 3 disc of
      // particles); the flow rate is the vessel's
      e.radius = std::max(h.radius, Real(1.5) * fluid_->fluid.params.spacing);
      e.flow_rate = bleeding_flow_rate(h.radius, fd.bleed_pressure, fluid_->fluid.params, fd.bleed_length);
      e.profile = bleeding_profile(h.radius, fd.bleed_pressure, fluid_->fluid.params, fd.bleed_length);
      e.start = state_.time;
      e.end = state_.time + fd.bleed_duration;
      fluid_->state.emitters.push_back(e);
      {  // the emitter moves with the wound: its point of the vessel at rest, carried
        const auto& ves = model_->vessels[static_cast<std::size_t>(h.vessel)];
        const Vec3 a = load3(ves.nodes.data(), ves.edges[2 * static_cast<std::size_t>(h.edge)]),
                   b = load3(ves.nodes.data(), ves.edges[2 * static_cast<std::size_t>(h.edge) + 1]);
        const Vec3 r = a + h.along * (b - a);
        const Carried c = carry_points(*model_, std::vector<Real>{r.x, r.y, r.z});
        Carried& all = fluid_->emitter_carry;
        all.k = c.k;
        all.rest.insert(all.rest.end(), c.rest.begin(), c.rest.end());
        all.node.insert(all.node.end(), c.node.begin(), c.node.end());
        all.weight.insert(all.weight.end(), c.weight.begin(), c.weight.end());
      }
      // the disc's centre and 16 points on its rim and half-way out
      const Vec3 d = rep.direction;
      const Vec3 u0 = std::abs(d.x) < 0.9 ? Vec3{1, 0, 0} : Vec3{0, 1, 0};
      Vec3 u = u0 - dot(u0, d) * d;
      u = (1 / norm(u)) * u;
      const Vec3 v{d.y * u.z - d.z * u.y, d.z * u.x - d.x * u.z, d.x * u.y - d.y * u.x};
      disc.push_back(h.point);
      for (int k = 0; k < 8; ++k) {
        const Real a = k * std::numbers::pi / 4;
        for (Real r : {e.radius, Real(0.5) * e.radius}) disc.push_back(h.point + r * (std::cos(a) * u + std::sin(a) * v));
      }
    }
    rep.columns_opened += open_columns_at(fluid_->wound, state_.x, disc);
    update_fluid_surface();
  }
  rep.time = state_.time;
  cuts_.push_back(rep);
  return rep;
}

CutReport Scene::cut(const CutDef& def) {
  check_mutable("cut()");
  try {
    validate(def);
  } catch (const Error& e) {
    throw Error(def_.file, e.message());
  }
  return apply_cut(def);
}

void Scene::simulate(Real dt) {
  check_mutable("simulate()");
  if (!(std::isfinite(dt) && dt > 0)) throw Error(def_.file, "simulate(): dt must be positive and finite");
  update_tools(state_.time);
  // external forces of this step: user forces and pressure tools
  std::fill(state_.f_ext.begin(), state_.f_ext.end(), 0);
  if (user_force_set_) state_.f_ext = user_force_;
  for (const auto& tr : tools_) {
    if (!tr.active || tr.def.type != ToolType::pressure) continue;
    const Real total = tr.def.pressure * M_PI * tr.def.radius * tr.def.radius;
    const Real each = total / static_cast<Real>(tr.nodes.size());
    for (auto i : tr.nodes)
      for (int k = 0; k < 3; ++k) state_.f_ext[3 * static_cast<std::size_t>(i) + k] += each * tr.def.direction[k];
  }
  if (fluid_ && def_.fluid.couple)
    for (std::size_t i = 0; i < state_.f_ext.size(); ++i) state_.f_ext[i] += fluid_->force[i];
  in_step_ = true;
  if (fluid_) {
    const std::vector<Real> x_start = state_.x;
    arena_->arena.execute([&] {
      last_ = step(*model_, state_, dt, def_.solver);
      fluid_step_now(dt, x_start);
    });
  } else {
    arena_->arena.execute([&] { last_ = step(*model_, state_, dt, def_.solver); });
  }
  if (user_force_set_) {
    std::fill(user_force_.begin(), user_force_.end(), 0);
    user_force_set_ = false;
  }
}

StepInfo Scene::fetch_results() {
  in_step_ = false;
  return last_;
}

Real Scene::step_limit() { return symplectic_step_limit(*model_, state_, def_.solver); }

void Scene::add_force(std::int32_t node, const std::array<Real, 3>& f) {
  check_mutable("add_force()");
  if (node < 0 || node >= model_->n_nodes) throw Error(def_.file, "add_force(): node " + std::to_string(node) + " out of range");
  for (int k = 0; k < 3; ++k) {
    if (!std::isfinite(f[k])) throw Error(def_.file, "add_force(): force must be finite");
    user_force_[3 * static_cast<std::size_t>(node) + k] += f[k];
  }
  user_force_set_ = true;
}

int Scene::tool(const std::string& name) const {
  for (std::size_t i = 0; i < tools_.size(); ++i)
    if (tools_[i].def.name == name) return static_cast<int>(i);
  return -1;
}

const std::vector<std::int32_t>& Scene::tool_nodes(int tool) const { return tools_.at(static_cast<std::size_t>(tool)).nodes; }
Real Scene::tool_snap_distance(int tool) const { return tools_.at(static_cast<std::size_t>(tool)).snap_m; }
std::array<Real, 3> Scene::tool_center(int tool) const { return tools_.at(static_cast<std::size_t>(tool)).def.center; }

void Scene::move_tool(int tool, const std::array<Real, 3>& p) {
  check_mutable("move_tool()");
  if (tool < 0 || tool >= static_cast<int>(tools_.size())) throw Error(def_.file, "move_tool(): no tool " + std::to_string(tool));
  for (Real x : p)
    if (!std::isfinite(x)) throw Error(def_.file, "move_tool(): target must be finite");
  ToolRun& tr = tools_[static_cast<std::size_t>(tool)];
  const Real t = state_.time;
  const Vec3 now = tr.def.path.at(t);
  Path path;
  path.t = {t, t + def_.dt};
  path.p = {now.x, now.y, now.z, p[0], p[1], p[2]};
  tr.def.path = path;
  if (tr.active && tr.attachment >= 0) {
    state_.attachments[static_cast<std::size_t>(tr.attachment)].path = path;
    state_.step_limit = 0;
  }
}

int Scene::collider(const std::string& name) const {
  for (std::size_t i = 0; i < def_.colliders.size(); ++i)
    if (def_.colliders[i].name == name) return static_cast<int>(i);
  return -1;
}

void Scene::move_collider(int collider, const std::array<Real, 3>& d) {
  check_mutable("move_collider()");
  if (collider < 0 || collider >= static_cast<int>(def_.colliders.size()))
    throw Error(def_.file, "move_collider(): no collider " + std::to_string(collider));
  ColliderDef& c = def_.colliders[static_cast<std::size_t>(collider)];
  if (c.path.t.empty())
    throw Error(def_.file, "move_collider(): the collider '" + c.name +
                               "' has no path (give it one, [[0, 0, 0, 0]] to start where it is given, to move it)");
  for (Real x : d)
    if (!std::isfinite(x) || std::abs(x) > 1e9) throw Error(def_.file, "move_collider(): displacement must be finite, within +-1e9 m");
  const Real t = state_.time;
  const Vec3 now = c.path.at(t);
  Path path;
  path.t = {t, t + def_.dt};
  path.p = {now.x, now.y, now.z, d[0], d[1], d[2]};
  c.path = path;
  if (c.tissue && state_.obstacles) {
    // its obstacle: the tissue's planes, then its meshes, each in the colliders' order
    std::size_t k = 0;
    for (int kind = 0; kind < 2; ++kind)
      for (std::size_t i = 0; i < def_.colliders.size(); ++i) {
        const ColliderDef& e = def_.colliders[i];
        if (!e.tissue || (e.kind == ColliderDef::Kind::plane) != (kind == 0)) continue;
        if (i == static_cast<std::size_t>(collider)) state_.obstacle_paths.at(k) = path;
        ++k;
      }
  }
}

void Scene::fix(std::span<const std::int32_t> nodes) {
  check_mutable("fix()");
  fix_nodes(*model_, state_, nodes);
}

void Scene::release(std::span<const std::int32_t> nodes) {
  check_mutable("release()");
  release_nodes(*model_, state_, nodes);
}

void Scene::write_frame() {
  if (vtk_) vtk_->write(*model_, state_);
  if (vtk_ && fluid_) write_fluid_frame();
  if (vtk_) write_moving_colliders();
}

RunSummary run(Scene& scene, long steps, const std::function<void(long)>& progress) {
  using clock = std::chrono::steady_clock;
  RunSummary r;
  const auto t0 = clock::now();
  const Real dt = scene.def().dt;
  const int every = scene.def().output.every;
  auto frame = [&] {
    const auto a = clock::now();
    scene.write_frame();
    r.output_wall_s += std::chrono::duration<double>(clock::now() - a).count();
    ++r.frames;
  };
  const bool out = scene.output() != nullptr;
  if (out) frame();
  const Real start = scene.time();
  for (long k = 1; k <= steps; ++k) {
    const auto a = clock::now();
    scene.simulate(dt);
    scene.fetch_results();
    r.step_wall_s += std::chrono::duration<double>(clock::now() - a).count();
    if (out && (k % every == 0 || k == steps)) frame();
    if (progress) progress(k);
  }
  r.steps = steps;
  r.simulated_s = scene.time() - start;
  r.wall_s = std::chrono::duration<double>(clock::now() - t0).count();
  return r;
}

}  // namespace orthosim::runtime
