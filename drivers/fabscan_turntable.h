#pragma once
// The FabScan (FabScan100 / Watterott shield, Arduino firmware) turntable over
// a serial port: a one-byte protocol.
//   210 ping -> the board answers 211 (pong)
//   212 <n>  select stepper n (10 = turntable, 11 = laser)
//   205/206  selected stepper on / off
//   203/204  direction clockwise / counter-clockwise (of the motor shaft)
//   202 <n>  perform n steps (1..255) on the selected stepper
// Steps are not acknowledged; the driver follows each move with a ping and
// waits for the pong, which the firmware sends only after it has stepped (it
// handles bytes in order), so "reached" means the board really got there.
// Steps per revolution and microstepping come from the profile: the classic
// FabScan bug is a hard-coded 3200 steps that is wrong for other gearing.
//
// URI: fabscan:/dev/ttyACM0?steps=200&microsteps=16&direction=ccw
// Options: steps (required), microsteps, direction, baud (9600), stepper (10),
// timeout_ms (2000), step_ms (per microstep, for the move time-out; 2),
// connect_timeout_ms (5000: the Arduino reboots when the port opens).
#include <memory>
#include <string>

#include "drivers/serial_port.h"
#include "drivers/serial_turntable.h"

namespace station {

namespace fabscan {
constexpr unsigned char kPerformStep = 202;
constexpr unsigned char kDirectionCw = 203;
constexpr unsigned char kDirectionCcw = 204;
constexpr unsigned char kStepperOn = 205;
constexpr unsigned char kStepperOff = 206;
constexpr unsigned char kPing = 210;
constexpr unsigned char kPong = 211;
constexpr unsigned char kSelectStepper = 212;
constexpr unsigned char kTurntableStepper = 10;
}  // namespace fabscan

struct FabScanOptions {
  StepperConfig stepper;
  int baud = 9600;
  int stepper_id = fabscan::kTurntableStepper;
  int timeout_ms = 2000;
  double step_ms = 2.0;
  int connect_timeout_ms = 5000;
};
FabScanOptions fabscan_options(const DeviceOptions& options, const std::string& uri);

class FabScanTurntable final : public Turntable {
 public:
  FabScanTurntable(const std::string& uri, const std::string& path, FabScanOptions options,
                   std::unique_ptr<SerialPort> port);
  ~FabScanTurntable() override;

  void open() override;
  void close() override;
  /// No end stop: home is the position at open(); drives there forwards.
  void home() override;
  /// Forwards only, to `degrees` wrapped to [0, 360), in whole microsteps.
  void rotate_to(double degrees) override;
  /// Microsteps the board confirmed (pong after the steps), as degrees in [0, 360).
  double angle() const override;
  int steps_per_revolution() const override;
  std::string uri() const override { return uri_; }

  /// Ping -> pong within `timeout_ms`; DeviceError otherwise, and the port is
  /// closed (a late pong would confirm the next move too early).
  void ping(int timeout_ms);

 private:
  void require_open(const char* what) const;
  void send(const std::string& bytes);
  /// false on time-out; `other` keeps a stray byte for the error message.
  bool try_ping(int timeout_ms, int& other);
  std::string uri_, path_;
  FabScanOptions opt_;
  std::unique_ptr<SerialPort> port_;
  LineReader reader_;
  bool open_ = false;
  long long position_steps_ = 0;  ///< confirmed microsteps since open, modulo one revolution
};

}  // namespace station
