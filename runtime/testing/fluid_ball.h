// A ball of blood on the cubic lattice and how far its surface (the paper's
// colour field, runtime/sph_surface.h) lies from the truth, for tests and
// benchmarks. The truth is the sphere of the particles' volume, N dx^3, about
// the ball's centre; the centre is off the lattice's symmetry planes.
#pragma once

#include "runtime/sph.h"
#include "runtime/sph_surface.h"

#include <cstdint>

namespace orthosim::runtime::testing {

struct BallSurfaceError {
  std::int64_t particles = 0, triangles = 0;
  Real radius = 0;        // m, of the sphere of the particles' volume
  Real mean_offset = 0;   // m, mean over the vertices of |x - c| - radius (> 0: outside)
  Real max_error = 0;     // m, largest | |x - c| - radius | over the vertices
  Real volume_ratio = 0;  // enclosed volume / the particles' volume
  double seconds = 0;     // wall time of extract_fluid_surface
};

// A ball of radius radius_spacings x spacing at rest, its densities updated
// (no walls), its surface extracted with o.
BallSurfaceError ball_surface_error(const Fluid& f, Real radius_spacings, const FluidSurfaceOptions& o = {});

}  // namespace orthosim::runtime::testing
