# orthosim_runtime: the loader and the mass-spring solver (no CGAL, no OpenCV).
target_sources(orthosim_runtime PRIVATE
  ${CMAKE_CURRENT_LIST_DIR}/model.cpp
  ${CMAKE_CURRENT_LIST_DIR}/state.cpp
  ${CMAKE_CURRENT_LIST_DIR}/solver.cpp
  ${CMAKE_CURRENT_LIST_DIR}/loader.cpp
  ${CMAKE_CURRENT_LIST_DIR}/scene.cpp
  ${CMAKE_CURRENT_LIST_DIR}/vtk.cpp
  ${CMAKE_CURRENT_LIST_DIR}/cut.cpp
  ${CMAKE_CURRENT_LIST_DIR}/obstacles.cpp)
# sqrt in the spring loops compiles to one instruction without an errno path
target_compile_options(orthosim_runtime PRIVATE -fno-math-errno)

# orthosim_runtime_testing: models built in code and a reference static
# solver, shared by the runtime's tests and benchmarks (not by the runtime).
add_library(orthosim_runtime_testing STATIC
  ${CMAKE_CURRENT_LIST_DIR}/testing/lattice.cpp
  ${CMAKE_CURRENT_LIST_DIR}/testing/newton.cpp
  ${CMAKE_CURRENT_LIST_DIR}/testing/stress.cpp
  ${CMAKE_CURRENT_LIST_DIR}/testing/fluid_ball.cpp)
target_link_libraries(orthosim_runtime_testing PUBLIC orthosim_runtime orthosim_format orthosim_flags Eigen3::Eigen)

# orthosim_lattice: writes a layered lattice block as a model file (a runnable
# example, and a model for `orthosim run` before the builder's is at hand).
add_executable(orthosim_lattice ${CMAKE_CURRENT_LIST_DIR}/testing/make_lattice_main.cpp)
target_link_libraries(orthosim_lattice PRIVATE orthosim_runtime_testing orthosim_flags)

# weakly compressible SPH blood (issue 9): the hot loops use GCC vector
# extensions (4 lanes) and target clones; -Wno-psabi silences the note on
# passing 32-byte vectors by value between inlined helpers.
target_sources(orthosim_runtime PRIVATE ${CMAKE_CURRENT_LIST_DIR}/sph.cpp ${CMAKE_CURRENT_LIST_DIR}/sph_surface.cpp)
set_source_files_properties(${CMAKE_CURRENT_LIST_DIR}/sph.cpp ${CMAKE_CURRENT_LIST_DIR}/sph_surface.cpp
                            PROPERTIES COMPILE_OPTIONS "-Wno-psabi")
