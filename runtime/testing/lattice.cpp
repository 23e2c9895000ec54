#include "runtime/testing/lattice.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <map>

namespace orthosim::runtime::testing {

namespace {

struct SpringAcc {
  Real k1 = 0, k2 = 0, turning_strain = 0;
  std::uint8_t cls = 0;
};

}  // namespace

LayeredBlock make_layered_block(int nu, int nv, int layers) {
  LayeredBlockOptions o;
  o.nu = nu;
  o.nv = nv;
  o.layers = layers;
  if (layers != 4) {
    // repeat the default tissues downward (muscle below the defaults), bone last
    const auto base = LayeredBlockOptions{};
    o.thickness.clear(), o.youngs.clear(), o.youngs2.clear(), o.turning_strain.clear(), o.density.clear(), o.names.clear();
    for (int i = 0; i + 1 < layers; ++i) {
      const int j = std::min(i, 2);
      o.thickness.push_back(base.thickness[j]);
      o.youngs.push_back(base.youngs[j]);
      o.youngs2.push_back(base.youngs2[j]);
      o.turning_strain.push_back(base.turning_strain[j]);
      o.density.push_back(base.density[j]);
      o.names.push_back(i < 3 ? base.names[i] : "muscle" + std::to_string(i - 1));
    }
    o.names.push_back("bone");
  }
  return make_layered_block(o);
}

LayeredBlock make_layered_block(const LayeredBlockOptions& o) {
  const int nu = o.nu, nv = o.nv, ns = o.layers;
  const auto nc = static_cast<std::size_t>(ns - 1);
  if (nu < 2 || nv < 2 || ns < 2) throw Error("", "layered block needs at least 2 x 2 nodes and 2 sheets");
  if (o.thickness.size() != nc || o.youngs.size() != nc || o.youngs2.size() != nc || o.turning_strain.size() != nc ||
      o.density.size() != nc || o.names.size() != static_cast<std::size_t>(ns))
    throw Error("", "layered block options need one value per cell layer and one name per sheet");
  const std::int64_t per_sheet = static_cast<std::int64_t>(nu) * nv;
  auto id = [&](int i, int j, int s) { return static_cast<std::int32_t>(s * per_sheet + static_cast<std::int64_t>(j) * nu + i); };
  std::vector<Real> depth(static_cast<std::size_t>(ns), 0);
  for (int s = 1; s < ns; ++s) depth[s] = depth[s - 1] + o.thickness[s - 1];

  // nodes and masses
  const std::int64_t n = per_sheet * ns;
  std::vector<Real> pos(3 * static_cast<std::size_t>(n)), mass(static_cast<std::size_t>(n), 0);
  for (int s = 0; s < ns; ++s)
    for (int j = 0; j < nv; ++j)
      for (int i = 0; i < nu; ++i) {
        const auto g = static_cast<std::size_t>(id(i, j, s));
        pos[3 * g] = i * o.spacing_u;
        pos[3 * g + 1] = depth[s];
        pos[3 * g + 2] = j * o.spacing_v;
      }

  // springs accumulated per (a, b), cell by cell
  std::map<std::pair<std::int32_t, std::int32_t>, SpringAcc> acc;
  auto add = [&](std::int32_t a, std::int32_t b, Real k1, Real k2, Real eps_t, std::uint8_t cls) {
    if (a > b) std::swap(a, b);
    SpringAcc& sp = acc[{a, b}];
    sp.k1 += k1;
    sp.k2 += k2;
    if (k2 > k1) sp.turning_strain = eps_t;
    sp.cls = cls;
  };
  for (int s = 0; s + 1 < ns; ++s) {
    const Real E1 = o.youngs[s], E2 = std::max(o.youngs2[s], o.youngs[s]), et = o.turning_strain[s];
    const Real V = o.spacing_u * o.spacing_v * o.thickness[s];
    for (int j = 0; j + 1 < nv; ++j)
      for (int i = 0; i + 1 < nu; ++i) {
        std::array<std::int32_t, 8> c{};
        for (int q = 0; q < 8; ++q) c[q] = id(i + (q & 1), j + ((q >> 1) & 1), s + ((q >> 2) & 1));
        for (int q = 0; q < 8; ++q) mass[static_cast<std::size_t>(c[q])] += o.density[s] * V / 8;
        for (int p = 0; p < 8; ++p)
          for (int q = p + 1; q < 8; ++q) {
            const int diff = p ^ q;
            const int bits = (diff & 1) + ((diff >> 1) & 1) + ((diff >> 2) & 1);
            if (bits == 3) continue;  // body diagonal: not used
            const Real coef = bits == 1 ? Real(0.1) : Real(0.4);
            const auto a = static_cast<std::size_t>(c[p]), b = static_cast<std::size_t>(c[q]);
            Real l2 = 0;
            for (int k = 0; k < 3; ++k) l2 += (pos[3 * b + k] - pos[3 * a + k]) * (pos[3 * b + k] - pos[3 * a + k]);
            const bool across = (diff & 4) != 0;
            const std::uint8_t cls = across ? std::uint8_t(SpringClass::inter_layer)
                                            : (bits == 1 ? std::uint8_t(SpringClass::structural) : std::uint8_t(SpringClass::shear));
            add(c[p], c[q], coef * E1 * V / l2, coef * E2 * V / l2, et, cls);
          }
      }
  }

  // layer ownership: the sheet of the shallower end
  LayeredBlock out;
  out.options = o;
  out.n_nodes = n;
  std::vector<std::vector<std::pair<std::pair<std::int32_t, std::int32_t>, SpringAcc>>> owned(static_cast<std::size_t>(ns));
  for (const auto& e : acc) owned[static_cast<std::size_t>(e.first.first / per_sheet)].push_back(e);
  for (int s = 0; s < ns; ++s) {
    Layer l;
    l.tissue = o.names[s];
    l.kind = s + 1 == ns ? "rigid" : "lattice";
    l.order = s;
    l.node_offset = s * per_sheet;
    l.nodes.resize(per_sheet, 3);
    l.masses.resize(per_sheet);
    for (std::int64_t q = 0; q < per_sheet; ++q) {
      const auto g = static_cast<std::size_t>(s * per_sheet + q);
      for (int k = 0; k < 3; ++k) l.nodes(q, k) = pos[3 * g + k];
      l.masses[q] = mass[g];
    }
    const auto& sp = owned[static_cast<std::size_t>(s)];
    const auto m = static_cast<Eigen::Index>(sp.size());
    l.springs.resize(m, 2);
    l.rest_length.resize(m);
    l.spring_class.resize(m);
    l.k1.resize(m);
    l.k2.resize(m);
    l.turning_length.resize(m);
    l.damping.resize(m);
    std::vector<std::array<std::int32_t, 2>> lin_ends;
    std::vector<Real> lin_rest, lin_k, lin_c;
    std::vector<std::uint8_t> lin_slack;
    for (Eigen::Index q = 0; q < m; ++q) {
      const auto [a, b] = sp[q].first;
      const SpringAcc& v = sp[q].second;
      Real l2 = 0;
      for (int k = 0; k < 3; ++k) l2 += (pos[3 * b + k] - pos[3 * a + k]) * (pos[3 * b + k] - pos[3 * a + k]);
      const Real L0 = std::sqrt(l2);
      const Real mu = mass[a] * mass[b] / (mass[a] + mass[b]);
      const Real c = 2 * o.damping_ratio * std::sqrt(v.k1 * mu);
      const bool biphasic = v.k2 > v.k1 * (1 + 1e-12);
      l.springs(q, 0) = a;
      l.springs(q, 1) = b;
      l.rest_length[q] = L0;
      l.spring_class[q] = v.cls;
      l.k1[q] = v.k1;
      l.k2[q] = biphasic ? v.k2 : v.k1;
      l.turning_length[q] = biphasic ? L0 * (1 + v.turning_strain) : L0;
      l.damping[q] = c;
      lin_ends.push_back({a, b});
      lin_rest.push_back(L0);
      lin_k.push_back(v.k1);
      lin_c.push_back(c);
      lin_slack.push_back(0);
      if (biphasic) {
        lin_ends.push_back({a, b});
        lin_rest.push_back(L0 * (1 + v.turning_strain));
        lin_k.push_back(v.k2 - v.k1);
        lin_c.push_back(0);
        lin_slack.push_back(1);
      }
    }
    const auto nl = static_cast<Eigen::Index>(lin_ends.size());
    l.lin_springs.resize(nl, 2);
    l.lin_rest_length.resize(nl);
    l.lin_k.resize(nl);
    l.lin_damping.resize(nl);
    l.lin_slack.resize(nl);
    for (Eigen::Index q = 0; q < nl; ++q) {
      l.lin_springs(q, 0) = lin_ends[q][0];
      l.lin_springs(q, 1) = lin_ends[q][1];
      l.lin_rest_length[q] = lin_rest[q];
      l.lin_k[q] = lin_k[q];
      l.lin_damping[q] = lin_c[q];
      l.lin_slack[q] = lin_slack[q];
    }
    // the volume term's tetrahedra: the Kuhn triangulation of each cell, a
    // path from corner 000 to 111 along the axes in each of the 6 orders
    const auto per_layer = [&](const std::vector<Real>& v) { return static_cast<std::size_t>(s) < v.size() ? v[static_cast<std::size_t>(s)] : 0; };
    if ((per_layer(o.volume_modulus) > 0 || per_layer(o.guard_modulus) > 0) && s + 1 < ns) {
      if (per_layer(o.volume_modulus) > 0) {
        l.volume_modulus = per_layer(o.volume_modulus);
        if (o.volume_group != 1 && o.volume_group != 6) throw Error("", "layered block: volume_group must be 1 or 6");
        l.volume_group = o.volume_group;
      }
      if (per_layer(o.guard_modulus) > 0) {
        l.guard_modulus = per_layer(o.guard_modulus);
        l.guard_ratio = o.guard_ratio;
      }
      static constexpr int kOrders[6][3] = {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}};
      l.tets.resize(static_cast<Eigen::Index>(nu - 1) * (nv - 1) * 6, 4);
      Eigen::Index t = 0;
      for (int j = 0; j + 1 < nv; ++j)
        for (int i = 0; i + 1 < nu; ++i)
          for (const auto& ord : kOrders) {
            int d[3] = {0, 0, 0};  // offsets along i, j, s
            l.tets(t, 0) = id(i, j, s);
            for (int k = 0; k < 3; ++k) {
              d[ord[k]] = 1;
              l.tets(t, k + 1) = id(i + d[0], j + d[1], s + d[2]);
            }
            // positive orientation, as build writes them
            Real e[3][3];
            for (int k = 0; k < 3; ++k)
              for (int c = 0; c < 3; ++c)
                e[k][c] = pos[3 * static_cast<std::size_t>(l.tets(t, k + 1)) + c] - pos[3 * static_cast<std::size_t>(l.tets(t, 0)) + c];
            const Real det = e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1]) -
                             e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0]) +
                             e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0]);
            if (det < 0) std::swap(l.tets(t, 2), l.tets(t, 3));
            ++t;
          }
    }
    // top surface of the sheet, counter-clockwise seen from -y (outside)
    l.quads.resize(static_cast<Eigen::Index>(nu - 1) * (nv - 1), 4);
    Eigen::Index qi = 0;
    for (int j = 0; j + 1 < nv; ++j)
      for (int i = 0; i + 1 < nu; ++i, ++qi) {
        l.quads(qi, 0) = id(i, j, s);
        l.quads(qi, 1) = id(i + 1, j, s);
        l.quads(qi, 2) = id(i + 1, j + 1, s);
        l.quads(qi, 3) = id(i, j + 1, s);
      }
    VecXi set(per_sheet);
    for (std::int64_t q = 0; q < per_sheet; ++q) set[q] = static_cast<std::int32_t>(s * per_sheet + q);
    out.sets["layer_" + o.names[s]] = set;
    if (s == 0) out.sets["skin"] = set;
    if (s + 1 == ns) out.sets["fixed"] = set;
    out.layers.emplace_back(o.names[s], std::move(l));
  }
  return out;
}

void write_model_file(const std::string& path, const LayeredBlock& b, bool extras) {
  ModelWriter w(path, ModelWriter::Start::fresh);
  for (const auto& [name, l] : b.layers) w.write_layer(name, l);
  for (const auto& [name, ids] : b.sets) w.write_node_set(name, ids);
  if (extras) {
    Volume v;
    v.nx = v.ny = v.nz = 4;
    v.labels.assign(64, 1);
    v.label_names = {"background", "skin"};
    w.write(v);
    Surface s;
    s.vertices.resize(3, 3);
    s.vertices << 0, 0, 0, 1e-2, 0, 0, 0, 1e-2, 0;
    s.faces.resize(1, 3);
    s.faces << 0, 1, 2;
    w.write("skin", s);
    QuadSurface q;
    q.nu = 2, q.nv = 2;
    q.vertices.resize(4, 3);
    q.vertices << 0, 0, 0, 1e-2, 0, 0, 0, 0, 1e-2, 1e-2, 0, 1e-2;
    q.quads.resize(1, 4);
    q.quads << 0, 1, 3, 2;
    q.uv.resize(4, 2);
    q.uv << 0, 0, 1, 0, 0, 1, 1, 1;
    w.write("skin", q);
    VesselTree t;
    t.nodes.resize(3, 3);
    t.nodes << 0.01, 0.005, 0, 0.01, 0.005, 0.01, 0.01, 0.005, 0.02;
    t.radii.resize(3);
    t.radii << 1e-3, 1e-3, 0.8e-3;
    t.edges.resize(2, 2);
    t.edges << 0, 1, 1, 2;
    t.branch_parent.resize(1);
    t.branch_parent << -1;
    t.branch_offsets.resize(2);
    t.branch_offsets << 0, 3;
    t.branch_nodes.resize(3);
    t.branch_nodes << 0, 1, 2;
    // a square tube of side 2 mm around the centreline, closed by two triangles at each end
    t.tube_vertices.resize(12, 3);
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) {
        const double a = 0.5 * 3.14159265358979 * c;
        t.tube_vertices.row(4 * r + c) << 0.01 + 1e-3 * std::cos(a), 0.005 + 1e-3 * std::sin(a), 0.01 * r;
      }
    t.tube_quads.resize(8, 4);
    for (int r = 0; r < 2; ++r)
      for (int c = 0; c < 4; ++c) t.tube_quads.row(4 * r + c) << 4 * r + c, 4 * r + (c + 1) % 4, 4 * (r + 1) + (c + 1) % 4, 4 * (r + 1) + c;
    t.tube_tris.resize(4, 3);
    t.tube_tris << 0, 2, 1, 0, 3, 2, 8, 9, 10, 8, 10, 11;
    w.write("artery", t);
    Tuning tu;
    tu.method = "none";
    tu.target.resize(1);
    tu.target << 1;
    tu.achieved = tu.target;
    tu.weights = tu.target;
    w.write("dermis", tu);
  }
  w.commit();
}

Vec3 fixed_reaction(const Model& m, std::span<const Real> x, std::span<const Real> inv_mass) {
  Vec3 r;
  for (std::int32_t k = 0; k < m.n_springs; ++k) {
    const std::int32_t a = m.spring_a[static_cast<std::size_t>(k)], b = m.spring_b[static_cast<std::size_t>(k)];
    const bool fa = inv_mass[static_cast<std::size_t>(a)] == 0, fb = inv_mass[static_cast<std::size_t>(b)] == 0;
    if (fa == fb) continue;
    const Vec3 d = load3(x.data(), b) - load3(x.data(), a);
    const Real l = norm(d), stretch = l - m.spring_rest[static_cast<std::size_t>(k)];
    if ((m.spring_tension[static_cast<std::size_t>(k)] && stretch < 0) || !(l > 0)) continue;
    const Vec3 on_a = (m.spring_k[static_cast<std::size_t>(k)] * stretch / l) * d;
    r += fa ? on_a : -on_a;
  }
  return r;
}

}  // namespace orthosim::runtime::testing
