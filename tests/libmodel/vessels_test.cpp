// vessels: accuracy against analytic tubes and the phantom's true vessel
// trees, tree rules, Bezier and tube-mesh invariants, determinism, bad input
// (the CLI is vessels_cli_test.cpp).
#include "libmodel/vessels/vessels.h"
#include "libmodel/phantom/phantom.h"
#include "libmodel/segment/segment.h"
#include "tests/libmodel/vessels_shapes.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>

#include <functional>
#include <tbb/global_control.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>

namespace orthosim {
namespace {

using test::TubeSpec;
constexpr double kPi = 3.14159265358979323846;

// ---- shared checks --------------------------------------------------------------------

void print(const std::string& name, const VesselResult& r, const CentrelineError& e, double vox) {
  const VesselMetrics& m = r.metrics;
  std::printf(
      "[%s] branches %d trees %d bif %d trif %d | mean %.3f max %.3f vox (truth->ext mean %.3f max %.3f) | overlap "
      "%.4f/%.4f | radius mean %.1f%% p95 %.1f%% max %.1f%% | bezier %d pieces dev %.4f mm (tol %.4f) | tube %lld q "
      "%lld t, self-x %d, boundary mean %.3f p95 %.3f max %.3f mm | spurs %d loops %d contacts %d | %.0f ms\n",
      name.c_str(), m.branches, m.trees, m.bifurcations, m.trifurcations, e.mean_m / vox, e.max_m / vox,
      e.truth_mean_m / vox, e.truth_max_m / vox, e.overlap_extracted, e.overlap_truth, 100 * e.radius_mean_rel,
      100 * e.radius_p95_rel, 100 * e.radius_max_rel, m.bezier_pieces, 1e3 * m.bezier_max_deviation_m,
      1e3 * m.tolerance_m, static_cast<long long>(m.tube_quads), static_cast<long long>(m.tube_tris),
      m.self_intersections, 1e3 * m.boundary_mean_m, 1e3 * m.boundary_p95_m, 1e3 * m.boundary_max_m, m.spurs_pruned,
      m.loops_broken, m.contacts_cut,
      1e3 * (m.distance_s + m.thinning_s + m.graph_s + m.centreline_s + m.fit_s + m.tube_s));
}

// The extracted centreline against the truth: distances in voxels, overlap
// both ways, radius error.
void expect_accuracy(const CentrelineError& e, double vox) {
  EXPECT_LE(e.mean_m, 0.5 * vox);
  EXPECT_LE(e.max_m, 2.0 * vox);
  EXPECT_GE(e.overlap_extracted, 0.99);
  EXPECT_GE(e.overlap_truth, 0.99);
  EXPECT_LE(e.radius_mean_rel, 0.10);
  EXPECT_LE(e.radius_p95_rel, 0.10);
}

// Same branch count and the same parent of every branch, up to the order of siblings.
void expect_topology(const VesselTree& t, const std::vector<int>& parents) {
  ASSERT_EQ(t.branch_parent.size(), static_cast<Eigen::Index>(parents.size()));
  std::vector<int> a(t.branch_parent.data(), t.branch_parent.data() + t.branch_parent.size());
  std::vector<int> b = parents;
  std::sort(a.begin(), a.end());
  std::sort(b.begin(), b.end());
  EXPECT_EQ(a, b);
  // parents come first and children start at their parent's end node
  for (Eigen::Index i = 0; i < t.branch_parent.size(); ++i) {
    const int p = t.branch_parent(i);
    if (p < 0) continue;
    EXPECT_LT(p, i);
    EXPECT_EQ(t.branch_nodes(t.branch_offsets(i)), t.branch_nodes(t.branch_offsets(p + 1) - 1));
  }
}

// Bezier: 3k+1 control points per branch, within the tolerance of the
// centreline both ways, C1 in arc length at every join.
void expect_bezier(const VesselTree& t, double tol) {
  for (Eigen::Index b = 0; b + 1 < t.branch_offsets.size(); ++b) {
    const int nc = t.bezier_offsets(b + 1) - t.bezier_offsets(b);
    ASSERT_EQ((nc - 1) % 3, 0);
    const int pieces = bezier_pieces(t, static_cast<int>(b));
    ASSERT_GE(pieces, 1);
    std::vector<Eigen::Vector3d> poly;
    for (int k = t.branch_offsets(b); k < t.branch_offsets(b + 1); ++k) poly.push_back(t.nodes.row(t.branch_nodes(k)).transpose());
    // curve -> centreline polyline
    double worst = 0;
    std::vector<Eigen::Vector3d> samples;
    for (int p = 0; p < pieces; ++p)
      for (int i = 0; i <= 40; ++i) samples.push_back(bezier_point(t, static_cast<int>(b), p, i / 40.0));
    for (const auto& q : samples) {
      double d = 1e300;
      for (std::size_t i = 0; i + 1 < poly.size(); ++i) {
        const Eigen::Vector3d a = poly[i], c = poly[i + 1], e = c - a;
        const double s = std::clamp((q - a).dot(e) / e.squaredNorm(), 0.0, 1.0);
        d = std::min(d, (q - (a + s * e)).norm());
      }
      worst = std::max(worst, d);
    }
    EXPECT_LE(worst, tol * 1.05 + 1e-9) << "branch " << b;
    // centreline nodes -> curve
    double worst2 = 0;
    for (const auto& q : poly) {
      double d = 1e300;
      for (std::size_t i = 0; i + 1 < samples.size(); ++i) {
        const Eigen::Vector3d a = samples[i], c = samples[i + 1], e = c - a;
        const double s = e.squaredNorm() > 0 ? std::clamp((q - a).dot(e) / e.squaredNorm(), 0.0, 1.0) : 0.0;
        d = std::min(d, (q - (a + s * e)).norm());
      }
      worst2 = std::max(worst2, d);
    }
    EXPECT_LE(worst2, tol * 1.05 + 1e-9) << "branch " << b;
    // joins: the same tangent direction, speeds in the ratio of the pieces' lengths
    for (int p = 0; p + 1 < pieces; ++p) {
      const Eigen::Vector3d d0 = bezier_derivative(t, static_cast<int>(b), p, 1.0);
      const Eigen::Vector3d d1 = bezier_derivative(t, static_cast<int>(b), p + 1, 0.0);
      EXPECT_NEAR(d0.normalized().dot(d1.normalized()), 1.0, 1e-9);
    }
  }
}

void expect_tube(const VesselResult& r, int trees) {
  const VesselTree& t = r.tree;
  const MeshCheck c = check_mesh(t.tube_vertices, t.tube_quads, t.tube_tris);
  EXPECT_TRUE(c.closed()) << c.boundary_edges << " boundary edges";
  EXPECT_TRUE(c.manifold()) << c.nonmanifold_edges << " non-manifold edges, " << c.nonmanifold_vertices << " vertices";
  EXPECT_TRUE(c.oriented()) << c.misoriented_edges;
  EXPECT_EQ(c.degenerate_faces, 0);
  EXPECT_EQ(c.components, trees);
  for (int e : c.euler) EXPECT_EQ(e, 2);
  EXPECT_GT(c.volume_m3, 0);
  EXPECT_EQ(r.metrics.self_intersections, 0);
  EXPECT_GT(t.tube_quads.rows(), 0);
  EXPECT_GE(t.tube_quads.rows(), 10 * t.tube_tris.rows());  // quads preferred
}

struct Case {
  Volume v;
  std::vector<TubeSpec> tubes;
  VesselTree truth;
  double vox;
};

Case make_case(int nx, int ny, int nz, std::array<double, 3> h, std::vector<TubeSpec> tubes, bool clip = true) {
  Case c;
  c.v = test::empty_volume(nx, ny, nz, h, {0, 0, 0});
  test::rasterise(c.v, tubes, 6);
  c.vox = std::min({h[0], h[1], h[2]});
  c.truth = test::truth_tree(tubes, 0.25 * c.vox, clip ? &c.v : nullptr);
  c.tubes = std::move(tubes);
  return c;
}

// ---- analytic cases ------------------------------------------------------------------------

// The distance to a label's voxel faces, against brute force over every face,
// on strongly anisotropic voxels (0.01 x 0.3 x 1 mm). The search grid's cells
// were two voxels per axis, so each ring of the search ran 30-100x farther
// along the coarse axes than it was sure of along the fine one: the vessels
// stage ran for minutes on such a stack. Its cubes now make it about 2 s;
// the distances are the same, which this checks (also on the demo's voxels).
TEST(Vessels, DistanceToTheLabelBoundaryIsExactOnAnisotropicVoxels) {
  for (const std::array<double, 3> h : {std::array<double, 3>{0.01e-3, 0.3e-3, 1e-3}, std::array<double, 3>{0.45e-3, 0.45e-3, 1.5e-3}}) {
    Volume v;
    v.nx = 24, v.ny = 20, v.nz = 12;
    v.spacing_m = h;
    v.label_names = {"background", "vessel"};
    v.labels.assign(static_cast<std::size_t>(v.nx) * v.ny * v.nz, 0);
    std::mt19937 rng(5);
    for (int z = 2; z < 10; ++z)  // a lumpy blob
      for (int y = 3; y < 17; ++y)
        for (int x = 4; x < 20; ++x)
          if (std::hypot(x - 12.0, y - 10.0) < 6 + 2.0 * ((rng() % 100) / 100.0)) v.labels[v.index(x, y, z)] = 1;
    // every face between a label voxel and another, brute force
    std::vector<std::pair<Eigen::Vector3d, int>> faces;
    for (int z = 0; z < v.nz; ++z)
      for (int y = 0; y < v.ny; ++y)
        for (int x = 0; x < v.nx; ++x)
          for (int a = 0; a < 3; ++a) {
            const int c[3] = {x + (a == 0), y + (a == 1), z + (a == 2)};
            if (c[0] >= v.nx || c[1] >= v.ny || c[2] >= v.nz || (v.at(x, y, z) == 1) == (v.at(c[0], c[1], c[2]) == 1)) continue;
            Eigen::Vector3d p = v.position(x, y, z);
            p(a) += 0.5 * h[static_cast<std::size_t>(a)];
            faces.push_back({p, a});
          }
    MatX3d pts(200, 3);
    std::uniform_real_distribution<double> ux(0, 24 * h[0]), uy(0, 20 * h[1]), uz(0, 12 * h[2]);
    for (Eigen::Index i = 0; i < pts.rows(); ++i) pts.row(i) << ux(rng), uy(rng), uz(rng);
    const double max_m = 1.0;
    const VecXd d = distance_to_label_boundary(v, 1, pts, max_m);
    for (Eigen::Index i = 0; i < pts.rows(); ++i) {
      double best = max_m;
      for (const auto& [c, a] : faces) {
        Eigen::Vector3d e = pts.row(i).transpose() - c;
        for (int k = 0; k < 3; ++k)
          if (k != a) e(k) = std::max(0.0, std::abs(e(k)) - 0.5 * h[static_cast<std::size_t>(k)]);
        best = std::min(best, e.norm());
      }
      EXPECT_NEAR(d(i), best, 1e-15) << "point " << i << ", spacing " << h[0] << " " << h[1] << " " << h[2];
    }
  }
}

TEST(Vessels, StraightTubeCutByTheBorder) {
  const double h = 0.5e-3;
  // along z, slightly tilted, through both end faces of the volume
  Case c = make_case(40, 40, 60, {h, h, h},
                     {{test::segment({9.5e-3, 10e-3, -2e-3}, {10.5e-3, 9.5e-3, 32e-3}), test::constant(3e-3), -1}});
  const VesselResult r = extract_vessels(c.v, "artery", {});
  const CentrelineError e = compare_centrelines(r.tree, c.truth);
  print("straight", r, e, c.vox);
  expect_accuracy(e, c.vox);
  expect_topology(r.tree, {-1});
  expect_bezier(r.tree, r.metrics.tolerance_m);
  expect_tube(r, 1);
  // both ends are open (cut by the border) and reported
  ASSERT_EQ(r.metrics.ends.size(), 2u);
  for (const auto& end : r.metrics.ends) EXPECT_TRUE(end.open);
  // a straight tube needs few pieces
  EXPECT_LE(r.metrics.bezier_pieces, 4);
}

TEST(Vessels, Helix) {
  const double h = 0.4e-3;
  const double R = 6e-3, pitch = 16e-3, turns = 1.5, r = 1.6e-3;
  const Eigen::Vector3d c0(12e-3, 12e-3, 4e-3);
  auto centre = [=](double t) {
    const double a = 2 * kPi * turns * t;
    return Eigen::Vector3d(c0.x() + R * std::cos(a), c0.y() + R * std::sin(a), c0.z() + pitch * turns * t);
  };
  Case c = make_case(60, 60, 80, {h, h, h}, {{centre, test::constant(r), -1}});
  const VesselResult res = extract_vessels(c.v, "artery", {});
  const CentrelineError e = compare_centrelines(res.tree, c.truth);
  print("helix", res, e, c.vox);
  expect_accuracy(e, c.vox);
  expect_topology(res.tree, {-1});
  expect_bezier(res.tree, res.metrics.tolerance_m);
  expect_tube(res, 1);
  // closed ends inside the volume
  for (const auto& end : res.metrics.ends) EXPECT_FALSE(end.open);
  // curvature-adaptive: a bent vessel needs more pieces per length than a straight one
  EXPECT_GE(res.metrics.bezier_pieces, 6);
}

TEST(Vessels, YBifurcation) {
  const double h = 0.4e-3;
  Case c = make_case(70, 40, 100, {h, h, h},
                     test::y_tubes({14e-3, 8e-3, -1e-3}, 16e-3, 26e-3, 0.45, 2.2e-3, 1.8e-3));
  const VesselResult r = extract_vessels(c.v, "artery", {});
  const CentrelineError e = compare_centrelines(r.tree, c.truth);
  print("Y", r, e, c.vox);
  expect_accuracy(e, c.vox);
  expect_topology(r.tree, {-1, 0, 0});
  EXPECT_EQ(r.metrics.bifurcations, 1);
  expect_bezier(r.tree, r.metrics.tolerance_m);
  expect_tube(r, 1);
  // the root is the wide end cut by the border (z = 0)
  EXPECT_LT(r.tree.nodes(r.tree.branch_nodes(0), 2), 1e-3);
}

// Narrow bifurcations: the children's first rings are close and tilted
// apart, so the crotch turns tightly. A faired (free) crotch folded through
// itself here; the placed crotch keeps the patch free of self-intersections.
TEST(Vessels, NarrowYBifurcation) {
  const double h = 0.4e-3;
  Case c = make_case(70, 40, 100, {h, h, h},
                     test::y_tubes({14e-3, 8e-3, -1e-3}, 16e-3, 26e-3, 0.2, 2.2e-3, 1.8e-3));
  const VesselResult r = extract_vessels(c.v, "artery", {});
  const CentrelineError e = compare_centrelines(r.tree, c.truth);
  print("narrow Y", r, e, c.vox);
  expect_accuracy(e, c.vox);
  expect_topology(r.tree, {-1, 0, 0});
  expect_bezier(r.tree, r.metrics.tolerance_m);
  expect_tube(r, 1);
}

// One child continues the parent's axis, the other leaves it: seen from the
// parent's axis the continuing child has no angle, so the patch's split
// points follow the children's directions around their own centroid.
TEST(Vessels, SideBranchOffAStraightVessel) {
  const double h = 0.4e-3, ang = 0.6;
  const Eigen::Vector3d a(12e-3, 8e-3, -1e-3), b(12e-3, 8e-3, 15e-3);
  std::vector<TubeSpec> tubes{{test::segment(a, b), test::constant(2.2e-3), -1}};
  tubes.push_back({test::segment(b, b + Eigen::Vector3d(0, 0, 26e-3)),
                   [](double t) { return 2.2e-3 - 0.3e-3 * std::min(1.0, 3 * t); }, 0});
  const Eigen::Vector3d d(std::sin(ang), 0, std::cos(ang));
  const Eigen::Vector3d p1 = b + 26e-3 / 3 * d, p3 = b + 26e-3 * Eigen::Vector3d(0.75 * std::sin(ang), 0, 0.95),
                        p2 = p3 - 26e-3 / 3 * Eigen::Vector3d::UnitZ();
  tubes.push_back({[=](double u) {
                     const double w = 1 - u;
                     return Eigen::Vector3d(w * w * w * b + 3 * w * w * u * p1 + 3 * w * u * u * p2 + u * u * u * p3);
                   },
                   [](double t) { return 2.2e-3 - 0.6e-3 * std::min(1.0, 3 * t); }, 0});
  Case c = make_case(70, 40, 100, {h, h, h}, tubes);
  const VesselResult r = extract_vessels(c.v, "artery", {});
  const CentrelineError e = compare_centrelines(r.tree, c.truth);
  print("side branch", r, e, c.vox);
  expect_accuracy(e, c.vox);
  expect_topology(r.tree, {-1, 0, 0});
  expect_bezier(r.tree, r.metrics.tolerance_m);
  expect_tube(r, 1);
}

TEST(Vessels, Trifurcation) {
  const double h = 0.4e-3;
  const Eigen::Vector3d a(14e-3, 14e-3, -1e-3), b(14e-3, 14e-3, 14e-3);
  std::vector<TubeSpec> tubes{{test::segment(a, b), test::constant(2.2e-3), -1}};
  for (int i = 0; i < 3; ++i) {
    const double phi = 2 * kPi * i / 3 + 0.3;
    const Eigen::Vector3d e = b + Eigen::Vector3d(9e-3 * std::cos(phi), 9e-3 * std::sin(phi), 17e-3);
    tubes.push_back({test::segment(b, e), [](double t) { return 2.2e-3 - 0.6e-3 * std::min(1.0, 3 * t); }, 0});
  }
  Case c = make_case(70, 70, 90, {h, h, h}, tubes);
  const VesselResult r = extract_vessels(c.v, "artery", {});
  const CentrelineError e = compare_centrelines(r.tree, c.truth);
  print("trifurcation", r, e, c.vox);
  expect_accuracy(e, c.vox);
  expect_topology(r.tree, {-1, 0, 0, 0});
  EXPECT_EQ(r.metrics.trifurcations, 1);
  expect_bezier(r.tree, r.metrics.tolerance_m);
  expect_tube(r, 1);
  // refused clearly when only bifurcations are allowed and pruning is off
  VesselOptions o;
  o.max_children = 2;
  o.prune_excess_children = false;
  try {
    extract_vessels(c.v, "artery", o);
    ADD_FAILURE() << "a trifurcation with max_children = 2 was accepted";
  } catch (const Error& err) {
    EXPECT_NE(std::string(err.what()).find("3 children"), std::string::npos) << err.what();
  }
}

TEST(Vessels, JunctionWithMoreChildrenThanAllowedLosesItsShortestLeaf) {
  // four children, one of them short (8 mm against 19 mm): with at most 3
  // children the short one is dropped and counted, the rest is the
  // trifurcation; with 4 allowed all are kept; with pruning off it is refused
  const double h = 0.4e-3;
  const Eigen::Vector3d a(16e-3, 16e-3, -1e-3), b(16e-3, 16e-3, 14e-3);
  std::vector<TubeSpec> tubes{{test::segment(a, b), test::constant(2.2e-3), -1}};
  std::vector<Eigen::Vector3d> ends;
  for (int i = 0; i < 4; ++i) {
    const double phi = 2 * kPi * i / 4 + 0.3, len = i == 2 ? 0.45 : 1.0;
    ends.push_back(b + len * Eigen::Vector3d(10e-3 * std::cos(phi), 10e-3 * std::sin(phi), 16e-3));
    tubes.push_back({test::segment(b, ends.back()), [](double t) { return 2.2e-3 - 0.6e-3 * std::min(1.0, 3 * t); }, 0});
  }
  Case c = make_case(80, 80, 90, {h, h, h}, tubes);
  const VesselResult r = extract_vessels(c.v, "artery", {});
  EXPECT_EQ(r.metrics.children_pruned, 1);
  EXPECT_NEAR(r.metrics.pruned_length_m, (ends[2] - b).norm(), 4e-3) << "the short child was not the one dropped";
  expect_topology(r.tree, {-1, 0, 0, 0});
  EXPECT_EQ(r.metrics.trifurcations, 1);
  // the kept children are the three long ones: each ends within 2 voxels of a long tube's end
  for (int i : {0, 1, 3}) {
    double best = 1e9;
    for (const VesselEnd& e : r.metrics.ends) best = std::min(best, (e.position_m - ends[static_cast<std::size_t>(i)]).norm());
    EXPECT_LT(best, 2 * h + 2.2e-3) << "child " << i;
  }
  expect_tube(r, 1);

  VesselOptions four;
  four.max_children = 4;
  const VesselResult r4 = extract_vessels(c.v, "artery", four);
  EXPECT_EQ(r4.metrics.children_pruned, 0);
  expect_topology(r4.tree, {-1, 0, 0, 0, 0});
  expect_tube(r4, 1);

  VesselOptions strict;
  strict.prune_excess_children = false;
  try {
    extract_vessels(c.v, "artery", strict);
    ADD_FAILURE() << "a junction with 4 children was accepted with pruning off";
  } catch (const Error& err) {
    EXPECT_NE(std::string(err.what()).find("4 children"), std::string::npos) << err.what();
  }
}

TEST(Vessels, TwoTouchingVessels) {
  // two tubes bowing toward each other, overlapping by 0.2 mm at mid-height:
  // two trees, the contact cut and reported
  const double h = 0.4e-3, r = 2e-3, gap = r - 0.1e-3;  // axis to the mid-plane at mid-height
  auto bow = [=](double s) {
    return [=](double t) {
      const double x = 10e-3 + s * (gap + (3.5e-3 - gap) * (1 - std::sin(kPi * t)));
      return Eigen::Vector3d(x, 10e-3, -1e-3 + 34e-3 * t);
    };
  };
  Case c = make_case(50, 50, 80, {h, h, h}, {{bow(-1), test::constant(r), -1}, {bow(1), test::constant(r), -1}});
  const VesselResult res = extract_vessels(c.v, "artery", {});
  const CentrelineError e = compare_centrelines(res.tree, c.truth);
  print("touching", res, e, c.vox);
  expect_accuracy(e, c.vox);
  expect_topology(res.tree, {-1, -1});
  EXPECT_EQ(res.metrics.trees, 2);
  EXPECT_GE(res.metrics.contacts_cut + res.metrics.loops_broken, 1);
  EXPECT_FALSE(res.metrics.cuts.empty());
  expect_tube(res, 2);
}

TEST(Vessels, LoopIsBrokenAtItsThinnestEdge) {
  // a Y whose children come back and overlap by 0.2 mm lower down, then part
  // again: a skeleton cycle, broken at the contact (reported); the tree keeps
  // the parent and its two children
  const double h = 0.4e-3, r = 1.8e-3, meet = r - 0.1e-3;
  const Eigen::Vector3d b(14e-3, 10e-3, 10e-3);
  std::vector<TubeSpec> tubes{{test::segment({14e-3, 10e-3, -1e-3}, b), test::constant(2.2e-3), -1}};
  for (int s : {-1, 1})
    tubes.push_back({[=](double t) {
                       // out to 5 mm, back to `meet` at t = 0.6, out again to 4 mm
                       const double g = t <= 0.6 ? meet * t / 0.6 + 5e-3 * std::sin(kPi * t / 0.6)
                                                 : meet + 4e-3 * std::pow((t - 0.6) / 0.4, 2);
                       return Eigen::Vector3d(b.x() + s * g, b.y(), b.z() + 28e-3 * t);
                     },
                     [](double t) { return 2.2e-3 - 0.4e-3 * std::min(1.0, 4 * t); }, 0});
  Case c = make_case(70, 50, 100, {h, h, h}, tubes);
  const VesselResult res = extract_vessels(c.v, "artery", {});
  const CentrelineError e = compare_centrelines(res.tree, c.truth);
  print("loop", res, e, c.vox);
  EXPECT_GE(res.metrics.loops_broken, 1);
  EXPECT_FALSE(res.metrics.cuts.empty());
  expect_topology(res.tree, {-1, 0, 0});
  expect_tube(res, 1);
}

TEST(Vessels, ObliqueTubeAnisotropicVoxels) {
  const std::array<double, 3> h{0.3e-3, 0.3e-3, 0.9e-3};
  Case c = make_case(80, 70, 40, h,
                     {{test::segment({2e-3, 3e-3, -1e-3}, {22e-3, 18e-3, 36e-3}), test::constant(2.0e-3), -1}});
  const VesselResult r = extract_vessels(c.v, "artery", {});
  const CentrelineError e = compare_centrelines(r.tree, c.truth);
  print("oblique", r, e, c.vox);
  expect_accuracy(e, c.vox);
  expect_topology(r.tree, {-1});
  expect_bezier(r.tree, r.metrics.tolerance_m);
  expect_tube(r, 1);
}

// ---- the phantom ---------------------------------------------------------------------------

TEST(Vessels, PhantomTrees) {
  PhantomOptions po;
  po.nx = po.ny = 160, po.nz = 64;
  po.spacing_m = {0.4e-3, 0.4e-3, 1.2e-3};
  const Volume v = phantom_labels(po);
  const auto truth = phantom_vessels(po);
  for (const std::string tissue : {"artery", "vein"}) {
    const VesselResult r = extract_vessels(v, tissue, {});
    const CentrelineError e = compare_centrelines(r.tree, truth.at(tissue));
    print("phantom " + tissue, r, e, 0.4e-3);
    expect_accuracy(e, 0.4e-3);
    const VesselTree& t = truth.at(tissue);
    expect_topology(r.tree, std::vector<int>(t.branch_parent.data(), t.branch_parent.data() + t.branch_parent.size()));
    expect_bezier(r.tree, r.metrics.tolerance_m);
    expect_tube(r, 1);
    for (const auto& end : r.metrics.ends) EXPECT_TRUE(end.open);
  }
}

// The vein of a segmented phantom at 8-bit noise 24 (the pipeline's command:
// `orthosim phantom --size 160x160x64 --spacing 0.4,0.4,1.0 --noise 24`, then
// segment with the defaults): its noisy labels grow short branches between
// junctions, and moving a junction's last clean point back one radius took
// it into the branch's own head region. The tail's rewrite then cut off the
// head's index: an internal error (vector::_M_range_insert), exit 1. Now a
// tree with valid Bezier curves and tube. The labels are the per-voxel
// rule's (smoothness 0, as segment's default was then): the smoothness
// prior gives the vein its one true branch.
TEST(Vessels, NoisySegmentedVeinWithShortBranches) {
  PhantomOptions po;
  po.nx = po.ny = 160, po.nz = 64;
  po.spacing_m = {0.4e-3, 0.4e-3, 1.0e-3};
  po.noise_sigma = 24;
  po.seed = 1;
  const Volume truth = phantom_labels(po);
  std::vector<RgbImage> slices(static_cast<std::size_t>(po.nz));
  for (int z = 0; z < po.nz; ++z) {
    auto& sl = slices[static_cast<std::size_t>(z)];
    sl.nx = po.nx, sl.ny = po.ny;
    phantom_slice_rgb(po, truth, z, sl.rgb);
  }
  SegmentOptions so;
  so.spacing_m = po.spacing_m;
  so.smoothness = 0;
  const Volume labels = segment_volume(memory_source(std::move(slices)), phantom_tissue_table(), so);
  const VesselResult r = extract_vessels(labels, "vein", {});
  std::printf("  noisy vein: %d trees, %d branches, %d self-intersecting face pairs\n", r.metrics.trees,
              r.metrics.branches, r.metrics.self_intersections);
  EXPECT_GE(r.metrics.branches, 3);  // the phantom's vein branches once at least
  expect_bezier(r.tree, r.metrics.tolerance_m);
  // each tree's tube is closed, manifold and oriented; the noise's islands
  // make more trees than the phantom's one, and their tubes may cut each
  // other (counted, and `orthosim vessels` warns)
  const MeshCheck c = check_mesh(r.tree.tube_vertices, r.tree.tube_quads, r.tree.tube_tris);
  EXPECT_TRUE(c.closed() && c.manifold() && c.oriented()) << c.boundary_edges << " " << c.nonmanifold_edges;
  EXPECT_EQ(c.degenerate_faces, 0);
  EXPECT_EQ(c.components, r.metrics.trees);
  EXPECT_GE(r.metrics.self_intersections, 0);  // counted
}

// The phantom's vessels on a stack of nx x ny x nz voxels of h x h x hz: each
// tissue's extraction, its error against the phantom's trees and that tree
// (whose topology the extraction must have).
void for_each_phantom_vessel(
    int nx, int ny, int nz, double h, double hz, const std::string& tag,
    const std::function<void(const VesselResult&, const CentrelineError&, const VesselTree&)>& check) {
  PhantomOptions po;
  po.nx = nx, po.ny = ny, po.nz = nz;
  po.spacing_m = {h, h, hz};
  const Volume v = phantom_labels(po);
  const auto truth = phantom_vessels(po);
  const std::string size = std::to_string(nx) + "x" + std::to_string(ny) + "x" + std::to_string(nz);
  for (const std::string tissue : {"artery", "vein"}) {
    SCOPED_TRACE(tissue + " " + size);
    const VesselResult r = extract_vessels(v, tissue, {});
    const CentrelineError e = compare_centrelines(r.tree, truth.at(tissue));
    print(tag + " " + size + " " + tissue, r, e, h);
    const VesselTree& t = truth.at(tissue);
    expect_topology(r.tree, std::vector<int>(t.branch_parent.data(), t.branch_parent.data() + t.branch_parent.size()));
    // the tube ends flush with the border planes it is cut by: a vessel leaving
    // obliquely stuck out by r sin(tilt) (3.5 mm for the wide stack's artery)
    const Eigen::Vector3d lo(v.origin_m[0], v.origin_m[1], v.origin_m[2]);
    const Eigen::Vector3d hi = lo + Eigen::Vector3d((nx - 1) * h, (ny - 1) * h, (nz - 1) * hz);
    double out = 0;
    for (Eigen::Index i = 0; i < r.tree.tube_vertices.rows(); ++i) {
      const Eigen::Vector3d q = r.tree.tube_vertices.row(i).transpose();
      out = std::max({out, (lo - q).maxCoeff(), (q - hi).maxCoeff()});
    }
    EXPECT_LE(out, 1e-9) << "the tube reaches past the volume's border planes";
    check(r, e, t);
  }
}

// The default `orthosim phantom` sample (its bifurcation is narrow: the
// children leave the brachial artery about 20 degrees apart), a coarse one
// (vessel radii of about two voxels) and a short wide one (a stack shorter
// than the limb is wide: the artery's radius is 5.4 mm and one child turns
// about 80 degrees off it; the parent's last ring lay level with that child's
// first ring, and the patch between folded, 40 self-intersecting face pairs
// until 2026-11-27): right trees and valid tubes.
TEST(Vessels, PhantomTreesAtOtherResolutions) {
  struct Res {
    int nx, ny, nz;
    double h, hz;
    bool accuracy;
  };
  for (const Res res : {Res{256, 256, 128, 0.3e-3, 1.0e-3, true}, Res{64, 64, 32, 0.8e-3, 2.0e-3, false},
                         Res{256, 256, 64, 0.7e-3, 1.0e-3, false}})
    for_each_phantom_vessel(res.nx, res.ny, res.nz, res.h, res.hz, "phantom",
                            [&](const VesselResult& r, const CentrelineError& e, const VesselTree& t) {
                              if (res.accuracy) expect_accuracy(e, res.h);
                              // Within a junction the centreline is a convention: the phantom's axes
                              // meet on the parent's, the extracted ones where the children's axes
                              // cross the rebuilt parent's. For the wide stack's 5.4 mm artery (7.7
                              // voxels) they are 3 mm apart, and the largest deviations (2.8 voxels,
                              // 1.9 mm, before and after the ring fix) lie there: the bound is the
                              // larger of 2 voxels and half the widest truth radius.
                              EXPECT_LE(e.max_m, std::max(2.0 * res.h, 0.5 * t.radii.maxCoeff()));
                              EXPECT_LE(e.mean_m, 0.5 * res.h);
                              EXPECT_GE(e.overlap_truth, 0.99);  // the whole vessel, to the border
                              // every end of the phantom's vessels is cut by the volume border
                              for (const auto& end : r.metrics.ends) EXPECT_TRUE(end.open) << end.position_m.transpose();
                              expect_tube(r, 1);
                            });
}

// Vessels cut by the volume border reach it, whatever the stack: thinning
// peeled the first slices of a vessel leaving through the first slice (the
// axis's voxels tie in distance near an open end and went lowest index
// first). On exact labels at 0.45 x 0.45 x 1.5 mm the phantom's vein lost
// its first 5 slices, its root came out closed at z = 7.5 mm and the tree
// 7.5 mm short (overlap with the truth 0.957); on a 32 x 32 x 48 stack at
// 0.45 x 0.45 x 0.6 mm half the vein and the artery's trunk and bifurcation
// were lost. Silent, exit 0, until 2026-11-27. And no tube cuts itself.
TEST(Vessels, VesselsCutByTheBorderReachIt) {
  struct Stack {
    int nx, ny, nz;
    double h, hz;
    bool resolved;  // vessel radii of 1.5 voxels or more (the 32 x 32 stack's are about 1: vessels.md, limits)
  };
  for (const Stack st : {Stack{96, 160, 96, 0.45e-3, 1.5e-3, true}, Stack{32, 32, 48, 0.45e-3, 0.6e-3, false},
                         Stack{200, 120, 80, 0.45e-3, 1.5e-3, true}, Stack{64, 64, 40, 0.45e-3, 1.5e-3, false}})
    for_each_phantom_vessel(st.nx, st.ny, st.nz, st.h, st.hz, "border",
                            [&](const VesselResult& r, const CentrelineError& e, const VesselTree& t) {
                              if (st.resolved) {
                                EXPECT_GE(e.overlap_truth, 0.99);
                                EXPECT_GE(e.overlap_extracted, 0.99);
                              }
                              std::size_t leaves = 0;  // the truth's ends: its root and its leaf branches' ends
                              const int* p = t.branch_parent.data();
                              const Eigen::Index n = t.branch_parent.size();
                              for (Eigen::Index b = 0; b < n; ++b) leaves += std::find(p, p + n, b) == p + n;
                              EXPECT_EQ(r.metrics.ends.size(), leaves + 1);
                              for (const auto& end : r.metrics.ends) EXPECT_TRUE(end.open) << end.position_m.transpose();
                              const MeshCheck c = check_mesh(r.tree.tube_vertices, r.tree.tube_quads, r.tree.tube_tris);
                              EXPECT_TRUE(c.closed() && c.manifold() && c.oriented());
                              EXPECT_EQ(c.degenerate_faces, 0);
                              // the narrow Y's first rings overlapped at the crotch on these coarse
                              // slices (37 self-intersecting face pairs at 96 x 160 x 96 and 64 x 64 x 40)
                              EXPECT_EQ(r.metrics.self_intersections, 0);
                            });
}

// Segmentation noise turns misclassified voxels into pieces of vessel label
// 1-2 voxels thick (the phantom at 8-bit noise 20-24: 2-53 trees a vessel
// where it has one). Beside a resolved vessel they are dropped as noise
// (VesselOptions::min_radius_voxels); alone, as in a stack too coarse for
// its vessels, they are kept; 0 keeps them always.
TEST(Vessels, ThinPiecesBesideAResolvedVesselAreNoise) {
  const double h = 0.5e-3;
  Case c = make_case(40, 40, 60, {h, h, h},
                     {{test::segment({10e-3, 10e-3, -2e-3}, {10e-3, 10e-3, 32e-3}), test::constant(2e-3), -1}});
  // noise: chains of vessel voxels 16 long and one thick (two straight, one
  // bent), away from the tube and each other (a chain two thick thins to
  // less than 3 radii and goes as a speck)
  auto put = [&](int x, int y, int z) { c.v.labels[static_cast<std::size_t>(x + c.v.nx * (y + c.v.ny * z))] = 6; };
  for (int k = 0; k < 16; ++k) put(32, 32, 6 + k);
  for (int k = 0; k < 16; ++k) put(22 + k, 5, 40);
  for (int k = 0; k < 16; ++k) put(5, 24 + std::min(k, 8), 30 + std::max(k - 8, 0));
  const VesselResult r = extract_vessels(c.v, "artery", {});
  EXPECT_EQ(r.metrics.trees, 1);
  EXPECT_EQ(r.metrics.thin_components_dropped, 3);
  expect_topology(r.tree, {-1});
  expect_tube(r, 1);
  const CentrelineError e = compare_centrelines(r.tree, c.truth);
  expect_accuracy(e, c.vox);
  // the rule off: the three pieces are trees of their own
  VesselOptions keep;
  keep.min_radius_voxels = 0;
  const VesselResult all = extract_vessels(c.v, "artery", keep);
  EXPECT_EQ(all.metrics.trees, 4);
  EXPECT_EQ(all.metrics.thin_components_dropped, 0);
  // without the resolved tube the thin pieces are all there is: kept
  Volume thin = c.v;
  for (auto& l : thin.labels) l = 0;
  for (int k = 0; k < 16; ++k) thin.labels[static_cast<std::size_t>(32 + thin.nx * (32 + thin.ny * (6 + k)))] = 6;
  const VesselResult lone = extract_vessels(thin, "artery", {});
  EXPECT_EQ(lone.metrics.trees, 1);
  EXPECT_EQ(lone.metrics.thin_components_dropped, 0);
  VesselOptions bad;
  bad.min_radius_voxels = -1;
  EXPECT_THROW(validate(bad), Error);
}

// A bump on the vessel wall, as segmentation noise leaves it (3 x 3 voxels
// across, reaching 2.6 radii from the axis; docs/vessels.md, Graph and tree
// rules): the default spur ratio (1.5) keeps its skeleton branch, which splits
// the tube in two at a junction; --spur-ratio 4 removes it as a spur and the
// tube is one branch again, its centreline as accurate as without the bump.
TEST(Vessels, TheSpurRatioRemovesAWallBump) {
  const double h = 0.5e-3;
  Case c = make_case(40, 40, 60, {h, h, h},
                     {{test::segment({10e-3, 10e-3, -2e-3}, {10e-3, 10e-3, 32e-3}), test::constant(2e-3), -1}});
  // the axis is at voxel 19.5 (x, y); the bump runs along +x from inside the
  // wall (x 22) to x 29 (5.25 mm from the axis), voxels y 19-21, z 28-30
  for (int z = 28; z <= 30; ++z)
    for (int y = 19; y <= 21; ++y)
      for (int x = 22; x <= 29; ++x) c.v.labels[static_cast<std::size_t>(x + c.v.nx * (y + c.v.ny * z))] = 6;
  const VesselResult kept = extract_vessels(c.v, "artery", {});
  expect_topology(kept.tree, {-1, 0, 0});
  VesselOptions o;
  o.spur_ratio = 4;
  const VesselResult r = extract_vessels(c.v, "artery", o);
  EXPECT_EQ(r.metrics.spurs_pruned, kept.metrics.spurs_pruned + 1);
  expect_topology(r.tree, {-1});
  expect_tube(r, 1);
  const CentrelineError e = compare_centrelines(r.tree, c.truth);
  expect_accuracy(e, c.vox);
  VesselOptions bad;
  bad.spur_ratio = 0;
  EXPECT_THROW(validate(bad), Error);
}

// ---- determinism, bad input ---------------------------------------------------------------

TEST(Vessels, SameResultWhateverTheThreadCount) {
  const double h = 0.4e-3;
  Case c = make_case(70, 40, 100, {h, h, h},
                     test::y_tubes({14e-3, 8e-3, -1e-3}, 16e-3, 26e-3, 0.45, 2.2e-3, 1.8e-3));
  VesselResult one, two;
  {
    tbb::global_control gc(tbb::global_control::max_allowed_parallelism, 1);
    one = extract_vessels(c.v, "artery", {});
  }
  {
    tbb::global_control gc(tbb::global_control::max_allowed_parallelism, 2);
    two = extract_vessels(c.v, "artery", {});
  }
  EXPECT_EQ(one.tree.nodes, two.tree.nodes);
  EXPECT_EQ(one.tree.radii, two.tree.radii);
  EXPECT_EQ(one.tree.bezier_ctrl, two.tree.bezier_ctrl);
  EXPECT_EQ(one.tree.tube_vertices, two.tree.tube_vertices);
  EXPECT_EQ(one.tree.tube_quads, two.tree.tube_quads);
  EXPECT_EQ(one.metrics.boundary_max_m, two.metrics.boundary_max_m);
}

TEST(Vessels, BadInputIsRefusedWithAMessage) {
  const double h = 0.4e-3;
  Case c = make_case(40, 40, 60, {h, h, h},
                     {{test::segment({9.5e-3, 10e-3, -2e-3}, {10.5e-3, 9.5e-3, 32e-3}), test::constant(3e-3), -1}});
  auto message = [&](const std::string& tissue, const VesselOptions& o) -> std::string {
    try {
      extract_vessels(c.v, tissue, o);
    } catch (const Error& e) {
      EXPECT_TRUE(e.file().empty());
      return e.message();
    }
    return "(accepted)";
  };
  EXPECT_NE(message("nerve", {}).find("unknown tissue 'nerve'"), std::string::npos);
  EXPECT_NE(message("background", {}).find("unknown tissue"), std::string::npos);
  EXPECT_NE(message("vein", {}).find("no voxels of tissue 'vein'"), std::string::npos);
  VesselOptions o;
  o.ring_vertices = 26;
  EXPECT_NE(message("artery", o).find("ring_vertices"), std::string::npos);
  o = {};
  o.tolerance_m = -1;
  EXPECT_NE(message("artery", o).find("tolerance"), std::string::npos);
  o = {};
  o.roots_m.push_back(Eigen::Vector3d(0, std::nan(""), 0));
  EXPECT_NE(message("artery", o).find("root"), std::string::npos);
  // a speck is no vessel
  Volume speck = test::empty_volume(20, 20, 20, {h, h, h}, {0, 0, 0});
  speck.labels[speck.index(10, 10, 10)] = 6;
  speck.labels[speck.index(11, 10, 10)] = 6;
  try {
    extract_vessels(speck, "artery", {});
    ADD_FAILURE() << "a two-voxel speck was accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("no vessel"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace orthosim
