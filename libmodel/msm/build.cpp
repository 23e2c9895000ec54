#include "libmodel/msm/build.h"

#include "libmodel/msm/biphasic.h"
#include "libmodel/msm/lattice.h"
#include "libmodel/msm/tetra.h"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <memory>
#include <numeric>
#include <sstream>

namespace orthosim::msm {

namespace {

using Vec3 = Eigen::Vector3d;
using Clock = std::chrono::steady_clock;

std::string fmt(double v) {
  std::ostringstream s;
  s.precision(4);
  s << v;
  return s.str();
}

std::string vertex_name(int v, int nu) {
  return "grid vertex (" + std::to_string(v % nu) + ", " + std::to_string(v / nu) + ")";
}

// area-weighted outward vertex normals of a quad grid (unit; zero if isolated)
MatX3d vertex_normals(const MatX3d& x, const MatX4i& quads) {
  MatX3d n = MatX3d::Zero(x.rows(), 3);
  for (Eigen::Index q = 0; q < quads.rows(); ++q) {
    const Vec3 d1 = (x.row(quads(q, 2)) - x.row(quads(q, 0))).transpose();
    const Vec3 d2 = (x.row(quads(q, 3)) - x.row(quads(q, 1))).transpose();
    const Vec3 a = 0.5 * d1.cross(d2);  // vector area of the quad
    for (int k = 0; k < 4; ++k) n.row(quads(q, k)) += a.transpose();
  }
  for (Eigen::Index v = 0; v < n.rows(); ++v) {
    const double l = n.row(v).norm();
    if (l > 0) n.row(v) /= l;
  }
  return n;
}

struct UnionFind {
  std::vector<std::int32_t> p;
  explicit UnionFind(std::size_t n) : p(n) { std::iota(p.begin(), p.end(), 0); }
  std::int32_t find(std::int32_t a) {
    while (p[static_cast<std::size_t>(a)] != a) {
      p[static_cast<std::size_t>(a)] = p[static_cast<std::size_t>(p[static_cast<std::size_t>(a)])];
      a = p[static_cast<std::size_t>(a)];
    }
    return a;
  }
  void unite(std::int32_t a, std::int32_t b) {
    a = find(a), b = find(b);
    if (a != b) p[static_cast<std::size_t>(std::max(a, b))] = std::min(a, b);
  }
};

const char* class_name(std::uint8_t c) {
  switch (static_cast<SpringClass>(c)) {
    case SpringClass::structural: return "structural";
    case SpringClass::shear: return "shear";
    case SpringClass::inter_layer: return "inter_layer";
    case SpringClass::body: return "body";
  }
  return "unknown";
}

SpringLaw law_of(const Tissue& t) {
  SpringLaw l;
  if (t.mechanics.model == Mechanics::Model::biphasic) {
    l.k1_pa = t.mechanics.k1_pa;
    l.k2_pa = t.mechanics.k2_pa;
    l.turning_strain = t.mechanics.turning_strain;
  } else {
    l.k1_pa = l.k2_pa = t.mechanics.k_pa;
    l.turning_strain = 0;
  }
  return l;
}

void validate_options(const BuildOptions& o) {
  if (o.through_cells < 1 || o.through_cells > 64) throw Error("", "through_cells must be in 1..64");
  if (!(o.lattice_min_weight >= 0 && o.lattice_min_weight < 1)) throw Error("", "lattice_min_weight must be in [0, 1)");
  if (!(o.damping_ratio >= 0 && o.damping_ratio <= 10)) throw Error("", "damping_ratio must be in [0, 10]");
  if (!(o.min_thickness_m >= 0 && std::isfinite(o.min_thickness_m))) throw Error("", "min_thickness_m must be >= 0 and finite");
  if (!(o.max_spring_ratio > 1)) throw Error("", "max_spring_ratio must be > 1");
  if (!(o.mass_tolerance > 0 && o.mass_tolerance < 1)) throw Error("", "mass_tolerance must be in (0, 1)");
  if (!(o.projection.min_barycentric >= 0 && o.projection.min_barycentric < 1.0 / 3))
    throw Error("", "min_barycentric must be in [0, 1/3)");
  if (!(o.projection.max_distance_factor > 0)) throw Error("", "max_distance_factor must be > 0");
  if (!(o.poisson_ratio >= 0.25 && o.poisson_ratio < 0.5)) throw Error("", "poisson_ratio must be in [0.25, 0.5)");
  if (!(o.inversion_guard >= 0 && o.inversion_guard < 1)) throw Error("", "inversion_guard must be in [0, 1) (0: none)");
  if (o.tetra_volume_term != "tets" && o.tetra_volume_term != "prisms")
    throw Error("", "tetra_volume_term must be tets or prisms, not '" + o.tetra_volume_term + "'");
  if (o.tetra_volume_term == "prisms" && !(volume_ratio(o.poisson_ratio) > 0))
    throw Error("", "tetra_volume_term prisms needs a volume term: a Poisson's ratio above 0.25");
}

}  // namespace

void check_build_options(const BuildOptions& o) { validate_options(o); }

std::vector<LayerSpec> parse_layer_specs(const std::string& text) {
  std::vector<LayerSpec> out;
  std::stringstream s(text);
  std::string item;
  while (std::getline(s, item, ',')) {
    const auto colon = item.find(':');
    if (item.empty() || colon == std::string::npos || colon == 0 || colon + 1 == item.size())
      throw Error("", "--layers: expected items like skin:tetra, got '" + item + "'");
    LayerSpec l{item.substr(0, colon), item.substr(colon + 1)};
    if (l.kind != "tetra" && l.kind != "lattice")
      throw Error("", "--layers: kind of '" + l.tissue + "' must be tetra or lattice, not '" + l.kind + "'");
    out.push_back(l);
  }
  if (out.empty()) throw Error("", "--layers: no layers given");
  return out;
}

Stack resolve_stack(const std::vector<LayerSpec>& requested, const std::vector<std::string>& present,
                    const TissueTable& tissues) {
  for (const auto& p : present)
    if (!tissues.find(p)) throw Error("", "tissue '" + p + "' (from /quads) is missing from the tissue table " + tissues.path);
  for (const auto& l : requested)
    if (!tissues.find(l.tissue)) throw Error("", "tissue '" + l.tissue + "' is missing from the tissue table " + tissues.path);
  auto depth = [&](const std::string& n) { return tissues.depth(*tissues.find(n)); };
  std::vector<std::string> sorted = present;
  std::stable_sort(sorted.begin(), sorted.end(), [&](const std::string& a, const std::string& b) {
    return depth(a) < depth(b);
  });
  Stack st;
  if (requested.empty()) {
    for (const auto& n : sorted) {
      const Tissue& t = *tissues.find(n);
      if (t.layer == "rigid") {
        st.surfaces.push_back(n);
        break;
      }
      if (t.layer != "tetra" && t.layer != "lattice") continue;
      st.layers.push_back({n, t.layer});
      st.surfaces.push_back(n);
    }
    if (!st.layers.empty() && st.surfaces.size() == st.layers.size()) {
      // no rigid tissue: the innermost layer's surface becomes the fixed bottom
      st.layered_bottom = st.layers.back().tissue;
      st.layers.pop_back();
    }
    if (st.layers.empty())
      throw Error("", "no tetra or lattice layer with a surface below it among /quads (" + std::to_string(present.size()) +
                          " surfaces)");
    return st;
  }
  for (std::size_t i = 0; i < requested.size(); ++i) {
    const auto& l = requested[i];
    if (std::find(present.begin(), present.end(), l.tissue) == present.end())
      throw Error("", "layer '" + l.tissue + "' has no quad surface /quads/" + l.tissue);
    for (std::size_t j = 0; j < i; ++j)
      if (requested[j].tissue == l.tissue) throw Error("", "layer '" + l.tissue + "' is listed twice");
    if (i > 0 && depth(l.tissue) <= depth(requested[i - 1].tissue))
      throw Error("", "layers out of order: '" + l.tissue + "' is listed after '" + requested[i - 1].tissue +
                          "' but is not inside it (tissue table nesting)");
    st.layers.push_back(l);
    st.surfaces.push_back(l.tissue);
  }
  const int d_last = depth(requested.back().tissue);
  for (const auto& n : sorted)
    if (depth(n) > d_last) {
      st.surfaces.push_back(n);
      return st;
    }
  throw Error("", "no quad surface below layer '" + requested.back().tissue + "' to rest it on");
}

BuiltModel build_layers(const std::vector<std::pair<std::string, QuadSurface>>& surfaces,
                        const std::vector<LayerSpec>& specs, const TissueTable& tissues, const BuildOptions& o) {
  auto t_phase = Clock::now();
  BuiltModel out;
  auto phase = [&](const std::string& name) {
    const auto now = Clock::now();
    out.report.phases_s[name] += std::chrono::duration<double>(now - t_phase).count();
    t_phase = now;
  };
  validate_options(o);
  const std::size_t nl = specs.size();
  if (nl == 0) throw Error("", "no layers to build");
  if (surfaces.size() != nl + 1)
    throw Error("", "need one surface more than layers (" + std::to_string(nl) + " layers, " +
                        std::to_string(surfaces.size()) + " surfaces)");

  // ---- tissues ----
  std::vector<const Tissue*> tis;
  for (std::size_t s = 0; s < surfaces.size(); ++s) {
    const auto& name = surfaces[s].first;
    for (std::size_t r = 0; r < s; ++r)
      if (surfaces[r].first == name) throw Error("", "surface '" + name + "' is used twice");
    const Tissue* t = tissues.find(name);
    if (!t) throw Error("", "tissue '" + name + "' is missing from the tissue table " + tissues.path);
    tis.push_back(t);
    if (s < nl) {
      if (specs[s].tissue != name) throw Error("", "layer " + std::to_string(s) + " does not start on its surface");
      if (specs[s].kind != "tetra" && specs[s].kind != "lattice")
        throw Error("", "layer '" + name + "': kind must be tetra or lattice, not '" + specs[s].kind + "'");
      if (t->mechanics.model == Mechanics::Model::none)
        throw Error("", "tissue '" + name + "' has no mechanics in the tissue table: it cannot be a " + specs[s].kind +
                            " layer");
    }
  }

  // ---- grids ----
  const QuadSurface& g0 = surfaces[0].second;
  const int nu = g0.nu, nv = g0.nv, ng = nu * nv;
  for (const auto& [name, g] : surfaces) {
    if (g.nu < 2 || g.nv < 2 || g.quads.rows() == 0)
      throw Error("", "quad surface '" + name + "' is empty or has a grid below 2 x 2");
    if (g.vertices.rows() != static_cast<Eigen::Index>(g.nu) * g.nv)
      throw Error("", "quad surface '" + name + "': nu*nv does not match its vertex count");
    if (!g.vertices.allFinite()) throw Error("", "quad surface '" + name + "' has non-finite vertices");
    if (g.nu != nu || g.nv != nv || g.quads.rows() != g0.quads.rows() || g.quads != g0.quads)
      throw Error("", "grids do not match between layers: '" + name + "' is " + std::to_string(g.nu) + "x" +
                          std::to_string(g.nv) + " with " + std::to_string(g.quads.rows()) + " quads, '" +
                          surfaces[0].first + "' is " + std::to_string(nu) + "x" + std::to_string(nv) + " with " +
                          std::to_string(g0.quads.rows()) + " quads" +
                          (g.nu == nu && g.nv == nv ? " (different quad connectivity)" : ""));
    if (g.quads.minCoeff() < 0 || g.quads.maxCoeff() >= ng)
      throw Error("", "quad surface '" + name + "' has a vertex id out of range");
    // no degenerate quads; outward orientation
    const Vec3 C = g.vertices.colwise().mean().transpose();
    double flux = 0;
    for (Eigen::Index q = 0; q < g.quads.rows(); ++q) {
      const Vec3 d1 = (g.vertices.row(g.quads(q, 2)) - g.vertices.row(g.quads(q, 0))).transpose();
      const Vec3 d2 = (g.vertices.row(g.quads(q, 3)) - g.vertices.row(g.quads(q, 1))).transpose();
      const Vec3 a = 0.5 * d1.cross(d2);
      if (!(a.norm() > 0)) throw Error("", "quad surface '" + name + "' has a degenerate quad " + std::to_string(q));
      Vec3 m = Vec3::Zero();
      for (int k = 0; k < 4; ++k) m += 0.25 * g.vertices.row(g.quads(q, k)).transpose();
      flux += (m - C).dot(a);
    }
    if (!(flux > 0))
      throw Error("", "quad surface '" + name + "' faces inward (quads must be counter-clockwise seen from outside)");
  }
  const MatX4i& quads = g0.quads;

  // ---- order, thickness, intersections ----
  std::vector<std::pair<double, double>> thickness(nl);  // min, mean
  for (std::size_t l = 0; l < nl; ++l) {
    const MatX3d& top = surfaces[l].second.vertices;
    const MatX3d& bot = surfaces[l + 1].second.vertices;
    const MatX3d n = vertex_normals(top, quads);
    double mn = std::numeric_limits<double>::infinity(), sum = 0;
    int at = 0;
    for (int v = 0; v < ng; ++v) {
      const double d = (top.row(v) - bot.row(v)).dot(n.row(v));
      sum += d;
      if (d < mn) mn = d, at = v;
    }
    thickness[l] = {mn, sum / ng};
    if (!(mn > 0))
      throw Error("", "layers out of order or intersecting: surface '" + surfaces[l + 1].first + "' is not inside '" +
                          surfaces[l].first + "' at " + vertex_name(at, nu) + " (depth " + fmt(mn) + " m)");
    if (mn < o.min_thickness_m)
      throw Error("", "layer '" + surfaces[l].first + "' is thinner than " + fmt(o.min_thickness_m) + " m: " + fmt(mn) +
                          " m at " + vertex_name(at, nu));
  }
  phase("validate");
  // one AABB tree per surface below a layer, shared by the intersection test
  // and the centroid rays
  // (tetra layers split the quads as their cells do: alternating diagonals
  // with the axis correction)
  const std::vector<std::uint8_t> split = o.axis_correction ? alternating_split(quads) : std::vector<std::uint8_t>{};
  auto split_of = [&](std::size_t l) {
    return specs[l].kind == "tetra" ? split : std::vector<std::uint8_t>{};
  };
  std::vector<std::unique_ptr<RayCaster>> casters(nl);
  auto caster = [&](std::size_t l) -> const RayCaster& {
    if (!casters[l]) casters[l] = std::make_unique<RayCaster>(triangulate(surfaces[l + 1].second.vertices, quads, split_of(l)));
    return *casters[l];
  };
  if (o.check_intersections) {
    for (std::size_t l = 0; l < nl; ++l) {
      const Surface upper = triangulate(surfaces[l].second.vertices, quads, split_of(l));
      const std::int64_t k = caster(l).count_intersecting(upper, 1);
      out.report.surface_intersections += k;
      if (k > 0)
        throw Error("", "layers intersect: surfaces '" + surfaces[l].first + "' and '" + surfaces[l + 1].first +
                            "' cross each other");
    }
    phase("intersections");
  }

  // ---- cells ----
  std::vector<LayerCells> cells(nl);
  std::vector<NodeBlocks> blocks(nl + 1);
  std::int32_t offset = 0;
  for (std::size_t l = 0; l < nl; ++l) {
    NodeBlocks& b = blocks[l];
    b.top = offset;
    b.created = offset + ng;
    const std::int64_t n_created = specs[l].kind == "tetra" ? 2 * quads.rows() : static_cast<std::int64_t>(ng) * (o.through_cells - 1);
    const std::int64_t next = static_cast<std::int64_t>(b.created) + n_created;
    if (next + ng > std::numeric_limits<std::int32_t>::max()) throw Error("", "too many nodes for 32-bit ids");
    b.bottom = static_cast<std::int32_t>(next);
    offset = b.bottom;
  }
  blocks[nl].top = offset;
  blocks[nl].created = offset + ng;
  blocks[nl].bottom = offset + ng;
  const std::int32_t n_nodes = offset + ng;
  const bool grid_prisms = o.tetra_volume_term == "prisms";
  // a tetra layer's term modulus over K1 (per group: half the tissue's over the grid prisms)
  const double tetra_ratio = volume_ratio(o.poisson_ratio) * (grid_prisms ? kGridPrismShare : 1.0);
  std::vector<std::array<double, 3>> tetra_shape(nl, {0, 0, 0});
  std::vector<AxisCalibration> tetra_axes(nl);
  for (std::size_t l = 0; l < nl; ++l) {
    const MatX3d& top = surfaces[l].second.vertices;
    const MatX3d& bot = surfaces[l + 1].second.vertices;
    if (specs[l].kind == "tetra") {
      TetraOptions to;
      to.projection = o.projection;
      to.inverted_ratio = o.inverted_ratio;
      tetra_shape[l] = mean_cell_shape(top, bot, quads);
      if (o.axis_correction) {
        if (!(tetra_shape[l][0] > 0 && tetra_shape[l][1] > 0 && tetra_shape[l][2] > 0))
          throw Error("", "layer '" + surfaces[l].first + "' has degenerate cells");
        tetra_axes[l] = tetra_layer_axes(tetra_shape[l], tetra_ratio, 0, grid_prisms);
        to.axis_factors = tetra_axes[l].factors;
        to.alternate_diagonals = true;
      }
      cells[l] = tetra_cells(top, bot, quads, blocks[l], to, &caster(l));
    } else {
      LatticeOptions lo;
      lo.through_cells = o.through_cells;
      lo.body_diagonals = o.body_diagonals;
      lo.min_weight = o.lattice_min_weight;
      lo.inverted_ratio = o.inverted_ratio;
      lo.axis_correction = o.axis_correction;
      lo.volume_ratio = o.lattice_volume_term ? volume_ratio(o.poisson_ratio) : 0.0;
      lo.tets = o.inversion_guard > 0;
      cells[l] = lattice_cells(top, bot, quads, blocks[l], lo);
    }
    casters[l].reset();
    if (cells[l].inverted > 0) {
      // The surfaces are in order and apart (thickness > 0 at every vertex,
      // checked above; not crossing, unless --no-intersection-check), so the
      // cause is the cells' shape. Its measure at the first inverted quad: the
      // depth of its column (the offset of the bottom quad's centroid from the
      // top one's along the top quad's normal) against the narrowest edge of
      // the top and bottom quads. A tetrahedral layer over a deep column of
      // narrow, twisted quads inverts whatever the grid: the demo's muscle
      // (12.6 mm deep, 2.9 mm wide at the top, 1.0 mm at the bone) fails at
      // 39x9 and at 15x5 alike, and builds as a lattice.
      const std::int64_t fq = cells[l].first_inverted_quad;
      Eigen::Vector3d ct = Eigen::Vector3d::Zero(), cb = Eigen::Vector3d::Zero();
      double wt = HUGE_VAL, wb = HUGE_VAL;
      for (int k = 0; k < 4; ++k) {
        ct += top.row(quads(fq, k)).transpose() / 4;
        cb += bot.row(quads(fq, k)).transpose() / 4;
        wt = std::min(wt, (top.row(quads(fq, (k + 1) % 4)) - top.row(quads(fq, k))).norm());
        wb = std::min(wb, (bot.row(quads(fq, (k + 1) % 4)) - bot.row(quads(fq, k))).norm());
      }
      Eigen::Vector3d n = (top.row(quads(fq, 2)) - top.row(quads(fq, 0))).transpose().cross(
          (top.row(quads(fq, 3)) - top.row(quads(fq, 1))).transpose());
      n /= std::max(n.norm(), 1e-300);
      const double depth = std::abs((cb - ct).dot(n));
      const std::string where = "(i, j) = (" + std::to_string(fq % nu) + ", " + std::to_string(fq / nu) + ")";
      const std::string shape = "its column is " + fmt(depth * 1e3) + " mm deep under quads whose narrowest edge is " +
                                fmt(wt * 1e3) + " mm at the top and " + fmt(wb * 1e3) + " mm at the bottom";
      const std::string cause =
          specs[l].kind == "tetra"
              ? "the prisms are too deep and distorted for the 7-tetrahedron split (the paper's tetrahedral layer is a thin "
                "outer one); build it as a lattice layer (build --layers " + specs[l].tissue +
                    ":lattice, or its \"layer\": \"lattice\" in the tissue table for the pipeline)"
              : "the hexahedra are too distorted (twisted or flattened between the two surfaces)";
      throw Error("", "inverted cells in layer '" + specs[l].tissue + "': " + std::to_string(cells[l].inverted) + " of " +
                          (specs[l].kind == "tetra"
                               ? std::to_string(cells[l].sub_tets) + " tetrahedra have volume <= 0 (smallest " +
                                     fmt(cells[l].min_tet_volume_m3) + " m^3)"
                               : std::to_string(cells[l].cells) + " hexahedra have a Jacobian <= 0 (smallest " +
                                     fmt(cells[l].min_jacobian_m3) + " m^3)") +
                          ", the first under quad " + where + ": " + shape + "; " + cause +
                          (o.check_intersections ? "" : " (or the surfaces cross: --no-intersection-check skipped that test)"));
    }
  }
  phase("cells");

  // ---- global positions and masses ----
  MatX3d X(n_nodes, 3);
  for (std::size_t l = 0; l < nl; ++l) {
    X.middleRows(blocks[l].top, ng) = surfaces[l].second.vertices;
    if (cells[l].created.rows()) X.middleRows(blocks[l].created, cells[l].created.rows()) = cells[l].created;
  }
  X.middleRows(blocks[nl].top, ng) = surfaces[nl].second.vertices;
  VecXd mass = VecXd::Zero(n_nodes);
  std::vector<double> layer_mass(nl, 0);
  for (std::size_t l = 0; l < nl; ++l) {
    const double rho = tis[l]->density_kg_m3;
    const auto& nvol = cells[l].node_volume;
    for (std::size_t i = 0; i < nvol.size(); ++i) mass(static_cast<Eigen::Index>(i)) += rho * nvol[i];
    layer_mass[l] = rho * cells[l].volume_m3;
  }

  // ---- springs per layer ----
  out.layers.resize(nl + 1);
  out.names.resize(nl + 1);
  std::vector<MergedSprings> merged(nl);
  std::vector<std::int64_t> zero_k(nl, 0);
  for (std::size_t l = 0; l < nl; ++l) {
    merged[l] = merge_terms(std::move(cells[l].terms), X);
    zero_k[l] = drop_zero_stiffness(merged[l]);
    const MergedSprings& m = merged[l];
    const SpringLaw law = law_of(*tis[l]);
    Layer& L = out.layers[l];
    out.names[l] = specs[l].tissue;
    L.tissue = specs[l].tissue;
    L.kind = specs[l].kind;
    L.order = static_cast<int>(l);
    L.node_offset = blocks[l].top;
    const std::int32_t owned = blocks[l].bottom - blocks[l].top;
    L.nodes = X.middleRows(blocks[l].top, owned);
    L.masses = mass.segment(blocks[l].top, owned);
    L.springs = m.pairs;
    L.rest_length = m.rest_length;
    L.spring_class = m.spring_class;
    L.k1 = law.k1_pa * m.k_per_pa;
    L.k2 = law.k2_pa * m.k_per_pa;
    L.turning_length = m.rest_length * (1 + law.turning_strain);
    for (int c = 0; c < 4; ++c) L.spring_law.insert(L.spring_law.end(), {law.k1_pa, law.turning_strain, law.k2_pa});
    // the volume term: per tetrahedron of a tetra layer, per hexahedron (its
    // 6 tetrahedra) of a lattice layer with lattice_volume_term
    if (!cells[l].tets.empty() && volume_ratio(o.poisson_ratio) > 0 &&
        (specs[l].kind == "tetra" || o.lattice_volume_term)) {
      L.volume_modulus = volume_ratio(o.poisson_ratio) * law.k1_pa;
      L.volume_group = specs[l].kind == "lattice" ? 6 : 1;
      // (or per grid prism and its cap: their own tetrahedra, split as
      // tetra_cells split the quads, two groups a prism at half the modulus)
      if (specs[l].kind == "tetra" && grid_prisms) {
        L.volume_modulus = tetra_ratio * law.k1_pa;
        const auto split = o.axis_correction ? alternating_split(quads) : std::vector<std::uint8_t>{};
        const auto pt = grid_prism_tets(quads, split, blocks[l].top, blocks[l].bottom, blocks[l].created);
        L.volume_tets.resize(static_cast<Eigen::Index>(pt.size()), 4);
        for (std::size_t t = 0; t < pt.size(); ++t)
          for (int k = 0; k < 4; ++k) L.volume_tets(static_cast<Eigen::Index>(t), k) = pt[t][static_cast<std::size_t>(k)];
        L.volume_group = kGridPrismTets;
      }
    }
    // the inversion guard on every tetrahedron, but not where each has a
    // two-sided term of its own (a tetra layer at nu > 1/4: that term already
    // resists from the rest volume down)
    const bool own_term = L.volume_modulus > 0 && L.volume_group == 1 && L.volume_tets.rows() == 0;
    if (!cells[l].tets.empty() && o.inversion_guard > 0 && !own_term) {
      L.guard_modulus = bulk_ratio(o.poisson_ratio) * law.k1_pa;
      L.guard_ratio = o.inversion_guard;
    }
    L.damping.resize(m.pairs.rows());
    for (Eigen::Index s = 0; s < m.pairs.rows(); ++s) {
      const double ma = mass(m.pairs(s, 0)), mb = mass(m.pairs(s, 1));
      const double mr = ma + mb > 0 ? ma * mb / (ma + mb) : 0;
      L.damping(s) = 2 * o.damping_ratio * std::sqrt(std::max(0.0, L.k1(s) * mr));
    }
    decompose_biphasic(L);
    L.tets.resize(static_cast<Eigen::Index>(cells[l].tets.size()), 4);
    for (std::size_t t = 0; t < cells[l].tets.size(); ++t)
      for (int k = 0; k < 4; ++k) L.tets(static_cast<Eigen::Index>(t), k) = cells[l].tets[t][static_cast<std::size_t>(k)];
    L.quads = quads.array() + blocks[l].top;
  }
  {
    // the rigid bottom: its grid, fixed
    Layer& B = out.layers[nl];
    out.names[nl] = surfaces[nl].first;
    B.tissue = surfaces[nl].first;
    B.kind = "rigid";
    B.order = static_cast<int>(nl);
    B.node_offset = blocks[nl].top;
    B.nodes = X.middleRows(blocks[nl].top, ng);
    B.masses = mass.segment(blocks[nl].top, ng);
    B.quads = quads.array() + blocks[nl].top;
  }
  phase("springs");

  // ---- quality checks ----
  BuildReport& R = out.report;
  R.nodes = n_nodes;
  double lmin = std::numeric_limits<double>::infinity(), lmax = 0;
  UnionFind uf(static_cast<std::size_t>(n_nodes));
  double median_scale = 0;
  {
    // a length scale for "zero length": the mean grid edge of the outer surface
    const GridEdges e = grid_edges(quads);
    for (Eigen::Index i = 0; i < e.edges.rows(); ++i)
      median_scale += (g0.vertices.row(e.edges(i, 1)) - g0.vertices.row(e.edges(i, 0))).norm();
    median_scale /= std::max<Eigen::Index>(1, e.edges.rows());
  }
  for (std::size_t l = 0; l < nl; ++l) {
    const Layer& L = out.layers[l];
    for (Eigen::Index s = 0; s < L.springs.rows(); ++s) {
      const double len = L.rest_length(s);
      if (!(len > 1e-9 * median_scale)) ++R.zero_length_springs;
      lmin = std::min(lmin, len);
      lmax = std::max(lmax, len);
      uf.unite(L.springs(s, 0), L.springs(s, 1));
      // rows come sorted by (a, b): a repeat is a duplicate within the layer
      if (s > 0 && L.springs(s, 0) == L.springs(s - 1, 0) && L.springs(s, 1) == L.springs(s - 1, 1))
        ++R.duplicate_springs;
    }
  }
  // A layer's nodes are its own and the next layer's top grid, so only
  // consecutive layers can share a pair, and only on that grid: two tissues'
  // springs in parallel on their shared surface, counted, not duplicates.
  std::vector<std::int64_t> interface_count(nl, 0);
  for (std::size_t l = 0; l + 1 < nl; ++l) {
    const std::int32_t g = blocks[l + 1].top;
    auto on_grid = [&](const Layer& L, Eigen::Index s) {
      return L.springs(s, 0) >= g && L.springs(s, 0) < g + ng && L.springs(s, 1) >= g && L.springs(s, 1) < g + ng;
    };
    const Layer& U = out.layers[l];
    const Layer& D = out.layers[l + 1];
    Eigen::Index i = 0, j = 0;
    while (i < U.springs.rows() && j < D.springs.rows()) {
      if (!on_grid(U, i)) {
        ++i;
        continue;
      }
      if (!on_grid(D, j)) {
        ++j;
        continue;
      }
      const auto u = std::make_pair(U.springs(i, 0), U.springs(i, 1));
      const auto d = std::make_pair(D.springs(j, 0), D.springs(j, 1));
      if (u < d) {
        ++i;
      } else if (d < u) {
        ++j;
      } else {
        ++interface_count[l + 1], ++i, ++j;
      }
    }
  }
  std::int64_t comps = 0;
  for (std::int32_t i = 0; i < n_nodes; ++i)
    if (uf.find(i) == i) ++comps;
  R.components = comps;
  R.spring_ratio = lmin > 0 ? lmax / lmin : std::numeric_limits<double>::infinity();

  for (std::size_t l = 0; l <= nl; ++l) {
    const Layer& L = out.layers[l];
    LayerReport lr;
    lr.name = out.names[l];
    lr.tissue = L.tissue;
    lr.kind = L.kind;
    lr.order = L.order;
    lr.node_offset = L.node_offset;
    lr.nodes = L.nodes.rows();
    lr.springs = L.springs.rows();
    lr.lin_springs = L.lin_springs.rows();
    lr.tets = L.tets.rows();
    lr.volume_modulus_pa = L.volume_modulus;
    lr.volume_group = L.volume_group;
    lr.volume_tets = L.volume_tets.rows();
    lr.guard_modulus_pa = L.guard_modulus;
    lr.guard_ratio = L.guard_ratio;
    const Tissue* t = tissues.find(L.tissue);
    lr.density_kg_m3 = t->density_kg_m3;
    if (l < nl) {
      const SpringLaw law = law_of(*t);
      lr.k1_pa = law.k1_pa;
      lr.k2_pa = law.k2_pa;
      lr.turning_strain = law.turning_strain;
      lr.cells = cells[l].cells;
      lr.interface_springs = interface_count[l];
      lr.zero_stiffness_dropped = zero_k[l];
      for (Eigen::Index s = 0; s < L.spring_class.size(); ++s) ++lr.springs_by_class[class_name(L.spring_class(s))];
      lr.volume_m3 = cells[l].volume_m3;
      // the reference: the region between the faceted surfaces (sum over the
      // lattice's interior grids, which are straight interpolations)
      if (L.kind == "lattice" && o.through_cells > 1) {
        const MatX3d& top = surfaces[l].second.vertices;
        const MatX3d& bot = surfaces[l + 1].second.vertices;
        double v = 0;
        for (int k = 0; k < o.through_cells; ++k) {
          const double s0 = static_cast<double>(k) / o.through_cells, s1 = static_cast<double>(k + 1) / o.through_cells;
          v += layer_volume((1 - s0) * top + s0 * bot, (1 - s1) * top + s1 * bot, quads);
        }
        lr.reference_volume_m3 = v;
      } else {
        lr.reference_volume_m3 =
            layer_volume(surfaces[l].second.vertices, surfaces[l + 1].second.vertices, quads, split_of(l));
      }
      lr.mass_kg = layer_mass[l];
      const double ref = lr.density_kg_m3 * lr.reference_volume_m3;
      lr.mass_error = ref > 0 ? std::abs(lr.mass_kg - ref) / ref : std::numeric_limits<double>::infinity();
      lr.thickness_min_m = thickness[l].first;
      lr.thickness_mean_m = thickness[l].second;
      lr.spring_min_m = L.rest_length.size() ? L.rest_length.minCoeff() : 0;
      lr.spring_max_m = L.rest_length.size() ? L.rest_length.maxCoeff() : 0;
      lr.min_tet_volume_m3 = cells[l].min_tet_volume_m3;
      lr.inverted = cells[l].inverted;
      lr.projection = cells[l].projection;
      lr.rule = cells[l].rule;
      lr.mean_cell_m = tetra_shape[l];
      lr.axes = tetra_axes[l];
      R.springs += lr.springs;
      R.lin_springs += lr.lin_springs;
      R.tets += lr.tets;
      R.inverted_tets += lr.inverted;
      R.projection_fallbacks += lr.projection.fallbacks();
      R.layer_mass_kg += lr.mass_kg;
      R.max_mass_error = std::max(R.max_mass_error, lr.mass_error);
    }
    R.layers.push_back(lr);
  }
  R.mass_kg = mass.sum();
  phase("checks");

  if (R.zero_length_springs > 0)
    throw Error("", std::to_string(R.zero_length_springs) + " springs have zero length (coincident nodes)");
  if (R.duplicate_springs > 0) throw Error("", std::to_string(R.duplicate_springs) + " duplicate springs");
  if (R.components != 1)
    throw Error("", "the spring network falls into " + std::to_string(R.components) + " connected components");
  for (const auto& lr : R.layers)
    if (lr.kind != "rigid" && lr.mass_error > o.mass_tolerance)
      throw Error("", "layer '" + lr.name + "' mass " + fmt(lr.mass_kg) + " kg differs from density x volume by " +
                          fmt(100 * lr.mass_error) + " % (tolerance " + fmt(100 * o.mass_tolerance) + " %)");
  if (std::abs(R.mass_kg - R.layer_mass_kg) > 1e-9 * R.layer_mass_kg)
    throw Error("", "node masses do not add up to the layers' masses");
  if (!(R.spring_ratio <= o.max_spring_ratio))
    throw Error("", "longest / shortest spring = " + fmt(R.spring_ratio) + " exceeds " + fmt(o.max_spring_ratio));

  // ---- node sets ----
  auto range = [](std::int32_t from, std::int32_t n) {
    VecXi v(n);
    for (std::int32_t i = 0; i < n; ++i) v(i) = from + i;
    return v;
  };
  out.node_sets.emplace_back("fixed", range(blocks[nl].top, ng));
  out.node_sets.emplace_back("skin", range(blocks[0].top, ng));
  for (std::size_t l = 0; l < nl; ++l) {
    // every node of the layer's cells: its own nodes and its bottom grid
    out.node_sets.emplace_back("layer_" + out.names[l], range(blocks[l].top, blocks[l].bottom + ng - blocks[l].top));
  }
  out.node_sets.emplace_back("layer_" + out.names[nl], range(blocks[nl].top, ng));
  for (std::size_t s = 0; s <= nl; ++s) out.node_sets.emplace_back("surface_" + surfaces[s].first, range(blocks[s].top, ng));
  phase("sets");
  return out;
}

std::string build_parameters_json(const BuildOptions& o, const Stack& st) {
  nlohmann::json j;
  j["through_cells"] = o.through_cells;
  j["body_diagonals"] = o.body_diagonals;
  j["lattice_min_weight"] = o.lattice_min_weight;
  j["damping_ratio"] = o.damping_ratio;
  j["min_thickness_m"] = o.min_thickness_m;
  j["max_distance_factor"] = o.projection.max_distance_factor;
  j["min_barycentric"] = o.projection.min_barycentric;
  j["max_spring_ratio"] = o.max_spring_ratio;
  j["mass_tolerance"] = o.mass_tolerance;
  j["check_intersections"] = o.check_intersections;
  j["axis_correction"] = o.axis_correction;
  j["poisson_ratio"] = o.poisson_ratio;
  j["inversion_guard"] = o.inversion_guard;
  j["tetra_volume_term"] = o.tetra_volume_term;
  j["surfaces"] = st.surfaces;
  nlohmann::json layers = nlohmann::json::array();
  for (const auto& l : st.layers) layers.push_back(l.tissue + ":" + l.kind);
  j["layers"] = layers;
  return j.dump();
}

}  // namespace orthosim::msm
