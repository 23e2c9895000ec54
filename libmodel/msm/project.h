// Centroid projection: rays from the centroids of an upper triangle surface,
// along each triangle's inward normal, onto a lower triangle surface, with an
// exact ray-mesh intersection (CGAL AABB tree; CGAL stays inside project.cpp).
//
// "Lands on the lower surface" means on the lower *triangle mesh*: a hit is
// the intersection of the ray with the plane of the facet it crosses, in
// double precision (distance to that facet ~1e-16 relative). Its distance to
// the smooth surface the mesh samples is bounded by the facets' sagitta,
// which is the remesh's own approximation error, not the projection's.
#pragma once

#include "libmodel/format/model.h"
#include "libmodel/msm/cells.h"

#include <Eigen/Core>

#include <cstdint>
#include <memory>

namespace orthosim::msm {

// Why a ray's point is what it is.
enum class ProjectionStatus : std::uint8_t {
  hit = 0,         // first front-facing hit, in the expected face if one was given
  miss = 1,        // no hit within max_distance: closest point used
  backface = 2,    // the first hit was on the back of a lower facet (layers crossed): closest point used
  other_cell = 3,  // the first hit was not in the expected face: closest point in the expected face used
};

struct RayHit {
  Eigen::Vector3d point{0, 0, 0};
  int face = -1;        // face of the target; -1 when nothing was hit
  double distance = 0;  // along the ray (m)
  bool front = false;   // the ray enters the facet from its outer (normal) side
};

// A triangle surface prepared for ray and closest-point queries. Queries are
// const and thread-safe once constructed.
class RayCaster {
 public:
  explicit RayCaster(const Surface& target);  // faces counter-clockwise seen from outside
  ~RayCaster();
  RayCaster(const RayCaster&) = delete;
  RayCaster& operator=(const RayCaster&) = delete;

  // First intersection of origin + t dir, t > 0, with the target.
  RayHit first_hit(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir) const;
  // Closest point of the target to p, and its face.
  RayHit closest(const Eigen::Vector3d& p) const;
  // Number of faces of `other` that intersect the target (exact predicate),
  // stopping once `stop_after` are found.
  std::int64_t count_intersecting(const Surface& other, std::int64_t stop_after = 1) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

struct ProjectionOptions {
  // Rays longer than max_distance_factor x the reach given for each ray count
  // as misses (reach: the local layer thickness). With no reach, any distance.
  double max_distance_factor = 3;
  // A point whose barycentric coordinate in its face is below this is pulled
  // inside (keeps the cells that join it to the face's corners non-degenerate),
  // in [0, 1/3).
  double min_barycentric = 0.02;
};

struct Projection {
  MatX3d points;   // (n_rays x 3) m, on the lower surface
  VecXi faces;     // (n_rays) lower face holding each point
  VecXu8 status;   // (n_rays) ProjectionStatus
  ProjectionCounts counts;
};

// Projects the centroid of every face of `upper` along the face's inward
// normal onto `lower`. expected_face: empty, or (n_upper_faces) the lower face
// each point must fall in (the face under it in corresponding grids). reach:
// empty, or (n_upper_faces) local thickness (m). Rays run in parallel;
// results do not depend on the thread count.
Projection project_centroids(const Surface& upper, const Surface& lower, const VecXi& expected_face,
                             const VecXd& reach, const ProjectionOptions& options);
// The same with a caster already built on `lower`.
Projection project_centroids(const Surface& upper, const Surface& lower, const RayCaster& lower_caster,
                             const VecXi& expected_face, const VecXd& reach, const ProjectionOptions& options);

// Closest point of triangle (a, b, c) to p, returned with its barycentric
// coordinates (l0, l1, l2) (Ericson, Real-Time Collision Detection, 5.1.5).
Eigen::Vector3d closest_on_triangle(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                                    const Eigen::Vector3d& c, Eigen::Vector3d* bary = nullptr);

}  // namespace orthosim::msm
