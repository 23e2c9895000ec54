#include "runtime/sph.h"

#include "libmodel/format/types.h"

#include <Eigen/Dense>

#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#define ORTHOSIM_SPH_AVX2 1
#endif

#include <algorithm>
#include <chrono>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <iterator>
#include <numeric>
#include <sstream>
#include <tuple>

#include <sys/mman.h>

namespace orthosim::runtime {

namespace {

// ---- small helpers ------------------------------------------------------------

constexpr Real kPi = 3.14159265358979323846;

template <class T>
std::string str(T v) {
  std::ostringstream o;
  o << v;
  return o.str();
}

bool finite3(const std::array<Real, 3>& a) { return std::isfinite(a[0]) && std::isfinite(a[1]) && std::isfinite(a[2]); }
Vec3 vec(const std::array<Real, 3>& a) { return {a[0], a[1], a[2]}; }

// Wall sums for a particle at distance d from a plane wall: the lattice
// sites the wall takes away from a rest lattice of spacing dx around the
// particle (lateral (i, j) dx, normal distances d + dx/2 + k dx beyond the
// particle, k >= 0), each of volume V. Summed over the discrete mirror
// lattice rather than integrated, so that a rest lattice beside a wall has
// rho = rho0 exactly and is in balance under a uniform pressure. Computed
// with dx = 1 and stored for q = d / H (see WallTables).
WallTables make_wall_tables(int n, Real ratio, Real volume, Real grad_scale, Real visc_scale) {
  WallTables t;
  t.n = n;
  t.f0.assign(n + 1, 0);
  t.g0.assign(n + 1, 0);
  t.g1.assign(n + 1, 0);
  t.vm.assign(n + 1, 0);
  t.av.assign(n + 1, 0);
  const Real H = ratio;
  const Real eta2 = 0.01 * (H / 2) * (H / 2);
  const int m = static_cast<int>(std::ceil(H)) + 1;
  for (int q = 0; q < n; ++q) {  // entry n (d = H) stays 0
    const Real d = H * q / n;
    Real f0 = 0, g0 = 0, g1 = 0, vm = 0, av = 0;
    for (int k = 0;; ++k) {
      const Real z = d + 0.5 + k;
      if (!(z < H)) break;
      // Morris et al. cap the ghost velocity factor at 1.5; at H = 2 dx that
      // leaves a slip of ~0.18 dx (3.6 % of u_max in the Poiseuille test), 2
      // extrapolates the first mirrored layer exactly and keeps the explicit
      // wall term at 0.0625 |vm| < 2 under the viscous substep limit
      const Real beta = d > 0 ? std::min(Real(2), 1 + (z - d) / d) : Real(2);
      for (int j = -m; j <= m; ++j)
        for (int i = -m; i <= m; ++i) {
          const Real r2 = z * z + i * i + j * j, r = std::sqrt(r2);
          if (!(r < H)) continue;
          const Real g = wendland_grad_factor(r, H);  // -grad W = g r_vec
          f0 += volume * wendland_w(r, H);
          g0 += volume * g * z;
          g1 += volume * g * z * z;
          vm -= volume * beta * g * r2 / (r2 + eta2);
          av += volume * g * z * z / (r2 + eta2);
        }
    }
    t.f0[q] = f0;
    t.g0[q] = grad_scale * g0 * H;          // physical g0 = g0_unit / dx = table / H
    t.g1[q] = grad_scale * g1;
    t.vm[q] = visc_scale * vm * H * H;      // physical vm = vm_unit / dx^2 = table / H^2
    t.av[q] = grad_scale * av * H * H;
  }
  return t;
}

// ---- SIMD: 4 lanes of Real through GCC vector extensions ----------------------
// The hot loops are compiled twice (x86-64-v3 = AVX2 + FMA, and the
// baseline) and picked at load time; the lane arithmetic and the order of
// every sum are fixed, so results do not depend on the thread count.

using V = Real __attribute__((vector_size(4 * sizeof(Real))));
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define ORTHOSIM_SPH_CLONES __attribute__((target_clones("arch=x86-64-v3", "default")))
#else
#define ORTHOSIM_SPH_CLONES
#endif
// Every helper and lambda that takes or returns a vector is inlined into its
// clone, at every optimisation level: out of line it would be compiled for
// the baseline target and read a 32-byte vector argument where the
// x86-64-v3 caller did not put it (an ABI mismatch, wrong values at -O0).
#define ORTHOSIM_SPH_INLINE inline __attribute__((always_inline))
#define ORTHOSIM_SPH_LAMBDA __attribute__((always_inline))

// lane-wise sqrt of a vector of 4 doubles or 8 floats
template <class W>
ORTHOSIM_SPH_INLINE W vsqrt(W x) {
  W r;
  for (int k = 0; k < static_cast<int>(sizeof(W) / sizeof(x[0])); ++k) r[k] = std::sqrt(x[k]);
  return r;
}
ORTHOSIM_SPH_INLINE Real hsum(V v) { return (v[0] + v[1]) + (v[2] + v[3]); }

// periodic minimum image of a lane of differences (4 doubles or 8 floats)
template <class W, class S>
ORTHOSIM_SPH_INLINE W minimum_image(W d, S period) {
  if (period <= 0) return d;
  W r;
  for (int k = 0; k < static_cast<int>(sizeof(W) / sizeof(d[0])); ++k) r[k] = d[k] - period * std::nearbyint(d[k] / period);
  return r;
}

// ---- walls ----------------------------------------------------------------------

// One wall near a particle: distance d >= 0, unit normal n pointing into the
// fluid, the wall's velocity u at the contact, and for a moving surface the
// triangle and barycentric weights of the contact (for the reaction).
struct Contact {
  Real d = 0;
  Vec3 n, u;
  const WallParams* wall = nullptr;
  int surface = -1;  // index into FluidState::surfaces, -1 for static walls
  std::int32_t tri = -1;
  Real w0 = 0, w1 = 0, w2 = 0;
  Vec3 c;            // contact point
  Vec3 face;         // face normal (meshes, surfaces)
  bool behind = false;
};

struct ClosestPoint {
  Vec3 p;
  Real w0, w1, w2;
};

// Closest point of a triangle to p with its barycentric weights (Ericson,
// Real-Time Collision Detection, 2005, §5.1.5). Degenerate triangles never
// reach it (the grids leave them out).
ClosestPoint closest_on_triangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c) {
  const Vec3 ab = b - a, ac = c - a, ap = p - a;
  const Real d1 = dot(ab, ap), d2 = dot(ac, ap);
  if (d1 <= 0 && d2 <= 0) return {a, 1, 0, 0};
  const Vec3 bp = p - b;
  const Real d3 = dot(ab, bp), d4 = dot(ac, bp);
  if (d3 >= 0 && d4 <= d3) return {b, 0, 1, 0};
  const Real vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) {
    const Real v = d1 - d3 > 0 ? d1 / (d1 - d3) : 0;
    return {a + v * ab, 1 - v, v, 0};
  }
  const Vec3 cp = p - c;
  const Real d5 = dot(ab, cp), d6 = dot(ac, cp);
  if (d6 >= 0 && d5 <= d6) return {c, 0, 0, 1};
  const Real vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) {
    const Real w = d2 - d6 > 0 ? d2 / (d2 - d6) : 0;
    return {a + w * ac, 1 - w, 0, w};
  }
  const Real va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
    const Real den = (d4 - d3) + (d5 - d6);
    const Real w = den > 0 ? (d4 - d3) / den : 0;
    return {b + w * (c - b), 0, 1 - w, w};
  }
  const Real sum = va + vb + vc;
  if (!(sum > 0)) return {a, 1, 0, 0};
  const Real v = vb / sum, w = vc / sum;
  return {a + v * ab + w * ac, 1 - v - w, v, w};
}

// Triangle vertex k of triangle t at time tau after the step's start.
struct TriangleSource {
  const Real* x = nullptr;  // (nv x 3)
  const Real* v = nullptr;  // (nv x 3) or null
  const std::int32_t* tri = nullptr;
  std::int32_t n_vertices = 0, n_triangles = 0;
  Vec3 vertex(std::int32_t t, int k, Real tau) const {
    const std::int32_t i = tri[3 * t + k];
    Vec3 p = load3(x, i);
    if (v) p += tau * load3(v, i);
    return p;
  }
  Vec3 velocity(std::int32_t t, int k) const { return v ? load3(v, tri[3 * t + k]) : Vec3{}; }
  bool valid(std::int32_t t) const {
    for (int k = 0; k < 3; ++k)
      if (tri[3 * t + k] < 0 || tri[3 * t + k] >= n_vertices) return false;
    return true;
  }
};

bool finite(const Vec3& a) { return std::isfinite(a.x) && std::isfinite(a.y) && std::isfinite(a.z); }

// Whether triangle t is binned: valid indices, finite at 0 and duration, not
// degenerate at 0.
bool binnable(const TriangleSource& src, std::int32_t t, Real duration) {
  if (!src.valid(t)) return false;
  const Vec3 a = src.vertex(t, 0, 0), b = src.vertex(t, 1, 0), c = src.vertex(t, 2, 0);
  if (!finite(a) || !finite(b) || !finite(c)) return false;
  if (!finite(src.vertex(t, 0, duration)) || !finite(src.vertex(t, 1, duration)) || !finite(src.vertex(t, 2, duration)))
    return false;
  const Vec3 nrm = cross(b - a, c - a);
  const Real scale = std::max({dot(b - a, b - a), dot(c - a, c - a), Real(1e-300)});
  return dot(nrm, nrm) > 1e-24 * scale * scale;
}

// Builds g over the triangles' bounding boxes during [0, duration], level 0
// inflated by margin, level 1 by margin / 2. Each vertex is binned with its
// box over [0, duration] grown by slack (g.vertex_box), a triangle with the
// union of its vertices' boxes, so that the grid serves later steps whose
// vertices stay in those boxes (triangle_grid_holds). Degenerate or invalid
// triangles are left out.
void build_triangle_grid(const TriangleSource& src, Real duration, Real margin, TriangleGrid& g, Real slack = 0) {
  const std::int32_t nt = src.n_triangles;
  ++g.builds;
  g.vertex_box.resize(6 * static_cast<std::size_t>(src.n_vertices));
  for (std::int32_t i = 0; i < src.n_vertices; ++i) {
    Vec3 p0 = load3(src.x, i), p1 = p0;
    if (src.v) p1 += duration * load3(src.v, i);
    Real* B = g.vertex_box.data() + 6 * static_cast<std::size_t>(i);
    B[0] = std::min(p0.x, p1.x) - slack, B[1] = std::min(p0.y, p1.y) - slack, B[2] = std::min(p0.z, p1.z) - slack;
    B[3] = std::max(p0.x, p1.x) + slack, B[4] = std::max(p0.y, p1.y) + slack, B[5] = std::max(p0.z, p1.z) + slack;
  }
  g.triangles.assign(src.tri, src.tri + 3 * static_cast<std::size_t>(nt));
  std::vector<std::array<Real, 6>> box;
  std::vector<std::int32_t> ids;
  box.reserve(nt);
  Real lo[3] = {HUGE_VAL, HUGE_VAL, HUGE_VAL}, hi[3] = {-HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
  for (std::int32_t t = 0; t < nt; ++t) {
    if (!binnable(src, t, duration)) continue;
    std::array<Real, 6> bb{HUGE_VAL, HUGE_VAL, HUGE_VAL, -HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
    for (int j = 0; j < 3; ++j) {
      const Real* B = g.vertex_box.data() + 6 * static_cast<std::size_t>(src.tri[3 * t + j]);
      for (int k = 0; k < 3; ++k) {
        bb[k] = std::min(bb[k], B[k]);
        bb[3 + k] = std::max(bb[3 + k], B[3 + k]);
      }
    }
    for (int k = 0; k < 3; ++k) {
      lo[k] = std::min(lo[k], bb[k]);
      hi[k] = std::max(hi[k], bb[3 + k]);
    }
    box.push_back(bb);
    ids.push_back(t);
  }
  g.listed.assign(static_cast<std::size_t>(nt), 0);
  for (const std::int32_t t : ids) g.listed[static_cast<std::size_t>(t)] = 1;
  // the two levels side by side (independent: the same boxes, their own cells)
  tbb::parallel_for(0, 2, [&](int lv) {
    TriangleCells& G = g.level[static_cast<std::size_t>(lv)];
    const Real m = lv == 0 ? margin : margin / 2;
    G.margin = m;
    G.start.assign(1, 0);
    G.items.clear();
    G.dims = {0, 0, 0};
    if (ids.empty()) return;
    const Real glo[3] = {lo[0] - m, lo[1] - m, lo[2] - m}, ghi[3] = {hi[0] + m, hi[1] + m, hi[2] + m};
    const std::int64_t cap = std::max<std::int64_t>(8 * static_cast<std::int64_t>(ids.size()), 4096);
    Real cell = std::max(m, Real(1e-9));
    auto dims_for = [&](Real c, std::array<std::int32_t, 3>& d) {
      std::int64_t total = 1;
      for (int k = 0; k < 3; ++k) {
        d[k] = static_cast<std::int32_t>(std::min<Real>(std::floor((ghi[k] - glo[k]) / c) + 1, 1 << 20));
        total *= d[k];
      }
      return total;
    };
    std::array<std::int32_t, 3> d{};
    while (dims_for(cell, d) > cap) cell *= 1.26;
    G.origin = {glo[0], glo[1], glo[2]};
    G.cell = cell;
    G.dims = d;
    const std::int64_t nc = static_cast<std::int64_t>(d[0]) * d[1] * d[2];
    std::vector<std::int32_t> count(nc + 1, 0);
    auto range = [&](const std::array<Real, 6>& bb, int k) {
      const auto a = static_cast<std::int32_t>(std::clamp<Real>(std::floor((bb[k] - m - glo[k]) / cell), 0, d[k] - 1));
      const auto b = static_cast<std::int32_t>(std::clamp<Real>(std::floor((bb[3 + k] + m - glo[k]) / cell), 0, d[k] - 1));
      return std::pair{a, b};
    };
    for (int pass = 0; pass < 2; ++pass) {
      for (std::size_t q = 0; q < ids.size(); ++q) {
        const auto [x0, x1] = range(box[q], 0);
        const auto [y0, y1] = range(box[q], 1);
        const auto [z0, z1] = range(box[q], 2);
        for (std::int32_t z = z0; z <= z1; ++z)
          for (std::int32_t y = y0; y <= y1; ++y)
            for (std::int32_t x = x0; x <= x1; ++x) {
              const std::int64_t c = x + static_cast<std::int64_t>(d[0]) * (y + static_cast<std::int64_t>(d[1]) * z);
              if (pass == 0) ++count[c + 1];
              else G.items[count[c]++] = ids[q];
            }
      }
      if (pass == 0) {
        for (std::int64_t c = 0; c < nc; ++c) count[c + 1] += count[c];
        G.start.assign(count.begin(), count.end());
        G.items.assign(static_cast<std::size_t>(count[nc]), 0);
      }
    }
  });
}

// Whether g still serves src over [0, duration]: the triangles it binned,
// every vertex at 0 and at duration inside its binning box (so every triangle
// at any time of the step inside its binned box: the boxes are convex), and
// every triangle's listing unchanged. Then each cell still lists every
// triangle within its level's margin, and a query finds what it would find on
// a new grid.
bool triangle_grid_holds(const TriangleSource& src, Real duration, const TriangleGrid& g) {
  const auto nt = static_cast<std::size_t>(src.n_triangles);
  if (g.triangles.size() != 3 * nt || g.listed.size() != nt ||
      g.vertex_box.size() != 6 * static_cast<std::size_t>(src.n_vertices))
    return false;
  if (nt > 0 && std::memcmp(g.triangles.data(), src.tri, 3 * nt * sizeof(std::int32_t)) != 0) return false;
  auto vertices_hold = [&](std::int32_t b, std::int32_t e) {
    for (std::int32_t i = b; i < e; ++i) {
      const Real* B = g.vertex_box.data() + 6 * static_cast<std::size_t>(i);
      Vec3 p = load3(src.x, i);
      for (int end = 0; end < 2; ++end) {
        if (!(p.x >= B[0] && p.y >= B[1] && p.z >= B[2] && p.x <= B[3] && p.y <= B[4] && p.z <= B[5])) return false;
        if (!src.v) break;
        p += duration * load3(src.v, i);
      }
    }
    return true;
  };
  auto listing_holds = [&](std::int32_t b, std::int32_t e) {
    for (std::int32_t t = b; t < e; ++t)
      if (static_cast<bool>(g.listed[static_cast<std::size_t>(t)]) != binnable(src, t, duration)) return false;
    return true;
  };
  auto all = [](std::int32_t n, auto&& part) {
    return tbb::parallel_reduce(
        tbb::blocked_range<std::int32_t>(0, n, 1024), true,
        [&](const tbb::blocked_range<std::int32_t>& r, bool ok) { return ok && part(r.begin(), r.end()); },
        [](bool a, bool b) { return a && b; });
  };
  return all(src.n_vertices, vertices_hold) && all(src.n_triangles, listing_holds);
}

// The candidates of the grid cell containing p: [begin, end) of g.items (empty outside).
std::pair<std::int32_t, std::int32_t> grid_candidates(const TriangleCells& g, const Vec3& p) {
  if (g.dims[0] == 0) return {0, 0};
  const Real q[3] = {p.x, p.y, p.z};
  std::int64_t idx[3];
  for (int k = 0; k < 3; ++k) {
    const Real f = std::floor((q[k] - g.origin[k]) / g.cell);
    if (!(f >= 0 && f < g.dims[k])) return {0, 0};
    idx[k] = static_cast<std::int64_t>(f);
  }
  const std::int64_t c = idx[0] + g.dims[0] * (idx[1] + static_cast<std::int64_t>(g.dims[1]) * idx[2]);
  return {g.start[c], g.start[c + 1]};
}

// The triangles of a source at one time tau: their vertices (x + tau v, as
// TriangleSource::vertex) and bounding spheres about the centroid, computed
// once per substep instead of per query. The culling data of a triangle
// (what a query reads of most candidates) fills one cache line of its own.
struct TriFrame {
  struct alignas(64) Cull {
    Real m[3];  // centroid
    Real r;     // bounding radius about it (rounded up)
    Real n[3];  // unit normal
    Real pad;
  };
  Real tau = -HUGE_VAL;
  bool valid = false;
  std::vector<std::array<Real, 9>> tri;  // (n_triangles) a, b, c
  std::vector<Cull> cull;                // (n_triangles)
  void build(const TriangleSource& src, Real t) {
    tau = t;
    valid = true;
    tri.resize(static_cast<std::size_t>(src.n_triangles));
    cull.resize(static_cast<std::size_t>(src.n_triangles));
    // each triangle's entries from its own vertices: any split gives the same frame
    tbb::parallel_for(tbb::blocked_range<std::int32_t>(0, src.n_triangles, 512), [&](const auto& range) {
      for (std::int32_t k = range.begin(); k < range.end(); ++k) {
        auto& T = tri[static_cast<std::size_t>(k)];
        auto& C = cull[static_cast<std::size_t>(k)];
        if (!src.valid(k)) {
          T.fill(0);
          C = Cull{};
          continue;
        }
        const Vec3 a = src.vertex(k, 0, t), b = src.vertex(k, 1, t), c = src.vertex(k, 2, t);
        const Vec3 m = (Real(1) / 3) * (a + b + c);
        const Real r = std::sqrt(std::max({dot(a - m, a - m), dot(b - m, b - m), dot(c - m, c - m)}));
        Vec3 nrm = cross(b - a, c - a);
        const Real ln = norm(nrm);
        nrm = ln > 0 ? (1 / ln) * nrm : Vec3{};
        T = {a.x, a.y, a.z, b.x, b.y, b.z, c.x, c.y, c.z};
        C = Cull{{m.x, m.y, m.z}, r * (1 + 1e-9) + 1e-15, {nrm.x, nrm.y, nrm.z}, 0};
      }
    });
  }
};

// Closest triangle within H of p at time tau; fills a contact and returns
// true. One-sided: fluid on the face normal's side, a particle behind gets
// d = 0 and n = the face normal. Two-sided: the side the particle is on.
// With a frame at tau, candidates whose bounding sphere lies farther than the
// best distance so far are skipped (exact: they cannot be closer). hint: a
// triangle likely to be the closest (the particle's contact a moment ago),
// tried first so that the others are mostly skipped; the result does not
// depend on it (the closest, ties to the lowest triangle id, as without).
bool triangle_contact(const TriangleSource& src, const TriangleGrid& g, const Vec3& p, Real tau, Real H,
                      const WallParams& wall, bool two_sided, Contact& out, const TriFrame* frame = nullptr,
                      std::int32_t hint = -1) {
  Real best = H * H, best_d = H;
  std::int32_t best_t = -1;
  ClosestPoint best_c{};
  if (frame && !(frame->valid && (frame->tau == tau || src.v == nullptr))) frame = nullptr;
  auto closest = [&](std::int32_t t) {
    if (frame) {
      const auto& T = frame->tri[static_cast<std::size_t>(t)];
      return closest_on_triangle(p, {T[0], T[1], T[2]}, {T[3], T[4], T[5]}, {T[6], T[7], T[8]});
    }
    return closest_on_triangle(p, src.vertex(t, 0, tau), src.vertex(t, 1, tau), src.vertex(t, 2, tau));
  };
  auto consider = [&](std::int32_t t, const ClosestPoint& c) {
    const Vec3 dd = p - c.p;
    const Real d2 = dot(dd, dd);
    if (d2 < best || (d2 == best && t < best_t)) {
      best = d2;
      best_d = std::sqrt(d2);
      best_t = t;
      best_c = c;
    }
  };
  if (hint >= 0 && hint < static_cast<std::int32_t>(g.listed.size()) && g.listed[static_cast<std::size_t>(hint)])
    consider(hint, closest(hint));
  else
    hint = -1;
  // a contact within the fine level's margin (with room for the rounding of
  // its boxes): every closer triangle is in the fine level's cell
  const TriangleCells& lv = best_t >= 0 && best_d < g.level[1].margin * (1 - 1e-9) ? g.level[1] : g.level[0];
  const auto [b, e] = grid_candidates(lv, p);
  for (std::int32_t k = b; k < e; ++k) {
    const std::int32_t t = lv.items[k];
    if (t == hint) continue;
    if (frame) {
      const TriFrame::Cull& C = frame->cull[static_cast<std::size_t>(t)];
      const Vec3 dm{p.x - C.m[0], p.y - C.m[1], p.z - C.m[2]};
      const Real lim = best_d + C.r;
      if (dot(dm, dm) > lim * lim) continue;  // the bounding sphere is farther than the best
      // the plane is farther than the best (the margin covers the rounding of the normal)
      if (std::abs(dm.x * C.n[0] + dm.y * C.n[1] + dm.z * C.n[2]) > best_d * (1 + 1e-9) + 1e-12 * C.r) continue;
    }
    consider(t, closest(t));
  }
  if (best_t < 0) return false;
  const Vec3 a = src.vertex(best_t, 0, tau), bb = src.vertex(best_t, 1, tau), cc = src.vertex(best_t, 2, tau);
  Vec3 face = cross(bb - a, cc - a);
  face = (1 / norm(face)) * face;
  const Vec3 rel = p - best_c.p;
  const Real dist = std::sqrt(best);
  const Real s = dot(rel, face);
  out = Contact{};
  out.wall = &wall;
  out.tri = best_t;
  out.w0 = best_c.w0;
  out.w1 = best_c.w1;
  out.w2 = best_c.w2;
  out.c = best_c.p;
  out.u = best_c.w0 * src.velocity(best_t, 0) + best_c.w1 * src.velocity(best_t, 1) + best_c.w2 * src.velocity(best_t, 2);
  if (!two_sided && s < 0) {  // behind a one-sided wall
    out.face = face;
    out.n = face;
    out.d = 0;
    out.behind = true;
    return true;
  }
  out.face = (two_sided && s < 0) ? -face : face;  // the particle's side
  out.n = dist > 1e-12 * H ? (1 / dist) * rel : out.face;
  out.d = dist;
  return true;
}

// Everything the passes need about the boundaries at one time of the step.
struct Walls {
  const FluidBoundaries* b = nullptr;
  std::vector<TriangleSource> meshes;    // static
  std::vector<TriangleSource> surfaces;  // moving
  const std::vector<FluidSurface>* surf = nullptr;
  Real H = 0;
  // Where no wall can be within H: inside [inner_lo, inner_hi] when only box
  // faces are walls (only_box); see set_inner.
  bool only_box = false;
  Real inner_lo[3] = {0, 0, 0}, inner_hi[3] = {0, 0, 0};

  void set_inner() {
    only_box = b->planes.empty() && meshes.empty() && surfaces.empty();
    for (int a = 0; a < 3; ++a) {
      inner_lo[a] = b->faces[2 * a] == Face::wall ? b->lo[a] + H : -HUGE_VAL;
      inner_hi[a] = b->faces[2 * a + 1] == Face::wall ? b->hi[a] - H : HUGE_VAL;
    }
  }
  // false: certainly no wall within H of p (the common case: a fast test)
  bool maybe_near(const Vec3& p) const {
    if (!only_box) return true;
    return !(p.x > inner_lo[0] && p.x < inner_hi[0] && p.y > inner_lo[1] && p.y < inner_hi[1] && p.z > inner_lo[2] &&
             p.z < inner_hi[2]);
  }

  // Calls f(const Contact&) for every wall within H of p at time tau.
  // cache: (n_triangle_walls) the particle's triangle contacts at this tau;
  // cached: read them from it, else query and store them. hints:
  // (n_triangle_walls) first guesses of the queries, or null.
  template <class F>
  void contacts(const Vec3& p, Real tau, F&& f, Contact* cache = nullptr, bool cached = false,
                const std::int32_t* hints = nullptr) const {
    const Real q[3] = {p.x, p.y, p.z};
    for (int a = 0; a < 3; ++a) {
      for (int side = 0; side < 2; ++side) {
        if (b->faces[2 * a + side] != Face::wall) continue;
        const Real d = side == 0 ? q[a] - b->lo[a] : b->hi[a] - q[a];
        if (!(d < H)) continue;
        Contact c;
        c.d = std::max(Real(0), d);
        Real n[3] = {0, 0, 0};
        n[a] = side == 0 ? 1 : -1;
        c.n = {n[0], n[1], n[2]};
        c.face = c.n;
        c.wall = &b->box_wall;
        f(c);
      }
    }
    for (const FluidPlane& pl : b->planes) {
      const Vec3 n = vec(pl.normal);
      const Real d = dot(n, p - vec(pl.point));
      if (!(d < H)) continue;
      Contact c;
      c.d = std::max(Real(0), d);
      c.n = n;
      c.face = n;
      c.wall = &pl.wall;
      f(c);
    }
    // triangle walls: from the cache when given and filled, else queried (and
    // stored in the cache when given)
    for (std::size_t m = 0; m < meshes.size(); ++m) {
      Contact c;
      if (cache && cached) c = cache[m];
      else if (!triangle_contact(meshes[m], b->meshes[m].grid, p, 0, H, b->meshes[m].wall, b->meshes[m].two_sided, c,
                                 &mesh_frames[m], hints ? hints[m] : -1))
        c = Contact{};
      if (cache && !cached) cache[m] = c;
      if (c.wall) f(c);
    }
    for (std::size_t k = 0; k < surfaces.size(); ++k) {
      const FluidSurface& sf = (*surf)[k];
      Contact c;
      if (cache && cached) c = cache[meshes.size() + k];
      else if (triangle_contact(surfaces[k], sf.grid, p, tau, H, sf.wall, sf.two_sided, c, &surface_frames[k],
                                hints ? hints[meshes.size() + k] : -1))
        c.surface = static_cast<int>(k);
      else
        c = Contact{};
      if (cache && !cached) cache[meshes.size() + k] = c;
      if (c.wall) f(c);
    }
  }

  // triangle frames: the static meshes once, the moving surfaces at tau
  std::vector<TriFrame> mesh_frames, surface_frames;
  void frames_at(Real tau) {
    mesh_frames.resize(meshes.size());
    for (std::size_t m = 0; m < meshes.size(); ++m)
      if (!mesh_frames[m].valid) mesh_frames[m].build(meshes[m], 0);
    surface_frames.resize(surfaces.size());
    for (std::size_t k = 0; k < surfaces.size(); ++k)
      if (surface_frames[k].tau != tau) surface_frames[k].build(surfaces[k], tau);
  }
  std::size_t n_triangle_walls() const { return meshes.size() + surfaces.size(); }
};

// ---- the passes -----------------------------------------------------------------

struct BigLists;

struct Pass {
  const Fluid* f = nullptr;
  const NeighbourGrid* g = nullptr;
  const Walls* walls = nullptr;
  std::int32_t n = 0;
  const Real *x = nullptr, *y = nullptr, *z = nullptr, *vx = nullptr, *vy = nullptr, *vz = nullptr;
  Real *rho = nullptr, *p = nullptr, *ir = nullptr, *nb = nullptr, *ksum = nullptr;
  Real *ax = nullptr, *ay = nullptr, *az = nullptr, *wx = nullptr, *wy = nullptr, *wz = nullptr;
  float* pack = nullptr;          // (n x 8) x, y, z (- origin), P, vx, vy, vz, 1/rho in single precision (the force pass)
  std::uint8_t* near = nullptr;   // (n) 1 where a wall may be within H (Walls::maybe_near): the force pass sums psum
  Real* psum = nullptr;           // (n) Pa, sum_{j != i} p_j (1 - q)^4 (1 + 4 q), where near (the walls' Shepard pressure)
  Real* mu = nullptr;             // (n) Pa s, per-particle viscosity (carreau rheology), else null
  std::int32_t* list = nullptr;   // (n x kListStride) neighbour lists (self excluded), padded with i
  std::int32_t* count = nullptr;  // (n) list lengths; > kMaxList: the list is in big
  BigLists* big = nullptr;        // the full lists of the particles with more than kMaxList neighbours
  std::array<Real, 3> period{};   // m, > 0 on periodic axes
  const float *xf = nullptr, *yf = nullptr, *zf = nullptr;  // positions - origin, single precision (search, pack)
  std::array<Real, 3> origin{};   // m, the grid origin the float positions are relative to
  float search_r2 = 0;            // m^2, (1.005 H)^2: the search radius of the lists
  Real tau = 0;  // time since the step's start
};

// Neighbour lists: at most kMaxList entries per particle in the flat array
// (~30 at rest with H = 2 dx); a particle with more (a fluid compressed ~3x)
// gets a list of its own (BigLists). The stride leaves room for the 8 slots
// the vector search writes past the count.
constexpr int kMaxList = 92, kListStride = kMaxList + 8;

// Grows a scratch array that every pass rewrites before reading (old values
// are dropped) to n entries. A new allocation is advised to use transparent
// huge pages before it is first touched: the density pass writes the lists
// (400 B per particle) and the force pass gathers from the pack (32 B per
// particle) across the whole particle range, and with 4 KiB pages a
// 100 k-particle step (44 MB of both) misses the TLB on most gathers. Advice
// only: where the kernel declines it nothing changes, and the values are the
// same either way.
template <class T>
void grow_scratch(std::vector<T>& v, std::size_t n) {
  if (v.capacity() < n) {
    std::vector<T>().swap(v);
    v.reserve(n + n / 4);
    constexpr std::uintptr_t kHuge = std::uintptr_t{1} << 21;
    const std::uintptr_t b = (reinterpret_cast<std::uintptr_t>(v.data()) + kHuge - 1) & ~(kHuge - 1);
    const std::uintptr_t e = reinterpret_cast<std::uintptr_t>(v.data() + v.capacity()) & ~(kHuge - 1);
    if (e > b) madvise(reinterpret_cast<void*>(b), e - b, MADV_HUGEPAGE);
  }
  v.resize(n);
}

// ---- neighbour search in single precision ---------------------------------------
// The lists are found in float (8 lanes, no square root) with a search radius
// 1.005 H; the density's kernel values and sums are then evaluated in double
// over the list (the force pass's pair terms in float, summed in double),
// where pairs beyond H give exactly 0. A float distance errs by about
// 1e-7 of the coordinates (relative to the grid origin), so no pair within H
// is missed while the grid is less than ~10^4 H across. Both code paths below
// compute r^2 = (dx dx + dy dy) + dz dz without fused multiply-adds and list
// the same slots in ascending order.
//
// Appends the slots j in [b, e), j != self, with r^2 < r2max to list[cnt..];
// returns the new count. The write position is clamped at cap (the count is
// not: cnt > cap means the list overflowed). The float arrays have 8 readable
// entries past the last slot; the list, 8 writable entries past cap.
inline std::int32_t scan_run_generic(const float* xf, const float* yf, const float* zf, std::int32_t b, std::int32_t e,
                                     std::int32_t self, float xi, float yi, float zi, float r2max, std::int32_t* list,
                                     std::int32_t cnt, std::int32_t cap) {
  for (std::int32_t j = b; j < e; ++j) {
    const float dx = xi - xf[j], dy = yi - yf[j], dz = zi - zf[j];
    const float dx2 = dx * dx, dy2 = dy * dy, dz2 = dz * dz;
    const float r2 = (dx2 + dy2) + dz2;
    list[std::min(cnt, cap)] = j;
    cnt += static_cast<std::int32_t>(r2 < r2max) & static_cast<std::int32_t>(j != self);
  }
  return cnt;
}

#ifdef ORTHOSIM_SPH_AVX2
// kCompact[m]: the lanes set in the 8-bit mask m, in ascending order, first
struct CompactTable {
  alignas(32) std::int32_t lanes[256][8];
  CompactTable() {
    for (int m = 0; m < 256; ++m) {
      int k = 0;
      for (int l = 0; l < 8; ++l)
        if (m & (1 << l)) lanes[m][k++] = l;
      for (; k < 8; ++k) lanes[m][k] = 0;
    }
  }
};
const CompactTable kCompact;

__attribute__((target("avx2"), always_inline)) inline std::int32_t scan_run_avx2(const float* xf, const float* yf, const float* zf,
                                                           std::int32_t b, std::int32_t e, std::int32_t self, float xi,
                                                           float yi, float zi, float r2max, std::int32_t* list,
                                                           std::int32_t cnt, std::int32_t cap) {
  const __m256 X = _mm256_set1_ps(xi), Y = _mm256_set1_ps(yi), Z = _mm256_set1_ps(zi), R = _mm256_set1_ps(r2max);
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const __m256i E = _mm256_set1_epi32(e), S = _mm256_set1_epi32(self);
  for (std::int32_t j = b; j < e; j += 8) {
    const __m256 dx = _mm256_sub_ps(X, _mm256_loadu_ps(xf + j));
    const __m256 dy = _mm256_sub_ps(Y, _mm256_loadu_ps(yf + j));
    const __m256 dz = _mm256_sub_ps(Z, _mm256_loadu_ps(zf + j));
    const __m256 r2 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(dx, dx), _mm256_mul_ps(dy, dy)), _mm256_mul_ps(dz, dz));
    const __m256i idx = _mm256_add_epi32(_mm256_set1_epi32(j), lane);
    const __m256i valid = _mm256_andnot_si256(_mm256_cmpeq_epi32(idx, S), _mm256_cmpgt_epi32(E, idx));
    const int bits = _mm256_movemask_ps(_mm256_and_ps(_mm256_cmp_ps(r2, R, _CMP_LT_OQ), _mm256_castsi256_ps(valid)));
    const __m256i perm = _mm256_load_si256(reinterpret_cast<const __m256i*>(kCompact.lanes[bits]));
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(list + std::min(cnt, cap)), _mm256_permutevar8x32_epi32(idx, perm));
    cnt += __builtin_popcount(static_cast<unsigned>(bits));
  }
  return cnt;
}
#endif

// The lists of the particles [b, e) of one cell over the runs around it:
// list and count of each (see scan_run). One call per cell. The runs are the
// outer loop and the cell's particles the inner one (in chunks of 64), so
// the scan of a run repeats its trip count for every particle of the cell
// (a predictable branch); each list is still filled run by run, in the same
// order as particle by particle. A particle's float position is its xf
// entry, recomputed from the double only for a run shifted by a period.
// scan_one lists one particle into a list of its own (cap: its known count).
using ScanCellFn = void (*)(const Pass& c, const NeighbourRun* runs, int nr, std::int32_t b, std::int32_t e);
using ScanOneFn = std::int32_t (*)(const Pass& c, const NeighbourRun* runs, int nr, std::int32_t i, std::int32_t* list,
                                   std::int32_t cap);

// particle i's float position for run r (relative to the grid origin, less the run's period shift)
inline std::array<float, 3> scan_position(const Pass& c, const NeighbourRun& run, std::int32_t i) {
  if (run.sx == 0 && run.sy == 0 && run.sz == 0) return {c.xf[i], c.yf[i], c.zf[i]};
  return {static_cast<float>(c.x[i] - run.sx - c.origin[0]), static_cast<float>(c.y[i] - run.sy - c.origin[1]),
          static_cast<float>(c.z[i] - run.sz - c.origin[2])};
}

#define ORTHOSIM_SPH_SCAN_CELL(scan)                                                                          \
  constexpr std::int32_t kChunk = 64;                                                                        \
  std::int32_t cnt[kChunk];                                                                                  \
  for (std::int32_t cb = b; cb < e; cb += kChunk) {                                                          \
    const std::int32_t ce = std::min(e, cb + kChunk);                                                        \
    for (std::int32_t i = cb; i < ce; ++i) cnt[i - cb] = 0;                                                  \
    for (int r = 0; r < nr; ++r) {                                                                           \
      const NeighbourRun& run = runs[r];                                                                     \
      for (std::int32_t i = cb; i < ce; ++i) {                                                               \
        const auto q = scan_position(c, run, i);                                                             \
        std::int32_t* list = c.list + static_cast<std::int64_t>(i) * kListStride;                           \
        cnt[i - cb] = scan(c.xf, c.yf, c.zf, run.begin, run.end, i, q[0], q[1], q[2], c.search_r2, list,     \
                           cnt[i - cb], kMaxList);                                                           \
      }                                                                                                      \
    }                                                                                                        \
    for (std::int32_t i = cb; i < ce; ++i) c.count[i] = cnt[i - cb];                                        \
  }
#define ORTHOSIM_SPH_SCAN_ONE(scan)                                                                           \
  std::int32_t cnt = 0;                                                                                      \
  for (int r = 0; r < nr; ++r) {                                                                             \
    const auto q = scan_position(c, runs[r], i);                                                             \
    cnt = scan(c.xf, c.yf, c.zf, runs[r].begin, runs[r].end, i, q[0], q[1], q[2], c.search_r2, list, cnt, cap); \
  }                                                                                                          \
  return cnt;

void scan_cell_generic(const Pass& c, const NeighbourRun* runs, int nr, std::int32_t b, std::int32_t e) {
  ORTHOSIM_SPH_SCAN_CELL(scan_run_generic)
}
std::int32_t scan_one_generic(const Pass& c, const NeighbourRun* runs, int nr, std::int32_t i, std::int32_t* list,
                              std::int32_t cap) {
  ORTHOSIM_SPH_SCAN_ONE(scan_run_generic)
}

#ifdef ORTHOSIM_SPH_AVX2
__attribute__((target("avx2"))) void scan_cell_avx2(const Pass& c, const NeighbourRun* runs, int nr, std::int32_t b,
                                                    std::int32_t e) {
  ORTHOSIM_SPH_SCAN_CELL(scan_run_avx2)
}
__attribute__((target("avx2"))) std::int32_t scan_one_avx2(const Pass& c, const NeighbourRun* runs, int nr,
                                                           std::int32_t i, std::int32_t* list, std::int32_t cap) {
  ORTHOSIM_SPH_SCAN_ONE(scan_run_avx2)
}
#endif
#undef ORTHOSIM_SPH_SCAN_CELL
#undef ORTHOSIM_SPH_SCAN_ONE

struct Scanners {
  ScanCellFn cell = scan_cell_generic;
  ScanOneFn one = scan_one_generic;
};
Scanners pick_scan() {
#ifdef ORTHOSIM_SPH_AVX2
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx2")) return {scan_cell_avx2, scan_one_avx2};
#endif
  return {};
}
const Scanners kScan = pick_scan();

// The full lists of the particles with more than kMaxList neighbours (a
// fluid compressed ~3x, e.g. PhysX-soft blood pooling): per-thread buffers
// filled by the density pass and read by the shear and force passes of the
// same substep. A list's place: its buffer and offset (buffers may move as
// they grow; the elements of enumerable_thread_specific do not).
struct BigLists {
  tbb::enumerable_thread_specific<std::vector<std::int32_t>> buf;
  std::vector<std::pair<std::vector<std::int32_t>*, std::int64_t>> where;  // (n) valid where count > kMaxList

  std::atomic<bool> used{false};  // a list overflowed in this build

  void reset(std::size_t n) {
    for (auto& b : buf) b.clear();
    where.resize(n);
    used = false;
  }
  // lists particle i (count known: cnt) into the calling thread's buffer
  std::int32_t* fill(const Pass& c, const NeighbourRun* runs, int nr, std::int32_t i, std::int32_t cnt) {
    used.store(true, std::memory_order_relaxed);
    std::vector<std::int32_t>& b = buf.local();
    const auto off = static_cast<std::int64_t>(b.size());
    b.resize(static_cast<std::size_t>(off + cnt + 8));  // 8 past the count: the vector stores and the padding
    std::int32_t* list = b.data() + off;
    kScan.one(c, runs, nr, i, list, cnt);
    where[static_cast<std::size_t>(i)] = {&b, off};
    return list;
  }
  const std::int32_t* list(std::int32_t i) const {
    const auto& w = where[static_cast<std::size_t>(i)];
    return w.first->data() + w.second;
  }
};

// particle i's list: its slot of c.list, or its full list where it overflowed
inline const std::int32_t* list_of(const Pass& c, std::int32_t i) {
  return c.count[i] <= kMaxList ? c.list + static_cast<std::int64_t>(i) * kListStride : c.big->list(i);
}

// Over particle i's list of cnt neighbours (padded with i past cnt), at the
// positions (x, y, z): the lanes of the kernel sum sum_j (1 - q)^4 (1 + 4 q)
// and of the count within H, self excluded. 4 lanes in double; the density
// pass sums at the current positions, pcisph at the predicted ones.
struct KernelSums {
  V acc, within;
};
ORTHOSIM_SPH_INLINE KernelSums kernel_sums(const Pass& c, const std::int32_t* list, std::int32_t cnt, std::int32_t i,
                                           const Real* x, const Real* y, const Real* z) {
  const Real invH = 1 / c.f->H;
  const V zero = {0, 0, 0, 0}, one = {1, 1, 1, 1}, lane = {0, 1, 2, 3};
  const bool periodic = c.period[0] > 0 || c.period[1] > 0 || c.period[2] > 0;
  KernelSums k{zero, zero};
  const Real xi = x[i], yi = y[i], zi = z[i];
  for (std::int32_t b = 0; b < cnt; b += 4) {
    const std::int32_t* j = list + b;
    auto gather = [&](const Real* a) ORTHOSIM_SPH_LAMBDA { return V{a[j[0]], a[j[1]], a[j[2]], a[j[3]]}; };
    V dx = xi - gather(x), dy = yi - gather(y), dz = zi - gather(z);
    if (periodic) {
      dx = minimum_image(dx, c.period[0]);
      dy = minimum_image(dy, c.period[1]);
      dz = minimum_image(dz, c.period[2]);
    }
    const V mask = (lane + static_cast<Real>(b)) < static_cast<Real>(cnt) ? one : zero;
    const V q = vsqrt(dx * dx + dy * dy + dz * dz) * invH;
    V t = 1 - q;
    t = t > 0 ? t * mask : zero;
    const V t2 = t * t;
    k.acc += t2 * t2 * (1 + 4 * q);
    k.within += t > 0 ? one : zero;
  }
  return k;
}

// The passes hand out the grid's pieces (NeighbourGrid::pieces: a cell's
// particles, at most 32 at a time), kPieceGrain pieces or more a task: a
// crowded cell is shared among tasks (it was one task, so a pool of the soft
// PhysX blood, hundreds of particles a cell, kept the scene from scaling past
// 4 threads; BENCHMARKS.md). Each particle's sums are its own, so the results
// do not depend on the split.
constexpr std::size_t kPieceGrain = 8;

// Density pass of the particles of one piece of a cell: the list of the neighbours
// within the search radius (self excluded; found in float, see scan_run),
// then in double over the list the kernel sums S_i = sum_j (1 - q)^4 (1 + 4 q)
// (self included) and the number of particles within H. A particle with more
// than kMaxList neighbours is listed again into a list of its own (BigLists).
ORTHOSIM_SPH_CLONES
void density_cell(const Pass& c, const NeighbourGrid::Piece& piece, bool scan) {
  NeighbourRun runs[27];
  int nr = 0;
  if (scan) {
    nr = neighbour_runs(*c.g, piece.cell, runs);
    kScan.cell(c, runs, nr, piece.begin, piece.end);
  }
  for (std::int32_t i = piece.begin; i < piece.end; ++i) {
    const std::int32_t cnt = c.count[i];
    std::int32_t* list = c.list + static_cast<std::int64_t>(i) * kListStride;
    if (scan) {  // kept lists (no overflow) are padded already
      if (cnt > kMaxList) list = c.big->fill(c, runs, nr, i, cnt);
      for (int k = cnt; k < cnt + 8; ++k) list[k] = i;  // padding of the last group (4 here, 8 in the force pass)
    }
    const KernelSums sums = kernel_sums(c, list, cnt, i, c.x, c.y, c.z);
    c.ksum[i] = 1 + hsum(sums.acc);
    c.nb[i] = 1 + hsum(sums.within);
  }
}

// pcisph: the kernel sums S_i = sum_j (1 - q)^4 (1 + 4 q) (self included) of
// the particles of one cell at the predicted positions (px, py, pz), over the
// substep's lists, as density_cell sums them at the current ones.
ORTHOSIM_SPH_CLONES
void predicted_sum_cell(const Pass& c, const Real* px, const Real* py, const Real* pz, const NeighbourGrid::Piece& piece, Real* out) {
  for (std::int32_t i = piece.begin; i < piece.end; ++i)
    out[i] = 1 + hsum(kernel_sums(c, list_of(c, i), c.count[i], i, px, py, pz).acc);  // lists padded with i past the count
}

// Pair accelerations (without the mass factor):
//   a_i = m sum_j g_ij [ (P_i + P_j + Pi_ij) r_ij - 2 mu / (rho_i rho_j) r_ij^2 / (r_ij^2 + eta^2) v_ij ]
// with grad_i W_ij = -g_ij r_ij (Wendland C2), P = p / rho^2 (Monaghan 1992),
// the laminar viscosity of Morris, Fox & Zhu (1997) and Monaghan's artificial
// viscosity Pi_ij = -alpha c0 h (v_ij . r_ij) / (r_ij^2 + eta^2) (1/rho_i + 1/rho_j) / 2
// for approaching pairs (v_ij . r_ij < 0), eta^2 = 0.01 h^2; the lattice
// scales are folded into P, Pi and the viscosity.
//
// The pair terms are computed in single precision, 8 lanes, from the float
// pack (positions relative to the grid origin, P, v, 1/rho), and summed in
// double. Every operation of a pair term sees the same operands for (i, j)
// as for (j, i), up to the sign of r_ij and v_ij or the order of a commutative
// + or *, so the term of (j, i) is exactly minus that of (i, j), and linear
// momentum is conserved to the round-off of the double sums. A float term
// errs by ~1e-7 of itself, and by ~1e-7 of the coordinates in r_ij (see the
// neighbour search), far below the discretisation's error.
using VF = float __attribute__((vector_size(8 * sizeof(float))));
using VI = std::int32_t __attribute__((vector_size(8 * sizeof(std::int32_t))));

struct PairConstants {
  float invH, eta2, avc, two_mu, vscale;
  explicit PairConstants(const Fluid& f)
      : invH(static_cast<float>(1 / f.H)),
        eta2(static_cast<float>(0.01 * f.h * f.h)),
        avc(static_cast<float>(f.params.artificial_viscosity * f.c0 * f.h * 0.5 * f.gradient_scale)),
        two_mu(static_cast<float>(2 * f.params.viscosity * f.viscous_scale)),
        vscale(static_cast<float>(f.viscous_scale)) {}
};

struct PairSums {
  V ax, ay, az;
};

// 8 lanes of float added into 4 lanes of double (lanes k and k + 4 first;
// through an 8-double vector: GCC then converts with two vcvtps2pd)
ORTHOSIM_SPH_INLINE void add_wide(V& acc, VF v) {
  using V8 = Real __attribute__((vector_size(8 * sizeof(Real))));
  const V8 w = __builtin_convertvector(v, V8);
  acc += __builtin_shufflevector(w, w, 0, 1, 2, 3) + __builtin_shufflevector(w, w, 4, 5, 6, 7);
}

ORTHOSIM_SPH_INLINE VF loadf(const float* a) {
  VF v;
  std::memcpy(&v, a, sizeof v);
  return v;
}

// 8 x 8 transpose: r[k] is particle k's record, c[a] the field a of the 8
ORTHOSIM_SPH_INLINE void transpose8(const VF* r, VF* c) {
  const VI lo = {0, 8, 1, 9, 4, 12, 5, 13}, hi = {2, 10, 3, 11, 6, 14, 7, 15};
  const VI s0 = {0, 1, 8, 9, 4, 5, 12, 13}, s1 = {2, 3, 10, 11, 6, 7, 14, 15};
  const VI p0 = {0, 1, 2, 3, 8, 9, 10, 11}, p1 = {4, 5, 6, 7, 12, 13, 14, 15};
  VF t[8], u[8];
  for (int k = 0; k < 4; ++k) {
    t[2 * k] = __builtin_shuffle(r[2 * k], r[2 * k + 1], lo);
    t[2 * k + 1] = __builtin_shuffle(r[2 * k], r[2 * k + 1], hi);
  }
  for (int h = 0; h < 2; ++h) {  // rows 0-3, rows 4-7
    u[4 * h] = __builtin_shuffle(t[4 * h], t[4 * h + 2], s0);
    u[4 * h + 1] = __builtin_shuffle(t[4 * h], t[4 * h + 2], s1);
    u[4 * h + 2] = __builtin_shuffle(t[4 * h + 1], t[4 * h + 3], s0);
    u[4 * h + 3] = __builtin_shuffle(t[4 * h + 1], t[4 * h + 3], s1);
  }
  for (int a = 0; a < 4; ++a) {
    c[a] = __builtin_shuffle(u[a], u[4 + a], p0);
    c[4 + a] = __builtin_shuffle(u[a], u[4 + a], p1);
  }
}

// kVar: per-particle viscosity (carreau), mu_i + mu_j per pair; else 2 mu
template <bool kVar>
ORTHOSIM_SPH_INLINE void force_cell_impl(const Pass& c, const NeighbourGrid::Piece& piece) {
  const Fluid& f = *c.f;
  const PairConstants k(f);
  const VF zero = {0, 0, 0, 0, 0, 0, 0, 0}, one = {1, 1, 1, 1, 1, 1, 1, 1};
  const VI lane = {0, 1, 2, 3, 4, 5, 6, 7};
  const V zero4 = {0, 0, 0, 0};
  const bool periodic = c.period[0] > 0 || c.period[1] > 0 || c.period[2] > 0;
  const float per[3] = {static_cast<float>(c.period[0]), static_cast<float>(c.period[1]), static_cast<float>(c.period[2])};
  for (std::int32_t i = piece.begin; i < piece.end; ++i) {
    const float* pi = c.pack + 8 * static_cast<std::int64_t>(i);
    const float xi = pi[0], yi = pi[1], zi = pi[2], Pi = pi[3], vxi = pi[4], vyi = pi[5], vzi = pi[6], iri = pi[7];
    const bool shepard = c.near[i] != 0;
    V psum = zero4;
    const float mui = kVar ? static_cast<float>(c.mu[i]) : 0;
    PairSums acc{zero4, zero4, zero4};
    // neighbours j[0..7] (their records), lanes where mask = 0 add exactly 0
    auto group = [&](const std::int32_t* j, VF mask, auto with_psum) ORTHOSIM_SPH_LAMBDA {
      VF r[8], col[8];
      for (int l = 0; l < 8; ++l) r[l] = loadf(c.pack + 8 * static_cast<std::int64_t>(j[l]));
      transpose8(r, col);
      VF dx = xi - col[0], dy = yi - col[1], dz = zi - col[2];
      if (periodic) {
        dx = minimum_image(dx, per[0]);
        dy = minimum_image(dy, per[1]);
        dz = minimum_image(dz, per[2]);
      }
      const VF dvx = vxi - col[4], dvy = vyi - col[5], dvz = vzi - col[6], irj = col[7];
      VF visc;  // 2 mu / (rho_i rho_j) with the lattice scale
      if constexpr (kVar) {
        auto mu = [&](int l) { return static_cast<float>(c.mu[j[l]]); };
        const VF muj = {mu(0), mu(1), mu(2), mu(3), mu(4), mu(5), mu(6), mu(7)};
        visc = (k.vscale * (mui + muj)) * (iri * irj);
      } else {
        visc = k.two_mu * (iri * irj);
      }
      const VF r2 = dx * dx + dy * dy + dz * dz;
      const VF q = vsqrt(r2) * k.invH;
      VF t = 1 - q;
      t = t > 0 ? t * mask : zero;
      const VF gw = t * t * t;
      const VF vr = dvx * dx + dvy * dy + dvz * dz;
      const VF ie = 1 / (r2 + k.eta2);
      const VF piv = vr < 0 ? (-k.avc) * vr * ie * (iri + irj) : zero;
      const VF A = gw * (Pi + col[3] + piv);
      const VF B = gw * r2 * ie * visc;
      add_wide(acc.ax, A * dx - B * dvx);
      add_wide(acc.ay, A * dy - B * dvy);
      add_wide(acc.az, A * dz - B * dvz);
      if constexpr (decltype(with_psum)::value) {  // p_j W_ij, p_j = P_j rho_j^2 / gs (the 1 / gs below)
        const VF t2 = t * t;
        add_wide(psum, col[3] / (irj * irj) * (t2 * t2 * (1 + 4 * q)));
      }
    };
    using Yes = std::true_type;
    using No = std::false_type;
    // over the list, 8 at a time (padded with i: the self term is exactly 0)
    const std::int32_t cnt = c.count[i];
    const std::int32_t* list = list_of(c, i);
    if (shepard)
      for (std::int32_t b = 0; b < cnt; b += 8) group(list + b, (lane + b) < cnt ? one : zero, Yes{});
    else
      for (std::int32_t b = 0; b < cnt; b += 8) group(list + b, (lane + b) < cnt ? one : zero, No{});
    const Real m = f.mass * Real(210) / (kPi * f.H * f.H * f.H * f.H * f.H);
    c.ax[i] = m * hsum(acc.ax);
    c.ay[i] = m * hsum(acc.ay);
    c.az[i] = m * hsum(acc.az);
    if (shepard) c.psum[i] = hsum(psum) / f.gradient_scale;
  }
}

ORTHOSIM_SPH_CLONES
void force_cell(const Pass& c, const NeighbourGrid::Piece& piece) { force_cell_impl<false>(c, piece); }
ORTHOSIM_SPH_CLONES
void force_cell_var(const Pass& c, const NeighbourGrid::Piece& piece) { force_cell_impl<true>(c, piece); }

// Carreau viscosity of every particle of the cell from its shear rate
// sqrt(2 D:D), D = (A + A^T) / 2 and A the velocity gradient
//   A = [sum_j V_j w_ij (v_i - v_j) d^T] [sum_j V_j w_ij d d^T]^-1,
// d = x_i - x_j, w_ij = 210 / (pi H^5) (1 - q)^3 (so grad_i W_ij = -w_ij d): the
// renormalised SPH gradient, exact for a linear velocity field also where the
// neighbourhood is cut by a wall or a free surface (where the moment matrix
// is near singular, the lattice-calibrated sum is used instead).
void shear_viscosity_cell(const Pass& c, const NeighbourGrid::Piece& piece) {
  const Fluid& f = *c.f;
  const Real invH = 1 / f.H, G = f.mass * Real(210) / (kPi * f.H * f.H * f.H * f.H * f.H);
  const bool periodic = c.period[0] > 0 || c.period[1] > 0 || c.period[2] > 0;
  for (std::int32_t i = piece.begin; i < piece.end; ++i) {
    // M = sum w d d^T (symmetric: 6 sums), A = sum w (v_i - v_j) d^T (9 sums)
    Real m00 = 0, m01 = 0, m02 = 0, m11 = 0, m12 = 0, m22 = 0;
    Real a[3][3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}};
    const Real xi = c.x[i], yi = c.y[i], zi = c.z[i], vxi = c.vx[i], vyi = c.vy[i], vzi = c.vz[i];
    auto add = [&](std::int32_t j) {
      Real d[3] = {xi - c.x[j], yi - c.y[j], zi - c.z[j]};
      if (periodic)
        for (int k = 0; k < 3; ++k)
          if (c.period[k] > 0) d[k] -= c.period[k] * std::round(d[k] / c.period[k]);
      const Real r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
      if (!(r2 < f.H * f.H) || r2 == 0) return;
      const Real t = 1 - std::sqrt(r2) * invH, w = G * c.ir[j] * t * t * t;
      m00 += w * d[0] * d[0], m01 += w * d[0] * d[1], m02 += w * d[0] * d[2];
      m11 += w * d[1] * d[1], m12 += w * d[1] * d[2], m22 += w * d[2] * d[2];
      const Real dv[3] = {w * (vxi - c.vx[j]), w * (vyi - c.vy[j]), w * (vzi - c.vz[j])};
      for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k) a[r][k] += dv[r] * d[k];
    };
    const std::int32_t cnt = c.count[i];
    const std::int32_t* list = list_of(c, i);
    for (std::int32_t b = 0; b < cnt; ++b) add(list[b]);
    Eigen::Matrix3d M, A;
    M << m00, m01, m02, m01, m11, m12, m02, m12, m22;
    A << a[0][0], a[0][1], a[0][2], a[1][0], a[1][1], a[1][2], a[2][0], a[2][1], a[2][2];
    const Real det = M.determinant(), scale = M.trace() / 3;
    const Eigen::Matrix3d grad = scale > 0 && det > 1e-3 * scale * scale * scale ? Eigen::Matrix3d(A * M.inverse())
                                                                              : Eigen::Matrix3d(f.gradient_scale * A);
    const Eigen::Matrix3d D = 0.5 * (grad + grad.transpose());
    c.mu[i] = carreau_viscosity(f.params.carreau, std::sqrt(2 * D.squaredNorm()));
  }
}

// Wall share of the kernel sum over all contacts, sum_w f0(d_w / H). The
// plain sum counts the sites beyond two walls twice; on the rest lattice in
// a right-angled corner that overlap is ~2 % of the kernel sum, far less than
// the product rule 1 - prod(1 - f0) removes (~9 %).
// cached: the triangle contacts are in cache already (else queried and stored).
Real wall_fraction(const Fluid& f, const Walls& w, const Vec3& p, Real tau, Contact* cache, bool cached,
                   const std::int32_t* hints) {
  Real sum = 0;
  w.contacts(p, tau, [&](const Contact& c) { sum += WallTables::at(f.walls.f0, f.walls.n, c.d / f.H); }, cache, cached,
             hints);
  return sum;
}

// Reaction record of a moving surface: surface, triangle, weights, force (N).
struct Reaction {
  std::int32_t particle, surface, tri;
  Real w0, w1, w2;
  Vec3 force;
};

// Semi-analytic wall acceleration of particle i (m/s^2) and the reactions.
//   pressure: the symmetric pair term with the wall's sites, whose pressure is
//     extrapolated from the fluid (Adami, Hu & Adams, JCP 231, 2012):
//     p_w(z) = pbar_i - rho_i (g . n) z, pbar_i the Shepard average of the
//     neighbours' pressure, so
//     a = max(0, (p_i + pbar_i) g0 / (H rho_i) - (g . n) g1) n
//     (p_w = p_i, a plain mirror, pumps energy near walls: not used)
//   artificial viscosity with the mirrored sites (see WallTables::av)
//   no-slip viscosity (Morris et al. 1997 ghost velocities, summed):
//     a = 2 mu / rho_i vm / H^2 (v_i - u)
template <class Pw, class Sink>
Vec3 wall_acceleration(const Fluid& f, const Walls& w, const Vec3& p, const Vec3& v, Real rho, Real pr, Real mu, Pw&& pw_fn,
                       Real tau, Sink&& reaction, Contact* cache) {
  Vec3 total;
  Real pw = -1;
  const Vec3 g = vec(f.params.gravity);
  w.contacts(p, tau, [&](const Contact& c) {
    const Real q = c.d / f.H;
    if (pw < 0) pw = pw_fn();
    const Real an = (pr + pw) * WallTables::at(f.walls.g0, f.walls.n, q) / (f.H * rho) -
                    dot(g, c.n) * WallTables::at(f.walls.g1, f.walls.n, q);
    Vec3 a = std::max(Real(0), an) * c.n;
    // artificial viscosity with the mirrored particles (velocity reflected
    // in the wall), for approaching particles: a = -2 alpha c0 h v_n av / H^2 n
    const Real vn = dot(v - c.u, c.n);
    if (vn < 0 && f.params.artificial_viscosity > 0)
      a += (-2 * f.params.artificial_viscosity * f.c0 * f.h * vn * WallTables::at(f.walls.av, f.walls.n, q) / (f.H * f.H)) * c.n;
    if (!c.wall->slip && mu > 0) a += (2 * mu / rho * WallTables::at(f.walls.vm, f.walls.n, q) / (f.H * f.H)) * (v - c.u);
    total += a;
    if (c.surface >= 0) reaction(c, a);
  }, cache, cache != nullptr);
  return total;
}

// Shepard average of the fluid pressure around particle i (Adami, Hu &
// Adams 2012): sum_j p_j W_ij / sum_j W_ij, self included, from the sums of
// the two passes.
inline Real shepard_pressure(const Pass& c, std::int32_t i) {
  const Real den = c.ksum[i];
  return den > 0 ? std::max(Real(0), (c.psum[i] + c.p[i]) / den) : c.p[i];
}

// Projection of a particle out of a wall with restitution and friction.
// Returns the velocity change; x and v are updated.
struct Hit {
  bool hit = false;
  Vec3 dv;
};
Hit collide(Vec3& x, Vec3& v, const Vec3& n, Real s, Real dmin, const Vec3& u, const WallParams& wall) {
  if (!(s < dmin)) return {};
  x += (dmin - s) * n;
  const Vec3 rel = v - u;
  const Real vn = dot(rel, n);
  Vec3 out = v;
  if (vn < 0) {
    const Vec3 vt = rel - vn * n;
    const Real vtn = norm(vt);
    const Real dvt = std::min(wall.friction * (1 + wall.restitution) * (-vn), vtn);
    const Vec3 vt2 = vtn > 0 ? (1 - dvt / vtn) * vt : vt;
    out = u + vt2 - wall.restitution * vn * n;
  }
  const Vec3 dv = out - v;
  v = out;
  return {true, dv};
}

// Removal reasons in FluidScratch::dead.
constexpr std::uint8_t kAlive = 0, kLeft = 1, kNonfinite = 2, kDrained = 3;  // kDrained + drain index

// ---- the solver's internals -----------------------------------------------------

struct Stepper {
  const Fluid& f;
  FluidState& s;
  const FluidBoundaries& b;
  Walls walls;
  Real dt = 0;  // the whole step (for the reaction forces' mean)
  std::array<bool, 3> periodic{};

  Stepper(const Fluid& f_, FluidState& s_, const FluidBoundaries& b_, Real dt_) : f(f_), s(s_), b(b_), dt(dt_) {
    walls.b = &b;
    walls.H = f.H;
    for (const FluidMesh& m : b.meshes)
      walls.meshes.push_back({m.vertices.data(), nullptr, m.triangles.data(),
                              static_cast<std::int32_t>(m.vertices.size() / 3),
                              static_cast<std::int32_t>(m.triangles.size() / 3)});
    walls.surf = &s.surfaces;
    for (FluidSurface& sf : s.surfaces) {
      const bool moving = sf.v.size() == sf.x.size();
      walls.surfaces.push_back({sf.x.data(), moving ? sf.v.data() : nullptr, sf.triangles.data(),
                                static_cast<std::int32_t>(sf.x.size() / 3),
                                static_cast<std::int32_t>(sf.triangles.size() / 3)});
      if (triangle_grid_holds(walls.surfaces.back(), dt, sf.grid))
        ++sf.grid.reuses;
      else
        build_triangle_grid(walls.surfaces.back(), dt, f.H, sf.grid, f.params.surface_grid_slack * f.H);
      if (dt > 0) sf.force.assign(sf.x.size(), 0);  // a step's output; diagnostics leave it
    }
    for (int a = 0; a < 3; ++a) periodic[a] = b.faces[2 * a] == Face::periodic;
    walls.set_inner();
  }

  std::vector<Contact> contact_cache;  // (n x n_triangle_walls) of the density pass, reused by the force pass
  // The triangle contacts the drift's collision tests found at the substep's
  // end, (n_drifted x n_triangle_walls) in the drift's particle order, and
  // for each particle after compact and emit the row of its contacts, or -1
  // where a triangle wall moved it after its queries (or it is new). The next
  // density pass, at the same position and time, reads them instead of
  // querying again. Removals move the rows' indices, not the contacts.
  std::vector<Contact> end_contacts;
  std::vector<std::int32_t> end_row;
  BigLists big;                        // the full lists of the substep's overflowed particles
  bool built = true;                   // this substep sorted the particles and builds the lists (else keeps them)

  std::int32_t n() const { return static_cast<std::int32_t>(s.id.size()); }

  // The substep's particle order and neighbour lists: kept from the last
  // build where they still hold (lists_hold), else sorted and built afresh.
  void prepare() {
    if (lists_hold()) {
      built = false;
      ++s.counters.list_reuses;
      // the single-precision positions (relative to the build's grid origin) at the new positions
      FluidScratch& sc = s.scratch;
      const std::array<Real, 3> o = sc.grid.origin;
      tbb::parallel_for(tbb::blocked_range<std::int32_t>(0, n(), 2048), [&](const auto& r) {
        for (int k = 0; k < 3; ++k) {
          const Real* x = s.x[k].data();
          float* xf = sc.xf[k].data();
          for (std::int32_t i = r.begin(); i < r.end(); ++i) xf[i] = static_cast<float>(x[i] - o[k]);
        }
      });
    } else {
      sort();
    }
  }

  // The last build's lists hold every pair within H while the particles are
  // the same ones in the same order and none has moved more than half the
  // skin since: a pair left out was at least (1 + skin) H apart then (the
  // grid's cells are that wide, the search reaches 1.005 (1 + skin) H), and
  // two displacements below skin / 2 cannot bring it within H.
  bool lists_hold() const {
    const FluidScratch& sc = s.scratch;
    const Real skin = f.params.neighbour_skin * f.H;
    if (!sc.list_reusable || !(sc.list_skin > 0) || sc.list_skin != skin || sc.list_H != f.H) return false;
    for (int a = 0; a < 3; ++a)
      if (sc.grid.period[a] != (periodic[a] ? b.hi[a] - b.lo[a] : 0)) return false;
    if (sc.list_id != s.id) return false;
    const std::int32_t np = n();
    const Real* x0[3] = {sc.list_x[0].data(), sc.list_x[1].data(), sc.list_x[2].data()};
    const Real d2 = tbb::parallel_reduce(
        tbb::blocked_range<std::int32_t>(0, np, 2048), Real(0),
        [&](const tbb::blocked_range<std::int32_t>& r, Real m) {
          for (std::int32_t i = r.begin(); i < r.end(); ++i) {
            const Real dx = s.x[0][i] - x0[0][i], dy = s.x[1][i] - x0[1][i], dz = s.x[2][i] - x0[2][i];
            const Real q = dx * dx + dy * dy + dz * dz;
            m = q > m || q != q ? q : m;  // a NaN fails the test below
          }
          return m;
        },
        [](Real a, Real b2) { return a > b2 || a != a ? a : b2; });
    return d2 < Real(0.25) * skin * skin;
  }

  // counting sort into cell order; every particle array permuted alike
  void sort() {
    const std::int32_t np = n();
    NeighbourGrid& g = s.scratch.grid;
    built = true;
    ++s.counters.list_builds;
    // the skin, unless it cannot pay: particles came or went since the last
    // build (an emitter or a drain at work: the next substep rebuilds
    // anyway), or the fastest particle moved more than a quarter of the skin
    // over the last substep (the lists would not outlast two substeps)
    const Real full = f.params.neighbour_skin * f.H;
    const Real skin = s.scratch.set_changed || s.scratch.substep_motion > full / 4 ? 0 : full;
    build_neighbour_grid(s.x[0].data(), s.x[1].data(), s.x[2].data(), np, f.H + skin, b.lo, b.hi, periodic, g);
    // one pass permutes positions, velocities and ids into cell order and
    // makes the single-precision positions (relative to the grid origin, 8
    // entries of padding far away); rho and p are not permuted: the density
    // pass overwrites them for every particle before anything reads them
    FluidScratch& sc = s.scratch;
    const std::size_t nz = static_cast<std::size_t>(np);
    Real* src[6];
    Real* dst[6];
    float* xf[3];
    for (int k = 0; k < 3; ++k) {
      sc.perm[k].resize(nz);
      sc.perm[3 + k].resize(nz);
      src[k] = s.x[k].data(), src[3 + k] = s.v[k].data();
      dst[k] = sc.perm[k].data(), dst[3 + k] = sc.perm[3 + k].data();
      sc.xf[k].resize(nz + 8);
      std::fill(sc.xf[k].begin() + np, sc.xf[k].end(), 1e30f);
      xf[k] = sc.xf[k].data();
    }
    auto& tid = sc.tmp_id;
    tid.resize(nz);
    // the collision tests' first guesses travel with their particles
    const std::size_t ntw = walls.n_triangle_walls();
    auto& hint = sc.wall_hint;
    if (hint.size() != nz * ntw) hint.assign(nz * ntw, -1);
    sc.tmp_hint.resize(nz * ntw);
    const std::int32_t* hold = hint.data();
    std::int32_t* hnew = sc.tmp_hint.data();
    const std::int32_t* order = g.order.data();
    const std::array<Real, 3> o = g.origin;
    tbb::parallel_for(tbb::blocked_range<std::int32_t>(0, np, 1024), [&](const auto& r) {
      for (std::int32_t k = r.begin(); k < r.end(); ++k) {
        const std::int32_t j = order[k];
        for (int a = 0; a < 6; ++a) dst[a][k] = src[a][j];
        for (int a = 0; a < 3; ++a) xf[a][k] = static_cast<float>(src[a][j] - o[a]);
        tid[k] = s.id[j];
        for (std::size_t w = 0; w < ntw; ++w) hnew[static_cast<std::size_t>(k) * ntw + w] = hold[static_cast<std::size_t>(j) * ntw + w];
      }
    });
    hint.swap(sc.tmp_hint);
    for (int k = 0; k < 3; ++k) {
      s.x[k].swap(sc.perm[k]);
      s.v[k].swap(sc.perm[3 + k]);
    }
    s.id.swap(tid);
    s.rho.resize(nz);
    s.p.resize(nz);
    sc.list_H = f.H;
    sc.list_skin = skin;
    sc.list_reusable = skin > 0;  // until a list overflows (density)
    sc.set_changed = false;
    if (skin > 0) {
      for (int k = 0; k < 3; ++k) sc.list_x[k] = s.x[k];
      sc.list_id = s.id;
    }
  }

  Pass pass(Real tau) {
    FluidScratch& sc = s.scratch;
    const std::size_t np = static_cast<std::size_t>(n());
    sc.near.resize(np);
    sc.psum.resize(np);
    sc.inv_rho.resize(np);
    sc.neighbours.resize(np);
    sc.ksum.resize(np);
    sc.count.resize(np);
    if (sc.list.size() < np * kListStride) grow_scratch(sc.list, np * kListStride);
    for (int k = 0; k < 3; ++k) {
      sc.a[k].resize(np);
      sc.aw[k].resize(np);
    }
    Pass c;
    c.f = &f;
    c.g = &sc.grid;
    c.walls = &walls;
    c.n = n();
    c.x = s.x[0].data(), c.y = s.x[1].data(), c.z = s.x[2].data();
    c.vx = s.v[0].data(), c.vy = s.v[1].data(), c.vz = s.v[2].data();
    c.rho = s.rho.data(), c.p = s.p.data(), c.near = sc.near.data(), c.psum = sc.psum.data(), c.ir = sc.inv_rho.data(), c.nb = sc.neighbours.data();
    grow_scratch(sc.pack, 8 * np);
    c.pack = sc.pack.data();
    if (f.params.rheology == Rheology::carreau) {
      sc.mu.resize(np);
      c.mu = sc.mu.data();
    }
    c.ksum = sc.ksum.data(), c.list = sc.list.data(), c.count = sc.count.data();
    c.big = &big;
    c.period = sc.grid.period;
    c.ax = sc.a[0].data(), c.ay = sc.a[1].data(), c.az = sc.a[2].data();
    c.wx = sc.aw[0].data(), c.wy = sc.aw[1].data(), c.wz = sc.aw[2].data();
    c.xf = sc.xf[0].data(), c.yf = sc.xf[1].data(), c.zf = sc.xf[2].data();
    c.origin = sc.grid.origin;
    const Real reach = 1.005 * (f.H + sc.list_skin);
    c.search_r2 = static_cast<float>(reach * reach);
    c.tau = tau;
    walls.frames_at(tau);
    return c;
  }

  // rho_i = m W-sum + rho0 * wall share; p from the EOS. Returns max compression.
  Real density(const Pass& c) {
    const auto& pieces = c.g->pieces;
    const Real mk = f.mass * Real(21) / (2 * kPi * f.H * f.H * f.H);
    const Real rho0 = f.params.rest_density;
    const int gamma = f.params.tait_gamma;
    const bool clamp = f.params.clamp_negative_pressure;
    const bool pci = f.params.pressure_solver == PressureSolver::pcisph;
    const std::size_t ntw = walls.n_triangle_walls();  // the triangle contacts are cached for the force pass
    contact_cache.resize(ntw * static_cast<std::size_t>(c.n));
    // the last drift's contacts, by the particles' order before the sort
    const bool reuse = ntw > 0 && f.params.reuse_wall_contacts && end_row.size() == static_cast<std::size_t>(c.n);
    if (reuse) {
      std::int64_t k = 0;
      for (const std::int32_t r : end_row) k += r >= 0;
      s.counters.contacts_reused += k;
    }
    const std::int32_t* order = built ? c.g->order.data() : nullptr;  // kept lists: the drift's order
    if (built) big.reset(static_cast<std::size_t>(c.n));
    const Real worst = tbb::parallel_reduce(
        tbb::blocked_range<std::size_t>(0, pieces.size(), kPieceGrain), Real(-HUGE_VAL),
        [&](const tbb::blocked_range<std::size_t>& r, Real best) {
          for (std::size_t k = r.begin(); k < r.end(); ++k) {
            const NeighbourGrid::Piece& piece = pieces[k];
            density_cell(c, piece, built);
            for (std::int32_t i = piece.begin; i < piece.end; ++i) {
              const Vec3 p{c.x[i], c.y[i], c.z[i]};
              Contact* cache = ntw > 0 ? contact_cache.data() + static_cast<std::size_t>(i) * ntw : nullptr;
              const std::int32_t* hint = ntw > 0 ? s.scratch.wall_hint.data() + static_cast<std::size_t>(i) * ntw : nullptr;
              const bool near = walls.maybe_near(p);
              c.near[i] = near;
              const std::int32_t row = reuse && near ? end_row[static_cast<std::size_t>(order ? order[i] : i)] : -1;
              const bool cached = row >= 0;
              if (cached) std::copy_n(end_contacts.data() + static_cast<std::size_t>(row) * ntw, ntw, cache);
              const Real rho =
                  mk * c.ksum[i] + (near ? rho0 * wall_fraction(f, walls, p, c.tau, cache, cached, hint) : Real(0));
              Real pr = pci ? 0 : eos_pressure(f.eos, rho, rho0, f.c0, gamma);  // pcisph: its solver starts from 0
              if (clamp) pr = std::max(Real(0), pr);
              c.rho[i] = rho;
              c.p[i] = pr;
              c.ir[i] = 1 / rho;
              float* pk = c.pack + 8 * static_cast<std::int64_t>(i);
              pk[0] = c.xf[i], pk[1] = c.yf[i], pk[2] = c.zf[i], pk[3] = static_cast<float>(f.gradient_scale * pr / (rho * rho));
              pk[4] = static_cast<float>(c.vx[i]), pk[5] = static_cast<float>(c.vy[i]), pk[6] = static_cast<float>(c.vz[i]);
              pk[7] = static_cast<float>(c.ir[i]);
              best = std::max(best, rho / rho0 - 1);
            }
          }
          return best;
        },
        [](Real a, Real b2) { return std::max(a, b2); });
    if (built && big.used) s.scratch.list_reusable = false;  // the full lists live in this Stepper only
    return worst;
  }

  // accelerations (pair + walls); returns (max |a|^2, max |v|^2) and the reactions.
  // shear: the Carreau viscosities first (pcisph's corrections keep the velocities, so
  // they keep their viscosities too)
  std::array<Real, 2> forces(const Pass& c, std::vector<Reaction>& reactions, bool shear = true) {
    const auto& pieces = c.g->pieces;
    if (c.mu && shear)
      tbb::parallel_for(tbb::blocked_range<std::size_t>(0, pieces.size(), kPieceGrain), [&](const tbb::blocked_range<std::size_t>& r) {
        for (std::size_t k = r.begin(); k < r.end(); ++k) shear_viscosity_cell(c, pieces[k]);
      });
    tbb::enumerable_thread_specific<std::vector<Reaction>> local;
    const Vec3 g = vec(f.params.gravity);
    const bool any_surface = !walls.surfaces.empty();
    const std::size_t ntw = walls.n_triangle_walls();
    auto res = tbb::parallel_reduce(
        tbb::blocked_range<std::size_t>(0, pieces.size(), kPieceGrain), std::array<Real, 2>{0, 0},
        [&](const tbb::blocked_range<std::size_t>& r, std::array<Real, 2> best) {
          std::vector<Reaction>* rec = any_surface ? &local.local() : nullptr;
          for (std::size_t k = r.begin(); k < r.end(); ++k) {
            const NeighbourGrid::Piece& piece = pieces[k];
            if (c.mu)
              force_cell_var(c, piece);
            else
              force_cell(c, piece);
            for (std::int32_t i = piece.begin; i < piece.end; ++i) {
              const Vec3 p{c.x[i], c.y[i], c.z[i]}, v{c.vx[i], c.vy[i], c.vz[i]};
              const auto pw = [&] { return shepard_pressure(c, i); };
              const Vec3 aw = !walls.maybe_near(p) ? Vec3{}
                              : wall_acceleration(f, walls, p, v, c.rho[i], c.p[i], c.mu ? c.mu[i] : f.params.viscosity, pw, c.tau,
                                                  [&](const Contact& ct, const Vec3& a) {
                                  rec->push_back({i, ct.surface, ct.tri, ct.w0, ct.w1, ct.w2, -f.mass * a});
                                }, ntw > 0 ? contact_cache.data() + static_cast<std::size_t>(i) * ntw : nullptr);
              c.wx[i] = aw.x, c.wy[i] = aw.y, c.wz[i] = aw.z;
              c.ax[i] += aw.x, c.ay[i] += aw.y, c.az[i] += aw.z;
              const Vec3 at{c.ax[i] + g.x, c.ay[i] + g.y, c.az[i] + g.z};
              const Real a2 = dot(at, at), v2 = dot(v, v);
              // a NaN never raises the maxima (NaN comparisons are false); the particle is removed in the drift
              if (a2 > best[0]) best[0] = a2;
              if (v2 > best[1]) best[1] = v2;
            }
          }
          return best;
        },
        [](std::array<Real, 2> a, std::array<Real, 2> b2) {
          return std::array<Real, 2>{std::max(a[0], b2[0]), std::max(a[1], b2[1])};
        });
    if (any_surface) {
      for (auto& v : local) reactions.insert(reactions.end(), v.begin(), v.end());
      std::sort(reactions.begin(), reactions.end(), [](const Reaction& a, const Reaction& b2) {
        return a.particle != b2.particle ? a.particle < b2.particle : a.surface < b2.surface;
      });
    }
    return res;
  }

  // the substep limit and which one it is (FluidCounters::substep_limit's index);
  // pcisph: without the sound speed (the force limit sees the accelerations
  // without pressure), and at most the substep its solver asked for last (fluid_step)
  std::pair<Real, int> limit(const std::array<Real, 2>& maxima) const {
    const bool pci = f.params.pressure_solver == PressureSolver::pcisph;
    const Real vmax = std::sqrt(maxima[1]), amax = std::sqrt(maxima[0]);
    const Real speed = (pci ? 0 : f.c0) + vmax;
    Real h = speed > 0 ? f.params.cfl * f.h / speed : HUGE_VAL;
    int which = 1;
    auto take = [&](Real l, int k) {
      if (l < h) h = l, which = k;
    };
    if (amax > 0) take(f.params.force_cfl * std::sqrt(f.h / amax), 2);
    take(f.viscous_limit, 3);
    if (f.params.max_substep > 0) take(f.params.max_substep, 4);
    if (pci && s.pressure_substep > 0) take(s.pressure_substep, 5);
    return {h, which};
  }

  // pcisph: the pass's pressures (and their pack entries) back to 0
  void zero_pressure(const Pass& c) {
    tbb::parallel_for(tbb::blocked_range<std::int32_t>(0, c.n, 4096), [&](const auto& r) {
      for (std::int32_t i = r.begin(); i < r.end(); ++i) {
        c.p[i] = 0;
        c.pack[8 * static_cast<std::int64_t>(i) + 3] = 0;
      }
    });
  }

  // pcisph (PressureSolver): corrects the pass's pressures (0 on entry, with
  // the pass's accelerations at those) for a substep of h until the largest
  // predicted compression is within the tolerance. Leaves the accelerations of
  // the last pressures in the pass, with their reactions; sets the corrections
  // made, the last predicted compression and the first (without pressure), and
  // whether the particle of the last one was compressed beyond the tolerance
  // at the substep's start. Stops early, stalled, where the largest
  // predicted compression has repeated itself every second correction
  // (within 1e-3 of itself) pcisph_stall_repeats times in a row: a particle whose
  // response to its own pressure is more than twice the lattice's (delta's)
  // overshoots, and with the clamp at 0 it cycles between two states (seen
  // beside the two-sided tissue surface of the physical-mode bleeding scene);
  // more corrections change nothing. (A solve still building its pressure
  // changes its largest compression from one correction to the next.)
  void pcisph(const Pass& c, Real h, std::vector<Reaction>& reactions, int* iterations, Real* compression, Real* first,
              bool* compressed_before, bool* stalled) {
    const std::int32_t np = c.n;
    FluidScratch& sc = s.scratch;
    for (int k = 0; k < 3; ++k) sc.pred[k].resize(static_cast<std::size_t>(np));
    sc.pred_sum.resize(static_cast<std::size_t>(np));
    Real* px = sc.pred[0].data();
    Real* py = sc.pred[1].data();
    Real* pz = sc.pred[2].data();
    const FluidParams& fp = f.params;
    const Real rho0 = fp.rest_density;
    // the pressure a full neighbourhood needs for a compression rho* - rho0 in one substep
    const Real delta = rho0 * rho0 / (2 * h * h * f.mass * f.mass * f.gradient_scale * f.lattice_grad2);
    const Real mk = f.mass * Real(21) / (2 * kPi * f.H * f.H * f.H);
    const Vec3 g = vec(fp.gravity);
    const Real damp = 1 / (1 + fp.damping * h);
    const std::size_t ntw = walls.n_triangle_walls();
    int it = 0, repeats = 0;
    Real err = 0, back1 = HUGE_VAL, back2 = HUGE_VAL;  // the last two errors
    *stalled = false;
    for (;;) {
      // positions as the drift would move them, the walls' projections aside
      tbb::parallel_for(tbb::blocked_range<std::int32_t>(0, np, 1024), [&](const auto& r) {
        for (std::int32_t i = r.begin(); i < r.end(); ++i) {
          const Vec3 v = damp * (Vec3{c.vx[i], c.vy[i], c.vz[i]} + h * (Vec3{c.ax[i], c.ay[i], c.az[i]} + g));
          px[i] = c.x[i] + h * v.x, py[i] = c.y[i] + h * v.y, pz[i] = c.z[i] + h * v.z;
        }
      });
      // density there (over the substep's lists: a pair that comes within H
      // meanwhile adds W ~ 0), the pressure's correction
      const auto& pieces = c.g->pieces;
      Real* sums = sc.pred_sum.data();
      // the largest predicted compression, and its particle (the lowest index of a tie)
      using Worst = std::pair<Real, std::int32_t>;
      auto worse = [](const Worst& a, const Worst& b2) { return a.first != b2.first ? a.first > b2.first : a.second < b2.second; };
      const Worst worst = tbb::parallel_reduce(
          tbb::blocked_range<std::size_t>(0, pieces.size(), kPieceGrain), Worst{-HUGE_VAL, -1},
          [&](const tbb::blocked_range<std::size_t>& r, Worst best) {
            for (std::size_t k = r.begin(); k < r.end(); ++k) {
              const NeighbourGrid::Piece& piece = pieces[k];
              predicted_sum_cell(c, px, py, pz, piece, sums);
              for (std::int32_t i = piece.begin; i < piece.end; ++i) {
                const Vec3 p{px[i], py[i], pz[i]};
                Real rho = mk * sums[i];
                if (walls.maybe_near(p)) {
                  // box faces and planes at the predicted position; a triangle wall
                  // by the substep's contact (the density pass's), its distance moved
                  // along the contact normal by the particle's and the wall's motion
                  // (the closest triangle kept over the substep, in which a particle
                  // moves at most cfl H / 2)
                  const Vec3 moved = p - Vec3{c.x[i], c.y[i], c.z[i]};
                  Real share = 0;
                  walls.contacts(p, c.tau, [&](const Contact& w) {
                    const Real d = w.tri >= 0 ? std::max(Real(0), w.d + dot(moved - h * w.u, w.n)) : w.d;
                    share += WallTables::at(f.walls.f0, f.walls.n, d / f.H);
                  }, ntw > 0 ? contact_cache.data() + static_cast<std::size_t>(i) * ntw : nullptr, true);
                  rho += rho0 * share;
                }
                const Real pr = std::max(Real(0), c.p[i] + delta * (rho - rho0));
                c.p[i] = pr;
                c.pack[8 * static_cast<std::int64_t>(i) + 3] = static_cast<float>(f.gradient_scale * pr * c.ir[i] * c.ir[i]);
                const Worst here{rho / rho0 - 1, i};
                if (worse(here, best)) best = here;
              }
            }
            return best;
          },
          [&](const Worst& a, const Worst& b2) { return worse(a, b2) ? a : b2; });
      err = worst.first;
      // compressed beyond the tolerance already at the substep's start: a shorter
      // substep cannot bring it back within it
      *compressed_before = worst.second >= 0 && c.rho[worst.second] / rho0 - 1 > fp.pcisph_tolerance;
      if (it == 0) *first = err;
      repeats = std::abs(err - back2) <= Real(1e-3) * std::abs(err) ? repeats + 1 : 0;
      back2 = back1, back1 = err;
      ++it;
      reactions.clear();
      forces(c, reactions, false);
      if ((err <= fp.pcisph_tolerance && it >= fp.pcisph_min_iterations) || it >= fp.pcisph_max_iterations) break;
      if (fp.pcisph_stall_repeats > 0 && repeats >= fp.pcisph_stall_repeats) {
        *stalled = true;
        break;
      }
    }
    *iterations = it;
    *compression = err;
  }

  void add_reaction(const Reaction& r, Real weight) {
    FluidSurface& sf = s.surfaces[static_cast<std::size_t>(r.surface)];
    const Real w[3] = {r.w0, r.w1, r.w2};
    for (int k = 0; k < 3; ++k) {
      const std::int32_t vtx = sf.triangles[3 * static_cast<std::size_t>(r.tri) + k];
      sf.force[3 * vtx] += weight * w[k] * r.force.x;
      sf.force[3 * vtx + 1] += weight * w[k] * r.force.y;
      sf.force[3 * vtx + 2] += weight * w[k] * r.force.z;
    }
  }

  // symplectic Euler kick and drift, walls, domain, drains. Returns (removed, collisions).
  std::array<std::int64_t, 2> integrate(Real h, Real tau, std::vector<Reaction>& impulses) {
    const std::int32_t np = n();
    FluidScratch& sc = s.scratch;
    sc.dead.assign(np, kAlive);
    const std::size_t ntw = walls.n_triangle_walls();
    if (sc.wall_hint.size() != static_cast<std::size_t>(np) * ntw) sc.wall_hint.assign(static_cast<std::size_t>(np) * ntw, -1);
    walls.frames_at(tau + h);
    end_contacts.resize(static_cast<std::size_t>(np) * ntw);
    end_row.assign(ntw > 0 ? static_cast<std::size_t>(np) : 0, -1);
    const Vec3 g = vec(f.params.gravity);
    const Real damp = 1 / (1 + f.params.damping * h);
    const Real dmin = f.params.collision_distance * f.params.spacing;
    const bool any_surface = !walls.surfaces.empty();
    tbb::enumerable_thread_specific<std::vector<Reaction>> local;
    auto res = tbb::parallel_reduce(
        tbb::blocked_range<std::int32_t>(0, np, 1024), std::array<std::int64_t, 2>{0, 0},
        [&](const tbb::blocked_range<std::int32_t>& r, std::array<std::int64_t, 2> cnt) {
          for (std::int32_t i = r.begin(); i < r.end(); ++i) {
            Vec3 v{s.v[0][i], s.v[1][i], s.v[2][i]};
            const Vec3 x0{s.x[0][i], s.x[1][i], s.x[2][i]};
            v = damp * (v + h * (Vec3{sc.a[0][i], sc.a[1][i], sc.a[2][i]} + g));
            Vec3 x = x0 + h * v;
            if (!finite(x) || !finite(v)) {
              sc.dead[i] = kNonfinite;
              ++cnt[0];
              continue;
            }
            // periodic wrap
            Real* xc[3] = {&x.x, &x.y, &x.z};
            for (int a = 0; a < 3; ++a) {
              if (!periodic[a]) continue;
              const Real L = b.hi[a] - b.lo[a];
              if (*xc[a] < b.lo[a]) *xc[a] += L;
              else if (*xc[a] >= b.hi[a]) *xc[a] -= L;
              if (!(*xc[a] >= b.lo[a] && *xc[a] < b.hi[a])) *xc[a] = b.lo[a];  // rounding at hi
            }
            // box faces and planes: signed distance s along the inward normal
            const Real q[3] = {x.x, x.y, x.z};
            for (int a = 0; a < 3; ++a)
              for (int side = 0; side < 2; ++side) {
                if (b.faces[2 * a + side] != Face::wall) continue;
                Real nn[3] = {0, 0, 0};
                nn[a] = side == 0 ? 1 : -1;
                const Real sd = side == 0 ? q[a] - b.lo[a] : b.hi[a] - q[a];
                if (collide(x, v, {nn[0], nn[1], nn[2]}, sd, dmin, {}, b.box_wall).hit) ++cnt[1];
              }
            for (const FluidPlane& pl : b.planes) {
              const Vec3 n = vec(pl.normal);
              if (collide(x, v, n, dot(n, x - vec(pl.point)), dmin, {}, pl.wall).hit) ++cnt[1];
            }
            // triangle walls: the closest triangle at the new time; a two-sided
            // wall keeps the particle on the side it started the substep on
            // first guesses: the density pass's contacts at tau (same particle
            // order); the contacts found here are the next substep's
            const Contact* cached = ntw > 0 && contact_cache.size() >= (static_cast<std::size_t>(i) + 1) * ntw
                                        ? contact_cache.data() + static_cast<std::size_t>(i) * ntw
                                        : nullptr;
            std::int32_t* hint = ntw > 0 ? sc.wall_hint.data() + static_cast<std::size_t>(i) * ntw : nullptr;
            Contact* end = ntw > 0 ? end_contacts.data() + static_cast<std::size_t>(i) * ntw : nullptr;
            bool moved = false;  // by a triangle wall (after the queries before it)
            auto mesh_collide = [&](const TriangleSource& src, const TriangleGrid& grid, const WallParams& wall,
                                    bool two_sided, int surface, const TriFrame* frame, std::size_t slot) {
              Contact& ct = end[slot];  // the query fills it when it finds a contact
              const bool found = triangle_contact(src, grid, x, tau + h, f.H, wall, two_sided, ct, frame, cached ? cached[slot].tri : -1);
              hint[slot] = found ? ct.tri : -1;
              if (!found) {
                ct = Contact{};
                return;
              }
              if (surface >= 0) ct.surface = surface;  // as Walls::contacts gives it
              Vec3 face = ct.face;
              Real sd;
              if (two_sided) {
                // side of the start position relative to the same triangle at the substep's start
                const Vec3 a0 = src.vertex(ct.tri, 0, tau), b0 = src.vertex(ct.tri, 1, tau), c0 = src.vertex(ct.tri, 2, tau);
                Vec3 fn = cross(b0 - a0, c0 - a0);
                fn = (1 / norm(fn)) * fn;
                const Real side = dot(x0 - a0, fn) >= 0 ? 1 : -1;
                const Vec3 fnew = dot(ct.face, fn) * side >= 0 ? ct.face : -ct.face;  // same side as the start
                face = fnew;
                sd = dot(x - ct.c, face);
              } else {
                sd = dot(x - ct.c, face);
              }
              Vec3 n = face;
              if (sd >= 0) {  // on the right side: keep at least dmin from the closest point
                if (!(ct.d < dmin)) return;
                n = ct.n;
                sd = ct.d;
              }
              const Hit hit = collide(x, v, n, sd, dmin, ct.u, wall);
              if (hit.hit) {
                moved = true;
                ++cnt[1];
                if (surface >= 0) local.local().push_back({i, surface, ct.tri, ct.w0, ct.w1, ct.w2, (-f.mass / dt) * hit.dv});
              }
            };
            for (std::size_t m = 0; m < walls.meshes.size(); ++m)
              mesh_collide(walls.meshes[m], b.meshes[m].grid, b.meshes[m].wall, b.meshes[m].two_sided, -1, &walls.mesh_frames[m],
                           m);
            if (any_surface)
              for (std::size_t k = 0; k < walls.surfaces.size(); ++k)
                mesh_collide(walls.surfaces[k], s.surfaces[k].grid, s.surfaces[k].wall, s.surfaces[k].two_sided,
                             static_cast<int>(k), &walls.surface_frames[k], walls.meshes.size() + k);
            if (ntw > 0) end_row[static_cast<std::size_t>(i)] = moved ? -1 : i;
            // domain
            bool out = false;
            const Real q2[3] = {x.x, x.y, x.z};
            for (int a = 0; a < 3; ++a)
              if (!periodic[a] && !(q2[a] >= b.lo[a] && q2[a] <= b.hi[a])) out = true;
            if (out) {
              sc.dead[i] = kLeft;
              ++cnt[0];
            } else {
              for (std::size_t d = 0; d < s.drains.size(); ++d) {
                const FluidDrain& dr = s.drains[d];
                if (!dr.enabled) continue;
                const Vec3 rel = x - vec(dr.center);
                if (dot(rel, rel) < dr.radius * dr.radius) {
                  sc.dead[i] = static_cast<std::uint8_t>(kDrained + std::min<std::size_t>(d, 250));
                  ++cnt[0];
                  break;
                }
              }
            }
            s.v[0][i] = v.x, s.v[1][i] = v.y, s.v[2][i] = v.z;
            s.x[0][i] = x.x, s.x[1][i] = x.y, s.x[2][i] = x.z;
          }
          return cnt;
        },
        [](std::array<std::int64_t, 2> a, std::array<std::int64_t, 2> b2) {
          return std::array<std::int64_t, 2>{a[0] + b2[0], a[1] + b2[1]};
        });
    if (any_surface) {
      for (auto& v : local) impulses.insert(impulses.end(), v.begin(), v.end());
      std::sort(impulses.begin(), impulses.end(), [](const Reaction& a, const Reaction& b2) {
        return a.particle != b2.particle ? a.particle < b2.particle : a.surface < b2.surface;
      });
    }
    return res;
  }

  // stable removal of the dead particles, counting each reason
  void compact() {
    const std::int32_t np = n();
    auto& dead = s.scratch.dead;
    const std::size_t ntw = walls.n_triangle_walls();
    auto& hint = s.scratch.wall_hint;
    if (hint.size() != static_cast<std::size_t>(np) * ntw) hint.assign(static_cast<std::size_t>(np) * ntw, -1);
    FluidCounters& k = s.counters;
    for (std::int32_t i = 0; i < np; ++i) {
      const std::uint8_t d = dead[i];
      if (d == kAlive) continue;
      if (d == kLeft) {
        ++k.left_domain;
        k.lost_volume += f.volume;
      } else if (d == kNonfinite) {
        ++k.nonfinite;
        k.lost_volume += f.volume;
      } else {
        FluidDrain& dr = s.drains[d - kDrained];
        ++dr.drained;
        dr.drained_volume += f.volume;
        ++k.drained;
        k.drained_volume += f.volume;
      }
    }
    std::int32_t w = 0;
    for (std::int32_t i = 0; i < np; ++i) {
      if (dead[i] != kAlive) continue;
      if (w != i) {
        for (int a = 0; a < 3; ++a) {
          s.x[a][w] = s.x[a][i];
          s.v[a][w] = s.v[a][i];
        }
        s.rho[w] = s.rho[i];
        s.p[w] = s.p[i];
        s.id[w] = s.id[i];
        for (std::size_t t = 0; t < ntw; ++t) hint[static_cast<std::size_t>(w) * ntw + t] = hint[static_cast<std::size_t>(i) * ntw + t];
        if (end_row.size() == static_cast<std::size_t>(np)) end_row[w] = end_row[i];
      }
      ++w;
    }
    s.scratch.set_changed = true;
    hint.resize(static_cast<std::size_t>(w) * ntw);
    if (end_row.size() == static_cast<std::size_t>(np)) end_row.resize(static_cast<std::size_t>(w));
    for (int a = 0; a < 3; ++a) {
      s.x[a].resize(w);
      s.v[a].resize(w);
    }
    s.rho.resize(w);
    s.p.resize(w);
    s.id.resize(w);
  }

  // emitters advance by h; returns particles emitted
  std::int64_t emit(Real h, Real t0) {
    std::int64_t total = 0;
    const Real dx = f.params.spacing;
    for (FluidEmitter& e : s.emitters) {
      if (!e.enabled || !(t0 >= e.start && t0 < e.end) || !(e.flow_rate > 0) || !(e.radius > 0)) continue;
      Vec3 d = vec(e.direction);
      const Real dn = norm(d);
      if (!(dn > 0) || !std::isfinite(dn) || !finite3(e.center) || !std::isfinite(e.flow_rate)) continue;
      d = (1 / dn) * d;
      // an orthonormal basis of the disc
      const Vec3 axis = std::abs(d.x) < 0.9 ? Vec3{1, 0, 0} : Vec3{0, 1, 0};
      Vec3 e1 = cross(d, axis);
      e1 = (1 / norm(e1)) * e1;
      const Vec3 e2 = cross(d, e1);
      // the lattice points of the disc and their speeds
      const int m = static_cast<int>(std::floor(e.radius / dx));
      std::vector<std::array<Real, 3>> pts;  // (a, b, raw speed)
      for (int j = -m; j <= m; ++j)
        for (int i = -m; i <= m; ++i) {
          const Real a = i * dx, bb = j * dx, rr = a * a + bb * bb;
          if (rr > e.radius * e.radius) continue;
          const Real raw = e.profile == EmitterProfile::parabolic ? 1 - rr / (e.radius * e.radius) : 1;
          pts.push_back({a, bb, raw});
        }
      const Real area = kPi * e.radius * e.radius;
      const Real mean = e.flow_rate / area;
      Real raw_sum = 0;
      for (auto& p : pts) raw_sum += p[2];
      const Real np = static_cast<Real>(pts.size());
      const Real spacing_along = np * f.volume / area;  // l
      if (e.travelled.size() != pts.size()) e.travelled.assign(pts.size(), 0);
      const Vec3 c = vec(e.center);
      for (std::size_t k = 0; k < pts.size(); ++k) {
        const Real u = mean * np * pts[k][2] / raw_sum;
        e.travelled[k] += u * h;
        int guard = 0;
        while (e.travelled[k] >= spacing_along && guard++ < 1 << 16) {
          if (s.max_particles > 0 && s.size() >= s.max_particles) {
            e.travelled[k] = std::min(e.travelled[k], spacing_along);  // held back: one particle due at most
            break;
          }
          e.travelled[k] -= spacing_along;
          const Vec3 pos = c + pts[k][0] * e1 + pts[k][1] * e2 + e.travelled[k] * d;
          const Vec3 vel = u * d;
          for (int a = 0; a < 3; ++a) {
            s.x[a].push_back(a == 0 ? pos.x : a == 1 ? pos.y : pos.z);
            s.v[a].push_back(a == 0 ? vel.x : a == 1 ? vel.y : vel.z);
          }
          s.rho.push_back(f.params.rest_density);
          s.p.push_back(0);
          s.id.push_back(s.next_id++);
          ++e.emitted;
          e.emitted_volume += f.volume;
          ++total;
        }
      }
    }
    if (total > 0 && s.scratch.wall_hint.size() == (s.id.size() - static_cast<std::size_t>(total)) * walls.n_triangle_walls())
      s.scratch.wall_hint.resize(s.id.size() * walls.n_triangle_walls(), -1);  // new particles: no guess
    if (total > 0 && end_row.size() == s.id.size() - static_cast<std::size_t>(total))
      end_row.resize(s.id.size(), -1);  // new particles: no contacts
    if (total > 0) s.scratch.set_changed = true;
    s.counters.emitted += total;
    s.counters.emitted_volume += static_cast<Real>(total) * f.volume;
    return total;
  }
};

}  // namespace

// ---- public functions -------------------------------------------------------------

const char* to_string(Eos e) { return e == Eos::linear ? "linear" : "tait"; }
const char* to_string(Rheology r) { return r == Rheology::carreau ? "carreau" : "newtonian"; }
const char* to_string(PressureSolver p) { return p == PressureSolver::pcisph ? "pcisph" : "eos"; }
const char* fluid_phase_name(int k) {
  static const char* names[] = {"prepare", "density", "forces", "pressure", "integrate", "emit"};
  return k >= 0 && k < static_cast<int>(std::size(names)) ? names[k] : "?";
}
const char* substep_limit_name(int k) {
  static const char* const names[6] = {"step", "cfl", "force", "viscous", "max_substep", "pressure"};
  return k >= 0 && k < static_cast<int>(std::size(names)) ? names[k] : "?";
}

Real carreau_viscosity(const Carreau& c, Real shear_rate) {
  const Real lg = c.lambda * shear_rate;
  return c.mu_inf + (c.mu0 - c.mu_inf) * std::pow(1 + lg * lg, (c.n - 1) / 2);
}

Real carreau_shear_rate(const Carreau& c, Real stress) {
  if (!(stress > 0) || !(c.mu0 > 0)) return 0;
  // mu g is increasing in g; g lies in [stress / mu0, stress / max(mu_inf, ...)]: bisection
  Real lo = stress / c.mu0, hi = c.mu_inf > 0 ? stress / c.mu_inf : 2 * lo;
  while (carreau_viscosity(c, hi) * hi < stress) hi *= 2;  // mu_inf = 0: grow the bracket
  for (int it = 0; it < 200 && hi - lo > 1e-15 * hi; ++it) {
    const Real g = 0.5 * (lo + hi);
    (carreau_viscosity(c, g) * g < stress ? lo : hi) = g;
  }
  return 0.5 * (lo + hi);
}

Real carreau_pipe_flow_rate(Real radius, Real pressure_drop, Real length, const Carreau& c) {
  if (!(radius > 0) || !(pressure_drop > 0) || !(length > 0)) return 0;
  // Gauss-Legendre on [0, r] in 8 panels of 4 points (the integrand is smooth)
  static const Real x4[4] = {-0.8611363115940526, -0.3399810435848563, 0.3399810435848563, 0.8611363115940526};
  static const Real w4[4] = {0.3478548451374538, 0.6521451548625461, 0.6521451548625461, 0.3478548451374538};
  const int panels = 8;
  const Real h = radius / panels;
  Real sum = 0;
  for (int k = 0; k < panels; ++k)
    for (int q = 0; q < 4; ++q) {
      const Real s = (k + 0.5 + 0.5 * x4[q]) * h;
      sum += 0.5 * h * w4[q] * s * s * carreau_shear_rate(c, pressure_drop * s / (2 * length));
    }
  return kPi * sum;
}

Real eos_density(Eos e, Real p, Real rho0, Real c0, int gamma) {
  if (e == Eos::linear) return rho0 + p / (c0 * c0);
  return rho0 * std::pow(1 + p * gamma / (rho0 * c0 * c0), Real(1) / gamma);
}

Real physx_stiffness_to_sound_speed(Real stiffness, Real spacing) { return 10 * spacing * std::sqrt(stiffness); }
Real sound_speed_to_physx_stiffness(Real c0, Real spacing) {
  const Real r = c0 / (10 * spacing);
  return r * r;
}

Real poiseuille_flow_rate(Real radius, Real pressure_drop, Real viscosity, Real length) {
  return kPi * std::pow(radius, 4) * pressure_drop / (8 * viscosity * length);
}

Real WallTables::at(const std::vector<Real>& t, int n, Real q) {
  if (!(q > 0)) return t[0];
  if (!(q < 1)) return 0;
  const Real u = q * n;
  const int k = static_cast<int>(u);
  const Real w = u - k;
  return t[k] + w * (t[k + 1] - t[k]);
}

void validate(const FluidParams& p) {
  auto fail = [](const std::string& what) { throw Error("", "fluid: " + what); };
  auto positive = [&](Real v, const char* name) {
    if (!(std::isfinite(v) && v > 0)) fail(std::string(name) + " must be finite and > 0 (got " + str(v) + ")");
  };
  auto nonneg = [&](Real v, const char* name) {
    if (!(std::isfinite(v) && v >= 0)) fail(std::string(name) + " must be finite and >= 0 (got " + str(v) + ")");
  };
  positive(p.rest_density, "rest_density");
  nonneg(p.viscosity, "viscosity");
  if (p.rheology == Rheology::carreau) {
    const Carreau& c = p.carreau;
    if (!(std::isfinite(c.mu0) && c.mu0 > 0)) fail("carreau.mu0 must be > 0 (got " + str(c.mu0) + ")");
    if (!(c.mu_inf >= 0 && c.mu_inf <= c.mu0))
      fail("carreau.mu_inf must be in [0, mu0] (got " + str(c.mu_inf) + ")");
    if (!(std::isfinite(c.lambda) && c.lambda >= 0)) fail("carreau.lambda must be >= 0 (got " + str(c.lambda) + ")");
    if (!(c.n > 0 && c.n <= 1)) fail("carreau.n must be in (0, 1] (got " + str(c.n) + ")");
  }
  positive(p.spacing, "spacing");
  if (!(p.support_ratio >= 1.5 && p.support_ratio <= 4))
    fail("support_ratio must be in [1.5, 4] (got " + str(p.support_ratio) + ")");
  if (!finite3(p.gravity)) fail("gravity must be finite");
  if (p.tait_gamma < 1 || p.tait_gamma > 7) fail("tait_gamma must be in [1, 7] (got " + str(p.tait_gamma) + ")");
  nonneg(p.sound_speed, "sound_speed");
  nonneg(p.physx_stiffness, "physx_stiffness");
  if (p.physx_stiffness > 0 && p.sound_speed > 0)
    fail("give either sound_speed (physical) or physx_stiffness (PhysX-compatible), not both");
  if (p.physx_stiffness == 0 && p.sound_speed == 0) positive(p.max_speed, "max_speed (sound_speed = 0 means 10 * max_speed)");
  if (!(p.artificial_viscosity >= 0 && p.artificial_viscosity <= 1))
    fail("artificial_viscosity must be in [0, 1] (got " + str(p.artificial_viscosity) + ")");
  nonneg(p.damping, "damping");
  if (!(p.collision_distance >= 0 && p.collision_distance <= 1))
    fail("collision_distance must be in [0, 1] spacings (got " + str(p.collision_distance) + ")");
  if (!(p.cfl > 0 && p.cfl <= 1)) fail("cfl must be in (0, 1] (got " + str(p.cfl) + ")");
  if (!(p.force_cfl > 0 && p.force_cfl <= 1)) fail("force_cfl must be in (0, 1] (got " + str(p.force_cfl) + ")");
  if (!(p.viscous_cfl > 0 && p.viscous_cfl <= 1)) fail("viscous_cfl must be in (0, 1] (got " + str(p.viscous_cfl) + ")");
  nonneg(p.max_substep, "max_substep");
  if (p.max_substeps < 1) fail("max_substeps must be >= 1 (got " + str(p.max_substeps) + ")");
  if (!(p.surface_grid_slack >= 0 && p.surface_grid_slack <= 1))
    fail("surface_grid_slack must be in [0, 1] (got " + str(p.surface_grid_slack) + ")");
  if (!(p.neighbour_skin >= 0 && p.neighbour_skin <= 1))
    fail("neighbour_skin must be in [0, 1] (got " + str(p.neighbour_skin) + ")");
  if (p.pressure_solver == PressureSolver::pcisph) {
    if (p.physx_stiffness > 0) fail("pressure_solver pcisph needs the physical mode (physx_stiffness 0)");
    if (p.pcisph_target_iterations < 1 || p.pcisph_target_iterations > p.pcisph_max_iterations)
      fail("pcisph_target_iterations must be in [1, pcisph_max_iterations] (got " + str(p.pcisph_target_iterations) + ")");
    if (!(p.pcisph_tolerance > 0 && p.pcisph_tolerance <= 0.5))
      fail("pcisph_tolerance must be in (0, 0.5] (got " + str(p.pcisph_tolerance) + ")");
    if (p.pcisph_max_iterations < 1 || p.pcisph_max_iterations > 1000)
      fail("pcisph_max_iterations must be in [1, 1000] (got " + str(p.pcisph_max_iterations) + ")");
    if (p.pcisph_stall_repeats < 0 || p.pcisph_stall_repeats > 1000)
      fail("pcisph_stall_repeats must be in [0, 1000] (got " + str(p.pcisph_stall_repeats) + ")");
    if (p.pcisph_min_iterations < 1 || p.pcisph_min_iterations > p.pcisph_max_iterations)
      fail("pcisph_min_iterations must be in [1, pcisph_max_iterations] (got " + str(p.pcisph_min_iterations) + ")");
  }
}

Fluid make_fluid(const FluidParams& p) {
  validate(p);
  Fluid f;
  f.params = p;
  f.H = p.support_ratio * p.spacing;
  f.h = f.H / 2;
  // sums over the rest lattice around a particle (dx = 1): the kernel, so a
  // rest lattice has rho = rho0 exactly; the gradient moment V sum g x^2 and
  // the Morris operator on x^2, which a consistent discretisation has equal
  // to 1 (Wendland C2 at H = 2 dx: 0.95 and ~0.95)
  const Real ratio = p.support_ratio, eta2 = 0.01 * (ratio / 2) * (ratio / 2);
  const int m = static_cast<int>(std::ceil(ratio)) + 1;
  Real sum = 0, grad = 0, lap = 0, grad2 = 0;
  for (int k = -m; k <= m; ++k)
    for (int j = -m; j <= m; ++j)
      for (int i = -m; i <= m; ++i) {
        const Real r2 = Real(i * i + j * j + k * k), r = std::sqrt(r2);
        sum += wendland_w(r, ratio);
        grad += wendland_grad_factor(r, ratio) * i * i;
        grad2 += wendland_grad_factor(r, ratio) * wendland_grad_factor(r, ratio) * r2;
        lap += wendland_grad_factor(r, ratio) * r2 * i * i / (r2 + eta2);
      }
  f.gradient_scale = sum / grad;
  f.viscous_scale = sum / lap;
  f.lattice_grad2 = grad2 / std::pow(p.spacing, 8);
  sum /= p.spacing * p.spacing * p.spacing;
  f.lattice_sum = sum;
  f.mass = p.rest_density / sum;
  f.volume = f.mass / p.rest_density;
  if (p.physx_stiffness > 0) {
    f.eos = Eos::linear;
    f.c0 = physx_stiffness_to_sound_speed(p.physx_stiffness, p.spacing);
  } else {
    f.eos = p.eos;
    f.c0 = p.sound_speed > 0 ? p.sound_speed : 10 * p.max_speed;
  }
  f.physx_stiffness = sound_speed_to_physx_stiffness(f.c0, p.spacing);
  f.nu = (p.rheology == Rheology::carreau ? p.carreau.mu0 : p.viscosity) / p.rest_density;  // the largest viscosity
  f.expected_density_variation = (p.max_speed / f.c0) * (p.max_speed / f.c0);
  f.viscous_limit = f.nu > 0 ? p.viscous_cfl * f.h * f.h / f.nu : HUGE_VAL;
  f.walls = make_wall_tables(256, ratio, 1 / (f.lattice_sum * p.spacing * p.spacing * p.spacing), f.gradient_scale,
                             f.viscous_scale);
  return f;
}

FluidBoundaries make_box_boundaries(const std::array<Real, 3>& lo, const std::array<Real, 3>& hi) {
  FluidBoundaries b;
  b.lo = lo;
  b.hi = hi;
  return b;
}

void add_plane(FluidBoundaries& b, FluidPlane plane) {
  const Vec3 n = vec(plane.normal);
  const Real l = norm(n);
  if (!(l > 0) || !std::isfinite(l) || !finite3(plane.point)) throw Error("", "fluid plane: normal must be non-zero and finite");
  plane.normal = {n.x / l, n.y / l, n.z / l};
  b.planes.push_back(plane);
}

void validate_triangle_mesh(std::span<const Real> vertices, std::span<const std::int32_t> triangles, const char* what) {
  if (vertices.size() % 3 != 0 || triangles.size() % 3 != 0)
    throw Error("", std::string(what) + ": vertices and triangles must be (n x 3) arrays");
  for (Real v : vertices)
    if (!std::isfinite(v)) throw Error("", std::string(what) + ": vertex coordinates must be finite");
  const auto nv = static_cast<std::int32_t>(vertices.size() / 3);
  for (std::int32_t t : triangles)
    if (t < 0 || t >= nv)
      throw Error("", std::string(what) + ": triangle index " + str(t) + " out of range (" + str(nv) + " vertices)");
}

void add_mesh(FluidBoundaries& b, FluidMesh mesh, const Fluid& fluid) {
  validate_triangle_mesh(mesh.vertices, mesh.triangles, "fluid mesh");
  const auto nv = static_cast<std::int32_t>(mesh.vertices.size() / 3);
  if (!(mesh.wall.restitution >= 0 && mesh.wall.restitution <= 1) || !(mesh.wall.friction >= 0))
    throw Error("", "fluid mesh: restitution must be in [0, 1] and friction >= 0");
  TriangleSource src{mesh.vertices.data(), nullptr, mesh.triangles.data(), nv,
                     static_cast<std::int32_t>(mesh.triangles.size() / 3)};
  build_triangle_grid(src, 0, fluid.H, mesh.grid);
  b.meshes.push_back(std::move(mesh));
}

void build_static_triangle_grid(std::span<const Real> vertices, std::span<const std::int32_t> triangles, Real margin,
                                TriangleGrid& g) {
  const TriangleSource src{vertices.data(), nullptr, triangles.data(), static_cast<std::int32_t>(vertices.size() / 3),
                           static_cast<std::int32_t>(triangles.size() / 3)};
  build_triangle_grid(src, 0, margin, g);
}

std::pair<std::int32_t, std::int32_t> cell_candidates(const TriangleCells& g, const Vec3& p) { return grid_candidates(g, p); }

Vec3 closest_point_on_triangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c) {
  return closest_on_triangle(p, a, b, c).p;
}

void validate(const FluidBoundaries& b, const Fluid& fluid) {
  auto fail = [](const std::string& what) { throw Error("", "fluid boundaries: " + what); };
  if (!finite3(b.lo) || !finite3(b.hi)) fail("the domain box must be finite");
  static const char* axis = "xyz";
  for (int a = 0; a < 3; ++a) {
    if (!(b.hi[a] > b.lo[a])) fail(std::string("empty domain along ") + axis[a]);
    const bool p0 = b.faces[2 * a] == Face::periodic, p1 = b.faces[2 * a + 1] == Face::periodic;
    if (p0 != p1) fail(std::string("periodic faces come in pairs (axis ") + axis[a] + ")");
    if (p0 && b.hi[a] - b.lo[a] < 3 * fluid.H)
      fail(std::string("periodic length along ") + axis[a] + " must be >= 3 H = " + str(3 * fluid.H) + " m");
  }
  auto wall = [&](const WallParams& w) {
    if (!(w.restitution >= 0 && w.restitution <= 1)) fail("restitution must be in [0, 1]");
    if (!(w.friction >= 0 && std::isfinite(w.friction))) fail("friction must be finite and >= 0");
  };
  wall(b.box_wall);
  for (const auto& p : b.planes) wall(p.wall);
  for (const auto& m : b.meshes) wall(m.wall);
}

FluidState make_fluid_state() { return FluidState{}; }

void add_particles(const Fluid& f, FluidState& s, std::span<const Real> xyz, std::span<const Real> vel) {
  const std::size_t n = xyz.size() / 3;
  for (std::size_t i = 0; i < n; ++i) {
    bool ok = true;
    for (int a = 0; a < 3; ++a)
      ok = ok && std::isfinite(xyz[3 * i + a]) && (vel.size() != xyz.size() || std::isfinite(vel[3 * i + a]));
    if (!ok) {  // never let a NaN in
      ++s.counters.nonfinite;
      continue;
    }
    for (int a = 0; a < 3; ++a) {
      s.x[a].push_back(xyz[3 * i + a]);
      s.v[a].push_back(vel.size() == xyz.size() ? vel[3 * i + a] : 0);
    }
    s.rho.push_back(f.params.rest_density);
    s.p.push_back(0);
    s.id.push_back(s.next_id++);
  }
  if (!xyz.empty()) s.scratch.set_changed = true;
}

std::int64_t fill_box(const Fluid& f, FluidState& s, const std::array<Real, 3>& lo, const std::array<Real, 3>& hi,
                      const std::array<Real, 3>& velocity) {
  const Real dx = f.params.spacing;
  std::array<std::int64_t, 3> n{};
  for (int a = 0; a < 3; ++a) n[a] = std::max<std::int64_t>(0, static_cast<std::int64_t>(std::floor((hi[a] - lo[a]) / dx + 1e-9)));
  std::vector<Real> xyz, vel;
  xyz.reserve(3 * n[0] * n[1] * n[2]);
  for (std::int64_t k = 0; k < n[2]; ++k)
    for (std::int64_t j = 0; j < n[1]; ++j)
      for (std::int64_t i = 0; i < n[0]; ++i) {
        xyz.insert(xyz.end(), {lo[0] + (i + 0.5) * dx, lo[1] + (j + 0.5) * dx, lo[2] + (k + 0.5) * dx});
        vel.insert(vel.end(), velocity.begin(), velocity.end());
      }
  add_particles(f, s, xyz, vel);
  return n[0] * n[1] * n[2];
}

std::int64_t fill_ball(const Fluid& f, FluidState& s, const std::array<Real, 3>& c, Real r, Real lattice) {
  const Real dx = lattice > 0 ? lattice : f.params.spacing;
  if (!(std::isfinite(r) && r >= 0 && std::isfinite(dx) && r / dx < 1e4)) return 0;  // nothing for a bad ball
  const auto m = static_cast<std::int64_t>(std::ceil(r / dx)) + 1;
  std::vector<Real> xyz;
  for (std::int64_t k = -m; k <= m; ++k)
    for (std::int64_t j = -m; j <= m; ++j)
      for (std::int64_t i = -m; i <= m; ++i) {
        const Real q[3] = {(i + 0.5) * dx, (j + 0.5) * dx, (k + 0.5) * dx};
        if (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] <= r * r) xyz.insert(xyz.end(), {c[0] + q[0], c[1] + q[1], c[2] + q[2]});
      }
  const std::size_t n0 = s.id.size();
  add_particles(f, s, xyz);  // leaves out what is not finite (a non-finite centre)
  return static_cast<std::int64_t>(s.id.size() - n0);
}

std::int32_t NeighbourGrid::cell_of(Real x, Real y, Real z) const {
  const Real q[3] = {x, y, z};
  std::int32_t idx[3];
  for (int a = 0; a < 3; ++a) {
    const Real u = (q[a] - origin[a]) / cell[a];
    idx[a] = u >= 0 ? static_cast<std::int32_t>(std::min<Real>(u, dims[a] - 1)) : 0;
  }
  return idx[0] + dims[0] * (idx[1] + dims[1] * idx[2]);
}

void build_neighbour_grid(const Real* x, const Real* y, const Real* z, std::int64_t n64, Real radius,
                          const std::array<Real, 3>& lo, const std::array<Real, 3>& hi,
                          const std::array<bool, 3>& periodic, NeighbourGrid& g) {
  const auto n = static_cast<std::int32_t>(n64);
  // bounding box (exact min / max: independent of the partition)
  using Box = std::array<Real, 6>;
  const Box init{HUGE_VAL, HUGE_VAL, HUGE_VAL, -HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
  const Box bb = tbb::parallel_reduce(
      tbb::blocked_range<std::int32_t>(0, n, 1024), init,
      [&](const tbb::blocked_range<std::int32_t>& r, Box b) {
        for (std::int32_t i = r.begin(); i < r.end(); ++i) {
          b[0] = std::min(b[0], x[i]), b[3] = std::max(b[3], x[i]);
          b[1] = std::min(b[1], y[i]), b[4] = std::max(b[4], y[i]);
          b[2] = std::min(b[2], z[i]), b[5] = std::max(b[5], z[i]);
        }
        return b;
      },
      [](Box a, const Box& b) {
        for (int k = 0; k < 3; ++k) a[k] = std::min(a[k], b[k]), a[3 + k] = std::max(a[3 + k], b[3 + k]);
        return a;
      });
  const std::int64_t cap = std::max<std::int64_t>(4 * static_cast<std::int64_t>(n), 4096);
  Real factor = 1;
  for (;;) {
    std::int64_t total = 1;
    for (int a = 0; a < 3; ++a) {
      const Real c = radius * factor;
      if (periodic[a]) {
        const Real L = hi[a] - lo[a];
        g.dims[a] = std::max<std::int32_t>(3, static_cast<std::int32_t>(std::min<Real>(std::floor(L / c), 1 << 20)));
        g.cell[a] = L / g.dims[a];
        g.origin[a] = lo[a];
        g.period[a] = L;
      } else {
        const Real ext = n > 0 && bb[3 + a] >= bb[a] ? bb[3 + a] - bb[a] : 0;
        g.dims[a] = static_cast<std::int32_t>(std::min<Real>(std::floor(ext / c) + 1, 1 << 20));
        g.cell[a] = c;
        g.origin[a] = n > 0 && std::isfinite(bb[a]) ? bb[a] : 0;
        g.period[a] = 0;
      }
      total *= g.dims[a];
    }
    if (total <= cap) break;
    factor *= 1.26;
  }
  const std::int64_t nc = g.n_cells();
  g.point_cell.resize(n);
  tbb::parallel_for(tbb::blocked_range<std::int32_t>(0, n, 1024), [&](const auto& r) {
    for (std::int32_t i = r.begin(); i < r.end(); ++i) g.point_cell[i] = g.cell_of(x[i], y[i], z[i]);
  });
  // counting sort: count, exclusive prefix sum, stable fill
  g.start.assign(nc + 1, 0);
  for (std::int32_t i = 0; i < n; ++i) ++g.start[g.point_cell[i] + 1];
  g.occupied.clear();
  for (std::int64_t c = 0; c < nc; ++c) {
    if (g.start[c + 1] > 0) g.occupied.push_back(static_cast<std::int32_t>(c));
    g.start[c + 1] += g.start[c];
  }
  g.pieces.clear();
  for (const std::int32_t c : g.occupied)
    for (std::int32_t b = g.start[c]; b < g.start[c + 1]; b += NeighbourGrid::kPieceSlots)
      g.pieces.push_back({c, b, std::min(b + NeighbourGrid::kPieceSlots, g.start[c + 1])});
  g.order.resize(n);
  std::vector<std::int32_t> fill(g.start.begin(), g.start.end() - 1);
  for (std::int32_t i = 0; i < n; ++i) g.order[fill[g.point_cell[i]]++] = i;
}

int neighbour_runs(const NeighbourGrid& g, std::int32_t cell, NeighbourRun* runs) {
  const std::int32_t nx = g.dims[0], ny = g.dims[1], nz = g.dims[2];
  const std::int32_t cx = cell % nx, cy = (cell / nx) % ny, cz = cell / (nx * ny);
  int nr = 0;
  for (int dz = -1; dz <= 1; ++dz) {
    std::int32_t z = cz + dz;
    Real sz = 0;
    if (z < 0 || z >= nz) {
      if (g.period[2] <= 0) continue;
      sz = z < 0 ? -g.period[2] : g.period[2];
      z = (z + nz) % nz;
    }
    for (int dy = -1; dy <= 1; ++dy) {
      std::int32_t y = cy + dy;
      Real sy = 0;
      if (y < 0 || y >= ny) {
        if (g.period[1] <= 0) continue;
        sy = y < 0 ? -g.period[1] : g.period[1];
        y = (y + ny) % ny;
      }
      const std::int32_t row = nx * (y + ny * z);
      if (g.period[0] > 0 && (cx == 0 || cx == nx - 1)) {
        for (int dx = -1; dx <= 1; ++dx) {
          std::int32_t x = cx + dx;
          Real sx = 0;
          if (x < 0) x += nx, sx = -g.period[0];
          else if (x >= nx) x -= nx, sx = g.period[0];
          const std::int32_t b = g.start[row + x], e = g.start[row + x + 1];
          if (b < e) runs[nr++] = {b, e, sx, sy, sz};
        }
      } else {
        const std::int32_t x0 = std::max(cx - 1, 0), x1 = std::min(cx + 1, nx - 1);
        const std::int32_t b = g.start[row + x0], e = g.start[row + x1 + 1];
        if (b < e) runs[nr++] = {b, e, 0, sy, sz};
      }
    }
  }
  return nr;
}

void fluid_update_density(const Fluid& f, FluidState& s, const FluidBoundaries& b) {
  Stepper st(f, s, b, 0);
  st.prepare();
  st.density(st.pass(0));
}

Real fluid_substep_limit(const Fluid& f, FluidState& s, const FluidBoundaries& b) {
  Stepper st(f, s, b, 0);
  st.prepare();
  const Pass c = st.pass(0);
  st.density(c);
  std::vector<Reaction> rec;
  return st.limit(st.forces(c, rec)).first;
}

FluidStepInfo fluid_step(const Fluid& f, FluidState& s, Real dt, const FluidBoundaries& b) {
  FluidStepInfo info;
  if (!(std::isfinite(dt) && dt > 0)) {
    ++s.counters.invalid_steps;
    s.last = info;
    return info;
  }
  Stepper st(f, s, b, dt);
  const bool pci = f.params.pressure_solver == PressureSolver::pcisph;
  Real tau = 0;
  info.min_substep = HUGE_VAL;
  info.max_compression = -HUGE_VAL;
  std::vector<Reaction> reactions, impulses;
  using clock = std::chrono::steady_clock;
  auto lap = [&, t = clock::now()](int phase) mutable {
    const auto now = clock::now();
    s.counters.phase_s[static_cast<std::size_t>(phase)] += std::chrono::duration<double>(now - t).count();
    t = now;
  };
  while (tau < dt) {
    if (info.substeps >= f.params.max_substeps) {
      info.truncated = true;
      ++s.counters.truncated_steps;
      break;
    }
    Real h;
    int which;
    Real vtop = 0;  // m/s, the force pass's top speed
    Pass c;
    if (st.n() > 0) {
      lap(5);  // the loop's own bookkeeping goes with emit
      st.prepare();
      c = st.pass(tau);
      lap(0);
      info.max_compression = std::max(info.max_compression, st.density(c));
      lap(1);
      reactions.clear();
      const auto maxima = st.forces(c, reactions);
      lap(2);
      std::tie(h, which) = st.limit(maxima);
      vtop = std::sqrt(maxima[1]);
    } else {
      std::tie(h, which) = st.limit({0, 0});
    }
    // even substeps over the rest of the step
    const Real rest = dt - tau;
    if (h >= rest) h = rest, which = 0;
    else h = rest / std::ceil(rest / h);
    if (pci && st.n() > 0) {
      // Not converged: again from 0 at half the substep (at most 10 times).
      // The next substep is the one that would take about
      // pcisph_target_iterations corrections, the corrections growing as h^2
      // (a solve builds its pressure from 0 in steps of delta ~ 1/h^2), within
      // 0.5x ... 1.25x of this one.
      Real first_before = HUGE_VAL;
      // No halving below the substep the equation of state would take at the
      // same c0, cfl (H/2) / (c0 + |v|max): there one EOS pass is the cheaper
      // solver, and an unreachable tolerance would otherwise ratchet the
      // substep down without end (each redo's h sets the next substep's).
      const Real floor = f.params.cfl * f.h / (f.c0 + vtop);
      for (int retry = 0;; ++retry) {
        int it = 0;
        Real err = 0, first = 0;
        bool compressed_before = false, stalled = false;
        st.pcisph(c, h, reactions, &it, &err, &first, &compressed_before, &stalled);
        ++s.counters.pressure_solves;
        s.counters.pressure_iterations += it;
        info.pressure_iterations += it;
        const bool ok = err <= f.params.pcisph_tolerance;
        // halving helps where the compression comes from the motion over the
        // substep; where the fluid is compressed already (the worst particle was
        // at the substep's start, or the first prediction, without pressure, no
        // longer shrinks), the solve is taken as it is
        // (a stalled solve, Stepper::pcisph, is redone at half the substep like one
        // that ran out of corrections: the shorter motion may bring its particle in)
        const bool hopeless = compressed_before || first > Real(0.7) * first_before || h / 2 < floor;
        if (stalled) ++s.counters.pressure_stalled;
        first_before = first;
        if (ok || retry == 10 || hopeless) {
          if (!ok) ++s.counters.pressure_unconverged;
          info.max_predicted_compression = std::max(info.max_predicted_compression, err);
          s.pressure_substep = std::max(
              floor, h * std::clamp(std::sqrt(Real(f.params.pcisph_target_iterations) / std::max(it, 1)), Real(0.5),
                                    Real(1.25)));
          break;
        }
        ++s.counters.pressure_retries;
        h /= 2;
        which = 5;
        st.zero_pressure(c);
        reactions.clear();
        st.forces(c, reactions, false);
      }
      lap(3);
    }
    ++s.counters.substep_limit[static_cast<std::size_t>(which)];
    s.scratch.substep_motion = vtop * h;
    for (const Reaction& r : reactions) st.add_reaction(r, h / dt);
    impulses.clear();
    if (st.n() > 0) {
      lap(5);
      const auto [removed, collisions] = st.integrate(h, tau, impulses);
      s.counters.collisions += collisions;
      for (const Reaction& r : impulses) st.add_reaction(r, 1);
      lap(4);
      if (removed > 0) {
        st.compact();
        info.removed += removed;
      }
    }
    info.emitted += st.emit(h, s.time + tau);
    lap(5);
    // the last substep ends exactly at dt
    tau = (h == rest) ? dt : tau + h;
    ++info.substeps;
    info.min_substep = std::min(info.min_substep, h);
    info.max_substep = std::max(info.max_substep, h);
  }
  s.time += dt;
  ++s.counters.steps;
  s.counters.substeps += info.substeps;
  if (info.substeps == 0) info.min_substep = 0;
  if (!(info.max_compression > -HUGE_VAL)) info.max_compression = 0;
  // the neighbour counts (whole numbers: an exact sum) and the top speed, in parallel
  const auto& nb = s.scratch.neighbours;
  using Tail = std::pair<std::int64_t, Real>;
  const std::size_t nn = std::max(nb.size(), s.id.size());
  const Tail tail = tbb::parallel_reduce(
      tbb::blocked_range<std::size_t>(0, nn, 4096), Tail{0, 0},
      [&](const tbb::blocked_range<std::size_t>& r, Tail t) {
        for (std::size_t i = r.begin(); i < r.end(); ++i) {
          if (i < nb.size()) t.first += static_cast<std::int64_t>(nb[i]);
          if (i < s.id.size()) t.second = std::max(t.second, s.v[0][i] * s.v[0][i] + s.v[1][i] * s.v[1][i] + s.v[2][i] * s.v[2][i]);
        }
        return t;
      },
      [](Tail a, const Tail& b2) { return Tail{a.first + b2.first, std::max(a.second, b2.second)}; });
  if (!nb.empty()) info.mean_neighbours = static_cast<Real>(tail.first) / static_cast<Real>(nb.size());
  info.max_speed = std::sqrt(tail.second);
  lap(5);
  s.last = info;
  return info;
}

std::vector<Real> fluid_positions(const FluidState& s) {
  const std::size_t n = s.id.size();
  std::vector<Real> out(3 * n);
  for (std::size_t i = 0; i < n; ++i)
    for (int a = 0; a < 3; ++a) out[3 * i + a] = s.x[a][i];
  return out;
}

std::uint64_t fluid_state_hash(const FluidState& s) {
  std::uint64_t h = 1469598103934665603ull;
  auto mix = [&](const void* p, std::size_t bytes) {
    const auto* c = static_cast<const unsigned char*>(p);
    for (std::size_t k = 0; k < bytes; ++k) {
      h ^= c[k];
      h *= 1099511628211ull;
    }
  };
  mix(&s.time, sizeof s.time);
  for (int a = 0; a < 3; ++a) {
    mix(s.x[a].data(), s.x[a].size() * sizeof(Real));
    mix(s.v[a].data(), s.v[a].size() * sizeof(Real));
  }
  mix(s.id.data(), s.id.size() * sizeof(std::int64_t));
  return h;
}

std::array<Real, 3> fluid_momentum(const Fluid& f, const FluidState& s) {
  std::array<Real, 3> m{0, 0, 0};
  for (int a = 0; a < 3; ++a)
    for (Real v : s.v[a]) m[a] += f.mass * v;
  return m;
}

Real fluid_kinetic_energy(const Fluid& f, const FluidState& s) {
  Real e = 0;
  for (std::size_t i = 0; i < s.id.size(); ++i)
    e += 0.5 * f.mass * (s.v[0][i] * s.v[0][i] + s.v[1][i] * s.v[1][i] + s.v[2][i] * s.v[2][i]);
  return e;
}

Real fluid_volume(const Fluid& f, const FluidState& s) { return static_cast<Real>(s.id.size()) * f.volume; }

}  // namespace orthosim::runtime
