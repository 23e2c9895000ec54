#include "libmodel/msm/cells.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <tuple>

namespace orthosim::msm {

MergedSprings merge_terms(std::vector<SpringTerm> terms, const MatX3d& positions) {
  // bucket the terms by their smaller node (counting sort, in term order),
  // then sort each small bucket by (b, k): the sums no longer depend on the
  // order the cells were visited, and the whole is O(n) but for tiny sorts
  std::int32_t n_nodes = 0;
  for (auto& t : terms) {
    if (t.a > t.b) std::swap(t.a, t.b);
    n_nodes = std::max(n_nodes, t.b + 1);
  }
  std::vector<std::int64_t> start(static_cast<std::size_t>(n_nodes) + 1, 0);
  for (const auto& t : terms) ++start[static_cast<std::size_t>(t.a) + 1];
  for (std::size_t i = 1; i < start.size(); ++i) start[i] += start[i - 1];
  std::vector<SpringTerm> sorted(terms.size());
  {
    std::vector<std::int64_t> fill(start.begin(), start.end() - 1);
    for (const auto& t : terms) sorted[static_cast<std::size_t>(fill[static_cast<std::size_t>(t.a)]++)] = t;
  }
  terms.clear();
  terms.shrink_to_fit();
  std::vector<std::int64_t> unique(static_cast<std::size_t>(n_nodes) + 1, 0);
  tbb::parallel_for(tbb::blocked_range<std::int32_t>(0, n_nodes, 4096), [&](const tbb::blocked_range<std::int32_t>& r) {
    for (std::int32_t a = r.begin(); a != r.end(); ++a) {
      auto* b0 = sorted.data() + start[static_cast<std::size_t>(a)];
      auto* b1 = sorted.data() + start[static_cast<std::size_t>(a) + 1];
      std::sort(b0, b1, [](const SpringTerm& x, const SpringTerm& y) {
        return std::tie(x.b, x.k_per_pa) < std::tie(y.b, y.k_per_pa);
      });
      std::int64_t u = 0;
      for (auto* p = b0; p != b1; ++p)
        if (p == b0 || p->b != (p - 1)->b) ++u;
      unique[static_cast<std::size_t>(a) + 1] = u;
    }
  });
  for (std::size_t i = 1; i < unique.size(); ++i) unique[i] += unique[i - 1];
  const Eigen::Index n = static_cast<Eigen::Index>(unique.back());
  MergedSprings m;
  m.pairs.resize(n, 2);
  m.rest_length.resize(n);
  m.k_per_pa.setZero(n);
  m.spring_class.resize(n);
  m.cells.setZero(n);
  tbb::parallel_for(tbb::blocked_range<std::int32_t>(0, n_nodes, 4096), [&](const tbb::blocked_range<std::int32_t>& r) {
    for (std::int32_t a = r.begin(); a != r.end(); ++a) {
      Eigen::Index row = static_cast<Eigen::Index>(unique[static_cast<std::size_t>(a)]) - 1;
      const auto* b0 = sorted.data() + start[static_cast<std::size_t>(a)];
      const auto* b1 = sorted.data() + start[static_cast<std::size_t>(a) + 1];
      for (const auto* p = b0; p != b1; ++p) {
        if (p == b0 || p->b != (p - 1)->b) {
          ++row;
          m.pairs(row, 0) = p->a;
          m.pairs(row, 1) = p->b;
          m.rest_length(row) = (positions.row(p->b) - positions.row(p->a)).norm();
          m.spring_class(row) = static_cast<std::uint8_t>(p->cls);
        } else {
          // the class of a pair is its role in the cells; keep the lowest role code
          m.spring_class(row) = std::min(m.spring_class(row), static_cast<std::uint8_t>(p->cls));
        }
        m.k_per_pa(row) += p->k_per_pa;
        ++m.cells(row);
      }
    }
  });
  return m;
}

std::int64_t drop_zero_stiffness(MergedSprings& m) {
  Eigen::Index w = 0;
  for (Eigen::Index r = 0; r < m.pairs.rows(); ++r) {
    if (!(m.k_per_pa(r) > 0)) continue;
    m.pairs.row(w) = m.pairs.row(r);
    m.rest_length(w) = m.rest_length(r);
    m.k_per_pa(w) = m.k_per_pa(r);
    m.spring_class(w) = m.spring_class(r);
    m.cells(w) = m.cells(r);
    ++w;
  }
  const std::int64_t dropped = m.pairs.rows() - w;
  m.pairs.conservativeResize(w, 2);
  m.rest_length.conservativeResize(w);
  m.k_per_pa.conservativeResize(w);
  m.spring_class.conservativeResize(w);
  m.cells.conservativeResize(w);
  return dropped;
}

double layer_volume(const MatX3d& top, const MatX3d& bottom, const MatX4i& quads, const std::vector<std::uint8_t>& split) {
  auto tri = [](const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c) {
    return a.dot(b.cross(c)) / 6.0;
  };
  // a fixed reference point near the layer keeps the sum well conditioned
  const Eigen::Vector3d o = top.colwise().mean().transpose();
  auto T = [&](int i) -> Eigen::Vector3d { return top.row(i).transpose() - o; };
  auto B = [&](int i) -> Eigen::Vector3d { return bottom.row(i).transpose() - o; };
  double v = 0;
  for (Eigen::Index q = 0; q < quads.rows(); ++q) {
    const int r = !split.empty() && split[static_cast<std::size_t>(q)] ? 1 : 0;  // the diagonal's first corner
    const int a = quads(q, r), b = quads(q, (r + 1) % 4), c = quads(q, (r + 2) % 4), d = quads(q, (r + 3) % 4);
    v += tri(T(a), T(b), T(c)) + tri(T(a), T(c), T(d));  // top, outward
    v -= tri(B(a), B(b), B(c)) + tri(B(a), B(c), B(d));  // bottom, reversed
  }
  // open ends: side quads of boundary edges, in the direction their quad runs
  GridEdges e = grid_edges(quads);
  std::vector<std::pair<int, int>> directed;
  for (Eigen::Index q = 0; q < quads.rows(); ++q)
    for (int k = 0; k < 4; ++k) directed.emplace_back(quads(q, k), quads(q, (k + 1) % 4));
  std::sort(directed.begin(), directed.end());
  for (Eigen::Index i = 0; i < e.edges.rows(); ++i) {
    if (e.uses(i) != 1) continue;
    int va = e.edges(i, 0), vb = e.edges(i, 1);
    if (!std::binary_search(directed.begin(), directed.end(), std::make_pair(va, vb))) std::swap(va, vb);
    // outward side face (va, wa, wb, vb), cut along the diagonal from the smaller top id
    if (va < vb) {
      v += tri(T(va), B(va), B(vb)) + tri(T(va), B(vb), T(vb));
    } else {
      v += tri(T(va), B(va), T(vb)) + tri(T(vb), B(va), B(vb));
    }
  }
  return v;
}

GridEdges grid_edges(const MatX4i& quads) {
  std::vector<std::pair<int, int>> all;
  all.reserve(static_cast<std::size_t>(quads.rows()) * 4);
  for (Eigen::Index q = 0; q < quads.rows(); ++q)
    for (int k = 0; k < 4; ++k) {
      int a = quads(q, k), b = quads(q, (k + 1) % 4);
      all.emplace_back(std::min(a, b), std::max(a, b));
    }
  std::sort(all.begin(), all.end());
  std::vector<std::pair<int, int>> uniq;
  std::vector<int> uses;
  for (std::size_t i = 0; i < all.size(); ++i) {
    if (i == 0 || all[i] != all[i - 1]) {
      uniq.push_back(all[i]);
      uses.push_back(1);
    } else {
      ++uses.back();
    }
  }
  GridEdges g;
  g.edges.resize(static_cast<Eigen::Index>(uniq.size()), 2);
  g.uses.resize(static_cast<Eigen::Index>(uniq.size()));
  for (std::size_t i = 0; i < uniq.size(); ++i) {
    g.edges(static_cast<Eigen::Index>(i), 0) = uniq[i].first;
    g.edges(static_cast<Eigen::Index>(i), 1) = uniq[i].second;
    g.uses(static_cast<Eigen::Index>(i)) = uses[i];
  }
  return g;
}

}  // namespace orthosim::msm
