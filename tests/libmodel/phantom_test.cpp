// Tests of the CVH-like phantom (libmodel/phantom) and `orthosim phantom`.
#include "libmodel/phantom/phantom.h"
#include "libmodel/format/model.h"
#include "libmodel/tissues.h"
#include "tests/test_util.h"

#include <Eigen/Dense>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <tbb/global_control.h>

#include <cmath>
#include <filesystem>
#include <numeric>
#include <set>
#include <unordered_map>

using namespace orthosim;
namespace fs = std::filesystem;

namespace {

constexpr double kPi = 3.14159265358979323846;

// Small enough to be fast, fine enough that every tissue is a few voxels thick.
PhantomOptions small_options() {
  PhantomOptions o;
  o.nx = 128, o.ny = 128, o.nz = 48;
  o.spacing_m = {0.45e-3, 0.45e-3, 2.5e-3};
  return o;
}

const Volume& small_labels() {
  static const Volume v = phantom_labels(small_options());
  return v;
}

const std::map<std::string, Surface>& small_surfaces() {
  static const auto s = phantom_surfaces(small_options());
  return s;
}

std::vector<std::uint8_t> slice_of(const Volume& v, int z) {
  const std::size_t n = static_cast<std::size_t>(v.nx) * v.ny;
  return {v.labels.begin() + z * n, v.labels.begin() + (z + 1) * n};
}

// Connected components (4-neighbourhood) of the pixels of one slice for which
// `in` holds.
int components(const Volume& v, int z, const std::function<bool(int)>& in) {
  std::vector<int> seen(static_cast<std::size_t>(v.nx) * v.ny, 0);
  int n = 0;
  for (int y = 0; y < v.ny; ++y)
    for (int x = 0; x < v.nx; ++x) {
      if (seen[y * v.nx + x] || !in(v.at(x, y, z))) continue;
      ++n;
      std::vector<std::pair<int, int>> stack{{x, y}};
      seen[y * v.nx + x] = 1;
      while (!stack.empty()) {
        auto [cx, cy] = stack.back();
        stack.pop_back();
        const int d[4][2] = {{1, 0}, {-1, 0}, {0, 1}, {0, -1}};
        for (auto& e : d) {
          const int nx = cx + e[0], ny = cy + e[1];
          if (nx < 0 || ny < 0 || nx >= v.nx || ny >= v.ny) continue;
          if (seen[ny * v.nx + nx] || !in(v.at(nx, ny, z))) continue;
          seen[ny * v.nx + nx] = 1;
          stack.push_back({nx, ny});
        }
      }
    }
  return n;
}

struct MeshStats {
  bool closed = true;    // every edge in exactly two faces, opposite directions
  double volume = 0;     // signed enclosed volume (m^3)
  int components = 0;
  long euler = 0;        // V - E + F
};

MeshStats mesh_stats(const Surface& s) {
  MeshStats m;
  const std::int64_t nv = s.vertices.rows();
  std::unordered_map<std::int64_t, int> directed;
  std::vector<int> parent(static_cast<std::size_t>(nv));
  std::iota(parent.begin(), parent.end(), 0);
  std::function<int(int)> find = [&](int a) { return parent[a] == a ? a : parent[a] = find(parent[a]); };
  std::set<int> used;
  for (Eigen::Index f = 0; f < s.faces.rows(); ++f) {
    const int v[3] = {s.faces(f, 0), s.faces(f, 1), s.faces(f, 2)};
    const Eigen::Vector3d a = s.vertices.row(v[0]), b = s.vertices.row(v[1]), c = s.vertices.row(v[2]);
    m.volume += a.dot(b.cross(c)) / 6;
    for (int k = 0; k < 3; ++k) {
      ++directed[v[k] * nv + v[(k + 1) % 3]];
      parent[find(v[k])] = find(v[(k + 1) % 3]);
      used.insert(v[k]);
    }
  }
  for (const auto& [key, count] : directed) {
    const std::int64_t u = key / nv, w = key % nv;
    auto it = directed.find(w * nv + u);
    if (count != 1 || it == directed.end() || it->second != 1) m.closed = false;
  }
  std::set<int> roots;
  for (int u : used) roots.insert(find(u));
  m.components = static_cast<int>(roots.size());
  m.euler = static_cast<long>(used.size()) - static_cast<long>(directed.size() / 2) + static_cast<long>(s.faces.rows());
  return m;
}

void expect_invalid(const std::function<void(PhantomOptions&)>& edit, const std::string& needle) {
  PhantomOptions o = small_options();
  edit(o);
  try {
    validate(o);
    ADD_FAILURE() << "expected an error mentioning '" << needle << "'";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
  }
  EXPECT_THROW(phantom_labels(o), Error);
}

}  // namespace

// ---- options -------------------------------------------------------------------------------

TEST(Phantom, RejectsBadOptions) {
  EXPECT_NO_THROW(validate(PhantomOptions{}));
  expect_invalid([](PhantomOptions& o) { o.nx = 0; }, "size");
  expect_invalid([](PhantomOptions& o) { o.ny = -5; }, "size");
  expect_invalid([](PhantomOptions& o) { o.nz = 0; }, "size");
  expect_invalid([](PhantomOptions& o) { o.nz = 1; }, "size");
  expect_invalid([](PhantomOptions& o) { o.spacing_m[1] = -0.3e-3; }, "spacing");
  expect_invalid([](PhantomOptions& o) { o.spacing_m[2] = 0; }, "spacing");
  expect_invalid([](PhantomOptions& o) { o.spacing_m[0] = std::nan(""); }, "spacing");
  expect_invalid([](PhantomOptions& o) { o.noise_sigma = -1; }, "noise");
  expect_invalid([](PhantomOptions& o) { o.noise_sigma = std::nan(""); }, "noise");
  expect_invalid([](PhantomOptions& o) { o.jpeg_quality = 0; }, "jpeg");
  EXPECT_THROW(phantom_interface_distance(small_options(), "liver", {0, 0, 0}), Error);
}

// ---- labels --------------------------------------------------------------------------------

TEST(Phantom, LabelsAreDeterministicAndIndependentOfSeedAndThreads) {
  PhantomOptions o = small_options();
  const Volume& a = small_labels();
  o.seed = 12345;
  const Volume b = phantom_labels(o);
  EXPECT_EQ(a.labels, b.labels);
  {
    tbb::global_control one(tbb::global_control::max_allowed_parallelism, 1);
    EXPECT_EQ(phantom_labels(small_options()).labels, a.labels);
  }
  EXPECT_EQ(a.nx, 128);
  EXPECT_EQ(a.nz, 48);
  EXPECT_EQ(a.label_names, phantom_tissue_table().label_names());
  EXPECT_EQ(a.label_names[kPhantomArtery], "artery");
  // the limb axis is near the centre of the field, the first slice at z = 0
  EXPECT_NEAR(a.position(63.5, 63.5, 0).norm(), 0, 1e-12);
}

TEST(Phantom, PointLabelsMatchTheVolume) {
  const PhantomOptions o = small_options();
  const Volume& v = small_labels();
  MatX3d p(4000, 3);
  std::vector<std::uint8_t> expect;
  std::uint64_t h = 7;
  for (Eigen::Index i = 0; i < p.rows(); ++i) {
    h = h * 6364136223846793005ULL + 1442695040888963407ULL;
    const int x = static_cast<int>((h >> 20) % v.nx), y = static_cast<int>((h >> 35) % v.ny),
              z = static_cast<int>((h >> 50) % v.nz);
    p.row(i) = v.position(x, y, z).transpose();
    expect.push_back(v.at(x, y, z));
  }
  EXPECT_EQ(phantom_labels_at(o, p), expect);
  EXPECT_EQ(phantom_label_at(o, p.row(17).transpose()), expect[17]);
}

TEST(Phantom, EveryTissueIsPresentAndNested) {
  const Volume& v = small_labels();
  std::array<std::int64_t, 8> count{};
  for (auto l : v.labels) {
    ASSERT_LT(l, 8);
    ++count[l];
  }
  for (int l = 0; l < 8; ++l) EXPECT_GT(count[l], 100) << v.label_names[l];
  // nothing but background on the border of the field
  for (int z = 0; z < v.nz; ++z)
    for (int k = 0; k < v.nx; ++k) {
      EXPECT_EQ(v.at(k, 0, z), 0);
      EXPECT_EQ(v.at(k, v.ny - 1, z), 0);
      EXPECT_EQ(v.at(0, k, z), 0);
      EXPECT_EQ(v.at(v.nx - 1, k, z), 0);
    }
  // in-plane neighbours: which labels may touch which
  auto allowed = [](int a, int b) {
    if (a == b) return true;
    if (a > b) std::swap(a, b);
    static const std::set<std::pair<int, int>> ok = {
        {0, 1}, {1, 2}, {2, 3}, {3, 4}, {4, 5}, {3, 6}, {3, 7}};
    return ok.count({a, b}) > 0;
  };
  std::set<std::pair<int, int>> bad;
  for (int z = 0; z < v.nz; ++z)
    for (int y = 0; y + 1 < v.ny; ++y)
      for (int x = 0; x + 1 < v.nx; ++x) {
        const int a = v.at(x, y, z);
        for (int b : {static_cast<int>(v.at(x + 1, y, z)), static_cast<int>(v.at(x, y + 1, z))})
          if (!allowed(a, b)) bad.insert({std::min(a, b), std::max(a, b)});
      }
  for (auto [a, b] : bad) ADD_FAILURE() << v.label_names[a] << " touches " << v.label_names[b];
}

TEST(Phantom, RadialOrderAndLayerThicknessAtDefaultSize) {
  // rays from the limb centroid outward at the default size and spacing: from
  // outside in, background -> skin -> fat -> muscle; skin 1.5-3 mm, fat 3-8 mm
  const PhantomOptions o;
  const double step = 0.03e-3;
  for (int z : {5, 40, 64, 90, 125}) {
    // centroid of the limb section from a coarse grid
    const int ng = 96;
    MatX3d grid(ng * ng, 3);
    for (int i = 0; i < ng; ++i)
      for (int j = 0; j < ng; ++j) grid.row(i * ng + j) << (j - ng / 2) * 0.8e-3, (i - ng / 2) * 0.8e-3, z * 1e-3;
    const auto gl = phantom_labels_at(o, grid);
    Eigen::Vector2d c(0, 0);
    long n = 0;
    for (int i = 0; i < ng * ng; ++i)
      if (gl[i] != 0) c += grid.row(i).head<2>().transpose(), ++n;
    c /= static_cast<double>(n);
    const int n_rays = 48, n_steps = 1000;  // from 38 mm to 8 mm off the centroid
    MatX3d p(n_rays * n_steps, 3);
    for (int r = 0; r < n_rays; ++r)
      for (int k = 0; k < n_steps; ++k) {
        const double th = 2 * kPi * r / n_rays, s = 38e-3 - k * step;  // outside in
        p.row(r * n_steps + k) << c.x() + s * std::cos(th), c.y() + s * std::sin(th), z * o.spacing_m[2];
      }
    const auto l = phantom_labels_at(o, p);
    for (int r = 0; r < n_rays; ++r) {
      std::vector<std::pair<int, int>> runs;  // (label, length in steps)
      for (int k = 0; k < n_steps; ++k) {
        const int lab = l[r * n_steps + k];
        if (runs.empty() || runs.back().first != lab) runs.push_back({lab, 0});
        ++runs.back().second;
      }
      ASSERT_GE(runs.size(), 4u) << "z " << z << " ray " << r;
      EXPECT_EQ(runs[0].first, kPhantomBackground);
      EXPECT_EQ(runs[1].first, kPhantomSkin);
      EXPECT_EQ(runs[2].first, kPhantomFat);
      EXPECT_EQ(runs[3].first, kPhantomMuscle) << "z " << z << " ray " << r;
      const double skin = runs[1].second * step, fat = runs[2].second * step;
      EXPECT_GE(skin, 1.45e-3) << "z " << z << " ray " << r;
      EXPECT_LE(skin, 3.3e-3) << "z " << z << " ray " << r;
      EXPECT_GE(fat, 3.0e-3) << "z " << z << " ray " << r;
      EXPECT_LE(fat, 8.0e-3) << "z " << z << " ray " << r;
    }
  }
}

TEST(Phantom, OneBoneProximallyTwoDistally) {
  const Volume& v = small_labels();
  auto is_bone = [](int l) { return l == kPhantomBone || l == kPhantomMarrow; };
  for (int z = 1; z < v.nz * 4 / 10; ++z) EXPECT_EQ(components(v, z, is_bone), 1) << "slice " << z;
  for (int z = v.nz * 6 / 10; z < v.nz; ++z) EXPECT_EQ(components(v, z, is_bone), 2) << "slice " << z;
  // every bone section has marrow
  for (int z : {5, 40}) EXPECT_EQ(components(v, z, [](int l) { return l == kPhantomMarrow; }),
                                  components(v, z, is_bone));
}

// ---- vessels -------------------------------------------------------------------------------

TEST(Phantom, ArteryBifurcatesOnceVeinDoesNot) {
  const PhantomOptions o;
  const auto trees = phantom_vessels(o);
  ASSERT_EQ(trees.size(), 2u);
  const VesselTree& a = trees.at("artery");
  const VesselTree& vn = trees.at("vein");
  ASSERT_EQ(a.branch_parent.size(), 3);
  EXPECT_EQ(a.branch_parent(0), -1);
  EXPECT_EQ(a.branch_parent(1), 0);
  EXPECT_EQ(a.branch_parent(2), 0);
  ASSERT_EQ(a.branch_offsets.size(), 4);
  EXPECT_EQ(a.branch_offsets(3), a.branch_nodes.size());
  ASSERT_EQ(vn.branch_parent.size(), 1);
  EXPECT_EQ(vn.branch_parent(0), -1);
  for (const VesselTree* t : {&a, &vn}) {
    EXPECT_EQ(t->edges.rows(), t->nodes.rows() - 1);  // a tree
    EXPECT_EQ(t->radii.size(), t->nodes.rows());
    EXPECT_EQ(t->bezier_ctrl.rows(), 0);
    EXPECT_EQ(t->tube_vertices.rows(), 0);
    std::vector<int> degree(static_cast<std::size_t>(t->nodes.rows()), 0);
    for (Eigen::Index e = 0; e < t->edges.rows(); ++e) {
      ++degree[t->edges(e, 0)], ++degree[t->edges(e, 1)];
      const double len = (t->nodes.row(t->edges(e, 0)) - t->nodes.row(t->edges(e, 1))).norm();
      EXPECT_LE(len, 0.5 * 0.3e-3 + 1e-12);
      EXPECT_GT(len, 0);
    }
    const long forks = std::count_if(degree.begin(), degree.end(), [](int d) { return d == 3; });
    EXPECT_EQ(forks, t == &a ? 1 : 0);
    EXPECT_EQ(std::count_if(degree.begin(), degree.end(), [](int d) { return d > 3; }), 0);
    EXPECT_GE(t->radii.minCoeff(), 1.5e-3);
    EXPECT_LE(t->radii.maxCoeff(), 3.0e-3);
    // the centreline runs from the first to the last slice
    EXPECT_NEAR(t->nodes.col(2).minCoeff(), 0, 1e-12);
    EXPECT_NEAR(t->nodes.col(2).maxCoeff(), (o.nz - 1) * o.spacing_m[2], 1e-9);
  }
  // both children start at the brachial's end node
  const int parent_end = a.branch_nodes(a.branch_offsets(1) - 1);
  EXPECT_EQ(a.branch_nodes(a.branch_offsets(1)), parent_end);
  EXPECT_EQ(a.branch_nodes(a.branch_offsets(2)), parent_end);
  // centreline points are inside their vessel, points 1 mm beyond the radius
  // are muscle (vessels lie in muscle and never touch bone)
  for (const auto& [name, t] : trees) {
    const int label = name == "artery" ? kPhantomArtery : kPhantomVein;
    MatX3d in(t.nodes.rows() / 7 + 1, 3), out(8 * (t.nodes.rows() / 7 + 1), 3);
    Eigen::Index k = 0, m = 0;
    for (Eigen::Index i = 0; i < t.nodes.rows(); i += 7, ++k) {
      in.row(k) = t.nodes.row(i);
      for (int q = 0; q < 8; ++q, ++m) {
        const double th = 2 * kPi * q / 8, r = t.radii(i) + 1.0e-3;
        out.row(m) = t.nodes.row(i) + Eigen::RowVector3d(r * std::cos(th), r * std::sin(th), 0);
      }
    }
    for (auto l : phantom_labels_at(o, in.topRows(k))) EXPECT_EQ(l, label);
    int muscle = 0, other_vessel = 0;
    for (auto l : phantom_labels_at(o, out.topRows(m))) {
      muscle += l == kPhantomMuscle;
      other_vessel += l == kPhantomArtery || l == kPhantomVein;  // near the fork: the sibling tube
      EXPECT_TRUE(l == kPhantomMuscle || l == label) << name << " label " << int(l);
    }
    EXPECT_GT(muscle, 0.95 * m);
  }
}

// ---- truth meshes --------------------------------------------------------------------------

TEST(Phantom, TruthMeshesAreClosedOutwardAndOnTheInterface) {
  const PhantomOptions o = small_options();
  const auto& surfaces = small_surfaces();
  const std::map<std::string, int> expect_components{
      {"skin", 1}, {"fat", 1}, {"muscle", 1}, {"bone", 3}, {"marrow", 3}};
  ASSERT_EQ(surfaces.size(), expect_components.size());
  for (const auto& [name, s] : surfaces) {
    SCOPED_TRACE(name);
    ASSERT_TRUE(expect_components.count(name));
    const MeshStats m = mesh_stats(s);
    EXPECT_TRUE(m.closed);
    EXPECT_GT(m.volume, 0);
    EXPECT_EQ(m.components, expect_components.at(name));
    EXPECT_EQ(m.euler, 2 * m.components);  // closed genus-0 components
    // every few vertices lie on the analytic interface
    const int stride = 5;
    MatX3d p((s.vertices.rows() + stride - 1) / stride, 3);
    for (Eigen::Index i = 0; i < p.rows(); ++i) p.row(i) = s.vertices.row(i * stride);
    const VecXd d = phantom_interface_distances(o, name, p);
    EXPECT_LT(d.maxCoeff(), 1e-6);
    // the limb surfaces span the stack: flat caps at the first and last slice
    if (name == "skin") {
      EXPECT_NEAR(s.vertices.col(2).minCoeff(), 0, 1e-12);
      EXPECT_NEAR(s.vertices.col(2).maxCoeff(), (o.nz - 1) * o.spacing_m[2], 1e-12);
    }
  }
}

TEST(Phantom, InterfaceDistanceIsAClosestPointDistance) {
  // for points off the surface the distance is at most the distance to any
  // mesh vertex (vertices lie on the surface) and not much less than the
  // nearest one (the mesh is fine)
  const PhantomOptions o = small_options();
  const auto& surfaces = small_surfaces();
  for (const std::string name : {"skin", "muscle", "bone"}) {
    SCOPED_TRACE(name);
    const Surface& s = surfaces.at(name);
    MatX3d p(60, 3);
    for (Eigen::Index i = 0; i < p.rows(); ++i) {
      const Eigen::RowVector3d v = s.vertices.row((i * 7919) % s.vertices.rows());
      p.row(i) = v + Eigen::RowVector3d(std::sin(1.3 * i + 0.4), std::cos(2.1 * i), 0.5 + std::sin(0.7 * i + 0.9)) * 1.5e-3;
    }
    const VecXd d = phantom_interface_distances(o, name, p);
    for (Eigen::Index i = 0; i < p.rows(); ++i) {
      const double nearest = (s.vertices.rowwise() - p.row(i)).rowwise().norm().minCoeff();
      EXPECT_LE(d(i), nearest + 1e-9);
      EXPECT_GE(d(i), nearest - 2.6e-3);  // vertex spacing: 0.9 mm around, 2.5 mm along
      EXPECT_GT(d(i), 0);
    }
  }
  // a point on the limb axis at mid-length is deep inside: about the limb radius
  const double d = phantom_interface_distance(o, "skin", {0, 0, 0.06});
  EXPECT_GT(d, 15e-3);
  EXPECT_LT(d, 25e-3);
  EXPECT_NEAR(phantom_interface_distance(o, "skin", {0, 0, 0}), 0, 1e-12);  // on the cap
}

TEST(Phantom, VoxelVolumesMatchTheTruthMeshes) {
  // the label volume and the truth meshes describe the same solids: voxel
  // counts (trapezoid rule over slices: the meshes end at the end slices)
  // match the enclosed mesh volumes
  const PhantomOptions o = small_options();
  const Volume& v = small_labels();
  const auto& surfaces = small_surfaces();
  const double voxel = o.spacing_m[0] * o.spacing_m[1] * o.spacing_m[2];
  const std::map<std::string, std::set<int>> inside{
      {"skin", {1, 2, 3, 4, 5, 6, 7}}, {"fat", {2, 3, 4, 5, 6, 7}}, {"muscle", {3, 4, 5, 6, 7}}, {"bone", {4, 5}},
      {"marrow", {5}}};
  for (const auto& [name, labels] : inside) {
    double sum = 0;
    for (int z = 0; z < v.nz; ++z) {
      const auto s = slice_of(v, z);
      const double n = static_cast<double>(std::count_if(s.begin(), s.end(), [&](int l) { return labels.count(l); }));
      sum += (z == 0 || z == v.nz - 1 ? 0.5 : 1.0) * n * voxel;
    }
    const double mesh = mesh_stats(surfaces.at(name)).volume;
    EXPECT_NEAR(sum / mesh, 1.0, name == "skin" || name == "fat" || name == "muscle" ? 0.01 : 0.05) << name;
  }
}

// ---- colour --------------------------------------------------------------------------------

TEST(Phantom, SlicesAreDeterministicWithSeededNoise) {
  PhantomOptions o = small_options();
  const Volume& v = small_labels();
  std::vector<std::uint8_t> a, b, c, clean;
  phantom_slice_rgb(o, v, 20, a);
  phantom_slice_rgb(o, v, 20, b);
  EXPECT_EQ(a, b);
  ASSERT_EQ(a.size(), static_cast<std::size_t>(o.nx) * o.ny * 3);
  o.seed = 2;
  phantom_slice_rgb(o, v, 20, c);
  EXPECT_NE(a, c);
  // noise: the difference to a noise-free rendering has the requested sigma
  PhantomOptions q = small_options();
  q.noise_sigma = 0;
  phantom_slice_rgb(q, v, 20, clean);
  double s2 = 0, mean = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    const double d = static_cast<double>(a[i]) - clean[i];
    mean += d, s2 += d * d;
  }
  mean /= static_cast<double>(a.size());
  const double sigma = std::sqrt(s2 / static_cast<double>(a.size()) - mean * mean);
  EXPECT_NEAR(mean, 0, 0.1);
  EXPECT_NEAR(sigma, 4.0, 0.25);
  // noise-free tissue means stay within 12 % of the nominal colours of the
  // tissue table (texture and illumination are small)
  const TissueTable t = phantom_tissue_table();
  for (int z : {3, 24, 45}) {
    phantom_slice_rgb(q, v, z, clean);
    std::array<std::array<double, 4>, 8> acc{};
    for (int i = 0; i < o.nx * o.ny; ++i) {
      const int l = v.labels[static_cast<std::size_t>(z) * o.nx * o.ny + i];
      for (int ch = 0; ch < 3; ++ch) acc[l][ch] += clean[3 * i + ch];
      acc[l][3] += 1;
    }
    for (int l = 0; l < 8; ++l) {
      if (acc[l][3] < 20) continue;
      const auto& nominal = l == 0 ? t.background_rgb[0] : t.by_label(l)->rgb[0];
      for (int ch = 0; ch < 3; ++ch)
        EXPECT_NEAR(acc[l][ch] / acc[l][3], nominal[ch], 0.12 * nominal[ch] + 2) << "label " << l << " ch " << ch;
    }
  }
}

// ---- tissue tables -------------------------------------------------------------------------

namespace {
void expect_same_table(const TissueTable& a, const TissueTable& b) {
  EXPECT_EQ(a.background_rgb, b.background_rgb);
  ASSERT_EQ(a.tissues.size(), b.tissues.size());
  for (std::size_t i = 0; i < a.tissues.size(); ++i) {
    const Tissue &x = a.tissues[i], &y = b.tissues[i];
    SCOPED_TRACE(x.name);
    EXPECT_EQ(x.name, y.name);
    EXPECT_EQ(x.label, y.label);
    EXPECT_EQ(x.rgb, y.rgb);
    EXPECT_DOUBLE_EQ(x.density_kg_m3, y.density_kg_m3);
    EXPECT_EQ(x.layer, y.layer);
    EXPECT_EQ(x.inside, y.inside);
    EXPECT_EQ(x.mechanics.model, y.mechanics.model);
    EXPECT_NEAR(x.mechanics.k_pa, y.mechanics.k_pa, 1e-9);
    EXPECT_NEAR(x.mechanics.k1_pa, y.mechanics.k1_pa, 1e-9);
    EXPECT_NEAR(x.mechanics.k2_pa, y.mechanics.k2_pa, 1e-9);
    EXPECT_NEAR(x.mechanics.turning_strain, y.mechanics.turning_strain, 1e-12);
    EXPECT_FALSE(y.source.empty());
  }
}
}  // namespace

TEST(Phantom, TissueTableRoundTripsAndMatchesTheSharedSample) {
  const TissueTable t = phantom_tissue_table();
  ASSERT_EQ(t.tissues.size(), 7u);
  EXPECT_EQ(t.find("artery")->label, kPhantomArtery);
  EXPECT_EQ(t.find("marrow")->inside, "bone");
  EXPECT_EQ(t.depth(*t.find("marrow")), 4);
  expect_same_table(t, parse_tissue_table(to_json(t), "roundtrip"));
  expect_same_table(t, load_tissue_table(std::string(ORTHOSIM_SOURCE_DIR) + "/data-samples/tissues.json"));
}

// ---- writing -------------------------------------------------------------------------------

TEST(Phantom, WritesSlicesTissuesAndTruth) {
  test::TempDir tmp("phantom");
  PhantomOptions o = small_options();
  o.nz = 12;
  const std::string out = tmp / "stack";
  long calls = 0, last = 0;
  const PhantomMetrics m = write_phantom(o, out, "orthosim phantom --test", [&](long done, long total) {
    ++calls;
    EXPECT_EQ(total, 12);
    EXPECT_GT(done, last);
    last = done;
  });
  EXPECT_EQ(last, 12);
  EXPECT_GE(calls, 1);
  for (int z = 0; z < o.nz; ++z) {
    char name[64];
    std::snprintf(name, sizeof name, "/slices/slice_%04d.png", z);
    EXPECT_TRUE(fs::is_regular_file(out + name)) << name;
  }
  EXPECT_EQ(std::distance(fs::directory_iterator(out + "/slices"), fs::directory_iterator{}), 12);
  expect_same_table(phantom_tissue_table(), load_tissue_table(out + "/tissues.json"));
  ModelReader r(out + "/truth.h5");
  const Volume v = r.volume();
  const Volume expect = phantom_labels(o);
  EXPECT_EQ(v.labels, expect.labels);
  EXPECT_EQ(v.label_names, expect.label_names);
  for (int k = 0; k < 3; ++k) {
    EXPECT_DOUBLE_EQ(v.spacing_m[k], o.spacing_m[k]);
    EXPECT_DOUBLE_EQ(v.origin_m[k], expect.origin_m[k]);
  }
  EXPECT_EQ(r.vessels("artery").branch_parent.size(), 3);
  EXPECT_EQ(r.vessels("vein").branch_parent.size(), 1);
  EXPECT_EQ(r.names("/surfaces"), (std::vector<std::string>{"bone", "fat", "marrow", "muscle", "skin"}));
  EXPECT_EQ(r.surface("skin").faces.rows(), m.surface_faces.at("skin"));
  const auto prov = r.provenance();
  ASSERT_TRUE(prov.count("phantom"));
  EXPECT_EQ(prov.at("phantom").seed, 1);
  EXPECT_EQ(prov.at("phantom").command_line, "orthosim phantom --test");
  EXPECT_EQ(m.voxels.at("background") + m.voxels.at("skin") + m.voxels.at("fat") + m.voxels.at("muscle") +
                m.voxels.at("bone") + m.voxels.at("marrow") + m.voxels.at("artery") + m.voxels.at("vein"),
            static_cast<std::int64_t>(o.nx) * o.ny * o.nz);
  // nothing else left beside the output (no temporary directories)
  EXPECT_EQ(std::distance(fs::directory_iterator(tmp.path), fs::directory_iterator{}), 1);

  // rewriting with fewer JPEG slices replaces the stack
  o.nz = 6;
  o.jpeg = true;
  write_phantom(o, out);
  EXPECT_EQ(std::distance(fs::directory_iterator(out + "/slices"), fs::directory_iterator{}), 6);
  EXPECT_TRUE(fs::is_regular_file(out + "/slices/slice_0005.jpg"));
  EXPECT_EQ(ModelReader(out + "/truth.h5").volume().nz, 6);
}

TEST(Phantom, RefusesToWriteOverAFile) {
  test::TempDir tmp("phantom");
  const std::string path = tmp / "not-a-dir";
  test::write_file(path, "keep me");
  EXPECT_THROW(write_phantom(small_options(), path), Error);
  EXPECT_EQ(test::read_file(path), "keep me");
  EXPECT_EQ(std::distance(fs::directory_iterator(tmp.path), fs::directory_iterator{}), 1);
}

TEST(Phantom, CommittedSampleIsWhatThisCodeGenerates) {
  const std::string dir = std::string(ORTHOSIM_SOURCE_DIR) + "/data-samples/phantom";
  ModelReader r(dir + "/truth.h5");
  const auto prov = r.provenance();
  ASSERT_TRUE(prov.count("phantom"));
  const nlohmann::json p = nlohmann::json::parse(prov.at("phantom").parameters_json);
  PhantomOptions o;
  o.nx = p["size"][0], o.ny = p["size"][1], o.nz = p["size"][2];
  for (int k = 0; k < 3; ++k) o.spacing_m[k] = p["spacing_m"][k];
  const Volume v = r.volume();
  EXPECT_EQ(v.labels, phantom_labels(o).labels);
  const std::string ext = p["jpeg"].get<bool>() ? ".jpg" : ".png";
  EXPECT_EQ(std::distance(fs::directory_iterator(dir + "/slices"), fs::directory_iterator{}), o.nz);
  EXPECT_TRUE(fs::is_regular_file(dir + "/slices/slice_0000" + ext));
  expect_same_table(phantom_tissue_table(), load_tissue_table(dir + "/tissues.json"));
  std::uintmax_t bytes = 0;
  for (const auto& e : fs::recursive_directory_iterator(dir))
    if (e.is_regular_file()) bytes += e.file_size();
  EXPECT_LE(bytes, 4u << 20);
}

// ---- command line --------------------------------------------------------------------------

TEST(PhantomCli, WritesAStackAndReportsBadFlagsInOneLine) {
  test::TempDir tmp("phantom-cli");
  const std::string out = tmp / "x";
  auto r = test::run_cli("phantom --out " + out + " --size 64x64x6 --spacing 0.8,0.8,3 --jpeg --seed 9 --report " +
                         (tmp / "r.json") + " --quiet");
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(fs::is_regular_file(out + "/slices/slice_0005.jpg"));
  EXPECT_TRUE(fs::is_regular_file(out + "/truth.h5"));
  EXPECT_TRUE(r.out.empty());
  const auto report = nlohmann::json::parse(test::read_file(tmp / "r.json"));
  EXPECT_EQ(report["parameters"]["size"], nlohmann::json({64, 64, 6}));
  EXPECT_GT(report["metrics"]["voxels"]["muscle"].get<long>(), 0);

  for (const std::string bad : {"--size 0x64x6", "--size 64x64", "--spacing 0.3,-0.3,1", "--noise -1",
                                "--size 8x8x8", "--jpeg-quality 0"}) {
    auto e = test::run_cli("phantom --out " + (tmp / "y") + " " + bad);
    EXPECT_EQ(e.code, 2) << bad;
    EXPECT_EQ(test::count_lines(e.err), 1) << bad << ": " << e.err;
    EXPECT_EQ(e.err.rfind("orthosim phantom: error: ", 0), 0u) << e.err;
    EXPECT_FALSE(fs::exists(tmp / "y")) << bad;
  }
  test::write_file(tmp / "file", "keep");
  auto f = test::run_cli("phantom --out " + (tmp / "file") + " --size 32x32x4");
  EXPECT_EQ(f.code, 2);
  EXPECT_EQ(test::read_file(tmp / "file"), "keep");
}
