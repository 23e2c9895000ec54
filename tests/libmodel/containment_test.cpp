// points_inside / first_point_outside: exact containment against a known
// truth (voxel staircases, whose vertices, edges and faces the query lattice
// hits exactly) and against CGAL's Side_of_triangle_mesh on a smooth tube.
#include "libmodel/remesh/remesh.h"
#include "tests/libmodel/remesh_shapes.h"

#include <gtest/gtest.h>

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Side_of_triangle_mesh.h>
#include <CGAL/Surface_mesh.h>

#include <cstdint>
#include <map>
#include <random>
#include <tuple>
#include <vector>

namespace orthosim {
namespace {

// Nested boxes stacked along z: level l spans [x0, x1] x [y0, y1] x [l, l+1]
// in voxel units, each footprint inside the one below (sides may coincide).
struct Staircase {
  std::vector<std::array<int, 4>> level;  // x0, x1, y0, y1
  double h = 0.5e-3;                      // voxel size, m
  Eigen::Vector3d origin{0.0123, -0.0071, 0.0333};

  Eigen::Vector3d at(double x, double y, double z) const { return origin + h * Eigen::Vector3d(x, y, z); }

  bool occupied(int x, int y, int z) const {
    if (z < 0 || z >= static_cast<int>(level.size())) return false;
    const auto& r = level[static_cast<std::size_t>(z)];
    return x >= r[0] && x < r[1] && y >= r[2] && y < r[3];
  }
  // closed box union, in lattice units (half-integers allowed)
  bool inside(double x, double y, double z) const {
    for (std::size_t l = 0; l < level.size(); ++l) {
      const auto& r = level[l];
      if (z >= static_cast<double>(l) && z <= static_cast<double>(l + 1) && x >= r[0] && x <= r[1] && y >= r[2] && y <= r[3])
        return true;
    }
    return false;
  }

  // the voxel faces between occupied and empty cells, outward, welded; the
  // quads split along alternating diagonals
  Surface mesh() const {
    Surface s;
    std::map<std::tuple<int, int, int>, int> id;
    std::vector<Eigen::Vector3d> v;
    std::vector<Eigen::Vector3i> f;
    auto vid = [&](int x, int y, int z) {
      auto [it, added] = id.try_emplace({x, y, z}, static_cast<int>(v.size()));
      if (added) v.push_back(at(x, y, z));
      return it->second;
    };
    int xmax = 0, ymax = 0;
    for (const auto& r : level) xmax = std::max(xmax, r[1]), ymax = std::max(ymax, r[3]);
    const int zmax = static_cast<int>(level.size());
    int parity = 0;
    auto quad = [&](std::array<int, 4> q) {  // counter-clockwise seen from outside
      if (++parity % 2) {
        f.emplace_back(q[0], q[1], q[2]), f.emplace_back(q[0], q[2], q[3]);
      } else {
        f.emplace_back(q[0], q[1], q[3]), f.emplace_back(q[1], q[2], q[3]);
      }
    };
    for (int z = -1; z <= zmax; ++z)
      for (int y = -1; y <= ymax; ++y)
        for (int x = -1; x <= xmax; ++x) {
          if (!occupied(x, y, z)) continue;
          if (!occupied(x + 1, y, z)) quad({vid(x + 1, y, z), vid(x + 1, y + 1, z), vid(x + 1, y + 1, z + 1), vid(x + 1, y, z + 1)});
          if (!occupied(x - 1, y, z)) quad({vid(x, y, z), vid(x, y, z + 1), vid(x, y + 1, z + 1), vid(x, y + 1, z)});
          if (!occupied(x, y + 1, z)) quad({vid(x, y + 1, z), vid(x, y + 1, z + 1), vid(x + 1, y + 1, z + 1), vid(x + 1, y + 1, z)});
          if (!occupied(x, y - 1, z)) quad({vid(x, y, z), vid(x + 1, y, z), vid(x + 1, y, z + 1), vid(x, y, z + 1)});
          if (!occupied(x, y, z + 1)) quad({vid(x, y, z + 1), vid(x + 1, y, z + 1), vid(x + 1, y + 1, z + 1), vid(x, y + 1, z + 1)});
          if (!occupied(x, y, z - 1)) quad({vid(x, y, z), vid(x, y + 1, z), vid(x + 1, y + 1, z), vid(x + 1, y, z)});
        }
    s.vertices.resize(static_cast<Eigen::Index>(v.size()), 3);
    for (std::size_t k = 0; k < v.size(); ++k) s.vertices.row(static_cast<Eigen::Index>(k)) = v[k];
    s.faces.resize(static_cast<Eigen::Index>(f.size()), 3);
    for (std::size_t k = 0; k < f.size(); ++k) s.faces.row(static_cast<Eigen::Index>(k)) = f[k];
    return s;
  }
};

// the points as the rows of a matrix
MatX3d rows(const std::vector<Eigen::Vector3d>& q) {
  MatX3d P(static_cast<Eigen::Index>(q.size()), 3);
  for (std::size_t k = 0; k < q.size(); ++k) P.row(static_cast<Eigen::Index>(k)) = q[k];
  return P;
}

Staircase random_staircase(unsigned seed, int levels, int width) {
  std::mt19937 rng(seed);
  Staircase st;
  std::array<int, 4> r{0, width, 0, width - 3};
  for (int l = 0; l < levels; ++l) {
    st.level.push_back(r);
    // shrink each side by 0 or 1 voxel, keeping at least 2 x 2
    std::uniform_int_distribution<int> d(0, 1);
    std::array<int, 4> n = {r[0] + d(rng), r[1] - d(rng), r[2] + d(rng), r[3] - d(rng)};
    if (n[1] - n[0] >= 2 && n[3] - n[2] >= 2) r = n;
  }
  return st;
}

TEST(Containment, VoxelStaircaseOnEveryHalfLatticePoint) {
  // taller than wide: rays run across (x or y), the caps and every step
  // are parallel to them, and the lattice hits vertices, edges and faces
  for (unsigned seed : {1u, 2u, 3u}) {
    const Staircase st = random_staircase(seed, 24, 12);
    const Surface s = st.mesh();
    ASSERT_EQ(check_closed_surface(s, "staircase", true).euler, 2);
    std::vector<Eigen::Vector3d> q;
    std::vector<char> truth;
    for (int z = -2; z <= 2 * 24 + 2; ++z)
      for (int y = -2; y <= 2 * 12 + 2; ++y)
        for (int x = -2; x <= 2 * 12 + 2; ++x) {
          q.push_back(st.at(0.5 * x, 0.5 * y, 0.5 * z));
          truth.push_back(st.inside(0.5 * x, 0.5 * y, 0.5 * z));
        }
    const MatX3d P = rows(q);
    const std::vector<char> in = points_inside(s, P);
    ASSERT_EQ(in.size(), truth.size());
    int wrong = 0, n_in = 0;
    for (std::size_t k = 0; k < q.size(); ++k) wrong += in[k] != truth[k], n_in += truth[k];
    EXPECT_EQ(wrong, 0) << "seed " << seed << ": " << wrong << " of " << q.size() << " points";
    EXPECT_GT(n_in, 1000);
    EXPECT_LT(n_in, static_cast<int>(q.size()) - 1000);
  }
}

TEST(Containment, AHollowShellsEmptyCellsShareOneRayPerSet) {
  // a box with a box-shaped cavity (its faces turned inward): two sets of
  // empty cells (the shell's material, the cavity), each answered by one
  // ray, and every lattice point (on vertices, edges and faces of both
  // surfaces included) classified exactly
  Staircase outer, cavity;
  outer.level.assign(40, {0, 32, 0, 32});  // walls of 10 voxels: 4.4 cells
  cavity.level.assign(20, {10, 22, 10, 22});
  cavity.origin = outer.at(0, 0, 10);
  Surface inward = cavity.mesh();
  inward.faces.col(1).swap(inward.faces.col(2));
  const Surface s = test::merge(outer.mesh(), inward);
  ASSERT_EQ(check_closed_surface(s, "shell", false).components, 2);
  std::vector<Eigen::Vector3d> q;
  std::vector<char> truth;
  for (int z = -2; z <= 2 * 40 + 2; ++z)
    for (int y = -2; y <= 2 * 32 + 2; ++y)
      for (int x = -2; x <= 2 * 32 + 2; ++x) {
        const double X = 0.5 * x, Y = 0.5 * y, Z = 0.5 * z;
        q.push_back(outer.at(X, Y, Z));
        const bool in_cavity = X > 10 && X < 22 && Y > 10 && Y < 22 && Z > 10 && Z < 30;
        truth.push_back(outer.inside(X, Y, Z) && !in_cavity);
      }
  const MatX3d P = rows(q);
  ContainmentStats stats;
  const std::vector<char> in = points_inside(s, P, &stats);
  int wrong = 0, n_in = 0, n_cavity = 0;
  for (std::size_t k = 0; k < q.size(); ++k) wrong += in[k] != truth[k], n_in += truth[k];
  for (int z = 21; z < 60; ++z) n_cavity += !in[static_cast<std::size_t>(((z + 2) * 69 + 34) * 69 + 34)];
  EXPECT_EQ(wrong, 0) << "of " << q.size() << " points";
  EXPECT_EQ(n_cavity, 39);  // the cavity's axis is outside
  EXPECT_GT(n_in, 1000);
  EXPECT_EQ(stats.points, static_cast<std::int64_t>(q.size()));
  EXPECT_EQ(stats.empty_components, 2);  // the boundary cells are all occupied: no set outside
  EXPECT_GE(stats.ray_tests, stats.empty_components);
  // the walls are only about four cells thick, so about half the points sit
  // in cells a face reaches (or outside the box); the rest took their set's answer
  EXPECT_LT(stats.ray_tests, stats.points * 3 / 4);
}

TEST(Containment, FirstPointOutside) {
  const Staircase st = random_staircase(7, 10, 8);
  const Surface s = st.mesh();
  MatX3d P(4, 3);
  P.row(0) = st.at(4, 2.5, 0);     // on the bottom cap
  P.row(1) = s.vertices.row(5);    // a vertex
  P.row(2) = st.at(4, 2.5, 10);    // at the top level's height: on the cap or outside
  P.row(3) = st.at(-0.5, 2, 5);    // outside
  const std::int64_t bad = first_point_outside(s, P);
  EXPECT_EQ(bad, st.inside(4, 2.5, 10) ? 3 : 2);
  EXPECT_EQ(first_point_outside(s, P.topRows(2)), -1);
  MatX3d nan(1, 3);
  nan << std::nan(""), 0, 0;
  EXPECT_EQ(first_point_outside(s, nan), 0);
}

TEST(Containment, AgreesWithCgalOnABentTube) {
  using K = CGAL::Exact_predicates_inexact_constructions_kernel;
  using Mesh = CGAL::Surface_mesh<K::Point_3>;
  const Surface s = test::BentTube{}.mesh(96, 48);
  Mesh m;
  std::vector<Mesh::Vertex_index> vi;
  for (Eigen::Index v = 0; v < s.vertices.rows(); ++v)
    vi.push_back(m.add_vertex(K::Point_3(s.vertices(v, 0), s.vertices(v, 1), s.vertices(v, 2))));
  for (Eigen::Index f = 0; f < s.faces.rows(); ++f) m.add_face(vi[s.faces(f, 0)], vi[s.faces(f, 1)], vi[s.faces(f, 2)]);
  const CGAL::Side_of_triangle_mesh<Mesh, K> side(m);

  // random points in the box, the vertices, and points on edges and faces
  const Eigen::Vector3d lo = s.vertices.colwise().minCoeff(), hi = s.vertices.colwise().maxCoeff();
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<Eigen::Vector3d> q;
  for (int k = 0; k < 20000; ++k) q.push_back(lo + (hi - lo).cwiseProduct(Eigen::Vector3d(u(rng), u(rng), u(rng))));
  for (Eigen::Index v = 0; v < s.vertices.rows(); ++v) q.push_back(s.vertices.row(v));
  for (Eigen::Index f = 0; f < s.faces.rows(); f += 7) {
    const Eigen::Vector3d a = s.vertices.row(s.faces(f, 0)), b = s.vertices.row(s.faces(f, 1)), c = s.vertices.row(s.faces(f, 2));
    q.push_back(0.5 * (a + b));
    q.push_back((a + b + c) / 3);
    q.push_back((a + b + c) / 3 + 1e-9 * (b - a).cross(c - a).normalized());
  }
  const MatX3d P = rows(q);
  const std::vector<char> in = points_inside(s, P);
  int wrong = 0, n_in = 0;
  for (std::size_t k = 0; k < q.size(); ++k) {
    const bool ref = side(K::Point_3(q[k].x(), q[k].y(), q[k].z())) != CGAL::ON_UNBOUNDED_SIDE;
    wrong += ref != static_cast<bool>(in[k]);
    n_in += ref;
  }
  EXPECT_EQ(wrong, 0) << "of " << q.size();
  EXPECT_GT(n_in, 5000);
}

}  // namespace
}  // namespace orthosim
