# The mass-spring builder (issue 5): library tests, the CLI test, the benchmark.
orthosim_add_test(msm_test SOURCES libmodel/msm_test.cpp LIBS orthosim_msm)
orthosim_add_test(msm_cli_test SOURCES tools/build_test.cpp LIBS orthosim_msm CLI)
orthosim_add_bench(msm_bench SOURCES bench/msm_bench.cpp LIBS orthosim_msm)
