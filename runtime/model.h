// The runtime's immutable model: what the solver reads and never writes.
//
// A Model is the part of a model file a scene asked for, flattened into
// structure-of-arrays form for the hot loops (counts first, then one array
// per quantity, each documented with its shape and unit). It is built once,
// by the loader (runtime/loader.h) or from in-memory layers
// (assemble_model), and shared read-only by every State that steps it; what
// a step changes lives in State (runtime/state.h).
//
// Node ids here are *local*: 0 .. n_nodes-1, the loaded layers' nodes first
// (in ascending file id), then anchors. `file_id` maps back to the model
// file's global ids. Anchors are nodes of layers the scene did not load that
// springs of loaded layers reach: they are fixed at their rest positions.
//
// Springs are the linear decomposition of the file's springs (lin_* fields):
// a biphasic spring is two linear springs in parallel, the second
// tension-only. They are sorted by (a, b) with a < b so that the springs of
// which node i is the first end form the contiguous range
// [a_first[i], a_first[i+1]); the springs of which it is the second end are
// listed in b_spring[b_first[i] .. b_first[i+1]). The solver gathers forces
// per node through these two lists: no scatter, no atomics, and results that
// do not depend on the thread count.
//
// Topology edits (issue 9's incision) build a new Model: edit the spring
// arrays of a copy and call finalize() again; a State keeps its node arrays.
#pragma once

#include "libmodel/format/model.h"
#include "runtime/types.h"

#include <array>
#include <cstdint>
#include <map>
#include <span>
#include <string>
#include <utility>
#include <vector>

namespace orthosim::runtime {

// The largest coordinate or length (m) a model may hold: nothing anatomical
// comes near it, and squares of it stay far from overflow.
inline constexpr Real kMaxLength = 1e6;

struct Model {
  // ---- counts
  std::int32_t n_nodes = 0;    // simulated nodes, anchors included
  std::int32_t n_anchors = 0;  // nodes [n_nodes - n_anchors, n_nodes) are anchors
  std::int32_t n_springs = 0;  // linear springs
  std::int32_t n_quads = 0;    // surface quads (only when the scene writes surfaces)

  // ---- nodes
  std::vector<Real> rest_x;             // (n_nodes x 3) m, rest positions, physical frame
  std::vector<Real> mass;               // (n_nodes) kg; 0 for anchors
  std::vector<Real> inv_mass;           // (n_nodes) 1/kg; 0 for anchors
  std::vector<std::int32_t> file_id;    // (n_nodes) global node id in the model file
  std::vector<std::int32_t> node_layer; // (n_nodes) index into `layers`, -1 for anchors

  // ---- springs, sorted by (a, b), a < b
  std::vector<std::int32_t> spring_a;       // (n_springs) first end, local id
  std::vector<std::int32_t> spring_b;       // (n_springs) second end, local id
  std::vector<Real> spring_rest;            // (n_springs) m, rest length (>= 0)
  std::vector<Real> spring_k;               // (n_springs) N/m, stiffness (>= 0)
  std::vector<Real> spring_c;               // (n_springs) N s/m, axial damping (>= 0)
  std::vector<std::uint8_t> spring_tension; // (n_springs) 1: tension-only (a biphasic second phase)

  // ---- adjacency (built by finalize)
  std::vector<std::int32_t> a_first;   // (n_nodes + 1) springs with a == i: [a_first[i], a_first[i+1])
  std::vector<std::int32_t> b_first;   // (n_nodes + 1) offsets into b_spring
  std::vector<std::int32_t> b_spring;  // (n_springs) springs with b == i, ascending

  // ---- node-neighbour rows (built by finalize), for the implicit matrix
  // Row i lists node i's distinct neighbours ascending; the springs between
  // i and a neighbour (a biphasic pair) share one 3x3 block.
  std::vector<std::int32_t> nbr_first;  // (n_nodes + 1) offsets into nbr
  std::vector<std::int32_t> nbr;        // (n_entries) neighbour ids
  std::vector<std::int32_t> slot_a;     // (n_springs) entry of spring s in row a: neighbour b
  std::vector<std::int32_t> slot_b;     // (n_springs) entry of spring s in row b: neighbour a

  // ---- volume term (docs/runtime.md, "The volume term")
  // Groups of tetrahedra of layers with a volume_modulus (Layer::tets in
  // groups of Layer::volume_group: a tetra layer's each tetrahedron, a
  // lattice layer's the 6 of each hexahedron):
  // group g adds the energy (k/2) (V - V0)^2 / |V0|, V and V0 the sums of its
  // tetrahedra's signed volumes, so that a layer resists compression and
  // folding through itself (a lattice cell's 6 share one pressure, "mean
  // dilatation", which does not lock; a tetra layer's term per tetrahedron
  // locks a thin layer in bending: docs/msm.md, "The volume term"). A group is kept where all its corners are loaded
  // nodes or anchors and one is loaded.
  std::int32_t n_tets = 0;
  std::vector<std::int32_t> tet;             // (n_tets x 4) local ids
  std::vector<Real> tet_k;                   // (n_tets) Pa, the volume modulus k of the tetrahedron's group
  // (n_tets; empty: all 0, finalize fills it) the group's guard ratio a: 0 for
  // the two-sided term above; in (0, 1) for an inversion guard, one-sided:
  // (k/2) min(0, s V - a |V0|)^2 / |V0|, s the sign of V0 (Layer::guard_modulus,
  // guard_ratio)
  std::vector<Real> tet_guard;
  std::int32_t flat_guards_skipped = 0;      // guarded tetrahedra of zero rest volume, left out by the loader
  std::vector<std::int32_t> tet_group_first; // (n_groups + 1) each group's tetrahedra, consecutive; empty: one group each (finalize fills it)
  std::int32_t n_groups = 0;                 // (built by finalize from here on)
  std::vector<std::int32_t> tet_group;       // (n_tets) the group of each tetrahedron
  std::vector<Real> tet_rest_volume;         // (n_tets) m^3, signed V0 at rest_x
  std::vector<Real> group_rest_volume;       // (n_groups) m^3, signed sum over the group (non-zero)
  std::vector<std::int32_t> tet_first;       // (n_nodes + 1) node i's corners: tet_corner[tet_first[i] .. tet_first[i+1])
  // (4 n_tets) 4 t + c for corner c of tetrahedron t: per node, the corners of
  // volume-term groups first, then those of inversion guards from
  // tet_guard_begin[i] on, each part ascending (so a group's come together)
  std::vector<std::int32_t> tet_corner;
  std::vector<std::int32_t> tet_guard_begin; // (n_nodes) where node i's guard corners start in tet_corner
  std::int32_t tet_chunk = 1;                // groups per work chunk (a function of n_groups only)
  std::int32_t n_tet_chunks = 0;

  // ---- deterministic work partition (built by finalize)
  // Parallel loops run over chunks of `chunk` consecutive nodes; reductions
  // add per-chunk partial sums in chunk order. Both depend only on n_nodes,
  // so results are bitwise identical for any thread count.
  std::int32_t chunk = 1;
  std::int32_t n_chunks = 0;

  // ---- stability data (built by finalize)
  // Gershgorin bounds per node on the spectrum of M^-1/2 K M^-1/2 and of the
  // damping: omega2[i] = sum_s k_s (1/m_i + 1/sqrt(m_i m_j)) (1/s^2), with k_s
  // the largest stiffness a spring can have (a tension-only spring counted as
  // active), plus each volume group's (k/|V0|) |g_i| sum_j |g_j| / sqrt(m_i m_j)
  // with g = dV/dx of the group's volume at rest; gamma[i] likewise with c_s
  // (1/s). Anchors get 0.
  std::vector<Real> omega2;  // (n_nodes) 1/s^2
  std::vector<Real> gamma;   // (n_nodes) 1/s
  // (n_nodes) m, the rest length of each node's shortest spring in the model
  // as first finalized (0: none); a cut's re-finalize keeps it, so a node's
  // snap distance (CutDef::node_snap) does not grow as cuts take its springs.
  // finalize() computes it when it is empty or the node count changed: code
  // that adds springs otherwise clears it (as runtime/testing/stress.cpp)
  std::vector<Real> shortest_spring;
  Real total_mass = 0;       // kg, free nodes
  Real extent = 0;           // m, diagonal of the rest bounding box

  // ---- names (cold data)
  struct LayerInfo {
    std::string name, tissue, kind;
    int order = 0;
    std::int32_t first = 0, count = 0;  // local node range
  };
  std::vector<LayerInfo> layers;
  std::map<std::string, std::vector<std::int32_t>> node_sets;  // local ids, ascending
  std::vector<std::int32_t> quads;  // (n_quads x 4) local ids, the loaded layers' top surfaces

  // ---- vessels the scene named (static centrelines until issue 9 couples them)
  struct Vessel {
    std::string name;
    std::vector<Real> nodes;  // (n x 3) m
    std::vector<Real> radii;  // (n) m
    std::vector<std::int32_t> edges;  // (n_edges x 2)
    // (n_edges, or empty: none) 1 where a cut has opened the edge: a later cut
    // across it opens no second wound (an identical second cut doubled the bleeding)
    std::vector<char> edge_cut;
    // the tube surface, read only when a scene writes output (LoadRequest::vessel_tubes):
    // the file's quads split into two triangles each, then its triangles
    std::vector<Real> tube_vertices;            // (n_tube x 3) m
    std::vector<std::int32_t> tube_triangles;   // (n_tri x 3), outward
  };
  std::vector<Vessel> vessels;

  // (top, bottom) local ids of the layer columns (layer_columns) a cut has
  // severed: a blade passed between the two ends (cut_model), which then lie
  // on two faces of the wound. Sorted; inverted_columns skips them.
  std::vector<std::pair<std::int32_t, std::int32_t>> severed_columns;

  // Builds the adjacency, chunks and stability data from the arrays above
  // (after sorting the springs). Throws Error("", ...) on inconsistent sizes,
  // ids out of range, self-springs or invalid numbers.
  void finalize();

  // Local ids of a named set; throws Error("", ...) naming it when absent.
  const std::vector<std::int32_t>& set(const std::string& name) const;
};

// In-memory source for assemble_model: the fields of the loaded layers (the
// loader reads exactly these), anchor positions and springs of other layers
// that reach loaded nodes.
struct ModelSource {
  std::string file;  // for error messages
  std::vector<std::pair<std::string, Layer>> layers;  // needs nodes, masses, lin_*; quads optional; tets where volume_modulus > 0 (groups of volume_group) or guard_modulus > 0
  std::map<std::int32_t, std::array<Real, 3>> anchor_positions;  // global id -> rest position
  Layer extra_springs;  // lin_* of unloaded layers' springs that reach loaded nodes
  std::map<std::string, VecXi> node_sets;  // global ids
};

// Flattens a source into a finalized Model. Springs whose both ends are
// neither loaded nor anchors are dropped; node-set ids outside the model are
// dropped. Throws Error(source.file, ...) on invalid data.
Model assemble_model(const ModelSource& source);

// Convenience: all of `layers` loaded, no anchors.
Model model_from_layers(const std::vector<std::pair<std::string, Layer>>& layers,
                        const std::map<std::string, VecXi>& node_sets);

// The layer columns: each loaded layer's top grid and the next layer's (its
// bottom, by order) correspond node for node, column i of the grid, when the
// deepest loaded layer is the rigid fixed bottom (its nodes are one grid: the
// grid's size). Per such pair of layers, the top layer's name and its
// columns' (top, bottom) local ids, in grid order; columns whose nodes a cut
// has split (two local nodes of one file id) are left out. Empty otherwise.
struct LayerColumns {
  std::string layer;
  std::vector<std::pair<std::int32_t, std::int32_t>> columns;
};
std::vector<LayerColumns> layer_columns(const Model& m);

// A layer turned inside out (docs/runtime.md, "Inverted layers"): each
// layer's top grid and the next layer's (its bottom) correspond node for
// node, column i of the grid; a column is inverted where the top node has
// passed its bottom node, (x_top - x_bottom) . (X_top - X_bottom) <= 0 with
// X the rest positions. Central springs alone do not resist it: a soft layer
// pressed or hung under gravity can fold through itself. Checked for every
// loaded layer whose next layer (by order) is loaded, when the deepest
// loaded layer is the rigid fixed bottom (its nodes are one grid: the grid's
// size); empty otherwise (layer_columns). Columns a cut has severed
// (Model::severed_columns) are skipped: their two ends lie on two faces of the
// wound, and their order says nothing about a fold.
struct InvertedColumns {
  std::string layer;
  std::int32_t columns = 0;   // grid columns checked
  std::int32_t inverted = 0;  // of them inside out at x
};
std::vector<InvertedColumns> inverted_columns(const Model& m, std::span<const Real> x);

}  // namespace orthosim::runtime
