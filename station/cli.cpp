#include "station/cli.h"

#include <CLI/CLI.hpp>
#include <unistd.h>

#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <new>
#include <vector>

#include "core/atomic_file.h"
#include "core/error.h"
#include "station/commands.h"

#ifndef STATION_VERSION
#define STATION_VERSION "dev"
#endif

namespace station {

using namespace cli;

namespace cli {

extern "C" void on_interrupt(int) {
  remove_unfinished_outputs();
  static const char msg[] = "\nstation: interrupted; files being written were removed\n";
  [[maybe_unused]] auto n = ::write(2, msg, sizeof msg - 1);
  std::_Exit(130);
}

void default_interrupt_handling() {
  // A signal ignored when the program started (a job a script runs in the background,
  // nohup) stays ignored, as the default action would have left it.
  static const bool int_ignored = [] {
    struct sigaction old {};
    return ::sigaction(SIGINT, nullptr, &old) == 0 && old.sa_handler == SIG_IGN;
  }();
  static const bool term_ignored = [] {
    struct sigaction old {};
    return ::sigaction(SIGTERM, nullptr, &old) == 0 && old.sa_handler == SIG_IGN;
  }();
  std::signal(SIGINT, int_ignored ? SIG_IGN : on_interrupt);
  std::signal(SIGTERM, term_ignored ? SIG_IGN : on_interrupt);
}

}  // namespace cli

int run_cli(int argc, char** argv) {
  CLI::App app{"station: capture-to-mesh station for turntable 3D-scanning benches"};
  app.set_version_flag("--version", STATION_VERSION);
  app.require_subcommand(1);
  std::vector<Command> commands;
  add_capture_commands(app, commands);
  add_eval_commands(app, commands);
  add_register_commands(app, commands);
  add_surface_commands(app, commands);
  add_serve_commands(app, commands);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    if (e.get_exit_code() == 0) return app.exit(e);  // --help, --version
    std::fprintf(stderr, "station: %s\n", parse_error_line(app, e).c_str());
    return 2;
  }
  // Ctrl-C or a kill: one line, exit 130, no temporary or half-made output left
  // (`run` and `scan` stop after the step in progress first: cmd_capture.cpp).
  default_interrupt_handling();
  try {
    for (const Command& c : commands)
      if (*c.app) return c.run();
  } catch (const UsageError& e) {
    std::fprintf(stderr, "station: %s\n", e.what());
    return 2;
  } catch (const Error& e) {
    std::fprintf(stderr, "station: %s\n", e.what());
    return 1;
  } catch (const std::bad_alloc&) {
    std::fprintf(stderr, "station: out of memory\n");
    return 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "station: internal error: %s\n", e.what());
    return 1;
  }
  return 2;
}

}  // namespace station
