#include "libmodel/tune/anneal.h"

#include "libmodel/format/types.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <random>

namespace orthosim::tune {

namespace {

using Clock = std::chrono::steady_clock;

// uniform in [0, 1) from the top 53 bits: the same on every platform
double uniform(std::mt19937_64& rng) { return static_cast<double>(rng() >> 11) * 0x1.0p-53; }

// x + d reflected into [0, 1]
double reflect(double x) {
  for (int k = 0; k < 8 && (x < 0 || x > 1); ++k) x = x < 0 ? -x : 2 - x;
  return std::clamp(x, 0.0, 1.0);
}

void check(const AnnealOptions& o, const std::vector<double>& x0) {
  if (x0.empty()) throw Error("", "anneal: no variables");
  for (double v : x0)
    if (!(v >= 0 && v <= 1)) throw Error("", "anneal: the start point must lie in the unit box");
  if (!(o.t0 >= 0)) throw Error("", "anneal: t0 must be >= 0");
  if (!(o.cooling > 0 && o.cooling < 1)) throw Error("", "anneal: cooling must be in (0, 1)");
  if (o.sweeps_per_adjust < 1 || o.adjusts_per_stage < 1 || o.stall_stages < 1)
    throw Error("", "anneal: sweeps, adjustments and stall stages must be >= 1");
  if (!(o.initial_step > 0 && o.initial_step <= 1)) throw Error("", "anneal: initial_step must be in (0, 1]");
  if (!(o.min_step > 0 && o.min_step <= o.initial_step)) throw Error("", "anneal: min_step must be in (0, initial_step]");
  if (!(o.restart_heat > 0 && o.restart_heat <= 1)) throw Error("", "anneal: restart_heat must be in (0, 1]");
  if (!(o.t_min > 0 && o.t_min < 1)) throw Error("", "anneal: t_min must be in (0, 1)");
  if (o.walk_sweeps < 0) throw Error("", "anneal: walk_sweeps must be >= 0");
  if (o.max_evaluations < 0) throw Error("", "anneal: max_evaluations must be >= 0");
  if (!(o.budget_s >= 0)) throw Error("", "anneal: budget_s must be >= 0");
}

struct Stop {};  // unwinds the loops once a limit is reached

}  // namespace

AnnealResult anneal(const std::function<double(const std::vector<double>&)>& f, const std::vector<double>& x0,
                    const AnnealOptions& o, const std::function<bool(double)>& done) {
  check(o, x0);
  const auto start = Clock::now();
  const std::size_t n = x0.size();
  std::mt19937_64 rng(o.seed);
  AnnealResult r;
  auto elapsed = [&] { return std::chrono::duration<double>(Clock::now() - start).count(); };
  auto limited = [&] {
    if (o.max_evaluations > 0 && r.evaluations >= o.max_evaluations) return r.stop = "evaluations", true;
    if (o.budget_s > 0 && elapsed() >= o.budget_s) return r.stop = "budget", true;
    return false;
  };
  // every evaluation goes through here: counts, keeps the best, checks the target
  auto eval = [&](const std::vector<double>& x) {
    if (limited()) throw Stop{};
    const double v = f(x);
    ++r.evaluations;
    const double fv = std::isfinite(v) ? v : std::numeric_limits<double>::max();
    if (r.x.empty() || fv < r.f) {
      r.x = x;
      r.f = fv;
      r.trace.push_back({r.evaluations, elapsed(), fv});
      if (done && done(fv)) {
        r.stop = "target";
        throw Stop{};
      }
    }
    return fv;
  };

  try {
    std::vector<double> x = x0;
    double fx = eval(x);
    // initial temperature: 80 % acceptance of the mean uphill move of a sample
    double T0 = o.t0;
    if (!(T0 > 0)) {
      double up = 0;
      int n_up = 0;
      for (std::size_t k = 0; k < std::max<std::size_t>(2 * n, 8); ++k) {
        std::vector<double> y = x;
        const std::size_t j = k % n;
        y[j] = reflect(y[j] + (2 * uniform(rng) - 1) * o.initial_step);
        const double d = eval(y) - fx;
        if (d > 0 && d < 1e300) up += d, ++n_up;
      }
      T0 = n_up ? -(up / n_up) / std::log(0.8) : 1.0;
      x = r.x, fx = r.f;
    }
    // one walk: from x at T0 with fresh steps; stages restart from the walk's
    // own best point, so that a fresh walk is not pulled back to the old basin
    const std::int64_t walk_evals = static_cast<std::int64_t>(o.walk_sweeps) * static_cast<std::int64_t>(n);
    for (;;) {
      const std::int64_t walk_start = r.evaluations;
      std::vector<double> wx = x;
      double wf = fx;
      double T = T0;
      std::vector<double> v(n, o.initial_step);
      std::vector<int> accepted(n, 0);
      double stage_best = wf;
      int stalled = 0;
      while (walk_evals == 0 || r.evaluations - walk_start < walk_evals) {
        for (int a = 0; a < o.adjusts_per_stage; ++a) {
          std::fill(accepted.begin(), accepted.end(), 0);
          for (int s = 0; s < o.sweeps_per_adjust; ++s)
            for (std::size_t j = 0; j < n; ++j) {
              std::vector<double> y = x;
              y[j] = reflect(y[j] + (2 * uniform(rng) - 1) * v[j]);
              const double fy = eval(y);
              const double u = uniform(rng);  // drawn on every trial: the stream does not depend on the outcome
              if (fy < wf) wx = y, wf = fy;
              if (fy <= fx || u < std::exp(-(fy - fx) / T)) {
                x = std::move(y);
                fx = fy;
                ++accepted[j];
              }
            }
          // Corana's step rule
          for (std::size_t j = 0; j < n; ++j) {
            const double ratio = static_cast<double>(accepted[j]) / o.sweeps_per_adjust;
            if (ratio > 0.6) v[j] *= 1 + 2 * (ratio - 0.6) / 0.4;
            else if (ratio < 0.4) v[j] /= 1 + 2 * (0.4 - ratio) / 0.4;
            v[j] = std::clamp(v[j], o.min_step, 1.0);
          }
        }
        // cooling: next stage from the walk's best point
        ++r.stages;
        T *= o.cooling;
        x = wx, fx = wf;
        if (wf < stage_best - o.stall_tolerance * std::max(1.0, std::abs(stage_best))) {
          stage_best = wf;
          stalled = 0;
        } else {
          ++stalled;
        }
        if (stalled >= o.stall_stages || T < o.t_min * T0) {
          // restart: reheat and widen the steps again
          ++r.restarts;
          T = o.restart_heat * T0;
          std::fill(v.begin(), v.end(), o.initial_step);
          stalled = 0;
          stage_best = wf;
        }
      }
      // a fresh walk from a random point of the box
      ++r.walks;
      for (double& xi : x) xi = uniform(rng);
      fx = eval(x);
    }
  } catch (const Stop&) {
  }
  r.seconds = elapsed();
  return r;
}

}  // namespace orthosim::tune
