// The tube mesh of a vessel forest: rings swept along each branch's Bezier
// with rotation-minimising frames, bifurcation patches between a parent's
// last ring and its children's first rings, caps at the vessel ends, then
// fairing of the patches and one consistent outward orientation.
//
// Bifurcation patch (docs/vessels.md has the figure): a junction with n
// children is a sphere with n + 1 holes. The children are taken in
// counter-clockwise order around the parent's axis; between two neighbours
// c_i, c_i+1 lies a "valley", a hexagon bounded by
//   S1 the parent ring's arc facing the valley          (k/n edges)
//   S2 a seam from the parent ring down to c_i+1's outer point (k/2)
//   S3 c_i+1's ring from its outer to its inner point    (k/2)
//   S4 the crotch: c_i+1's inner point -> crotch centre -> c_i's inner point (k/n)
//   S5 c_i's ring from its inner to its outer point      (k/2)
//   S6 the seam from c_i's outer point back up to the parent ring (k/2)
// For n = 2 the two valleys are the front and back of the junction and each
// is the paper's Bezier triangle (parent half-ring, two child half-rings)
// with its corners cut by the seams. Opposite sides have equal edge counts,
// so a valley splits from an interior point into three structured quad grids
// (S1 x S2, S3 x S4, S5 x S6): the patch is all quads, shares every ring
// vertex with the tubes (watertight by construction) and is a manifold.
// The crotch (S4 of every valley: the crotch centre and its spokes to the
// children's inner points) is placed, a cubic Hermite curve per spoke that
// dips below the inner points and arrives along each child's axis. The other
// new vertices minimise the umbrella-Laplacian energy with the rings, the
// tubes' next rings and the crotch fixed (a discrete thin plate), which joins
// the tubes with continuous tangent planes.
#include "libmodel/vessels/detail.h"

#include <Eigen/Dense>
#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>

#include <algorithm>
#include <array>
#include <cmath>
#include <deque>
#include <map>
#include <set>

namespace orthosim::vessels_detail {
namespace {

constexpr double kPi = 3.14159265358979323846;

struct Mesh {
  std::vector<Eigen::Vector3d> v;
  std::vector<std::vector<int>> faces;  // quads (4) and triangles (3)
  std::vector<char> free;               // patch vertices placed by fairing
  std::vector<char> open_cap;
  int add(const Eigen::Vector3d& p, bool is_free = false, bool cap = false) {
    v.push_back(p);
    free.push_back(is_free);
    open_cap.push_back(cap);
    return static_cast<int>(v.size()) - 1;
  }
};

struct Ring {
  std::vector<int> ids;
  Eigen::Vector3d c{0, 0, 0}, t{0, 0, 1}, u{1, 0, 0};
  double r = 0;
};

Eigen::Vector3d perpendicular(const Eigen::Vector3d& t) {
  Eigen::Vector3d a = std::abs(t.x()) < 0.6 ? Eigen::Vector3d::UnitX()
                      : (std::abs(t.y()) < 0.6 ? Eigen::Vector3d::UnitY() : Eigen::Vector3d::UnitZ());
  return (a - a.dot(t) * t).normalized();
}

Ring make_ring(Mesh& m, const Eigen::Vector3d& c, const Eigen::Vector3d& t, const Eigen::Vector3d& u, double r, int k) {
  Ring R;
  R.c = c, R.t = t, R.u = u, R.r = r;
  const Eigen::Vector3d v = t.cross(u);
  for (int j = 0; j < k; ++j) {
    const double phi = 2 * kPi * j / k;
    R.ids.push_back(m.add(c + r * (std::cos(phi) * u + std::sin(phi) * v)));
  }
  return R;
}

void bridge(Mesh& m, const std::vector<int>& a, const std::vector<int>& b) {
  const int k = static_cast<int>(a.size());
  for (int j = 0; j < k; ++j) m.faces.push_back({a[j], a[(j + 1) % k], b[(j + 1) % k], b[j]});
}

// Ring stations along [a, e]: spacing ratio x 2 pi r / k, equidistributed.
std::vector<double> stations(const Branch& b, int k, double ratio) {
  const double a = b.tube_a, e = std::max(b.tube_b, b.tube_a);
  const int m = 256;
  std::vector<double> ss(m + 1), N(m + 1, 0);
  double prev = 0;
  for (int i = 0; i <= m; ++i) {
    ss[i] = a + (e - a) * i / m;
    double r = 0;
    branch_point(b, ss[i], nullptr, &r);
    const double inv = 1 / std::max(ratio * 2 * kPi * std::max(r, 1e-6) / k, 1e-9);
    if (i > 0) N[i] = N[i - 1] + (ss[i] - ss[i - 1]) * 0.5 * (prev + inv);
    prev = inv;
  }
  const int n = std::max(1, static_cast<int>(std::lround(N[m])));
  std::vector<double> out;
  int i = 0;
  for (int j = 0; j <= n; ++j) {
    const double target = N[m] * j / n;
    while (i + 1 < m && N[i + 1] < target) ++i;
    const double dn = N[i + 1] - N[i];
    const double t = dn > 0 ? std::clamp((target - N[i]) / dn, 0.0, 1.0) : 0.0;
    out.push_back(ss[i] + t * (ss[i + 1] - ss[i]));
  }
  out.front() = a, out.back() = e;
  return out;
}

// Rotation-minimising frames by double reflection (Wang, Juttler, Zheng and
// Liu, "Computation of rotation minimizing frames", ACM TOG 27(1), 2008):
// reflect (r_i, t_i) in the bisector plane of x_i x_i+1, then in the plane
// that maps the reflected tangent onto t_i+1.
std::vector<Eigen::Vector3d> rmf(const std::vector<Eigen::Vector3d>& x, const std::vector<Eigen::Vector3d>& t,
                                 const Eigen::Vector3d& u0) {
  std::vector<Eigen::Vector3d> u(x.size());
  u[0] = (u0 - u0.dot(t[0]) * t[0]).normalized();
  for (std::size_t i = 0; i + 1 < x.size(); ++i) {
    const Eigen::Vector3d v1 = x[i + 1] - x[i];
    const double c1 = v1.dot(v1);
    Eigen::Vector3d rl = u[i], tl = t[i];
    if (c1 > 0) {
      rl = u[i] - (2 / c1) * v1.dot(u[i]) * v1;
      tl = t[i] - (2 / c1) * v1.dot(t[i]) * v1;
    }
    const Eigen::Vector3d v2 = t[i + 1] - tl;
    const double c2 = v2.dot(v2);
    Eigen::Vector3d r = c2 > 0 ? Eigen::Vector3d(rl - (2 / c2) * v2.dot(rl) * v2) : rl;
    r -= r.dot(t[i + 1]) * t[i + 1];
    u[i + 1] = r.norm() > 1e-12 ? r.normalized() : perpendicular(t[i + 1]);
  }
  return u;
}

// a structured grid between four boundary polylines (bottom and top a + 1
// ids, left and right b + 1 ids, corners shared)
void grid(Mesh& m, const std::vector<int>& B, const std::vector<int>& R, const std::vector<int>& T,
          const std::vector<int>& L) {
  const int a = static_cast<int>(B.size()) - 1, b = static_cast<int>(L.size()) - 1;
  std::vector<int> id((a + 1) * (b + 1), -1);
  auto at = [&](int i, int j) -> int& { return id[j * (a + 1) + i]; };
  for (int i = 0; i <= a; ++i) at(i, 0) = B[i], at(i, b) = T[i];
  for (int j = 0; j <= b; ++j) at(0, j) = L[j], at(a, j) = R[j];
  for (int j = 1; j < b; ++j)
    for (int i = 1; i < a; ++i) at(i, j) = m.add(Eigen::Vector3d::Zero(), true);
  for (int j = 0; j < b; ++j)
    for (int i = 0; i < a; ++i) m.faces.push_back({at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)});
}

// a polyline of `n` edges from vertex a to vertex b with n - 1 new free vertices
std::vector<int> curve(Mesh& m, int a, int b, int n) {
  std::vector<int> c{a};
  for (int i = 1; i < n; ++i) c.push_back(m.add(Eigen::Vector3d::Zero(), true));
  c.push_back(b);
  return c;
}

std::vector<int> reversed(std::vector<int> v) {
  std::reverse(v.begin(), v.end());
  return v;
}

double angle_diff(double a, double b) {
  double d = std::fmod(a - b, 2 * kPi);
  if (d > kPi) d -= 2 * kPi;
  if (d < -kPi) d += 2 * kPi;
  return d;
}

void junction_patch(Mesh& m, const Ring& P, const std::vector<const Ring*>& C, int k) {
  const int n = static_cast<int>(C.size());
  if (n == 1) {  // a plain continuation: bridge with the best rotation
    int best = 0;
    double bd = 1e300;
    for (int s = 0; s < k; ++s) {
      double d = 0;
      for (int j = 0; j < k; ++j) d += (m.v[P.ids[j]] - m.v[C[0]->ids[(j + s) % k]]).squaredNorm();
      if (d < bd) bd = d, best = s;
    }
    std::vector<int> b(k);
    for (int j = 0; j < k; ++j) b[j] = C[0]->ids[(j + best) % k];
    bridge(m, P.ids, b);
    return;
  }
  if (k % (2 * n) != 0)
    throw Error("", "ring_vertices " + std::to_string(k) + " is not a multiple of " + std::to_string(2 * n) +
                        " as a junction with " + std::to_string(n) + " children needs");
  const Eigen::Vector3d up = P.u, vp = P.t.cross(P.u);
  // children counter-clockwise around the parent's axis, seen from the
  // centroid of their first rings (not from the parent's centre: when one
  // child continues the parent's axis its angle around that axis is
  // meaningless, while the children always lie around their own centroid)
  Eigen::Vector3d mid = Eigen::Vector3d::Zero();
  for (int c = 0; c < n; ++c) mid += C[c]->c;
  mid /= n;
  std::vector<Eigen::Vector3d> radial(n);
  std::vector<std::pair<double, int>> ang;
  for (int c = 0; c < n; ++c) {
    Eigen::Vector3d d = C[c]->c - mid;
    d -= d.dot(P.t) * P.t;
    radial[c] = d.norm() > 0 ? Eigen::Vector3d(d.normalized()) : up;
    ang.push_back({std::atan2(d.dot(vp), d.dot(up)), c});
  }
  std::sort(ang.begin(), ang.end());
  // the parent ring's split points follow the children's angles
  const int arc = k / n;
  int base = 0;
  double bcost = 1e300;
  for (int b = 0; b < k; ++b) {
    double cost = 0;
    for (int i = 0; i < n; ++i) {
      const double d = angle_diff(2 * kPi * ((b + i * arc) % k) / k, ang[i].first);
      cost += d * d;
    }
    if (cost < bcost) bcost = cost, base = b;
  }
  const int half = k / 2, spoke = k / (2 * n);
  // The crotch is placed, not faired: its centre X lies below the centroid of
  // the children's inner points (along their mean axis) by their mean
  // distance to that centroid, and each spoke is the cubic Hermite curve from
  // X, leaving level toward the child, to the child's inner point, arriving
  // along the child's axis. Left free, the thin plate pulls X and the spokes
  // into a pinch where the two sides of a tight crotch pass through each
  // other.
  Eigen::Vector3d cin = Eigen::Vector3d::Zero(), axis = Eigen::Vector3d::Zero();
  for (int c = 0; c < n; ++c) cin += m.v[C[c]->ids[0]], axis += C[c]->t;
  cin /= n;
  axis = axis.norm() > 1e-12 ? Eigen::Vector3d(axis.normalized()) : P.t;
  double spread = 0;
  for (int c = 0; c < n; ++c) spread += (m.v[C[c]->ids[0]] - cin).norm() / n;
  const Eigen::Vector3d xc = cin - spread * axis;
  const int X = m.add(xc);
  auto spoke_curve = [&](const Ring& R) {
    const Eigen::Vector3d b = m.v[R.ids[0]];
    Eigen::Vector3d ta = b - xc;
    ta -= ta.dot(axis) * axis;
    ta = ta.norm() > 1e-12 ? Eigen::Vector3d(ta.normalized()) : R.t;
    const double L = (b - xc).norm();
    std::vector<int> c{X};
    for (int s = 1; s < spoke; ++s) {
      const double u = static_cast<double>(s) / spoke, u2 = u * u, u3 = u2 * u;
      c.push_back(m.add((2 * u3 - 3 * u2 + 1) * xc + (u3 - 2 * u2 + u) * L * ta + (-2 * u3 + 3 * u2) * b +
                        (u3 - u2) * L * R.t));
    }
    c.push_back(R.ids[0]);
    return c;
  };
  // per child (in angular order): seam, crotch spoke, the two half rings
  std::vector<std::vector<int>> seam(n), crotch(n), to_next(n), to_prev(n);
  for (int i = 0; i < n; ++i) {
    const Ring& R = *C[ang[i].second];
    const int a = P.ids[(base + i * arc) % k];
    const int outer = R.ids[half];
    seam[i] = curve(m, a, outer, half);
    crotch[i] = spoke_curve(R);
    // which half of the ring faces the next child (counter-clockwise)
    const Eigen::Vector3d w = P.t.cross(radial[ang[i].second]);
    const Eigen::Vector3d q = m.v[R.ids[k / 4]] - R.c;
    std::vector<int> plus, minus;  // inner -> outer through k/4 and through 3k/4
    for (int j = 0; j <= half; ++j) plus.push_back(R.ids[j]), minus.push_back(R.ids[(k - j) % k]);
    if (q.dot(w) >= 0) to_next[i] = plus, to_prev[i] = minus;
    else to_next[i] = minus, to_prev[i] = plus;
  }
  for (int i = 0; i < n; ++i) {
    const int j = (i + 1) % n;
    std::vector<int> S1;
    for (int s = 0; s <= arc; ++s) S1.push_back(P.ids[(base + i * arc + s) % k]);
    const std::vector<int>& S2 = seam[j];
    const std::vector<int> S3 = reversed(to_prev[j]);  // c_j outer -> inner
    std::vector<int> S4 = reversed(crotch[j]);          // c_j inner -> X
    S4.insert(S4.end(), crotch[i].begin() + 1, crotch[i].end());  // X -> c_i inner
    const std::vector<int>& S5 = to_next[i];             // c_i inner -> outer
    const std::vector<int> S6 = reversed(seam[i]);       // c_i outer -> parent
    const int H = m.add(Eigen::Vector3d::Zero(), true);
    const std::vector<int> h23 = curve(m, H, S2.back(), arc);   // to c_j outer
    const std::vector<int> h45 = curve(m, H, S4.back(), half);  // to c_i inner
    const std::vector<int> h61 = curve(m, H, S1.front(), half); // to the parent ring
    grid(m, S1, S2, h23, reversed(h61));
    grid(m, S3, S4, h45, reversed(h23));
    grid(m, S5, S6, h61, reversed(h45));
  }
}

// Rounded or flat cap closing ring R; `out` points away from the tube.
void cap(Mesh& m, const Ring& R, const Eigen::Vector3d& out, bool open, int k) {
  std::vector<int> ring = R.ids;
  Eigen::Vector3d pole = R.c;
  if (!open) {
    const Eigen::Vector3d v = R.t.cross(R.u);
    for (double th : {kPi / 6, kPi / 3}) {
      std::vector<int> next;
      for (int j = 0; j < k; ++j) {
        const double phi = 2 * kPi * j / k;
        next.push_back(m.add(R.c + R.r * std::sin(th) * out + R.r * std::cos(th) * (std::cos(phi) * R.u + std::sin(phi) * v)));
      }
      bridge(m, ring, next);
      ring = next;
    }
    pole = R.c + R.r * out;
  }
  const int p = m.add(pole, false, open);
  for (int i = 0; i < k / 2; ++i) m.faces.push_back({p, ring[2 * i], ring[2 * i + 1], ring[(2 * i + 2) % k]});
}

// Positions of the free (patch) vertices: least squares on the umbrella
// Laplacians of every free vertex and of every vertex next to one.
void fair(Mesh& m) {
  const int nv = static_cast<int>(m.v.size());
  std::vector<std::set<int>> adj(nv);
  for (const auto& f : m.faces)
    for (std::size_t i = 0; i < f.size(); ++i) {
      const int a = f[i], b = f[(i + 1) % f.size()];
      adj[a].insert(b), adj[b].insert(a);
    }
  std::vector<int> fi(nv, -1);
  int nf = 0;
  for (int i = 0; i < nv; ++i)
    if (m.free[i]) fi[i] = nf++;
  if (nf == 0) return;
  std::vector<int> rows;
  std::vector<char> is_row(nv, 0);
  for (int i = 0; i < nv; ++i)
    if (m.free[i]) {
      if (!is_row[i]) is_row[i] = 1, rows.push_back(i);
      for (int j : adj[i])
        if (!is_row[j]) is_row[j] = 1, rows.push_back(j);
    }
  std::sort(rows.begin(), rows.end());
  std::vector<Eigen::Triplet<double>> trip;
  Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(rows.size()), 3);
  for (std::size_t r = 0; r < rows.size(); ++r) {
    const int j = rows[r];
    const double w = -1.0 / static_cast<double>(adj[j].size());
    auto term = [&](int v, double c) {
      if (fi[v] >= 0) trip.emplace_back(static_cast<int>(r), fi[v], c);
      else rhs.row(static_cast<Eigen::Index>(r)) -= c * m.v[v].transpose();
    };
    term(j, 1.0);
    for (int l : adj[j]) term(l, w);
  }
  Eigen::SparseMatrix<double> A(static_cast<Eigen::Index>(rows.size()), nf);
  A.setFromTriplets(trip.begin(), trip.end());
  const Eigen::SparseMatrix<double> AtA = A.transpose() * A;
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver(AtA);
  if (solver.info() != Eigen::Success) throw Error("", "bifurcation patch: the fairing system is singular");
  const Eigen::MatrixXd x = solver.solve(A.transpose() * rhs);
  for (int i = 0; i < nv; ++i)
    if (fi[i] >= 0) m.v[i] = x.row(fi[i]).transpose();
}

// One orientation per connected component, agreeing across every edge, outward.
void orient(Mesh& m) {
  const int nf = static_cast<int>(m.faces.size());
  std::map<std::pair<int, int>, std::vector<int>> edge_faces;
  for (int f = 0; f < nf; ++f) {
    const auto& F = m.faces[f];
    for (std::size_t i = 0; i < F.size(); ++i) edge_faces[std::minmax(F[i], F[(i + 1) % F.size()])].push_back(f);
  }
  auto dir = [&](int f, int a, int b) {  // +1 when face f runs a -> b
    const auto& F = m.faces[f];
    for (std::size_t i = 0; i < F.size(); ++i) {
      if (F[i] == a && F[(i + 1) % F.size()] == b) return 1;
      if (F[i] == b && F[(i + 1) % F.size()] == a) return -1;
    }
    return 0;
  };
  std::vector<int> flip(nf, -1), comp(nf, -1);
  int nc = 0;
  for (int s = 0; s < nf; ++s) {
    if (flip[s] >= 0) continue;
    flip[s] = 0, comp[s] = nc;
    std::deque<int> q{s};
    while (!q.empty()) {
      const int f = q.front();
      q.pop_front();
      const auto& F = m.faces[f];
      for (std::size_t i = 0; i < F.size(); ++i) {
        const int a = F[i], b = F[(i + 1) % F.size()];
        const int df = dir(f, a, b) * (flip[f] ? -1 : 1);
        for (int g : edge_faces[std::minmax(a, b)]) {
          if (g == f || flip[g] >= 0) continue;
          flip[g] = dir(g, a, b) == df ? 1 : 0;  // the neighbour must run b -> a
          comp[g] = nc;
          q.push_back(g);
        }
      }
    }
    ++nc;
  }
  std::vector<double> vol(nc, 0);
  for (int f = 0; f < nf; ++f) {
    if (flip[f]) std::reverse(m.faces[f].begin(), m.faces[f].end());
    const auto& F = m.faces[f];
    for (std::size_t i = 1; i + 1 < F.size(); ++i)
      vol[comp[f]] += m.v[F[0]].dot(m.v[F[i]].cross(m.v[F[i + 1]])) / 6;
  }
  for (int f = 0; f < nf; ++f)
    if (vol[comp[f]] < 0) std::reverse(m.faces[f].begin(), m.faces[f].end());
}

// Where two tubes come closer than the sum of their radii (touching vessels,
// a branch running along another, a vessel looping onto itself) both are
// thinned in proportion, so that the tubes stay apart by 5 % of the sum, and
// the thinning fades out over two radii along each tube. Rings of branches
// meeting at a junction are not compared near that junction (the patch
// joins them there).
void separate_touching(const Forest& f, const std::vector<std::vector<double>>& st,
                       const std::vector<std::vector<Eigen::Vector3d>>& xs, std::vector<std::vector<double>>& rad) {
  const std::size_t nb = f.branches.size();
  std::vector<Eigen::Vector3d> junction_point(nb, Eigen::Vector3d::Constant(1e300));  // at a branch's end
  for (const Junction& J : f.junctions) junction_point[J.parent] = f.branches[J.parent].x.back();
  auto shared_junction = [&](std::size_t a, std::size_t b, Eigen::Vector3d* p) {
    const Branch& A = f.branches[a];
    const Branch& B = f.branches[b];
    if (A.parent >= 0 && A.parent == B.parent) return *p = junction_point[A.parent], true;
    if (A.parent == static_cast<int>(b)) return *p = junction_point[b], true;
    if (B.parent == static_cast<int>(a)) return *p = junction_point[a], true;
    return false;
  };
  std::vector<std::vector<double>> factor(nb);
  for (std::size_t b = 0; b < nb; ++b) factor[b].assign(xs[b].size(), 1.0);
  const double margin = 0.05;
  for (std::size_t a = 0; a < nb; ++a)
    for (std::size_t b = a; b < nb; ++b) {
      Eigen::Vector3d jp = Eigen::Vector3d::Zero();
      const bool related = a != b && shared_junction(a, b, &jp);
      for (std::size_t i = 0; i < xs[a].size(); ++i)
        for (std::size_t j = a == b ? i + 1 : 0; j < xs[b].size(); ++j) {
          const double ri = rad[a][i], rj = rad[b][j];
          const double d = (xs[a][i] - xs[b][j]).norm();
          const double need = (ri + rj) * (1 + margin);
          if (d >= need) continue;
          if (a == b && std::abs(st[a][i] - st[b][j]) < kPi * (ri + rj)) continue;
          if (related && ((xs[a][i] - jp).norm() < 4 * (ri + rj) || (xs[b][j] - jp).norm() < 4 * (ri + rj))) continue;
          const double s = d / need;
          factor[a][i] = std::min(factor[a][i], s);
          factor[b][j] = std::min(factor[b][j], s);
        }
    }
  for (std::size_t b = 0; b < nb; ++b) {
    const std::vector<double> f0 = factor[b];
    for (std::size_t i = 0; i < f0.size(); ++i) {
      double fi = 1;
      for (std::size_t j = 0; j < f0.size(); ++j) {
        if (f0[j] >= 1) continue;
        const double w = std::abs(st[b][i] - st[b][j]) / (2 * rad[b][j]);
        fi = std::min(fi, f0[j] + (1 - f0[j]) * std::min(1.0, w * w));
      }
      rad[b][i] *= fi;
    }
  }
}

}  // namespace

void build_tube(const Forest& f, const VesselOptions& o, VesselTree& t, std::vector<char>& open_cap) {
  const int k = o.ring_vertices;
  Mesh m;
  std::vector<Ring> first(f.branches.size()), last(f.branches.size());
  // the first frame of a child: its ring's vertex 0 faces the junction's axis
  std::vector<Eigen::Vector3d> u0(f.branches.size(), Eigen::Vector3d::Zero());
  for (const Junction& J : f.junctions) {
    Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
    for (int c : J.children) centroid += branch_point(f.branches[c], f.branches[c].tube_a);
    centroid /= static_cast<double>(J.children.size());
    for (int c : J.children) {
      Eigen::Vector3d tc;
      const Eigen::Vector3d pc = branch_point(f.branches[c], f.branches[c].tube_a, &tc);
      Eigen::Vector3d d = centroid - pc;
      d -= d.dot(tc) * tc;
      u0[c] = d.norm() > 1e-12 ? d.normalized() : perpendicular(tc);
    }
  }
  // stations of every branch first: touching tubes are thinned where they meet
  const std::size_t nb = f.branches.size();
  std::vector<std::vector<double>> st(nb), rad(nb);
  std::vector<std::vector<Eigen::Vector3d>> xs(nb), tgs(nb);
  for (std::size_t bi = 0; bi < nb; ++bi) {
    st[bi] = stations(f.branches[bi], k, o.ring_spacing);
    xs[bi].resize(st[bi].size()), tgs[bi].resize(st[bi].size()), rad[bi].resize(st[bi].size());
    for (std::size_t i = 0; i < st[bi].size(); ++i)
      xs[bi][i] = branch_point(f.branches[bi], st[bi][i], &tgs[bi][i], &rad[bi][i]);
  }
  separate_touching(f, st, xs, rad);
  for (std::size_t bi = 0; bi < nb; ++bi) {
    const Branch& b = f.branches[bi];
    std::vector<Eigen::Vector3d> x = xs[bi], tg = tgs[bi];
    std::vector<double> r = rad[bi];
    // Open ends lie flush with their border plane: the end ring is the tube's
    // section in that plane (its vertices slid along the axis onto it), and the
    // rings before it that would reach past the plane are left out. A vessel
    // leaving the volume obliquely stuck out by r sin(tilt) (3.5 mm for the
    // wide stack's 5.4 mm artery) before 2026-11-27. Not where the axis grazes
    // the plane (more than 60 degrees off its normal): the slide would be long.
    struct Flush {
      int axis = -1;
      double plane = 0;
      Eigen::Vector3d out{0, 0, 0};  // the axis's outward direction at that end
    } at_start, at_end;
    auto flush_of = [&](int axis, double plane, const Eigen::Vector3d& out) {
      Flush fl;
      if (axis >= 0 && std::abs(out(axis)) >= 0.5) fl.axis = axis, fl.plane = plane, fl.out = out;
      return fl;
    };
    if (b.start_root && b.start_open && !x.empty()) at_start = flush_of(b.start_axis, b.start_plane, -tg.front());
    if (b.end_leaf && b.end_open && !x.empty()) at_end = flush_of(b.end_axis, b.end_plane, tg.back());
    // how far station i's ring reaches past the plane, along its outward normal
    auto past = [&](const Flush& fl, std::size_t i) {
      const double sgn = fl.out(fl.axis) > 0 ? 1.0 : -1.0;
      const double c = std::clamp(tg[i](fl.axis), -1.0, 1.0);
      return sgn * (x[i](fl.axis) - fl.plane) + r[i] * std::sqrt(1 - c * c);
    };
    auto erase = [&](std::size_t i) {
      x.erase(x.begin() + static_cast<std::ptrdiff_t>(i));
      tg.erase(tg.begin() + static_cast<std::ptrdiff_t>(i));
      r.erase(r.begin() + static_cast<std::ptrdiff_t>(i));
    };
    if (at_end.axis >= 0)
      while (x.size() > 2 && past(at_end, x.size() - 2) > 0) erase(x.size() - 2);
    if (at_start.axis >= 0)
      while (x.size() > 2 && past(at_start, 1) > 0) erase(1);
    const Eigen::Vector3d start_u = u0[bi].norm() > 0 ? u0[bi] : perpendicular(tg[0]);
    const std::vector<Eigen::Vector3d> u = rmf(x, tg, start_u);
    Ring prev;
    for (std::size_t i = 0; i < x.size(); ++i) {
      Ring R = make_ring(m, x[i], tg[i], u[i], std::max(r[i], 1e-6), k);
      if (i > 0) bridge(m, prev.ids, R.ids);
      if (i == 0) first[bi] = R;
      prev = R;
    }
    last[bi] = prev;
    auto slide = [&](Ring& R, const Flush& fl) {
      if (fl.axis < 0) return;
      auto onto = [&](const Eigen::Vector3d& q) { return Eigen::Vector3d(q - (q(fl.axis) - fl.plane) / fl.out(fl.axis) * fl.out); };
      for (int id : R.ids) m.v[static_cast<std::size_t>(id)] = onto(m.v[static_cast<std::size_t>(id)]);
      R.c = onto(R.c);
    };
    slide(first[bi], at_start);
    slide(last[bi], at_end);
    if (b.start_root) cap(m, first[bi], -first[bi].t, b.start_open, k);
    if (b.end_leaf) cap(m, last[bi], last[bi].t, b.end_open, k);
  }
  for (const Junction& J : f.junctions) {
    std::vector<const Ring*> C;
    for (int c : J.children) C.push_back(&first[c]);
    junction_patch(m, last[J.parent], C, k);
  }
  fair(m);
  orient(m);
  // into the tree: quads and triangles
  t.tube_vertices.resize(static_cast<Eigen::Index>(m.v.size()), 3);
  for (std::size_t i = 0; i < m.v.size(); ++i) t.tube_vertices.row(static_cast<Eigen::Index>(i)) = m.v[i].transpose();
  std::vector<std::array<int, 4>> q;
  std::vector<std::array<int, 3>> tr;
  for (const auto& F : m.faces) {
    if (F.size() == 4) q.push_back({F[0], F[1], F[2], F[3]});
    else tr.push_back({F[0], F[1], F[2]});
  }
  t.tube_quads.resize(static_cast<Eigen::Index>(q.size()), 4);
  for (std::size_t i = 0; i < q.size(); ++i)
    t.tube_quads.row(static_cast<Eigen::Index>(i)) << q[i][0], q[i][1], q[i][2], q[i][3];
  t.tube_tris.resize(static_cast<Eigen::Index>(tr.size()), 3);
  for (std::size_t i = 0; i < tr.size(); ++i) t.tube_tris.row(static_cast<Eigen::Index>(i)) << tr[i][0], tr[i][1], tr[i][2];
  open_cap = m.open_cap;
}

}  // namespace orthosim::vessels_detail
