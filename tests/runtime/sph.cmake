# weakly compressible SPH blood (issue 9): kernels, neighbour grid, hydrostatic
# column, dam break (Martin & Moyce 1952), Poiseuille start-up (Morris et al.
# 1997), conservation, determinism, robustness, emitters, drains, walls,
# two-way coupling, the colour-field surface and its .vtp output.
orthosim_add_test(runtime_sph_test SOURCES runtime/sph_test.cpp LIBS orthosim_runtime)

# steps per second against particle count (the paper's Fig. 3b), neighbour
# counts and density error; --dam-break: the resolution study; --scene: the
# integrated paper scene (39x9x4 lattice + 5 000 particles + a bleeding cut)
orthosim_add_bench(sph_bench SOURCES bench/sph_bench.cpp LIBS orthosim_runtime orthosim_runtime_testing)
