// surface: tissue label volume -> one closed, outward, 2-manifold triangle
// surface per tissue (the second half of issue 3). docs/surface.md describes
// the method, the accuracy against the phantom and the timings.
//
// Pipeline, all on plain data (Volume and Surface of libmodel/format/model.h):
//
//   label_parents (nesting: the tissue table's "inside", or inferred from the
//   volume) -> solid_label_set (the tissue and every label nested in it) ->
//   extract_surface:
//     1. solid    the voxels whose label is in the set, with every pocket that
//                 does not reach the lateral (x/y) border of the volume filled
//                 (fill_holes), cropped to its bounding box plus a margin;
//     2. field    the 0/1 indicator smoothed by a separable Gaussian of
//                 sigma_vox voxels along each axis (the anisotropic grid),
//                 values beyond the volume border replicated from the border;
//     3. extract  marching tetrahedra (Freudenthal split of every cube into
//                 six tetrahedra) at `iso` on that field, padded by one layer
//                 of outside so the surface closes at the volume border;
//     4. smooth   Taubin lambda|mu smoothing (does not shrink), then the
//                 Gaussian's curvature shrinkage undone (compensate_blur);
//     5. decimate CGAL edge collapse to target_faces (optional);
//     6. check    closed, manifold, outward, Euler characteristic,
//                 self-intersections (check_surface).
//
// A tissue's surface is the OUTER boundary of the tissue including everything
// nested inside it (docs/phantom.md): the skin surface encloses the whole
// limb, the fat surface fat, muscle, bone, marrow and vessels, the bone
// surface bone and marrow. Where the limb is cut by the first or last slice
// (or the tissue touches the lateral border) the surface closes with a flat
// cap border_offset x spacing outside the centre of the border voxels.
//
// Marching tetrahedra on a sign field is closed and 2-manifold by
// construction (the surface is the zero set of a piecewise-linear function on
// a tetrahedral mesh; no ambiguous cases), so every extracted surface passes
// the checks; check_surface still verifies it, and a failure is an internal
// error (std::logic_error).
//
// Units: metres, the physical frame of the volume: voxel (i,j,k) at
// origin_m + (i,j,k) * spacing_m. Deterministic: the same volume and options
// give bit-identical surfaces whatever the thread count.
//
// STL files: read_stl / write_stl (binary, atomic) of libmodel/format/stl.h.
#pragma once

#include "libmodel/format/model.h"
#include "libmodel/tissues.h"

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

namespace orthosim {

// ---- options ---------------------------------------------------------------------------
enum class DecimationCost {
  lindstrom_turk,    // CGAL LindstromTurk cost and placement (volume- and shape-preserving)
  garland_heckbert,  // CGAL GarlandHeckbert plane quadrics
};

struct SurfaceOptions {
  // Standard deviation of the Gaussian that smooths the 0/1 indicator before
  // extraction, in voxels along each axis (so sigma_vox * spacing_m[k] metres
  // along axis k). 0: no smoothing, vertices at edge midpoints. [0, 4].
  double sigma_vox = 0.7;
  // Level of the smoothed indicator that is the surface, in (0, 1).
  double iso = 0.5;
  // Fill pockets of the solid that do not reach the lateral (x/y) border of
  // the volume (background or other labels enclosed by the tissue).
  bool fill_holes = true;
  // Components of the extracted surface that enclose fewer voxels than this
  // (|volume| / voxel volume) are dropped before smoothing: specks of
  // sensor noise classified as the tissue (at 8-bit noise 16 the phantom's
  // skin had 3 of 0.04-0.13 voxels, its fat one of 1.7). 27, a 3 x 3 x 3
  // block, is the least the voxel grid resolves as a part of a body; the
  // largest component is always kept. >= 0; 0 keeps every component.
  double min_component_voxels = 27;
  // Distance of the outside layer beyond the volume border, as a fraction of
  // the spacing along that axis, in (0, 1]. The cap lies about half of it
  // outside the border voxel centres (the phantom's caps lie on them).
  double border_offset = 0.05;
  // Taubin smoothing: iterations of a lambda step then a mu step with
  // uniform (umbrella) weights. [0, 10000]; 0: none.
  int smooth_iterations = 10;
  double taubin_lambda = 0.5;   // in (0, 1)
  double taubin_mu = -0.53;     // in (-1, -lambda): mu < -lambda makes it non-shrinking
  // Undo the shrinkage of the Gaussian: the 0.5 level of a blurred indicator
  // lies sigma^2 H inside the true surface (H the mean curvature, in voxel
  // units), so after smoothing every vertex moves out by that much
  // (compensate_blur). No effect when sigma_vox is 0.
  bool compensate_blur = true;
  // Decimation to at most this many faces by edge collapse (CGAL); 0: keep
  // every face. Must be 0 or >= 4.
  std::int64_t target_faces = 0;
  DecimationCost decimation = DecimationCost::lindstrom_turk;
  // Edge collapses that would turn a face normal by more than 90 degrees are
  // refused (CGAL Bounded_normal_change_placement): fewer self-intersections.
  bool bounded_normal_change = true;
  // Count self-intersections (CGAL) in the final check. Costs about as much
  // as the extraction for large surfaces; off: self_intersections = -1.
  bool check_self_intersections = true;
  // Nesting (orthosim surface, enforce_nesting): a nested tissue's surface is
  // kept at least this far inside its parent's, as a fraction of the
  // smallest voxel spacing. [0, 1].
  double nest_clearance_vox = 0.1;
  // Nesting in the field (extract_surface with the parent's solid): where a
  // nested tissue reaches its parent's outside (the parent's shell thinner
  // than a voxel, lost by the segmentation: fat against the gel where the
  // skin is torn), the nested surface is drawn this far inside the parent's,
  // in voxels along the surface normal. A shell the voxels do not resolve is
  // between 0 and 1 voxel thick: half a voxel is its expected thickness.
  // [0, 0.5]; 0: off (the surfaces coincide there, and only the nesting step
  // above separates them, by moving vertices). Needs sigma_vox > 0.
  double nest_gap_vox = 0.5;
};

// Throws Error("", "<option>: ...") naming the bad option.
void validate(const SurfaceOptions& o);

// The options as a JSON object (for provenance and reports).
std::string surface_parameters_json(const SurfaceOptions& o);

// ---- metrics -----------------------------------------------------------------------------
struct SurfaceMetrics {
  std::int64_t faces = 0, vertices = 0;  // of the surface as returned
  std::int64_t extracted_faces = 0;      // before decimation
  std::int64_t solid_voxels = 0;         // voxels of the solid (after fill_holes)
  std::int64_t filled_voxels = 0;        // of those, added by fill_holes
  double volume_m3 = 0;                  // signed (> 0: outward)
  double area_m2 = 0;
  double smooth_volume_change = 0;       // (V after Taubin - V before) / V before
  std::int64_t clamped_to_caps = 0;      // vertices smoothing had carried past the volume's border planes, moved back
  int euler = 0;                         // V - E + F over all components
  int components = 0;                    // edge-connected components
  int dropped_components = 0;            // components dropped as specks (min_component_voxels)
  double dropped_volume_m3 = 0;          // their enclosed volume, summed (|volume| each)
  std::int64_t gap_samples = 0;          // inside samples of the field lowered below the parent's (nest_gap_vox)
  bool closed = false;                   // every edge in exactly two faces, traversed opposite ways
  bool manifold = false;                 // every vertex a single fan of faces, no isolated vertex
  bool outward = false;                  // volume_m3 > 0
  std::int64_t self_intersections = -1;  // intersecting face pairs (CGAL); -1: not checked
  // wall time per phase (s)
  double solid_s = 0, field_s = 0, extract_s = 0, smooth_s = 0, decimate_s = 0, check_s = 0;
  double total_s() const { return solid_s + field_s + extract_s + smooth_s + decimate_s + check_s; }
};

struct SurfaceResult {
  Surface surface;
  SurfaceMetrics metrics;
  // the check's intersecting face pairs (face ids), when it looked for them
  // (untangle_surface takes them rather than testing the surface again)
  std::vector<std::array<std::int64_t, 2>> intersecting_pairs;
};

// ---- nesting ------------------------------------------------------------------------------
// parent[v] is the label that encloses label v (0: background, the outermost),
// parent[0] = -1; size label_names.size() (at least the largest label + 1).
//
// From a tissue table: its "inside" relation, matched to the volume's label
// names (a tissue with no "inside" or one absent from the volume has parent
// 0). Throws Error(table.path, ...) when a volume label name is not in the table.
std::vector<int> label_parents(const Volume& v, const TissueTable& table);
// Inferred from the volume when no table is at hand: each label's parent is
// the label (background included) it shares the most voxel faces with. For
// an onion of shells (skin > fat > muscle > bone > marrow, vessels in
// muscle) this is the anatomical nesting, because a shell's outer boundary is
// larger than its inner one. Where two labels touch each other most (a
// cycle), the one nearer the background (breadth-first depth over contacts
// of at least 2 % of a label's faces) takes instead the shallower label it
// shares the most faces with.
std::vector<int> label_parents(const Volume& v);

// The labels of `tissue`'s solid: its own label and every label nested in it
// (transitively), sorted. Throws Error("", "unknown tissue '...' (the volume
// has: ...)") for a name that is not a non-background label of the volume.
std::vector<int> solid_label_set(const Volume& v, const std::string& tissue, const std::vector<int>& parents);

// ---- extraction -----------------------------------------------------------------------------
// The closed outward surface of the voxels whose label is in `solid_labels`
// (values 1..255), through steps 1-6 above. Throws Error("", ...) when the
// volume is malformed or no voxel has one of the labels, and std::logic_error
// if the result fails the closed/manifold/outward check (a bug).
//
// parent_labels: the solid labels of the tissue it is nested in (its
// solid_label_set), or empty. Then where the two solids' blurred indicators
// come within nest_gap_vox of each other the nested one is lowered below the
// parent's (see nest_gap_vox): the surfaces no longer coincide where the
// parent's shell is missing.
SurfaceResult extract_surface(const Volume& v, const std::vector<int>& solid_labels, const SurfaceOptions& o,
                              const std::vector<int>& parent_labels = {});

// Taubin lambda|mu smoothing with uniform weights (G. Taubin, "A signal
// processing approach to fair surface design", SIGGRAPH 1995): each iteration
// moves every vertex by lambda * L(p) then by mu * L(p), L(p) = mean of the
// neighbours - p. Parallel, deterministic. Needs a closed surface.
// With fixed_axes (one entry per vertex, or empty), bit k set keeps that
// vertex's coordinate k (the flat caps at the volume border stay flat).
void taubin_smooth(Surface& s, int iterations, double lambda, double mu,
                   const std::vector<std::uint8_t>& fixed_axes = {});

// Moves every vertex out by sigma_vox^2 H along its normal, in voxel units
// (coordinates divided by spacing_m, where the blur was isotropic), H the
// mean curvature (cotangent Laplacian, barycentric areas, clamped to radii of
// at least one voxel and averaged over 8 rings of neighbours). This undoes
// to first order the shift of the 0.5 level of a Gaussian-blurred indicator
// (a ball of radius r comes out with radius r - sigma^2 / r). fixed_axes as
// for taubin_smooth.
void compensate_blur(Surface& s, const std::array<double, 3>& spacing_m, double sigma_vox,
                     const std::vector<std::uint8_t>& fixed_axes = {});

// Edge-collapse decimation (CGAL Surface_mesh_simplification) of a closed
// triangle surface to at most target_faces faces (>= 4). The result is
// compacted (no unused vertices). Throws Error("", ...) if the input is not a
// closed oriented 2-manifold.
Surface decimate_surface(const Surface& s, std::int64_t target_faces, DecimationCost cost, bool bounded_normal_change);

// Topology and size of a triangle surface: faces, vertices, volume, area,
// Euler characteristic, components, closed, manifold, outward; with
// `self_intersections`, the number of intersecting face pairs (CGAL). Never
// throws on a bad surface: it reports it.
SurfaceMetrics check_surface(const Surface& s, bool self_intersections = true);

// Intersecting pairs of non-adjacent faces (CGAL
// Polygon_mesh_processing::self_intersections); 0 for an embedded surface.
std::int64_t surface_self_intersections(const Surface& s);
// The pairs themselves (face ids, in CGAL's order).
std::vector<std::array<std::int64_t, 2>> surface_self_intersection_pairs(const Surface& s);

// Keeps `inner` inside `outer` (both closed and outward; inner is a tissue
// nested in outer's): every vertex of inner that lies outside outer, or
// inside but closer than clearance_m to it, moves to its closest point on
// outer and then clearance_m inwards along that face's normal. The surfaces
// of nested tissues are extracted, smoothed and decimated separately, so
// where a shell is about a voxel thin (cortical bone around marrow) they can
// cross by a fraction of a voxel; the remesh and build stages need strict
// nesting. Vertices on a flat border cap that inner shares with outer stay:
// outer's faces whose corners lie on one of `caps` (cap_planes of the volume
// both come from), or without caps, in a plane of outer's bounding box.
// Parallel, deterministic.
struct NestingResult {
  std::int64_t moved = 0;          // vertices moved
  std::int64_t outside = 0;        // of those, outside outer before
  double max_move_m = 0;           // the largest move (m)
  std::int64_t moved_again = 0;    // extra moves of vertices the first move carried through a shell thinner than the clearance
  std::int64_t still_outside = 0;  // vertices outside outer after (0 unless outer is very thin there)
  std::int64_t on_cap = 0;         // left on a border cap they share with outer (coplanar flat caps)
  std::int64_t cap_lookups = 0;    // of the vertex tests (the untangling's included), those a cap face lookup settled
  std::int64_t folds = 0;          // intersecting face pairs after the moves (near moved vertices, and with cap_folds near inner's caps)
  int untangle_rounds = 0;         // rounds of relaxing them (each: relax, keep inside, test again)
  std::int64_t folds_left = 0;     // intersecting pairs near relaxed vertices after them (0 unless 20 rounds, or 3 without progress, did not do)
};
// The planes of the flat caps where a volume's border cuts a surface
// extracted from it (extract_surface, steps 3): per axis, border_offset / 2
// spacings outside the first and the last voxel centres, computed as the
// extraction places a cap vertex, so the cap vertices lie on them exactly.
// Smoothing leaves the cap vertices in their plane, but may carry the
// vertices next to the rim slightly past it: a surface's bounding box is not
// its caps' planes.
struct CapPlane {
  int axis = 0;      // 0 x, 1 y, 2 z
  double at = 0;     // m
  double reach = 0;  // m: how far in the border shapes the surface (the blur's reach, ceil(3 sigma) + 1 spacings)
};
std::vector<CapPlane> cap_planes(const Volume& v, const SurfaceOptions& o);

//
// cap_folds: the untangling also takes the folds next to inner's own caps
// (within a plane's reach of one of `caps`): there the field is replicated
// beyond the border and smoothing holds the cap vertices along their axis,
// and on thin stacks the faces there fold. The caps' vertices
// used to be moved on every stack (see CapPlane), and that untangled these
// folds as a side effect: the real crop halved, 8 slices, kept 678 face
// pairs in its fat where 88 were left before, until the untangling took them.
NestingResult enforce_nesting(Surface& inner, const Surface& outer, double clearance_m,
                              const std::vector<CapPlane>& caps = {}, bool cap_folds = true);
// The same against an outer surface prepared once (its mesh, the AABB tree
// and the distance queries' search tree, its cap faces: most of the cost on
// large surfaces) and shared by every tissue nested in it, read-only, from
// several threads at once.
// A vertex of inner lying exactly in one of outer's cap planes, on a face
// of outer exactly in that plane, is found there by a lookup on a grid of
// those faces instead of the queries (which fall back to exact arithmetic for
// such points); the result is the same. cap_lookup = false: every vertex
// takes the queries (the reference the lookup is tested against).
struct NestingIndex;
std::shared_ptr<const NestingIndex> make_nesting_index(const Surface& outer, const std::vector<CapPlane>& caps = {},
                                                       bool cap_lookup = true);
NestingResult enforce_nesting(Surface& inner, const NestingIndex& outer, double clearance_m, bool cap_folds = true);

// Untangles an outermost surface (one no nesting moves: the skin): the
// faces that intersect others (CGAL, over the whole surface), and those
// within two rings of them, are relaxed as enforce_nesting relaxes its folds,
// in rounds until none intersect; the vertices on one of `caps` stay (a cap
// stays flat). Smoothing folds a thin, torn shell where it meets itself: the
// real crop's skin as 8 slices had 196 intersecting face pairs. Untangle it
// before nesting the tissues inside it. Deterministic.
struct FoldsResult {
  std::int64_t folds = 0;      // intersecting face pairs before
  int untangle_rounds = 0;     // rounds of relaxing them
  std::int64_t folds_left = 0; // pairs near relaxed vertices after them (0 unless the rounds ran out)
};
// pairs: the surface's intersecting pairs when known (SurfaceResult::
// intersecting_pairs: a whole-surface test took 28 s on the real crop's 1.6 M
// skin faces); null: tested here.
FoldsResult untangle_surface(Surface& s, const std::vector<CapPlane>& caps,
                             const std::vector<std::array<std::int64_t, 2>>* pairs = nullptr);

// Unsigned distance (m) from each point (n x 3, m) to the surface's
// triangles (CGAL AABB tree), in parallel. For accuracy tests and reports.
VecXd distance_to_surface(const Surface& s, const MatX3d& points);

// Points on the surface for distance statistics: every vertex, every face
// centroid and every edge midpoint ((V + F + E) x 3, m; the edges taken from
// the half-edges a -> b with a < b, each edge once on a closed surface).
MatX3d surface_samples(const Surface& s);

}  // namespace orthosim
