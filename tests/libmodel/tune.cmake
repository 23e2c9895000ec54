# tune (issue 7): library tests on analytic lattices and synthetic curves, the
# Table 1 / tissue-table accuracy checks, the CLI tests, the benchmark.
if(TARGET orthosim_tune)
  orthosim_add_test(tune_test SOURCES libmodel/tune_test.cpp LIBS orthosim_tune)
  orthosim_add_test(tune_cli_test SOURCES libmodel/tune_cli_test.cpp LIBS orthosim_tune CLI)
  orthosim_add_bench(tune_bench SOURCES bench/tune_bench.cpp LIBS orthosim_tune)
endif()
