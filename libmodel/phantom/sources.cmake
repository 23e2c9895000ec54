# orthosim_phantom: the CVH-like upper-limb phantom with exact ground truth.
# OpenCV (image files) and TBB stay inside its .cpp files.
add_library(orthosim_phantom STATIC
  ${CMAKE_CURRENT_LIST_DIR}/geometry.cpp
  ${CMAKE_CURRENT_LIST_DIR}/phantom.cpp)
target_link_libraries(orthosim_phantom
  PUBLIC orthosim_core orthosim_flags
  PRIVATE opencv_core opencv_imgcodecs TBB::tbb nlohmann_json::nlohmann_json)
