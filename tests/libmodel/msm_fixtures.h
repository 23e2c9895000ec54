// Analytic corresponding quad surfaces for the msm tests and benchmark: what
// remesh (issue 4) will write to /quads, built in code. Tubes along z with
// nu points around (periodic) and nv rings along (open ends), vertex (i, j)
// at row j*nu + i, quads counter-clockwise seen from outside.
#pragma once

#include "libmodel/format/model.h"

#include <cmath>
#include <functional>
#include <string>
#include <utility>
#include <vector>

namespace orthosim::test {

// r(theta, z): the section's polar radius; c(z): the section centre (x, y).
inline QuadSurface tube(int nu, int nv, double length, const std::function<double(double, double)>& r,
                        const std::function<Eigen::Vector2d(double)>& c = {}) {
  QuadSurface q;
  q.nu = nu;
  q.nv = nv;
  q.vertices.resize(static_cast<Eigen::Index>(nu) * nv, 3);
  q.uv.resize(static_cast<Eigen::Index>(nu) * nv, 2);
  for (int j = 0; j < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      const double th = 2 * M_PI * i / nu, z = length * j / (nv - 1);
      const Eigen::Vector2d o = c ? c(z) : Eigen::Vector2d(0, 0);
      const double rr = r(th, z);
      q.vertices.row(j * nu + i) << o.x() + rr * std::cos(th), o.y() + rr * std::sin(th), z;
      q.uv.row(j * nu + i) << static_cast<double>(i) / nu, static_cast<double>(j) / (nv - 1);
    }
  q.quads.resize(static_cast<Eigen::Index>(nu) * (nv - 1), 4);
  for (int j = 0; j + 1 < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      const int i1 = (i + 1) % nu;
      q.quads.row(j * nu + i) << j * nu + i, j * nu + i1, (j + 1) * nu + i1, (j + 1) * nu + i;
    }
  return q;
}

inline QuadSurface cylinder(int nu, int nv, double length, double radius) {
  return tube(nu, nv, length, [radius](double, double) { return radius; });
}

// Concentric cylinders skin, fat, muscle, bone (m).
inline std::vector<std::pair<std::string, QuadSurface>> cylinder_stack(int nu, int nv, double length = 0.12,
                                                                       std::vector<double> radii = {0.030, 0.028,
                                                                                                    0.022, 0.010}) {
  const char* names[] = {"skin", "fat", "muscle", "bone"};
  std::vector<std::pair<std::string, QuadSurface>> s;
  for (std::size_t k = 0; k < radii.size(); ++k) s.emplace_back(names[k], cylinder(nu, nv, length, radii[k]));
  return s;
}

// A limb-like stack: elliptic, tapering, lobed sections around a gently
// bent axis; each inner surface a fraction of the outer radius.
inline std::vector<std::pair<std::string, QuadSurface>> limb_stack(int nu, int nv, double length = 0.12) {
  const char* names[] = {"skin", "fat", "muscle", "bone"};
  const double frac[] = {1.0, 0.93, 0.74, 0.33};
  auto centre = [length](double z) {
    const double s = z / length;
    return Eigen::Vector2d(0.004 * std::sin(M_PI * s), 0.002 * s * s);
  };
  std::vector<std::pair<std::string, QuadSurface>> s;
  for (int k = 0; k < 4; ++k) {
    const double f = frac[k];
    s.emplace_back(names[k], tube(nu, nv, length,
                                  [f, length](double th, double z) {
                                    const double taper = 0.030 - 0.008 * z / length;
                                    const double ell = 1.0 / std::sqrt(std::pow(std::cos(th) / 1.0, 2) +
                                                                       std::pow(std::sin(th) / 0.8, 2));
                                    return f * taper * ell * (1 + 0.04 * std::cos(3 * th + 2 * z / length));
                                  },
                                  centre));
  }
  return s;
}

// A tissue table for these stacks (kPa in the file, as orthosim-tissues/1).
inline std::string msm_tissue_table(bool with_fat = true) {
  std::string fat = R"(,
    {"name": "fat", "label": 2, "rgb": [[230, 200, 120]], "density_kg_m3": 950, "layer": "lattice",
     "inside": "skin", "mechanics": {"model": "linear", "k_kpa": 2.3}})";
  return std::string(R"({
  "format": "orthosim-tissues/1",
  "tissues": [
    {"name": "skin", "label": 1, "rgb": [[205, 160, 140]], "density_kg_m3": 1090, "layer": "tetra",
     "mechanics": {"model": "biphasic", "k1_kpa": 0.1, "turning_strain": 0.4, "k2_kpa": 18.8}})") +
         (with_fat ? fat : "") + R"(,
    {"name": "muscle", "label": 3, "rgb": [[150, 50, 50]], "density_kg_m3": 1050, "layer": "lattice",
     "inside": ")" + (with_fat ? std::string("fat") : std::string("skin")) +
         R"(", "mechanics": {"model": "linear", "k_kpa": 3.0}},
    {"name": "bone", "label": 4, "rgb": [[240, 240, 230]], "density_kg_m3": 1920, "layer": "rigid",
     "inside": "muscle"}
  ]
})";
}

}  // namespace orthosim::test
