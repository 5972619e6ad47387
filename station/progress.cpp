#include "station/progress.h"

#include <unistd.h>

#include <cstdio>

namespace station {

Progress::Progress(std::string label, int total, bool quiet, ProgressSink sink)
    : label_(std::move(label)), total_(total), quiet_(quiet), tty_(::isatty(2) != 0),
      start_(std::chrono::steady_clock::now()), sink_(std::move(sink)) {}

Progress::~Progress() {
  if (tty_ && !quiet_ && !finished_) std::fputc('\n', stderr);
}

void Progress::update(int done, const std::string& note) {
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  if (sink_ && (done >= total_ || s - last_event_s_ >= 0.1)) {
    last_event_s_ = s;
    sink_({ProgressEvent::Kind::kStep, label_, note, done, total_, s});
  }
  if (quiet_) return;
  if (tty_) {
    const int width = 24;
    const int filled = total_ > 0 ? done * width / total_ : 0;
    // Rate and ETA once there is something to go on.
    char eta[64] = "";
    if (done > 0 && done < total_ && s > 0.2)
      std::snprintf(eta, sizeof eta, " %.3g/s ETA %.0fs", done / s, (total_ - done) * s / done);
    std::fprintf(stderr, "\r%s [%.*s%*s] %d/%d %5.1fs%s %s\033[K", label_.c_str(), filled,
                 "########################", width - filled, "", done, total_, s, eta, note.c_str());
  } else {
    // Logs get a line at most every two seconds (and the last step), not one per step.
    if (done < total_ && s - last_line_s_ < 2.0) return;
    last_line_s_ = s;
    std::fprintf(stderr, "%s %d/%d (%.1fs) %s\n", label_.c_str(), done, total_, s, note.c_str());
  }
  std::fflush(stderr);
}

void Progress::finish(const std::string& note) {
  if (finished_) return;
  finished_ = true;
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  if (sink_) sink_({ProgressEvent::Kind::kFinish, label_, note, total_, total_, s});
  if (quiet_) return;
  if (tty_) std::fputc('\n', stderr);
  std::fprintf(stderr, "%s done in %.1fs %s\n", label_.c_str(), s, note.c_str());
}

}  // namespace station
