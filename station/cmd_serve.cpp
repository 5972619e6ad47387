// `station serve`: the station page and its API (station/serve.h, docs/serve.md).
#include <CLI/CLI.hpp>
#include <tbb/global_control.h>

#include <atomic>
#include <csignal>
#include <cstdlib>
#include <mutex>
#include <pthread.h>
#include <cstdio>
#include <memory>
#include <thread>
#include <unistd.h>

#include "core/atomic_file.h"
#include "station/commands.h"
#include "station/serve.h"

namespace station::cli {

namespace {

struct ServeArgs {
  ServeOptions options;
  std::string data = "out/station";
  std::string token_file;
};

/// SIGINT and SIGTERM are waited for on a thread of their own (no work in a signal
/// handler): the first stops the server and its jobs after the view or stage in
/// progress, a second aborts.
int cmd_serve(const Common& c, ServeArgs a) {
  const StationConfig cfg = load_common(c);
  a.options.data_dir = a.data;
  a.options.token_file = a.token_file;
  if (c.threads >= 0) a.options.threads = c.threads;
  else a.options.threads = cfg.threads;
  if (!c.config.empty()) a.options.profile_dir = fs::path(c.config).parent_path().empty() ? fs::path(".") : fs::path(c.config).parent_path();
  auto threads = limit_threads(a.options.threads);
  sigset_t set;
  sigemptyset(&set);
  sigaddset(&set, SIGINT);
  sigaddset(&set, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &set, nullptr);  // every thread started from here on inherits it
  auto server = std::make_unique<StationServer>(a.options);
  std::mutex server_mutex;  // the waiter stops the server only while it exists
  std::atomic<bool> done{false};
  std::thread waiter([&] {
    bool asked = false;
    for (;;) {
      int sig = 0;
      sigwait(&set, &sig);
      if (done) return;
      if (asked) {
        remove_unfinished_outputs();  // the files the jobs were writing (temporaries)
        std::fprintf(stderr, "serve: aborted\n");
        std::_Exit(130);
      }
      asked = true;
      std::fprintf(stderr, "\nserve: stopping; running jobs stop after the view or stage in progress "
                           "(Ctrl-C again to abort now)\n");
      std::lock_guard<std::mutex> lock(server_mutex);
      if (server) server->stop();
    }
  });
  const std::string shown = a.options.bind.find(':') != std::string::npos ? "[" + a.options.bind + "]" : a.options.bind;
  std::printf("station page: http://%s:%d/  (data: %s; Ctrl-C to stop)\n", shown.c_str(), server->port(),
              fs::absolute(a.options.data_dir).c_str());
  std::fflush(stdout);
  server->listen();
  {
    // Waits for the jobs to stop, a second Ctrl-C still aborting.
    std::unique_ptr<StationServer> ending;
    {
      std::lock_guard<std::mutex> lock(server_mutex);
      ending = std::move(server);
    }
    ending.reset();
  }
  done = true;
  ::kill(::getpid(), SIGTERM);  // wakes the waiter
  waiter.join();
  return 0;
}

}  // namespace

void add_serve_commands(CLI::App& app, std::vector<Command>& out) {
  struct State {
    Common c;
    ServeArgs a;
  };
  auto s = std::make_shared<State>();
  auto* serve = app.add_subcommand("serve", "The station page: scan, watch and download from a browser");
  add_common(serve, s->c);
  serve->add_option("--port", s->a.options.port, "port to listen on (0: any free one)")->capture_default_str()->check(whole_number(0, 65535));
  serve->add_option("--bind", s->a.options.bind,
                    "address to listen on; beyond loopback only with --token-file")->capture_default_str();
  serve->add_option("--token-file", s->a.token_file,
                    "file whose first line (16+ characters) every API request must carry");
  serve->add_option("--data", s->a.data, "folder of the sessions the page scans, runs and lists")->capture_default_str();
  out.push_back({serve, [s] { return cmd_serve(s->c, s->a); }});
}

}  // namespace station::cli
