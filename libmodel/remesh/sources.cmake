# orthosim_remesh: quad re-parameterisation of tube-like surfaces, layer
# correspondence, texture baking and viewer exports. CGAL is confined to
# remesh_cgal.cpp (distances) and containment.cpp (exact predicates), OpenCV to texture.cpp, assimp to export.cpp.
add_library(orthosim_remesh STATIC
  ${CMAKE_CURRENT_LIST_DIR}/topology.cpp
  ${CMAKE_CURRENT_LIST_DIR}/remesh.cpp
  ${CMAKE_CURRENT_LIST_DIR}/remesh_cgal.cpp
  ${CMAKE_CURRENT_LIST_DIR}/containment.cpp
  ${CMAKE_CURRENT_LIST_DIR}/texture.cpp
  ${CMAKE_CURRENT_LIST_DIR}/export.cpp)
target_link_libraries(orthosim_remesh PUBLIC orthosim_core PRIVATE orthosim_segment CGAL::CGAL ${OpenCV_LIBS} assimp::assimp TBB::tbb)
target_include_directories(orthosim_remesh SYSTEM PRIVATE ${OpenCV_INCLUDE_DIRS})
