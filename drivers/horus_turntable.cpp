#include "drivers/horus_turntable.h"

#include <chrono>
#include <cmath>
#include <cstdio>

#include "core/error.h"

namespace station {
namespace {

std::string format_number(double v) {
  // Short, locale-free, enough digits for a microstep (1/3200 turn ~ 0.1 degree).
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.4f", v);
  std::string s = buf;
  while (!s.empty() && s.back() == '0') s.pop_back();
  if (!s.empty() && s.back() == '.') s.pop_back();
  if (s == "-0") s = "0";
  return s;
}

std::string printable(const std::string& s) {
  std::string out;
  for (unsigned char c : s) {
    if (c >= 32 && c < 127)
      out.push_back(static_cast<char>(c));
    else {
      char b[8];
      std::snprintf(b, sizeof b, "\\x%02x", c);
      out += b;
    }
    if (out.size() > 60) return out + "...";
  }
  return out;
}

}  // namespace

HorusOptions horus_options(const DeviceOptions& options, const std::string& uri) {
  reject_unknown_options(options,
                         {"steps", "microsteps", "direction", "baud", "speed", "acceleration",
                          "timeout_ms", "banner_timeout_ms", "settle_ms"},
                         uri);
  HorusOptions o;
  o.stepper = stepper_config_from_options(options, uri);
  o.baud = option_integer(options, "baud", o.baud, 1, 4000000, uri);
  o.speed = option_number(options, "speed", o.speed, 0.01, 100000, uri);
  o.acceleration = option_number(options, "acceleration", o.acceleration, 0, 1e6, uri);
  o.timeout_ms = option_integer(options, "timeout_ms", o.timeout_ms, 1, 600000, uri);
  o.banner_timeout_ms =
      option_integer(options, "banner_timeout_ms", o.banner_timeout_ms, 1, 600000, uri);
  o.settle_ms = option_integer(options, "settle_ms", o.settle_ms, 0, 600000, uri);
  try {
    baud_to_speed(o.baud);
  } catch (const InvalidInput& e) {
    throw DeviceError(uri + ": " + e.what());
  }
  return o;
}

std::string horus_handshake(SerialPort& port, LineReader& reader, const std::string& who,
                            int timeout_ms) {
  port.discard_input();
  reader.clear();
  port.write(std::string(1, '\x18'), timeout_ms);
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  std::string last;
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                          deadline - std::chrono::steady_clock::now())
                          .count();
    std::string line;
    if (left <= 0 || !reader.read_line(line, static_cast<int>(left))) break;
    if (line.find("Horus") != std::string::npos) return line;
    if (!line.empty()) last = line;
  }
  if (last.empty() && !reader.pending().empty()) last = reader.pending();
  throw DeviceError(who + ": no Horus banner within " + std::to_string(timeout_ms) + " ms" +
                    (last.empty()
                         ? std::string(" (no answer; is it the right port?)")
                         : " (got '" + printable(last) + "'; wrong firmware or baud rate?)"));
}

HorusTurntable::HorusTurntable(const std::string& uri, const std::string& path,
                               HorusOptions options, std::unique_ptr<SerialPort> port,
                               Sleeper sleep)
    : uri_(uri),
      path_(path),
      opt_(options),
      port_(std::move(port)),
      sleep_(std::move(sleep)),
      reader_(*port_) {}

HorusTurntable::~HorusTurntable() {
  try {
    close();
  } catch (...) {
  }
}

void HorusTurntable::require_open(const char* what) const {
  if (!open_) throw DeviceError(uri_ + ": " + what + " before open()");
}

void HorusTurntable::open() {
  if (open_) return;
  port_->open(path_, opt_.baud);
  try {
    horus_handshake(*port_, reader_, uri_, opt_.banner_timeout_ms);
    open_ = true;
    command("M17", opt_.timeout_ms);
    command("G50", opt_.timeout_ms);
    command("G1F" + format_number(opt_.speed), opt_.timeout_ms);
    if (opt_.acceleration > 0) command("$120=" + format_number(opt_.acceleration), opt_.timeout_ms);
  } catch (...) {
    open_ = false;
    port_->close();
    throw;
  }
  position_deg_ = 0;
}

void HorusTurntable::close() {
  if (!open_) return;
  open_ = false;
  try {
    // Motor off so the table can be turned by hand; best effort (may be unplugged).
    port_->write("M18\r\n", opt_.timeout_ms);
    std::string line;
    reader_.read_line(line, opt_.timeout_ms);
  } catch (const DeviceError&) {
  }
  port_->close();
}

void HorusTurntable::command(const std::string& gcode, int timeout_ms) {
  require_open("command");
  port_->write(gcode + "\r\n", timeout_ms);
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                          deadline - std::chrono::steady_clock::now())
                          .count();
    std::string line;
    if (left <= 0 || !reader_.read_line(line, static_cast<int>(left))) {
      // The late "ok" could be taken for the next command's answer: the link
      // is out of step, so close it; open() resets the board and resyncs.
      const std::string got = reader_.pending();
      open_ = false;
      port_->close();
      throw DeviceError(uri_ + ": no answer to '" + gcode + "' within " +
                        std::to_string(timeout_ms) + " ms" +
                        (got.empty() ? std::string() : " (got '" + printable(got) + "')") +
                        "; port closed, open() again to resynchronise");
    }
    if (line == "ok") return;
    if (line.rfind("error", 0) == 0 || line.rfind("ALARM", 0) == 0)
      throw DeviceError(uri_ + ": board answered '" + printable(line) + "' to '" + gcode + "'");
    // Anything else (status lines, echoes, a late banner) is not an answer: keep waiting.
  }
}

void HorusTurntable::rotate_to(double degrees) {
  require_open("rotate_to");
  if (!std::isfinite(degrees)) throw InvalidInput(uri_ + ": rotate_to: angle is not finite");
  const double current = wrap_degrees(position_deg_);
  double delta = wrap_degrees(degrees) - current;
  if (delta < 0) delta += 360.0;
  const double target = opt_.stepper.quantize_degrees(position_deg_ + delta);
  if (target == position_deg_) return;
  const double motor = opt_.stepper.direction * target;
  const double seconds = std::abs(target - position_deg_) / opt_.speed;
  command("G1X" + format_number(motor), opt_.timeout_ms);
  position_deg_ = target;
  sleep_(seconds + opt_.settle_ms / 1000.0);
}

void HorusTurntable::home() {
  require_open("home");
  rotate_to(0);
  command("G50", opt_.timeout_ms);
  position_deg_ = 0;
}

double HorusTurntable::angle() const {
  return wrap_degrees(opt_.stepper.quantize_degrees(position_deg_));
}

int HorusTurntable::steps_per_revolution() const {
  return static_cast<int>(opt_.stepper.microsteps_per_revolution());
}

}  // namespace station
