#include "runtime/sph_surface.h"

#include "libmodel/format/types.h"
#include "runtime/vtk.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <unordered_map>

namespace orthosim::runtime {

namespace {

// The particles in cell order with their volumes m / rho.
struct Cloud {
  NeighbourGrid g;
  std::vector<Real> x, y, z, vol;
  Real H = 0, gfac = 0;

  Cloud(const Fluid& f, const FluidState& s, int volume_passes = 0) : H(f.H) {
    const std::int64_t n = s.size();
    build_neighbour_grid(s.x[0].data(), s.x[1].data(), s.x[2].data(), n, f.H, {0, 0, 0}, {0, 0, 0}, {false, false, false}, g);
    x.resize(n), y.resize(n), z.resize(n), vol.resize(n);
    const bool have_rho = static_cast<std::int64_t>(s.rho.size()) == n;
    for (std::int64_t k = 0; k < n; ++k) {
      const std::int32_t i = g.order[k];
      x[k] = s.x[0][i], y[k] = s.x[1][i], z[k] = s.x[2][i];
      const Real rho = have_rho && s.rho[i] > 0 ? s.rho[i] : f.params.rest_density;
      vol[k] = f.mass / rho;
    }
    // Shepard passes (FluidSurfaceOptions::volume_passes): each reads the last
    // pass's volumes only, so the result does not depend on the threads
    std::vector<Real> next(volume_passes > 0 ? n : 0);
    for (int pass = 0; pass < volume_passes; ++pass) {
      tbb::parallel_for(tbb::blocked_range<std::int64_t>(0, n, 512), [&](const auto& r) {
        for (std::int64_t k = r.begin(); k < r.end(); ++k) {
          Real mass_sum = 0, volume_sum = 0;  // sum m W, sum V W
          for_neighbours({x[k], y[k], z[k]}, [&](std::int32_t j, Real len, const Vec3&) {
            const Real w = wendland_w(len, H);
            mass_sum += f.mass * w;
            volume_sum += vol[j] * w;
          });
          next[k] = mass_sum > 0 ? f.mass * volume_sum / mass_sum : vol[k];
        }
      });
      vol.swap(next);
    }
  }

  // fn(j, |p - x_j|, p - x_j) for every particle j within H of p
  template <class Fn>
  void for_neighbours(const Vec3& p, Fn&& fn) const {
    NeighbourRun runs[27];
    const int nr = neighbour_runs(g, g.cell_of(p.x, p.y, p.z), runs);
    for (int r = 0; r < nr; ++r)
      for (std::int32_t j = runs[r].begin; j < runs[r].end; ++j) {
        const Vec3 rv{p.x - x[j], p.y - y[j], p.z - z[j]};
        const Real len = norm(rv);
        if (len < H) fn(j, len, rv);
      }
  }

  // d(p) and grad d(p)
  Real field(const Vec3& p, Vec3* grad) const {
    if (x.empty()) {
      if (grad) *grad = {};
      return 0;
    }
    Real d = 0;
    Vec3 gr;
    for_neighbours(p, [&](std::int32_t j, Real len, const Vec3& rv) {
      d += vol[j] * wendland_w(len, H);
      if (grad) gr -= (vol[j] * wendland_grad_factor(len, H)) * rv;
    });
    if (grad) *grad = gr;
    return d;
  }
};

constexpr int kBrick = 8;  // cells per brick edge


}  // namespace

Real default_surface_threshold(const Fluid& f) { return 0.5 / f.H; }

SurfaceParticles surface_particles(const Fluid& f, const FluidState& s, Real threshold) {
  SurfaceParticles out;
  out.threshold = threshold > 0 ? threshold : default_surface_threshold(f);
  const std::int64_t n = s.size();
  out.colour.assign(n, 0);
  out.gradient.assign(3 * n, 0);
  out.normal.assign(3 * n, 0);
  out.surface.assign(n, 0);
  const Cloud cloud(f, s);
  tbb::parallel_for(tbb::blocked_range<std::int64_t>(0, n, 512), [&](const auto& r) {
    for (std::int64_t i = r.begin(); i < r.end(); ++i) {
      Vec3 g;
      out.colour[i] = cloud.field({s.x[0][i], s.x[1][i], s.x[2][i]}, &g);
      store3(out.gradient.data(), i, g);
      const Real len = norm(g);
      if (len > 0) store3(out.normal.data(), i, (-1 / len) * g);
      out.surface[i] = len > out.threshold ? 1 : 0;
    }
  });
  return out;
}

FluidSurfaceMesh extract_fluid_surface(const Fluid& f, const FluidState& s, const FluidSurfaceOptions& o) {
  if (!(o.cell >= 0.1 && o.cell <= 2)) throw Error("", "fluid surface: cell must be in [0.1, 2] spacings");
  if (!(o.iso > 0 && o.iso < 1)) throw Error("", "fluid surface: iso must be in (0, 1)");
  if (!(o.volume_passes >= 0 && o.volume_passes <= 64)) throw Error("", "fluid surface: volume_passes must be in [0, 64]");
  FluidSurfaceMesh mesh;
  const std::int64_t n = s.size();
  if (n == 0) return mesh;
  const Cloud cloud(f, s, o.volume_passes);
  const Real c = o.cell * f.params.spacing, H = f.H;
  // global node lattice: node (i, j, k) at origin + (i, j, k) c
  Real lo[3] = {HUGE_VAL, HUGE_VAL, HUGE_VAL}, hi[3] = {-HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
  for (std::int64_t i = 0; i < n; ++i)
    for (int a = 0; a < 3; ++a) lo[a] = std::min(lo[a], s.x[a][i]), hi[a] = std::max(hi[a], s.x[a][i]);
  Real origin[3];
  std::int64_t nodes[3];
  for (int a = 0; a < 3; ++a) {
    origin[a] = lo[a] - H - c;
    nodes[a] = static_cast<std::int64_t>(std::ceil((hi[a] + H + c - origin[a]) / c)) + 1;
    if (nodes[a] > (1 << 20)) throw Error("", "fluid surface: the particles span more than 2^20 grid cells; raise cell");
  }
  // bricks within H of a particle (sorted, unique: deterministic)
  auto key = [](std::int64_t bx, std::int64_t by, std::int64_t bz) { return bx | (by << 21) | (bz << 42); };
  std::vector<std::int64_t> bricks;
  for (std::int64_t i = 0; i < n; ++i) {
    std::int64_t b0[3], b1[3];
    for (int a = 0; a < 3; ++a) {
      const Real p = s.x[a][i];
      b0[a] = static_cast<std::int64_t>(std::floor((p - H - origin[a]) / c)) / kBrick;
      b1[a] = static_cast<std::int64_t>(std::ceil((p + H - origin[a]) / c)) / kBrick;
    }
    for (std::int64_t bz = b0[2]; bz <= b1[2]; ++bz)
      for (std::int64_t by = b0[1]; by <= b1[1]; ++by)
        for (std::int64_t bx = b0[0]; bx <= b1[0]; ++bx) bricks.push_back(key(bx, by, bz));
  }
  std::sort(bricks.begin(), bricks.end());
  bricks.erase(std::unique(bricks.begin(), bricks.end()), bricks.end());
  const std::size_t nb = bricks.size();
  mesh.cells = static_cast<std::int64_t>(nb) * kBrick * kBrick * kBrick;
  // field at the (kBrick + 1)^3 nodes of every brick
  constexpr int kn = kBrick + 1;
  std::vector<Real> values(nb * kn * kn * kn);
  auto brick_coords = [](std::int64_t k, std::int64_t* b) {
    const std::int64_t m = (1 << 21) - 1;
    b[0] = k & m, b[1] = (k >> 21) & m, b[2] = (k >> 42) & m;
  };
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, nb, 1), [&](const auto& r) {
    for (std::size_t q = r.begin(); q < r.end(); ++q) {
      std::int64_t b[3];
      brick_coords(bricks[q], b);
      Real* v = &values[q * kn * kn * kn];
      for (int k = 0; k < kn; ++k)
        for (int j = 0; j < kn; ++j)
          for (int i = 0; i < kn; ++i) {
            const Vec3 p{origin[0] + (b[0] * kBrick + i) * c, origin[1] + (b[1] * kBrick + j) * c,
                         origin[2] + (b[2] * kBrick + k) * c};
            v[i + kn * (j + kn * k)] = cloud.field(p, nullptr);
          }
    }
  });
  // marching tetrahedra: the six tetrahedra {0, a, a|b, 7} of a cube
  // (corner bit 1 = +x, 2 = +y, 4 = +z) for the orders (a, b, c) of the axes
  static const int kTets[6][4] = {{0, 1, 3, 7}, {0, 1, 5, 7}, {0, 2, 3, 7}, {0, 2, 6, 7}, {0, 4, 5, 7}, {0, 4, 6, 7}};
  std::unordered_map<std::int64_t, std::int32_t> vertex_of_edge;
  const Real iso = o.iso;
  for (std::size_t q = 0; q < nb; ++q) {
    std::int64_t b[3];
    brick_coords(bricks[q], b);
    const Real* v = &values[q * kn * kn * kn];
    for (int k = 0; k < kBrick; ++k)
      for (int j = 0; j < kBrick; ++j)
        for (int i = 0; i < kBrick; ++i) {
          Real fc[8];
          bool any_in = false, any_out = false;
          for (int corner = 0; corner < 8; ++corner) {
            const int di = corner & 1, dj = (corner >> 1) & 1, dk = (corner >> 2) & 1;
            fc[corner] = v[(i + di) + kn * ((j + dj) + kn * (k + dk))];
            (fc[corner] > iso ? any_in : any_out) = true;
          }
          if (!any_in || !any_out) continue;
          const std::int64_t gi = b[0] * kBrick + i, gj = b[1] * kBrick + j, gk = b[2] * kBrick + k;
          auto corner_pos = [&](int corner) {
            return Vec3{origin[0] + (gi + (corner & 1)) * c, origin[1] + (gj + ((corner >> 1) & 1)) * c,
                        origin[2] + (gk + ((corner >> 2) & 1)) * c};
          };
          // vertex on the edge between corners u and w (u's bits a subset of w's)
          auto edge_vertex = [&](int u, int w) {
            if ((u & w) != u) std::swap(u, w);
            const std::int64_t node = (gi + (u & 1)) + nodes[0] * ((gj + ((u >> 1) & 1)) + nodes[1] * (gk + ((u >> 2) & 1)));
            const std::int64_t k8 = node * 8 + (w & ~u);
            auto [it, fresh] = vertex_of_edge.try_emplace(k8, static_cast<std::int32_t>(mesh.vertices.size() / 3));
            if (fresh) {
              const Real t = std::clamp((iso - fc[u]) / (fc[w] - fc[u]), Real(0), Real(1));
              const Vec3 pu = corner_pos(u), pw = corner_pos(w);
              const Vec3 p = pu + t * (pw - pu);
              mesh.vertices.insert(mesh.vertices.end(), {p.x, p.y, p.z});
            }
            return it->second;
          };
          auto mid = [&](int u, int w) { return Real(0.5) * (corner_pos(u) + corner_pos(w)); };
          for (const auto& tet : kTets) {
            int in[4], out[4], ni = 0, no = 0;
            for (int m = 0; m < 4; ++m) (fc[tet[m]] > iso ? in[ni++] : out[no++]) = tet[m];
            if (ni == 0 || no == 0) continue;
            // the polygon's edges, in cyclic order
            std::pair<int, int> e[4];
            int ne;
            if (ni == 1) {
              e[0] = {in[0], out[0]}, e[1] = {in[0], out[1]}, e[2] = {in[0], out[2]};
              ne = 3;
            } else if (no == 1) {
              e[0] = {in[0], out[0]}, e[1] = {in[1], out[0]}, e[2] = {in[2], out[0]};
              ne = 3;
            } else {
              e[0] = {in[0], out[0]}, e[1] = {in[0], out[1]}, e[2] = {in[1], out[1]}, e[3] = {in[1], out[0]};
              ne = 4;
            }
            // orientation from the edge midpoints (never degenerate): normal from inside to outside
            Vec3 ci, co;
            for (int m = 0; m < ni; ++m) ci += corner_pos(in[m]);
            for (int m = 0; m < no; ++m) co += corner_pos(out[m]);
            const Vec3 dir = (Real(1) / no) * co - (Real(1) / ni) * ci;
            const Vec3 m0 = mid(e[0].first, e[0].second), m1 = mid(e[1].first, e[1].second),
                       m2 = mid(e[2].first, e[2].second);
            const bool flip = dot(cross(m1 - m0, m2 - m0), dir) < 0;
            std::int32_t id[4];
            for (int m = 0; m < ne; ++m) id[m] = edge_vertex(e[m].first, e[m].second);
            auto tri = [&](int a, int b2, int c2) {
              if (flip) std::swap(b2, c2);
              mesh.triangles.insert(mesh.triangles.end(), {id[a], id[b2], id[c2]});
            };
            tri(0, 1, 2);
            if (ne == 4) tri(0, 2, 3);
          }
        }
  }
  // normals, Eq. 6
  const std::int64_t nv = mesh.n_vertices();
  mesh.normals.assign(3 * nv, 0);
  tbb::parallel_for(tbb::blocked_range<std::int64_t>(0, nv, 256), [&](const auto& r) {
    for (std::int64_t i = r.begin(); i < r.end(); ++i) {
      Vec3 g;
      cloud.field(load3(mesh.vertices.data(), i), &g);
      const Real len = norm(g);
      if (len > 0) store3(mesh.normals.data(), i, (-1 / len) * g);
    }
  });
  return mesh;
}

Real enclosed_volume(const FluidSurfaceMesh& m) {
  Real v = 0;
  for (std::int64_t t = 0; t < m.n_triangles(); ++t) {
    const Vec3 a = load3(m.vertices.data(), m.triangles[3 * t]), b = load3(m.vertices.data(), m.triangles[3 * t + 1]),
               c = load3(m.vertices.data(), m.triangles[3 * t + 2]);
    v += (a.x * (b.y * c.z - b.z * c.y) - a.y * (b.x * c.z - b.z * c.x) + a.z * (b.x * c.y - b.y * c.x)) / 6;
  }
  return v;
}

void write_fluid_surface_vtp(const std::string& path, const FluidSurfaceMesh& m, bool binary, Real time) {
  write_vtp(path, m.vertices, m.triangles, {VtpArray{"normal", 3, m.normals}}, binary, time);
}

void write_fluid_particles_vtp(const std::string& path, const FluidState& s, bool binary) {
  const std::size_t n = s.id.size();
  const std::vector<Real> x = fluid_positions(s);
  std::vector<double> vel(3 * n), rho(n), p(n), id(n);
  for (std::size_t i = 0; i < n; ++i) {
    for (int a = 0; a < 3; ++a) vel[3 * i + a] = s.v[a][i];
    rho[i] = i < s.rho.size() ? s.rho[i] : 0;
    p[i] = i < s.p.size() ? s.p[i] : 0;
    id[i] = static_cast<double>(s.id[i]);
  }
  write_vtp(path, x, {}, {VtpArray{"velocity", 3, vel}, VtpArray{"density", 1, rho}, VtpArray{"pressure", 1, p},
                          VtpArray{"id", 1, id}},
            binary, s.time);
}

}  // namespace orthosim::runtime
