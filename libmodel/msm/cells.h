// The cells of one mass-spring layer before a tissue is applied: geometry and
// topology only. The layer builders (lattice.h, tetra.h) emit one SpringTerm
// per spring per cell; merge_terms() sums the terms of a spring shared by
// several cells into one spring. The tissue's moduli then turn the summed
// `k_per_pa` (stiffness per unit Young's modulus, N/m per Pa = m) into N/m.
//
// Node ids are global (see libmodel/format/model.h, Layer). A builder is told
// where its top grid, its own new nodes and its bottom grid sit in the global
// numbering, and reports lumped volumes by global id.
#pragma once

#include "libmodel/format/model.h"

#include <Eigen/Core>
#include <Eigen/Geometry>

#include <algorithm>
#include <array>
#include <cstdint>
#include <vector>

namespace orthosim::msm {

// One cell's share of one spring: k = k_per_pa * E once the modulus E is known.
struct SpringTerm {
  std::int32_t a = 0, b = 0;  // global node ids
  double k_per_pa = 0;        // m (N/m per Pa)
  SpringClass cls = SpringClass::structural;
};

// Where a layer's nodes sit in the global numbering. The top grid (nu*nv
// nodes, row j*nu+i) starts at `top`, the nodes the layer creates at
// `created`, the bottom grid at `bottom`.
struct NodeBlocks {
  std::int32_t top = 0, created = 0, bottom = 0;
};

// Counts of the centroid projection of a tetra layer (project.h explains each).
struct ProjectionCounts {
  std::int64_t rays = 0;           // one per top triangle
  std::int64_t hits = 0;           // exact ray hits kept (near_edge of them pulled inside their face)
  std::int64_t miss = 0;           // fallback: the ray hit nothing within reach
  std::int64_t backface = 0;       // fallback: first hit on the back of the lower surface
  std::int64_t other_cell = 0;     // fallback: first hit in another cell than the one below
  std::int64_t near_edge = 0;      // hit kept but pulled inside its triangle (barycentric clamp)
  std::int64_t sheared = 0;        // fallback: the point would invert a cell of a sheared prism and was moved
                                   // toward the centroid of its bottom triangle (tetra.h)
  std::int64_t fallbacks() const { return miss + backface + other_cell + sheared; }
};

// Diagnostics of the lattice stiffness rule over a layer's cells (lattice.h).
struct RuleStats {
  std::int64_t cells = 0;
  std::int64_t exact = 0;          // cells where the isotropic target is met exactly
  double max_residual = 0;         // largest relative residual of the rule's fit (0 when exact)
  std::array<double, 3> mean_modulus_ratio{0, 0, 0};  // predicted E_u, E_v, E_w over target E, mean over cells
  std::array<double, 3> mean_cell_m{0, 0, 0};         // mean equivalent box a, b, c (m): a tuner's specimen shape
  // predicted shear moduli G_vw, G_uw, G_uv over target E, mean over cells
  // (isotropic, nu = 1/4: 0.4; long cells are soft in shear, docs/msm.md)
  std::array<double, 3> mean_shear_ratio{0, 0, 0};
};

struct LayerCells {
  MatX3d created;                              // (n_created x 3) m: nodes the layer adds (centroids, interior grids)
  std::vector<SpringTerm> terms;               // one per spring per cell
  std::vector<std::array<std::int32_t, 4>> tets;  // tetra layers: (n_tets) global ids, positive orientation
  std::vector<double> node_volume;             // lumped cell volume by global id (m^3); size = last id + 1
  double volume_m3 = 0;                        // sum of the cell volumes
  std::int64_t cells = 0;                      // prisms (tetra) or hexahedra (lattice)
  std::int64_t sub_tets = 0;                   // tetrahedra the cells were cut into for volumes and checks
  std::int64_t inverted = 0;                   // tetra: sub-tetrahedra with volume <= min_volume; lattice:
                                               // hexahedra with a Jacobian <= min_volume at a corner or the centre
  std::int64_t first_inverted_quad = -1;       // the quad over the first of them (-1: none)
  double min_jacobian_m3 = 0;                  // lattice: smallest hexahedron Jacobian (corners, centre)
  double min_tet_volume_m3 = 0;                // smallest sub-tetrahedron volume
  double mean_tet_volume_m3 = 0;
  ProjectionCounts projection;                 // tetra layers
  RuleStats rule;                              // lattice layers
};

// Springs after merging: one row per distinct node pair, sorted by (a, b), a < b.
struct MergedSprings {
  MatX2i pairs;          // (n x 2) global ids, a < b
  VecXd rest_length;     // (n) m, from `positions`
  VecXd k_per_pa;        // (n) m, summed over cells
  VecXu8 spring_class;   // (n) SpringClass of the pair (its lowest role code over the cells)
  VecXi cells;           // (n) number of terms (cells) summed into the spring
};

// Sums the terms of each node pair (order-independent of how cells were
// visited: terms are sorted by pair, then by k, before summing).
// `positions` holds every global node (row = id).
MergedSprings merge_terms(std::vector<SpringTerm> terms, const MatX3d& positions);

// Removes springs whose summed stiffness is zero (a rule weight of 0 in every
// cell sharing them, lattice.h); returns how many.
std::int64_t drop_zero_stiffness(MergedSprings& m);

// Signed volume of the tetrahedron (a, b, c, d): det[b-a, c-a, d-a] / 6.
inline double tet_volume(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
                         const Eigen::Vector3d& d) {
  return (b - a).dot((c - a).cross(d - a)) / 6.0;
}

// A corner of the prism over a quad's triangle: the quad's local vertex
// (0-3) on the top grid, or on the bottom grid (the same vertex one layer down).
struct PrismCorner {
  int local;
  bool bottom;
};

// The prism over the triangle `tri` (local vertices of a quad whose node ids
// are `ids`; counter-clockwise seen from the top, the bottom below it) cut
// into 3 tetrahedra by the side diagonals from the vertex with the smaller
// id, so that two prisms sharing a side quad cut it the same way. Each
// tetrahedron is positively oriented where the prism is. The lattice's
// hexahedra (two prisms each) and the tetra layer's grid prisms
// (grid_prism_tets) are cut by it.
inline std::array<std::array<PrismCorner, 4>, 3> prism_cut(const int ids[4], const std::array<int, 3>& tri) {
  std::array<int, 3> s = tri;
  std::sort(s.begin(), s.end(), [&](int x, int y) { return ids[x] < ids[y]; });
  // the sorted order is counter-clockwise iff it is an even permutation of tri
  const bool ccw = (s[0] == tri[0] && s[1] == tri[1]) || (s[0] == tri[1] && s[1] == tri[2]) ||
                   (s[0] == tri[2] && s[1] == tri[0]);
  const PrismCorner a{s[0], false}, b{s[1], false}, c{s[2], false}, a_{s[0], true}, b_{s[1], true}, c_{s[2], true};
  if (ccw) return {{{a, b_, a_, c_}, {a, b, b_, c_}, {a, c, b, c_}}};
  return {{{a, a_, b_, c_}, {a, b_, b, c_}, {a, b, c, c_}}};
}

// Volume enclosed between a top and a bottom grid with the same quads (both
// split into triangles along the diagonal q0-q2, or q1-q3 where split[q] is
// 1: tetra.h triangulate), closed at the open ends by the side quads of
// boundary edges split like the cells' side faces (diagonal from the top
// vertex with the smaller id). Divergence theorem over the closed faceted
// surface; independent of how the cells are cut. m^3.
double layer_volume(const MatX3d& top, const MatX3d& bottom, const MatX4i& quads,
                    const std::vector<std::uint8_t>& split = {});

// The unique undirected edges of a quad grid, with the number of quads using
// each (1 on an open boundary, 2 inside). Sorted by (a, b), a < b, local ids.
struct GridEdges {
  MatX2i edges;
  VecXi uses;
};
GridEdges grid_edges(const MatX4i& quads);

}  // namespace orthosim::msm
