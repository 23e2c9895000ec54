// Curvature-adaptive piecewise cubic Bezier fit of each branch's centreline
// and radius.
//
// Each piece is the cubic Hermite segment between two centreline points
// (knots) with the centreline's unit tangents there and handles of a third of
// the piece's arc length h: P1 = P0 + h/3 T0, P2 = P3 - h/3 T1. In the global
// parameter s (arc length at the knots) every join has the derivative T, the
// same on both sides: the curve is C1 in s (and G1 geometrically). A piece
// whose largest distance to the centreline points it spans exceeds the
// tolerance is split at its worst point (kept in the middle half), so knots
// gather where the centreline bends and stay sparse where it is straight.
// The radius is the same construction on the scalar r(s).
#include "libmodel/vessels/detail.h"

#include <algorithm>
#include <cmath>

namespace orthosim::vessels_detail {
namespace {

struct PieceError {
  double pos = 0, rad = 0;
  int worst_pos = -1, worst_rad = -1;
};

PieceError piece_error(const std::vector<Eigen::Vector3d>& x, const std::vector<double>& r,
                       const std::vector<double>& s, const std::vector<Eigen::Vector3d>& T,
                       const std::vector<double>& dr, int i0, int i1) {
  PieceError e;
  const double h = s[i1] - s[i0];
  if (!(h > 0)) return e;
  const Eigen::Vector3d P0 = x[i0], P3 = x[i1], P1 = P0 + h / 3 * T[i0], P2 = P3 - h / 3 * T[i1];
  const double R0 = r[i0], R3 = r[i1], R1 = R0 + h / 3 * dr[i0], R2 = R3 - h / 3 * dr[i1];
  for (int i = i0 + 1; i < i1; ++i) {
    double t = (s[i] - s[i0]) / h;
    for (int it = 0; it < 4; ++it) {  // Newton on (C(t) - x) . C'(t) = 0
      const Eigen::Vector3d c = bezier3(P0, P1, P2, P3, t) - x[i];
      const Eigen::Vector3d d1 = bezier3_d(P0, P1, P2, P3, t);
      const double u = 1 - t;
      const Eigen::Vector3d d2 = 6 * u * (P2 - 2 * P1 + P0) + 6 * t * (P3 - 2 * P2 + P1);
      const double f = c.dot(d1), fp = d1.dot(d1) + c.dot(d2);
      if (!(fp > 0)) break;
      t = std::clamp(t - f / fp, 0.0, 1.0);
    }
    const double dp = (bezier3(P0, P1, P2, P3, t) - x[i]).norm();
    const double drr = std::abs(bezier3(R0, R1, R2, R3, (s[i] - s[i0]) / h) - r[i]);
    if (dp > e.pos) e.pos = dp, e.worst_pos = i;
    if (drr > e.rad) e.rad = drr, e.worst_rad = i;
  }
  return e;
}

}  // namespace

double fit_bezier(Forest& f, double tol) {
  double worst = 0;
  for (Branch& b : f.branches) {
    const int n = static_cast<int>(b.x.size());
    std::vector<double> s(n, 0);
    for (int i = 1; i < n; ++i) s[i] = s[i - 1] + (b.x[i] - b.x[i - 1]).norm();
    // tangents and radius slopes: central differences over about half a
    // radius, second-order one-sided at the ends
    std::vector<Eigen::Vector3d> T(n);
    std::vector<double> dr(n, 0);
    const double step = n > 1 ? s.back() / (n - 1) : 1;
    for (int i = 0; i < n; ++i) {
      const int w = std::max(1, std::min(static_cast<int>(std::lround(0.5 * b.r[i] / std::max(step, 1e-12))), (n - 1) / 2));
      Eigen::Vector3d d;
      double ds, rr;
      if (i - w >= 0 && i + w < n) {
        d = b.x[i + w] - b.x[i - w];
        rr = b.r[i + w] - b.r[i - w];
        ds = s[i + w] - s[i - w];
      } else if (i - w < 0) {
        const int a = std::min(n - 1, i + w), c = std::min(n - 1, i + 2 * w);
        d = c > a ? Eigen::Vector3d(-3 * b.x[i] + 4 * b.x[a] - b.x[c]) : Eigen::Vector3d(b.x[a] - b.x[i]);
        rr = c > a ? -3 * b.r[i] + 4 * b.r[a] - b.r[c] : b.r[a] - b.r[i];
        ds = c > a ? 2 * (s[a] - s[i]) : s[a] - s[i];
      } else {
        const int a = std::max(0, i - w), c = std::max(0, i - 2 * w);
        d = c < a ? Eigen::Vector3d(3 * b.x[i] - 4 * b.x[a] + b.x[c]) : Eigen::Vector3d(b.x[i] - b.x[a]);
        rr = c < a ? 3 * b.r[i] - 4 * b.r[a] + b.r[c] : b.r[i] - b.r[a];
        ds = c < a ? 2 * (s[i] - s[a]) : s[i] - s[a];
      }
      T[i] = d.norm() > 0 ? d.normalized() : Eigen::Vector3d(0, 0, 1);
      dr[i] = ds > 0 ? rr / ds : 0;
    }
    // recursive split
    std::vector<int> knots{0};
    std::vector<std::pair<int, int>> stack{{0, n - 1}};
    std::vector<std::pair<int, int>> done;
    while (!stack.empty()) {
      const auto [i0, i1] = stack.back();
      stack.pop_back();
      const PieceError e = piece_error(b.x, b.r, s, T, dr, i0, i1);
      if ((e.pos > tol || e.rad > tol) && i1 - i0 >= 2) {
        int m = e.pos > tol ? e.worst_pos : e.worst_rad;
        const int q = (i1 - i0) / 4;
        m = std::clamp(m, i0 + std::max(1, q), i1 - std::max(1, q));
        stack.push_back({m, i1});
        stack.push_back({i0, m});
        continue;
      }
      worst = std::max(worst, e.pos);
      knots.push_back(i1);
    }
    b.ctrl.clear(), b.ctrl_r.clear(), b.knots.clear();
    for (std::size_t k = 0; k + 1 < knots.size(); ++k) {
      const int i0 = knots[k], i1 = knots[k + 1];
      const double h = s[i1] - s[i0];
      if (k == 0) b.ctrl.push_back(b.x[i0]), b.ctrl_r.push_back(b.r[i0]), b.knots.push_back(s[i0]);
      b.ctrl.push_back(b.x[i0] + h / 3 * T[i0]);
      b.ctrl.push_back(b.x[i1] - h / 3 * T[i1]);
      b.ctrl.push_back(b.x[i1]);
      b.ctrl_r.push_back(b.r[i0] + h / 3 * dr[i0]);
      b.ctrl_r.push_back(b.r[i1] - h / 3 * dr[i1]);
      b.ctrl_r.push_back(b.r[i1]);
      b.knots.push_back(s[i1]);
    }
  }
  return worst;
}

Eigen::Vector3d branch_point(const Branch& b, double s, Eigen::Vector3d* tangent, double* radius) {
  const int pieces = static_cast<int>(b.knots.size()) - 1;
  s = std::clamp(s, b.knots.front(), b.knots.back());
  const int i = std::clamp(static_cast<int>(std::upper_bound(b.knots.begin(), b.knots.end(), s) - b.knots.begin()) - 1,
                           0, pieces - 1);
  const double h = b.knots[i + 1] - b.knots[i];
  const double t = h > 0 ? (s - b.knots[i]) / h : 0;
  const Eigen::Vector3d *p = &b.ctrl[3 * i];
  if (tangent) {
    Eigen::Vector3d d = bezier3_d(p[0], p[1], p[2], p[3], t);
    if (d.norm() == 0) d = p[3] - p[0];
    *tangent = d.normalized();
  }
  if (radius) *radius = bezier3(b.ctrl_r[3 * i], b.ctrl_r[3 * i + 1], b.ctrl_r[3 * i + 2], b.ctrl_r[3 * i + 3], t);
  return bezier3(p[0], p[1], p[2], p[3], t);
}

}  // namespace orthosim::vessels_detail
