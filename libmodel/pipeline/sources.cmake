# orthosim_pipeline: the work-folder cache of `orthosim pipeline` (issue 11).
add_library(orthosim_pipeline STATIC ${CMAKE_CURRENT_LIST_DIR}/cache.cpp)
target_link_libraries(orthosim_pipeline PUBLIC orthosim_core orthosim_flags PRIVATE nlohmann_json::nlohmann_json)
