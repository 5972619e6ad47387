#pragma once
// The Ciclop / Horus scanner board (BQ's grbl-derived "Horus" firmware) driving
// the turntable over a serial port (USB CDC / CH340). Protocol as used here:
//   - 115200 baud, 8N1; commands end with "\r\n"; each is answered "ok"
//     (or a line starting "error").
//   - reset: Ctrl-X (0x18); the board answers a banner line containing "Horus"
//     ("Horus 0.2 ['$' for help]"); lines before it are ignored.
//   - M17 / M18: stepper motor on / off; G50: current position is the origin;
//     G1F<f>: feed rate (degrees per second); G1X<deg>: move to an absolute
//     motor angle in degrees.
// The firmware answers "ok" when a move is accepted, not when it ends; the
// driver then waits the move's duration at the configured speed plus a settle
// time before it reports the table there.
//
// URI: horus:/dev/ttyUSB0?steps=200&microsteps=16&direction=ccw&speed=200
// Options (profile or URI): steps (required), microsteps, direction (see
// serial_turntable.h), baud (115200), speed (deg/s, 200), acceleration
// (deg/s^2, sent as $120 when given), timeout_ms (per command, 2000),
// banner_timeout_ms (5000), settle_ms (100).
#include <memory>
#include <string>

#include "drivers/serial_port.h"
#include "drivers/serial_turntable.h"

namespace station {

struct HorusOptions {
  StepperConfig stepper;
  int baud = 115200;
  double speed = 200;       ///< degrees per second (G1F)
  double acceleration = 0;  ///< degrees per second^2 ($120); 0: leave the board's
  int timeout_ms = 2000;
  int banner_timeout_ms = 5000;
  int settle_ms = 100;
};
HorusOptions horus_options(const DeviceOptions& options, const std::string& uri);

class HorusTurntable final : public Turntable {
 public:
  /// `port` is the back-end (real termios port or a test fake); `uri` names the
  /// device in errors; its path is the serial device.
  HorusTurntable(const std::string& uri, const std::string& path, HorusOptions options,
                 std::unique_ptr<SerialPort> port, Sleeper sleep = real_sleeper());
  ~HorusTurntable() override;

  void open() override;
  void close() override;
  /// There is no end stop on the Ciclop: home is the position the table had
  /// when it was opened (the origin set with G50). Drives there forwards and
  /// makes it the origin again.
  void home() override;
  /// Moves forwards (never backwards: no backlash) to `degrees` (wrapped to
  /// [0, 360)), quantized to whole microsteps.
  void rotate_to(double degrees) override;
  /// The angle reached, [0, 360): the last commanded position the board
  /// acknowledged, quantized to microsteps.
  double angle() const override;
  int steps_per_revolution() const override;
  std::string uri() const override { return uri_; }

  /// Sends one command and waits for "ok"; DeviceError on "error..." or
  /// time-out. After a time-out the port is closed (a late "ok" would be taken
  /// for the next command's answer); open() resets the board and resyncs.
  void command(const std::string& gcode, int timeout_ms);

 private:
  void require_open(const char* what) const;
  std::string uri_, path_;
  HorusOptions opt_;
  std::unique_ptr<SerialPort> port_;
  Sleeper sleep_;
  LineReader reader_;
  bool open_ = false;
  double position_deg_ = 0;  ///< table angle since the origin, unwrapped, quantized
};

/// Resets the board and waits for the banner; returns the banner line.
/// DeviceError naming the port when nothing Horus-like answers in time.
std::string horus_handshake(SerialPort& port, LineReader& reader, const std::string& who,
                            int timeout_ms);

}  // namespace station
