#include "runtime/loader.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <set>

namespace orthosim::runtime {

namespace {

std::string join(const std::vector<std::string>& v) {
  std::string s;
  for (const auto& x : v) s += (s.empty() ? "" : ", ") + x;
  return s.empty() ? "none" : s;
}

struct Extent {
  std::string name;
  std::int64_t offset = 0, count = 0;
};

}  // namespace

ModelIndex index_model(const ModelReader& r) {
  ModelIndex idx;
  if (r.has("/layers"))
    for (const auto& n : r.names("/layers"))
      if (n != "sets" && r.h5().is_group("/layers/" + n)) idx.layers.push_back(n);
  if (r.has("/layers/sets")) idx.node_sets = r.names("/layers/sets");
  return idx;
}

Model load_model(const ModelReader& r, const LoadRequest& req) {
  const std::string& path = r.path();
  const h5::File& f = r.h5();
  const ModelIndex idx = index_model(r);

  // every layer's global node range, from attributes and shapes only
  std::vector<Extent> extents;
  std::int64_t n_global = 0;
  for (const auto& name : idx.layers) {
    const std::string g = "/layers/" + name;
    if (!f.has_attr(g, "node_offset")) throw Error(path, g + " has no node_offset attribute");
    if (!f.exists(g + "/nodes")) throw Error(path, "missing dataset " + g + "/nodes");
    const auto d = f.dims(g + "/nodes");
    if (d.size() != 2 || d[1] != 3) throw Error(path, g + "/nodes must have shape (n x 3)");
    Extent e{name, f.attr_int(g, "node_offset"), static_cast<std::int64_t>(d[0])};
    if (e.offset < 0) throw Error(path, g + " has a negative node_offset");
    n_global = std::max(n_global, e.offset + e.count);
    extents.push_back(e);
  }
  {
    auto sorted = extents;
    std::sort(sorted.begin(), sorted.end(), [](const Extent& a, const Extent& b) { return a.offset < b.offset; });
    for (std::size_t i = 1; i < sorted.size(); ++i)
      if (sorted[i].offset < sorted[i - 1].offset + sorted[i - 1].count)
        throw Error(path, "layers '" + sorted[i - 1].name + "' and '" + sorted[i].name + "' own overlapping node ids");
  }
  if (n_global > std::numeric_limits<std::int32_t>::max()) throw Error(path, "too many nodes for 32-bit ids");
  auto owner = [&](std::int64_t gid) -> const Extent* {
    for (const auto& e : extents)
      if (gid >= e.offset && gid < e.offset + e.count) return &e;
    return nullptr;
  };

  // the requested layers
  std::vector<std::string> wanted = req.layers.empty() ? idx.layers : req.layers;
  if (wanted.empty()) throw Error(path, "the model has no layers");
  std::set<std::string> wanted_set;
  for (const auto& name : wanted) {
    if (std::find(idx.layers.begin(), idx.layers.end(), name) == idx.layers.end())
      throw Error(path, "no layer '" + name + "' in the model (layers: " + join(idx.layers) + ")");
    if (!wanted_set.insert(name).second) throw Error(path, "layer '" + name + "' is named twice");
  }
  auto loaded = [&](std::int64_t gid) {
    const Extent* e = owner(gid);
    return e && wanted_set.count(e->name) > 0;
  };

  ModelSource src;
  src.file = path;
  std::vector<std::string> fields{"nodes", "masses", "lin_springs", "lin_rest_length", "lin_k", "lin_damping", "lin_slack"};
  if (req.surface) fields.push_back("quads");
  std::set<std::int64_t> far_ends;
  for (const auto& name : wanted) {
    const std::string g = "/layers/" + name;
    Layer l = r.layer_fields(name, fields);
    // the tetrahedra of the volume term and the inversion guard (a layer with
    // a volume_modulus or a guard_modulus)
    if (l.volume_modulus > 0 || l.guard_modulus > 0) {
      if (f.exists(g + "/tets")) l.tets = r.layer_fields(name, {"tets"}).tets;
      // (the term's own tetrahedra, where the layer has them: Layer::volume_tets)
      if (l.volume_modulus > 0 && f.exists(g + "/volume_tets"))
        l.volume_tets = r.layer_fields(name, {"volume_tets"}).volume_tets;
      if (l.tets.rows() == 0 && (l.guard_modulus > 0 || l.volume_tets.rows() == 0))
        throw Error(path, g + " has a " + (l.guard_modulus > 0 ? "guard_modulus" : "volume_modulus") + " but no tets");
      check_index_range(l.tets, n_global, path, g + "/tets");
      check_index_range(l.volume_tets, n_global, path, g + "/volume_tets");
    }
    check_index_range(l.lin_springs, n_global, path, g + "/lin_springs");
    if (req.surface) check_index_range(l.quads, n_global, path, g + "/quads");
    for (Eigen::Index s = 0; s < l.lin_springs.rows(); ++s)
      for (int k = 0; k < 2; ++k)
        if (!loaded(l.lin_springs(s, k))) far_ends.insert(l.lin_springs(s, k));
    src.layers.emplace_back(name, std::move(l));
  }
  // the layers' stacking (0 outermost): the wound's columns and the report follow it
  for (std::size_t i = 0; i < src.layers.size(); ++i)
    for (std::size_t j = i + 1; j < src.layers.size(); ++j)
      if (src.layers[i].second.order == src.layers[j].second.order)
        throw Error(path, "layers '" + src.layers[i].first + "' and '" + src.layers[j].first + "' have the same order " +
                              std::to_string(src.layers[i].second.order));

  // springs of other layers that reach the loaded nodes
  if (req.couple_unloaded) {
    Layer& extra = src.extra_springs;
    std::vector<std::array<std::int32_t, 2>> ends;
    std::vector<Real> rest, k, c;
    std::vector<std::uint8_t> slack;
    for (const auto& e : extents) {
      if (wanted_set.count(e.name)) continue;
      const std::string g = "/layers/" + e.name;
      if (!f.exists(g + "/lin_springs")) continue;
      Layer idx_only = r.layer_fields(e.name, {"lin_springs"});
      check_index_range(idx_only.lin_springs, n_global, path, g + "/lin_springs");
      std::vector<Eigen::Index> touching;
      for (Eigen::Index s = 0; s < idx_only.lin_springs.rows(); ++s)
        if (loaded(idx_only.lin_springs(s, 0)) || loaded(idx_only.lin_springs(s, 1))) touching.push_back(s);
      if (touching.empty()) continue;
      Layer params = r.layer_fields(e.name, {"lin_rest_length", "lin_k", "lin_damping", "lin_slack"});
      if (params.lin_k.size() != idx_only.lin_springs.rows())
        throw Error(path, g + ": lin_k and lin_springs have different lengths");
      for (auto s : touching) {
        const std::int32_t a = idx_only.lin_springs(s, 0), b = idx_only.lin_springs(s, 1);
        ends.push_back({a, b});
        rest.push_back(params.lin_rest_length[s]);
        k.push_back(params.lin_k[s]);
        c.push_back(params.lin_damping[s]);
        slack.push_back(params.lin_slack[s]);
        if (!loaded(a)) far_ends.insert(a);
        if (!loaded(b)) far_ends.insert(b);
      }
    }
    const auto n = static_cast<Eigen::Index>(ends.size());
    extra.lin_springs.resize(n, 2);
    extra.lin_rest_length.resize(n);
    extra.lin_k.resize(n);
    extra.lin_damping.resize(n);
    extra.lin_slack.resize(n);
    for (Eigen::Index s = 0; s < n; ++s) {
      extra.lin_springs(s, 0) = ends[s][0];
      extra.lin_springs(s, 1) = ends[s][1];
      extra.lin_rest_length[s] = rest[s];
      extra.lin_k[s] = k[s];
      extra.lin_damping[s] = c[s];
      extra.lin_slack[s] = slack[s];
    }
  }

  // anchor positions: the nodes of the layers owning the far ends
  std::set<std::string> anchor_layers;
  for (auto gid : far_ends) {
    const Extent* e = owner(gid);
    if (!e) throw Error(path, "a spring reaches node " + std::to_string(gid) + ", which no layer owns");
    anchor_layers.insert(e->name);
  }
  for (const auto& name : anchor_layers) {
    const Layer l = r.layer_fields(name, {"nodes"});
    const std::int64_t off = l.node_offset;
    for (auto gid : far_ends) {
      if (gid < off || gid >= off + l.nodes.rows()) continue;
      const auto i = static_cast<Eigen::Index>(gid - off);
      src.anchor_positions[static_cast<std::int32_t>(gid)] = {l.nodes(i, 0), l.nodes(i, 1), l.nodes(i, 2)};
    }
  }

  // node sets
  for (const auto& name : req.node_sets) {
    if (std::find(idx.node_sets.begin(), idx.node_sets.end(), name) == idx.node_sets.end())
      throw Error(path, "no node set '" + name + "' in the model (sets: " + join(idx.node_sets) + ")");
    VecXi ids = r.node_set(name);
    check_index_range(ids, n_global, path, "/layers/sets/" + name);
    src.node_sets[name] = std::move(ids);
  }

  Model m = assemble_model(src);

  // vessels (static until issue 9 couples them)
  for (const auto& name : req.vessels) {
    const std::string g = "/vessels/" + name;
    if (!f.is_group(g)) throw Error(path, "no vessel tree '" + name + "' in the model");
    for (const char* d : {"nodes", "radii", "edges"})
      if (!f.exists(g + "/" + d)) throw Error(path, "missing dataset " + g + "/" + d);
    std::vector<std::uint64_t> dn, dr, de;
    Model::Vessel v;
    v.name = name;
    v.nodes = f.read<double>(g + "/nodes", &dn);
    v.radii = f.read<double>(g + "/radii", &dr);
    v.edges = f.read<std::int32_t>(g + "/edges", &de);
    if (dn.size() != 2 || dn[1] != 3 || dr.size() != 1 || dr[0] != dn[0] || de.size() != 2 || de[1] != 2)
      throw Error(path, g + ": nodes (n x 3), radii (n) and edges (n_edges x 2) do not match");
    for (auto e : v.edges)
      if (e < 0 || static_cast<std::uint64_t>(e) >= dn[0]) throw Error(path, g + "/edges has a node id out of range");
    for (auto x : v.nodes)
      if (!(std::isfinite(x) && std::abs(x) <= kMaxLength)) throw Error(path, g + "/nodes has a non-finite value or one beyond 1e6 m");
    for (auto x : v.radii)
      if (!(std::isfinite(x) && x >= 0 && x <= kMaxLength)) throw Error(path, g + "/radii has a negative or non-finite value or one beyond 1e6 m");
    if (req.vessel_tubes && f.exists(g + "/tube_vertices")) {
      std::vector<std::uint64_t> dv, dq, dt;
      v.tube_vertices = f.read<double>(g + "/tube_vertices", &dv);
      const std::vector<std::int32_t> quads =
          f.exists(g + "/tube_quads") ? f.read<std::int32_t>(g + "/tube_quads", &dq) : std::vector<std::int32_t>{};
      const std::vector<std::int32_t> tris =
          f.exists(g + "/tube_tris") ? f.read<std::int32_t>(g + "/tube_tris", &dt) : std::vector<std::int32_t>{};
      const std::uint64_t nt = v.tube_vertices.size() / 3;
      if ((!v.tube_vertices.empty() && (dv.size() != 2 || dv[1] != 3)) || (!quads.empty() && (dq.size() != 2 || dq[1] != 4)) ||
          (!tris.empty() && (dt.size() != 2 || dt[1] != 3)))
        throw Error(path, g + ": tube_vertices (n x 3), tube_quads (n x 4) and tube_tris (n x 3) have wrong shapes");
      for (auto x : v.tube_vertices)
        if (!(std::isfinite(x) && std::abs(x) <= kMaxLength)) throw Error(path, g + "/tube_vertices has a non-finite value or one beyond 1e6 m");
      for (const auto* ids : {&quads, &tris})
        for (auto i : *ids)
          if (i < 0 || static_cast<std::uint64_t>(i) >= nt) throw Error(path, g + ": a tube face has a vertex id out of range");
      v.tube_triangles.reserve(quads.size() / 4 * 6 + tris.size());
      for (std::size_t q = 0; q + 3 < quads.size(); q += 4)
        v.tube_triangles.insert(v.tube_triangles.end(),
                                {quads[q], quads[q + 1], quads[q + 2], quads[q], quads[q + 2], quads[q + 3]});
      v.tube_triangles.insert(v.tube_triangles.end(), tris.begin(), tris.end());
    }
    m.vessels.push_back(std::move(v));
  }
  return m;
}

}  // namespace orthosim::runtime
