// Colour stack -> tissue labels: the first pipeline stage.
//
// A folder of 2-D colour slices (PNG, JPEG, TIFF, BMP) is classified voxel by
// voxel into the tissues of a tissue table and cleaned up in 3-D. The method,
// in order (docs/segment.md has the details and figures):
//
//  1. Calibration. A few slices spread over the stack (calibration_slices) are
//     read first. Their background (the embedding medium, the table's
//     background prototypes) gives the stack's reference background colour,
//     and an EM fit (in 8-bit RGB by default, or CIELAB: colour_space) over
//     their pixels (each sample the per-channel median of its 3 x 3
//     neighbourhood) of a mixture of Gaussians
//     seeded by the table's colour prototypes, with mixing weights and a
//     shared full covariance, moves each prototype to where its tissue really is in
//     this stack (a Bayesian shrinkage towards the prototype, at most
//     refine_max_shift CIE76 units away). The table's colours only need to be
//     roughly right; the weights keep a rare tissue's prototype out of the
//     noise tail of a common one (plain k-means let it run off there), and
//     the full covariance follows the noise's shape (with one variance in
//     CIELAB the vein still ran into the gel's chroma tail at 8-bit noise
//     20). In RGB sensor noise is the same for every tissue, so one shared
//     covariance fits them all; in CIELAB it does not (the vein ran into the
//     gel at noise 64).
//  2. Per slice: normalisation against the background. A per-channel gain
//     field (constant or a plane across the slice) maps the slice's background
//     onto the reference: illumination drift along and across slices goes.
//     Then the nearest refined prototype under the calibration's covariance
//     (Mahalanobis; or in CIELAB, see classify), memoised per 24-bit sRGB
//     colour in a 16 MiB table filled as colours are met. The prototypes'
//     colours and covariance for this are those of single pixels (pixel_lab:
//     the fit is made on 3 x 3 medians, whose mean lies off the pixels' under
//     noise where the space is not linear in RGB, or where RGB clips).
//  2b. Smoothness prior (smoothness, 0 = off): a Potts prior over the 26
//     neighbours, minimised by a few Jacobi sweeps of iterated conditional
//     modes: a voxel weighs its colour's evidence against its neighbours'
//     labels (segment_detail::Smoother).
//  3. Per slice: anatomical order. For every tissue U that encloses others
//     (the table's "inside"), the 2-D region of U and everything nested in it is
//     filled; what that fill encloses but is neither U nor nested in U (skin
//     inside the fat, fat inside the muscle, gel inside the limb) is
//     reclassified by colour among U and its descendants, unless that pocket
//     is larger than the whole region of U and its descendants in the slice:
//     then the outline is misplaced pixels (shaded fat taken for bone around
//     the muscle), not the pocket, and the pocket is kept. Vessel tissues are
//     never reclassified by this rule (they cross layers).
//  4. 3-D rank filter (the multi-label analogue of an opening and a closing
//     with a 3x3x3 element): a voxel with fewer than speck_support of its 26
//     neighbours sharing its label takes the neighbourhood's majority label.
//     Unlike a binary opening it keeps sheets and strands one voxel thin;
//     vessel voxels need only one like neighbour.
//  5. 3-D connected components (6-connected, same label), streamed slice by
//     slice with a union-find over run-length runs: background pockets that do
//     not reach the lateral border are holes and are filled by their majority
//     neighbour; islands of a bulk tissue smaller than min_island_voxels and
//     of a vessel tissue smaller than min_vessel_voxels, and components of a
//     nested tissue out of place (their parent's region is not the majority
//     of what surrounds them; a tissue's anchor, the component meeting its
//     place most, only when it meets none of it; a vessel's place is the
//     body, so a piece of one meeting the gel more than the body is out of
//     place), are absorbed
//     by their majority neighbour (not a tissue's largest component when it
//     is larger than that neighbour: then the neighbour is misplaced); then
//     only the body (the largest 6-connected
//     non-background component, and any other of at least min_body_fraction
//     of its size) is kept.
//
// Memory does not grow with the number of slices: slices stream through in
// slabs; between the two passes the cleaned labels wait as run-length runs
// in memory up to scratch_memory_bytes, beyond that in an unlinked scratch
// file; the output is written slab by slab.
//
// Frame (libmodel/format/model.h): x along image columns, y along rows, z
// along slices in natural name order; voxel (i,j,k) at origin_m + (i,j,k) *
// spacing_m. Deterministic: same input and options give the same labels
// whatever the thread count.
#pragma once

#include "libmodel/format/model.h"
#include "libmodel/tissues.h"

#include <array>
#include <cstdint>
#include <functional>
#include <map>
#include <string>
#include <vector>

namespace orthosim {

// ---- slice stacks --------------------------------------------------------

// Natural order of file names: digit runs compare as numbers ("s2" < "s10"),
// the rest character by character, case-insensitively; ties by plain order.
bool natural_less(const std::string& a, const std::string& b);

// The image files of a stack folder (extensions png, jpg, jpeg, jpe, tif,
// tiff, bmp, any case; hidden files ignored), as full paths in natural order.
// Throws Error(dir, ...) if the folder is missing or holds no image.
std::vector<std::string> list_stack(const std::string& dir);
// The content hash of a stack as segment reads it ("xxh3:..."): the names of
// the files list_stack gives, in that order (they number the slices), and the
// bytes of the first file (its size, channels and depth are the stack's) and
// of the slices first_slice..last_slice (segment's --slices; -1: to the last).
// A hidden file or a note beside the slices does not change it (hash_path of
// the folder did: the pipeline re-ran every stage and the model's provenance
// changed), nor does a slice outside the range (hashing every file of a
// full-body stack for a part of it read gigabytes before each cached run).
// With the whole range it is the hash of before 2026-11-29.
std::string hash_stack(const std::string& dir, int first_slice = 0, int last_slice = -1);

// One decoded 8-bit RGB image, row-major, x fastest: rgb[(y*nx + x)*3 + c].
struct RgbImage {
  int nx = 0, ny = 0;
  std::vector<std::uint8_t> rgb;
};

// What a slice file holds before conversion to RGB.
struct SliceFormat {
  int nx = 0, ny = 0;
  int channels = 0;  // 1 grey, 2 grey+alpha, 3 colour, 4 colour+alpha
  int bits = 8;      // 8 or 16
  int max_value = 0; // 16-bit files: the largest colour value (alpha excluded); 0 for 8-bit ones
};

// Reads one colour slice. 16-bit images are scaled to 8 bits from
// `bit_depth` significant bits (8..16: v x 255 / (2^bit_depth - 1), clamped;
// a 12-bit camera's data in a 16-bit file: 12), an alpha channel is dropped.
// Throws Error(path, ...) for a missing, empty, corrupt or undecodable file
// and for grey-scale images (one or two channels, or three equal channels).
// `format` receives what the file held (its whole size, also when it throws
// after reading the header).
// region (x, y, w, h in pixels from the top left; w = h = 0: the whole slice):
// the pixels of that part alone, the same values as the whole slice's cut,
// decoded as far as the format lets (docs/segment.md, Region of interest):
// a JPEG's rows of the region (the rows above skipped, the rows below read
// only to check the data) and its iMCU columns, a PNG's rows down to the
// region's last, a TIFF's strips of the region; other files whole, then cut.
// A region beyond the slice throws Error(path, ...).
RgbImage read_slice(const std::string& path, SliceFormat* format = nullptr, int bit_depth = 16,
                    const std::array<int, 4>& region = {0, 0, 0, 0});

// Writes an RGB image as PNG atomically (overlays, tests). Throws Error(path).
void write_png(const std::string& path, const RgbImage& image);

// A stack of slices: sizes and a reader that may be called from several
// threads at once. read(z, rgb) fills ny*nx*3 bytes (RgbImage layout) or
// throws Error naming the slice.
struct SliceSource {
  int nx = 0, ny = 0, nz = 0;
  std::string name;  // what the stack is (folder), for messages
  // a remark on the stack worth a warning (e.g. a 16-bit stack whose first
  // slice uses 12 bits or fewer while read as 16-bit), or empty
  std::string note;
  std::function<void(int z, std::vector<std::uint8_t>& rgb)> read;
  // Optional: the pixels of the part (x, y, w, h) of slice z alone (w*h*3
  // bytes), as read then cut would give them, at the cost of decoding only
  // what the part needs (stack_source's: read_slice's region). roi_source
  // uses it when it is there.
  std::function<void(int z, const std::array<int, 4>& region, std::vector<std::uint8_t>& rgb)> read_region;
};

// A source over the folder `dir`: lists it, reads the first slice for the
// size, and checks every later slice against it when read (same size, same
// channel count and bit depth, colour). Throws Error(file, ...) on the first
// slice that is wrong.
// bit_depth: the significant bits of 16-bit slices (read_slice), 8..16.
SliceSource stack_source(const std::string& dir, int bit_depth = 16);

// A source over images held in memory (tests, benchmarks). All the same size.
SliceSource memory_source(std::vector<RgbImage> slices, std::string name = "memory");

// ---- slice registration --------------------------------------------------
// Cryosection slices are photographed one by one, and a stack's slices can sit
// a few pixels off each other (the real arm crop's, docs/segment.md): every
// tissue wall then zigzags from slice to slice, the surfaces fold and the
// quad remesher fails. register_slices finds each slice's translation against
// the one before by phase correlation (OpenCV, Hann window) of its luma; the
// path the stack's content takes through the slices, summed from those, is
// split into its smooth part (the least-squares line over 2 half_window + 1
// slices around each: the anatomy's own drift, kept) and the rest (the
// jitter), which `shift` undoes in whole pixels.
struct RegisterOptions {
  int half_window = 8;         // slices each side of the local line (1..100000)
  double max_shift_px = 32;    // a slice-to-slice match beyond this is rejected (taken as 0)
  double min_response = 0.1;   // a match whose phase-correlation peak is below this is rejected
};

struct SliceRegistration {
  std::vector<std::array<double, 2>> pairwise;  // px (x, y) slice z's content moved against z - 1; [0] = 0
  std::vector<double> response;                // the phase correlation's peak, 0..1 ([0] = 1)
  std::vector<std::array<int, 2>> shift;       // px (x, y) slice z is moved by
  int moved = 0;                               // slices with a non-zero shift
  int rejected = 0;                            // pairs beyond max_shift_px or below min_response
  std::vector<int> weak;                       // slices whose match to the one before was rejected
  int max_shift_px = 0;                        // largest |shift| component
  double min_response = 1;
  double seconds = 0;
};

// Throws Error("", ...) naming the bad option.
void validate(const RegisterOptions& o);

// Reads every slice once (and two slices per 8 twice). Deterministic for any
// thread count. Stacks of one slice, or slices under 8 px, are left as they are.
SliceRegistration register_slices(const SliceSource& src, const RegisterOptions& o = {});

// `src` with slice z moved by shift[z] (content at (x, y) goes to (x + dx,
// y + dy); edge pixels fill what comes in).
SliceSource shifted_source(SliceSource src, std::vector<std::array<int, 2>> shift);

// ---- segmentation --------------------------------------------------------

struct SegmentOptions {
  // Frame of the output volume (m): voxel size along x, y, z (each > 0) and
  // the position of voxel (0,0,0).
  std::array<double, 3> spacing_m{1e-3, 1e-3, 1e-3};
  std::array<double, 3> origin_m{0, 0, 0};

  // -- region of interest (default: the whole stack) --
  // The part of the slices segmented: x0, y0, width, height in pixels of the
  // slice files (x along columns, y along rows; width or height 0: whole
  // slices), and the slices first_slice..last_slice of the stack in natural
  // name order, 0-based and inclusive (last_slice -1: to the last). A full
  // cryosection photograph holds the body, the embedding block, its frame, a
  // grey scale and a label card; a limb model wants the limb. origin_m stays
  // the position of the stack's voxel (0,0,0): the labels' voxel (0,0,0) is at
  // volume_origin(o) (docs/segment.md, "Region of interest").
  std::array<int, 4> roi_px{0, 0, 0, 0};
  int first_slice = 0;
  int last_slice = -1;

  // -- registration (off by default: a registered stack has no jitter to undo,
  // and a stack's true slice-to-slice drift stays either way) --
  bool register_slices = false;
  RegisterOptions registration;

  // -- colour model --
  // Slices read before the main pass to calibrate colours (spread evenly,
  // first and last included); at most nz. 1..64.
  int calibration_slices = 9;
  // Significant bits of a 16-bit stack (8..16; read_slice): 12 for a 12-bit
  // camera's data stored in 16-bit files. No effect on 8-bit slices.
  int bit_depth = 16;
  // Pixels sampled for calibration and per-slice normalisation: every n-th
  // row and column (1..64).
  int sample_stride = 4;
  // Background normalisation: none, gain (one gain per channel and slice),
  // plane (per channel, a gain varying linearly across the slice). Needs the
  // table's background prototypes; without them it is off.
  enum class Normalise { none, gain, plane };
  Normalise normalise = Normalise::plane;
  // EM iterations of the calibration (0 = the table's colours as they
  // are), 0..100.
  int refine_iterations = 8;
  // Prior weight of each prototype, as a fraction of the calibration samples
  // per prototype: a prototype with few pixels moves little. >= 0.
  double refine_prior = 0.05;
  // Largest move of a prototype by the refinement (CIE76 units), >= 0.
  double refine_max_shift = 30;
  // The stack's exposure from the slices' border (the embedding medium):
  // where it has the table background's chromaticity and its brightness is
  // off by more than 20 %, every table colour is scaled by that ratio before
  // the calibration (docs/segment.md). Off by default: a vignetted stack's
  // dark border is not its exposure.
  bool exposure_from_border = false;
  // Weight of lightness against chroma in the colour distance, > 0.
  // Values below 1 make the classification more robust to brightness.
  // CIELAB only (colour_space); rgb has no lightness axis to weigh, and
  // validate refuses a weight other than 1 there.
  double lightness_weight = 1.0;
  // The space the calibration's mixture is fitted in and colours are scored
  // in (docs/segment.md, "The colour space"). cielab: CIE 1976 L*a*b* (D65).
  // rgb: the stack's 8-bit sRGB values, where the sensor's noise is, so
  // that one shared covariance fits every tissue's spread alike; in CIELAB
  // the same noise spreads differently for each colour (the blue gel's a
  // third wider than the bone's), and under heavy noise (8-bit sigma 48-64) a rare tissue's prototype ran
  // into a common one's tail. Reports give CIELAB either way.
  enum class Space { cielab, rgb };
  Space colour_space = Space::rgb;

  // How a colour picks its prototype. nearest: the nearest in colour_space
  // (Euclidean; in CIELAB CIE76, lightness weighted). mahalanobis: the
  // nearest under the calibration mixture's shared covariance (the lightness
  // weight is then unused): distances count in units of the stack's own
  // colour spread along each direction, so the noise's wide spread along
  // some directions (in CIELAB the chroma of dark and saturated colours) no
  // longer carries a common tissue's pixels into a rare one next to it (the
  // blue gel into the vein). Equal priors: the mixing weights
  // would keep thin layers' boundary pixels from them. Needs
  // refine_iterations > 0 (else nearest).
  enum class Classify { nearest, mahalanobis };
  Classify classify = Classify::mahalanobis;
  // Smoothness prior (docs/segment.md, "Smoothness prior"): a Potts prior
  // over the 26 neighbours, in nats of colour evidence per unlike face
  // neighbour (neighbours farther away count less, by their distance), so a
  // voxel's label weighs its colour against its neighbours' labels instead of
  // its colour alone. 0 = off (the per-voxel rule). Needs the Mahalanobis
  // rule (its distances are in units of the pixels' own spread); with the
  // nearest rule it is off. >= 0.
  double smoothness = 1;
  // Jacobi sweeps of iterated conditional modes, 1..16. Each keeps
  // `smoothing_sweeps` slices each side of a slab in memory.
  int smoothing_sweeps = 4;
  // -- clean-up (each can be switched off) --
  bool cleanup = true;        // master switch for steps 3-5 of the header
  bool enforce_order = true;  // anatomical order from the table's "inside"
  bool fill_holes = true;     // background enclosed by the body becomes tissue
  // A voxel keeps its label if at least this many of its 26 neighbours share
  // it (0..26; 0 = no rank filter). Vessel voxels need min(1, this).
  int speck_support = 2;
  // 3-D islands of a bulk tissue below this many voxels join their majority
  // neighbour (0 = keep all)...
  std::int64_t min_island_voxels = 64;
  // ...when they are also smaller than this volume (mm^3; 0 = no island
  // goes by size). 20 mm^3 is 64 voxels of 0.31 mm^3 (0.5 x 0.5 x 1.25 mm):
  // finer stacks (the CVH's, the sample's 0.30 mm^3) keep the voxel rule
  // (noise specks are voxel-sized), coarser ones keep anatomy of that volume
  // (64 voxels of 1.2 x 1.2 x 5 mm deleted two 390 mm^3 pieces of marrow,
  // all of it).
  double min_island_mm3 = 20;
  // The same for vessel tissues (table layer "vessel"): only specks go.
  std::int64_t min_vessel_voxels = 4;
  // Body components kept besides the largest: those with at least this
  // fraction of its voxels, in (0, 1]. 1 keeps the largest only.
  double min_body_fraction = 0.1;

  // -- streaming --
  int slab = 8;  // slices classified together (1..256)
  // Run-length scratch kept in memory up to this many bytes, beyond it in an
  // unlinked file in scratch_dir ("" = the system temporary folder).
  std::int64_t scratch_memory_bytes = std::int64_t(256) << 20;
  std::string scratch_dir;
};

// Throws Error("", ...) naming the bad option.
void validate(const SegmentOptions& o);
// True when o selects a part of the stack (roi_px or the slice range).
bool has_roi(const SegmentOptions& o);
// The stack's voxel the labels' voxel (0,0,0) is: (roi x0, roi y0, first_slice).
std::array<int, 3> roi_offset(const SegmentOptions& o);
// Where the labels' voxel (0,0,0) lies: origin_m + roi_offset(o) * spacing_m.
std::array<double, 3> volume_origin(const SegmentOptions& o);
// `src` cut to o's region of interest (`src` itself without one). Throws
// Error(src.name, ...) when the region reaches beyond the stack.
SliceSource roi_source(SliceSource src, const SegmentOptions& o);
// The options as a JSON object (reports, provenance).
std::string segment_parameters_json(const SegmentOptions& o);
const char* to_string(SegmentOptions::Normalise n);
const char* to_string(SegmentOptions::Classify c);
const char* to_string(SegmentOptions::Space s);

// A prototype after calibration.
struct Prototype {
  int label = 0;                      // tissue label, 0 = background
  std::array<double, 3> table_lab{};  // from the table's rgb (CIELAB, D65)
  std::array<double, 3> lab{};        // refined on the stack (on its 3 x 3 medians)
  std::array<double, 3> pixel_lab{};  // the mean colour of its single pixels, which classification scores against
  std::int64_t samples = 0;           // calibration samples assigned
};

// For each prototype, the label of the table colour nearest its calibrated
// colour (CIE76 over every prototype's table colour; its own on a tie). A
// prototype whose calibrated colour lies nearer another tissue's table colour
// than its own has probably taken that tissue's pixels (or the table's colour
// for it is far off): the CLI warns.
std::vector<int> nearest_table_labels(const std::vector<Prototype>& prototypes);

struct SegmentMetrics {
  int nx = 0, ny = 0, nz = 0;                // the labels' size (the region of interest's)
  std::array<int, 3> stack_size{0, 0, 0};    // the whole stack's, px and slices
  std::string stack_note;  // SliceSource::note: worth a warning (empty: none)
  std::map<std::string, std::int64_t> voxels;  // per tissue name, "background" included
  std::vector<Prototype> prototypes;
  // How far apart the calibration found each pair of labels' colours: the
  // smallest Mahalanobis distance between a prototype of one and of the
  // other under the pixels' shared covariance (the classifier's own
  // distance), in standard deviations of a pixel's colour. Two tissues
  // delta apart are confused per voxel, at equal priors, with probability
  // Phi(-delta / 2). Empty with the nearest rule. Sorted by delta.
  struct Separation {
    int a = 0, b = 0;  // labels, a < b
    double delta = 0;
  };
  std::vector<Separation> separations;
  // Per-slice normalisation: smallest and largest mean gain over the slices
  // (1 = no correction), and slices where it fell back to a constant or none.
  double gain_min = 1, gain_max = 1;
  int normalise_fallbacks = 0;
  // The stack's exposure (observed / table brightness, the same in each RGB
  // channel) the table colours were scaled by; {1, 1, 1}: none
  // (SegmentOptions::exposure_from_border).
  std::array<double, 3> exposure{1, 1, 1};
  // The slices' registration (SegmentOptions::register_slices; empty without).
  SliceRegistration registration;
  // Voxels changed by each clean-up step.
  std::int64_t order_changed = 0;
  std::int64_t speck_changed = 0;
  std::int64_t smooth_changed = 0;  // voxels the smoothness prior relabelled
  std::int64_t holes_filled = 0;
  std::int64_t islands_absorbed = 0;
  std::int64_t misplaced_absorbed = 0;  // components out of place (their parent's region not the majority around them)
  std::int64_t detached_removed = 0;
  std::int64_t components = 0;        // 3-D same-label components before clean-up
  std::int64_t body_components = 0;   // kept non-background components
  std::int64_t scratch_bytes = 0;     // run-length scratch at its largest
  bool scratch_spilled = false;       // went to the scratch file
  // Wall times (s).
  double calibrate_s = 0, read_s = 0, classify_s = 0, cleanup_s = 0, components_s = 0, write_s = 0;
};

// Receives the finished labels in z order, one slab at a time:
// labels[(k*ny + y)*nx + x] for slices z0 .. z0+n-1.
using LabelSink = std::function<void(int z0, int n, const std::uint8_t* labels)>;

// Segments `src` with `table` and calls `sink` with the labels: of o's region
// of interest (roi_source), the whole stack by default.
// progress(done, total) is called from the calling thread, slices done of
// 2*nz (two passes). Throws Error for bad options, a bad table (no tissue,
// labels without prototypes) or a bad slice, and Error(src.name, ...) when no
// voxel is classified as tissue.
SegmentMetrics segment(const SliceSource& src, const TissueTable& table, const SegmentOptions& opt,
                       const LabelSink& sink, const std::function<void(long, long)>& progress = {});

// The same into a Volume (spacing, origin and label names filled; the origin
// is volume_origin(opt)).
Volume segment_volume(const SliceSource& src, const TissueTable& table, const SegmentOptions& opt,
                      SegmentMetrics* metrics = nullptr);

// The whole stage: segments the folder `stack_dir` and writes `out_h5`
// (/volume: labels, spacing_m, origin_m, label_names, label_inside; and
// /provenance/segment) and, if `nrrd_path` is not empty, a NRRD copy for 3D
// Slicer. All outputs are atomic: on any error nothing is written.
// Throws Error(path, ...).
struct SegmentFiles {
  std::string stack_dir, tissues_path, out_h5, nrrd_path;
  std::string command_line;  // for provenance
  std::string inputs_json;   // {"path": "xxh3:..."}; "" = hash the stack and table here
};
SegmentMetrics segment_stack(const SegmentFiles& files, const TissueTable& table, const SegmentOptions& opt,
                             const std::function<void(long, long)>& progress = {});

// The "inside" of each label value, as written to /volume@label_inside:
// names[v] is the tissue that encloses label v's tissue ("" for none).
std::vector<std::string> label_inside(const TissueTable& table);

// ---- evaluation ----------------------------------------------------------

// Dice 2|A n B| / (|A| + |B|) per tissue name between two label volumes of
// the same size whose label_names agree for the tissues compared (by name:
// a tissue is compared when both volumes name it). Tissues absent from both
// get no entry. Voxel counts of the truth in `truth_voxels` if given.
std::map<std::string, double> dice_per_tissue(const Volume& labels, const Volume& truth,
                                              std::map<std::string, std::int64_t>* truth_voxels = nullptr);

// The same between two model files, streamed slab by slab. A truth larger
// than the labels is compared where the labels lie in it: the labels' voxel
// (i, j, k) against the truth's (i, j, k) + truth_offset (a region of
// interest's roi_offset against the whole stack's truth).
std::map<std::string, double> dice_per_tissue(const std::string& labels_h5, const std::string& truth_h5,
                                              std::map<std::string, std::int64_t>* truth_voxels = nullptr,
                                              const std::array<int, 3>& truth_offset = {0, 0, 0});

}  // namespace orthosim
