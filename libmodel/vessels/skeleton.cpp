// The cropped voxels, their anisotropic distance transform and the
// distance-ordered topology-preserving curve thinning.
#include "libmodel/vessels/detail.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <queue>

namespace orthosim::vessels_detail {

// ---- grid ------------------------------------------------------------------------

Grid make_grid(const Volume& v, int label, const std::string& tissue) {
  int lo[3] = {v.nx, v.ny, v.nz}, hi[3] = {-1, -1, -1};
  std::int64_t count = 0;
  for (int z = 0; z < v.nz; ++z)
    for (int y = 0; y < v.ny; ++y) {
      const std::uint8_t* row = v.labels.data() + v.index(0, y, z);
      for (int x = 0; x < v.nx; ++x)
        if (row[x] == label) {
          ++count;
          lo[0] = std::min(lo[0], x), hi[0] = std::max(hi[0], x);
          lo[1] = std::min(lo[1], y), hi[1] = std::max(hi[1], y);
          lo[2] = std::min(lo[2], z), hi[2] = std::max(hi[2], z);
        }
    }
  if (count == 0) throw Error("", "no voxels of tissue '" + tissue + "' (label " + std::to_string(label) + ")");
  Grid g;
  g.vx = v.nx, g.vy = v.ny, g.vz = v.nz;
  g.h = v.spacing_m;
  g.ox = lo[0] - 1, g.oy = lo[1] - 1, g.oz = lo[2] - 1;
  g.nx = hi[0] - lo[0] + 3, g.ny = hi[1] - lo[1] + 3, g.nz = hi[2] - lo[2] + 3;
  g.origin = v.position(g.ox, g.oy, g.oz);
  g.mask.assign(static_cast<std::size_t>(g.nx) * g.ny * g.nz, 0);
  for (int z = 1; z + 1 < g.nz; ++z)
    for (int y = 1; y + 1 < g.ny; ++y)
      for (int x = 1; x + 1 < g.nx; ++x)
        g.mask[g.index(x, y, z)] = v.at(x + g.ox, y + g.oy, z + g.oz) == label;
  g.voxels = count;
  return g;
}

int Grid::border_distance(std::size_t i) const {
  const Eigen::Vector3i c = coords(i);
  const int x = c.x() + ox, y = c.y() + oy, z = c.z() + oz;
  return std::min({x, y, z, vx - 1 - x, vy - 1 - y, vz - 1 - z});
}

double Grid::dt_at(const Eigen::Vector3d& p) const {
  double f[3];
  int i0[3];
  const int n[3] = {nx, ny, nz};
  for (int d = 0; d < 3; ++d) {
    const double u = (p(d) - origin(d)) / h[d];
    const double fl = std::floor(u);
    i0[d] = static_cast<int>(fl);
    f[d] = u - fl;
    if (i0[d] < 0) i0[d] = 0, f[d] = 0;
    if (i0[d] >= n[d] - 1) i0[d] = n[d] - 2, f[d] = 1;
  }
  double acc = 0;
  for (int c = 0; c < 8; ++c) {
    const int dx = c & 1, dy = (c >> 1) & 1, dz = (c >> 2) & 1;
    const double w = (dx ? f[0] : 1 - f[0]) * (dy ? f[1] : 1 - f[1]) * (dz ? f[2] : 1 - f[2]);
    if (w > 0) acc += w * dt[index(i0[0] + dx, i0[1] + dy, i0[2] + dz)];
  }
  return acc;
}

// ---- distance transform ------------------------------------------------------------

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

// d[q] = min_p w (q - p)^2 + f[p]: the lower envelope of parabolas
// (Felzenszwalb & Huttenlocher, "Distance transforms of sampled functions",
// Theory of Computing 8, 2012). Points with f = inf are skipped.
void edt_1d(const double* f, int n, double w, double* d, int* v, double* z) {
  int k = -1;
  for (int q = 0; q < n; ++q) {
    if (f[q] == kInf) continue;
    if (k < 0) {
      k = 0, v[0] = q, z[0] = -kInf, z[1] = kInf;
      continue;
    }
    double s = 0;
    for (;; --k) {  // z[0] = -inf ends the loop at k = 0
      const int p = v[k];
      s = ((f[q] + w * q * q) - (f[p] + w * p * p)) / (2 * w * (q - p));
      if (s > z[k]) break;
    }
    ++k;
    v[k] = q, z[k] = s, z[k + 1] = kInf;
  }
  if (k < 0) {
    for (int q = 0; q < n; ++q) d[q] = kInf;
    return;
  }
  int j = 0;
  for (int q = 0; q < n; ++q) {
    while (z[j + 1] < q) ++j;
    const double dq = q - v[j];
    d[q] = w * dq * dq + f[v[j]];
  }
}

}  // namespace

void distance_transform(Grid& g) {
  const std::size_t n = g.mask.size();
  std::vector<double> f(n);
  for (int z = 0; z < g.nz; ++z)
    for (int y = 0; y < g.ny; ++y)
      for (int x = 0; x < g.nx; ++x) {
        const std::size_t i = g.index(x, y, z);
        f[i] = (!g.mask[i] && g.in_volume(x, y, z)) ? 0.0 : kInf;
      }
  const int nmax = std::max({g.nx, g.ny, g.nz});
  const int dims[3] = {g.nx, g.ny, g.nz};
  const std::size_t stride[3] = {1, static_cast<std::size_t>(g.nx), static_cast<std::size_t>(g.nx) * g.ny};
  // one pass per axis; the lines of a pass are independent (parallel over
  // planes, each line written by one task: deterministic)
  for (int axis = 0; axis < 3; ++axis) {
    const int a1 = (axis + 1) % 3, a2 = (axis + 2) % 3;
    const double w = g.h[axis] * g.h[axis];
    tbb::parallel_for(tbb::blocked_range<int>(0, dims[a2]), [&](const tbb::blocked_range<int>& range) {
      std::vector<double> in(nmax), out(nmax), zz(nmax + 1);
      std::vector<int> vv(nmax);
      for (int j = range.begin(); j < range.end(); ++j)
        for (int i = 0; i < dims[a1]; ++i) {
          const std::size_t base = i * stride[a1] + j * stride[a2];
          const int len = dims[axis];
          for (int q = 0; q < len; ++q) in[q] = f[base + q * stride[axis]];
          edt_1d(in.data(), len, w, out.data(), vv.data(), zz.data());
          for (int q = 0; q < len; ++q) f[base + q * stride[axis]] = out[q];
        }
    });
  }
  g.dt.resize(n);
  for (std::size_t i = 0; i < n; ++i) g.dt[i] = f[i] == kInf ? 1e3f : static_cast<float>(std::sqrt(f[i]));
}

// ---- simple points -------------------------------------------------------------------

namespace {

struct Tables {
  std::uint32_t adj26[27]{}, adj6[27]{};
  std::uint32_t n26 = 0, n18 = 0, n6 = 0;
  Tables() {
    auto pos = [](int b, int* c) { c[0] = b % 3 - 1, c[1] = (b / 3) % 3 - 1, c[2] = b / 9 - 1; };
    for (int a = 0; a < 27; ++a) {
      if (a == 13) continue;
      int ca[3];
      pos(a, ca);
      const int l1 = std::abs(ca[0]) + std::abs(ca[1]) + std::abs(ca[2]);
      n26 |= 1u << a;
      if (l1 <= 2) n18 |= 1u << a;
      if (l1 == 1) n6 |= 1u << a;
      for (int b = 0; b < 27; ++b) {
        if (b == 13 || b == a) continue;
        int cb[3];
        pos(b, cb);
        const int dx = std::abs(ca[0] - cb[0]), dy = std::abs(ca[1] - cb[1]), dz = std::abs(ca[2] - cb[2]);
        if (std::max({dx, dy, dz}) == 1) adj26[a] |= 1u << b;
        if (dx + dy + dz == 1) adj6[a] |= 1u << b;
      }
    }
  }
};
const Tables& tables() {
  static const Tables t;
  return t;
}

// components of `set` under `adj`; with `touch`, only those meeting it count;
// stops early once the count exceeds 1
int components(std::uint32_t set, const std::uint32_t* adj, std::uint32_t touch) {
  int count = 0;
  while (set) {
    std::uint32_t comp = set & (~set + 1), frontier = comp;
    while (frontier) {
      std::uint32_t grow = 0;
      for (std::uint32_t f = frontier; f; f &= f - 1) grow |= adj[__builtin_ctz(f)];
      frontier = grow & set & ~comp;
      comp |= frontier;
    }
    set &= ~comp;
    if (!touch || (comp & touch))
      if (++count > 1) return count;
  }
  return count;
}

}  // namespace

// Simple point (Bertrand & Malandain, "A new characterization of
// three-dimensional simple points", Pattern Recognition Letters 15, 1994):
// one 26-component of the object in N26*(p) and one 6-component of the
// background in N18*(p) that is 6-adjacent to p.
bool is_simple(std::uint32_t bits) {
  const Tables& t = tables();
  const std::uint32_t fg = bits & t.n26;
  if (components(fg, t.adj26, 0) != 1) return false;
  const std::uint32_t bg = ~bits & t.n18;
  return components(bg, t.adj6, t.n6) == 1;
}

// ---- thinning -------------------------------------------------------------------------

// Distance-ordered homotopic thinning (after Pudney, "Distance-ordered
// homotopic thinning", CVIU 72, 1998): object voxels are visited in order of
// increasing distance to the background (physical units, so anisotropic
// voxels peel evenly), and deleted when simple and not the end of a curve.
// A voxel that cannot go yet is looked at again whenever a neighbour goes.
// Where the tissue reaches the volume border the vessel goes on beyond it: the
// crop's pad voxels outside the volume take the tissue of the nearest border
// voxel and are never deleted, so the curve keeps reaching the border. (With
// the border as background, the axis's tie in distance near an open end was
// peeled from the lower-index end first: the phantom's vein at 0.45 x 0.45 x
// 1.5 mm lost its first 5 slices and its root came out closed.) They are left
// out of the result.
std::vector<std::size_t> thin(const Grid& g) {
  std::vector<std::uint8_t> m = g.mask;
  std::vector<std::uint8_t> fixed(m.size(), 0);
  for (int z = 0; z < g.nz; ++z)
    for (int y = 0; y < g.ny; ++y)
      for (int x = 0; x < g.nx; ++x) {
        if (g.in_volume(x, y, z)) continue;
        const int cx = std::clamp(x + g.ox, 0, g.vx - 1) - g.ox, cy = std::clamp(y + g.oy, 0, g.vy - 1) - g.oy,
                  cz = std::clamp(z + g.oz, 0, g.vz - 1) - g.oz;
        const std::size_t i = g.index(x, y, z);
        if (cx < 0 || cy < 0 || cz < 0 || cx >= g.nx || cy >= g.ny || cz >= g.nz) continue;
        if (g.mask[g.index(cx, cy, cz)]) m[i] = 1, fixed[i] = 1;
      }
  std::vector<std::uint8_t> queued(m.size(), 0);
  std::ptrdiff_t off[27];
  for (int b = 0; b < 27; ++b) {
    const int dx = b % 3 - 1, dy = (b / 3) % 3 - 1, dz = b / 9 - 1;
    off[b] = (static_cast<std::ptrdiff_t>(dz) * g.ny + dy) * g.nx + dx;
  }
  using Item = std::pair<float, std::size_t>;
  std::priority_queue<Item, std::vector<Item>, std::greater<Item>> pq;
  // (the crop's outermost layer, without a full neighbourhood, holds only fixed voxels)
  for (std::size_t i = 0; i < m.size(); ++i) {
    if (!m[i] || fixed[i]) continue;
    bool border = false;
    for (int b : {4, 10, 12, 14, 16, 22}) border |= !m[i + off[b]];
    if (border) pq.push({g.dt[i], i}), queued[i] = 1;
  }
  const std::uint32_t n26 = tables().n26;
  while (!pq.empty()) {
    const std::size_t i = pq.top().second;
    pq.pop();
    queued[i] = 0;
    if (!m[i]) continue;
    std::uint32_t bits = 0;
    for (int b = 0; b < 27; ++b)
      if (m[i + off[b]]) bits |= 1u << b;
    if (__builtin_popcount(bits & n26) <= 1) continue;  // the end of a curve, or isolated
    if (!is_simple(bits)) continue;
    m[i] = 0;
    for (int b = 0; b < 27; ++b) {
      const std::size_t j = i + off[b];
      if (b != 13 && m[j] && !queued[j] && !fixed[j]) pq.push({g.dt[j], j}), queued[j] = 1;
    }
  }
  std::vector<std::size_t> out;
  for (std::size_t i = 0; i < m.size(); ++i)
    if (m[i] && !fixed[i]) out.push_back(i);
  return out;
}

}  // namespace orthosim::vessels_detail
