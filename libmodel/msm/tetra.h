// Tetrahedral layers by centroid projection (paper §3).
//
// Each quad (q0 q1 q2 q3) of the top grid is split along q0-q2 into the
// triangles (q0 q1 q2) and (q0 q2 q3), or with alternate_diagonals along
// alternating diagonals (alternating_split; q1-q3: (q1 q2 q3), (q1 q3 q0)),
// which keeps the layer from coupling stretch to shear (docs/msm.md). The
// centroid of each triangle is shot
// along the triangle's inward normal onto the bottom grid, split the same way
// (project.h). Springs join the triangle's vertices to its projected centroid
// c: the tetrahedron (v0 v1 v2 c) of the paper.
//
// The next surface. The projected centroids lie on the bottom surface, inside
// the bottom triangle under their top triangle; that triangle is cut 1-to-3 at
// c, so the next surface is the triangulation of the projected centroids
// together with the bottom grid's own vertices. The bottom grid is the
// remesh grid of the next tissue, vertex (i, j) under vertex (i, j) of the top,
// so a lattice layer below uses it unchanged and the (u, v) correspondence
// holds through every layer; a tetra layer below projects the centroids of
// that grid's triangles in turn. (The paper's triangulation of the centroids
// alone would double the node count per tetra layer and leave a lattice below
// without corresponding grid vertices.) The centroid nodes belong to the
// tetra layer that made them.
//
// Cells fill the layer exactly: the prism between top triangle (v0 v1 v2) and
// bottom triangle (w0 w1 w2) is the tetrahedron (v0 v1 v2 c) plus, over each
// side quad (va vb wb wa), the pyramid with apex c, cut into two tetrahedra
// by the side diagonal from the smaller vertex id (shared consistently with
// the neighbouring prism): 7 tetrahedra per prism, so the springs are the top
// and bottom triangle edges, v-c, w-c, the vertical v-w edges and one
// diagonal per side quad. Stiffness (a trace rule, docs/msm.md): every
// tetrahedron t adds k = E V_t / l^2 to each of its six edges, so that
// sum k l^2 = 6 E V, the trace of the isotropic nu = 1/4 tensor.
#pragma once

#include "libmodel/msm/cells.h"
#include "libmodel/msm/project.h"

namespace orthosim::msm {

// A tetra layer's cell is two prisms (one per triangle of its quad) of 7
// tetrahedra each, consecutive in LayerCells::tets (a prism is a possible
// volume group, Layer::volume_group: docs/msm.md, "The volume term").
inline constexpr int kTetsPerPrism = 7;

struct TetraOptions {
  ProjectionOptions projection;
  double inverted_ratio = 1e-9;  // a tetrahedron below this fraction of the mean volume counts as inverted
  // Axis factors s_u, s_v, s_w (> 0): every spring's trace-rule stiffness is
  // scaled by sum_a s_a n_a^2, n its unit direction in its prism's frame (u
  // along the quad's q0 -> q1, w along the top quad's normal, v = w x u).
  // {1, 1, 1}: the trace rule alone. msm::calibrate_tetra_axes finds the
  // factors that give a layer's cell shape equal moduli along u, v and w.
  std::array<double, 3> axis_factors{1, 1, 1};
  bool alternate_diagonals = false;  // split the quads by alternating_split (else all along q0-q2)
};

// The triangles of a quad grid: quad q split along q0-q2, face 2q = (q0 q1
// q2), 2q+1 = (q0 q2 q3); where split[q] is 1, along q1-q3, face 2q = (q1 q2
// q3), 2q+1 = (q1 q3 q0). An empty split: every quad along q0-q2.
Surface triangulate(const MatX3d& vertices, const MatX4i& quads, const std::vector<std::uint8_t>& split = {});

// Alternating diagonals: a two-colouring of the quads by breadth-first search
// over shared edges, in quad order (a grid's checkerboard; where a closed
// grid has an odd number of quads around, one seam keeps the same diagonal
// twice). With one diagonal in every quad the prisms of a tetra layer couple
// stretch to in-plane shear (docs/msm.md); alternating cancels it.
std::vector<std::uint8_t> alternating_split(const MatX4i& quads);

// The volume term of a tetra layer over its grid prisms (docs/msm.md, "The
// volume term"; BuildOptions::tetra_volume_term "prisms"). Under each
// triangle of quad q (split as triangulate: faces 2q, 2q+1) lies the prism of
// its 3 top and 3 bottom grid vertices, cut into 3 tetrahedra with side
// diagonals from the smaller vertex id (consistent between neighbours, as
// lattice_cells cuts its hexahedra), positively oriented where the top grid's
// quads wind counter-clockwise seen from outside; its cap is the tetrahedron
// (w0 w1 w2 c) of the bottom triangle and the face's projected centroid c,
// flat at rest. Each prism gives two groups of kGridPrismTets: its 3
// tetrahedra with the cap reversed, then with the cap; at modulus k' each
// their two terms sum to k' ((V_p - V0)^2 + V_cap^2) / |V0| (exactly where
// the cap is flat at rest): the grid's volume, which one term per prism keeps
// without locking in bending, and the centroid's height over the bottom
// triangle, which its own 3 dofs meet (so it locks nothing) and which keeps
// the centroid, in no other term, on the surface below. 4 groups per quad, in
// quad order; top ids top_block + vertex, bottom ids bottom_block + vertex,
// centroids created_block + face.
// So each group carries half the tissue's modulus: Layer::volume_modulus =
// kGridPrismShare x volume_ratio(nu) K1 (and the specimen's volume_ratio the
// same share).
inline constexpr int kGridPrismTets = 4;
inline constexpr double kGridPrismShare = 0.5;
std::vector<std::array<std::int32_t, 4>> grid_prism_tets(const MatX4i& quads, const std::vector<std::uint8_t>& split,
                                                         std::int32_t top_block, std::int32_t bottom_block,
                                                         std::int32_t created_block);

// The cells of a tetra layer between `top` and `bottom` grids (same rows and
// quads). The projected centroids are created at blocks.created + face index.
// `bottom_caster`: a RayCaster on triangulate(bottom, quads), or null to build one.
LayerCells tetra_cells(const MatX3d& top, const MatX3d& bottom, const MatX4i& quads, const NodeBlocks& blocks,
                       const TetraOptions& options, const RayCaster* bottom_caster = nullptr);

}  // namespace orthosim::msm
