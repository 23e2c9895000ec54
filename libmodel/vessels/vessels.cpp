// extract_vessels: the stage, from the label volume to the VesselTree, and
// its options and metrics.
#include "libmodel/surface/surface.h"
#include "libmodel/vessels/detail.h"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>

namespace orthosim {

using namespace vessels_detail;

void validate(const VesselOptions& o) {
  auto need = [](bool ok, const std::string& what) {
    if (!ok) throw Error("", what);
  };
  need(std::isfinite(o.tolerance_m) && o.tolerance_m >= 0, "tolerance must be >= 0");
  need(std::isfinite(o.spur_ratio) && o.spur_ratio > 0, "spur_ratio must be > 0");
  need(std::isfinite(o.neck_ratio) && o.neck_ratio >= 0 && o.neck_ratio < 1, "neck_ratio must be in [0, 1)");
  need(std::isfinite(o.min_length_ratio) && o.min_length_ratio >= 0, "min_length_ratio must be >= 0");
  need(std::isfinite(o.min_radius_voxels) && o.min_radius_voxels >= 0, "min_radius_voxels must be >= 0");
  need(std::isfinite(o.merge_ratio) && o.merge_ratio >= 0, "merge_ratio must be >= 0");
  need(std::isfinite(o.patch_gap) && o.patch_gap >= 0, "patch_gap must be >= 0");
  need(o.max_children >= 2 && o.max_children <= 4, "max_children must be in 2..4");
  need(o.ring_vertices >= 8 && o.ring_vertices <= 256 && o.ring_vertices % 4 == 0,
       "ring_vertices must be a multiple of 4 in 8..256, got " + std::to_string(o.ring_vertices));
  need(std::isfinite(o.ring_spacing) && o.ring_spacing > 0, "ring_spacing must be > 0");
  for (const auto& p : o.roots_m) need(p.allFinite(), "root points must be finite");
}

std::string vessel_parameters_json(const VesselOptions& o) {
  nlohmann::json j = {{"tolerance_m", o.tolerance_m},     {"spur_ratio", o.spur_ratio},
                      {"neck_ratio", o.neck_ratio},       {"min_length_ratio", o.min_length_ratio},
                      {"min_radius_voxels", o.min_radius_voxels},
                      {"merge_ratio", o.merge_ratio},     {"patch_gap", o.patch_gap},
                      {"max_children", o.max_children},   {"prune_excess_children", o.prune_excess_children},
                      {"ring_vertices", o.ring_vertices},
                      {"ring_spacing", o.ring_spacing},   {"check_self_intersections", o.check_self_intersections}};
  j["roots_m"] = nlohmann::json::array();
  for (const auto& p : o.roots_m) j["roots_m"].push_back({p.x(), p.y(), p.z()});
  return j.dump();
}

namespace {

double since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// the forest into the model file's arrays
void fill_tree(const Forest& f, VesselTree& t) {
  std::vector<Eigen::Vector3d> nodes;
  std::vector<double> radii;
  std::vector<std::array<int, 2>> edges;
  std::vector<int> parent, offsets{0}, bnodes, last(f.branches.size(), -1);
  std::vector<Eigen::Vector3d> ctrl;
  std::vector<double> ctrl_r;
  std::vector<int> boff{0};
  for (std::size_t bi = 0; bi < f.branches.size(); ++bi) {
    const Branch& b = f.branches[bi];
    int prev = -1;
    std::size_t i0 = 0;
    if (b.parent >= 0) {
      prev = last[b.parent];
      bnodes.push_back(prev);
      i0 = 1;
    }
    for (std::size_t i = i0; i < b.x.size(); ++i) {
      const int id = static_cast<int>(nodes.size());
      nodes.push_back(b.x[i]);
      radii.push_back(b.r[i]);
      bnodes.push_back(id);
      if (prev >= 0) edges.push_back({prev, id});
      prev = id;
    }
    last[bi] = prev;
    parent.push_back(b.parent);
    offsets.push_back(static_cast<int>(bnodes.size()));
    ctrl.insert(ctrl.end(), b.ctrl.begin(), b.ctrl.end());
    ctrl_r.insert(ctrl_r.end(), b.ctrl_r.begin(), b.ctrl_r.end());
    boff.push_back(static_cast<int>(ctrl.size()));
  }
  t.nodes.resize(static_cast<Eigen::Index>(nodes.size()), 3);
  t.radii.resize(static_cast<Eigen::Index>(nodes.size()));
  for (std::size_t i = 0; i < nodes.size(); ++i) {
    t.nodes.row(static_cast<Eigen::Index>(i)) = nodes[i].transpose();
    t.radii(static_cast<Eigen::Index>(i)) = radii[i];
  }
  t.edges.resize(static_cast<Eigen::Index>(edges.size()), 2);
  for (std::size_t i = 0; i < edges.size(); ++i) t.edges.row(static_cast<Eigen::Index>(i)) << edges[i][0], edges[i][1];
  auto vec = [](const std::vector<int>& v) { return VecXi(Eigen::Map<const VecXi>(v.data(), static_cast<Eigen::Index>(v.size()))); };
  t.branch_parent = vec(parent);
  t.branch_offsets = vec(offsets);
  t.branch_nodes = vec(bnodes);
  t.bezier_offsets = vec(boff);
  t.bezier_ctrl.resize(static_cast<Eigen::Index>(ctrl.size()), 3);
  t.bezier_radius.resize(static_cast<Eigen::Index>(ctrl.size()));
  for (std::size_t i = 0; i < ctrl.size(); ++i) {
    t.bezier_ctrl.row(static_cast<Eigen::Index>(i)) = ctrl[i].transpose();
    t.bezier_radius(static_cast<Eigen::Index>(i)) = ctrl_r[i];
  }
}

}  // namespace

VesselResult extract_vessels(const Volume& v, const std::string& tissue, const VesselOptions& o) {
  validate(o);
  const int label = v.label_of(tissue);
  if (label < 0 || tissue.empty() || tissue == "background") {
    std::string names;
    for (std::size_t i = 1; i < v.label_names.size(); ++i)
      if (!v.label_names[i].empty()) names += (names.empty() ? "" : ", ") + v.label_names[i];
    throw Error("", "unknown tissue '" + tissue + "' (the volume's tissues: " + (names.empty() ? "none" : names) + ")");
  }
  if (static_cast<std::size_t>(v.nx) * v.ny * v.nz != v.labels.size() || v.nx <= 0)
    throw Error("", "the label volume's size does not match its data");
  VesselResult res;
  VesselMetrics& M = res.metrics;
  M.tissue = tissue;
  M.label = label;

  auto t0 = std::chrono::steady_clock::now();
  Grid g = make_grid(v, label, tissue);
  M.voxels = g.voxels;
  distance_transform(g);
  M.distance_s = since(t0);

  t0 = std::chrono::steady_clock::now();
  const std::vector<std::size_t> skel = thin(g);
  M.skeleton_voxels = static_cast<std::int64_t>(skel.size());
  M.thinning_s = since(t0);

  t0 = std::chrono::steady_clock::now();
  GraphStats gs;
  Forest f = build_forest(g, skel, o, gs);
  M.graph_s = since(t0);
  M.spurs_pruned = gs.spurs;
  M.loops_broken = gs.loops;
  M.contacts_cut = gs.contacts;
  M.components_dropped = gs.dropped;
  M.thin_components_dropped = gs.thin;
  M.cuts = gs.cuts;
  M.roots_used = gs.roots_used;
  if (f.branches.empty()) {
    std::ostringstream ratio;  // "3", not std::to_string's "3.000000"
    ratio << o.min_length_ratio;
    throw NoVesselError("", "tissue '" + tissue + "': its " + std::to_string(M.voxels) +
                        " voxels form no vessel (every piece is shorter than " + ratio.str() + " radii)");
  }

  t0 = std::chrono::steady_clock::now();
  refine_centrelines(g, o, f);
  M.children_pruned = f.children_pruned;
  M.pruned_length_m = f.pruned_length_m;
  M.centreline_s = since(t0);

  t0 = std::chrono::steady_clock::now();
  M.tolerance_m = o.tolerance_m > 0 ? o.tolerance_m : 0.25 * g.hmin();
  M.bezier_max_deviation_m = fit_bezier(f, M.tolerance_m);
  M.fit_s = since(t0);

  t0 = std::chrono::steady_clock::now();
  std::vector<char> open_cap;
  build_tube(f, o, res.tree, open_cap);
  fill_tree(f, res.tree);
  M.tube_s = since(t0);

  // ---- metrics -------------------------------------------------------------------------
  M.trees = f.trees;
  M.branches = static_cast<int>(f.branches.size());
  for (const Junction& J : f.junctions) {
    if (J.children.size() == 2) ++M.bifurcations;
    if (J.children.size() == 3) ++M.trifurcations;
  }
  for (std::size_t bi = 0; bi < f.branches.size(); ++bi) {
    const Branch& b = f.branches[bi];
    M.bezier_pieces += static_cast<int>(b.knots.size()) - 1;
    double len = 0;
    for (std::size_t i = 1; i < b.x.size(); ++i) len += (b.x[i] - b.x[i - 1]).norm();
    M.length_m += len;
    if (b.start_root) M.ends.push_back({b.x.front(), b.r.front(), static_cast<int>(bi), true, b.start_open});
    if (b.end_leaf) M.ends.push_back({b.x.back(), b.r.back(), static_cast<int>(bi), false, b.end_open});
  }
  M.radius_min_m = res.tree.radii.size() ? res.tree.radii.minCoeff() : 0;
  M.radius_max_m = res.tree.radii.size() ? res.tree.radii.maxCoeff() : 0;
  M.tube_vertices = res.tree.tube_vertices.rows();
  M.tube_quads = res.tree.tube_quads.rows();
  M.tube_tris = res.tree.tube_tris.rows();

  t0 = std::chrono::steady_clock::now();
  const MeshCheck mc = check_mesh(res.tree.tube_vertices, res.tree.tube_quads, res.tree.tube_tris);
  M.tube_closed = mc.closed();
  M.tube_manifold = mc.manifold();
  M.tube_oriented = mc.oriented();
  M.tube_components = mc.components;
  if (o.check_self_intersections) M.self_intersections = static_cast<int>(surface_self_intersections(tube_triangles(res.tree)));
  {
    std::vector<Eigen::Index> keep;
    for (Eigen::Index i = 0; i < res.tree.tube_vertices.rows(); ++i)
      if (!open_cap[static_cast<std::size_t>(i)]) keep.push_back(i);
    MatX3d pts(static_cast<Eigen::Index>(keep.size()), 3);
    for (std::size_t i = 0; i < keep.size(); ++i) pts.row(static_cast<Eigen::Index>(i)) = res.tree.tube_vertices.row(keep[i]);
    VecXd d = distance_to_label_boundary(v, label, pts, 0.05);
    if (d.size()) {
      std::vector<double> s(d.data(), d.data() + d.size());
      std::sort(s.begin(), s.end());
      M.boundary_mean_m = d.mean();
      M.boundary_max_m = s.back();
      M.boundary_p95_m = s[std::min(s.size() - 1, static_cast<std::size_t>(0.95 * static_cast<double>(s.size())))];
    }
  }
  M.check_s = since(t0);
  return res;
}

// ---- Bezier evaluation ----------------------------------------------------------------

int bezier_pieces(const VesselTree& t, int b) { return (t.bezier_offsets(b + 1) - t.bezier_offsets(b) - 1) / 3; }

Eigen::Vector3d bezier_point(const VesselTree& t, int b, int piece, double u) {
  const int o = t.bezier_offsets(b) + 3 * piece;
  return bezier3(t.bezier_ctrl.row(o).transpose(), t.bezier_ctrl.row(o + 1).transpose(),
                 t.bezier_ctrl.row(o + 2).transpose(), t.bezier_ctrl.row(o + 3).transpose(), u);
}

Eigen::Vector3d bezier_derivative(const VesselTree& t, int b, int piece, double u) {
  const int o = t.bezier_offsets(b) + 3 * piece;
  return bezier3_d(t.bezier_ctrl.row(o).transpose(), t.bezier_ctrl.row(o + 1).transpose(),
                   t.bezier_ctrl.row(o + 2).transpose(), t.bezier_ctrl.row(o + 3).transpose(), u);
}

double bezier_radius_at(const VesselTree& t, int b, int piece, double u) {
  const int o = t.bezier_offsets(b) + 3 * piece;
  return bezier3(t.bezier_radius(o), t.bezier_radius(o + 1), t.bezier_radius(o + 2), t.bezier_radius(o + 3), u);
}

}  // namespace orthosim
