// Exact point-in-closed-surface classification by ray parity, with no
// spatial tree: the rays run along one coordinate axis, so the triangles a
// ray can cross are those whose projection onto the other two coordinates
// covers the point, found in a flat grid of that projection (counting sort).
//
// Exactness. All tests are CGAL's filtered exact predicates on the input
// doubles (orientation in 2D and 3D), so no tolerance is involved:
// - a point exactly on a triangle (vertex, edge or interior) is on the
//   surface, and counts as inside;
// - otherwise the point is moved symbolically by (eps, eps^2) in the
//   projection plane (simulation of simplicity): the moved ray meets no
//   vertex or edge of the surface, two triangles sharing an edge agree on
//   which of them it crosses (the tie-break is antisymmetric in the edge's
//   ends), and triangles parallel to the ray are never crossed. The parity
//   of the crossings beyond the point is then exact for any closed,
//   consistently oriented surface, including voxel surfaces whose vertices
//   share coordinates with the points (the segmented sample's layers touch
//   on their common cap planes).
#include "libmodel/remesh/remesh.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <numeric>
#include <vector>

namespace orthosim {

namespace {

using K = CGAL::Exact_predicates_inexact_constructions_kernel;
using P2 = K::Point_2;
using P3 = K::Point_3;

int orient2(double ux, double uy, double vx, double vy, double qx, double qy) {
  return static_cast<int>(CGAL::orientation(P2(ux, uy), P2(vx, vy), P2(qx, qy)));
}

// orientation of (u, v, q + (eps, eps^2)): the exact one, else the sign of
// its eps term, else of its eps^2 term (u != v in projection)
int orient2_sos(double ux, double uy, double vx, double vy, double qx, double qy, int* exact) {
  const int o = orient2(ux, uy, vx, vy, qx, qy);
  *exact = o;
  if (o != 0) return o;
  if (uy != vy) return uy > vy ? 1 : -1;
  return vx > ux ? 1 : -1;
}

// point p exactly on the closed triangle (a, b, c), any shape
bool on_triangle(const P3& a, const P3& b, const P3& c, const P3& p) {
  // four points with one coordinate equal are coplanar (exact, and the common
  // case of a voxel surface or a flat cap, where the filtered predicate would
  // fall back to exact arithmetic to find the zero)
  bool flat = false;
  for (int k = 0; k < 3 && !flat; ++k) flat = a[k] == b[k] && b[k] == c[k] && c[k] == p[k];
  if (!flat && CGAL::orientation(a, b, c, p) != CGAL::COPLANAR) return false;
  for (int drop = 0; drop < 3; ++drop) {
    const int i = (drop + 1) % 3, j = (drop + 2) % 3;
    const int s = orient2(a[i], a[j], b[i], b[j], c[i], c[j]);
    if (s == 0) continue;
    // the plane projects one-to-one onto this coordinate plane
    return s * orient2(a[i], a[j], b[i], b[j], p[i], p[j]) >= 0 && s * orient2(b[i], b[j], c[i], c[j], p[i], p[j]) >= 0 &&
           s * orient2(c[i], c[j], a[i], a[j], p[i], p[j]) >= 0;
  }
  // collinear corners: on one of the three segments
  return K::Segment_3(a, b).has_on(p) || K::Segment_3(b, c).has_on(p) || K::Segment_3(c, a).has_on(p);
}

// Axis-aligned bounding box of each face (both grids below read them).
struct FaceBox {
  FaceBox() {}  // left unset: face_boxes writes every entry
  std::array<double, 3> lo, hi;
};
std::vector<FaceBox> face_boxes(const Surface& s) {
  std::vector<FaceBox> b(static_cast<std::size_t>(s.faces.rows()));
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, s.faces.rows(), 4096), [&](const auto& r) {
    for (Eigen::Index f = r.begin(); f != r.end(); ++f) {
      FaceBox& x = b[static_cast<std::size_t>(f)];
      for (int a = 0; a < 3; ++a) {
        const double p = s.vertices(s.faces(f, 0), a), q = s.vertices(s.faces(f, 1), a), w = s.vertices(s.faces(f, 2), a);
        x.lo[a] = std::min({p, q, w}), x.hi[a] = std::max({p, q, w});
      }
    }
  });
  return b;
}

class ParityGrid {
 public:
  // faces_per_cell: the mean number of faces per cell of the box; more cells
  // cost more span entries to build, fewer a longer list per ray
  ParityGrid(const Surface& s, const std::vector<FaceBox>& box, double faces_per_cell) : s_(s), box_(box) {
    const int nf = static_cast<int>(s.faces.rows());
    const Eigen::Vector3d lo = s.vertices.colwise().minCoeff(), hi = s.vertices.colwise().maxCoeff();
    // rays along the axis of least extent: across a limb, not along it
    Eigen::Index ax = 0;
    (hi - lo).minCoeff(&ax);
    a_ = static_cast<int>(ax), b_ = (a_ + 1) % 3, c_ = (a_ + 2) % 3;  // (a, b, c) cyclic: n_a = orient2_bc
    lo_ = lo, hi_ = hi;
    const double eb = hi[b_] - lo[b_], ec = hi[c_] - lo[c_];
    const double h = std::sqrt(std::max(eb * ec, 1e-300) / std::max(1.0, nf / faces_per_cell));
    nb_ = std::clamp(static_cast<int>(eb / h) + 1, 1, 4096);
    nc_ = std::clamp(static_cast<int>(ec / h) + 1, 1, 4096);
    ib_ = nb_ / std::max(eb, 1e-300), ic_ = nc_ / std::max(ec, 1e-300);
    std::vector<std::array<int, 4>> span(static_cast<std::size_t>(nf));
    std::vector<int> count(static_cast<std::size_t>(nb_) * nc_ + 1, 0);
    for (int f = 0; f < nf; ++f) {
      const FaceBox& x = box[static_cast<std::size_t>(f)];
      // a point at b lies in cell cell_b(b), which is monotone in b: every
      // point inside the face's projected box finds the face
      auto& sp = span[static_cast<std::size_t>(f)];
      sp = {cell_b(x.lo[b_]), cell_b(x.hi[b_]), cell_c(x.lo[c_]), cell_c(x.hi[c_])};
      for (int i = sp[0]; i <= sp[1]; ++i)
        for (int j = sp[2]; j <= sp[3]; ++j) ++count[static_cast<std::size_t>(i) * nc_ + j + 1];
    }
    for (std::size_t k = 1; k < count.size(); ++k) count[k] += count[k - 1];
    start_ = count;
    face_.resize(static_cast<std::size_t>(count.back()));
    for (int f = 0; f < nf; ++f) {
      const auto& sp = span[static_cast<std::size_t>(f)];
      for (int i = sp[0]; i <= sp[1]; ++i)
        for (int j = sp[2]; j <= sp[3]; ++j) face_[static_cast<std::size_t>(count[static_cast<std::size_t>(i) * nc_ + j]++)] = f;
    }
  }

  // true when p is inside or on the surface
  bool inside(const Eigen::Vector3d& p) const {
    for (int k = 0; k < 3; ++k)
      if (!(p(k) >= lo_(k) && p(k) <= hi_(k))) return false;  // outside the box (or NaN)
    const std::size_t cell = static_cast<std::size_t>(cell_b(p(b_))) * nc_ + cell_c(p(c_));
    const P3 P(p(0), p(1), p(2));
    const double pa = p(a_), pb = p(b_), pc = p(c_);
    int crossings = 0;
    for (int q = start_[cell]; q < start_[cell + 1]; ++q) {
      const int f = face_[static_cast<std::size_t>(q)];
      const FaceBox& x = box_[static_cast<std::size_t>(f)];
      if (x.hi[a_] < pa) continue;  // wholly behind the ray's start
      if (pb < x.lo[b_] || pb > x.hi[b_] || pc < x.lo[c_] || pc > x.hi[c_]) continue;
      const auto V = [&](int k) {
        const double* v = s_.vertices.data() + 3 * static_cast<std::ptrdiff_t>(s_.faces(f, k));
        return P3(v[0], v[1], v[2]);
      };
      const P3 A = V(0), B = V(1), Cc = V(2);
      // a projection onto a line of constant b or c is degenerate (exact; it
      // spares the filtered predicate its exact fallback on axis-aligned faces)
      const bool flat = (A[b_] == B[b_] && B[b_] == Cc[b_]) || (A[c_] == B[c_] && B[c_] == Cc[c_]);
      const int s = flat ? 0 : orient2(A[b_], A[c_], B[b_], B[c_], Cc[b_], Cc[c_]);
      if (s == 0) {
        // parallel to the ray: never crossed by the moved ray; p may lie on it
        // (only where p is within the face's extent along the ray)
        if (pa >= x.lo[a_] && on_triangle(A, B, Cc, P)) return true;
        continue;
      }
      int e0 = 0, e1 = 0, e2 = 0;
      const int o0 = orient2_sos(A[b_], A[c_], B[b_], B[c_], pb, pc, &e0);
      const int o1 = orient2_sos(B[b_], B[c_], Cc[b_], Cc[c_], pb, pc, &e1);
      const int o2 = orient2_sos(Cc[b_], Cc[c_], A[b_], A[c_], pb, pc, &e2);
      const bool closed_in = e0 * s >= 0 && e1 * s >= 0 && e2 * s >= 0;
      if (!closed_in) continue;  // then the moved point is outside too
      const int o3 = static_cast<int>(CGAL::orientation(A, B, Cc, P));
      if (o3 == 0) return true;  // on the plane, over the closed triangle: on it
      if (o0 == s && o1 == s && o2 == s && o3 != s) ++crossings;  // crossed beyond p
    }
    return (crossings & 1) != 0;
  }

 private:
  int cell_b(double b) const { return std::clamp(static_cast<int>((b - lo_(b_)) * ib_), 0, nb_ - 1); }
  int cell_c(double c) const { return std::clamp(static_cast<int>((c - lo_(c_)) * ic_), 0, nc_ - 1); }

  int a_ = 0, b_ = 1, c_ = 2, nb_ = 1, nc_ = 1;
  double ib_ = 1, ic_ = 1;
  Eigen::Vector3d lo_, hi_;
  const Surface& s_;
  const std::vector<FaceBox>& box_;
  std::vector<int> start_, face_;
};

// Empty cells of a box grid over the surface. A cell that no face's bounding
// box reaches holds no point of the surface, and the cell of a point is
// monotone in each coordinate, so the points that fall in one cell form a box
// and the points of two face-adjacent cells form a box too. A set of empty
// cells connected through their faces therefore holds points of one side
// only: one exact ray test (of its first point in point order) answers for
// every point in it. Points in occupied cells take their own ray. The answer
// is the exact test's, whatever the cell size; the size only moves work
// between the two paths: twice the mean edge (of a sample of faces), so that
// a point a few edges inside the surface finds an empty cell, and at most
// kCellsPerFace cells per face, so that a fine mesh of a large box does not
// grow the grid beyond the surface's own size.
class EmptyCells {
 public:
  static constexpr double kCellsPerFace = 4;

  EmptyCells(const Surface& s, const std::vector<FaceBox>& box) {
    const Eigen::Index nf = s.faces.rows();
    lo_ = s.vertices.colwise().minCoeff(), hi_ = s.vertices.colwise().maxCoeff();
    // the mean edge of at most 4 096 faces spread over the list
    const Eigen::Index stride = std::max<Eigen::Index>(1, nf / 4096);
    double edges = 0;
    Eigen::Index sampled = 0;
    for (Eigen::Index f = 0; f < nf; f += stride, ++sampled)
      for (int k = 0; k < 3; ++k) edges += (s.vertices.row(s.faces(f, k)) - s.vertices.row(s.faces(f, (k + 1) % 3))).norm();
    const Eigen::Vector3d ext = (hi_ - lo_).cwiseMax(1e-300);
    double h = 2 * edges / (3.0 * static_cast<double>(std::max<Eigen::Index>(sampled, 1)));
    auto cells_at = [&](double hh) {
      double n = 1;
      for (int a = 0; a < 3; ++a) n *= std::min(4096.0, std::floor(ext(a) / hh) + 1);
      return n;
    };
    const double cap = kCellsPerFace * static_cast<double>(nf) + 64;
    if (!(h > 0)) h = ext.maxCoeff();
    while (cells_at(h) > cap) h *= 1.25;
    for (int a = 0; a < 3; ++a) {
      n_[a] = static_cast<int>(std::min(4096.0, std::floor(ext(a) / h) + 1));
      inv_[a] = n_[a] / ext(a);
    }
    const std::size_t ncell = static_cast<std::size_t>(n_[0]) * n_[1] * n_[2];
    std::vector<unsigned char> occupied(ncell, 0);
    for (const FaceBox& x : box) {
      std::array<int, 3> c0, c1;
      for (int a = 0; a < 3; ++a) c0[a] = cell(x.lo[a], a), c1[a] = cell(x.hi[a], a);
      for (int k = c0[2]; k <= c1[2]; ++k)
        for (int j = c0[1]; j <= c1[1]; ++j)
          for (int i = c0[0]; i <= c1[0]; ++i) occupied[index(i, j, k)] = 1;
    }
    // runs of empty cells along x, joined across rows by union-find
    struct Run {
      int x0, x1;
    };
    const int nrow = n_[1] * n_[2];
    std::vector<Run> runs;
    std::vector<int> row_start(static_cast<std::size_t>(nrow) + 1, 0), parent;
    for (int r = 0; r < nrow; ++r) {
      row_start[static_cast<std::size_t>(r)] = static_cast<int>(runs.size());
      const unsigned char* row = occupied.data() + static_cast<std::size_t>(r) * n_[0];
      for (int i = 0; i < n_[0];) {
        if (row[i]) {
          ++i;
          continue;
        }
        const int i0 = i;
        while (i < n_[0] && !row[i]) ++i;
        runs.push_back({i0, i - 1});
      }
    }
    row_start[static_cast<std::size_t>(nrow)] = static_cast<int>(runs.size());
    parent.resize(runs.size());
    std::iota(parent.begin(), parent.end(), 0);
    auto find = [&](int a) {
      while (parent[static_cast<std::size_t>(a)] != a)
        a = parent[static_cast<std::size_t>(a)] = parent[static_cast<std::size_t>(parent[static_cast<std::size_t>(a)])];
      return a;
    };
    auto join_rows = [&](int r, int q) {  // runs of row r with the overlapping runs of row q
      int a = row_start[static_cast<std::size_t>(r)], b = row_start[static_cast<std::size_t>(q)];
      const int ae = row_start[static_cast<std::size_t>(r) + 1], be = row_start[static_cast<std::size_t>(q) + 1];
      while (a < ae && b < be) {
        const Run &ra = runs[static_cast<std::size_t>(a)], &rb = runs[static_cast<std::size_t>(b)];
        if (ra.x0 <= rb.x1 && rb.x0 <= ra.x1) {
          const int x = find(a), y = find(b);
          if (x != y) parent[static_cast<std::size_t>(std::max(x, y))] = std::min(x, y);
        }
        if (ra.x1 < rb.x1)
          ++a;
        else
          ++b;
      }
    };
    for (int r = 0; r < nrow; ++r) {
      if (r % n_[1] > 0) join_rows(r, r - 1);      // the row below in y
      if (r >= n_[1]) join_rows(r, r - n_[1]);     // the row below in z
    }
    component_.assign(ncell, -1);
    std::vector<int> id(runs.size(), -1);
    for (int r = 0; r < nrow; ++r)
      for (int a = row_start[static_cast<std::size_t>(r)]; a < row_start[static_cast<std::size_t>(r) + 1]; ++a) {
        int& c = id[static_cast<std::size_t>(find(a))];
        if (c < 0) c = n_components_++;
        const Run& ra = runs[static_cast<std::size_t>(a)];
        std::fill_n(component_.begin() + static_cast<std::ptrdiff_t>(static_cast<std::size_t>(r) * n_[0] + ra.x0),
                    ra.x1 - ra.x0 + 1, c);
      }
  }

  int components() const { return n_components_; }
  // the component of the empty cell holding p, -1 when p's cell is occupied,
  // p lies outside the surface's box or is not finite
  int component(const Eigen::Vector3d& p) const {
    for (int a = 0; a < 3; ++a)
      if (!(p(a) >= lo_(a) && p(a) <= hi_(a))) return -1;
    return component_[index(cell(p(0), 0), cell(p(1), 1), cell(p(2), 2))];
  }

 private:
  // monotone in x (a point and a face's box corner map alike)
  int cell(double x, int a) const {
    const double t = (x - lo_(a)) * inv_[a];
    return t > 0 ? (t < n_[a] ? static_cast<int>(t) : n_[a] - 1) : 0;
  }
  std::size_t index(int i, int j, int k) const {
    return (static_cast<std::size_t>(k) * n_[1] + j) * n_[0] + i;
  }

  Eigen::Vector3d lo_, hi_;
  std::array<int, 3> n_{1, 1, 1};
  std::array<double, 3> inv_{1, 1, 1};
  std::vector<int> component_;
  int n_components_ = 0;
};

}  // namespace

std::vector<char> points_inside(const Surface& closed, const MatX3d& points, ContainmentStats* stats) {
  std::vector<char> in(static_cast<std::size_t>(points.rows()), 0);
  if (stats) *stats = ContainmentStats{points.rows(), 0, 0};
  if (points.rows() == 0 || closed.faces.rows() == 0) return in;
  // a surface it cannot read is refused (its closedness is the caller's check)
  if (!closed.vertices.allFinite()) throw Error("", "containment: the surface has a non-finite vertex");
  if (closed.faces.minCoeff() < 0 || closed.faces.maxCoeff() >= closed.vertices.rows())
    throw Error("", "containment: the surface has a vertex id out of range");
  const std::vector<FaceBox> box = face_boxes(closed);
  const EmptyCells cells(closed, box);
  // pass 1: a point in an empty cell whose set's side is known takes it;
  // the others (in occupied cells, and the first point of each set, in point
  // order) take a ray in pass 2, then the rest of each set takes its side
  std::vector<int> comp(static_cast<std::size_t>(points.rows()));
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, points.rows(), 4096), [&](const auto& r) {
    for (Eigen::Index i = r.begin(); i != r.end(); ++i) comp[static_cast<std::size_t>(i)] = cells.component(points.row(i).transpose());
  });
  std::vector<std::int64_t> first(static_cast<std::size_t>(cells.components()), -1), ray;
  for (Eigen::Index i = 0; i < points.rows(); ++i) {
    const int c = comp[static_cast<std::size_t>(i)];
    if (c >= 0 && first[static_cast<std::size_t>(c)] >= 0) continue;
    if (c >= 0) first[static_cast<std::size_t>(c)] = i;
    ray.push_back(i);
  }
  if (stats) stats->ray_tests = static_cast<std::int64_t>(ray.size()), stats->empty_components = cells.components();
  // at least eight faces per cell; more when few rays share the grid's build
  const ParityGrid grid(closed, box, std::max(8.0, static_cast<double>(closed.faces.rows()) / static_cast<double>(ray.size())));
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, ray.size(), 256), [&](const auto& r) {
    for (std::size_t k = r.begin(); k != r.end(); ++k) {
      const Eigen::Index i = ray[k];
      in[static_cast<std::size_t>(i)] = grid.inside(points.row(i).transpose()) ? 1 : 0;
    }
  });
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, points.rows(), 4096), [&](const auto& r) {
    for (Eigen::Index i = r.begin(); i != r.end(); ++i) {
      const int c = comp[static_cast<std::size_t>(i)];
      if (c >= 0) in[static_cast<std::size_t>(i)] = in[static_cast<std::size_t>(first[static_cast<std::size_t>(c)])];
    }
  });
  return in;
}

std::int64_t first_point_outside(const Surface& closed, const MatX3d& points) {
  const std::vector<char> in = points_inside(closed, points);
  auto it = std::find(in.begin(), in.end(), 0);
  return it == in.end() ? -1 : static_cast<std::int64_t>(it - in.begin());
}

}  // namespace orthosim
