// Slice registration: each slice's translation against the one before by
// phase correlation, the cumulative path's smooth part kept (the anatomy's own
// drift through the stack), the rest undone in whole pixels.
#include "libmodel/segment/segment.h"

#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>

namespace orthosim {

namespace {

// Rec. 601 luma of an RGB slice, as a float image.
cv::Mat luma(const std::vector<std::uint8_t>& rgb, int nx, int ny) {
  cv::Mat m(ny, nx, CV_32F);
  for (int y = 0; y < ny; ++y) {
    float* row = m.ptr<float>(y);
    const std::uint8_t* p = rgb.data() + static_cast<std::size_t>(y) * nx * 3;
    for (int x = 0; x < nx; ++x) row[x] = 0.299f * p[3 * x] + 0.587f * p[3 * x + 1] + 0.114f * p[3 * x + 2];
  }
  return m;
}

// The value at z of the least-squares line through (k, c[k]) for k in
// [z - w, z + w] clamped to the stack.
double local_line(const std::vector<double>& c, int z, int w) {
  const int n = static_cast<int>(c.size());
  const int a = std::max(0, z - w), b = std::min(n - 1, z + w);
  if (a == b) return c[static_cast<std::size_t>(z)];
  double sk = 0, sc = 0;
  for (int k = a; k <= b; ++k) sk += k, sc += c[static_cast<std::size_t>(k)];
  const double m = b - a + 1, kb = sk / m, cb = sc / m;
  double num = 0, den = 0;
  for (int k = a; k <= b; ++k) num += (k - kb) * (c[static_cast<std::size_t>(k)] - cb), den += (k - kb) * (k - kb);
  return cb + (den > 0 ? num / den : 0) * (z - kb);
}

}  // namespace

void validate(const RegisterOptions& o) {
  if (o.half_window < 1 || o.half_window > 100000) throw Error("", "register-window: must be in 1..100000 slices");
  if (!(o.max_shift_px > 0 && o.max_shift_px <= 1e6)) throw Error("", "register-max-shift: must be in (0, 1e6] pixels");
  if (!(o.min_response >= 0 && o.min_response < 1)) throw Error("", "register-min-response: must be in [0, 1)");
}

SliceRegistration register_slices(const SliceSource& src, const RegisterOptions& o) {
  validate(o);
  const auto t0 = std::chrono::steady_clock::now();
  const int nz = src.nz;
  SliceRegistration r;
  r.pairwise.assign(static_cast<std::size_t>(nz), {0.0, 0.0});
  r.response.assign(static_cast<std::size_t>(nz), 1.0);
  r.shift.assign(static_cast<std::size_t>(nz), {0, 0});
  if (nz < 2 || src.nx < 8 || src.ny < 8) return r;
  cv::Mat window;
  cv::createHanningWindow(window, cv::Size(src.nx, src.ny), CV_32F);
  // Each slice against the one and the two before it: a chain of neighbours
  // alone sums its errors (a slice where a branch ends matched 1.5 px off and
  // every later slice followed); the second baseline lets a robust fit see
  // such a match as the outlier it is.
  constexpr int kGaps = 2;
  struct Pair {
    int a = 0, b = 0;
    double dx = 0, dy = 0, response = 0;
    bool ok = false;
  };
  std::vector<Pair> pairs(static_cast<std::size_t>(nz) * kGaps);
  const int block = 8;  // consecutive slices per task, each re-reading the kGaps slices before it
  const int blocks = (nz - 1 + block - 1) / block;
  tbb::parallel_for(0, blocks, [&](int b) {
    const int z0 = 1 + b * block, z1 = std::min(nz, z0 + block);
    std::vector<std::uint8_t> rgb;
    std::vector<cv::Mat> before;  // luma of z - kGaps .. z - 1 (fewer at the start)
    for (int z = std::max(0, z0 - kGaps); z < z0; ++z) {
      src.read(z, rgb);
      before.push_back(luma(rgb, src.nx, src.ny));
    }
    for (int z = z0; z < z1; ++z) {
      src.read(z, rgb);
      cv::Mat cur = luma(rgb, src.nx, src.ny);
      for (int g = 1; g <= kGaps && g <= static_cast<int>(before.size()); ++g) {
        Pair& p = pairs[static_cast<std::size_t>(z) * kGaps + static_cast<std::size_t>(g - 1)];
        p.a = z - g, p.b = z;
        const cv::Point2d d = cv::phaseCorrelate(before[before.size() - static_cast<std::size_t>(g)], cur, window, &p.response);
        // a peak beyond the largest plausible shift is another structure's
        // match, not the slice's: left out (and counted)
        p.ok = std::isfinite(d.x) && std::isfinite(d.y) && std::isfinite(p.response) &&
               std::abs(d.x) <= g * o.max_shift_px && std::abs(d.y) <= g * o.max_shift_px;
        p.dx = d.x, p.dy = d.y;
      }
      before.push_back(std::move(cur));
      if (static_cast<int>(before.size()) > kGaps) before.erase(before.begin());
    }
  });
  std::vector<Pair> used;
  for (const Pair& p : pairs) {
    if (p.b == 0) continue;  // (unfilled: slice 0, or slice 1's second baseline)
    if (p.b - p.a == 1) {
      r.response[static_cast<std::size_t>(p.b)] = p.response;
      r.pairwise[static_cast<std::size_t>(p.b)] = {p.dx, p.dy};
    }
    // a flat correlation is no match (the phantom squeezed into 16 slices
    // matched 7 px off at a peak of 0.17; the sample's weakest good match
    // peaks at 0.17 too, so the line is drawn lower)
    if (p.ok && p.response >= o.min_response) {
      used.push_back(p);
    } else {
      ++r.rejected;
      if (p.b - p.a == 1) r.weak.push_back(p.b);
    }
  }
  // positions: least squares over every pair's difference, weighted by its
  // correlation peak, then reweighted (Huber, 0.5 px) against outliers; slice 0
  // at the origin; a slice with no pair stays where the one before it is
  std::vector<double> cx(static_cast<std::size_t>(nz), 0.0), cy(static_cast<std::size_t>(nz), 0.0);
  std::vector<double> w(used.size());
  for (std::size_t i = 0; i < used.size(); ++i) w[i] = std::max(used[i].response, 1e-3);
  const double tie = 1e-6;  // keeps every slice tied to its neighbour when its pairs are all gone
  for (int iteration = 0; iteration < 4; ++iteration) {
    std::vector<Eigen::Triplet<double>> t;
    Eigen::VectorXd bx = Eigen::VectorXd::Zero(nz), by = Eigen::VectorXd::Zero(nz);
    auto add = [&](int a, int b, double wt, double dx, double dy) {
      t.emplace_back(a, a, wt), t.emplace_back(b, b, wt), t.emplace_back(a, b, -wt), t.emplace_back(b, a, -wt);
      bx(a) -= wt * dx, bx(b) += wt * dx, by(a) -= wt * dy, by(b) += wt * dy;
    };
    for (std::size_t i = 0; i < used.size(); ++i) add(used[i].a, used[i].b, w[i], used[i].dx, used[i].dy);
    for (int z = 1; z < nz; ++z) add(z - 1, z, tie, 0, 0);
    t.emplace_back(0, 0, 1.0);  // slice 0 at the origin
    Eigen::SparseMatrix<double> A(nz, nz);
    A.setFromTriplets(t.begin(), t.end());
    Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt(A);
    if (ldlt.info() != Eigen::Success) throw Error(src.name, "slice registration: the shifts' least-squares system is singular");
    const Eigen::VectorXd px = ldlt.solve(bx), py = ldlt.solve(by);
    for (int z = 0; z < nz; ++z) cx[static_cast<std::size_t>(z)] = px(z), cy[static_cast<std::size_t>(z)] = py(z);
    for (std::size_t i = 0; i < used.size(); ++i) {
      const double ex = cx[static_cast<std::size_t>(used[i].b)] - cx[static_cast<std::size_t>(used[i].a)] - used[i].dx;
      const double ey = cy[static_cast<std::size_t>(used[i].b)] - cy[static_cast<std::size_t>(used[i].a)] - used[i].dy;
      const double e = std::hypot(ex, ey);
      w[i] = std::max(used[i].response, 1e-3) * (e > 0.5 ? 0.5 / e : 1.0);
    }
  }
  for (int z = 0; z < nz; ++z) {
    const auto zi = static_cast<std::size_t>(z);
    r.shift[zi] = {static_cast<int>(std::lround(local_line(cx, z, o.half_window) - cx[zi])),
                   static_cast<int>(std::lround(local_line(cy, z, o.half_window) - cy[zi]))};
    r.max_shift_px = std::max({r.max_shift_px, std::abs(r.shift[zi][0]), std::abs(r.shift[zi][1])});
    if (r.shift[zi][0] != 0 || r.shift[zi][1] != 0) ++r.moved;
  }
  r.min_response = *std::min_element(r.response.begin() + 1, r.response.end());
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return r;
}

SliceSource shifted_source(SliceSource src, std::vector<std::array<int, 2>> shift) {
  if (shift.size() != static_cast<std::size_t>(src.nz)) throw Error(src.name, "one shift per slice is needed");
  auto in = std::make_shared<SliceSource>(src);
  auto by = std::make_shared<std::vector<std::array<int, 2>>>(std::move(shift));
  src.read = [in, by](int z, std::vector<std::uint8_t>& rgb) {
    const auto [sx, sy] = (*by)[static_cast<std::size_t>(z)];
    if (sx == 0 && sy == 0) {
      in->read(z, rgb);
      return;
    }
    std::vector<std::uint8_t> raw;
    in->read(z, raw);
    const int nx = in->nx, ny = in->ny;
    rgb.resize(raw.size());
    // content moves by (sx, sy); the edge pixels fill what comes in (the gel)
    for (int y = 0; y < ny; ++y) {
      const int fy = std::clamp(y - sy, 0, ny - 1);
      for (int x = 0; x < nx; ++x) {
        const int fx = std::clamp(x - sx, 0, nx - 1);
        const std::size_t to = (static_cast<std::size_t>(y) * nx + x) * 3, from = (static_cast<std::size_t>(fy) * nx + fx) * 3;
        rgb[to] = raw[from], rgb[to + 1] = raw[from + 1], rgb[to + 2] = raw[from + 2];
      }
    }
  };
  return src;
}

}  // namespace orthosim
