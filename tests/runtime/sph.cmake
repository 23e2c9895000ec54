# SPH blood (issue 9; the EOS and PCISPH): kernels, neighbour grid, hydrostatic
# column, dam break (Martin & Moyce 1952), Poiseuille start-up (Morris et al.
# 1997), conservation, determinism, robustness, emitters, drains, walls,
# two-way coupling, the colour-field surface and its .vtp output.
orthosim_add_test(runtime_sph_test SOURCES runtime/sph_test.cpp LIBS orthosim_runtime orthosim_runtime_testing)

# steps per second against particle count (the paper's Fig. 3b), neighbour
# counts and density error; --dam-break: the resolution study; --scene: the
# integrated paper scene (39x9x4 lattice + 5 000 particles + a bleeding cut)
orthosim_add_bench(sph_bench SOURCES bench/sph_bench.cpp LIBS orthosim_runtime orthosim_runtime_testing)

# The SPH passes at -O0. runtime/sph.cpp compiles its hot loops twice
# (x86-64-v3 and baseline clones); a helper or lambda that takes a 32-byte
# vector and is not inlined into its clone is compiled for the baseline and
# reads its arguments from the wrong place, which only an unoptimised build
# shows (the code of 2026-11-25 crashed at -O0). Here sph.cpp at -O0 replaces
# the library's copy (an object file given to the linker wins over the
# archive member) and the conservation (EOS and PCISPH), crowded-list,
# determinism (Newtonian and Carreau) and kept-list (Verlet) tests run on it
# (~20 s).
add_library(orthosim_sph_O0 OBJECT ${CMAKE_SOURCE_DIR}/runtime/sph.cpp)
target_link_libraries(orthosim_sph_O0 PRIVATE orthosim_format orthosim_flags Eigen3::Eigen TBB::tbb)
target_compile_options(orthosim_sph_O0 PRIVATE -O0 -fno-math-errno -Wno-psabi)
add_executable(runtime_sph_O0_test runtime/sph_test.cpp $<TARGET_OBJECTS:orthosim_sph_O0>)
target_link_libraries(runtime_sph_O0_test PRIVATE orthosim_core orthosim_runtime orthosim_runtime_testing orthosim_flags GTest::gtest
                      GTest::gtest_main)
target_compile_definitions(runtime_sph_O0_test PRIVATE ORTHOSIM_BINARY="${CMAKE_BINARY_DIR}/tools/orthosim"
                           ORTHOSIM_SHARED_DIR="${CMAKE_SOURCE_DIR}/../shared")
add_test(NAME runtime_sph_O0_test
         COMMAND runtime_sph_O0_test
                 --gtest_filter=SphPhysics.Momentum*:SphPhysics.Crowded*:SphPhysics.Deterministic*:SphPhysics.Kept*
         WORKING_DIRECTORY ${CMAKE_CURRENT_BINARY_DIR})
set_tests_properties(runtime_sph_O0_test PROPERTIES TIMEOUT 900)
