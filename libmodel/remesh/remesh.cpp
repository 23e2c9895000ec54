// Tube sweep (axis, caps, rotation-minimising frames) and the layered quad grids.
#include "libmodel/remesh/remesh.h"

#include "libmodel/remesh/detail.h"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <Eigen/Sparse>

#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/task_group.h>

#include <algorithm>
#include <exception>
#include <limits>
#include <memory>
#include <chrono>
#include <cmath>
#include <deque>
#include <optional>
#include <numeric>
#include <sstream>
#include <iomanip>

namespace orthosim {

using remesh_detail::Loop;
using remesh_detail::Slicer;
using remesh_detail::Topology;
using Vec3 = Eigen::Vector3d;
using Vec2 = Eigen::Vector2d;

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr int kTable = 2049;         // entries of the sweep table
constexpr double kMaxCreaseInset = 0.05;  // an end ring moves at most this fraction of the length past a crease
constexpr double kCapInset = 1e-5;   // end rings sit this fraction of the length inside a flat cap

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

std::string mm(double m) {
  std::ostringstream o;
  o.precision(4);
  o << m * 1e3 << " mm";
  return o.str();
}

// a unit vector orthogonal to n, close to world x (or y when n is near x)
Vec3 reference_perpendicular(const Vec3& n) {
  Vec3 ref = std::abs(n.x()) > 0.9 ? Vec3(0, 1, 0) : Vec3(1, 0, 0);
  return (ref - ref.dot(n) * n).normalized();
}

SweepPlane make_plane(const Vec3& c, const Vec3& n, const Vec3& e1_hint) {
  SweepPlane p;
  p.centre = c;
  p.normal = n.normalized();
  Vec3 e1 = e1_hint - e1_hint.dot(p.normal) * p.normal;
  if (e1.norm() < 1e-9) e1 = reference_perpendicular(p.normal);
  p.e1 = e1.normalized();
  p.e2 = p.normal.cross(p.e1);
  return p;
}

// ---- principal axis ----------------------------------------------------------
struct Axis {
  Vec3 m = Vec3::Zero(), d = Vec3::UnitZ();
  Vec3 others[2] = {Vec3::UnitX(), Vec3::UnitY()};  // the other principal directions, by falling variance
};

Axis principal_axis(const Surface& s) {
  Axis ax;
  double A = 0;
  const int nf = static_cast<int>(s.faces.rows());
  std::vector<Vec3> c(nf);
  std::vector<double> a(nf);
  for (int f = 0; f < nf; ++f) {
    const Vec3 p0 = s.vertices.row(s.faces(f, 0)), p1 = s.vertices.row(s.faces(f, 1)),
               p2 = s.vertices.row(s.faces(f, 2));
    c[f] = (p0 + p1 + p2) / 3;
    a[f] = 0.5 * (p1 - p0).cross(p2 - p0).norm();
    A += a[f];
    ax.m += a[f] * c[f];
  }
  if (!(A > 0)) return ax;
  ax.m /= A;
  Eigen::Matrix3d C = Eigen::Matrix3d::Zero();
  for (int f = 0; f < nf; ++f) C += a[f] * (c[f] - ax.m) * (c[f] - ax.m).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(C);
  auto oriented = [](Vec3 d) {  // the largest component positive: a fixed sign
    d.normalize();
    int big = 0;
    for (int k = 1; k < 3; ++k)
      if (std::abs(d(k)) > std::abs(d(big)) + 1e-12) big = k;
    return d(big) < 0 ? Vec3(-d) : d;
  };
  ax.d = oriented(es.eigenvectors().col(2));
  ax.others[0] = oriented(es.eigenvectors().col(1));
  ax.others[1] = oriented(es.eigenvectors().col(0));
  return ax;
}

// ---- flat caps --------------------------------------------------------------
struct Cap {
  bool flat = false;
  Vec3 q = Vec3::Zero();  // area centroid of the cap faces
  Vec3 n = Vec3::Zero();  // unit normal pointing into the tube (towards increasing s)
  double area = 0;
  double crease = 0;      // how far into the tube the wall faces touching the cap reach (along n)
  std::vector<int> faces;
};

// Outward unit normal, centroid and area of every face (shared by both caps).
struct FaceData {
  std::vector<Vec3> nrm, cen;
  std::vector<double> area;
};

FaceData face_data(const Surface& s, const Topology& t) {
  const int nf = static_cast<int>(s.faces.rows());
  FaceData d;
  d.nrm.resize(nf), d.cen.resize(nf), d.area.resize(nf);
  for (int f = 0; f < nf; ++f) {
    const Vec3 p0 = s.vertices.row(s.faces(f, 0)), p1 = s.vertices.row(s.faces(f, 1)),
               p2 = s.vertices.row(s.faces(f, 2));
    const Vec3 n = (p1 - p0).cross(p2 - p0);
    d.area[f] = 0.5 * n.norm();
    d.nrm[f] = d.area[f] > 0 ? Vec3(n.normalized()) : Vec3::Zero();
    if (t.component_volume[t.face_component[f]] < 0) d.nrm[f] = -d.nrm[f];
    d.cen[f] = (p0 + p1 + p2) / 3;
  }
  return d;
}

// The largest planar patch facing the end `dir` (unit, pointing out of the
// tube), grown from the face furthest along dir.
Cap detect_cap(const Surface& s, const Topology& t, const FaceData& fd, const Vec3& dir, double angle_deg, double length) {
  Cap cap;
  const int nf = static_cast<int>(s.faces.rows());
  const std::vector<Vec3>&nrm = fd.nrm, &cen = fd.cen;
  const std::vector<double>& area = fd.area;
  int seed = -1;
  double best = -1e300;
  const double cos_seed = std::cos(50 * kPi / 180);
  for (int f = 0; f < nf; ++f) {
    if (area[f] > 0 && nrm[f].dot(dir) > cos_seed && cen[f].dot(dir) > best) {
      best = cen[f].dot(dir);
      seed = f;
    }
  }
  if (seed < 0) return cap;
  const double cos_tol = std::cos(angle_deg * kPi / 180), dist_tol = 1e-4 * length;
  std::vector<char> in(nf, 0);
  std::deque<int> queue{seed};
  in[seed] = 1;
  Vec3 nsum = Vec3::Zero(), qsum = Vec3::Zero();
  while (!queue.empty()) {
    const int f = queue.front();
    queue.pop_front();
    cap.faces.push_back(f);
    cap.area += area[f];
    nsum += area[f] * nrm[f];
    qsum += area[f] * cen[f];
    for (int k = 0; k < 3; ++k) {
      const auto& ef = t.edge_face[t.face_edge[f][k]];
      const int g = ef[0] == f ? ef[1] : ef[0];
      if (in[g] || !(area[g] > 0)) continue;
      // against the patch's plane so far (area-weighted normal and centroid):
      // a decimated cap is planar only to within its faces' tilt, so a far
      // face measured against the seed's own plane would drift out of it
      const Vec3 pn = nsum.normalized(), pq = qsum / cap.area;
      double edge = 0;  // the face's longest edge: its tilt within cos_tol moves its centroid by ~edge sin(angle)
      for (int j = 0; j < 3; ++j)
        edge = std::max(edge, (s.vertices.row(s.faces(g, j)) - s.vertices.row(s.faces(g, (j + 1) % 3))).norm());
      const double tol = std::max(dist_tol, 0.1 * edge);
      if (nrm[g].dot(pn) < cos_tol || std::abs((cen[g] - pq).dot(pn)) > tol) continue;
      in[g] = 1;
      queue.push_back(g);
    }
  }
  cap.q = qsum / cap.area;
  cap.n = -nsum.normalized();
  // The crease: the wall faces that share a vertex with the cap join it to
  // the wall; on a voxel surface they are the staircase that closes the
  // volume at its boundary. The end rings sit beyond them.
  std::vector<char> on_cap(static_cast<std::size_t>(s.vertices.rows()), 0);
  for (int f : cap.faces)
    for (int k = 0; k < 3; ++k) on_cap[static_cast<std::size_t>(s.faces(f, k))] = 1;
  for (int f = 0; f < nf; ++f) {
    if (in[f]) continue;
    const int v[3] = {s.faces(f, 0), s.faces(f, 1), s.faces(f, 2)};
    if (!on_cap[static_cast<std::size_t>(v[0])] && !on_cap[static_cast<std::size_t>(v[1])] && !on_cap[static_cast<std::size_t>(v[2])])
      continue;
    for (int k = 0; k < 3; ++k) cap.crease = std::max(cap.crease, (s.vertices.row(v[k]).transpose() - cap.q).dot(cap.n));
  }
  return cap;
}

// Whether the surface ends in a flat cap at both ends along d: each end's
// planar patch (detect_cap) covers at least half the surface's shadow on the
// plane normal to d (half the sum of a_f |n_f . d|: the section's area for a
// convex tube, more for others).
bool capped_along(const Surface& s, const Topology& t, const FaceData& fd, const Vec3& d, double angle_deg) {
  double shadow = 0;
  for (std::size_t f = 0; f < fd.area.size(); ++f) shadow += fd.area[f] * std::abs(fd.nrm[f].dot(d));
  shadow *= 0.5;
  double t0 = 1e300, t1 = -1e300;
  for (Eigen::Index v = 0; v < s.vertices.rows(); ++v) {
    const double x = s.vertices.row(v).dot(d);
    t0 = std::min(t0, x), t1 = std::max(t1, x);
  }
  if (!(shadow > 0) || !(t1 > t0)) return false;
  return detect_cap(s, t, fd, -d, angle_deg, t1 - t0).area >= 0.5 * shadow &&
         detect_cap(s, t, fd, d, angle_deg, t1 - t0).area >= 0.5 * shadow;
}

// The sweep along capped_alternative's axis stands only if its ring planes
// do not cross inside the tube; else the error of the principal axis, or one
// naming the short tube.
// The surface's straight extent along d and its largest across d (along the
// axis's other two directions), m: what the short-tube message quotes (the
// sweep's own length is an arc along a centreline that may wander).
std::pair<double, double> spans(const Surface& s, const Axis& ax) {
  std::array<double, 3> lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
  const Vec3 dirs[3] = {ax.d, ax.others[0], ax.others[1]};
  for (Eigen::Index v = 0; v < s.vertices.rows(); ++v)
    for (int k = 0; k < 3; ++k) {
      const double x = s.vertices.row(v).dot(dirs[k]);
      lo[k] = std::min(lo[k], x), hi[k] = std::max(hi[k], x);
    }
  return {hi[0] - lo[0], std::max(hi[1] - lo[1], hi[2] - lo[2])};
}

void check_alternative_sweep(const TubeSweep& sw, const RemeshOptions& o, const std::string& name,
                             const std::exception_ptr& first, const std::pair<double, double>& span) {
  if (sw.plane_turn < o.max_plane_turn) return;
  if (first) std::rethrow_exception(first);
  std::ostringstream m;
  m.precision(3);
  m << "not tube-like: no flat cap ends the sweep along the largest extent, and along the axis of the flat caps "
    << "(the surface spans " << span.first * 1e3 << " mm along it and " << span.second * 1e3
    << " mm across: a stack shorter than the limb is wide?) the ring planes cross inside the tube "
    << "(R |dn/ds| ";
  if (std::isfinite(sw.plane_turn)) m << "= " << sw.plane_turn << ", at most " << o.max_plane_turn << ")";
  else m << "unbounded, at most " << o.max_plane_turn << ": the surface has no length along it)";  // (a one-slice stack)
  throw Error(name, m.str());
}

// Another principal direction along which the surface is capped at both
// ends, if one is and the principal axis (the largest extent) is not
// (sweep_from_axes sweeps along it first). A stack shorter than the limb is wide has its largest extent across
// the limb; its flat caps, at the stack's ends, still give the limb's axis.
// Then the coordinate axes, z first: a limb about as long as it is wide has
// no clear largest extent, its principal directions can lie diagonally
// between the axes, and none of them is capped; the slices still cut it in
// planes normal to z (the stack's axis).
std::optional<Axis> capped_alternative(const Surface& s, const Topology& t, const Axis& ax, const RemeshOptions& o) {
  const FaceData fd = face_data(s, t);
  if (capped_along(s, t, fd, ax.d, o.cap_angle_deg)) return std::nullopt;
  for (int k = 0; k < 2; ++k)
    if (capped_along(s, t, fd, ax.others[k], o.cap_angle_deg)) {
      Axis b = ax;
      b.d = ax.others[k];
      b.others[k] = ax.d;
      return b;
    }
  const std::array<Vec3, 3> axes{Vec3::UnitZ(), Vec3::UnitX(), Vec3::UnitY()};
  for (const Vec3& e : axes) {
    bool tested = false;  // the same direction as one tested above (a principal direction on an axis)
    for (const Vec3& d : {ax.d, ax.others[0], ax.others[1]}) tested = tested || std::abs(e.dot(d)) >= 1 - 1e-12;
    if (tested || !capped_along(s, t, fd, e, o.cap_angle_deg)) continue;
    Axis b = ax;
    b.d = e;
    // the others: the principal plane's directions projected off e, by falling variance
    Vec3 u = ax.d - ax.d.dot(e) * e;
    if (u.norm() < 1e-6) u = ax.others[0] - ax.others[0].dot(e) * e;
    b.others[0] = u.normalized();
    b.others[1] = e.cross(b.others[0]).normalized();
    return b;
  }
  return std::nullopt;
}

// ---- centreline: smoothed points, natural cubic spline, arc-length table ----
class Curve {
 public:
  // Whittaker smoothing of the interior points (second-difference penalty
  // lambda, in units of their spacing), then a natural cubic spline through
  // front (if any), the smoothed points and back (if any), chord-length
  // parameter. The end points are exact: cap centres or extensions. End
  // conditions: clamped to the direction d0 / d1 where given (cap normals),
  // else parabolic runout (the end piece keeps the curvature next to it).
  Curve(const std::vector<Vec3>& interior, double lambda, const Vec3* front, const Vec3* back,
        const Vec3* d0 = nullptr, const Vec3* d1 = nullptr) {
    const int n0 = static_cast<int>(interior.size());
    std::vector<Vec3> z(interior);
    if (n0 >= 4 && lambda > 0) {
      // pad both ends by quadratic extrapolation so that the smoother leaves
      // locally quadratic data (constant curvature) unchanged up to the ends
      constexpr int pad = 4;
      std::vector<Vec3> y;
      auto quad = [](const Vec3& a, const Vec3& b, const Vec3& c, double j) {  // through a(0), b(1), c(2), at -j
        const double x = -j;
        return Vec3(a * (x - 1) * (x - 2) / 2 - b * x * (x - 2) + c * x * (x - 1) / 2);
      };
      for (int j = pad; j >= 1; --j) y.push_back(quad(interior[0], interior[1], interior[2], j));
      y.insert(y.end(), interior.begin(), interior.end());
      for (int j = 1; j <= pad; ++j) y.push_back(quad(interior[n0 - 1], interior[n0 - 2], interior[n0 - 3], j));
      const int n = static_cast<int>(y.size());
      Eigen::SparseMatrix<double> M(n, n);
      std::vector<Eigen::Triplet<double>> tr;
      for (int i = 0; i < n; ++i) tr.emplace_back(i, i, 1.0);
      for (int i = 0; i + 2 < n; ++i) {
        const int id[3] = {i, i + 1, i + 2};
        const double c[3] = {1, -2, 1};
        for (int a = 0; a < 3; ++a)
          for (int b = 0; b < 3; ++b) tr.emplace_back(id[a], id[b], lambda * c[a] * c[b]);
      }
      M.setFromTriplets(tr.begin(), tr.end());
      Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver(M);
      for (int k = 0; k < 3; ++k) {
        Eigen::VectorXd rhs(n);
        for (int i = 0; i < n; ++i) rhs(i) = y[i](k);
        Eigen::VectorXd sol = solver.solve(rhs);
        for (int i = 0; i < n0; ++i) z[i](k) = sol(i + pad);
      }
    }
    if (front) z.insert(z.begin(), *front);
    if (back) z.push_back(*back);
    // drop coincident points
    p_.push_back(z[0]);
    for (int i = 1; i < static_cast<int>(z.size()); ++i)
      if ((z[i] - p_.back()).norm() > 1e-12) p_.push_back(z[i]);
    const int m = static_cast<int>(p_.size());
    tau_.assign(m, 0);
    for (int i = 1; i < m; ++i) tau_[i] = tau_[i - 1] + (p_[i] - p_[i - 1]).norm();
    m2_.assign(m, Vec3::Zero());
    if (m >= 3) {  // tridiagonal solve for the second derivatives
      std::vector<double> a(m, 0), b(m, 1), c(m, 0);
      std::vector<Vec3> r(m, Vec3::Zero());
      for (int i = 1; i + 1 < m; ++i) {
        const double h0 = tau_[i] - tau_[i - 1], h1 = tau_[i + 1] - tau_[i];
        a[i] = h0;
        b[i] = 2 * (h0 + h1);
        c[i] = h1;
        r[i] = 6 * ((p_[i + 1] - p_[i]) / h1 - (p_[i] - p_[i - 1]) / h0);
      }
      const double hf = tau_[1] - tau_[0], hb = tau_[m - 1] - tau_[m - 2];
      if (d0) {
        Vec3 d = d0->normalized();
        if (d.dot(p_[1] - p_[0]) < 0) d = -d;
        b[0] = 2 * hf, c[0] = hf, r[0] = 6 * ((p_[1] - p_[0]) / hf - d);
      } else {
        b[0] = 1, c[0] = -1;
      }
      if (d1) {
        Vec3 d = d1->normalized();
        if (d.dot(p_[m - 1] - p_[m - 2]) < 0) d = -d;
        a[m - 1] = hb, b[m - 1] = 2 * hb, r[m - 1] = 6 * (d - (p_[m - 1] - p_[m - 2]) / hb);
      } else {
        a[m - 1] = -1, b[m - 1] = 1;
      }
      for (int i = 1; i < m; ++i) {
        const double k = a[i] / b[i - 1];
        b[i] -= k * c[i - 1];
        r[i] -= k * r[i - 1];
      }
      m2_[m - 1] = r[m - 1] / b[m - 1];
      for (int i = m - 2; i >= 0; --i) m2_[i] = (r[i] - c[i] * m2_[i + 1]) / b[i];
    }
    // arc-length table
    const int fine = std::max(4096, 64 * m);
    std::vector<double> tt(fine + 1), ss(fine + 1, 0);
    Vec3 prev = eval_tau(0);
    for (int i = 0; i <= fine; ++i) {
      tt[i] = tau_.back() * i / fine;
      const Vec3 x = eval_tau(tt[i]);
      if (i) ss[i] = ss[i - 1] + (x - prev).norm();
      prev = x;
    }
    length_ = ss.back();
    s_tab_ = std::move(ss);
    tau_tab_ = std::move(tt);
  }

  double length() const { return length_; }
  Vec3 point(double s) const { return eval_tau(tau_of(s)); }
  Vec3 tangent(double s) const {
    Vec3 d = deriv_tau(tau_of(s));
    return d.norm() > 0 ? Vec3(d.normalized()) : Vec3((p_.back() - p_.front()).normalized());
  }

 private:
  double tau_of(double s) const {
    s = std::clamp(s, 0.0, length_);
    auto it = std::upper_bound(s_tab_.begin(), s_tab_.end(), s);
    std::size_t i = std::min<std::size_t>(std::max<std::ptrdiff_t>(it - s_tab_.begin(), 1), s_tab_.size() - 1);
    const double ds = s_tab_[i] - s_tab_[i - 1];
    const double f = ds > 0 ? (s - s_tab_[i - 1]) / ds : 0;
    return tau_tab_[i - 1] + f * (tau_tab_[i] - tau_tab_[i - 1]);
  }
  std::size_t seg(double t) const {
    auto it = std::upper_bound(tau_.begin(), tau_.end(), t);
    return std::min<std::size_t>(std::max<std::ptrdiff_t>(it - tau_.begin(), 1), tau_.size() - 1) - 1;
  }
  Vec3 eval_tau(double t) const {
    if (p_.size() == 1) return p_[0];
    const std::size_t i = seg(t);
    const double h = tau_[i + 1] - tau_[i], A = (tau_[i + 1] - t) / h, B = (t - tau_[i]) / h;
    return A * p_[i] + B * p_[i + 1] + ((A * A * A - A) * m2_[i] + (B * B * B - B) * m2_[i + 1]) * (h * h) / 6;
  }
  Vec3 deriv_tau(double t) const {
    if (p_.size() == 1) return Vec3::UnitZ();
    const std::size_t i = seg(t);
    const double h = tau_[i + 1] - tau_[i], A = (tau_[i + 1] - t) / h, B = (t - tau_[i]) / h;
    return (p_[i + 1] - p_[i]) / h - (3 * A * A - 1) * h / 6 * m2_[i] + (3 * B * B - 1) * h / 6 * m2_[i + 1];
  }

  std::vector<Vec3> p_, m2_;
  std::vector<double> tau_, s_tab_, tau_tab_;
  double length_ = 0;
};

double smoothstep01(double x) {
  x = std::clamp(x, 0.0, 1.0);
  return x * x * (3 - 2 * x);
}

// Plane normals along a curve, blended into the cap normals near flat caps.
struct NormalField {
  const Curve* c = nullptr;
  bool flat[2] = {false, false};
  Vec3 n[2], t[2];
  double blend[2] = {1, 1};
  double w0(double s) const { return flat[0] ? smoothstep01(1 - s / blend[0]) : 0; }
  double w1(double s) const { return flat[1] ? smoothstep01(1 - (c->length() - s) / blend[1]) : 0; }
  // a convex blend: where a cap's weight is near 1 the plane is the cap's,
  // whatever the tangent does there (the section centroids next to a cap
  // wander, and adding their rotation to the cap normal tilted the first
  // rings into the cap: every layer's cap is coplanar, so the layers met)
  Vec3 operator()(double s) const {
    const double a = w0(s), b = w1(s);
    Vec3 v = (1 - a - b) * c->tangent(s) + a * n[0] + b * n[1];
    if (!(v.norm() > 1e-9)) v = c->tangent(s);
    return v.normalized();
  }
};

NormalField normal_field(const Curve& c, const Cap caps[2], const double radius[2]) {
  NormalField f;
  f.c = &c;
  for (int e = 0; e < 2; ++e) {
    f.flat[e] = caps[e].flat;
    f.t[e] = c.tangent(e == 0 ? 0 : c.length());
    f.n[e] = caps[e].flat ? caps[e].n : f.t[e];
    if (f.n[e].dot(f.t[e]) < 0) f.n[e] = -f.n[e];
    f.blend[e] = std::max(1e-12, std::min(2 * radius[e], c.length() / 3));
  }
  return f;
}

// area of faces of `s` whose centroid lies beyond the plane (on the side opposite to its normal)
double area_behind(const Surface& s, const SweepPlane& p) {
  double A = 0;
  for (int f = 0; f < s.faces.rows(); ++f) {
    const Vec3 p0 = s.vertices.row(s.faces(f, 0)), p1 = s.vertices.row(s.faces(f, 1)),
               p2 = s.vertices.row(s.faces(f, 2));
    if (((p0 + p1 + p2) / 3 - p.centre).dot(p.normal) < 0) A += 0.5 * (p1 - p0).cross(p2 - p0).norm();
  }
  return A;
}

}  // namespace

namespace remesh_detail {

// The loop of a ring plane that the sweep follows: the only loop, winding
// around the centre. Throws Error(name, "not tube-like: ...") otherwise.
const Loop& tube_loop(const std::vector<Loop>& loops, const std::string& name, double s, double length) {
  const std::string where = "the ring plane at " + mm(s) + " of " + mm(length) + " along the axis";
  if (loops.empty()) throw Error(name, "not tube-like: " + where + " misses the surface");
  if (loops.size() == 1) {
    if (remesh_detail::winding(loops[0], Vec2(0, 0)) == 0)
      throw Error(name, "not tube-like: the axis leaves the surface at " + where);
    return loops[0];
  }
  // several: the one around the axis, when the others are side loops
  const Loop* tube = nullptr;
  int around = 0;
  for (const Loop& l : loops)
    if (remesh_detail::winding(l, Vec2(0, 0)) != 0) tube = &l, ++around;
  double side = 0;  // the largest other loop's area
  for (const Loop& l : loops)
    if (&l != tube) side = std::max(side, std::abs(l.area));
  if (around == 1 && side <= kSideLoopAreaRatio * std::abs(tube->area)) return *tube;
  std::ostringstream share;
  if (around == 1) share << ", the largest beside the tube's " << std::setprecision(2) << 100 * side / std::abs(tube->area)
                         << " % of its area";
  throw Error(name, "not tube-like: " + where + " cuts the surface in " + std::to_string(loops.size()) + " loops (" +
                        std::to_string(around) + " around the axis" + share.str() +
                        "; branching, folded or ring-shaped surface, or jagged by slices off each other: segment "
                        "--register); remesh needs a single tube");
}

// Points of a ring at fractions u (sorted, in [0, 1)): equal arc length from
// the phase point (the outermost crossing of the ray along e1), or rays at
// angles 2 pi u. inward (optional): unit in-plane normals pointing inside.
void sample_loop(const Loop& l, const SweepPlane& pl, RingSampling mode, int window, const std::vector<double>& u,
                 std::vector<Vec3>& out, std::vector<Vec3>* inward, const std::string& name) {
  const std::size_t m = l.q.size(), n = u.size();
  out.resize(n);
  if (inward) inward->resize(n);
  auto to3 = [&](const Vec2& q) { return Vec3(pl.centre + q.x() * pl.e1 + q.y() * pl.e2); };
  auto seg_inward = [&](std::size_t i) {
    const Vec2 d = l.q[(i + 1) % m] - l.q[i];
    const Vec3 t = d.x() * pl.e1 + d.y() * pl.e2;
    const Vec3 w = pl.normal.cross(t);
    return w.norm() > 0 ? Vec3(w.normalized()) : Vec3::Zero();
  };
  if (mode == RingSampling::angle) {
    for (std::size_t k = 0; k < n; ++k) {
      const Vec2 w(std::cos(2 * kPi * u[k]), std::sin(2 * kPi * u[k]));
      double best = -1;
      std::size_t bi = 0;
      for (std::size_t i = 0; i < m; ++i) {
        const Vec2 a = l.q[i];
        const Vec2 d = l.q[(i + 1) % m] - l.q[i];
        const double den = w.x() * d.y() - w.y() * d.x();
        if (den == 0) continue;
        const double t = (a.x() * d.y() - a.y() * d.x()) / den;
        const double lam = (a.x() * w.y() - a.y() * w.x()) / den;
        if (lam >= -1e-9 && lam <= 1 + 1e-9 && t > best) best = t, bi = i;
      }
      if (best < 0) throw Error(name, "a ring is not star-shaped around its centre: use arc-length sampling");
      out[k] = to3(best * w);
      if (inward) (*inward)[k] = seg_inward(bi);
    }
    return;
  }
  // phase: outermost crossing of the ray from the centre along e1
  double best = -1, blam = 0;
  std::size_t bi = 0;
  for (std::size_t i = 0; i < m; ++i) {
    const Vec2 a = l.q[i], b = l.q[(i + 1) % m];
    if ((a.y() < 0) == (b.y() < 0)) continue;
    const double lam = a.y() / (a.y() - b.y());
    const double x = a.x() + lam * (b.x() - a.x());
    if (x >= 0 && x > best) best = x, bi = i, blam = lam;
  }
  if (best < 0) throw Error(name, "a ring does not surround its centre");
  std::vector<double> len(m);
  double P = 0;
  // arc length of the section smoothed by a moving average over an arc of
  // half-width window x its mean vertex spacing: a staircase at the input's
  // resolution adds length that is not the limb's (RemeshOptions::arc_window).
  // The average is the integral of the polyline over the arc, so the vertex
  // distribution does not bias it (a circle stays a circle, scaled). The
  // points stay on the section.
  std::vector<double> cs(m + 1, 0);
  for (std::size_t i = 0; i < m; ++i) cs[i + 1] = cs[i] + (l.q[(i + 1) % m] - l.q[i]).norm();
  const double per = cs[m];
  if (window > 0 && m >= 3 && per > 0) {
    // F(x) = integral of the polyline from 0 to x, periodic extension
    std::vector<Vec2> F(m + 1, Vec2::Zero());
    for (std::size_t i = 0; i < m; ++i) F[i + 1] = F[i] + 0.5 * (cs[i + 1] - cs[i]) * (l.q[i] + l.q[(i + 1) % m]);
    // F at x through a cursor that only moves forward (the window's ends
    // advance with i): one pass instead of a search per end
    struct Cursor {
      double turns;
      std::size_t seg;
    };
    auto cursor_at = [&](double x) {
      const double turns = std::floor(x / per);
      std::size_t i = static_cast<std::size_t>(std::upper_bound(cs.begin(), cs.end(), x - turns * per) - cs.begin());
      return Cursor{turns, std::clamp<std::size_t>(i, 1, m) - 1};
    };
    auto integral = [&](Cursor& c, double x) {
      while (x >= c.turns * per + cs[c.seg + 1]) {
        if (++c.seg == m) c.seg = 0, c.turns += 1;
      }
      const std::size_t i = c.seg;
      const double d = x - c.turns * per - cs[i], li = cs[i + 1] - cs[i];
      const Vec2 a = l.q[i], b = l.q[(i + 1) % m];
      const Vec2 part = li > 0 ? Vec2(d * a + 0.5 * d * d / li * (b - a)) : Vec2::Zero();
      return Vec2(c.turns * F[m] + F[i] + part);
    };
    const double h = std::min(static_cast<double>(window) * per / static_cast<double>(m), 0.25 * per);
    std::vector<Vec2> sm(m);
    Cursor lo_end = cursor_at(-h), hi_end = cursor_at(h);
    for (std::size_t i = 0; i < m; ++i) sm[i] = (integral(hi_end, cs[i] + h) - integral(lo_end, cs[i] - h)) / (2 * h);
    for (std::size_t i = 0; i < m; ++i) P += len[i] = (sm[(i + 1) % m] - sm[i]).norm();
  } else {
    for (std::size_t i = 0; i < m; ++i) P += len[i] = (l.q[(i + 1) % m] - l.q[i]).norm();
  }
  // walk from the phase point
  std::size_t i = bi;
  double start = blam * len[bi];  // distance already covered inside segment i
  double walked = -start;         // arc length at the start of segment i, from the phase point
  for (std::size_t k = 0; k < n; ++k) {
    const double target = u[k] * P;
    while (walked + len[i] < target) {
      walked += len[i];
      i = (i + 1) % m;
    }
    const double f = len[i] > 0 ? (target - walked) / len[i] : 0;
    const Vec2 q = l.q[i] + std::clamp(f, 0.0, 1.0) * (l.q[(i + 1) % m] - l.q[i]);
    out[k] = to3(q);
    if (inward) (*inward)[k] = seg_inward(i);
  }
}

// Cumulative arc length of the closed polygon T at each vertex, and its
// perimeter last (T.size() + 1 entries).
std::vector<double> closed_arc_lengths(const std::vector<Vec2>& T) {
  const std::size_t m = T.size();
  std::vector<double> cum(m + 1, 0);
  for (std::size_t s = 0; s < m; ++s) cum[s + 1] = cum[s] + (T[(s + 1) % m] - T[s]).norm();
  return cum;
}

Vec2 point_at_arc(const std::vector<Vec2>& T, const std::vector<double>& cum, double x, std::size_t* segment) {
  const std::size_t m = T.size();
  x = std::fmod(x, cum[m]);
  if (x < 0) x += cum[m];
  std::size_t s = static_cast<std::size_t>(std::upper_bound(cum.begin(), cum.end(), x) - cum.begin());
  s = std::clamp<std::size_t>(s, 1, m) - 1;
  const double len = cum[s + 1] - cum[s];
  const double f = len > 0 ? std::clamp((x - cum[s]) / len, 0.0, 1.0) : 0;
  if (segment) *segment = s;
  return T[s] + f * (T[(s + 1) % m] - T[s]);
}

// A uniform grid over the segments of a closed polygon, walked along a ray
// (Amanatides & Woo 1987): the ray casts of the layer correspondence test
// only the segments near the ray instead of all of them.
class SegmentGrid {
 public:
  explicit SegmentGrid(const std::vector<Vec2>& T) {
    const std::size_t m = T.size();
    lo_ = hi_ = T[0];
    double len = 0;
    for (std::size_t s = 0; s < m; ++s) {
      lo_ = lo_.cwiseMin(T[s]), hi_ = hi_.cwiseMax(T[s]);
      len += (T[(s + 1) % m] - T[s]).norm();
    }
    const Vec2 ext = hi_ - lo_;
    h_ = std::max({2 * len / static_cast<double>(m), ext.maxCoeff() / 256, 1e-300});
    lo_ -= Vec2::Constant(1e-9 * h_), hi_ += Vec2::Constant(1e-9 * h_);
    nx_ = std::max(1, static_cast<int>(std::ceil((hi_.x() - lo_.x()) / h_)));
    ny_ = std::max(1, static_cast<int>(std::ceil((hi_.y() - lo_.y()) / h_)));
    // counting sort of (cell, segment) pairs
    std::vector<std::pair<int, int>> pairs;
    for (std::size_t s = 0; s < m; ++s) {
      const Vec2 a = T[s].cwiseMin(T[(s + 1) % m]), b = T[s].cwiseMax(T[(s + 1) % m]);
      const int x0 = cx(a.x()), x1 = cx(b.x()), y0 = cy(a.y()), y1 = cy(b.y());
      for (int y = y0; y <= y1; ++y)
        for (int x = x0; x <= x1; ++x) pairs.emplace_back(y * nx_ + x, static_cast<int>(s));
    }
    start_.assign(static_cast<std::size_t>(nx_) * ny_ + 1, 0);
    for (const auto& pr : pairs) ++start_[static_cast<std::size_t>(pr.first) + 1];
    for (std::size_t c = 0; c + 1 < start_.size(); ++c) start_[c + 1] += start_[c];
    seg_.resize(pairs.size());
    std::vector<int> fill(start_.begin(), start_.end() - 1);
    for (const auto& pr : pairs) seg_[static_cast<std::size_t>(fill[static_cast<std::size_t>(pr.first)]++)] = pr.second;
  }
  // Visits the cells the ray o + t w (t >= 0) passes, in order: visit(segments
  // begin, end, t at which the ray leaves the cell) returns true to stop.
  template <class Visit>
  void walk(const Vec2& o, const Vec2& w, Visit&& visit) const {
    double t0 = 0, t1 = std::numeric_limits<double>::infinity();
    for (int d = 0; d < 2; ++d) {  // clip to the grid's box
      if (w(d) != 0) {
        double a = (lo_(d) - o(d)) / w(d), b = (hi_(d) - o(d)) / w(d);
        if (a > b) std::swap(a, b);
        t0 = std::max(t0, a), t1 = std::min(t1, b);
      } else if (o(d) < lo_(d) || o(d) > hi_(d)) {
        return;
      }
    }
    if (!(t0 <= t1)) return;
    const Vec2 p = o + t0 * w;
    int x = cx(p.x()), y = cy(p.y());
    const int sx = w.x() > 0 ? 1 : -1, sy = w.y() > 0 ? 1 : -1;
    const double inf = std::numeric_limits<double>::infinity();
    auto next = [&](int c, int sgn, int d) {  // t where the ray crosses the next cell boundary along d
      if (w(d) == 0) return inf;
      const double edge = lo_(d) + (c + (sgn > 0 ? 1 : 0)) * h_;
      return (edge - o(d)) / w(d);
    };
    double tx = next(x, sx, 0), ty = next(y, sy, 1);
    for (;;) {
      const double exit = std::min({tx, ty, t1});
      const std::size_t c = static_cast<std::size_t>(y) * nx_ + x;
      if (visit(seg_.data() + start_[c], seg_.data() + start_[c + 1], exit)) return;
      if (exit >= t1) return;
      if (tx <= ty) {
        x += sx;
        if (x < 0 || x >= nx_) return;
        tx = next(x, sx, 0);
      } else {
        y += sy;
        if (y < 0 || y >= ny_) return;
        ty = next(y, sy, 1);
      }
    }
  }

 private:
  int cx(double v) const { return std::clamp(static_cast<int>(std::floor((v - lo_.x()) / h_)), 0, nx_ - 1); }
  int cy(double v) const { return std::clamp(static_cast<int>(std::floor((v - lo_.y()) / h_)), 0, ny_ - 1); }
  Vec2 lo_, hi_;
  double h_ = 1;
  int nx_ = 1, ny_ = 1;
  std::vector<int> start_, seg_;
};

namespace {
// Where the ray o + t w crosses segment s of the closed polygon T: true with
// t and the fraction lam along the segment when the ray's line meets it.
bool ray_segment(const Vec2& o, const Vec2& w, const std::vector<Vec2>& T, std::size_t s, double& t, double& lam) {
  const Vec2 a = T[s] - o;
  const Vec2 d = T[(s + 1) % T.size()] - T[s];
  const double den = w.x() * d.y() - w.y() * d.x();
  if (den == 0) return false;
  t = (a.x() * d.y() - a.y() * d.x()) / den;
  lam = (a.x() * w.y() - a.y() * w.x()) / den;
  return lam >= 0 && lam <= 1;
}

// Unwraps arc-length parameters around a closed curve of perimeter per so
// that consecutive ones differ by less than half a turn; true when they go
// once around.
bool unwrap_once(std::vector<double>& s, double per) {
  const std::size_t n = s.size();
  auto wrap = [&](double d) { return d - per * std::floor(d / per + 0.5); };
  for (std::size_t i = 1; i < n; ++i) s[i] = s[i - 1] + wrap(s[i] - s[i - 1]);
  const double turn = s[n - 1] + wrap(s[0] - s[n - 1]) - s[0];
  return std::abs(turn - per) < 0.5 * per;
}
}  // namespace

// Arc-length parameters on T where the inward normals of the ring P first
// meet T, unwrapped (see detail.h).
std::vector<double> normal_hits(const std::vector<Vec2>& P, const std::vector<Vec2>& T, const std::vector<double>* halfwidth) {
  const int n = static_cast<int>(P.size());
  const std::size_t m = T.size();
  std::vector<double> sig(static_cast<std::size_t>(n), 0);
  const std::vector<double> cum = closed_arc_lengths(T);
  const double per = cum[m];
  if (n == 0 || m < 3 || !(per > 0)) return sig;
  // closest point of T to x, as an arc-length parameter
  auto closest = [&](const Vec2& x) {
    double best = std::numeric_limits<double>::infinity(), at = 0;
    for (std::size_t s = 0; s < m; ++s) {
      const Vec2 a = T[s], d = T[(s + 1) % m] - a;
      const double dd = d.squaredNorm();
      const double f = dd > 0 ? std::clamp((x - a).dot(d) / dd, 0.0, 1.0) : 0;
      const double e = (a + f * d - x).squaredNorm();
      if (e < best) best = e, at = cum[s] + f * (cum[s + 1] - cum[s]);
    }
    return at;
  };
  // the ring P as a closed polyline with arc length, for the windowed chords
  const std::vector<double> pcum = halfwidth ? closed_arc_lengths(P) : std::vector<double>{};
  auto p_at = [&](double x) { return point_at_arc(P, pcum, x); };
  // first crossing of the inward normal ray (counter-clockwise ring: inward is the left normal)
  const SegmentGrid grid(T);
  for (int i = 0; i < n; ++i) {
    Vec2 tan = P[static_cast<std::size_t>((i + 1) % n)] - P[static_cast<std::size_t>((i - 1 + n) % n)];
    if (halfwidth && pcum.back() > 0) {
      const double h = std::min((*halfwidth)[static_cast<std::size_t>(i)], 0.125 * pcum.back());
      const Vec2& pi = P[static_cast<std::size_t>(i)];
      const double step = 0.5 * ((P[static_cast<std::size_t>((i + 1) % n)] - pi).norm() +
                                 (pi - P[static_cast<std::size_t>((i - 1 + n) % n)]).norm());
      if (h > step) tan = p_at(pcum[static_cast<std::size_t>(i)] + h) - p_at(pcum[static_cast<std::size_t>(i)] - h);
    }
    Vec2 w(-tan.y(), tan.x());
    double best = -1, at = 0;
    if (w.norm() > 0) {
      w.normalize();
      std::size_t bs = m;
      grid.walk(P[static_cast<std::size_t>(i)], w, [&](const int* b, const int* e, double exit) {
        for (; b != e; ++b) {
          const std::size_t s = static_cast<std::size_t>(*b);
          double t, lam;
          // the first crossing; among equal ones the lowest segment (as a scan of all would)
          if (ray_segment(P[static_cast<std::size_t>(i)], w, T, s, t, lam) && t > 0 &&
              (best < 0 || t < best || (t == best && s < bs)))
            best = t, bs = s, at = cum[s] + lam * (cum[s + 1] - cum[s]);
        }
        return best > 0 && best <= exit;
      });
    }
    sig[static_cast<std::size_t>(i)] = best > 0 ? at : closest(P[static_cast<std::size_t>(i)]);
  }
  // unwrap around the ring; the parameters must go once around T
  if (unwrap_once(sig, per)) return sig;
  for (int i = 0; i < n; ++i) sig[static_cast<std::size_t>(i)] = closest(P[static_cast<std::size_t>(i)]);
  if (unwrap_once(sig, per)) return sig;
  for (int i = 1; i < n; ++i) sig[static_cast<std::size_t>(i)] = sig[0] + per * i / n;
  return sig;
}

std::vector<double> radial_hits(const std::vector<Vec2>& P, const std::vector<Vec2>& T, const Vec2& c) {
  const int n = static_cast<int>(P.size());
  const std::size_t m = T.size();
  std::vector<double> sig(static_cast<std::size_t>(n), 0);
  const std::vector<double> cum = closed_arc_lengths(T);
  const double per = cum[m];
  if (n == 0 || m < 3 || !(per > 0)) return sig;
  const SegmentGrid grid(T);
  for (int i = 0; i < n; ++i) {
    Vec2 w = P[static_cast<std::size_t>(i)] - c;
    if (w.norm() > 0) w.normalize();
    double best = -1, at = 0;
    std::size_t bs = m;
    // the outermost crossing (t >= 0; the whole ray is walked); among equal
    // ones the lowest segment (as a scan of all would)
    grid.walk(c, w, [&](const int* b, const int* e, double) {
      for (; b != e; ++b) {
        const std::size_t s = static_cast<std::size_t>(*b);
        double t, lam;
        if (ray_segment(c, w, T, s, t, lam) && t >= 0 && (t > best || (t == best && s < bs)))
          best = t, bs = s, at = cum[s] + lam * (cum[s + 1] - cum[s]);
      }
      return false;
    });
    sig[static_cast<std::size_t>(i)] = best >= 0 ? at : (i ? sig[static_cast<std::size_t>(i - 1)] : 0.0);
  }
  if (!unwrap_once(sig, per))
    for (int i = 1; i < n; ++i) sig[static_cast<std::size_t>(i)] = sig[0] + per * i / n;
  return sig;
}

namespace {
// the base shifted by whole turns to start next to x
std::vector<double> aligned(const std::vector<double>& base, const std::vector<double>& x, double per) {
  std::vector<double> b(base);
  if (b.empty() || x.empty()) return b;
  const double k = std::round((x[0] - b[0]) / per);
  for (auto& v : b) v += k * per;
  return b;
}
}  // namespace

double max_ordered_blend(const std::vector<double>& x, const std::vector<double>& base_in, double per,
                         double min_spacing_fraction, int steps) {
  const std::size_t n = x.size();
  if (n < 2) return 1;
  const std::vector<double> base = aligned(base_in, x, per);
  const double delta = min_spacing_fraction * per / static_cast<double>(n);
  for (int k = steps; k > 0; --k) {
    const double a = static_cast<double>(k) / steps;
    bool ok = true;
    for (std::size_t i = 0; i < n && ok; ++i) {
      const double xi = base[i] + a * (x[i] - base[i]);
      const double xj = i + 1 < n ? base[i + 1] + a * (x[i + 1] - base[i + 1]) : base[0] + per + a * (x[0] - base[0]);
      ok = xj - xi >= delta;
    }
    if (ok) return a;
  }
  return 0;
}

std::vector<double> ordered_blend(const std::vector<double>& x, const std::vector<double>& base_in, double per,
                                  double alpha, double min_spacing_fraction) {
  const int n = static_cast<int>(x.size());
  std::vector<double> sig(x);
  if (n < 2 || !(per > 0)) return sig;
  const std::vector<double> base = aligned(base_in, x, per);
  for (int i = 0; i < n; ++i) {
    const double b = base[static_cast<std::size_t>(i)];
    sig[static_cast<std::size_t>(i)] = b + alpha * (x[static_cast<std::size_t>(i)] - b);
  }
  // strictly increasing with spacing >= delta: start after the largest gap,
  // isotonic regression (pool adjacent violators) of s_i - i delta, then
  // compress into one turn if needed (a no-op where the blend is ordered)
  const double delta = min_spacing_fraction * per / n;
  auto gap = [&](int i) {  // sig[i] - sig[i-1], around
    return i == 0 ? sig[0] + per - sig[static_cast<std::size_t>(n - 1)] : sig[static_cast<std::size_t>(i)] - sig[static_cast<std::size_t>(i - 1)];
  };
  int start = 0;
  double gmax = -std::numeric_limits<double>::infinity();
  for (int i = 0; i < n; ++i)
    if (gap(i) > gmax) gmax = gap(i), start = i;
  std::vector<double> v(static_cast<std::size_t>(n));
  for (int q = 0; q < n; ++q) {
    const int i = (start + q) % n;
    v[static_cast<std::size_t>(q)] = sig[static_cast<std::size_t>(i)] + (i < start ? per : 0.0) - q * delta;
  }
  std::vector<double> val, wt;
  std::vector<int> cnt;
  for (int q = 0; q < n; ++q) {
    val.push_back(v[static_cast<std::size_t>(q)]), wt.push_back(1), cnt.push_back(1);
    while (val.size() > 1 && val[val.size() - 2] > val.back()) {
      const double w = wt[wt.size() - 2] + wt.back();
      val[val.size() - 2] = (val[val.size() - 2] * wt[wt.size() - 2] + val.back() * wt.back()) / w;
      wt[wt.size() - 2] = w;
      cnt[cnt.size() - 2] += cnt.back();
      val.pop_back(), wt.pop_back(), cnt.pop_back();
    }
  }
  for (std::size_t b = 0, q = 0; b < val.size(); ++b)
    for (int c = 0; c < cnt[b]; ++c, ++q) v[q] = val[b] + static_cast<double>(q) * delta;
  const double span = v[static_cast<std::size_t>(n - 1)] - v[0];
  if (span > per - delta && span > 0)
    for (int q = 1; q < n; ++q) v[static_cast<std::size_t>(q)] = v[0] + (v[static_cast<std::size_t>(q)] - v[0]) * (per - delta) / span;
  for (int q = 0; q < n; ++q) sig[static_cast<std::size_t>((start + q) % n)] = v[static_cast<std::size_t>(q)];
  return sig;
}

}  // namespace remesh_detail

namespace {

using remesh_detail::sample_loop;
using remesh_detail::tube_loop;

// cap_guard (the sweep along capped_alternative's axis): a refinement whose
// sections reach a flat cap (a loop point within the cap's crease of its
// plane) is undone and ends the refinement.
// A short tube (shorter than it is wide) breaks the refinement's premise that
// a tilted plane cuts a larger section: there a tilted plane leaves through
// the caps and cuts a smaller one, and the centreline ran off across the
// tube (64 -> 199 mm on a 64-slice stack of a 180 mm wide limb).
TubeSweep sweep_impl(const Surface& s, const Topology& topo, const Slicer& sl, const Axis& ax,
                     const RemeshOptions& o, const std::string& name, bool cap_guard = false) {
  // extent along the principal axis
  double t0 = 1e300, t1 = -1e300;
  for (int v = 0; v < s.vertices.rows(); ++v) {
    const double t = (s.vertices.row(v).transpose() - ax.m).dot(ax.d);
    t0 = std::min(t0, t), t1 = std::max(t1, t);
  }
  const double extent = t1 - t0;
  if (!(extent > 0)) throw Error(name, "not tube-like: the surface is flat");
  const FaceData fd = face_data(s, topo);
  Cap caps[2] = {detect_cap(s, topo, fd, -ax.d, o.cap_angle_deg, extent),
                 detect_cap(s, topo, fd, ax.d, o.cap_angle_deg, extent)};

  // a cap is flat when its planar patch is at least half as large as the
  // middle section
  {
    const SweepPlane mid = make_plane(ax.m + 0.5 * (t0 + t1) * ax.d, ax.d, reference_perpendicular(ax.d));
    const auto loops = sl.slice(mid);
    const double amid = loops.empty() ? 0 : std::abs(loops[0].area);
    for (auto& c : caps) c.flat = amid > 0 && c.area >= 0.5 * amid;
  }
  // first pass: sections normal to the principal axis, largest loop, between
  // the flat caps (a plane through a tilted cap would mix cap and wall)
  double ta = t0, tb = t1;
  for (int e = 0; e < 2; ++e) {
    if (!caps[e].flat) continue;
    for (int f : caps[e].faces)
      for (int k = 0; k < 3; ++k) {
        const double t = (s.vertices.row(s.faces(f, k)).transpose() - ax.m).dot(ax.d);
        if (e == 0) ta = std::max(ta, t);
        if (e == 1) tb = std::min(tb, t);
      }
  }
  if (!(tb > ta)) ta = t0, tb = t1;
  const int K = o.axis_sections;
  std::vector<Vec3> pts;
  std::vector<double> areas;
  std::vector<SweepPlane> first(static_cast<std::size_t>(K));
  for (int k = 0; k < K; ++k) {
    const double t = ta + (k + 0.5) / K * (tb - ta);
    first[static_cast<std::size_t>(k)] = make_plane(ax.m + t * ax.d, ax.d, reference_perpendicular(ax.d));
  }
  const std::vector<std::vector<Loop>> first_loops = remesh_detail::slice_all(sl, first);
  for (int k = 0; k < K; ++k) {
    const SweepPlane& pl = first[static_cast<std::size_t>(k)];
    const auto& loops = first_loops[static_cast<std::size_t>(k)];
    if (loops.empty()) continue;
    const Loop& l = loops[0];
    pts.push_back(pl.centre + l.centroid.x() * pl.e1 + l.centroid.y() * pl.e2);
    areas.push_back(std::abs(l.area));
  }
  if (pts.size() < 2) throw Error(name, "not tube-like: too few sections cut the surface");
  double radius[2] = {std::sqrt(areas.front() / kPi), std::sqrt(areas.back() / kPi)};

  auto build_curve = [&](const std::vector<Vec3>& p) {
    const Vec3* front = caps[0].flat ? &caps[0].q : nullptr;
    const Vec3* back = caps[1].flat ? &caps[1].q : nullptr;
    const Vec3* d0 = caps[0].flat ? &caps[0].n : nullptr;
    const Vec3* d1 = caps[1].flat ? &caps[1].n : nullptr;
    Curve c(p, 2.0, front, back, d0, d1);
    // open (rounded) ends: extend straight until the end plane passes every vertex
    Vec3 ext[2];
    bool extended = false;
    for (int e = 0; e < 2; ++e) {
      if (caps[e].flat) continue;
      const double se = e == 0 ? 0 : c.length();
      const Vec3 x = c.point(se), tt = c.tangent(se) * (e == 0 ? -1.0 : 1.0);
      double beyond = 0;
      for (int v = 0; v < s.vertices.rows(); ++v)
        beyond = std::max(beyond, (s.vertices.row(v).transpose() - x).dot(tt));
      ext[e] = x + (beyond * (1 + 1e-6) + 1e-9 * extent) * tt;
      if (e == 0) front = &ext[0];
      if (e == 1) back = &ext[1];
      extended = true;
    }
    return extended ? Curve(p, 2.0, front, back, d0, d1) : c;
  };
  Curve curve = build_curve(pts);

  // refinement: centroids of sections normal to the current axis. The true
  // axis makes the sections normal to it smallest (a tilted plane cuts a
  // larger section), so a refinement is kept only while the total section
  // area falls; a pass that raises it (the centroid iteration can oscillate
  // on tapering, non-circular sections near flat caps) is undone and the
  // refinement stops there.
  std::vector<double> sec_s, sec_a;
  double rmax = 0;  // largest distance from the axis to the surface over all these sections
  Curve prev_curve = curve;
  std::vector<double> prev_s, prev_a;
  double prev_total = std::numeric_limits<double>::infinity();
  for (int it = 0; it <= o.axis_iterations; ++it) {
    bool beyond_cap = false;
    const NormalField nf = normal_field(curve, caps, radius);
    std::vector<Vec3> next;
    sec_s.clear(), sec_a.clear();
    std::vector<SweepPlane> sec(static_cast<std::size_t>(K));
    for (int k = 0; k < K; ++k) {
      const double sk = (k + 0.5) / K * curve.length();
      sec[static_cast<std::size_t>(k)] = make_plane(curve.point(sk), nf(sk), reference_perpendicular(nf(sk)));
    }
    const std::vector<std::vector<Loop>> sec_loops = remesh_detail::slice_all(sl, sec);
    for (int k = 0; k < K; ++k) {
      const double sk = (k + 0.5) / K * curve.length();
      const SweepPlane& pl = sec[static_cast<std::size_t>(k)];
      const auto& loops = sec_loops[static_cast<std::size_t>(k)];
      const Loop* l = nullptr;
      for (const auto& c : loops)
        if (remesh_detail::winding(c, Vec2(0, 0)) != 0) {
          l = &c;
          break;
        }
      if (!l) continue;
      if (cap_guard)
        for (int e = 0; e < 2 && !beyond_cap; ++e) {
          if (!caps[e].flat) continue;
          const double tol = std::max(caps[e].crease, 1e-3 * extent);
          for (const Vec2& q : l->q)
            if ((pl.centre + q.x() * pl.e1 + q.y() * pl.e2 - caps[e].q).dot(caps[e].n) < tol) {  // on the cap
              beyond_cap = true;
              break;
            }
        }
      next.push_back(pl.centre + l->centroid.x() * pl.e1 + l->centroid.y() * pl.e2);
      for (const Vec2& q : l->q) rmax = std::max(rmax, q.norm());
      sec_s.push_back(sk);
      sec_a.push_back(std::abs(l->area));
    }
    if (next.size() < 2) throw Error(name, "not tube-like: the sections do not surround an axis");
    // mean area per unit length of axis, comparable between curves of different length
    double total = 0;
    for (double a : sec_a) total += a;
    total /= static_cast<double>(sec_a.size());
    if (it > 0 && (!(total < prev_total) || beyond_cap)) {
      curve = prev_curve, sec_s = prev_s, sec_a = prev_a;
      break;
    }
    if (it == o.axis_iterations) break;  // last pass only measures the section areas
    prev_curve = curve, prev_s = sec_s, prev_a = sec_a, prev_total = total;
    curve = build_curve(next);
    radius[0] = std::sqrt(sec_a.front() / kPi), radius[1] = std::sqrt(sec_a.back() / kPi);
  }

  // sweep range: flat caps at the ends of the curve, open ends trimmed where
  // the section area falls below end_area_fraction of the largest
  const double L = curve.length();
  const double amax = *std::max_element(sec_a.begin(), sec_a.end());
  const double athr = o.end_area_fraction * amax;
  double sa = 0, sb = L;
  if (!caps[0].flat) {
    double ps = 0, pa = 0;
    for (std::size_t k = 0; k < sec_s.size(); ++k) {
      if (sec_a[k] >= athr) {
        sa = ps + (athr - pa) / (sec_a[k] - pa) * (sec_s[k] - ps);
        break;
      }
      ps = sec_s[k], pa = sec_a[k];
    }
  }
  if (!caps[1].flat) {
    double ps = L, pa = 0;
    for (std::size_t k = sec_s.size(); k-- > 0;) {
      if (sec_a[k] >= athr) {
        sb = ps - (athr - pa) / (sec_a[k] - pa) * (ps - sec_s[k]);
        break;
      }
      ps = sec_s[k], pa = sec_a[k];
    }
  }
  if (!(sb > sa)) throw Error(name, "not tube-like: no part of the axis has a full section");

  // the table: centres (moved so that flat-cap end planes sit kCapInset*L
  // inside the caps), blended normals, rotation-minimising frames
  const NormalField nfield = normal_field(curve, caps, radius);
  double inset[2];
  for (int e = 0; e < 2; ++e)
    inset[e] = o.ends == EndRings::crease ? std::clamp(caps[e].crease, kCapInset * L, kMaxCreaseInset * L) : kCapInset * L;
  double delta[2] = {0, 0};
  if (caps[0].flat) delta[0] = (curve.point(0) - caps[0].q).dot(nfield.n[0]) - inset[0];
  if (caps[1].flat) delta[1] = (curve.point(L) - caps[1].q).dot(nfield.n[1]) + inset[1];
  TubeSweep sw;
  sw.length_m = sb - sa;
  sw.axis_direction = ax.d;
  sw.flat_cap = {caps[0].flat, caps[1].flat};
  sw.cap_inset_m = {caps[0].flat ? inset[0] : 0.0, caps[1].flat ? inset[1] : 0.0};
  sw.s.resize(kTable);
  sw.centre.resize(kTable, 3);
  sw.normal.resize(kTable, 3);
  sw.e1.resize(kTable, 3);
  std::vector<Vec3> tang(kTable);
  std::vector<double> wa(kTable), wb(kTable);
  for (int i = 0; i < kTable; ++i) {
    const double sc = sa + (sb - sa) * i / (kTable - 1);
    sw.s(i) = sc - sa;
    Vec3 c = curve.point(sc) - delta[0] * nfield.w0(sc) * nfield.n[0] - delta[1] * nfield.w1(sc) * nfield.n[1];
    sw.centre.row(i) = c;
    sw.normal.row(i) = nfield(sc);
    tang[static_cast<std::size_t>(i)] = curve.tangent(sc);
    wa[static_cast<std::size_t>(i)] = nfield.w0(sc), wb[static_cast<std::size_t>(i)] = nfield.w1(sc);
  }
  sw.s(kTable - 1) = sw.length_m;
  // Planes must not cross inside the tube: a point at distance R from the
  // axis on plane i lies on the far side of plane i+1 once R sin(angle between
  // their normals) exceeds their spacing on the axis, and a fine grid puts
  // rings there that cross (the quads fold). Where the section centroids wander
  // (a segmented limb's staircase, taper), the smoothed centreline still turns
  // too fast for the limb's radius, so the tangent part of the normal field is
  // averaged over a growing window (doubling) until R_max |dn/ds| <=
  // o.max_plane_turn everywhere, R_max the largest distance from the axis to
  // the surface on the refinement's sections. The cap
  // blend is kept, so end planes stay the caps.
  {
    auto turn = [&]() {
      double worst = 0;
      for (int i = 0; i + 1 < kTable; ++i) {
        const Vec3 n0 = sw.normal.row(i), n1 = sw.normal.row(i + 1);
        const double gap = (sw.centre.row(i + 1) - sw.centre.row(i)).dot(n1);
        const double sn = n0.cross(n1).norm();
        if (sn > 0) worst = std::max(worst, gap > 0 ? rmax * sn / gap : std::numeric_limits<double>::infinity());
      }
      return worst;
    };
    std::vector<Vec3> prefix(kTable + 1, Vec3::Zero());
    for (int i = 0; i < kTable; ++i) prefix[static_cast<std::size_t>(i + 1)] = prefix[static_cast<std::size_t>(i)] + tang[static_cast<std::size_t>(i)];
    sw.plane_turn = turn();
    for (int h = 4; sw.plane_turn > o.max_plane_turn && h < kTable; h *= 2) {
      for (int i = 0; i < kTable; ++i) {
        const int w = std::min({h, i, kTable - 1 - i});  // centred window, shrinking at the ends
        Vec3 t = prefix[static_cast<std::size_t>(i + w + 1)] - prefix[static_cast<std::size_t>(i - w)];
        if (!(t.norm() > 0)) t = tang[static_cast<std::size_t>(i)];
        const double a = wa[static_cast<std::size_t>(i)], b = wb[static_cast<std::size_t>(i)];
        Vec3 v = (1 - a - b) * t.normalized() + a * nfield.n[0] + b * nfield.n[1];
        if (!(v.norm() > 1e-9)) v = t;
        sw.normal.row(i) = v.normalized();
      }
      sw.plane_turn = turn();
      sw.normal_window_m = (2 * h + 1) * (sb - sa) / (kTable - 1);
    }
  }
  // double reflection (Wang, Juettler, Zheng, Liu 2008), tangents = plane normals
  Vec3 r = reference_perpendicular(sw.normal.row(0).transpose());
  sw.e1.row(0) = r;
  for (int i = 0; i + 1 < kTable; ++i) {
    const Vec3 x0 = sw.centre.row(i), x1 = sw.centre.row(i + 1);
    const Vec3 t0v = sw.normal.row(i), t1v = sw.normal.row(i + 1);
    const Vec3 v1 = x1 - x0;
    const double c1 = v1.dot(v1);
    Vec3 rL = r, tL = t0v;
    if (c1 > 0) {
      rL = r - (2 / c1) * v1.dot(r) * v1;
      tL = t0v - (2 / c1) * v1.dot(t0v) * v1;
    }
    const Vec3 v2 = t1v - tL;
    const double c2 = v2.dot(v2);
    r = c2 > 0 ? Vec3(rL - (2 / c2) * v2.dot(rL) * v2) : rL;
    r = (r - r.dot(t1v) * t1v).normalized();
    sw.e1.row(i + 1) = r;
  }
  return sw;
}

}  // namespace

void validate(const RemeshOptions& o) {
  auto bad = [](const std::string& what) { throw Error("", what); };
  if (o.nu < 3 || o.nu > 10000) bad("grid: nu (points around) must be in 3..10000, got " + std::to_string(o.nu));
  if (o.nv < 2 || o.nv > 10000) bad("grid: nv (rings along) must be in 2..10000, got " + std::to_string(o.nv));
  if (!(o.max_spacing_ratio >= 1) || !std::isfinite(o.max_spacing_ratio)) bad("max_spacing_ratio must be >= 1");
  if (o.axis_sections < 8 || o.axis_sections > 4096) bad("axis_sections must be in 8..4096");
  if (o.axis_iterations < 0 || o.axis_iterations > 20) bad("axis_iterations must be in 0..20");
  if (o.arc_window < 0 || o.arc_window > 64) bad("arc_window must be in 0..64");
  if (!(o.end_area_fraction > 0 && o.end_area_fraction < 1)) bad("end_area_fraction must be in (0, 1)");
  if (!(o.cap_angle_deg > 0 && o.cap_angle_deg < 45)) bad("cap_angle_deg must be in (0, 45)");
  if (!(o.fill_max_depth_fraction > 0 && o.fill_max_depth_fraction < 1))
    bad("fill_max_depth_fraction must be in (0, 1)");
  if (!(o.min_ring_spacing_fraction > 0 && o.min_ring_spacing_fraction < 1))
    bad("min_ring_spacing_fraction must be in (0, 1)");
  if (!(o.max_plane_turn > 0 && o.max_plane_turn < 1)) bad("max_plane_turn must be in (0, 1)");
}

SweepPlane sweep_plane(const TubeSweep& sw, double s) {
  const int n = static_cast<int>(sw.s.size());
  const double x = sw.length_m > 0 ? std::clamp(s / sw.length_m, 0.0, 1.0) * (n - 1) : 0;
  const int i = std::min(static_cast<int>(x), n - 2);
  const double f = x - i;
  const Vec3 c = (1 - f) * sw.centre.row(i) + f * sw.centre.row(i + 1);
  const Vec3 nn = (1 - f) * sw.normal.row(i) + f * sw.normal.row(i + 1);
  const Vec3 e = (1 - f) * sw.e1.row(i) + f * sw.e1.row(i + 1);
  return make_plane(c, nn, e);
}

namespace {

// The sweep along capped_alternative's axis where there is one and its ring
// planes do not cross inside the tube; else from the principal axis, and
// where that fails or finds no flat cap at either end, from the alternative
// axis again (check_alternative_sweep).
// slice(axis) gives the outer surface's slicer along an axis, valid until the
// next call (the layered remesh slices its inner layers there too).
template <class Slice>
TubeSweep sweep_from_axes(const Surface& s, const Topology& topo, const RemeshOptions& o, const std::string& name,
                          Slice&& slice) {
  const Axis ax = principal_axis(s);
  // Capped at both ends along another direction than the principal axis
  // (none if the principal axis is): the flat caps' normal gives the tube's
  // axis at its ends, so that sweep goes first, and it stands where its ring
  // planes do not cross inside the tube (R |dn/ds| < 1; above max_plane_turn
  // the rings come closer at the surface than the margin asks, and the sweep
  // reports it). A limb as long as it is wide tilted its principal axis 8.6
  // degrees off the slices' normal; the sweep along it wandered to 81.6 mm on
  // a 63 mm stack and its rings cut the skin in two loops or put the bone
  // outside the muscle, depending on the noise alone; along the caps' normal
  // its planes turn by 0.74.
  const auto alt = capped_alternative(s, topo, ax, o);
  TubeSweep alt_sw;
  std::exception_ptr alt_error;  // the alternative sweep failed: the principal axis may still do
  if (alt) {
    try {
      alt_sw = sweep_impl(s, topo, slice(*alt), *alt, o, name, /*cap_guard=*/true);
      if (alt_sw.plane_turn < 1) return alt_sw;
    } catch (const Error&) {
      alt_error = std::current_exception();
    }
  }
  TubeSweep sw;
  std::exception_ptr first;
  try {
    sw = sweep_impl(s, topo, slice(ax), ax, o, name);
  } catch (const Error&) {
    first = std::current_exception();
  }
  if (first || (!sw.flat_cap[0] && !sw.flat_cap[1])) {
    if (alt_error) {
      std::rethrow_exception(alt_error);
    } else if (alt) {
      // its planes cross (R |dn/ds| >= 1 > max_plane_turn): this throws, with
      // the principal sweep's error where that failed
      check_alternative_sweep(alt_sw, o, name, first, spans(s, *alt));
    } else if (first) {
      std::rethrow_exception(first);
    }
  }
  return sw;
}

}  // namespace

TubeSweep find_tube_sweep(const Surface& outer, const RemeshOptions& o, const std::string& name) {
  validate(o);
  const Topology topo = remesh_detail::build_topology(outer, name, true);
  std::optional<Slicer> sl;
  TubeSweep sw = sweep_from_axes(outer, topo, o, name, [&](const Axis& a) -> const Slicer& {
    sl.emplace(outer, topo, a.m, a.d);
    return *sl;
  });
  sw.uncovered_m2 = {sw.flat_cap[0] ? 0.0 : area_behind(outer, sweep_plane(sw, 0)),
                     sw.flat_cap[1] ? 0.0 : [&] {
                       SweepPlane p = sweep_plane(sw, sw.length_m);
                       p.normal = -p.normal;
                       return area_behind(outer, p);
                     }()};
  return sw;
}

// ---- the layered grids -------------------------------------------------------

namespace {

// Convex hull of the points of several loops (plane frame), counter-clockwise
// (Andrew's monotone chain), as a Loop with its area and area centroid, and
// per hull edge q[v] q[v+1] the loop it lies on (the edge joins consecutive
// points of that loop), -1 where it bridges between loops. Empty (and `on`
// empty) when the points span no area.
Loop convex_hull_loop(const std::vector<Loop>& loops, std::vector<int>& on) {
  struct P2 {
    Vec2 q;
    int loop, idx;
  };
  std::vector<P2> p;
  for (std::size_t li = 0; li < loops.size(); ++li)
    for (std::size_t qi = 0; qi < loops[li].q.size(); ++qi)
      p.push_back({loops[li].q[qi], static_cast<int>(li), static_cast<int>(qi)});
  std::sort(p.begin(), p.end(), [](const P2& x, const P2& y) {
    return x.q.x() < y.q.x() || (x.q.x() == y.q.x() && x.q.y() < y.q.y());
  });
  auto cross = [](const Vec2& o, const Vec2& a, const Vec2& b) {
    return (a.x() - o.x()) * (b.y() - o.y()) - (a.y() - o.y()) * (b.x() - o.x());
  };
  std::vector<P2> h(2 * p.size() + 1);
  std::size_t k = 0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    while (k >= 2 && cross(h[k - 2].q, h[k - 1].q, p[i].q) <= 0) --k;
    h[k++] = p[i];
  }
  for (std::size_t i = p.size() - 1, t = k + 1; i-- > 0;) {
    while (k >= t && cross(h[k - 2].q, h[k - 1].q, p[i].q) <= 0) --k;
    h[k++] = p[i];
  }
  Loop hull;
  on.clear();
  if (k < 4) return hull;
  h.resize(k - 1);
  for (std::size_t v = 0; v < h.size(); ++v) {
    const P2& x = h[v];
    const P2& y = h[(v + 1) % h.size()];
    const int ns = static_cast<int>(loops[static_cast<std::size_t>(x.loop)].q.size());
    hull.q.push_back(x.q);
    on.push_back(x.loop == y.loop && (x.idx + 1) % ns == y.idx ? x.loop : -1);
  }
  remesh_detail::set_area_centroid(hull);
  return hull;
}

QuadSurface make_grid(int nu, int nv, const std::vector<Vec3>& x, const VecXd& stations, double length) {
  QuadSurface q;
  q.nu = nu;
  q.nv = nv;
  q.vertices.resize(static_cast<Eigen::Index>(nu) * nv, 3);
  q.uv.resize(static_cast<Eigen::Index>(nu) * nv, 2);
  for (int j = 0; j < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      const Eigen::Index r = static_cast<Eigen::Index>(j) * nu + i;
      q.vertices.row(r) = x[r];
      q.uv(r, 0) = static_cast<double>(i) / nu;
      q.uv(r, 1) = length > 0 ? stations(j) / length : 0;
    }
  q.quads.resize(static_cast<Eigen::Index>(nu) * (nv - 1), 4);
  for (int j = 0; j + 1 < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      const int i1 = (i + 1) % nu;
      q.quads.row(static_cast<Eigen::Index>(j) * nu + i) << j * nu + i, j * nu + i1, (j + 1) * nu + i1,
          (j + 1) * nu + i;
    }
  return q;
}

// Stations s_0 = 0 < ... < s_{nv-1} = L. Adaptive: equidistribute
// m(s) = sqrt(g(s) + mean g), g = RMS of |d2p/ds2| over a ring, with the
// ratio of largest to smallest spacing bounded by o.max_spacing_ratio.
VecXd place_stations(const TubeSweep& sw, const Slicer& sl, const RemeshOptions& o, const std::string& name) {
  const int nv = o.nv;
  const double L = sw.length_m;
  VecXd st(nv);
  for (int j = 0; j < nv; ++j) st(j) = L * j / (nv - 1);
  if (!o.adaptive || nv <= 2) return st;
  const int K = std::max(32, o.axis_sections), M = 32;
  std::vector<double> u(M);
  for (int i = 0; i < M; ++i) u[i] = static_cast<double>(i) / M;
  std::vector<std::vector<Vec3>> ring(K);
  const double ds = L / (K - 1);
  std::vector<SweepPlane> planes(static_cast<std::size_t>(K));
  for (int k = 0; k < K; ++k) planes[static_cast<std::size_t>(k)] = sweep_plane(sw, k * ds);
  const std::vector<std::vector<Loop>> loops = remesh_detail::slice_all(sl, planes);
  for (int k = 0; k < K; ++k)
    sample_loop(tube_loop(loops[static_cast<std::size_t>(k)], name, k * ds, L), planes[static_cast<std::size_t>(k)], o.around,
                o.arc_window, u, ring[k], nullptr, name);
  std::vector<double> g(K, 0);
  for (int k = 1; k + 1 < K; ++k) {
    double acc = 0;
    for (int i = 0; i < M; ++i) acc += (ring[k + 1][i] - 2 * ring[k][i] + ring[k - 1][i]).squaredNorm();
    g[k] = std::sqrt(acc / M) / (ds * ds);
  }
  g[0] = g[1], g[K - 1] = g[K - 2];
  for (int pass = 0; pass < 2; ++pass) {  // [1 2 1] smoothing
    std::vector<double> h(g);
    for (int k = 1; k + 1 < K; ++k) h[k] = 0.25 * g[k - 1] + 0.5 * g[k] + 0.25 * g[k + 1];
    g = h;
  }
  // floor: the mean, plus a fraction of the curvature around (1 / mean radius),
  // so that bending far below the around curvature leaves the rings evenly spaced
  double rsum = 0;
  for (int k = 0; k < K; ++k) {
    const SweepPlane pl = sweep_plane(sw, k * ds);
    for (int i = 0; i < M; ++i) rsum += (ring[k][i] - pl.centre).norm();
  }
  const double rmean = rsum / (K * M);
  const double gm = std::accumulate(g.begin(), g.end(), 0.0) / K + (rmean > 0 ? 0.05 / rmean : 0);
  if (!(gm > 0)) return st;
  std::vector<double> m(K);
  for (int k = 0; k < K; ++k) m[k] = std::sqrt(g[k] + gm);
  const double mmin = *std::min_element(m.begin(), m.end());
  for (auto& x : m) x = std::min(x, mmin * o.max_spacing_ratio);
  std::vector<double> cum(K, 0);
  for (int k = 1; k < K; ++k) cum[k] = cum[k - 1] + 0.5 * (m[k] + m[k - 1]) * ds;
  for (int j = 1; j + 1 < nv; ++j) {
    const double target = cum.back() * j / (nv - 1);
    const int k = static_cast<int>(std::upper_bound(cum.begin(), cum.end(), target) - cum.begin());
    const int k1 = std::clamp(k, 1, K - 1);
    const double f = (target - cum[k1 - 1]) / (cum[k1] - cum[k1 - 1]);
    st(j) = (k1 - 1 + f) * ds;
  }
  st(0) = 0, st(nv - 1) = L;
  return st;
}

}  // namespace

RemeshResult remesh_layers(const std::vector<NamedSurface>& layers, const RemeshOptions& o) {
  validate(o);
  if (layers.empty()) throw Error("", "no surface to remesh");
  auto t0 = std::chrono::steady_clock::now();
  const auto t_start = t0;
  RemeshResult res;
  const int nl = static_cast<int>(layers.size());
  // Two branches side by side: (A) the outer layer's topology, then its axis
  // (which starts the inner layers' slicers as tasks: they need only the axis
  // and their surface), sweep and stations; (B) the inner layers' topologies
  // and each inner layer's containment in the one above. On 2 cores the axis's sequential
  // parts fill the gaps of the checks. Errors are reported as a sequential run
  // would: topology in layer order, then containment, then the axis.
  std::vector<Topology> topo(static_cast<std::size_t>(nl));
  std::vector<std::exception_ptr> topo_err(static_cast<std::size_t>(nl)), contain_err(static_cast<std::size_t>(nl));
  std::exception_ptr axis_err;
  auto capture = [](std::exception_ptr& e, auto&& f) {
    try {
      f();
    } catch (...) {
      e = std::current_exception();
    }
  };
  Axis ax;
  std::vector<std::unique_ptr<Slicer>> slicers(static_cast<std::size_t>(nl));
  tbb::task_group inner_slicers;
  tbb::parallel_invoke(
      [&] {
        capture(topo_err[0], [&] {
          topo[0] = remesh_detail::build_topology(layers[0].surface, layers[0].name, true);
          if (topo[0].check.euler != 2)
            throw Error(layers[0].name, "not tube-like: the surface has " + std::to_string((2 - topo[0].check.euler) / 2) +
                                            " handle(s) (Euler characteristic " + std::to_string(topo[0].check.euler) +
                                            "); remesh needs a tube closed at both ends");
        });
        if (topo_err[0]) return;
        const auto ta = std::chrono::steady_clock::now();
        capture(axis_err, [&] {
          // the inner layers' slicers along the sweep's axis, beside the
          // sweep and the checks (a layer with a face id out of range or a
          // non-finite vertex gets none: its topology reports it)
          res.sweep = sweep_from_axes(layers[0].surface, topo[0], o, layers[0].name, [&](const Axis& a) -> const Slicer& {
            inner_slicers.wait();  // the slicers of an earlier axis read ax
            ax = a;
            for (int k = 1; k < nl; ++k)
              if (const Surface& sk = layers[k].surface; sk.faces.size() > 0 && sk.faces.minCoeff() >= 0 &&
                                                        sk.faces.maxCoeff() < sk.vertices.rows() && sk.vertices.allFinite())
                inner_slicers.run([&, k] {
                  slicers[static_cast<std::size_t>(k)] = std::make_unique<Slicer>(layers[k].surface, topo[k], ax.m, ax.d);
                });
            slicers[0] = std::make_unique<Slicer>(layers[0].surface, topo[0], ax.m, ax.d);
            return *slicers[0];
          });
          const TubeSweep& sw = res.sweep;
          SweepPlane pa = sweep_plane(sw, 0), pb = sweep_plane(sw, sw.length_m);
          pb.normal = -pb.normal;
          res.sweep.uncovered_m2 = {sw.flat_cap[0] ? 0.0 : area_behind(layers[0].surface, pa),
                                    sw.flat_cap[1] ? 0.0 : area_behind(layers[0].surface, pb)};
          res.stations_m = place_stations(sw, *slicers[0], o, layers[0].name);
        });
        res.axis_s = seconds_since(ta);
      },
      [&] {
        // the inner layers' topologies and containment tests, all side by
        // side: points_inside refuses a surface it cannot read, and a failed
        // check of the layer above is reported before the containment
        tbb::parallel_for(0, 2 * (nl - 1), [&](int task) {
          const int k = 1 + task % (nl - 1);
          if (task >= nl - 1) {
            capture(topo_err[static_cast<std::size_t>(k)], [&] {
              topo[static_cast<std::size_t>(k)] = remesh_detail::build_topology(layers[k].surface, layers[k].name, false);
            });
            return;
          }
          capture(contain_err[static_cast<std::size_t>(k)], [&] {
            const Surface& outer = layers[k - 1].surface;
            const MatX3d& pts = layers[k].surface.vertices;
            const std::vector<char> in = points_inside(outer, pts);
            std::vector<Eigen::Index> out;
            for (std::size_t i = 0; i < in.size(); ++i)
              if (!in[i]) out.push_back(static_cast<Eigen::Index>(i));
            const double size = outer.vertices.rows() > 0
                                    ? (outer.vertices.colwise().maxCoeff() - outer.vertices.colwise().minCoeff()).norm()
                                    : 0.0;
            const double tol = 1e-6 * size;  // (below)
            if (out.empty()) {
              // inside, but the same surface? Up to 1024 of its vertices all on the
              // outer one: no thickness between the layers (the same STL given twice
              // passed, and build refused its "depth -4e-18 m")
              const Eigen::Index n = pts.rows(), stride = std::max<Eigen::Index>(1, n / 1024);
              MatX3d q((n + stride - 1) / stride, 3);
              for (Eigen::Index i = 0, r = 0; i < n; i += stride, ++r) q.row(r) = pts.row(i);
              if (q.rows() > 0 && remesh_detail::all_on_surface(outer, q, tol))
                throw Error(layers[k].name, "lies on " + layers[k - 1].name +
                                                ": every vertex sampled is on its surface, no thickness between the "
                                                "layers (the same surface twice?)");
              return;
            }
            // a non-finite vertex is outside, and no distance is taken of it
            // (CGAL's exact fallback traps on a NaN); its layer's own check names it
            for (const Eigen::Index i : out)
              if (!pts.row(i).allFinite()) {
                std::ostringstream m;
                m << "not inside " << layers[k - 1].name << ": vertex " << i << " has a non-finite coordinate";
                throw Error(layers[k].name, m.str());
              }
            // The test is exact; a vertex on the outer surface but for the
            // rounding of its coordinates (the layers share their cap planes,
            // and an STL's float32 moved a tilted cap's vertex 2e-12 m off
            // it: refused as "not inside") is on it. The tolerance is a
            // millionth of the outer surface's size, far below any voxel.
            MatX3d q(static_cast<Eigen::Index>(out.size()), 3);
            for (std::size_t i = 0; i < out.size(); ++i) q.row(static_cast<Eigen::Index>(i)) = pts.row(out[i]);
            const std::vector<double> d = remesh_detail::distances_to_surface(outer, q);
            for (std::size_t i = 0; i < out.size(); ++i) {
              if (d[i] <= tol) continue;
              const Vec3 p = pts.row(out[i]);
              std::ostringstream m;
              m.precision(4);
              m << "not inside " << layers[k - 1].name << ": vertex " << out[i] << " at (" << p.x() * 1e3 << ", "
                << p.y() * 1e3 << ", " << p.z() * 1e3 << ") mm lies outside it, " << d[i] * 1e3 << " mm from it";
              throw Error(layers[k].name, m.str());
            }
          });
        });
        res.check_s = seconds_since(t0);
      });
  inner_slicers.wait();
  for (const auto* errs : {&topo_err, &contain_err})
    for (const auto& e : *errs)
      if (e) std::rethrow_exception(e);
  if (axis_err) std::rethrow_exception(axis_err);
  for (int k = 1; k < nl; ++k)  // every layer that passed its checks has one
    if (!slicers[static_cast<std::size_t>(k)]) throw Error(layers[k].name, "internal: the layer was not sliced");
  const TubeSweep& sw = res.sweep;
  t0 = std::chrono::steady_clock::now();

  const int nu = o.nu, nv = o.nv;
  const double L = sw.length_m;
  std::vector<double> u(nu);
  for (int i = 0; i < nu; ++i) u[i] = static_cast<double>(i) / nu;
  std::vector<SweepPlane> planes(nv);
  res.ring_centre.resize(nv, 3);
  res.ring_normal.resize(nv, 3);
  std::vector<std::vector<Vec3>> pts(nl, std::vector<Vec3>(static_cast<std::size_t>(nu) * nv));
  res.ray_origin.assign(nl, MatX3d(nv, 3));
  res.stats.resize(nl);
  for (int k = 0; k < nl; ++k) {
    res.stats[k].name = layers[k].name;
    res.stats[k].components = topo[k].check.components;
  }

  // outer rings, side by side (the first failing ring is reported)
  auto each_ring = [nv, &capture](auto&& f) {
    std::vector<std::exception_ptr> err(static_cast<std::size_t>(nv));
    tbb::parallel_for(0, nv, [&](int j) { capture(err[static_cast<std::size_t>(j)], [&] { f(j); }); });
    for (const auto& e : err)
      if (e) std::rethrow_exception(e);
  };
  for (int j = 0; j < nv; ++j) {
    planes[j] = sweep_plane(sw, res.stations_m(j));
    res.ring_centre.row(j) = planes[j].centre;
    res.ring_normal.row(j) = planes[j].normal;
    res.ray_origin[0].row(j) = planes[j].centre;
  }
  // inner layers: in each ring plane, vertex (i, j) of layer k is where the
  // in-plane inward normal of layer k-1's ring at vertex i first meets layer
  // k's target curve (the section loop, or the envelope of several loops),
  // with the order around the ring made strictly monotone (no crossing
  // correspondences). The target of every layer in every ring is kept: it is
  // the bound for the envelope of the layer below.
  std::vector<std::vector<Vec2>> prev_target(nv);  // layer k-1's section in ring j (plane frame), empty if filled
  std::vector<std::int64_t> side(static_cast<std::size_t>(nv), 0);  // side loops left out, per ring
  each_ring([&](int j) {
    const auto loops = slicers[0]->slice(planes[j]);
    const Loop& l = tube_loop(loops, layers[0].name, res.stations_m(j), L);
    side[static_cast<std::size_t>(j)] = static_cast<std::int64_t>(loops.size()) - 1;
    std::vector<Vec3> ring;
    sample_loop(l, planes[j], o.around, o.arc_window, u, ring, nullptr, layers[0].name);
    std::copy(ring.begin(), ring.end(), pts[0].begin() + static_cast<std::ptrdiff_t>(j) * nu);
    prev_target[j] = l.q;
  });
  res.stats[0].hit = static_cast<std::int64_t>(nu) * nv;
  res.side_loops = std::accumulate(side.begin(), side.end(), std::int64_t{0});
  for (int k = 1; k < nl; ++k) {
    const std::string& name = layers[k].name;
    std::vector<char> has(nv, 0);
    std::vector<Vec2> origin(nv, Vec2::Zero());                          // plane frame
    std::vector<Vec2> q2(static_cast<std::size_t>(nu) * nv, Vec2::Zero());  // the inner vertices, plane frame
    std::vector<std::vector<Vec2>> target(nv);
    struct RingTarget {
      std::vector<Vec2> T;   // target curve, counter-clockwise
      std::vector<double> cum;  // its closed_arc_lengths
      std::vector<int> on;   // per edge T[v] T[v+1]: the loop it lies on, -1 bridged
      bool several = false;
      std::vector<double> x; // normal hits, unwrapped arc length on T
      std::vector<double> base; // radial hits from the section centre, unwrapped
      double per = 0;        // perimeter of T
    };
    std::vector<RingTarget> rings(static_cast<std::size_t>(nv));
    each_ring([&](int j) {
      const SweepPlane& pl = planes[j];
      std::vector<Loop> loops = slicers[k]->slice(pl);
      if (topo[k].check.components > 1) {
        // Several parts (the bones): the envelope is taken over the slab
        // between the midpoints to the neighbouring rings, its sections
        // projected onto this ring's plane. A plane near the end of one part
        // cuts only its tip, a tiny loop (on the sample at 40x10 a bone tip
        // 1 mm round took a whole ring; at the joint the envelope jumped by
        // 6 mm between rings 3.4 mm apart and inverted muscle cells); the
        // slab sees the part as it is around the ring.
        const double sp = 0.5 * ((j > 0 ? res.stations_m(j) - res.stations_m(j - 1) : 0) +
                                 (j + 1 < nv ? res.stations_m(j + 1) - res.stations_m(j) : 0));
        double w = 0.5 * sp;
        {
          // depth of the cells above: equivalent radii of the ring above and of these sections
          double ap = 0, as = 0;
          for (int i = 0; i < nu; ++i) {
            const Vec3 r0 = pts[k - 1][static_cast<std::size_t>(j) * nu + i] - pl.centre;
            const Vec3 r1 = pts[k - 1][static_cast<std::size_t>(j) * nu + (i + 1) % nu] - pl.centre;
            ap += 0.5 * (r0.dot(pl.e1) * r1.dot(pl.e2) - r0.dot(pl.e2) * r1.dot(pl.e1));
          }
          for (const auto& l : loops) as += std::abs(l.area);
          w = std::max(w, std::sqrt(std::abs(ap) / kPi) - std::sqrt(as / kPi));
        }
        const double lo = std::max(0.0, res.stations_m(j) - w), hi = std::min(L, res.stations_m(j) + w);
        const int nplanes = std::clamp(static_cast<int>(std::ceil((hi - lo) / std::max(0.5 * sp, 1e-12))), 4, 16);
        for (int q = 0; q <= nplanes; ++q) {
          const double sj = lo + (hi - lo) * q / nplanes;
          if (sj == res.stations_m(j)) continue;
          const SweepPlane ps = sweep_plane(sw, sj);
          for (Loop l : slicers[k]->slice(ps)) {
            remesh_detail::to_plane_frame(l, pl);
            loops.push_back(std::move(l));
          }
        }
      }
      double A = 0;
      Vec2 c = Vec2::Zero();
      for (const auto& l : loops) A += l.area, c += l.area * l.centroid;
      if (loops.empty() || !(std::abs(A) > 0)) return;
      c /= A;
      // the enclosing ring (layer k-1) in the plane frame
      std::vector<Vec2> P(nu);
      for (int i = 0; i < nu; ++i) {
        const Vec3 r = pts[k - 1][static_cast<std::size_t>(j) * nu + i] - pl.centre;
        P[i] = Vec2(r.dot(pl.e1), r.dot(pl.e2));
      }
      Loop outer;
      outer.q = prev_target[j].empty() ? P : prev_target[j];
      const bool several = loops.size() > 1;
      Loop hull;
      std::vector<int> hull_on;
      if (several) {
        hull = convex_hull_loop(loops, hull_on);
        if (hull.q.size() >= 3 && hull.area > 0) c = hull.centroid;
      }
      if (remesh_detail::winding(outer, c) == 0)
        throw Error(name, "the centre of its section at " + mm(res.stations_m(j)) + " along the axis lies outside " +
                              layers[k - 1].name);
      // target curve T (counter-clockwise) and, per vertex, the loop it lies on (-1: bridged)
      std::vector<Vec2> T;
      std::vector<int> on;
      if (!several) {
        T = loops[0].q;
        on.assign(T.size(), 0);
      } else {
        // the envelope of several loops (the radius and the ulna): their
        // convex hull, the bones' outer boundary bridged by straight sheets
        // (the interosseous membrane). Convex, so the rays from its centroid
        // and the outer normals meet it in order, with no zig-zag between the
        // bones; an edge is on a bone where it joins consecutive loop points.
        if (hull.q.empty()) return;
        T = hull.q;
        on = hull_on;
        // the hull must stay inside the layer above
        for (const Vec2& q : T) {
          const Vec2 w = q - c;
          const double bound = w.norm() > 0 ? remesh_detail::ray_hit(outer, c, w.normalized()) : -1;
          if (bound > 0 && w.norm() >= bound * (1 - 1e-12))
            throw Error(name, "not inside " + layers[k - 1].name + ": the envelope of its " +
                                  std::to_string(loops.size()) + " parts reaches the outer layer at ring " +
                                  std::to_string(j) + " (" + mm(res.stations_m(j)) + " along the axis)");
        }
      }
      has[j] = 1;
      origin[j] = c;
      RingTarget& rt = rings[static_cast<std::size_t>(j)];
      rt.base = remesh_detail::radial_hits(P, T, c);
      {
        // A ray of length d turns an error e in the normal into d e across:
        // the normals are taken over arcs of half-width d (chords), so that
        // bumps of the ring at the input's voxel scale, whose slopes are large
        // but whose extent is small, move the hits by about their height, not
        // by d times their slope. d: the distance to the radial hit.
        rt.cum = remesh_detail::closed_arc_lengths(T);
        std::vector<double> depth(static_cast<std::size_t>(nu));
        for (int i = 0; i < nu; ++i)
          depth[static_cast<std::size_t>(i)] =
              (remesh_detail::point_at_arc(T, rt.cum, rt.base[static_cast<std::size_t>(i)]) - P[static_cast<std::size_t>(i)]).norm();
        rt.x = remesh_detail::normal_hits(P, T, &depth);
      }
      rt.per = rt.cum.back();
      rt.T = std::move(T);
      rt.on = std::move(on);
      rt.several = several;
    });
    // one blend of the normal hits with the radial ones for the whole layer:
    // the largest that keeps every ring in order (blends that differ between
    // rings shear the cells between them: on the sample at 200x50, a per-ring
    // blend inverted 163 skin tetrahedra, one per layer 18; docs/remesh.md)
    double alpha = 1;
    for (int j = 0; j < nv; ++j)
      if (has[j]) {
        const RingTarget& rt = rings[static_cast<std::size_t>(j)];
        alpha = std::min(alpha, remesh_detail::max_ordered_blend(rt.x, rt.base, rt.per, o.min_ring_spacing_fraction, 20));
      }
    res.stats[k].normal_blend = alpha;
    for (int j = 0; j < nv; ++j) {
      if (!has[j]) continue;
      RingTarget& rt = rings[static_cast<std::size_t>(j)];
      const std::vector<Vec2>& T = rt.T;
      const std::vector<double> sig = remesh_detail::ordered_blend(rt.x, rt.base, rt.per, alpha, o.min_ring_spacing_fraction);
      // points at the parameters; on a stretch of one loop, exactly on it
      for (int i = 0; i < nu; ++i) {
        std::size_t s = 0;
        const Vec2 q = remesh_detail::point_at_arc(T, rt.cum, sig[static_cast<std::size_t>(i)], &s);
        if (!rt.several || rt.on[s] >= 0)
          ++res.stats[k].hit;
        else
          ++res.stats[k].bridged;
        q2[static_cast<std::size_t>(j) * nu + i] = q;
      }
      target[j] = T;
    }
    // rings that miss the surface: plane-frame positions interpolated along
    // the axis (held at the ends), kept inside the layer above
    std::vector<int> with;
    for (int j = 0; j < nv; ++j)
      if (has[j]) with.push_back(j);
    if (with.empty()) throw Error(name, "no ring plane of " + layers[0].name + " meets this surface");
    for (int j = 0; j < nv; ++j) {
      if (has[j]) continue;
      auto it = std::lower_bound(with.begin(), with.end(), j);
      int a = it == with.begin() ? *it : *(it - 1);
      int b = it == with.end() ? with.back() : *it;
      const double f = a == b ? 0 : (res.stations_m(j) - res.stations_m(a)) / (res.stations_m(b) - res.stations_m(a));
      origin[j] = (1 - f) * origin[a] + f * origin[b];
      const SweepPlane& pl = planes[j];
      Loop outer;
      if (!prev_target[j].empty()) {
        outer.q = prev_target[j];
      } else {
        for (int i = 0; i < nu; ++i) {
          const Vec3 r = pts[k - 1][static_cast<std::size_t>(j) * nu + i] - pl.centre;
          outer.q.emplace_back(r.dot(pl.e1), r.dot(pl.e2));
        }
      }
      for (int i = 0; i < nu; ++i) {
        const std::size_t r = static_cast<std::size_t>(j) * nu + i;
        Vec2 q = (1 - f) * q2[static_cast<std::size_t>(a) * nu + i] + f * q2[static_cast<std::size_t>(b) * nu + i];
        const Vec2 w = q - origin[j];
        const double bound = w.norm() > 0 ? remesh_detail::ray_hit(outer, origin[j], w.normalized()) : -1;
        if (bound > 0 && w.norm() > o.fill_max_depth_fraction * bound)
          q = origin[j] + o.fill_max_depth_fraction * bound * w.normalized();
        q2[r] = q;
      }
      res.stats[k].filled += nu;
    }
    for (int j = 0; j < nv; ++j) {
      const SweepPlane& pl = planes[j];
      res.ray_origin[k].row(j) = pl.centre + origin[j].x() * pl.e1 + origin[j].y() * pl.e2;
      for (int i = 0; i < nu; ++i) {
        const std::size_t r = static_cast<std::size_t>(j) * nu + i;
        pts[k][r] = pl.centre + q2[r].x() * pl.e1 + q2[r].y() * pl.e2;
      }
    }
    prev_target = std::move(target);
  }
  for (int k = 0; k < nl; ++k) res.layers.push_back(make_grid(nu, nv, pts[k], res.stations_m, L));
  res.rings_s = seconds_since(t0);
  res.total_s = seconds_since(t_start);
  return res;
}

// ---- quality and alignment ----------------------------------------------------

QuadQuality quad_quality(const QuadSurface& q, const MatX3d& ring_centre) {
  QuadQuality m;
  m.min_angle_deg = 360, m.min_edge_m = 1e300, m.max_angle_deg = 0;
  const Eigen::Index nq = q.quads.rows();
  if (nq == 0) return m;
  double sum_edge = 0, sum_aspect = 0;
  std::vector<double> edges;
  for (Eigen::Index f = 0; f < nq; ++f) {
    Vec3 p[4];
    for (int k = 0; k < 4; ++k) p[k] = q.vertices.row(q.quads(f, k));
    double e[4], emin = 1e300, emax = 0;
    for (int k = 0; k < 4; ++k) {
      e[k] = (p[(k + 1) % 4] - p[k]).norm();
      emin = std::min(emin, e[k]), emax = std::max(emax, e[k]);
      sum_edge += e[k];
    }
    m.min_edge_m = std::min(m.min_edge_m, emin);
    m.max_edge_m = std::max(m.max_edge_m, emax);
    const Vec3 n = (p[2] - p[0]).cross(p[3] - p[1]);
    const double area = 0.5 * n.norm();
    const bool degenerate = !(emin > 1e-9 * emax) || !(area > 1e-9 * emax * emax);
    if (degenerate) {
      ++m.degenerate;
      continue;
    }
    for (int k = 0; k < 4; ++k) {
      const Vec3 a = p[(k + 1) % 4] - p[k], b = p[(k + 3) % 4] - p[k];
      const double ang = std::atan2(a.cross(b).norm(), a.dot(b)) * 180 / kPi;
      m.min_angle_deg = std::min(m.min_angle_deg, ang);
      m.max_angle_deg = std::max(m.max_angle_deg, ang);
    }
    const double asp = emax / emin;
    m.max_aspect = std::max(m.max_aspect, asp);
    sum_aspect += asp;
    const Vec3 n1 = (p[1] - p[0]).cross(p[2] - p[0]), n2 = (p[2] - p[0]).cross(p[3] - p[0]);
    if (n1.norm() > 0 && n2.norm() > 0)
      m.max_warp_deg = std::max(m.max_warp_deg, std::atan2(n1.cross(n2).norm(), n1.dot(n2)) * 180 / kPi);
    // outward: away from the ring centres of the quad's two rings
    if (q.nu > 0 && ring_centre.rows() == q.nv) {
      const int j = static_cast<int>(q.quads(f, 0) / q.nu);
      const Vec3 c = 0.5 * (ring_centre.row(j) + ring_centre.row(std::min(j + 1, q.nv - 1))).transpose();
      const Vec3 mid = 0.25 * (p[0] + p[1] + p[2] + p[3]);
      if (n.dot(mid - c) <= 0) ++m.flipped;
    }
  }
  m.mean_edge_m = sum_edge / (4.0 * nq);
  m.mean_aspect = sum_aspect / std::max<Eigen::Index>(1, nq - m.degenerate);
  return m;
}

namespace {

// closest point on triangle abc to p (Ericson, Real-Time Collision Detection 5.1.5)
Vec3 closest_on_triangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c) {
  const Vec3 ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const Vec3 bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return a + d1 / (d1 - d3) * ab;
  const Vec3 cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return a + d2 / (d2 - d6) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b);
  const double den = 1 / (va + vb + vc);
  return a + ab * (vb * den) + ac * (vc * den);
}

// ray o + t d (t > 0) against triangle abc (Moeller-Trumbore); t or -1
double ray_triangle(const Vec3& o, const Vec3& d, const Vec3& a, const Vec3& b, const Vec3& c) {
  const Vec3 e1 = b - a, e2 = c - a, pv = d.cross(e2);
  const double det = e1.dot(pv);
  if (std::abs(det) < 1e-300) return -1;
  const double inv = 1 / det;
  const Vec3 tv = o - a;
  const double u = tv.dot(pv) * inv;
  if (u < -1e-12 || u > 1 + 1e-12) return -1;
  const Vec3 qv = tv.cross(e1);
  const double v = d.dot(qv) * inv;
  if (v < -1e-12 || u + v > 1 + 1e-12) return -1;
  const double t = e2.dot(qv) * inv;
  return t > 0 ? t : -1;
}

}  // namespace

LayerAlignment layer_alignment(const QuadSurface& a, const QuadSurface& b, const std::string& an,
                               const std::string& bn) {
  LayerAlignment r;
  r.outer = an, r.inner = bn;
  if (a.nu != b.nu || a.nv != b.nv) throw Error(bn, "grid differs from " + an);
  const int nu = a.nu, nv = a.nv;
  auto A = [&](int i, int j) { return Vec3(a.vertices.row(static_cast<Eigen::Index>(j) * nu + ((i + nu) % nu))); };
  auto B = [&](int i, int j) { return Vec3(b.vertices.row(static_cast<Eigen::Index>(j) * nu + ((i + nu) % nu))); };
  // lateral offset of corresponding vertices across the outer normal
  for (int j = 0; j < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      const int jm = std::max(j - 1, 0), jp = std::min(j + 1, nv - 1);
      const Vec3 du = A(i + 1, j) - A(i - 1, j), dv = A(i, jp) - A(i, jm);
      const Vec3 n = du.cross(dv).normalized();
      const Vec3 d = B(i, j) - A(i, j);
      const double lat = (d - d.dot(n) * n).norm();
      if (d.norm() > 0) {
        const double ang = std::atan2(d.cross(-n).norm(), d.dot(-n)) * 180 / kPi;
        r.max_normal_angle_deg = std::max(r.max_normal_angle_deg, ang);
        r.mean_normal_angle_deg += ang / (static_cast<double>(nu) * nv);
      }
      const double h = std::max({(A(i + 1, j) - A(i, j)).norm(), (A(i - 1, j) - A(i, j)).norm(),
                                 (A(i, jp) - A(i, j)).norm(), (A(i, jm) - A(i, j)).norm()});
      r.max_lateral_m = std::max(r.max_lateral_m, lat);
      if (h > 0) r.max_lateral_rel = std::max(r.max_lateral_rel, lat / h);
    }
  // the builder's test: the inward normal ray from each outer quad centroid
  std::int64_t in = 0, total = 0;
  for (int j = 0; j + 1 < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      const Vec3 p0 = A(i, j), p1 = A(i + 1, j), p2 = A(i + 1, j + 1), p3 = A(i, j + 1);
      const Vec3 c = 0.25 * (p0 + p1 + p2 + p3);
      const Vec3 d = -((p2 - p0).cross(p3 - p1)).normalized();
      ++total;
      auto hit_quad = [&](int ii, int jj) {
        const Vec3 q0 = B(ii, jj), q1 = B(ii + 1, jj), q2 = B(ii + 1, jj + 1), q3 = B(ii, jj + 1);
        double t = ray_triangle(c, d, q0, q1, q2);
        const double t2 = ray_triangle(c, d, q0, q2, q3);
        if (t2 > 0 && (t < 0 || t2 < t)) t = t2;
        return t;
      };
      if (hit_quad(i, j) > 0) {
        ++in;
        continue;
      }
      // where does it land instead? nearest hit among the neighbours
      double best = -1;
      for (int dj = -3; dj <= 3; ++dj)
        for (int di = -3; di <= 3; ++di) {
          const int jj = j + dj;
          if (jj < 0 || jj + 1 >= nv) continue;
          const double t = hit_quad(i + di, jj);
          if (t > 0 && (best < 0 || t < best)) best = t;
        }
      const Vec3 q0 = B(i, j), q1 = B(i + 1, j), q2 = B(i + 1, j + 1), q3 = B(i, j + 1);
      const Vec3 qc = 0.25 * (q0 + q1 + q2 + q3);
      double miss;
      if (best > 0) {
        const Vec3 x = c + best * d;
        miss = std::min((x - closest_on_triangle(x, q0, q1, q2)).norm(), (x - closest_on_triangle(x, q0, q2, q3)).norm());
      } else {
        const Vec3 w = qc - c;
        miss = (w - w.dot(d) * d).norm();  // distance from the ray's line to the quad centre
      }
      r.max_ray_miss_m = std::max(r.max_ray_miss_m, miss);
    }
  r.ray_in_quad = total ? static_cast<double>(in) / total : 1.0;
  return r;
}

}  // namespace orthosim
