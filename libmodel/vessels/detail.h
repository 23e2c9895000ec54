// Internal to libmodel/vessels: the steps of extract_vessels over plain
// data. Not part of the library interface (vessels.h is).
#pragma once

#include "libmodel/vessels/vessels.h"

#include <Eigen/Core>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace orthosim::vessels_detail {

// ---- the cropped voxels ----------------------------------------------------------
// The tissue's voxels cropped to their bounding box plus a one-voxel pad on
// every side (the pad may lie outside the volume), so that every tissue voxel
// has its 26 neighbours inside the crop.
struct Grid {
  int nx = 0, ny = 0, nz = 0;        // crop size
  int ox = 0, oy = 0, oz = 0;        // volume index of crop voxel (0,0,0)
  int vx = 0, vy = 0, vz = 0;        // volume size
  std::array<double, 3> h{0, 0, 0};  // spacing (m)
  Eigen::Vector3d origin{0, 0, 0};   // physical position of crop voxel (0,0,0)
  std::vector<std::uint8_t> mask;    // 1: tissue
  std::vector<float> dt;             // (m) voxel centre to the nearest in-volume non-tissue voxel centre
  std::int64_t voxels = 0;           // tissue voxels

  std::size_t index(int x, int y, int z) const {
    return (static_cast<std::size_t>(z) * ny + y) * nx + x;
  }
  Eigen::Vector3i coords(std::size_t i) const {
    const int x = static_cast<int>(i % nx);
    const std::size_t r = i / nx;
    return {x, static_cast<int>(r % ny), static_cast<int>(r / ny)};
  }
  Eigen::Vector3d position(std::size_t i) const {
    const Eigen::Vector3i c = coords(i);
    return origin + Eigen::Vector3d(c.x() * h[0], c.y() * h[1], c.z() * h[2]);
  }
  bool in_volume(int x, int y, int z) const {
    return x + ox >= 0 && y + oy >= 0 && z + oz >= 0 && x + ox < vx && y + oy < vy && z + oz < vz;
  }
  double hmin() const { return std::min({h[0], h[1], h[2]}); }
  double hmax() const { return std::max({h[0], h[1], h[2]}); }
  // Voxel distance of crop voxel i to the nearest face of the volume (0: on the border layer).
  int border_distance(std::size_t i) const;
  // Trilinear interpolation of the tissue indicator at p (m): in [0, 1];
  // -1 when p lies outside the volume's voxel centres (unknown). Inline: the
  // cross-section rays call it about a million times per vessel tree.
  inline double mask_at(const Eigen::Vector3d& p) const;
  // Trilinear interpolation of dt at p (m); 0 outside the crop.
  double dt_at(const Eigen::Vector3d& p) const;
};

inline double Grid::mask_at(const Eigen::Vector3d& p) const {
  double f[3];
  int i0[3];
  const int n[3] = {nx, ny, nz}, o[3] = {ox, oy, oz}, vn[3] = {vx, vy, vz};
  for (int d = 0; d < 3; ++d) {
    const double u = (p(d) - origin(d)) / h[d];
    const double uv = u + o[d];  // volume index coordinate
    if (uv < -1e-9 || uv > vn[d] - 1 + 1e-9) return -1;
    const double fl = std::floor(u);
    i0[d] = static_cast<int>(fl);
    f[d] = u - fl;
    if (i0[d] < 0 || i0[d] + 1 >= n[d]) return 0;  // outside the crop: not tissue
  }
  const std::uint8_t* m = mask.data() + index(i0[0], i0[1], i0[2]);
  const std::size_t sy = static_cast<std::size_t>(nx), sz = static_cast<std::size_t>(nx) * ny;
  const double g[2][3] = {{1 - f[0], 1 - f[1], 1 - f[2]}, {f[0], f[1], f[2]}};
  double acc = 0;
  for (int c = 0; c < 8; ++c) {
    const int dx = c & 1, dy = (c >> 1) & 1, dz = (c >> 2) & 1;
    if (m[dx + dy * sy + dz * sz]) acc += g[dx][0] * g[dy][1] * g[dz][2];
  }
  return acc;
}

// Crops `label` out of v. Throws Error("", ...) when there is no such voxel.
Grid make_grid(const Volume& v, int label, const std::string& tissue);
// Exact anisotropic Euclidean distance transform (Felzenszwalb-Huttenlocher,
// separable) into g.dt. Voxels outside the volume are not background: a
// vessel cut by the border keeps its radius up to the border.
void distance_transform(Grid& g);
// Distance-ordered topology-preserving curve thinning. Returns the crop
// indices of the skeleton voxels in increasing order.
std::vector<std::size_t> thin(const Grid& g);
// True when the centre of the 3x3x3 neighbourhood `bits` (bit (dz+1)*9 +
// (dy+1)*3 + (dx+1), centre bit 13) is a simple point (26/6 topology).
bool is_simple(std::uint32_t bits);

// ---- the tree of branches ------------------------------------------------------------
struct Branch {
  int tree = 0;
  int parent = -1;
  std::vector<int> children;
  std::vector<Eigen::Vector3d> x;  // centreline points, start to end (m)
  std::vector<double> r;           // radius at each point (m)
  std::vector<double> rho;         // inscribed-sphere radius at each point (m)
  bool start_root = false;         // starts at the tree's root end
  bool end_leaf = false;           // ends at a vessel end (else at a junction)
  bool start_open = false, end_open = false;  // that end is cut by the volume border
  // the border plane an open end lies on: axis (0..2, -1: none) and coordinate (m)
  int start_axis = -1, end_axis = -1;
  double start_plane = 0, end_plane = 0;
  // tube interval: arc lengths along x where the swept tube starts and ends
  double tube_a = 0, tube_b = 0;
  // Bezier (filled by fit_bezier)
  std::vector<Eigen::Vector3d> ctrl;  // 3k+1
  std::vector<double> ctrl_r;         // 3k+1
  std::vector<double> knots;          // k+1 arc lengths of the piece ends
};

struct Junction {
  int parent = -1;
  std::vector<int> children;
};

struct Forest {
  std::vector<Branch> branches;  // parents before children
  std::vector<Junction> junctions;
  int trees = 0;
  int children_pruned = 0;     // leaves dropped at junctions with too many children
  double pruned_length_m = 0;  // their total length
};

struct GraphStats {
  int spurs = 0, loops = 0, contacts = 0, dropped = 0, thin = 0, merged = 0;
  std::vector<VesselCut> cuts;
  std::vector<int> roots_used;
};

// Skeleton voxels -> pruned, loop-free, rooted forest of branches carrying
// voxel-centre positions and inscribed radii.
Forest build_forest(const Grid& g, const std::vector<std::size_t>& skeleton, const VesselOptions& o,
                    GraphStats& stats);

// Sub-voxel re-centring and radii from cross-sections; resampling; junction
// regions and the bifurcation points; open ends extended to the border.
void refine_centrelines(const Grid& g, const VesselOptions& o, Forest& f);

// Curvature-adaptive piecewise cubic Bezier of each branch (C1 in arc
// length) with max deviation <= tol; radius as a cubic in the same
// parameter. Returns the largest deviation found.
double fit_bezier(Forest& f, double tol);
// Evaluation of a branch's Bezier at arc length s (clamped).
Eigen::Vector3d branch_point(const Branch& b, double s, Eigen::Vector3d* tangent = nullptr, double* radius = nullptr);

// The tube mesh: rings along every branch's tube interval, bifurcation
// patches, caps. Fills t.tube_*; open_cap[v] = 1 for the cap vertices of
// ends cut by the volume border.
void build_tube(const Forest& f, const VesselOptions& o, VesselTree& t, std::vector<char>& open_cap);

// Cubic Bezier helpers.
inline Eigen::Vector3d bezier3(const Eigen::Vector3d& p0, const Eigen::Vector3d& p1, const Eigen::Vector3d& p2,
                               const Eigen::Vector3d& p3, double t) {
  const double s = 1 - t;
  return s * s * s * p0 + 3 * s * s * t * p1 + 3 * s * t * t * p2 + t * t * t * p3;
}
inline Eigen::Vector3d bezier3_d(const Eigen::Vector3d& p0, const Eigen::Vector3d& p1, const Eigen::Vector3d& p2,
                                 const Eigen::Vector3d& p3, double t) {
  const double s = 1 - t;
  return 3 * s * s * (p1 - p0) + 6 * s * t * (p2 - p1) + 3 * t * t * (p3 - p2);
}
inline double bezier3(double p0, double p1, double p2, double p3, double t) {
  const double s = 1 - t;
  return s * s * s * p0 + 3 * s * s * t * p1 + 3 * s * t * t * p2 + t * t * t * p3;
}

// Distance from p to the segment [a, b].
inline double segment_distance(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                               double* t_out = nullptr) {
  const Eigen::Vector3d d = b - a;
  const double l2 = d.squaredNorm();
  double t = l2 > 0 ? (p - a).dot(d) / l2 : 0;
  t = t < 0 ? 0 : (t > 1 ? 1 : t);
  if (t_out) *t_out = t;
  return (p - (a + t * d)).norm();
}

}  // namespace orthosim::vessels_detail
