#include "runtime/obstacles.h"

#include "libmodel/format/types.h"

#include <Eigen/Geometry>

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

ObstacleContact rests_on(const Obstacles& o, std::int32_t k, const Vec3& x_world, const ObstacleMotion& mo) {
  const auto np = static_cast<std::int32_t>(o.planes.size());
  if (k < 0 || k >= np + static_cast<std::int32_t>(o.meshes.size())) return {};
  const Vec3 x = mo.to_body(k, x_world, 0);  // in the obstacle's frame
  const Real reach = obstacle_reach(x_world);
  if (k < np) {
    const ObstaclePlane& p = o.planes[static_cast<std::size_t>(k)];
    if (dot(p.normal, x - p.point) > reach) return {};
    return {k, mo.normal_to_world(k, p.normal, 0)};
  }
  const ObstacleMesh& m = o.meshes[static_cast<std::size_t>(k - np)];
  const Closest c = closest_triangle(m, x, std::min(reach, m.grid.level[0].margin));
  if (c.tri < 0) return {};
  return {k, mo.normal_to_world(k, m.two_sided || !c.behind ? c.n : -c.n, 0)};
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
  // the motion in obstacle k's own frame, and a crossing there back in space
  // (at rest: the identity, so that the results are bitwise those of the
  // static query)
  auto world = [&](std::int32_t k, Real t, const Vec3& q, const Vec3& n) {
    const Real s = s0 + t * (s1 - s0);
    best = {t, k, mo.to_world(k, q, s), mo.normal_to_world(k, n, s)};
  };
  for (std::int32_t k = 0; k < np; ++k) {
    const ObstaclePlane& p = o.planes[static_cast<std::size_t>(k)];
    const Vec3 r0 = mo.to_body(k, x0, s0), r1 = mo.to_body(k, x, s1);
    const Real d1 = dot(p.normal, r1 - p.point);
    if (!(d1 < 0)) continue;
    const Real d0 = dot(p.normal, r0 - p.point);
    const Real t = d0 > 0 ? d0 / (d0 - d1) : 0;
    if (t < best.t) {
      Vec3 q = r0 + t * (r1 - r0);
      q -= dot(p.normal, q - p.point) * p.normal;  // on it (x0 may have been behind it)
      world(k, t, q, p.normal);
    }
  }
  for (std::size_t mi = 0; mi < o.meshes.size(); ++mi) {
    const auto k = np + static_cast<std::int32_t>(mi);
    const Hit c = first_crossing(o.meshes[mi], mo.to_body(k, x0, s0), mo.to_body(k, x, s1));
    if (c.tri >= 0 && c.t < best.t) world(k, c.t, c.q, c.n);
  }
  return best;
}

}  // namespace

ObstacleContact resolve_obstacle_contact(const Obstacles& o, Vec3 x0, Vec3& x, Vec3& v, Real h,
                                         const ObstacleMotion& mo) {
  ObstacleContact touched;
  const auto np = static_cast<std::int32_t>(o.planes.size());
  Real left = 1;  // the fraction of the substep still to move after the contacts so far
  Real s_x0 = 0;  // where in the substep the node was at x0
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
    // the contact law on the velocity relative to the obstacle's surface there
    const Real s_hit = s0 + c.t * left;
    const Vec3 u = mo.velocity(c.k, c.q, s_hit, h);
    Vec3 vr = v - u;
    if (c.k < np) {
      const ObstaclePlane& p = o.planes[static_cast<std::size_t>(c.k)];
      respond(vr, c.n, p.restitution, p.friction);
    } else {
      const ObstacleMesh& m = o.meshes[static_cast<std::size_t>(c.k - np)];
      respond(vr, c.n, m.restitution, m.friction);
    }
    v = vr + u;
    left *= 1 - c.t;
    // on to the crossing, stood off in front of it (so that round-off cannot
    // leave the node behind); in a corner that step off may cross the other
    // obstacle, and the node then stays where the round began
    const Vec3 q = c.q + standoff(c.q) * c.n;
    if (earliest_crossing(o, x0, q, mo, s0, s_hit).k < 0) x0 = q, s_x0 = s_hit;
    x = x0 + (left * h) * v;
  }
  // Out of rounds, the node stays where it is on the last obstacle it touched:
  // carried with it to the substep's end (at rest: where it is). A node
  // resting on a turning obstacle gets here: its straight motion at the
  // surface's velocity cuts into the turning face, by r (w h)^3 / 3 (a
  // node on a door swung at 50 rad/s, 1 ms substeps, r = 0.1 m: 4 um), so
  // each round finds a crossing a little later; left where it stood, it was
  // passed by the door (MovingObstacles.ASwingingDoorDoesNotPassANode).
  if (round == kRounds) x = touched.obstacle >= 0 ? mo.to_world(touched.obstacle, mo.to_body(touched.obstacle, x0, s_x0), 1) : x0;
  return touched;
}

std::vector<std::int64_t> obstacle_nodes_behind(const Obstacles& o, std::span<const Real> x,
                                                std::span<const std::int32_t> nodes, const ObstacleMotion& mo) {
  std::vector<std::int64_t> out;
  for (const ObstaclePlane& p : o.planes) {
    std::int64_t n = 0;
    const auto k = static_cast<std::int32_t>(out.size());
    for (const std::int32_t i : nodes) n += dot(p.normal, mo.to_body(k, load3(x.data(), i), 0) - p.point) < 0;
    out.push_back(n);
  }
  for (const ObstacleMesh& m : o.meshes) {
    std::int64_t n = 0;
    const auto k = static_cast<std::int32_t>(out.size());
    if (!m.two_sided)
      for (const std::int32_t i : nodes)
        n += closest_triangle(m, mo.to_body(k, load3(x.data(), i), 0), m.grid.level[0].margin).behind;
    out.push_back(n);
  }
  return out;
}

Rot3 operator*(const Rot3& a, const Rot3& b) {
  Rot3 c;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      c.m[3 * i + j] = a.m[3 * i] * b.m[j] + a.m[3 * i + 1] * b.m[3 + j] + a.m[3 * i + 2] * b.m[6 + j];
  return c;
}

namespace {
Rot3 from_quaternion(const Eigen::Quaterniond& q) {
  const Eigen::Matrix3d r = q.normalized().toRotationMatrix();
  Rot3 out;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) out.m[3 * i + j] = r(i, j);
  return out;
}
Eigen::Quaterniond quaternion_from_vector(const Vec3& r) {
  const Real a = norm(r);
  if (!(a > 0)) return Eigen::Quaterniond::Identity();
  return Eigen::Quaterniond(Eigen::AngleAxisd(a, Eigen::Vector3d(r.x / a, r.y / a, r.z / a)));
}
Eigen::Quaterniond path_quaternion(const Path& p, Real time) {
  const std::size_t n = p.t.size();
  if (p.r.size() != 3 * n || n == 0) return Eigen::Quaterniond::Identity();
  if (time <= p.t[0]) return quaternion_from_vector(load3(p.r.data(), 0));
  if (time >= p.t[n - 1]) return quaternion_from_vector(load3(p.r.data(), static_cast<std::int64_t>(n - 1)));
  const auto j = static_cast<std::int64_t>(std::upper_bound(p.t.begin(), p.t.end(), time) - p.t.begin());  // t[j-1] <= time < t[j]
  const Real w = (time - p.t[static_cast<std::size_t>(j - 1)]) / (p.t[static_cast<std::size_t>(j)] - p.t[static_cast<std::size_t>(j - 1)]);
  return quaternion_from_vector(load3(p.r.data(), j - 1)).slerp(w, quaternion_from_vector(load3(p.r.data(), j)));
}
}  // namespace

Rot3 rotation_from_vector(const Vec3& r) {
  const Real a = norm(r);
  if (!(a > 0)) return {};
  const Vec3 k = (1 / a) * r;
  const Real c = std::cos(a), s = std::sin(a), v = 1 - c;
  Rot3 out;
  out.m[0] = c + k.x * k.x * v, out.m[1] = k.x * k.y * v - k.z * s, out.m[2] = k.x * k.z * v + k.y * s;
  out.m[3] = k.y * k.x * v + k.z * s, out.m[4] = c + k.y * k.y * v, out.m[5] = k.y * k.z * v - k.x * s;
  out.m[6] = k.z * k.x * v - k.y * s, out.m[7] = k.z * k.y * v + k.x * s, out.m[8] = c + k.z * k.z * v;
  return out;
}

Rot3 path_rotation(const Path& p, Real t) { return from_quaternion(path_quaternion(p, t)); }

Real path_max_angular_speed(const Path& p) {
  Real w = 0;
  if (p.r.size() != 3 * p.t.size()) return 0;
  for (std::size_t j = 1; j < p.t.size(); ++j) {
    const Real dt = p.t[j] - p.t[j - 1];
    const Eigen::AngleAxisd rel(quaternion_from_vector(load3(p.r.data(), static_cast<std::int64_t>(j - 1))).conjugate() *
                                quaternion_from_vector(load3(p.r.data(), static_cast<std::int64_t>(j))));
    if (dt > 0) w = std::max(w, std::abs(rel.angle()) / dt);
  }
  return w;
}

void obstacle_frames(const Obstacles& o, std::span<const Path> paths, Real t, Real h, std::vector<ObstacleFrame>& out) {
  out.clear();
  if (std::none_of(paths.begin(), paths.end(), [](const Path& p) { return !p.t.empty(); })) return;
  const auto n = static_cast<std::size_t>(obstacle_count(o));
  out.assign(n, ObstacleFrame{});
  const auto np = o.planes.size();
  for (std::size_t k = 0; k < std::min(n, paths.size()); ++k) {
    const Path& p = paths[k];
    ObstacleFrame& f = out[k];
    f.d0 = p.at(t);
    f.d1 = p.at(t + h);
    if (p.r.empty()) continue;
    f.rotates = true;
    f.pivot = k < np ? o.planes[k].pivot : o.meshes[k - np].pivot;
    const Eigen::Quaterniond q0 = path_quaternion(p, t), q1 = path_quaternion(p, t + h);
    f.r0 = from_quaternion(q0);
    const Eigen::AngleAxisd rel(q0.conjugate() * q1);  // R1 = R0 exp([w])
    Real angle = rel.angle();
    Eigen::Vector3d axis = rel.axis();
    if (angle > M_PI) angle -= 2 * M_PI;  // the short way
    f.w = {angle * axis.x(), angle * axis.y(), angle * axis.z()};
    f.r1 = f.r0 * rotation_from_vector(f.w);
  }
}

}  // namespace orthosim::runtime
