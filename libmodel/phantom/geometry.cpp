// The analytic geometry of the phantom: limb layers, bones, vessels, labels,
// distances and truth meshes. See geometry.h for the model and docs/phantom.md
// for the anatomy.
#include "libmodel/phantom/geometry.h"

#include <Eigen/Dense>

#include <algorithm>
#include <cmath>
#include <limits>

namespace orthosim::phantom_detail {
namespace {

constexpr double kPi = 3.14159265358979323846;

double gauss(double t, double c, double w) {
  const double u = (t - c) / w;
  return std::exp(-u * u);
}

// C2 step from 0 at t <= a to 1 at t >= b.
double step(double a, double b, double t) {
  const double x = std::clamp((t - a) / (b - a), 0.0, 1.0);
  return x * x * x * (x * (6 * x - 15) + 10);
}

// r(theta) = r0 (1 + a1 cos(theta - p1) + a2 cos 2(theta - p2) + a3 cos 3(theta - p3))
Ring section(const Eigen::Vector2d& centre, double r0, double a1, double p1, double a2, double p2, double a3,
             double p3) {
  Ring r;
  r.centre = centre;
  r.c[0] = r0;
  r.c[1] = r0 * a1 * std::cos(p1), r.s[1] = r0 * a1 * std::sin(p1);
  r.c[2] = r0 * a2 * std::cos(2 * p2), r.s[2] = r0 * a2 * std::sin(2 * p2);
  r.c[3] = r0 * a3 * std::cos(3 * p3), r.s[3] = r0 * a3 * std::sin(3 * p3);
  return r;
}

// a - b coefficient-wise (b's centre ignored): the inner boundary of a layer
// of radial thickness b under the boundary a.
Ring minus(Ring a, const Ring& b) {
  for (int k = 0; k <= kHarmonics; ++k) a.c[k] -= b.c[k], a.s[k] -= b.s[k];
  return a;
}

Ring scaled(Ring a, double f) {
  for (int k = 0; k <= kHarmonics; ++k) a.c[k] *= f, a.s[k] *= f;
  return a;
}

// Cubic Hermite interpolation through (t_i, v_i), Catmull-Rom tangents for
// non-uniform knots, one-sided at the ends; clamped outside [t_0, t_n].
template <class V>
V hermite(const std::vector<double>& t, const std::vector<V>& v, double x) {
  const std::size_t n = t.size();
  if (x <= t.front()) return v.front();
  if (x >= t.back()) return v.back();
  std::size_t i = 0;
  while (i + 2 < n && x > t[i + 1]) ++i;
  auto tangent = [&](std::size_t k) -> V {
    if (k == 0) return (v[1] - v[0]) / (t[1] - t[0]);
    if (k == n - 1) return (v[n - 1] - v[n - 2]) / (t[n - 1] - t[n - 2]);
    return (v[k + 1] - v[k - 1]) / (t[k + 1] - t[k - 1]);
  };
  const double dt = t[i + 1] - t[i];
  const double s = (x - t[i]) / dt, s2 = s * s, s3 = s2 * s;
  const double h00 = 2 * s3 - 3 * s2 + 1, h10 = s3 - 2 * s2 + s, h01 = -2 * s3 + 3 * s2, h11 = s3 - s2;
  return V(h00 * v[i] + h10 * dt * tangent(i) + h01 * v[i + 1] + h11 * dt * tangent(i + 1));
}

Eigen::Vector2d axis_at(double R, double L, double z) {
  const double t = L > 0 ? z / L : 0;
  return R * Eigen::Vector2d(0.1 * std::sin(3.0 * t + 0.3) - 0.04, 0.06 * std::cos(2.2 * t + 0.2) - 0.02);
}

}  // namespace

double Ring::bound() const {
  double b = c[0];
  for (int k = 1; k <= kHarmonics; ++k) b += std::abs(c[k]) + std::abs(s[k]);
  return b;
}

// ---- body ---------------------------------------------------------------------

double Body::end_factor(double z) const {
  if (z < z_lo || z > z_hi) return 0;
  double e = 1;
  if (h_lo > 0 && z < z_lo + h_lo) {
    const double u = (z_lo + h_lo - z) / h_lo;
    e = std::sqrt(std::max(0.0, 1 - u * u));
  }
  if (h_hi > 0 && z > z_hi - h_hi) {
    const double u = (z - (z_hi - h_hi)) / h_hi;
    e = std::min(e, std::sqrt(std::max(0.0, 1 - u * u)));
  }
  return e;
}

bool Body::inside(const Eigen::Vector3d& p) const {
  const double e = end_factor(p.z());
  if (!(e > 0)) return false;
  const Ring r = ring(p.z());
  const double dx = p.x() - r.centre.x(), dy = p.y() - r.centre.y();
  const double rr = std::hypot(dx, dy);
  if (rr == 0) return true;
  return rr <= e * r.radius(dx / rr, dy / rr);
}

double Body::s_length() const {
  return h_lo * kPi / 2 + ((z_hi - h_hi) - (z_lo + h_lo)) + h_hi * kPi / 2;
}

void Body::at_s(double s, double* z, double* e) const {
  const double a = h_lo * kPi / 2;
  const double shaft = (z_hi - h_hi) - (z_lo + h_lo);
  if (h_lo > 0 && s < a) {
    const double phi = std::max(s, 0.0) / h_lo;
    *z = z_lo + h_lo * (1 - std::cos(phi));
    *e = std::sin(phi);
  } else if (s <= a + shaft || h_hi <= 0) {
    *z = std::min(z_lo + h_lo + (s - a), z_hi);
    *e = 1;
  } else {
    const double phi = std::min((s - a - shaft) / h_hi, kPi / 2);
    *z = z_hi - h_hi + h_hi * std::sin(phi);
    *e = std::cos(phi);
  }
}

double Body::s_of_z(double z) const {
  z = std::clamp(z, z_lo, z_hi);
  const double a = h_lo * kPi / 2;
  const double shaft = (z_hi - h_hi) - (z_lo + h_lo);
  if (h_lo > 0 && z < z_lo + h_lo) return h_lo * std::acos(std::clamp(1 - (z - z_lo) / h_lo, -1.0, 1.0));
  if (h_hi <= 0 || z <= z_hi - h_hi) return a + (z - z_lo - h_lo);
  return a + shaft + h_hi * std::asin(std::clamp((z - (z_hi - h_hi)) / h_hi, -1.0, 1.0));
}

Eigen::Vector3d Body::point(double theta, double s) const {
  double z = 0, e = 0;
  at_s(s, &z, &e);
  const Ring r = ring(z);
  const double ct = std::cos(theta), st = std::sin(theta);
  const double rho = e * r.radius(ct, st);
  return {r.centre.x() + rho * ct, r.centre.y() + rho * st, z};
}

// ---- geometry -----------------------------------------------------------------

Eigen::Vector2d Geometry::axis(double z) const { return axis_at(R, L, z); }

Eigen::Vector3d Geometry::centreline(const Branch& b, double z) const {
  const Eigen::Vector2d xy = axis(z) + R * hermite(b.t, b.rel, L > 0 ? z / L : 0);
  return {xy.x(), xy.y(), z};
}

double Geometry::vessel_radius(const Branch& b, double z) const {
  return R * hermite(b.t, b.rad, L > 0 ? z / L : 0);
}

namespace {
double branch_slope(const Geometry& g, const Branch& b);
}

Geometry make_geometry(const PhantomOptions& o) {
  Geometry g;
  g.opt = o;
  const double W = std::min(o.nx * o.spacing_m[0], o.ny * o.spacing_m[1]);
  const double R = 0.36 * W;
  const double L = (o.nz - 1) * o.spacing_m[2];
  g.R = R;
  g.L = L;

  // limb outline: taper from the upper arm to the wrist, a slight biceps
  // bulge, a narrowing at the elbow, flattening of the forearm
  auto skin = [R, L](double z) {
    const double t = z / L;
    const double r0 = R * (1 + 0.03 * gauss(t, 0.2, 0.12) - 0.06 * gauss(t, 0.47, 0.07) +
                           0.02 * gauss(t, 0.62, 0.1) - 0.16 * step(0.55, 1.0, t));
    const double a2 = 0.04 + 0.08 * step(0.35, 0.7, t);
    return section(axis_at(R, L, z), r0, 0.02, 2.0 + t, a2, 0.15 * std::sin(2.5 * t), 0.02, 0.3 + 0.7 * t);
  };
  // skin thickness, thicker posteriorly (+y), varying around and along
  auto skin_thickness = [R, L](double z) {
    const double t = z / L;
    const double T = 0.076 * R * (1 + 0.04 * std::sin(5 * t));
    return section({0, 0}, T, 0.18, kPi / 2 + 0.6 * std::sin(5.0 * t), 0.08, 1.0 + 2.2 * t, 0, 0);
  };
  // hypodermis thickness
  auto fat_thickness = [R, L](double z) {
    const double t = z / L;
    const double T = 0.16 * R * (1 + 0.06 * std::cos(4 * t));
    return section({0, 0}, T, 0.2, 1.2 + 1.5 * t, 0, 0, 0.08, 0.5 + t);
  };
  g.skin.ring = skin;
  g.fat.ring = [skin, skin_thickness](double z) { return minus(skin(z), skin_thickness(z)); };
  g.muscle.ring = [skin, skin_thickness, fat_thickness](double z) {
    return minus(minus(skin(z), skin_thickness(z)), fat_thickness(z));
  };
  for (Body* b : {&g.skin, &g.fat, &g.muscle}) b->z_lo = 0, b->z_hi = L;

  // bones: humerus ends (rounded) above the elbow, radius and ulna start
  // (rounded) below it; offsets from the limb axis and radii in units of R
  auto humerus = [R, L](double z) {
    const double t = z / L;
    const Eigen::Vector2d off(0.03 + 0.03 * t, 0.03 - 0.08 * step(0.25, 0.46, t));
    const double r = 0.24 * R * (1 + 0.08 * step(0.3, 0.46, t));
    return section(axis_at(R, L, z) + R * off, r, 0, 0, 0.2 * step(0.25, 0.45, t), 0, 0.05, 0.4);
  };
  auto radius = [R, L](double z) {
    const double t = z / L;
    const Eigen::Vector2d off(0.22 + 0.03 * step(0.5, 1.0, t), -0.01 + 0.02 * t);
    const double r = R * (0.12 + 0.03 * step(0.6, 1.0, t));
    return section(axis_at(R, L, z) + R * off, r, 0, 0, 0.08, 0.1, 0.03, 1.0);
  };
  auto ulna = [R, L](double z) {
    const double t = z / L;
    const Eigen::Vector2d off(-0.19 - 0.02 * t, 0.14 - 0.04 * t);
    const double r = R * (0.14 - 0.04 * step(0.55, 1.0, t));
    return section(axis_at(R, L, z) + R * off, r, 0, 0, 0.1, kPi / 2, 0.04, 0.2);
  };
  const double tip_h = 0.46, rad_lo = 0.51, uln_lo = 0.49;
  auto cap = [L](double r) { return std::min(0.8 * r, 0.1 * L); };
  g.bones[0] = Body{humerus, 0, tip_h * L, 0, cap(0.26 * R)};
  g.bones[1] = Body{radius, rad_lo * L, L, cap(0.12 * R), 0};
  g.bones[2] = Body{ulna, uln_lo * L, L, cap(0.14 * R), 0};
  // marrow: the bone section scaled by k, ends shortened by d in rounded zones
  const std::array<double, 3> k{0.58, 0.5, 0.5};
  for (int j = 0; j < 3; ++j) {
    const Body& b = g.bones[j];
    Body m = b;
    auto ring = b.ring;
    const double f = k[j];
    m.ring = [ring, f](double z) { return scaled(ring(z), f); };
    if (b.h_lo > 0) {
      const double d = 0.3 * b.h_lo;
      m.z_lo += d, m.h_lo -= d;
    }
    if (b.h_hi > 0) {
      const double d = 0.3 * b.h_hi;
      m.z_hi -= d, m.h_hi -= d;
    }
    g.marrows[j] = m;
  }

  // arteries: brachial (medial, then into the cubital fossa), bifurcating just
  // below the elbow into the radial (lateral, anterior to the radius) and the
  // ulnar (medial, anterior to the ulna) arteries. Children start at the
  // parent's end point with the parent's radius.
  const double tb = 0.485;
  Branch brachial{"brachial", -1, {0, 0.15, 0.32, tb},
                  {{-0.50, -0.06}, {-0.48, -0.15}, {-0.36, -0.28}, {-0.08, -0.36}},
                  {0.085, 0.083, 0.08, 0.078}};
  Branch radial{"radial", 0, {tb, 0.56, 0.75, 1.0},
                {{-0.08, -0.36}, {0.08, -0.34}, {0.22, -0.27}, {0.24, -0.27}},
                {0.078, 0.062, 0.058, 0.055}};
  Branch ulnar{"ulnar", 0, {tb, 0.56, 0.75, 1.0},
               {{-0.08, -0.36}, {-0.18, -0.26}, {-0.24, -0.15}, {-0.25, -0.12}},
               {0.078, 0.066, 0.062, 0.06}};
  // vein: one branch, posteromedial in the arm (basilic vein), then along the
  // medial side of the forearm
  Branch vein{"basilic", -1, {0, 0.25, 0.45, 0.7, 1.0},
              {{-0.52, 0.22}, {-0.5, 0.18}, {-0.45, 0.02}, {-0.45, -0.09}, {-0.43, -0.07}},
              {0.09, 0.088, 0.085, 0.08, 0.075}};
  g.artery = {brachial, radial, ulnar};
  g.vein = {vein};
  for (auto* tree : {&g.artery, &g.vein})
    for (Branch& b : *tree) {
      b.z0 = b.t.front() * L;
      b.z1 = b.t.back() * L;
      b.r_max = R * *std::max_element(b.rad.begin(), b.rad.end());
      b.r_min = R * *std::min_element(b.rad.begin(), b.rad.end());
      b.slope = branch_slope(g, b);
    }
  return g;
}

// ---- vessels --------------------------------------------------------------------

double branch_sdf(const Geometry& g, const Branch& b, const Eigen::Vector3d& p) {
  auto f = [&](double z) { return (p - g.centreline(b, z)).norm() - g.vessel_radius(b, z); };
  const double zc = std::clamp(p.z(), b.z0, b.z1);
  const double d0 = f(zc);
  // |p - x(z')| >= |p.z - z'|, so only z' within d0 + r_max of p.z can do better
  const double w = d0 + b.r_max;
  const double za = std::max(b.z0, p.z() - w), zb = std::min(b.z1, p.z() + w);
  if (!(zb > za)) return d0;
  const int n = std::clamp(static_cast<int>(std::ceil((zb - za) / (0.25 * b.r_min))), 4, 4000);
  const double h = (zb - za) / n;
  double best = d0, best_z = zc;
  for (int i = 0; i <= n; ++i) {
    const double z = za + i * h;
    const double v = f(z);
    if (v < best) best = v, best_z = z;
  }
  // golden-section refinement inside the bracketing samples
  double lo = std::max(za, best_z - h), hi = std::min(zb, best_z + h);
  const double gr = 0.5 * (std::sqrt(5.0) - 1);
  double x1 = hi - gr * (hi - lo), x2 = lo + gr * (hi - lo);
  double f1 = f(x1), f2 = f(x2);
  for (int it = 0; it < 60 && hi - lo > 1e-10; ++it) {
    if (f1 < f2) {
      hi = x2, x2 = x1, f2 = f1;
      x1 = hi - gr * (hi - lo), f1 = f(x1);
    } else {
      lo = x1, x1 = x2, f1 = f2;
      x2 = lo + gr * (hi - lo), f2 = f(x2);
    }
  }
  return std::min({best, f1, f2});
}

namespace {

// max |d(xy)/dz| of a branch centreline, estimated by dense sampling, padded
double branch_slope(const Geometry& g, const Branch& b) {
  double m = 0;
  const int n = 200;
  const double h = (b.z1 - b.z0) / n;
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d a = g.centreline(b, b.z0 + i * h), c = g.centreline(b, b.z0 + (i + 1) * h);
    m = std::max(m, (c - a).head<2>().norm() / h);
  }
  return 1.25 * m + 0.05;
}

// Everything label_at needs that depends on z only.
struct SliceCtx {
  const Geometry* g = nullptr;
  double z = 0;
  Ring skin, fat, muscle;
  std::array<Ring, 3> bone, marrow;
  std::array<double, 3> bone_e{}, marrow_e{};
  std::array<double, 3> bone_bound2{};  // squared bounding radius of each bone
  double skin_bound2 = 0;
  struct Tube {
    const Branch* b;
    std::uint8_t label;
    double slope;       // bound of |d(xy)/dz|
    Eigen::Vector2d xy; // centreline at this z (clamped)
    bool active;
  };
  std::vector<Tube> tubes;
};

SliceCtx make_ctx(const Geometry& g, double z) {
  SliceCtx c;
  c.g = &g;
  c.z = z;
  c.skin = g.skin.ring(z);
  c.fat = g.fat.ring(z);
  c.muscle = g.muscle.ring(z);
  c.skin_bound2 = std::pow(c.skin.bound() * (1 + 1e-9), 2);
  for (int j = 0; j < 3; ++j) {
    c.bone_e[j] = g.bones[j].end_factor(z);
    if (c.bone_e[j] > 0) c.bone[j] = g.bones[j].ring(z);
    c.bone_bound2[j] = c.bone_e[j] > 0 ? std::pow(c.bone_e[j] * c.bone[j].bound() * (1 + 1e-9), 2) : 0;
    c.marrow_e[j] = g.marrows[j].end_factor(z);
    if (c.marrow_e[j] > 0) c.marrow[j] = g.marrows[j].ring(z);
  }
  for (const auto* tree : {&g.artery, &g.vein}) {
    const std::uint8_t label = tree == &g.artery ? kPhantomArtery : kPhantomVein;
    for (const Branch& b : *tree) {
      SliceCtx::Tube t{&b, label, b.slope, {0, 0}, false};
      t.active = z >= b.z0 - b.r_max && z <= b.z1 + b.r_max;
      if (t.active) t.xy = g.centreline(b, std::clamp(z, b.z0, b.z1)).head<2>();
      c.tubes.push_back(t);
    }
  }
  return c;
}

bool in_ring(const Ring& r, double e, double x, double y) {
  const double dx = x - r.centre.x(), dy = y - r.centre.y();
  const double rr = std::sqrt(dx * dx + dy * dy);
  if (rr == 0) return e > 0;
  return rr <= e * r.radius(dx / rr, dy / rr);
}

int classify(const SliceCtx& c, double x, double y) {
  for (const auto& t : c.tubes) {
    if (!t.active) continue;
    const Branch& b = *t.b;
    // quick reject: with a the in-plane distance to the centreline at the
    // clamped z and d = |z' - z_clamped|, |p - x(z')| >= sqrt((a - slope d)^2 + d^2)
    // >= a / sqrt(1 + slope^2)
    const double ax = x - t.xy.x(), ay = y - t.xy.y();
    if (ax * ax + ay * ay > b.r_max * b.r_max * (1 + t.slope * t.slope)) continue;
    if (branch_sdf(*c.g, b, Eigen::Vector3d(x, y, c.z)) < 0) return t.label;
  }
  // bones and their marrow share a centre; reject by the bounding circle first
  int bone = 0;
  for (int j = 0; j < 3; ++j) {
    if (!(c.bone_e[j] > 0)) continue;
    const Ring& rb = c.bone[j];
    const double dx = x - rb.centre.x(), dy = y - rb.centre.y();
    const double d2 = dx * dx + dy * dy;
    if (d2 > c.bone_bound2[j]) continue;
    const double rr = std::sqrt(d2);
    const double ct = rr > 0 ? dx / rr : 1, st = rr > 0 ? dy / rr : 0;
    if (c.marrow_e[j] > 0 && rr <= c.marrow_e[j] * c.marrow[j].radius(ct, st)) return kPhantomMarrow;
    if (rr <= c.bone_e[j] * rb.radius(ct, st)) bone = kPhantomBone;
  }
  if (bone) return bone;
  // the limb layers share the limb axis
  const double dx = x - c.skin.centre.x(), dy = y - c.skin.centre.y();
  const double d2 = dx * dx + dy * dy;
  if (d2 > c.skin_bound2) return kPhantomBackground;
  const double rr = std::sqrt(d2);
  const double ct = rr > 0 ? dx / rr : 1, st = rr > 0 ? dy / rr : 0;
  if (rr <= c.muscle.radius(ct, st)) return kPhantomMuscle;
  if (rr <= c.fat.radius(ct, st)) return kPhantomFat;
  if (rr <= c.skin.radius(ct, st)) return kPhantomSkin;
  return kPhantomBackground;
}

}  // namespace

int label_at(const Geometry& g, const Eigen::Vector3d& p) {
  if (p.z() < 0 || p.z() > g.L) return kPhantomBackground;
  const SliceCtx c = make_ctx(g, p.z());
  return classify(c, p.x(), p.y());
}

void label_slice(const Geometry& g, int z, std::uint8_t* out) {
  const PhantomOptions& o = g.opt;
  const std::array<double, 3> origin = phantom_origin(o);
  const double zz = origin[2] + z * o.spacing_m[2];
  const SliceCtx c = make_ctx(g, zz);
  for (int y = 0; y < o.ny; ++y) {
    const double py = origin[1] + y * o.spacing_m[1];
    for (int x = 0; x < o.nx; ++x) {
      const double px = origin[0] + x * o.spacing_m[0];
      out[static_cast<std::size_t>(y) * o.nx + x] = static_cast<std::uint8_t>(classify(c, px, py));
    }
  }
}

// ---- distances to bodies -----------------------------------------------------------

double body_distance(const Body& b, const Eigen::Vector3d& p) {
  double best = std::numeric_limits<double>::infinity();
  // flat caps at cut ends
  for (int end = 0; end < 2; ++end) {
    const bool cut = end == 0 ? b.h_lo <= 0 : b.h_hi <= 0;
    if (!cut) continue;
    const double zc = end == 0 ? b.z_lo : b.z_hi;
    const Ring r = b.ring(zc);
    if (in_ring(r, 1, p.x(), p.y())) best = std::min(best, std::abs(p.z() - zc));
  }
  const double S = b.s_length();
  auto fval = [&](double th, double s) { return (b.point(th, s) - p).squaredNorm(); };
  // an upper bound: the surface point in the direction of p at its (clamped) z
  const double zc = std::clamp(p.z(), b.z_lo, b.z_hi);
  const Eigen::Vector2d cen = b.ring(zc).centre;
  const double th_p = std::atan2(p.y() - cen.y(), p.x() - cen.x());
  const double s_p = b.s_of_z(zc);
  best = std::min(best, std::sqrt(fval(th_p, s_p)));
  // lateral points closer than `best` have |z - p.z| < best
  const double za = std::max(b.z_lo, p.z() - best), zb = std::min(b.z_hi, p.z() + best);
  if (zb < za) return best;
  const double sa = b.s_of_z(za), sb = b.s_of_z(zb);
  const int ns = std::clamp(static_cast<int>(std::ceil((sb - sa) / std::max(best / 3, 1e-9))), 1, 64);
  const int nt = 96;
  struct Cand {
    double f, th, s;
  };
  std::vector<Cand> cands;
  cands.push_back({fval(th_p, s_p), th_p, s_p});
  for (int i = 0; i <= ns; ++i) {
    const double s = sa + (sb - sa) * i / ns;
    for (int k = 0; k < nt; ++k) {
      const double th = 2 * kPi * k / nt;
      cands.push_back({fval(th, s), th, s});
    }
  }
  std::partial_sort(cands.begin(), cands.begin() + 3, cands.end(),
                    [](const Cand& x, const Cand& y) { return x.f < y.f; });
  // Levenberg-Marquardt on |S(theta, s) - p|^2 from the three best samples
  const double scale = std::max(b.ring(zc).c[0], 1e-6);
  for (int c = 0; c < 3; ++c) {
    double th = cands[c].th, s = cands[c].s, f = cands[c].f;
    double lambda = 1e-3;
    for (int it = 0; it < 100; ++it) {
      const Eigen::Vector3d r = b.point(th, s) - p;
      const double ht = 1e-6;
      const double hs = 1e-6 * scale;
      const Eigen::Vector3d jt = (b.point(th + ht, s) - b.point(th - ht, s)) / (2 * ht);
      const double s1 = std::min(s + hs, S), s0 = std::max(s - hs, 0.0);
      const Eigen::Vector3d js = (b.point(th, s1) - b.point(th, s0)) / (s1 - s0);
      Eigen::Matrix2d A;
      A << jt.dot(jt), jt.dot(js), jt.dot(js), js.dot(js);
      const Eigen::Vector2d grad(jt.dot(r), js.dot(r));
      bool accepted = false;
      Eigen::Vector2d d(0, 0);
      while (lambda < 1e12) {
        Eigen::Matrix2d M = A;
        M(0, 0) += lambda * A(0, 0) + 1e-30;
        M(1, 1) += lambda * A(1, 1) + 1e-30;
        d = -M.ldlt().solve(grad);
        const double th2 = th + d(0), s2 = std::clamp(s + d(1), 0.0, S);
        const double f2 = fval(th2, s2);
        if (f2 < f) {
          d(1) = s2 - s;
          th = th2, s = s2, f = f2;
          lambda = std::max(lambda / 4, 1e-12);
          accepted = true;
          break;
        }
        lambda *= 8;
      }
      if (!accepted || std::abs(d(0)) * scale + std::abs(d(1)) < 1e-14) break;
    }
    best = std::min(best, std::sqrt(f));
  }
  return best;
}

// ---- meshes ----------------------------------------------------------------------

void mesh_body(const Body& b, double around, double along, Surface& out) {
  // ring resolution from the largest section
  double rmax = 0;
  for (int i = 0; i <= 16; ++i) rmax = std::max(rmax, b.ring(b.z_lo + (b.z_hi - b.z_lo) * i / 16).bound());
  int nt = static_cast<int>(std::ceil(2 * kPi * rmax / around));
  nt = std::max(24, (nt + 3) / 4 * 4);
  // s values of the rings
  const double a = b.h_lo * kPi / 2;
  const double shaft = (b.z_hi - b.h_hi) - (b.z_lo + b.h_lo);
  const double step = std::min(around, along);
  std::vector<double> ss;
  if (b.h_lo > 0) {
    const int n = std::max(4, static_cast<int>(std::ceil(kPi / 2 * std::max(b.h_lo, rmax) / step)));
    for (int k = 1; k < n; ++k) ss.push_back(a * k / n);
  }
  const int nsh = std::max(1, static_cast<int>(std::ceil(shaft / along)));
  for (int k = 0; k <= nsh; ++k) ss.push_back(a + shaft * k / nsh);
  if (b.h_hi > 0) {
    const int n = std::max(4, static_cast<int>(std::ceil(kPi / 2 * std::max(b.h_hi, rmax) / step)));
    for (int k = 1; k < n; ++k) ss.push_back(a + shaft + b.h_hi * kPi / 2 * k / n);
  }
  const int nr = static_cast<int>(ss.size());
  const int base = static_cast<int>(out.vertices.rows());
  const int n_ring_v = nr * nt;
  const int n_v = n_ring_v + 2;  // + bottom and top (pole or cap centre)
  const int n_f = 2 * nt * (nr - 1) + 2 * nt;
  MatX3d V(n_v, 3);
  MatX3i F(n_f, 3);
  for (int j = 0; j < nr; ++j)
    for (int i = 0; i < nt; ++i) V.row(j * nt + i) = b.point(2 * kPi * i / nt, ss[j]).transpose();
  const int bottom = n_ring_v, top = n_ring_v + 1;
  {
    double z = 0, e = 0;
    b.at_s(0, &z, &e);
    const Eigen::Vector2d c = b.ring(z).centre;
    V.row(bottom) << c.x(), c.y(), z;
    b.at_s(b.s_length(), &z, &e);
    const Eigen::Vector2d c2 = b.ring(z).centre;
    V.row(top) << c2.x(), c2.y(), z;
  }
  int f = 0;
  auto vid = [&](int j, int i) { return base + j * nt + (i % nt); };
  for (int j = 0; j + 1 < nr; ++j)
    for (int i = 0; i < nt; ++i) {
      F.row(f++) << vid(j, i), vid(j, i + 1), vid(j + 1, i + 1);
      F.row(f++) << vid(j, i), vid(j + 1, i + 1), vid(j + 1, i);
    }
  for (int i = 0; i < nt; ++i) F.row(f++) << base + bottom, vid(0, i + 1), vid(0, i);
  for (int i = 0; i < nt; ++i) F.row(f++) << vid(nr - 1, i), vid(nr - 1, i + 1), base + top;
  MatX3d V2(out.vertices.rows() + n_v, 3);
  V2 << out.vertices, V;
  MatX3i F2(out.faces.rows() + n_f, 3);
  F2 << out.faces, F;
  out.vertices = std::move(V2);
  out.faces = std::move(F2);
}

}  // namespace orthosim::phantom_detail
