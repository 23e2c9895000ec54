# orthosim_vessels: centreline tree -> Bezier tube tree with bifurcation
# patches (docs/vessels.md). CGAL is confined to vessels_cgal.cpp (the
# benchmark's mean-curvature-flow peer); the tube's self-intersection count is
# orthosim_surface's (one exact pair test for every surface the pipeline makes).
add_library(orthosim_vessels STATIC
  ${CMAKE_CURRENT_LIST_DIR}/skeleton.cpp
  ${CMAKE_CURRENT_LIST_DIR}/graph.cpp
  ${CMAKE_CURRENT_LIST_DIR}/centreline.cpp
  ${CMAKE_CURRENT_LIST_DIR}/bezier.cpp
  ${CMAKE_CURRENT_LIST_DIR}/tube.cpp
  ${CMAKE_CURRENT_LIST_DIR}/vessels.cpp
  ${CMAKE_CURRENT_LIST_DIR}/evaluate.cpp
  ${CMAKE_CURRENT_LIST_DIR}/vessels_cgal.cpp)
target_link_libraries(orthosim_vessels PUBLIC orthosim_core orthosim_flags
                      PRIVATE orthosim_surface CGAL::CGAL TBB::tbb nlohmann_json::nlohmann_json)
