// Simulated annealing over a box (the paper's optimiser, §4.1; docs/tune.md).
//
// Continuous SA after Corana, Marchesi, Martini & Ridella, ACM TOMS 13 (1987):
// the variables live in the unit box [0, 1]^n. Each trial moves one
// coordinate j (in turn) by u v_j, u uniform in (-1, 1), reflected into the
// box, and is accepted by the Metropolis rule at temperature T. Adaptive
// step: after `sweeps_per_adjust` sweeps over the coordinates each v_j is
// widened if more than 60 % of its moves were accepted and narrowed below
// 40 % (Corana's rule, c = 2), within [min_step, 1]. Cooling schedule: after
// `adjusts_per_stage` adjustments T <- cooling x T and the walk restarts from
// the best point found. Restarts: when the best value has not improved by
// more than `stall_tolerance` for `stall_stages` stages, or T fell below
// `t_min`, the annealer reheats to restart_heat x T0 with fresh steps, from
// the best point. Fresh walks: after `walk_sweeps` sweeps (walk_sweeps x n
// evaluations) a walk that has not met the stopping target is abandoned and
// a new one starts from a uniformly random point of the box at T0 with fresh
// steps; each walk's stages restart from that walk's own best point, so a
// walk stuck in a basin (a narrow valley, or a minimum pinned on the box
// boundary) does not hold the search. The overall best is kept across walks.
// Stops when `done(best)` says so (the stopping target), after
// max_evaluations, or after budget_s seconds of wall time.
//
// Seeded and reproducible: one std::mt19937_64 from `seed`, uniform numbers
// from its raw 64-bit output (no implementation-defined distributions), so a
// run that stops on the target or on max_evaluations is the same on every
// platform; a run cut by budget_s depends on the machine's speed.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

namespace orthosim::tune {

struct AnnealOptions {
  std::uint64_t seed = 1;
  double t0 = 0;                 // initial temperature; 0: set from a sample of moves (80 % uphill acceptance)
  double cooling = 0.8;          // T <- cooling x T per stage, (0, 1)
  int sweeps_per_adjust = 4;     // N_s: sweeps over all coordinates between step adjustments, >= 1
  int adjusts_per_stage = 2;     // N_T: step adjustments per temperature stage, >= 1
  double initial_step = 0.2;     // v_j at the start and after each restart (unit box), (0, 1]
  double min_step = 1e-9;        // smallest v_j
  int stall_stages = 4;          // restart after this many stages without improvement, >= 1
  double stall_tolerance = 1e-6; // an improvement smaller than this does not count
  double t_min = 1e-6;           // restart when T falls below t_min x T0
  double restart_heat = 0.1;     // reheat to restart_heat x T0, (0, 1]
  int walk_sweeps = 0;           // sweeps per walk before a fresh walk from a random point, >= 0; 0: one walk
  std::int64_t max_evaluations = 0;  // 0: no limit
  double budget_s = 0;           // wall-clock limit; 0: none
};

// One point of the convergence history: the best value after `evaluations`.
struct TracePoint {
  std::int64_t evaluations = 0;
  double seconds = 0;
  double best = 0;
};

struct AnnealResult {
  std::vector<double> x;          // best point (unit box)
  double f = 0;                   // its value
  std::int64_t evaluations = 0;
  int stages = 0;
  int restarts = 0;               // reheats within walks
  int walks = 0;                  // fresh walks started after the first
  double seconds = 0;
  std::string stop;               // "target" | "evaluations" | "budget"
  std::vector<TracePoint> trace;  // every improvement of the best value
};

// Minimises f over [0, 1]^n from x0 (inside the box). `done(best)` is the
// stopping target, checked after every improvement (may be empty). Throws
// Error("", ...) for bad options or an x0 outside the box.
AnnealResult anneal(const std::function<double(const std::vector<double>&)>& f, const std::vector<double>& x0,
                    const AnnealOptions& options, const std::function<bool(double)>& done = {});

}  // namespace orthosim::tune
