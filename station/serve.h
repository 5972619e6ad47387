#pragma once
// `station serve`: the station as an app for the operator at the bench. An HTTP
// server (cpp-httplib) serving the page (web/) and a JSON API over the same
// library the CLI drives (station/jobs.h): devices, profiles, sessions under the
// data folder, scan and run jobs with their progress as server-sent events, the
// results for download, and the scanner's live preview. API and security:
// docs/serve.md.
//
// Security: loopback by default; any other address needs a token (--token-file),
// then every /api request must carry it (Authorization: Bearer, X-Station-Token
// or the station_token cookie), compared in constant time. POSTs must be JSON
// from the page's own origin. No path a client gives leaves the data folder.
#include <filesystem>
#include <memory>
#include <string>

namespace station {

class JobManager;

struct ServeOptions {
  std::string bind = "127.0.0.1";
  int port = 8080;                    ///< 0: any free port (see StationServer::port)
  std::filesystem::path token_file;   ///< holds the token (first line); empty: no token
  std::filesystem::path data_dir = "out/station";
  std::filesystem::path web_dir;      ///< the page; empty: web/ of the source tree
  std::filesystem::path three_dir;    ///< three.js (Debian's libjs-three); empty: its install path
  std::filesystem::path profile_dir;  ///< the profiles a client may pick; empty: config/ of the source tree
  int threads = 0;                    ///< for every job (0: all cores)
};

/// True for 127.0.0.0/8, ::1 and "localhost".
bool is_loopback_address(const std::string& address);

/// The token of a token file: its first line without surrounding white space.
/// InvalidInput naming the file when unreadable, empty or shorter than 16 characters.
std::string read_token_file(const std::filesystem::path& file);

class StationServer {
 public:
  /// Checks the options (InvalidInput: a bind beyond loopback without a token, a
  /// bad token file, no page folder) and binds the port (IoError naming the
  /// address when it cannot).
  explicit StationServer(const ServeOptions& options);
  /// Stops listening, then asks the jobs to stop and waits for them.
  ~StationServer();
  StationServer(const StationServer&) = delete;
  StationServer& operator=(const StationServer&) = delete;

  /// The bound port (the chosen one when ServeOptions::port was 0).
  int port() const;
  /// Serves until stop() (from another thread or a signal handler's thread).
  void listen();
  void stop();
  JobManager& jobs();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace station
