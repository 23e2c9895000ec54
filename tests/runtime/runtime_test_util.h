// Helpers shared by the runtime tests: small models built directly.
#pragma once

#include "runtime/model.h"
#include "runtime/obstacles.h"
#include "runtime/sph.h"
#include "runtime/scene.h"
#include "runtime/state.h"

#include <array>
#include <cmath>
#include <initializer_list>
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

// A box [lo, hi] as an obstacle mesh, counter-clockwise seen from outside.
// A path of displacements: {t, dx, dy, dz} waypoints.
inline Path displacement_path(std::initializer_list<std::array<Real, 4>> w) {
  Path p;
  for (const auto& e : w) {
    p.t.push_back(e[0]);
    p.p.insert(p.p.end(), {e[1], e[2], e[3]});
  }
  return p;
}

// The triangle of m's quads (quad_triangle) with face row r's corners, -1
// if none: where a row's face is after a cut renumbered the quads.
inline std::int32_t face_with_corners(const Model& m, const FaceRow& r) {
  for (std::int32_t t = 0; t < 2 * m.n_quads; ++t)
    if (quad_triangle(m.quads, t) == r.node) return t;
  return -1;
}

inline ObstacleMesh box_mesh(const Vec3& lo, const Vec3& hi) {
  ObstacleMesh b;
  for (int k = 0; k < 8; ++k) {
    const bool i = k == 1 || k == 2 || k == 5 || k == 6, j = k == 2 || k == 3 || k == 6 || k == 7, l = k >= 4;
    b.vertices.insert(b.vertices.end(), {i ? hi.x : lo.x, j ? hi.y : lo.y, l ? hi.z : lo.z});
  }
  b.triangles = {0, 3, 2, 0, 2, 1, 4, 5, 6, 4, 6, 7, 0, 1, 5, 0, 5, 4, 3, 7, 6, 3, 6, 2, 0, 4, 7, 0, 7, 3, 1, 2, 6, 1, 6, 5};
  return b;
}

// The quads of the sheet at y = 0 at rest (a layered block's skin), (n x 4).
inline std::vector<std::int32_t> top_sheet_quads(const Model& m) {
  std::vector<std::int32_t> out;
  for (std::size_t q = 0; q < static_cast<std::size_t>(m.n_quads); ++q) {
    bool top = true;
    for (std::size_t c = 0; c < 4; ++c) top = top && m.rest_x[3 * static_cast<std::size_t>(m.quads[4 * q + c]) + 1] == 0;
    if (top) out.insert(out.end(), &m.quads[4 * q], &m.quads[4 * q] + 4);
  }
  return out;
}

// How far the points p (n x 3, moved by d) lie inside the skin: a point is
// inside where it lies behind (deeper in +y than) a triangle of the quads
// (n x 4, each split (q0, q1, q2), (q0, q2, q3)) whose (x, z) projection
// holds it, at the positions x, and its depth is then its distance to the
// nearest triangle (so that a point on a sharp crease, behind one face's
// plane and on the next, is 0 deep). `behind`: the deepest (-HUGE_VAL: none
// inside); `gap`: the least distance from a point outside to the face over
// it (HUGE_VAL: none over any). For a skin facing -y: triangles folded over
// (facing +y) are left out of the inside test and counted.
struct SkinDepth {
  Real behind = -HUGE_VAL, gap = HUGE_VAL;
  int folded = 0;  // triangles folded over (facing +y)
  // the deepest a point lies behind a triangle along its normal, within its
  // extent and less than half its shortest edge deep (what the face contacts
  // resolve; -HUGE_VAL: none)
  Real behind_face = -HUGE_VAL;
};
inline SkinDepth depth_behind_skin(const std::vector<Real>& p, const Vec3& d, const std::vector<std::int32_t>& quads,
                                   const std::vector<Real>& x) {
  SkinDepth r;
  auto at = [&](const std::vector<Real>& a, std::size_t i) { return Vec3{a[3 * i], a[3 * i + 1], a[3 * i + 2]}; };
  auto area = [](const Vec3& u, const Vec3& v, const Vec3& w) { return (v.x - u.x) * (w.z - u.z) - (w.x - u.x) * (v.z - u.z); };
  auto corners = [&](std::size_t f, std::size_t half, Vec3& a, Vec3& b, Vec3& c) {
    a = at(x, static_cast<std::size_t>(quads[f])), b = at(x, static_cast<std::size_t>(quads[f + 1 + half])),
    c = at(x, static_cast<std::size_t>(quads[f + 2 + half]));
  };
  for (std::size_t f = 0; f + 3 < quads.size(); f += 4)
    for (std::size_t half = 0; half < 2; ++half) {
      Vec3 a, b, c;
      corners(f, half, a, b, c);
      r.folded += !(area(a, b, c) > 0);
    }
  for (std::size_t j = 0; 3 * j < p.size(); ++j) {
    const Vec3 q = at(p, j) + d;
    bool inside = false;
    for (std::size_t f = 0; f + 3 < quads.size(); f += 4)
      for (std::size_t half = 0; half < 2; ++half) {
        Vec3 a, b, c;
        corners(f, half, a, b, c);
        const Real A = area(a, b, c);  // > 0: facing -y (outward)
        if (!(A > 0)) continue;
        const Real wa = area(q, b, c) / A, wb = area(a, q, c) / A, wc = area(a, b, q) / A;
        if (!(wa >= 0 && wb >= 0 && wc >= 0)) continue;
        const Real below = wa * a.y + wb * b.y + wc * c.y - q.y;  // >= 0: the face is behind (deeper than) q
        if (below < 0) inside = true;
        else r.gap = std::min(r.gap, below);
      }
    for (std::size_t f = 0; f + 3 < quads.size(); f += 4)
      for (std::size_t half = 0; half < 2; ++half) {
        Vec3 a, b, c;
        corners(f, half, a, b, c);
        const Vec3 n = cross(b - a, c - a);
        const Real n2 = dot(n, n);
        if (!(n2 > 0)) continue;
        const Real dn = dot(n, q - a) / std::sqrt(n2);
        const Real thick = 0.5 * std::sqrt(std::min({dot(b - a, b - a), dot(c - b, c - b), dot(a - c, a - c)}));
        if (!(dn < 0 && dn > -thick)) continue;
        if (dot(cross(b - q, c - q), n) >= 0 && dot(cross(c - q, a - q), n) >= 0 && dot(cross(a - q, b - q), n) >= 0)
          r.behind_face = std::max(r.behind_face, -dn);
      }
    if (!inside) continue;
    Real nearest = HUGE_VAL;
    for (std::size_t f = 0; f + 3 < quads.size(); f += 4)
      for (std::size_t half = 0; half < 2; ++half) {
        Vec3 a, b, c;
        corners(f, half, a, b, c);
        nearest = std::min(nearest, norm(q - closest_point_on_triangle(q, a, b, c)));
      }
    r.behind = std::max(r.behind, nearest);
  }
  return r;
}

}  // namespace orthosim::runtime::test
