#include "runtime/obstacles.h"

#include "libmodel/format/types.h"

#include <algorithm>
#include <cmath>

namespace orthosim::runtime {

namespace {

bool finite(const Vec3& a) { return std::isfinite(a.x) && std::isfinite(a.y) && std::isfinite(a.z); }

void check_contact_law(const char* what, Real restitution, Real friction) {
  if (!(restitution >= 0 && restitution <= 1)) throw Error("", std::string(what) + ": restitution must be in [0, 1]");
  if (!(friction >= 0 && std::isfinite(friction))) throw Error("", std::string(what) + ": friction must be finite and >= 0");
}

// How far a node is put in front of a mesh's surface: enough that round-off
// cannot leave it behind (so the next substep's motion starts in front), far
// below any length of the model.
Real standoff(const Vec3& p) { return 1e-9 * std::max({Real(1), std::abs(p.x), std::abs(p.y), std::abs(p.z)}); }

// The contact law on the velocity for the unit normal n of the free side.
void slow_down(Vec3& v, const Vec3& n, Real dvn, Real friction) {
  const Vec3 vt = v - dot(v, n) * n;
  const Real st = norm(vt);
  if (st > 0 && dvn > 0) v -= std::min(Real(1), friction * dvn / st) * vt;
}

void respond(Vec3& v, const Vec3& n, Real restitution, Real friction) {
  const Real vn = dot(v, n);
  if (!(vn < 0)) return;
  const Real dvn = -(1 + restitution) * vn;
  v += dvn * n;
  slow_down(v, n, dvn, friction);
}

// The mesh's triangle closest to p within `within` (by the grid cell of p,
// which lists every triangle within the grid's margin of it: within must
// not exceed it), ties to the lowest id: its id (-1: none), the closest point
// and the unit normal of the side p is on (counter-clockwise: +; behind: -).
struct Closest {
  std::int32_t tri = -1;
  Vec3 c, n;
  bool behind = false;
};
Closest closest_triangle(const ObstacleMesh& m, const Vec3& p, Real within) {
  const TriangleCells& g = m.grid.level[0];
  const Real* X = m.vertices.data();
  const std::int32_t* T = m.triangles.data();
  Closest out;
  Real best = within * within;
  const auto [b, e] = cell_candidates(g, p);
  for (std::int32_t q = b; q < e; ++q) {
    const std::int32_t t = g.items[q];
    const Vec3 c = closest_point_on_triangle(p, load3(X, T[3 * t]), load3(X, T[3 * t + 1]), load3(X, T[3 * t + 2]));
    const Real d2 = dot(p - c, p - c);
    if (d2 < best || (d2 == best && t < out.tri)) best = d2, out.tri = t, out.c = c;
  }
  if (out.tri < 0) return out;
  const Vec3 a = load3(X, T[3 * out.tri]);
  const Vec3 nrm = cross(load3(X, T[3 * out.tri + 1]) - a, load3(X, T[3 * out.tri + 2]) - a);
  out.behind = dot(nrm, p - out.c) < 0;
  out.n = ((out.behind ? -1 : 1) / norm(nrm)) * nrm;
  return out;
}

struct Hit {
  Real t = 2;              // along the motion, [0, 1]
  std::int32_t tri = -1;
  Vec3 q, n;               // crossing point, unit normal of the side the motion came from
};

// The first crossing of segment p0 -> p1 with the mesh's triangles (the
// lowest triangle id among equal t), if any.
Hit first_crossing(const ObstacleMesh& m, const Vec3& p0, const Vec3& p1) {
  Hit best;
  const TriangleCells& g = m.grid.level[0];
  const Vec3 d = p1 - p0;
  const Real len = norm(d);
  if (!std::isfinite(len)) return best;  // (a non-finite motion: the solver's check redoes the substep)
  // candidates: the cells of points along the motion at most one margin
  // apart; a triangle the motion crosses at c is within half a margin of one
  // of them, so listed in its cell
  const int samples = g.margin > 0 ? static_cast<int>(std::min<Real>(std::ceil(len / g.margin), 1 << 16)) : 1;
  const Real* X = m.vertices.data();
  const std::int32_t* T = m.triangles.data();
  for (int k = 0; k <= samples; ++k) {
    const Vec3 p = samples > 0 ? p0 + (static_cast<Real>(k) / samples) * d : p0;
    const auto [b, e] = cell_candidates(g, p);
    for (std::int32_t q = b; q < e; ++q) {
      const std::int32_t t = g.items[q];
      const Vec3 a = load3(X, T[3 * t]), bb = load3(X, T[3 * t + 1]), c = load3(X, T[3 * t + 2]);
      const Vec3 nrm = cross(bb - a, c - a);
      const Real s0 = dot(nrm, p0 - a), s1 = dot(nrm, p1 - a);
      Real side;
      if (s0 >= 0 && s1 < 0) side = 1;
      else if (m.two_sided && s0 < 0 && s1 > 0) side = -1;
      else continue;
      const Real tt = s0 / (s0 - s1);
      if (tt > best.t || (tt == best.t && t > best.tri)) continue;
      const Vec3 x = p0 + tt * d;
      const Real n2 = dot(nrm, nrm), tol = -1e-12 * n2;
      if (dot(cross(bb - x, c - x), nrm) < tol || dot(cross(c - x, a - x), nrm) < tol || dot(cross(a - x, bb - x), nrm) < tol)
        continue;
      best.t = tt;
      best.tri = t;
      best.q = x;
      best.n = (side / std::sqrt(n2)) * nrm;
    }
  }
  return best;
}

}  // namespace

void add_obstacle_plane(Obstacles& o, ObstaclePlane plane) {
  const Real l = norm(plane.normal);
  if (!(l > 0) || !std::isfinite(l) || !finite(plane.point))
    throw Error("", "obstacle plane: normal must be non-zero and finite, and the point finite");
  check_contact_law("obstacle plane", plane.restitution, plane.friction);
  plane.normal = (1 / l) * plane.normal;
  o.planes.push_back(plane);
}

void add_obstacle_mesh(Obstacles& o, ObstacleMesh mesh) {
  validate_triangle_mesh(mesh.vertices, mesh.triangles, "obstacle mesh");
  check_contact_law("obstacle mesh", mesh.restitution, mesh.friction);
  // the grid's margin: the mean edge length, so a cell lists a few triangles
  // and a motion of a substep (far shorter, as a rule) samples one or two cells
  Real sum = 0;
  const std::size_t nt = mesh.triangles.size() / 3;
  for (std::size_t t = 0; t < nt; ++t)
    for (int k = 0; k < 3; ++k)
      sum += norm(load3(mesh.vertices.data(), mesh.triangles[3 * t + k]) -
                  load3(mesh.vertices.data(), mesh.triangles[3 * t + (k + 1) % 3]));
  const Real margin = nt > 0 ? sum / static_cast<Real>(3 * nt) : 0;
  build_static_triangle_grid(mesh.vertices, mesh.triangles, margin, mesh.grid);
  if (std::find(mesh.grid.listed.begin(), mesh.grid.listed.end(), 1) == mesh.grid.listed.end())
    throw Error("", "obstacle mesh: no triangle with an area (" + std::to_string(nt) + " triangles, all degenerate)");
  o.meshes.push_back(std::move(mesh));
}

Real obstacle_friction_coefficient(const Obstacles& o, std::int32_t k) {
  const auto np = static_cast<std::int32_t>(o.planes.size());
  if (k < 0 || k >= np + static_cast<std::int32_t>(o.meshes.size())) return 0;
  return k < np ? o.planes[static_cast<std::size_t>(k)].friction : o.meshes[static_cast<std::size_t>(k - np)].friction;
}

void obstacle_friction(const Obstacles& o, std::int32_t k, const Vec3& n, Real dvn, Vec3& v) {
  slow_down(v, n, dvn, obstacle_friction_coefficient(o, k));
}

Real obstacle_reach(const Vec3& x) { return 1e3 * standoff(x); }

ObstacleContact rests_on(const Obstacles& o, std::int32_t k, const Vec3& x_world, const Vec3& offset) {
  const auto np = static_cast<std::int32_t>(o.planes.size());
  if (k < 0 || k >= np + static_cast<std::int32_t>(o.meshes.size())) return {};
  const Vec3 x = x_world - offset;  // in the obstacle's frame
  const Real reach = obstacle_reach(x_world);
  if (k < np) {
    const ObstaclePlane& p = o.planes[static_cast<std::size_t>(k)];
    if (dot(p.normal, x - p.point) > reach) return {};
    return {k, p.normal};
  }
  const ObstacleMesh& m = o.meshes[static_cast<std::size_t>(k - np)];
  const Closest c = closest_triangle(m, x, std::min(reach, m.grid.level[0].margin));
  if (c.tri < 0) return {};
  return {k, m.two_sided || !c.behind ? c.n : -c.n};
}

namespace {

// The earliest crossing of any obstacle along x0 -> x (k = -1: none), the
// node moving over the fractions [s0, s1] of the substep and each obstacle as
// `mo` says: a plane where the motion relative to it goes behind it (at once,
// if x0 is behind it already), a mesh where the relative motion crosses a
// triangle from its free side(s); ties to the lowest index. t is the fraction
// of x0 -> x, q the crossing point (in space: on the obstacle's surface where
// it is then), n its free side's normal.
struct Crossing {
  Real t = 2;
  std::int32_t k = -1;
  Vec3 q, n;
};
Crossing earliest_crossing(const Obstacles& o, const Vec3& x0, const Vec3& x, const ObstacleMotion& mo, Real s0,
                           Real s1) {
  Crossing best;
  const auto np = static_cast<std::int32_t>(o.planes.size());
  // obstacle k's displacements at s0 and s1 (zero for obstacles at rest, so
  // that their results are bitwise those of the static query)
  auto ends = [&](std::int32_t k) -> std::pair<Vec3, Vec3> {
    if (!mo.moving()) return {};
    return {mo.at(k, s0), mo.at(k, s1)};
  };
  for (std::int32_t k = 0; k < np; ++k) {
    const ObstaclePlane& p = o.planes[static_cast<std::size_t>(k)];
    const auto [a, b] = ends(k);
    const Vec3 r0 = x0 - a, r1 = x - b;  // the motion in the plane's frame
    const Real d1 = dot(p.normal, r1 - p.point);
    if (!(d1 < 0)) continue;
    const Real d0 = dot(p.normal, r0 - p.point);
    const Real t = d0 > 0 ? d0 / (d0 - d1) : 0;
    if (t < best.t) {
      Vec3 q = r0 + t * (r1 - r0);
      q -= dot(p.normal, q - p.point) * p.normal;  // on it (x0 may have been behind it)
      best = {t, k, q + a + t * (b - a), p.normal};
    }
  }
  for (std::size_t mi = 0; mi < o.meshes.size(); ++mi) {
    const auto k = np + static_cast<std::int32_t>(mi);
    const auto [a, b] = ends(k);
    const Hit c = first_crossing(o.meshes[mi], x0 - a, x - b);
    if (c.tri >= 0 && c.t < best.t) best = {c.t, k, c.q + a + c.t * (b - a), c.n};
  }
  return best;
}

}  // namespace

ObstacleContact resolve_obstacle_contact(const Obstacles& o, Vec3 x0, Vec3& x, Vec3& v, Real h,
                                         const ObstacleMotion& mo) {
  ObstacleContact touched;
  const auto np = static_cast<std::int32_t>(o.planes.size());
  Real left = 1;  // the fraction of the substep still to move after the contacts so far
  // The earliest crossing of any obstacle along x0 -> x: respond there and
  // move on from it with the new velocity for the rest of the substep, that
  // motion itself checked again (a corner between obstacles, or of a mesh).
  // After kRounds crossings the node stays where it is.
  constexpr int kRounds = 8;
  int round = 0;
  for (; round < kRounds; ++round) {
    const Real s0 = 1 - left;  // where in the substep x0 is
    const Crossing c = earliest_crossing(o, x0, x, mo, s0, 1);
    if (c.k < 0) break;
    touched = {c.k, c.n};
    // the contact law on the velocity relative to the obstacle
    const Vec3 u = mo.velocity(c.k, h);
    Vec3 vr = v - u;
    if (c.k < np) {
      const ObstaclePlane& p = o.planes[static_cast<std::size_t>(c.k)];
      respond(vr, c.n, p.restitution, p.friction);
    } else {
      const ObstacleMesh& m = o.meshes[static_cast<std::size_t>(c.k - np)];
      respond(vr, c.n, m.restitution, m.friction);
    }
    v = vr + u;
    const Real s_hit = s0 + c.t * left;
    left *= 1 - c.t;
    // on to the crossing, stood off in front of it (so that round-off cannot
    // leave the node behind); in a corner that step off may cross the other
    // obstacle, and the node then stays where the round began
    const Vec3 q = c.q + standoff(c.q) * c.n;
    if (earliest_crossing(o, x0, q, mo, s0, s_hit).k < 0) x0 = q;
    x = x0 + (left * h) * v;
  }
  if (round == kRounds) x = x0;
  return touched;
}

std::vector<std::int64_t> obstacle_nodes_behind(const Obstacles& o, std::span<const Real> x,
                                                std::span<const std::int32_t> nodes, std::span<const Vec3> offset) {
  std::vector<std::int64_t> out;
  auto shift = [&](std::size_t k) { return k < offset.size() ? offset[k] : Vec3{}; };
  for (const ObstaclePlane& p : o.planes) {
    std::int64_t n = 0;
    const Vec3 d = shift(out.size());
    for (const std::int32_t i : nodes) n += dot(p.normal, load3(x.data(), i) - d - p.point) < 0;
    out.push_back(n);
  }
  for (const ObstacleMesh& m : o.meshes) {
    std::int64_t n = 0;
    const Vec3 d = shift(out.size());
    if (!m.two_sided)
      for (const std::int32_t i : nodes) n += closest_triangle(m, load3(x.data(), i) - d, m.grid.level[0].margin).behind;
    out.push_back(n);
  }
  return out;
}

}  // namespace orthosim::runtime
