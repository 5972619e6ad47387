#include "drivers/fabscan_turntable.h"

#include <algorithm>
#include <chrono>
#include <cmath>

#include "core/error.h"

namespace station {

FabScanOptions fabscan_options(const DeviceOptions& options, const std::string& uri) {
  reject_unknown_options(options,
                         {"steps", "microsteps", "direction", "baud", "stepper", "timeout_ms",
                          "step_ms", "connect_timeout_ms"},
                         uri);
  FabScanOptions o;
  o.stepper = stepper_config_from_options(options, uri);
  o.baud = option_integer(options, "baud", o.baud, 1, 4000000, uri);
  o.stepper_id = option_integer(options, "stepper", o.stepper_id, 0, 199, uri);
  o.timeout_ms = option_integer(options, "timeout_ms", o.timeout_ms, 1, 600000, uri);
  o.step_ms = option_number(options, "step_ms", o.step_ms, 0, 10000, uri);
  o.connect_timeout_ms =
      option_integer(options, "connect_timeout_ms", o.connect_timeout_ms, 1, 600000, uri);
  try {
    baud_to_speed(o.baud);
  } catch (const InvalidInput& e) {
    throw DeviceError(uri + ": " + e.what());
  }
  return o;
}

FabScanTurntable::FabScanTurntable(const std::string& uri, const std::string& path,
                                   FabScanOptions options, std::unique_ptr<SerialPort> port)
    : uri_(uri), path_(path), opt_(options), port_(std::move(port)), reader_(*port_) {}

FabScanTurntable::~FabScanTurntable() {
  try {
    close();
  } catch (...) {
  }
}

void FabScanTurntable::require_open(const char* what) const {
  if (!open_) throw DeviceError(uri_ + ": " + what + " before open()");
}

void FabScanTurntable::send(const std::string& bytes) { port_->write(bytes, opt_.timeout_ms); }

void FabScanTurntable::ping(int timeout_ms) {
  int other = -1;
  if (try_ping(timeout_ms, other)) return;
  // Its pong may still come and be taken for the next one's: the link is out
  // of step, so close it; open() resyncs.
  open_ = false;
  port_->close();
  throw DeviceError(
      uri_ + ": no pong (211) to ping (210) within " + std::to_string(timeout_ms) + " ms" +
      (other >= 0
           ? " (got byte " + std::to_string(other) + "; not a FabScan board or wrong baud rate?)"
           : std::string()) +
      "; port closed, open() again to resynchronise");
}

bool FabScanTurntable::try_ping(int timeout_ms, int& other) {
  // Bytes already here are stale (boot noise): only the answer to this ping counts.
  port_->discard_input();
  reader_.clear();
  send(std::string(1, static_cast<char>(fabscan::kPing)));
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                          deadline - std::chrono::steady_clock::now())
                          .count();
    const int b = left > 0 ? reader_.read_byte(static_cast<int>(left)) : -1;
    if (b == fabscan::kPong) return true;
    if (b < 0) return false;
    other = b;  // ignore stray bytes (boot messages), remember one for the error
  }
}

void FabScanTurntable::open() {
  if (open_) return;
  port_->open(path_, opt_.baud);
  try {
    port_->discard_input();
    reader_.clear();
    // Opening the port reboots most Arduinos: ping until the firmware answers.
    const auto deadline =
        std::chrono::steady_clock::now() + std::chrono::milliseconds(opt_.connect_timeout_ms);
    const int slice = std::min(opt_.timeout_ms, 250);
    int other = -1;
    while (!try_ping(slice, other)) {
      if (std::chrono::steady_clock::now() >= deadline)
        throw DeviceError(
            uri_ + ": no FabScan board answered the ping (210 -> 211) within " +
            std::to_string(opt_.connect_timeout_ms) + " ms" +
            (other >= 0 ? " (got byte " + std::to_string(other) + "; wrong firmware or baud rate?)"
                        : std::string()));
    }
    const unsigned char dir =
        opt_.stepper.direction > 0 ? fabscan::kDirectionCcw : fabscan::kDirectionCw;
    send(std::string{static_cast<char>(fabscan::kSelectStepper), static_cast<char>(opt_.stepper_id),
                     static_cast<char>(fabscan::kStepperOn), static_cast<char>(dir)});
    // Pings sent while the board booted may still be answered: wait for quiet.
    reader_.drain(100, 1000);
    open_ = true;
    ping(opt_.timeout_ms);  // the board took the setup bytes
  } catch (...) {
    open_ = false;
    port_->close();
    throw;
  }
  position_steps_ = 0;
}

void FabScanTurntable::close() {
  if (!open_) return;
  open_ = false;
  try {
    send(std::string{static_cast<char>(fabscan::kSelectStepper), static_cast<char>(opt_.stepper_id),
                     static_cast<char>(fabscan::kStepperOff)});
  } catch (const DeviceError&) {
  }
  port_->close();
}

void FabScanTurntable::rotate_to(double degrees) {
  require_open("rotate_to");
  if (!std::isfinite(degrees)) throw InvalidInput(uri_ + ": rotate_to: angle is not finite");
  const long long per_rev = opt_.stepper.microsteps_per_revolution();
  long long target =
      static_cast<long long>(std::llround(wrap_degrees(degrees) * per_rev / 360.0)) % per_rev;
  long long todo = ((target - position_steps_) % per_rev + per_rev) % per_rev;
  while (todo > 0) {
    const int chunk = static_cast<int>(std::min<long long>(todo, 255));
    // Select the stepper each time: the laser stepper may have been selected since.
    send(std::string{static_cast<char>(fabscan::kSelectStepper), static_cast<char>(opt_.stepper_id),
                     static_cast<char>(fabscan::kPerformStep), static_cast<char>(chunk)});
    ping(opt_.timeout_ms + static_cast<int>(std::ceil(chunk * opt_.step_ms)));
    position_steps_ = (position_steps_ + chunk) % per_rev;
    todo -= chunk;
  }
}

void FabScanTurntable::home() {
  require_open("home");
  rotate_to(0);
}

double FabScanTurntable::angle() const {
  return wrap_degrees(360.0 * static_cast<double>(position_steps_) /
                      static_cast<double>(opt_.stepper.microsteps_per_revolution()));
}

int FabScanTurntable::steps_per_revolution() const {
  return static_cast<int>(opt_.stepper.microsteps_per_revolution());
}

}  // namespace station
