# orthosim_tune: spring-parameter optimisation (issue 7; docs/tune.md). NLopt only in tune.cpp, OpenCV only in plot.cpp.
add_library(orthosim_tune STATIC
  ${CMAKE_CURRENT_LIST_DIR}/anneal.cpp
  ${CMAKE_CURRENT_LIST_DIR}/experiment.cpp
  ${CMAKE_CURRENT_LIST_DIR}/fit.cpp
  ${CMAKE_CURRENT_LIST_DIR}/plot.cpp
  ${CMAKE_CURRENT_LIST_DIR}/tune.cpp)
target_link_libraries(orthosim_tune PUBLIC orthosim_core orthosim_msm PRIVATE NLopt::nlopt opencv_core opencv_imgproc opencv_imgcodecs)
