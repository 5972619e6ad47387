#pragma once
// Progress for long work: a redrawn bar on a terminal, plain lines otherwise
// (logs, CI). Writes to stderr so stdout stays clean for --json.
#include <chrono>
#include <functional>
#include <string>

namespace station {

/// What the CLI prints about long work, as data (for `station serve`'s event
/// stream): a line ("[2/3] consolidate...", "note: ..."), a step of a bar, a
/// bar's end, or a run stage starting, done or kept (label: the stage's name;
/// text: "start", "done" or "kept"; done/total: its index, 1-based, of total).
struct ProgressEvent {
  enum class Kind { kLine, kStep, kFinish, kStage };
  Kind kind = Kind::kLine;
  std::string label;  ///< the bar's label ("  register: pairs") or the stage; empty for a line
  std::string text;   ///< the line, or the step's note
  int done = 0, total = 0;
  double seconds = 0;  ///< since the bar started; a stage's time when done or kept
};
/// Receives events; called on the thread doing the work.
using ProgressSink = std::function<void(const ProgressEvent&)>;

class Progress {
 public:
  /// `quiet` suppresses the terminal output (used with --json); `sink`, when set,
  /// gets every step (at most ten a second, and the last) and the finish, quiet or not.
  Progress(std::string label, int total, bool quiet = false, ProgressSink sink = {});
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
  ProgressSink sink_;
  double last_event_s_ = -1e9;  ///< when the sink last got a step
};

}  // namespace station
