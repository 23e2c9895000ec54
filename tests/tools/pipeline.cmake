# `orthosim pipeline` and its work-folder cache (issue 11).
orthosim_add_test(pipeline_test SOURCES tools/pipeline_test.cpp LIBS orthosim_pipeline ${OpenCV_LIBS} CLI)
target_include_directories(pipeline_test SYSTEM PRIVATE ${OpenCV_INCLUDE_DIRS})
