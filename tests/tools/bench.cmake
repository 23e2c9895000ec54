# `orthosim bench` (issue 10): the harness on a real stage (build, msm_bench)
# and on stand-in programs (missing, failing, goal missed), bad usage.
orthosim_add_test(bench_test SOURCES tools/bench_test.cpp CLI)
target_compile_definitions(bench_test PRIVATE ORTHOSIM_BENCH_DIR="${CMAKE_BINARY_DIR}/tests"
                           ORTHOSIM_SOURCE_DIR="${CMAKE_SOURCE_DIR}")
if(TARGET msm_bench)
  add_dependencies(bench_test msm_bench)
  target_compile_definitions(bench_test PRIVATE ORTHOSIM_HAVE_MSM_BENCH)
endif()
