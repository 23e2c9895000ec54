// Clean-up kernels: anatomical order, the 3-D rank filter, run-length runs
// with 2-D components, and the streamed 3-D component tracker.
#include "libmodel/segment/detail.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <map>
#include <numeric>

namespace orthosim::segment_detail {

namespace {

// Union-find over small index ranges (runs of one slice).
struct SmallUf {
  std::vector<std::uint32_t> p;
  void reset(std::size_t n) {
    p.resize(n);
    std::iota(p.begin(), p.end(), 0u);
  }
  std::uint32_t find(std::uint32_t a) {
    while (p[a] != a) a = p[a] = p[p[a]];
    return a;
  }
  void unite(std::uint32_t a, std::uint32_t b) {
    a = find(a), b = find(b);
    if (a == b) return;
    if (a > b) std::swap(a, b);
    p[b] = a;  // the smaller index is the root: scan order decides
  }
};

struct Span {
  std::int32_t x0, x1;
};

// Calls f(label, k) for each of the 26 neighbours of pixel (x, y) of the
// middle plane that exist (planes[p] null: no such plane; the image's edge
// clips), k = p * 9 + (dy + 1) * 3 + dx + 1 its place in a 3 x 3 x 3 block.
template <class F>
void for_each_neighbour(const std::uint8_t* const planes[3], int x, int y, int nx, int ny, F&& f) {
  for (int p = 0; p < 3; ++p) {
    const std::uint8_t* pl = planes[p];
    if (!pl) continue;
    for (int dy = -1; dy <= 1; ++dy) {
      const int yy = y + dy;
      if (yy < 0 || yy >= ny) continue;
      for (int dx = -1; dx <= 1; ++dx) {
        const int xx = x + dx;
        if (xx < 0 || xx >= nx || (p == 1 && dx == 0 && dy == 0)) continue;
        f(pl[static_cast<std::size_t>(yy) * nx + xx], p * 9 + (dy + 1) * 3 + dx + 1);
      }
    }
  }
}

}  // namespace

// ---- smoothness prior ----------------------------------------------------------

Smoother make_smoother(const ColourModel& m, double beta, const std::array<double, 3>& spacing) {
  Smoother s;
  s.beta = beta;
  const double h = std::min({spacing[0], spacing[1], spacing[2]});
  for (int dz = -1; dz <= 1; ++dz)
    for (int dy = -1; dy <= 1; ++dy)
      for (int dx = -1; dx <= 1; ++dx) {
        const double r = std::sqrt(dx * dx * spacing[0] * spacing[0] + dy * dy * spacing[1] * spacing[1] +
                                   dz * dz * spacing[2] * spacing[2]);
        s.w[static_cast<std::size_t>((dz + 1) * 9 + (dy + 1) * 3 + dx + 1)] = r > 0 ? h / r : 0;
      }
  s.centres_of.assign(256, {});
  for (std::size_t i = 0; i < m.centres.size(); ++i)
    s.centres_of[static_cast<std::size_t>(m.centres[i].label)].push_back(static_cast<int>(i));
  return s;
}

void uniform_3x3(const std::uint8_t* c, int nx, int ny, std::vector<std::uint8_t>& u) {
  const std::size_t n = static_cast<std::size_t>(nx) * ny;
  // row[i]: pixel i and its row neighbours agree; then the rows above and below
  thread_local std::vector<std::uint8_t> row;
  row.resize(n);
  for (int y = 0; y < ny; ++y) {
    const std::uint8_t* cr = c + static_cast<std::size_t>(y) * nx;
    std::uint8_t* rr = row.data() + static_cast<std::size_t>(y) * nx;
    rr[0] = nx == 1 || cr[1] == cr[0];
    for (int x = 1; x + 1 < nx; ++x) rr[x] = static_cast<std::uint8_t>((cr[x - 1] == cr[x]) & (cr[x + 1] == cr[x]));
    if (nx > 1) rr[nx - 1] = cr[nx - 2] == cr[nx - 1];
  }
  u.assign(row.begin(), row.begin() + static_cast<std::ptrdiff_t>(n));
  for (int y = 0; y < ny; ++y) {
    const std::size_t r = static_cast<std::size_t>(y) * nx;
    std::uint8_t* ur = u.data() + r;
    const std::uint8_t* cr = c + r;
    if (y > 0) {
      const std::uint8_t *ca = cr - nx, *ra = row.data() + r - nx;
      for (int x = 0; x < nx; ++x) ur[x] &= static_cast<std::uint8_t>(ra[x] & (ca[x] == cr[x]));
    }
    if (y + 1 < ny) {
      const std::uint8_t *cb = cr + nx, *rb = row.data() + r + nx;
      for (int x = 0; x < nx; ++x) ur[x] &= static_cast<std::uint8_t>(rb[x] & (cb[x] == cr[x]));
    }
  }
}

bool changed_3x3(const std::uint8_t* a, const std::uint8_t* b, int nx, int ny, std::vector<std::uint8_t>& d,
                 std::vector<std::uint8_t>& rows) {
  const std::size_t n = static_cast<std::size_t>(nx) * ny;
  d.resize(n);  // only the rows flagged in `rows` are written (and read)
  rows.assign(static_cast<std::size_t>(ny), 0);
  if (std::memcmp(a, b, n) == 0) return false;
  // per row: the pixels that changed, dilated along the row (rows without a
  // change are not used); scratch reused by the thread (a fresh megabyte a
  // slice cost page faults)
  thread_local std::vector<std::uint8_t> row, row_any;
  row.resize(n);
  row_any.assign(static_cast<std::size_t>(ny), 0);
  for (int y = 0; y < ny; ++y) {
    const std::size_t r = static_cast<std::size_t>(y) * nx;
    if (std::memcmp(a + r, b + r, static_cast<std::size_t>(nx)) == 0) continue;
    row_any[static_cast<std::size_t>(y)] = 1;
    std::uint8_t* rr = row.data() + r;
    std::uint8_t left = 0, here = a[r] != b[r];
    for (int x = 0; x < nx; ++x) {
      const std::uint8_t right = x + 1 < nx ? static_cast<std::uint8_t>(a[r + x + 1] != b[r + x + 1]) : 0;
      rr[x] = static_cast<std::uint8_t>(left | here | right);
      left = here, here = right;
    }
  }
  // then across the rows
  for (int y = 0; y < ny; ++y) {
    const bool up = y > 0 && row_any[static_cast<std::size_t>(y - 1)], down = y + 1 < ny && row_any[static_cast<std::size_t>(y + 1)];
    if (!(up || down || row_any[static_cast<std::size_t>(y)])) continue;
    rows[static_cast<std::size_t>(y)] = 1;
    std::uint8_t* dr = d.data() + static_cast<std::size_t>(y) * nx;
    const std::uint8_t* rr = row.data() + static_cast<std::size_t>(y) * nx;
    if (row_any[static_cast<std::size_t>(y)])
      for (int x = 0; x < nx; ++x) dr[x] = rr[x];
    else
      std::memset(dr, 0, static_cast<std::size_t>(nx));
    if (up)
      for (int x = 0; x < nx; ++x) dr[x] |= rr[x - nx];
    if (down)
      for (int x = 0; x < nx; ++x) dr[x] |= rr[x + nx];
  }
  return true;
}

std::int64_t smooth_sweep(const Smoother& s, const ColourModel& m, const std::uint8_t* rgb, const SweepSlice& sp,
                          const SweepSlice& sc, const SweepSlice& sn, int nx, int ny, std::uint8_t* out) {
  std::int64_t changed = 0;
  const std::uint8_t *prev = sp.labels, *cur = sc.labels, *next = sn.labels;
  const std::uint8_t *uprev = sp.uniform, *ucur = sc.uniform, *unext = sn.uniform;
  const std::uint8_t* planes[3] = {prev, cur, next};
  std::array<std::uint8_t, 27> cand{};
  std::array<double, 27> cw{};
  for (int y = 0; y < ny; ++y) {
    const std::size_t r = static_cast<std::size_t>(y) * nx;
    // after the first sweep, a row without a change within reach keeps its labels
    if (sc.active && !(sc.active_rows[y] || (sp.active && sp.active_rows[y]) || (sn.active && sn.active_rows[y]))) {
      std::memcpy(out + r, cur + r, static_cast<std::size_t>(nx));
      continue;
    }
    for (int x = 0; x < nx; ++x) {
      const std::size_t i = r + x;
      const std::uint8_t l = cur[i];
      // a voxel none of whose neighbours changed in the last sweep keeps its
      // label, and so does one whose neighbours all share it (most voxels)
      if (sc.active && !((sc.active_rows[y] && sc.active[i]) || (sp.active && sp.active_rows[y] && sp.active[i]) ||
                         (sn.active && sn.active_rows[y] && sn.active[i]))) {
        out[i] = l;
        continue;
      }
      if (ucur[i] && (!prev || (uprev[i] && prev[i] == l)) && (!next || (unext[i] && next[i] == l))) {
        out[i] = l;
        continue;
      }
      // the neighbours' labels and weights, then the weight of each label
      // among them (summed per label afterwards: accumulating into a small
      // array as they come chained every add through memory)
      std::array<std::uint8_t, 26> nl{};
      std::array<double, 26> nw{};
      int n = 0;
      double total = 0;
      for_each_neighbour(planes, x, y, nx, ny, [&](std::uint8_t v, int k) {
        const double w = s.w[static_cast<std::size_t>(k)];
        nl[static_cast<std::size_t>(n)] = v;
        nw[static_cast<std::size_t>(n++)] = w;
        total += w;
      });
      int nc = 1;  // candidates: the voxel's own label first, then the others as met
      cand[0] = l;
      for (int j = 0; j < n; ++j) {
        const std::uint8_t v = nl[static_cast<std::size_t>(j)];
        int k = 0;
        while (k < nc && cand[static_cast<std::size_t>(k)] != v) ++k;
        if (k == nc) cand[static_cast<std::size_t>(nc++)] = v;
      }
      if (nc == 1) {
        out[i] = l;
        continue;
      }
      for (int k = 0; k < nc; ++k) {
        const std::uint8_t v = cand[static_cast<std::size_t>(k)];
        double sum = 0;
        for (int j = 0; j < n; ++j) sum += nl[static_cast<std::size_t>(j)] == v ? nw[static_cast<std::size_t>(j)] : 0.0;
        cw[static_cast<std::size_t>(k)] = sum;
      }
      const std::uint8_t* c = rgb + 3 * i;
      const std::array<double, 3> colour = m.coords(c[0], c[1], c[2]);
      std::uint8_t best = l;
      double be = 1e300;
      for (int k = 0; k < nc; ++k) {  // cand[0] is the voxel's own label: it wins ties
        const auto cl = cand[static_cast<std::size_t>(k)];
        double u = 1e300;
        for (int ci : s.centres_of[cl]) u = std::min(u, 0.5 * m.score(colour, static_cast<std::size_t>(ci)));
        const double e = u + s.beta * (total - cw[static_cast<std::size_t>(k)]);
        if (e < be) be = e, best = cl;
      }
      out[i] = best;
      changed += best != l;
    }
  }
  return changed;
}

// ---- anatomical order ----------------------------------------------------------

std::int64_t enforce_order(const LabelInfo& info, const ColourModel& m, const std::uint8_t* rgb, int nx, int ny,
                           std::uint8_t* labels) {
  std::int64_t changed = 0;
  std::vector<Span> spans;
  std::vector<std::uint32_t> row_start(static_cast<std::size_t>(ny) + 1);
  SmallUf uf;
  std::vector<std::uint8_t> outside;
  std::vector<std::int64_t> pocket;
  for (const auto& e : info.enclosers) {
    // spans of the complement of the region, row by row
    spans.clear();
    for (int y = 0; y < ny; ++y) {
      row_start[static_cast<std::size_t>(y)] = static_cast<std::uint32_t>(spans.size());
      const std::uint8_t* row = labels + static_cast<std::size_t>(y) * nx;
      int x = 0;
      while (x < nx) {
        while (x < nx && e.in_region[row[x]]) ++x;
        if (x == nx) break;
        const int x0 = x;
        while (x < nx && !e.in_region[row[x]]) ++x;
        spans.push_back({x0, x});
      }
    }
    row_start[static_cast<std::size_t>(ny)] = static_cast<std::uint32_t>(spans.size());
    if (spans.empty()) continue;
    // 4-connected components of the complement; those touching the border are outside
    uf.reset(spans.size());
    for (int y = 1; y < ny; ++y) {
      std::uint32_t i = row_start[static_cast<std::size_t>(y) - 1], ie = row_start[static_cast<std::size_t>(y)];
      std::uint32_t j = row_start[static_cast<std::size_t>(y)], je = row_start[static_cast<std::size_t>(y) + 1];
      while (i < ie && j < je) {
        if (spans[i].x0 < spans[j].x1 && spans[j].x0 < spans[i].x1) uf.unite(i, j);
        if (spans[i].x1 < spans[j].x1) ++i; else ++j;
      }
    }
    outside.assign(spans.size(), 0);
    for (int y = 0; y < ny; ++y)
      for (std::uint32_t k = row_start[static_cast<std::size_t>(y)]; k < row_start[static_cast<std::size_t>(y) + 1]; ++k)
        if (y == 0 || y == ny - 1 || spans[k].x0 == 0 || spans[k].x1 == nx) outside[uf.find(k)] = 1;
    // an enclosed pocket larger than the whole region is a real tissue ringed
    // by misclassified pixels of the region (muscle ringed by shaded fat taken
    // for bone), not a misclassified pocket: it is left as it is
    {
      std::int64_t region = static_cast<std::int64_t>(nx) * ny;
      pocket.assign(spans.size(), 0);
      for (std::uint32_t k = 0; k < spans.size(); ++k) {
        region -= spans[k].x1 - spans[k].x0;
        pocket[uf.find(k)] += spans[k].x1 - spans[k].x0;
      }
      for (std::uint32_t k = 0; k < spans.size(); ++k)
        if (uf.find(k) == k && !outside[k] && pocket[k] > region) outside[k] = 1;
    }
    // what the region encloses is reclassified among the region's tissues
    for (int y = 0; y < ny; ++y)
      for (std::uint32_t k = row_start[static_cast<std::size_t>(y)]; k < row_start[static_cast<std::size_t>(y) + 1]; ++k) {
        if (outside[uf.find(k)]) continue;
        std::uint8_t* row = labels + static_cast<std::size_t>(y) * nx;
        for (int x = spans[k].x0; x < spans[k].x1; ++x) {
          const std::uint8_t l = row[x];
          if (info.is_vessel[l]) continue;      // vessels cross layers
          if (l == 0 && !info.fill_holes) continue;  // holes are kept when not filled
          const std::size_t i = static_cast<std::size_t>(y) * nx + x;
          const std::uint8_t* p = rgb + 3 * i;
          const int c = m.nearest_allowed(m.coords(p[0], p[1], p[2]), e.allowed);
          if (c < 0) continue;
          const std::uint8_t nl = static_cast<std::uint8_t>(m.centres[static_cast<std::size_t>(c)].label);
          if (nl != l) row[x] = nl, ++changed;
        }
      }
  }
  return changed;
}

// ---- 3-D rank filter --------------------------------------------------------------

std::int64_t rank_filter(const LabelInfo& info, int support, const std::uint8_t* prev, const std::uint8_t* cur,
                         const std::uint8_t* next, int nx, int ny, std::uint8_t* out) {
  const std::size_t n = static_cast<std::size_t>(nx) * ny;
  if (support <= 0) {
    std::memcpy(out, cur, n);
    return 0;
  }
  std::int64_t changed = 0;
  const std::uint8_t* planes[3] = {prev, cur, next};
  for (int y = 0; y < ny; ++y) {
    const std::size_t r = static_cast<std::size_t>(y) * nx;
    for (int x = 0; x < nx; ++x) {
      const std::size_t i = r + x;
      const std::uint8_t l = cur[i];
      const int need = info.is_vessel[l] ? std::min(1, support) : support;
      // fast path: both row neighbours agree
      int cnt = (x > 0 && cur[i - 1] == l) + (x + 1 < nx && cur[i + 1] == l);
      if (cnt >= need) {
        out[i] = l;
        continue;
      }
      // the full 26-neighbourhood
      cnt = 0;
      std::uint8_t lab[26];
      int nl = 0;
      for_each_neighbour(planes, x, y, nx, ny, [&](std::uint8_t v, int) {
        lab[nl++] = v;
        cnt += v == l;
      });
      if (cnt >= need || nl == 0) {
        out[i] = l;
        continue;
      }
      // majority of the neighbours, ties to the smaller label
      std::sort(lab, lab + nl);
      std::uint8_t best = lab[0];
      int bestn = 0;
      for (int a = 0; a < nl;) {
        int b = a;
        while (b < nl && lab[b] == lab[a]) ++b;
        if (b - a > bestn) bestn = b - a, best = lab[a];
        a = b;
      }
      out[i] = best;
      changed += best != l;
    }
  }
  return changed;
}

// ---- runs -------------------------------------------------------------------------

void make_runs(const std::uint8_t* labels, int nx, int ny, SliceRuns& out) {
  out.nx = nx;
  out.ny = ny;
  out.runs.clear();
  out.row_start.assign(static_cast<std::size_t>(ny) + 1, 0);
  for (int y = 0; y < ny; ++y) {
    out.row_start[static_cast<std::size_t>(y)] = static_cast<std::uint32_t>(out.runs.size());
    const std::uint8_t* row = labels + static_cast<std::size_t>(y) * nx;
    int x = 0;
    while (x < nx) {
      const std::uint8_t l = row[x];
      const int x0 = x;
      while (x < nx && row[x] == l) ++x;
      out.runs.push_back({x0, x, 0, l});
    }
  }
  out.row_start[static_cast<std::size_t>(ny)] = static_cast<std::uint32_t>(out.runs.size());
  // components: same label, overlapping runs in consecutive rows
  SmallUf uf;
  uf.reset(out.runs.size());
  std::vector<std::array<std::int64_t, 3>> contacts;
  for (int y = 1; y < ny; ++y) {
    std::uint32_t i = out.row_start[static_cast<std::size_t>(y) - 1], ie = out.row_start[static_cast<std::size_t>(y)];
    std::uint32_t j = out.row_start[static_cast<std::size_t>(y)], je = out.row_start[static_cast<std::size_t>(y) + 1];
    while (i < ie && j < je) {
      const Run &a = out.runs[i], &b = out.runs[j];
      if (a.x0 < b.x1 && b.x0 < a.x1 && a.label == b.label) uf.unite(i, j);
      if (a.x1 < b.x1) ++i; else ++j;
    }
  }
  // number components in scan order of their first run
  std::vector<std::uint32_t> id(out.runs.size(), ~0u);
  out.n_comps = 0;
  out.comp_voxels.clear();
  out.comp_label.clear();
  out.comp_lateral.clear();
  for (int y = 0; y < ny; ++y)
    for (std::uint32_t k = out.row_start[static_cast<std::size_t>(y)]; k < out.row_start[static_cast<std::size_t>(y) + 1]; ++k) {
      const std::uint32_t root = uf.find(k);
      if (id[root] == ~0u) {
        id[root] = out.n_comps++;
        out.comp_voxels.push_back(0);
        out.comp_label.push_back(out.runs[k].label);
        out.comp_lateral.push_back(0);
      }
      Run& r = out.runs[k];
      r.comp = id[root];
      out.comp_voxels[r.comp] += r.x1 - r.x0;
      if (y == 0 || y == ny - 1 || r.x0 == 0 || r.x1 == nx) out.comp_lateral[r.comp] = 1;
    }
  // contacts between different components: faces shared in the slice
  for (int y = 0; y < ny; ++y) {
    const std::uint32_t b = out.row_start[static_cast<std::size_t>(y)], e = out.row_start[static_cast<std::size_t>(y) + 1];
    for (std::uint32_t k = b + 1; k < e; ++k) {
      const std::uint32_t p = out.runs[k - 1].comp, q = out.runs[k].comp;
      if (p != q) contacts.push_back({std::min(p, q), std::max(p, q), 1});
    }
    if (y == 0) continue;
    std::uint32_t i = out.row_start[static_cast<std::size_t>(y) - 1], ie = b, j = b;
    while (i < ie && j < e) {
      const Run &ra = out.runs[i], &rb = out.runs[j];
      const int ov = std::min(ra.x1, rb.x1) - std::max(ra.x0, rb.x0);
      if (ov > 0 && ra.comp != rb.comp)
        contacts.push_back({std::min(ra.comp, rb.comp), std::max(ra.comp, rb.comp), ov});
      if (ra.x1 < rb.x1) ++i; else ++j;
    }
  }
  std::sort(contacts.begin(), contacts.end());
  out.contacts.clear();
  for (const auto& c : contacts) {
    if (!out.contacts.empty() && out.contacts.back()[0] == c[0] && out.contacts.back()[1] == c[1])
      out.contacts.back()[2] += c[2];
    else
      out.contacts.push_back(c);
  }
}

void encode_runs(const SliceRuns& r, std::vector<std::uint8_t>& blob) {
  blob.clear();
  blob.reserve(4 * static_cast<std::size_t>(r.ny) + 9 * r.runs.size());
  auto put = [&](const void* p, std::size_t n) {
    const auto* b = static_cast<const std::uint8_t*>(p);
    blob.insert(blob.end(), b, b + n);
  };
  for (int y = 0; y < r.ny; ++y) {
    const std::uint32_t b = r.row_start[static_cast<std::size_t>(y)], e = r.row_start[static_cast<std::size_t>(y) + 1];
    const std::uint32_t count = e - b;
    put(&count, 4);
    for (std::uint32_t k = b; k < e; ++k) {
      const std::uint32_t x1 = static_cast<std::uint32_t>(r.runs[k].x1);
      put(&x1, 4);
      put(&r.runs[k].comp, 4);
      put(&r.runs[k].label, 1);
    }
  }
}

void decode_runs(const std::uint8_t* blob, std::size_t size, int nx, int ny, const std::uint8_t* final_label,
                 std::uint8_t* labels) {
  std::size_t at = 0;
  auto get32 = [&]() {
    std::uint32_t v;
    if (at + 4 > size) throw Error("", "segment: corrupt scratch data");
    std::memcpy(&v, blob + at, 4);
    at += 4;
    return v;
  };
  for (int y = 0; y < ny; ++y) {
    const std::uint32_t count = get32();
    std::uint8_t* row = labels + static_cast<std::size_t>(y) * nx;
    std::uint32_t x0 = 0;
    for (std::uint32_t k = 0; k < count; ++k) {
      const std::uint32_t x1 = get32();
      const std::uint32_t comp = get32();
      at += 1;  // the label before clean-up: final_label decides
      if (x1 > static_cast<std::uint32_t>(nx) || x1 < x0) throw Error("", "segment: corrupt scratch data");
      std::memset(row + x0, final_label[comp], x1 - x0);
      x0 = x1;
    }
  }
}

// ---- 3-D components ---------------------------------------------------------------

std::uint32_t ComponentTracker::find(std::uint32_t a) {
  while (parent_[a] != a) a = parent_[a] = parent_[parent_[a]];
  return a;
}

void ComponentTracker::unite(std::uint32_t a, std::uint32_t b) {
  a = find(a), b = find(b);
  if (a == b) return;
  if (a > b) std::swap(a, b);
  parent_[b] = a;
  size_[a] += size_[b];
  lateral_[a] |= lateral_[b];
}

void ComponentTracker::contact(std::uint32_t a, std::uint32_t b, std::int64_t w) {
  a = find(a), b = find(b);
  if (a == b) return;
  if (a > b) std::swap(a, b);
  contacts_[static_cast<std::uint64_t>(a) << 32 | b] += w;
}

void ComponentTracker::compact() {
  std::unordered_map<std::uint64_t, std::int64_t> next;
  next.reserve(contacts_.size());
  for (const auto& [k, w] : contacts_) {
    std::uint32_t a = find(static_cast<std::uint32_t>(k >> 32)), b = find(static_cast<std::uint32_t>(k & 0xffffffffu));
    if (a == b) continue;
    if (a > b) std::swap(a, b);
    next[static_cast<std::uint64_t>(a) << 32 | b] += w;
  }
  contacts_.swap(next);
}

void ComponentTracker::add_slice(const SliceRuns& cur, const SliceRuns* prev) {
  const std::uint64_t off = parent_.size();
  if (off + cur.n_comps >= 0xffffffffull) throw Error("", "segment: too many components (noisy stack?)");
  offsets_.push_back(off);
  for (std::uint32_t c = 0; c < cur.n_comps; ++c) {
    parent_.push_back(static_cast<std::uint32_t>(off + c));
    size_.push_back(cur.comp_voxels[c]);
    label_.push_back(cur.comp_label[c]);
    lateral_.push_back(cur.comp_lateral[c]);
  }
  const auto o32 = static_cast<std::uint32_t>(off);
  for (const auto& c : cur.contacts)
    contact(o32 + static_cast<std::uint32_t>(c[0]), o32 + static_cast<std::uint32_t>(c[1]), c[2]);
  if (prev) {
    const auto p32 = static_cast<std::uint32_t>(offsets_[offsets_.size() - 2]);
    for (int y = 0; y < cur.ny; ++y) {
      std::uint32_t i = prev->row_start[static_cast<std::size_t>(y)], ie = prev->row_start[static_cast<std::size_t>(y) + 1];
      std::uint32_t j = cur.row_start[static_cast<std::size_t>(y)], je = cur.row_start[static_cast<std::size_t>(y) + 1];
      while (i < ie && j < je) {
        const Run &a = prev->runs[i], &b = cur.runs[j];
        const int ov = std::min(a.x1, b.x1) - std::max(a.x0, b.x0);
        if (ov > 0) {
          if (a.label == b.label)
            unite(p32 + a.comp, o32 + b.comp);
          else
            contact(p32 + a.comp, o32 + b.comp, ov);
        }
        if (a.x1 < b.x1) ++i; else ++j;
      }
    }
  }
  if (contacts_.size() > compact_at_) {
    compact();
    compact_at_ = std::max<std::size_t>(2 * contacts_.size(), 1 << 16);
  }
}

std::vector<std::uint8_t> ComponentTracker::resolve(const LabelInfo& info, const SegmentOptions& o, Decision* d) {
  compact();
  const std::size_t n = parent_.size();
  Decision dec;
  std::vector<std::uint32_t> roots;
  for (std::uint32_t i = 0; i < n; ++i)
    if (parent_[i] == i) roots.push_back(i);
  dec.components = static_cast<std::int64_t>(roots.size());
  std::vector<std::uint8_t> final_label(n);

  if (o.cleanup) {
    // adjacency between roots, ordered for deterministic tie-breaks
    std::unordered_map<std::uint32_t, std::map<std::uint32_t, std::int64_t>> adj;
    for (const auto& [k, w] : contacts_) {
      const auto a = static_cast<std::uint32_t>(k >> 32), b = static_cast<std::uint32_t>(k & 0xffffffffu);
      adj[a][b] += w;
      adj[b][a] += w;
    }
    // each tissue's largest component before any merge (the first of equals)
    std::vector<std::uint32_t> largest_of(256, std::uint32_t(-1));
    for (auto r : roots) {
      auto& b = largest_of[label_[r]];
      if (b == std::uint32_t(-1) || size_[r] > size_[b]) b = r;
    }
    // a component of a nested tissue is out of place (bone in the skin, fat
    // in the gel, shaded fat taken for bone in the fat) when its parent's
    // region is not the majority of what surrounds it: faces with tissues
    // nested in it and with vessels aside, fewer of its faces meet its place
    // than meet the rest. Each tissue's anchor, the component meeting its
    // place on the most faces, is out of place only when it meets none of it:
    // a torn parent (thin skin missing over the fat) must not push the
    // tissue itself out.
    auto place_faces = [&](std::uint32_t r) {
      std::array<std::int64_t, 2> io{0, 0};  // in place, out of place
      const auto& where = info.touch[label_[r]];
      if (auto it = adj.find(r); it != adj.end())
        for (const auto& [nb, w] : it->second)
          if (where[label_[nb]] < 2) io[where[label_[nb]] == 1 ? 0 : 1] += w;
      return io;
    };
    std::vector<std::uint32_t> anchor(256, std::uint32_t(-1));
    {
      std::vector<std::int64_t> best(256, -1);
      for (auto r : roots)
        if (!info.touch[label_[r]].empty())
          if (const auto in = place_faces(r)[0]; in > best[label_[r]]) best[label_[r]] = in, anchor[label_[r]] = r;
    }
    auto misplaced = [&](std::uint32_t r) {
      if (!o.enforce_order || info.touch[label_[r]].empty()) return false;
      const auto [in, out] = place_faces(r);
      return in == 0 ? out > 0 : anchor[label_[r]] != r && in < out;
    };
    // the island rule's size in voxels: min_island_voxels, or fewer where
    // those would hold more than min_island_mm3 (coarse stacks)
    const double voxel_mm3 = 1e9 * o.spacing_m[0] * o.spacing_m[1] * o.spacing_m[2];
    const std::int64_t min_island = std::min<std::int64_t>(
        o.min_island_voxels, voxel_mm3 > 0 ? static_cast<std::int64_t>(std::ceil(o.min_island_mm3 / voxel_mm3 - 1e-9)) : 0);
    auto small = [&](std::uint32_t r) {
      const std::uint8_t l = label_[r];
      if (l == 0) return o.fill_holes && !lateral_[r];
      if (info.is_vessel[l]) return size_[r] < o.min_vessel_voxels || misplaced(r);
      return size_[r] < min_island || misplaced(r);
    };
    std::vector<std::uint32_t> cand;
    for (auto r : roots)
      if (small(r)) cand.push_back(r);
    std::sort(cand.begin(), cand.end(), [&](std::uint32_t a, std::uint32_t b) {
      return size_[a] != size_[b] ? size_[a] < size_[b] : a < b;
    });
    for (auto c : cand) {
      if (parent_[c] != c || !small(c)) continue;
      auto it = adj.find(c);
      if (it == adj.end() || it->second.empty()) continue;
      // the neighbour sharing the most faces (then the larger, then the first)
      std::uint32_t t = 0;
      std::int64_t tw = -1;
      for (const auto& [nb, w] : it->second)
        if (w > tw || (w == tw && size_[nb] > size_[t])) t = nb, tw = w;
      // a tissue's largest component, out of place but larger than the
      // neighbour that would take it, stays: then the neighbour is what is
      // misplaced (shaded fat taken for bone ringing the muscle; absorbing
      // the muscle into that ring deleted it on the real arm slice), as the
      // slices' order rule keeps a pocket larger than its outline
      if (label_[c] != 0 && size_[c] >= min_island && largest_of[label_[c]] == c && size_[c] > size_[t])
        continue;
      (label_[c] == 0 ? dec.holes_filled : size_[c] < min_island ? dec.islands_absorbed
                                                                           : dec.misplaced_absorbed) += size_[c];
      // merge c into t
      auto nbs = std::move(it->second);
      adj.erase(it);
      for (const auto& [nb, w] : nbs) {
        auto& m = adj[nb];
        m.erase(c);
        if (nb == t) continue;
        m[t] += w;
        adj[t][nb] += w;
      }
      parent_[c] = t;
      size_[t] += size_[c];
      lateral_[t] |= lateral_[c];
    }
    // the body: groups of non-background roots in contact
    std::map<std::uint32_t, std::uint32_t> group;  // root -> group root
    std::function<std::uint32_t(std::uint32_t)> gfind = [&](std::uint32_t a) {
      auto it = group.find(a);
      if (it == group.end() || it->second == a) return a;
      const std::uint32_t r = gfind(it->second);
      it->second = r;
      return r;
    };
    for (const auto& [a, m] : adj) {
      if (label_[a] == 0 || parent_[a] != a) continue;
      for (const auto& [b, w] : m) {
        if (label_[b] == 0 || parent_[b] != b) continue;
        std::uint32_t ra = gfind(a), rb = gfind(b);
        if (ra == rb) continue;
        if (ra > rb) std::swap(ra, rb);
        group[rb] = ra;
        group.emplace(ra, ra);
      }
    }
    std::map<std::uint32_t, std::int64_t> gsize;
    for (auto r : roots)
      if (parent_[r] == r && label_[r] != 0) gsize[gfind(r)] += size_[r];
    std::int64_t largest = 0;
    for (const auto& [g, s] : gsize) largest = std::max(largest, s);
    std::map<std::uint32_t, bool> keep;
    for (const auto& [g, s] : gsize) {
      keep[g] = s > 0 && static_cast<double>(s) >= o.min_body_fraction * static_cast<double>(largest);
      dec.body_components += keep[g];
    }
    std::vector<std::uint8_t> root_label(n, 0);
    for (auto r : roots) {
      if (parent_[r] != r) continue;
      std::uint8_t l = label_[r];
      if (l != 0 && !keep[gfind(r)]) {
        dec.detached_removed += size_[r];
        l = 0;
      }
      root_label[r] = l;
    }
    for (std::uint32_t i = 0; i < n; ++i) final_label[i] = root_label[find(i)];
  } else {
    for (std::uint32_t i = 0; i < n; ++i) final_label[i] = label_[find(i)];
    for (auto r : roots) dec.body_components += label_[r] != 0;
  }
  if (d) *d = dec;
  return final_label;
}

}  // namespace orthosim::segment_detail
