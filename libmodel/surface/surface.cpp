// surface: label volume -> closed outward 2-manifold triangle surface per tissue.
// Nesting, the solid and its hole filling, the Gaussian-smoothed indicator,
// marching tetrahedra, Taubin smoothing and the topology check. CGAL
// (decimation, self-intersections, distances) lives in surface_cgal.cpp.
#include "libmodel/surface/surface.h"

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <climits>
#include <cmath>
#include <cstring>
#include <memory>
#include <numeric>
#include <optional>
#include <stdexcept>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace orthosim {

namespace {

using Clock = std::chrono::steady_clock;

// Large arrays are written once, right after allocation: ask for 2 MiB pages
// (Linux transparent huge pages in "madvise" mode) so that first-touch page
// faults, which dominate the extraction on some virtual machines, are 512x
// fewer. A hint only: nothing changes where it is not supported.
void advise_huge_pages(void* p, std::size_t bytes) {
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  constexpr std::uintptr_t kHuge = std::uintptr_t{1} << 21;
  const std::uintptr_t a = (reinterpret_cast<std::uintptr_t>(p) + kHuge - 1) & ~(kHuge - 1);
  const std::uintptr_t b = (reinterpret_cast<std::uintptr_t>(p) + bytes) & ~(kHuge - 1);
  if (b > a) madvise(reinterpret_cast<void*>(a), b - a, MADV_HUGEPAGE);
#else
  (void)p, (void)bytes;
#endif
}

// an uninitialised array of n T, huge-page hinted
template <class T>
class BigArray {
 public:
  BigArray() = default;
  explicit BigArray(std::size_t n) : p_(new T[n]), n_(n) { advise_huge_pages(p_.get(), n * sizeof(T)); }
  T& operator[](std::size_t i) { return p_[i]; }
  const T& operator[](std::size_t i) const { return p_[i]; }
  T* data() { return p_.get(); }
  const T* data() const { return p_.get(); }
  std::size_t size() const { return n_; }

 private:
  std::unique_ptr<T[]> p_;
  std::size_t n_ = 0;
};
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// ---- marching-tetrahedra tables ------------------------------------------------------------
// Cube corners c = x + 2y + 4z (bit 0: +x, bit 1: +y, bit 2: +z). The
// Freudenthal split: six tetrahedra around the main diagonal 0-7, each a
// chain 0 -> one bit -> two bits -> 7, so every tetrahedron edge joins a
// corner to a corner with more bits set. Neighbouring cubes split their
// shared faces the same way, so the tetrahedra form a conforming mesh.
constexpr int kTets[6][4] = {{0, 1, 3, 7}, {0, 3, 2, 7}, {0, 2, 6, 7}, {0, 6, 4, 7}, {0, 4, 5, 7}, {0, 5, 1, 7}};

// Edge types by direction from the anchor (the corner with fewer bits).
// x, y, z, xy, xz, yz, xyz.
constexpr int kTypes = 7;
constexpr int kTypeDir[kTypes][3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}, {1, 1, 0}, {1, 0, 1}, {0, 1, 1}, {1, 1, 1}};

// The 19 tetrahedron edges of a cube. `slot` is the running counter that
// numbers the edge's vertex along the cell row: one counter per (anchor row
// offset dy, dz, type). Edges anchored at dx = 0 each have their own slot
// (14 of them); the 5 anchored at dx = 1 (the +x face) reuse the slot of the
// same row and type.
struct CubeEdge {
  int a, b;          // corners
  int dx, dy, dz;    // anchor offset
  int type;
  int slot;
};

struct Tables {
  std::array<CubeEdge, 19> edges{};
  int n_slots = 0;
  std::array<int, 14> slot_dy{}, slot_dz{}, slot_type{};
  // per case (8 corner bits): crossing slots at dx = 0, and triangles as
  // triples of cube-edge ids, oriented counter-clockwise seen from outside
  std::array<std::uint16_t, 256> cross0{};  // bits 0..6: the corner-0 edges (slot == type)
  std::array<std::uint8_t, 19> edge_slot{}, edge_dx{};
  std::array<std::uint8_t, 256> n_tris{};
  std::array<std::array<std::uint8_t, 36>, 256> tris{};  // at most 2 per tetrahedron

  Tables() {
    // the edges
    int n = 0;
    for (const auto& t : kTets)
      for (int i = 0; i < 4; ++i)
        for (int j = i + 1; j < 4; ++j) {
          const int a = std::min(t[i], t[j]), b = std::max(t[i], t[j]);
          bool seen = false;
          for (int e = 0; e < n; ++e) seen |= edges[e].a == a && edges[e].b == b;
          if (seen) continue;
          if ((a & b) != a) throw std::logic_error("Freudenthal edge not monotone");
          CubeEdge E{a, b, a & 1, (a >> 1) & 1, (a >> 2) & 1, -1, -1};
          const int d = b ^ a;
          for (int k = 0; k < kTypes; ++k)
            if (kTypeDir[k][0] == (d & 1) && kTypeDir[k][1] == ((d >> 1) & 1) && kTypeDir[k][2] == ((d >> 2) & 1))
              E.type = k;
          edges[n++] = E;
        }
    if (n != 19) throw std::logic_error("expected 19 Freudenthal edges");
    // slots: the seven corner-0 edges first, slot == type; then the other
    // dx = 0 edges; dx = 1 edges map onto the slot of their row and type
    for (int t = 0; t < kTypes; ++t)
      for (auto& e : edges)
        if (e.a == 0 && e.type == t) {
          slot_dy[n_slots] = 0, slot_dz[n_slots] = 0, slot_type[n_slots] = t;
          e.slot = n_slots++;
        }
    for (auto& e : edges)
      if (e.dx == 0 && e.a != 0) {
        slot_dy[n_slots] = e.dy, slot_dz[n_slots] = e.dz, slot_type[n_slots] = e.type;
        e.slot = n_slots++;
      }
    for (auto& e : edges)
      if (e.dx == 1)
        for (int s = 0; s < n_slots; ++s)
          if (slot_dy[s] == e.dy && slot_dz[s] == e.dz && slot_type[s] == e.type) e.slot = s;
    for (const auto& e : edges)
      if (e.slot < 0) throw std::logic_error("Freudenthal edge without a slot");
    if (n_slots != 14) throw std::logic_error("expected 14 edge slots");
    for (int e = 0; e < 19; ++e) edge_slot[e] = static_cast<std::uint8_t>(edges[e].slot), edge_dx[e] = static_cast<std::uint8_t>(edges[e].dx);

    auto edge_id = [&](int a, int b) {
      if (a > b) std::swap(a, b);
      for (int e = 0; e < 19; ++e)
        if (edges[e].a == a && edges[e].b == b) return e;
      throw std::logic_error("not a Freudenthal edge");
    };
    auto corner = [](int c) { return Eigen::Vector3d(c & 1, (c >> 1) & 1, (c >> 2) & 1); };
    auto mid = [&](int e) { return Eigen::Vector3d(0.5 * (corner(edges[e].a) + corner(edges[e].b))); };
    for (int c = 0; c < 256; ++c) {
      auto in = [&](int k) { return (c >> k) & 1; };
      for (const auto& e : edges)
        if (e.dx == 0 && in(e.a) != in(e.b)) cross0[c] |= static_cast<std::uint16_t>(1u << e.slot);
      int nt = 0;
      for (const auto& t : kTets) {
        int ins[4], outs[4], ni = 0, no = 0;
        for (int k : t) (in(k) ? ins[ni++] : outs[no++]) = k;
        if (ni == 0 || no == 0) continue;
        Eigen::Vector3d ci = Eigen::Vector3d::Zero(), co = Eigen::Vector3d::Zero();
        for (int k = 0; k < ni; ++k) ci += corner(ins[k]) / ni;
        for (int k = 0; k < no; ++k) co += corner(outs[k]) / no;
        auto emit = [&](int e0, int e1, int e2) {
          const Eigen::Vector3d nrm = (mid(e1) - mid(e0)).cross(mid(e2) - mid(e0));
          if (nrm.dot(co - ci) < 0) std::swap(e1, e2);
          tris[c][3 * nt] = static_cast<std::uint8_t>(e0);
          tris[c][3 * nt + 1] = static_cast<std::uint8_t>(e1);
          tris[c][3 * nt + 2] = static_cast<std::uint8_t>(e2);
          ++nt;
        };
        if (ni == 1) {
          emit(edge_id(ins[0], outs[0]), edge_id(ins[0], outs[1]), edge_id(ins[0], outs[2]));
        } else if (no == 1) {
          emit(edge_id(outs[0], ins[0]), edge_id(outs[0], ins[1]), edge_id(outs[0], ins[2]));
        } else {  // 2-2: the quad (i0,o0) (i0,o1) (i1,o1) (i1,o0), two triangles
          const int q0 = edge_id(ins[0], outs[0]), q1 = edge_id(ins[0], outs[1]), q2 = edge_id(ins[1], outs[1]),
                    q3 = edge_id(ins[1], outs[0]);
          emit(q0, q1, q2);
          emit(q0, q2, q3);
        }
      }
      n_tris[c] = static_cast<std::uint8_t>(nt);
    }
  }
};

const Tables& tables() {
  static const Tables t;
  return t;
}

// ---- the padded grid ---------------------------------------------------------------------------
// The working grid: the solid's bounding box plus a margin, plus one layer
// of padding on every side (always outside). Padded index p along axis k is
// volume index lo[k] + p - 1; its coordinate is coord[k][p] (the padding
// beyond a volume border sits border_offset x spacing outside the border).
// Every row (y, z) of the field is a pointer to either a shared constant row
// or its own data, with the first and last x where its sign changes.
template <class T>
struct RowField {
  int n[3] = {0, 0, 0};
  std::vector<const T*> f;           // (n[1]*n[2]) rows of n[0] values
  std::vector<const std::uint8_t*> s;  // signs: value > iso
  std::vector<int> first, last;      // first and last x with s[x] != s[x+1]; first > last: none
  std::size_t row(int y, int z) const { return static_cast<std::size_t>(z) * n[1] + y; }
};

struct Grid {
  int n[3] = {0, 0, 0};    // padded size
  int lo[3] = {0, 0, 0};   // volume index of padded index 1
  std::array<std::vector<double>, 3> coord;
  bool cap_lo[3] = {false, false, false}, cap_hi[3] = {false, false, false};  // padding beyond a volume border
  std::unique_ptr<std::uint8_t[]> ind;  // padded indicator, 0/1, x fastest
  std::vector<int> one_lo, one_hi;      // per row: first and last x of a 1 (one_lo > one_hi: none)
  std::size_t index(int x, int y, int z) const { return (static_cast<std::size_t>(z) * n[1] + y) * n[0] + x; }
  std::size_t rows() const { return static_cast<std::size_t>(n[1]) * n[2]; }
  const std::uint8_t* row(std::size_t r) const { return ind.get() + r * static_cast<std::size_t>(n[0]); }
  std::uint8_t* row(std::size_t r) { return ind.get() + r * static_cast<std::size_t>(n[0]); }
};

// first and last non-zero byte of a row (lo > hi: none), eight bytes at a time
void nonzero_range(const std::uint8_t* s, int n, int& lo, int& hi) {
  lo = 0;
  while (lo + 8 <= n) {
    std::uint64_t w;
    std::memcpy(&w, s + lo, 8);
    if (w) break;
    lo += 8;
  }
  while (lo < n && !s[lo]) ++lo;
  hi = n - 1;
  while (hi - 7 > lo) {
    std::uint64_t w;
    std::memcpy(&w, s + hi - 7, 8);
    if (w) break;
    hi -= 8;
  }
  while (hi >= lo && !s[hi]) --hi;
  if (lo >= n) lo = INT_MAX, hi = -1;
}

// labels -> 0/1 for a set of labels: compares (vectorised) for small sets, a table otherwise
class LabelSet {
 public:
  explicit LabelSet(const std::vector<int>& labels) {
    for (int l : labels)
      if (l >= 1 && l <= 255 && !lut_[static_cast<std::size_t>(l)]) {
        lut_[static_cast<std::size_t>(l)] = 1;
        list_.push_back(static_cast<std::uint8_t>(l));
      }
  }
  void row(const std::uint8_t* src, int n, std::uint8_t* dst) const {
    if (list_.size() > 8) {
      for (int x = 0; x < n; ++x) dst[x] = lut_[src[x]];
      return;
    }
    std::memset(dst, 0, static_cast<std::size_t>(n));
    for (std::uint8_t l : list_)
      for (int x = 0; x < n; ++x) dst[x] |= static_cast<std::uint8_t>(src[x] == l);
  }

 private:
  std::array<std::uint8_t, 256> lut_{};
  std::vector<std::uint8_t> list_;
};

// The edge-connected component of every vertex of s: up[v] ends as the
// smallest vertex id of v's component (union-find over the faces' edges, then
// every path resolved). up holds s.vertices.rows() entries.
void vertex_components(const Surface& s, std::int32_t* up) {
  const Eigen::Index V = s.vertices.rows(), F = s.faces.rows();
  std::iota(up, up + V, 0);
  auto find = [&](std::int32_t a) {
    while (up[a] != a) a = up[a] = up[up[a]];
    return a;
  };
  for (Eigen::Index f = 0; f < F; ++f)
    for (int k = 0; k < 2; ++k) {
      const std::int32_t a = find(s.faces(f, k)), b = find(s.faces(f, k + 1));
      if (a != b) up[std::max(a, b)] = std::min(a, b);
    }
  for (Eigen::Index v = 0; v < V; ++v) up[v] = up[up[v]];  // roots are smaller ids: one pass resolves
}

// Drops the edge-connected components of s that enclose less than
// min_volume (|signed volume|, m^3), never the largest; compacts the
// vertices (and their per-vertex flags `fixed`, when sized to them).
void drop_small_components(Surface& s, std::vector<std::uint8_t>& fixed, double min_volume, int& dropped,
                           double& dropped_volume) {
  const Eigen::Index nv = s.vertices.rows(), nf = s.faces.rows();
  std::vector<std::int32_t> root(static_cast<std::size_t>(nv));
  vertex_components(s, root.data());
  // signed volume per component (divergence theorem), indexed by its root
  std::vector<double> volume(static_cast<std::size_t>(nv), 0.0);
  std::vector<std::uint8_t> has_face(static_cast<std::size_t>(nv), 0);
  for (Eigen::Index f = 0; f < nf; ++f) {
    const Eigen::Vector3d a = s.vertices.row(s.faces(f, 0)), b = s.vertices.row(s.faces(f, 1)), c = s.vertices.row(s.faces(f, 2));
    const auto r = static_cast<std::size_t>(root[static_cast<std::size_t>(s.faces(f, 0))]);
    volume[r] += a.dot(b.cross(c)) / 6;
    has_face[r] = 1;
  }
  std::int32_t largest = -1, components = 0;
  for (Eigen::Index r = 0; r < nv; ++r) {
    if (!has_face[static_cast<std::size_t>(r)]) continue;
    ++components;
    if (largest < 0 || std::abs(volume[static_cast<std::size_t>(r)]) > std::abs(volume[static_cast<std::size_t>(largest)]))
      largest = static_cast<std::int32_t>(r);
  }
  if (components < 2) return;
  std::vector<std::uint8_t> drop(static_cast<std::size_t>(nv), 0);
  for (Eigen::Index r = 0; r < nv; ++r) {
    const auto u = static_cast<std::size_t>(r);
    if (!has_face[u] || r == largest || !(std::abs(volume[u]) < min_volume)) continue;
    drop[u] = 1;
    ++dropped;
    dropped_volume += std::abs(volume[u]);
  }
  if (std::find(drop.begin(), drop.end(), 1) == drop.end()) return;
  std::vector<std::int32_t> id(static_cast<std::size_t>(nv), -1);
  std::int32_t n = 0;
  for (Eigen::Index i = 0; i < nv; ++i)
    if (!drop[static_cast<std::size_t>(root[static_cast<std::size_t>(i)])]) id[static_cast<std::size_t>(i)] = n++;
  MatX3d vertices(n, 3);
  std::vector<std::uint8_t> kept_fixed;
  const bool flags = fixed.size() == static_cast<std::size_t>(nv);
  if (flags) kept_fixed.resize(static_cast<std::size_t>(n));
  for (Eigen::Index i = 0; i < nv; ++i) {
    const std::int32_t j = id[static_cast<std::size_t>(i)];
    if (j < 0) continue;
    vertices.row(j) = s.vertices.row(i);
    if (flags) kept_fixed[static_cast<std::size_t>(j)] = fixed[static_cast<std::size_t>(i)];
  }
  Eigen::Index kept = 0;
  for (Eigen::Index f = 0; f < nf; ++f) kept += id[static_cast<std::size_t>(s.faces(f, 0))] >= 0;
  MatX3i faces(kept, 3);
  for (Eigen::Index f = 0, w = 0; f < nf; ++f) {
    if (id[static_cast<std::size_t>(s.faces(f, 0))] < 0) continue;
    for (int k = 0; k < 3; ++k) faces(w, k) = id[static_cast<std::size_t>(s.faces(f, k))];
    ++w;
  }
  s.vertices = std::move(vertices);
  s.faces = std::move(faces);
  if (flags) fixed = std::move(kept_fixed);
}

// The Gaussian's radius in voxels (its kernel spans -w..w): ceil(3 sigma),
// at least 1; 0 without smoothing.
int blur_radius(double sigma) { return sigma > 0 ? std::max(1, static_cast<int>(std::ceil(3 * sigma))) : 0; }

// Coordinate (m) along axis k of volume index i, i in -1..n: -1 and n are the
// padding beyond the volume's border, border_offset spacings outside it. The
// padded grids and the cap planes both come from here, so a cap vertex
// (half-way into the padding) lies on its plane exactly.
double axis_coord(const Volume& v, const SurfaceOptions& o, int k, int i) {
  const double s = v.spacing_m[static_cast<std::size_t>(k)], org = v.origin_m[static_cast<std::size_t>(k)];
  const int n = k == 0 ? v.nx : k == 1 ? v.ny : v.nz;
  if (i < 0) return org - o.border_offset * s;
  if (i >= n) return org + (n - 1 + o.border_offset) * s;
  return org + i * s;
}

// The solid's indicator on the padded grid, holes filled. Hole filling works
// on runs: the maximal x-runs of non-solid voxels of every row, joined by a
// union-find where runs of neighbouring rows (y +- 1, z +- 1) overlap; the
// components with a run on a lateral face of the box (x or y at its border)
// are outside, every other component is a hole.
// With `box`, the grid is laid over box's (the parent's solid on the nested
// one's grid); then a pocket reaching box's lateral faces counts as outside.
Grid build_solid(const Volume& v, const std::vector<int>& labels, const SurfaceOptions& o, int margin,
                 std::int64_t& solid_voxels, std::int64_t& filled_voxels, const Grid* box = nullptr) {
  const LabelSet set(labels);
  Grid g;
  if (box) {
    std::copy(box->n, box->n + 3, g.n);
    std::copy(box->lo, box->lo + 3, g.lo);
    g.coord = box->coord;
    std::copy(box->cap_lo, box->cap_lo + 3, g.cap_lo);
    std::copy(box->cap_hi, box->cap_hi + 3, g.cap_hi);
  } else {
    // bounding box, per slice then reduced
    std::vector<std::array<int, 4>> slice_box(static_cast<std::size_t>(v.nz), {INT_MAX, INT_MAX, -1, -1});
    tbb::parallel_for(tbb::blocked_range<int>(0, v.nz), [&](const tbb::blocked_range<int>& r) {
      std::vector<std::uint8_t> tmp(static_cast<std::size_t>(v.nx));
      for (int z = r.begin(); z != r.end(); ++z) {
        auto& b = slice_box[static_cast<std::size_t>(z)];
        for (int y = 0; y < v.ny; ++y) {
          set.row(v.labels.data() + v.index(0, y, z), v.nx, tmp.data());
          int x0, x1;
          nonzero_range(tmp.data(), v.nx, x0, x1);
          if (x0 > x1) continue;
          b[0] = std::min(b[0], x0), b[2] = std::max(b[2], x1);
          b[1] = std::min(b[1], y), b[3] = std::max(b[3], y);
        }
      }
    });
    int lo[3] = {INT_MAX, INT_MAX, INT_MAX}, hi[3] = {-1, -1, -1};
    for (int z = 0; z < v.nz; ++z) {
      const auto& b = slice_box[static_cast<std::size_t>(z)];
      if (b[2] < 0) continue;
      lo[0] = std::min(lo[0], b[0]), hi[0] = std::max(hi[0], b[2]);
      lo[1] = std::min(lo[1], b[1]), hi[1] = std::max(hi[1], b[3]);
      lo[2] = std::min(lo[2], z), hi[2] = z;
    }
    if (hi[2] < 0) throw Error("", "no voxel has a label of the solid");
    const int nv[3] = {v.nx, v.ny, v.nz};
    for (int k = 0; k < 3; ++k) {
      const int a = std::max(0, lo[k] - margin), b = std::min(nv[k] - 1, hi[k] + margin);
      g.lo[k] = a;
      g.n[k] = b - a + 3;
      auto& c = g.coord[static_cast<std::size_t>(k)];
      c.resize(static_cast<std::size_t>(g.n[k]));
      for (int p = 0; p < g.n[k]; ++p) c[static_cast<std::size_t>(p)] = axis_coord(v, o, k, a + p - 1);
      g.cap_lo[k] = a == 0, g.cap_hi[k] = b == nv[k] - 1;
    }
  }
  // the indicator, the first and last 1 of every row, and the runs of 0s
  const int NX = g.n[0], NY = g.n[1], NZ = g.n[2];
  const std::size_t R = g.rows();
  g.ind.reset(new std::uint8_t[R * static_cast<std::size_t>(NX)]);
  advise_huge_pages(g.ind.get(), R * static_cast<std::size_t>(NX));
  g.one_lo.assign(R, INT_MAX), g.one_hi.assign(R, -1);
  std::vector<int> nruns(R, 0);
  std::vector<std::vector<std::array<int, 2>>> slice_runs(static_cast<std::size_t>(NZ));
  std::vector<std::int64_t> ones(static_cast<std::size_t>(NZ), 0);
  tbb::parallel_for(tbb::blocked_range<int>(0, NZ), [&](const tbb::blocked_range<int>& r) {
    for (int z = r.begin(); z != r.end(); ++z)
      for (int y = 0; y < NY; ++y) {
        const std::size_t i = static_cast<std::size_t>(z) * NY + y;
        std::uint8_t* dst = g.row(i);
        if (y == 0 || y == NY - 1 || z == 0 || z == NZ - 1) {
          std::memset(dst, 0, static_cast<std::size_t>(NX));
          continue;
        }
        dst[0] = dst[NX - 1] = 0;
        set.row(v.labels.data() + v.index(g.lo[0], g.lo[1] + y - 1, g.lo[2] + z - 1), NX - 2, dst + 1);
        nonzero_range(dst, NX, g.one_lo[i], g.one_hi[i]);
        std::int64_t count = 0;
        for (int x = 1; x < NX - 1; ++x) count += dst[x];
        ones[static_cast<std::size_t>(z)] += count;
        if (!o.fill_holes) continue;
        // runs of 0s, skipping eight 1s or eight 0s at a time
        constexpr std::uint64_t kOnes = 0x0101010101010101ull;
        auto& runs = slice_runs[static_cast<std::size_t>(z)];
        int n = 0;
        for (int x = 1; x < NX - 1;) {
          if (dst[x]) {
            std::uint64_t w;
            while (x + 8 <= NX - 1 && (std::memcpy(&w, dst + x, 8), w == kOnes)) x += 8;
            while (x < NX - 1 && dst[x]) ++x;
            continue;
          }
          const int x0 = x;
          std::uint64_t w;
          while (x + 8 <= NX - 1 && (std::memcpy(&w, dst + x, 8), w == 0)) x += 8;
          while (x < NX - 1 && !dst[x]) ++x;
          runs.push_back({x0, x - 1});
          ++n;
        }
        nruns[i] = n;
      }
  });
  std::int64_t solid = 0, filled = 0;
  for (std::int64_t c : ones) solid += c;
  if (o.fill_holes) {
    std::vector<std::int64_t> off(R + 1, 0);
    for (std::size_t i = 0; i < R; ++i) off[i + 1] = off[i] + nruns[i];
    std::vector<std::array<int, 2>> runs(static_cast<std::size_t>(off[R]));
    for (int z = 0; z < NZ; ++z) {
      const auto& sr = slice_runs[static_cast<std::size_t>(z)];
      std::copy(sr.begin(), sr.end(), runs.begin() + off[static_cast<std::size_t>(z) * NY]);
    }
    std::vector<std::int32_t> up(runs.size());
    std::iota(up.begin(), up.end(), 0);
    auto find = [&](std::int32_t a) {
      while (up[static_cast<std::size_t>(a)] != a)
        a = up[static_cast<std::size_t>(a)] = up[static_cast<std::size_t>(up[static_cast<std::size_t>(a)])];
      return a;
    };
    auto unite = [&](std::int32_t a, std::int32_t b) {
      a = find(a), b = find(b);
      if (a != b) up[static_cast<std::size_t>(std::max(a, b))] = std::min(a, b);
    };
    // overlapping runs of two rows
    auto join = [&](std::size_t ra, std::size_t rb) {
      std::int64_t i = off[ra], j = off[rb];
      while (i < off[ra + 1] && j < off[rb + 1]) {
        const auto& A = runs[static_cast<std::size_t>(i)];
        const auto& B = runs[static_cast<std::size_t>(j)];
        if (std::max(A[0], B[0]) <= std::min(A[1], B[1])) unite(static_cast<std::int32_t>(i), static_cast<std::int32_t>(j));
        (A[1] < B[1] ? i : j) += 1;
      }
    };
    for (int z = 1; z < NZ - 1; ++z)
      for (int y = 1; y < NY - 1; ++y) {
        const std::size_t i = static_cast<std::size_t>(z) * NY + y;
        if (y > 1) join(i, i - 1);
        if (z > 1) join(i, i - static_cast<std::size_t>(NY));
      }
    std::vector<char> outside(runs.size(), 0);
    for (int z = 1; z < NZ - 1; ++z)
      for (int y = 1; y < NY - 1; ++y) {
        const std::size_t i = static_cast<std::size_t>(z) * NY + y;
        for (std::int64_t k = off[i]; k < off[i + 1]; ++k) {
          const auto& A = runs[static_cast<std::size_t>(k)];
          if (y == 1 || y == NY - 2 || A[0] == 1 || A[1] == NX - 2) outside[static_cast<std::size_t>(find(static_cast<std::int32_t>(k)))] = 1;
        }
      }
    std::vector<std::int32_t> root(runs.size());
    for (std::size_t k = 0; k < runs.size(); ++k) root[k] = find(static_cast<std::int32_t>(k));
    std::vector<std::int64_t> fs(static_cast<std::size_t>(NZ), 0);
    tbb::parallel_for(tbb::blocked_range<int>(1, NZ - 1), [&](const tbb::blocked_range<int>& r) {
      for (int z = r.begin(); z != r.end(); ++z)
        for (int y = 1; y < NY - 1; ++y) {
          const std::size_t i = static_cast<std::size_t>(z) * NY + y;
          for (std::int64_t k = off[i]; k < off[i + 1]; ++k) {
            if (outside[static_cast<std::size_t>(root[static_cast<std::size_t>(k)])]) continue;
            const auto& A = runs[static_cast<std::size_t>(k)];
            std::memset(g.row(i) + A[0], 1, static_cast<std::size_t>(A[1] - A[0] + 1));
            fs[static_cast<std::size_t>(z)] += A[1] - A[0] + 1;
          }
        }
    });
    for (std::int64_t c : fs) filled += c;
  }
  solid_voxels = solid + filled;
  filled_voxels = filled;
  return g;
}

// rows of the unsmoothed indicator as the field: its sign changes are just
// before the first 1 and at the last 1 (holes lie between 1s)
RowField<std::uint8_t> binary_field(const Grid& g) {
  RowField<std::uint8_t> F;
  std::copy(g.n, g.n + 3, F.n);
  const std::size_t R = g.rows();
  F.f.resize(R), F.s.resize(R), F.first.resize(R), F.last.resize(R);
  for (std::size_t i = 0; i < R; ++i) {
    F.f[i] = F.s[i] = g.row(i);
    const bool any = g.one_lo[i] <= g.one_hi[i];
    F.first[i] = any ? g.one_lo[i] - 1 : INT_MAX;
    F.last[i] = any ? g.one_hi[i] : -1;
  }
  return F;
}

// The indicator smoothed by a separable Gaussian (sigma in voxels), values
// beyond the box replicated from its border. Constant rows stay shared
// constants; only rows near the surface are computed.
struct SmoothField {
  RowField<float> F;
  std::unique_ptr<float[]> a, b;       // row storage (padded layout; only rows in use are touched)
  std::unique_ptr<std::uint8_t[]> s;   // sign storage
  std::vector<float> zeros, ones;      // constant rows (ones: 0 at the padding)
  std::vector<std::uint8_t> szeros, sones;
  std::unique_ptr<float[]> c;          // rows changed by clip_field
};

void smooth_field(const Grid& g, double sigma, double iso, SmoothField& out) {
  const int NX = g.n[0], NY = g.n[1], NZ = g.n[2];
  const std::size_t R = g.rows(), cells = R * static_cast<std::size_t>(NX);
  const int w = blur_radius(sigma);
  std::vector<float> k(static_cast<std::size_t>(2 * w + 1));
  double ks = 0;
  for (int i = -w; i <= w; ++i) ks += std::exp(-0.5 * i * i / (sigma * sigma));
  for (int i = -w; i <= w; ++i) k[static_cast<std::size_t>(i + w)] = static_cast<float>(std::exp(-0.5 * i * i / (sigma * sigma)) / ks);

  out.zeros.assign(static_cast<std::size_t>(NX), 0.f);
  out.ones.assign(static_cast<std::size_t>(NX), 1.f);
  out.ones.front() = out.ones.back() = 0.f;
  out.szeros.assign(static_cast<std::size_t>(NX), 0);
  out.sones.assign(static_cast<std::size_t>(NX), 1);
  out.sones.front() = out.sones.back() = 0;
  out.a.reset(new float[cells]);
  out.b.reset(new float[cells]);
  out.s.reset(new std::uint8_t[cells]);
  advise_huge_pages(out.a.get(), cells * sizeof(float));
  advise_huge_pages(out.b.get(), cells * sizeof(float));
  advise_huge_pages(out.s.get(), cells);
  const float* Z = out.zeros.data();
  const float* O = out.ones.data();
  // Row state: 0 constant 0, 1 constant 1, 2 data. A data row is written in
  // full, but may be non-zero only within [lo, hi]: the passes compute there.
  struct Rows {
    std::vector<std::uint8_t> st;
    std::vector<const float*> p;
    std::vector<int> lo, hi;
    explicit Rows(std::size_t n, const float* z) : st(n, 0), p(n, z), lo(n, INT_MAX), hi(n, -1) {}
  };
  Rows r1(R, Z), r2(R, Z), r3(R, Z);
  auto rowptr = [&](float* base, std::size_t i) { return base + i * static_cast<std::size_t>(NX); };

  // x: each row of the indicator, non-zero at most w beyond its first and last 1
  tbb::parallel_for(tbb::blocked_range<int>(1, NZ - 1), [&](const tbb::blocked_range<int>& r) {
    std::vector<float> ext(static_cast<std::size_t>(NX + 2 * w));
    for (int z = r.begin(); z != r.end(); ++z)
      for (int y = 1; y < NY - 1; ++y) {
        const std::size_t i = static_cast<std::size_t>(z) * NY + y;
        const std::uint8_t* in = g.row(i);
        const int l1 = g.one_lo[i], h1 = g.one_hi[i];
        if (l1 > h1) continue;  // constant 0
        if (l1 == 1 && h1 == NX - 2 && std::find(in + 1, in + NX - 1, std::uint8_t{0}) == in + NX - 1) {
          r1.st[i] = 1, r1.p[i] = O;
          continue;
        }
        const int a = std::max(1, l1 - w), b = std::min(NX - 2, h1 + w), n = b - a + 1;
        // ext[j] = indicator at x = a - w + j, clamped to the box
        float* __restrict e = ext.data();
        for (int j = 0; j < n + 2 * w; ++j) e[j] = in[std::clamp(a - w + j, 1, NX - 2)];
        float* __restrict o = rowptr(out.a.get(), i);
        std::fill(o, o + a, 0.f);
        std::fill(o + b + 1, o + NX, 0.f);
        float* __restrict os = o + a;
        for (int x = 0; x < n; ++x) os[x] = k[0] * e[x];
        for (int t = 1; t <= 2 * w; ++t) {
          const float kt = k[static_cast<std::size_t>(t)];
          const float* __restrict et = e + t;
          for (int x = 0; x < n; ++x) os[x] += kt * et[x];
        }
        r1.st[i] = 2, r1.p[i] = o, r1.lo[i] = a, r1.hi[i] = b;
      }
  });
  // y then z: a row is the weighted sum of 2w+1 rows of the previous pass
  auto pass = [&](const Rows& in, Rows& outr, float* store, int axis) {
    tbb::parallel_for(tbb::blocked_range<int>(1, NZ - 1), [&](const tbb::blocked_range<int>& r) {
      const float* src[64];
      float wt[64];
      for (int z = r.begin(); z != r.end(); ++z)
        for (int y = 1; y < NY - 1; ++y) {
          const std::size_t i = static_cast<std::size_t>(z) * NY + y;
          int ns = 0, n0 = 0, n1 = 0, lo = INT_MAX, hi = -1;
          float c = 0;
          for (int t = -w; t <= w; ++t) {
            const int yy = axis == 1 ? std::clamp(y + t, 1, NY - 2) : y;
            const int zz = axis == 2 ? std::clamp(z + t, 1, NZ - 2) : z;
            const std::size_t j = static_cast<std::size_t>(zz) * NY + yy;
            const float kt = k[static_cast<std::size_t>(t + w)];
            if (in.st[j] == 0) {
              ++n0;
            } else if (in.st[j] == 1) {
              ++n1, c += kt;
            } else {
              src[ns] = in.p[j], wt[ns++] = kt;
              lo = std::min(lo, in.lo[j]), hi = std::max(hi, in.hi[j]);
            }
          }
          if (ns == 0 && (n0 == 0 || n1 == 0)) {
            outr.st[i] = n1 > 0;
            outr.p[i] = n1 > 0 ? O : Z;
            continue;
          }
          if (n1 > 0) lo = 1, hi = NX - 2;
          float* __restrict o = rowptr(store, i);
          std::fill(o, o + lo, 0.f);
          std::fill(o + hi + 1, o + NX, 0.f);
          for (int x = lo; x <= hi; ++x) o[x] = c;
          for (int m = 0; m < ns; ++m) {
            const float kt = wt[m];
            const float* __restrict q = src[m];
            for (int x = lo; x <= hi; ++x) o[x] += kt * q[x];
          }
          outr.st[i] = 2, outr.p[i] = o, outr.lo[i] = lo, outr.hi[i] = hi;
        }
    });
  };
  pass(r1, r2, out.b.get(), 1);
  pass(r2, r3, out.a.get(), 2);  // the x-pass rows are no longer needed

  // signs and transitions (the padding is 0, so they lie before the first
  // and at the last positive sample)
  auto& F = out.F;
  std::copy(g.n, g.n + 3, F.n);
  F.f.assign(R, Z), F.s.assign(R, out.szeros.data()), F.first.assign(R, INT_MAX), F.last.assign(R, -1);
  const float fiso = static_cast<float>(iso);
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, R), [&](const tbb::blocked_range<std::size_t>& r) {
    for (std::size_t i = r.begin(); i != r.end(); ++i) {
      F.f[i] = r3.p[i];
      if (r3.st[i] == 0) continue;
      if (r3.st[i] == 1) {
        F.s[i] = out.sones.data();
        F.first[i] = 0, F.last[i] = NX - 2;
        continue;
      }
      std::uint8_t* __restrict sg = out.s.get() + i * static_cast<std::size_t>(NX);
      const float* __restrict f = r3.p[i];
      const int lo = r3.lo[i], hi = r3.hi[i];
      std::memset(sg, 0, static_cast<std::size_t>(lo));
      std::memset(sg + hi + 1, 0, static_cast<std::size_t>(NX - hi - 1));
      for (int x = lo; x <= hi; ++x) sg[x] = f[x] > fiso;
      F.s[i] = sg;
      int a, b;
      nonzero_range(sg, NX, a, b);
      if (a <= b) F.first[i] = a - 1, F.last[i] = b;
    }
  });
}

// Nesting in the field: the nested field c becomes smin(c, A(p)) with
// A(f) = (f - a) / (1 - a), a = gap / (1 - iso). A fixes 1, so inside the
// parent (p = 1) the nested field is left alone, and takes the parent's level
// iso + gap to iso: where the two solids coincide the nested level set lies
// where the parent's field is iso + gap. Only rows where both fields vary can
// change: a constant-1 nested row lies in a constant-1 parent row, and a
// constant-0 nested row adjoins no crossing. Returns the samples inside the
// nested solid (above iso) that were lowered: where its surface moved.
std::int64_t clip_field(SmoothField& c, const SmoothField& p, double gap, double iso) {
  auto& F = c.F;
  const int NX = F.n[0];
  const std::size_t R = F.f.size();
  const float a = static_cast<float>(gap / (1 - iso)), k = static_cast<float>(gap), fiso = static_cast<float>(iso);
  auto varies = [](const SmoothField& s, std::size_t i) {
    return s.F.f[i] != s.zeros.data() && s.F.f[i] != s.ones.data();
  };
  if (!c.c) c.c.reset(new float[R * static_cast<std::size_t>(NX)]);
  std::vector<std::int64_t> lowered(R, 0);
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, R), [&](const tbb::blocked_range<std::size_t>& r) {
    for (std::size_t i = r.begin(); i != r.end(); ++i) {
      if (!varies(c, i) || !varies(p, i)) continue;
      const float* __restrict fc = F.f[i];
      const float* __restrict fp = p.F.f[i];
      // the smooth minimum (polynomial, width k = gap at the nested level,
      // narrowing to 0 inside the parent): no crease where the two fields
      // cross, which smoothing and the blur compensation folded (4 face pairs
      // on the phantom at noise 16, 64^3 of 1 mm), and the parent's inside
      // stays untouched
      float* __restrict o = c.c.get() + i * static_cast<std::size_t>(NX);
      std::int64_t n = 0;
      bool any = false;
      for (int x = 0; x < NX; ++x) {
        const float b = (fp[x] - a) / (1 - a);
        const float kb = k * std::clamp((1 - b) / (1 - fiso), 0.f, 1.f);  // 0 inside the parent
        const float h = std::max(kb - std::abs(fc[x] - b), 0.f);
        o[x] = kb > 0 ? std::min(fc[x], b) - h * h / (4 * kb) : std::min(fc[x], b);
        const bool low = o[x] < fc[x];
        any = any || low;
        n += low && fc[x] > fiso;
      }
      if (!any) continue;
      lowered[i] = n;
      std::uint8_t* __restrict sg = c.s.get() + i * static_cast<std::size_t>(NX);
      for (int x = 0; x < NX; ++x) sg[x] = o[x] > fiso;
      F.f[i] = o;
      F.s[i] = sg;
      int lo, hi;
      nonzero_range(sg, NX, lo, hi);
      F.first[i] = lo <= hi ? lo - 1 : INT_MAX;
      F.last[i] = lo <= hi ? hi : -1;
    }
  });
  return std::accumulate(lowered.begin(), lowered.end(), std::int64_t{0});
}

// ---- marching tetrahedra ---------------------------------------------------------------------
// Two passes over the cell rows (y, z), each parallel over z: the first
// counts the crossing edges anchored at each row (per edge type) and the
// triangles of each cell row, a prefix sum turns the counts into vertex and
// face offsets, and the second writes vertices and faces in place. Vertex
// ids follow (z, y, type, x): the output does not depend on the thread count.
// Along a cell row, the vertex of an edge is found by a running counter per
// (anchor row, type) that advances at each crossing: no hash map and no
// per-edge index array. Cells whose eight corners agree are skipped eight at
// a time.
// Vertices on an edge into the padding beyond a volume border are placed
// half-way along that axis (the cap plane, border_offset / 2 spacings outside
// the border voxel centres) whatever the field, so caps are exactly flat;
// fixed[v] has bit k set for such a vertex and axis k.
template <class T>
Surface march(const Grid& g, const RowField<T>& F, double iso, std::vector<std::uint8_t>& fixed) {
  const Tables& tb = tables();
  const int NX = g.n[0], NY = g.n[1], NZ = g.n[2];
  const std::size_t R = g.rows();
  std::vector<std::int64_t> vcount(R * kTypes, 0), tcount(R, 0);

  // visits the non-trivial cells of cell row (y, z): fn(x, case)
  auto for_cells = [&](int y, int z, auto&& fn) {
    const std::size_t r00 = F.row(y, z), r10 = F.row(y + 1, z), r01 = F.row(y, z + 1), r11 = F.row(y + 1, z + 1);
    const int L = std::min(std::min(F.first[r00], F.first[r10]), std::min(F.first[r01], F.first[r11]));
    const int Rr = std::max(std::max(F.last[r00], F.last[r10]), std::max(F.last[r01], F.last[r11]));
    if (L > Rr) return;
    const std::uint8_t *s0 = F.s[r00], *s1 = F.s[r10], *s2 = F.s[r01], *s3 = F.s[r11];
    int x = L;
    constexpr std::uint64_t kOnes = 0x0101010101010101ull;
    while (x <= Rr) {
      if (x + 9 <= NX) {  // eight cells x..x+7 at once: all corners equal?
        std::uint64_t w[8];
        std::memcpy(&w[0], s0 + x, 8), std::memcpy(&w[1], s0 + x + 1, 8);
        std::memcpy(&w[2], s1 + x, 8), std::memcpy(&w[3], s1 + x + 1, 8);
        std::memcpy(&w[4], s2 + x, 8), std::memcpy(&w[5], s2 + x + 1, 8);
        std::memcpy(&w[6], s3 + x, 8), std::memcpy(&w[7], s3 + x + 1, 8);
        std::uint64_t a = w[0], o = w[0];
        for (int i = 1; i < 8; ++i) a &= w[i], o |= w[i];
        if (o == 0 || a == kOnes) {
          x += 8;
          continue;
        }
      }
      const int end = std::min(Rr, x + 7);
      for (; x <= end; ++x) {
        const unsigned c = s0[x] | (s0[x + 1] << 1) | (s1[x] << 2) | (s1[x + 1] << 3) | (s2[x] << 4) |
                           (s2[x + 1] << 5) | (s3[x] << 6) | (s3[x + 1] << 7);
        if (c != 0 && c != 255) fn(x, c);
      }
    }
  };

  // pass 1: counts
  tbb::parallel_for(tbb::blocked_range<int>(0, NZ - 1), [&](const tbb::blocked_range<int>& r) {
    for (int z = r.begin(); z != r.end(); ++z)
      for (int y = 0; y < NY - 1; ++y) {
        const std::size_t row = F.row(y, z);
        std::int64_t vc[kTypes] = {0, 0, 0, 0, 0, 0, 0}, tc = 0;
        for_cells(y, z, [&](int, unsigned c) {
          const unsigned m = tb.cross0[c];
          for (int t = 0; t < kTypes; ++t) vc[t] += (m >> t) & 1;
          tc += tb.n_tris[c];
        });
        for (int t = 0; t < kTypes; ++t) vcount[row * kTypes + t] = vc[t];
        tcount[row] = tc;
      }
  });
  // prefix sums: vertex ids by (z, y, type, x), faces by (z, y, x)
  std::vector<std::int64_t> vbase(R * kTypes), tbase(R);
  std::int64_t nv = 0, nf = 0;
  for (std::size_t i = 0; i < R * kTypes; ++i) vbase[i] = nv, nv += vcount[i];
  for (std::size_t i = 0; i < R; ++i) tbase[i] = nf, nf += tcount[i];
  if (nv >= INT32_MAX || nf >= INT32_MAX) throw Error("", "surface too large (more than 2^31 vertices or faces)");

  Surface out;
  out.vertices.resize(nv, 3);
  out.faces.resize(nf, 3);
  fixed.assign(static_cast<std::size_t>(nv), 0);
  advise_huge_pages(out.vertices.data(), static_cast<std::size_t>(nv) * 3 * sizeof(double));
  advise_huge_pages(out.faces.data(), static_cast<std::size_t>(nf) * 3 * sizeof(std::int32_t));
  const std::array<const std::vector<double>*, 3> coord{&g.coord[0], &g.coord[1], &g.coord[2]};
  // pass 2: vertices and faces
  tbb::parallel_for(tbb::blocked_range<int>(0, NZ - 1), [&](const tbb::blocked_range<int>& r) {
    for (int z = r.begin(); z != r.end(); ++z)
      for (int y = 0; y < NY - 1; ++y) {
        std::int64_t ctr[14];
        for (int s = 0; s < 14; ++s)
          ctr[s] = vbase[F.row(y + tb.slot_dy[static_cast<std::size_t>(s)], z + tb.slot_dz[static_cast<std::size_t>(s)]) * kTypes +
                         static_cast<std::size_t>(tb.slot_type[static_cast<std::size_t>(s)])];
        std::int64_t tf = tbase[F.row(y, z)];
        const std::size_t r0 = F.row(y, z);
        for_cells(y, z, [&](int x, unsigned c) {
          std::int64_t id0[14];
          const unsigned m = tb.cross0[c];
          for (unsigned mm = m; mm; mm &= mm - 1) {
            const int sl = __builtin_ctz(mm);
            id0[sl] = ctr[sl]++;
          }
          // the cell's corner-0 edges own their vertex: position it
          for (unsigned mm = m & 0x7Fu; mm; mm &= mm - 1) {
            const int t = __builtin_ctz(mm);
            const int d[3] = {kTypeDir[t][0], kTypeDir[t][1], kTypeDir[t][2]};
            const double fa = static_cast<double>(F.f[r0][x]);
            const double fb = static_cast<double>(F.f[F.row(y + d[1], z + d[2])][x + d[0]]);
            const double u = std::clamp((fa - iso) / (fa - fb), 1e-3, 1 - 1e-3);
            const int at[3] = {x, y, z};
            double* p = out.vertices.data() + 3 * id0[t];
            std::uint8_t fix = 0;
            for (int k = 0; k < 3; ++k) {
              const double* ck = coord[static_cast<std::size_t>(k)]->data();
              const double c0 = ck[at[k]];
              if (!d[k]) {
                p[k] = c0;
                continue;
              }
              const double c1 = ck[at[k] + 1];
              if ((g.cap_lo[k] && at[k] == 0) || (g.cap_hi[k] && at[k] + 2 == g.n[k])) {
                p[k] = 0.5 * (c0 + c1);
                fix |= static_cast<std::uint8_t>(1u << k);
              } else {
                p[k] = c0 + u * (c1 - c0);
              }
            }
            if (fix) fixed[static_cast<std::size_t>(id0[t])] = fix;
          }
          // triangles; an edge on the +x face has the next anchor's id, ctr[slot] after the increment
          const auto& tri = tb.tris[c];
          std::int32_t* f = out.faces.data() + 3 * tf;
          const int nt3 = 3 * tb.n_tris[c];
          for (int k = 0; k < nt3; ++k) {
            const int e = tri[static_cast<std::size_t>(k)];
            const int sl = tb.edge_slot[static_cast<std::size_t>(e)];
            f[k] = static_cast<std::int32_t>(tb.edge_dx[static_cast<std::size_t>(e)] ? ctr[sl] : id0[sl]);
          }
          tf += tb.n_tris[c];
        });
      }
  });
  return out;
}

// ---- surface helpers ---------------------------------------------------------------------------
// Corners grouped by vertex: for each vertex its (prev, next) neighbours in
// each incident face, counter-clockwise.
struct Corners {
  BigArray<std::int64_t> offset;               // (V+1)
  BigArray<std::array<std::int32_t, 2>> pn;    // (3F): prev, next
};

Corners corners_by_vertex(const Surface& s) {
  const std::int64_t V = s.vertices.rows(), F = s.faces.rows();
  Corners c;
  c.offset = BigArray<std::int64_t>(static_cast<std::size_t>(V + 1));
  std::fill(c.offset.data(), c.offset.data() + V + 1, 0);
  const std::int32_t* fc = s.faces.data();
  for (std::int64_t i = 0; i < 3 * F; ++i) ++c.offset[static_cast<std::size_t>(fc[i]) + 1];
  for (std::int64_t v = 0; v < V; ++v) c.offset[static_cast<std::size_t>(v + 1)] += c.offset[static_cast<std::size_t>(v)];
  BigArray<std::int64_t> fill(static_cast<std::size_t>(V));
  std::copy(c.offset.data(), c.offset.data() + V, fill.data());
  c.pn = BigArray<std::array<std::int32_t, 2>>(static_cast<std::size_t>(3 * F));
  for (std::int64_t f = 0; f < F; ++f) {
    const std::int32_t a = fc[3 * f], b = fc[3 * f + 1], d = fc[3 * f + 2];
    c.pn[static_cast<std::size_t>(fill[static_cast<std::size_t>(a)]++)] = {d, b};
    c.pn[static_cast<std::size_t>(fill[static_cast<std::size_t>(b)]++)] = {a, d};
    c.pn[static_cast<std::size_t>(fill[static_cast<std::size_t>(d)]++)] = {b, a};
  }
  return c;
}

// volume and area in fixed blocks of faces summed in order: the same sums
// whatever the thread count
std::array<double, 2> volume_area(const Surface& s) {
  const Eigen::Index F = s.faces.rows(), B = 1 << 14;
  const Eigen::Index nb = (F + B - 1) / B;
  std::vector<std::array<double, 2>> part(static_cast<std::size_t>(nb), {0, 0});
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, nb), [&](const tbb::blocked_range<Eigen::Index>& r) {
    for (Eigen::Index b = r.begin(); b != r.end(); ++b) {
      double vol = 0, area = 0;
      for (Eigen::Index f = b * B; f < std::min(F, (b + 1) * B); ++f) {
        const Eigen::Vector3d a = s.vertices.row(s.faces(f, 0)), bb = s.vertices.row(s.faces(f, 1)), c = s.vertices.row(s.faces(f, 2));
        const Eigen::Vector3d n = (bb - a).cross(c - a);
        vol += a.dot(bb.cross(c));
        area += n.norm();
      }
      part[static_cast<std::size_t>(b)] = {vol / 6, area / 2};
    }
  });
  std::array<double, 2> t{0, 0};
  for (const auto& p : part) t[0] += p[0], t[1] += p[1];
  return t;
}

double signed_volume(const Surface& s) { return volume_area(s)[0]; }

}  // namespace

// ---- options -------------------------------------------------------------------------------------

// The most Taubin smoothing may grow the band it passes, over all iterations
// (validate below).
constexpr double kMaxTaubinGain = 1.1;

void validate(const SurfaceOptions& o) {
  auto bad = [](const std::string& m) { throw Error("", m); };
  if (!(o.sigma_vox >= 0 && o.sigma_vox <= 4)) bad("sigma: must be in [0, 4] voxels, got " + std::to_string(o.sigma_vox));
  if (!(o.iso > 0 && o.iso < 1)) bad("iso: must be in (0, 1), got " + std::to_string(o.iso));
  if (!(o.border_offset > 0 && o.border_offset <= 1))
    bad("border-offset: must be in (0, 1], got " + std::to_string(o.border_offset));
  if (o.smooth_iterations < 0 || o.smooth_iterations > 10000)
    bad("smooth-iterations: must be in [0, 10000], got " + std::to_string(o.smooth_iterations));
  if (!(o.taubin_lambda > 0 && o.taubin_lambda < 1))
    bad("taubin-lambda: must be in (0, 1), got " + std::to_string(o.taubin_lambda));
  if (!(o.taubin_mu > -1 && o.taubin_mu < -o.taubin_lambda))
    bad("taubin-mu: must be in (-1, -lambda), got " + std::to_string(o.taubin_mu));
  // Taubin's filter multiplies the mesh's frequency k (an eigenvalue of the
  // umbrella Laplacian, in [0, 2]) by f(k) = (1 - lambda k)(1 - mu k) per
  // iteration. Past 1/lambda it must not grow: |f(2)| <= 1 (lambda 0.99, mu
  // -0.995: f(2) = -2.9, surface hung or blew up). Its passband grows by
  // f(k*) = 1 + (lambda + mu)^2 / (4 |lambda mu|) > 1 per iteration, at
  // k* = (lambda + mu) / (2 lambda mu): over all iterations at most
  // kMaxTaubinGain (the defaults' 1000 iterations grew it 2.3x and the bone
  // 30 % in volume) (sweep of 2026-11-27)
  if (o.smooth_iterations > 0) {
    const auto num = [](double v) { return (std::ostringstream() << std::setprecision(4) << v).str(); };
    const double l = o.taubin_lambda, m = o.taubin_mu, f2 = (1 - 2 * l) * (1 - 2 * m);
    if (std::abs(f2) > 1)
      bad("taubin-lambda and --taubin-mu: lambda " + num(l) + " and mu " + num(m) +
          " grow the finest detail " + num(std::abs(f2)) +
          "x per iteration, |(1 - 2 lambda)(1 - 2 mu)| (at most 1: lambda nearer 0.5, or mu nearer -lambda)");
    const double peak = 1 + (l + m) * (l + m) / (4 * std::abs(l * m));
    const double gain = std::exp(o.smooth_iterations * std::log(peak));
    if (gain > kMaxTaubinGain)
      bad("smooth-iterations: " + std::to_string(o.smooth_iterations) + " iterations of lambda " + num(l) + ", mu " +
          num(m) + " grow the band Taubin passes " + num(gain) + "x (at most " + num(kMaxTaubinGain) + "x: at most " +
          std::to_string(static_cast<long long>(std::log(kMaxTaubinGain) / std::log(peak))) +
          " iterations, or mu nearer -lambda)");
  }
  if (o.target_faces < 0) bad("target-faces: must be >= 0, got " + std::to_string(o.target_faces));
  if (o.target_faces > 0 && o.target_faces < 4) bad("target-faces: must be 0 (keep all) or >= 4, got " + std::to_string(o.target_faces));
  if (!(o.nest_clearance_vox >= 0 && o.nest_clearance_vox <= 1))
    bad("nest-clearance: must be in [0, 1] voxels, got " + std::to_string(o.nest_clearance_vox));
  if (!(o.nest_gap_vox >= 0 && o.nest_gap_vox <= 0.5))
    bad("nest-gap: must be in [0, 0.5] voxels, got " + std::to_string(o.nest_gap_vox));
  if (!(o.min_component_voxels >= 0 && std::isfinite(o.min_component_voxels)))
    bad("min-component-voxels: must be >= 0 and finite, got " + std::to_string(o.min_component_voxels));
}

std::string surface_parameters_json(const SurfaceOptions& o) {
  nlohmann::json j;
  j["sigma_vox"] = o.sigma_vox;
  j["iso"] = o.iso;
  j["fill_holes"] = o.fill_holes;
  j["border_offset"] = o.border_offset;
  j["smooth_iterations"] = o.smooth_iterations;
  j["taubin_lambda"] = o.taubin_lambda;
  j["taubin_mu"] = o.taubin_mu;
  j["compensate_blur"] = o.compensate_blur;
  j["target_faces"] = o.target_faces;
  j["decimation"] = o.decimation == DecimationCost::lindstrom_turk ? "lindstrom_turk" : "garland_heckbert";
  j["bounded_normal_change"] = o.bounded_normal_change;
  j["check_self_intersections"] = o.check_self_intersections;
  j["nest_clearance_vox"] = o.nest_clearance_vox;
  j["nest_gap_vox"] = o.nest_gap_vox;
  j["min_component_voxels"] = o.min_component_voxels;
  return j.dump();
}

// ---- nesting -------------------------------------------------------------------------------------

std::vector<int> label_parents(const Volume& v, const TissueTable& table) {
  const int n = std::max<int>(static_cast<int>(v.label_names.size()), 1);
  std::vector<int> parent(static_cast<std::size_t>(n), 0);
  parent[0] = -1;
  for (int l = 1; l < n; ++l) {
    const std::string& name = v.label_names[static_cast<std::size_t>(l)];
    if (name.empty()) continue;
    const Tissue* t = table.find(name);
    if (!t) throw Error(table.path, "label '" + name + "' of the volume is not in the tissue table");
    // the nearest enclosing tissue that the volume has
    int p = 0;
    for (int guard = 0; t && !t->inside.empty() && guard <= static_cast<int>(table.tissues.size()); ++guard) {
      const int q = v.label_of(t->inside);
      if (q > 0) {
        p = q;
        break;
      }
      t = table.find(t->inside);
    }
    parent[static_cast<std::size_t>(l)] = p;
  }
  return parent;
}

std::vector<int> label_parents(const Volume& v) {
  int n = std::max<int>(static_cast<int>(v.label_names.size()), 1);
  for (std::uint8_t l : v.labels) n = std::max(n, l + 1);
  // voxel faces shared by each pair of labels, per slice then summed
  const std::size_t N = static_cast<std::size_t>(n);
  std::vector<std::vector<std::int64_t>> per(static_cast<std::size_t>(v.nz), std::vector<std::int64_t>(N * N, 0));
  tbb::parallel_for(tbb::blocked_range<int>(0, v.nz), [&](const tbb::blocked_range<int>& r) {
    for (int z = r.begin(); z != r.end(); ++z) {
      auto& c = per[static_cast<std::size_t>(z)];
      for (int y = 0; y < v.ny; ++y)
        for (int x = 0; x < v.nx; ++x) {
          const std::uint8_t a = v.at(x, y, z);
          auto add = [&](std::uint8_t b) {
            if (a != b) ++c[a * N + b], ++c[b * N + a];
          };
          if (x + 1 < v.nx) add(v.at(x + 1, y, z));
          if (y + 1 < v.ny) add(v.at(x, y + 1, z));
          if (z + 1 < v.nz) add(v.at(x, y, z + 1));
        }
    }
  });
  std::vector<std::int64_t> contact(N * N, 0), total(N, 0);
  for (const auto& c : per)
    for (std::size_t i = 0; i < N * N; ++i) contact[i] += c[i];
  for (std::size_t a = 0; a < N; ++a)
    for (std::size_t b = 0; b < N; ++b) total[a] += contact[a * N + b];
  // depth from the background over significant contacts (>= 2 % of a label's faces)
  const int kFar = INT_MAX / 2;
  std::vector<int> depth(N, kFar);
  depth[0] = 0;
  for (bool changed = true; changed;) {
    changed = false;
    for (std::size_t l = 1; l < N; ++l)
      for (std::size_t m = 0; m < N; ++m)
        if (depth[m] < kFar && contact[l * N + m] > 0 && 50 * contact[l * N + m] >= total[l] &&
            depth[m] + 1 < depth[l]) {
          depth[l] = depth[m] + 1;
          changed = true;
        }
  }
  // parent: the label sharing the most voxel faces (the background included)
  std::vector<int> parent(N, 0);
  parent[0] = -1;
  for (std::size_t l = 1; l < N; ++l) {
    std::int64_t best = contact[l * N];
    for (std::size_t m = 1; m < N; ++m)
      if (m != l && contact[l * N + m] > best) best = contact[l * N + m], parent[l] = static_cast<int>(m);
  }
  // cycles (two labels that each touch the other most): the shallowest
  // member of a cycle not yet re-parented takes the shallower label it
  // shares the most faces with. Re-parented labels point to strictly
  // shallower ones, so every cycle has a member left to re-parent.
  std::vector<char> fixed(N, 0);
  for (bool again = true; again;) {
    again = false;
    for (std::size_t start = 1; start < N && !again; ++start) {
      std::vector<char> seen(N, 0);
      std::size_t u = start;
      while (u != 0 && !seen[u]) seen[u] = 1, u = static_cast<std::size_t>(parent[u]);
      if (u == 0) continue;
      // u is on a cycle: pick its member to re-parent
      std::size_t pick = 0;
      std::size_t w = u;
      do {
        if (!fixed[w] && (pick == 0 || depth[w] < depth[pick] || (depth[w] == depth[pick] && contact[w * N] > contact[pick * N])))
          pick = w;
        w = static_cast<std::size_t>(parent[w]);
      } while (w != u);
      if (pick == 0) pick = u;  // cannot happen (see above); background as a last resort
      std::int64_t best = -1;
      int to = 0;
      for (std::size_t m = 0; m < N; ++m)
        if (m != pick && (m == 0 || depth[m] < depth[pick]) && contact[pick * N + m] > best)
          best = contact[pick * N + m], to = static_cast<int>(m);
      parent[pick] = fixed[pick] ? 0 : to;
      fixed[pick] = 1;
      again = true;
    }
  }
  return parent;
}

std::vector<int> solid_label_set(const Volume& v, const std::string& tissue, const std::vector<int>& parents) {
  const int l = v.label_of(tissue);
  if (l < 1 || tissue.empty()) {
    std::string have;
    for (std::size_t i = 1; i < v.label_names.size(); ++i)
      if (!v.label_names[i].empty()) have += (have.empty() ? "" : ", ") + v.label_names[i];
    throw Error("", "unknown tissue '" + tissue + "' (the volume has: " + (have.empty() ? "no tissues" : have) + ")");
  }
  std::vector<int> out;
  for (int u = 1; u < static_cast<int>(parents.size()); ++u) {
    int p = u;
    for (int guard = 0; p > 0 && p != l && guard <= static_cast<int>(parents.size()); ++guard) p = parents[static_cast<std::size_t>(p)];
    if (p == l) out.push_back(u);
  }
  if (std::find(out.begin(), out.end(), l) == out.end()) out.push_back(l);
  std::sort(out.begin(), out.end());
  return out;
}

// ---- smoothing and checks --------------------------------------------------------------------------

namespace {

void taubin_impl(Surface& s, const Corners& c, int iterations, double lambda, double mu,
                 const std::vector<std::uint8_t>& fixed_axes) {
  if (iterations <= 0 || s.faces.rows() == 0) return;
  const Eigen::Index V = s.vertices.rows();
  const bool use_fixed = static_cast<Eigen::Index>(fixed_axes.size()) == V;
  MatX3d tmp(V, 3);
  advise_huge_pages(tmp.data(), static_cast<std::size_t>(V) * 3 * sizeof(double));
  auto step = [&](const MatX3d& in, MatX3d& out, double f) {
    const double* __restrict P = in.data();
    double* __restrict Q = out.data();
    tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, V, 4096), [&](const tbb::blocked_range<Eigen::Index>& r) {
      for (Eigen::Index v = r.begin(); v != r.end(); ++v) {
        const std::int64_t b = c.offset[static_cast<std::size_t>(v)], e = c.offset[static_cast<std::size_t>(v + 1)];
        const double* p = P + 3 * v;
        double* o = Q + 3 * v;
        if (b == e) {
          o[0] = p[0], o[1] = p[1], o[2] = p[2];
          continue;
        }
        double m0 = 0, m1 = 0, m2 = 0;
        for (std::int64_t k = b; k < e; ++k) {
          const double* q = P + 3 * static_cast<std::int64_t>(c.pn[static_cast<std::size_t>(k)][1]);
          m0 += q[0], m1 += q[1], m2 += q[2];
        }
        const double inv = 1.0 / static_cast<double>(e - b);
        const unsigned fix = use_fixed ? fixed_axes[static_cast<std::size_t>(v)] : 0u;
        o[0] = fix & 1u ? p[0] : p[0] + f * (m0 * inv - p[0]);
        o[1] = fix & 2u ? p[1] : p[1] + f * (m1 * inv - p[1]);
        o[2] = fix & 4u ? p[2] : p[2] + f * (m2 * inv - p[2]);
      }
    });
  };
  for (int it = 0; it < iterations; ++it) {
    step(s.vertices, tmp, lambda);
    step(tmp, s.vertices, mu);
  }
}

void compensate_impl(Surface& s, const Corners& c, const std::array<double, 3>& spacing_m, double sigma_vox,
                     const std::vector<std::uint8_t>& fixed_axes) {
  if (!(sigma_vox > 0) || s.faces.rows() == 0) return;
  const Eigen::Index V = s.vertices.rows();
  const bool use_fixed = static_cast<Eigen::Index>(fixed_axes.size()) == V;
  const double sp[3] = {spacing_m[0], spacing_m[1], spacing_m[2]};
  const double inv[3] = {1 / sp[0], 1 / sp[1], 1 / sp[2]};
  // Vertices within two rings of a cap vertex are left alone: the cap rim is
  // a sharp edge of the solid that the blur did not round (values beyond the
  // border are replicated), so there is no shrinkage to undo there.
  std::vector<char> valid(static_cast<std::size_t>(V), 1);
  if (use_fixed) {
    std::vector<Eigen::Index> ring;
    for (Eigen::Index v = 0; v < V; ++v)
      if (fixed_axes[static_cast<std::size_t>(v)]) valid[static_cast<std::size_t>(v)] = 0, ring.push_back(v);
    for (int r = 0; r < 2; ++r) {
      std::vector<Eigen::Index> next;
      for (Eigen::Index v : ring)
        for (std::int64_t k = c.offset[static_cast<std::size_t>(v)]; k < c.offset[static_cast<std::size_t>(v + 1)]; ++k) {
          const auto u = static_cast<std::size_t>(c.pn[static_cast<std::size_t>(k)][1]);
          if (valid[u]) valid[u] = 0, next.push_back(static_cast<Eigen::Index>(u));
        }
      ring.swap(next);
    }
  }
  // Per vertex, in voxel-index space (where the blur was isotropic), from its
  // own corners: the cotangent Laplacian L = (1 / 2A) sum (cot a + cot b)
  // (q_i - q_j) = 2 H n with barycentric area A, the area-weighted normal n,
  // and H clamped to radii of at least 2 voxels.
  std::vector<double> H(static_cast<std::size_t>(V), 0.0), H2(static_cast<std::size_t>(V), 0.0);
  MatX3d N(V, 3);
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, V, 4096), [&](const tbb::blocked_range<Eigen::Index>& r) {
    for (Eigen::Index v = r.begin(); v != r.end(); ++v) {
      auto q = [&](std::int64_t id) {
        return Eigen::Vector3d(s.vertices(id, 0) * inv[0], s.vertices(id, 1) * inv[1], s.vertices(id, 2) * inv[2]);
      };
      const Eigen::Vector3d qi = q(v);
      Eigen::Vector3d L = Eigen::Vector3d::Zero(), n = Eigen::Vector3d::Zero();
      double area2 = 0;
      for (std::int64_t k = c.offset[static_cast<std::size_t>(v)]; k < c.offset[static_cast<std::size_t>(v + 1)]; ++k) {
        const Eigen::Vector3d qp = q(c.pn[static_cast<std::size_t>(k)][0]), qn = q(c.pn[static_cast<std::size_t>(k)][1]);
        const Eigen::Vector3d fn = (qn - qi).cross(qp - qi);  // face (p, i, n), counter-clockwise: i -> n -> p
        const double a2 = fn.norm();
        if (!(a2 > 1e-12)) continue;
        // edge (i, n) is opposite corner p, edge (i, p) opposite corner n
        const double cot_p = std::clamp((qi - qp).dot(qn - qp) / a2, -10.0, 10.0);
        const double cot_n = std::clamp((qi - qn).dot(qp - qn) / a2, -10.0, 10.0);
        L += cot_p * (qi - qn) + cot_n * (qi - qp);
        n += fn;
        area2 += a2;
      }
      const double nn = n.norm();
      if (nn > 0) n /= nn;
      N.row(v) = n.transpose();
      // A = area2 / 6, L / (2 A) = 2 H n
      H[static_cast<std::size_t>(v)] =
          valid[static_cast<std::size_t>(v)] && area2 > 0 && nn > 0 ? std::clamp(1.5 * L.dot(n) / area2, -0.5, 0.5) : 0.0;
    }
  });
  // averaged over 16 rings of valid neighbours: the bias is a smooth
  // function of the shape, the estimate on a voxel-scale mesh is noisy
  for (int it = 0; it < 16; ++it) {
    tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, V, 4096), [&](const tbb::blocked_range<Eigen::Index>& r) {
      for (Eigen::Index v = r.begin(); v != r.end(); ++v) {
        if (!valid[static_cast<std::size_t>(v)]) {
          H2[static_cast<std::size_t>(v)] = 0;
          continue;
        }
        double sum = H[static_cast<std::size_t>(v)];
        int n = 1;
        for (std::int64_t k = c.offset[static_cast<std::size_t>(v)]; k < c.offset[static_cast<std::size_t>(v + 1)]; ++k) {
          const auto u = static_cast<std::size_t>(c.pn[static_cast<std::size_t>(k)][1]);
          if (valid[u]) sum += H[u], ++n;
        }
        H2[static_cast<std::size_t>(v)] = sum / n;
      }
    });
    H.swap(H2);
  }
  // the 0.5 level of a Gaussian-blurred indicator lies sigma^2 H inside the surface
  const double s2 = sigma_vox * sigma_vox;
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, V, 4096), [&](const tbb::blocked_range<Eigen::Index>& r) {
    for (Eigen::Index v = r.begin(); v != r.end(); ++v) {
      const unsigned fix = use_fixed ? fixed_axes[static_cast<std::size_t>(v)] : 0u;
      for (int d = 0; d < 3; ++d)
        if (!((fix >> d) & 1u)) s.vertices(v, d) += s2 * H[static_cast<std::size_t>(v)] * N(v, d) * sp[d];
    }
  });
}

SurfaceMetrics check_impl(const Surface& s, const Corners* corners, bool self_intersections,
                          std::vector<std::array<std::int64_t, 2>>* pairs = nullptr) {
  SurfaceMetrics m;
  const std::int64_t V = s.vertices.rows(), F = s.faces.rows();
  m.vertices = V, m.faces = F;
  if (V == 0 || F == 0) return m;
  for (std::int64_t f = 0; f < F; ++f)
    for (int k = 0; k < 3; ++k)
      if (s.faces(f, k) < 0 || s.faces(f, k) >= V) return m;  // not even a mesh
  Corners own;
  if (!corners) own = corners_by_vertex(s);
  const Corners& c = corners ? *corners : own;
  // Per vertex, from its own corners only: the half-edges leaving v are the
  // corners' next vertices, those arriving the corners' previous vertices. A
  // closed, consistently oriented surface has each leaving half-edge v->n
  // once and its opposite n->v once, i.e. the nexts are distinct, the prevs
  // are distinct and both are the same set. Manifold: the corners chain into
  // one fan (from a corner with next n to the corner whose prev is n).
  // Integer counts: the same sums in any order.
  struct Counts {
    std::int64_t bad_edges = 0, bad_fans = 0, isolated = 0, edges = 0, unmatched = 0;
  };
  auto count = [&](const tbb::blocked_range<std::int64_t>& r, Counts n) {
    for (std::int64_t v = r.begin(); v != r.end(); ++v) {
      const std::int64_t b = c.offset[static_cast<std::size_t>(v)], e = c.offset[static_cast<std::size_t>(v + 1)];
      if (b == e) {
        ++n.isolated;
        continue;
      }
      // walk: from corner k to the one corner whose prev is k's next. Each
      // step finding exactly one such corner and the walk visiting every
      // corner once before it returns means: the nexts are distinct, the
      // prevs are distinct, every next is a prev (closed, oriented), and the
      // faces form a single fan (manifold).
      const std::int64_t val = e - b;
      bool ok = true, one_fan = true;
      char small[64] = {};
      std::vector<char> large(val > 64 ? static_cast<std::size_t>(val) : 0, 0);
      char* seen = val > 64 ? large.data() : small;
      std::int64_t k = b, visited = 0;
      for (std::int64_t step = 0; ok && step < val; ++step) {
        const std::int32_t nx = c.pn[static_cast<std::size_t>(k)][1], pv = c.pn[static_cast<std::size_t>(k)][0];
        if (nx == v || pv == v || nx == pv) ok = false;  // degenerate face
        std::int64_t match = -1;
        int matches = 0;
        for (std::int64_t q = b; q < e; ++q)
          if (c.pn[static_cast<std::size_t>(q)][0] == nx) match = q, ++matches;
        if (matches != 1) {
          ok = false;
          n.unmatched += matches == 0;
          break;
        }
        if (seen[k - b]) one_fan = false;
        else seen[k - b] = 1, ++visited;
        k = match;
      }
      if (ok && (k != b || visited != val)) one_fan = false;
      if (ok && !one_fan)  // several fans: the corners the walk missed still need their match
        for (std::int64_t q = b; q < e && ok; ++q) {
          int matches = 0;
          for (std::int64_t u = b; u < e; ++u) matches += c.pn[static_cast<std::size_t>(u)][0] == c.pn[static_cast<std::size_t>(q)][1];
          if (matches != 1) ok = false, n.unmatched += matches == 0;
        }
      for (std::int64_t q = b; q < e; ++q) n.edges += v < c.pn[static_cast<std::size_t>(q)][1];
      if (!ok) ++n.bad_edges;
      else if (!one_fan) ++n.bad_fans;
    }
    return n;
  };
  const Counts n = tbb::parallel_reduce(
      tbb::blocked_range<std::int64_t>(0, V, 8192), Counts{}, count, [](Counts a, const Counts& b) {
        a.bad_edges += b.bad_edges, a.bad_fans += b.bad_fans, a.isolated += b.isolated, a.edges += b.edges;
        a.unmatched += b.unmatched;
        return a;
      });
  m.closed = n.bad_edges == 0 && n.unmatched == 0;
  m.manifold = m.closed && n.bad_fans == 0 && n.isolated == 0;
  m.euler = static_cast<int>(V - n.edges + F);
  // components
  BigArray<std::int32_t> up(static_cast<std::size_t>(V));
  vertex_components(s, up.data());
  int comps = 0;
  for (std::int64_t v = 0; v < V; ++v)
    if (up[static_cast<std::size_t>(v)] == v && c.offset[static_cast<std::size_t>(v)] != c.offset[static_cast<std::size_t>(v + 1)]) ++comps;
  m.components = comps;
  const auto va = volume_area(s);
  m.volume_m3 = va[0];
  m.area_m2 = va[1];
  m.outward = m.volume_m3 > 0;
  if (self_intersections && m.closed) {
    std::vector<std::array<std::int64_t, 2>> found = surface_self_intersection_pairs(s);
    m.self_intersections = static_cast<std::int64_t>(found.size());
    if (pairs) *pairs = std::move(found);
  }
  return m;
}

}  // namespace

void taubin_smooth(Surface& s, int iterations, double lambda, double mu, const std::vector<std::uint8_t>& fixed_axes) {
  if (iterations <= 0 || s.faces.rows() == 0) return;
  taubin_impl(s, corners_by_vertex(s), iterations, lambda, mu, fixed_axes);
}

void compensate_blur(Surface& s, const std::array<double, 3>& spacing_m, double sigma_vox,
                     const std::vector<std::uint8_t>& fixed_axes) {
  if (!(sigma_vox > 0) || s.faces.rows() == 0) return;
  compensate_impl(s, corners_by_vertex(s), spacing_m, sigma_vox, fixed_axes);
}

SurfaceMetrics check_surface(const Surface& s, bool self_intersections) { return check_impl(s, nullptr, self_intersections); }

MatX3d surface_samples(const Surface& s) {
  const Eigen::Index V = s.vertices.rows(), F = s.faces.rows();
  std::vector<std::array<std::int32_t, 2>> edges;  // half-edges a -> b with a < b: each edge of a closed surface once
  edges.reserve(static_cast<std::size_t>(3 * F / 2 + 1));
  for (Eigen::Index f = 0; f < F; ++f)
    for (int k = 0; k < 3; ++k) {
      const std::int32_t a = s.faces(f, k), b = s.faces(f, (k + 1) % 3);
      if (a < b) edges.push_back({a, b});
    }
  MatX3d p(V + F + static_cast<Eigen::Index>(edges.size()), 3);
  p.topRows(V) = s.vertices;
  for (Eigen::Index f = 0; f < F; ++f)
    p.row(V + f) = (s.vertices.row(s.faces(f, 0)) + s.vertices.row(s.faces(f, 1)) + s.vertices.row(s.faces(f, 2))) / 3.0;
  for (std::size_t e = 0; e < edges.size(); ++e)
    p.row(V + F + static_cast<Eigen::Index>(e)) = 0.5 * (s.vertices.row(edges[e][0]) + s.vertices.row(edges[e][1]));
  return p;
}

// ---- the pipeline ------------------------------------------------------------------------------------

std::vector<CapPlane> cap_planes(const Volume& v, const SurfaceOptions& o) {
  // half-way into the padding, as march places a cap vertex
  std::vector<CapPlane> planes;
  for (int k = 0; k < 3; ++k) {
    const int n = k == 0 ? v.nx : k == 1 ? v.ny : v.nz;
    const double reach = (blur_radius(o.sigma_vox) + 1) * v.spacing_m[static_cast<std::size_t>(k)];
    planes.push_back({k, 0.5 * (axis_coord(v, o, k, -1) + axis_coord(v, o, k, 0)), reach});
    planes.push_back({k, 0.5 * (axis_coord(v, o, k, n - 1) + axis_coord(v, o, k, n)), reach});
  }
  return planes;
}

SurfaceResult extract_surface(const Volume& v, const std::vector<int>& solid_labels, const SurfaceOptions& o,
                              const std::vector<int>& parent_labels) {
  validate(o);
  if (v.nx < 1 || v.ny < 1 || v.nz < 1 ||
      v.labels.size() != static_cast<std::size_t>(v.nx) * static_cast<std::size_t>(v.ny) * static_cast<std::size_t>(v.nz))
    throw Error("", "volume: labels do not match its size");
  for (int k = 0; k < 3; ++k)
    if (!(v.spacing_m[static_cast<std::size_t>(k)] > 0) || !std::isfinite(v.spacing_m[static_cast<std::size_t>(k)]))
      throw Error("", "volume: spacing must be positive");
  for (const auto* set : {&solid_labels, &parent_labels})
    for (int l : *set)
      if (l < 1 || l > 255) throw Error("", "solid label " + std::to_string(l) + " is not in 1..255");

  SurfaceResult res;
  SurfaceMetrics& m = res.metrics;
  auto t0 = Clock::now();
  const int w = blur_radius(o.sigma_vox);
  // with a parent, a margin of 2w + 1: the parent's field within w of this
  // solid then comes from the parent's voxels, not from the box's border
  const bool gap = !parent_labels.empty() && o.nest_gap_vox > 0 && o.sigma_vox > 0;
  Grid g = build_solid(v, solid_labels, o, (gap ? 2 : 1) * w + 1, m.solid_voxels, m.filled_voxels);
  m.solid_s = since(t0);

  Surface s;
  std::vector<std::uint8_t> fixed;  // cap vertices: axes they must not move along
  if (o.sigma_vox > 0) {
    t0 = Clock::now();
    SmoothField sf;
    smooth_field(g, o.sigma_vox, o.iso, sf);
    if (gap) {
      // the parent's solid on this grid, with this solid's filled pockets
      std::int64_t unused_solid = 0, unused_filled = 0;
      Grid gp = build_solid(v, parent_labels, o, 0, unused_solid, unused_filled, &g);
      tbb::parallel_for(std::size_t{0}, g.rows(), [&](std::size_t i) {
        if (g.one_lo[i] > g.one_hi[i]) return;
        std::uint8_t* dst = gp.row(i);
        const std::uint8_t* src = g.row(i);
        for (int x = g.one_lo[i]; x <= g.one_hi[i]; ++x) dst[x] |= src[x];
        gp.one_lo[i] = std::min(gp.one_lo[i], g.one_lo[i]);
        gp.one_hi[i] = std::max(gp.one_hi[i], g.one_hi[i]);
      });
      SmoothField sp;
      smooth_field(gp, o.sigma_vox, o.iso, sp);
      // the level of the parent's field nest_gap_vox voxels inside its own
      // (iso) level: across a boundary midway between voxel centres the
      // blurred indicator's samples either side are Phi(+-1/2 sigma), so its
      // linear interpolation rises by erf(1 / (2 sqrt(2) sigma)) a voxel
      m.gap_samples = clip_field(sf, sp, o.nest_gap_vox * std::erf(1 / (2 * std::sqrt(2.0) * o.sigma_vox)), o.iso);
    }
    m.field_s = since(t0);
    t0 = Clock::now();
    s = march(g, sf.F, o.iso, fixed);
    m.extract_s = since(t0);
  } else {
    t0 = Clock::now();
    const RowField<std::uint8_t> F = binary_field(g);
    m.field_s = since(t0);
    t0 = Clock::now();
    s = march(g, F, o.iso, fixed);
    m.extract_s = since(t0);
  }
  if (s.faces.rows() == 0) throw Error("", "the solid has no surface at this iso level (smoothed away)");
  if (o.min_component_voxels > 0)
    drop_small_components(s, fixed, o.min_component_voxels * v.spacing_m[0] * v.spacing_m[1] * v.spacing_m[2],
                          m.dropped_components, m.dropped_volume_m3);
  m.extracted_faces = s.faces.rows();

  t0 = Clock::now();
  std::optional<Corners> corners;  // of the extracted surface, shared by smoothing and the check
  if (o.smooth_iterations > 0 || (o.compensate_blur && o.sigma_vox > 0) || o.target_faces == 0 || s.faces.rows() <= o.target_faces)
    corners.emplace(corners_by_vertex(s));
  if (o.smooth_iterations > 0) {
    const double before = signed_volume(s);
    taubin_impl(s, *corners, o.smooth_iterations, o.taubin_lambda, o.taubin_mu, fixed);
    m.smooth_volume_change = (signed_volume(s) - before) / before;
  }
  if (o.compensate_blur && o.sigma_vox > 0) compensate_impl(s, *corners, v.spacing_m, o.sigma_vox, fixed);
  // Nothing lies beyond the volume's border: Taubin's inflating (mu) pass and
  // the blur compensation's push along the normals carry rim vertices past a
  // flat cap's plane where a jagged (misregistered) wall meets it; such a cap
  // no longer ends the limb for remesh ("not tube-like": 20 skin vertices past
  // the caps of a stack shifted by a pixel a slice, the stack 60 mm long and
  // the axis found 75 mm). Those vertices go back to 1 % of a spacing inside
  // the plane (never onto it: a rim vertex in the cap's plane could overlap
  // the cap's faces); the cap vertices themselves never move along their axis.
  if (o.smooth_iterations > 0 || (o.compensate_blur && o.sigma_vox > 0))
    for (std::size_t k = 0; const CapPlane& pl : cap_planes(v, o)) {
      const double inside = 0.01 * v.spacing_m[static_cast<std::size_t>(pl.axis)];
      const bool low = k++ % 2 == 0;  // cap_planes: each axis's low plane, then its high one
      const double bound = low ? pl.at + inside : pl.at - inside;
      for (Eigen::Index i = 0; i < s.vertices.rows(); ++i) {
        if (fixed.size() == static_cast<std::size_t>(s.vertices.rows()) && (fixed[static_cast<std::size_t>(i)] >> pl.axis & 1u))
          continue;
        double& x = s.vertices(i, pl.axis);
        if (low ? x < bound : x > bound) x = bound, ++m.clamped_to_caps;
      }
    }
  m.smooth_s = since(t0);

  t0 = Clock::now();
  if (o.target_faces > 0 && s.faces.rows() > o.target_faces) {
    s = decimate_surface(s, o.target_faces, o.decimation, o.bounded_normal_change);
    corners.reset();
  }
  m.decimate_s = since(t0);

  t0 = Clock::now();
  const SurfaceMetrics c = check_impl(s, corners ? &*corners : nullptr, o.check_self_intersections, &res.intersecting_pairs);
  m.check_s = since(t0);
  m.faces = c.faces, m.vertices = c.vertices, m.volume_m3 = c.volume_m3, m.area_m2 = c.area_m2;
  m.euler = c.euler, m.components = c.components, m.closed = c.closed, m.manifold = c.manifold;
  m.outward = c.outward, m.self_intersections = c.self_intersections;
  if (!m.closed || !m.manifold || !m.outward)
    throw std::logic_error(std::string("surface: extracted surface is not ") +
                           (!m.closed ? "closed" : !m.manifold ? "manifold" : "outward") + " (internal error)");
  res.surface = std::move(s);
  return res;
}

}  // namespace orthosim
