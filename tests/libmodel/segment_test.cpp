// orthosim_segment: natural order, stack checks, the clean-up rules on small
// synthetic volumes, determinism and streaming, accuracy against the
// phantom's truth (PNG and JPEG, perturbed prototypes and illumination), the
// real cryosection, and every bad input through the CLI.
#include "libmodel/phantom/phantom.h"
#include "libmodel/segment/segment.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <tbb/global_control.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <functional>
#include <random>

using namespace orthosim;
namespace fs = std::filesystem;

namespace {

// ---- helpers ------------------------------------------------------------------------

// A small table: background gel, skin > fat > muscle > bone > marrow, a vessel.
TissueTable small_table() {
  const char* json = R"({
    "format": "orthosim-tissues/1",
    "background": {"name": "background", "rgb": [[72, 96, 138]]},
    "tissues": [
      {"name": "skin", "label": 1, "rgb": [[214, 168, 140]], "density_kg_m3": 1090, "layer": "none"},
      {"name": "fat", "label": 2, "rgb": [[226, 196, 104]], "density_kg_m3": 950, "layer": "none", "inside": "skin"},
      {"name": "muscle", "label": 3, "rgb": [[136, 42, 38]], "density_kg_m3": 1050, "layer": "none", "inside": "fat"},
      {"name": "bone", "label": 4, "rgb": [[236, 232, 214]], "density_kg_m3": 1920, "layer": "rigid", "inside": "muscle"},
      {"name": "marrow", "label": 5, "rgb": [[196, 116, 66]], "density_kg_m3": 980, "layer": "rigid", "inside": "bone"},
      {"name": "artery", "label": 6, "rgb": [[222, 34, 40]], "density_kg_m3": 1060, "layer": "vessel", "inside": "muscle"}
    ]})";
  return parse_tissue_table(json, "small.json");
}

// Paints slices from a label function; colour = the table's prototype plus
// Gaussian noise (deterministic).
std::vector<RgbImage> paint(const TissueTable& t, int nx, int ny, int nz, const std::function<int(int, int, int)>& label,
                            double noise, std::uint32_t seed = 1) {
  std::vector<std::array<std::uint8_t, 3>> colour(256, t.background_rgb[0]);
  for (const auto& x : t.tissues) colour[x.label] = x.rgb[0];
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0, noise);
  std::vector<RgbImage> out;
  for (int z = 0; z < nz; ++z) {
    RgbImage im;
    im.nx = nx, im.ny = ny;
    im.rgb.resize(static_cast<std::size_t>(nx) * ny * 3);
    for (int y = 0; y < ny; ++y)
      for (int x = 0; x < nx; ++x)
        for (int c = 0; c < 3; ++c) {
          const double v = colour[static_cast<std::size_t>(label(x, y, z))][c] + (noise > 0 ? g(rng) : 0);
          im.rgb[(static_cast<std::size_t>(y) * nx + x) * 3 + c] = static_cast<std::uint8_t>(std::clamp(std::lround(v), 0L, 255L));
        }
    out.push_back(std::move(im));
  }
  return out;
}

// Concentric limb: skin ring, fat ring, muscle, bone ring with marrow, along z.
int limb(int x, int y, int /*z*/, int nx, int ny) {
  const double r = std::hypot(x - 0.5 * (nx - 1), y - 0.5 * (ny - 1));
  const double R = 0.4 * std::min(nx, ny);
  if (r > R) return 0;
  if (r > R - 2) return 1;
  if (r > 0.75 * R) return 2;
  if (r > 0.3 * R) return 3;
  if (r > 0.18 * R) return 4;
  return 5;
}

SegmentOptions iso_options() {
  SegmentOptions o;
  o.spacing_m = {1e-3, 1e-3, 1e-3};
  return o;
}

std::int64_t count_label(const Volume& v, int l) {
  return std::count(v.labels.begin(), v.labels.end(), static_cast<std::uint8_t>(l));
}

// The phantom's slices in memory.
SliceSource phantom_source(const PhantomOptions& o, const Volume& truth) {
  std::vector<RgbImage> slices(static_cast<std::size_t>(o.nz));
  for (int z = 0; z < o.nz; ++z) {
    slices[static_cast<std::size_t>(z)].nx = o.nx;
    slices[static_cast<std::size_t>(z)].ny = o.ny;
    phantom_slice_rgb(o, truth, z, slices[static_cast<std::size_t>(z)].rgb);
  }
  return memory_source(std::move(slices), "phantom");
}

SegmentOptions phantom_segment_options(const PhantomOptions& p) {
  SegmentOptions o;
  o.spacing_m = p.spacing_m;
  o.origin_m = phantom_origin(p);
  o.lightness_weight = 3;
  return o;
}

void expect_dice(const std::map<std::string, double>& dice, const std::map<std::string, std::int64_t>& truth_voxels,
                 const TissueTable& table, const std::string& what) {
  for (const auto& t : table.tissues) {
    const auto n = truth_voxels.count(t.name) ? truth_voxels.at(t.name) : 0;
    const double d = dice.count(t.name) ? dice.at(t.name) : 0.0;
    if (t.layer == "vessel") {
      if (n > 0) EXPECT_GE(d, 0.90) << what << ": " << t.name << " (" << n << " voxels)";
    } else if (n >= 1000) {
      EXPECT_GE(d, 0.97) << what << ": " << t.name << " (" << n << " voxels)";
    }
  }
}

PhantomOptions test_phantom() {
  PhantomOptions p;
  p.nx = 128, p.ny = 128, p.nz = 40;
  p.spacing_m = {0.4e-3, 0.4e-3, 1.0e-3};
  p.noise_sigma = 4;
  p.seed = 3;
  return p;
}

}  // namespace

// ---- accuracy against the phantom ------------------------------------------------------

TEST(SegmentPhantom, DicePng) {
  const PhantomOptions p = test_phantom();
  const Volume truth = phantom_labels(p);
  const TissueTable table = phantom_tissue_table();
  SegmentMetrics m;
  const Volume v = segment_volume(phantom_source(p, truth), table, phantom_segment_options(p), &m);
  std::map<std::string, std::int64_t> tv;
  const auto dice = dice_per_tissue(v, truth, &tv);
  for (const auto& [k, d] : dice) std::printf("  %-8s dice %.4f  truth %lld\n", k.c_str(), d, (long long)tv[k]);
  std::printf("  order %lld speck %lld holes %lld islands %lld misplaced %lld detached %lld comps %lld\n", (long long)m.order_changed,
              (long long)m.speck_changed, (long long)m.holes_filled, (long long)m.islands_absorbed, (long long)m.misplaced_absorbed,
              (long long)m.detached_removed, (long long)m.components);
  expect_dice(dice, tv, table, "png");
}

TEST(SegmentPhantom, DiceJpeg) {
  PhantomOptions p = test_phantom();
  p.jpeg = true;
  test::TempDir dir("segjpeg");
  write_phantom(p, dir / "ph");
  const Volume truth = phantom_labels(p);
  const TissueTable table = load_tissue_table(dir / "ph/tissues.json");
  SegmentMetrics m;
  auto t0 = std::chrono::steady_clock::now();
  const Volume v = segment_volume(stack_source(dir / "ph/slices"), table, phantom_segment_options(p), &m);
  std::printf("  segment %.3f s\n", std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  std::map<std::string, std::int64_t> tv;
  const auto dice = dice_per_tissue(v, truth, &tv);
  for (const auto& [k, d] : dice) std::printf("  %-8s dice %.4f  truth %lld\n", k.c_str(), d, (long long)tv[k]);
  std::printf("  order %lld speck %lld holes %lld islands %lld misplaced %lld detached %lld comps %lld\n", (long long)m.order_changed,
              (long long)m.speck_changed, (long long)m.holes_filled, (long long)m.islands_absorbed, (long long)m.misplaced_absorbed,
              (long long)m.detached_removed, (long long)m.components);
  for (const auto& pr : m.prototypes)
    std::printf("  proto %d table (%.1f %.1f %.1f) -> (%.1f %.1f %.1f) n=%lld\n", pr.label, pr.table_lab[0], pr.table_lab[1],
                pr.table_lab[2], pr.lab[0], pr.lab[1], pr.lab[2], (long long)pr.samples);
  {
    std::int64_t conf[8][8] = {};
    for (std::size_t i = 0; i < v.labels.size(); ++i) ++conf[truth.labels[i]][v.labels[i]];
    for (int a = 0; a < 8; ++a) {
      for (int b = 0; b < 8; ++b) std::printf(" %7lld", (long long)conf[a][b]);
      std::printf("\n");
    }
  }
  expect_dice(dice, tv, table, "jpeg");
}

TEST(SegmentPhantom, PerturbedPrototypesAndIllumination) {
  const PhantomOptions p = test_phantom();
  const Volume truth = phantom_labels(p);
  TissueTable table = phantom_tissue_table();
  // every prototype channel moved by +-10, in a fixed pseudo-random pattern
  std::mt19937 rng(11);
  auto jiggle = [&](std::array<std::uint8_t, 3>& c) {
    for (auto& v : c) v = static_cast<std::uint8_t>(std::clamp(int(v) + (rng() % 2 ? 10 : -10), 0, 255));
  };
  for (auto& c : table.background_rgb) jiggle(c);
  for (auto& t : table.tissues)
    for (auto& c : t.rgb) jiggle(c);
  // a global illumination shift: 12 % darker, warmer, plus a gradient across the slices
  std::vector<RgbImage> slices(static_cast<std::size_t>(p.nz));
  for (int z = 0; z < p.nz; ++z) {
    auto& s = slices[static_cast<std::size_t>(z)];
    s.nx = p.nx, s.ny = p.ny;
    phantom_slice_rgb(p, truth, z, s.rgb);
    for (int y = 0; y < p.ny; ++y)
      for (int x = 0; x < p.nx; ++x)
        for (int c = 0; c < 3; ++c) {
          const double gain = 0.88 * (c == 0 ? 1.04 : c == 2 ? 0.95 : 1.0) * (1 + 0.08 * (x - p.nx / 2) / p.nx) *
                              (1 + 0.05 * std::sin(0.2 * z));
          auto& v = s.rgb[(static_cast<std::size_t>(y) * p.nx + x) * 3 + c];
          v = static_cast<std::uint8_t>(std::clamp(std::lround(v * gain), 0L, 255L));
        }
  }
  SegmentMetrics m;
  const Volume v = segment_volume(memory_source(std::move(slices)), table, phantom_segment_options(p), &m);
  std::map<std::string, std::int64_t> tv;
  const auto dice = dice_per_tissue(v, truth, &tv);
  for (const auto& [k, d] : dice) std::printf("  %-8s dice %.4f\n", k.c_str(), d);
  std::printf("  gain %.3f..%.3f\n", m.gain_min, m.gain_max);
  expect_dice(dice, tv, table, "perturbed");
}
