// remesh on the phantom's truth surfaces (skin, fat, muscle, and the bones:
// humerus proximally, radius and ulna distally).
#include "libmodel/phantom/phantom.h"
#include "libmodel/remesh/remesh.h"
#include "tests/libmodel/remesh_shapes.h"

#include <gtest/gtest.h>

#include <cmath>

using namespace orthosim;

namespace {

PhantomOptions small() {
  PhantomOptions o;
  o.nx = o.ny = 128;
  o.nz = 64;
  o.spacing_m = {0.6e-3, 0.6e-3, 2e-3};
  return o;
}

const std::map<std::string, Surface>& surfaces() {
  static const auto s = phantom_surfaces(small());
  return s;
}

std::vector<NamedSurface> layers() {
  std::vector<NamedSurface> l;
  for (const char* n : {"skin", "fat", "muscle", "bone"}) l.push_back({n, surfaces().at(n)});
  return l;
}

RemeshOptions grid(int nu, int nv) {
  RemeshOptions o;
  o.nu = nu, o.nv = nv;
  return o;
}

}  // namespace

TEST(RemeshPhantom, LayeredGridsOnTheTruthSurfaces) {
  const auto in = layers();
  const auto r = remesh_layers(in, grid(39, 9));
  ASSERT_EQ(r.layers.size(), 4u);
  EXPECT_TRUE(r.sweep.flat_cap[0] && r.sweep.flat_cap[1]);
  const PhantomOptions o = small();
  const double L = (o.nz - 1) * o.spacing_m[2];
  // the end rings sit past the crease: the row of wall faces touching the
  // caps at z = 0 and z = L, one slice deep on this surface
  for (int i = 0; i < 39; ++i) {
    EXPECT_NEAR(r.layers[0].vertices(i, 2), o.spacing_m[2], 1e-5);
    EXPECT_NEAR(r.layers[0].vertices(8 * 39 + i, 2), L - o.spacing_m[2], 1e-5);
  }
  // on the rims with EndRings::rim
  RemeshOptions rim = grid(39, 9);
  rim.ends = EndRings::rim;
  const auto rr = remesh_layers(in, rim);
  for (int i = 0; i < 39; ++i) {
    EXPECT_NEAR(rr.layers[0].vertices(i, 2), 0, 1e-5);
    EXPECT_NEAR(rr.layers[0].vertices(8 * 39 + i, 2), L, 1e-5);
  }
  // vertices that hit a surface lie on the analytic interface
  for (int k = 0; k < 3; ++k) {
    double worst = 0;
    for (Eigen::Index v = 0; v < r.layers[k].vertices.rows(); ++v)
      worst = std::max(worst, phantom_interface_distance(o, in[k].name, r.layers[k].vertices.row(v).transpose()));
    EXPECT_LT(worst, 5e-5) << in[k].name;
  }
  EXPECT_EQ(r.stats[3].components, 3);
  const auto e = evaluate_remesh(r, in);
  for (std::size_t k = 0; k < 4; ++k) {
    EXPECT_EQ(e.quality[k].flipped, 0) << in[k].name;
    EXPECT_EQ(e.quality[k].degenerate, 0) << in[k].name;
  }
  EXPECT_LT(e.distance[0].hausdorff_m, 2e-3);
  EXPECT_LT(e.distance[0].mean_m, 0.5e-3);
  // skin -> fat -> muscle: the builder's centroid rays land in the quad below
  EXPECT_GT(e.alignment[0].ray_in_quad, 0.99);
  EXPECT_GT(e.alignment[1].ray_in_quad, 0.99);
  // thin layers: corresponding vertices under each other to a tenth of a quad
  EXPECT_LT(e.alignment[0].max_lateral_rel, 0.1);
  EXPECT_LT(e.alignment[1].max_lateral_rel, 0.1);
  // and every cell between two layers is positive (the builder's lattice split)
  for (std::size_t k = 0; k + 1 < 4; ++k)
    EXPECT_GT(test::min_cell_tet_ratio(r.layers[k], r.layers[k + 1]), 0.0) << in[k].name;
}

TEST(RemeshPhantom, SkinErrorFallsWithTheGrid) {
  const auto in = layers();
  std::vector<double> err;
  for (int k : {1, 2, 4}) {
    const auto r = remesh_layers({in[0]}, grid(20 * k, 5 * k));
    err.push_back(evaluate_remesh(r, {in[0]}, 2).distance[0].mean_m);
  }
  EXPECT_GT(err[0] / err[1], 2.5);
  EXPECT_GT(err[1] / err[2], 2.0);
}
