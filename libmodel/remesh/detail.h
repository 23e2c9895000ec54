// Internal to libmodel/remesh: mesh topology and plane slicing.
// Not part of the library interface (remesh.h is).
#pragma once

#include "libmodel/remesh/remesh.h"

#include <Eigen/Core>

#include <tbb/enumerable_thread_specific.h>

#include <array>
#include <string>
#include <vector>

namespace orthosim::remesh_detail {

// Edges and components of a checked closed surface.
struct Topology {
  int n_edges = 0;
  std::vector<std::array<int, 3>> face_edge;  // edge id of face edge k = (v[k], v[k+1])
  std::vector<std::array<int, 2>> edge_face;  // the two faces of each edge
  std::vector<int> face_component;            // component of each face
  std::vector<double> component_volume;       // signed volume of each component
  std::vector<double> component_area;
  std::vector<int> component_euler;
  SurfaceCheck check;
};

// Builds the topology and runs every check of check_closed_surface.
Topology build_topology(const Surface& s, const std::string& name, bool single_component);

// A closed polyline where a plane cuts the surface, counter-clockwise around
// the plane normal for an outward component (clockwise around a hole).
struct Loop {
  std::vector<Eigen::Vector3d> p;  // points
  std::vector<Eigen::Vector2d> q;  // in the plane frame: ((p-c).e1, (p-c).e2)
  double area = 0;                 // signed area in the plane frame
  Eigen::Vector2d centroid{0, 0};  // area centroid in the plane frame
  int component = 0;
};

// Cuts a surface with planes. Faces are sorted along an axis so that a plane
// nearly normal to it touches only the faces of a slab.
class Slicer {
 public:
  // Reads the surface only (its face ids must be in range); the topology is
  // read by slice(), so it may be built after the slicer.
  Slicer(const Surface& s, const Topology& t, const Eigen::Vector3d& axis_point, const Eigen::Vector3d& axis_dir);
  // Loops of the plane through p.centre with normal p.normal; q uses p.e1, p.e2.
  // Thread-safe (per-thread scratch).
  std::vector<Loop> slice(const SweepPlane& p) const;

 private:
  const Surface& s_;
  const Topology& t_;
  Eigen::Vector3d a0_, ad_;
  std::vector<int> order_;          // faces sorted by tmin
  std::vector<double> tmin_sorted_, tmax_sorted_;  // tmin, tmax in sorted order
  double max_extent_ = 0, rho_max_ = 0;
  // per-thread scratch of slice(): slices may run side by side
  struct Scratch {
    struct Vert {
      unsigned stamp;
      double dist;  // signed distance to the current plane, valid when stamp == cur
    };
    struct Face {
      unsigned stamp;
      int exit;  // exit edge (- to + in face order), -1 none, -2 - slot once walked
    };
    std::vector<Vert> vert;
    std::vector<Face> face;
    unsigned cur = 0;
  };
  mutable tbb::enumerable_thread_specific<Scratch> scratch_;
};

// The loops of each plane, sliced side by side (result in plane order).
std::vector<std::vector<Loop>> slice_all(const Slicer& sl, const std::vector<SweepPlane>& planes);

// Signed area and area centroid of the loop's plane-frame points q.
void set_area_centroid(Loop& l);
// q of the loop's points p in the frame of plane pl, then its area and centroid.
void to_plane_frame(Loop& l, const SweepPlane& pl);

// Winding number of the loop around point x (plane frame).
int winding(const Loop& l, const Eigen::Vector2d& x);

// Largest t >= 0 with o + t w on the loop (plane frame), or -1 when the ray misses.
double ray_hit(const Loop& l, const Eigen::Vector2d& o, const Eigen::Vector2d& w);

// Side loops a ring plane may cut beside the tube's own, each at most this
// share of the tube loop's area: noise on the surface (a bump of a few
// voxels that folds back along the axis). For a limb 30 or more voxels
// across (a cross-section of 700 voxels or more) it is under a voxel's area,
// detail the data cannot hold; a branch (a second limb) or a fold of slices
// off each other is far larger and is still refused.
inline constexpr double kSideLoopAreaRatio = 1e-3;

// The loop of a ring plane that the sweep follows: the one loop winding
// around the centre, where every other loop (none winding around it) is a
// side loop of at most kSideLoopAreaRatio of its area. Throws Error(name,
// "not tube-like: ...") otherwise.
const Loop& tube_loop(const std::vector<Loop>& loops, const std::string& name, double s, double length);

// Points of a ring at fractions u (sorted, in [0, 1)): equal arc length from
// the phase point (the outermost crossing of the ray from the centre along
// e1), arc length measured on the section smoothed over 2 arc_window + 1
// vertices (RemeshOptions::arc_window), or rays at angles 2 pi u from e1. inward (optional): unit in-plane
// normals pointing inside. Throws Error(name, ...) when a ray misses.
void sample_loop(const Loop& l, const SweepPlane& pl, RingSampling mode, int arc_window, const std::vector<double>& u,
                 std::vector<Eigen::Vector3d>& out, std::vector<Eigen::Vector3d>* inward, const std::string& name);

// Cumulative arc length of the closed polygon T at each vertex, its perimeter
// last (T.size() + 1 entries).
std::vector<double> closed_arc_lengths(const std::vector<Eigen::Vector2d>& T);
// The point at arc length x (taken around) of the closed polygon T (cum:
// closed_arc_lengths(T)); its segment in *segment when given.
Eigen::Vector2d point_at_arc(const std::vector<Eigen::Vector2d>& T, const std::vector<double>& cum, double x,
                             std::size_t* segment = nullptr);

// Correspondence between a ring and the section of the layer below it, both
// closed counter-clockwise polygons in one plane. normal_hits: the arc-length
// parameter on T (from T[0]) of the first crossing of the inward normal of P
// at P[i] (normal of the chord P[i-1] P[i+1]) with T, or of the closest point
// of T where the normal misses; unwrapped so that it goes once around T
// (x[i] may exceed the perimeter: take it modulo).
std::vector<double> normal_hits(const std::vector<Eigen::Vector2d>& P, const std::vector<Eigen::Vector2d>& T,
                                const std::vector<double>* halfwidth = nullptr);
// radial_hits: the same for the rays from c (inside T) through P[i], outermost
// crossing: ordered wherever T is star-shaped around c (rays from one point do
// not cross).
std::vector<double> radial_hits(const std::vector<Eigen::Vector2d>& P, const std::vector<Eigen::Vector2d>& T,
                                const Eigen::Vector2d& c);
// The blend base_i + alpha (x_i - base_i) of the normal hits x and the radial
// hits base, made strictly increasing around the ring with spacing >=
// min_spacing_fraction per / n (isotonic regression; a no-op when the blend is
// ordered already).
std::vector<double> ordered_blend(const std::vector<double>& x, const std::vector<double>& base, double per,
                                  double alpha, double min_spacing_fraction);
// The largest alpha in {1, (steps-1)/steps, ..., 0} whose blend is ordered
// with that spacing without the isotonic fix (0 if none).
double max_ordered_blend(const std::vector<double>& x, const std::vector<double>& base, double per,
                         double min_spacing_fraction, int steps);

// Distance (m) from each of `points` (rows) to the triangles of `s` (CGAL AABB
// tree; remesh_cgal.cpp).
std::vector<double> distances_to_surface(const Surface& s, const MatX3d& points);

// True when every one of `points` lies within `tol` (m) of a triangle of `s`.
// A scan of the triangles' boxes per point that stops at the first point with
// none near: one pass over `s` when the points lie off it (a layer inside
// another), where an AABB tree over a 256^3 stack's 1.7 M triangles took 2-3 s
// to build for 1 024 points (remesh_cgal.cpp).
bool all_on_surface(const Surface& s, const MatX3d& points, double tol);

}  // namespace orthosim::remesh_detail
