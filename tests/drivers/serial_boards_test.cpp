// Implementation of serial_boards.h (named *_test.cpp so the test glob builds it).
#include "serial_boards.h"

#include <fcntl.h>
#include <poll.h>
#include <stdlib.h>
#include <unistd.h>

#include <cstdlib>
#include <stdexcept>

#include "core/error.h"

namespace station::testing {

std::string HorusSim::feed(const std::string& in) {
  std::string out;
  for (char c : in) {
    if (c == '\x18') {
      line_.clear();
      out += noise_before_banner + "\r\n" + banner + "\r\n";
      continue;
    }
    if (c == '\r') continue;
    if (c != '\n') {
      line_.push_back(c);
      continue;
    }
    const std::string cmd = line_;
    line_.clear();
    commands.push_back(cmd);
    bool scripted = false;
    for (const auto& [prefix, answer] : answers)
      if (cmd.rfind(prefix, 0) == 0) {
        out += answer.empty() ? "" : answer + "\r\n";
        scripted = true;
        break;
      }
    if (scripted) continue;
    if (cmd == "M17") motor_on = true;
    if (cmd == "M18") motor_on = false;
    if (cmd.rfind("G1X", 0) == 0) x = std::atof(cmd.c_str() + 3);
    out += "ok\r\n";
  }
  return out;
}

std::string FabScanSim::feed(const std::string& in) {
  std::string out;
  for (unsigned char b : in) {
    if (pending_ >= 0) {
      if (pending_ == 212) selected = b;
      if (pending_ == 202) {
        step_bytes.push_back(b);
        if (selected == 10) steps += direction * static_cast<long long>(b);
      }
      pending_ = -1;
      continue;
    }
    switch (b) {
      case 210:
        if (answers_ping) out.push_back(static_cast<char>(pong_byte));
        break;
      case 212:
      case 202:
        pending_ = b;
        break;
      case 205:
        motor_on = true;
        break;
      case 206:
        motor_on = false;
        break;
      case 203:
        direction = -1;
        break;
      case 204:
        direction = 1;
        break;
      default:
        break;
    }
  }
  return out;
}

void ScriptedPort::open(const std::string& path, int b) {
  path_ = path;
  baud = b;
  if (fail_open) throw DeviceError(path + ": no such serial port (unplugged?)");
  open_ = true;
}

void ScriptedPort::write(const std::string& bytes, int) {
  if (!open_) throw DeviceError(path_ + ": not open");
  if (unplug_after_writes >= 0 && writes >= unplug_after_writes)
    throw DeviceError(path_ + ": write failed (unplugged?): Input/output error");
  ++writes;
  written += bytes;
  inbox_ += sim_.feed(bytes);
}

std::string ScriptedPort::read_some(std::size_t max, int) {
  if (!open_) throw DeviceError(path_ + ": not open");
  if (unplug_after_writes >= 0 && writes >= unplug_after_writes)
    throw DeviceError(path_ + ": read failed (unplugged?): Input/output error");
  if (!extra_input.empty()) {
    inbox_ = extra_input + inbox_;
    extra_input.clear();
  }
  const std::string out = inbox_.substr(0, max);
  inbox_.erase(0, out.size());
  return out;
}

PtyBoard::PtyBoard(BoardSim& sim, long hang_up_after) : sim_(sim), hang_up_after_(hang_up_after) {
  master_ = posix_openpt(O_RDWR | O_NOCTTY);
  if (master_ < 0 || grantpt(master_) < 0 || unlockpt(master_) < 0)
    throw std::runtime_error("cannot create a pseudo-terminal");
  slave_ = ptsname(master_);
  thread_ = std::thread([this] { serve(); });
}

PtyBoard::~PtyBoard() {
  stop_ = true;
  thread_.join();
  if (master_ >= 0) ::close(master_);
}

std::string PtyBoard::received() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return received_;
}

void PtyBoard::serve() {
  char buf[256];
  // One chunk from the port; false when the board stops (hang-up, write error).
  auto handle = [&](const char* data, std::size_t n) {
    std::string in(data, n);
    long total;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      received_ += in;
      total = static_cast<long>(received_.size());
    }
    if (hang_up_after_ >= 0 && total >= hang_up_after_) {
      ::close(master_);  // the board disappears
      master_ = -1;
      return false;
    }
    const std::string out = sim_.feed(in);
    return out.empty() || ::write(master_, out.data(), out.size()) >= 0;
  };
  while (!stop_) {
    pollfd p{master_, POLLIN, 0};
    const int r = ::poll(&p, 1, 20);
    if (r <= 0) continue;
    if (!(p.revents & POLLIN)) {  // POLLHUP until the slave is opened
      ::usleep(2000);
      continue;
    }
    const ssize_t n = ::read(master_, buf, sizeof buf);
    if (n <= 0) continue;
    if (!handle(buf, static_cast<std::size_t>(n))) return;
  }
  // Stopping: the driver's last bytes (a FabScan motor-off has no answer) may
  // still be in the pty; take them before the sim is handed back to the test.
  for (;;) {
    pollfd p{master_, POLLIN, 0};
    if (::poll(&p, 1, 50) <= 0 || !(p.revents & POLLIN)) return;
    const ssize_t n = ::read(master_, buf, sizeof buf);
    if (n <= 0 || !handle(buf, static_cast<std::size_t>(n))) return;
  }
}

}  // namespace station::testing
