#include "libmodel/tune/fit.h"

#include "libmodel/format/types.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace orthosim::tune {

namespace {

void check_curve(const std::vector<double>& e, const std::vector<double>& s, std::size_t min_n) {
  if (e.size() != s.size()) throw Error("", "fit: one stress per strain");
  if (e.size() < min_n) throw Error("", "fit: needs at least " + std::to_string(min_n) + " samples");
  for (std::size_t i = 0; i < e.size(); ++i) {
    if (!std::isfinite(e[i]) || !std::isfinite(s[i])) throw Error("", "fit: non-finite sample");
    if (!(e[i] > (i ? e[i - 1] : 0.0))) throw Error("", "fit: strains must be positive and increasing");
  }
}

// weighted sum of squared residuals of the bilinear law with these parameters
double ssr(const std::vector<double>& e, const std::vector<double>& s, const std::vector<double>& w, double k1,
           double b, double k2) {
  double r2 = 0;
  for (std::size_t i = 0; i < e.size(); ++i) {
    const double model = e[i] < b ? k1 * e[i] : k1 * b + k2 * (e[i] - b);
    r2 += w[i] * (s[i] - model) * (s[i] - model);
  }
  return r2;
}

}  // namespace

BilinearFit fit_bilinear(const std::vector<double>& e, const std::vector<double>& s, FitWeighting weighting) {
  check_curve(e, s, 3);
  const std::size_t n = e.size();
  // weights: 1, or 1 / stress^2 with a floor of 1e-6 x the largest |stress|
  std::vector<double> w(n, 1.0);
  if (weighting == FitWeighting::relative) {
    double smax = 0;
    for (double v : s) smax = std::max(smax, std::abs(v));
    const double floor = std::max(1e-6 * smax, std::numeric_limits<double>::min());
    for (std::size_t i = 0; i < n; ++i) w[i] = 1.0 / std::pow(std::max(std::abs(s[i]), floor), 2);
  }
  BilinearFit best;
  double best_r2 = std::numeric_limits<double>::infinity();
  auto consider = [&](double k1, double b, double k2) {
    if (!std::isfinite(k1) || !std::isfinite(b) || !std::isfinite(k2)) return;
    const double r2 = ssr(e, s, w, k1, b, k2);
    if (r2 < best_r2) {
      best_r2 = r2;
      best.k1_pa = k1, best.turning_strain = b, best.k2_pa = k2;
    }
  };
  // b fixed at a sample: linear least squares in (K1, K2) with the basis
  // phi1 = min(e, b), phi2 = max(e - b, 0)
  for (std::size_t i = 0; i + 2 <= n; ++i) {
    const double b = e[i];
    double a11 = 0, a12 = 0, a22 = 0, r1 = 0, r2 = 0;
    for (std::size_t k = 0; k < n; ++k) {
      const double p1 = std::min(e[k], b), p2 = std::max(e[k] - b, 0.0);
      a11 += w[k] * p1 * p1, a12 += w[k] * p1 * p2, a22 += w[k] * p2 * p2;
      r1 += w[k] * p1 * s[k], r2 += w[k] * p2 * s[k];
    }
    const double det = a11 * a22 - a12 * a12;
    if (!(std::abs(det) > 1e-14 * a11 * a22)) continue;
    consider((r1 * a22 - r2 * a12) / det, b, (a11 * r2 - a12 * r1) / det);
  }
  // b strictly inside [e[j-1], e[j]]: points 0..j-1 on a line through the
  // origin, j..n-1 on a free line; b where the two lines meet
  for (std::size_t j = 1; j + 2 <= n; ++j) {
    double sxy = 0, sxx = 0;
    for (std::size_t k = 0; k < j; ++k) sxy += w[k] * e[k] * s[k], sxx += w[k] * e[k] * e[k];
    const double k1 = sxy / sxx;
    double sw = 0, mx = 0, my = 0;
    for (std::size_t k = j; k < n; ++k) sw += w[k], mx += w[k] * e[k], my += w[k] * s[k];
    mx /= sw, my /= sw;
    double cxy = 0, cxx = 0;
    for (std::size_t k = j; k < n; ++k)
      cxy += w[k] * (e[k] - mx) * (s[k] - my), cxx += w[k] * (e[k] - mx) * (e[k] - mx);
    const double k2 = cxy / cxx;
    const double c = my - k2 * mx;  // segment 2: sigma = k2 e + c, c = (k1 - k2) b
    if (!(k1 != k2)) continue;
    const double b = c / (k1 - k2);
    if (b > e[j - 1] && b < e[j]) consider(k1, b, k2);
  }
  if (!std::isfinite(best_r2)) throw Error("", "fit: the curve has no bilinear least-squares fit");
  best.rms_pa = std::sqrt(ssr(e, s, std::vector<double>(n, 1.0), best.k1_pa, best.turning_strain, best.k2_pa) /
                          static_cast<double>(n));
  return best;
}

double fit_linear(const std::vector<double>& e, const std::vector<double>& s) {
  check_curve(e, s, 1);
  double sxy = 0, sxx = 0;
  for (std::size_t i = 0; i < e.size(); ++i) sxy += e[i] * s[i], sxx += e[i] * e[i];
  return sxy / sxx;
}

}  // namespace orthosim::tune
