// vessels: centreline tree -> Bezier tube tree with bifurcation patches
// (paper §3: "the centreline of the entire vascular structure have to be
// extracted first ... a tree structure is deployed ... a series of Bezier
// curves are fitted onto the extracted centreline where the distribution of
// control points depend on the local curvature ... Bifurcations are handled
// through a modified Bezier triangle ... the external surface structure are
// modeled through a swap of local frame"). docs/vessels.md describes the
// method, the tree rules and the limitations.
//
// Pipeline, all on plain data (Volume in, VesselTree out):
//   crop the tissue's voxels -> anisotropic exact distance transform ->
//   distance-ordered topology-preserving 3-D thinning -> skeleton graph ->
//   spur pruning, loop breaking, contact cutting -> rooted tree ->
//   sub-voxel re-centring and radii from cross-sections -> junction regions
//   (children's inscribed spheres) -> curvature-adaptive C1 cubic Bezier per
//   branch -> rings swept with rotation-minimising frames, bifurcation
//   patches, caps -> one closed quad mesh per tree.
//
// Units: metres throughout, the physical frame of the image stack
// (libmodel/format/model.h). No CGAL in this header: the CGAL peer and the
// self-intersection test are plain functions over Surface.
#pragma once

#include "libmodel/format/model.h"

#include <Eigen/Core>

#include <cstdint>
#include <string>
#include <vector>

namespace orthosim {

// ---- options -----------------------------------------------------------------
struct VesselOptions {
  // Largest distance (m) between the fitted Bezier curve and the extracted
  // centreline. 0: a quarter of the smallest voxel spacing. >= 0.
  double tolerance_m = 0;
  // Root points (m): the vessel end nearest to each becomes the root of its
  // tree when it lies within 3 local radii + 2 voxels of that end (a point
  // near no end of this tissue is ignored: VesselMetrics::roots_used says
  // which applied). Trees without a root point are rooted at their
  // largest-radius end.
  std::vector<Eigen::Vector3d> roots_m;
  // A terminal skeleton branch shorter than spur_ratio x the inscribed radius
  // at its junction is a spur and is removed. > 0.
  double spur_ratio = 1.5;
  // A junction-to-junction skeleton edge whose narrowest inscribed radius is
  // below neck_ratio x the radius of the vessels on both sides is a contact
  // between two touching vessels and is cut at its narrowest point. [0, 1).
  double neck_ratio = 0.5;
  // Skeleton components whose total length is below min_length_ratio x their
  // largest inscribed radius are dropped (reported). >= 0.
  double min_length_ratio = 3.0;
  // Where a tissue has a resolved piece, skeleton components whose largest
  // inscribed radius (the distance transform less half a voxel) is below
  // min_radius_voxels x the smallest voxel spacing are dropped as noise
  // (reported): with the default 0.75 these are the pieces with no voxel
  // whose neighbours across its faces (in the finest directions) are all
  // the tissue's, nowhere more than 2 voxels across, which is what
  // segmentation noise makes of misclassified voxels (the phantom at 8-bit
  // noise 20-24 gave 2-53 such trees a vessel, each 1-2 voxels thick); a
  // tube that thin would be finer than the voxels. When no piece reaches
  // it (a stack too coarse for its vessels) none is dropped so. >= 0 (0: none).
  double min_radius_voxels = 0.75;
  // Two junctions closer than merge_ratio x their larger inscribed radius
  // are one junction (a trifurcation when it then has three children). >= 0.
  double merge_ratio = 1.0;
  // The children's tube rings start where their inscribed spheres are apart
  // by at least patch_gap x their mean radius (room for the crotch). >= 0.
  double patch_gap = 0.5;
  // Most children a junction may have. 2..4.
  int max_children = 3;
  // A junction with more children loses its shortest leaf children (counted
  // in the metrics); false: refused with a message, as it is when too few of
  // its children are leaves.
  bool prune_excess_children = true;
  // Vertices around each tube ring: a multiple of 4 and, at a junction with
  // n children, of 2n (24 serves n = 2, 3, 4). 8..256.
  int ring_vertices = 24;
  // Ring spacing along the tube / edge length around the ring (2 pi r / k). > 0.
  double ring_spacing = 1.0;
  // Count the tube mesh's self-intersections (CGAL, about 0.1 s per tree).
  bool check_self_intersections = true;
};

// Throws Error("", "...") naming the bad option.
void validate(const VesselOptions& o);
// The options as a JSON object (for provenance and reports).
std::string vessel_parameters_json(const VesselOptions& o);

// ---- metrics -------------------------------------------------------------------
struct VesselEnd {
  Eigen::Vector3d position_m{0, 0, 0};
  double radius_m = 0;
  int branch = -1;
  bool root = false;
  bool open = false;  // cut by the volume border: the vessel goes on outside
};

// A place where the skeleton was cut: "loop" (a cycle broken at its thinnest
// edge), "contact" (a narrow bridge between touching vessels) or "spur".
struct VesselCut {
  std::string kind;
  Eigen::Vector3d position_m{0, 0, 0};
  double radius_m = 0;  // inscribed radius at the cut
};

struct VesselMetrics {
  std::string tissue;
  int label = 0;
  std::int64_t voxels = 0;            // tissue voxels
  std::int64_t skeleton_voxels = 0;   // after thinning
  int trees = 0, branches = 0;
  int bifurcations = 0, trifurcations = 0;
  int spurs_pruned = 0;
  int children_pruned = 0;            // leaves dropped at junctions with more than max_children
  double pruned_length_m = 0;         // their total centreline length
  int loops_broken = 0, contacts_cut = 0;
  int components_dropped = 0;         // too small to be a vessel (specks, thin components included)
  int thin_components_dropped = 0;    // of which nowhere min_radius_voxels across (noise)
  std::vector<VesselEnd> ends;
  std::vector<VesselCut> cuts;        // loops and contacts (not spurs)
  std::vector<int> roots_used;        // indices into VesselOptions::roots_m that rooted a tree
  double radius_min_m = 0, radius_max_m = 0;
  double length_m = 0;                // total centreline length
  double tolerance_m = 0;
  int bezier_pieces = 0;
  double bezier_max_deviation_m = 0;  // fitted curve vs centreline nodes
  std::int64_t tube_vertices = 0, tube_quads = 0, tube_tris = 0;
  bool tube_closed = false, tube_manifold = false, tube_oriented = false;
  int tube_components = 0;            // one per tree when all is well
  int self_intersections = -1;        // intersecting face pairs; -1 when not checked
  // Tube vertices to the voxel boundary of the label (faces between tissue and
  // other voxels); cap vertices of open ends are left out.
  double boundary_mean_m = 0, boundary_p95_m = 0, boundary_max_m = 0;
  // Phase wall times (s).
  double distance_s = 0, thinning_s = 0, graph_s = 0, centreline_s = 0, fit_s = 0, tube_s = 0, check_s = 0;
};

struct VesselResult {
  VesselTree tree;
  VesselMetrics metrics;
};

// ---- the stage -------------------------------------------------------------------
// Extracts the vessel forest of `tissue` from the label volume: the sampled
// centreline graph (branch by branch, children start at their parent's end
// node), the tree, the Bezier control points and the closed tube mesh (one
// component per tree). Deterministic for any thread count.
// Throws Error("", ...) when the tissue is not in v.label_names, has no
// voxels, leaves nothing after clean-up, or has a junction with more than
// max_children children that pruning (prune_excess_children) cannot mend.
// A tissue whose voxels form no vessel (every piece shorter than
// min_length_ratio radii) throws NoVesselError, so a caller may leave that
// tissue out (orthosim vessels --skip-unformed) instead of failing.
VesselResult extract_vessels(const Volume& v, const std::string& tissue, const VesselOptions& o);

class NoVesselError : public Error {
 public:
  using Error::Error;
};

// ---- Bezier evaluation -------------------------------------------------------------
// Number of cubic pieces of branch b.
int bezier_pieces(const VesselTree& t, int b);
// Point, radius and derivative of piece `piece` of branch b at t in [0, 1].
Eigen::Vector3d bezier_point(const VesselTree& t, int b, int piece, double u);
Eigen::Vector3d bezier_derivative(const VesselTree& t, int b, int piece, double u);
double bezier_radius_at(const VesselTree& t, int b, int piece, double u);

// ---- checks shared by the stage, the tests and the benchmark ------------------------
// Topology of a polygon mesh given as quads and triangles over `vertices`.
struct MeshCheck {
  int components = 0;
  int boundary_edges = 0;       // used by one face
  int nonmanifold_edges = 0;    // used by three or more faces
  int nonmanifold_vertices = 0; // faces around the vertex are not one fan
  int misoriented_edges = 0;    // two faces traverse the edge the same way
  int degenerate_faces = 0;     // repeated vertex or zero area
  std::vector<int> euler;       // V - E + F of each component (2: a sphere)
  double volume_m3 = 0;         // signed volume (> 0: outward)
  bool closed() const { return components > 0 && boundary_edges == 0; }
  bool manifold() const { return nonmanifold_edges == 0 && nonmanifold_vertices == 0; }
  bool oriented() const { return misoriented_edges == 0; }
};
MeshCheck check_mesh(const MatX3d& vertices, const MatX4i& quads, const MatX3i& tris);

// The tube mesh of a tree as triangles (each quad split along its shorter diagonal).
Surface tube_triangles(const VesselTree& t);

// Distance (m) from each point to the voxel boundary of `label` in `v` (the
// squares between a voxel of the label and a 6-neighbour of another label).
// Points farther than max_m get max_m.
VecXd distance_to_label_boundary(const Volume& v, int label, const MatX3d& points, double max_m);

// A closed, manifold triangle surface of the voxels of `label` (marching
// tetrahedra on the label's indicator, smoothed by a Gaussian of
// `smooth_vox` voxels; outside the volume counts as other tissue).
Surface label_surface(const Volume& v, int label, double smooth_vox);

// ---- comparison with a true centreline (tests, benchmark) ----------------------------
struct CentrelineError {
  double mean_m = 0, max_m = 0;     // extracted nodes to the true polyline
  double truth_mean_m = 0, truth_max_m = 0;  // true nodes to the extracted polyline
  double overlap_extracted = 0;     // share of extracted nodes within the true local radius of the truth
  double overlap_truth = 0;         // share of true nodes within the extracted local radius
  double radius_mean_rel = 0;       // mean |r - r_true| / r_true over extracted nodes
  double radius_p95_rel = 0, radius_max_rel = 0;
};
// Both trees' polylines are their edges (nodes, edges). Radii from `radii`.
CentrelineError compare_centrelines(const VesselTree& extracted, const VesselTree& truth);
// The same for a bare graph (CGAL skeleton): nodes and edges only, no radii
// (overlap uses the truth radius both ways).
CentrelineError compare_centrelines(const MatX3d& nodes, const MatX2i& edges, const VesselTree& truth);

// ---- the CGAL peer (benchmark only) ----------------------------------------------------
struct SkeletonGraph {
  MatX3d nodes;  // (n x 3) m
  MatX2i edges;  // (m x 2)
  int branches = 0;       // maximal paths between nodes of degree != 2
  int junctions = 0;      // nodes of degree >= 3
};
// CGAL::Mean_curvature_flow_skeletonization with its default parameters
// (scaled to the mesh) on a closed triangle surface. Throws Error("", ...)
// when the surface is not a closed 2-manifold.
SkeletonGraph cgal_mcf_skeleton(const Surface& s);

// ---- files ----------------------------------------------------------------------------
// Binary STL of the tube (triangulated), OBJ of the tube (quads and
// triangles), OBJ of the centreline (one polyline per branch). Atomic.
void write_tube_stl(const std::string& path, const VesselTree& t);
void write_tube_obj(const std::string& path, const VesselTree& t);
void write_centreline_obj(const std::string& path, const VesselTree& t);

}  // namespace orthosim
