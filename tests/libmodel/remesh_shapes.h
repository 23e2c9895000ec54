// Analytic closed test surfaces for remesh: generalised cylinders along a
// centreline, closed by flat caps like limb surfaces cut by the first and last
// slice (or by domes), meshed finely.
#pragma once

#include "libmodel/format/model.h"

#include <Eigen/Geometry>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <functional>

namespace orthosim::test {

constexpr double kPi = 3.14159265358979323846;

// p(t, theta): point of the surface at axis parameter t in [0, 1] and angle
// theta, counter-clockwise around the direction of increasing t. c(t): the
// centre of the end caps. na points around, nl + 1 rings.
inline Surface tube_mesh(const std::function<Eigen::Vector3d(double, double)>& p,
                         const std::function<Eigen::Vector3d(double)>& c, int na, int nl) {
  Surface s;
  const int nv = na * (nl + 1) + 2;
  s.vertices.resize(nv, 3);
  for (int l = 0; l <= nl; ++l)
    for (int a = 0; a < na; ++a) s.vertices.row(l * na + a) = p(static_cast<double>(l) / nl, 2 * kPi * a / na);
  const int c0 = na * (nl + 1), c1 = c0 + 1;
  s.vertices.row(c0) = c(0);
  s.vertices.row(c1) = c(1);
  s.faces.resize(2 * na * nl + 2 * na, 3);
  int f = 0;
  for (int l = 0; l < nl; ++l)
    for (int a = 0; a < na; ++a) {
      const int a1 = (a + 1) % na;
      const int v00 = l * na + a, v10 = l * na + a1, v11 = (l + 1) * na + a1, v01 = (l + 1) * na + a;
      s.faces.row(f++) << v00, v10, v11;
      s.faces.row(f++) << v00, v11, v01;
    }
  for (int a = 0; a < na; ++a) {
    const int a1 = (a + 1) % na;
    s.faces.row(f++) << c0, a1, a;
    s.faces.row(f++) << c1, nl * na + a, nl * na + a1;
  }
  return s;
}

// straight circular cylinder of radius r along z from z0 to z0 + len, centred at (x, y)
inline Surface cylinder(double r, double len, int na = 128, int nl = 64, double x = 0, double y = 0, double z0 = 0) {
  return tube_mesh([=](double t, double th) { return Eigen::Vector3d(x + r * std::cos(th), y + r * std::sin(th), z0 + t * len); },
                   [=](double t) { return Eigen::Vector3d(x, y, z0 + t * len); }, na, nl);
}

// cone tapering from radius r0 at z = 0 to r1 at z = len
inline Surface cone(double r0, double r1, double len, int na = 128, int nl = 64) {
  return tube_mesh([=](double t, double th) {
                     const double r = r0 + (r1 - r0) * t;
                     return Eigen::Vector3d(r * std::cos(th), r * std::sin(th), t * len);
                   },
                   [=](double t) { return Eigen::Vector3d(0, 0, t * len); }, na, nl);
}

// elliptic tube (semi-axes a in the bend plane, b across it) bent along a
// circular arc of radius rho through angle phi in the x-z plane, starting at
// the origin along +z. Caps are normal to the arc at its ends.
struct BentTube {
  double a = 0.03, b = 0.02, rho = 0.15, phi = kPi / 3;
  Eigen::Vector3d centre(double t) const {
    const double f = t * phi;
    return {rho * (1 - std::cos(f)), 0, rho * std::sin(f)};
  }
  Eigen::Vector3d point(double t, double th) const {
    const double f = t * phi;
    const Eigen::Vector3d n1(std::cos(f), 0, -std::sin(f)), n2(0, 1, 0);
    return centre(t) + a * std::cos(th) * n1 + b * std::sin(th) * n2;
  }
  Surface mesh(int na, int nl) const {
    return tube_mesh([this](double t, double th) { return point(t, th); }, [this](double t) { return centre(t); }, na, nl);
  }
};

// capsule: cylinder of radius r and shaft length len along z with hemispherical ends
inline Surface capsule(double r, double len, int na = 96, int nl = 96) {
  // t in [0, 1] runs over the arc length of the profile: dome, shaft, dome
  const double total = kPi * r + len;
  auto prof = [=](double t, double* z, double* rr) {
    const double s = t * total;
    if (s < kPi * r / 2) {
      const double a = s / r;  // 0 at the pole
      *z = -r * std::cos(a), *rr = r * std::sin(a);
    } else if (s < kPi * r / 2 + len) {
      *z = s - kPi * r / 2, *rr = r;
    } else {
      const double a = (s - kPi * r / 2 - len) / r;
      *z = len + r * std::sin(a), *rr = r * std::cos(a);
    }
  };
  // rings l = 0..nl at profile fractions (l + 1) / (nl + 2); the poles are the fan centres
  return tube_mesh([=](double t, double th) {
                     double z, rr;
                     prof((t * nl + 1) / (nl + 2), &z, &rr);
                     return Eigen::Vector3d(rr * std::cos(th), rr * std::sin(th), z);
                   },
                   [=](double t) { return Eigen::Vector3d(0, 0, t < 0.5 ? -r : len + r); }, na, nl);
}

// torus (not tube-like for remesh: ring-shaped)
inline Surface torus(double R, double r, int na = 64, int nl = 64) {
  Surface s;
  s.vertices.resize(na * nl, 3);
  for (int l = 0; l < nl; ++l)
    for (int a = 0; a < na; ++a) {
      const double u = 2 * kPi * l / nl, v = 2 * kPi * a / na;
      s.vertices.row(l * na + a) << (R + r * std::cos(v)) * std::cos(u), (R + r * std::cos(v)) * std::sin(u), r * std::sin(v);
    }
  s.faces.resize(2 * na * nl, 3);
  int f = 0;
  for (int l = 0; l < nl; ++l)
    for (int a = 0; a < na; ++a) {
      const int l1 = (l + 1) % nl, a1 = (a + 1) % na;
      s.faces.row(f++) << l * na + a, l1 * na + a, l1 * na + a1;
      s.faces.row(f++) << l * na + a, l1 * na + a1, l * na + a1;
    }
  return s;
}

// the union of two surfaces as one (two components)
inline Surface merge(const Surface& a, const Surface& b) {
  Surface s;
  s.vertices.resize(a.vertices.rows() + b.vertices.rows(), 3);
  s.vertices << a.vertices, b.vertices;
  s.faces.resize(a.faces.rows() + b.faces.rows(), 3);
  s.faces.topRows(a.faces.rows()) = a.faces;
  s.faces.bottomRows(b.faces.rows()) = b.faces.array() + static_cast<int>(a.vertices.rows());
  return s;
}

// Smallest sub-tetrahedron volume of the hexahedral cells between corresponding
// quads of two layers, over the mean: the split and orientation of the
// builder's lattice cells (libmodel/msm/lattice.cpp). <= 0: a cell inverts.
inline double min_cell_tet_ratio(const QuadSurface& top, const QuadSurface& bot) {
  auto vol = [](const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c, const Eigen::Vector3d& d) { return (b - a).dot((c - a).cross(d - a)) / 6; };
  double mn = std::numeric_limits<double>::infinity(), sum = 0;
  int n = 0;
  for (Eigen::Index q = 0; q < top.quads.rows(); ++q) {
    const Eigen::Vector4i v = top.quads.row(q).transpose();
    Eigen::Vector3d T[4], B[4];
    for (int i = 0; i < 4; ++i) T[i] = top.vertices.row(v[i]).transpose(), B[i] = bot.vertices.row(v[i]).transpose();
    for (const auto& tri : {std::array<int, 3>{0, 1, 2}, std::array<int, 3>{0, 2, 3}}) {
      std::array<int, 3> s = tri;
      std::sort(s.begin(), s.end(), [&](int x, int y) { return v[x] < v[y]; });
      const bool ccw = (s[0] == tri[0] && s[1] == tri[1]) || (s[0] == tri[1] && s[1] == tri[2]) ||
                       (s[0] == tri[2] && s[1] == tri[0]);
      const Eigen::Vector3d &a = T[s[0]], &bb = T[s[1]], &c = T[s[2]], &a_ = B[s[0]], &b_ = B[s[1]], &c_ = B[s[2]];
      const double tv[3] = {ccw ? vol(a, b_, a_, c_) : vol(a, a_, b_, c_), ccw ? vol(a, bb, b_, c_) : vol(a, b_, bb, c_),
                            ccw ? vol(a, c, bb, c_) : vol(a, bb, c, c_)};
      for (double x : tv) mn = std::min(mn, x), sum += x, ++n;
    }
  }
  return mn / (sum / n);
}

}  // namespace orthosim::test
