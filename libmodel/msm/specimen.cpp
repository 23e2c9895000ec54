#include "libmodel/msm/specimen.h"

#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>

namespace orthosim::msm {

namespace {

using Vec3 = Eigen::Vector3d;

using Tet = Eigen::Matrix<double, 4, 3>;

Tet tet_corners(const SpringNetwork& n, const MatX3d& x, Eigen::Index t) {
  Tet c;
  for (int k = 0; k < 4; ++k) c.row(k) = x.row(n.tets(t, k));
  return c;
}

// [v]_x: the cross-product matrix, [v]_x w = v x w
Eigen::Matrix3d cross_matrix(const Vec3& v) {
  Eigen::Matrix3d m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

double total_energy(const SpringNetwork& n, const MatX3d& x) {
  double e = 0;
  for (Eigen::Index s = 0; s < n.springs.rows(); ++s) {
    const double L = (x.row(n.springs(s, 1)) - x.row(n.springs(s, 0))).norm();
    e += biphasic_energy(L, n.rest_length(s), n.k1(s), n.k2(s), n.turning_length(s));
  }
  for (Eigen::Index g = 0; g < n.n_volume_groups(); ++g) e += group_volume_term(n, x, g, true, false).energy;
  return e;
}

// gradient of the energy (3n) and the largest spring force
VecXd gradient(const SpringNetwork& n, const MatX3d& x, double* fmax) {
  VecXd g = VecXd::Zero(3 * x.rows());
  double m = 0;
  for (Eigen::Index s = 0; s < n.springs.rows(); ++s) {
    const int a = n.springs(s, 0), b = n.springs(s, 1);
    const Vec3 d = (x.row(b) - x.row(a)).transpose();
    const double L = d.norm();
    if (!(L > 0)) continue;
    const double f = biphasic_force(L, n.rest_length(s), n.k1(s), n.k2(s), n.turning_length(s));
    m = std::max(m, std::abs(f));
    const Vec3 fv = f * d / L;
    g.segment<3>(3 * b) += fv;
    g.segment<3>(3 * a) -= fv;
  }
  for (Eigen::Index gr = 0; gr < n.n_volume_groups(); ++gr) {
    const GroupVolumeTerm v = group_volume_term(n, x, gr, true, false);
    for (Eigen::Index c = 0; c < v.nodes.size(); ++c) {
      g.segment<3>(3 * v.nodes(c)) += v.gradient.segment<3>(3 * c);
      m = std::max(m, v.gradient.segment<3>(3 * c).norm());
    }
  }
  if (fmax) *fmax = m;
  return g;
}

}  // namespace

namespace {

// V and dV/dx of the tetrahedron's corners (rows a, b, c, d)
Eigen::Matrix<double, 4, 3> volume_gradient(const Eigen::Matrix<double, 4, 3>& x, double* volume) {
  const Vec3 e1 = (x.row(1) - x.row(0)).transpose(), e2 = (x.row(2) - x.row(0)).transpose(),
             e3 = (x.row(3) - x.row(0)).transpose();
  Eigen::Matrix<double, 4, 3> g;
  g.row(1) = e2.cross(e3).transpose() / 6;
  g.row(2) = e3.cross(e1).transpose() / 6;
  g.row(3) = e1.cross(e2).transpose() / 6;
  g.row(0) = -(g.row(1) + g.row(2) + g.row(3));
  *volume = e1.dot(e2.cross(e3)) / 6;
  return g;
}

// d2V/dx2 (12 x 12, corners a, b, c, d): with e_i the edges from a,
// d2V/de_i de_j (i != j; zero on the diagonal) is (1,2) = -[e3]x / 6,
// (1,3) = [e2]x / 6, (2,3) = -[e1]x / 6, and (j,i) the transpose; the rows
// and columns of a are minus the sums
Eigen::Matrix<double, 12, 12> volume_second(const Eigen::Matrix<double, 4, 3>& x) {
  const Vec3 e1 = (x.row(1) - x.row(0)).transpose(), e2 = (x.row(2) - x.row(0)).transpose(),
             e3 = (x.row(3) - x.row(0)).transpose();
  std::array<std::array<Eigen::Matrix3d, 4>, 4> H;
  for (auto& row : H)
    for (auto& b : row) b.setZero();
  H[1][2] = -cross_matrix(e3) / 6, H[1][3] = cross_matrix(e2) / 6, H[2][3] = -cross_matrix(e1) / 6;
  H[2][1] = H[1][2].transpose(), H[3][1] = H[1][3].transpose(), H[3][2] = H[2][3].transpose();
  for (int j = 1; j < 4; ++j) {
    H[0][j] = -(H[1][j] + H[2][j] + H[3][j]);
    H[j][0] = H[0][j].transpose();
  }
  H[0][0] = -(H[0][1] + H[0][2] + H[0][3]);
  Eigen::Matrix<double, 12, 12> out;
  for (int i = 0; i < 4; ++i)
    for (int j = 0; j < 4; ++j) out.block<3, 3>(3 * i, 3 * j) = H[i][j];
  return out;
}

}  // namespace

TetVolumeTerm tet_volume_term(const Eigen::Matrix<double, 4, 3>& x, double rest_volume, double k, bool gauss_newton) {
  TetVolumeTerm out;
  const Eigen::Matrix<double, 4, 3> g = volume_gradient(x, &out.volume);
  const double v0 = std::abs(rest_volume);
  const double strain = v0 > 0 ? (out.volume - rest_volume) / v0 : 0.0;
  out.energy = 0.5 * k * v0 * strain * strain;
  out.gradient = k * strain * g;
  out.hessian.setZero();
  if (!(v0 > 0)) return out;
  Eigen::Matrix<double, 12, 1> gv;
  for (int c = 0; c < 4; ++c) gv.segment<3>(3 * c) = g.row(c).transpose();
  out.hessian = (k / v0) * gv * gv.transpose();
  if (!gauss_newton) out.hessian += k * strain * volume_second(x);
  return out;
}

GroupVolumeTerm group_volume_term(const SpringNetwork& net, const MatX3d& x, Eigen::Index group, bool gauss_newton,
                                  bool want_hessian) {
  const bool single = net.tet_group_first.size() == 0;
  const Eigen::Index t0 = single ? group : net.tet_group_first(group), t1 = single ? group + 1 : net.tet_group_first(group + 1);
  GroupVolumeTerm out;
  // the group's distinct nodes, in order of first appearance
  int nodes[kMaxGroupNodes], n = 0;
  auto slot_of = [&](int node) { return static_cast<int>(std::find(nodes, nodes + n, node) - nodes); };
  for (Eigen::Index t = t0; t < t1; ++t)
    for (int c = 0; c < 4; ++c) {
      const int node = net.tets(t, c);
      if (slot_of(node) < n) continue;
      if (n == kMaxGroupNodes) throw Error("", "a volume group has more than " + std::to_string(kMaxGroupNodes) + " nodes");
      nodes[n++] = node;
    }
  out.nodes = Eigen::Map<const Eigen::VectorXi>(nodes, n);
  const Eigen::Index m = 3 * n;
  const bool exact = want_hessian && !gauss_newton;
  decltype(out.gradient) G = decltype(out.gradient)::Zero(m);
  decltype(out.hessian) H2 = decltype(out.hessian)::Zero(exact ? m : 0, exact ? m : 0);
  for (Eigen::Index t = t0; t < t1; ++t) {
    const Eigen::Matrix<double, 4, 3> X = tet_corners(net, x, t);
    double V = 0;
    const Eigen::Matrix<double, 4, 3> g = volume_gradient(X, &V);
    out.volume += V;
    out.rest_volume += net.tet_rest_volume(t);
    int sl[4];
    for (int c = 0; c < 4; ++c) sl[c] = slot_of(net.tets(t, c));
    for (int c = 0; c < 4; ++c) G.segment<3>(3 * sl[c]) += g.row(c).transpose();
    if (exact) {
      const Eigen::Matrix<double, 12, 12> d2V = volume_second(X);
      for (int a = 0; a < 4; ++a)
        for (int b = 0; b < 4; ++b) H2.block<3, 3>(3 * sl[a], 3 * sl[b]) += d2V.block<3, 3>(3 * a, 3 * b);
    }
  }
  const double k = net.tet_k(group), a0 = std::abs(out.rest_volume);
  const double strain = a0 > 0 ? (out.volume - out.rest_volume) / a0 : 0.0;
  out.energy = 0.5 * k * a0 * strain * strain;
  out.gradient = k * strain * G;
  if (want_hessian) {
    out.hessian.setZero(m, m);
    if (a0 > 0) out.hessian.noalias() += (k / a0) * G * G.transpose();
    if (exact) out.hessian += k * strain * H2;
  }
  return out;
}

double volume_ratio(double nu) {
  return std::max(0.0, bulk_ratio(nu) - 2.0 / 3.0);
}

double bulk_ratio(double nu) {
  if (!(nu >= 0.25 && nu < 0.5)) throw Error("", "Poisson's ratio must be in [0.25, 0.5)");
  return 1 / (3 * (1 - 2 * nu));
}

StaticResult solve_static(const SpringNetwork& net, const std::vector<std::int64_t>& prescribed,
                          const std::vector<double>& displacement, const MatX3d* start, const StaticOptions& o) {
  const Eigen::Index nn = net.nodes.rows(), nd = 3 * nn;
  if (prescribed.size() != displacement.size()) throw Error("", "solve_static: one displacement per prescribed dof");
  if (!(o.force_tolerance > 0 && o.force_tolerance <= 1e-3)) throw Error("", "solve_static: force_tolerance in (0, 1e-3]");
  // free dof numbering
  std::vector<std::int64_t> free_of(static_cast<std::size_t>(nd), 0);
  for (auto d : prescribed) {
    if (d < 0 || d >= nd) throw Error("", "solve_static: prescribed dof out of range");
    free_of[static_cast<std::size_t>(d)] = -1;
  }
  std::int64_t nfree = 0;
  for (auto& f : free_of)
    if (f == 0) f = nfree++;
    else f = -1;
  StaticResult r;
  r.x = start ? *start : net.nodes;
  if (r.x.rows() != nn) throw Error("", "solve_static: start has the wrong number of nodes");
  for (std::size_t i = 0; i < prescribed.size(); ++i) {
    const auto d = prescribed[i];
    r.x(d / 3, d % 3) = net.nodes(d / 3, d % 3) + displacement[i];
  }
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt;
  Eigen::Index analysed_nnz = -1;  // the pattern analysed (springs of zero length drop out of it)
  std::vector<Eigen::Triplet<double>> trip;
  auto assemble = [&](const MatX3d& x, bool clamp_geometric) {
    trip.clear();
    trip.reserve(static_cast<std::size_t>(net.springs.rows()) * 36);
    for (Eigen::Index s = 0; s < net.springs.rows(); ++s) {
      const int a = net.springs(s, 0), b = net.springs(s, 1);
      const Vec3 d = (x.row(b) - x.row(a)).transpose();
      const double L = d.norm();
      // a spring of zero length keeps its (zero) entries: the pattern never changes
      Eigen::Matrix3d H = Eigen::Matrix3d::Zero();
      if (L > 0) {
        const Vec3 n = d / L;
        const double f = biphasic_force(L, net.rest_length(s), net.k1(s), net.k2(s), net.turning_length(s));
        const double kt = biphasic_slope(L, net.k1(s), net.k2(s), net.turning_length(s));
        double geo = f / L;
        if (clamp_geometric) geo = std::max(geo, 0.0);
        H = kt * n * n.transpose() + geo * (Eigen::Matrix3d::Identity() - n * n.transpose());
      }
      const int nodes[2] = {a, b};
      for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 2; ++j) {
          const double sign = i == j ? 1.0 : -1.0;
          for (int p = 0; p < 3; ++p) {
            const auto fi = free_of[static_cast<std::size_t>(3 * nodes[i] + p)];
            if (fi < 0) continue;
            for (int q = 0; q < 3; ++q) {
              const auto fj = free_of[static_cast<std::size_t>(3 * nodes[j] + q)];
              if (fj < 0) continue;
              trip.emplace_back(static_cast<int>(fi), static_cast<int>(fj), sign * H(p, q));
            }
          }
        }
    }
    for (Eigen::Index g = 0; g < net.n_volume_groups(); ++g) {
      const GroupVolumeTerm v = group_volume_term(net, x, g, clamp_geometric, true);
      const Eigen::Index nl = 3 * v.nodes.size();
      for (Eigen::Index i = 0; i < nl; ++i) {
        const auto fi = free_of[static_cast<std::size_t>(3 * v.nodes(i / 3) + i % 3)];
        if (fi < 0) continue;
        for (Eigen::Index j = 0; j < nl; ++j) {
          const auto fj = free_of[static_cast<std::size_t>(3 * v.nodes(j / 3) + j % 3)];
          if (fj >= 0) trip.emplace_back(static_cast<int>(fi), static_cast<int>(fj), v.hessian(i, j));
        }
      }
    }
    Eigen::SparseMatrix<double> K(nfree, nfree);
    K.setFromTriplets(trip.begin(), trip.end());
    return K;
  };
  // factorises; false when not positive definite
  auto factor = [&](const Eigen::SparseMatrix<double>& K) {
    if (K.nonZeros() != analysed_nnz) {
      ldlt.analyzePattern(K);
      analysed_nnz = K.nonZeros();
    }
    ldlt.factorize(K);
    if (ldlt.info() != Eigen::Success) return false;
    const auto& D = ldlt.vectorD();
    if (D.size() == 0) return true;
    const double dmax = D.cwiseAbs().maxCoeff();
    return D.minCoeff() > 1e-13 * dmax;
  };

  // round-off floor of the residual: forces are k (L - L0), each good to a
  // few ulps of k L
  double kl = 0;
  for (Eigen::Index s = 0; s < net.springs.rows(); ++s)
    kl = std::max(kl, std::max(net.k1(s), net.k2(s)) * std::max(net.rest_length(s), net.turning_length(s)));
  // and a volume term's, k |dV/dx| ~ k V0^(2/3) (an area)
  const double k_volume = net.tet_k.size() ? net.tet_k.maxCoeff() : 0.0;
  for (Eigen::Index t = 0; t < net.tets.rows(); ++t)
    kl = std::max(kl, k_volume * std::pow(std::abs(net.tet_rest_volume(t)), 2.0 / 3.0));
  const double floor = 256 * std::numeric_limits<double>::epsilon() * kl;
  double fmax = 0;
  for (r.iterations = 0; r.iterations <= o.max_iterations; ++r.iterations) {
    VecXd g = gradient(net, r.x, &fmax);
    VecXd gf(nfree);
    for (Eigen::Index d = 0; d < nd; ++d)
      if (free_of[static_cast<std::size_t>(d)] >= 0) gf(free_of[static_cast<std::size_t>(d)]) = g(d);
    r.residual = nfree ? gf.cwiseAbs().maxCoeff() : 0.0;
    r.force_scale = fmax;
    if (r.residual <= std::max({o.force_tolerance * fmax, floor, 1e-300})) {
      // an equilibrium found without a factorisation (e.g. the start) must
      // still be checked for a singular stiffness: a mechanism has no unique one
      if (r.iterations == 0 && nfree > 0 && !factor(assemble(r.x, false)) && !factor(assemble(r.x, true)))
        throw Error("", "the spring network is a mechanism: its stiffness matrix is singular on the free dofs");
      r.converged = true;
      break;
    }
    if (r.iterations == o.max_iterations) break;
    Eigen::VectorXd step;
    bool ok = factor(assemble(r.x, false));
    if (ok) {
      step = -ldlt.solve(gf);
      if (!(step.dot(gf) < 0)) ok = false;
    }
    if (!ok) {
      if (!factor(assemble(r.x, true)))
        throw Error("", "the spring network is a mechanism: its stiffness matrix is singular on the free dofs");
      step = -ldlt.solve(gf);
    }
    // backtracking: accept a step that lowers the energy enough (Armijo) or,
    // where the energy no longer resolves the change (L - L0 loses digits at
    // small strains), one that lowers the largest free residual force
    const double e0 = total_energy(net, r.x), slope = step.dot(gf);
    auto free_residual = [&](const MatX3d& x) {
      const VecXd gt = gradient(net, x, nullptr);
      double m = 0;
      for (Eigen::Index d = 0; d < nd; ++d)
        if (free_of[static_cast<std::size_t>(d)] >= 0) m = std::max(m, std::abs(gt(d)));
      return m;
    };
    double alpha = 1;
    MatX3d trial = r.x;
    for (int k = 0; k < 40; ++k) {
      trial = r.x;
      for (Eigen::Index d = 0; d < nd; ++d) {
        const auto f = free_of[static_cast<std::size_t>(d)];
        if (f >= 0) trial(d / 3, d % 3) += alpha * step(f);
      }
      const double e1 = total_energy(net, trial);
      if (e1 <= e0 + 1e-4 * alpha * slope) break;
      if (free_residual(trial) < (1 - 1e-4 * alpha) * r.residual) break;
      alpha *= 0.5;
    }
    r.x = trial;
  }
  VecXd g = gradient(net, r.x, &fmax);
  r.reaction = VecXd::Zero(nd);
  for (auto d : prescribed) r.reaction(d) = g(d);
  return r;
}

Specimen make_specimen(const SpecimenOptions& o) {
  if (o.kind != "lattice" && o.kind != "tetra") throw Error("", "specimen kind must be lattice or tetra, not '" + o.kind + "'");
  for (int k = 0; k < 3; ++k) {
    if (o.cells[static_cast<std::size_t>(k)] < 1 || o.cells[static_cast<std::size_t>(k)] > 200)
      throw Error("", "specimen cells must be in 1..200");
    if (!(o.cell_m[static_cast<std::size_t>(k)] > 0)) throw Error("", "specimen cell size must be > 0");
  }
  const int cx = o.cells[0], cy = o.cells[1], cz = o.cells[2];
  const int nu = cx + 1, nv = cy + 1, ng = nu * nv;
  const double H = cz * o.cell_m[2];
  MatX3d top(ng, 3), bottom(ng, 3);
  for (int j = 0; j < nv; ++j)
    for (int i = 0; i < nu; ++i) {
      top.row(j * nu + i) << i * o.cell_m[0], j * o.cell_m[1], H;
      bottom.row(j * nu + i) << i * o.cell_m[0], j * o.cell_m[1], 0.0;
    }
  MatX4i quads(cx * cy, 4);
  for (int j = 0; j < cy; ++j)
    for (int i = 0; i < cx; ++i) quads.row(j * cx + i) << j * nu + i, j * nu + i + 1, (j + 1) * nu + i + 1, (j + 1) * nu + i;

  LayerCells cells;
  NodeBlocks blocks;
  blocks.top = 0;
  blocks.created = ng;
  if (o.kind == "lattice") {
    LatticeOptions lo;
    lo.through_cells = cz;
    lo.body_diagonals = o.body_diagonals;
    lo.min_weight = o.lattice_min_weight;
    lo.axis_correction = o.lattice_axis_correction;
    lo.volume_ratio = o.volume_ratio;
    blocks.bottom = ng + ng * (cz - 1);
    cells = lattice_cells(top, bottom, quads, blocks, lo);
  } else {
    for (double f : o.tetra_axis_factors)
      if (!(f > 0 && std::isfinite(f))) throw Error("", "specimen tetra axis factors must be finite and > 0");
    TetraOptions to;
    to.projection = o.projection;
    to.axis_factors = o.tetra_axis_factors;
    to.alternate_diagonals = o.tetra_alternate_diagonals;
    blocks.bottom = ng + 2 * static_cast<std::int32_t>(quads.rows());
    cells = tetra_cells(top, bottom, quads, blocks, to);
  }
  if (cells.inverted) throw Error("", "specimen has inverted cells");
  Specimen s;
  s.options = o;
  const Eigen::Index n_created = cells.created.rows();
  MatX3d X(2 * ng + n_created, 3);
  X.topRows(ng) = top;
  X.middleRows(ng, n_created) = cells.created;
  X.bottomRows(ng) = bottom;
  // every cell spring stays, even where the rule gives it no stiffness (the
  // tuner may give it some); build_layers drops those from the model
  MergedSprings m = merge_terms(std::move(cells.terms), X);
  s.network.nodes = X;
  s.network.springs = m.pairs;
  s.network.rest_length = m.rest_length;
  s.k_per_pa = m.k_per_pa;
  s.spring_class = m.spring_class;
  s.cells = m.cells;
  s.size_m = {cx * o.cell_m[0], cy * o.cell_m[1], H};
  s.volume_m3 = cells.volume_m3;
  s.tets = static_cast<std::int64_t>(cells.tets.size());
  if (!(o.volume_ratio >= 0 && std::isfinite(o.volume_ratio))) throw Error("", "specimen volume ratio must be finite and >= 0");
  if (o.volume_ratio > 0) {
    // the global ids of the cells are the rows of X (top, created, bottom);
    // as build writes them: one term per tetrahedron of a tetra layer, per
    // hexahedron (6 tetrahedra) of a lattice layer
    // (a tetra layer's term over its grid prisms and their caps instead,
    // grid_prism_tets: two groups of 4 a prism)
    const bool grid = o.kind == "tetra" && o.tetra_grid_prisms;
    if (grid && o.volume_group != 0 && o.volume_group != kGridPrismTets)
      throw Error("", "specimen: the grid prisms' terms are groups of " + std::to_string(kGridPrismTets));
    const std::vector<std::array<std::int32_t, 4>> vt =
        grid ? grid_prism_tets(quads, o.tetra_alternate_diagonals ? alternating_split(quads) : std::vector<std::uint8_t>{},
                               blocks.top, blocks.bottom, blocks.created)
             : std::move(cells.tets);
    const auto nt = static_cast<Eigen::Index>(vt.size());
    s.network.tets.resize(nt, 4);
    s.network.tet_rest_volume.resize(nt);
    for (Eigen::Index t = 0; t < nt; ++t) {
      const auto& c = vt[static_cast<std::size_t>(t)];
      for (int k = 0; k < 4; ++k) s.network.tets(t, k) = c[static_cast<std::size_t>(k)];
      s.network.tet_rest_volume(t) = tet_volume(X.row(c[0]), X.row(c[1]), X.row(c[2]), X.row(c[3]));
    }
    const int G = grid ? kGridPrismTets : o.volume_group > 0 ? o.volume_group : o.kind == "lattice" ? 6 : 1;
    if (nt % G != 0) throw Error("", "specimen: its tetrahedra are not groups of volume_group " + std::to_string(G));
    if (G > 1) {
      const Eigen::Index ng = nt / G;
      s.network.tet_group_first.resize(ng + 1);
      for (Eigen::Index g = 0; g <= ng; ++g) s.network.tet_group_first(g) = static_cast<int>(G * g);
    }
  }
  apply_law(s, {1.0, 1.0, 0.0});
  return s;
}

void apply_law(Specimen& s, const SpringLaw& law) {
  if (!(law.k1_pa > 0) || !(law.k2_pa >= law.k1_pa) || !(law.turning_strain >= 0))
    throw Error("", "spring law needs K1 > 0, K2 >= K1 and a turning strain >= 0");
  s.network.k1 = law.k1_pa * s.k_per_pa;
  s.network.k2 = law.k2_pa * s.k_per_pa;
  s.network.turning_length = s.network.rest_length * (1 + law.turning_strain);
  s.network.tet_k = VecXd::Constant(s.network.n_volume_groups(), s.options.volume_ratio * law.k1_pa);
}

UniaxialCurve uniaxial_test(const Specimen& s, const std::vector<double>& strains, const UniaxialOptions& o) {
  const auto t0 = std::chrono::steady_clock::now();
  if (o.axis < 0 || o.axis > 2) throw Error("", "uniaxial_test: axis must be 0, 1 or 2");
  const int ax = o.axis, l1 = (ax + 1) % 3, l2 = (ax + 2) % 3;
  const MatX3d& X = s.network.nodes;
  const double L = s.size_m[static_cast<std::size_t>(ax)];
  const double tol = 1e-9 * std::max({s.size_m[0], s.size_m[1], s.size_m[2]});
  std::vector<int> lo, hi, side[2][2];
  const Eigen::Index ng = static_cast<Eigen::Index>(s.options.cells[0] + 1) * (s.options.cells[1] + 1);
  for (Eigen::Index i = 0; i < X.rows(); ++i) {
    const int n = static_cast<int>(i);
    if (std::abs(X(i, ax)) < tol) lo.push_back(n);
    if (std::abs(X(i, ax) - L) < tol) hi.push_back(n);
    // a tetra layer's created nodes (the projected centroids, rows ng ..
    // n - ng) lie on the bottom face at rest but are inside the layer: the
    // next layer holds only the grid, so the faces' motion is the grids'
    if (s.options.kind == "tetra" && i >= ng && i < X.rows() - ng) continue;
    for (int k = 0; k < 2; ++k) {
      const int lat = k == 0 ? l1 : l2;
      if (std::abs(X(i, lat)) < tol) side[k][0].push_back(n);
      if (std::abs(X(i, lat) - s.size_m[static_cast<std::size_t>(lat)]) < tol) side[k][1].push_back(n);
    }
  }
  if (lo.empty() || hi.empty()) throw Error("", "uniaxial_test: the specimen has no loaded faces");
  // rigid-body modes of the sliding clamp: the lo-face corner at the lateral
  // minimum holds both lateral dofs, the corner at (max l1, min l2) holds l2
  auto corner = [&](double w1, double w2) {
    int best = lo.front();
    double bd = std::numeric_limits<double>::infinity();
    for (int n : lo) {
      const double d = std::abs(X(n, l1) - w1) + std::abs(X(n, l2) - w2);
      if (d < bd) bd = d, best = n;
    }
    return best;
  };
  const int c0 = corner(0, 0), c1 = corner(s.size_m[static_cast<std::size_t>(l1)], 0);

  UniaxialCurve out;
  MatX3d x = X;
  double prev = 0;
  for (double eps : strains) {
    std::vector<std::int64_t> dofs;
    std::vector<double> disp;
    auto fix = [&](int n, int a, double u) {
      dofs.push_back(3 * static_cast<std::int64_t>(n) + a);
      disp.push_back(u);
    };
    for (int n : lo) {
      fix(n, ax, 0);
      if (o.clamp == Clamp::full) fix(n, l1, 0), fix(n, l2, 0);
    }
    for (int n : hi) {
      fix(n, ax, eps * L);
      if (o.clamp == Clamp::full) fix(n, l1, 0), fix(n, l2, 0);
    }
    if (o.clamp == Clamp::sliding) {
      fix(c0, l1, 0);
      fix(c0, l2, 0);
      fix(c1, l2, 0);
    }
    // start from the previous state stretched affinely by the strain increment
    MatX3d guess = x;
    guess.col(ax) += (eps - prev) * X.col(ax);
    StaticResult r = solve_static(s.network, dofs, disp, &guess, o.solver);
    if (!r.converged)
      throw Error("", "uniaxial_test: no equilibrium at strain " + std::to_string(eps) + " after " +
                          std::to_string(r.iterations) + " Newton iterations");
    x = r.x;
    prev = eps;
    double F = 0;
    for (int n : hi) F += r.reaction(3 * n + ax);
    const double A = s.size_m[static_cast<std::size_t>(l1)] * s.size_m[static_cast<std::size_t>(l2)];
    out.strain.push_back(eps);
    out.stress_pa.push_back(F / A);
    for (int k = 0; k < 2; ++k) {
      const int lat = k == 0 ? l1 : l2;
      double m0 = 0, m1 = 0;
      for (int n : side[k][0]) m0 += x(n, lat) - X(n, lat);
      for (int n : side[k][1]) m1 += x(n, lat) - X(n, lat);
      m0 /= std::max<std::size_t>(1, side[k][0].size());
      m1 /= std::max<std::size_t>(1, side[k][1].size());
      out.lateral_strain.push_back((m1 - m0) / s.size_m[static_cast<std::size_t>(lat)]);
    }
    out.iterations.push_back(r.iterations);
    out.max_residual = std::max(out.max_residual, r.residual);
  }
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return out;
}

AxisCalibration calibrate_tetra_axes(SpecimenOptions o, double tolerance, int max_iterations) {
  if (o.kind != "tetra") throw Error("", "calibrate_tetra_axes: the specimen must be a tetra layer");
  if (!(tolerance > 0 && tolerance < 0.5)) throw Error("", "calibrate_tetra_axes: tolerance in (0, 0.5)");
  AxisCalibration out;
  const double strain = 1e-4;
  // The flat specimen's prisms all have the frame x, y, z, so the factors
  // scale each spring by sum_a s_a n_a^2 of its own direction, exactly as
  // tetra_cells does per prism: the specimen is made once.
  o.tetra_axis_factors = {1, 1, 1};
  const Specimen base = make_specimen(o);
  const Eigen::Index ns = base.k_per_pa.size();
  MatX3d n2(ns, 3);
  for (Eigen::Index e = 0; e < ns; ++e) {
    const Eigen::Vector3d d = (base.network.nodes.row(base.network.springs(e, 1)) -
                               base.network.nodes.row(base.network.springs(e, 0))).transpose();
    n2.row(e) = d.cwiseProduct(d).transpose() / d.squaredNorm();
  }
  auto moduli = [&](const Eigen::Vector3d& f) {
    Specimen s = base;
    s.k_per_pa = base.k_per_pa.cwiseProduct(n2 * f);
    apply_law(s, SpringLaw{1.0, 1.0, 0.0});
    Eigen::Vector3d E;
    for (int axis = 0; axis < 3; ++axis) {
      UniaxialOptions u;
      u.axis = axis;
      E(axis) = uniaxial_test(s, {strain}, u).stress_pa[0] / strain;
    }
    return E;
  };
  // Broyden's method on log E(log s) = 0, starting from the fixed point's
  // Jacobian (the identity: s <- s / E); 3-4 iterations where the fixed
  // point took 5-9 (each one three linear uniaxial tests)
  Eigen::Vector3d x = Eigen::Vector3d::Zero();  // log s
  Eigen::Matrix3d J = Eigen::Matrix3d::Identity();
  Eigen::Vector3d y_prev = Eigen::Vector3d::Zero(), x_prev = Eigen::Vector3d::Zero();
  for (out.iterations = 0; out.iterations <= max_iterations; ++out.iterations) {
    const Eigen::Vector3d E = moduli(x.array().exp().matrix());
    if (out.iterations == 0) out.moduli_before = {E(0), E(1), E(2)};
    if (!E.allFinite() || !(E.minCoeff() > 0)) break;
    const double error = (E.array() - 1).abs().maxCoeff();
    if (error <= tolerance) {
      const Eigen::Vector3d f = x.array().exp().matrix();
      out.factors = {f(0), f(1), f(2)};
      out.moduli_after = {E(0), E(1), E(2)};
      return out;
    }
    const Eigen::Vector3d y = E.array().log().matrix();
    if (out.iterations > 0) {
      const Eigen::Vector3d dx = x - x_prev, dy = y - y_prev;
      if (dx.squaredNorm() > 0) J += (dy - J * dx) * dx.transpose() / dx.squaredNorm();
    }
    x_prev = x, y_prev = y;
    Eigen::Vector3d step = -J.partialPivLu().solve(y);
    if (!step.allFinite()) step = -y;        // a singular update: the fixed point's step
    const double big = step.cwiseAbs().maxCoeff();
    if (big > 1.0) step *= 1.0 / big;        // at most e-fold a step
    x += step;
  }
  throw Error("", "the tetra layer's axis factors did not converge (cell " + std::to_string(o.cell_m[0] * 1e3) + " x " +
                      std::to_string(o.cell_m[1] * 1e3) + " x " + std::to_string(o.cell_m[2] * 1e3) + " mm)");
}

AxisCalibration tetra_layer_axes(const std::array<double, 3>& cell_m, double volume_ratio, int volume_group,
                                 bool grid_prisms) {
  SpecimenOptions o;
  o.volume_ratio = volume_ratio;
  o.volume_group = volume_group;
  o.tetra_grid_prisms = grid_prisms;
  o.kind = "tetra";
  o.cells = kTetraCalibrationCells;
  o.cell_m = cell_m;
  o.tetra_alternate_diagonals = true;
  return calibrate_tetra_axes(o);
}

std::array<double, 3> mean_cell_shape(const MatX3d& top, const MatX3d& bottom, const MatX4i& quads) {
  double a = 0, b = 0, h = 0;
  auto P = [&](Eigen::Index q, int k) { return top.row(quads(q, k)); };
  for (Eigen::Index q = 0; q < quads.rows(); ++q) {
    a += 0.5 * ((P(q, 1) - P(q, 0)).norm() + (P(q, 2) - P(q, 3)).norm());
    b += 0.5 * ((P(q, 2) - P(q, 1)).norm() + (P(q, 3) - P(q, 0)).norm());
  }
  const Eigen::Index ng = std::min(top.rows(), bottom.rows());
  for (Eigen::Index v = 0; v < ng; ++v) h += (top.row(v) - bottom.row(v)).norm();
  const double nq = static_cast<double>(std::max<Eigen::Index>(1, quads.rows()));
  return {a / nq, b / nq, h / static_cast<double>(std::max<Eigen::Index>(1, ng))};
}

}  // namespace orthosim::msm
