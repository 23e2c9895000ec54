// orthosim: one executable, one subcommand per pipeline stage.
#include "libmodel/format/atomic.h"
#include "tools/common.h"

#include <csignal>
#include <pthread.h>
#include <unistd.h>

#include <iostream>
#include <thread>

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

// Interrupts (Ctrl-C, SIGTERM, SIGHUP) go to one thread that removes the
// temporary outputs not yet committed and then ends the process by the same
// signal; every other thread blocks them (an interrupted build left a 300 MB
// ".model.h5.tmp-*" beside the model). In a thread of its own, not a handler,
// so that the clean-up may lock and use the file system freely. Children
// (pipeline's parallel stages) get the default mask back at spawn.
void handle_interrupts() {
  static sigset_t set;
  sigemptyset(&set);
  for (int s : {SIGINT, SIGTERM, SIGHUP}) sigaddset(&set, s);
  if (pthread_sigmask(SIG_BLOCK, &set, nullptr) != 0) return;
  std::thread([] {
    int sig = 0;
    if (sigwait(&set, &sig) != 0) return;
    orthosim::remove_uncommitted_outputs();
    std::signal(sig, SIG_DFL);
    pthread_sigmask(SIG_UNBLOCK, &set, nullptr);
    ::kill(::getpid(), sig);  // this thread alone takes it now: the default action ends the process
    ::_exit(128 + sig);
  }).detach();
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
  handle_interrupts();  // before any other thread exists, so that all inherit the mask
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
