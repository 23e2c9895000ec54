#include "libmodel/tune/plot.h"

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>

namespace orthosim::tune {

namespace {

// the law sigma(e) of a target or a fit, in Pa
double law(const Target& q, double k1, double b, double k2, double k, double e) {
  if (!q.biphasic) return k * e;
  return e < b ? k1 * e : k1 * b + k2 * (e - b);
}

std::string num(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4g", v);
  return buf;
}

}  // namespace

void write_curve_png(const std::string& path, const TuneResult& r, const PlotOptions& o) {
  if (o.width_px < 200 || o.height_px < 150) throw Error(path, "plot: the image must be at least 200 x 150");
  const Curve& c = r.measured.curve;
  if (c.strain.empty()) throw Error(path, "plot: the result holds no measured curve");
  const Target& q = r.target;
  const double emax = c.strain.back();
  // the curves, sampled finely for the laws
  const int n = 200;
  auto sample = [&](const std::function<double(double)>& f) {
    std::vector<cv::Point2d> p;
    for (int i = 0; i <= n; ++i) p.emplace_back(emax * i / n, f(emax * i / n));
    return p;
  };
  const auto target = sample([&](double e) { return law(q, q.k1_pa, q.turning_strain, q.k2_pa, q.k_pa, e); });
  std::vector<cv::Point2d> achieved;
  if (r.measured.p.size() == q.values().size()) {
    const auto& p = r.measured.p;
    achieved = q.biphasic ? sample([&](double e) { return law(q, p[0], p[1], p[2], 0, e); })
                          : sample([&](double e) { return law(q, 0, 0, 0, p[0], e); });
  }
  std::vector<cv::Point2d> measured{{0, 0}}, untuned{{0, 0}};
  for (std::size_t i = 0; i < c.strain.size(); ++i) measured.emplace_back(c.strain[i], c.stress_pa[i]);
  for (std::size_t i = 0; i < r.untuned.curve.strain.size(); ++i)
    untuned.emplace_back(r.untuned.curve.strain[i], r.untuned.curve.stress_pa[i]);
  double smax = 0;
  for (const std::vector<cv::Point2d>* v : std::initializer_list<const std::vector<cv::Point2d>*>{&target, &achieved, &measured, &untuned})
    for (const auto& p : *v) smax = std::max(smax, p.y);
  if (!(smax > 0) || !std::isfinite(smax)) smax = 1;
  smax *= 1.05;

  // axes: margins for the labels
  const int W = o.width_px, H = o.height_px, left = 80, right = 20, top = 40, bottom = 60;
  cv::Mat img(H, W, CV_8UC3, cv::Scalar(255, 255, 255));
  auto px = [&](const cv::Point2d& p) {
    return cv::Point(static_cast<int>(std::lround(left + (W - left - right) * p.x / emax)),
                     static_cast<int>(std::lround(H - bottom - (H - top - bottom) * p.y / smax)));
  };
  const cv::Scalar black(0, 0, 0), grey(200, 200, 200);
  const int font = cv::FONT_HERSHEY_SIMPLEX;
  for (int i = 0; i <= 5; ++i) {
    const double e = emax * i / 5, s = smax * i / 5;
    cv::line(img, px({e, 0}), px({e, smax}), grey, 1);
    cv::line(img, px({0, s}), px({emax, s}), grey, 1);
    cv::putText(img, num(e), px({e, 0}) + cv::Point(-12, 20), font, 0.4, black, 1, cv::LINE_AA);
    cv::putText(img, num(s / 1e3), cv::Point(8, px({0, s}).y + 4), font, 0.4, black, 1, cv::LINE_AA);
  }
  cv::rectangle(img, px({0, smax}), px({emax, 0}), black, 1);
  cv::putText(img, "nominal strain", cv::Point(W / 2 - 50, H - 15), font, 0.5, black, 1, cv::LINE_AA);
  cv::putText(img, "stress (kPa)", cv::Point(8, top - 12), font, 0.5, black, 1, cv::LINE_AA);
  cv::putText(img, o.title, cv::Point(W / 2 - 40, top - 12), font, 0.6, black, 1, cv::LINE_AA);

  auto polyline = [&](const std::vector<cv::Point2d>& v, const cv::Scalar& colour, int thickness) {
    for (std::size_t i = 1; i < v.size(); ++i) cv::line(img, px(v[i - 1]), px(v[i]), colour, thickness, cv::LINE_AA);
  };
  // colours (BGR): target black dashed-looking thick grey, achieved red, measured blue dots, untuned orange
  const cv::Scalar c_target(60, 60, 60), c_achieved(40, 40, 220), c_measured(200, 90, 20), c_untuned(0, 160, 255);
  polyline(untuned, c_untuned, 1);
  polyline(target, c_target, 4);
  polyline(achieved, c_achieved, 2);
  for (const auto& p : measured) cv::circle(img, px(p), 4, c_measured, cv::FILLED, cv::LINE_AA);

  // legend with the values
  auto keys = q.keys();
  std::string tv = "target", av = "achieved";
  const auto qv = q.values();
  for (std::size_t i = 0; i < keys.size(); ++i) {
    const double scale = keys[i] == "turning_strain" ? 1.0 : 1e-3;
    tv += " " + keys[i] + " " + num(qv[i] * scale);
    if (i < r.measured.p.size()) av += " " + keys[i] + " " + num(r.measured.p[i] * scale);
  }
  int y = top + 20;
  auto entry = [&](const std::string& text, const cv::Scalar& colour) {
    cv::line(img, cv::Point(left + 10, y - 4), cv::Point(left + 40, y - 4), colour, 3, cv::LINE_AA);
    cv::putText(img, text, cv::Point(left + 48, y), font, 0.42, black, 1, cv::LINE_AA);
    y += 20;
  };
  entry(tv, c_target);
  entry(av + " (psi " + num(r.psi) + ", " + r.method + ")", c_achieved);
  entry("measured (virtual experiment, tuned)", c_measured);
  entry("untuned rule", c_untuned);
  try {
    if (!cv::imwrite(path, img)) throw Error(path, "plot: could not write the PNG");
  } catch (const cv::Exception& e) {
    throw Error(path, std::string("plot: ") + e.what());
  }
}

}  // namespace orthosim::tune
