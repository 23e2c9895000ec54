#include "runtime/scene.h"

#include "libmodel/format/atomic.h"
#include "runtime/loader.h"

#include <nlohmann/json.hpp>
#include <tbb/info.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
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

// Reads typed values out of one JSON object, rejecting unknown keys.
class Obj {
 public:
  Obj(const json& j, std::string where, const std::string& file) : j_(j), where_(std::move(where)), file_(file) {
    if (!j.is_object()) fail("must be an object");
  }
  [[noreturn]] void fail(const std::string& what) const { throw Error(file_, where_ + what); }
  bool has(const char* key) {
    seen_.insert(key);
    return j_.contains(key) && !j_.at(key).is_null();
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
    if (!v.is_number_integer()) fail(std::string(key) + " must be an integer (got " + v.dump() + ")");
    const long x = v.get<long>();
    if (x < lo || x > hi) fail(std::string(key) + " must be in [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
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
      if (!v[k].is_number() || !std::isfinite(v[k].get<Real>())) fail(std::string(key) + " must be three finite numbers");
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

std::string resolve(const std::string& base_dir, const std::string& p) {
  if (p.empty() || fs::path(p).is_absolute() || base_dir.empty()) return p;
  return (fs::path(base_dir) / p).lexically_normal().string();
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
  else o.fail("type must be pull, pressure, hook or cut (got '" + type + "')");
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
  } else {
    if (o.has("radius")) o.fail("radius needs a center");
    if (t.nodes.empty() && t.type != ToolType::cut) o.fail("needs a center and radius, or a node set in 'nodes'");
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
        if (!x.is_number() || !std::isfinite(x.get<Real>())) o.fail(std::string(key) + " values must be finite numbers");
        if (t.polyline_relative && (x.get<Real>() < 0 || x.get<Real>() > 1)) o.fail("polyline_in_box fractions must be in [0, 1]");
        t.polyline.push_back(x.get<Real>());
      }
    }
    t.depth = o.number("depth", 0, 0, 10, true);
    if (!o.has("depth")) o.fail("depth (m) is required");
    t.direction = o.vec3("direction", {0, 0, 0});
    t.snap = o.boolean("snap", true);
  }
  t.start = o.number("start", 0, 0, 1e9);
  t.end = o.number("end", std::numeric_limits<Real>::infinity(), 0, 1e9);
  if (o.has("end") && !(t.end > t.start)) o.fail("end must be after start");
  if (t.type == ToolType::pull) {
    t.stiffness = o.number("stiffness", 0, 0, 1e12);
    if (o.has("path")) {
      const json& p = o.at("path");
      if (!p.is_array() || p.empty()) o.fail("path must be a list of [t, dx, dy, dz]");
      for (const auto& e : p) {
        if (!e.is_array() || e.size() != 4) o.fail("path must be a list of [t, dx, dy, dz]");
        for (const auto& x : e)
          if (!x.is_number() || !std::isfinite(x.get<Real>())) o.fail("path values must be finite numbers");
        const Real tt = e[0].get<Real>();
        if (tt < 0 || (!t.path.t.empty() && !(tt > t.path.t.back()))) o.fail("path times must be >= 0 and increasing");
        t.path.t.push_back(tt);
        for (int k = 1; k < 4; ++k) t.path.p.push_back(e[k].get<Real>());
      }
    }
  }
  if (t.type == ToolType::pressure) {
    t.pressure = o.number("pressure", 0, -1e9, 1e9);
    if (!o.has("pressure")) o.fail("pressure (Pa) is required");
    if (!t.has_center) o.fail("a pressure tool needs a center and radius");
    t.direction = o.vec3("direction", {0, 0, 0});
    const Real n = std::sqrt(t.direction[0] * t.direction[0] + t.direction[1] * t.direction[1] + t.direction[2] * t.direction[2]);
    if (!(n > 0)) o.fail("direction must be a non-zero [x, y, z]");
    for (auto& d : t.direction) d /= n;
  }
  o.finish();
  return t;
}

}  // namespace

SceneDef parse_scene(const std::string& text, const std::string& file) {
  json j;
  try {
    j = json::parse(text);
  } catch (const json::exception& e) {
    std::string what = e.what();
    for (auto& c : what)
      if (c == '\n') c = ' ';
    throw Error(file, "invalid JSON: " + what);
  }
  const std::string base = file.empty() ? "" : fs::path(file).parent_path().string();
  SceneDef d = default_scene_def();
  d.file = file;
  Obj o(j, "", file);
  o.string("description", "");
  d.model = resolve(base, o.string("model", "", true));
  d.layers = o.strings("layers");
  if (d.layers.size() == 1 && d.layers[0] == "all") d.layers.clear();
  d.vessels = o.strings("vessels");
  if (o.has("fluid")) o.fail("fluid is not supported by this runtime yet (runtime II); remove it or set it to null");
  d.fixed = o.strings("fixed");
  d.sets = o.strings("sets");
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
    Obj s(o.at("implicit"), "implicit: ", file);
    d.solver.cg_tolerance = s.number("cg_tolerance", d.solver.cg_tolerance, 0, 1, true);
    d.solver.cg_max_iterations = static_cast<int>(s.integer("cg_max_iterations", d.solver.cg_max_iterations, 1, 100000));
    const std::string pc = s.string("preconditioner", "block_jacobi");
    if (pc == "block_jacobi") d.solver.preconditioner = Preconditioner::block_jacobi;
    else if (pc == "jacobi") d.solver.preconditioner = Preconditioner::jacobi;
    else s.fail("preconditioner must be jacobi or block_jacobi (got '" + pc + "')");
    d.solver.warm_start = s.boolean("warm_start", true);
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
    d.output.dir = resolve(base, out.string("dir", "", true));
    d.output.name = out.string("name", d.output.name);
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
    if (!t.has_center && t.nodes.empty() && t.type != ToolType::cut) fail("tool '" + t.name + "' needs a center and radius, or a node set");
    if (t.type == ToolType::cut && (t.polyline.size() < 6 || t.polyline.size() % 3 || !(t.depth > 0)))
      fail("tool '" + t.name + "': a cut needs a polyline of at least 2 points and a depth > 0");
    if (!(t.end > t.start)) fail("tool '" + t.name + "': end must be after start");
    if (!(std::isfinite(t.stiffness) && t.stiffness >= 0)) fail("tool '" + t.name + "': stiffness must be >= 0");
    if (!std::isfinite(t.pressure)) fail("tool '" + t.name + "': pressure must be finite");
    if (t.path.p.size() != 3 * t.path.t.size()) fail("tool '" + t.name + "': path points do not match its times");
  }
  if (d.output.enabled && d.output.dir.empty()) fail("output: dir is required");
}

// ---- Scene ------------------------------------------------------------------

struct Scene::Arena {
  tbb::task_arena arena;
  explicit Arena(int threads) : arena(threads > 0 ? threads : tbb::info::default_concurrency()) {}
};

Scene::Scene(const SceneDef& def) : def_(def) {
  validate(def_);
  std::error_code ec;
  if (def_.model.empty()) throw Error(def_.file, "no model file given");
  if (!fs::is_regular_file(def_.model, ec)) throw Error(def_.file, "model file '" + def_.model + "' does not exist");
  init(def_.model);
}

Scene::Scene(Model model, const SceneDef& def) : def_(def) {
  validate(def_);
  model_ = std::make_shared<const Model>(std::move(model));
  init("");
}

Scene::~Scene() = default;

void Scene::init(const std::string& model_file) {
  const std::string& file = def_.file;
  if (!model_) {
    ModelReader reader(model_file);
    LoadRequest req;
    req.layers = def_.layers;
    req.vessels = def_.vessels;
    req.surface = def_.output.enabled && def_.output.vtk.surface;
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
      Vec3 lo{HUGE_VAL, HUGE_VAL, HUGE_VAL}, hi{-HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
      for (auto i : candidates) {
        const Vec3 p = load3(m.rest_x.data(), i);
        lo = {std::min(lo.x, p.x), std::min(lo.y, p.y), std::min(lo.z, p.z)};
        hi = {std::max(hi.x, p.x), std::max(hi.y, p.y), std::max(hi.z, p.z)};
      }
      for (std::size_t k = 0; 3 * k < t.polyline.size(); ++k) {
        Vec3 p = load3(t.polyline.data(), static_cast<std::int64_t>(k));
        if (t.polyline_relative) p = {lo.x + p.x * (hi.x - lo.x), lo.y + p.y * (hi.y - lo.y), lo.z + p.z * (hi.z - lo.z)};
        if (t.snap) {
          Real best = HUGE_VAL;
          Vec3 q = p;
          for (auto i : candidates) {
            const Vec3 r = load3(m.rest_x.data(), i);
            if (norm(r - p) < best) best = norm(r - p), q = r;
          }
          p = q;
        }
        store3(run.def.polyline.data(), static_cast<std::int64_t>(k), p);
      }
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
      Vec3 lo{HUGE_VAL, HUGE_VAL, HUGE_VAL}, hi{-HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
      for (auto i : candidates) {
        const Vec3 p = load3(m.rest_x.data(), i);
        lo = {std::min(lo.x, p.x), std::min(lo.y, p.y), std::min(lo.z, p.z)};
        hi = {std::max(hi.x, p.x), std::max(hi.y, p.y), std::max(hi.z, p.z)};
      }
      if (candidates.empty()) throw Error(file, "tool '" + t.name + "' has no candidate node");
      const auto& f = t.center_fraction;
      run.def.center = {lo.x + f[0] * (hi.x - lo.x), lo.y + f[1] * (hi.y - lo.y), lo.z + f[2] * (hi.z - lo.z)};
    }
    if (t.has_center) {
      const Vec3 c{run.def.center[0], run.def.center[1], run.def.center[2]};
      for (auto i : candidates)
        if (norm(load3(m.rest_x.data(), i) - c) <= t.radius) run.nodes.push_back(i);
      if (run.nodes.empty())
        throw Error(file, "tool '" + t.name + "' takes no node: no " + (t.nodes.empty() ? "free node" : "node of set '" + t.nodes + "'") +
                              " lies within " + fmt(t.radius) + " m of (" + fmt(c.x) + ", " + fmt(c.y) + ", " + fmt(c.z) + ")");
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

  // output directory, after everything else is known to be valid
  if (def_.output.enabled) {
    check_output_dir(def_.output.dir);
    std::error_code ec;
    fs::create_directories(def_.output.dir, ec);
    if (ec) throw Error(def_.output.dir, "cannot create the output directory: " + ec.message());
    vtk_ = std::make_unique<VtkSeries>(m, def_.output.dir, def_.output.name, def_.output.vtk);
  }
  user_force_.assign(3 * static_cast<std::size_t>(m.n_nodes), 0);
  arena_ = std::make_unique<Arena>(def_.threads);
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
        CutDef cd;
        for (std::size_t k = 0; 3 * k < d.polyline.size(); ++k)
          cd.polyline.push_back(load3(d.polyline.data(), static_cast<std::int64_t>(k)));
        cd.depth = d.depth;
        cd.direction = {d.direction[0], d.direction[1], d.direction[2]};
        apply_cut(cd);
        tr.active = false;
        tr.done = true;
      }
    }
  }
}

CutReport Scene::apply_cut(const CutDef& def) {
  auto edited = std::make_shared<Model>(*model_);
  CutReport rep = cut_model(*edited, state_.x, def);
  model_ = edited;
  if (!rep.detached.empty()) fix_nodes(*model_, state_, rep.detached);
  state_.step_limit = 0;
  if (vtk_) vtk_->set_topology(*model_);
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
  in_step_ = true;
  arena_->arena.execute([&] { last_ = step(*model_, state_, dt, def_.solver); });
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
