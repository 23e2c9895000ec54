// orthosim_segment: natural order, stack checks, the clean-up rules on small
// synthetic volumes, determinism and streaming, accuracy against the
// phantom's truth (PNG and JPEG, perturbed prototypes and illumination), the
// real cryosection, and every bad input through the CLI.
#include "libmodel/phantom/phantom.h"
#include "libmodel/segment/segment.h"
#include "tests/libmodel/real_stack.h"
#include "tests/test_util.h"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <tbb/global_control.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
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

// In CIELAB with lightness weighed 3 (CIELAB's alone: validate refuses a
// weight in RGB).
SegmentOptions phantom_segment_options(const PhantomOptions& p,
                                       SegmentOptions::Space space = SegmentOptions{}.colour_space) {
  SegmentOptions o;
  o.spacing_m = p.spacing_m;
  o.origin_m = phantom_origin(p);
  o.colour_space = space;
  if (space == SegmentOptions::Space::cielab) o.lightness_weight = 3;
  return o;
}

// The Dice goal of tissue t with n true voxels: 0.90 for a vessel, 0.97 for
// a bulk tissue of at least 1000 voxels, none (0) otherwise.
double dice_goal(const Tissue& t, std::int64_t n) {
  if (t.layer == "vessel") return n > 0 ? 0.90 : 0.0;
  return n >= 1000 ? 0.97 : 0.0;
}

// The tissues of `table` whose Dice misses its goal.
std::vector<std::string> missed_goals(const std::map<std::string, double>& dice,
                                      const std::map<std::string, std::int64_t>& truth_voxels, const TissueTable& table) {
  std::vector<std::string> missed;
  for (const auto& t : table.tissues) {
    const auto n = truth_voxels.count(t.name) ? truth_voxels.at(t.name) : 0;
    const double d = dice.count(t.name) ? dice.at(t.name) : 0.0;
    if (d < dice_goal(t, n)) missed.push_back(t.name);
  }
  return missed;
}

void expect_dice(const std::map<std::string, double>& dice, const std::map<std::string, std::int64_t>& truth_voxels,
                 const TissueTable& table, const std::string& what) {
  for (const auto& t : table.tissues) {
    const auto n = truth_voxels.count(t.name) ? truth_voxels.at(t.name) : 0;
    const double d = dice.count(t.name) ? dice.at(t.name) : 0.0;
    EXPECT_GE(d, dice_goal(t, n)) << what << ": " << t.name << " (" << n << " voxels)";
  }
}

// The phantom's table with every prototype channel moved by +-10, in a
// fixed pseudo-random pattern.
TissueTable jiggled_phantom_table() {
  TissueTable table = phantom_tissue_table();
  std::mt19937 rng(11);
  auto jiggle = [&](std::array<std::uint8_t, 3>& c) {
    for (auto& v : c) v = static_cast<std::uint8_t>(std::clamp(int(v) + (rng() % 2 ? 10 : -10), 0, 255));
  };
  for (auto& c : table.background_rgb) jiggle(c);
  for (auto& t : table.tissues)
    for (auto& c : t.rgb) jiggle(c);
  return table;
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

// Segments the phantom `p` (its labels `truth`) with `o`, prints and returns
// the Dice per tissue; `tv` receives the true voxel counts, `m` the metrics.
std::map<std::string, double> segment_dice(const PhantomOptions& p, const Volume& truth, const SegmentOptions& o,
                                           const std::string& what, std::map<std::string, std::int64_t>* tv,
                                           SegmentMetrics* m) {
  const Volume v = segment_volume(phantom_source(p, truth), phantom_tissue_table(), o, m);
  const auto dice = dice_per_tissue(v, truth, tv);
  for (const auto& [k, d] : dice) std::printf("  %s: %-8s dice %.4f\n", what.c_str(), k.c_str(), d);
  return dice;
}

// Sensor noise sigma 12 (8-bit units, three times the sample's): plain
// k-means calibration let the vein's prototype (0.3 % of the voxels) run
// off into the noise tail of the blue gel next to it in colour, and the
// vein then took the whole gel (and the order clean-up the body): Dice 0
// for every bulk tissue. The calibration's 3 x 3 medians and its mixture
// weights keep every prototype on its tissue (docs/segment.md).
TEST(SegmentPhantom, HighNoiseKeepsRareTissues) {
  using Space = SegmentOptions::Space;
  // the default space, and CIELAB with and without a lightness weight (CIELAB's alone)
  const std::vector<std::pair<Space, double>> variants{
      {SegmentOptions{}.colour_space, 1.0}, {Space::cielab, 1.0}, {Space::cielab, 3.0}};
  for (const unsigned seed : {3u, 7u}) {
    for (const auto& [space, lw] : variants) {
      PhantomOptions p = test_phantom();
      p.noise_sigma = 12;
      p.seed = seed;
      const Volume truth = phantom_labels(p);
      const TissueTable table = phantom_tissue_table();
      SegmentOptions o = phantom_segment_options(p);
      o.colour_space = space;
      o.lightness_weight = lw;
      SegmentMetrics m;
      std::map<std::string, std::int64_t> tv;
      const std::string what = "noise 12, seed " + std::to_string(seed) + ", " + to_string(space) +
                               ", lightness weight " + std::to_string(lw);
      const auto dice = segment_dice(p, truth, o, what, &tv, &m);
      expect_dice(dice, tv, table, what);
      for (const auto& pr : m.prototypes) {
        const double shift = std::hypot(pr.lab[0] - pr.table_lab[0], pr.lab[1] - pr.table_lab[1], pr.lab[2] - pr.table_lab[2]);
        EXPECT_LT(shift, 10) << what << ": prototype of label " << pr.label;  // the table is the phantom's own colours
      }
    }
  }
}

// Sensor noise sigma 20: the blue gel's chroma then spreads twice as wide in
// CIELAB as its lightness. With one shared variance in the calibration the
// vein's prototype ran 20 units off into the gel's chroma tail and took
// most of the gel, and the order clean-up then the body (skin Dice 0.39,
// bone 0.13, exit 0); a full shared covariance keeps it on the vein. Then
// the Mahalanobis rule, which counts distances in that spread, keeps the
// gel's noisy pixels out of the vein (vein Dice 0.63-0.68 by the nearest
// colour, 0.95-0.97 by Mahalanobis on the 96 x 96 x 48 phantoms of seeds 1
// and 3). The bulk tissues' goal is lower than at low noise: the skin, a
// rim a few voxels thick, loses its boundary voxels to the noise.
TEST(SegmentPhantom, VeryHighNoiseDoesNotCollapse) {
  for (const unsigned seed : {1u, 3u}) {
    PhantomOptions p = test_phantom();
    p.noise_sigma = 20;
    p.seed = seed;
    const Volume truth = phantom_labels(p);
    const TissueTable table = phantom_tissue_table();
    for (const auto rule : {SegmentOptions::Classify::nearest, SegmentOptions::Classify::mahalanobis}) {
      SegmentOptions o = phantom_segment_options(p);
      o.classify = rule;
      SegmentMetrics m;
      std::map<std::string, std::int64_t> tv;
      const std::string what = std::string("noise 20, seed ") + std::to_string(seed) + ", " + to_string(rule);
      const auto dice = segment_dice(p, truth, o, what, &tv, &m);
      for (const auto& pr : m.prototypes) {
        const double shift = std::hypot(pr.lab[0] - pr.table_lab[0], pr.lab[1] - pr.table_lab[1], pr.lab[2] - pr.table_lab[2]);
        EXPECT_LT(shift, 15) << what << ": prototype of label " << pr.label;  // the table is the phantom's own colours
      }
      for (const auto& t : table.tissues) {
        if (tv[t.name] < 1000 && t.layer != "vessel") continue;
        const double d = dice.count(t.name) ? dice.at(t.name) : 0.0;
        if (rule == SegmentOptions::Classify::mahalanobis)
          EXPECT_GE(d, t.layer == "vessel" ? 0.90 : 0.85) << what << ": " << t.name;
        else
          EXPECT_GE(d, 0.5) << what << ": " << t.name;  // no collapse
      }
    }
  }
}

// The background normalisation stays unbiased under strong noise. Its
// per-slice fit took single pixels where the reference took 3 x 3 medians, a
// trimmed mean where the reference took a median, and picked the background by
// the calibrated rule where the reference used the table's colours. Each pick
// cuts a noisy gel's distribution on the side of its neighbours, differently,
// and at 8-bit noise 32 the fitted gains came out 1.03-1.09 where the
// illumination's are 0.975-1.02: every colour was moved by them, the
// prototypes by 9-19 units, the vein's took the gel, and the segmentation
// collapsed (vein Dice 0.01, skin 0.56 on 128 x 128 x 48, seed 2). Now the two
// pick and estimate alike. The gains at noise 0 are the illumination's; the
// fits at noise 32 and 48 must find them.
TEST(SegmentPhantom, TheBackgroundGainIsUnbiasedUnderNoise) {
  for (const unsigned seed : {2u, 3u}) {
    PhantomOptions p = test_phantom();
    p.seed = seed;
    p.noise_sigma = 0;
    const Volume truth = phantom_labels(p);
    SegmentMetrics quiet;
    segment_dice(p, truth, phantom_segment_options(p), "noise 0, seed " + std::to_string(seed), nullptr, &quiet);
    ASSERT_LT(quiet.gain_min, 0.99);  // the phantom's illumination varies: there is something to find
    ASSERT_GT(quiet.gain_max, 1.01);
    for (const double noise : {32.0, 48.0}) {
      p.noise_sigma = noise;
      const std::string what = "noise " + std::to_string(int(noise)) + ", seed " + std::to_string(seed);
      SegmentMetrics m;
      std::map<std::string, std::int64_t> tv;
      const auto dice = segment_dice(p, truth, phantom_segment_options(p), what, &tv, &m);
      EXPECT_NEAR(m.gain_min, quiet.gain_min, 0.01) << what;
      EXPECT_NEAR(m.gain_max, quiet.gain_max, 0.01) << what;
      if (noise > 32) continue;  // at 48 the gain alone is asked for
      for (const auto& pr : m.prototypes) {
        const double shift = std::hypot(pr.lab[0] - pr.table_lab[0], pr.lab[1] - pr.table_lab[1], pr.lab[2] - pr.table_lab[2]);
        EXPECT_LT(shift, 8) << what << ": prototype of label " << pr.label;  // the table is the phantom's own colours
      }
      for (const auto& [name, d] : dice) EXPECT_GE(d, 0.9) << what << ": " << name;
    }
  }
}

// The colour space (SegmentOptions::colour_space). The calibration fits one
// covariance shared by every tissue; sensor noise is the same for every
// colour in RGB, but in CIELAB it spreads differently for each colour (the
// blue gel's a third wider than the bone's: scripts/lab_noise_spread.py), so
// no one covariance fits them. At 8-bit noise 64 on 128 x 128 x 48 stacks the CIELAB fit moved the vein's prototype 13 units
// into the blue gel; it took 13 % of the samples (the truth: 0.3 %) and the
// gel's noisy pixels. Here (seeds 2 and 3) the worst tissue by CIELAB was
// the skin at 0.42 and the vein at 0.03; in RGB the skin, a rim a few voxels
// thick, is the worst at 0.58 and 0.50, and the vein is at 0.92 and 0.90.
// The CIELAB runs are there to show the space is what does it.
TEST(SegmentPhantom, TheRgbCalibrationHoldsAtNoise64) {
  for (const unsigned seed : {2u, 3u}) {
    PhantomOptions p;
    p.nx = 128, p.ny = 128, p.nz = 48;
    p.spacing_m = {0.45e-3, 0.45e-3, 1.5e-3};
    p.noise_sigma = 64;
    p.seed = seed;
    const Volume truth = phantom_labels(p);
    const std::string what = "noise 64, seed " + std::to_string(seed);
    std::map<std::string, std::int64_t> tv;
    SegmentOptions o = phantom_segment_options(p);
    ASSERT_EQ(o.colour_space, SegmentOptions::Space::rgb);  // the default
    SegmentMetrics m;
    auto worst = [](const std::map<std::string, double>& dice) {
      double w = 1;
      for (const auto& [name, d] : dice) w = std::min(w, d);
      return w;
    };
    const auto rgb = segment_dice(p, truth, o, what + ", rgb", &tv, &m);
    for (const auto& [name, d] : rgb) EXPECT_GE(d, 0.45) << what << ", rgb: " << name;
    EXPECT_GE(rgb.at("vein"), 0.85) << what << ", rgb";
    int vein_label = -1;
    for (const auto& t : phantom_tissue_table().tissues)
      if (t.name == "vein") vein_label = t.label;
    ASSERT_GT(vein_label, 0);
    std::int64_t all = 0, vein = 0;
    for (const auto& pr : m.prototypes) all += pr.samples, vein += pr.label == vein_label ? pr.samples : 0;
    EXPECT_LT(static_cast<double>(vein) / static_cast<double>(all), 0.06) << what << ", rgb: the vein's share";
    o.colour_space = SegmentOptions::Space::cielab;
    o.lightness_weight = 3;  // (as phantom_segment_options gives CIELAB)
    const auto lab = segment_dice(p, truth, o, what + ", cielab", &tv, &m);
    EXPECT_GT(worst(rgb), worst(lab) + 0.1) << what;
  }
}

// The lightness weight is CIELAB's: the library refuses it in RGB, where it
// would be ignored without a word (the CLI said so since cf90b69; the library
// took it silently).
TEST(SegmentOptionsCheck, ALightnessWeightIsRefusedOutsideCielab) {
  SegmentOptions o;
  o.spacing_m = {1e-3, 1e-3, 1e-3};
  o.colour_space = SegmentOptions::Space::rgb;
  EXPECT_NO_THROW(validate(o));
  o.lightness_weight = 2;
  try {
    validate(o);
    ADD_FAILURE() << "a lightness weight in RGB was taken";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("lightness-weight: weighs CIELAB's lightness"), std::string::npos) << e.what();
  }
  o.colour_space = SegmentOptions::Space::cielab;
  EXPECT_NO_THROW(validate(o));
}

// The smoothness prior (SegmentOptions::smoothness, docs/segment.md): at
// 8-bit noise 28, seven times the sample's, the per-voxel rule lost a third
// of the skin and most of the vein (worst tissue 0.59-0.68 on 96 x 96 x 48
// phantoms); with the prior every tissue meets the goals of the low-noise
// phantom (expect_dice: 0.97 bulk, 0.90 vessels). The per-voxel rule's run is
// there to show the prior is what does it. (Those figures were the CIELAB
// calibration's; in RGB, 2026-11-29, the per-voxel rule's worst tissue is
// 0.87-0.91, the artery and the skin, still short of the goals.)
TEST(SegmentPhantom, TheSmoothnessPriorHoldsTheGoalsAtNoise28) {
  for (const unsigned seed : {1u, 3u}) {
    PhantomOptions p = test_phantom();
    p.noise_sigma = 28;
    p.seed = seed;
    const Volume truth = phantom_labels(p);
    const TissueTable table = phantom_tissue_table();
    SegmentOptions o = phantom_segment_options(p);
    std::map<std::string, std::int64_t> tv;
    SegmentMetrics m;
    const std::string what = "noise 28, seed " + std::to_string(seed);
    expect_dice(segment_dice(p, truth, o, what + ", prior", &tv, &m), tv, table, what + ", prior");
    EXPECT_GT(m.smooth_changed, 0);
    o.smoothness = 0;
    const auto plain = segment_dice(p, truth, o, what + ", per voxel", &tv, &m);
    EXPECT_FALSE(missed_goals(plain, tv, table).empty()) << what << ": the per-voxel rule meets every goal";
    EXPECT_EQ(m.smooth_changed, 0);
  }
}

// The calibration fits 3 x 3 medians, but classification scores single
// pixels, and CIELAB is not linear in RGB: under strong noise the mean colour
// of a tissue's pixels lies off its medians' mean (on the phantom, with its
// texture, by several CIE76 units), and the per-voxel rule scored the pixels
// against the medians' colours. Now against pixel_lab, the medians' colour
// moved by the samples' mean (pixel - median). The per-voxel rule's skin, a
// rim a few voxels thick and the first tissue the noise takes, at noise 24
// (seeds 1 / 3): 0.91 / 0.89, against 0.86 / 0.85 with the pixels' covariance
// but the medians' colours (measured with the shift switched off by hand).
TEST(SegmentCalibration, PixelsAreScoredAgainstTheirOwnMeanColour) {
  for (const unsigned seed : {1u, 3u}) {
    PhantomOptions p = test_phantom();
    p.noise_sigma = 24;
    p.seed = seed;
    const Volume truth = phantom_labels(p);
    SegmentOptions o = phantom_segment_options(p);
    o.smoothness = 0;
    std::map<std::string, std::int64_t> tv;
    SegmentMetrics m;
    const std::string what = "noise 24, seed " + std::to_string(seed) + ", per voxel";
    const auto dice = segment_dice(p, truth, o, what, &tv, &m);
    EXPECT_GE(dice.at("skin"), 0.88) << what;
    for (const auto& pr : m.prototypes) {
      const double moved = std::hypot(pr.pixel_lab[0] - pr.lab[0], pr.pixel_lab[1] - pr.lab[1], pr.pixel_lab[2] - pr.lab[2]);
      EXPECT_LT(moved, 15) << what << ": label " << pr.label;  // a correction, not a new colour
    }
  }
}

// A vessel runs inside the body. Blue gel next to pink skin, partly in one
// voxel, has the colour of a vein, and at high noise such voxels formed
// pieces of "vein" of 66-246 voxels on the skin's outside (45 of them on a
// 160 x 160 x 64 phantom at noise 28), which the surfaces took for parts of
// every nested tissue (fat and muscle came out with 3 components) and
// remesh refused. A vessel's piece that meets the embedding medium on more
// faces than the body is now out of place and goes to the medium; the
// vessel inside stays whole.
TEST(SegmentCleanup, AVesselPieceOnTheSkinsOutsideIsNotAVessel) {
  const TissueTable table = small_table();
  const int nx = 64, ny = 64, nz = 12;
  const double c = 0.5 * (nx - 1), R = 0.4 * std::min(nx, ny);
  auto label = [&](int x, int y, int z) {
    if (std::hypot(x - c, y - c) < 2.5) return 6;  // the artery, in the marrow's middle: inside
    // a piece of artery outside the skin, on it (4 x 4 x 6 voxels)
    if (z >= 3 && z < 9 && y >= c - 2 && y < c + 2 && x >= c + R + 1 && x < c + R + 5) return 6;
    return limb(x, y, z, nx, ny);
  };
  std::int64_t inside = 0, outside = 0;
  for (int z = 0; z < nz; ++z)
    for (int y = 0; y < ny; ++y)
      for (int x = 0; x < nx; ++x)
        if (label(x, y, z) == 6) (std::hypot(x - c, y - c) < R ? inside : outside) += 1;
  ASSERT_EQ(outside, 96);
  SegmentMetrics m;
  const Volume v = segment_volume(memory_source(paint(table, nx, ny, nz, label, 0)), table, iso_options(), &m);
  std::int64_t kept_inside = 0, kept_outside = 0;
  for (int z = 0; z < nz; ++z)
    for (int y = 0; y < ny; ++y)
      for (int x = 0; x < nx; ++x)
        if (v.labels[v.index(x, y, z)] == 6) (std::hypot(x - c, y - c) < R ? kept_inside : kept_outside) += 1;
  EXPECT_EQ(kept_inside, inside);
  EXPECT_EQ(kept_outside, 0);
}

// The calibration's sanity check: a prototype whose calibrated colour lies
// nearer another tissue's table colour than its own is named (the CLI warns).
// The numbers are the vein's at 8-bit noise 20 under the old single-variance
// calibration: it moved 19.6 units, to 19.5 from the gel's table colour.
TEST(SegmentCalibration, NearestTableColourNamesACapturedPrototype) {
  std::vector<Prototype> p(3);
  p[0].label = 0, p[0].table_lab = {40.5, 3.2, -26.1}, p[0].lab = {39.6, 6.4, -28.2};  // gel
  p[1].label = 3, p[1].table_lab = {31.9, 39.7, 25.0}, p[1].lab = {32.9, 41.9, 24.5};  // muscle
  p[2].label = 7, p[2].table_lab = {23.0, 33.3, -37.7}, p[2].lab = {35.5, 18.2, -37.6};  // vein, captured
  EXPECT_EQ(nearest_table_labels(p), (std::vector<int>{0, 3, 0}));
  p[2].lab = {25.0, 30.0, -37.0};  // moved a little: its own
  EXPECT_EQ(nearest_table_labels(p), (std::vector<int>{0, 3, 7}));
  p[2].lab = p[2].table_lab;  // unmoved
  EXPECT_EQ(nearest_table_labels(p)[2], 7);
}

// The phantom's slices under an illumination: each channel c of pixel (x, y)
// of slice z multiplied by light(x, y, z, c), rounded and clamped to 0..255.
std::vector<RgbImage> lit_slices(const PhantomOptions& p, const Volume& truth,
                                 const std::function<double(int, int, int, int)>& light) {
  std::vector<RgbImage> slices(static_cast<std::size_t>(p.nz));
  for (int z = 0; z < p.nz; ++z) {
    auto& s = slices[static_cast<std::size_t>(z)];
    s.nx = p.nx, s.ny = p.ny;
    phantom_slice_rgb(p, truth, z, s.rgb);
    for (int y = 0; y < p.ny; ++y)
      for (int x = 0; x < p.nx; ++x)
        for (int c = 0; c < 3; ++c) {
          auto& v = s.rgb[(static_cast<std::size_t>(y) * p.nx + x) * 3 + c];
          v = static_cast<std::uint8_t>(std::clamp(std::lround(v * light(x, y, z, c)), 0L, 255L));
        }
  }
  return slices;
}

TEST(SegmentPhantom, PerturbedPrototypesAndIllumination) {
  const PhantomOptions p = test_phantom();
  const Volume truth = phantom_labels(p);
  const TissueTable table = jiggled_phantom_table();
  // a global illumination shift: 12 % darker, warmer, plus a gradient across the slices
  std::vector<RgbImage> slices = lit_slices(p, truth, [&](int x, int, int z, int c) {
    return 0.88 * (c == 0 ? 1.04 : c == 2 ? 0.95 : 1.0) * (1 + 0.08 * (x - p.nx / 2) / p.nx) * (1 + 0.05 * std::sin(0.2 * z));
  });
  SegmentMetrics m;
  const Volume v = segment_volume(memory_source(std::move(slices)), table, phantom_segment_options(p), &m);
  std::map<std::string, std::int64_t> tv;
  const auto dice = dice_per_tissue(v, truth, &tv);
  for (const auto& [k, d] : dice) std::printf("  %-8s dice %.4f\n", k.c_str(), d);
  std::printf("  gain %.3f..%.3f\n", m.gain_min, m.gain_max);
  expect_dice(dice, tv, table, "perturbed");
}

// refine_max_shift bounds a prototype's move in CIE76 units in either space:
// in CIELAB the move is cut back along its line, in RGB (not linear in
// CIELAB) by bisection along it. With every table colour 10 off per channel
// and a bound of 3 units, each prototype ends within 3 units of its table
// colour and some end on the bound; without the bound they move 1.7-12.7
// units.
TEST(SegmentCalibration, TheLargestMoveIsHeldInEitherSpace) {
  const PhantomOptions p = test_phantom();
  const Volume truth = phantom_labels(p);
  const TissueTable table = jiggled_phantom_table();
  for (const auto space : {SegmentOptions::Space::rgb, SegmentOptions::Space::cielab}) {
    auto shifts = [&](double bound) {
      SegmentOptions o = phantom_segment_options(p, space);
      o.refine_max_shift = bound;
      SegmentMetrics m;
      segment_volume(phantom_source(p, truth), table, o, &m);
      std::vector<double> s;
      for (const auto& pr : m.prototypes)
        s.push_back(std::hypot(pr.lab[0] - pr.table_lab[0], pr.lab[1] - pr.table_lab[1], pr.lab[2] - pr.table_lab[2]));
      return s;
    };
    const std::vector<double> free = shifts(1e9), held = shifts(3);
    ASSERT_EQ(free.size(), held.size());
    std::printf("  %s: moves %.1f..%.1f free, up to %.3f held\n", to_string(space),
                *std::min_element(free.begin(), free.end()), *std::max_element(free.begin(), free.end()),
                *std::max_element(held.begin(), held.end()));
    int on_bound = 0;
    for (std::size_t k = 0; k < held.size(); ++k) {
      EXPECT_LE(held[k], 3 + 1e-6) << to_string(space) << ": prototype " << k;
      on_bound += held[k] > 2.9;
    }
    EXPECT_GT(*std::max_element(free.begin(), free.end()), 5) << to_string(space) << ": the bound must bind";
    EXPECT_GT(on_bound, 0) << to_string(space);
  }
}

// The whole stack exposed darker or brighter than the table's slices (a
// camera's gain): the calibration moves a prototype at most refine_max_shift,
// so at 0.65 of the phantom's brightness fat, bone, marrow and the vessels
// were lost, exit 0 (0.70 was fine: a cliff; a helper's sweep found it). With
// exposure_from_border the slices' border, the gel, gives the exposure. Also
// 0.5 and 1.3 (where the skin turned to bone). Off by default: a vignetted
// stack (below) has a dark border over a well-exposed specimen.
TEST(SegmentPhantom, TheStacksExposureComesFromTheGel) {
  PhantomOptions p = test_phantom();
  p.nz = 16;
  const Volume truth = phantom_labels(p);
  const TissueTable table = phantom_tissue_table();
  for (const double gain : {0.5, 0.65, 1.3}) {
    std::vector<RgbImage> slices = lit_slices(p, truth, [&](int, int, int, int) { return gain; });
    SegmentMetrics m;
    SegmentOptions o = phantom_segment_options(p);
    o.exposure_from_border = true;
    const Volume v = segment_volume(memory_source(std::move(slices)), table, o, &m);
    std::map<std::string, std::int64_t> tv;
    const auto dice = dice_per_tissue(v, truth, &tv);
    const std::string what = "gain " + std::to_string(gain);
    for (const auto& [k, d] : dice) std::printf("  %s: %-8s dice %.4f\n", what.c_str(), k.c_str(), d);
    std::printf("  %s: exposure %.3f %.3f %.3f\n", what.c_str(), m.exposure[0], m.exposure[1], m.exposure[2]);
    expect_dice(dice, tv, table, what);
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(m.exposure[static_cast<std::size_t>(k)], gain, 0.05 * gain) << what;
  }
  // the sample's own exposure: nothing scaled
  SegmentMetrics m;
  SegmentOptions o = phantom_segment_options(p);
  o.exposure_from_border = true;
  segment_volume(phantom_source(p, truth), table, o, &m);
  EXPECT_EQ(m.exposure, (std::array<double, 3>{1, 1, 1}));
  // vignetted (the corners at 0.4 of the centre): a dark border over a
  // well-exposed specimen. With the option on, the border says 0.64 and the
  // muscle is labelled artery; by default (off) every tissue is right
  {
    const double r2max = 0.25 * (p.nx * p.nx + p.ny * p.ny);
    std::vector<RgbImage> slices = lit_slices(p, truth, [&](int x, int y, int, int) {
      const double dx = x - 0.5 * p.nx, dy = y - 0.5 * p.ny;
      return 1 - 0.6 * (dx * dx + dy * dy) / r2max;
    });
    SegmentMetrics mv;
    const Volume v = segment_volume(memory_source(std::move(slices)), table, phantom_segment_options(p), &mv);
    std::map<std::string, std::int64_t> tv;
    const auto dice = dice_per_tissue(v, truth, &tv);
    for (const auto& [k, d] : dice) std::printf("  vignette: %-8s dice %.4f\n", k.c_str(), d);
    expect_dice(dice, tv, table, "vignette");
    EXPECT_EQ(mv.exposure, (std::array<double, 3>{1, 1, 1}));
  }
}

// A coarse stack (1.2 x 1.2 x 5 mm voxels, 7.2 mm^3 each): the island rule of
// 64 voxels deleted pieces of marrow of 54 and 59 voxels, 390 mm^3 each
// (marrow Dice 0.80, bone 0.93, no noise at all). Islands go by size only
// below min_island_mm3 too.
TEST(SegmentPhantom, CoarseStacksKeepAnatomyTheIslandRuleWouldDelete) {
  PhantomOptions p;
  p.nx = 64, p.ny = 64, p.nz = 16;
  p.spacing_m = {1.2e-3, 1.2e-3, 5e-3};
  p.noise_sigma = 0;
  p.seed = 5;
  const Volume truth = phantom_labels(p);
  std::map<std::string, std::int64_t> tv;
  const auto dice = segment_dice(p, truth, phantom_segment_options(p), "coarse", &tv, nullptr);
  for (const char* t : {"skin", "fat", "muscle", "bone", "marrow"}) {
    ASSERT_GT(tv[t], 0) << t;
    EXPECT_GE(dice.at(t), 0.97) << t;
  }
}

// ---- the real cryosection --------------------------------------------------------------
//
// data-samples/real/vhp-f-1432a-arm.png: a 300 x 410 crop of the left upper arm
// of the Visible Human female slice avf1432a (0.33 mm pixels; README.md there),
// with a tissue table whose prototypes are medians of hand-picked patches of
// the crop. There is no ground truth: the test checks plausibility (fractions,
// contiguity, nesting, gel around the arm). Set ORTHOSIM_SEGMENT_OVERLAY=FILE
// to also write the labels coloured over the crop (docs/img/segment-real.png).

namespace {

// 4-connected components of the pixels of `mask` (ny x nx): sizes, largest first.
// Sizes of the 4-connected components of `mask`, largest first; `left`
// (optional) receives the size of those touching the left image edge (x = 0)
// other than the largest.
std::vector<std::int64_t> component_sizes(const std::vector<char>& mask, int nx, int ny,
                                          std::int64_t* left = nullptr) {
  std::vector<char> seen(mask.size(), 0);
  std::vector<std::int64_t> sizes;
  std::vector<std::int64_t> at_left;
  std::vector<int> todo;
  for (int start = 0; start < nx * ny; ++start) {
    if (!mask[start] || seen[start]) continue;
    std::int64_t n = 0;
    bool touches = false;
    seen[start] = 1;
    todo.assign(1, start);
    while (!todo.empty()) {
      const int i = todo.back();
      todo.pop_back();
      ++n;
      const int x = i % nx, y = i / nx;
      touches |= x == 0;
      const int nb[4] = {x > 0 ? i - 1 : -1, x + 1 < nx ? i + 1 : -1, y > 0 ? i - nx : -1, y + 1 < ny ? i + nx : -1};
      for (int j : nb)
        if (j >= 0 && mask[j] && !seen[j]) seen[j] = 1, todo.push_back(j);
    }
    sizes.push_back(n);
    if (touches) at_left.push_back(n);
  }
  std::sort(sizes.rbegin(), sizes.rend());
  if (left) {
    *left = 0;
    for (auto a : at_left) *left += a;
    if (std::find(at_left.begin(), at_left.end(), sizes[0]) != at_left.end()) *left -= sizes[0];
  }
  return sizes;
}

// Pixels reachable from the image border through pixels where `pass` is set
// (4-connected): what is not reached is enclosed by the other pixels.
std::vector<char> reached_from_border(const std::vector<char>& pass, int nx, int ny) {
  std::vector<char> seen(pass.size(), 0);
  std::vector<int> todo;
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x)
      if ((x == 0 || y == 0 || x == nx - 1 || y == ny - 1) && pass[y * nx + x]) seen[y * nx + x] = 1, todo.push_back(y * nx + x);
  while (!todo.empty()) {
    const int i = todo.back();
    todo.pop_back();
    const int x = i % nx, y = i / nx;
    const int nb[4] = {x > 0 ? i - 1 : -1, x + 1 < nx ? i + 1 : -1, y > 0 ? i - nx : -1, y + 1 < ny ? i + nx : -1};
    for (int j : nb)
      if (j >= 0 && pass[j] && !seen[j]) seen[j] = 1, todo.push_back(j);
  }
  return seen;
}

// The image and, right of it, the labels of one slice coloured over it: a
// 50 % tint inside each tissue and its boundary in full colour (gel blue,
// skin magenta, fat yellow, muscle red, bone white, marrow green).
RgbImage overlay(const RgbImage& image, const std::uint8_t* labels) {
  static const std::uint8_t colour[6][3] = {
      {40, 90, 255}, {255, 0, 255}, {255, 220, 0}, {255, 40, 40}, {255, 255, 255}, {0, 230, 120}};
  const int nx = image.nx, ny = image.ny, gap = 8;
  RgbImage out;
  out.nx = 2 * nx + gap;
  out.ny = ny;
  out.rgb.assign(static_cast<std::size_t>(out.nx) * ny * 3, 255);
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x) {
      const int i = y * nx + x, l = std::min<int>(labels[i], 5);
      const bool edge = (x > 0 && labels[i - 1] != labels[i]) || (y > 0 && labels[i - nx] != labels[i]);
      for (int c = 0; c < 3; ++c) {
        const std::uint8_t v = image.rgb[static_cast<std::size_t>(i) * 3 + c];
        const std::size_t row = static_cast<std::size_t>(y) * out.nx;
        out.rgb[(row + x) * 3 + c] = v;
        out.rgb[(row + nx + gap + x) * 3 + c] = edge ? colour[l][c] : static_cast<std::uint8_t>((v + colour[l][c] + 1) / 2);
      }
    }
  return out;
}

}  // namespace

TEST(SegmentReal, ArmCropIsPlausible) {
  const std::string dir = std::string(ORTHOSIM_SOURCE_DIR) + "/data-samples/real";
  const TissueTable table = load_tissue_table(dir + "/tissues.json");
  const std::string crop = dir + "/vhp-f-1432a-arm.png";
  // a stack folder of five copies of the crop (the clean-up is 3-D)
  test::TempDir stack("segreal");
  for (char z = '0'; z < '5'; ++z) fs::copy_file(crop, stack.path / (std::string("s") + z + ".png"));
  SegmentOptions o;
  o.spacing_m = {0.33e-3, 0.33e-3, 0.33e-3};
  SegmentMetrics m;
  const Volume v = segment_volume(stack_source(stack.path.string()), table, o, &m);
  ASSERT_EQ(v.nx, 300);
  ASSERT_EQ(v.ny, 410);
  ASSERT_EQ(v.nz, 5);
  const int nx = v.nx, ny = v.ny, n = nx * ny;
  const std::uint8_t* mid = v.labels.data() + v.index(0, 0, 2);
  if (const char* path = std::getenv("ORTHOSIM_SEGMENT_OVERLAY")) write_png(path, overlay(read_slice(crop), mid));
  // identical slices give identical labels
  for (int z = 0; z < v.nz; ++z)
    EXPECT_TRUE(std::equal(mid, mid + n, v.labels.data() + v.index(0, 0, z))) << "slice " << z;

  const int bg = 0, skin = v.label_of("skin"), fat = v.label_of("fat"), muscle = v.label_of("muscle"),
            bone = v.label_of("bone"), marrow = v.label_of("marrow");
  ASSERT_TRUE(skin > 0 && fat > 0 && muscle > 0 && bone > 0 && marrow > 0);
  std::array<std::int64_t, 256> count{};
  for (int i = 0; i < n; ++i) ++count[mid[i]];
  auto frac = [&](int l) { return static_cast<double>(count[static_cast<std::size_t>(l)]) / n; };
  std::printf("  fractions: gel %.3f skin %.3f fat %.3f muscle %.3f bone %.3f marrow %.3f\n", frac(bg), frac(skin),
              frac(fat), frac(muscle), frac(bone), frac(marrow));
  for (const auto& pr : m.prototypes)
    std::printf("  proto %d table (%.1f %.1f %.1f) -> (%.1f %.1f %.1f) n=%lld\n", pr.label, pr.table_lab[0],
                pr.table_lab[1], pr.table_lab[2], pr.lab[0], pr.lab[1], pr.lab[2], (long long)pr.samples);
  std::printf("  order %lld speck %lld holes %lld islands %lld misplaced %lld detached %lld body %lld\n",
              (long long)m.order_changed, (long long)m.speck_changed, (long long)m.holes_filled,
              (long long)m.islands_absorbed, (long long)m.misplaced_absorbed, (long long)m.detached_removed,
              (long long)m.body_components);

  auto mask_of = [&](std::initializer_list<int> ls) {
    std::vector<char> mk(static_cast<std::size_t>(n), 0);
    for (int i = 0; i < n; ++i)
      for (int l : ls) mk[static_cast<std::size_t>(i)] |= mid[i] == l;
    return mk;
  };

  // fractions of the crop, against a visual estimate (README.md there): gel
  // in the corners and a band around the arm ~ 1/5 .. 1/4; subcutaneous fat
  // (with the strip of the torso on the left edge) ~ 2/5 .. 1/2; the two
  // muscle groups ~ 1/4; the humerus cortex, a ring ~ 60 px across and ~ 10 px
  // thick, ~ 1.5 %; the marrow, ~ 30 x 25 px, ~ 0.6 %; the skin, a rim 3 to 8 px
  // thick around ~ 1000 px of outline, 1 .. 5 %, partly taken as fat (the
  // rim's colour is between the gel's and the fat's).
  EXPECT_GT(frac(bg), 0.15);
  EXPECT_LT(frac(bg), 0.32);
  EXPECT_GT(frac(fat), 0.33);
  EXPECT_LT(frac(fat), 0.58);
  EXPECT_GT(frac(muscle), 0.18);
  EXPECT_LT(frac(muscle), 0.33);
  EXPECT_GT(frac(bone), 0.008);
  EXPECT_LT(frac(bone), 0.04);
  EXPECT_GT(frac(marrow), 0.003);
  EXPECT_LT(frac(marrow), 0.015);
  EXPECT_GT(frac(skin), 0.003);
  EXPECT_LT(frac(skin), 0.06);

  // contiguity: the largest 2-D component of each bulk tissue holds most of
  // it (fat, muscle, marrow); the bone's largest is the cortex ring, besides
  // it a few pale patches of fat or fascia at the muscle's border; the skin
  // rim is found in pieces, so it gets no bound. The torso's strip on the
  // left edge is another body: where the arm's skin is found between them,
  // its fat is a component of its own and is not counted against the arm's.
  std::map<int, double> largest;
  for (int l : {fat, muscle, bone, marrow, skin}) {
    std::int64_t torso = 0;
    const auto sizes = component_sizes(mask_of({l}), nx, ny, l == fat ? &torso : nullptr);
    ASSERT_FALSE(sizes.empty()) << v.label_names[static_cast<std::size_t>(l)];
    largest[l] = static_cast<double>(sizes[0]) / static_cast<double>(count[static_cast<std::size_t>(l)] - torso);
    std::printf("  %-7s components %zu, largest holds %.3f\n", v.label_names[static_cast<std::size_t>(l)].c_str(),
                sizes.size(), largest[l]);
  }
  EXPECT_GT(largest[fat], 0.95);
  EXPECT_GT(largest[muscle], 0.95);
  EXPECT_GT(largest[marrow], 0.95);
  EXPECT_GT(largest[bone], 0.5);

  // nesting: the share of `inner` that a flood from the border through every
  // label but `wall` does not reach, i.e. that `wall` encloses
  auto enclosed = [&](std::initializer_list<int> wall, std::initializer_list<int> inner) {
    std::vector<char> pass = mask_of(wall);
    for (auto& p : pass) p = !p;
    const auto reached = reached_from_border(pass, nx, ny);
    std::int64_t in = 0, total = 0;
    for (int i = 0; i < n; ++i)
      for (int l : inner)
        if (mid[i] == l) ++total, in += !reached[static_cast<std::size_t>(i)];
    return total ? static_cast<double>(in) / static_cast<double>(total) : 0.0;
  };
  const double marrow_in_bone = enclosed({bone}, {marrow});
  const double bone_in_muscle = enclosed({muscle}, {bone, marrow});
  const double muscle_in_fat = enclosed({fat}, {muscle, bone, marrow});
  std::printf("  marrow enclosed by bone %.3f, bone+marrow by muscle %.3f, muscle+bone+marrow by fat %.3f\n",
              marrow_in_bone, bone_in_muscle, muscle_in_fat);
  EXPECT_GT(marrow_in_bone, 0.99);
  EXPECT_GT(bone_in_muscle, 0.6);  // the cortex ring and the marrow; not the patches at the muscle's border
  EXPECT_GT(muscle_in_fat, 0.99);

  // gel around the arm: the top and right edges of the crop, and the bottom
  // edge right of x = 60, are gel (the left edge and the bottom-left corner
  // cut through the torso, which touches the arm there)
  std::int64_t edge = 0, edge_gel = 0;
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x)
      if (y == 0 || x == nx - 1 || (y == ny - 1 && x >= 60)) ++edge, edge_gel += mid[y * nx + x] == bg;
  std::printf("  edges around the arm: gel %.3f\n", static_cast<double>(edge_gel) / static_cast<double>(edge));
  EXPECT_GT(static_cast<double>(edge_gel) / static_cast<double>(edge), 0.97);
  // and the arm is one body: nothing of it is detached
  EXPECT_EQ(m.body_components, 1);
}

// The same crop with the dark-shaded fat prototype left out: the shaded fat
// lobules now look like bone (cortex and shaded fat have the same colour) and
// ring the muscle. The anatomical order must not then take the muscle, a
// pocket larger than that ring, for misplaced marrow (it did: muscle 0.1 %,
// marrow 24 % of the crop); bone is overestimated, the muscle stays.
// The whole photograph the sample crop was cut from (a chest slice with both
// arms, the embedding block, its dark frame, a grey scale and a label card):
// segmented whole with the arm's table, its frame came out as muscle around the
// gel and the gel as muscle inside it. A region of interest around the arm is
// segmented exactly as the crop is, and placed where it lies in the slice.
TEST(SegmentReal, TheFullSlicesRegionOfTheArmIsTheCrop) {
  const std::string dir = std::string(ORTHOSIM_SOURCE_DIR) + "/data-samples/real";
  const TissueTable table = load_tissue_table(dir + "/tissues.json");
  test::TempDir full("segreal-full"), crop("segreal-crop");
  for (char z = '0'; z < '3'; ++z) {
    fs::create_symlink(std::string(ORTHOSIM_SHARED_DIR) + "/reference/real/vhp-female-avf1432a.png",
                       full.path / (std::string("s") + z + ".png"));
    fs::create_symlink(dir + "/vhp-f-1432a-arm.png", crop.path / (std::string("s") + z + ".png"));
  }
  SegmentOptions o;
  o.spacing_m = {0.33e-3, 0.33e-3, 0.33e-3};
  o.origin_m = {-1e-3, 2e-3, 5e-3};
  const Volume want = segment_volume(stack_source(crop.path.string()), table, o);
  o.roi_px = {1578, 150, 300, 410};  // the crop's columns and rows (data-samples/real/README.md)
  SegmentMetrics m;
  const Volume got = segment_volume(stack_source(full.path.string()), table, o, &m);
  ASSERT_EQ(got.nx, 300);
  ASSERT_EQ(got.ny, 410);
  ASSERT_EQ(got.nz, 3);
  EXPECT_EQ(m.stack_size, (std::array<int, 3>{2048, 1216, 3}));
  EXPECT_TRUE(got.labels == want.labels) << "the region's labels differ from the crop's";
  EXPECT_NEAR(got.origin_m[0], -1e-3 + 1578 * 0.33e-3, 1e-12);
  EXPECT_NEAR(got.origin_m[1], 2e-3 + 150 * 0.33e-3, 1e-12);
  EXPECT_NEAR(got.origin_m[2], 5e-3, 1e-12);
  // the slice range: the last two slices, from slice 1 on
  o.first_slice = 1;
  const Volume tail = segment_volume(stack_source(full.path.string()), table, o);
  ASSERT_EQ(tail.nz, 2);
  EXPECT_NEAR(tail.origin_m[2], 5e-3 + 0.33e-3, 1e-12);
  // a region beyond the slice: refused, naming the stack
  o.roi_px = {1900, 150, 300, 410};
  try {
    segment_volume(stack_source(full.path.string()), table, o);
    ADD_FAILURE() << "a region beyond the slices was segmented";
  } catch (const Error& e) {
    EXPECT_EQ(e.file(), full.path.string());
    EXPECT_NE(std::string(e.what()).find("reaches beyond the slices, which are 2048 x 1216 px"), std::string::npos)
        << e.what();
  }
}

TEST(SegmentReal, MisplacedOutlineDoesNotSwallowMuscle) {
  const std::string dir = std::string(ORTHOSIM_SOURCE_DIR) + "/data-samples/real";
  TissueTable table = load_tissue_table(dir + "/tissues.json");
  for (auto& t : table.tissues)
    if (t.name == "fat") {
      ASSERT_EQ(t.rgb.size(), 3u);
      t.rgb.pop_back();
    }
  test::TempDir stack("segreal2");
  for (char z = '0'; z < '3'; ++z)
    fs::copy_file(dir + "/vhp-f-1432a-arm.png", stack.path / (std::string("s") + z + ".png"));
  SegmentOptions o;
  o.spacing_m = {0.33e-3, 0.33e-3, 0.33e-3};
  const Volume v = segment_volume(stack_source(stack.path.string()), table, o);
  const std::size_t n = static_cast<std::size_t>(v.nx) * v.ny;
  const std::uint8_t* mid = v.labels.data() + v.index(0, 0, 1);
  auto frac = [&](const char* name) {
    return static_cast<double>(std::count(mid, mid + n, static_cast<std::uint8_t>(v.label_of(name)))) /
           static_cast<double>(n);
  };
  std::printf("  muscle %.3f marrow %.3f bone %.3f fat %.3f\n", frac("muscle"), frac("marrow"), frac("bone"), frac("fat"));
  EXPECT_GT(frac("muscle"), 0.18);
  EXPECT_LT(frac("marrow"), 0.015);
}

// A tissue nested in a vessel tissue (a clot in the artery) is in its place
// against the vessel. The out-of-place rule sets other vessels aside (they
// cross layers), and at first that set aside the clot's own parent too: the
// clot, touching the muscle on a sliver, was out of place and absorbed (all
// of it; a phantom's marrow under a bone made a vessel went the same way).
TEST(SegmentCleanup, ATissueInAVesselStaysInIt) {
  TissueTable table = small_table();
  Tissue clot = table.tissues.back();  // the artery's entry, as a template
  clot.name = "clot", clot.label = 7, clot.rgb = {{60, 20, 90}}, clot.layer = "none", clot.inside = "artery";
  table.tissues.push_back(clot);
  const int nx = 64, ny = 64, nz = 12;
  const double cx = 0.5 * (nx - 1) + 13, cy = 0.5 * (ny - 1);
  auto label = [&](int x, int y, int z) {
    if (std::hypot(x - cx - 2.5, y - cy) < 2.2) return 7;  // reaches past the artery's wall on a sliver
    if (std::hypot(x - cx, y - cy) < 4) return 6;
    return limb(x, y, z, nx, ny);
  };
  std::int64_t painted = 0, beyond = 0;
  for (int y = 0; y < ny; ++y)
    for (int x = 0; x < nx; ++x)
      if (label(x, y, 0) == 7) ++painted, beyond += std::hypot(x - cx, y - cy) >= 4;
  ASSERT_GT(beyond, 0);  // the sliver the test needs
  SegmentMetrics m;
  const Volume v = segment_volume(memory_source(paint(table, nx, ny, nz, label, 0)), table, iso_options(), &m);
  EXPECT_EQ(count_label(v, 7), painted * nz);
  EXPECT_EQ(m.misplaced_absorbed, 0);
}

// Real stacks are not registered to the pixel. The crop as 8 slices shifted
// by up to 2 px each (a fixed sequence, edges repeated): the shaded fat
// lobules taken for bone then join from slice to slice into components that
// meet the muscle here and there, and stayed bone (6.8 % of the voxels on 12
// such slices, against 1.6 % for identical copies). Mostly surrounded by fat,
// they are out of place and go; the humerus stays, as with identical slices.
TEST(SegmentReal, MisregisteredSlicesKeepTheBoneInPlace) {
  const std::string dir = std::string(ORTHOSIM_SOURCE_DIR) + "/data-samples/real";
  const TissueTable table = load_tissue_table(dir + "/tissues.json");
  test::TempDir stack("segreal3");
  test::write_shifted_arm_crop(stack.path, test::arm_crop_shifts());
  SegmentOptions o;
  o.spacing_m = {0.33e-3, 0.33e-3, 0.33e-3};
  SegmentMetrics m;
  const Volume v = segment_volume(stack_source(stack.path.string()), table, o, &m);
  const int n = v.nx * v.ny;
  const std::uint8_t bone = static_cast<std::uint8_t>(v.label_of("bone"));
  for (int z = 0; z < v.nz; ++z) {
    const std::uint8_t* s = v.labels.data() + v.index(0, 0, z);
    const double frac = static_cast<double>(std::count(s, s + n, bone)) / n;
    // the bounds of ArmCropIsPlausible (the cortex ring, ~ 1.5 %)
    EXPECT_GT(frac, 0.008) << "slice " << z;
    EXPECT_LT(frac, 0.04) << "slice " << z;
  }
  EXPECT_GT(m.misplaced_absorbed, 0);
  EXPECT_EQ(m.body_components, 1);
}

// ---- slice registration -----------------------------------------------------------------

namespace {

// Slice z's content moved by shift[z] (to x + dx, y + dy), edges replicated.
std::vector<RgbImage> jittered(std::vector<RgbImage> slices, const std::vector<std::array<int, 2>>& shift) {
  for (std::size_t z = 0; z < slices.size(); ++z) {
    const RgbImage in = slices[z];
    for (int y = 0; y < in.ny; ++y)
      for (int x = 0; x < in.nx; ++x) {
        const int fx = std::clamp(x - shift[z][0], 0, in.nx - 1), fy = std::clamp(y - shift[z][1], 0, in.ny - 1);
        for (int c = 0; c < 3; ++c)
          slices[z].rgb[(static_cast<std::size_t>(y) * in.nx + x) * 3 + c] =
              in.rgb[(static_cast<std::size_t>(fy) * in.nx + fx) * 3 + c];
      }
  }
  return slices;
}

// Steps between neighbouring slices of what is left of the jitter (jitter +
// shift), per axis: the largest and the mean, in pixels.
struct Steps {
  int largest = 0;
  double mean = 0;
};
Steps steps(const std::vector<std::array<int, 2>>& jitter, const std::vector<std::array<int, 2>>& shift) {
  Steps st;
  for (std::size_t z = 1; z < jitter.size(); ++z)
    for (int c = 0; c < 2; ++c) {
      const int d = std::abs((jitter[z][c] + shift[z][c]) - (jitter[z - 1][c] + shift[z - 1][c]));
      st.largest = std::max(st.largest, d);
      st.mean += d / (2.0 * static_cast<double>(jitter.size() - 1));
    }
  return st;
}

}  // namespace

// The real arm crop moved 1-2 px a slice (the same slice each time): the
// phase correlation measures each move to a tenth of a pixel, and the
// registration moves every slice onto the moves' own least-squares line (the
// part nothing can tell from drift: kept), to the nearest pixel.
TEST(SegmentRegister, UndoesTheJitterOfTheRealCrop) {
  test::TempDir stack("segreg");
  const auto& j = test::arm_crop_shifts();
  test::write_shifted_arm_crop(stack.path, j);
  const SliceRegistration r = register_slices(stack_source(stack.path.string()));
  ASSERT_EQ(r.shift.size(), j.size());
  EXPECT_EQ(r.rejected, 0);
  for (std::size_t z = 1; z < j.size(); ++z)
    for (int c = 0; c < 2; ++c) EXPECT_NEAR(r.pairwise[z][c], j[z][c] - j[z - 1][c], 0.1) << "slice " << z << " axis " << c;
  const double n = static_cast<double>(j.size()), zm = (n - 1) / 2;  // (8 slices: one local line, half window 8)
  for (int c = 0; c < 2; ++c) {
    double jm = 0, num = 0, den = 0;
    for (std::size_t z = 0; z < j.size(); ++z) jm += j[z][c] / n;
    for (std::size_t z = 0; z < j.size(); ++z) num += (z - zm) * (j[z][c] - jm), den += (z - zm) * (z - zm);
    for (std::size_t z = 0; z < j.size(); ++z) {
      const double line = jm + num / den * (static_cast<double>(z) - zm);
      EXPECT_LE(std::abs(j[z][c] + r.shift[z][c] - line), 0.6) << "slice " << z << " axis " << c << ": line " << line;
    }
  }
  EXPECT_GT(r.moved, 0);
  EXPECT_EQ(r.max_shift_px, 2);
}

// The phantom with every slice moved by up to 2 px: registered, neighbouring
// slices sit 0.1 px apart on average (1.6 before) and 2 px at most (4; its
// anatomy moves between slices too, so the measured moves are off by up to
// half a pixel), and the labels match the truth moved as the slices end up,
// to the goals of the unmoved stack; unregistered they do not. An unmoved
// stack moves by a pixel at most and keeps those goals.
TEST(SegmentRegister, AJitteredPhantomSegmentsLikeARegisteredOne) {
  const PhantomOptions p = test_phantom();
  const Volume truth = phantom_labels(p);
  const TissueTable table = phantom_tissue_table();
  std::mt19937 rng(7);
  std::uniform_int_distribution<int> u(-2, 2);
  std::vector<std::array<int, 2>> j(static_cast<std::size_t>(p.nz));
  for (std::size_t z = 1; z < j.size(); ++z) j[z] = {u(rng), u(rng)};
  const std::vector<RgbImage> plain = lit_slices(p, truth, [](int, int, int, int) { return 1.0; });
  const std::vector<RgbImage> moved = jittered(plain, j);
  SegmentOptions o = phantom_segment_options(p);
  o.register_slices = true;
  SegmentMetrics m;
  const Volume v = segment_volume(memory_source(moved), table, o, &m);
  const SliceRegistration& r = m.registration;
  ASSERT_EQ(r.shift.size(), j.size());
  std::vector<std::array<int, 2>> none(j.size());
  const Steps before = steps(j, none), after = steps(j, r.shift);
  EXPECT_LE(after.largest, 2) << "unregistered: " << before.largest;
  EXPECT_LT(after.mean, 0.25) << "unregistered: " << before.mean;
  EXPECT_GT(before.mean, 1.0);
  // the truth where the registered slices put it
  auto truth_moved = [&](const std::vector<std::array<int, 2>>& jitter, const std::vector<std::array<int, 2>>& shift) {
    Volume t = truth;
    for (int z = 0; z < t.nz; ++z) {
      const int dx = jitter[static_cast<std::size_t>(z)][0] + shift[static_cast<std::size_t>(z)][0];
      const int dy = jitter[static_cast<std::size_t>(z)][1] + shift[static_cast<std::size_t>(z)][1];
      for (int y = 0; y < t.ny; ++y)
        for (int x = 0; x < t.nx; ++x)
          t.labels[t.index(x, y, z)] =
              truth.labels[truth.index(std::clamp(x - dx, 0, t.nx - 1), std::clamp(y - dy, 0, t.ny - 1), z)];
    }
    return t;
  };
  std::map<std::string, std::int64_t> tv;
  expect_dice(dice_per_tissue(v, truth_moved(j, r.shift), &tv), tv, table, "registered");
  // unregistered, the same stack misses the goals (the test can fail)
  SegmentOptions plain_o = phantom_segment_options(p);
  const Volume u0 = segment_volume(memory_source(moved), table, plain_o);
  const auto d0 = dice_per_tissue(u0, truth, &tv);
  EXPECT_LT(d0.at("skin"), 0.97) << "the jitter should cost the thin skin its Dice";
  // an unmoved stack stays as it is
  // an unmoved stack: its anatomy's own uneven motion moves some slices by a
  // pixel (why registering is a choice: against the unmoved truth the skin's
  // Dice drops to about 0.95), its labels right where it puts them
  SegmentMetrics still;
  const Volume vs = segment_volume(memory_source(plain), table, o, &still);
  EXPECT_LE(still.registration.max_shift_px, 1);
  EXPECT_LE(steps(none, still.registration.shift).largest, 1);
  expect_dice(dice_per_tissue(vs, truth_moved(none, still.registration.shift), &tv), tv, table, "an unmoved stack, registered");
}

// ---- determinism and streaming ----------------------------------------------------------

// The concentric limb of small_table() with noise: the same labels whatever
// the thread count, the slab size (also one narrower than the smoothness
// prior's sweeps) and whether the run-length scratch stays in memory or goes
// to the scratch file.
TEST(SegmentStreaming, SameLabelsWhateverThreadsSlabsAndScratch) {
  const TissueTable table = small_table();
  const int nx = 48, ny = 40, nz = 12;
  // noise 30: enough for the smoothness prior to relabel voxels
  const auto slices = paint(table, nx, ny, nz, [&](int x, int y, int z) { return limb(x, y, z, nx, ny); }, 30.0, 9);
  struct Run {
    int threads, slab;
    std::int64_t scratch;
  };
  std::vector<std::uint8_t> first;
  // slabs of 1, 3 and 5 slices are narrower than the smoothness prior's 4
  // sweeps each side: its slices ahead come from the slabs after
  for (const Run r : {Run{1, 8, std::int64_t(256) << 20}, Run{2, 8, std::int64_t(256) << 20}, Run{2, 1, 0},
                      Run{1, 5, 0}, Run{2, 3, std::int64_t(256) << 20}}) {
    tbb::global_control gc(tbb::global_control::max_allowed_parallelism, static_cast<std::size_t>(r.threads));
    SegmentOptions o = iso_options();
    o.slab = r.slab;
    o.scratch_memory_bytes = r.scratch;
    SegmentMetrics m;
    const Volume v = segment_volume(memory_source(slices), table, o, &m);
    EXPECT_EQ(m.scratch_spilled, r.scratch == 0) << r.threads << " threads, slab " << r.slab;
    EXPECT_GT(m.smooth_changed, 0) << "the prior the test needs";
    if (first.empty()) {
      first = v.labels;
      // every tissue of the limb is there, the gel around it
      for (int l = 0; l <= 5; ++l) EXPECT_GT(count_label(v, l), 0) << "label " << l;
    } else {
      EXPECT_EQ(v.labels, first) << r.threads << " threads, slab " << r.slab << ", scratch " << r.scratch;
    }
  }
}
