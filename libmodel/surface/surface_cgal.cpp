// The only CGAL translation unit of the surface stage: edge-collapse
// decimation, self-intersection count and point-to-surface distances.
#include "libmodel/surface/surface.h"

#include <CGAL/AABB_face_graph_triangle_primitive.h>
#include <CGAL/AABB_traits.h>
#include <CGAL/AABB_tree.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Polygon_mesh_processing/compute_normal.h>
#include <CGAL/Polygon_mesh_processing/self_intersections.h>
#include <CGAL/Side_of_triangle_mesh.h>
#include <CGAL/Surface_mesh.h>
#include <CGAL/Surface_mesh_simplification/Policies/Edge_collapse/Bounded_normal_change_placement.h>
#include <CGAL/Surface_mesh_simplification/Policies/Edge_collapse/Count_stop_predicate.h>
#include <CGAL/Surface_mesh_simplification/Policies/Edge_collapse/GarlandHeckbert_plane_policies.h>
#include <CGAL/Surface_mesh_simplification/Policies/Edge_collapse/LindstromTurk_cost.h>
#include <CGAL/Surface_mesh_simplification/Policies/Edge_collapse/LindstromTurk_placement.h>
#include <CGAL/Surface_mesh_simplification/edge_collapse.h>
#include <CGAL/boost/graph/helpers.h>
#include <CGAL/box_intersection_d.h>

#include <Eigen/Geometry>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <stdexcept>
#include <vector>

namespace orthosim {

namespace {

using K = CGAL::Exact_predicates_inexact_constructions_kernel;
using Point = K::Point_3;
using Mesh = CGAL::Surface_mesh<Point>;
namespace SMS = CGAL::Surface_mesh_simplification;

Mesh to_mesh(const Surface& s, const char* what) {
  Mesh m;
  m.reserve(static_cast<Mesh::size_type>(s.vertices.rows()), static_cast<Mesh::size_type>(3 * s.faces.rows() / 2),
            static_cast<Mesh::size_type>(s.faces.rows()));
  std::vector<Mesh::Vertex_index> v;
  v.reserve(static_cast<std::size_t>(s.vertices.rows()));
  for (Eigen::Index i = 0; i < s.vertices.rows(); ++i) v.push_back(m.add_vertex(Point(s.vertices(i, 0), s.vertices(i, 1), s.vertices(i, 2))));
  for (Eigen::Index i = 0; i < s.faces.rows(); ++i) {
    const auto f = m.add_face(v[static_cast<std::size_t>(s.faces(i, 0))], v[static_cast<std::size_t>(s.faces(i, 1))],
                              v[static_cast<std::size_t>(s.faces(i, 2))]);
    if (f == Mesh::null_face()) throw Error("", std::string(what) + ": the surface is not an oriented 2-manifold");
  }
  return m;
}

// The face pairs of `range` that intersect other than in a shared edge or
// vertex, and each degenerate (collinear) face paired with itself: what
// CGAL::Polygon_mesh_processing::self_intersections reports (with its own
// exact test of a pair, internal::do_faces_intersect), as pairs (a, b) with
// a <= b, sorted. Only the box filter differs: it takes the faces' boxes in
// a frame turned by 0.05 rad about a generic axis (each box grown by the
// turn's round-off, so it still holds its face). In the stack's frame the
// flat caps where a tissue meets the stack's ends give hundreds of
// thousands of boxes one identical start along the slice axis, where
// box_intersection_d's segment tree cannot split its points and scans all of
// them along x instead: 38 % of the surface stage's samples on an 8-slice
// real stack. Turned, a cap's boxes start where their faces lie across it and
// split as any. (With box_intersection_d's default cutoff of 10 instead of
// PMP's 2 000 the turned test was 1.4x slower on a 256^3 phantom's surfaces;
// a tie-breaking growth per box instead of the turn was slower than no change.)
template <class FaceRange>
std::vector<std::pair<Mesh::Face_index, Mesh::Face_index>> self_intersecting_faces(const Mesh& m, const FaceRange& range) {
  using Box = CGAL::Box_intersection_d::Box_with_info_d<double, 3, Mesh::Face_index, CGAL::Box_intersection_d::ID_FROM_BOX_ADDRESS>;
  std::vector<std::pair<Mesh::Face_index, Mesh::Face_index>> out;
  const Eigen::Matrix3d rot = Eigen::AngleAxisd(0.05, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  std::vector<Eigen::Vector3d> at(m.num_vertices() + m.number_of_removed_vertices());
  double reach = 0;
  for (auto v : m.vertices()) {
    const Point& p = m.point(v);
    at[v.idx()] = rot * Eigen::Vector3d(p.x(), p.y(), p.z());
    reach = std::max({reach, std::abs(p.x()), std::abs(p.y()), std::abs(p.z())});
  }
  // |fl(R p) - R p| <= 3 u |R| |p| per coordinate (u = 2^-53, |p| <= sqrt(3) reach): room to spare
  const double grow = 1e-14 * reach + std::numeric_limits<double>::min();
  std::vector<Box> boxes;
  for (auto f : range) {
    const auto h = m.halfedge(f);
    const auto a = m.target(h), b = m.target(m.next(h)), c = m.target(m.prev(h));
    if (CGAL::collinear(m.point(a), m.point(b), m.point(c))) {
      out.push_back({f, f});
      continue;
    }
    const Eigen::Vector3d lo = at[a.idx()].cwiseMin(at[b.idx()]).cwiseMin(at[c.idx()]).array() - grow;
    const Eigen::Vector3d hi = at[a.idx()].cwiseMax(at[b.idx()]).cwiseMax(at[c.idx()]).array() + grow;
    boxes.emplace_back(CGAL::Bbox_3(lo.x(), lo.y(), lo.z(), hi.x(), hi.y(), hi.z()), f);
  }
  std::vector<const Box*> ptr;
  ptr.reserve(boxes.size());
  for (const Box& b : boxes) ptr.push_back(&b);
  const K gt;
  const auto segment = gt.construct_segment_3_object();
  const auto triangle = gt.construct_triangle_3_object();
  const auto intersect = gt.do_intersect_3_object();
  CGAL::box_self_intersection_d<CGAL::Sequential_tag>(ptr.begin(), ptr.end(), [&](const Box* a, const Box* b) {
    if (CGAL::Polygon_mesh_processing::internal::do_faces_intersect<K>(m.halfedge(a->info()), m.halfedge(b->info()), m, m.points(),
                                                                        segment, triangle, intersect))
      out.push_back(a->info() < b->info() ? std::make_pair(a->info(), b->info()) : std::make_pair(b->info(), a->info()));
  }, std::ptrdiff_t{2000});  // PMP's cutoff: below 2 000 boxes a scan beats the tree
  std::sort(out.begin(), out.end());
  return out;
}

// compacted copy, vertices in their original order
Surface from_mesh(const Mesh& m) {
  Surface s;
  std::vector<std::int32_t> id(m.num_vertices() + m.number_of_removed_vertices(), -1);
  std::int32_t n = 0;
  for (auto v : m.vertices()) id[v.idx()] = n++;
  s.vertices.resize(n, 3);
  for (auto v : m.vertices()) {
    const Point& p = m.point(v);
    s.vertices.row(id[v.idx()]) << p.x(), p.y(), p.z();
  }
  s.faces.resize(static_cast<Eigen::Index>(m.number_of_faces()), 3);
  Eigen::Index f = 0;
  for (auto fi : m.faces()) {
    int k = 0;
    for (auto v : CGAL::vertices_around_face(m.halfedge(fi), m)) s.faces(f, k++) = id[v.idx()];
    ++f;
  }
  return s;
}

// Garland-Heckbert plane quadrics made full rank. CGAL 5.5's plane policy
// sums each face's plane quadric into its vertices; where the faces about an
// edge are (nearly) coplanar, as on the smoothed staircases of a voxel
// surface, that sum is (nearly) singular. Its test for a singular matrix is
// an exact det == 0, so a nearly singular one is inverted and places the new
// vertex far along the plane; the bounded-normal-change filter then refuses
// the collapse, and the run crawls: the demo's skin (365 k faces) had not
// reached 2 000 faces after 2 minutes, where Lindstrom-Turk takes 2 s (CGAL
// issue 8988, fixed in CGAL 6.1 by adding line quadrics). Here each face also
// adds `weight` times the point quadric of its centroid, |x - c|^2, so the
// summed matrix has its tangential part bounded below by `weight` per face:
// the optimum is unique and lies near the merged faces (weight 0.01, CGAL
// 6.1's ratio of line to plane quadrics). Same units (m^2), so the cost stays
// a squared distance; the normal offset is biased by 1 % towards the faces'
// centroids (chords of a curved surface), far below a voxel.
template <class TriangleMesh, class GeomTraits>
class RegularisedPlaneQuadric {
 public:
  using Mat_4 = typename SMS::internal::GarlandHeckbert_matrix_types<GeomTraits>::Mat_4;
  using Col_4 = typename SMS::internal::GarlandHeckbert_matrix_types<GeomTraits>::Col_4;
  explicit RegularisedPlaneQuadric(double weight) : weight_(weight) {}

  template <class VertexPointMap>
  Mat_4 construct_quadric_from_edge(typename boost::graph_traits<TriangleMesh>::halfedge_descriptor he,
                                    const TriangleMesh& tmesh, const VertexPointMap vpm, const GeomTraits& gt) const {
    return SMS::internal::construct_classic_plane_quadric_from_edge(he, tmesh, vpm, gt);
  }
  template <class VertexPointMap>
  Mat_4 construct_quadric_from_face(typename boost::graph_traits<TriangleMesh>::face_descriptor f,
                                    const TriangleMesh& tmesh, const VertexPointMap vpm, const GeomTraits& gt) const {
    Mat_4 q = SMS::internal::construct_classic_plane_quadric_from_face(f, tmesh, vpm, gt);
    double c[3] = {0, 0, 0};
    for (auto v : CGAL::vertices_around_face(CGAL::halfedge(f, tmesh), tmesh)) {
      const auto& p = get(vpm, v);
      c[0] += p.x() / 3, c[1] += p.y() / 3, c[2] += p.z() / 3;
    }
    // |x - c|^2 = x.x - 2 c.x + c.c as a 4 x 4 quadric in (x, 1)
    for (int a = 0; a < 3; ++a) {
      q(a, a) += weight_;
      q(a, 3) -= weight_ * c[a];
      q(3, a) -= weight_ * c[a];
    }
    q(3, 3) += weight_ * (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
    return q;
  }
  Col_4 construct_optimal_point(const Mat_4& quadric, const Col_4& p0, const Col_4& p1) const {
    return SMS::internal::construct_optimal_point_singular<GeomTraits>(quadric, p0, p1);
  }

 private:
  double weight_;
};

// Cost and placement as CGAL's GarlandHeckbert_plane_policies, over the
// regularised quadrics. GCC 12 warns that a 4 x 4 Eigen matrix inside CGAL's
// base class "may be used uninitialized" once its constructor is inlined
// (CGAL 5.5's internals, not this code): silenced for this class and its use.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
class RegularisedGarlandHeckbert
    : public SMS::internal::GarlandHeckbert_cost_and_placement<RegularisedPlaneQuadric<Mesh, K>, Mesh, K> {
  using Base = SMS::internal::GarlandHeckbert_cost_and_placement<RegularisedPlaneQuadric<Mesh, K>, Mesh, K>;

 public:
  using Get_cost = RegularisedGarlandHeckbert;
  using Get_placement = RegularisedGarlandHeckbert;
  RegularisedGarlandHeckbert(Mesh& m, double weight) : Base(m, RegularisedPlaneQuadric<Mesh, K>(weight)) {}
  const Get_cost& get_cost() const { return *this; }
  const Get_placement& get_placement() const { return *this; }
  using Base::operator();
};

// The vertices each vertex shares an edge with (sorted, unique).
std::vector<std::vector<std::int32_t>> vertex_rings(const Surface& s) {
  std::vector<std::vector<std::int32_t>> ring(static_cast<std::size_t>(s.vertices.rows()));
  for (Eigen::Index f = 0; f < s.faces.rows(); ++f)
    for (int k = 0; k < 3; ++k) {
      const std::int32_t a = s.faces(f, k), b = s.faces(f, (k + 1) % 3);
      ring[static_cast<std::size_t>(a)].push_back(b);
      ring[static_cast<std::size_t>(b)].push_back(a);
    }
  for (auto& r : ring) {
    std::sort(r.begin(), r.end());
    r.erase(std::unique(r.begin(), r.end()), r.end());
  }
  return ring;
}

struct Untangled {
  std::int64_t folds = 0;  // intersecting pairs in the first test
  int rounds = 0;          // rounds of relaxing
  std::int64_t left = 0;   // pairs in the last test
};

// Untangles the folds of `s` near `seeds` (one flag per vertex): the faces
// within two rings of a seed are tested for intersecting pairs (CGAL); the
// vertices of those faces and their neighbours are relaxed (each to the mean
// of its neighbours, Jacobi, so the result does not depend on an order) and
// handed to keep(i) (a constraint: the nesting's move back inside), and the
// faces near them join the test; in rounds until none intersect (at most 20,
// and none after 3 that left more folds than the fewest so far: on a broken
// real segmentation (1.5 M faces, a thin, torn skin) the count fell from
// 13 138 to ~1 100 in 6 rounds and then wandered for 14 more, 6-20 s each,
// before the stage failed anyway). Vertices flagged in `held` stay (a flat
// border cap: remesh finds the limb's axis by it). Without test_held, faces
// with all three corners held are not tested (flat, and where every vertex
// within a cap's reach is a seed their coplanar neighbours made most of the
// test's cost; keep must then hold the vertices off the caps). Only surfaces
// with such a fold change.
template <class Keep>
Untangled untangle(Surface& s, const std::vector<std::uint8_t>& seeds, const std::vector<std::uint8_t>& held, bool test_held,
                   Keep&& keep) {
  Untangled res;
  const Eigen::Index n = s.vertices.rows();
  const std::vector<std::vector<std::int32_t>> ring = vertex_rings(s);
  std::vector<std::uint8_t> near(static_cast<std::size_t>(n), 0);
  for (Eigen::Index i = 0; i < n; ++i)
    if (seeds[static_cast<std::size_t>(i)]) {
      near[static_cast<std::size_t>(i)] = 1;
      for (auto j : ring[static_cast<std::size_t>(i)]) {
        near[static_cast<std::size_t>(j)] = 1;
        for (auto k : ring[static_cast<std::size_t>(j)]) near[static_cast<std::size_t>(k)] = 1;
      }
    }
  std::int64_t fewest = -1;
  int since_fewest = 0;
  for (int round = 0; round < 20 && since_fewest < 3; ++round) {
    const Mesh im = to_mesh(s, "untangling");
    std::vector<Mesh::Face_index> range;
    for (auto f : im.faces()) {
      bool any = false, cap_face = true;
      for (auto v : CGAL::vertices_around_face(im.halfedge(f), im))
        any = any || near[v.idx()], cap_face = cap_face && held[v.idx()];
      if (any && (test_held || !cap_face)) range.push_back(f);
    }
    const auto pairs = self_intersecting_faces(im, range);
    res.left = static_cast<std::int64_t>(pairs.size());
    if (pairs.empty()) break;
    if (fewest < 0 || res.left < fewest) fewest = res.left, since_fewest = 0;
    else ++since_fewest;
    if (since_fewest >= 3) break;  // (the test left; no more relaxing)
    if (round == 0) res.folds = res.left;
    ++res.rounds;
    std::vector<std::uint8_t> relax(static_cast<std::size_t>(n), 0);
    for (const auto& [f1, f2] : pairs)
      for (auto f : {f1, f2})
        for (int k = 0; k < 3; ++k) {
          const auto v = static_cast<std::size_t>(s.faces(static_cast<Eigen::Index>(f.idx()), k));
          relax[v] = 1;
          for (auto j : ring[v]) relax[static_cast<std::size_t>(j)] = 1;
        }
    MatX3d next = s.vertices;
    for (Eigen::Index i = 0; i < n; ++i) {
      const auto u = static_cast<std::size_t>(i);
      if (!relax[u] || ring[u].empty() || held[u]) continue;
      Eigen::RowVector3d mean = Eigen::RowVector3d::Zero();
      for (auto j : ring[u]) mean += s.vertices.row(j);
      next.row(i) = mean / static_cast<double>(ring[u].size());
    }
    s.vertices = next;
    for (Eigen::Index i = 0; i < n; ++i)
      if (relax[static_cast<std::size_t>(i)]) {
        near[static_cast<std::size_t>(i)] = 1;
        keep(i);
      }
  }
  return res;
}


}  // namespace

Surface decimate_surface(const Surface& s, std::int64_t target_faces, DecimationCost cost, bool bounded_normal_change) {
  if (target_faces < 4) throw Error("", "decimation: target faces must be >= 4");
  Mesh m = to_mesh(s, "decimation");
  if (!CGAL::is_closed(m) || !CGAL::is_triangle_mesh(m)) throw Error("", "decimation: the surface must be a closed triangle mesh");
  // a closed triangle mesh has 3F/2 edges; each collapse removes 3 edges and 2 faces
  SMS::Count_stop_predicate<Mesh> stop(static_cast<std::size_t>(3 * target_faces / 2));
  if (cost == DecimationCost::lindstrom_turk) {
    SMS::LindstromTurk_cost<Mesh> c;
    if (bounded_normal_change) {
      SMS::Bounded_normal_change_placement<SMS::LindstromTurk_placement<Mesh>> p;
      SMS::edge_collapse(m, stop, CGAL::parameters::get_cost(c).get_placement(p));
    } else {
      SMS::LindstromTurk_placement<Mesh> p;
      SMS::edge_collapse(m, stop, CGAL::parameters::get_cost(c).get_placement(p));
    }
  } else {
    using GH = RegularisedGarlandHeckbert;
    GH gh(m, 0.01);
    if (bounded_normal_change) {
      SMS::Bounded_normal_change_placement<GH::Get_placement> p(gh.get_placement());
      SMS::edge_collapse(m, stop, CGAL::parameters::get_cost(gh.get_cost()).get_placement(p));
    } else {
      SMS::edge_collapse(m, stop, CGAL::parameters::get_cost(gh.get_cost()).get_placement(gh.get_placement()));
    }
  }
  return from_mesh(m);
}
#pragma GCC diagnostic pop

std::vector<std::array<std::int64_t, 2>> surface_self_intersection_pairs(const Surface& s) {
  const Mesh m = to_mesh(s, "self-intersection test");
  const auto pairs = self_intersecting_faces(m, m.faces());
  std::vector<std::array<std::int64_t, 2>> out;
  out.reserve(pairs.size());
  for (const auto& [a, b] : pairs) out.push_back({static_cast<std::int64_t>(a.idx()), static_cast<std::int64_t>(b.idx())});
  return out;
}

std::int64_t surface_self_intersections(const Surface& s) {
  return static_cast<std::int64_t>(surface_self_intersection_pairs(s).size());
}

namespace {

// The faces of a surface that lie exactly in one cap plane, bucketed on a
// uniform grid over the plane: where a point of that plane lies on them.
struct CapGrid {
  int axis = 0, u = 1, v = 2;  // the plane's normal axis and its two in-plane axes
  double at = 0;
  double x0 = 0, y0 = 0, inv = 0;
  int nx = 0, ny = 0;
  std::vector<std::int32_t> first;  // per cell, into faces (nx * ny + 1)
  std::vector<Mesh::Face_index> faces;
};

CapGrid make_cap_grid(const Mesh& m, int axis, double at) {
  CapGrid g;
  g.axis = axis, g.u = (axis + 1) % 3, g.v = (axis + 2) % 3, g.at = at;
  std::vector<Mesh::Face_index> in;
  double lo[2] = {1e300, 1e300}, hi[2] = {-1e300, -1e300};
  for (auto f : m.faces()) {
    bool on = true;
    for (auto w : CGAL::vertices_around_face(m.halfedge(f), m)) on = on && m.point(w)[axis] == at;
    if (!on) continue;
    in.push_back(f);
    for (auto w : CGAL::vertices_around_face(m.halfedge(f), m))
      for (int k = 0; k < 2; ++k) {
        const double c = m.point(w)[k == 0 ? g.u : g.v];
        lo[k] = std::min(lo[k], c), hi[k] = std::max(hi[k], c);
      }
  }
  if (in.empty()) return g;
  // about two faces a cell
  const double area = std::max(hi[0] - lo[0], 1e-300) * std::max(hi[1] - lo[1], 1e-300);
  const double cell = std::sqrt(2 * area / static_cast<double>(in.size()));
  g.inv = 1 / cell;
  g.x0 = lo[0], g.y0 = lo[1];
  // (clamped as doubles: a flat extent along one axis makes inv huge)
  g.nx = static_cast<int>(std::min((hi[0] - lo[0]) * g.inv, double(1 << 14) - 1)) + 1;
  g.ny = static_cast<int>(std::min((hi[1] - lo[1]) * g.inv, double(1 << 14) - 1)) + 1;
  auto cells = [&](Mesh::Face_index f, const auto& visit) {
    double flo[2] = {1e300, 1e300}, fhi[2] = {-1e300, -1e300};
    for (auto w : CGAL::vertices_around_face(m.halfedge(f), m))
      for (int k = 0; k < 2; ++k) {
        const double c = m.point(w)[k == 0 ? g.u : g.v];
        flo[k] = std::min(flo[k], c), fhi[k] = std::max(fhi[k], c);
      }
    auto cell_of = [](double t, int n) { return static_cast<int>(std::clamp(t, 0.0, n - 1.0)); };
    const int i0 = cell_of((flo[0] - g.x0) * g.inv, g.nx), i1 = cell_of((fhi[0] - g.x0) * g.inv, g.nx);
    const int j0 = cell_of((flo[1] - g.y0) * g.inv, g.ny), j1 = cell_of((fhi[1] - g.y0) * g.inv, g.ny);
    // one cell more on each side: a point on a cell's edge is looked up in either
    for (int j = std::max(0, j0 - 1); j <= std::min(g.ny - 1, j1 + 1); ++j)
      for (int i = std::max(0, i0 - 1); i <= std::min(g.nx - 1, i1 + 1); ++i) visit(static_cast<std::size_t>(j) * g.nx + i);
  };
  g.first.assign(static_cast<std::size_t>(g.nx) * g.ny + 1, 0);
  for (auto f : in) cells(f, [&](std::size_t c) { ++g.first[c + 1]; });
  for (std::size_t c = 1; c < g.first.size(); ++c) g.first[c] += g.first[c - 1];
  g.faces.resize(static_cast<std::size_t>(g.first.back()));
  std::vector<std::int32_t> at_cell(g.first.begin(), g.first.end() - 1);
  for (auto f : in) cells(f, [&](std::size_t c) { g.faces[static_cast<std::size_t>(at_cell[c]++)] = f; });
  return g;
}

}  // namespace

struct NestingIndex {
  using Primitive = CGAL::AABB_face_graph_triangle_primitive<Mesh>;
  using Tree = CGAL::AABB_tree<CGAL::AABB_traits<K, Primitive>>;
  Mesh m;
  Tree tree;
  std::optional<CGAL::Side_of_triangle_mesh<Mesh, K>> side;
  std::vector<std::uint8_t> cap;  // per face of m: on a border cap
  std::vector<CapPlane> caps;
  double tol = 0;
  std::vector<CapGrid> grids;  // per cap plane with faces exactly in it
  // A point exactly in a cap plane that lies on a face of m exactly in it,
  // inside it or on an edge or corner no face out of the plane shares. Every
  // face of m within distance 0 of it is then a cap face (m is embedded), and
  // it is on m's boundary: the closest-point query finds it on a cap, where
  // enforce_nesting leaves it. (Side_of_triangle_mesh's ray and the
  // closest-point query both fall back to exact arithmetic for points in a
  // face's plane: 1 M cap vertices of an 8-slice stack took 15 s.)
  bool on_cap_face(const Point& p) const {
    for (const CapGrid& g : grids) {
      if (p[g.axis] != g.at) continue;
      const double x = p[g.u], y = p[g.v];
      const double fi = (x - g.x0) * g.inv, fj = (y - g.y0) * g.inv;
      if (!(fi >= 0 && fj >= 0 && fi < g.nx && fj < g.ny)) continue;
      const std::size_t c = static_cast<std::size_t>(fj) * g.nx + static_cast<std::size_t>(fi);
      const K::Point_2 q(x, y);
      for (std::int32_t k = g.first[c]; k < g.first[c + 1]; ++k) {
        const Mesh::Face_index f = g.faces[static_cast<std::size_t>(k)];
        const Mesh::Halfedge_index h[3] = {m.halfedge(f), m.next(m.halfedge(f)), m.prev(m.halfedge(f))};
        K::Point_2 c2[3];
        for (int e = 0; e < 3; ++e) {
          const Point& w = m.point(m.source(h[e]));
          c2[e] = K::Point_2(w[g.u], w[g.v]);
        }
        const CGAL::Orientation turn = CGAL::orientation(c2[0], c2[1], c2[2]);
        if (turn == CGAL::COLLINEAR) continue;
        int zero = -1, zeros = 0;
        bool out = false;
        for (int e = 0; e < 3 && !out; ++e) {  // edge e: source(h[e]) -> target(h[e])
          const CGAL::Orientation o = CGAL::orientation(c2[e], c2[(e + 1) % 3], q);
          if (o == CGAL::COLLINEAR) zero = e, ++zeros;
          else out = o != turn;
        }
        if (out) continue;
        if (zeros == 0) return true;  // inside
        if (zeros == 1) {             // on edge `zero`: the face across must be a cap face too
          const auto across = m.face(m.opposite(h[zero]));
          return across != Mesh::null_face() && cap[across.idx()];
        }
        Mesh::Vertex_index vtx;  // a corner: the vertex p is
        for (int e = 0; e < 3; ++e) {
          const Point& w = m.point(m.source(h[e]));
          if (w[g.u] == x && w[g.v] == y) vtx = m.source(h[e]);
        }
        if (vtx == Mesh::null_vertex()) return false;
        // every face around it must be a cap face
        for (auto f2 : CGAL::faces_around_target(m.halfedge(vtx), m))
          if (f2 == Mesh::null_face() || !cap[f2.idx()]) return false;
        return true;
      }
    }
    return false;
  }
};

std::shared_ptr<const NestingIndex> make_nesting_index(const Surface& outer, const std::vector<CapPlane>& caps,
                                                       bool cap_lookup) {
  auto x = std::make_shared<NestingIndex>();
  x->caps = caps;
  if (outer.faces.rows() == 0) return x;
  x->m = to_mesh(outer, "nesting");
  const Mesh& m = x->m;
  x->tree.insert(faces(m).first, faces(m).second, m);
  // built here, with the distance queries' k-d tree of hints (CGAL would
  // build that at the first query): the children's queries only read them
  x->tree.build();
  x->tree.accelerate_distance_queries();
  x->tree.closest_point(m.point(*m.vertices().begin()));
  x->side.emplace(x->tree);
  // Flat caps where the volume border cuts a tissue: outer's faces whose
  // corners lie on one cap plane (or, without the planes, in a plane of its
  // bounding box). A nested tissue cut by the same border has its cap in the
  // same plane; there it is inside by construction, and pushing it off the
  // plane would fold the rim. (The bounding box missed the caps where
  // smoothing had carried a rim vertex past the plane: every nested cap
  // vertex was then moved, 729 000 of the fat's on 12 slices of the real crop.)
  std::vector<CapPlane> planes = caps;
  const Eigen::RowVector3d lo = outer.vertices.colwise().minCoeff(), hi = outer.vertices.colwise().maxCoeff();
  if (planes.empty())
    for (int k = 0; k < 3; ++k) planes.push_back({k, lo(k)}), planes.push_back({k, hi(k)});
  x->tol = 1e-9 * (hi - lo).maxCoeff();  // decimation's placement in a plane rounds
  x->cap.assign(m.number_of_faces() + m.number_of_removed_faces(), 0);
  for (auto f : m.faces())
    for (const CapPlane& pl : planes) {
      bool on = true;
      for (auto v : CGAL::vertices_around_face(m.halfedge(f), m)) on = on && std::abs(m.point(v)[pl.axis] - pl.at) <= x->tol;
      if (on) x->cap[f.idx()] = 1;
    }
  if (cap_lookup)
    for (const CapPlane& pl : planes)
      if (CapGrid g = make_cap_grid(m, pl.axis, pl.at); !g.faces.empty()) x->grids.push_back(std::move(g));
  return x;
}

NestingResult enforce_nesting(Surface& inner, const Surface& outer, double clearance_m, const std::vector<CapPlane>& caps,
                              bool cap_folds) {
  if (inner.vertices.rows() == 0 || outer.faces.rows() == 0) return {};
  return enforce_nesting(inner, *make_nesting_index(outer, caps), clearance_m, cap_folds);
}

NestingResult enforce_nesting(Surface& inner, const NestingIndex& index, double clearance_m, bool cap_folds) {
  NestingResult res;
  const Eigen::Index n = inner.vertices.rows();
  if (n == 0 || !index.side) return res;
  const Mesh& m = index.m;
  const auto& tree = index.tree;
  const auto& side = *index.side;
  const std::vector<std::uint8_t>& cap = index.cap;
  const std::vector<CapPlane>& caps = index.caps;
  const double tol = index.tol;
  const double c2 = clearance_m * clearance_m;
  std::vector<std::uint8_t> was_outside(static_cast<std::size_t>(n), 0), moved(static_cast<std::size_t>(n), 0),
      on_cap(static_cast<std::size_t>(n), 0);
  std::vector<double> move(static_cast<std::size_t>(n), 0.0);
  std::atomic<std::int64_t> lookups{0};
  auto fix = [&](Eigen::Index i) {
    const auto u = static_cast<std::size_t>(i);
    const Point p(inner.vertices(i, 0), inner.vertices(i, 1), inner.vertices(i, 2));
    if (index.on_cap_face(p)) {
      on_cap[u] = 1;  // on a shared border cap: what the queries below find, without them
      lookups.fetch_add(1, std::memory_order_relaxed);
      return;
    }
    const auto where = side(p);
    // Most vertices lie deep inside: no face of outer meets the cube of half
    // side `clearance` around them, so none lies within the clearance and the
    // vertex stays, as the closest point below would say, at a fraction of
    // its cost (the distance queries were most of a 256^3 stack's nesting).
    if (where == CGAL::ON_BOUNDED_SIDE &&
        !tree.do_intersect(K::Iso_cuboid_3(p.x() - clearance_m, p.y() - clearance_m, p.z() - clearance_m,
                                           p.x() + clearance_m, p.y() + clearance_m, p.z() + clearance_m)))
      return;
    const auto [c, f] = tree.closest_point_and_primitive(p);
    const double d2 = CGAL::squared_distance(p, c);
    if (where == CGAL::ON_BOUNDED_SIDE && d2 >= c2) return;
    if (cap[f.idx()] && where != CGAL::ON_UNBOUNDED_SIDE) {
      on_cap[u] = 1;  // on or just inside a shared border cap
      return;
    }
    const auto nf = CGAL::Polygon_mesh_processing::compute_face_normal(f, m);
    const Eigen::Vector3d q(c.x() - clearance_m * nf.x(), c.y() - clearance_m * nf.y(), c.z() - clearance_m * nf.z());
    move[u] = (q - inner.vertices.row(i).transpose()).norm();
    inner.vertices.row(i) = q.transpose();
    moved[u] = 1;
    was_outside[u] = where != CGAL::ON_BOUNDED_SIDE;
  };
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, n, 512), [&](const tbb::blocked_range<Eigen::Index>& r) {
    for (Eigen::Index i = r.begin(); i != r.end(); ++i) fix(i);
  });
  // Where the outer shell is thinner than the clearance (a fin of a noisy
  // segmentation), the move in by the clearance carries the vertex out
  // through the far side: it is moved again from where it landed, in from
  // the (far) face it is now closest to, by half the clearance, a quarter,
  // ... until inside; such a vertex ends inside but closer than the
  // clearance. Where that fails too (the offset leaves through a
  // neighbouring face where the outer surface folds), moves by twice the
  // clearance, four times, ... follow. Few vertices: serial, in index order.
  for (Eigen::Index i = 0; i < n; ++i) {
    const auto u = static_cast<std::size_t>(i);
    if (!moved[u]) continue;
    const Eigen::Vector3d start = inner.vertices.row(i).transpose();
    Eigen::Vector3d at = start;
    for (const double factor : {0.5, 2.0}) {
      Point p(start.x(), start.y(), start.z());
      at = start;
      double gap = clearance_m;
      for (int again = 0; again < 10 && side(p) == CGAL::ON_UNBOUNDED_SIDE; ++again) {
        gap *= factor;
        const auto [c, f] = tree.closest_point_and_primitive(p);
        const auto nf = CGAL::Polygon_mesh_processing::compute_face_normal(f, m);
        at = Eigen::Vector3d(c.x() - gap * nf.x(), c.y() - gap * nf.y(), c.z() - gap * nf.z());
        p = Point(at.x(), at.y(), at.z());
        ++res.moved_again;
      }
      if (side(p) != CGAL::ON_UNBOUNDED_SIDE) break;
    }
    move[u] += (at - start).norm();
    inner.vertices.row(i) = at.transpose();
  }
  // Untangle. Neighbouring vertices moved onto the closest points of a curved
  // outer surface can fold the inner one over itself: the phantom at noise 4
  // on 1.2 x 0.8 x 3.5 mm voxels left 6 intersecting face pairs in the bone
  // after its 531 vertices were moved inside the muscle. The folds near the
  // moved vertices, and near inner's vertices within a cap's reach (where it
  // folds on thin stacks; the caps of a surface that does not reach the
  // border lie beyond it: none), are relaxed and kept inside (the move above
  // again): untangle.
  std::vector<std::uint8_t> on_plane(static_cast<std::size_t>(n), 0), in_cap(static_cast<std::size_t>(n), 0);
  if (cap_folds)
    for (const CapPlane& pl : caps) {
      bool cut = false;  // inner has vertices on this plane
      for (Eigen::Index i = 0; i < n; ++i)
        if (std::abs(inner.vertices(i, pl.axis) - pl.at) <= tol) cut = true, in_cap[static_cast<std::size_t>(i)] = 1;
      if (cut)
        for (Eigen::Index i = 0; i < n; ++i)
          if (std::abs(inner.vertices(i, pl.axis) - pl.at) <= pl.reach) on_plane[static_cast<std::size_t>(i)] = 1;
    }
  std::vector<std::uint8_t> seeds(static_cast<std::size_t>(n), 0);
  for (std::size_t u = 0; u < seeds.size(); ++u) seeds[u] = moved[u] || on_plane[u];
  if (std::find(seeds.begin(), seeds.end(), 1) != seeds.end()) {
    const Untangled t = untangle(inner, seeds, in_cap, false, fix);
    res.folds = t.folds, res.untangle_rounds = t.rounds, res.folds_left = t.left;
  }
  for (Eigen::Index i = 0; i < n; ++i) {
    const auto u = static_cast<std::size_t>(i);
    if (!moved[u]) continue;
    ++res.moved;
    res.outside += was_outside[u];
    res.max_move_m = std::max(res.max_move_m, move[u]);
    if (side(Point(inner.vertices(i, 0), inner.vertices(i, 1), inner.vertices(i, 2))) == CGAL::ON_UNBOUNDED_SIDE)
      ++res.still_outside;
  }
  for (auto c : on_cap) res.on_cap += c;
  res.cap_lookups = lookups.load();
  return res;
}

FoldsResult untangle_surface(Surface& s, const std::vector<CapPlane>& caps,
                             const std::vector<std::array<std::int64_t, 2>>* known) {
  FoldsResult res;
  const Eigen::Index n = s.vertices.rows();
  if (n == 0) return res;
  // (to_mesh keeps the face order, so CGAL's face ids are the rows of s.faces)
  const std::vector<std::array<std::int64_t, 2>> pairs = known ? *known : surface_self_intersection_pairs(s);
  if (pairs.empty()) return res;
  std::vector<std::uint8_t> seeds(static_cast<std::size_t>(n), 0), held(static_cast<std::size_t>(n), 0);
  for (const auto& pair : pairs)
    for (const std::int64_t f : pair) {
      if (f < 0 || f >= s.faces.rows()) throw std::invalid_argument("untangle_surface: a pair's face is not a face of the surface");
      for (int k = 0; k < 3; ++k) seeds[static_cast<std::size_t>(s.faces(static_cast<Eigen::Index>(f), k))] = 1;
    }
  const Eigen::RowVector3d lo = s.vertices.colwise().minCoeff(), hi = s.vertices.colwise().maxCoeff();
  const double tol = 1e-9 * (hi - lo).maxCoeff();  // as enforce_nesting's
  for (const CapPlane& pl : caps)
    for (Eigen::Index i = 0; i < n; ++i)
      if (std::abs(s.vertices(i, pl.axis) - pl.at) <= tol) held[static_cast<std::size_t>(i)] = 1;
  // (the seeds are the faces of the pairs, few: the cap faces among them are
  // tested, since nothing keeps a relaxed rim vertex off its cap's plane)
  const Untangled t = untangle(s, seeds, held, true, [](Eigen::Index) {});
  res.folds = static_cast<std::int64_t>(pairs.size()), res.untangle_rounds = t.rounds, res.folds_left = t.left;
  return res;
}

VecXd distance_to_surface(const Surface& s, const MatX3d& points) {
  using Primitive = CGAL::AABB_face_graph_triangle_primitive<Mesh>;
  using Tree = CGAL::AABB_tree<CGAL::AABB_traits<K, Primitive>>;
  VecXd d = VecXd::Zero(points.rows());
  if (points.rows() == 0 || s.faces.rows() == 0) return d;
  const Mesh m = to_mesh(s, "distance");
  Tree tree(faces(m).first, faces(m).second, m);
  tree.accelerate_distance_queries();
  d(0) = std::sqrt(tree.squared_distance(Point(points(0, 0), points(0, 1), points(0, 2))));  // builds the tree
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(1, points.rows(), 1024), [&](const tbb::blocked_range<Eigen::Index>& r) {
    for (Eigen::Index i = r.begin(); i != r.end(); ++i)
      d(i) = std::sqrt(tree.squared_distance(Point(points(i, 0), points(i, 1), points(i, 2))));
  });
  return d;
}

}  // namespace orthosim
