# runtime (issue 8): solver accuracy, conservation, determinism; lazy loading;
# scenes, tools and output; the stability stress test (small); `orthosim run`.
orthosim_add_test(runtime_solver_test SOURCES runtime/solver_test.cpp LIBS orthosim_runtime_testing)
orthosim_add_test(runtime_scene_test SOURCES runtime/scene_test.cpp runtime/loader_test.cpp LIBS orthosim_runtime_testing)
orthosim_add_test(runtime_stress_test SOURCES runtime/stress_test.cpp LIBS orthosim_runtime_testing)
orthosim_add_test(runtime_run_test SOURCES runtime/run_test.cpp LIBS orthosim_runtime_testing CLI)

# benchmarks: speed on the paper's lattice and a large one, memory bandwidth,
# run time against error and the stress sweep (--tables), Bullet btSoftBody
# side by side with -DORTHOSIM_WITH_BULLET_PEER=ON
orthosim_add_bench(runtime_bench SOURCES bench/runtime_bench.cpp LIBS orthosim_runtime_testing)
if(TARGET runtime_bench AND ORTHOSIM_WITH_BULLET_PEER)
  target_compile_definitions(runtime_bench PRIVATE ORTHOSIM_HAVE_BULLET)
  target_include_directories(runtime_bench SYSTEM PRIVATE ${BULLET_ROOT_DIR}/${BULLET_INCLUDE_DIR})
  target_link_libraries(runtime_bench PRIVATE BulletSoftBody BulletDynamics BulletCollision LinearMath)
endif()
orthosim_add_test(runtime_cut_test SOURCES runtime/cut_test.cpp LIBS orthosim_runtime_testing)
orthosim_add_test(runtime_bleeding_test SOURCES runtime/bleeding_test.cpp LIBS orthosim_runtime_testing)
