// The blood surface (paper §4.2, Eq. 4-6): a colour field over the particles,
// its gradient, the surface particles and normals, and a triangle mesh of the
// field's level set by marching tetrahedra on a sparse grid.
//
//   colour field   d(x) = sum_j m_j / rho_j W(x - x_j)     (Eq. 2 with Q = 1; ~1 inside, 0 outside)
//   gradient       g = grad d                               (Eq. 4)
//   surface        |g(x_i)| > threshold                     (Eq. 5)
//   normal         n = -g / |g|                             (Eq. 6, pointing out of the fluid)
//
// Periodic images are not taken into account (the surface of a periodic
// slab is open at its faces). Nothing here runs inside fluid_step: call it
// per rendered frame.
#pragma once

#include "runtime/sph.h"

#include <cstdint>
#include <string>
#include <vector>

namespace orthosim::runtime {

struct SurfaceParticles {
  std::vector<Real> colour;           // (n) d at each particle (its own term included)
  std::vector<Real> gradient;         // (n x 3) 1/m, g
  std::vector<Real> normal;           // (n x 3) unit, -g / |g|; 0 where g = 0
  std::vector<std::uint8_t> surface;  // (n) 1 where |g| > threshold
  Real threshold = 0;                 // 1/m, the threshold used
};

// Default surface threshold (1/m): 0.5 / H. Inside a full neighbourhood |g|
// is 0; on a rest lattice the outermost layer of a block has |g| H in
// [0.95, 1.56] (faces to corners) and the layer below at most 0.24
// (support ratio 2).
Real default_surface_threshold(const Fluid& f);

// Eq. 4-6 at every particle, in the state's particle order. threshold <= 0:
// default_surface_threshold.
SurfaceParticles surface_particles(const Fluid& f, const FluidState& s, Real threshold = 0);

struct FluidSurfaceOptions {
  // grid cell size / particle spacing, [0.1, 2]: at 0.1, 40 cells span a
  // kernel's support (4 spacings), and the colour field, a sum of kernels, has
  // no detail finer; 0.001 asked for 10^8 grid bricks per particle and ran the
  // machine out of memory (the run failed after a minute, "out of memory")
  Real cell = 0.5;
  Real iso = 0.5;   // level of the colour field taken as the surface, (0, 1)
  // The particle volumes V_j of d = sum V_j W. 0: the paper's m / rho_j (Eq. 4).
  // k > 0: k passes of the fixed point rho_j <- sum_k m W_jk / sum_k V_k W_jk,
  // V_j = m / rho_j (a Shepard-normalised density: rho at a full
  // neighbourhood, uniform compression kept, not short at the free surface,
  // where m / rho_j overstates the volume and puts the surface about 0.1
  // spacing outside; docs/sph.md). [0, 64].
  int volume_passes = 0;
};

// A closed, consistently oriented triangle mesh (every edge shared by two
// triangles in opposite directions) unless cut by periodic faces.
struct FluidSurfaceMesh {
  std::vector<Real> vertices;           // (n_vertices x 3) m
  std::vector<Real> normals;            // (n_vertices x 3) unit, -grad d / |grad d| (Eq. 6)
  std::vector<std::int32_t> triangles;  // (n_triangles x 3), counter-clockwise seen from outside
  std::int64_t cells = 0;               // grid cells visited (sparse: only 8^3 bricks near particles)
  std::int64_t n_vertices() const { return static_cast<std::int64_t>(vertices.size() / 3); }
  std::int64_t n_triangles() const { return static_cast<std::int64_t>(triangles.size() / 3); }
};

// The level set d = iso by marching tetrahedra (6 per cube, split along the
// main diagonal so neighbouring cubes agree on their faces) on the nodes of
// 8^3-cell bricks that lie within H of a particle; vertices are shared along
// grid edges. Deterministic. Throws Error on invalid options.
FluidSurfaceMesh extract_fluid_surface(const Fluid& f, const FluidState& s, const FluidSurfaceOptions& o = {});

// Enclosed volume of a closed mesh (m^3, divergence theorem).
Real enclosed_volume(const FluidSurfaceMesh& m);

// .vtp output (runtime/vtk.h write_vtp): the surface with point data
// "normal"; the particles as vertices with "velocity", "density", "pressure", "id".
void write_fluid_surface_vtp(const std::string& path, const FluidSurfaceMesh& m, bool binary = true, Real time = 0);
void write_fluid_particles_vtp(const std::string& path, const FluidState& s, bool binary = true);

}  // namespace orthosim::runtime
