// Skeleton voxels -> graph -> spur pruning, loop breaking, contact cutting,
// junction merging -> rooted forest of branches.
#include "libmodel/vessels/detail.h"

#include <algorithm>
#include <cmath>
#include <deque>
#include <map>
#include <numeric>
#include <set>

namespace orthosim::vessels_detail {
namespace {

struct Node {
  std::size_t rep = 0;  // the voxel standing for the node (largest distance in a junction cluster)
  bool alive = true;
  bool cut = false;     // an end made by a cut
};

struct Edge {
  int a = -1, b = -1;
  std::vector<std::size_t> path;  // voxels from node a's rep to node b's rep
  bool alive = true;
};

class Graph {
 public:
  Graph(const Grid& g, const VesselOptions& o, GraphStats& s) : g_(g), o_(o), s_(s) {}

  void build(const std::vector<std::size_t>& skel);
  void prune_spurs();
  void merge_degree2();
  void break_loops();
  void cut_contacts();
  void merge_close_junctions();
  Forest forest();

 private:
  const Grid& g_;
  const VesselOptions& o_;
  GraphStats& s_;
  std::vector<Node> nodes_;
  std::vector<Edge> edges_;
  std::vector<std::vector<int>> inc_;  // alive edge ids per node (a self-loop twice)

  int add_node(std::size_t rep, bool cut = false) {
    nodes_.push_back({rep, true, cut});
    inc_.emplace_back();
    return static_cast<int>(nodes_.size()) - 1;
  }
  int add_edge(int a, int b, std::vector<std::size_t> path) {
    edges_.push_back({a, b, std::move(path), true});
    const int e = static_cast<int>(edges_.size()) - 1;
    inc_[a].push_back(e);
    inc_[b].push_back(e);
    return e;
  }
  void kill_edge(int e) {
    Edge& E = edges_[e];
    if (!E.alive) return;
    E.alive = false;
    for (int n : {E.a, E.b}) {
      auto& v = inc_[n];
      auto it = std::find(v.begin(), v.end(), e);
      if (it != v.end()) v.erase(it);
    }
  }
  int degree(int n) const { return static_cast<int>(inc_[n].size()); }
  int other(int e, int n) const { return edges_[e].a == n ? edges_[e].b : edges_[e].a; }
  double dt(std::size_t v) const { return g_.dt[v]; }
  double length(const std::vector<std::size_t>& p) const {
    double l = 0;
    for (std::size_t i = 1; i < p.size(); ++i) l += (g_.position(p[i]) - g_.position(p[i - 1])).norm();
    return l;
  }
  // path of e oriented to start at node n
  std::vector<std::size_t> from(int e, int n) const {
    std::vector<std::size_t> p = edges_[e].path;
    if (edges_[e].a != n) std::reverse(p.begin(), p.end());
    return p;
  }
  double median_dt(const std::vector<std::size_t>& p) const {
    std::vector<double> d;
    for (std::size_t v : p) d.push_back(dt(v));
    std::nth_element(d.begin(), d.begin() + d.size() / 2, d.end());
    return d[d.size() / 2];
  }
  // index of the narrowest interior voxel of a path (1 .. n-2), or -1
  int narrowest(const std::vector<std::size_t>& p) const {
    int best = -1;
    for (int i = 1; i + 1 < static_cast<int>(p.size()); ++i)
      if (best < 0 || dt(p[i]) < dt(p[best])) best = i;
    return best;
  }
  void cut_edge(int e, const std::string& kind);
  double end_radius(int e, int n) const {
    const std::vector<std::size_t> p = from(e, n);
    const std::size_t m = std::max<std::size_t>(1, std::min<std::size_t>(10, (p.size() + 3) / 4));
    return median_dt(std::vector<std::size_t>(p.begin(), p.begin() + m));
  }
};

void Graph::build(const std::vector<std::size_t>& skel) {
  std::vector<std::uint8_t> in(g_.mask.size(), 0);
  for (std::size_t v : skel) in[v] = 1;
  std::ptrdiff_t off[26];
  {
    int k = 0;
    for (int b = 0; b < 27; ++b) {
      if (b == 13) continue;
      const int dx = b % 3 - 1, dy = (b / 3) % 3 - 1, dz = b / 9 - 1;
      off[k++] = (static_cast<std::ptrdiff_t>(dz) * g_.ny + dy) * g_.nx + dx;
    }
  }
  auto neighbours = [&](std::size_t v) {
    std::vector<std::size_t> out;
    for (auto d : off)
      if (in[v + d]) out.push_back(v + d);
    return out;
  };
  std::map<std::size_t, int> node_of;
  std::map<std::size_t, int> deg;
  for (std::size_t v : skel) deg[v] = static_cast<int>(neighbours(v).size());
  // junction clusters (26-connected voxels of degree >= 3) and ends
  for (std::size_t v : skel) {
    if (node_of.count(v)) continue;
    if (deg[v] == 2) continue;
    if (deg[v] <= 1) {
      node_of[v] = add_node(v);
      continue;
    }
    std::vector<std::size_t> cluster{v}, stack{v};
    std::set<std::size_t> seen{v};
    while (!stack.empty()) {
      const std::size_t u = stack.back();
      stack.pop_back();
      for (std::size_t w : neighbours(u))
        if (deg[w] >= 3 && !seen.count(w)) seen.insert(w), cluster.push_back(w), stack.push_back(w);
    }
    std::size_t rep = cluster[0];
    for (std::size_t w : cluster)
      if (dt(w) > dt(rep) || (dt(w) == dt(rep) && w < rep)) rep = w;
    const int id = add_node(rep);
    for (std::size_t w : cluster) node_of[w] = id;
  }
  // chains between nodes
  std::set<std::size_t> visited;
  std::set<std::pair<std::size_t, std::size_t>> direct;
  auto trace = [&](int n, std::size_t v, std::size_t w) {
    std::vector<std::size_t> path{nodes_[n].rep};
    if (v != nodes_[n].rep) path.push_back(v);
    std::size_t prev = v, cur = w;
    for (;;) {
      auto it = node_of.find(cur);
      if (it != node_of.end()) {
        path.push_back(cur);
        if (cur != nodes_[it->second].rep) path.push_back(nodes_[it->second].rep);
        add_edge(n, it->second, std::move(path));
        return;
      }
      visited.insert(cur);
      path.push_back(cur);
      std::size_t next = prev;
      for (std::size_t u : neighbours(cur))
        if (u != prev) next = u;
      if (next == prev) {  // cannot happen for a degree-2 voxel; keep what was traced as an end
        const int end = add_node(cur);
        node_of[cur] = end;
        path.pop_back();
        path.push_back(cur);
        add_edge(n, end, std::move(path));
        return;
      }
      if (visited.count(next) && !node_of.count(next)) return;  // met a traced chain
      prev = cur, cur = next;
    }
  };
  auto trace_from = [&](int n) {
    std::vector<std::size_t> members;
    for (const auto& [v, id] : node_of)
      if (id == n) members.push_back(v);
    for (std::size_t v : members)
      for (std::size_t w : neighbours(v)) {
        auto it = node_of.find(w);
        if (it != node_of.end()) {
          if (it->second == n) continue;
          const auto key = std::minmax(v, w);
          if (direct.count(key)) continue;
          direct.insert(key);
          std::vector<std::size_t> path{nodes_[n].rep};
          if (v != nodes_[n].rep) path.push_back(v);
          path.push_back(w);
          if (w != nodes_[it->second].rep) path.push_back(nodes_[it->second].rep);
          add_edge(n, it->second, std::move(path));
        } else if (!visited.count(w)) {
          trace(n, v, w);
        }
      }
  };
  const int n0 = static_cast<int>(nodes_.size());
  for (int n = 0; n < n0; ++n) trace_from(n);
  // pure cycles: chains that met no node
  for (std::size_t v : skel) {
    if (deg[v] != 2 || node_of.count(v) || visited.count(v)) continue;
    const int n = add_node(v);
    node_of[v] = n;
    trace_from(n);
  }
  // junction artefacts: short self-loops and short parallel edges inside a cluster
  for (std::size_t e = 0; e < edges_.size(); ++e) {
    const Edge& E = edges_[e];
    if (E.alive && E.a == E.b && length(E.path) < 2 * dt(nodes_[E.a].rep)) kill_edge(static_cast<int>(e));
  }
}

void Graph::merge_degree2() {
  for (int n = 0; n < static_cast<int>(nodes_.size()); ++n) {
    if (!nodes_[n].alive || degree(n) != 2) continue;
    const int e1 = inc_[n][0], e2 = inc_[n][1];
    if (e1 == e2) continue;  // a lone cycle
    std::vector<std::size_t> p = from(e1, n);
    std::reverse(p.begin(), p.end());  // ends at n
    const std::vector<std::size_t> q = from(e2, n);
    p.insert(p.end(), q.begin() + 1, q.end());
    const int a = other(e1, n), b = other(e2, n);
    kill_edge(e1);
    kill_edge(e2);
    nodes_[n].alive = false;
    add_edge(a, b, std::move(p));
  }
}

void Graph::prune_spurs() {
  for (;;) {
    std::vector<std::pair<double, int>> cand;
    for (int e = 0; e < static_cast<int>(edges_.size()); ++e) {
      const Edge& E = edges_[e];
      if (!E.alive || E.a == E.b) continue;
      const int da = degree(E.a), db = degree(E.b);
      const int j = da == 1 && db >= 3 ? E.b : (db == 1 && da >= 3 ? E.a : -1);
      if (j < 0) continue;
      const double l = length(E.path);
      if (l < o_.spur_ratio * dt(nodes_[j].rep)) cand.push_back({l, e});
    }
    if (cand.empty()) break;
    std::sort(cand.begin(), cand.end());
    for (const auto& [l, e] : cand) {
      const Edge& E = edges_[e];
      if (!E.alive) continue;
      const int da = degree(E.a), db = degree(E.b);
      const int leaf = da == 1 && db >= 3 ? E.a : (db == 1 && da >= 3 ? E.b : -1);
      if (leaf < 0) continue;
      kill_edge(e);
      nodes_[leaf].alive = false;
      ++s_.spurs;
    }
    merge_degree2();
  }
}

void Graph::cut_edge(int e, const std::string& kind) {
  const Edge E = edges_[e];
  const int m = narrowest(E.path);
  kill_edge(e);
  if (m < 0) {
    const std::size_t v = E.path[E.path.size() / 2];
    s_.cuts.push_back({kind, g_.position(v), dt(v)});
    return;
  }
  s_.cuts.push_back({kind, g_.position(E.path[m]), dt(E.path[m])});
  if (m - 1 >= 1) {
    const int c = add_node(E.path[m - 1], true);
    add_edge(E.a, c, std::vector<std::size_t>(E.path.begin(), E.path.begin() + m));
  }
  if (m + 1 <= static_cast<int>(E.path.size()) - 2) {
    const int c = add_node(E.path[m + 1], true);
    add_edge(c, E.b, std::vector<std::size_t>(E.path.begin() + m + 1, E.path.end()));
  }
}

// A maximum spanning forest by edge thickness (narrowest inscribed radius):
// every edge that closes a cycle is the thinnest of it and is cut at its
// narrowest point.
void Graph::break_loops() {
  std::vector<int> parent(nodes_.size());
  std::iota(parent.begin(), parent.end(), 0);
  auto find = [&](int x) {
    while (parent[x] != x) x = parent[x] = parent[parent[x]];
    return x;
  };
  struct C {
    double thick, len;
    int e;
  };
  std::vector<C> order;
  for (int e = 0; e < static_cast<int>(edges_.size()); ++e) {
    if (!edges_[e].alive) continue;
    const auto& p = edges_[e].path;
    const int m = narrowest(p);
    order.push_back({m >= 0 ? dt(p[m]) : std::min(dt(p.front()), dt(p.back())), length(p), e});
  }
  std::sort(order.begin(), order.end(), [](const C& x, const C& y) {
    if (x.thick != y.thick) return x.thick > y.thick;
    if (x.len != y.len) return x.len > y.len;
    return x.e < y.e;
  });
  std::vector<int> closing;
  for (const C& c : order) {
    const int a = find(edges_[c.e].a), b = find(edges_[c.e].b);
    if (a == b) closing.push_back(c.e);
    else parent[a] = b;
  }
  for (int e : closing) {
    cut_edge(e, "loop");
    ++s_.loops;
  }
}

// Bridges between touching vessels: a junction-to-junction edge much
// narrower than the vessels on both sides.
void Graph::cut_contacts() {
  std::vector<int> cuts;
  for (int e = 0; e < static_cast<int>(edges_.size()); ++e) {
    const Edge& E = edges_[e];
    if (!E.alive || E.a == E.b || degree(E.a) < 3 || degree(E.b) < 3) continue;
    const int m = narrowest(E.path);
    if (m < 0) continue;
    double side[2];
    for (int k = 0; k < 2; ++k) {
      const int n = k == 0 ? E.a : E.b;
      std::vector<double> r;
      for (int f : inc_[n])
        if (f != e) r.push_back(median_dt(edges_[f].path));
      std::sort(r.begin(), r.end());
      side[k] = r[r.size() / 2];
    }
    const double thin = dt(E.path[m]);
    if (thin < o_.neck_ratio * std::min(side[0], side[1]) && length(E.path) < 4 * std::max(side[0], side[1]))
      cuts.push_back(e);
  }
  for (int e : cuts) {
    cut_edge(e, "contact");
    ++s_.contacts;
  }
}

// Two junctions joined by an edge shorter than merge_ratio x their larger
// inscribed radius are one junction (placed at the edge's middle voxel).
void Graph::merge_close_junctions() {
  for (bool again = true; again;) {
    again = false;
    for (int e = 0; e < static_cast<int>(edges_.size()); ++e) {
      const Edge E = edges_[e];
      if (!E.alive || E.a == E.b || degree(E.a) < 3 || degree(E.b) < 3) continue;
      const double ra = dt(nodes_[E.a].rep), rb = dt(nodes_[E.b].rep);
      if (!(length(E.path) < o_.merge_ratio * std::max(ra, rb))) continue;
      const std::size_t mid = E.path.size() / 2;
      std::vector<std::size_t> seg_a(E.path.rbegin() + static_cast<std::ptrdiff_t>(E.path.size() - 1 - mid),
                                     E.path.rend());  // mid .. rep_a
      std::vector<std::size_t> seg_b(E.path.begin() + static_cast<std::ptrdiff_t>(mid), E.path.end());  // mid .. rep_b
      kill_edge(e);
      const int a = E.a, b = E.b;
      // re-root every other edge of a and b at the middle voxel
      std::vector<int> touched = inc_[a];
      for (int f : inc_[b])
        if (std::find(touched.begin(), touched.end(), f) == touched.end()) touched.push_back(f);
      std::vector<std::pair<std::pair<int, int>, std::vector<std::size_t>>> redo;
      for (int f : touched) {
        Edge F = edges_[f];
        kill_edge(f);
        auto fix = [&](int n, bool at_start) {
          const std::vector<std::size_t>& seg = n == a ? seg_a : seg_b;
          if (at_start) {
            std::vector<std::size_t> p = seg;
            p.insert(p.end(), F.path.begin() + 1, F.path.end());
            F.path = p;
          } else {
            std::vector<std::size_t> p(F.path.begin(), F.path.end() - 1);
            p.insert(p.end(), seg.rbegin(), seg.rend());
            F.path = p;
          }
        };
        if (F.a == a || F.a == b) fix(F.a, true), F.a = a;
        if (F.b == a || F.b == b) fix(F.b, false), F.b = a;
        redo.push_back({{F.a, F.b}, F.path});
      }
      nodes_[a].rep = E.path[mid];
      nodes_[b].alive = false;
      for (auto& [ab, p] : redo) add_edge(ab.first, ab.second, std::move(p));
      ++s_.merged;
      again = true;
      break;
    }
  }
}

Forest Graph::forest() {
  Forest f;
  // components
  std::vector<int> comp(nodes_.size(), -1);
  std::vector<std::vector<int>> comps;
  for (int n = 0; n < static_cast<int>(nodes_.size()); ++n) {
    if (!nodes_[n].alive || comp[n] >= 0) continue;
    const int c = static_cast<int>(comps.size());
    comps.emplace_back();
    std::deque<int> q{n};
    comp[n] = c;
    while (!q.empty()) {
      const int u = q.front();
      q.pop_front();
      comps[c].push_back(u);
      for (int e : inc_[u]) {
        const int w = other(e, u);
        if (comp[w] < 0) comp[w] = c, q.push_back(w);
      }
    }
  }
  // drop specks; find the ends of the others
  std::vector<int> keep;
  std::vector<double> comp_rmax;  // of the kept ones
  for (int c = 0; c < static_cast<int>(comps.size()); ++c) {
    double len = 0, rmax = 0;
    std::set<int> es;
    for (int n : comps[c])
      for (int e : inc_[n]) es.insert(e);
    for (int e : es) {
      len += length(edges_[e].path);
      for (std::size_t v : edges_[e].path) rmax = std::max(rmax, dt(v));
    }
    if (es.empty() || len < o_.min_length_ratio * rmax) {
      ++s_.dropped;
      continue;
    }
    keep.push_back(c);
    comp_rmax.push_back(rmax);
  }
  // thin pieces beside a resolved one are noise: rmax is a voxel centre's
  // distance to the nearest background centre, the inscribed radius plus half
  // a voxel (1e-3 of a voxel spares the float distances of an exact width)
  {
    const double least = 0.5 * g_.hmin() + (o_.min_radius_voxels - 1e-3) * g_.hmin();
    if (o_.min_radius_voxels > 0 && std::any_of(comp_rmax.begin(), comp_rmax.end(), [&](double r) { return r >= least; })) {
      std::vector<int> resolved;
      for (std::size_t k = 0; k < keep.size(); ++k)
        if (comp_rmax[k] >= least) resolved.push_back(keep[k]);
        else ++s_.dropped, ++s_.thin;
      keep = std::move(resolved);
    }
  }
  // roots: each root point picks the nearest end within reach; else the widest end
  std::map<int, int> root_of;  // component -> node
  for (int i = 0; i < static_cast<int>(o_.roots_m.size()); ++i) {
    double best = 1e300;
    int bn = -1;
    for (int c : keep)
      for (int n : comps[c]) {
        if (degree(n) != 1) continue;
        const double d = (g_.position(nodes_[n].rep) - o_.roots_m[i]).norm();
        const double reach = 3 * end_radius(inc_[n][0], n) + 2 * g_.hmax();
        if (d <= reach && d < best) best = d, bn = n;
      }
    if (bn >= 0 && !root_of.count(comp[bn])) {
      root_of[comp[bn]] = bn;
      s_.roots_used.push_back(i);
    }
  }
  for (int c : keep) {
    if (root_of.count(c)) continue;
    int bn = -1;
    double br = -1;
    for (int n : comps[c]) {
      if (degree(n) != 1) continue;
      const double r = end_radius(inc_[n][0], n);
      if (r > br || (r == br && nodes_[n].rep < nodes_[bn].rep)) br = r, bn = n;
    }
    root_of[c] = bn;
  }
  // trees in the order of their root voxel
  std::vector<int> order = keep;
  std::sort(order.begin(), order.end(),
            [&](int x, int y) { return nodes_[root_of[x]].rep < nodes_[root_of[y]].rep; });
  auto open_end = [&](int n) { return !nodes_[n].cut && g_.border_distance(nodes_[n].rep) <= 2; };
  for (int c : order) {
    const int tree = f.trees++;
    const int root = root_of[c];
    std::vector<char> used(edges_.size(), 0);
    std::deque<std::pair<int, int>> q{{root, -1}};  // node, branch ending there
    while (!q.empty()) {
      const auto [n, pb] = q.front();
      q.pop_front();
      std::vector<int> out;
      for (int e : inc_[n])
        if (!used[e]) out.push_back(e);
      std::sort(out.begin(), out.end(), [&](int x, int y) {
        const double rx = median_dt(edges_[x].path), ry = median_dt(edges_[y].path);
        if (rx != ry) return rx > ry;
        return from(x, n)[1] < from(y, n)[1];
      });
      out.erase(std::unique(out.begin(), out.end()), out.end());
      if (pb >= 0 && !out.empty()) f.junctions.push_back({pb, {}});
      for (int e : out) {
        used[e] = 1;
        const int far = other(e, n);
        Branch b;
        b.tree = tree;
        b.parent = pb;
        for (std::size_t v : from(e, n)) {
          b.x.push_back(g_.position(v));
          b.rho.push_back(dt(v));
        }
        b.r = b.rho;
        b.start_root = pb < 0;
        if (b.start_root) b.start_open = open_end(n);
        b.end_leaf = degree(far) == 1;
        b.end_open = b.end_leaf && open_end(far);
        const int id = static_cast<int>(f.branches.size());
        if (pb >= 0) {
          f.branches[pb].children.push_back(id);
          f.junctions.back().children.push_back(id);
        }
        f.branches.push_back(std::move(b));
        if (!f.branches.back().end_leaf) q.push_back({far, id});
      }
    }
  }
  return f;
}

}  // namespace

Forest build_forest(const Grid& g, const std::vector<std::size_t>& skeleton, const VesselOptions& o,
                    GraphStats& stats) {
  Graph G(g, o, stats);
  G.build(skeleton);
  G.prune_spurs();
  G.merge_degree2();
  G.break_loops();
  G.prune_spurs();
  G.cut_contacts();
  G.prune_spurs();
  G.merge_close_junctions();
  G.prune_spurs();
  G.merge_degree2();
  return G.forest();
}

}  // namespace orthosim::vessels_detail
