// Point-to-mesh distances of remesh's evaluation (CGAL AABB tree).
#include "libmodel/remesh/remesh.h"
#include "libmodel/remesh/detail.h"

#include <Eigen/Geometry>

#include <CGAL/AABB_traits.h>
#include <CGAL/AABB_tree.h>
#include <CGAL/AABB_triangle_primitive.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace orthosim {

namespace {

using K = CGAL::Exact_predicates_inexact_constructions_kernel;
using Point = K::Point_3;
using Triangle = K::Triangle_3;
using TriIter = std::vector<Triangle>::const_iterator;
using Primitive = CGAL::AABB_triangle_primitive<K, TriIter>;
using Tree = CGAL::AABB_tree<CGAL::AABB_traits<K, Primitive>>;
using Vec3 = Eigen::Vector3d;

Point P(const Vec3& v) { return {v.x(), v.y(), v.z()}; }

// distances from points to a triangle set, in parallel (order-independent)
std::vector<double> distances(const std::vector<Triangle>& tris, const std::vector<Vec3>& pts) {
  std::vector<double> d(pts.size(), 0);
  if (tris.empty()) return d;
  Tree tree(tris.begin(), tris.end());
  tree.accelerate_distance_queries();
  tree.squared_distance(P(pts.empty() ? Vec3::Zero() : pts[0]));  // builds the tree before the parallel loop
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, pts.size(), 1024), [&](const auto& r) {
    for (std::size_t i = r.begin(); i != r.end(); ++i) d[i] = std::sqrt(tree.squared_distance(P(pts[i])));
  });
  return d;
}

}  // namespace

std::vector<double> remesh_detail::distances_to_surface(const Surface& s, const MatX3d& points) {
  std::vector<Triangle> tris;
  tris.reserve(static_cast<std::size_t>(s.faces.rows()));
  for (Eigen::Index f = 0; f < s.faces.rows(); ++f)
    tris.emplace_back(P(s.vertices.row(s.faces(f, 0)).transpose()), P(s.vertices.row(s.faces(f, 1)).transpose()),
                      P(s.vertices.row(s.faces(f, 2)).transpose()));
  std::vector<Vec3> pts(static_cast<std::size_t>(points.rows()));
  for (Eigen::Index i = 0; i < points.rows(); ++i) pts[static_cast<std::size_t>(i)] = points.row(i).transpose();
  return distances(tris, pts);
}

bool remesh_detail::all_on_surface(const Surface& s, const MatX3d& points, double tol) {
  const double tol2 = tol * tol;
  for (Eigen::Index i = 0; i < points.rows(); ++i) {
    const Vec3 p = points.row(i).transpose();
    bool on = false;
    for (Eigen::Index f = 0; f < s.faces.rows() && !on; ++f) {
      const Vec3 a = s.vertices.row(s.faces(f, 0)), b = s.vertices.row(s.faces(f, 1)), c = s.vertices.row(s.faces(f, 2));
      if ((p.array() < a.array().min(b.array()).min(c.array()) - tol).any() ||
          (p.array() > a.array().max(b.array()).max(c.array()) + tol).any())
        continue;
      on = CGAL::squared_distance(P(p), Triangle(P(a), P(b), P(c))) <= tol2;
    }
    if (!on) return false;
  }
  return true;
}

SurfaceDistance quad_surface_distance(const QuadSurface& q, const Surface& input, const SweepPlane& first,
                                      const SweepPlane& last, int k) {
  SurfaceDistance r;
  k = std::max(1, k);
  // bilinear patches: samples for quad -> input, a 2 x 2 tessellation for input -> quad
  std::vector<Vec3> qs;
  std::vector<double> qw;
  std::vector<Triangle> qt;
  for (Eigen::Index f = 0; f < q.quads.rows(); ++f) {
    const Vec3 p0 = q.vertices.row(q.quads(f, 0)), p1 = q.vertices.row(q.quads(f, 1)),
               p2 = q.vertices.row(q.quads(f, 2)), p3 = q.vertices.row(q.quads(f, 3));
    auto at = [&](double a, double b) { return Vec3((1 - a) * (1 - b) * p0 + a * (1 - b) * p1 + a * b * p2 + (1 - a) * b * p3); };
    const double area = 0.5 * (p2 - p0).cross(p3 - p1).norm();
    for (int i = 0; i <= k; ++i)
      for (int j = 0; j <= k; ++j) {
        qs.push_back(at(static_cast<double>(i) / k, static_cast<double>(j) / k));
        // trapezoid weights over the patch
        const double wi = (i == 0 || i == k) ? 0.5 : 1.0, wj = (j == 0 || j == k) ? 0.5 : 1.0;
        qw.push_back(area * wi * wj / (k * k));
      }
    const Vec3 g[3][3] = {{at(0, 0), at(0, .5), at(0, 1)}, {at(.5, 0), at(.5, .5), at(.5, 1)}, {at(1, 0), at(1, .5), at(1, 1)}};
    for (int a = 0; a < 2; ++a)
      for (int b = 0; b < 2; ++b) {
        qt.emplace_back(P(g[a][b]), P(g[a + 1][b]), P(g[a + 1][b + 1]));
        qt.emplace_back(P(g[a][b]), P(g[a + 1][b + 1]), P(g[a][b + 1]));
      }
  }
  std::vector<Triangle> it;
  it.reserve(input.faces.rows());
  for (Eigen::Index f = 0; f < input.faces.rows(); ++f)
    it.emplace_back(P(input.vertices.row(input.faces(f, 0))), P(input.vertices.row(input.faces(f, 1))),
                    P(input.vertices.row(input.faces(f, 2))));
  const std::vector<double> dq = distances(it, qs);
  double sw = 0, sd = 0;
  for (std::size_t i = 0; i < dq.size(); ++i) {
    r.quad_to_input_max_m = std::max(r.quad_to_input_max_m, dq[i]);
    sd += qw[i] * dq[i], sw += qw[i];
  }
  r.quad_to_input_mean_m = sw > 0 ? sd / sw : 0;

  // the input between the end planes: vertices and face centroids
  auto between = [&](const Vec3& x) {
    return (x - first.centre).dot(first.normal) >= 0 && (x - last.centre).dot(last.normal) <= 0;
  };
  std::vector<Vec3> is;
  std::vector<double> iw;
  std::vector<char> used(input.vertices.rows(), 0);
  for (Eigen::Index f = 0; f < input.faces.rows(); ++f) {
    const Vec3 p0 = input.vertices.row(input.faces(f, 0)), p1 = input.vertices.row(input.faces(f, 1)),
               p2 = input.vertices.row(input.faces(f, 2));
    const Vec3 c = (p0 + p1 + p2) / 3;
    if (!between(c)) continue;
    const double a = 0.5 * (p1 - p0).cross(p2 - p0).norm();
    r.compared_input_area_m2 += a;
    is.push_back(c);
    iw.push_back(a);
    for (int k3 = 0; k3 < 3; ++k3) {
      const int v = input.faces(f, k3);
      const Vec3 x = input.vertices.row(v);
      if (!used[v] && between(x)) {
        used[v] = 1;
        is.push_back(x);
        iw.push_back(0);  // vertices count for the maximum only
      }
    }
  }
  const std::vector<double> di = distances(qt, is);
  sw = 0, sd = 0;
  for (std::size_t i = 0; i < di.size(); ++i) {
    r.input_to_quad_max_m = std::max(r.input_to_quad_max_m, di[i]);
    sd += iw[i] * di[i], sw += iw[i];
  }
  r.input_to_quad_mean_m = sw > 0 ? sd / sw : 0;
  r.hausdorff_m = std::max(r.quad_to_input_max_m, r.input_to_quad_max_m);
  r.mean_m = 0.5 * (r.quad_to_input_mean_m + r.input_to_quad_mean_m);
  r.samples = static_cast<std::int64_t>(qs.size() + is.size());
  return r;
}

RemeshEvaluation evaluate_remesh(const RemeshResult& res, const std::vector<NamedSurface>& inputs, int k) {
  RemeshEvaluation e;
  const SweepPlane first = sweep_plane(res.sweep, 0), last = sweep_plane(res.sweep, res.sweep.length_m);
  // the layers side by side: each builds its own AABB trees over its input
  // surface (single-threaded in CGAL; the layers in turn left a core idle)
  e.quality.resize(res.layers.size());
  e.distance.resize(res.layers.size());
  tbb::parallel_for(std::size_t{0}, res.layers.size(), [&](std::size_t l) {
    e.quality[l] = quad_quality(res.layers[l], res.ray_origin[l]);
    e.distance[l] = quad_surface_distance(res.layers[l], inputs.at(l).surface, first, last, k);
  });
  for (std::size_t l = 1; l < res.layers.size(); ++l) {
    LayerAlignment a = layer_alignment(res.layers[l - 1], res.layers[l], inputs[l - 1].name, inputs[l].name);
    e.worst_lateral_m = std::max(e.worst_lateral_m, a.max_lateral_m);
    e.worst_lateral_rel = std::max(e.worst_lateral_rel, a.max_lateral_rel);
    e.worst_ray_miss_m = std::max(e.worst_ray_miss_m, a.max_ray_miss_m);
    e.alignment.push_back(a);
  }
  return e;
}

}  // namespace orthosim
