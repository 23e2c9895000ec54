#include "runtime/obstacles.h"

#include "libmodel/format/types.h"

#include <Eigen/Geometry>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <utility>

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
Real obstacle_standoff(const Vec3& x) { return standoff(x); }

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

// ---- the meshes' edges against the tissue's faces ---------------------------

TriangleProjection triangle_projection(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c, const Vec3& n, Real n2) {
  const Real wa = dot(cross(b - p, c - p), n), wb = dot(cross(c - p, a - p), n), wc = dot(cross(a - p, b - p), n);
  const Real tol = -1e-12 * n2;
  return {{wa / n2, wb / n2, wc / n2}, wa >= tol && wb >= tol && wc >= tol};
}

bool near_edge(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c, Real d) {
  const Vec3 e = p - closest_point_on_triangle(p, a, b, c);
  return dot(e, e) <= 2 * d * d;
}

Real default_edge_spacing(std::span<const std::int32_t> quads, std::span<const Real> x) {
  std::vector<Real> len;
  len.reserve(quads.size());
  for (std::size_t q = 0; q + 3 < quads.size(); q += 4)
    for (int k = 0; k < 4; ++k) len.push_back(norm(load3(x.data(), quads[q + static_cast<std::size_t>(k)]) - load3(x.data(), quads[q + static_cast<std::size_t>((k + 1) % 4)])));
  if (len.empty()) return 0;
  std::nth_element(len.begin(), len.begin() + static_cast<std::ptrdiff_t>(len.size() / 2), len.end());
  return Real(0.5) * len[len.size() / 2];
}

void sample_obstacle_edges(ObstacleMesh& m, Real spacing) {
  if (std::isnan(spacing) || std::isinf(spacing)) throw Error("", "obstacle mesh: the edge sample spacing must be finite");
  {
    m.samples.clear();
    m.sample_grid = NeighbourGrid{};
    if (!(spacing > 0)) return;
    const std::size_t nt = m.triangles.size() / 3;
    std::vector<std::pair<std::int32_t, std::int32_t>> edges;
    std::vector<std::int32_t> used;
    edges.reserve(3 * nt);
    for (std::size_t t = 0; t < nt; ++t)
      for (int k = 0; k < 3; ++k) {
        const std::int32_t a = m.triangles[3 * t + k], b = m.triangles[3 * t + (k + 1) % 3];
        edges.emplace_back(std::min(a, b), std::max(a, b));
        used.push_back(a);
      }
    std::sort(edges.begin(), edges.end());
    edges.erase(std::unique(edges.begin(), edges.end()), edges.end());
    std::sort(used.begin(), used.end());
    used.erase(std::unique(used.begin(), used.end()), used.end());
    std::int64_t total = static_cast<std::int64_t>(used.size());
    for (const auto& [a, b] : edges) {
      const Real len = norm(load3(m.vertices.data(), b) - load3(m.vertices.data(), a));
      total += static_cast<std::int64_t>(std::min<Real>(std::ceil(len / spacing), 1e8)) - 1;
      if (total > 10'000'000) {
        char text[32];
        std::snprintf(text, sizeof text, "%g", spacing);
        throw Error("", std::string("obstacle mesh: edge samples ") + text + " m apart would be more than 10^7 points");
      }
    }
    m.samples.reserve(3 * static_cast<std::size_t>(total));
    for (const std::int32_t v : used) m.samples.insert(m.samples.end(), &m.vertices[3 * static_cast<std::size_t>(v)], &m.vertices[3 * static_cast<std::size_t>(v)] + 3);
    for (const auto& [a, b] : edges) {
      const Vec3 pa = load3(m.vertices.data(), a), pb = load3(m.vertices.data(), b);
      const auto pieces = static_cast<int>(std::ceil(norm(pb - pa) / spacing));
      for (int j = 1; j < pieces; ++j) {
        const Vec3 q = pa + (static_cast<Real>(j) / pieces) * (pb - pa);
        m.samples.insert(m.samples.end(), {q.x, q.y, q.z});
      }
    }
    // their box and grid (the neighbour grid of the blood's particles, here over the samples)
    const std::size_t ns = m.samples.size() / 3;
    std::vector<Real> xyz[3];
    for (int a = 0; a < 3; ++a) xyz[a].resize(ns);
    for (std::size_t i = 0; i < ns; ++i)
      for (int a = 0; a < 3; ++a) xyz[a][i] = m.samples[3 * i + static_cast<std::size_t>(a)];
    m.samples_lo = {*std::min_element(xyz[0].begin(), xyz[0].end()), *std::min_element(xyz[1].begin(), xyz[1].end()),
                    *std::min_element(xyz[2].begin(), xyz[2].end())};
    m.samples_hi = {*std::max_element(xyz[0].begin(), xyz[0].end()), *std::max_element(xyz[1].begin(), xyz[1].end()),
                    *std::max_element(xyz[2].begin(), xyz[2].end())};
    build_neighbour_grid(xyz[0].data(), xyz[1].data(), xyz[2].data(), static_cast<std::int64_t>(ns), 2 * spacing, {0, 0, 0},
                         {0, 0, 0}, {false, false, false}, m.sample_grid);
  }
}

bool has_edge_samples(const Obstacles& o) {
  return std::any_of(o.meshes.begin(), o.meshes.end(), [](const ObstacleMesh& m) { return !m.samples.empty(); });
}

FaceContacts resolve_face_contacts(const Obstacles& o, const ObstacleMotion& mo, std::span<const std::int32_t> quads,
                                   std::span<const Real> x, std::span<Real> v, std::span<const Real> inv_mass, Real h,
                                   std::span<Real> impulse, FaceScratch& sc, std::vector<FaceRow>* rows,
                                   std::span<std::uint8_t> met) {
  FaceContacts out;
  if (rows) rows->clear();
  const auto n = static_cast<std::int64_t>(x.size() / 3);
  const std::size_t nq = quads.size() / 4;
  if (nq == 0 || !(h > 0)) return out;
  const auto np = static_cast<std::int32_t>(o.planes.size());
  const bool with_rows = rows != nullptr;
  auto corners = [&](std::size_t t, std::int32_t c[3]) {
    const auto q = quad_triangle(quads, static_cast<std::int32_t>(t));
    c[0] = q[0], c[1] = q[1], c[2] = q[2];
  };
  std::size_t met_first = 0;  // the mesh's first sample in `met`
  for (std::size_t mi = 0; mi < o.meshes.size(); ++mi) {
    const ObstacleMesh& mesh = o.meshes[mi];
    if (mesh.samples.empty()) continue;
    const auto k = np + static_cast<std::int32_t>(mi);
    const NeighbourGrid& g = mesh.sample_grid;
    const Vec3 glo = mesh.samples_lo, ghi = mesh.samples_hi;
    // the samples that met the faces in the last substep (in), and in this one (out)
    const std::size_t ns = mesh.samples.size() / 3;
    std::uint8_t* met_now = nullptr;
    const std::uint8_t* was_met = nullptr;
    if (met.size() >= met_first + ns) {
      met_now = met.data() + met_first;
      sc.met.assign(met_now, met_now + ns);
      std::fill(met_now, met_now + ns, 0);
      was_met = sc.met.data();
    }
    met_first += ns;

    // The meetings, as (sample, triangle) in sc.hits: each triangle where
    // the velocities put it at the substep's end, against the samples of the
    // grid cells its box over the substep (grown by how deep a sample may
    // meet it) covers; with rows, the samples that touch it too.
    auto find_meetings = [&] {
      sc.body0.resize(3 * static_cast<std::size_t>(n));
      sc.body1.resize(3 * static_cast<std::size_t>(n));
      for (std::int64_t i = 0; i < n; ++i) {  // the nodes in the mesh's frame at the substep's start and end
        const Vec3 xi = load3(x.data(), i);
        store3(sc.body0.data(), i, mo.to_body(k, xi, 0));
        store3(sc.body1.data(), i, mo.to_body(k, xi + h * load3(v.data(), i), 1));
      }
      sc.hits.clear();
      for (std::size_t t = 0; t < 2 * nq; ++t) {
        std::int32_t c[3];
        corners(t, c);
        const Vec3 a = load3(sc.body1.data(), c[0]), b = load3(sc.body1.data(), c[1]), cc = load3(sc.body1.data(), c[2]);
        const Vec3 a0 = load3(sc.body0.data(), c[0]), b0 = load3(sc.body0.data(), c[1]), c0 = load3(sc.body0.data(), c[2]);
        // how deep a sample meets it: within its thickness (half its shortest
        // edge), or no deeper than it moved relative to the mesh
        const Real motion = std::max({norm(a - a0), norm(b - b0), norm(cc - c0)}) + obstacle_reach(a);
        const Real thick = Real(0.5) * std::sqrt(std::min({dot(b - a, b - a), dot(cc - b, cc - b), dot(a - cc, a - cc)}));
        const Real depth = std::max(motion, thick);
        if (!(depth > 0)) continue;  // (a non-finite triangle)
        Real lo[3], hi[3];
        for (int d = 0; d < 3; ++d) {
          const Real e[6] = {(&a.x)[d], (&b.x)[d], (&cc.x)[d], (&a0.x)[d], (&b0.x)[d], (&c0.x)[d]};
          lo[d] = *std::min_element(e, e + 6) - depth, hi[d] = *std::max_element(e, e + 6) + depth;
        }
        if (lo[0] > ghi.x || lo[1] > ghi.y || lo[2] > ghi.z || hi[0] < glo.x || hi[1] < glo.y || hi[2] < glo.z) continue;
        const Vec3 nrm = cross(b - a, cc - a), nrm0 = cross(b0 - a0, c0 - a0);
        const Real n2 = dot(nrm, nrm), n20 = dot(nrm0, nrm0);
        if (!(n2 > 0)) continue;
        const Vec3 nh = (1 / std::sqrt(n2)) * nrm;
        // how far in front it takes a sample: touching it (within
        // obstacle_reach), or with rows within its motion (a candidate row)
        const Real front = with_rows ? std::max(obstacle_reach(a), motion) : obstacle_reach(a);
        std::int32_t r0[3], r1[3];
        for (int d = 0; d < 3; ++d) {
          r0[d] = static_cast<std::int32_t>(std::clamp<Real>(std::floor((lo[d] - g.origin[d]) / g.cell[d]), 0, g.dims[d] - 1));
          r1[d] = static_cast<std::int32_t>(std::clamp<Real>(std::floor((hi[d] - g.origin[d]) / g.cell[d]), 0, g.dims[d] - 1));
        }
        for (std::int32_t cz = r0[2]; cz <= r1[2]; ++cz)
          for (std::int32_t cy = r0[1]; cy <= r1[1]; ++cy) {
            // the row's cells cx = r0 .. r1 are consecutive in the sorted order
            const auto row = static_cast<std::size_t>((static_cast<std::int64_t>(cz) * g.dims[1] + cy) * g.dims[0]);
            for (std::int32_t q = g.start[row + static_cast<std::size_t>(r0[0])]; q < g.start[row + static_cast<std::size_t>(r1[0]) + 1]; ++q) {
              const std::int32_t id = g.order[static_cast<std::size_t>(q)];
              const Vec3 p = load3(mesh.samples.data(), id);
              const Real d1 = dot(nh, p - a);
              if (!(d1 <= front && d1 >= -depth)) continue;
              // a candidate (in front, beyond a touch) is a sample on the
              // surface, one that met or touched a face in the last substep:
              // where it slides from face to face (a sample coming in from
              // outside meets the faces in the face pass first)
              if (d1 > obstacle_reach(a) && !(was_met && was_met[id])) continue;
              // within it, or behind its edge: beyond its extent by no more
              // than it is behind its plane (the wedge behind a convex crease
              // of the surface, where no face's extent holds it)
              const bool within = triangle_projection(p, a, b, cc, nrm, n2).inside;
              if (!within && !(d1 < 0 && near_edge(p, a, b, cc, d1))) continue;
              // A sample that met the faces in the last substep (on the
              // surface) meets it within its thickness, if within it; any
              // other no deeper than the triangle moved, and not if it was
              // behind it (or its edge) at the start too (inside the tissue,
              // not entering it)
              const bool on_surface = was_met && was_met[id] && within;
              if (!on_surface || d1 < -thick) {
                if (!(d1 >= -motion)) continue;
                const Real d0 = n20 > 0 ? dot(nrm0, p - a0) / std::sqrt(n20) : 0;
                const bool front0 = n20 > 0 && d0 >= -obstacle_reach(p);
                const bool in0 = n20 > 0 && (triangle_projection(p, a0, b0, c0, nrm0, n20).inside || (d0 < 0 && near_edge(p, a0, b0, c0, d0)));
                if (in0 && !front0) continue;
              }
              sc.hits.insert(sc.hits.end(), {id, static_cast<std::int32_t>(t)});
              }
            }
      }
    };

    // One sweep over the meetings (sc.order), each in turn against the
    // velocities as the earlier ones left them; returns whether one moved a face.
    Vec3 total_impulse{};
    auto sweep_meetings = [&](bool first_sweep, bool first_round) {
      bool moved = false;
      if (first_sweep) sc.row_of.assign(sc.order.size(), -1);
      for (std::size_t o_j = 0; o_j < sc.order.size(); ++o_j) {
        const auto [id, t] = sc.order[o_j];
        std::int32_t c[3];
        corners(static_cast<std::size_t>(t), c);
        Vec3 y[3];
        for (int j = 0; j < 3; ++j) y[j] = mo.to_body(k, load3(x.data(), c[j]) + h * load3(v.data(), c[j]), 1);
        const Vec3 p = load3(mesh.samples.data(), id);
        const Vec3 nrm = cross(y[1] - y[0], y[2] - y[0]);
        const Real n2 = dot(nrm, nrm);
        if (!(n2 > 0)) continue;
        const Vec3 nh = (1 / std::sqrt(n2)) * nrm;
        const Real d = dot(nh, p - y[0]);
        if (!(d < 0) && !first_sweep) continue;  // an earlier meeting has moved it
        // a touch: on the surface, and with rows, holding the face; with
        // rows, a sample further in front (find_meetings took it within the
        // triangle's motion) is a candidate row, not a meeting
        const bool touch = d <= obstacle_reach(p);
        if (!touch && !(with_rows && first_sweep)) continue;
        TriangleProjection w = triangle_projection(p, y[0], y[1], y[2], nrm, n2);
        Real ws = 0;
        for (Real& wj : w.w) ws += (wj = std::max<Real>(wj, 0));
        if (!(ws > 0)) continue;
        Real W = 0, free_w = 0;
        for (int j = 0; j < 3; ++j) {
          w.w[j] /= ws;
          const Real im = inv_mass[static_cast<std::size_t>(c[j])];
          W += w.w[j] * w.w[j] * im;
          free_w += im > 0 ? w.w[j] : 0;
        }
        if (!(W > 0)) continue;  // all its nodes fixed
        const Vec3 nw = mo.normal_to_world(k, nh, 1);
        if (first_sweep) {
          if (with_rows) {
            FaceRow row;
            row.obstacle = k, row.sample = id, row.triangle = t;
            for (int j = 0; j < 3; ++j) row.node[j] = c[j], row.w[j] = w.w[j];
            row.n = -1 * nw;
            row.candidate = !touch;
            sc.row_of[o_j] = static_cast<std::int32_t>(rows->size());
            rows->push_back(row);
          }
          if (!touch) continue;
          if (met_now) met_now[id] = 1;
          if (first_round && (d < 0 || with_rows)) ++out.contacts;
        }
        if (!(d < 0)) continue;  // touching: held, not moved
        moved = true;
        // (a candidate an earlier meeting of this sweep brought behind the face meets it)
        if (!first_sweep && with_rows && sc.row_of[o_j] >= 0 && (*rows)[static_cast<std::size_t>(sc.row_of[o_j])].candidate) {
          (*rows)[static_cast<std::size_t>(sc.row_of[o_j])].candidate = false;
          if (met_now) met_now[id] = 1;
        }
        // the normal change: the point moves behind the sample by a standoff, over the substep
        const Real need = standoff(p) - d;
        auto apply = [&](const Vec3& change) {
          for (int j = 0; j < 3; ++j) {
            const Real im = inv_mass[static_cast<std::size_t>(c[j])];
            if (im > 0) store3(v.data(), c[j], load3(v.data(), c[j]) + (w.w[j] * im / W) * change);
          }
        };
        Vec3 dv = (-need / h) * nw;
        apply(dv);
        // friction on the point's velocity relative to the mesh's surface there
        const Vec3 u = mo.velocity(k, mo.to_world(k, p, 1), 1, h);
        Vec3 vp{};
        for (int j = 0; j < 3; ++j) vp += w.w[j] * load3(v.data(), c[j]);
        const Vec3 vr = vp - u, vt = vr - dot(vr, nw) * nw;
        const Real st = norm(vt);
        if (st > 0) {
          const Vec3 dvt = (-std::min(Real(1), mesh.friction * (need / h) / st)) * vt;
          apply(dvt);
          dv += dvt;
        }
        // the tissue's momentum change: sum m_j dv_j = (free weights / W) dv
        const Vec3 imp = (free_w / W) * dv;
        total_impulse += imp;
        if (with_rows && sc.row_of[o_j] >= 0) (*rows)[static_cast<std::size_t>(sc.row_of[o_j])].impulse -= dot(imp, nw);
        out.work += dot(imp, u);
      }
      return moved;
    };

    // Rounds of finding the meetings and resolving them in Gauss-Seidel
    // sweeps (by sample, then triangle) until no sweep moves a face (a
    // meeting moves nodes that others' triangles share), at most kSweeps; a
    // round's corrections may bring a sample behind a triangle it did not
    // meet (a neighbour of one it met), which the next round finds, at most
    // kRounds. The first sweep of a round records the rows and what met, the
    // first round's counts the meetings.
    constexpr int kRounds = 4, kSweeps = 8;
    for (int round = 0; round < kRounds; ++round) {
      find_meetings();
      if (sc.hits.empty()) break;
      sc.order.resize(sc.hits.size() / 2);
      for (std::size_t j = 0; j < sc.order.size(); ++j) sc.order[j] = {sc.hits[2 * j], sc.hits[2 * j + 1]};
      std::sort(sc.order.begin(), sc.order.end());
      bool moved = false;
      for (int sweep = 0; sweep < kSweeps; ++sweep) {
        if (!sweep_meetings(sweep == 0, round == 0)) break;
        moved = true;
      }
      if (!moved) break;
    }
    if (impulse.size() >= 3 * static_cast<std::size_t>(k + 1)) store3(impulse.data(), k, load3(impulse.data(), k) + total_impulse);
  }
  if (rows && !rows->empty()) {
    // one row per (mesh, sample, triangle): a later round's finds the same
    // meeting again (its geometry the later one's, the impulses summed)
    std::stable_sort(rows->begin(), rows->end(), [](const FaceRow& a, const FaceRow& b) { return a.key() < b.key(); });
    std::size_t kept = 0;
    for (std::size_t j = 0; j < rows->size(); ++j) {
      FaceRow& r = (*rows)[j];
      if (kept > 0 && (*rows)[kept - 1].key() == r.key()) {
        r.impulse += (*rows)[kept - 1].impulse;
        r.candidate = r.candidate && (*rows)[kept - 1].candidate;
        (*rows)[kept - 1] = r;
      } else {
        (*rows)[kept++] = r;
      }
    }
    rows->resize(kept);
  }
  return out;
}

}  // namespace orthosim::runtime
