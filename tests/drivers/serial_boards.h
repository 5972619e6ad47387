#pragma once
// Test doubles for the serial turntable drivers: board simulators that turn
// received bytes into replies (Horus G-code, FabScan one-byte protocol), a
// scripted in-process SerialPort around them with fault injection, and a
// pseudo-terminal pair whose master end is played by a thread, so the real
// termios port is exercised without hardware.
#include <atomic>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "drivers/serial_port.h"

namespace station::testing {

/// Reply bytes for received bytes; keeps its own state (position, motor...).
class BoardSim {
 public:
  virtual ~BoardSim() = default;
  virtual std::string feed(const std::string& in) = 0;
};

/// Horus firmware: Ctrl-X -> banner; "CMD\r\n" -> "ok\r\n" (or a scripted
/// answer). Records each command line.
class HorusSim : public BoardSim {
 public:
  std::string banner = "Horus 0.2 ['$' for help]";
  std::string noise_before_banner;  ///< e.g. boot garbage
  /// Command prefix -> answer instead of "ok" ("" = stay silent).
  std::vector<std::pair<std::string, std::string>> answers;
  std::vector<std::string> commands;
  bool motor_on = false;
  double x = 0;  ///< last G1X argument
  std::string feed(const std::string& in) override;

 private:
  std::string line_;
};

/// FabScan firmware: 210 -> 211; 212 n select; 205/206 on/off; 203/204 dir;
/// 202 n steps. Tracks the turntable stepper's signed microstep count.
class FabScanSim : public BoardSim {
 public:
  bool answers_ping = true;
  int pong_byte = 211;
  int selected = -1;
  bool motor_on = false;
  int direction = 0;            ///< +1 after 204 (ccw), -1 after 203 (cw)
  long long steps = 0;          ///< signed microsteps of stepper 10
  std::vector<int> step_bytes;  ///< arguments of each 202
  std::string feed(const std::string& in) override;

 private:
  int pending_ = -1;  ///< command waiting for its argument byte
};

/// In-process SerialPort around a BoardSim. read_some returns "" at once when
/// nothing is pending (a time-out without waiting).
class ScriptedPort : public SerialPort {
 public:
  explicit ScriptedPort(BoardSim& sim) : sim_(sim) {}
  void open(const std::string& path, int baud) override;
  void close() override { open_ = false; }
  bool is_open() const override { return open_; }
  void write(const std::string& bytes, int timeout_ms) override;
  std::string read_some(std::size_t max, int timeout_ms) override;
  void discard_input() override { inbox_.clear(); }
  std::string path() const override { return path_; }

  // Fault injection.
  bool fail_open = false;
  int unplug_after_writes = -1;  ///< reads fail after this many writes
  std::string extra_input;       ///< queued before the first read (garbage)
  int baud = 0;
  int writes = 0;
  std::string written;

 private:
  BoardSim& sim_;
  std::string inbox_, path_;
  bool open_ = false;
};

/// A pseudo-terminal whose master end is served by a thread running `sim`.
/// `slave_path()` is what the driver opens. `hang_up_after` closes the master
/// (an unplug) after that many bytes were received.
class PtyBoard {
 public:
  explicit PtyBoard(BoardSim& sim, long hang_up_after = -1);
  ~PtyBoard();
  const std::string& slave_path() const { return slave_; }
  std::string received() const;

 private:
  void serve();
  BoardSim& sim_;
  long hang_up_after_;
  int master_ = -1;
  std::string slave_;
  std::atomic<bool> stop_{false};
  mutable std::mutex mutex_;
  std::string received_;
  std::thread thread_;
};

}  // namespace station::testing
