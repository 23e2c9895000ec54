# vessels: library tests on analytic tubes and the phantom, CLI tests on a
# small phantom label volume, the benchmark (time and accuracy against the
# CGAL mean-curvature-flow skeleton).
if(TARGET orthosim_vessels AND TARGET orthosim_phantom)
  orthosim_add_test(vessels_test SOURCES libmodel/vessels_test.cpp LIBS orthosim_vessels orthosim_phantom orthosim_segment)
  orthosim_add_test(vessels_cli_test SOURCES libmodel/vessels_cli_test.cpp LIBS orthosim_phantom CLI)
endif()
orthosim_add_bench(vessels_bench SOURCES bench/vessels_bench.cpp LIBS orthosim_vessels orthosim_phantom)
