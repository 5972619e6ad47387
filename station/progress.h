#pragma once
// Progress for long work: a redrawn bar on a terminal, plain lines otherwise
// (logs, CI). Writes to stderr so stdout stays clean for --json.
#include <chrono>
#include <string>

namespace station {

class Progress {
 public:
  /// `quiet` suppresses everything (used with --json).
  Progress(std::string label, int total, bool quiet = false);
  ~Progress();
  /// Reports `done` of `total` steps with a short note.
  void update(int done, const std::string& note = {});
  void finish(const std::string& note = {});

 private:
  std::string label_;
  int total_;
  bool quiet_, tty_, finished_ = false;
  std::chrono::steady_clock::time_point start_;
  double last_line_s_ = -1e9;  ///< when the last plain line was printed (not a terminal)
};

}  // namespace station
