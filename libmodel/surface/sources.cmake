# orthosim_surface: tissue label volume -> closed outward triangle surfaces
# (docs/surface.md). CGAL (decimation, self-intersections, distances) is
# confined to surface_cgal.cpp. STL I/O is libmodel/format/stl.h; the public
# link to orthosim_remesh serves the stage's users that go on to remesh's
# surface checks (its tests).
add_library(orthosim_surface STATIC
  ${CMAKE_CURRENT_LIST_DIR}/surface.cpp
  ${CMAKE_CURRENT_LIST_DIR}/surface_cgal.cpp)
target_link_libraries(orthosim_surface
  PUBLIC orthosim_core orthosim_flags orthosim_remesh
  PRIVATE CGAL::CGAL TBB::tbb nlohmann_json::nlohmann_json)
