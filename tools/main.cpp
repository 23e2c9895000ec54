// orthosim: one executable, one subcommand per pipeline stage.
#include "tools/common.h"

#include <iostream>

namespace orthosim::cli {
#define ORTHOSIM_DECLARE(name) void add_##name##_command(CLI::App& app);
ORTHOSIM_DECLARE(phantom)
ORTHOSIM_DECLARE(inspect)
ORTHOSIM_DECLARE(segment)
ORTHOSIM_DECLARE(surface)
ORTHOSIM_DECLARE(remesh)
ORTHOSIM_DECLARE(build)
ORTHOSIM_DECLARE(vessels)
ORTHOSIM_DECLARE(tune)
ORTHOSIM_DECLARE(run)
ORTHOSIM_DECLARE(bench)
ORTHOSIM_DECLARE(pipeline)
#undef ORTHOSIM_DECLARE

void register_commands(CLI::App& app) {
#ifdef ORTHOSIM_HAVE_PHANTOM
  add_phantom_command(app);
#endif
#ifdef ORTHOSIM_HAVE_INSPECT
  add_inspect_command(app);
#endif
#ifdef ORTHOSIM_HAVE_SEGMENT
  add_segment_command(app);
#endif
#ifdef ORTHOSIM_HAVE_SURFACE
  add_surface_command(app);
#endif
#ifdef ORTHOSIM_HAVE_REMESH
  add_remesh_command(app);
#endif
#ifdef ORTHOSIM_HAVE_BUILD
  add_build_command(app);
#endif
#ifdef ORTHOSIM_HAVE_VESSELS
  add_vessels_command(app);
#endif
#ifdef ORTHOSIM_HAVE_TUNE
  add_tune_command(app);
#endif
#ifdef ORTHOSIM_HAVE_RUN
  add_run_command(app);
#endif
#ifdef ORTHOSIM_HAVE_BENCH
  add_bench_command(app);
#endif
#ifdef ORTHOSIM_HAVE_PIPELINE
  add_pipeline_command(app);
#endif
}

}  // namespace orthosim::cli

namespace orthosim::cli {
namespace {

// one line, exit 2, whatever CLI11 would have printed
int parse_error(CLI::App& app, const CLI::ParseError& e) {
  std::string sub;
  for (auto* s : app.get_subcommands()) sub = " " + s->get_name();
  std::string what = e.what();
  for (auto& c : what)
    if (c == '\n') c = ' ';
  std::cerr << "orthosim" << sub << ": error: " << what << "\n";
  return 2;
}

}  // namespace

int run_command(const std::vector<std::string>& args) {
  CLI::App app{"orthosim"};
  app.require_subcommand(1);
  register_commands(app);
  std::vector<std::string> reversed(args.rbegin(), args.rend());  // CLI11 takes them last first
  exit_code() = 0;
  try {
    app.parse(reversed);
  } catch (const CLI::ParseError& e) {
    if (e.get_exit_code() == 0) return 0;  // --help and --version
    return parse_error(app, e);
  }
  return exit_code();
}

}  // namespace orthosim::cli

int main(int argc, char** argv) {
  using namespace orthosim::cli;
  for (int i = 0; i < argc; ++i) command_line() += (i ? " " : "") + std::string(argv[i]);
  CLI::App app{"orthosim: colour cryosection stacks to simulation-ready surgical models, and their runtime"};
  app.set_version_flag("--version", std::string("orthosim ") + ORTHOSIM_VERSION);
  app.require_subcommand(1);
  register_commands(app);
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForAllHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForVersion& e) {
    return app.exit(e);
  } catch (const CLI::ParseError& e) {
    return parse_error(app, e);
  }
  return exit_code();
}
