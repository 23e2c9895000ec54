// A ball of blood on the cubic lattice and how far its surface (the paper's
// colour field, runtime/sph_surface.h) lies from the truth, for tests and
// benchmarks. The truth is the sphere of the space the particles fill, N a^3
// (one lattice cell of spacing a each), about the ball's centre; the centre is off the
// lattice's symmetry planes. (Not N m / rho0: the particle mass makes the rest
// lattice's summed density rho0, and m / rho0 is 0.967 dx^3 for Wendland C2 at
// H = 2 dx.)
#pragma once

#include "runtime/sph.h"
#include "runtime/sph_surface.h"

#include <cstdint>

namespace orthosim::runtime::testing {

struct BallSurfaceError {
  std::int64_t particles = 0, triangles = 0;
  Real radius = 0;        // m, of the sphere of volume N a^3
  Real mean_offset = 0;   // m, mean over the vertices of |x - c| - radius (> 0: outside)
  Real max_error = 0;     // m, largest | |x - c| - radius | over the vertices
  Real volume_ratio = 0;  // enclosed volume / (N a^3)
  double seconds = 0;     // wall time of extract_fluid_surface
};

// A ball of radius radius_spacings x a at rest on the lattice of spacing
// a = packing x the fluid's spacing (packing < 1: compressed by 1 / packing^3),
// its densities updated (no walls), its surface extracted with o. The truth
// is then the sphere of volume N a^3.
BallSurfaceError ball_surface_error(const Fluid& f, Real radius_spacings, const FluidSurfaceOptions& o = {},
                                    Real packing = 1);

}  // namespace orthosim::runtime::testing
