// Static obstacles of the tissue: planes and triangle meshes (an operating
// table, a tray, a retractor blade) that the free nodes cannot pass. A
// scene's colliders (runtime/scene.h, ColliderDef) act on the blood through
// FluidBoundaries and on the tissue through these.
//
// Contact is node-based and resolved after each substep's update (solver.h),
// like a position-based collision step: a node whose motion over the substep
// crossed an obstacle is put back on its surface, on the side it came from,
// with its remaining motion along the surface (sliding); its velocity loses
// its component into the obstacle (restitution e: v_n -> -e v_n) and, by
// Coulomb friction, at most friction x (1 + e) |v_n| of its tangential part,
// never reversing it (the fluid's walls follow the same law, sph.h,
// WallParams). A plane is a half-space, so a node behind it however far is put
// back on it. A mesh stops crossings of its triangles, swept along each
// node's motion (continuous: a fast node cannot tunnel through a thin mesh):
// one-sided meshes stop motion from the front (the counter-clockwise normal's
// side) to the back, two-sided ones each way. A node that starts behind a
// one-sided mesh is not pushed out (it is not known to be inside);
// obstacle_nodes_behind counts the nodes a scene starts with behind its
// obstacles, for a warning.
//
// Edges and faces of the tissue between nodes are not tested: a coarse
// skin quad may dip past a convex corner of a mesh between its nodes.
// Obstacles are static and do not feel the tissue.
#pragma once

#include "runtime/sph.h"
#include "runtime/types.h"

#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace orthosim::runtime {

struct ObstaclePlane {
  Vec3 point;   // m
  Vec3 normal;  // unit (add_obstacle_plane normalises it): the free side is normal . (x - point) >= 0
  Real restitution = 0;  // [0, 1]
  Real friction = 0.2;   // >= 0
};

struct ObstacleMesh {
  std::vector<Real> vertices;           // (n_vertices x 3) m
  std::vector<std::int32_t> triangles;  // (n_triangles x 3), counter-clockwise seen from the free side
  bool two_sided = false;
  Real restitution = 0;
  Real friction = 0.2;
  TriangleGrid grid;                    // built by add_obstacle_mesh; level 0's margin is the sampling step along a motion
};

struct Obstacles {
  std::vector<ObstaclePlane> planes;
  std::vector<ObstacleMesh> meshes;
  bool empty() const { return planes.empty() && meshes.empty(); }
};

// Throws Error("", "obstacle plane: ...") for a zero or non-finite normal, a
// non-finite point, restitution outside [0, 1] or negative friction.
void add_obstacle_plane(Obstacles& o, ObstaclePlane plane);
// Validates the mesh (indices in range, finite coordinates, at least one
// triangle that is not degenerate) and builds its grid with a margin of the
// mean edge length. Throws Error("", "obstacle mesh: ...").
void add_obstacle_mesh(Obstacles& o, ObstacleMesh mesh);

// One node's motion over a substep from x0 to x with velocity v: puts x back
// on the free side of every obstacle it crossed (see above) and changes v by
// the contact law. Returns true when the node touched an obstacle. Meshes
// first, planes last (a half-space always holds).
bool resolve_obstacle_contact(const Obstacles& o, Vec3 x0, Vec3& x, Vec3& v);

// Of the given positions (n x 3), how many are behind plane k (for each
// plane), and how many lie within one grid margin behind a triangle of
// one-sided mesh k, the closest triangle's back (for each mesh): planes
// first, then meshes, in order.
std::vector<std::int64_t> obstacle_nodes_behind(const Obstacles& o, std::span<const Real> x,
                                                std::span<const std::int32_t> nodes);

}  // namespace orthosim::runtime
