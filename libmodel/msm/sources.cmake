# orthosim_msm: the multilayer mass-spring builder (issue 5). CGAL only in project.cpp.
add_library(orthosim_msm STATIC
  ${CMAKE_CURRENT_LIST_DIR}/biphasic.cpp
  ${CMAKE_CURRENT_LIST_DIR}/build.cpp
  ${CMAKE_CURRENT_LIST_DIR}/cells.cpp
  ${CMAKE_CURRENT_LIST_DIR}/lattice.cpp
  ${CMAKE_CURRENT_LIST_DIR}/project.cpp
  ${CMAKE_CURRENT_LIST_DIR}/specimen.cpp
  ${CMAKE_CURRENT_LIST_DIR}/tetra.cpp)
target_link_libraries(orthosim_msm PUBLIC orthosim_core PRIVATE CGAL::CGAL)
