// Internal to libmodel/phantom: the analytic geometry of the phantom.
// Not part of the library interface (phantom.h is).
//
// Every layer interface and bone is a Body: a generalised cylinder along z
// whose section in each z plane is star-shaped around a centre, with polar
// radius a short Fourier series in the angle. Body ends are either cut (the
// body continues beyond the stack; closed by a flat cap at the end plane) or
// rounded (a half-ellipsoid of length h). Vessels are canal surfaces: the
// union of balls of radius r(z) centred on a smooth centreline x(z), y(z).
#pragma once

#include "libmodel/phantom/phantom.h"

#include <Eigen/Core>

#include <array>
#include <functional>
#include <vector>

namespace orthosim::phantom_detail {

constexpr int kHarmonics = 3;

// A star-shaped closed curve in a z plane. Polar radius around `centre`:
//   r(theta) = c[0] + sum_{k=1..3} (c[k] cos k theta + s[k] sin k theta)   (m)
struct Ring {
  Eigen::Vector2d centre{0, 0};
  std::array<double, kHarmonics + 1> c{}, s{};

  // r at the angle with cosine ct and sine st.
  double radius(double ct, double st) const {
    const double c2 = ct * ct - st * st, s2 = 2 * ct * st;
    const double c3 = c2 * ct - s2 * st, s3 = s2 * ct + c2 * st;
    return c[0] + c[1] * ct + s[1] * st + c[2] * c2 + s[2] * s2 + c[3] * c3 + s[3] * s3;
  }
  double bound() const;  // an upper bound of r over all angles
};

// A generalised cylinder along z, z in [z_lo, z_hi].
struct Body {
  std::function<Ring(double z)> ring;  // section at z before end rounding
  double z_lo = 0, z_hi = 0;
  double h_lo = 0, h_hi = 0;  // rounded end zone lengths; 0 = cut end

  // Scale e(z) in [0, 1] of the section: 1 in the shaft, sqrt(1-u^2) in the
  // rounded zones, 0 outside [z_lo, z_hi].
  double end_factor(double z) const;
  bool inside(const Eigen::Vector3d& p) const;

  // Surface parameterisation (theta, s), s in [0, s_length()]: s runs along z
  // in the shaft and along the ellipse angle (times h) in rounded zones, so
  // that the surface is smooth in (theta, s) up to the poles.
  double s_length() const;
  void at_s(double s, double* z, double* e) const;
  double s_of_z(double z) const;  // inverse of z(s) on [z_lo, z_hi]
  Eigen::Vector3d point(double theta, double s) const;
};

// A vessel branch: centreline and radius as cubic Hermite interpolants of
// control values at normalised heights t = z / L; positions are relative to
// the limb axis in units of the limb radius R.
struct Branch {
  std::string name;
  int parent = -1;
  std::vector<double> t;               // increasing control heights
  std::vector<Eigen::Vector2d> rel;    // (x, y) / R relative to the axis
  std::vector<double> rad;             // radius / R
  double z0 = 0, z1 = 0;               // z extent (m)
  double r_max = 0, r_min = 0;         // radius bounds (m)
  double slope = 0;                    // bound of |d(x, y)/dz| of the centreline
};

struct Geometry {
  PhantomOptions opt;
  double R = 0;  // limb reference radius (m)
  double L = 0;  // stack length (m)
  Body skin, fat, muscle;
  std::array<Body, 3> bones;    // humerus, radius, ulna
  std::array<Body, 3> marrows;  // inside each bone
  std::vector<Branch> artery;   // brachial, radial, ulnar
  std::vector<Branch> vein;     // one branch

  Eigen::Vector2d axis(double z) const;                          // limb axis (m)
  Eigen::Vector3d centreline(const Branch& b, double z) const;   // (m)
  double vessel_radius(const Branch& b, double z) const;         // (m)
};

Geometry make_geometry(const PhantomOptions& o);

// min over the branch of |p - x(z')| - r(z'): negative inside the tube. Exact
// distance to the canal surface outside it.
double branch_sdf(const Geometry& g, const Branch& b, const Eigen::Vector3d& p);

// Unsigned distance from p to the closed surface of a body (caps included).
double body_distance(const Body& b, const Eigen::Vector3d& p);

// Closed outward triangle mesh of a body; `around` is the vertex spacing along
// the section (m), `along` along z (m). Appends to `s`.
void mesh_body(const Body& b, double around, double along, Surface& s);

// Label at p (precedence vessel > marrow > bone > muscle > fat > skin).
int label_at(const Geometry& g, const Eigen::Vector3d& p);

// Labels of one slice z (ny*nx, x fastest) into out.
void label_slice(const Geometry& g, int z, std::uint8_t* out);

}  // namespace orthosim::phantom_detail
