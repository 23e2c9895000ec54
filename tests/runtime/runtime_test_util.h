// Helpers shared by the runtime tests: small models built directly.
#pragma once

#include "runtime/model.h"
#include "runtime/scene.h"
#include "runtime/state.h"

#include <array>
#include <cmath>
#include <string>
#include <utility>
#include <vector>

namespace orthosim::runtime::test {

// A model from raw arrays; springs given as (a, b, rest, k, c, tension_only).
struct SpringSpec {
  std::int32_t a, b;
  Real rest, k, c;
  bool tension = false;
};
inline Model make_model(const std::vector<Real>& x, const std::vector<Real>& mass, const std::vector<SpringSpec>& springs) {
  Model m;
  m.n_nodes = static_cast<std::int32_t>(mass.size());
  m.rest_x = x;
  m.mass = mass;
  for (const auto& s : springs) {
    m.spring_a.push_back(s.a);
    m.spring_b.push_back(s.b);
    m.spring_rest.push_back(s.rest);
    m.spring_k.push_back(s.k);
    m.spring_c.push_back(s.c);
    m.spring_tension.push_back(s.tension ? 1 : 0);
  }
  m.n_springs = static_cast<std::int32_t>(springs.size());
  m.finalize();
  return m;
}

// A straight vessel along x through the layered test block (56 mm long), 3 mm
// deep (in its second layer) at z = 8 mm, radius r0 at x = 0 to r1 at the end.
inline Model::Vessel vessel_along_x(const std::string& name, Real r0, Real r1) {
  Model::Vessel v;
  v.name = name;
  v.nodes = {0, 3e-3, 0.008, 0.056, 3e-3, 0.008};
  v.radii = {r0, r1};
  v.edges = {0, 1};
  return v;
}

// A kinematic grip of the skin nodes within `radius` of `center`, moved along
// `path` (offsets from where it grips) from `start`.
inline ToolDef skin_grasper(const std::array<Real, 3>& center, Real radius, Path path, Real start) {
  ToolDef g;
  g.name = "grasper";
  g.type = ToolType::pull;
  g.nodes = "skin";
  g.has_center = true;
  g.center = center;
  g.radius = radius;
  g.path = std::move(path);
  g.start = start;
  return g;
}

inline bool all_finite(const State& s) {
  for (Real v : s.x)
    if (!std::isfinite(v)) return false;
  for (Real v : s.v)
    if (!std::isfinite(v)) return false;
  return true;
}

inline Real max_abs_diff(const std::vector<Real>& a, const std::vector<Real>& b) {
  Real d = 0;
  for (std::size_t i = 0; i < a.size(); ++i) d = std::max(d, std::abs(a[i] - b[i]));
  return d;
}

// largest node displacement |x_i - y_i|
inline Real max_node_distance(const std::vector<Real>& a, const std::vector<Real>& b) {
  Real d = 0;
  for (std::size_t i = 0; i + 2 < a.size(); i += 3)
    d = std::max(d, std::sqrt((a[i] - b[i]) * (a[i] - b[i]) + (a[i + 1] - b[i + 1]) * (a[i + 1] - b[i + 1]) +
                              (a[i + 2] - b[i + 2]) * (a[i + 2] - b[i + 2])));
  return d;
}

}  // namespace orthosim::runtime::test
