// remesh: re-parameterise closed, tube-like tissue surfaces into structured
// nu x nv quad grids whose layers correspond (paper §3: "by re-parameterizing
// the polygonal surface meshes into a quad-based surface, we can easily
// control the complexity of the surface"). docs/remesh.md describes the
// method, the treatment of the two ends and what is refused.
//
// Pipeline, all on plain data (Surface / QuadSurface of libmodel/format/model.h):
//   read_stl -> check_closed_surface -> find_tube_sweep (axis, ring planes,
//   rotation-minimising frames) -> remesh_layers (rings of the outer surface,
//   inner surfaces sampled on the same rays) -> evaluate_remesh (distances,
//   quad quality, layer alignment).
//
// Units: metres throughout; the physical frame of the image stack.
#pragma once

#include "libmodel/format/model.h"
#include "libmodel/format/stl.h"  // read_stl, write_stl (the stage's input)

#include <Eigen/Core>

#include <array>
#include <cstdint>
#include <string>
#include <vector>

namespace orthosim {

// ---- input checks ----------------------------------------------------------
struct SurfaceCheck {
  int components = 0;       // edge-connected components
  int euler = 0;            // V - E + F (2 per sphere-like component)
  double area_m2 = 0;
  double volume_m3 = 0;     // signed: > 0 when the faces are outward
};

// Checks that `s` is a usable closed surface: non-empty, finite coordinates,
// valid face ids, every edge shared by exactly two faces traversing it in
// opposite directions, every vertex a single fan (manifold), and, when
// `single_component`, exactly one connected component. Throws
// Error(name, "<one line>") for the first problem found.
SurfaceCheck check_closed_surface(const Surface& s, const std::string& name, bool single_component);

// ---- options ---------------------------------------------------------------
// Where the end ring of a flat cap sits.
enum class EndRings {
  rim,     // on the cap's rim (just inside the cap plane)
  crease,  // just past the crease: the wall faces that touch the cap (default)
};

enum class RingSampling {
  arc_length,  // nu points at equal arc length around each ring (default: even edges)
  angle,       // nu rays at equal angles from the ring centre (star-shaped sections)
};

struct RemeshOptions {
  int nu = 39;  // points around each ring (periodic), in [3, 10000]
  int nv = 9;   // rings along the axis, in [2, 10000]
  RingSampling around = RingSampling::arc_length;
  // Flat caps: the wall faces that share a vertex with the cap join it to the
  // wall. On a voxel surface they are the staircase that closes the volume at
  // the stack's boundary, and a ring through them is jagged in every layer
  // (on the segmented sample at 400x100 the fat's end ring inverted skin
  // cells). `crease` puts the end rings where those faces end (0.45 mm on the
  // sample, one face row of an analytic mesh; at most 5 % of the length),
  // leaving that strip of the wall out; `rim` keeps them on the cap's rim.
  EndRings ends = EndRings::crease;
  // Arc-length sampling measures each section's length on the section
  // smoothed by a box of 2 arc_window + 1 vertices. A section's vertices are
  // where it crosses the input's edges, so the window is in units of the
  // input's resolution: the staircase of a voxel surface (jagged at that
  // scale, most of all where a flat cap meets the wall: 7 % longer there on
  // the segmented sample) no longer shifts the phase of a ring against its
  // neighbours, while features larger than the window keep their length.
  // 0: the raw section. In [0, 64].
  int arc_window = 4;
  // Place more rings where the surface bends along the axis (the axis curves
  // or the section changes fast): stations equidistribute sqrt(|d2p/ds2|),
  // the spacing that equalises the O(h^2) chord error. Off: equal arc length.
  bool adaptive = true;
  double max_spacing_ratio = 3.0;  // adaptive: largest / smallest station spacing, >= 1
  int axis_sections = 64;          // sections used to find the axis, in [8, 4096]
  int axis_iterations = 3;         // centroid refinements of the axis, in [0, 20]
  // Ends that are not flat caps (rounded or closed tubes): the end rings sit
  // where the section area has fallen to this fraction of the largest section.
  double end_area_fraction = 0.25;  // in (0, 1)
  // Flat caps: faces whose normals are within this angle of the end face's
  // normal and coplanar with it form the cap.
  double cap_angle_deg = 3.0;  // in (0, 45)
  // Inner surfaces: points filled where a ray misses the inner surface are
  // kept at most this fraction of the way from the ray origin to the
  // enclosing layer.
  double fill_max_depth_fraction = 0.98;  // in (0, 1)
  // Inner layers follow the outer layer's in-plane normals; where normals
  // cross (a concave or thick stretch) the order is restored with corresponding
  // inner vertices at least this fraction of the mean inner spacing apart.
  double min_ring_spacing_fraction = 0.2;  // in (0, 1)
  // Ring planes must not cross inside the tube: R_max |dn/ds| (the largest
  // section radius times the turning rate of the plane normal) is kept below
  // this, so rings at the surface are at least (1 - max_plane_turn) of their
  // axial spacing apart; the centreline tangent is averaged until it holds.
  double max_plane_turn = 0.5;  // in (0, 1)
};

// Throws Error("", "...") naming the bad option (e.g. "grid: nu must be in 3..10000, got 0").
void validate(const RemeshOptions& o);

// ---- the sweep: a smooth one-parameter family of ring planes ----------------
// The plane at arc length s in [0, length_m] passes through centre(s) with unit
// normal normal(s) (pointing towards increasing s); e1(s) is the rotation-
// minimising unit vector in that plane where u = 0 (phase), e2 = normal x e1.
// Stored as a dense table (equal steps in s) and interpolated linearly.
struct TubeSweep {
  double length_m = 0;    // arc length of the centreline between the end rings
  VecXd s;                // (n) arc length of each table entry, m; s[0] = 0, s[n-1] = length_m
  MatX3d centre;          // (n x 3) centreline, m
  MatX3d normal;          // (n x 3) unit plane normals
  MatX3d e1;              // (n x 3) unit phase vectors, orthogonal to normal
  std::array<bool, 2> flat_cap{false, false};       // start, end: closed by a flat cap
  std::array<double, 2> uncovered_m2{0, 0};        // start, end: surface area beyond the end rings
  std::array<double, 2> cap_inset_m{0, 0};         // start, end (flat caps): distance of the end ring inside the cap
  Eigen::Vector3d axis_direction{0, 0, 1};         // principal axis used to start (unit)
  double plane_turn = 0;      // max over the sweep of R_max |dn/ds| (< 1: planes do not cross inside the tube)
  double normal_window_m = 0; // length of the window the tangent was averaged over (0: none needed)
};

// Plane of the sweep at arc length s (clamped to [0, length_m]).
struct SweepPlane {
  Eigen::Vector3d centre, normal, e1, e2;
};
SweepPlane sweep_plane(const TubeSweep& sweep, double s);

// Finds the axis of a tube-like closed surface and the sweep of ring planes:
// principal axis, flat-cap detection, section centroids refined
// `axis_iterations` times on planes normal to the current axis, a smoothed
// cubic centreline, plane normals blended into the cap normals near flat caps
// (so the end rings are the rims of the caps), rotation-minimising frames by
// double reflection (Wang et al. 2008, ACM TOG 27(1):2). Throws Error(name,
// "not tube-like: ...") when a section plane cuts the surface in more than one
// loop or misses the axis (branching, folded or ring-shaped surfaces).
TubeSweep find_tube_sweep(const Surface& outer, const RemeshOptions& o, const std::string& name);

// ---- remeshing -------------------------------------------------------------
struct NamedSurface {
  std::string name;  // tissue name ("skin"), used in messages and outputs
  Surface surface;
};

struct LayerStats {
  std::string name;
  int components = 0;          // of the input surface
  std::int64_t hit = 0;        // vertices exactly on the input surface
  std::int64_t bridged = 0;    // inner: interpolated across angular gaps of a ring
  std::int64_t filled = 0;     // inner: interpolated along the axis (ring misses the surface)
  double normal_blend = 1;     // inner: 1 = on the normals of the layer above, 0 = equal spacing (see remesh_layers)
};

struct RemeshResult {
  TubeSweep sweep;
  std::vector<QuadSurface> layers;  // [0] the outer surface, then the inner ones in order
  std::vector<LayerStats> stats;    // one per layer
  VecXd stations_m;                 // (nv) arc length of each ring along the sweep
  // loops the outer surface's ring planes cut beside the tube's own, left out
  // as noise (each under remesh_detail::kSideLoopAreaRatio of its ring's area)
  std::int64_t side_loops = 0;
  MatX3d ring_centre;               // (nv x 3) centre of each ring plane (on the axis)
  MatX3d ring_normal;               // (nv x 3)
  std::vector<MatX3d> ray_origin;   // per layer (nv x 3): origin of the rays of each ring (layer 0: the ring centres)
  // wall time of the phases: check (topology, then the containment test),
  // axis (axis, sweep, stations; it runs beside the containment test, so the
  // phases may add up to more than total_s), rings
  double check_s = 0, axis_s = 0, rings_s = 0, total_s = 0;
};

// Remeshes `layers[0]` (the outer surface, one component) into an exact
// o.nu x o.nv grid and samples every inner surface layers[1..] at the same
// stations, in the same ring planes: vertex (i, j) of layer k lies on layer
// k's section in ring j where the in-plane inward normal of layer k-1's ring
// at vertex i meets it, blended per layer toward the ray from the section's
// centre (LayerStats::normal_blend) just enough that every ring stays in
// order (thick layers, where normals cross), then made strictly ordered.
// Inner surfaces may have several components (the bones of the forearm): a
// section with several loops is enveloped by their convex hull, and rings
// that miss the layer are interpolated along the axis (counted in
// LayerStats). Quads are (i,j) (i+1,j) (i+1,j+1) (i,j+1), outward; uv =
// (i / nu, s_j / length). Validates every input first and throws
// Error(name, ...) on bad input: an invalid surface (see
// check_closed_surface), several components in the outer surface, a surface
// that is not tube-like, or an inner surface not strictly inside the one
// before it. Deterministic. docs/remesh.md.
RemeshResult remesh_layers(const std::vector<NamedSurface>& layers, const RemeshOptions& o);

// ---- evaluation ------------------------------------------------------------
struct QuadQuality {
  double min_angle_deg = 0, max_angle_deg = 0;  // corner angles over all quads
  double max_aspect = 0, mean_aspect = 0;        // longest / shortest edge of a quad
  double min_edge_m = 0, max_edge_m = 0, mean_edge_m = 0;
  double max_warp_deg = 0;                       // angle between the two triangle normals of a quad
  std::int64_t flipped = 0;                      // quads facing the axis (inward)
  std::int64_t degenerate = 0;                   // quads with an edge or area ~ 0
};
// ring_centre: (nv x 3), the ring centres of RemeshResult (for the outward test).
QuadQuality quad_quality(const QuadSurface& q, const MatX3d& ring_centre);

struct SurfaceDistance {
  double hausdorff_m = 0;          // max of the two one-sided maxima
  double mean_m = 0;               // mean of the two one-sided area-weighted means
  double quad_to_input_max_m = 0, quad_to_input_mean_m = 0;
  double input_to_quad_max_m = 0, input_to_quad_mean_m = 0;
  double compared_input_area_m2 = 0;  // area of the input between the end planes
  std::int64_t samples = 0;
};
// Two-sided distances between the quad surface (each quad split into two
// triangles along (i,j)-(i+1,j+1), sampled k x k per quad) and the part of
// `input` between the first and last ring planes (the caps and any rounded
// ends beyond the end rings are not part of the open tube and are left out;
// their area is reported by the sweep). Point-to-mesh distances from a CGAL
// AABB tree.
SurfaceDistance quad_surface_distance(const QuadSurface& q, const Surface& input, const SweepPlane& first,
                                      const SweepPlane& last, int k = 4);

struct LayerAlignment {
  std::string outer, inner;        // consecutive layers
  double max_normal_angle_deg = 0; // angle between (inner - outer) and the outer layer's inward vertex normal
  double mean_normal_angle_deg = 0;
  double max_lateral_m = 0;        // inner vertex offset across the outer normal
  double max_lateral_rel = 0;      // ... relative to the local quad size
  double ray_in_quad = 0;          // fraction of quads whose inward normal ray from the centroid lands in quad (i,j) below
  double max_ray_miss_m = 0;       // worst distance from that landing point to quad (i,j) below
};
LayerAlignment layer_alignment(const QuadSurface& outer, const QuadSurface& inner, const std::string& outer_name,
                               const std::string& inner_name);

struct RemeshEvaluation {
  std::vector<QuadQuality> quality;          // per layer
  std::vector<SurfaceDistance> distance;     // per layer (the envelope of a multi-component layer included)
  std::vector<LayerAlignment> alignment;     // per consecutive pair
  double worst_lateral_m = 0, worst_lateral_rel = 0, worst_ray_miss_m = 0;
};
RemeshEvaluation evaluate_remesh(const RemeshResult& r, const std::vector<NamedSurface>& inputs, int k = 4);

// ---- containment (containment.cpp) -------------------------------------------
// Per point of `points`: 1 when it lies inside or on the closed, consistently
// oriented surface `closed`, 0 when strictly outside (or not finite). Exact:
// ray parity with CGAL's exact predicates and a symbolic perturbation of the
// ray; no spatial tree (a flat grid of the faces' projections). Points in a
// connected set of grid cells that no face's box reaches share one ray test
// (the first point's). Throws Error on a non-finite vertex or a face's vertex
// id out of range.
struct ContainmentStats {
  std::int64_t points = 0, ray_tests = 0;  // points asked; points that took their own ray
  int empty_components = 0;                // connected sets of empty cells
};
std::vector<char> points_inside(const Surface& closed, const MatX3d& points, ContainmentStats* stats = nullptr);
// Index of the first point of `points` strictly outside `closed`, or -1.
std::int64_t first_point_outside(const Surface& closed, const MatX3d& points);

}  // namespace orthosim
