// Incision: cutting the mass-spring tissue along a polyline to a depth
// (paper §5, Fig. 4a/b: "an incision is made ... held open by hooks").
//
// The blade sweeps a ruled surface: every segment p_i p_{i+1} of the
// polyline is moved along the inward direction d by the depth, giving the
// quad p_i, p_{i+1}, p_{i+1} + depth d, p_i + depth d (started a little
// outside the polyline, `lead` x depth against d, so that the springs of the
// skin surface the polyline lies on are caught too). A linear spring whose
// segment between its two ends' *current* positions crosses that surface is
// severed (removed from the model; a biphasic pair goes together, since both
// join the same two nodes), and so is a volume term's group of tetrahedra
// with an edge across it. Surface quads with an edge or a diagonal across
// the blade are removed from the rendered and collision surface, leaving the
// wound open. Vessel centreline edges the blade crosses are reported with
// the crossing point and the vessel radius there: a scene turns them into
// bleeding emitters.
//
// The model stays immutable for the solver: a cut edits a copy and calls
// Model::finalize() again (runtime/model.h); node ids do not change, so a
// State and the tools' node lists stay valid. Nodes left with no spring at
// all are reported (a scene pins them: a lone mass point is not tissue). The
// layer columns whose top and bottom the blade parts are recorded
// (Model::severed_columns): the inversion check skips them.
//
// Cost: O(n_springs + n_quads + n_vessel_edges) per cut after an AABB test
// against the blade, plus finalize() (O(n_springs log n_springs)).
#pragma once

#include "runtime/model.h"
#include "runtime/types.h"

#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace orthosim::runtime {

struct CutDef {
  std::vector<Vec3> polyline;  // (>= 2 points) m, on or just outside the tissue surface
  // Inward unit direction of the blade. Zero: automatic, from the polyline's
  // midpoint (along its length: a repeated point does not move it) towards the
  // nearest point of the principal axis of the model's rest positions (the limb
  // axis of a limb-like model).
  Vec3 direction{0, 0, 0};
  Real depth = 0;   // m, > 0: how deep the blade goes along `direction`
  Real lead = 0.1;  // the blade starts lead x depth outside the polyline, [0, 1]
  // Node snapping (Nienhuys and van der Stappen 2001), [0, 0.5): a node
  // within node_snap x (its shortest spring's rest length in the uncut model,
  // Model::shortest_spring) of a blade triangle's plane counts as on it, which
  // leaves it with the tissue behind the blade; a segment from it meets the
  // blade at its projection. A blade along a grid line otherwise passes the
  // line's nodes a hair to either side, as the tissue has moved them, and
  // cuts their springs along the line and through the layers in a zigzag
  // that depends on sub-millimetre motion. 0: the exact sides.
  Real node_snap = 0.25;
};

// Throws Error("", ...) naming the problem (fewer than 2 points, non-finite
// coordinates, depth <= 0, a zero-length polyline, lead outside [0, 1]).
void validate(const CutDef& def);

struct VesselHit {
  int vessel = 0;          // index into Model::vessels
  std::int32_t edge = 0;   // edge of that vessel's centreline
  Real along = 0;          // where on the edge: 0 at its first node, 1 at its second
  Vec3 point;              // m, where the blade crosses the centreline (as carried by the tissue)
  Vec3 tangent;            // unit centreline direction there
  Real radius = 0;         // m, vessel radius there (interpolated)
};

struct CutReport {
  Vec3 direction;                      // the blade direction used (unit)
  std::int32_t springs_cut = 0;        // linear springs removed
  std::int32_t tets_cut = 0;           // volume-term tetrahedra removed (their group had an edge across the blade)
  std::int32_t quads_removed = 0;      // surface quads removed
  std::int32_t columns_opened = 0;     // tissue columns it opened for the blood (WoundColumns)
  std::int32_t columns_severed = 0;    // layer columns (layer_columns) whose top and bottom it parted (Model::severed_columns)
  std::int32_t vessel_edges_open_already = 0;  // crossed vessel edges an earlier cut had opened (no new wound)
  bool quads_loaded = false;           // the model had surface quads to cut (a scene loads them only when it draws or collides with them)
  std::vector<std::int32_t> detached;  // nodes left without any spring, ascending
  std::vector<VesselHit> vessel_hits;
  std::string tool;                    // the scene tool that made it (set by Scene; empty for Scene::cut)
  Real time = 0;                       // s, when it was made (set by Scene)
};

// The tissue's columns, for the blood's wound walls. The loaded layers' top
// quad grids share one quad pattern (remesh's corresponding grids; the
// builder offsets one pattern per layer), so quad k of surface l and quad k of
// surface l + 1 bound one column of layer l: a hexahedron of tissue. The
// blood may enter a column only once a cut has opened it; the collision
// surface is then every surface quad that does not lie between two open
// columns (or an open column and the outside), a side wall between an open
// and a closed column, and an end wall on each column side at the grid's
// boundary (the limb's open ends: without them the gaps between the layer
// surfaces were open to the blood there). Without walls inside the tissue, a
// vein cut deep in the limb bled into the gap between two layer surfaces and
// the blood ran along it the whole limb's length (2026-11-27).
struct WoundColumns {
  std::int32_t n_surfaces = 0;          // loaded layer surfaces with quads, outer to inner
  std::int32_t n_quads = 0;             // quads per surface
  std::vector<std::int32_t> corners;    // (n_surfaces x n_quads x 4) local node ids
  std::vector<std::int32_t> neighbour;  // (n_quads x 4) quad across side c (corners c, c+1); -1: the grid's boundary
  std::vector<std::uint8_t> open;       // ((n_surfaces - 1) x n_quads) 1: a cut has opened the column
  bool valid() const { return n_surfaces >= 2 && n_quads > 0; }
  std::int32_t corner(std::int32_t surface, std::int32_t quad, int c) const {
    return corners[(static_cast<std::size_t>(surface) * static_cast<std::size_t>(n_quads) + static_cast<std::size_t>(quad)) * 4 +
                   static_cast<std::size_t>(c)];
  }
};

// The columns of an uncut model: its quads grouped by the layer of their
// corners (Model::node_layer), outer to inner (LayerInfo::order). Not valid
// (n_surfaces < 2) unless two or more layers have quads with one pattern
// (the same corners relative to each layer's first node, quad by quad).
WoundColumns wound_columns(const Model& m);

// Opens the column each point lies in (the one containing it, else the nearest
// by centroid whose corners' sphere holds it; none for a point outside them
// all) at the node positions `x`; returns how many it opened. A scene opens
// those of its emitters' discs (the centre, the vessel crossing, and points on
// the rim and half-way out), which may reach past the crossing's column (a disc
// on a column corner spans four).
std::int32_t open_columns_at(WoundColumns& w, std::span<const Real> x, const std::vector<Vec3>& points);

// The blood's collision triangles of the columns ((n x 3) local node ids),
// as described at WoundColumns.
std::vector<std::int32_t> wound_wall_triangles(const WoundColumns& w);

// The blade direction a CutDef resolves to on model `m` (unit).
Vec3 cut_direction(const Model& m, const CutDef& def);

// Cuts `m` in place at the node positions `x` ((n_nodes x 3) m, usually
// State::x) and re-finalizes it. Never produces non-finite data; throws
// Error("", ...) only for an invalid def (call validate first to check).
// With `columns` (valid), also opens the columns the blade crosses (any of
// their edges, face diagonals or vertical edges across it). A scene then opens
// the columns its new emitters' discs reach (open_columns_at), so a bleeding
// vessel's emitter is always inside the wound.
// vessel_x: per vessel of m, its centreline's nodes where the tissue has
// carried them ((n x 3) m, carried_positions); empty: at rest.
CutReport cut_model(Model& m, std::span<const Real> x, const CutDef& def, WoundColumns* columns = nullptr,
                    std::span<const std::vector<Real>> vessel_x = {});

// Points the tissue carries: the vessel centrelines (stored at rest) and the
// wounds' emitters. Each point moves by the mean displacement of its k
// nearest nodes at rest, weighted by 1 / (d^2 + s^2) (Shepard's inverse
// distances; s, a hundredth of the distance to the k-th nearest, keeps a
// point on a node finite and close to that node's motion): a translation carries it
// exactly, and a smooth deformation to first order in the node spacing. A
// cut tests the vessels where the tissue has carried them, so the blade meets
// the vessel inside the tissue it cuts; the vessels used to stay at rest while
// the tissue sagged (1-2 cm in the sample's bleeding scene by the cut at
// 0.1 s), and the cut bled where the vessel would have been.
struct Carried {
  int k = 0;
  std::vector<Real> rest;          // (n x 3) m, the points at rest
  std::vector<std::int32_t> node;  // (n x k) their nearest nodes at rest
  std::vector<Real> weight;        // (n x k), each row sums to 1
};
Carried carry_points(const Model& m, std::span<const Real> points, int k = 8);
// The points at the node positions x (n_nodes x 3): (n x 3) m.
std::vector<Real> carried_positions(const Carried& c, const Model& m, std::span<const Real> x);

// Segment p q against triangle a b c: true when they cross (Moller and
// Trumbore 1997 with the segment parameter in [0, 1]); degenerate triangles
// never cross.
bool segment_crosses_triangle(const Vec3& p, const Vec3& q, const Vec3& a, const Vec3& b, const Vec3& c,
                              Real* t = nullptr);

}  // namespace orthosim::runtime
