# orthosim_segment: colour slice stacks -> tissue label volume.
# OpenCV (decoding, Lab conversion), libjpeg, libpng and libtiff (decoding JPEG, PNG and TIFF regions, checking JPEG data) and TBB stay inside its .cpp files.
add_library(orthosim_segment STATIC
  ${CMAKE_CURRENT_LIST_DIR}/stack.cpp
  ${CMAKE_CURRENT_LIST_DIR}/colour.cpp
  ${CMAKE_CURRENT_LIST_DIR}/cleanup.cpp
  ${CMAKE_CURRENT_LIST_DIR}/segment.cpp
  ${CMAKE_CURRENT_LIST_DIR}/register.cpp)
target_link_libraries(orthosim_segment
  PUBLIC orthosim_core orthosim_flags
  PRIVATE opencv_core opencv_imgproc opencv_imgcodecs JPEG::JPEG PNG::PNG TIFF::TIFF TBB::tbb nlohmann_json::nlohmann_json)
