// The only file of the msm stage that sees CGAL.
#include "libmodel/msm/project.h"

#include <CGAL/AABB_traits.h>
#include <CGAL/AABB_tree.h>
#include <CGAL/AABB_triangle_primitive.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <vector>

namespace orthosim::msm {

namespace {
using K = CGAL::Exact_predicates_inexact_constructions_kernel;
using Triangles = std::vector<K::Triangle_3>;
using Primitive = CGAL::AABB_triangle_primitive<K, Triangles::const_iterator>;
using Tree = CGAL::AABB_tree<CGAL::AABB_traits<K, Primitive>>;

K::Point_3 P(const Eigen::Vector3d& v) { return {v.x(), v.y(), v.z()}; }
Eigen::Vector3d V(const K::Point_3& p) { return {p.x(), p.y(), p.z()}; }
}  // namespace

struct RayCaster::Impl {
  Triangles tris;
  std::vector<Eigen::Vector3d> normals;  // unit outward normals
  Tree tree;
};

RayCaster::RayCaster(const Surface& s) : impl_(std::make_unique<Impl>()) {
  auto& I = *impl_;
  I.tris.reserve(static_cast<std::size_t>(s.faces.rows()));
  I.normals.reserve(static_cast<std::size_t>(s.faces.rows()));
  for (Eigen::Index f = 0; f < s.faces.rows(); ++f) {
    const Eigen::Vector3d a = s.vertices.row(s.faces(f, 0)), b = s.vertices.row(s.faces(f, 1)),
                          c = s.vertices.row(s.faces(f, 2));
    I.tris.emplace_back(P(a), P(b), P(c));
    Eigen::Vector3d n = (b - a).cross(c - a);
    const double len = n.norm();
    I.normals.push_back(len > 0 ? Eigen::Vector3d(n / len) : Eigen::Vector3d::Zero());
  }
  I.tree.insert(I.tris.cbegin(), I.tris.cend());
  I.tree.build();
  // closest-point queries are rare (fallbacks without an expected face): no
  // KD-tree; the build above is explicit so that concurrent const queries only read
  I.tree.do_not_accelerate_distance_queries();
}

RayCaster::~RayCaster() = default;

RayHit RayCaster::first_hit(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir) const {
  RayHit h;
  if (impl_->tris.empty()) return h;
  const K::Ray_3 ray(P(origin), K::Vector_3(dir.x(), dir.y(), dir.z()));
  auto r = impl_->tree.first_intersection(ray);
  if (!r) return h;
  h.face = static_cast<int>(r->second - impl_->tris.cbegin());
  if (const K::Point_3* p = boost::get<K::Point_3>(&r->first)) {
    h.point = V(*p);
  } else if (const K::Segment_3* sg = boost::get<K::Segment_3>(&r->first)) {
    // ray in the facet's plane: take the segment end nearer the origin
    const Eigen::Vector3d s0 = V(sg->source()), s1 = V(sg->target());
    h.point = (s0 - origin).squaredNorm() <= (s1 - origin).squaredNorm() ? s0 : s1;
  }
  h.distance = (h.point - origin).norm();
  h.front = impl_->normals[static_cast<std::size_t>(h.face)].dot(dir) < 0;
  return h;
}

RayHit RayCaster::closest(const Eigen::Vector3d& p) const {
  RayHit h;
  if (impl_->tris.empty()) return h;
  auto pp = impl_->tree.closest_point_and_primitive(P(p));
  h.point = V(pp.first);
  h.face = static_cast<int>(pp.second - impl_->tris.cbegin());
  h.distance = (h.point - p).norm();
  h.front = true;
  return h;
}

std::int64_t RayCaster::count_intersecting(const Surface& other, std::int64_t stop_after) const {
  std::atomic<std::int64_t> n{0};
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, other.faces.rows(), 256),
                    [&](const tbb::blocked_range<Eigen::Index>& r) {
                      for (Eigen::Index f = r.begin(); f != r.end(); ++f) {
                        if (n.load(std::memory_order_relaxed) >= stop_after) return;
                        const K::Triangle_3 t(P(other.vertices.row(other.faces(f, 0))),
                                              P(other.vertices.row(other.faces(f, 1))),
                                              P(other.vertices.row(other.faces(f, 2))));
                        if (impl_->tree.do_intersect(t)) n.fetch_add(1, std::memory_order_relaxed);
                      }
                    });
  return std::min<std::int64_t>(n.load(), stop_after);
}

Eigen::Vector3d closest_on_triangle(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                                    const Eigen::Vector3d& c, Eigen::Vector3d* bary) {
  auto out = [&](double u, double v, double w) {
    if (bary) *bary = {u, v, w};
    return Eigen::Vector3d(u * a + v * b + w * c);
  };
  const Eigen::Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return out(1, 0, 0);
  const Eigen::Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return out(0, 1, 0);
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) {
    const double v = d1 / (d1 - d3);
    return out(1 - v, v, 0);
  }
  const Eigen::Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return out(0, 0, 1);
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) {
    const double w = d2 / (d2 - d6);
    return out(1 - w, 0, w);
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
    const double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    return out(0, 1 - w, w);
  }
  const double denom = 1 / (va + vb + vc);
  const double v = vb * denom, w = vc * denom;
  return out(1 - v - w, v, w);
}

namespace {
// barycentric coordinates of p (assumed in the plane) in triangle (a, b, c)
Eigen::Vector3d barycentric(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                            const Eigen::Vector3d& c) {
  const Eigen::Vector3d v0 = b - a, v1 = c - a, v2 = p - a;
  const double d00 = v0.dot(v0), d01 = v0.dot(v1), d11 = v1.dot(v1), d20 = v2.dot(v0), d21 = v2.dot(v1);
  const double den = d00 * d11 - d01 * d01;
  const double v = (d11 * d20 - d01 * d21) / den, w = (d00 * d21 - d01 * d20) / den;
  return {1 - v - w, v, w};
}
}  // namespace

Projection project_centroids(const Surface& upper, const Surface& lower, const VecXi& expected,
                             const VecXd& reach, const ProjectionOptions& o) {
  const RayCaster caster(lower);
  return project_centroids(upper, lower, caster, expected, reach, o);
}

Projection project_centroids(const Surface& upper, const Surface& lower, const RayCaster& caster,
                             const VecXi& expected, const VecXd& reach, const ProjectionOptions& o) {
  const Eigen::Index n = upper.faces.rows();
  if (expected.size() != 0 && expected.size() != n) throw Error("", "project_centroids: expected_face size mismatch");
  if (reach.size() != 0 && reach.size() != n) throw Error("", "project_centroids: reach size mismatch");
  if (!(o.min_barycentric >= 0 && o.min_barycentric < 1.0 / 3))
    throw Error("", "project_centroids: min_barycentric must be in [0, 1/3)");
  Projection out;
  out.points.resize(n, 3);
  out.faces.resize(n);
  out.status.resize(n);
  std::vector<std::uint8_t> clamped(static_cast<std::size_t>(n), 0);
  auto lower_vertex = [&](int f, int k) -> Eigen::Vector3d { return lower.vertices.row(lower.faces(f, k)); };

  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, n, 512), [&](const tbb::blocked_range<Eigen::Index>& r) {
    for (Eigen::Index f = r.begin(); f != r.end(); ++f) {
      const Eigen::Vector3d a = upper.vertices.row(upper.faces(f, 0)), b = upper.vertices.row(upper.faces(f, 1)),
                            c = upper.vertices.row(upper.faces(f, 2));
      const Eigen::Vector3d g = (a + b + c) / 3.0;
      Eigen::Vector3d nrm = (b - a).cross(c - a);
      const double len = nrm.norm();
      const Eigen::Vector3d dir = len > 0 ? Eigen::Vector3d(-nrm / len) : Eigen::Vector3d::Zero();
      const int want = expected.size() ? expected(f) : -1;
      const double max_d = reach.size() ? o.max_distance_factor * reach(f) : std::numeric_limits<double>::infinity();
      RayHit h = len > 0 ? caster.first_hit(g, dir) : RayHit{};
      ProjectionStatus st = ProjectionStatus::hit;
      if (h.face < 0 || h.distance > max_d) {
        st = ProjectionStatus::miss;
      } else if (!h.front) {
        st = ProjectionStatus::backface;
      } else if (want >= 0 && h.face != want) {
        st = ProjectionStatus::other_cell;
      }
      Eigen::Vector3d p = h.point;
      int face = h.face;
      if (st != ProjectionStatus::hit) {
        if (want >= 0) {
          p = closest_on_triangle(g, lower_vertex(want, 0), lower_vertex(want, 1), lower_vertex(want, 2));
          face = want;
        } else {
          RayHit cp = caster.closest(g);
          p = cp.point;
          face = cp.face;
        }
      }
      // keep the point strictly inside its face
      if (face >= 0 && o.min_barycentric > 0) {
        const Eigen::Vector3d A = lower_vertex(face, 0), B = lower_vertex(face, 1), C = lower_vertex(face, 2);
        Eigen::Vector3d l = barycentric(p, A, B, C);
        if (l.minCoeff() < o.min_barycentric) {
          // move toward the face centroid until every coordinate reaches the floor
          const double third = 1.0 / 3;
          double t = 0;
          for (int k = 0; k < 3; ++k)
            if (l(k) < o.min_barycentric) t = std::max(t, (o.min_barycentric - l(k)) / (third - l(k)));
          l = (1 - t) * l + t * Eigen::Vector3d::Constant(third);
          p = l(0) * A + l(1) * B + l(2) * C;
          clamped[static_cast<std::size_t>(f)] = 1;
        }
      }
      out.points.row(f) = p.transpose();
      out.faces(f) = face;
      out.status(f) = static_cast<std::uint8_t>(st);
    }
  });
  out.counts.rays = n;
  for (Eigen::Index f = 0; f < n; ++f) {
    switch (static_cast<ProjectionStatus>(out.status(f))) {
      case ProjectionStatus::hit: ++out.counts.hits; break;
      case ProjectionStatus::miss: ++out.counts.miss; break;
      case ProjectionStatus::backface: ++out.counts.backface; break;
      case ProjectionStatus::other_cell: ++out.counts.other_cell; break;
    }
    if (clamped[static_cast<std::size_t>(f)] && out.status(f) == 0) ++out.counts.near_edge;
  }
  return out;
}

}  // namespace orthosim::msm
