// Stateless mass-spring kernels: pure functions of their arguments, used by
// the solver's hot loops and by the reference solvers in tests.
//
// The spring is the emulated PPU's only element (paper §4.1): a linear spring
// with an axial dashpot. A biphasic spring (k1 up to its turning length Lt,
// total slope k2 beyond) arrives as two of them in parallel: (k1, L0) always
// active and (k2 - k1, Lt) tension-only, exerting nothing while shorter than
// its rest length (see Layer in libmodel/format/model.h).
#pragma once

#include "runtime/types.h"

#include <algorithm>

namespace orthosim::runtime {

// Below this length (m) a spring's direction is undefined: it exerts no force
// and contributes no stiffness. A spring of rest length 0 exerts k*d, which
// tends to 0 continuously, so this is a removable singularity, never a NaN.
inline constexpr Real kTinyLength = 1e-30;

// Force on end a and elastic energy of one linear spring.
//   d = x_b - x_a, dv = v_b - v_a, L = |d|, n = d / L
//   f_a = (k (L - L0) + c dv.n) n,  f_b = -f_a,  U = k (L - L0)^2 / 2
// A tension-only spring is inactive (f = 0, U = 0) while L < L0.
struct SpringForce {
  Vec3 f;      // N, on end a
  Real energy;  // J
};
inline SpringForce spring_force(const Vec3& d, const Vec3& dv, Real rest, Real k, Real c, bool tension_only) {
  // branch-free: at L = 0, d = 0 and the force is 0 whatever 1/max(L, tiny) is
  const Real len = norm(d);
  const Real inv_len = Real(1) / std::max(len, kTinyLength);
  const Real stretch = len - rest;
  const Real active = static_cast<Real>(!tension_only | (stretch >= 0));
  const Real mag = active * (k * stretch + c * dot(dv, d) * inv_len);
  return {(mag * inv_len) * d, active * Real(0.5) * k * stretch * stretch};
}

// Geometry of a spring, shared by the linear springs joining the same two
// nodes (a biphasic spring's two phases): d = x_b - x_a, L, 1/L and the
// axial rate dv.d / L (m/s).
struct SpringGeometry {
  Vec3 d;
  Real len, inv_len, rate;
};
inline SpringGeometry spring_geometry(const Vec3& d, const Vec3& dv) {
  const Real len = norm(d);
  const Real inv_len = Real(1) / std::max(len, kTinyLength);
  return {d, len, inv_len, dot(dv, d) * inv_len};
}
// The force of spring_force from a precomputed geometry (the symplectic hot loop).
inline Vec3 spring_force(const SpringGeometry& g, Real rest, Real k, Real c, bool tension_only) {
  const Real stretch = g.len - rest;
  const Real active = static_cast<Real>(!tension_only | (stretch >= 0));
  const Real mag = active * (k * stretch + c * g.rate);
  return (mag * g.inv_len) * g.d;
}

// Elastic force only (no damping), for the implicit integrator's right-hand side.
inline SpringForce spring_force_elastic(const Vec3& d, Real rest, Real k, bool tension_only) {
  return spring_force(d, Vec3{}, rest, k, 0, tension_only);
}

// A tetrahedron's signed volume V = det[b-a, c-a, d-a] / 6 and its gradient
// dV/dx of corners a, b, c, d (m^2; they sum to zero).
struct TetGradient {
  Real volume = 0;
  Vec3 g[4];
};
inline TetGradient tet_gradient(const Vec3& a, const Vec3& b, const Vec3& c, const Vec3& d) {
  const Vec3 e1 = b - a, e2 = c - a, e3 = d - a;
  TetGradient t;
  t.g[1] = Real(1) / 6 * cross(e2, e3);
  t.g[2] = Real(1) / 6 * cross(e3, e1);
  t.g[3] = Real(1) / 6 * cross(e1, e2);
  t.g[0] = -(t.g[1] + t.g[2] + t.g[3]);
  t.volume = dot(e1, t.g[1]);
  return t;
}

// A symmetric 3x3 block.
struct Sym3 {
  Real xx = 0, yy = 0, zz = 0, xy = 0, xz = 0, yz = 0;
};
inline Vec3 operator*(const Sym3& s, const Vec3& v) {
  return {s.xx * v.x + s.xy * v.y + s.xz * v.z, s.xy * v.x + s.yy * v.y + s.yz * v.z,
          s.xz * v.x + s.yz * v.y + s.zz * v.z};
}
// s g g^T
inline Sym3 outer(Real s, const Vec3& g) {
  return {s * g.x * g.x, s * g.y * g.y, s * g.z * g.z, s * g.x * g.y, s * g.x * g.z, s * g.y * g.z};
}
inline Sym3& operator+=(Sym3& a, const Sym3& b) {
  a.xx += b.xx, a.yy += b.yy, a.zz += b.zz, a.xy += b.xy, a.xz += b.xz, a.yz += b.yz;
  return a;
}

// Implicit-Euler coupling block of one spring for step h (Baraff & Witkin,
// SIGGRAPH 1998, with the geometric term clamped as in Choi & Ko, SIGGRAPH 2002):
//   S = h^2 K + h C,  K = k [ n n^T + max(0, 1 - L0/L) (I - n n^T) ],  C = c n n^T
// K and C are the negated force Jacobians (positive semi-definite); the spring
// adds [S -S; -S S] to the system matrix A = M + h C + h^2 K of ends (a, b).
inline Sym3 spring_block(const Vec3& d, Real rest, Real k, Real c, bool tension_only, Real h) {
  const Real len = norm(d);
  if (!(len > kTinyLength) || (tension_only && len < rest)) return {};
  const Real inv_len = Real(1) / len;
  const Vec3 n = inv_len * d;
  const Real geo = h * h * k * std::max(Real(0), Real(1) - rest * inv_len);  // transverse
  const Real ax = h * h * k + h * c - geo;                                     // axial minus transverse
  return {geo + ax * n.x * n.x, geo + ax * n.y * n.y, geo + ax * n.z * n.z,
          ax * n.x * n.y,       ax * n.x * n.z,       ax * n.y * n.z};
}

// Elastic force on end a, energy and implicit block of one spring from a
// precomputed geometry (spring_force_elastic and spring_block in one, for
// the implicit integrator's assembly).
struct SpringForceBlock {
  Vec3 f;
  Real energy;
  Sym3 block;
};
inline SpringForceBlock spring_force_block(const SpringGeometry& g, Real rest, Real k, Real c, bool tension_only, Real h) {
  const Real stretch = g.len - rest;
  if (!(g.len > kTinyLength) || (tension_only && stretch < 0)) return {{}, 0, {}};
  const Vec3 n = g.inv_len * g.d;
  const Real geo = h * h * k * std::max(Real(0), Real(1) - rest * g.inv_len);
  const Real ax = h * h * k + h * c - geo;
  return {(k * stretch) * n, Real(0.5) * k * stretch * stretch,
          {geo + ax * n.x * n.x, geo + ax * n.y * n.y, geo + ax * n.z * n.z, ax * n.x * n.y, ax * n.x * n.z, ax * n.y * n.z}};
}

// Inverse of a symmetric 3x3 block (adjugate / determinant). Returns the
// diagonal inverse when the block is singular or badly conditioned.
inline Sym3 inverse(const Sym3& s) {
  const Real c00 = s.yy * s.zz - s.yz * s.yz;
  const Real c01 = s.xz * s.yz - s.xy * s.zz;
  const Real c02 = s.xy * s.yz - s.xz * s.yy;
  const Real det = s.xx * c00 + s.xy * c01 + s.xz * c02;
  const Real scale = s.xx * s.yy * s.zz;
  if (!(std::abs(det) > 1e-12 * std::abs(scale)) || !std::isfinite(det)) {
    Sym3 d;
    d.xx = s.xx != 0 ? 1 / s.xx : 0;
    d.yy = s.yy != 0 ? 1 / s.yy : 0;
    d.zz = s.zz != 0 ? 1 / s.zz : 0;
    return d;
  }
  const Real inv = 1 / det;
  Sym3 r;
  r.xx = c00 * inv;
  r.xy = c01 * inv;
  r.xz = c02 * inv;
  r.yy = (s.xx * s.zz - s.xz * s.xz) * inv;
  r.yz = (s.xy * s.xz - s.xx * s.yz) * inv;
  r.zz = (s.xx * s.yy - s.xy * s.xy) * inv;
  return r;
}

// Stability limit of symplectic Euler for a damped oscillator x'' = -w^2 x - g x'
// (Jury criterion of v' = (1 - h g) v - h w^2 x, x' = x + h v'):
//   h < (2 / w) (sqrt(1 + z^2) - z),  z = g / (2 w)
// Returns +inf when w == 0 and g == 0.
inline Real symplectic_limit(Real omega, Real gamma) {
  if (!(omega > 0)) return gamma > 0 ? Real(2) / gamma : HUGE_VAL;
  const Real z = gamma / (2 * omega);
  // (2 / omega) (sqrt(1 + z^2) - z) without the cancellation: that form was 0
  // for z above ~1e8 (a heavily damped spring), read as "no limit", and the
  // run took one substep a step and blew up without a word
  return (2 / omega) / (std::hypot(Real(1), z) + z);
}

}  // namespace orthosim::runtime
