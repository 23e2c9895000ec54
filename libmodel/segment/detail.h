// Internal to libmodel/segment: the colour model and the clean-up kernels.
// Not part of the library interface (segment.h is). No OpenCV types here.
#pragma once

#include "libmodel/segment/segment.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <cstdint>
#include <unordered_map>
#include <vector>

namespace orthosim::segment_detail {

// ---- colour --------------------------------------------------------------

// CIELAB (D65, CIE 1976) of an sRGB colour with channels in [0, 255].
std::array<double, 3> srgb_to_lab(double r, double g, double b);
// The same for 8-bit channels, through a table of the sRGB transfer curve
// (equal to srgb_to_lab(r, g, b)).
std::array<double, 3> srgb8_to_lab(std::uint8_t r, std::uint8_t g, std::uint8_t b);

// Static facts about the table that the kernels need, indexed by label value.
struct LabelInfo {
  int n_labels = 1;                    // max label + 1
  bool fill_holes = true;              // enclosed background becomes tissue
  std::vector<std::uint8_t> is_tissue;  // label names a tissue of the table
  std::vector<std::uint8_t> is_vessel;  // layer == "vessel"
  // Tissues that enclose others, in order of increasing depth, each with the
  // labels of itself and everything nested in it (`in_region`), and the
  // labels a pixel it encloses may be reclassified to (non-vessel).
  struct Encloser {
    int label = 0;  // 0: the whole body (every tissue), used for hole filling
    std::vector<std::uint8_t> in_region;  // [label] 1 if in the region
    std::vector<std::uint8_t> allowed;    // [label] 1 if a reclassification target
  };
  std::vector<Encloser> enclosers;
  // touch[T][L] says where label L lies for a 3-D component of tissue T:
  // 1 in T's place (T's parent, or nested in the parent but not in T), 2 in
  // T itself (nested in T), 0 out of T's place; other vessels count as 2
  // (they cross layers), but a vessel that is T's parent or nested in it is
  // T's place (a clot in a vein). A vessel's place is the body: every bulk
  // tissue 1, the background 0, other vessels 2. Empty for tissues without a
  // parent.
  std::vector<std::vector<std::uint8_t>> touch;
};
LabelInfo make_label_info(const TissueTable& t, bool fill_holes);

// (a - b)^T P (a - b) for a symmetric P given as (xx, yy, zz, xy, xz, yz).
inline double mahalanobis2(const std::array<double, 6>& P, const std::array<double, 3>& a,
                           const std::array<double, 3>& b) {
  const double d0 = a[0] - b[0], d1 = a[1] - b[1], d2 = a[2] - b[2];
  return P[0] * d0 * d0 + P[1] * d1 * d1 + P[2] * d2 * d2 + 2 * (P[3] * d0 * d1 + P[4] * d0 * d2 + P[5] * d1 * d2);
}

struct Centre {
  int label = 0;
  // In the model's space (ColourModel::space): the table colour, the mean
  // calibrated on the samples' 3 x 3 medians, and what a single pixel of this
  // tissue looks like on average: x plus the mean difference between the raw
  // pixels' colour and their 3 x 3 medians' (calibrate(); CIELAB is not
  // linear in RGB, so under sensor noise the raw pixels' mean lies off the
  // medians'). Classification scores pixels against pixel_x; = x without
  // calibration.
  std::array<double, 3> table_x{}, x{}, pixel_x{};
  // The same three in CIELAB, for reports (= the above in the cielab space).
  std::array<double, 3> table_lab{}, lab{}, pixel_lab{};
  std::array<double, 3> table_rgb{};
  std::int64_t samples = 0;
};

// The calibrated colour model of one stack.
struct ColourModel {
  std::vector<Centre> centres;  // background ones (label 0) first
  double wl2 = 1;               // lightness weight squared (cielab; 1 in rgb)
  SegmentOptions::Space space = SegmentOptions::Space::cielab;
  // A colour's coordinates in the model's space: CIELAB, or the 8-bit sRGB
  // values themselves.
  std::array<double, 3> coords(std::uint8_t r, std::uint8_t g, std::uint8_t b) const {
    if (space == SegmentOptions::Space::rgb) return {double(r), double(g), double(b)};
    return srgb8_to_lab(r, g, b);
  }
  std::array<double, 3> coords(const std::array<double, 3>& rgb) const {
    if (space == SegmentOptions::Space::rgb) return rgb;
    return srgb_to_lab(rgb[0], rgb[1], rgb[2]);
  }
  // CIELAB of coordinates in the model's space (reports).
  std::array<double, 3> to_lab(const std::array<double, 3>& x) const {
    if (space == SegmentOptions::Space::cielab) return x;
    return srgb_to_lab(std::clamp(x[0], 0.0, 255.0), std::clamp(x[1], 0.0, 255.0), std::clamp(x[2], 0.0, 255.0));
  }
  // Reference background colour (RGB) of each background centre, from the
  // calibration slices; normalisation maps a slice's background onto it.
  std::vector<std::array<double, 3>> bg_reference;
  std::vector<std::uint8_t> centre_label;
  // The stack's exposure against the table (calibrate: observed / table
  // brightness from the slices' border, where the embedding medium is); the
  // centres' table colours were scaled by it. {1, 1, 1}: none applied.
  std::array<double, 3> exposure{1, 1, 1};

  int n_background() const {
    int n = 0;
    for (const auto& c : centres) n += c.label == 0;
    return n;
  }
  double dist2(const std::array<double, 3>& x, const std::array<double, 3>& c) const {
    const double dl = x[0] - c[0], da = x[1] - c[1], db = x[2] - c[2];
    return wl2 * dl * dl + da * da + db * db;
  }
  // The Mahalanobis rule (SegmentOptions::Classify::mahalanobis), set by
  // calibrate(): the inverse of the calibration mixture's shared covariance
  // (xx, yy, zz, xy, xz, yz). Off: dist2.
  bool mahalanobis = false;
  std::array<double, 6> precision{0, 0, 0, 0, 0, 0};
  // What a centre costs a pixel's colour x (coords): dist2, or the squared
  // Mahalanobis distance, to the centre's pixel_x.
  double score(const std::array<double, 3>& x, std::size_t i) const {
    return mahalanobis ? mahalanobis2(precision, x, centres[i].pixel_x) : dist2(x, centres[i].pixel_x);
  }
  // Best centre (first of equals) under score.
  int nearest(const std::array<double, 3>& x) const;
  // Best centre by the squared RGB distance to the table colours (table_rgb,
  // after the exposure): the background pick of the normalisation's reference
  // and of its per-slice fits, one rule for both whatever the calibration
  // did. RGB, where sensor noise is isotropic, so the nearest colour is the
  // likelier one, and no conversion per sample.
  int nearest_table_rgb(const std::uint8_t* rgb) const;
  // Best centre whose label is allowed[label] != 0; -1 if none.
  int nearest_allowed(const std::array<double, 3>& x, const std::vector<std::uint8_t>& allowed) const;

  // nearest(coords(r, g, b)) through a table over all 2^24 colours,
  // filled on first use of each colour (kUnknown: not yet). Filling races
  // are benign: every thread writes the same value.
  static constexpr std::uint8_t kUnknown = 0xFF;
  int centre_of(std::uint8_t r, std::uint8_t g, std::uint8_t b) const {
    const std::size_t key = static_cast<std::size_t>(r) << 16 | static_cast<std::size_t>(g) << 8 | b;
    std::atomic_ref<std::uint8_t> slot(memo_[key]);
    std::uint8_t c = slot.load(std::memory_order_relaxed);
    if (c == kUnknown) {
      c = static_cast<std::uint8_t>(nearest(coords(r, g, b)));
      slot.store(c, std::memory_order_relaxed);
    }
    return c;
  }
  int centre_of(const std::uint8_t* rgb) const { return centre_of(rgb[0], rgb[1], rgb[2]); }
  // Call after the centres change (and before the first centre_of).
  void reset_table();

 private:
  mutable std::vector<std::uint8_t> memo_;  // 2^24, indexed r << 16 | g << 8 | b
};

// Centres from the table (refined later by calibrate()).
ColourModel initial_model(const TissueTable& t, const SegmentOptions& o);

// A gain field per channel: s_c(u, v) = a + b u + c v with u, v the pixel's
// position relative to the image centre in image widths/heights. Corrected
// colour = observed / s.
struct GainField {
  std::array<std::array<double, 3>, 3> coef{{{1, 0, 0}, {1, 0, 0}, {1, 0, 0}}};
  bool fallback = false;  // fewer background pixels than the mode needed
  double mean_gain() const { return (coef[0][0] + coef[1][0] + coef[2][0]) / 3; }
};

// Fits the gain field of one slice against the model's background
// references. `mode`: the requested normalisation.
GainField fit_gain(const ColourModel& m, const std::uint8_t* rgb, int nx, int ny, SegmentOptions::Normalise mode);

// Applies the gain field: out = rgb / s, rounded and clamped; the _rows
// form does rows [y0, y1) only.
void apply_gain(const GainField& g, const std::uint8_t* rgb, int nx, int ny, std::uint8_t* out);
void apply_gain_rows(const GainField& g, const std::uint8_t* rgb, int nx, int ny, int y0, int y1, std::uint8_t* out);

// Calibration: reference background from the slices, then k-means.
void calibrate(ColourModel& m, const std::vector<std::vector<std::uint8_t>>& slices, int nx, int ny,
               const SegmentOptions& o);

// Per-slice scratch reused by one thread.
struct SliceWork {
  std::vector<std::uint8_t> rgb;        // ny*nx*3, the slice as read
  std::vector<std::uint8_t> corrected;  // ny*nx*3, after normalisation
  const std::uint8_t* colour = nullptr;  // the colours classified: corrected, or the input when the gain is 1
};

// Classifies one slice: normalisation, nearest centre in CIELAB. Fills labels
// (ny*nx) and work.colour; returns the gain field used.
GainField classify_slice(const ColourModel& m, const SegmentOptions& o, const std::uint8_t* rgb, int nx, int ny,
                         SliceWork& work, std::uint8_t* labels);

// ---- smoothness prior (SegmentOptions::smoothness) -----------------------

// A Potts prior on the labels, minimised by iterated conditional modes: each
// voxel takes the label l of least
//   E(l) = u_l(colour) + beta * sum over its 26 neighbours n with label != l of w_n,
// u_l = min over l's centres of score / 2 (nats under the calibrated pixel
// spread: needs the Mahalanobis rule), w_n = h_min / |offset to n| in
// physical units (1 for an in-plane face neighbour of square pixels; the
// slices' spacing weighs the neighbours across them less). Candidates are
// the voxel's label and its neighbours'. Sweeps are Jacobi (every voxel from
// the previous sweep's labels), so the result does not depend on the order,
// the threads or the slab. The stack's end slices mirror their neighbour.
struct Smoother {
  double beta = 0;
  std::array<double, 27> w{};                 // (dz + 1) * 9 + (dy + 1) * 3 + dx + 1; centre 0
  std::vector<std::vector<int>> centres_of;  // label -> centre indices
};
Smoother make_smoother(const ColourModel& m, double beta, const std::array<double, 3>& spacing);
// u[i] = 1 where the 3 x 3 neighbourhood of pixel i (clipped at the border)
// has one label.
void uniform_3x3(const std::uint8_t* labels, int nx, int ny, std::vector<std::uint8_t>& u);
// A slice's labels from the previous sweep and their uniform_3x3 (both null
// beyond the stack).
// `active` (null: every voxel) marks, after the first sweep, the pixels
// within the 3 x 3 of one the previous sweep changed: a voxel's energies
// change only when a neighbour's label does.
// active_rows[y] = 1 where row y of active has a 1 (active's other rows are
// not read).
struct SweepSlice {
  const std::uint8_t* labels = nullptr;
  const std::uint8_t* uniform = nullptr;
  const std::uint8_t* active = nullptr;
  const std::uint8_t* active_rows = nullptr;
};
// d[i] = 1 where pixel i or one of its 3 x 3 neighbours has a != b, written
// only in the rows y with rows[y] = 1 (the others are those with no 1).
// Returns whether a and b differ at all.
bool changed_3x3(const std::uint8_t* a, const std::uint8_t* b, int nx, int ny, std::vector<std::uint8_t>& d,
                 std::vector<std::uint8_t>& rows);
// One sweep over slice z: sp / sn the slices z - 1 / z + 1, sc slice z, `rgb`
// its classified colours. Writes out; returns the voxels changed.
std::int64_t smooth_sweep(const Smoother& s, const ColourModel& m, const std::uint8_t* rgb, const SweepSlice& sp,
                          const SweepSlice& sc, const SweepSlice& sn, int nx, int ny, std::uint8_t* out);

// ---- clean-up kernels ----------------------------------------------------

// Anatomical order in one slice (see segment.h); `rgb` are the colours that
// were classified (SliceWork::colour). Returns voxels changed.
std::int64_t enforce_order(const LabelInfo& info, const ColourModel& m, const std::uint8_t* rgb, int nx, int ny,
                           std::uint8_t* labels);

// 3-D rank filter of slice z: prev/next may be null at the stack ends.
// Returns voxels changed.
std::int64_t rank_filter(const LabelInfo& info, int support, const std::uint8_t* prev, const std::uint8_t* cur,
                         const std::uint8_t* next, int nx, int ny, std::uint8_t* out);

// Run-length runs of one slice with 2-D (4-connected, same label)
// components numbered in scan order of their first run.
struct Run {
  std::int32_t x0 = 0, x1 = 0;  // [x0, x1)
  std::uint32_t comp = 0;       // component within the slice
  std::uint8_t label = 0;
};
struct SliceRuns {
  int nx = 0, ny = 0;
  std::vector<Run> runs;
  std::vector<std::uint32_t> row_start;  // ny+1 offsets into runs
  std::uint32_t n_comps = 0;
  // per component
  std::vector<std::int64_t> comp_voxels;
  std::vector<std::uint8_t> comp_label;
  std::vector<std::uint8_t> comp_lateral;  // touches the lateral border of the image
  // contacts between different components in the slice: (a, b, faces), a < b, sorted
  std::vector<std::array<std::int64_t, 3>> contacts;
};
void make_runs(const std::uint8_t* labels, int nx, int ny, SliceRuns& out);

// Serialised runs (the scratch between the passes) and back to labels.
void encode_runs(const SliceRuns& r, std::vector<std::uint8_t>& blob);
// Expands a blob into labels using final_label[offset + comp].
void decode_runs(const std::uint8_t* blob, std::size_t size, int nx, int ny, const std::uint8_t* final_label,
                 std::uint8_t* labels);

// 3-D components over the whole stack, one slice at a time.
class ComponentTracker {
 public:
  // Adds slice z (after slice z-1 was added, whose runs are `prev`, or null
  // for the first slice).
  void add_slice(const SliceRuns& cur, const SliceRuns* prev);
  struct Decision {
    std::int64_t components = 0, holes_filled = 0, islands_absorbed = 0, misplaced_absorbed = 0,
                 detached_removed = 0, body_components = 0;
  };
  // Applies the clean-up rules (segment.h) and returns final_label for every
  // 2-D component id (slice offset + local id).
  std::vector<std::uint8_t> resolve(const LabelInfo& info, const SegmentOptions& o, Decision* d);
  std::uint64_t slice_offset(int z) const { return offsets_[static_cast<std::size_t>(z)]; }
  std::uint64_t total() const { return parent_.size(); }

 private:
  std::uint32_t find(std::uint32_t a);
  void unite(std::uint32_t a, std::uint32_t b);
  void contact(std::uint32_t a, std::uint32_t b, std::int64_t w);
  void compact();
  std::vector<std::uint32_t> parent_;
  std::vector<std::int64_t> size_;
  std::vector<std::uint8_t> label_, lateral_;
  std::vector<std::uint64_t> offsets_;
  std::unordered_map<std::uint64_t, std::int64_t> contacts_;
  std::size_t compact_at_ = 1 << 16;
};

}  // namespace orthosim::segment_detail
