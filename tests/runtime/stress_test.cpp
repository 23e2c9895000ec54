// The stability stress test, small: dt x K2/K1 x neighbour mass ratio x
// degenerate springs, for each integrator mode. No NaN ever reaches the
// state; implicit Euler stays bounded at dt = 1/30 s; automatic substeps
// never fail. The large sweep and the docs table: tests/bench/runtime_bench.cpp.
#include "runtime/testing/stress.h"

#include <gtest/gtest.h>

#include <cstdio>
#include <map>

namespace orthosim::runtime::testing {
namespace {

TEST(Stress, SmallSweepNeverProducesNaN) {
  StressSize size;
  size.nu = 4, size.nv = 3, size.layers = 3;
  size.steps = 8;
  size.max_substeps = 1 << 15;
  std::map<std::string, std::map<std::string, int>> table;  // mode -> verdict -> cells
  double wall = 0;
  for (StressMode mode : {StressMode::symplectic_auto, StressMode::symplectic_fixed, StressMode::implicit})
    for (Real dt : {1e-5, 1e-3, 1.0 / 30})
      for (Real kr : {1.0, 1e2, 1e4})
        for (Real mr : {1.0, 1e2, 1e4})
          for (Degenerate d : {Degenerate::none, Degenerate::zero, Degenerate::near_zero}) {
            StressCase c{dt, kr, mr, d, mode};
            const auto r = run_stress_case(c, size);
            wall += r.wall_s;
            SCOPED_TRACE(std::string(to_string(mode)) + " dt " + std::to_string(dt) + " K2/K1 " + std::to_string(kr) +
                         " mass ratio " + std::to_string(mr) + " degenerate " + to_string(d));
            EXPECT_FALSE(r.nan_seen);
            if (mode == StressMode::implicit) {
              EXPECT_TRUE(r.bounded) << "max displacement " << r.max_displacement << " m";
              EXPECT_EQ(r.counters.failed, 0);
            }
            if (mode == StressMode::symplectic_auto) {
              EXPECT_EQ(r.counters.failed, 0) << r.verdict();
            }
            ++table[to_string(mode)][r.verdict()];
          }
  for (const auto& [mode, counts] : table) {
    std::printf("%-28s", mode.c_str());
    for (const char* v : {"stable", "recovered", "failed"}) std::printf(" %s %d", v, counts.count(v) ? counts.at(v) : 0);
    std::printf("\n");
  }
  std::printf("sweep wall time %.2f s\n", wall);
}

}  // namespace
}  // namespace orthosim::runtime::testing
