# `orthosim pipeline` and its work-folder cache (issue 11).
orthosim_add_test(pipeline_test SOURCES tools/pipeline_test.cpp LIBS orthosim_pipeline CLI)
