#pragma once
// Serial ports for turntable controllers (USB CDC / FTDI boards). Drivers talk
// to a small SerialPort interface; the real one configures termios (raw 8N1,
// no flow control) and waits with poll(2), tests inject scripted fakes or a
// pseudo-terminal. Every wait has a time-out; every failure is a DeviceError
// naming the port.
#include <cstddef>
#include <functional>
#include <memory>
#include <string>

namespace station {

class SerialPort {
 public:
  virtual ~SerialPort() = default;
  /// Opens and configures the port (raw, 8N1, `baud`). DeviceError "PATH: ..."
  /// when it does not exist, is busy (another program has it open) or refuses.
  virtual void open(const std::string& path, int baud) = 0;
  virtual void close() = 0;
  virtual bool is_open() const = 0;
  /// Writes every byte; DeviceError on failure or when the port stops accepting
  /// data for `timeout_ms`.
  virtual void write(const std::string& bytes, int timeout_ms) = 0;
  /// Waits at most `timeout_ms` for data and returns what is there (up to
  /// `max` bytes); "" on time-out. DeviceError when the port fails or hangs up
  /// (unplugged).
  virtual std::string read_some(std::size_t max, int timeout_ms) = 0;
  /// Drops bytes received but not read yet.
  virtual void discard_input() = 0;
  virtual std::string path() const = 0;
};

/// The termios implementation. Opening takes an advisory exclusive lock
/// (flock) and sets TIOCEXCL, so a second station gets "busy".
std::unique_ptr<SerialPort> make_posix_serial_port();

/// Baud rates termios knows (9600 ... 4000000); InvalidInput otherwise.
unsigned baud_to_speed(int baud);

/// Line reader over a SerialPort: splits on '\n', drops '\r', keeps what
/// follows the last newline for the next call.
class LineReader {
 public:
  explicit LineReader(SerialPort& port) : port_(port) {}
  /// The next line, or false when no complete line arrived within `timeout_ms`
  /// (the partial line stays buffered).
  bool read_line(std::string& line, int timeout_ms);
  /// The next byte, or -1 on time-out.
  int read_byte(int timeout_ms);
  void clear() { pending_.clear(); }
  /// Drops everything buffered and whatever arrives until the line has been
  /// quiet for `quiet_ms` (at most `max_ms` in all): late answers to a command
  /// that timed out must not be taken for answers to the next one.
  void drain(int quiet_ms, int max_ms);
  const std::string& pending() const { return pending_; }

 private:
  SerialPort& port_;
  std::string pending_;
};

/// Sleeping, injectable so tests of motion waits run instantly.
using Sleeper = std::function<void(double seconds)>;
Sleeper real_sleeper();

}  // namespace station
