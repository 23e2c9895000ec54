// Precision and tiny vector helpers shared by the runtime.
//
// The runtime has one floating-point alias, `Real`. Hot loops work on flat
// arrays of Real where a 3-vector of node i lives at [3i, 3i+1, 3i+2]; the
// helpers below load and store such triples without any allocation.
#pragma once

#include <cmath>
#include <cstdint>

namespace orthosim::runtime {

using Real = double;  // the runtime's precision: change here and nowhere else

struct Vec3 {
  Real x = 0, y = 0, z = 0;
};

inline Vec3 load3(const Real* a, std::int64_t i) { return {a[3 * i], a[3 * i + 1], a[3 * i + 2]}; }
inline void store3(Real* a, std::int64_t i, const Vec3& v) {
  a[3 * i] = v.x;
  a[3 * i + 1] = v.y;
  a[3 * i + 2] = v.z;
}
inline Vec3 operator+(const Vec3& a, const Vec3& b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline Vec3 operator-(const Vec3& a, const Vec3& b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 operator-(const Vec3& a) { return {-a.x, -a.y, -a.z}; }
inline Vec3 operator*(Real s, const Vec3& a) { return {s * a.x, s * a.y, s * a.z}; }
inline Vec3& operator+=(Vec3& a, const Vec3& b) {
  a.x += b.x;
  a.y += b.y;
  a.z += b.z;
  return a;
}
inline Vec3& operator-=(Vec3& a, const Vec3& b) {
  a.x -= b.x;
  a.y -= b.y;
  a.z -= b.z;
  return a;
}
inline Real dot(const Vec3& a, const Vec3& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline Real norm(const Vec3& a) { return std::sqrt(dot(a, a)); }
inline Vec3 cross(const Vec3& a, const Vec3& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

// A rotation, row-major 3 x 3.
struct Rot3 {
  Real m[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  Vec3 operator()(const Vec3& a) const {
    return {m[0] * a.x + m[1] * a.y + m[2] * a.z, m[3] * a.x + m[4] * a.y + m[5] * a.z, m[6] * a.x + m[7] * a.y + m[8] * a.z};
  }
  Vec3 inverse(const Vec3& a) const {  // the transpose
    return {m[0] * a.x + m[3] * a.y + m[6] * a.z, m[1] * a.x + m[4] * a.y + m[7] * a.z, m[2] * a.x + m[5] * a.y + m[8] * a.z};
  }
};
}  // namespace orthosim::runtime
