// The colour model: CIELAB prototypes, calibration by k-means, per-slice
// background normalisation and the nearest-prototype table over 24-bit
// colours.
#include "libmodel/segment/detail.h"

#include <Eigen/Dense>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>

namespace orthosim::segment_detail {

// ---- colour spaces ---------------------------------------------------------

namespace {

// sRGB (IEC 61966-2-1) transfer curve: channel in [0, 255] to linear.
double srgb_linear(double v) {
  v = std::clamp(v / 255.0, 0.0, 1.0);
  return v <= 0.04045 ? v / 12.92 : std::pow((v + 0.055) / 1.055, 2.4);
}

// Linear sRGB to XYZ (D65) to CIELAB; the constants are OpenCV's (cvtColor).
std::array<double, 3> linear_to_lab(double R, double G, double B) {
  const double X = (0.412453 * R + 0.357580 * G + 0.180423 * B) / 0.950456;
  const double Y = 0.212671 * R + 0.715160 * G + 0.072169 * B;
  const double Z = (0.019334 * R + 0.119193 * G + 0.950227 * B) / 1.088754;
  auto f = [](double t) { return t > 0.008856 ? std::cbrt(t) : 7.787 * t + 16.0 / 116.0; };
  const double fx = f(X), fy = f(Y), fz = f(Z);
  const double L = Y > 0.008856 ? 116.0 * fy - 16.0 : 903.3 * Y;
  return {L, 500.0 * (fx - fy), 200.0 * (fy - fz)};
}

}  // namespace

std::array<double, 3> srgb_to_lab(double r, double g, double b) {
  return linear_to_lab(srgb_linear(r), srgb_linear(g), srgb_linear(b));
}

std::array<double, 3> srgb8_to_lab(std::uint8_t r, std::uint8_t g, std::uint8_t b) {
  static const std::array<double, 256> lin = [] {
    std::array<double, 256> t{};
    for (int i = 0; i < 256; ++i) t[static_cast<std::size_t>(i)] = srgb_linear(i);
    return t;
  }();
  return linear_to_lab(lin[r], lin[g], lin[b]);
}

// ---- the tissue tree ---------------------------------------------------------

LabelInfo make_label_info(const TissueTable& t, bool fill_holes) {
  LabelInfo info;
  int top = 0;
  for (const auto& x : t.tissues) top = std::max(top, static_cast<int>(x.label));
  info.n_labels = top + 1;
  info.fill_holes = fill_holes;
  info.is_tissue.assign(256, 0);
  info.is_vessel.assign(256, 0);
  for (const auto& x : t.tissues) {
    info.is_tissue[x.label] = 1;
    info.is_vessel[x.label] = x.layer == "vessel";
  }
  // descendants: every tissue whose chain of "inside" reaches U
  auto in_subtree = [&](const Tissue& x, const Tissue& u) {
    const Tissue* cur = &x;
    for (std::size_t guard = 0; cur && guard <= t.tissues.size(); ++guard) {
      if (cur->name == u.name) return true;
      cur = cur->inside.empty() ? nullptr : t.find(cur->inside);
    }
    return false;
  };
  info.touch.assign(256, {});
  for (const auto& x : t.tissues) {
    if (info.is_vessel[x.label]) {
      // vessels run inside the body: a piece of one that meets the embedding
      // medium more than the body is the medium's noise or the skin's
      // partial volume (blue gel next to pink skin looks like a vein)
      auto& m = info.touch[x.label];
      m.assign(256, 0);
      for (const auto& y : t.tissues) m[y.label] = info.is_vessel[y.label] ? 2 : 1;
      continue;
    }
    if (x.inside.empty()) continue;
    const Tissue* parent = t.find(x.inside);
    if (!parent) continue;
    auto& m = info.touch[x.label];
    m.assign(256, 0);
    for (const auto& y : t.tissues)
      m[y.label] = in_subtree(y, x) ? 2 : in_subtree(y, *parent) ? 1 : info.is_vessel[y.label] ? 2 : 0;
  }
  if (fill_holes) {
    LabelInfo::Encloser body;
    body.label = 0;
    body.in_region.assign(256, 0);
    body.allowed.assign(256, 0);
    for (const auto& x : t.tissues) {
      body.in_region[x.label] = 1;
      body.allowed[x.label] = !info.is_vessel[x.label];
    }
    info.enclosers.push_back(std::move(body));
  }
  std::vector<const Tissue*> order;
  for (const auto& u : t.tissues) order.push_back(&u);
  std::stable_sort(order.begin(), order.end(), [&](const Tissue* a, const Tissue* b) {
    const int da = t.depth(*a), db = t.depth(*b);
    return da != db ? da < db : a->label < b->label;
  });
  for (const Tissue* u : order) {
    if (info.is_vessel[u->label]) continue;
    LabelInfo::Encloser e;
    e.label = u->label;
    e.in_region.assign(256, 0);
    e.allowed.assign(256, 0);
    int members = 0;
    for (const auto& x : t.tissues)
      if (in_subtree(x, *u)) {
        e.in_region[x.label] = 1;
        e.allowed[x.label] = !info.is_vessel[x.label];
        ++members;
      }
    if (members > 1) info.enclosers.push_back(std::move(e));
  }
  return info;
}

// ---- the model -------------------------------------------------------------

int ColourModel::nearest(const std::array<double, 3>& x) const {
  int best = 0;
  double bd = 1e300;
  for (std::size_t i = 0; i < centres.size(); ++i) {
    const double d = score(x, i);
    if (d < bd) bd = d, best = static_cast<int>(i);
  }
  return best;
}

int ColourModel::nearest_table_rgb(const std::uint8_t* rgb) const {
  int best = 0;
  double bd = 1e300;
  for (std::size_t i = 0; i < centres.size(); ++i) {
    const auto& t = centres[i].table_rgb;
    const double d0 = rgb[0] - t[0], d1 = rgb[1] - t[1], d2 = rgb[2] - t[2];
    const double d = d0 * d0 + d1 * d1 + d2 * d2;
    if (d < bd) bd = d, best = static_cast<int>(i);
  }
  return best;
}

int ColourModel::nearest_allowed(const std::array<double, 3>& x, const std::vector<std::uint8_t>& allowed) const {
  int best = -1;
  double bd = 1e300;
  for (std::size_t i = 0; i < centres.size(); ++i) {
    if (!allowed[centres[i].label]) continue;
    const double d = score(x, i);
    if (d < bd) bd = d, best = static_cast<int>(i);
  }
  return best;
}

void ColourModel::reset_table() {
  centre_label.resize(centres.size());
  for (std::size_t i = 0; i < centres.size(); ++i) centre_label[i] = static_cast<std::uint8_t>(centres[i].label);
  memo_.assign(std::size_t(1) << 24, kUnknown);
}

ColourModel initial_model(const TissueTable& t, const SegmentOptions& o) {
  ColourModel m;
  m.space = o.colour_space;
  m.wl2 = m.space == SegmentOptions::Space::cielab ? o.lightness_weight * o.lightness_weight : 1.0;
  auto add = [&](int label, const std::array<std::uint8_t, 3>& rgb) {
    Centre c;
    c.label = label;
    c.table_rgb = {double(rgb[0]), double(rgb[1]), double(rgb[2])};
    c.table_lab = srgb_to_lab(rgb[0], rgb[1], rgb[2]);
    c.lab = c.pixel_lab = c.table_lab;
    c.table_x = c.x = c.pixel_x = m.coords(c.table_rgb);
    m.centres.push_back(c);
  };
  for (const auto& rgb : t.background_rgb) add(0, rgb);
  for (const auto& x : t.tissues)
    for (const auto& rgb : x.rgb) add(x.label, rgb);
  if (m.centres.size() > 255)
    throw Error(t.path, "too many colour prototypes (" + std::to_string(m.centres.size()) + ", at most 255)");
  return m;
}

// ---- normalisation -----------------------------------------------------------

namespace {

struct Samples {
  std::vector<std::uint8_t> rgb;  // interleaved: the pixels, or their 3 x 3 medians
  std::vector<std::uint8_t> raw;  // with medians: the pixels themselves (else empty)
  std::vector<double> u, v;       // position relative to the centre, in image sizes
};

// The median of 9 values by the 19 compare-exchanges of Paeth's network
// (Graphics Gems, 1990), branch-free: nth_element over a 9-array took a sixth
// of a quiet stack's run once the normalisation's fits sampled medians too.
std::uint8_t median9(std::array<std::uint8_t, 9> p) {
  auto sort2 = [&](int a, int b) {
    const std::uint8_t lo = std::min(p[a], p[b]), hi = std::max(p[a], p[b]);
    p[a] = lo, p[b] = hi;
  };
  sort2(1, 2), sort2(4, 5), sort2(7, 8), sort2(0, 1), sort2(3, 4), sort2(6, 7), sort2(1, 2), sort2(4, 5), sort2(7, 8);
  sort2(0, 3), sort2(5, 8), sort2(4, 7), sort2(3, 6), sort2(1, 4), sort2(2, 5), sort2(4, 7), sort2(4, 2), sort2(6, 4);
  sort2(4, 2);
  return p[4];
}

// The pixels on a grid of the given stride. median3: each sample is the
// per-channel median of its 3 x 3 neighbourhood (clipped at the border):
// the calibration's samples, whose noise it cuts to ~0.4 sigma (a tissue's
// mean colour is what calibration estimates) while keeping edges.
Samples grid_samples(const std::uint8_t* rgb, int nx, int ny, int stride, bool median3 = false) {
  Samples s;
  const int off = stride / 2;
  const int x0 = std::min(off, nx - 1), y0 = std::min(off, ny - 1);
  const std::size_t n = static_cast<std::size_t>((nx - x0 + stride - 1) / stride) * ((ny - y0 + stride - 1) / stride);
  s.rgb.reserve(3 * n), s.u.reserve(n), s.v.reserve(n);
  for (int y = y0; y < ny; y += stride)
    for (int x = x0; x < nx; x += stride) {
      const std::uint8_t* p = rgb + (static_cast<std::size_t>(y) * nx + x) * 3;
      if (median3 && x > 0 && y > 0 && x + 1 < nx && y + 1 < ny) {
        const std::size_t row = static_cast<std::size_t>(nx) * 3;
        for (int c = 0; c < 3; ++c) {
          const std::uint8_t* q = p + c;
          s.rgb.push_back(median9({q[-row - 3], q[-row], q[-row + 3], q[-3], q[0], q[3], q[row - 3], q[row], q[row + 3]}));
        }
        s.raw.insert(s.raw.end(), p, p + 3);
      } else if (median3) {  // at the border: the neighbours inside the slice
        for (int c = 0; c < 3; ++c) {
          std::array<std::uint8_t, 9> w{};
          int k = 0;
          for (int yy = std::max(0, y - 1); yy <= std::min(ny - 1, y + 1); ++yy)
            for (int xx = std::max(0, x - 1); xx <= std::min(nx - 1, x + 1); ++xx)
              w[static_cast<std::size_t>(k++)] = rgb[(static_cast<std::size_t>(yy) * nx + xx) * 3 + c];
          std::nth_element(w.begin(), w.begin() + k / 2, w.begin() + k);
          s.rgb.push_back(w[static_cast<std::size_t>(k / 2)]);
        }
        s.raw.insert(s.raw.end(), p, p + 3);
      } else {
        s.rgb.insert(s.rgb.end(), p, p + 3);
      }
      s.u.push_back((x - 0.5 * (nx - 1)) / nx);
      s.v.push_back((y - 0.5 * (ny - 1)) / ny);
    }
  return s;
}

double gain_at(const GainField& g, int c, double u, double v) { return g.coef[c][0] + g.coef[c][1] * u + g.coef[c][2] * v; }

// The samples' colours (or, raw, their pixels') under the gain field.
void correct_samples(const GainField& g, const Samples& s, std::vector<std::uint8_t>& out, bool raw = false) {
  const std::size_t n = s.u.size();
  const std::vector<std::uint8_t>& in = raw ? s.raw : s.rgb;
  out.resize(3 * n);
  for (std::size_t i = 0; i < n; ++i)
    for (int c = 0; c < 3; ++c) {
      const double v = in[3 * i + c] / gain_at(g, c, s.u[i], s.v[i]);
      out[3 * i + c] = static_cast<std::uint8_t>(std::clamp(std::lround(v), 0L, 255L));
    }
}

// The median of v (reordered in place).
double median_inplace(std::vector<double>& v) {
  if (v.empty()) return 0;
  auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

// Least-squares gain field over background samples: I_c = T_c * s_c(u, v).
// `plane` fits (a, b, c), otherwise a alone. Samples with |residual| beyond
// three robust standard deviations are dropped and the fit repeated once.
GainField fit_samples(const std::vector<std::array<double, 3>>& I, const std::vector<std::array<double, 3>>& T,
                      const std::vector<double>& u, const std::vector<double>& v, bool plane) {
  GainField g;
  const std::size_t n = I.size();
  std::vector<std::uint8_t> use(n, 1);
  std::vector<double> r;
  r.reserve(n);
  for (int round = 0; round < 2; ++round) {
    for (int c = 0; c < 3; ++c) {
      // normal equations of the rows (T, T u, T v): the six distinct entries
      // of the symmetric 3x3 matrix and the right-hand side, in registers
      double a00 = 0, a01 = 0, a02 = 0, a11 = 0, a12 = 0, a22 = 0, b0 = 0, b1 = 0, b2 = 0;
      for (std::size_t i = 0; i < n; ++i) {
        if (!use[i]) continue;
        const double r0 = T[i][c], r1 = T[i][c] * u[i], r2 = T[i][c] * v[i], y = I[i][c];
        a00 += r0 * r0, a01 += r0 * r1, a02 += r0 * r2, a11 += r1 * r1, a12 += r1 * r2, a22 += r2 * r2;
        b0 += r0 * y, b1 += r1 * y, b2 += r2 * y;
      }
      if (plane) {
        Eigen::Matrix3d A;
        A << a00, a01, a02, a01, a11, a12, a02, a12, a22;
        const Eigen::Vector3d x = A.ldlt().solve(Eigen::Vector3d(b0, b1, b2));
        if (x.allFinite()) g.coef[c] = {x[0], x[1], x[2]};
      } else if (a00 > 0) {
        g.coef[c] = {b0 / a00, 0, 0};
      }
    }
    if (round == 1) break;
    // robust trimming
    for (int c = 0; c < 3; ++c) {
      r.clear();
      for (std::size_t i = 0; i < n; ++i) r.push_back(std::abs(I[i][c] - T[i][c] * gain_at(g, c, u[i], v[i])));
      std::vector<double> sorted = r;
      const double mad = median_inplace(sorted);
      const double cut = std::max(3 * 1.4826 * mad, 3.0);
      for (std::size_t i = 0; i < n; ++i)
        if (r[i] > cut) use[i] = 0;
    }
  }
  return g;
}

}  // namespace

GainField fit_gain(const ColourModel& m, const std::uint8_t* rgb, int nx, int ny, SegmentOptions::Normalise mode) {
  GainField g;
  if (mode == SegmentOptions::Normalise::none || m.bg_reference.empty()) return g;
  // at most about 96 samples along the shorter side whatever the slice
  // size: plenty for 3 parameters. Each is the 3 x 3 median, as the
  // calibration's reference is: on single pixels the selection by nearest
  // colour below cut a noisy background's tail the reference's medians keep.
  const int stride = std::max(1, (std::min(nx, ny) + 95) / 96);
  const Samples s = grid_samples(rgb, nx, ny, stride, /*median3=*/true);
  std::vector<std::uint8_t> corr;
  std::vector<std::array<double, 3>> I, T;
  std::vector<double> u, v;
  I.reserve(s.u.size()), T.reserve(s.u.size()), u.reserve(s.u.size()), v.reserve(s.u.size());
  for (int iter = 0; iter < 2; ++iter) {
    correct_samples(g, s, corr);
    I.clear(), T.clear(), u.clear(), v.clear();
    double umin = 1, umax = -1, vmin = 1, vmax = -1;
    for (std::size_t i = 0; i < s.u.size(); ++i) {
      const int c = m.nearest_table_rgb(&corr[3 * i]);
      if (m.centres[static_cast<std::size_t>(c)].label != 0) continue;
      I.push_back({double(s.rgb[3 * i]), double(s.rgb[3 * i + 1]), double(s.rgb[3 * i + 2])});
      T.push_back(m.bg_reference[static_cast<std::size_t>(c)]);
      u.push_back(s.u[i]);
      v.push_back(s.v[i]);
      umin = std::min(umin, s.u[i]), umax = std::max(umax, s.u[i]);
      vmin = std::min(vmin, s.v[i]), vmax = std::max(vmax, s.v[i]);
    }
    // the plane needs background on several sides; a constant gain a few pixels
    bool plane = mode == SegmentOptions::Normalise::plane && I.size() >= 64 && umax - umin > 0.5 && vmax - vmin > 0.5;
    GainField next;
    if (I.size() >= 16) {
      next = fit_samples(I, T, u, v, plane);
      next.fallback = mode == SegmentOptions::Normalise::plane && !plane;
    } else {
      next.fallback = true;
    }
    // sanity: the gain stays within [1/3, 3] over the whole slice
    for (int c = 0; c < 3; ++c)
      for (double cu : {-0.5, 0.5})
        for (double cv : {-0.5, 0.5}) {
          const double s_ = gain_at(next, c, cu, cv);
          if (!(s_ > 1.0 / 3 && s_ < 3)) next = GainField{}, next.fallback = true;
        }
    g = next;
    if (g.fallback && I.size() < 16) break;
  }
  return g;
}

void apply_gain_rows(const GainField& g, const std::uint8_t* rgb, int nx, int ny, int y0, int y1, std::uint8_t* out) {
  for (int y = y0; y < y1; ++y) {
    const double v = (y - 0.5 * (ny - 1)) / ny;
    float inv0[3], dinv[3];
    for (int c = 0; c < 3; ++c) {
      // 1/s is linear in x to within (ds)^2: interpolate it along the row
      const double s0 = gain_at(g, c, (0 - 0.5 * (nx - 1)) / nx, v);
      const double s1 = gain_at(g, c, (nx - 1 - 0.5 * (nx - 1)) / nx, v);
      inv0[c] = static_cast<float>(1 / s0);
      dinv[c] = nx > 1 ? static_cast<float>((1 / s1 - 1 / s0) / (nx - 1)) : 0.f;
    }
    const std::uint8_t* src = rgb + static_cast<std::size_t>(y) * nx * 3;
    std::uint8_t* dst = out + static_cast<std::size_t>(y) * nx * 3;
    for (int x = 0; x < nx; ++x)
      for (int c = 0; c < 3; ++c) {
        const float w = src[3 * x + c] * (inv0[c] + dinv[c] * static_cast<float>(x)) + 0.5f;
        dst[3 * x + c] = static_cast<std::uint8_t>(std::min(w, 255.f));
      }
  }
}

void apply_gain(const GainField& g, const std::uint8_t* rgb, int nx, int ny, std::uint8_t* out) {
  apply_gain_rows(g, rgb, nx, ny, 0, ny, out);
}

// ---- calibration -------------------------------------------------------------

namespace {

// The mixture's posteriors of colour x, unnormalised: lp[c] = exp(log p_c(x) -
// max) for the shared precision P, their sum returned (r_c = lp[c] / sum).
double posteriors(const ColourModel& m, const std::vector<double>& log_pi, const std::array<double, 6>& P,
                  const std::array<double, 3>& x, std::vector<double>& lp) {
  double top = -1e300;
  for (std::size_t c = 0; c < m.centres.size(); ++c) {
    lp[c] = log_pi[c] - 0.5 * mahalanobis2(P, x, m.centres[c].x);
    top = std::max(top, lp[c]);
  }
  double z = 0;
  for (std::size_t c = 0; c < m.centres.size(); ++c) z += (lp[c] = std::exp(lp[c] - top));
  return z;
}

// The inverse of the covariance scatter / total (xx, yy, zz, xy, xz, yz), its
// diagonal floored at 0.25 units of the model's space (CIE76 units or 8-bit
// levels: below 8-bit rounding's), in the same packing.
std::array<double, 6> precision_of(const std::array<double, 6>& scatter, double total) {
  Eigen::Matrix3d S;
  const double inv_total = 1 / std::max(total, 1e-300);
  S << scatter[0], scatter[3], scatter[4], scatter[3], scatter[1], scatter[5], scatter[4], scatter[5], scatter[2];
  S *= inv_total;
  S.diagonal().array() += 0.0625;
  const Eigen::Matrix3d Pi = S.inverse();
  return {Pi(0, 0), Pi(1, 1), Pi(2, 2), Pi(0, 1), Pi(0, 2), Pi(1, 2)};
}

// The fit above is made on 3 x 3 medians, but the classifier scores single
// pixels. CIELAB is not linear in RGB, so under sensor noise the mean colour
// of a tissue's pixels lies off that of its medians (8-bit noise 24: 4-11
// units in a* for every tissue of the phantom); in RGB they differ where
// the pixels clip at 0 or 255 (a saturated red). The pixels spread wider
// than the medians either way. Each centre's pixel_x is its x moved by the
// responsibility-weighted mean of (pixel - median) over the samples, shrunk
// towards the pooled mean by the prior's n0 samples (a rare tissue's own mean
// is noisy), and P becomes the inverse of the pixels' shared covariance about
// them, so that the Mahalanobis distance of a pixel is in units of its own
// spread (what the smoothness prior's weights are measured against). The
// responsibilities are the fit's, of each sample's median colour. `pairs`:
// sorted (median key << 24 | pixel key), 24-bit sRGB keys.
void pixel_statistics(ColourModel& m, const std::vector<std::uint64_t>& pairs, const std::vector<double>& log_pi,
                      std::array<double, 6>& P, double n0) {
  const std::size_t C = m.centres.size();
  auto coords_of = [&m](std::uint32_t k) {
    return m.coords(static_cast<std::uint8_t>(k >> 16), static_cast<std::uint8_t>(k >> 8), static_cast<std::uint8_t>(k));
  };
  // distinct pairs with counts
  std::vector<std::uint64_t> key;
  std::vector<double> count;
  for (std::size_t i = 0; i < pairs.size();) {
    std::size_t j = i;
    while (j < pairs.size() && pairs[j] == pairs[i]) ++j;
    key.push_back(pairs[i]);
    count.push_back(static_cast<double>(j - i));
    i = j;
  }
  const std::size_t N = key.size();
  if (N == 0) return;
  std::vector<std::array<double, 3>> med(N), pix(N);
  tbb::parallel_for(std::size_t(0), N, [&](std::size_t i) {
    med[i] = coords_of(static_cast<std::uint32_t>(key[i] >> 24));
    pix[i] = coords_of(static_cast<std::uint32_t>(key[i] & 0xFFFFFF));
  });
  auto responsibilities = [&](std::size_t i, std::vector<double>& r) {
    const double z = posteriors(m, log_pi, P, med[i], r);
    for (std::size_t c = 0; c < C; ++c) r[c] = count[i] * r[c] / z;
  };
  // chunks summed in parallel, then in a fixed order: deterministic
  constexpr std::size_t kChunk = 4096;
  const std::size_t chunks = (N + kChunk - 1) / kChunk;
  // 1. the mean (pixel - median) per centre, and pooled
  std::vector<std::vector<std::array<double, 4>>> part(chunks, std::vector<std::array<double, 4>>(C));
  tbb::parallel_for(std::size_t(0), chunks, [&](std::size_t k) {
    std::vector<double> r(C);
    auto& acc = part[k];
    for (auto& x : acc) x = {0, 0, 0, 0};
    for (std::size_t i = k * kChunk; i < std::min(N, (k + 1) * kChunk); ++i) {
      responsibilities(i, r);
      for (std::size_t c = 0; c < C; ++c) {
        for (int d = 0; d < 3; ++d) acc[c][d] += r[c] * (pix[i][d] - med[i][d]);
        acc[c][3] += r[c];
      }
    }
  });
  std::vector<std::array<double, 4>> shift(C, {0, 0, 0, 0});
  std::array<double, 4> pooled{0, 0, 0, 0};
  for (std::size_t k = 0; k < chunks; ++k)
    for (std::size_t c = 0; c < C; ++c)
      for (int d = 0; d < 4; ++d) shift[c][d] += part[k][c][d];
  for (std::size_t c = 0; c < C; ++c)
    for (int k = 0; k < 4; ++k) pooled[k] += shift[c][k];
  for (std::size_t c = 0; c < C; ++c) {
    Centre& ce = m.centres[c];
    for (int k = 0; k < 3; ++k)
      ce.pixel_x[k] = ce.x[k] + (shift[c][k] + n0 * pooled[k] / std::max(pooled[3], 1e-300)) / (shift[c][3] + n0 + 1e-300);
  }
  // 2. the pixels' shared covariance about their centres
  std::vector<std::array<double, 7>> part2(chunks);
  tbb::parallel_for(std::size_t(0), chunks, [&](std::size_t k) {
    std::vector<double> r(C);
    std::array<double, 7> acc{0, 0, 0, 0, 0, 0, 0};
    for (std::size_t i = k * kChunk; i < std::min(N, (k + 1) * kChunk); ++i) {
      responsibilities(i, r);
      for (std::size_t c = 0; c < C; ++c) {
        const auto& mu = m.centres[c].pixel_x;
        const double d0 = pix[i][0] - mu[0], d1 = pix[i][1] - mu[1], d2 = pix[i][2] - mu[2];
        acc[0] += r[c] * d0 * d0, acc[1] += r[c] * d1 * d1, acc[2] += r[c] * d2 * d2;
        acc[3] += r[c] * d0 * d1, acc[4] += r[c] * d0 * d2, acc[5] += r[c] * d1 * d2;
        acc[6] += r[c];
      }
    }
    part2[k] = acc;
  });
  std::array<double, 6> sc{0, 0, 0, 0, 0, 0};
  double total = 0;
  for (std::size_t k = 0; k < chunks; ++k) {
    for (int j = 0; j < 6; ++j) sc[j] += part2[k][j];
    total += part2[k][6];
  }
  P = precision_of(sc, total);
}

// `next` moved back towards `table` (both in the model's space) until it is
// at most max_shift CIE76 units from it. In CIELAB that is along the line;
// in RGB (not linear in CIELAB) by bisection along it, which keeps the end
// it knows to be within max_shift: the result never lies beyond, and it is
// where the distance first reaches max_shift when the distance grows along
// the line.
std::array<double, 3> clamp_shift(const ColourModel& m, const std::array<double, 3>& table,
                                  const std::array<double, 3>& next, double max_shift) {
  const auto lab0 = m.to_lab(table);
  auto along = [&](double t) {
    return std::array<double, 3>{table[0] + t * (next[0] - table[0]), table[1] + t * (next[1] - table[1]),
                                 table[2] + t * (next[2] - table[2])};
  };
  auto cie = [&](const std::array<double, 3>& x) {
    const auto l = m.to_lab(x);
    return std::sqrt((l[0] - lab0[0]) * (l[0] - lab0[0]) + (l[1] - lab0[1]) * (l[1] - lab0[1]) +
                     (l[2] - lab0[2]) * (l[2] - lab0[2]));
  };
  const double d = cie(next);
  if (!(d > max_shift)) return next;
  if (m.space == SegmentOptions::Space::cielab) return along(max_shift / d);
  double lo = 0, hi = 1;
  for (int k = 0; k < 40; ++k) {
    const double t = 0.5 * (lo + hi);
    (cie(along(t)) > max_shift ? hi : lo) = t;
  }
  return along(lo);
}

}  // namespace

void calibrate(ColourModel& m, const std::vector<std::vector<std::uint8_t>>& slices, int nx, int ny,
               const SegmentOptions& o) {
  const int nb = m.n_background();
  const int stride = std::max(1, o.sample_stride);
  std::vector<Samples> samples;
  for (const auto& s : slices) samples.push_back(grid_samples(s.data(), nx, ny, stride, /*median3=*/true));

  // 0. The stack's exposure. The calibration moves each prototype at most
  // refine_max_shift from its table colour, so a stack exposed darker or
  // brighter than the table's slices as a whole (a camera's gain, a scanner's
  // white balance) fell off a cliff: at 0.70 of the sample's brightness every
  // tissue came out right, at 0.65 fat, bone, marrow and the vessels were lost,
  // exit 0. The slices' border is the embedding medium around the specimen in a
  // cryosection series: where its per-channel median has the table background's
  // chromaticity (the three observed / table ratios within 25 % of each other,
  // each in [1/4, 4]) and its brightness (the ratio of the channel sums) is
  // off by more than 20 %, that ratio is the stack's exposure and every
  // centre's table colour is seen under it (scaled, clamped to 0..255). One
  // gain, not three: the table's background colour is only roughly right, and
  // its per-channel error, carried to every tissue, lost the skin of a stack
  // whose table colours were each moved by 10 (the calibration's own job).
  // Within 20 % the calibration follows the stack by itself. A border of
  // another colour (a crop inside the body) changes nothing. Off by default
  // (SegmentOptions::exposure_from_border): a vignetted stack (its corners at
  // 0.4 of its centre) has a dark border over a well-exposed specimen; the
  // border said 0.64 and the muscle was labelled artery, exit 0, where the
  // stack segments perfectly without it (a helper's sweep found it).
  if (nb > 0 && o.exposure_from_border) {
    std::array<std::vector<double>, 3> border;
    const int w = std::max(1, std::min(nx, ny) / 16);
    for (const auto& s : slices)
      for (int y = 0; y < ny; y += stride)
        for (int x = 0; x < nx; x += stride) {
          if (!(y < w || y >= ny - w || x < w || x >= nx - w)) continue;  // the frame w pixels wide
          for (int k = 0; k < 3; ++k) border[k].push_back(s[(static_cast<std::size_t>(y) * nx + x) * 3 + k]);
        }
    const std::array<double, 3> table = m.centres[0].table_rgb;
    if (border[0].size() >= 32) {
      std::array<double, 3> g{}, b{};
      bool ok = true;
      for (int k = 0; k < 3; ++k) {
        b[k] = median_inplace(border[k]);
        g[k] = table[k] > 0 ? b[k] / table[k] : 0;
        ok = ok && g[k] >= 0.25 && g[k] <= 4;
      }
      const double gmin = std::min({g[0], g[1], g[2]}), gmax = std::max({g[0], g[1], g[2]});
      const double gain = (b[0] + b[1] + b[2]) / std::max(1.0, table[0] + table[1] + table[2]);
      if (ok && gmax <= 1.25 * gmin && std::abs(gain - 1) > 0.2) {
        m.exposure = {gain, gain, gain};
        for (Centre& c : m.centres) {
          for (int k = 0; k < 3; ++k) c.table_rgb[k] = std::clamp(c.table_rgb[k] * gain, 0.0, 255.0);
          c.table_lab = c.lab = c.pixel_lab = srgb_to_lab(c.table_rgb[0], c.table_rgb[1], c.table_rgb[2]);
          c.table_x = c.x = c.pixel_x = m.coords(c.table_rgb);
        }
        m.reset_table();
      }
    }
  }

  // 1. reference background colours: the calibration samples (3 x 3
  // medians) whose nearest table colour is a background's, estimated as
  // fit_gain estimates each slice's (its trimmed least squares, a constant
  // fit against 1): the same pick, samples and estimator on both sides, so a
  // slice lit as the calibration's gets a gain of 1 whatever the noise. The
  // pick truncates a noisy background's distribution on the side of the
  // tissues next to it in colour. Before 2026-11-29 the two sides cut it
  // differently (here a median of medians picked by the table, there a
  // trimmed mean of single pixels picked by the calibrated rule): gains of
  // 1.03-1.09 at 8-bit noise 32, every colour moved by them, and the
  // calibration collapsed.
  m.bg_reference.clear();
  if (nb > 0 && o.normalise != SegmentOptions::Normalise::none) {
    std::vector<std::vector<std::array<double, 3>>> vals(static_cast<std::size_t>(nb));
    for (const auto& s : samples) {
      for (std::size_t i = 0; i < s.u.size(); ++i) {
        const int c = m.nearest_table_rgb(&s.rgb[3 * i]);
        if (m.centres[static_cast<std::size_t>(c)].label != 0) continue;
        vals[static_cast<std::size_t>(c)].push_back({double(s.rgb[3 * i]), double(s.rgb[3 * i + 1]), double(s.rgb[3 * i + 2])});
      }
    }
    bool any = false;
    for (int c = 0; c < nb; ++c) {
      std::array<double, 3> ref = m.centres[static_cast<std::size_t>(c)].table_rgb;
      const auto& I = vals[static_cast<std::size_t>(c)];
      if (I.size() >= 32) {
        const std::vector<std::array<double, 3>> ones(I.size(), {1.0, 1.0, 1.0});
        const std::vector<double> zero(I.size(), 0.0);
        const GainField level = fit_samples(I, ones, zero, zero, /*plane=*/false);
        for (int k = 0; k < 3; ++k) ref[k] = std::max(1.0, level.coef[k][0]);
        any = true;
      }
      m.bg_reference.push_back(ref);
    }
    if (!any) m.bg_reference.clear();
  }

  // 2. normalised colours of every calibration slice, as distinct colours
  // with their counts (24-bit keys, sorted: the order is fixed)
  // (median, pixel) colour key pairs of every sample: sorted, their median
  // keys are the EM's colours in order; pixel_lab below uses both
  std::vector<std::uint64_t> pairs;
  {
    std::vector<std::uint8_t> corr, corr_raw;
    auto key = [](const std::vector<std::uint8_t>& c, std::size_t i) {
      return static_cast<std::uint32_t>(c[3 * i]) << 16 | static_cast<std::uint32_t>(c[3 * i + 1]) << 8 | c[3 * i + 2];
    };
    for (std::size_t k = 0; k < slices.size(); ++k) {
      const GainField g = fit_gain(m, slices[k].data(), nx, ny, o.normalise);
      correct_samples(g, samples[k], corr);
      correct_samples(g, samples[k], corr_raw, /*raw=*/true);
      for (std::size_t i = 0; i < samples[k].u.size(); ++i)
        pairs.push_back(std::uint64_t(key(corr, i)) << 24 | key(corr_raw, i));
    }
  }
  std::sort(pairs.begin(), pairs.end());
  std::vector<std::uint32_t> keys(pairs.size());
  for (std::size_t i = 0; i < pairs.size(); ++i) keys[i] = static_cast<std::uint32_t>(pairs[i] >> 24);
  std::vector<std::array<double, 3>> colour;  // in the model's space
  std::vector<double> weight;
  for (std::size_t i = 0; i < keys.size();) {
    std::size_t j = i;
    while (j < keys.size() && keys[j] == keys[i]) ++j;
    colour.push_back(m.coords(static_cast<std::uint8_t>(keys[i] >> 16), static_cast<std::uint8_t>(keys[i] >> 8),
                              static_cast<std::uint8_t>(keys[i])));
    weight.push_back(static_cast<double>(j - i));
    i = j;
  }

  // 3. EM for a mixture of Gaussians (one per prototype, a shared full
  // covariance, mixing weights) in the model's space (SegmentOptions::
  // colour_space), seeded by the prototypes, each mean shrunk
  // towards its prototype (a conjugate prior of weight n0 samples per
  // prototype), moves clamped. Plain k-means (equal weights, no variance) lets
  // a rare tissue's prototype run off into the noise tail of a common one
  // next to it (the vein into the blue gel at 8-bit noise sigma 8: the gel's
  // tail is nearer the vein than the gel and outnumbers the vein's own
  // pixels); the weights keep the tail with the common tissue. Where the
  // clusters are tight against their separation (low noise), the posteriors
  // are hard and this is k-means.
  const std::size_t C = m.centres.size(), N = colour.size();
  const double n0 = o.refine_prior * static_cast<double>(keys.size()) / static_cast<double>(C);
  constexpr std::size_t kChunk = 4096;
  const std::size_t chunks = (N + kChunk - 1) / kChunk;
  // per chunk and centre: weighted sums of L, a, b, the weight, and of the
  // products of the deviations from the centre (for the covariance)
  using Acc = std::array<double, 10>;
  std::vector<std::vector<Acc>> part(chunks, std::vector<Acc>(C));
  std::vector<double> log_pi(C, 0.0);  // log mixing weights (the first pass: hard, nearest)
  // the shared covariance's inverse (symmetric: xx, yy, zz, xy, xz, yz);
  // unused in the first, hard pass
  std::array<double, 6> P{0, 0, 0, 0, 0, 0};
  auto reduce = [&](std::size_t c) {
    Acc sum{};
    for (std::size_t k = 0; k < chunks; ++k)  // fixed order: deterministic
      for (std::size_t j = 0; j < sum.size(); ++j) sum[j] += part[k][c][j];
    return sum;
  };
  auto accumulate = [](Acc& a, double r, const std::array<double, 3>& x, const std::array<double, 3>& mu) {
    const double d0 = x[0] - mu[0], d1 = x[1] - mu[1], d2 = x[2] - mu[2];
    a[0] += r * x[0], a[1] += r * x[1], a[2] += r * x[2], a[3] += r;
    a[4] += r * d0 * d0, a[5] += r * d1 * d1, a[6] += r * d2 * d2;
    a[7] += r * d0 * d1, a[8] += r * d0 * d2, a[9] += r * d1 * d2;
  };
  // pass 0 (when refining): hard nearest assignments to the table's colours
  // give the first weights and covariance and move nothing; passes 1.. are EM
  for (int it = o.refine_iterations > 0 ? -1 : 0; it < o.refine_iterations; ++it) {
    const bool hard = it < 0;
    tbb::parallel_for(std::size_t(0), chunks, [&](std::size_t k) {
      auto& acc = part[k];
      for (auto& a : acc) a = Acc{};
      std::vector<double> lp(C);
      for (std::size_t i = k * kChunk; i < std::min(N, (k + 1) * kChunk); ++i) {
        const double w = weight[i];
        const auto& x = colour[i];
        if (hard) {
          const auto c = static_cast<std::size_t>(m.nearest(x));
          accumulate(acc[c], w, x, m.centres[c].x);
          continue;
        }
        const double z = posteriors(m, log_pi, P, x, lp);
        for (std::size_t c = 0; c < C; ++c) {
          const double r = w * lp[c] / z;
          if (r != 0) accumulate(acc[c], r, x, m.centres[c].x);
        }
      }
    });
    double moved = 0, total = 0;
    std::array<double, 6> scatter{0, 0, 0, 0, 0, 0};
    std::vector<double> weight_of(C);
    for (std::size_t c = 0; c < C; ++c) {
      const Acc sum = reduce(c);
      weight_of[c] = sum[3];
      total += sum[3];
      for (int j = 0; j < 6; ++j) scatter[j] += sum[4 + j];
      if (it < 0) continue;
      Centre& ce = m.centres[c];
      std::array<double, 3> next;
      for (int j = 0; j < 3; ++j) next[j] = (sum[j] + n0 * ce.table_x[j]) / (sum[3] + n0 + 1e-300);
      next = clamp_shift(m, ce.table_x, next, o.refine_max_shift);
      for (int j = 0; j < 3; ++j) moved = std::max(moved, std::abs(next[j] - ce.x[j]));
      ce.x = ce.pixel_x = next;
      ce.samples = static_cast<std::int64_t>(std::llround(sum[3]));
    }
    // the mixing weights (with the prior's samples, so none reaches 0) and the
    // shared covariance, its diagonal floored at 0.25 CIE76 units (8-bit
    // rounding). A full covariance, not one variance: sensor noise is
    // isotropic in RGB but not in CIELAB (the blue gel's chroma spreads twice
    // as wide as its lightness), and with one variance the gel's chroma tail
    // looked unlikely under the gel and a rare tissue next to it took it (the
    // vein moved 20 units into the gel at 8-bit noise 20 and the segmentation
    // collapsed). Even a full covariance is one shape for every tissue, which
    // CIELAB's noise does not have (the blue gel's spreads a third wider than
    // the bone's): hence RGB by default (at noise 64 the CIELAB fit let the
    // vein into the gel again).
    for (std::size_t c = 0; c < C; ++c)
      log_pi[c] = std::log((weight_of[c] + n0 + 1e-300) / (total + static_cast<double>(C) * n0 + 1e-300));
    P = precision_of(scatter, total);
    if (it >= 0 && moved < 0.01) break;
  }
  if (o.refine_iterations > 0) pixel_statistics(m, pairs, log_pi, P, n0);
  for (Centre& ce : m.centres) ce.lab = m.to_lab(ce.x), ce.pixel_lab = m.to_lab(ce.pixel_x);
  if (o.classify == SegmentOptions::Classify::mahalanobis && o.refine_iterations > 0) {
    m.mahalanobis = true;
    m.precision = P;
  }
  m.reset_table();
}

GainField classify_slice(const ColourModel& m, const SegmentOptions& o, const std::uint8_t* rgb, int nx, int ny,
                         SliceWork& work, std::uint8_t* labels) {
  const std::size_t n = static_cast<std::size_t>(nx) * ny;
  const GainField g = fit_gain(m, rgb, nx, ny, o.normalise);
  const bool identity = g.coef[0] == std::array<double, 3>{1, 0, 0} && g.coef[1] == std::array<double, 3>{1, 0, 0} &&
                        g.coef[2] == std::array<double, 3>{1, 0, 0};
  const std::uint8_t* src = rgb;
  if (!identity) {
    work.corrected.resize(3 * n);
    src = work.corrected.data();
  }
  // row by row: correct, then classify while the row is in cache
  for (int y = 0; y < ny; ++y) {
    const std::size_t r = static_cast<std::size_t>(y) * nx;
    if (!identity) apply_gain_rows(g, rgb, nx, ny, y, y + 1, work.corrected.data());
    const std::uint8_t* c = src + 3 * r;
    std::uint8_t* l = labels + r;
    for (int x = 0; x < nx; ++x) l[x] = m.centre_label[static_cast<std::size_t>(m.centre_of(c + 3 * x))];
  }
  work.colour = src;
  return g;
}

}  // namespace orthosim::segment_detail
