# segment and surface: unit, accuracy (phantom truth) and CLI tests; benchmarks.
orthosim_add_test(segment_test SOURCES libmodel/segment_test.cpp LIBS orthosim_segment orthosim_phantom CLI)
