// Centreline refinement: sub-voxel re-centring and radii from cross-sections,
// junction regions (where the children's inscribed spheres stop overlapping),
// bifurcation points, open ends extended to the volume border.
#include "libmodel/vessels/detail.h"

#include <Eigen/Dense>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <sstream>

namespace orthosim::vessels_detail {
namespace {

constexpr double kPi = 3.14159265358979323846;

// arc length at each point
std::vector<double> arc(const std::vector<Eigen::Vector3d>& x) {
  std::vector<double> s(x.size(), 0);
  for (std::size_t i = 1; i < x.size(); ++i) s[i] = s[i - 1] + (x[i] - x[i - 1]).norm();
  return s;
}

// resamples (x, r) at equal arc length, spacing at most `step`, ends kept
void resample(std::vector<Eigen::Vector3d>& x, std::vector<double>& r, double step) {
  if (x.size() < 2) return;
  const std::vector<double> s = arc(x);
  const double L = s.back();
  const int n = std::max(1, static_cast<int>(std::ceil(L / step - 1e-9)));
  std::vector<Eigen::Vector3d> nx;
  std::vector<double> nr;
  std::size_t j = 0;
  for (int i = 0; i <= n; ++i) {
    const double si = L * i / n;
    while (j + 2 < s.size() && s[j + 1] < si) ++j;
    const double seg = s[j + 1] - s[j];
    const double t = seg > 0 ? std::clamp((si - s[j]) / seg, 0.0, 1.0) : 0.0;
    nx.push_back((1 - t) * x[j] + t * x[j + 1]);
    nr.push_back((1 - t) * r[j] + t * r[j + 1]);
  }
  nx.front() = x.front(), nx.back() = x.back();
  x = std::move(nx), r = std::move(nr);
}

// any unit vector perpendicular to t (deterministic)
Eigen::Vector3d perpendicular(const Eigen::Vector3d& t) {
  Eigen::Vector3d a = std::abs(t.x()) < 0.6 ? Eigen::Vector3d::UnitX()
                      : (std::abs(t.y()) < 0.6 ? Eigen::Vector3d::UnitY() : Eigen::Vector3d::UnitZ());
  return (a - a.dot(t) * t).normalized();
}

// central-difference unit tangents over +-w(i) points
std::vector<Eigen::Vector3d> tangents(const std::vector<Eigen::Vector3d>& x, const std::vector<double>& span,
                                      double step) {
  const int n = static_cast<int>(x.size());
  std::vector<Eigen::Vector3d> t(n);
  for (int i = 0; i < n; ++i) {
    const int w = std::max(1, static_cast<int>(std::lround(span[i] / step)));
    const int a = std::max(0, i - w), b = std::min(n - 1, i + w);
    Eigen::Vector3d d = x[b] - x[a];
    if (d.norm() == 0) d = n > 1 ? Eigen::Vector3d(x[n - 1] - x[0]) : Eigen::Vector3d::UnitZ();
    t[i] = d.normalized();
  }
  return t;
}

// Gaussian smoothing along the points, sigma(i) in points, symmetric window
// truncated at the ends; `fixed` points keep their values.
template <class T>
std::vector<T> smooth(const std::vector<T>& v, const std::vector<double>& sigma, const std::vector<char>& fixed) {
  const int n = static_cast<int>(v.size());
  std::vector<T> out = v;
  for (int i = 0; i < n; ++i) {
    if (fixed[i] || sigma[i] <= 0) continue;
    const int w = std::min({static_cast<int>(std::ceil(3 * sigma[i])), i, n - 1 - i});
    if (w <= 0) continue;
    T acc = v[i] * 0.0;
    double ws = 0;
    for (int k = -w; k <= w; ++k) {
      const double g = std::exp(-0.5 * k * k / (sigma[i] * sigma[i]));
      acc = acc + v[i + k] * g;
      ws += g;
    }
    out[i] = acc / ws;
  }
  return out;
}

struct Section {
  bool ok = false;
  Eigen::Vector3d offset{0, 0, 0};
  double r = 0;
};

// Cross-section of the vessel in the plane through c normal to t: rays to the
// boundary (0.5 level of the trilinear tissue indicator), a least-squares fit
// d(phi) = r + a cos phi + b sin phi after dropping rays that leave through a
// neighbouring vessel or the volume; (a, b) moves the point to the centre.
Section fit_section(const Grid& g, const Eigen::Vector3d& c, const Eigen::Vector3d& t, double rho) {
  Section s;
  if (g.mask_at(c) < 0.5) return s;
  const int m = 32;
  const Eigen::Vector3d u = perpendicular(t), v = t.cross(u);
  // steps of one (smallest) voxel, then bisection to 1/128 of it: a single
  // background voxel across the ray keeps the indicator below 0.5 over about
  // a voxel, so no boundary is stepped over
  const double step = g.hmin();
  const double dmax = 2.5 * std::max(rho, 2 * g.hmin()) + 2 * g.hmax();
  // The march may start where the boundary can first be: every corner of the
  // cell around c + a dir lies within a + diag of c, and the voxel centres
  // nearer to c than its distance to the background (at least rho - diag, rho
  // being interpolated) are tissue or outside the volume; so below
  // rho - 2 diag the indicator is 1 or the ray has left the (convex) volume,
  // which it then never re-enters. The samples stay those of a march from 0.
  const double diag = std::sqrt(g.h[0] * g.h[0] + g.h[1] * g.h[1] + g.h[2] * g.h[2]);
  const int k0 = std::max(1, static_cast<int>(std::floor((rho - 2 * diag) / step)));
  double d[m];
  bool ok[m];
  for (int j = 0; j < m; ++j) {
    const double phi = 2 * kPi * j / m;
    const Eigen::Vector3d dir = std::cos(phi) * u + std::sin(phi) * v;
    ok[j] = false;
    double prev = (k0 - 1) * step;
    for (int ka = k0; ka * step <= dmax; ++ka) {
      const double a = ka * step;
      const double val = g.mask_at(c + a * dir);
      if (val < 0) break;  // left the volume: unknown
      if (val < 0.5) {
        double lo = prev, hi = a;
        for (int it = 0; it < 7; ++it) {
          const double mid = 0.5 * (lo + hi);
          const double mv = g.mask_at(c + mid * dir);
          (mv >= 0.5 ? lo : hi) = mid;
        }
        d[j] = 0.5 * (lo + hi);
        ok[j] = true;
        break;
      }
      prev = a;
    }
  }
  std::vector<double> valid;
  for (int j = 0; j < m; ++j)
    if (ok[j]) valid.push_back(d[j]);
  if (static_cast<int>(valid.size()) < m / 2) return s;
  std::nth_element(valid.begin(), valid.begin() + valid.size() / 2, valid.end());
  const double med = valid[valid.size() / 2];
  Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
  Eigen::Vector3d rhs = Eigen::Vector3d::Zero();
  int used = 0;
  for (int j = 0; j < m; ++j) {
    if (!ok[j] || d[j] > 1.5 * med + g.hmin() || d[j] < 0.5 * med - g.hmin()) continue;
    const double phi = 2 * kPi * j / m;
    const Eigen::Vector3d row(1, std::cos(phi), std::sin(phi));
    A += row * row.transpose();
    rhs += row * d[j];
    ++used;
  }
  if (used < (3 * m) / 4) return s;
  const Eigen::Vector3d p = A.ldlt().solve(rhs);
  if (!(p(0) > 0) || !std::isfinite(p(0))) return s;
  // a section that is not a circle (a junction, a neighbour, a kink) is no
  // measure of the centre or the radius
  double ss = 0;
  for (int j = 0; j < m; ++j) {
    if (!ok[j] || d[j] > 1.5 * med + g.hmin() || d[j] < 0.5 * med - g.hmin()) continue;
    const double phi = 2 * kPi * j / m;
    const double e = d[j] - (p(0) + p(1) * std::cos(phi) + p(2) * std::sin(phi));
    ss += e * e;
  }
  if (std::sqrt(ss / used) > 0.1 * p(0) + 0.35 * g.hmin()) return s;
  s.ok = true;
  s.r = p(0);
  s.offset = p(1) * u + p(2) * v;
  if (s.offset.norm() > 0.5 * s.r) s.offset *= 0.5 * s.r / s.offset.norm();
  return s;
}

}  // namespace

namespace {

// ---- junction regions -------------------------------------------------------------

struct Zone {
  std::vector<int> sep;    // per child: index where the spheres stop overlapping
  std::vector<int> start;  // per child: index where the child's tube starts
  int q = 0;               // parent index where its tube ends
};

double inscribed(const Grid& g, const Eigen::Vector3d& p) { return std::max(g.dt_at(p) - 0.5 * g.hmin(), 0.5 * g.hmin()); }

// sphere of child point i apart from every sibling sphere by `gap` (m, relative to the mean radius)
bool apart(const Grid& g, const Forest& f, const Junction& J, int ci, int i, double gap) {
  const Branch& c = f.branches[J.children[ci]];
  const double ri = inscribed(g, c.x[i]);
  for (std::size_t k = 0; k < J.children.size(); ++k) {
    if (static_cast<int>(k) == ci) continue;
    const Branch& o = f.branches[J.children[k]];
    for (std::size_t j = 0; j < o.x.size(); j += 1) {
      const double rj = inscribed(g, o.x[j]);
      if ((c.x[i] - o.x[j]).norm() < ri + rj + gap * 0.5 * (ri + rj)) return false;
    }
  }
  return true;
}

Zone find_zone(const Grid& g, const Forest& f, const Junction& J, double patch_gap) {
  Zone z;
  std::vector<Eigen::Vector3d> sep_pts;
  std::vector<double> sep_r;
  for (std::size_t ci = 0; ci < J.children.size(); ++ci) {
    const Branch& c = f.branches[J.children[ci]];
    const int n = static_cast<int>(c.x.size());
    int s = n - 1;
    for (int i = 1; i < n; ++i)
      if (apart(g, f, J, static_cast<int>(ci), i, 0)) {
        s = i;
        break;
      }
    int p = n - 1;
    for (int i = s; i < n; ++i)
      if (apart(g, f, J, static_cast<int>(ci), i, patch_gap)) {
        p = i;
        break;
      }
    // leave room for the tube of a short leaf
    p = std::min(p, std::max(1, n - 2));
    s = std::min(s, p);
    z.sep.push_back(s);
    z.start.push_back(p);
    sep_pts.push_back(c.x[s]);
    sep_r.push_back(inscribed(g, c.x[s]));
  }
  const Branch& P = f.branches[J.parent];
  const int n = static_cast<int>(P.x.size());
  int q = 0;
  for (int i = n - 2; i >= 0; --i) {
    const double ri = inscribed(g, P.x[i]);
    bool ok = true;
    for (std::size_t k = 0; k < sep_pts.size(); ++k)
      if ((P.x[i] - sep_pts[k]).norm() < ri + sep_r[k]) ok = false;
    if (ok) {
      q = i;
      break;
    }
  }
  z.q = q;
  return z;
}

// Merges the junction at the end of internal branch e into the one at its
// start: e's children become children of e's parent and start at e's start.
void merge_into_parent(Forest& f, int e) {
  Branch& E = f.branches[e];
  const int p = E.parent;
  Junction* jp = nullptr;
  Junction* je = nullptr;
  for (Junction& J : f.junctions) {
    if (J.parent == p) jp = &J;
    if (J.parent == e) je = &J;
  }
  for (int c : je->children) {
    Branch& C = f.branches[c];
    std::vector<Eigen::Vector3d> x = E.x;
    std::vector<double> r = E.r, rho = E.rho;
    x.insert(x.end(), C.x.begin() + 1, C.x.end());
    r.insert(r.end(), C.r.begin() + 1, C.r.end());
    rho.insert(rho.end(), C.rho.begin() + 1, C.rho.end());
    C.x = std::move(x), C.r = std::move(r), C.rho = std::move(rho);
    C.parent = p;
  }
  // e's place in the parent's children goes to e's children
  auto replace = [&](std::vector<int>& v) {
    auto it = std::find(v.begin(), v.end(), e);
    const std::ptrdiff_t at = it - v.begin();
    v.erase(it);
    v.insert(v.begin() + at, je->children.begin(), je->children.end());
  };
  replace(jp->children);
  replace(f.branches[p].children);
  // drop e and its junction, renumber
  const std::vector<int> kids = je->children;
  f.junctions.erase(f.junctions.begin() + (je - f.junctions.data()));
  std::vector<int> map(f.branches.size());
  for (int i = 0, k = 0; i < static_cast<int>(f.branches.size()); ++i) map[i] = i == e ? -1 : k++;
  f.branches.erase(f.branches.begin() + e);
  for (Branch& b : f.branches) {
    if (b.parent >= 0) b.parent = map[b.parent];
    for (int& c : b.children) c = map[c];
  }
  for (Junction& J : f.junctions) {
    J.parent = map[J.parent];
    for (int& c : J.children) c = map[c];
  }
  (void)kids;
}

// Removes branch e, a leaf (no children), from its junction and renumbers.
// Its junction keeps at least two children (the caller's bound).
void drop_leaf(Forest& f, int e) {
  const int p = f.branches[e].parent;
  for (Junction& J : f.junctions)
    if (J.parent == p) J.children.erase(std::find(J.children.begin(), J.children.end(), e));
  auto& pc = f.branches[p].children;
  pc.erase(std::find(pc.begin(), pc.end(), e));
  std::vector<int> map(f.branches.size());
  for (int i = 0, k = 0; i < static_cast<int>(f.branches.size()); ++i) map[i] = i == e ? -1 : k++;
  f.branches.erase(f.branches.begin() + e);
  for (Branch& b : f.branches) {
    if (b.parent >= 0) b.parent = map[b.parent];
    for (int& c : b.children) c = map[c];
  }
  for (Junction& J : f.junctions) {
    J.parent = map[J.parent];
    for (int& c : J.children) c = map[c];
  }
}

// Every junction with more than o.max_children children: its shortest leaf
// children are dropped (o.prune_excess_children) until it fits, counted in
// f.children_pruned. Refused with the position when that is off or when too
// few of the children are leaves. Returns whether anything was dropped.
bool prune_excess_children(Forest& f, const VesselOptions& o) {
  for (const Junction& J : f.junctions) {
    const int n = static_cast<int>(J.children.size());
    if (n <= o.max_children) continue;
    std::vector<std::pair<double, int>> leaves;  // (length, branch)
    for (int c : J.children)
      if (f.branches[c].children.empty()) leaves.push_back({arc(f.branches[c].x).back(), c});
    if (!o.prune_excess_children || static_cast<int>(leaves.size()) < n - o.max_children) {
      const Eigen::Vector3d x = 1e3 * f.branches[J.parent].x.back();
      std::ostringstream m;
      m.precision(4);
      m << "a junction with " << n << " children at (" << x.x() << ", " << x.y() << ", " << x.z() << ") mm: at most "
        << o.max_children << " are supported"
        << (o.prune_excess_children ? " (too few of them end freely to be dropped)" : "");
      throw Error("", m.str());
    }
    std::sort(leaves.begin(), leaves.end());
    std::vector<int> drop;
    for (int i = 0; i < n - o.max_children; ++i) {
      drop.push_back(leaves[static_cast<std::size_t>(i)].second);
      f.pruned_length_m += leaves[static_cast<std::size_t>(i)].first;
    }
    std::sort(drop.rbegin(), drop.rend());  // highest index first: the others keep theirs
    for (int e : drop) drop_leaf(f, e);
    f.children_pruned += static_cast<int>(drop.size());
    return true;
  }
  return false;
}

}  // namespace

void refine_centrelines(const Grid& g, const VesselOptions& o, Forest& f) {
  const double step = 0.5 * g.hmin();
  // ---- resample the voxel paths -----------------------------------------------------
  for (Branch& b : f.branches) {
    // a light moving average takes the voxel staircase out; ends stay
    std::vector<Eigen::Vector3d> x = b.x;
    for (int i = 1; i + 1 < static_cast<int>(b.x.size()); ++i) {
      const int w = std::min({2, i, static_cast<int>(b.x.size()) - 1 - i});
      Eigen::Vector3d acc = Eigen::Vector3d::Zero();
      for (int k = -w; k <= w; ++k) acc += b.x[i + k];
      x[i] = acc / (2 * w + 1);
    }
    b.x = std::move(x);
    resample(b.x, b.rho, step);
    b.r = b.rho;
  }
  // ---- re-centre on cross-sections ----------------------------------------------------
  // junction ends are held (they are rebuilt below); vessel ends move sideways
  struct Ref {
    int b, i;
  };
  std::vector<Ref> refs;
  for (int bi = 0; bi < static_cast<int>(f.branches.size()); ++bi)
    for (int i = 0; i < static_cast<int>(f.branches[bi].x.size()); ++i) refs.push_back({bi, i});
  std::vector<Section> sec;
  for (int iter = 0; iter < 3; ++iter) {
    refs.clear();
    for (int bi = 0; bi < static_cast<int>(f.branches.size()); ++bi)
      for (int i = 0; i < static_cast<int>(f.branches[bi].x.size()); ++i) refs.push_back({bi, i});
    std::vector<std::vector<Eigen::Vector3d>> tan(f.branches.size());
    for (std::size_t bi = 0; bi < f.branches.size(); ++bi) {
      const Branch& b = f.branches[bi];
      std::vector<double> span(b.x.size());
      for (std::size_t i = 0; i < b.x.size(); ++i) span[i] = 0.5 * std::max(g.dt_at(b.x[i]), 2 * g.hmin());
      tan[bi] = tangents(b.x, span, step);
    }
    sec.assign(refs.size(), Section{});
    tbb::parallel_for(std::size_t(0), refs.size(), [&](std::size_t k) {
      const Branch& b = f.branches[refs[k].b];
      const int i = refs[k].i;
      sec[k] = fit_section(g, b.x[i], tan[refs[k].b][i], g.dt_at(b.x[i]));
    });
    std::size_t k = 0;
    for (Branch& b : f.branches) {
      const int n = static_cast<int>(b.x.size());
      std::vector<char> fixed(n, 0);
      if (!b.start_root) fixed[0] = 1;
      if (!b.end_leaf) fixed[n - 1] = 1;
      std::vector<double> rr(n, 0);
      std::vector<char> ok(n, 0);
      for (int i = 0; i < n; ++i, ++k) {
        if (!sec[k].ok) continue;
        ok[i] = 1;
        rr[i] = sec[k].r;
        if (!fixed[i]) b.x[i] += sec[k].offset;
      }
      // radii: fitted where the section was clean, interpolated elsewhere,
      // the inscribed radius where no section was clean
      int first = -1;
      for (int i = 0; i < n; ++i)
        if (ok[i]) {
          if (first < 0)
            for (int j = 0; j < i; ++j) rr[j] = rr[i];
          else
            for (int j = first + 1; j < i; ++j) rr[j] = rr[first] + (rr[i] - rr[first]) * (j - first) / (i - first);
          first = i;
        }
      if (first < 0)
        for (int i = 0; i < n; ++i) rr[i] = inscribed(g, b.x[i]);
      else
        for (int j = first + 1; j < n; ++j) rr[j] = rr[first];
      std::vector<double> sig(n), sig_r(n);
      for (int i = 0; i < n; ++i) sig[i] = 0.5 * rr[i] / step, sig_r[i] = rr[i] / step;
      b.x = smooth(b.x, sig, fixed);
      b.r = smooth(rr, sig_r, std::vector<char>(n, 0));
      resample(b.x, b.r, step);
    }
  }
  for (Branch& b : f.branches) {
    b.rho.resize(b.x.size());
    for (std::size_t i = 0; i < b.x.size(); ++i) b.rho[i] = inscribed(g, b.x[i]);
  }

  // ---- junction regions; merge junctions whose regions overlap -----------------------
  std::vector<Zone> zones;
  for (bool again = true; again;) {
    again = false;
    zones.clear();
    for (const Junction& J : f.junctions) zones.push_back(find_zone(g, f, J, o.patch_gap));
    for (std::size_t ji = 0; ji < f.junctions.size() && !again; ++ji) {
      const int p = f.junctions[ji].parent;
      const Branch& P = f.branches[p];
      if (P.start_root) continue;
      // the junction at p's start
      for (std::size_t jk = 0; jk < f.junctions.size(); ++jk) {
        const auto& kids = f.junctions[jk].children;
        const auto it = std::find(kids.begin(), kids.end(), p);
        if (it == kids.end()) continue;
        const int start = zones[jk].start[it - kids.begin()];
        const std::vector<double> s = arc(P.x);
        const double room = s[zones[ji].q] - s[start];
        if (room < 0.5 * P.rho[start]) {
          merge_into_parent(f, p);
          again = true;
        }
        break;
      }
    }
    // a junction with more children than the tube can join loses its
    // shortest leaves (noisy labels grow short side branches near a junction;
    // two merged junctions add theirs up); the zones are then found again
    if (!again) again = prune_excess_children(f, o);
  }

  // ---- rebuild each junction region from the clean parts around it -----------------
  // deepest first: a junction rewrites its parent's tail and its children's
  // heads, so indices found above stay valid; the parent's tube end is kept as
  // the arc length from there to the branch's end
  std::vector<double> tail(f.branches.size(), 0);
  for (Branch& b : f.branches) b.tube_a = 0;
  for (std::size_t jr = f.junctions.size(); jr-- > 0;) {
    const std::size_t ji = jr;
    const Junction& J = f.junctions[ji];
    Zone z = zones[ji];
    Branch& P = f.branches[J.parent];
    const std::vector<double> sp = arc(P.x);
    const Eigen::Vector3d xj = P.x.back();
    // the children's axes back from their first clean point
    std::vector<Eigen::Vector3d> tc;
    for (std::size_t ci = 0; ci < J.children.size(); ++ci) {
      const Branch& C = f.branches[J.children[ci]];
      const int i = z.start[ci];
      const int n = static_cast<int>(C.x.size());
      const int w = std::max(2, static_cast<int>(std::lround(C.rho[i] / step)));
      Eigen::Vector3d t = C.x[std::min(n - 1, i + w)] - C.x[i];
      if (t.norm() == 0) t = C.x[i] - C.x[0];
      if (t.norm() == 0) t = P.x.back() - P.x.front();
      tc.push_back(t.normalized());
    }
    // the bifurcation point: least-squares meeting point of the parent's axis
    // (forward from its last clean point Q) and the children's axes; Q then
    // moves back to one parent radius before the bifurcation point, and the
    // meeting point is found again from there
    // Q stays after the parent's own head region (its start as a child of the
    // junction above, rewritten later): moved back over it, the tail's rewrite
    // cut the head's index off the branch (noisy labels' short branches: an
    // internal error, vector::_M_range_insert, at 8-bit noise 24)
    int q_min = 0;
    if (!P.start_root)
      for (std::size_t jk = 0; jk < f.junctions.size(); ++jk) {
        const auto& kids = f.junctions[jk].children;
        const auto it = std::find(kids.begin(), kids.end(), J.parent);
        if (it != kids.end()) q_min = zones[jk].start[static_cast<std::size_t>(it - kids.begin())] + 1;
      }
    Eigen::Vector3d xb = xj, tq;
    bool sane = false;
    for (int pass = 0; pass < 2; ++pass) {
      const int w = std::max(2, static_cast<int>(std::lround(P.rho[z.q] / step)));
      tq = P.x[z.q] - P.x[std::max(0, z.q - w)];
      if (tq.norm() == 0) tq = P.x.back() - P.x.front();
      tq.normalize();
      Eigen::Matrix3d A = 1e-3 * Eigen::Matrix3d::Identity();
      Eigen::Vector3d rhs = 1e-3 * xj;
      auto line = [&](const Eigen::Vector3d& a, const Eigen::Vector3d& d) {
        const Eigen::Matrix3d M = Eigen::Matrix3d::Identity() - d * d.transpose();
        A += M;
        rhs += M * a;
      };
      line(P.x[z.q], tq);
      for (std::size_t ci = 0; ci < J.children.size(); ++ci) line(f.branches[J.children[ci]].x[z.start[ci]], tc[ci]);
      xb = A.ldlt().solve(rhs);
      sane = (xb - xj).norm() < 3 * P.rho.back() + 2 * g.hmax();
      for (std::size_t ci = 0; ci < J.children.size(); ++ci)
        sane = sane && (f.branches[J.children[ci]].x[z.start[ci]] - xb).dot(tc[ci]) > 0;
      if (!sane) break;
      // Q at least one radius before B along the parent, and half a radius
      // behind every child's first ring (a child turning sharply off a wide
      // parent reaches back along the parent's axis by r_c sin(angle); a
      // parent ring level with it left the patch no room and it folded)
      const double sb = sp[z.q] + (xb - P.x[z.q]).dot(tq);
      const double rq = std::max(P.r[z.q], P.rho[z.q]);
      double want = sb - rq;
      for (std::size_t ci = 0; ci < J.children.size(); ++ci) {
        const Branch& C = f.branches[J.children[ci]];
        const int i = z.start[ci];
        const double c = std::clamp(tc[ci].dot(tq), -1.0, 1.0);
        const double back = (C.x[i] - xb).dot(tq) - C.r[i] * std::sqrt(1 - c * c);
        want = std::min(want, sb + back - 0.5 * rq);
      }
      int q = z.q;
      while (q > q_min && sp[q] > want) --q;
      if (q == z.q) break;
      z.q = q;
    }
    sane = sane && (xb - P.x[z.q]).dot(tq) > 0;
    if (!sane) xb = xj;
    const Eigen::Vector3d xq = P.x[z.q];
    // cubic Hermite pieces: parent Q -> B, each child B -> P_c; the tangent
    // at the far end of each is the parabola's (2 chord - known tangent)
    auto hermite = [&](const Eigen::Vector3d& a, const Eigen::Vector3d& ta, const Eigen::Vector3d& bb,
                       const Eigen::Vector3d& tb, double ra, double rb, std::vector<Eigen::Vector3d>& xs,
                       std::vector<double>& rs) {
      const double L = (bb - a).norm();
      const int n = std::max(1, static_cast<int>(std::ceil(L / step)));
      for (int i = 0; i <= n; ++i) {
        const double s = static_cast<double>(i) / n, s2 = s * s, s3 = s2 * s;
        xs.push_back((2 * s3 - 3 * s2 + 1) * a + (s3 - 2 * s2 + s) * L * ta + (-2 * s3 + 3 * s2) * bb +
                     (s3 - s2) * L * tb);
        rs.push_back(ra + (rb - ra) * s);
      }
    };
    {
      const double L = (xb - xq).norm();
      Eigen::Vector3d tb = L > 0 ? (2 * (xb - xq) / L - tq) : tq;
      tb = tb.norm() > 1e-9 ? tb.normalized() : tq;
      std::vector<Eigen::Vector3d> xs;
      std::vector<double> rs;
      hermite(xq, tq, xb, tb, P.r[z.q], P.r[z.q], xs, rs);
      P.x.resize(z.q);
      P.r.resize(z.q);
      P.x.insert(P.x.end(), xs.begin(), xs.end());
      P.r.insert(P.r.end(), rs.begin(), rs.end());
      tail[J.parent] = arc(xs).back();
    }
    const double rb = P.r.back();
    for (std::size_t ci = 0; ci < J.children.size(); ++ci) {
      Branch& C = f.branches[J.children[ci]];
      const int i = z.start[ci];
      const Eigen::Vector3d xp = C.x[i];
      const double L = (xp - xb).norm();
      Eigen::Vector3d ta = L > 0 ? (2 * (xp - xb) / L - tc[ci]) : tc[ci];
      ta = ta.norm() > 1e-9 ? ta.normalized() : tc[ci];
      std::vector<Eigen::Vector3d> xs;
      std::vector<double> rs;
      hermite(xb, ta, xp, tc[ci], rb, C.r[i], xs, rs);
      const double la = arc(xs).back();
      xs.insert(xs.end(), C.x.begin() + i + 1, C.x.end());
      rs.insert(rs.end(), C.r.begin() + i + 1, C.r.end());
      C.x = std::move(xs), C.r = std::move(rs);
      C.tube_a = la;
    }
  }

  // ---- the children's first rings apart ------------------------------------------------
  // The tube starts where the inscribed spheres are patch_gap apart (find_zone),
  // but its rings have the section's radius, up to half a voxel more: the first
  // rings of a narrow Y on coarse slices overlapped at the crotch and the patch
  // folded there (the phantom's artery at 0.45 x 0.45 x 1.5 mm: 37
  // self-intersecting face pairs on exact labels). Overlapping first rings move
  // down their branches, a step at a time, until their discs are patch_gap
  // apart; the centreline stays as it is.
  auto at_arc = [](const Branch& b, const std::vector<double>& s, double a, double* r) {
    const auto it = std::upper_bound(s.begin(), s.end(), a);
    const std::size_t k = std::min<std::size_t>(std::max<std::ptrdiff_t>(it - s.begin(), 1), s.size() - 1);
    const double d = s[k] - s[k - 1], t = d > 0 ? std::clamp((a - s[k - 1]) / d, 0.0, 1.0) : 0.0;
    *r = b.r[k - 1] + t * (b.r[k] - b.r[k - 1]);
    return Eigen::Vector3d(b.x[k - 1] + t * (b.x[k] - b.x[k - 1]));
  };
  for (const Junction& J : f.junctions) {
    const std::size_t nc = J.children.size();
    std::vector<std::vector<double>> s(nc);
    for (std::size_t c = 0; c < nc; ++c) s[c] = arc(f.branches[J.children[c]].x);
    for (int round = 0; round < 10000; ++round) {
      std::vector<char> move(nc, 0);
      for (std::size_t a = 0; a < nc; ++a)
        for (std::size_t b = a + 1; b < nc; ++b) {
          const Branch& A = f.branches[J.children[a]];
          const Branch& B = f.branches[J.children[b]];
          double ra = 0, rb = 0;
          const Eigen::Vector3d pa = at_arc(A, s[a], A.tube_a, &ra), pb = at_arc(B, s[b], B.tube_a, &rb);
          if ((pa - pb).norm() < (ra + rb) * (1 + 0.5 * o.patch_gap)) move[a] = move[b] = 1;
        }
      bool moved = false;
      for (std::size_t c = 0; c < nc; ++c) {
        Branch& C = f.branches[J.children[c]];
        // leave room for the tube of a short branch (a parent ends its tube
        // `tail` before its own junction)
        const double end = s[c].back() - (C.end_leaf ? 0.0 : tail[static_cast<std::size_t>(J.children[c])]);
        const double limit = std::max(C.tube_a, end - 2 * step);
        if (move[c] && C.tube_a + step <= limit) C.tube_a += step, moved = true;
      }
      if (!moved) break;
    }
  }

  // ---- open ends reach the border; tube intervals --------------------------------------
  // An open end: the section there is cut by the border, so the last part of
  // the skeleton (within a radius of the border) is replaced by the straight
  // continuation of the vessel's axis up to the border plane it meets.
  const double org[3] = {g.origin(0) - g.ox * g.h[0], g.origin(1) - g.oy * g.h[1], g.origin(2) - g.oz * g.h[2]};
  const int vn[3] = {g.vx, g.vy, g.vz};
  auto border_distance = [&](const Eigen::Vector3d& p) {
    double d = 1e300;
    for (int a = 0; a < 3; ++a) d = std::min({d, p(a) - org[a], org[a] + (vn[a] - 1) * g.h[a] - p(a)});
    return d;
  };
  // Returns the border plane the end now lies on (axis, coordinate), or axis -1.
  auto extend = [&](std::vector<Eigen::Vector3d>& x, std::vector<double>& r, bool at_start) -> std::pair<int, double> {
    if (x.size() < 4) return {-1, 0.0};
    if (at_start) std::reverse(x.begin(), x.end()), std::reverse(r.begin(), r.end());
    const std::size_t keep_min = x.size() / 2;
    while (x.size() > keep_min && border_distance(x.back()) < std::max(r.back(), 2 * g.hmax())) x.pop_back(), r.pop_back();
    const int n = static_cast<int>(x.size());
    const int w = std::min(n - 1, std::max(2, static_cast<int>(std::lround(r.back() / step))));
    const Eigen::Vector3d t = (x.back() - x[n - 1 - w]).normalized();
    double best = 1e300;
    std::pair<int, double> on{-1, 0.0};
    for (int d = 0; d < 3; ++d) {
      if (std::abs(t(d)) < 1e-6) continue;
      const double plane = t(d) > 0 ? org[d] + (vn[d] - 1) * g.h[d] : org[d];
      const double lam = (plane - x.back()(d)) / t(d);
      if (lam >= 0 && lam < best) best = lam, on = {d, plane};
    }
    if (!(best <= 4 * r.back() + 3 * g.hmax())) on = {-1, 0.0};
    if (best <= 4 * r.back() + 3 * g.hmax() && best > 1e-9) {
      const Eigen::Vector3d e = x.back() + best * t;
      const int k = std::max(1, static_cast<int>(std::ceil(best / step)));
      const Eigen::Vector3d a = x.back();
      const double ra = r.back();
      for (int i = 1; i <= k; ++i) x.push_back(a + (e - a) * (static_cast<double>(i) / k)), r.push_back(ra);
    }
    if (at_start) std::reverse(x.begin(), x.end()), std::reverse(r.begin(), r.end());
    return on;
  };
  for (std::size_t bi = 0; bi < f.branches.size(); ++bi) {
    Branch& b = f.branches[bi];
    if (b.start_root && b.start_open) std::tie(b.start_axis, b.start_plane) = extend(b.x, b.r, true);
    if (b.end_leaf && b.end_open) std::tie(b.end_axis, b.end_plane) = extend(b.x, b.r, false);
    b.tube_b = arc(b.x).back() - (b.end_leaf ? 0.0 : tail[bi]);
    b.rho.resize(b.x.size());
    for (std::size_t i = 0; i < b.x.size(); ++i) b.rho[i] = inscribed(g, b.x[i]);
  }
}

}  // namespace orthosim::vessels_detail
