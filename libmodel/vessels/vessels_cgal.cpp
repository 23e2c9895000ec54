// The only CGAL in libmodel/vessels: the mean-curvature-flow skeleton peer of
// the benchmark (the tube mesh's self-intersection count is the surface
// stage's surface_self_intersections).
#include "libmodel/vessels/vessels.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Mean_curvature_flow_skeletonization.h>
#include <CGAL/Simple_cartesian.h>
#include <CGAL/Surface_mesh.h>
#include <CGAL/boost/graph/helpers.h>
#include <CGAL/extract_mean_curvature_flow_skeleton.h>

#include <map>
#include <vector>

namespace orthosim {
namespace {

template <class Mesh>
Mesh to_mesh(const Surface& s, const char* what) {
  using P = typename Mesh::Point;
  Mesh m;
  std::vector<typename Mesh::Vertex_index> v;
  v.reserve(static_cast<std::size_t>(s.vertices.rows()));
  for (Eigen::Index i = 0; i < s.vertices.rows(); ++i)
    v.push_back(m.add_vertex(P(s.vertices(i, 0), s.vertices(i, 1), s.vertices(i, 2))));
  for (Eigen::Index i = 0; i < s.faces.rows(); ++i) {
    const auto f = m.add_face(v[s.faces(i, 0)], v[s.faces(i, 1)], v[s.faces(i, 2)]);
    if (f == Mesh::null_face()) throw Error("", std::string(what) + ": the surface is not an oriented 2-manifold");
  }
  return m;
}

}  // namespace

SkeletonGraph cgal_mcf_skeleton(const Surface& s) {
  using K = CGAL::Simple_cartesian<double>;
  using Mesh = CGAL::Surface_mesh<K::Point_3>;
  using Skeletonization = CGAL::Mean_curvature_flow_skeletonization<Mesh>;
  using Skeleton = Skeletonization::Skeleton;
  Mesh m = to_mesh<Mesh>(s, "CGAL skeleton");
  if (!CGAL::is_closed(m) || !CGAL::is_triangle_mesh(m))
    throw Error("", "CGAL skeleton: the surface must be a closed triangle mesh");
  Skeleton sk;
  CGAL::extract_mean_curvature_flow_skeleton(m, sk);
  SkeletonGraph g;
  const auto nv = boost::num_vertices(sk);
  g.nodes.resize(static_cast<Eigen::Index>(nv), 3);
  std::vector<int> degree(nv, 0);
  for (auto v : CGAL::make_range(vertices(sk))) {
    const auto& p = sk[v].point;
    g.nodes.row(static_cast<Eigen::Index>(v)) << p.x(), p.y(), p.z();
  }
  std::vector<std::pair<int, int>> e;
  for (auto ed : CGAL::make_range(edges(sk))) {
    const int a = static_cast<int>(source(ed, sk)), b = static_cast<int>(target(ed, sk));
    e.push_back({a, b});
    ++degree[a], ++degree[b];
  }
  g.edges.resize(static_cast<Eigen::Index>(e.size()), 2);
  for (std::size_t i = 0; i < e.size(); ++i) g.edges.row(static_cast<Eigen::Index>(i)) << e[i].first, e[i].second;
  // branches: maximal paths between nodes of degree != 2 (a lone cycle counts once)
  int ends = 0, junctions = 0, deg_sum_nodes = 0;
  for (int d : degree) {
    if (d != 2) ends += 1, deg_sum_nodes += d;
    if (d >= 3) ++junctions;
  }
  g.junctions = junctions;
  g.branches = ends > 0 ? deg_sum_nodes / 2 : (nv > 0 ? 1 : 0);
  return g;
}

}  // namespace orthosim
