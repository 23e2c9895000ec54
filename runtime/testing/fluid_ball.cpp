#include "runtime/testing/fluid_ball.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numbers>

namespace orthosim::runtime::testing {

BallSurfaceError ball_surface_error(const Fluid& f, Real radius_spacings, const FluidSurfaceOptions& o, Real packing) {
  const Real dx = packing * f.params.spacing;
  const std::array<Real, 3> c{0.31 * dx, 0.17 * dx, 0.23 * dx};
  FluidState s = make_fluid_state();
  BallSurfaceError e;
  e.particles = fill_ball(f, s, c, radius_spacings * dx, dx);
  FluidBoundaries open = make_box_boundaries({-1, -1, -1}, {1, 1, 1});
  open.faces.fill(Face::open);
  fluid_update_density(f, s, open);
  const auto t0 = std::chrono::steady_clock::now();
  const FluidSurfaceMesh m = extract_fluid_surface(f, s, o);
  e.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  e.triangles = m.n_triangles();
  const Real volume = static_cast<Real>(e.particles) * dx * dx * dx;
  e.radius = std::cbrt(3 * volume / (4 * std::numbers::pi));
  for (std::int64_t v = 0; v < m.n_vertices(); ++v) {
    const Real* p = m.vertices.data() + 3 * v;
    const Real d = std::hypot(p[0] - c[0], p[1] - c[1], p[2] - c[2]) - e.radius;
    e.mean_offset += d;
    e.max_error = std::max(e.max_error, std::abs(d));
  }
  if (m.n_vertices() > 0) e.mean_offset /= static_cast<Real>(m.n_vertices());
  e.volume_ratio = enclosed_volume(m) / volume;
  return e;
}

}  // namespace orthosim::runtime::testing
