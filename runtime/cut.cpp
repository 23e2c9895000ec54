#include "runtime/cut.h"

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <numeric>
#include <optional>
#include <utility>

namespace orthosim::runtime {

namespace {

bool finite(const Vec3& v) { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }

struct Box {
  Vec3 lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
  void add(const Vec3& p) {
    lo = {std::min(lo.x, p.x), std::min(lo.y, p.y), std::min(lo.z, p.z)};
    hi = {std::max(hi.x, p.x), std::max(hi.y, p.y), std::max(hi.z, p.z)};
  }
  // the segment p q's box, grown by `margin`, misses this one
  bool misses(const Vec3& p, const Vec3& q, Real margin = 0) const {
    return std::max(p.x, q.x) + margin < lo.x || std::min(p.x, q.x) - margin > hi.x || std::max(p.y, q.y) + margin < lo.y ||
           std::min(p.y, q.y) - margin > hi.y || std::max(p.z, q.z) + margin < lo.z || std::min(p.z, q.z) - margin > hi.z;
  }
};

bool crosses(const Vec3& p, const Vec3& q, const Vec3& a, const Vec3& b, const Vec3& c, Real* t_out, bool open_ac,
             bool open_bc, bool touch = false, Real snap_p = 0, Real snap_q = 0);

// the blade: two triangles per polyline segment. Its two end edges (the
// polyline's first and last point swept along the direction) are open: a
// spring that meets the blade only there, at a node the polyline ends on,
// runs beside the slit's end rather than across it (closed, the wound ran a
// quad past a snapped end).
struct Blade {
  std::vector<std::array<Vec3, 3>> tris;
  std::vector<std::array<bool, 2>> open;  // per triangle: edge a c, edge b c
  Box box;
  bool crosses(const Vec3& p, const Vec3& q, Real* t = nullptr) const {
    if (box.misses(p, q)) return false;
    for (std::size_t i = 0; i < tris.size(); ++i)
      if (runtime::crosses(p, q, tris[i][0], tris[i][1], tris[i][2], t, open[i][0], open[i][1])) return true;
    return false;
  }
  // a segment between two nodes, each end within its snap distance (m) of a
  // triangle's plane counting as on it (CutDef::node_snap); touch: an end on
  // the blade counts too (both sides' columns of a slit through nodes)
  bool severs(const Vec3& p, const Vec3& q, Real snap_p, Real snap_q, bool touch = false) const {
    if (box.misses(p, q, std::max(snap_p, snap_q))) return false;  // an end snapped onto the blade may lie outside its box
    for (std::size_t i = 0; i < tris.size(); ++i)
      if (runtime::crosses(p, q, tris[i][0], tris[i][1], tris[i][2], nullptr, open[i][0], open[i][1], touch, snap_p, snap_q))
        return true;
    return false;
  }
};

Blade make_blade(const CutDef& def, const Vec3& d) {
  Blade b;
  const Vec3 back = (-def.lead * def.depth) * d, deep = def.depth * d;
  for (std::size_t i = 0; i + 1 < def.polyline.size(); ++i) {
    const Vec3 p0 = def.polyline[i] + back, p1 = def.polyline[i + 1] + back;
    const Vec3 q0 = def.polyline[i] + deep, q1 = def.polyline[i + 1] + deep;
    const bool last = i + 2 == def.polyline.size();
    b.tris.push_back({p0, p1, q1});  // edge b c: p1 q1, the end edge of the last segment
    b.open.push_back({false, last});
    b.tris.push_back({p0, q1, q0});  // edge a c: p0 q0, the start edge of the first segment
    b.open.push_back({i == 0, false});
    for (const Vec3& p : {p0, p1, q0, q1}) b.box.add(p);
  }
  return b;
}

Real orient(const Vec3& a, const Vec3& b, const Vec3& c, const Vec3& d) { return dot(cross(b - a, c - a), d - a); }

// p in tetrahedron a b c d (either orientation; its faces count as inside)
bool in_tet(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c, const Vec3& d) {
  const Real v = orient(a, b, c, d);
  if (!(std::abs(v) > 0)) return false;
  const Real s[4] = {orient(p, b, c, d), orient(a, p, c, d), orient(a, b, p, d), orient(a, b, c, p)};
  const Real tol = -1e-12 * std::abs(v);
  for (Real x : s)
    if (x * (v > 0 ? 1 : -1) < tol) return false;
  return true;
}

// p in the column's hexahedron (top t, bottom b; six tetrahedra of two prisms)
bool in_column(const Vec3& p, const std::array<Vec3, 4>& t, const std::array<Vec3, 4>& b) {
  for (const auto& [i, j, k] : {std::array<int, 3>{0, 1, 2}, std::array<int, 3>{0, 2, 3}})
    if (in_tet(p, t[i], t[j], t[k], b[i]) || in_tet(p, t[j], t[k], b[i], b[j]) || in_tet(p, t[k], b[i], b[j], b[k]))
      return true;
  return false;
}

// the top t and bottom b corners of column (l, k) at the positions pos(node)
template <class Pos>
void column_corners(const WoundColumns& w, std::int32_t l, std::int32_t k, const Pos& pos, std::array<Vec3, 4>& t,
                    std::array<Vec3, 4>& b) {
  for (int c = 0; c < 4; ++c) t[c] = pos(w.corner(l, k, c)), b[c] = pos(w.corner(l + 1, k, c));
}

}  // namespace

WoundColumns wound_columns(const Model& m) {
  WoundColumns w;
  if (m.n_quads == 0 || m.node_layer.size() != static_cast<std::size_t>(m.n_nodes)) return w;
  // quads by layer, in the model's order
  std::vector<std::vector<std::int32_t>> by_layer(m.layers.size());
  for (std::int32_t q = 0; q < m.n_quads; ++q) {
    const std::int32_t* v = &m.quads[4 * static_cast<std::size_t>(q)];
    const int l = m.node_layer[static_cast<std::size_t>(v[0])];
    if (l < 0 || static_cast<std::size_t>(l) >= m.layers.size()) return w;
    for (int c = 1; c < 4; ++c)
      if (m.node_layer[static_cast<std::size_t>(v[c])] != l) return w;  // a quad across layers: not the builder's
    by_layer[static_cast<std::size_t>(l)].push_back(q);
  }
  std::vector<std::size_t> surfaces;
  for (std::size_t l = 0; l < m.layers.size(); ++l)
    if (!by_layer[l].empty()) surfaces.push_back(l);
  std::stable_sort(surfaces.begin(), surfaces.end(),
                   [&](std::size_t a, std::size_t b) { return m.layers[a].order < m.layers[b].order; });
  if (surfaces.size() < 2) return w;
  const std::size_t nq = by_layer[surfaces[0]].size();
  for (std::size_t s : surfaces)
    if (by_layer[s].size() != nq) return w;
  // one pattern: the same corners relative to each layer's first node
  const auto& first = by_layer[surfaces[0]];
  const std::int32_t base0 = m.layers[surfaces[0]].first;
  for (std::size_t s : surfaces) {
    const std::int32_t base = m.layers[s].first;
    for (std::size_t k = 0; k < nq; ++k)
      for (int c = 0; c < 4; ++c)
        if (m.quads[4 * static_cast<std::size_t>(by_layer[s][k]) + c] - base !=
            m.quads[4 * static_cast<std::size_t>(first[k]) + c] - base0)
          return w;
  }
  w.n_surfaces = static_cast<std::int32_t>(surfaces.size());
  w.n_quads = static_cast<std::int32_t>(nq);
  for (std::size_t s : surfaces)
    for (std::int32_t q : by_layer[s]) w.corners.insert(w.corners.end(), &m.quads[4 * static_cast<std::size_t>(q)], &m.quads[4 * static_cast<std::size_t>(q)] + 4);
  // sides shared by two quads of the pattern
  std::map<std::pair<std::int32_t, std::int32_t>, std::vector<std::int32_t>> sides;  // edge -> 4 k + c
  for (std::int32_t k = 0; k < w.n_quads; ++k)
    for (int c = 0; c < 4; ++c) {
      const std::int32_t a = w.corner(0, k, c), b = w.corner(0, k, (c + 1) % 4);
      sides[{std::min(a, b), std::max(a, b)}].push_back(4 * k + c);
    }
  w.neighbour.assign(4 * nq, -1);
  for (const auto& [edge, at] : sides)
    if (at.size() == 2) {
      w.neighbour[static_cast<std::size_t>(at[0])] = at[1] / 4;
      w.neighbour[static_cast<std::size_t>(at[1])] = at[0] / 4;
    }
  w.open.assign(static_cast<std::size_t>(w.n_surfaces - 1) * nq, 0);
  return w;
}

std::vector<std::int32_t> wound_wall_triangles(const WoundColumns& w) {
  std::vector<std::int32_t> tri;
  if (!w.valid()) return tri;
  const std::int32_t ns = w.n_surfaces, nq = w.n_quads;
  auto open = [&](std::int32_t l, std::int32_t k) { return w.open[static_cast<std::size_t>(l) * nq + k] != 0; };
  auto quad = [&](std::int32_t a, std::int32_t b, std::int32_t c, std::int32_t d) { tri.insert(tri.end(), {a, b, c, a, c, d}); };
  for (std::int32_t l = 0; l < ns; ++l)
    for (std::int32_t k = 0; k < nq; ++k) {
      // the skin: a wall over a closed column; the last surface: always a wall
      // (the wound's floor, the bone); between two columns: a wall where one
      // is open and the other closed (inside closed tissue the blood never
      // is, and a quad there took the closest-triangle query from the wound's
      // side wall at its edge: the blood crossed the side wall there)
      const bool above = l == 0 || open(l - 1, k), below = l + 1 < ns && open(l, k);
      if (l + 1 < ns && above == below) continue;
      quad(w.corner(l, k, 0), w.corner(l, k, 1), w.corner(l, k, 2), w.corner(l, k, 3));
    }
  for (std::int32_t l = 0; l + 1 < ns; ++l)
    for (std::int32_t k = 0; k < nq; ++k)
      for (int c = 0; c < 4; ++c) {
        const std::int32_t nb = w.neighbour[4 * static_cast<std::size_t>(k) + c];
        if (nb >= 0 && !(open(l, k) && !open(l, nb))) continue;
        const int d = (c + 1) % 4;
        quad(w.corner(l, k, c), w.corner(l, k, d), w.corner(l + 1, k, d), w.corner(l + 1, k, c));
      }
  return tri;
}

namespace {

// segment_crosses_triangle, with the triangle's edge a c (u = 0) and its edge
// b c (u + v = 1) optionally left out (open); with touch, an end on the
// triangle's plane (the other end off it) counts as crossing
bool crosses(const Vec3& p, const Vec3& q, const Vec3& a, const Vec3& b, const Vec3& c, Real* t_out, bool open_ac,
             bool open_bc, bool touch, Real snap_p, Real snap_q) {
  // Half-open: the ends' sides of the triangle's plane must differ, a point
  // on the plane counting as behind it. So of the springs of a node the blade
  // passes through, only those to the front are crossed: the node stays with
  // the tissue behind the blade (closed intervals cut both sides' springs and
  // opened the quads on both sides, a zigzag along a polyline through nodes).
  // The side of a point is one orientation sign per triangle, the same for
  // every segment that ends there. Coplanar triangles of the blade agree when
  // the point lies exactly in their plane, as the nodes of a grid line do.
  Real sp = orient(a, b, c, p), sq = orient(a, b, c, q);
  // node snapping: an end within its snap distance of the plane is on it
  // (orient is the signed distance times |(b - a) x (c - a)|)
  const Vec3* snapped = nullptr;
  if (snap_p > 0 || snap_q > 0) {
    const Real area2 = norm(cross(b - a, c - a));
    if (sp != 0 && std::abs(sp) <= snap_p * area2) sp = 0, snapped = &p;
    if (sq != 0 && std::abs(sq) <= snap_q * area2) sq = 0, snapped = snapped ? nullptr : &q;
  }
  if (touch ? (sp > 0 && sq > 0) || (sp < 0 && sq < 0) || (sp == 0 && sq == 0)
            : (sp > 0) == (sq > 0))
    return false;  // one side, or parallel, or a degenerate triangle (both 0)
  const Vec3 dir = q - p, e1 = b - a, e2 = c - a;
  if (snapped) {
    // the segment meets the blade where the snapped end lies on it: its
    // projection, not the line's crossing (which a segment slanted to the
    // blade puts beyond its end)
    const Vec3 w = *snapped - a;
    const Real d00 = dot(e1, e1), d01 = dot(e1, e2), d11 = dot(e2, e2), d20 = dot(w, e1), d21 = dot(w, e2);
    const Real den = d00 * d11 - d01 * d01;
    if (!(den > 0)) return false;  // a degenerate triangle
    const Real u = (d11 * d20 - d01 * d21) / den, v = (d00 * d21 - d01 * d20) / den;
    if (u < 0 || u > 1 || (open_ac && !(u > 0))) return false;
    if (v < 0 || u + v > 1 || (open_bc && !(u + v < 1))) return false;
    if (t_out) *t_out = snapped == &p ? 0 : 1;
    return true;
  }
  const Vec3 h = cross(dir, e2);
  const Real det = dot(e1, h);
  const Real scale = norm(e1) * norm(e2) * norm(dir);
  if (!(std::abs(det) > 1e-14 * scale)) return false;  // (nearly) parallel, or a degenerate triangle or segment
  const Real inv = 1 / det;
  const Vec3 s = p - a;
  const Real u = inv * dot(s, h);
  if (u < 0 || u > 1 || (open_ac && !(u > 0))) return false;
  const Vec3 qv = cross(s, e1);
  const Real v = inv * dot(dir, qv);
  if (v < 0 || u + v > 1 || (open_bc && !(u + v < 1))) return false;
  if (t_out) *t_out = std::clamp(sp / (sp - sq), Real(0), Real(1));
  return true;
}

}  // namespace

bool segment_crosses_triangle(const Vec3& p, const Vec3& q, const Vec3& a, const Vec3& b, const Vec3& c, Real* t_out) {
  return crosses(p, q, a, b, c, t_out, false, false);
}

void validate(const CutDef& def) {
  if (def.polyline.size() < 2) throw Error("", "cut: the polyline needs at least 2 points");
  Real length = 0;
  for (std::size_t i = 0; i < def.polyline.size(); ++i) {
    if (!finite(def.polyline[i])) throw Error("", "cut: polyline point " + std::to_string(i) + " is not finite");
    if (i > 0) length += norm(def.polyline[i] - def.polyline[i - 1]);
  }
  if (!(length > 0)) throw Error("", "cut: the polyline has zero length");
  if (!(def.depth > 0) || !std::isfinite(def.depth)) throw Error("", "cut: depth must be > 0 m");
  if (!(def.lead >= 0 && def.lead <= 1)) throw Error("", "cut: lead must be in [0, 1]");
  if (!finite(def.direction)) throw Error("", "cut: direction is not finite");
  if (!(def.node_snap >= 0 && def.node_snap < 0.5)) throw Error("", "cut: node_snap must be in [0, 0.5)");
}

namespace {

// The limb's axis from its quad grids, where they show one: the quads' edges
// along the limb (a -> d and b -> c of quad a, b, c, d, or a -> b and d -> c)
// all point one way, the edges around it turn with the ring. Of the two edge
// families, the one whose scatter matrix is nearly one-dimensional (largest
// eigenvalue >= 0.8 of the trace) while the other's is not (<= 0.7) runs
// along the limb: its principal direction. Else (no quads, a flat block
// whose both families are straight, mixed corner orders) none.
std::optional<Eigen::Vector3d> axis_from_quads(const Model& m) {
  if (m.n_quads < 8) return std::nullopt;
  Eigen::Matrix3d s1 = Eigen::Matrix3d::Zero(), s2 = Eigen::Matrix3d::Zero();
  auto at = [&](std::int32_t i) {
    return Eigen::Vector3d(m.rest_x[3 * static_cast<std::size_t>(i)], m.rest_x[3 * static_cast<std::size_t>(i) + 1],
                           m.rest_x[3 * static_cast<std::size_t>(i) + 2]);
  };
  for (std::int32_t q = 0; q < m.n_quads; ++q) {
    const std::int32_t* v = m.quads.data() + 4 * static_cast<std::size_t>(q);
    const Eigen::Vector3d a = at(v[0]), b = at(v[1]), c = at(v[2]), d = at(v[3]);
    for (const Eigen::Vector3d& e : {Eigen::Vector3d(b - a), Eigen::Vector3d(c - d)}) s1 += e * e.transpose();
    for (const Eigen::Vector3d& e : {Eigen::Vector3d(d - a), Eigen::Vector3d(c - b)}) s2 += e * e.transpose();
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> e1(s1), e2(s2);
  const double f1 = e1.eigenvalues()(2) / std::max(s1.trace(), 1e-300);
  const double f2 = e2.eigenvalues()(2) / std::max(s2.trace(), 1e-300);
  if (f1 >= 0.8 && f2 <= 0.7) return Eigen::Vector3d(e1.eigenvectors().col(2));
  if (f2 >= 0.8 && f1 <= 0.7) return Eigen::Vector3d(e2.eigenvectors().col(2));
  return std::nullopt;
}

}  // namespace

Vec3 cut_direction(const Model& m, const CutDef& def) {
  validate(def);
  if (norm(def.direction) > 0) return (1 / norm(def.direction)) * def.direction;
  const std::int64_t n = m.n_nodes;
  if (n == 0) throw Error("", "cut: the model has no nodes");
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  for (std::int64_t i = 0; i < n; ++i) c += Eigen::Vector3d(m.rest_x[3 * i], m.rest_x[3 * i + 1], m.rest_x[3 * i + 2]);
  c /= static_cast<double>(n);
  // the limb's axis: its quad grids' (a short, wide limb's principal axis of
  // the rest positions lies across it: the blade ran along the skin, beside
  // the vessels; sweep of 2026-11-27), else the principal axis of the rest positions
  Eigen::Vector3d axis;
  if (const auto q = axis_from_quads(m)) {
    axis = *q;
  } else {
    Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
    for (std::int64_t i = 0; i < n; ++i) {
      const Eigen::Vector3d r = Eigen::Vector3d(m.rest_x[3 * i], m.rest_x[3 * i + 1], m.rest_x[3 * i + 2]) - c;
      cov += r * r.transpose();
    }
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);
    axis = es.eigenvectors().col(2);
  }
  // the path's midpoint (its segments' midpoints weighted by their lengths):
  // the mean of the points moved with a repeated point, and the same path cut
  // one vessel or two
  Vec3 mid{0, 0, 0};
  Real length = 0;
  for (std::size_t i = 0; i + 1 < def.polyline.size(); ++i) {
    const Real l = norm(def.polyline[i + 1] - def.polyline[i]);
    mid += (Real(0.5) * l) * (def.polyline[i] + def.polyline[i + 1]);
    length += l;
  }
  mid = (1 / length) * mid;  // > 0: validate refuses a zero-length polyline
  const Eigen::Vector3d mm(mid.x, mid.y, mid.z);
  const Eigen::Vector3d foot = c + (mm - c).dot(axis) * axis;
  const Eigen::Vector3d d = foot - mm;
  if (!(d.norm() > 1e-12 * (1 + mm.norm())))
    throw Error("", "cut: the polyline lies on the model's axis: give the blade a direction");
  const Eigen::Vector3d u = d.normalized();
  return {u.x(), u.y(), u.z()};
}

std::int32_t open_columns_at(WoundColumns& w, std::span<const Real> x, const std::vector<Vec3>& points) {
  if (!w.valid() || points.empty()) return 0;
  const std::int32_t nq = w.n_quads;
  auto pos = [&](std::int32_t i) { return load3(x.data(), i); };
  std::int32_t opened = 0;
  for (const Vec3& p : points) {
    std::int32_t best_l = -1, best_k = -1;
    Real best = 1e300;
    bool inside = false;
    for (std::int32_t l = 0; l + 1 < w.n_surfaces && !inside; ++l)
      for (std::int32_t k = 0; k < nq; ++k) {
        std::array<Vec3, 4> t, b;
        column_corners(w, l, k, pos, t, b);
        Box box;
        Vec3 mid{0, 0, 0};
        for (int c = 0; c < 4; ++c) box.add(t[c]), box.add(b[c]), mid += t[c], mid += b[c];
        mid = Real(0.125) * mid;
        if (!box.misses(p, p) && in_column(p, t, b)) {
          best_l = l, best_k = k, inside = true;
          break;
        }
        // else the nearest column whose corners' sphere holds the point
        Real r2 = 0;
        for (int c = 0; c < 4; ++c) r2 = std::max({r2, dot(t[c] - mid, t[c] - mid), dot(b[c] - mid, b[c] - mid)});
        const Real d2 = dot(p - mid, p - mid);
        if (d2 <= r2 && d2 < best) best = d2, best_l = l, best_k = k;
      }
    if (best_l < 0) continue;
    std::uint8_t& o = w.open[static_cast<std::size_t>(best_l) * nq + best_k];
    if (!o) ++opened;
    o = 1;
  }
  return opened;
}

Carried carry_points(const Model& m, std::span<const Real> points, int k) {
  Carried c;
  const std::size_t n = points.size() / 3;
  c.k = static_cast<int>(std::min<std::int64_t>(k, m.n_nodes));
  c.rest.assign(points.begin(), points.begin() + static_cast<std::ptrdiff_t>(3 * n));
  if (c.k <= 0 || n == 0) return c;
  const auto kk = static_cast<std::size_t>(c.k);
  c.node.resize(n * kk);
  c.weight.resize(n * kk);
  // The nodes binned in a grid of cubes (about 8 nodes a cube where they were
  // spread evenly through their box): each point's k nearest are found ring by
  // ring, exactly (the same nodes as a scan of them all, ties by index), in
  // time that does not grow with the model (a scan of every node was 10^9
  // distance tests for a 5 000-node tree in a 400 x 100 grid's 240 000 nodes).
  Box box;
  for (std::int32_t i = 0; i < m.n_nodes; ++i) box.add(load3(m.rest_x.data(), i));
  const Vec3 ext = box.hi - box.lo;
  const Real vol = std::max(ext.x, Real(1e-12)) * std::max(ext.y, Real(1e-12)) * std::max(ext.z, Real(1e-12));
  const Real diag = std::max(norm(ext), Real(1e-12));
  const Real h = std::clamp(2 * std::cbrt(vol / static_cast<Real>(m.n_nodes)), diag / 256, diag);
  const std::array<int, 3> dim{static_cast<int>(ext.x / h) + 1, static_cast<int>(ext.y / h) + 1, static_cast<int>(ext.z / h) + 1};
  auto cell_of = [&](const Vec3& p, int a) {
    const Real u = ((a == 0 ? p.x - box.lo.x : a == 1 ? p.y - box.lo.y : p.z - box.lo.z)) / h;
    return static_cast<int>(std::floor(std::clamp(u, Real(-1e6), Real(1e6))));
  };
  auto lin = [&](int x, int y, int z) {
    return (static_cast<std::size_t>(z) * static_cast<std::size_t>(dim[1]) + static_cast<std::size_t>(y)) *
               static_cast<std::size_t>(dim[0]) + static_cast<std::size_t>(x);
  };
  std::vector<std::int32_t> start(static_cast<std::size_t>(dim[0]) * dim[1] * dim[2] + 1, 0), order(static_cast<std::size_t>(m.n_nodes));
  std::vector<std::size_t> cell(static_cast<std::size_t>(m.n_nodes));
  for (std::int32_t i = 0; i < m.n_nodes; ++i) {
    const Vec3 r = load3(m.rest_x.data(), i);
    cell[static_cast<std::size_t>(i)] = lin(std::clamp(cell_of(r, 0), 0, dim[0] - 1), std::clamp(cell_of(r, 1), 0, dim[1] - 1),
                                            std::clamp(cell_of(r, 2), 0, dim[2] - 1));
    ++start[cell[static_cast<std::size_t>(i)] + 1];
  }
  std::partial_sum(start.begin(), start.end(), start.begin());
  {
    std::vector<std::int32_t> fill(start.begin(), start.end() - 1);
    for (std::int32_t i = 0; i < m.n_nodes; ++i) order[static_cast<std::size_t>(fill[cell[static_cast<std::size_t>(i)]]++)] = i;
  }
  std::vector<std::pair<Real, std::int32_t>> d2;
  for (std::size_t p = 0; p < n; ++p) {
    const Vec3 q = load3(points.data(), static_cast<std::int64_t>(p));
    const int qc[3] = {cell_of(q, 0), cell_of(q, 1), cell_of(q, 2)};
    int last = 0;  // the ring after which every cell has been seen
    for (int a = 0; a < 3; ++a) last = std::max({last, std::abs(qc[a]), std::abs(dim[static_cast<std::size_t>(a)] - 1 - qc[a])});
    d2.clear();
    for (int ring = 0; ring <= last; ++ring) {
      for (int z = std::max(qc[2] - ring, 0); z <= std::min(qc[2] + ring, dim[2] - 1); ++z)
        for (int y = std::max(qc[1] - ring, 0); y <= std::min(qc[1] + ring, dim[1] - 1); ++y)
          for (int x = std::max(qc[0] - ring, 0); x <= std::min(qc[0] + ring, dim[0] - 1); ++x) {
            if (std::max({std::abs(x - qc[0]), std::abs(y - qc[1]), std::abs(z - qc[2])}) != ring) continue;
            const std::size_t l = lin(x, y, z);
            for (std::int32_t o = start[l]; o < start[l + 1]; ++o) {
              const std::int32_t i = order[static_cast<std::size_t>(o)];
              const Vec3 r = load3(m.rest_x.data(), i) - q;
              d2.push_back({dot(r, r), i});
            }
          }
      // every node within ring h of q has been seen (a node clamped into the
      // grid's edge cells lies beyond them, so no nearer than its cell says)
      if (d2.size() >= kk) {
        std::nth_element(d2.begin(), d2.begin() + static_cast<std::ptrdiff_t>(kk - 1), d2.end());
        const Real reach = ring * h;
        if (d2[kk - 1].first <= reach * reach) break;
      }
    }
    // the k nearest, ties by index: the same choice on every machine
    std::partial_sort(d2.begin(), d2.begin() + static_cast<std::ptrdiff_t>(kk), d2.end());
    // s^2: a hundredth of the distance to the k-th nearest, squared
    const Real s2 = 1e-4 * d2[kk - 1].first + std::numeric_limits<Real>::min();
    Real sum = 0;
    for (std::size_t j = 0; j < kk; ++j) sum += 1 / (d2[j].first + s2);
    for (std::size_t j = 0; j < kk; ++j) {
      c.node[p * kk + j] = d2[j].second;
      c.weight[p * kk + j] = (1 / (d2[j].first + s2)) / sum;
    }
  }
  return c;
}

std::vector<Real> carried_positions(const Carried& c, const Model& m, std::span<const Real> x) {
  std::vector<Real> out(c.rest);
  const std::size_t n = c.rest.size() / 3, kk = static_cast<std::size_t>(c.k);
  for (std::size_t p = 0; p < n; ++p)
    for (std::size_t j = 0; j < kk; ++j) {
      const auto i = static_cast<std::size_t>(c.node[p * kk + j]);
      const Real w = c.weight[p * kk + j];
      for (std::size_t a = 0; a < 3; ++a) {
        const Real u = x[3 * i + a] - m.rest_x[3 * i + a];
        if (std::isfinite(u)) out[3 * p + a] += w * u;  // a non-finite node (never in a healthy state) does not carry
      }
    }
  return out;
}

CutReport cut_model(Model& m, std::span<const Real> x, const CutDef& def, WoundColumns* columns,
                    std::span<const std::vector<Real>> vessel_x) {
  CutReport rep;
  rep.direction = cut_direction(m, def);
  if (x.size() != 3 * static_cast<std::size_t>(m.n_nodes)) throw Error("", "cut: positions do not match the model");
  const Blade blade = make_blade(def, rep.direction);
  auto pos = [&](std::int32_t i) {
    const Vec3 p = load3(x.data(), i);
    // a non-finite position (never in a healthy state) falls back to rest
    return finite(p) ? p : load3(m.rest_x.data(), i);
  };

  // nodes with springs before the cut, and each node's snap distance:
  // node_snap x the rest length of its shortest spring in the uncut model
  std::vector<std::uint8_t> had(static_cast<std::size_t>(m.n_nodes), 0);
  for (std::int32_t s = 0; s < m.n_springs; ++s) had[m.spring_a[s]] = had[m.spring_b[s]] = 1;
  std::vector<Real> snap(static_cast<std::size_t>(m.n_nodes), 0);
  if (m.shortest_spring.size() == snap.size())
    for (std::size_t i = 0; i < snap.size(); ++i) snap[i] = def.node_snap * m.shortest_spring[i];
  auto severs = [&](std::int32_t i, std::int32_t j, bool touch = false) {
    return blade.severs(pos(i), pos(j), snap[static_cast<std::size_t>(i)], snap[static_cast<std::size_t>(j)], touch);
  };

  // springs
  std::size_t keep = 0;
  const auto ns = static_cast<std::size_t>(m.n_springs);
  for (std::size_t s = 0; s < ns; ++s) {
    if (severs(m.spring_a[s], m.spring_b[s])) continue;
    m.spring_a[keep] = m.spring_a[s];
    m.spring_b[keep] = m.spring_b[s];
    m.spring_rest[keep] = m.spring_rest[s];
    m.spring_k[keep] = m.spring_k[s];
    m.spring_c[keep] = m.spring_c[s];
    m.spring_tension[keep] = m.spring_tension[s];
    ++keep;
  }
  rep.springs_cut = static_cast<std::int32_t>(ns - keep);
  for (auto* v : {&m.spring_a, &m.spring_b}) v->resize(keep);
  for (auto* v : {&m.spring_rest, &m.spring_k, &m.spring_c}) v->resize(keep);
  m.spring_tension.resize(keep);
  m.n_springs = static_cast<std::int32_t>(keep);

  // the volume term: a group of tetrahedra with an edge across the blade goes too
  std::size_t tkeep = 0;
  std::vector<std::int32_t> first{0};
  for (std::int32_t g = 0; g < m.n_groups; ++g) {
    const std::int32_t t0 = m.tet_group_first[g], t1 = m.tet_group_first[g + 1];
    bool cut = false;
    for (std::int32_t t = t0; t < t1 && !cut; ++t) {
      const std::int32_t* c = &m.tet[4 * static_cast<std::size_t>(t)];
      for (int i = 0; i < 4 && !cut; ++i)
        for (int j = i + 1; j < 4 && !cut; ++j) cut = severs(c[i], c[j]);
    }
    if (cut) continue;
    for (std::int32_t t = t0; t < t1; ++t, ++tkeep) {
      std::copy_n(&m.tet[4 * static_cast<std::size_t>(t)], 4, &m.tet[4 * tkeep]);
      m.tet_k[tkeep] = m.tet_k[static_cast<std::size_t>(t)];
      m.tet_guard[tkeep] = m.tet_guard[static_cast<std::size_t>(t)];
    }
    first.push_back(static_cast<std::int32_t>(tkeep));
  }
  rep.tets_cut = m.n_tets - static_cast<std::int32_t>(tkeep);
  m.tet.resize(4 * tkeep);
  m.tet_k.resize(tkeep);
  m.tet_guard.resize(tkeep);
  m.tet_group_first = std::move(first);
  m.n_tets = static_cast<std::int32_t>(tkeep);

  // surface quads: any edge or diagonal across the blade opens the quad
  std::size_t qkeep = 0;
  for (std::int32_t q = 0; q < m.n_quads; ++q) {
    const std::int32_t* v = &m.quads[4 * static_cast<std::size_t>(q)];
    const bool open = severs(v[0], v[1]) || severs(v[1], v[2]) || severs(v[2], v[3]) || severs(v[3], v[0]) ||
                      severs(v[0], v[2]) || severs(v[1], v[3]);
    if (open) continue;
    std::copy(v, v + 4, &m.quads[4 * qkeep]);
    ++qkeep;
  }
  rep.quads_loaded = m.n_quads > 0;
  rep.quads_removed = m.n_quads - static_cast<std::int32_t>(qkeep);
  m.quads.resize(4 * qkeep);
  m.n_quads = static_cast<std::int32_t>(qkeep);

  // vessels: their centrelines where the tissue has carried them (vessel_x), else at rest
  for (std::size_t vi = 0; vi < m.vessels.size(); ++vi) {
    auto& ves = m.vessels[vi];
    const Real* vx = vi < vessel_x.size() && vessel_x[vi].size() == ves.nodes.size() ? vessel_x[vi].data() : ves.nodes.data();
    const std::size_t ne = ves.edges.size() / 2;
    for (std::size_t e = 0; e < ne; ++e) {
      const std::int32_t a = ves.edges[2 * e], b = ves.edges[2 * e + 1];
      const Vec3 pa = load3(vx, a), pb = load3(vx, b);
      Real t = 0;
      if (!blade.crosses(pa, pb, &t)) continue;
      if (ves.edge_cut.size() != ne) ves.edge_cut.assign(ne, 0);
      if (ves.edge_cut[e]) {  // opened by an earlier cut: it bleeds already
        ++rep.vessel_edges_open_already;
        continue;
      }
      ves.edge_cut[e] = 1;
      VesselHit h;
      h.vessel = static_cast<int>(vi);
      h.edge = static_cast<std::int32_t>(e);
      h.along = t;
      h.point = pa + t * (pb - pa);
      const Real len = norm(pb - pa);
      h.tangent = len > 0 ? (1 / len) * (pb - pa) : Vec3{0, 0, 0};
      h.radius = ves.radii[static_cast<std::size_t>(a)] * (1 - t) + ves.radii[static_cast<std::size_t>(b)] * t;
      rep.vessel_hits.push_back(h);
    }
  }

  // the tissue columns the blade crosses (a scene opens those its emitters reach: open_columns_at)
  if (columns && columns->valid()) {
    WoundColumns& w = *columns;
    const std::int32_t nq = w.n_quads;
    for (std::int32_t l = 0; l + 1 < w.n_surfaces; ++l)
      for (std::int32_t k = 0; k < nq; ++k) {
        std::uint8_t& o = w.open[static_cast<std::size_t>(l) * nq + k];
        if (o) continue;
        std::array<std::int32_t, 4> t, b;
        for (int c = 0; c < 4; ++c) t[c] = w.corner(l, k, c), b[c] = w.corner(l + 1, k, c);
        // touches: a slit along the face between two columns (a blade through
        // their shared nodes) opens both to the blood, though only one side's
        // springs and quads go: the vessel's emitter lies on the slit, and
        // with one column open half its jet ran into the closed one's walls
        // (1 ms after the cut its fastest particle was 6 % past the Bernoulli speed).
        // Nodes within their snap distance of the blade are on it here as for
        // the springs (a blade 0.1 quad off a grid line opened one side only)
        auto touches = [&](std::int32_t i, std::int32_t j) { return severs(i, j, true); };
        bool crossed = touches(t[0], t[2]) || touches(t[1], t[3]) || touches(b[0], b[2]) || touches(b[1], b[3]);
        for (int c = 0; c < 4 && !crossed; ++c) {
          const int d = (c + 1) % 4;
          crossed = touches(t[c], t[d]) || touches(b[c], b[d]) || touches(t[c], b[c]) || touches(t[c], b[d]) ||
                    touches(t[d], b[c]);
        }
        if (crossed) o = 1, ++rep.columns_opened;
      }
  }

  // the layer columns whose two ends the blade parts (inverted_columns skips them)
  for (const LayerColumns& lc : layer_columns(m))
    for (const auto& pair : lc.columns)
      if (severs(pair.first, pair.second) &&
          !std::binary_search(m.severed_columns.begin(), m.severed_columns.end(), pair)) {
        m.severed_columns.insert(std::upper_bound(m.severed_columns.begin(), m.severed_columns.end(), pair), pair);
        ++rep.columns_severed;
      }

  m.finalize();

  // nodes that lost every spring (anchors have none to lose)
  if (rep.springs_cut > 0)
    for (std::int32_t i = 0; i < m.n_nodes - m.n_anchors; ++i)
      if (had[i] && m.a_first[i + 1] == m.a_first[i] && m.b_first[i + 1] == m.b_first[i])
        rep.detached.push_back(i);
  return rep;
}

}  // namespace orthosim::runtime
