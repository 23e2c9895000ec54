# phantom_test: the phantom library and `orthosim phantom` (CLI: runs the executable).
orthosim_add_test(phantom_test SOURCES libmodel/phantom_test.cpp LIBS orthosim_phantom CLI)
