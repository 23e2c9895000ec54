#include "libmodel/msm/tetra.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <utility>
#include <vector>

namespace orthosim::msm {

Surface triangulate(const MatX3d& vertices, const MatX4i& quads, const std::vector<std::uint8_t>& split) {
  Surface s;
  s.vertices = vertices;
  s.faces.resize(2 * quads.rows(), 3);
  for (Eigen::Index q = 0; q < quads.rows(); ++q) {
    const int r = !split.empty() && split[static_cast<std::size_t>(q)] ? 1 : 0;  // the diagonal's first corner
    const auto c = [&](int k) { return quads(q, (r + k) % 4); };
    s.faces.row(2 * q) << c(0), c(1), c(2);
    s.faces.row(2 * q + 1) << c(0), c(2), c(3);
  }
  return s;
}

std::vector<std::array<std::int32_t, 4>> grid_prism_tets(const MatX4i& quads, const std::vector<std::uint8_t>& split,
                                                         std::int32_t top_block, std::int32_t bottom_block,
                                                         std::int32_t created_block) {
  std::vector<std::array<std::int32_t, 4>> out;
  out.reserve(static_cast<std::size_t>(quads.rows()) * 2 * kGridPrismTets);
  for (Eigen::Index q = 0; q < quads.rows(); ++q) {
    const int v[4] = {quads(q, 0), quads(q, 1), quads(q, 2), quads(q, 3)};
    const bool alt = !split.empty() && split[static_cast<std::size_t>(q)] != 0;
    const std::array<std::array<int, 3>, 2> tris =
        alt ? std::array<std::array<int, 3>, 2>{{{1, 2, 3}, {1, 3, 0}}} : std::array<std::array<int, 3>, 2>{{{0, 1, 2}, {0, 2, 3}}};
    for (int i = 0; i < 2; ++i) {
      const auto& tri = tris[static_cast<std::size_t>(i)];
      std::array<std::array<std::int32_t, 4>, 3> g;
      const auto id = [&](PrismCorner c) { return (c.bottom ? bottom_block : top_block) + v[c.local]; };
      const auto cut = prism_cut(v, tri);
      for (std::size_t j = 0; j < 3; ++j) g[j] = {id(cut[j][0]), id(cut[j][1]), id(cut[j][2]), id(cut[j][3])};
      // the cap (bottom triangle, centroid) subtracted, then added
      const std::int32_t c = created_block + static_cast<std::int32_t>(2 * q + i);
      const std::int32_t w0 = bottom_block + v[tri[0]], w1 = bottom_block + v[tri[1]], w2 = bottom_block + v[tri[2]];
      for (const std::array<std::int32_t, 4>& cap : {std::array<std::int32_t, 4>{w1, w0, w2, c}, std::array<std::int32_t, 4>{w0, w1, w2, c}}) {
        out.insert(out.end(), g.begin(), g.end());
        out.push_back(cap);
      }
    }
  }
  return out;
}

std::vector<std::uint8_t> alternating_split(const MatX4i& quads) {
  const std::size_t nq = static_cast<std::size_t>(quads.rows());
  std::map<std::pair<std::int32_t, std::int32_t>, std::vector<std::int32_t>> by_edge;
  for (Eigen::Index q = 0; q < quads.rows(); ++q)
    for (int k = 0; k < 4; ++k) {
      const std::int32_t a = quads(q, k), b = quads(q, (k + 1) % 4);
      by_edge[{std::min(a, b), std::max(a, b)}].push_back(static_cast<std::int32_t>(q));
    }
  std::vector<std::uint8_t> colour(nq, 2);
  std::vector<std::int32_t> queue;
  for (std::size_t start = 0; start < nq; ++start) {
    if (colour[start] != 2) continue;
    colour[start] = 0;
    queue.assign(1, static_cast<std::int32_t>(start));
    for (std::size_t head = 0; head < queue.size(); ++head) {
      const std::int32_t q = queue[head];
      for (int k = 0; k < 4; ++k) {
        const std::int32_t a = quads(q, k), b = quads(q, (k + 1) % 4);
        for (std::int32_t n : by_edge[{std::min(a, b), std::max(a, b)}])
          if (colour[static_cast<std::size_t>(n)] == 2) {
            colour[static_cast<std::size_t>(n)] = static_cast<std::uint8_t>(1 - colour[static_cast<std::size_t>(q)]);
            queue.push_back(n);
          }
      }
    }
  }
  return colour;
}

LayerCells tetra_cells(const MatX3d& top, const MatX3d& bottom, const MatX4i& quads, const NodeBlocks& blocks,
                       const TetraOptions& o, const RayCaster* bottom_caster) {
  const std::vector<std::uint8_t> split = o.alternate_diagonals ? alternating_split(quads) : std::vector<std::uint8_t>{};
  const Surface upper = triangulate(top, quads, split), lower = triangulate(bottom, quads, split);
  const Eigen::Index nf = upper.faces.rows();
  VecXi expected(nf);
  VecXd reach(nf);
  for (Eigen::Index f = 0; f < nf; ++f) {
    expected(f) = static_cast<int>(f);
    double t = 0;
    for (int k = 0; k < 3; ++k) t += (top.row(upper.faces(f, k)) - bottom.row(upper.faces(f, k))).norm() / 3;
    reach(f) = t;
  }
  Projection proj = bottom_caster ? project_centroids(upper, lower, *bottom_caster, expected, reach, o.projection)
                                  : project_centroids(upper, lower, expected, reach, o.projection);

  LayerCells out;
  out.created = proj.points;
  out.projection = proj.counts;
  const std::int32_t ng = static_cast<std::int32_t>(top.rows());
  const std::int32_t last =
      std::max({blocks.top + ng, blocks.bottom + ng, blocks.created + static_cast<std::int32_t>(nf)});
  out.node_volume.assign(static_cast<std::size_t>(last), 0.0);
  // per prism: 7 tetrahedra and 18 distinct springs, in fixed slots
  constexpr int kTets = kTetsPerPrism, kPairs = 18;
  out.tets.assign(static_cast<std::size_t>(nf) * kTets, {0, 0, 0, 0});
  out.terms.assign(static_cast<std::size_t>(nf) * kPairs, SpringTerm{});
  std::vector<double> volumes(static_cast<std::size_t>(nf) * kTets, 0.0);
  std::vector<char> sheared(static_cast<std::size_t>(nf), 0);

  auto T = [&](int v) -> Eigen::Vector3d { return top.row(v).transpose(); };
  auto B = [&](int v) -> Eigen::Vector3d { return bottom.row(v).transpose(); };
  // the 7 tetrahedra of prism f as local nodes 0-2 top p[0..2], 3-5 bottom, 6 centroid
  auto prism_tets = [&](Eigen::Index f, std::array<std::array<int, 4>, kTets>& tt) {
    const int p[3] = {upper.faces(f, 0), upper.faces(f, 1), upper.faces(f, 2)};
    tt[0] = {0, 2, 1, 6};  // the paper's tetrahedron, positively oriented
    for (int e = 0; e < 3; ++e) {
      const int a = e, b = (e + 1) % 3;
      // pyramid c over the side quad (va vb wb wa), cut from the smaller id
      if (p[a] < p[b]) {
        tt[static_cast<std::size_t>(1 + 2 * e)] = {a, b, 3 + b, 6};
        tt[static_cast<std::size_t>(2 + 2 * e)] = {a, 3 + b, 3 + a, 6};
      } else {
        tt[static_cast<std::size_t>(1 + 2 * e)] = {a, b, 3 + a, 6};
        tt[static_cast<std::size_t>(2 + 2 * e)] = {b, 3 + b, 3 + a, 6};
      }
    }
  };
  // A hit may lie so far off the column under its triangle (a prism sheared
  // by curvature or misalignment) that a pyramid over a side quad inverts:
  // such a point moves along the bottom triangle toward its centroid, in
  // quarter steps, until all 7 tetrahedra have at least 1e-3 of the mean
  // volume. It stays on the bottom triangle, so volumes are unchanged.
  auto volumes_of = [&](Eigen::Index f, const Eigen::Vector3d& c, double* v) {
    const int p[3] = {upper.faces(f, 0), upper.faces(f, 1), upper.faces(f, 2)};
    const Eigen::Vector3d X[7] = {T(p[0]), T(p[1]), T(p[2]), B(p[0]), B(p[1]), B(p[2]), c};
    std::array<std::array<int, 4>, kTets> tt;
    prism_tets(f, tt);
    for (int i = 0; i < kTets; ++i)
      v[i] = tet_volume(X[tt[static_cast<std::size_t>(i)][0]], X[tt[static_cast<std::size_t>(i)][1]],
                        X[tt[static_cast<std::size_t>(i)][2]], X[tt[static_cast<std::size_t>(i)][3]]);
  };
  auto ok = [&](Eigen::Index f, const Eigen::Vector3d& c) {
    double v[kTets], sum = 0, mn = std::numeric_limits<double>::infinity();
    volumes_of(f, c, v);
    for (double x : v) sum += x, mn = std::min(mn, x);
    return sum > 0 && mn > 1e-3 * sum / kTets;
  };

  tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, nf, 256), [&](const tbb::blocked_range<Eigen::Index>& range) {
    for (Eigen::Index f = range.begin(); f != range.end(); ++f) {
      // the centroid node
      const Eigen::Vector3d hit = proj.points.row(f).transpose();
      Eigen::Vector3d c = hit;
      if (!ok(f, hit)) {
        const Eigen::Vector3d mid = (B(lower.faces(f, 0)) + B(lower.faces(f, 1)) + B(lower.faces(f, 2))) / 3.0;
        c = mid;
        for (double s : {0.25, 0.5, 0.75}) {
          const Eigen::Vector3d t = (1 - s) * hit + s * mid;
          if (ok(f, t)) {
            c = t;
            break;
          }
        }
        out.created.row(f) = c.transpose();
        sheared[static_cast<std::size_t>(f)] = 1;
      }
      // the 7 tetrahedra and their springs: k += V / l^2 per edge of each tetrahedron
      const Eigen::Index q = f / 2;
      const int p[3] = {upper.faces(f, 0), upper.faces(f, 1), upper.faces(f, 2)};
      const std::int32_t id[7] = {blocks.top + p[0],    blocks.top + p[1],    blocks.top + p[2],
                                  blocks.bottom + p[0], blocks.bottom + p[1], blocks.bottom + p[2],
                                  blocks.created + static_cast<std::int32_t>(f)};
      const Eigen::Vector3d X[7] = {T(p[0]), T(p[1]), T(p[2]), B(p[0]), B(p[1]), B(p[2]), c};
      const int local[7] = {p[0], p[1], p[2], p[0], p[1], p[2], -1};
      std::array<std::array<int, 4>, kTets> tt;
      prism_tets(f, tt);
      double k[7][7] = {};
      bool used[7][7] = {};
      for (int i = 0; i < kTets; ++i) {
        const auto& t4 = tt[static_cast<std::size_t>(i)];
        const double V = tet_volume(X[t4[0]], X[t4[1]], X[t4[2]], X[t4[3]]);
        volumes[static_cast<std::size_t>(f) * kTets + i] = V;
        out.tets[static_cast<std::size_t>(f) * kTets + i] = {id[t4[0]], id[t4[1]], id[t4[2]], id[t4[3]]};
        for (int x = 0; x < 4; ++x)
          for (int y = x + 1; y < 4; ++y) {
            const int a = std::min(t4[x], t4[y]), b = std::max(t4[x], t4[y]);
            used[a][b] = true;
            const double l2 = (X[b] - X[a]).squaredNorm();
            if (V > 0 && l2 > 0) k[a][b] += V / l2;  // an inverted tetrahedron adds no stiffness (and fails the build)
          }
      }
      if (o.axis_factors != std::array<double, 3>{1, 1, 1}) {
        // the prism's frame from its quad: u along q0 -> q1, w the normal
        const Eigen::Vector3d U = T(quads(q, 1)) - T(quads(q, 0)) + T(quads(q, 2)) - T(quads(q, 3));
        const Eigen::Vector3d V = T(quads(q, 3)) - T(quads(q, 0)) + T(quads(q, 2)) - T(quads(q, 1));
        const Eigen::Vector3d n = U.cross(V);
        const bool framed = n.squaredNorm() > 0 && U.squaredNorm() > 0;  // a degenerate quad keeps the trace rule
        const Eigen::Vector3d w = framed ? n.normalized() : n, u = framed ? U.normalized() : U, v = w.cross(u);
        for (int a = 0; a < 7 && framed; ++a)
          for (int b = a + 1; b < 7; ++b) {
            const Eigen::Vector3d d = X[b] - X[a];
            const double l2 = d.squaredNorm();
            if (!(l2 > 0)) continue;
            const double du = d.dot(u), dv = d.dot(v), dw = d.dot(w);
            k[a][b] *= (o.axis_factors[0] * du * du + o.axis_factors[1] * dv * dv + o.axis_factors[2] * dw * dw) / l2;
          }
      }
      const int r = split.empty() ? 0 : split[static_cast<std::size_t>(q)];
      const int d0 = quads(q, r), d2 = quads(q, r + 2);  // the quad's diagonal
      auto classify = [&](int a, int b) {            // a < b, local nodes
        if (b == 6) return a < 3 ? SpringClass::inter_layer : SpringClass::shear;  // v-c between layers, w-c in the surface
        const bool top_a = a < 3, top_b = b < 3;
        if (top_a == top_b) {
          const bool diagonal = (local[a] == d0 && local[b] == d2) || (local[a] == d2 && local[b] == d0);
          return diagonal ? SpringClass::shear : SpringClass::structural;
        }
        return local[a] == local[b] ? SpringClass::inter_layer : SpringClass::shear;  // vertical edge or side diagonal
      };
      SpringTerm* slot = out.terms.data() + static_cast<std::size_t>(f) * kPairs;
      int n = 0;
      for (int a = 0; a < 7; ++a)
        for (int b = a + 1; b < 7; ++b)
          if (used[a][b] && n < kPairs) slot[n++] = SpringTerm{id[a], id[b], k[a][b], classify(a, b)};
    }
  });
  for (Eigen::Index f = 0; f < nf; ++f) {
    for (int i = 0; i < kTets; ++i) {
      const double V = volumes[static_cast<std::size_t>(f) * kTets + i];
      for (std::int32_t n : out.tets[static_cast<std::size_t>(f) * kTets + i])
        out.node_volume[static_cast<std::size_t>(n)] += V / 4;
    }
    if (sheared[static_cast<std::size_t>(f)] && proj.status(f) == static_cast<std::uint8_t>(ProjectionStatus::hit)) {
      ++out.projection.sheared;
      --out.projection.hits;
    }
    ++out.cells;
  }
  double sum = 0, mn = std::numeric_limits<double>::infinity();
  for (double v : volumes) sum += v, mn = std::min(mn, v);
  out.volume_m3 = sum;
  out.sub_tets = static_cast<std::int64_t>(volumes.size());
  out.mean_tet_volume_m3 = volumes.empty() ? 0 : sum / static_cast<double>(volumes.size());
  out.min_tet_volume_m3 = volumes.empty() ? 0 : mn;
  const double floor = o.inverted_ratio * std::abs(out.mean_tet_volume_m3);
  for (std::size_t i = 0; i < volumes.size(); ++i)
    if (!(volumes[i] > floor) && out.inverted++ == 0) out.first_inverted_quad = static_cast<std::int64_t>(i / kTets / 2);
  return out;
}

}  // namespace orthosim::msm
