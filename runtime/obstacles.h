// Static obstacles of the tissue: planes and triangle meshes (an operating
// table, a tray, a retractor blade) that the free nodes cannot pass. A
// scene's colliders (runtime/scene.h, ColliderDef) act on the blood through
// FluidBoundaries and on the tissue through these.
//
// Contact is node-based and resolved after each substep's update (solver.h),
// like a position-based collision step: a node whose motion over the substep
// crossed an obstacle stops there, on the side it came from; its velocity
// loses its component into the obstacle (restitution e: v_n -> -e v_n) and,
// by Coulomb friction, at most friction x (1 + e) |v_n| of its tangential
// part, never reversing it (the fluid's walls follow the same law, sph.h,
// WallParams); and it moves on with that velocity for the rest of the
// substep (sliding along the surface, or bouncing off). A plane is a
// half-space, so a node behind it however far is put back on it. A mesh
// stops crossings of its triangles, swept along each node's motion
// (continuous: a fast node cannot tunnel through a thin mesh): one-sided
// meshes stop motion from the front (the counter-clockwise normal's side) to
// the back, two-sided ones each way. A node that starts behind a one-sided
// mesh is not pushed out (it is not known to be inside);
// obstacle_nodes_behind counts the nodes a scene starts with behind its
// obstacles, for a warning. The implicit integrator also holds a node that
// rests on an obstacle on its surface within its solve, with the friction
// as a damper in the solve (solver.cpp, docs/runtime.md).
//
// Edges and faces of the tissue between nodes meet a mesh through its edges
// (resolve_face_contacts): points sampled along them (its vertices, and
// points at most a spacing apart between) are kept in front of the tissue's
// surface faces (Model::quads, counter-clockwise seen from outside, each as
// two triangles), so a probe narrower than the skin's node spacing presses
// the skin between its nodes instead of passing through it.
//
// Moving obstacles (an instrument, a retractor blade pressed into the limb):
// each obstacle may be moved rigidly as the caller prescribes over time
// (State::obstacle_paths: a displacement and a rotation about its pivot);
// over a substep it moves as an ObstacleFrame says, its surface at the
// velocity u + w x r. Contact is then resolved in the obstacle's frame: the
// node's motion relative to it is tested against its geometry, the contact
// law acts on the velocity relative to its surface, and the implicit hold
// keeps the node's normal velocity at the surface's. Obstacles are
// kinematic: they do not feel the tissue (their force on it is reported).
#pragma once

#include "runtime/sph.h"
#include "runtime/state.h"
#include "runtime/types.h"

#include <array>
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
  Vec3 pivot{};          // m: the centre its path's rotations turn it about
};

struct ObstacleMesh {
  std::vector<Real> vertices;           // (n_vertices x 3) m
  std::vector<std::int32_t> triangles;  // (n_triangles x 3), counter-clockwise seen from the free side
  bool two_sided = false;
  Real restitution = 0;
  Real friction = 0.2;
  TriangleGrid grid;                    // built by add_obstacle_mesh; level 0's margin is the sampling step along a motion
  Vec3 pivot{};                         // m: the centre its path's rotations turn it about
  // the points of its edges that the tissue's faces meet (sample_obstacle_edges;
  // empty: none), in its own coordinates, their bounding box and their grid
  // (cells of about twice the sampling spacing)
  std::vector<Real> samples;            // (n_samples x 3) m
  Vec3 samples_lo, samples_hi;          // m
  NeighbourGrid sample_grid;
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

// An obstacle a node touches: its index (the planes 0 .. P-1, then the
// meshes P ..; -1: none) and the unit normal of the free side there.
struct ObstacleContact {
  std::int32_t obstacle = -1;
  Vec3 n;
};

Rot3 operator*(const Rot3& a, const Rot3& b);
// The rotation by |r| radians about r (Rodrigues).
Rot3 rotation_from_vector(const Vec3& r);

// Where the obstacles are over a substep: one frame per obstacle, or none (all
// at rest as given).
struct ObstacleMotion {
  std::span<const ObstacleFrame> f;
  bool moving() const { return !f.empty(); }
  const ObstacleFrame& frame(std::int32_t k) const { return f[static_cast<std::size_t>(k)]; }
  Vec3 displacement(std::int32_t k, Real s) const {
    const ObstacleFrame& a = frame(k);
    return a.d0 + s * (a.d1 - a.d0);
  }
  Rot3 rotation(std::int32_t k, Real s) const {
    const ObstacleFrame& a = frame(k);
    if (s == 0) return a.r0;  // (the ends, which most queries ask for, without the trigonometry)
    if (s == 1) return a.r1;
    return a.r0 * rotation_from_vector(s * a.w);
  }
  // a point in space at the fraction s, in obstacle k's own coordinates, and back
  Vec3 to_body(std::int32_t k, const Vec3& x, Real s) const {
    if (!moving()) return x;
    const ObstacleFrame& a = frame(k);
    if (!a.rotates) return x - displacement(k, s);
    return rotation(k, s).inverse(x - a.pivot - displacement(k, s)) + a.pivot;
  }
  Vec3 to_world(std::int32_t k, const Vec3& q, Real s) const {
    if (!moving()) return q;
    const ObstacleFrame& a = frame(k);
    if (!a.rotates) return q + displacement(k, s);
    return rotation(k, s)(q - a.pivot) + a.pivot + displacement(k, s);
  }
  Vec3 normal_to_world(std::int32_t k, const Vec3& n, Real s) const {
    if (!moving() || !frame(k).rotates) return n;
    return rotation(k, s)(n);
  }
  // the velocity (m/s) of obstacle k's material point at x at the fraction s
  // of a substep of h seconds (zero: none, or k < 0)
  Vec3 velocity(std::int32_t k, const Vec3& x, Real s, Real h) const {
    if (!moving() || k < 0) return {};
    const ObstacleFrame& a = frame(k);
    const Vec3 u = (1 / h) * (a.d1 - a.d0);
    if (!a.rotates) return u;
    const Vec3 omega = (1 / h) * rotation(k, s)(a.w);
    return u + cross(omega, x - a.pivot - displacement(k, s));
  }
};

// The obstacles' frames over the substep [t, t + h] from their paths
// (State::obstacle_paths: the displacement path(t), and its rotation
// path_rotation(t) about the obstacle's pivot); `out` is left empty when no
// obstacle has a path. h = 0: where they are at t.
void obstacle_frames(const Obstacles& o, std::span<const Path> paths, Real t, Real h, std::vector<ObstacleFrame>& out);
// A path's rotation at time t: the waypoints' rotation vectors (Path::r)
// interpolated by slerp, held before the first and after the last (I
// without any, or with r not 3 x the waypoints).
Rot3 path_rotation(const Path& p, Real t);
// A path's largest angular speed (rad/s) between two waypoints (0 without rotations).
Real path_max_angular_speed(const Path& p);

// One node's motion over a substep of h seconds from x0 to x = x0 + h v: where
// it crosses an obstacle (moving as `motion` says; the default: at rest), v
// changes by the contact law and the node moves on from the crossing with
// the new v for the rest of the substep (see above). The earliest crossing
// of any obstacle first, then the rest of the motion again (a corner between
// two obstacles), up to 8 crossings, after which the node stays where it is
// on the last obstacle it touched, carried with it to the substep's end; a
// plane the node starts behind is crossed at once. Returns the last obstacle
// it touched (-1: none).
ObstacleContact resolve_obstacle_contact(const Obstacles& o, Vec3 x0, Vec3& x, Vec3& v, Real h,
                                         const ObstacleMotion& motion = {});

// Coulomb friction on a node that an obstacle's contact (index k, unit normal
// n) gave the normal velocity change dvn >= 0: its tangential velocity loses
// at most friction x dvn, never reversed. (The implicit solve holds a resting
// node on its obstacle; dvn is then the impulse of that hold over the mass.)
void obstacle_friction(const Obstacles& o, std::int32_t k, const Vec3& n, Real dvn, Vec3& v);
// Obstacle k's friction coefficient (0 for no obstacle).
Real obstacle_friction_coefficient(const Obstacles& o, std::int32_t k);

// How far from an obstacle's surface a node still rests on it: 10^-6 of the
// coordinates' size, at least 1 micrometre (a node put on a surface stands
// 10^-9 in front of it).
Real obstacle_reach(const Vec3& x);
// How far in front of a mesh's surface a node (or a face under an edge
// sample) is put: 10^-9 of the coordinates' size, at least 1 nanometre.
Real obstacle_standoff(const Vec3& x);

// Whether a node at x rests on obstacle k (where `motion` puts it at the
// substep's start): within obstacle_reach(x) in front of it (a plane: or
// behind it). The normal there is that of the plane, or of the mesh's
// closest triangle on the node's side (a one-sided mesh: its front).
ObstacleContact rests_on(const Obstacles& o, std::int32_t k, const Vec3& x, const ObstacleMotion& motion = {});

// Of the given positions (n x 3), how many are behind plane k (for each
// plane), and how many lie within one grid margin behind a triangle of
// one-sided mesh k, the closest triangle's back (for each mesh): planes
// first, then meshes, in order; the obstacles where `motion` puts them at
// its start.
std::vector<std::int64_t> obstacle_nodes_behind(const Obstacles& o, std::span<const Real> x,
                                                std::span<const std::int32_t> nodes, const ObstacleMotion& motion = {});

// The barycentric weights of p's projection on the plane of triangle abc (n
// its unnormalised normal, n2 = |n|^2), and whether the projection lies in the
// triangle (edges included, to round-off).
struct TriangleProjection {
  Real w[3];
  bool inside;
};
TriangleProjection triangle_projection(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c, const Vec3& n, Real n2);
// Whether p, d (< 0) behind the plane of triangle abc, lies beyond its
// extent by no more than that, |p - closest point|^2 <= 2 d^2: in the wedge
// behind a convex crease, where a face contact still meets it.
bool near_edge(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c, Real d);

// The corners of the tissue's face t: triangle t of quad t / 2 of `quads`
// (n x 4 node ids), (q0, q1, q2) for even t and (q0, q2, q3) for odd t.
inline std::array<std::int32_t, 3> quad_triangle(std::span<const std::int32_t> quads, std::int32_t t) {
  const std::int32_t* q = quads.data() + 4 * static_cast<std::size_t>(t / 2);
  return {q[0], q[1 + (t & 1)], q[2 + (t & 1)]};
}
// Whether face row r's triangle is still a face of `quads` with the corners
// it names: a cut (cut_model) removes and renumbers quads, and a row of the
// quads before it holds nodes that may no longer be a face.
inline bool face_row_current(std::span<const std::int32_t> quads, const FaceRow& r) {
  return r.triangle >= 0 && static_cast<std::size_t>(r.triangle / 2) < quads.size() / 4 && quad_triangle(quads, r.triangle) == r.node;
}

// Samples a mesh's edges for resolve_face_contacts: its vertices (those of
// its triangles) and points along each edge, evenly, at most `spacing` apart.
// spacing <= 0 clears them (only nodes meet the mesh then). Throws
// Error("", "obstacle mesh: ...") for a spacing that is not finite, or one
// that gives the mesh more than 10^7 points.
void sample_obstacle_edges(ObstacleMesh& m, Real spacing);
// The spacing a scene samples colliders' edges at unless told: half the
// median edge length of the quads (n x 4 node ids) at positions x (0: no quads).
Real default_edge_spacing(std::span<const std::int32_t> quads, std::span<const Real> x);
// Whether some mesh has edge samples.
bool has_edge_samples(const Obstacles& o);

// The tissue's surface faces against the meshes' edge samples, over one
// substep of h seconds from positions x with the (tentative) velocities v:
// the faces are the quads (n x 4 node ids, counter-clockwise seen from
// outside) split into two triangles each, (q0, q1, q2) and (q0, q2, q3), where
// x + h v puts them at the substep's end; the meshes where `motion` puts them
// then. A sample meets a triangle when it is behind it at the end, within its
// extent or behind its edge (beyond its extent by no more than it is behind
// its plane: the wedge behind a convex crease); and then, if it met or touched
// a face in the last substep (`met`: it is on the surface) and is within the
// extent, less than the triangle's thickness (half its shortest edge) deep;
// otherwise no deeper than the triangle moved relative to the mesh over the
// substep, and not if it was behind it (or its edge) at the start too by more
// than obstacle_reach (inside the tissue, not entering it). Each meeting in
// turn (by sample, then triangle; Gauss-Seidel sweeps until none moves a
// face, and rounds of finding the meetings again) moves the triangle's point
// under the sample behind it by a standoff, its nodes' share w_j m_j^-1 /
// sum w^2 m^-1 each (w the point's barycentric weights, clamped to the
// triangle; fixed nodes do not move), as a change of their velocity (x + h v
// moves by it); then Coulomb friction takes at most friction x that normal
// velocity change off the point's tangential velocity relative to the mesh's
// surface there. Adds each mesh's impulse on the tissue (N s) to impulse
// (obstacles x 3, indexed as ObstacleContact::obstacle). With `rows`, it is
// set to one FaceRow per sample and triangle the sample meets or touches (in
// front of it by at most obstacle_reach) with a free node of weight > 0,
// sorted, each with the normal impulse it gave the face, and one candidate
// row (FaceRow::candidate) per sample on the surface (`met`) in front of a
// triangle by more than that but no more than the triangle moved relative to
// the mesh over the substep, within its extent: the implicit solve holds them
// in the next substep (and marks in `met` the samples whose rows pushed). With `met` sized (all meshes' samples, in
// order), it says which samples met or touched a face in the last substep
// and is set to those of this one (empty: none did).
struct FaceContacts {
  std::int64_t contacts = 0;  // sample-triangle meetings (with rows: and touches)
  Real work = 0;              // J, the moving meshes' work on the tissue (impulse . their surface's velocity)
};
FaceContacts resolve_face_contacts(const Obstacles& o, const ObstacleMotion& motion, std::span<const std::int32_t> quads,
                                   std::span<const Real> x, std::span<Real> v, std::span<const Real> inv_mass, Real h,
                                   std::span<Real> impulse, FaceScratch& scratch, std::vector<FaceRow>* rows = nullptr,
                                   std::span<std::uint8_t> met = {});

// The number of obstacles (planes, then meshes).
inline std::int32_t obstacle_count(const Obstacles& o) {
  return static_cast<std::int32_t>(o.planes.size() + o.meshes.size());
}

}  // namespace orthosim::runtime
