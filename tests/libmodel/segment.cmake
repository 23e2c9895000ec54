# segment: unit, accuracy (phantom truth) and real-slice tests; CLI tests on bad
# and good stacks; the benchmark (throughput, run time against error, memory).
orthosim_add_test(segment_test SOURCES libmodel/segment_test.cpp LIBS orthosim_segment orthosim_phantom)
orthosim_add_test(segment_cli_test SOURCES libmodel/segment_cli_test.cpp
                  LIBS orthosim_segment orthosim_phantom ${OpenCV_LIBS} CLI)
target_include_directories(segment_cli_test SYSTEM PRIVATE ${OpenCV_INCLUDE_DIRS})
orthosim_add_bench(segment_bench SOURCES bench/segment_bench.cpp
                   LIBS orthosim_segment orthosim_phantom TBB::tbb ${OpenCV_LIBS})
if(TARGET segment_bench)
  target_include_directories(segment_bench SYSTEM PRIVATE ${OpenCV_INCLUDE_DIRS})
endif()
# slice files read by region: each decoder's region against the whole slice cut
orthosim_add_test(stack_test SOURCES libmodel/stack_test.cpp LIBS orthosim_segment ${OpenCV_LIBS})
target_include_directories(stack_test SYSTEM PRIVATE ${OpenCV_INCLUDE_DIRS})
