#include "libmodel/msm/lattice.h"

#include "libmodel/format/types.h"

#include <Eigen/Dense>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>

namespace orthosim::msm {

namespace {

using Vec6 = Eigen::Matrix<double, 6, 1>;
using Vec3 = Eigen::Vector3d;

// Contribution of one unit weight of each spring group to the six orthotropic
// constants (C11 C22 C33 C23 C13 C12) per unit E, for a box a x b x c. A cell
// has 4 springs in every group; a spring along unit n adds beta n_i n_j n_k n_l.
Eigen::Matrix<double, 6, 7> group_matrix(double a, double b, double c) {
  const double a2 = a * a, b2 = b * b, c2 = c * c;
  Eigen::Matrix<double, 6, 7> A = Eigen::Matrix<double, 6, 7>::Zero();
  A(0, 0) = 4;  // edges u
  A(1, 1) = 4;  // edges v
  A(2, 2) = 4;  // edges w
  const double uv = (a2 + b2) * (a2 + b2), vw = (b2 + c2) * (b2 + c2), uw = (a2 + c2) * (a2 + c2);
  A(0, 3) = 4 * a2 * a2 / uv, A(1, 3) = 4 * b2 * b2 / uv, A(5, 3) = 4 * a2 * b2 / uv;  // face uv
  A(1, 4) = 4 * b2 * b2 / vw, A(2, 4) = 4 * c2 * c2 / vw, A(3, 4) = 4 * b2 * c2 / vw;  // face vw
  A(0, 5) = 4 * a2 * a2 / uw, A(2, 5) = 4 * c2 * c2 / uw, A(4, 5) = 4 * a2 * c2 / uw;  // face uw
  const double d = (a2 + b2 + c2) * (a2 + b2 + c2);                                   // body
  A(0, 6) = 4 * a2 * a2 / d, A(1, 6) = 4 * b2 * b2 / d, A(2, 6) = 4 * c2 * c2 / d;
  A(3, 6) = 4 * b2 * c2 / d, A(4, 6) = 4 * a2 * c2 / d, A(5, 6) = 4 * a2 * b2 / d;
  return A;
}

// the isotropic target per unit E with nu = 1/4: lambda = mu = 2E/5
Vec6 target() {
  Vec6 t;
  t << 1.2, 1.2, 1.2, 0.4, 0.4, 0.4;
  return t;
}

// Lawson-Hanson non-negative least squares, min |A x - b|, x >= 0, for the
// 6 x n (n <= 7) systems of the rule: fixed-size, no heap, normal equations
// on the passive set (well conditioned at these sizes).
using Mat67 = Eigen::Matrix<double, 6, 7>;
using Vec7 = Eigen::Matrix<double, 7, 1>;
Vec7 nnls(const Mat67& A, const Vec6& b, int n) {
  Vec7 x = Vec7::Zero();
  bool passive[7] = {false, false, false, false, false, false, false};
  const Eigen::Matrix<double, 7, 7> AtA = A.transpose() * A;
  const Vec7 Atb = A.transpose() * b;
  const double tol = 1e-12 * std::max(1.0, A.norm() * b.norm());
  auto solve_passive = [&](Vec7& s) {
    int P[7], m = 0;
    for (int i = 0; i < n; ++i)
      if (passive[i]) P[m++] = i;
    Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 7, 7> M(m, m);
    Eigen::Matrix<double, Eigen::Dynamic, 1, 0, 7, 1> r(m);
    for (int i = 0; i < m; ++i) {
      r(i) = Atb(P[i]);
      for (int j = 0; j < m; ++j) M(i, j) = AtA(P[i], P[j]);
    }
    const Eigen::Matrix<double, Eigen::Dynamic, 1, 0, 7, 1> y = M.ldlt().solve(r);
    s.setZero();
    for (int i = 0; i < m; ++i) s(P[i]) = y(i);
  };
  for (int outer = 0; outer < 3 * n + 10; ++outer) {
    const Vec7 w = Atb - AtA * x;
    int j = -1;
    double best = tol;
    for (int i = 0; i < n; ++i)
      if (!passive[i] && w(i) > best) best = w(i), j = i;
    if (j < 0) break;
    passive[j] = true;
    for (int inner = 0; inner < 3 * n + 10; ++inner) {
      Vec7 s;
      solve_passive(s);
      bool positive = true;
      for (int i = 0; i < n; ++i)
        if (passive[i] && !(s(i) > 0)) positive = false;
      if (positive) {
        x = s;
        break;
      }
      double alpha = 1;
      for (int i = 0; i < n; ++i)
        if (passive[i] && !(s(i) > 0)) alpha = std::min(alpha, x(i) / (x(i) - s(i)));
      x += alpha * (s - x);
      for (int i = 0; i < n; ++i)
        if (passive[i] && x(i) <= 1e-15) passive[i] = false, x(i) = 0;
    }
  }
  return x;
}

// r with every spring scaled by sum_a s_a n_a^2 (n: its direction in the box)
CellRule scaled_rule(const CellRule& r, double a, double b, double c, const std::array<double, 3>& s) {
  const double a2 = a * a, b2 = b * b, c2 = c * c;
  CellRule out = r;
  for (int i = 0; i < 3; ++i) out.edge[static_cast<std::size_t>(i)] *= s[static_cast<std::size_t>(i)];
  out.face[0] *= (s[0] * a2 + s[1] * b2) / (a2 + b2);
  out.face[1] *= (s[1] * b2 + s[2] * c2) / (b2 + c2);
  out.face[2] *= (s[0] * a2 + s[2] * c2) / (a2 + c2);
  out.body *= (s[0] * a2 + s[1] * b2 + s[2] * c2) / (a2 + b2 + c2);
  out.axis_factors = s;
  return out;
}

// The axis factors that make the box's three Young's moduli 1 (per unit E):
// the fixed point s_a <- s_a / E_a(s), to 1e-12 (it contracts: each modulus
// is dominated by its own axis's springs).
CellRule equalise_moduli(const CellRule& r, double a, double b, double c) {
  std::array<double, 3> s{1, 1, 1};
  // with a volume term the moduli are not linear in s: the same fixed point
  // converges (each modulus still follows its own axis's springs), more slowly
  CellRule best = r;
  double best_error = std::numeric_limits<double>::infinity();
  for (int it = 0; it < 2000; ++it) {
    const CellRule t = scaled_rule(r, a, b, c, s);
    const std::array<double, 3> E = axis_moduli(cell_stiffness(a, b, c, t));
    double error = 0;
    for (double e : E) error = std::max(error, std::abs(e - 1));
    if (!(error < best_error)) break;  // not contracting (never seen): keep the best
    best = t, best_error = error;
    if (error < 1e-12) break;
    for (int i = 0; i < 3; ++i) s[static_cast<std::size_t>(i)] /= E[static_cast<std::size_t>(i)];
  }
  return best;
}

// the least-squares weights of the six orthotropic constants
CellRule fit_cell_rule(double a, double b, double c, bool body_diagonals, double min_weight) {
  if (!(a > 0 && b > 0 && c > 0)) throw Error("", "lattice cell with a non-positive edge length");
  if (!(min_weight >= 0 && min_weight < 1)) throw Error("", "lattice min_weight must be in [0, 1)");
  const double edge_min = 0.1 * min_weight, face_min = 0.4 * min_weight;  // the cube's weights times the floor
  CellRule r;
  const double a2 = a * a, b2 = b * b, c2 = c * c;
  if (!body_diagonals) {
    // closed form: face diagonals carry the Poisson/shear terms, edges the rest
    r.face[0] = 0.1 * (a2 + b2) * (a2 + b2) / (a2 * b2);
    r.face[1] = 0.1 * (b2 + c2) * (b2 + c2) / (b2 * c2);
    r.face[2] = 0.1 * (a2 + c2) * (a2 + c2) / (a2 * c2);
    r.edge[0] = 0.1 * (3 - a2 / b2 - a2 / c2);
    r.edge[1] = 0.1 * (3 - b2 / a2 - b2 / c2);
    r.edge[2] = 0.1 * (3 - c2 / a2 - c2 / b2);
    // (face weights are >= 2/5 >= face_min for any box)
    if (r.edge[0] >= edge_min && r.edge[1] >= edge_min && r.edge[2] >= edge_min) return r;
  }
  // no exact solution above the floor (or body diagonals): relative least
  // squares with x >= x_min, i.e. NNLS in y = x - x_min
  const int n = body_diagonals ? 7 : 6;
  const Vec6 t = target();
  Mat67 A = group_matrix(a, b, c);
  if (!body_diagonals) A.col(6).setZero();
  for (int i = 0; i < 6; ++i) A.row(i) /= t(i);
  Vec7 x_min = Vec7::Zero();
  x_min << edge_min, edge_min, edge_min, face_min, face_min, face_min, 0.0;
  const Vec7 x = x_min + nnls(A, Vec6::Ones() - A * x_min, n);
  for (int k = 0; k < 3; ++k) r.edge[static_cast<std::size_t>(k)] = x(k);
  for (int k = 0; k < 3; ++k) r.face[static_cast<std::size_t>(k)] = x(3 + k);
  r.body = body_diagonals ? x(6) : 0;
  r.residual = std::sqrt((A * x - Vec6::Ones()).squaredNorm() / 6);
  r.exact = r.residual < 1e-9;
  return r;
}

}  // namespace

CellRule cell_rule(double a, double b, double c, bool body_diagonals, double min_weight, bool equal_moduli,
                   double volume_ratio) {
  if (!(volume_ratio >= 0 && volume_ratio < 1e6)) throw Error("", "lattice volume ratio must be in [0, 1e6)");
  CellRule r = fit_cell_rule(a, b, c, body_diagonals, min_weight);
  r.volume_ratio = volume_ratio;
  return equal_moduli && (!r.exact || volume_ratio > 0) ? equalise_moduli(r, a, b, c) : r;
}

Eigen::Matrix<double, 6, 6> box_stiffness(double a, double b, double c, const CellRule& r) {
  Eigen::Matrix<double, 7, 1> x;
  x << r.edge[0], r.edge[1], r.edge[2], r.face[0], r.face[1], r.face[2], r.body;
  const Vec6 k = group_matrix(a, b, c) * x;  // C11 C22 C33 C23 C13 C12
  Eigen::Matrix<double, 6, 6> C = Eigen::Matrix<double, 6, 6>::Zero();
  C(0, 0) = k(0), C(1, 1) = k(1), C(2, 2) = k(2);
  C(1, 2) = C(2, 1) = C(3, 3) = k(3);  // Cauchy relation: C44 = C23
  C(0, 2) = C(2, 0) = C(4, 4) = k(4);
  C(0, 1) = C(1, 0) = C(5, 5) = k(5);
  return C;
}

Eigen::Matrix<double, 6, 6> cell_stiffness(double a, double b, double c, const CellRule& r) {
  Eigen::Matrix<double, 6, 6> C = box_stiffness(a, b, c, r);
  C.topLeftCorner<3, 3>().array() += r.volume_ratio;
  return C;
}

std::array<double, 3> axis_moduli(const Eigen::Matrix<double, 6, 6>& C) {
  Eigen::Matrix3d n = C.topLeftCorner<3, 3>();
  Eigen::Matrix3d S = n.inverse();  // normal block: shears decouple for orthotropic lattices
  return {1 / S(0, 0), 1 / S(1, 1), 1 / S(2, 2)};
}

double hex_min_jacobian(const Vec3 T[4], const Vec3 B[4]) {
  // trilinear map from the unit cube: xi along q0 -> q1, eta along q0 -> q3,
  // zeta from the top (outer) quad to the bottom one; the quads are
  // counter-clockwise seen from outside, so det[x_xi, x_eta, x_zeta] < 0 on
  // a valid cell and J = -det
  auto J = [](const Vec3& xi, const Vec3& eta, const Vec3& zeta) { return -xi.cross(eta).dot(zeta); };
  double m = std::numeric_limits<double>::infinity();
  for (const Vec3* Q : {T, B})
    for (int i = 0; i < 4; ++i) {
      const Vec3 xi = (i == 0 || i == 1) ? Vec3(Q[1] - Q[0]) : Vec3(Q[2] - Q[3]);
      const Vec3 eta = (i == 0 || i == 3) ? Vec3(Q[3] - Q[0]) : Vec3(Q[2] - Q[1]);
      m = std::min(m, J(xi, eta, B[i] - T[i]));
    }
  const Vec3 xi = 0.25 * (T[1] - T[0] + T[2] - T[3] + B[1] - B[0] + B[2] - B[3]);
  const Vec3 eta = 0.25 * (T[3] - T[0] + T[2] - T[1] + B[3] - B[0] + B[2] - B[1]);
  const Vec3 zeta = 0.25 * (B[0] - T[0] + B[1] - T[1] + B[2] - T[2] + B[3] - T[3]);
  return std::min(m, J(xi, eta, zeta));
}

LayerCells lattice_cells(const MatX3d& top, const MatX3d& bottom, const MatX4i& quads, const NodeBlocks& blocks,
                         const LatticeOptions& o) {
  if (o.through_cells < 1 || o.through_cells > 64) throw Error("", "through_cells must be in 1..64");
  const int ng = static_cast<int>(top.rows());
  const int nw = o.through_cells;
  LayerCells out;
  // interior grids: linear between top and bottom
  out.created.resize(static_cast<Eigen::Index>(ng) * (nw - 1), 3);
  for (int k = 1; k < nw; ++k) {
    const double s = static_cast<double>(k) / nw;
    out.created.middleRows(static_cast<Eigen::Index>(k - 1) * ng, ng) = (1 - s) * top + s * bottom;
  }
  // grid k in 0..nw: global id and position of local vertex v
  auto gid = [&](int k, int v) -> std::int32_t {
    if (k == 0) return blocks.top + v;
    if (k == nw) return blocks.bottom + v;
    return blocks.created + (k - 1) * ng + v;
  };
  auto pos = [&](int k, int v) -> Vec3 {
    if (k == 0) return top.row(v).transpose();
    if (k == nw) return bottom.row(v).transpose();
    return out.created.row(static_cast<Eigen::Index>(k - 1) * ng + v).transpose();
  };
  const std::int32_t last = std::max({blocks.top + ng, blocks.bottom + ng, blocks.created + ng * (nw - 1)});
  out.node_volume.assign(static_cast<std::size_t>(last), 0.0);

  // pass 1, parallel over cells: volumes, rule, springs into fixed slots
  const Eigen::Index nq = quads.rows(), ncell = nq * nw;
  const int per = o.body_diagonals ? 28 : 24;
  out.terms.assign(static_cast<std::size_t>(ncell) * per, SpringTerm{});
  std::vector<double> cell_v(static_cast<std::size_t>(ncell)), sub_v(static_cast<std::size_t>(ncell) * 6),
      cell_j(static_cast<std::size_t>(ncell));
  std::vector<CellRule> rules(static_cast<std::size_t>(ncell));
  std::vector<std::array<double, 3>> moduli(static_cast<std::size_t>(ncell), {0, 0, 0});
  std::vector<std::array<double, 3>> shears(static_cast<std::size_t>(ncell), {0, 0, 0});
  std::vector<char> ruled(static_cast<std::size_t>(ncell), 0);
  const bool with_tets = o.volume_ratio > 0 || o.tets;
  if (with_tets) out.tets.assign(static_cast<std::size_t>(ncell) * 6, {0, 0, 0, 0});
  std::vector<std::array<double, 3>> dims(static_cast<std::size_t>(ncell), {0, 0, 0});
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, ncell, 256), [&](const tbb::blocked_range<Eigen::Index>& range) {
    for (Eigen::Index cell = range.begin(); cell != range.end(); ++cell) {
      const int k = static_cast<int>(cell / nq);
      const Eigen::Index q = cell % nq;
      const int v[4] = {quads(q, 0), quads(q, 1), quads(q, 2), quads(q, 3)};
      Vec3 T[4], B[4];
      std::int32_t t[4], b[4];
      for (int i = 0; i < 4; ++i) {
        T[i] = pos(k, v[i]);
        B[i] = pos(k + 1, v[i]);
        t[i] = gid(k, v[i]);
        b[i] = gid(k + 1, v[i]);
      }
      // volume: two prisms over (0,1,2) and (0,2,3), each cut into 3 tetrahedra
      // with side diagonals from the smaller node id (prism_cut: consistent
      // between cells)
      double V = 0;
      int sub = 0;
      std::array<std::int32_t, 4>* tet = with_tets ? &out.tets[static_cast<std::size_t>(cell) * 6] : nullptr;
      const auto P = [&](PrismCorner c) -> const Vec3& { return c.bottom ? B[c.local] : T[c.local]; };
      const auto I = [&](PrismCorner c) { return c.bottom ? b[c.local] : t[c.local]; };
      for (const auto& tri : {std::array<int, 3>{0, 1, 2}, std::array<int, 3>{0, 2, 3}})
        for (const auto& tc : prism_cut(v, tri)) {
          const double x = tet_volume(P(tc[0]), P(tc[1]), P(tc[2]), P(tc[3]));
          if (tet) *tet++ = {I(tc[0]), I(tc[1]), I(tc[2]), I(tc[3])};
          sub_v[static_cast<std::size_t>(cell) * 6 + sub++] = x;
          V += x;
        }
      cell_v[static_cast<std::size_t>(cell)] = V;
      cell_j[static_cast<std::size_t>(cell)] = hex_min_jacobian(T, B);
      // equivalent box: mean edge lengths along u (q0q1, q3q2), v (q1q2, q0q3), w
      const double a = 0.25 * ((T[1] - T[0]).norm() + (T[2] - T[3]).norm() + (B[1] - B[0]).norm() + (B[2] - B[3]).norm());
      const double bl = 0.25 * ((T[2] - T[1]).norm() + (T[3] - T[0]).norm() + (B[2] - B[1]).norm() + (B[3] - B[0]).norm());
      double c = 0;
      for (int i = 0; i < 4; ++i) c += 0.25 * (B[i] - T[i]).norm();
      const bool valid = a > 0 && bl > 0 && c > 0 && V > 0 && cell_j[static_cast<std::size_t>(cell)] > 0;  // else: inverted, k = 0
      CellRule r;
      if (valid) {
        r = cell_rule(a, bl, c, o.body_diagonals, o.min_weight, o.axis_correction, o.volume_ratio);
        rules[static_cast<std::size_t>(cell)] = r;
        const Eigen::Matrix<double, 6, 6> C = cell_stiffness(a, bl, c, r);
        moduli[static_cast<std::size_t>(cell)] = axis_moduli(C);
        shears[static_cast<std::size_t>(cell)] = {C(3, 3), C(4, 4), C(5, 5)};
        ruled[static_cast<std::size_t>(cell)] = 1;
        dims[static_cast<std::size_t>(cell)] = {a, bl, c};
      }
      SpringTerm* slot = out.terms.data() + static_cast<std::size_t>(cell) * per;
      auto add = [&](std::int32_t p, const Vec3& xp, std::int32_t qd, const Vec3& xq, double beta, SpringClass cls) {
        const double l2 = (xq - xp).squaredNorm();
        *slot++ = SpringTerm{p, qd, valid && l2 > 0 ? beta * V / l2 : 0.0, cls};
      };
      // 12 edges
      for (int i = 0; i < 4; ++i) {
        const int j = (i + 1) % 4;
        const double beta = r.edge[i % 2 == 0 ? 0 : 1];  // q0q1, q2q3 along u; q1q2, q3q0 along v
        add(t[i], T[i], t[j], T[j], beta, SpringClass::structural);
        add(b[i], B[i], b[j], B[j], beta, SpringClass::structural);
        add(t[i], T[i], b[i], B[i], r.edge[2], SpringClass::inter_layer);
      }
      // 12 face diagonals
      for (int i = 0; i < 2; ++i) {
        add(t[i], T[i], t[i + 2], T[i + 2], r.face[0], SpringClass::shear);
        add(b[i], B[i], b[i + 2], B[i + 2], r.face[0], SpringClass::shear);
      }
      for (int i = 0; i < 4; ++i) {
        const int j = (i + 1) % 4;
        const double beta = r.face[i % 2 == 0 ? 2 : 1];  // side over a u edge: uw face; over a v edge: vw face
        add(t[i], T[i], b[j], B[j], beta, SpringClass::shear);
        add(t[j], T[j], b[i], B[i], beta, SpringClass::shear);
      }
      if (o.body_diagonals)
        for (int i = 0; i < 4; ++i) add(t[i], T[i], b[(i + 2) % 4], B[(i + 2) % 4], r.body, SpringClass::body);
    }
  });
  // pass 2, serial: lumped volumes and statistics, in cell order
  double min_v = std::numeric_limits<double>::infinity(), sum_v = 0;
  double ratio_sum[3] = {0, 0, 0}, dim_sum[3] = {0, 0, 0}, shear_sum[3] = {0, 0, 0};
  for (Eigen::Index cell = 0; cell < ncell; ++cell) {
    const int k = static_cast<int>(cell / nq);
    const Eigen::Index q = cell % nq;
    const double V = cell_v[static_cast<std::size_t>(cell)];
    sum_v += V;
    ++out.cells;
    for (int i = 0; i < 4; ++i) {
      out.node_volume[static_cast<std::size_t>(gid(k, quads(q, i)))] += V / 8;
      out.node_volume[static_cast<std::size_t>(gid(k + 1, quads(q, i)))] += V / 8;
    }
    for (int s = 0; s < 6; ++s) min_v = std::min(min_v, sub_v[static_cast<std::size_t>(cell) * 6 + s]);
    if (!ruled[static_cast<std::size_t>(cell)]) continue;
    const CellRule& r = rules[static_cast<std::size_t>(cell)];
    ++out.rule.cells;
    if (r.exact) ++out.rule.exact;
    out.rule.max_residual = std::max(out.rule.max_residual, r.residual);
    for (int i = 0; i < 3; ++i) {
      ratio_sum[i] += moduli[static_cast<std::size_t>(cell)][static_cast<std::size_t>(i)];
      shear_sum[i] += shears[static_cast<std::size_t>(cell)][static_cast<std::size_t>(i)];
      dim_sum[i] += dims[static_cast<std::size_t>(cell)][static_cast<std::size_t>(i)];
    }
  }
  const std::vector<double>& sub_volumes = sub_v;
  out.volume_m3 = sum_v;
  out.sub_tets = static_cast<std::int64_t>(sub_volumes.size());
  out.mean_tet_volume_m3 = sub_volumes.empty() ? 0 : sum_v / static_cast<double>(sub_volumes.size());
  out.min_tet_volume_m3 = sub_volumes.empty() ? 0 : min_v;
  // a hexahedron is inverted where its Jacobian is not positive at a corner
  // or the centre (the sub-tetrahedra above are a volume quadrature, not
  // elements: a sheared but valid cell may have one of negative volume)
  const double floor = o.inverted_ratio * std::abs(ncell ? sum_v / static_cast<double>(ncell) : 0.0);
  out.min_jacobian_m3 = cell_j.empty() ? 0 : *std::min_element(cell_j.begin(), cell_j.end());
  for (std::size_t i = 0; i < cell_j.size(); ++i)
    if (!(cell_j[i] > floor) && out.inverted++ == 0) out.first_inverted_quad = static_cast<std::int64_t>(i) % nq;
  if (out.rule.cells > 0)
    for (int i = 0; i < 3; ++i)
      out.rule.mean_modulus_ratio[static_cast<std::size_t>(i)] = ratio_sum[i] / static_cast<double>(out.rule.cells),
      out.rule.mean_cell_m[static_cast<std::size_t>(i)] = dim_sum[i] / static_cast<double>(out.rule.cells),
      out.rule.mean_shear_ratio[static_cast<std::size_t>(i)] = shear_sum[i] / static_cast<double>(out.rule.cells);
  return out;
}

}  // namespace orthosim::msm
