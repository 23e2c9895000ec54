# surface: analytic solids, the phantom's tissues against their analytic
# interfaces, determinism, and the CLI (runs the executable); the benchmark,
# with VTK flying edges side by side when ORTHOSIM_WITH_VTK_PEER is ON.
if(TARGET orthosim_surface AND TARGET orthosim_phantom)
  orthosim_add_test(surface_test SOURCES libmodel/surface_test.cpp LIBS orthosim_surface orthosim_phantom orthosim_segment CLI)
  orthosim_add_bench(surface_bench SOURCES bench/surface_bench.cpp LIBS orthosim_surface orthosim_phantom)
  if(TARGET surface_bench AND ORTHOSIM_WITH_VTK_PEER)
    target_link_libraries(surface_bench PRIVATE VTK::FiltersCore VTK::FiltersGeneral VTK::CommonDataModel)
    target_compile_definitions(surface_bench PRIVATE ORTHOSIM_HAVE_VTK_PEER)
  endif()
endif()
