# orthosim_surface: tissue label volume -> closed outward triangle surfaces
# (docs/surface.md). CGAL (decimation, self-intersections, distances) is
# confined to surface_cgal.cpp. STL I/O is remesh's (read_stl, write_stl in
# libmodel/remesh/remesh.h), hence the public link to orthosim_remesh.
add_library(orthosim_surface STATIC
  ${CMAKE_CURRENT_LIST_DIR}/surface.cpp
  ${CMAKE_CURRENT_LIST_DIR}/surface_cgal.cpp)
target_link_libraries(orthosim_surface
  PUBLIC orthosim_core orthosim_flags orthosim_remesh
  PRIVATE CGAL::CGAL TBB::tbb nlohmann_json::nlohmann_json)
