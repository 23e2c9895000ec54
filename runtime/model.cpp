#include "runtime/model.h"

#include "runtime/kernels.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <numeric>
#include <unordered_map>

namespace orthosim::runtime {

namespace {

bool finite_nonneg(Real x) { return std::isfinite(x) && x >= 0; }
// Positions and lengths beyond 1e6 m are no anatomy, and their squares (1e300
// -> inf) made every step non-finite and wrote inf strains into the series
bool in_range(Real x) { return std::isfinite(x) && std::abs(x) <= kMaxLength; }

template <class T>
void permute(std::vector<T>& v, const std::vector<std::int32_t>& order) {
  std::vector<T> out(v.size());
  for (std::size_t i = 0; i < order.size(); ++i) out[i] = v[static_cast<std::size_t>(order[i])];
  v.swap(out);
}

}  // namespace

void Model::finalize() {
  const std::size_t n = static_cast<std::size_t>(n_nodes);
  const std::size_t ns = static_cast<std::size_t>(n_springs);
  if (n_nodes < 0 || n_springs < 0 || n_anchors < 0 || n_anchors > n_nodes)
    throw Error("", "model: negative or inconsistent counts");
  if (rest_x.size() != 3 * n || mass.size() != n) throw Error("", "model: node arrays do not match n_nodes");
  if (inv_mass.empty()) {
    inv_mass.resize(n);
    for (std::size_t i = 0; i < n; ++i) inv_mass[i] = mass[i] > 0 ? 1 / mass[i] : 0;
  }
  if (file_id.empty()) {
    file_id.resize(n);
    std::iota(file_id.begin(), file_id.end(), 0);
  }
  if (node_layer.empty()) node_layer.assign(n, -1);
  if (inv_mass.size() != n || file_id.size() != n || node_layer.size() != n)
    throw Error("", "model: node arrays do not match n_nodes");
  if (spring_a.size() != ns || spring_b.size() != ns || spring_rest.size() != ns || spring_k.size() != ns ||
      spring_c.size() != ns || spring_tension.size() != ns)
    throw Error("", "model: spring arrays do not match n_springs");
  if (quads.size() != 4 * static_cast<std::size_t>(n_quads)) throw Error("", "model: quads do not match n_quads");

  // nodes: finite positions, non-negative finite masses
  for (std::size_t i = 0; i < 3 * n; ++i)
    if (!in_range(rest_x[i]))
      throw Error("", "model: node " + std::to_string(i / 3) + " has a non-finite position or one beyond 1e6 m");
  for (std::size_t i = 0; i < n; ++i)
    if (!finite_nonneg(mass[i]) || !finite_nonneg(inv_mass[i]))
      throw Error("", "model: node " + std::to_string(i) + " has an invalid mass");

  // springs: ends in range and distinct, finite non-negative parameters; a < b
  for (std::size_t s = 0; s < ns; ++s) {
    auto& a = spring_a[s];
    auto& b = spring_b[s];
    if (a < 0 || b < 0 || a >= n_nodes || b >= n_nodes)
      throw Error("", "model: spring " + std::to_string(s) + " has an end outside [0, " + std::to_string(n_nodes) + ")");
    if (a == b) throw Error("", "model: spring " + std::to_string(s) + " joins node " + std::to_string(a) + " to itself");
    if (!finite_nonneg(spring_rest[s]) || !in_range(spring_rest[s]) || !finite_nonneg(spring_k[s]) || !finite_nonneg(spring_c[s]))
      throw Error("", "model: spring " + std::to_string(s) +
                          " has a negative or non-finite rest length, stiffness or damping, or a rest length beyond 1e6 m");
    if (a > b) std::swap(a, b);
  }
  std::vector<std::int32_t> order(ns);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](std::int32_t p, std::int32_t q) {
    return spring_a[p] != spring_a[q] ? spring_a[p] < spring_a[q] : spring_b[p] < spring_b[q];
  });
  permute(spring_a, order);
  permute(spring_b, order);
  permute(spring_rest, order);
  permute(spring_k, order);
  permute(spring_c, order);
  permute(spring_tension, order);

  // adjacency: first-end ranges and second-end lists
  a_first.assign(n + 1, 0);
  b_first.assign(n + 1, 0);
  for (std::size_t s = 0; s < ns; ++s) {
    ++a_first[static_cast<std::size_t>(spring_a[s]) + 1];
    ++b_first[static_cast<std::size_t>(spring_b[s]) + 1];
  }
  for (std::size_t i = 0; i < n; ++i) {
    a_first[i + 1] += a_first[i];
    b_first[i + 1] += b_first[i];
  }
  b_spring.assign(ns, 0);
  {
    std::vector<std::int32_t> fill(b_first.begin(), b_first.end() - 1);
    for (std::size_t s = 0; s < ns; ++s) b_spring[static_cast<std::size_t>(fill[spring_b[s]]++)] = static_cast<std::int32_t>(s);
  }

  // node-neighbour rows
  nbr_first.assign(n + 1, 0);
  nbr.clear();
  slot_a.assign(ns, 0);
  slot_b.assign(ns, 0);
  {
    std::vector<std::int32_t> row;
    for (std::size_t i = 0; i < n; ++i) {
      row.clear();
      for (std::int32_t q = a_first[i]; q < a_first[i + 1]; ++q) row.push_back(spring_b[static_cast<std::size_t>(q)]);
      for (std::int32_t q = b_first[i]; q < b_first[i + 1]; ++q) row.push_back(spring_a[static_cast<std::size_t>(b_spring[static_cast<std::size_t>(q)])]);
      std::sort(row.begin(), row.end());
      row.erase(std::unique(row.begin(), row.end()), row.end());
      const auto base = static_cast<std::int32_t>(nbr.size());
      nbr.insert(nbr.end(), row.begin(), row.end());
      nbr_first[i + 1] = static_cast<std::int32_t>(nbr.size());
      auto slot = [&](std::int32_t j) {
        return base + static_cast<std::int32_t>(std::lower_bound(row.begin(), row.end(), j) - row.begin());
      };
      for (std::int32_t q = a_first[i]; q < a_first[i + 1]; ++q) slot_a[static_cast<std::size_t>(q)] = slot(spring_b[static_cast<std::size_t>(q)]);
      for (std::int32_t q = b_first[i]; q < b_first[i + 1]; ++q) {
        const auto sq = static_cast<std::size_t>(b_spring[static_cast<std::size_t>(q)]);
        slot_b[sq] = slot(spring_a[sq]);
      }
    }
  }

  // volume term: corners in range and distinct, a finite modulus >= 0, the
  // same in a group, groups of consecutive tetrahedra with a non-zero rest
  // volume; each node's corners
  if (n_tets < 0 || tet.size() != 4 * static_cast<std::size_t>(n_tets) || tet_k.size() != static_cast<std::size_t>(n_tets))
    throw Error("", "model: tetrahedron arrays do not match n_tets");
  const auto nt = static_cast<std::size_t>(n_tets);
  if (tet_guard.empty()) tet_guard.assign(nt, 0);
  if (tet_guard.size() != nt) throw Error("", "model: tetrahedron guard ratios do not match n_tets");
  if (tet_group_first.empty()) {
    tet_group_first.resize(nt + 1);
    std::iota(tet_group_first.begin(), tet_group_first.end(), 0);
  }
  if (tet_group_first.front() != 0 || tet_group_first.back() != n_tets ||
      !std::is_sorted(tet_group_first.begin(), tet_group_first.end()) ||
      std::adjacent_find(tet_group_first.begin(), tet_group_first.end()) != tet_group_first.end())
    throw Error("", "model: tetrahedron groups are not consecutive non-empty ranges");
  n_groups = static_cast<std::int32_t>(tet_group_first.size()) - 1;
  tet_rest_volume.assign(nt, 0);
  tet_group.assign(nt, 0);
  group_rest_volume.assign(static_cast<std::size_t>(n_groups), 0);
  for (std::int32_t g = 0; g < n_groups; ++g)
    for (std::int32_t t = tet_group_first[g]; t < tet_group_first[g + 1]; ++t) {
      const std::int32_t* c = &tet[4 * static_cast<std::size_t>(t)];
      for (int k = 0; k < 4; ++k) {
        if (c[k] < 0 || c[k] >= n_nodes) throw Error("", "model: tetrahedron " + std::to_string(t) + " has a corner outside the model");
        for (int j = 0; j < k; ++j)
          if (c[j] == c[k]) throw Error("", "model: tetrahedron " + std::to_string(t) + " repeats a corner");
      }
      if (!(finite_nonneg(tet_k[t]) && tet_k[t] < 1e15) || tet_k[t] != tet_k[tet_group_first[g]])
        throw Error("", "model: tetrahedron " + std::to_string(t) + " has a negative or non-finite volume modulus, or not its group's");
      if (!(tet_guard[t] >= 0 && tet_guard[t] < 1) || tet_guard[t] != tet_guard[tet_group_first[g]])
        throw Error("", "model: tetrahedron " + std::to_string(t) + " has a guard ratio outside [0, 1), or not its group's");
      const Real v = tet_gradient(load3(rest_x.data(), c[0]), load3(rest_x.data(), c[1]), load3(rest_x.data(), c[2]),
                                  load3(rest_x.data(), c[3])).volume;
      if (!std::isfinite(v)) throw Error("", "model: tetrahedron " + std::to_string(t) + " has a non-finite volume");
      tet_rest_volume[t] = v;
      tet_group[t] = g;
      group_rest_volume[static_cast<std::size_t>(g)] += v;
    }
  for (std::int32_t g = 0; g < n_groups; ++g)
    if (!(std::abs(group_rest_volume[static_cast<std::size_t>(g)]) > 0))
      throw Error("", "model: tetrahedron group " + std::to_string(g) + " has no volume at rest");
  tet_first.assign(n + 1, 0);
  for (auto c : tet) ++tet_first[static_cast<std::size_t>(c) + 1];
  for (std::size_t i = 0; i < n; ++i) tet_first[i + 1] += tet_first[i];
  tet_corner.assign(4 * nt, 0);
  tet_guard_begin.assign(n, 0);
  {
    // the volume terms' corners, then the guards': a guard is mostly inactive,
    // and the solver skips a node's guard corners where none of its guards acts
    std::vector<std::int32_t> fill(tet_first.begin(), tet_first.end() - 1);
    for (std::size_t e = 0; e < 4 * nt; ++e)
      if (tet_guard[e / 4] == 0) tet_corner[static_cast<std::size_t>(fill[tet[e]]++)] = static_cast<std::int32_t>(e);
    std::copy(fill.begin(), fill.end(), tet_guard_begin.begin());
    for (std::size_t e = 0; e < 4 * nt; ++e)
      if (tet_guard[e / 4] != 0) tet_corner[static_cast<std::size_t>(fill[tet[e]]++)] = static_cast<std::int32_t>(e);
  }
  tet_chunk = std::clamp<std::int32_t>((n_groups + 15) / 16, 64, 2048);
  n_tet_chunks = n_groups == 0 ? 0 : (n_groups + tet_chunk - 1) / tet_chunk;

  // chunks: a function of n_nodes only
  chunk = std::clamp<std::int32_t>((n_nodes + 15) / 16, 64, 2048);
  n_chunks = n_nodes == 0 ? 0 : (n_nodes + chunk - 1) / chunk;

  // stability data
  omega2.assign(n, 0);
  gamma.assign(n, 0);
  for (std::size_t s = 0; s < ns; ++s) {
    const auto a = static_cast<std::size_t>(spring_a[s]);
    const auto b = static_cast<std::size_t>(spring_b[s]);
    const Real cross = std::sqrt(inv_mass[a] * inv_mass[b]);
    if (inv_mass[a] > 0) {
      omega2[a] += spring_k[s] * (inv_mass[a] + cross);
      gamma[a] += spring_c[s] * (inv_mass[a] + cross);
    }
    if (inv_mass[b] > 0) {
      omega2[b] += spring_k[s] * (inv_mass[b] + cross);
      gamma[b] += spring_c[s] * (inv_mass[b] + cross);
    }
  }
  // the volume groups: (k/|V0|) |G_i| sum_j |G_j| / sqrt(m_i m_j), G the group's dV/dx at rest
  for (std::int32_t g = 0; g < n_groups; ++g) {
    std::vector<std::pair<std::int32_t, Vec3>> G;  // node, its summed gradient
    for (std::int32_t t = tet_group_first[g]; t < tet_group_first[g + 1]; ++t) {
      const std::int32_t* c = &tet[4 * static_cast<std::size_t>(t)];
      const TetGradient tg = tet_gradient(load3(rest_x.data(), c[0]), load3(rest_x.data(), c[1]),
                                          load3(rest_x.data(), c[2]), load3(rest_x.data(), c[3]));
      for (int k = 0; k < 4; ++k) {
        auto it = std::find_if(G.begin(), G.end(), [&](const auto& e) { return e.first == c[k]; });
        if (it == G.end()) G.emplace_back(c[k], tg.g[k]);
        else it->second += tg.g[k];
      }
    }
    const Real coef = tet_k[tet_group_first[g]] / std::abs(group_rest_volume[static_cast<std::size_t>(g)]);
    Real row = 0;  // sum_j |G_j| / sqrt(m_j)
    for (const auto& [j, gj] : G) row += norm(gj) * std::sqrt(inv_mass[static_cast<std::size_t>(j)]);
    for (const auto& [i, gi] : G) {
      const auto a = static_cast<std::size_t>(i);
      if (inv_mass[a] > 0) omega2[a] += coef * norm(gi) * std::sqrt(inv_mass[a]) * row;
    }
  }
  total_mass = 0;
  for (std::size_t i = 0; i < n; ++i)
    if (inv_mass[i] > 0) total_mass += mass[i];
  extent = 0;
  if (n > 0) {
    Real lo[3] = {HUGE_VAL, HUGE_VAL, HUGE_VAL}, hi[3] = {-HUGE_VAL, -HUGE_VAL, -HUGE_VAL};
    for (std::size_t i = 0; i < n; ++i)
      for (int k = 0; k < 3; ++k) {
        lo[k] = std::min(lo[k], rest_x[3 * i + k]);
        hi[k] = std::max(hi[k], rest_x[3 * i + k]);
      }
    extent = std::sqrt((hi[0] - lo[0]) * (hi[0] - lo[0]) + (hi[1] - lo[1]) * (hi[1] - lo[1]) +
                       (hi[2] - lo[2]) * (hi[2] - lo[2]));
  }

  for (auto& [name, ids] : node_sets) {
    std::sort(ids.begin(), ids.end());
    ids.erase(std::unique(ids.begin(), ids.end()), ids.end());
    for (auto id : ids)
      if (id < 0 || id >= n_nodes) throw Error("", "model: node set '" + name + "' has a node outside the model");
  }
  for (auto q : quads)
    if (q < 0 || q >= n_nodes) throw Error("", "model: a surface quad has a node outside the model");

  // each node's shortest spring, at the first finalize (a cut keeps it)
  if (shortest_spring.size() != n) {
    shortest_spring.assign(n, 0);
    for (std::size_t s = 0; s < ns; ++s)
      for (const std::int32_t i : {spring_a[s], spring_b[s]}) {
        Real& l = shortest_spring[static_cast<std::size_t>(i)];
        l = l > 0 ? std::min(l, spring_rest[s]) : spring_rest[s];
      }
  }
}

const std::vector<std::int32_t>& Model::set(const std::string& name) const {
  auto it = node_sets.find(name);
  if (it == node_sets.end()) throw Error("", "no node set '" + name + "' in the model");
  return it->second;
}

namespace {

// appends the lin_* springs of `l` (global ids) through `local` into m
void append_springs(const Layer& l, const std::string& file, const std::string& what,
                    const std::function<bool(std::int32_t)>& loaded,
                    const std::function<std::int32_t(std::int32_t)>& local, Model& m) {
  const Eigen::Index ns = l.lin_springs.rows();
  if (l.lin_rest_length.size() != ns || l.lin_k.size() != ns || l.lin_damping.size() != ns || l.lin_slack.size() != ns)
    throw Error(file, what + ": lin_* arrays have different lengths");
  for (Eigen::Index s = 0; s < ns; ++s) {
    const std::int32_t ga = l.lin_springs(s, 0), gb = l.lin_springs(s, 1);
    if (!loaded(ga) && !loaded(gb)) continue;  // between two nodes not simulated
    const std::int32_t a = local(ga), b = local(gb);
    if (a < 0 || b < 0) continue;  // reaches nothing loaded: dropped
    const Real rest = l.lin_rest_length[s], k = l.lin_k[s], c = l.lin_damping[s];
    if (a == b) throw Error(file, what + ": linear spring " + std::to_string(s) + " joins a node to itself");
    if (!finite_nonneg(rest) || !in_range(rest))
      throw Error(file, what + ": linear spring " + std::to_string(s) + " has an invalid rest length (negative, non-finite or beyond 1e6 m)");
    if (!finite_nonneg(k)) throw Error(file, what + ": linear spring " + std::to_string(s) + " has a negative or non-finite stiffness");
    if (!finite_nonneg(c)) throw Error(file, what + ": linear spring " + std::to_string(s) + " has a negative or non-finite damping");
    if (l.lin_slack[s] > 1)
      throw Error(file, what + ": linear spring " + std::to_string(s) + " has lin_slack " + std::to_string(l.lin_slack[s]) +
                            " (0: always acts, 1: acts when longer than its rest length)");
    m.spring_a.push_back(a);
    m.spring_b.push_back(b);
    m.spring_rest.push_back(rest);
    m.spring_k.push_back(k);
    m.spring_c.push_back(c);
    m.spring_tension.push_back(l.lin_slack[s] ? 1 : 0);
  }
}

}  // namespace

Model assemble_model(const ModelSource& src) {
  Model m;
  const std::string& file = src.file;
  // loaded nodes in ascending global id
  std::vector<std::size_t> layer_order(src.layers.size());
  std::iota(layer_order.begin(), layer_order.end(), 0);
  std::stable_sort(layer_order.begin(), layer_order.end(), [&](std::size_t p, std::size_t q) {
    return src.layers[p].second.node_offset < src.layers[q].second.node_offset;
  });
  std::unordered_map<std::int32_t, std::int32_t> local;
  for (std::size_t li : layer_order) {
    const auto& [name, l] = src.layers[li];
    const Eigen::Index nn = l.nodes.rows();
    if (l.masses.size() != nn)
      throw Error(file, "/layers/" + name + ": masses has " + std::to_string(l.masses.size()) + " rows but nodes has " +
                            std::to_string(nn));
    Model::LayerInfo info{name, l.tissue, l.kind, l.order, m.n_nodes, static_cast<std::int32_t>(nn)};
    for (Eigen::Index i = 0; i < nn; ++i) {
      const auto gid = static_cast<std::int32_t>(l.node_offset + i);
      if (!local.emplace(gid, m.n_nodes).second)
        throw Error(file, "/layers/" + name + ": node " + std::to_string(gid) + " is owned by two loaded layers");
      const Real mass = l.masses[i];
      if (!(std::isfinite(mass) && mass > 0))
        throw Error(file, "/layers/" + name + ": node " + std::to_string(gid) + " has a non-positive or non-finite mass");
      for (int k = 0; k < 3; ++k) {
        if (!in_range(l.nodes(i, k)))
          throw Error(file, "/layers/" + name + ": node " + std::to_string(gid) + " has a non-finite position or one beyond 1e6 m");
        m.rest_x.push_back(l.nodes(i, k));
      }
      m.mass.push_back(mass);
      m.file_id.push_back(gid);
      m.node_layer.push_back(static_cast<std::int32_t>(m.layers.size()));
      ++m.n_nodes;
    }
    m.layers.push_back(info);
  }
  const std::int32_t n_loaded = m.n_nodes;
  // anchors are created on first use, in the order springs reach them
  auto to_local = [&](std::int32_t gid) -> std::int32_t {
    auto it = local.find(gid);
    if (it != local.end()) return it->second;
    auto a = src.anchor_positions.find(gid);
    if (a == src.anchor_positions.end()) return -1;
    const std::int32_t id = m.n_nodes++;
    local.emplace(gid, id);
    for (int k = 0; k < 3; ++k) m.rest_x.push_back(a->second[k]);
    m.mass.push_back(0);
    m.file_id.push_back(gid);
    m.node_layer.push_back(-1);
    return id;
  };
  auto is_loaded = [&](std::int32_t gid) {
    auto it = local.find(gid);
    return it != local.end() && it->second < n_loaded;
  };
  for (std::size_t li : layer_order) {
    const auto& [name, l] = src.layers[li];
    append_springs(l, file, "/layers/" + name, is_loaded, to_local, m);
  }
  append_springs(src.extra_springs, file, "springs of unloaded layers", is_loaded, to_local, m);
  // the volume term's groups of tetrahedra (volume_group each), then the
  // inversion guard's (one tetrahedron each), where every corner is in the
  // model and one is loaded
  m.tet_group_first.assign(1, 0);
  auto add_groups = [&](const MatX4i& tets, Eigen::Index G, Real k, Real guard) {
    for (Eigen::Index t0 = 0; t0 < tets.rows(); t0 += G) {
      std::vector<std::int32_t> c;
      bool any = false, all = true;
      for (Eigen::Index t = t0; t < t0 + G && all; ++t)
        for (int q = 0; q < 4; ++q) {
          any = any || is_loaded(tets(t, q));
          auto it = local.find(tets(t, q));
          all = all && it != local.end();
          c.push_back(all ? it->second : -1);
        }
      if (!any || !all) continue;
      // a guard needs a rest orientation: a tetrahedron flat at rest has none
      // and is left unguarded (counted) rather than refusing the model
      if (guard > 0 && !(std::abs(tet_gradient(load3(m.rest_x.data(), c[0]), load3(m.rest_x.data(), c[1]),
                                               load3(m.rest_x.data(), c[2]), load3(m.rest_x.data(), c[3]))
                                      .volume) > 0)) {
        ++m.flat_guards_skipped;
        continue;
      }
      m.tet.insert(m.tet.end(), c.begin(), c.end());
      m.tet_k.insert(m.tet_k.end(), static_cast<std::size_t>(G), k);
      m.tet_guard.insert(m.tet_guard.end(), static_cast<std::size_t>(G), guard);
      m.tet_group_first.push_back(static_cast<std::int32_t>(m.tet_k.size()));
    }
  };
  for (std::size_t li : layer_order) {
    const auto& [name, l] = src.layers[li];
    if (l.volume_modulus > 0) {
      // over the term's own tetrahedra where the layer has them (a tetra
      // layer's grid prisms), else over its cells'
      const bool own = l.volume_tets.rows() > 0;
      const MatX4i& vt = own ? l.volume_tets : l.tets;
      const Eigen::Index G = std::max(1, l.volume_group);
      if (vt.rows() % G != 0)
        throw Error(file, "/layers/" + name + ": " + std::to_string(vt.rows()) + (own ? " volume_tets" : " tets") +
                              " are not groups of volume_group " + std::to_string(G));
      add_groups(vt, G, l.volume_modulus, 0);
    }
    if (l.guard_modulus > 0) {
      if (!(l.guard_ratio > 0 && l.guard_ratio < 1))
        throw Error(file, "/layers/" + name + ": guard_ratio must be in (0, 1)");
      add_groups(l.tets, 1, l.guard_modulus, l.guard_ratio);
    }
  }
  m.n_tets = static_cast<std::int32_t>(m.tet_k.size());
  m.n_anchors = m.n_nodes - n_loaded;
  m.n_springs = static_cast<std::int32_t>(m.spring_a.size());
  m.inv_mass.resize(static_cast<std::size_t>(m.n_nodes));
  for (std::int32_t i = 0; i < m.n_nodes; ++i) m.inv_mass[i] = m.mass[i] > 0 ? 1 / m.mass[i] : 0;

  // surface quads of loaded layers whose four corners are in the model
  for (std::size_t li : layer_order) {
    const auto& l = src.layers[li].second;
    for (Eigen::Index q = 0; q < l.quads.rows(); ++q) {
      std::int32_t ids[4];
      bool ok = true;
      for (int k = 0; k < 4; ++k) {
        auto it = local.find(l.quads(q, k));
        ok = ok && it != local.end();
        ids[k] = ok ? it->second : -1;
      }
      if (!ok) continue;
      m.quads.insert(m.quads.end(), ids, ids + 4);
      ++m.n_quads;
    }
  }
  for (const auto& [name, gids] : src.node_sets) {
    auto& out = m.node_sets[name];
    for (Eigen::Index i = 0; i < gids.size(); ++i) {
      auto it = local.find(gids[i]);
      if (it != local.end()) out.push_back(it->second);
    }
  }
  try {
    m.finalize();
  } catch (const Error& e) {
    throw Error(file, e.message());
  }
  return m;
}

Model model_from_layers(const std::vector<std::pair<std::string, Layer>>& layers,
                        const std::map<std::string, VecXi>& node_sets) {
  ModelSource src;
  src.layers = layers;
  src.node_sets = node_sets;
  return assemble_model(src);
}

std::vector<LayerColumns> layer_columns(const Model& m) {
  std::vector<LayerColumns> out;
  if (m.layers.size() < 2) return out;
  std::vector<const Model::LayerInfo*> by_order;
  for (const auto& l : m.layers) by_order.push_back(&l);
  std::sort(by_order.begin(), by_order.end(), [](const auto* a, const auto* b) { return a->order < b->order; });
  if (by_order.back()->kind != "rigid") return out;
  const std::int32_t ng = by_order.back()->count;
  // local id of each file id (the first, where a cut split a node)
  std::int32_t max_file = 0;
  for (std::int32_t f : m.file_id) max_file = std::max(max_file, f);
  std::vector<std::int32_t> local(static_cast<std::size_t>(max_file) + 1, -1);
  std::vector<std::uint8_t> split(static_cast<std::size_t>(max_file) + 1, 0);
  for (std::int32_t i = 0; i < m.n_nodes - m.n_anchors; ++i) {
    const auto f = static_cast<std::size_t>(m.file_id[static_cast<std::size_t>(i)]);
    if (local[f] < 0) local[f] = i;
    else split[f] = 1;
  }
  for (std::size_t k = 0; k + 1 < by_order.size(); ++k) {
    const Model::LayerInfo &top = *by_order[k], &bottom = *by_order[k + 1];
    if (bottom.order != top.order + 1 || top.count < ng || bottom.count < ng) continue;
    const std::int32_t top0 = m.file_id[static_cast<std::size_t>(top.first)];
    const std::int32_t bottom0 = m.file_id[static_cast<std::size_t>(bottom.first)];
    LayerColumns c;
    c.layer = top.name;
    for (std::int32_t i = 0; i < ng; ++i) {
      const std::size_t ft = static_cast<std::size_t>(top0 + i), fb = static_cast<std::size_t>(bottom0 + i);
      if (ft >= local.size() || fb >= local.size() || local[ft] < 0 || local[fb] < 0 || split[ft] || split[fb]) continue;
      c.columns.push_back({local[ft], local[fb]});
    }
    out.push_back(std::move(c));
  }
  return out;
}

std::vector<InvertedColumns> inverted_columns(const Model& m, std::span<const Real> x) {
  std::vector<InvertedColumns> out;
  for (const LayerColumns& lc : layer_columns(m)) {
    InvertedColumns c;
    c.layer = lc.layer;
    for (const auto& pair : lc.columns) {
      if (std::binary_search(m.severed_columns.begin(), m.severed_columns.end(), pair)) continue;
      const std::size_t a = 3 * static_cast<std::size_t>(pair.first), b = 3 * static_cast<std::size_t>(pair.second);
      Real dot = 0;
      for (int d = 0; d < 3; ++d) dot += (x[a + d] - x[b + d]) * (m.rest_x[a + d] - m.rest_x[b + d]);
      ++c.columns;
      if (!(dot > 0)) ++c.inverted;
    }
    out.push_back(c);
  }
  return out;
}

}  // namespace orthosim::runtime
