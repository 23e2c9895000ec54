// The stability stress test shared by the test suite (small) and the
// benchmark (large): one lattice block per cell of
//   dt x stiffness ratio K2/K1 x neighbour mass ratio x degenerate springs
// loaded by gravity and a kinematic pull that stretches the skin past the
// biphasic turning point, run with one integrator mode.
//
// Model: a layered block (fixed bone sheet) of linear springs whose skin
// layer is biphasic with turning strain 0.02 and K2 = ratio * K1. Masses
// alternate in a checkerboard: light nodes base / sqrt(r), heavy ones
// base * sqrt(r), so neighbours differ by r. Degenerate springs: each skin
// node gets a twin at the same position (the spring between them has length
// 0 at rest) joined with rest length 0 ("zero") or 1e-9 m ("near_zero"), and
// the twin is also tied to the next skin node with rest length 0.
//
// Verdict per cell: "stable" (no stability event), "recovered" (events, all
// redone successfully), "failed" (some step gave up and was restored).
// `nan_seen` is true if any position or velocity was ever non-finite after a
// step: the runtime's contract is that it never is.
#pragma once

#include "runtime/solver.h"

#include <string>
#include <vector>

namespace orthosim::runtime::testing {

enum class Degenerate { none, zero, near_zero };
const char* to_string(Degenerate d);

enum class StressMode { symplectic_auto, symplectic_fixed, implicit };
const char* to_string(StressMode m);

struct StressCase {
  Real dt = 1e-3;               // s per step
  Real stiffness_ratio = 1;     // K2 / K1 of the skin
  Real mass_ratio = 1;          // between neighbours
  Degenerate degenerate = Degenerate::none;
  StressMode mode = StressMode::symplectic_auto;
};

struct StressSize {
  int nu = 4, nv = 3, layers = 3;
  int steps = 10;               // steps per cell; the pull reaches its full stretch at half of them
  int max_substeps = 1 << 16;   // per step
};

struct StressResult {
  bool nan_seen = false;
  bool bounded = true;          // every node stayed within 10 model extents of its rest position
  Counters counters;
  Real max_displacement = 0;    // m
  Real extent = 0;              // m
  double wall_s = 0;
  std::string verdict() const;  // stable | recovered | failed
};

StressResult run_stress_case(const StressCase& c, const StressSize& size);

}  // namespace orthosim::runtime::testing
