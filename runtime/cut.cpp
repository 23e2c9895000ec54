#include "runtime/cut.h"

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <array>
#include <cmath>

namespace orthosim::runtime {

namespace {

Vec3 cross(const Vec3& a, const Vec3& b) { return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x}; }
bool finite(const Vec3& v) { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }

struct Box {
  Vec3 lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
  void add(const Vec3& p) {
    lo = {std::min(lo.x, p.x), std::min(lo.y, p.y), std::min(lo.z, p.z)};
    hi = {std::max(hi.x, p.x), std::max(hi.y, p.y), std::max(hi.z, p.z)};
  }
  bool misses(const Vec3& p, const Vec3& q) const {
    return std::max(p.x, q.x) < lo.x || std::min(p.x, q.x) > hi.x || std::max(p.y, q.y) < lo.y ||
           std::min(p.y, q.y) > hi.y || std::max(p.z, q.z) < lo.z || std::min(p.z, q.z) > hi.z;
  }
};

// the blade: two triangles per polyline segment
struct Blade {
  std::vector<std::array<Vec3, 3>> tris;
  Box box;
  bool crosses(const Vec3& p, const Vec3& q, Real* t = nullptr) const {
    if (box.misses(p, q)) return false;
    for (const auto& tr : tris)
      if (segment_crosses_triangle(p, q, tr[0], tr[1], tr[2], t)) return true;
    return false;
  }
};

Blade make_blade(const CutDef& def, const Vec3& d) {
  Blade b;
  const Vec3 back = (-def.lead * def.depth) * d, deep = def.depth * d;
  for (std::size_t i = 0; i + 1 < def.polyline.size(); ++i) {
    const Vec3 p0 = def.polyline[i] + back, p1 = def.polyline[i + 1] + back;
    const Vec3 q0 = def.polyline[i] + deep, q1 = def.polyline[i + 1] + deep;
    b.tris.push_back({p0, p1, q1});
    b.tris.push_back({p0, q1, q0});
    for (const Vec3& p : {p0, p1, q0, q1}) b.box.add(p);
  }
  return b;
}

}  // namespace

bool segment_crosses_triangle(const Vec3& p, const Vec3& q, const Vec3& a, const Vec3& b, const Vec3& c, Real* t_out) {
  const Vec3 dir = q - p, e1 = b - a, e2 = c - a;
  const Vec3 h = cross(dir, e2);
  const Real det = dot(e1, h);
  const Real scale = norm(e1) * norm(e2) * norm(dir);
  if (!(std::abs(det) > 1e-14 * scale)) return false;  // parallel, or a degenerate triangle or segment
  const Real inv = 1 / det;
  const Vec3 s = p - a;
  const Real u = inv * dot(s, h);
  if (u < 0 || u > 1) return false;
  const Vec3 qv = cross(s, e1);
  const Real v = inv * dot(dir, qv);
  if (v < 0 || u + v > 1) return false;
  const Real t = inv * dot(e2, qv);
  if (t < 0 || t > 1) return false;
  if (t_out) *t_out = t;
  return true;
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
}

Vec3 cut_direction(const Model& m, const CutDef& def) {
  validate(def);
  if (norm(def.direction) > 0) return (1 / norm(def.direction)) * def.direction;
  // principal axis of the rest positions
  const std::int64_t n = m.n_nodes;
  if (n == 0) throw Error("", "cut: the model has no nodes");
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  for (std::int64_t i = 0; i < n; ++i) c += Eigen::Vector3d(m.rest_x[3 * i], m.rest_x[3 * i + 1], m.rest_x[3 * i + 2]);
  c /= static_cast<double>(n);
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (std::int64_t i = 0; i < n; ++i) {
    const Eigen::Vector3d r = Eigen::Vector3d(m.rest_x[3 * i], m.rest_x[3 * i + 1], m.rest_x[3 * i + 2]) - c;
    cov += r * r.transpose();
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);
  const Eigen::Vector3d axis = es.eigenvectors().col(2);
  Vec3 mid{0, 0, 0};
  for (const Vec3& p : def.polyline) mid += p;
  mid = (1.0 / static_cast<Real>(def.polyline.size())) * mid;
  const Eigen::Vector3d mm(mid.x, mid.y, mid.z);
  const Eigen::Vector3d foot = c + (mm - c).dot(axis) * axis;
  const Eigen::Vector3d d = foot - mm;
  if (!(d.norm() > 1e-12 * (1 + mm.norm())))
    throw Error("", "cut: the polyline lies on the model's axis: give the blade a direction");
  const Eigen::Vector3d u = d.normalized();
  return {u.x(), u.y(), u.z()};
}

CutReport cut_model(Model& m, std::span<const Real> x, const CutDef& def) {
  CutReport rep;
  rep.direction = cut_direction(m, def);
  if (x.size() != 3 * static_cast<std::size_t>(m.n_nodes)) throw Error("", "cut: positions do not match the model");
  const Blade blade = make_blade(def, rep.direction);
  auto pos = [&](std::int32_t i) {
    const Vec3 p = load3(x.data(), i);
    // a non-finite position (never in a healthy state) falls back to rest
    return finite(p) ? p : load3(m.rest_x.data(), i);
  };

  // nodes with springs before the cut
  std::vector<std::uint8_t> had(static_cast<std::size_t>(m.n_nodes), 0);
  for (std::int32_t s = 0; s < m.n_springs; ++s) had[m.spring_a[s]] = had[m.spring_b[s]] = 1;

  // springs
  std::size_t keep = 0;
  const auto ns = static_cast<std::size_t>(m.n_springs);
  for (std::size_t s = 0; s < ns; ++s) {
    if (blade.crosses(pos(m.spring_a[s]), pos(m.spring_b[s]))) continue;
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

  // surface quads: any edge or diagonal across the blade opens the quad
  std::size_t qkeep = 0;
  for (std::int32_t q = 0; q < m.n_quads; ++q) {
    const std::int32_t* v = &m.quads[4 * static_cast<std::size_t>(q)];
    const Vec3 p[4] = {pos(v[0]), pos(v[1]), pos(v[2]), pos(v[3])};
    const bool open = blade.crosses(p[0], p[1]) || blade.crosses(p[1], p[2]) || blade.crosses(p[2], p[3]) ||
                      blade.crosses(p[3], p[0]) || blade.crosses(p[0], p[2]) || blade.crosses(p[1], p[3]);
    if (open) continue;
    std::copy(v, v + 4, &m.quads[4 * qkeep]);
    ++qkeep;
  }
  rep.quads_loaded = m.n_quads > 0;
  rep.quads_removed = m.n_quads - static_cast<std::int32_t>(qkeep);
  m.quads.resize(4 * qkeep);
  m.n_quads = static_cast<std::int32_t>(qkeep);

  // vessels (static centrelines, rest frame)
  for (std::size_t vi = 0; vi < m.vessels.size(); ++vi) {
    auto& ves = m.vessels[vi];
    const std::size_t ne = ves.edges.size() / 2;
    for (std::size_t e = 0; e < ne; ++e) {
      const std::int32_t a = ves.edges[2 * e], b = ves.edges[2 * e + 1];
      const Vec3 pa = load3(ves.nodes.data(), a), pb = load3(ves.nodes.data(), b);
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
      h.point = pa + t * (pb - pa);
      const Real len = norm(pb - pa);
      h.tangent = len > 0 ? (1 / len) * (pb - pa) : Vec3{0, 0, 0};
      h.radius = ves.radii[static_cast<std::size_t>(a)] * (1 - t) + ves.radii[static_cast<std::size_t>(b)] * t;
      rep.vessel_hits.push_back(h);
    }
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
