// The phantom's library interface: options, tissue table, labels, colour
// slices, truth and the atomic writer. Geometry lives in geometry.cpp.
#include "libmodel/phantom/phantom.h"

#include "libmodel/format/atomic.h"
#include "libmodel/phantom/geometry.h"
#include "libmodel/provenance.h"

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/core/version.hpp>
#include <opencv2/imgcodecs.hpp>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <filesystem>
#include <set>
#include <system_error>

namespace orthosim {

using phantom_detail::Geometry;
using phantom_detail::make_geometry;

namespace {

constexpr double kPi = 3.14159265358979323846;

// ---- nominal colours (sRGB), indexed by label --------------------------------------
// CVH-like: blue-grey embedding, pale tan skin, yellow fat, dark red muscle,
// off-white cortex, yellowish-red marrow, bright red (perfused) artery, dark
// blue-purple vein. Every pair is at least 27 CIELAB (CIE76) units apart.
constexpr std::array<std::array<std::uint8_t, 3>, 8> kColour = {{
    {72, 96, 138},    // background (embedding medium)
    {214, 168, 140},  // skin
    {226, 196, 104},  // fat
    {136, 42, 38},    // muscle
    {236, 232, 214},  // bone (cortex)
    {196, 116, 66},   // marrow
    {222, 34, 40},    // artery
    {72, 36, 112},    // vein
}};

// Texture per label: brightness amplitude, cell size (fraction of the limb
// radius R), red/blue balance amplitude.
struct Texture {
  double amp, cell, chroma;
};
constexpr std::array<Texture, 8> kTexture = {{
    {0.02, 0.15, 0.01},   // background: smooth gel
    {0.04, 0.03, 0.01},   // skin
    {0.05, 0.05, 0.015},  // fat: lobules
    {0.06, 0.035, 0.02},  // muscle: mottled fibre bundles
    {0.03, 0.04, 0.01},   // bone
    {0.06, 0.03, 0.02},   // marrow
    {0.03, 0.05, 0.01},   // artery
    {0.04, 0.05, 0.01},   // vein
}};

// ---- counter-based random numbers (splitmix64 finaliser) ----------------------------
inline std::uint64_t mix(std::uint64_t x) {
  x += 0x9e3779b97f4a7c15ULL;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}
inline std::uint64_t key(std::uint64_t a, std::uint64_t b) { return mix(a ^ mix(b)); }

inline double lattice(std::uint64_t k, std::int64_t i, std::int64_t j, std::int64_t l) {
  const std::uint64_t h = mix(k ^ (static_cast<std::uint64_t>(i) * 0x8cb92ba72f3d8dd7ULL) ^
                              (static_cast<std::uint64_t>(j) * 0xd6e8feb86659fd93ULL) ^
                              (static_cast<std::uint64_t>(l) * 0xa0761d6478bd642fULL));
  return static_cast<double>(h >> 11) * (2.0 / 9007199254740992.0) - 1.0;
}

inline double fade(double t) { return t * t * t * (t * (6 * t - 15) + 10); }

// Smooth 3D value noise in [-1, 1] at a point given in cell units.
double value_noise(std::uint64_t k, double x, double y, double z) {
  const double fx = std::floor(x), fy = std::floor(y), fz = std::floor(z);
  const auto ix = static_cast<std::int64_t>(fx), iy = static_cast<std::int64_t>(fy),
             iz = static_cast<std::int64_t>(fz);
  const double u = fade(x - fx), v = fade(y - fy), w = fade(z - fz);
  double c[2][2][2];
  for (int a = 0; a < 2; ++a)
    for (int b = 0; b < 2; ++b)
      for (int d = 0; d < 2; ++d) c[a][b][d] = lattice(k, ix + a, iy + b, iz + d);
  auto lerp = [](double p, double q, double t) { return p + (q - p) * t; };
  const double x00 = lerp(c[0][0][0], c[1][0][0], u), x10 = lerp(c[0][1][0], c[1][1][0], u);
  const double x01 = lerp(c[0][0][1], c[1][0][1], u), x11 = lerp(c[0][1][1], c[1][1][1], u);
  return lerp(lerp(x00, x10, v), lerp(x01, x11, v), w);
}

double uniform01(std::uint64_t h) { return (static_cast<double>(h >> 11) + 0.5) / 9007199254740992.0; }

// Illumination of one slice: a slow gradient across it, a mild vignette and
// per-channel gains, all drifting slowly with z. Phases come from the seed.
struct Illumination {
  double gx = 0, gy = 0, g0 = 0, vignette = 0.02;
  std::array<double, 3> gain{1, 1, 1};
};

Illumination illumination(const PhantomOptions& o, int z) {
  const double t = o.nz > 1 ? static_cast<double>(z) / (o.nz - 1) : 0;
  std::array<double, 6> ph{};
  for (int i = 0; i < 6; ++i) ph[i] = 2 * kPi * uniform01(key(o.seed ^ 0x1111, static_cast<std::uint64_t>(i)));
  Illumination il;
  il.gx = 0.025 * std::sin(2 * kPi * 0.6 * t + ph[0]);
  il.gy = 0.025 * std::sin(2 * kPi * 0.45 * t + ph[1]);
  il.g0 = 0.015 * std::sin(2 * kPi * 1.1 * t + ph[2]);
  for (int c = 0; c < 3; ++c) il.gain[c] = 1 + 0.015 * std::sin(2 * kPi * 0.8 * t + ph[3 + c]);
  return il;
}

std::string slice_name(int z, bool jpeg) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "slice_%04d.%s", z, jpeg ? "jpg" : "png");
  return buf;
}

void write_slice_image(const PhantomOptions& o, const std::vector<std::uint8_t>& rgb, const std::string& path) {
  cv::Mat bgr(o.ny, o.nx, CV_8UC3);
  for (int y = 0; y < o.ny; ++y) {
    auto* row = bgr.ptr<std::uint8_t>(y);
    const std::uint8_t* src = rgb.data() + static_cast<std::size_t>(y) * o.nx * 3;
    for (int x = 0; x < o.nx; ++x) {
      row[3 * x + 0] = src[3 * x + 2];
      row[3 * x + 1] = src[3 * x + 1];
      row[3 * x + 2] = src[3 * x + 0];
    }
  }
  std::vector<int> params;
  if (o.jpeg) {
    params = {cv::IMWRITE_JPEG_QUALITY, o.jpeg_quality};
#if CV_VERSION_MAJOR > 4 || (CV_VERSION_MAJOR == 4 && CV_VERSION_MINOR >= 7)
    params.push_back(cv::IMWRITE_JPEG_SAMPLING_FACTOR);
    params.push_back(cv::IMWRITE_JPEG_SAMPLING_FACTOR_444);
#endif
  } else {
    params = {cv::IMWRITE_PNG_COMPRESSION, 6};
  }
  bool ok = false;
  try {
    ok = cv::imwrite(path, bgr, params);
  } catch (const cv::Exception& e) {
    throw Error(path, std::string("cannot write slice image: ") + e.what());
  }
  if (!ok) throw Error(path, "cannot write slice image");
}

}  // namespace

// ---- options ---------------------------------------------------------------------------

void validate(const PhantomOptions& o) {
  auto bad = [](const std::string& m) { throw Error("", "phantom options: " + m); };
  auto num = [](double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%g", v);
    return std::string(buf);
  };
  if (o.nx < 16 || o.nx > 4096 || o.ny < 16 || o.ny > 4096)
    bad("size: in-plane sizes must be in [16, 4096] voxels, got " + std::to_string(o.nx) + "x" + std::to_string(o.ny));
  if (o.nz < 2 || o.nz > 9999) bad("size: the slice count must be in [2, 9999], got " + std::to_string(o.nz));
  if (static_cast<double>(o.nx) * o.ny * o.nz > 2147483647.0) bad("size: more than 2^31 voxels");
  if (const std::string why = voxel_geometry_problem(o.spacing_m, {0, 0, 0}); !why.empty()) bad(why);  // as every stage
  if (!std::isfinite(o.noise_sigma) || o.noise_sigma < 0 || o.noise_sigma > 255)
    bad("noise: sigma must be in [0, 255], got " + num(o.noise_sigma));
  if (o.jpeg_quality < 1 || o.jpeg_quality > 100)
    bad("jpeg quality: must be in [1, 100], got " + std::to_string(o.jpeg_quality));
}

std::string phantom_parameters_json(const PhantomOptions& o) {
  nlohmann::json j;
  j["size"] = {o.nx, o.ny, o.nz};
  j["spacing_m"] = o.spacing_m;
  j["noise_sigma"] = o.noise_sigma;
  j["jpeg"] = o.jpeg;
  j["jpeg_quality"] = o.jpeg_quality;
  j["seed"] = o.seed;
  return j.dump();
}

std::array<double, 3> phantom_origin(const PhantomOptions& o) {
  return {-0.5 * (o.nx - 1) * o.spacing_m[0], -0.5 * (o.ny - 1) * o.spacing_m[1], 0.0};
}

// ---- tissue table ----------------------------------------------------------------------

TissueTable phantom_tissue_table() {
  TissueTable t;
  t.path = "phantom";
  t.background_name = "background";
  t.background_rgb = {kColour[kPhantomBackground]};
  auto add = [&](const char* name, PhantomLabel label, double density, const char* layer, const char* inside,
                 Mechanics m, const char* source) {
    Tissue x;
    x.name = name;
    x.label = label;
    x.rgb = {kColour[label]};
    x.density_kg_m3 = density;
    x.layer = layer;
    x.inside = inside;
    x.mechanics = std::move(m);
    x.source = source;
    t.tissues.push_back(std::move(x));
  };
  auto linear = [](double k_pa) {
    Mechanics m;
    m.model = Mechanics::Model::linear;
    m.k_pa = k_pa;
    m.weights = {1};
    return m;
  };
  Mechanics dermis;
  dermis.model = Mechanics::Model::biphasic;
  dermis.k1_pa = 100;
  dermis.turning_strain = 0.4;
  dermis.k2_pa = 18800;
  dermis.weights = {1, 1, 1};
  add("skin", kPhantomSkin, 1090, "tetra", "", dermis,
      "mechanics: dermis, the paper's Table 1 (biphasic, K1 = 0.1 kPa, turning strain 0.4, K2 = 18.8 kPa); "
      "the same digits appear in MPa in the skin literature (Silver, Freeman & DeVore, Skin Res. Technol. 7, "
      "2001), so the paper's kPa may be a unit slip (uncertain). density 1090 kg/m^3: skin, data book "
      "(Ni Annaidh et al., J. Mech. Behav. Biomed. Mater. 5, 2012).");
  add("fat", kPhantomFat, 950, "lattice", "skin", linear(2300),
      "mechanics: hypodermis/adipose in vivo, MR elastography shear modulus 752 Pa, E ~ 2.3 kPa, quasi-linear "
      "at small strain (J. Mech. Behav. Biomed. Mater., 2023); porcine adipose E ~ 1.6 kPa (Sims et al., "
      "Biomech. Model. Mechanobiol. 9, 2010) for comparison. density 950 kg/m^3: same data-book row.");
  add("muscle", kPhantomMuscle, 1050, "lattice", "fat", linear(3000),
      "mechanics: passive skeletal muscle, shear modulus 1000 Pa, E ~ 3 kPa, linear and isotropic here "
      "(anisotropic in reality) (J. Mech. Behav. Biomed. Mater., 2023, MR elastography). density 1050 kg/m^3: "
      "same data-book row.");
  add("bone", kPhantomBone, 1920, "rigid", "muscle", Mechanics{},
      "rigid in this model. density 1920 kg/m^3: McGPU material table (bone).");
  add("marrow", kPhantomMarrow, 980, "rigid", "bone", Mechanics{},
      "rigid, moves with its bone. density 980 kg/m^3: not in the data book; assumed (yellow marrow is mostly "
      "fat, between adipose 950 and soft tissue 1050) (uncertain).");
  add("artery", kPhantomArtery, 1060, "vessel", "muscle", Mechanics{},
      "perfused lumen; wall mechanics not modelled. density 1060 kg/m^3: blood, McGPU / NIST.");
  add("vein", kPhantomVein, 1060, "vessel", "muscle", Mechanics{},
      "perfused lumen; wall mechanics not modelled. density 1060 kg/m^3: blood, McGPU / NIST.");
  return t;
}

// ---- labels ------------------------------------------------------------------------------

int phantom_label_at(const PhantomOptions& o, const Eigen::Vector3d& p_m) {
  validate(o);
  return phantom_detail::label_at(make_geometry(o), p_m);
}

std::vector<std::uint8_t> phantom_labels_at(const PhantomOptions& o, const MatX3d& points_m) {
  validate(o);
  const Geometry g = make_geometry(o);
  std::vector<std::uint8_t> out(static_cast<std::size_t>(points_m.rows()));
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, points_m.rows(), 256),
                    [&](const tbb::blocked_range<Eigen::Index>& r) {
                      for (Eigen::Index i = r.begin(); i < r.end(); ++i)
                        out[static_cast<std::size_t>(i)] = static_cast<std::uint8_t>(
                            phantom_detail::label_at(g, points_m.row(i).transpose()));
                    });
  return out;
}

Volume phantom_labels(const PhantomOptions& o) {
  validate(o);
  const Geometry g = make_geometry(o);
  Volume v;
  v.nx = o.nx, v.ny = o.ny, v.nz = o.nz;
  v.spacing_m = o.spacing_m;
  v.origin_m = phantom_origin(o);
  v.label_names = phantom_tissue_table().label_names();
  v.labels.assign(static_cast<std::size_t>(o.nx) * o.ny * o.nz, 0);
  const std::size_t plane = static_cast<std::size_t>(o.nx) * o.ny;
  tbb::parallel_for(tbb::blocked_range<int>(0, o.nz, 1), [&](const tbb::blocked_range<int>& r) {
    for (int z = r.begin(); z < r.end(); ++z) phantom_detail::label_slice(g, z, v.labels.data() + z * plane);
  });
  return v;
}

namespace {

double interface_distance(const Geometry& g, const std::string& tissue, const Eigen::Vector3d& p) {
  using phantom_detail::body_distance;
  if (tissue == "skin") return body_distance(g.skin, p);
  if (tissue == "fat") return body_distance(g.fat, p);
  if (tissue == "muscle") return body_distance(g.muscle, p);
  if (tissue == "bone" || tissue == "marrow") {
    const auto& bodies = tissue == "bone" ? g.bones : g.marrows;
    double d = std::numeric_limits<double>::infinity();
    for (const auto& b : bodies) d = std::min(d, body_distance(b, p));
    return d;
  }
  const auto& tree = tissue == "artery" ? g.artery : g.vein;
  double d = std::numeric_limits<double>::infinity();
  for (const auto& b : tree) d = std::min(d, phantom_detail::branch_sdf(g, b, p));
  return std::abs(d);
}

void check_interface_name(const std::string& tissue) {
  static const std::set<std::string> known{"skin", "fat", "muscle", "bone", "marrow", "artery", "vein"};
  if (!known.count(tissue)) throw Error("", "phantom: no analytic interface for tissue '" + tissue + "'");
}

}  // namespace

double phantom_interface_distance(const PhantomOptions& o, const std::string& tissue, const Eigen::Vector3d& p) {
  validate(o);
  check_interface_name(tissue);
  return interface_distance(make_geometry(o), tissue, p);
}

VecXd phantom_interface_distances(const PhantomOptions& o, const std::string& tissue, const MatX3d& points_m) {
  validate(o);
  check_interface_name(tissue);
  const Geometry g = make_geometry(o);
  VecXd out(points_m.rows());
  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, points_m.rows(), 16),
                    [&](const tbb::blocked_range<Eigen::Index>& r) {
                      for (Eigen::Index i = r.begin(); i < r.end(); ++i)
                        out(i) = interface_distance(g, tissue, points_m.row(i).transpose());
                    });
  return out;
}

// ---- colour ------------------------------------------------------------------------------

void phantom_slice_rgb(const PhantomOptions& o, const Volume& labels, int z, std::vector<std::uint8_t>& rgb) {
  validate(o);
  if (labels.nx != o.nx || labels.ny != o.ny || labels.nz != o.nz ||
      labels.labels.size() != static_cast<std::size_t>(o.nx) * o.ny * o.nz)
    throw Error("", "phantom: label volume does not match the options");
  if (z < 0 || z >= o.nz) throw Error("", "phantom: slice index out of range");
  const double R = 0.36 * std::min(o.nx * o.spacing_m[0], o.ny * o.spacing_m[1]);
  const double pix = std::min(o.spacing_m[0], o.spacing_m[1]);
  const std::array<double, 3> origin = phantom_origin(o);
  const Illumination il = illumination(o, z);
  // per-label noise keys and cell sizes
  std::array<std::uint64_t, 8> k1{}, k2{}, k3{};
  std::array<double, 8> cell{};
  for (int l = 0; l < 8; ++l) {
    k1[l] = key(o.seed, 0x100 + l);
    k2[l] = key(o.seed, 0x200 + l);
    k3[l] = key(o.seed, 0x300 + l);
    cell[l] = std::max(kTexture[l].cell * R, 2.5 * pix);
  }
  const std::uint64_t knoise = key(key(o.seed, 0x400), static_cast<std::uint64_t>(z));
  rgb.resize(static_cast<std::size_t>(o.nx) * o.ny * 3);
  const double pz = origin[2] + z * o.spacing_m[2];
  for (int y = 0; y < o.ny; ++y) {
    const double py = origin[1] + y * o.spacing_m[1];
    const double Y = (y - 0.5 * (o.ny - 1)) / o.ny;
    for (int x = 0; x < o.nx; ++x) {
      const double px = origin[0] + x * o.spacing_m[0];
      const double X = (x - 0.5 * (o.nx - 1)) / o.nx;
      const int l = std::min<int>(labels.at(x, y, z), 7);
      const Texture& tx = kTexture[l];
      const double c = cell[l];
      // texture: two octaves of brightness, one of red/blue balance
      const double n1 = 0.75 * value_noise(k1[l], px / c, py / c, pz / c) +
                        0.25 * value_noise(k2[l], 2.5 * px / c, 2.5 * py / c, 2.5 * pz / c);
      const double n2 = value_noise(k3[l], px / c, py / c, pz / c);
      const double bright = 1 + tx.amp * n1;
      const std::array<double, 3> chroma{1 + tx.chroma * n2, 1, 1 - tx.chroma * n2};
      const double light = 1 + il.gx * 2 * X + il.gy * 2 * Y + il.g0 - il.vignette * 2 * (X * X + Y * Y);
      // sensor noise: Box-Muller on counter-based uniforms
      const std::size_t i = static_cast<std::size_t>(y) * o.nx + x;
      const std::uint64_t h1 = mix(knoise + 2 * i), h2 = mix(knoise + 2 * i + 1);
      const double u1 = ((h1 >> 32) + 0.5) / 4294967296.0, u2 = ((h1 & 0xffffffffULL) + 0.5) / 4294967296.0;
      const double u3 = ((h2 >> 32) + 0.5) / 4294967296.0, u4 = ((h2 & 0xffffffffULL) + 0.5) / 4294967296.0;
      const double ra = std::sqrt(-2 * std::log(u1)), rb = std::sqrt(-2 * std::log(u3));
      const std::array<double, 3> gn{ra * std::cos(2 * kPi * u2), ra * std::sin(2 * kPi * u2),
                                     rb * std::cos(2 * kPi * u4)};
      for (int ch = 0; ch < 3; ++ch) {
        const double v = kColour[l][ch] * bright * chroma[ch] * light * il.gain[ch] + o.noise_sigma * gn[ch];
        rgb[3 * i + ch] = static_cast<std::uint8_t>(std::clamp(std::lround(v), 0L, 255L));
      }
    }
  }
}

// ---- truth -------------------------------------------------------------------------------

std::map<std::string, VesselTree> phantom_vessels(const PhantomOptions& o) {
  validate(o);
  const Geometry g = make_geometry(o);
  const double step = 0.5 * std::min({o.spacing_m[0], o.spacing_m[1], o.spacing_m[2]});
  std::map<std::string, VesselTree> out;
  for (const auto* tree : {&g.artery, &g.vein}) {
    std::vector<Eigen::Vector3d> nodes;
    std::vector<double> radii;
    std::vector<std::array<int, 2>> edges;
    std::vector<int> parent, offsets{0}, bnodes;
    std::vector<int> last_node(tree->size(), -1);
    for (std::size_t bi = 0; bi < tree->size(); ++bi) {
      const phantom_detail::Branch& b = (*tree)[bi];
      // uniform in z, refined until every chord is at most `step`
      int n = std::max(1, static_cast<int>(std::ceil((b.z1 - b.z0) / step)));
      std::vector<Eigen::Vector3d> pts;
      for (;;) {
        pts.clear();
        for (int i = 0; i <= n; ++i) pts.push_back(g.centreline(b, b.z0 + (b.z1 - b.z0) * i / n));
        double worst = 0;
        for (int i = 0; i < n; ++i) worst = std::max(worst, (pts[i + 1] - pts[i]).norm());
        if (worst <= step) break;
        n = static_cast<int>(std::ceil(n * worst / step * 1.01));
      }
      int prev = -1;
      if (b.parent >= 0) {
        prev = last_node[b.parent];  // the child starts at its parent's end node
        bnodes.push_back(prev);
      }
      for (int i = b.parent >= 0 ? 1 : 0; i <= n; ++i) {
        const int id = static_cast<int>(nodes.size());
        nodes.push_back(pts[i]);
        radii.push_back(g.vessel_radius(b, pts[i].z()));
        bnodes.push_back(id);
        if (prev >= 0) edges.push_back({prev, id});
        prev = id;
      }
      last_node[bi] = prev;
      parent.push_back(b.parent);
      offsets.push_back(static_cast<int>(bnodes.size()));
    }
    VesselTree t;
    t.nodes.resize(static_cast<Eigen::Index>(nodes.size()), 3);
    t.radii.resize(static_cast<Eigen::Index>(nodes.size()));
    for (std::size_t i = 0; i < nodes.size(); ++i) {
      t.nodes.row(static_cast<Eigen::Index>(i)) = nodes[i].transpose();
      t.radii(static_cast<Eigen::Index>(i)) = radii[i];
    }
    t.edges.resize(static_cast<Eigen::Index>(edges.size()), 2);
    for (std::size_t i = 0; i < edges.size(); ++i)
      t.edges.row(static_cast<Eigen::Index>(i)) << edges[i][0], edges[i][1];
    t.branch_parent = Eigen::Map<const VecXi>(parent.data(), static_cast<Eigen::Index>(parent.size()));
    t.branch_offsets = Eigen::Map<const VecXi>(offsets.data(), static_cast<Eigen::Index>(offsets.size()));
    t.branch_nodes = Eigen::Map<const VecXi>(bnodes.data(), static_cast<Eigen::Index>(bnodes.size()));
    t.bezier_offsets = VecXi::Zero(0);
    out[tree == &g.artery ? "artery" : "vein"] = std::move(t);
  }
  return out;
}

std::map<std::string, Surface> phantom_surfaces(const PhantomOptions& o) {
  validate(o);
  const Geometry g = make_geometry(o);
  const double around = 2 * std::min(o.spacing_m[0], o.spacing_m[1]);
  const double along = o.spacing_m[2];
  std::map<std::string, Surface> out;
  phantom_detail::mesh_body(g.skin, around, along, out["skin"]);
  phantom_detail::mesh_body(g.fat, around, along, out["fat"]);
  phantom_detail::mesh_body(g.muscle, around, along, out["muscle"]);
  for (const auto& b : g.bones) phantom_detail::mesh_body(b, around, along, out["bone"]);
  for (const auto& b : g.marrows) phantom_detail::mesh_body(b, around, along, out["marrow"]);
  return out;
}

// ---- writer ------------------------------------------------------------------------------

PhantomMetrics write_phantom(const PhantomOptions& o, const std::string& out_dir, const std::string& command_line,
                             const std::function<void(long, long)>& progress) {
  namespace fs = std::filesystem;
  using clock = std::chrono::steady_clock;
  auto since = [](clock::time_point t0) { return std::chrono::duration<double>(clock::now() - t0).count(); };
  validate(o);
  const auto t_start = clock::now();
  PhantomMetrics m;
  AtomicDir dir(out_dir);
  {
    std::error_code ec;
    fs::create_directories(dir.temp_path("slices"), ec);
    if (ec) throw Error(dir.temp_path("slices"), "cannot create directory: " + ec.message());
  }

  // labels
  auto t0 = clock::now();
  const Volume labels = phantom_labels(o);
  const TissueTable table = phantom_tissue_table();
  {
    std::array<std::int64_t, 256> count{};
    for (std::uint8_t l : labels.labels) ++count[l];
    m.voxels["background"] = count[0];
    for (const auto& t : table.tissues) m.voxels[t.name] = count[t.label];
  }
  m.labels_s = since(t0);

  // colour slices, in chunks so that progress is reported from this thread
  t0 = clock::now();
  std::vector<std::string> names(static_cast<std::size_t>(o.nz));
  for (int z = 0; z < o.nz; ++z) names[z] = slice_name(z, o.jpeg);
  const int chunk = 16;
  for (int z0 = 0; z0 < o.nz; z0 += chunk) {
    const int z1 = std::min(o.nz, z0 + chunk);
    tbb::parallel_for(tbb::blocked_range<int>(z0, z1, 1), [&](const tbb::blocked_range<int>& r) {
      std::vector<std::uint8_t> rgb;
      for (int z = r.begin(); z < r.end(); ++z) {
        phantom_slice_rgb(o, labels, z, rgb);
        write_slice_image(o, rgb, dir.temp_path("slices/" + names[z]));
      }
    });
    if (progress) progress(z1, o.nz);
  }
  for (const auto& n : names) {
    std::error_code ec;
    m.slice_bytes += static_cast<std::int64_t>(fs::file_size(dir.temp_path("slices/" + n), ec));
  }
  m.slices_s = since(t0);

  // tissue table and truth
  t0 = clock::now();
  write_text_file(dir.temp_path("tissues.json"), to_json(table));
  {
    ModelWriter w(dir.temp_path("truth.h5"), ModelWriter::Start::fresh);
    w.write(labels);
    for (const auto& [name, tree] : phantom_vessels(o)) {
      w.write(name, tree);
      m.vessel_nodes[name] = tree.nodes.rows();
    }
    for (const auto& [name, s] : phantom_surfaces(o)) {
      w.write(name, s);
      m.surface_faces[name] = s.faces.rows();
    }
    w.write("phantom", make_provenance(command_line, "{}", phantom_parameters_json(o),
                                       static_cast<std::int64_t>(o.seed), since(t_start)));
    w.commit();
  }
  m.truth_s = since(t0);
  dir.commit();

  // remove slice files of an earlier run that this run did not write
  const std::set<std::string> written(names.begin(), names.end());
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(fs::path(dir.target()) / "slices", ec)) {
    const std::string n = e.path().filename().string();
    const bool ours = n.rfind("slice_", 0) == 0 && (e.path().extension() == ".png" || e.path().extension() == ".jpg");
    if (ours && !written.count(n)) fs::remove(e.path(), ec);
  }
  return m;
}

}  // namespace orthosim
