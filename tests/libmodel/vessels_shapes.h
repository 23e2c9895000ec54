// Analytic vessel shapes for the vessels tests and benchmark: canal surfaces
// (unions of balls) around parametric centrelines, rasterised into a label
// volume, with their exact centreline trees.
#pragma once

#include "libmodel/format/model.h"

#include <Eigen/Core>

#include <algorithm>
#include <cmath>
#include <functional>
#include <vector>

namespace orthosim::test {

struct TubeSpec {
  std::function<Eigen::Vector3d(double)> centre;  // t in [0, 1] -> m
  std::function<double(double)> radius;           // t in [0, 1] -> m
  int parent = -1;                                // a child starts at its parent's end point
};

// Labels: 0 background, 6 "artery", 7 "vein" (the phantom's table).
inline Volume empty_volume(int nx, int ny, int nz, std::array<double, 3> spacing, std::array<double, 3> origin) {
  Volume v;
  v.nx = nx, v.ny = ny, v.nz = nz;
  v.spacing_m = spacing;
  v.origin_m = origin;
  v.labels.assign(static_cast<std::size_t>(nx) * ny * nz, 0);
  v.label_names = {"background", "skin", "fat", "muscle", "bone", "marrow", "artery", "vein"};
  return v;
}

// Marks every voxel centre inside the union of balls along the tubes.
inline void rasterise(Volume& v, const std::vector<TubeSpec>& tubes, std::uint8_t label) {
  const double h = std::min({v.spacing_m[0], v.spacing_m[1], v.spacing_m[2]});
  for (const TubeSpec& tb : tubes) {
    // samples no farther apart than h / 10
    double len = 0;
    Eigen::Vector3d prev = tb.centre(0);
    for (int i = 1; i <= 1000; ++i) {
      const Eigen::Vector3d p = tb.centre(i / 1000.0);
      len += (p - prev).norm();
      prev = p;
    }
    const int n = std::max(10, static_cast<int>(std::ceil(len / (0.1 * h))));
    for (int i = 0; i <= n; ++i) {
      const double t = static_cast<double>(i) / n;
      const Eigen::Vector3d c = tb.centre(t);
      const double r = tb.radius(t);
      int lo[3], hi[3];
      const int dims[3] = {v.nx, v.ny, v.nz};
      for (int d = 0; d < 3; ++d) {
        lo[d] = std::max(0, static_cast<int>(std::floor((c(d) - r - v.origin_m[d]) / v.spacing_m[d])));
        hi[d] = std::min(dims[d] - 1, static_cast<int>(std::ceil((c(d) + r - v.origin_m[d]) / v.spacing_m[d])));
      }
      for (int z = lo[2]; z <= hi[2]; ++z)
        for (int y = lo[1]; y <= hi[1]; ++y)
          for (int x = lo[0]; x <= hi[0]; ++x)
            if ((v.position(x, y, z) - c).squaredNorm() <= r * r) v.labels[v.index(x, y, z)] = label;
    }
  }
}

// The tubes' exact centrelines as a VesselTree (nodes every `step` m or closer;
// children share their parent's end node), clipped to the volume's voxel
// centres when `clip` is given (a vessel leaving the volume).
inline VesselTree truth_tree(const std::vector<TubeSpec>& tubes, double step, const Volume* clip = nullptr) {
  VesselTree t;
  std::vector<Eigen::Vector3d> nodes;
  std::vector<double> radii;
  std::vector<std::array<int, 2>> edges;
  std::vector<int> parent, offsets{0}, bnodes, last(tubes.size(), -1);
  auto inside = [&](const Eigen::Vector3d& p) {
    if (!clip) return true;
    for (int d = 0; d < 3; ++d) {
      const int n = d == 0 ? clip->nx : (d == 1 ? clip->ny : clip->nz);
      const double lo = clip->origin_m[d], hi = clip->origin_m[d] + (n - 1) * clip->spacing_m[d];
      if (p(d) < lo - 1e-12 || p(d) > hi + 1e-12) return false;
    }
    return true;
  };
  for (std::size_t b = 0; b < tubes.size(); ++b) {
    const TubeSpec& tb = tubes[b];
    int n = 16;
    for (;;) {
      double worst = 0;
      for (int i = 0; i < n; ++i) worst = std::max(worst, (tb.centre((i + 1.0) / n) - tb.centre(double(i) / n)).norm());
      if (worst <= step) break;
      n = static_cast<int>(std::ceil(n * worst / step * 1.05));
    }
    int prev = -1;
    if (tb.parent >= 0) {
      prev = last[tb.parent];
      bnodes.push_back(prev);
    }
    for (int i = tb.parent >= 0 ? 1 : 0; i <= n; ++i) {
      const double s = static_cast<double>(i) / n;
      const Eigen::Vector3d p = tb.centre(s);
      if (!inside(p)) continue;
      const int id = static_cast<int>(nodes.size());
      nodes.push_back(p);
      radii.push_back(tb.radius(s));
      bnodes.push_back(id);
      if (prev >= 0) edges.push_back({prev, id});
      prev = id;
    }
    last[b] = prev;
    parent.push_back(tb.parent);
    offsets.push_back(static_cast<int>(bnodes.size()));
  }
  t.nodes.resize(static_cast<Eigen::Index>(nodes.size()), 3);
  t.radii.resize(static_cast<Eigen::Index>(nodes.size()));
  for (std::size_t i = 0; i < nodes.size(); ++i) {
    t.nodes.row(static_cast<Eigen::Index>(i)) = nodes[i].transpose();
    t.radii(static_cast<Eigen::Index>(i)) = radii[i];
  }
  t.edges.resize(static_cast<Eigen::Index>(edges.size()), 2);
  for (std::size_t i = 0; i < edges.size(); ++i) t.edges.row(static_cast<Eigen::Index>(i)) << edges[i][0], edges[i][1];
  t.branch_parent = Eigen::Map<const VecXi>(parent.data(), static_cast<Eigen::Index>(parent.size()));
  t.branch_offsets = Eigen::Map<const VecXi>(offsets.data(), static_cast<Eigen::Index>(offsets.size()));
  t.branch_nodes = Eigen::Map<const VecXi>(bnodes.data(), static_cast<Eigen::Index>(bnodes.size()));
  return t;
}

inline std::function<double(double)> constant(double r) {
  return [r](double) { return r; };
}
inline std::function<Eigen::Vector3d(double)> segment(Eigen::Vector3d a, Eigen::Vector3d b) {
  return [a, b](double t) { return Eigen::Vector3d(a + t * (b - a)); };
}

// A Y: a parent along z into a bifurcation point, two children leaving it at
// +-half_angle in the x-z plane, bending back toward z (cubic Bezier arms).
inline std::vector<TubeSpec> y_tubes(const Eigen::Vector3d& start, double parent_len, double child_len,
                                     double half_angle, double r_parent, double r_child) {
  const Eigen::Vector3d b = start + Eigen::Vector3d(0, 0, parent_len);
  std::vector<TubeSpec> t;
  t.push_back({segment(start, b), constant(r_parent), -1});
  for (int s : {-1, 1}) {
    const Eigen::Vector3d d(s * std::sin(half_angle), 0, std::cos(half_angle));
    const Eigen::Vector3d p1 = b + child_len / 3 * d;
    const Eigen::Vector3d p3 = b + child_len * Eigen::Vector3d(s * 0.75 * std::sin(half_angle), 0, 0.95);
    const Eigen::Vector3d p2 = p3 - child_len / 3 * Eigen::Vector3d(0, 0, 1);
    t.push_back({[b, p1, p2, p3](double u) {
                   const double v = 1 - u;
                   return Eigen::Vector3d(v * v * v * b + 3 * v * v * u * p1 + 3 * v * u * u * p2 + u * u * u * p3);
                 },
                 [r_parent, r_child](double u) { return r_parent + (r_child - r_parent) * std::min(1.0, 3 * u); }, 0});
  }
  return t;
}

}  // namespace orthosim::test
