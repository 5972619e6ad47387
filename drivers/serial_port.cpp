#include "drivers/serial_port.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/file.h>
#include <sys/ioctl.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <thread>

#include "core/error.h"

namespace station {
namespace {

std::string errno_text(int e) { return std::strerror(e); }

class PosixSerialPort final : public SerialPort {
 public:
  ~PosixSerialPort() override { close(); }

  void open(const std::string& path, int baud) override {
    close();
    const speed_t speed = baud_to_speed(baud);
    const int fd = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) {
      const int e = errno;
      if (e == EBUSY) throw DeviceError(path + ": busy (another program has it open)");
      if (e == ENOENT || e == ENODEV || e == ENXIO)
        throw DeviceError(path + ": no such serial port (unplugged?)");
      if (e == EACCES || e == EPERM)
        throw DeviceError(path + ": permission denied (is the user in the dialout group?)");
      throw DeviceError(path + ": cannot open serial port: " + errno_text(e));
    }
    if (::flock(fd, LOCK_EX | LOCK_NB) < 0) {
      const int e = errno;
      ::close(fd);
      if (e == EWOULDBLOCK) throw DeviceError(path + ": busy (another program has it open)");
      throw DeviceError(path + ": cannot lock serial port: " + errno_text(e));
    }
    termios t;
    if (::tcgetattr(fd, &t) < 0) {
      const int e = errno;
      ::close(fd);
      throw DeviceError(path + ": not a serial port: " + errno_text(e));
    }
    ::cfmakeraw(&t);
    t.c_cflag |= CLOCAL | CREAD;
    t.c_cflag &= ~(CSTOPB | PARENB | CRTSCTS);
    t.c_cflag = (t.c_cflag & ~CSIZE) | CS8;
    t.c_iflag &= ~(IXON | IXOFF | IXANY);
    t.c_cc[VMIN] = 0;
    t.c_cc[VTIME] = 0;
    ::cfsetispeed(&t, speed);
    ::cfsetospeed(&t, speed);
    if (::tcsetattr(fd, TCSANOW, &t) < 0) {
      const int e = errno;
      ::close(fd);
      throw DeviceError(path + ": cannot configure serial port at " + std::to_string(baud) +
                        " baud: " + errno_text(e));
    }
    ::ioctl(fd, TIOCEXCL);  // best effort: further opens fail with EBUSY
    fd_ = fd;
    path_ = path;
  }

  void close() override {
    if (fd_ >= 0) {
      ::ioctl(fd_, TIOCNXCL);
      ::close(fd_);
    }
    fd_ = -1;
  }

  bool is_open() const override { return fd_ >= 0; }

  void write(const std::string& bytes, int timeout_ms) override {
    require_open();
    std::size_t done = 0;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    while (done < bytes.size()) {
      const ssize_t n = ::write(fd_, bytes.data() + done, bytes.size() - done);
      if (n > 0) {
        done += static_cast<std::size_t>(n);
        continue;
      }
      if (n < 0 && errno == EINTR) continue;
      if (n < 0 && errno != EAGAIN)
        throw DeviceError(path_ + ": write failed (unplugged?): " + errno_text(errno));
      const int left = remaining_ms(deadline);
      if (left <= 0)
        throw DeviceError(path_ + ": write timed out after " + std::to_string(timeout_ms) + " ms");
      pollfd p{fd_, POLLOUT, 0};
      const int r = ::poll(&p, 1, left);
      if (r < 0 && errno != EINTR) throw DeviceError(path_ + ": poll failed: " + errno_text(errno));
      if (r > 0 && (p.revents & (POLLERR | POLLHUP | POLLNVAL)))
        throw DeviceError(path_ + ": port hung up (unplugged?)");
    }
  }

  std::string read_some(std::size_t max, int timeout_ms) override {
    require_open();
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    std::string out(std::max<std::size_t>(max, 1), '\0');
    bool hung_up = false;
    for (;;) {
      // Raw mode with VMIN = VTIME = 0: read returns 0 when nothing is there,
      // so a hang-up shows as poll's POLLHUP/POLLERR followed by no data.
      const ssize_t n = ::read(fd_, out.data(), out.size());
      if (n > 0) {
        out.resize(static_cast<std::size_t>(n));
        return out;
      }
      if (n < 0 && errno == EINTR) continue;
      if (n < 0 && errno != EAGAIN)
        throw DeviceError(path_ + ": read failed (unplugged?): " + errno_text(errno));
      if (hung_up) throw DeviceError(path_ + ": port hung up (unplugged?)");
      const int left = remaining_ms(deadline);
      if (left <= 0) return {};
      pollfd p{fd_, POLLIN, 0};
      const int r = ::poll(&p, 1, left);
      if (r < 0 && errno != EINTR) throw DeviceError(path_ + ": poll failed: " + errno_text(errno));
      if (r == 0) return {};
      if (r > 0 && (p.revents & (POLLERR | POLLHUP | POLLNVAL))) hung_up = true;
    }
  }

  void discard_input() override {
    if (fd_ >= 0) ::tcflush(fd_, TCIFLUSH);
  }

  std::string path() const override { return path_; }

 private:
  static int remaining_ms(std::chrono::steady_clock::time_point deadline) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        deadline - std::chrono::steady_clock::now());
    return static_cast<int>(std::max<long long>(0, left.count()));
  }
  void require_open() const {
    if (fd_ < 0)
      throw DeviceError((path_.empty() ? std::string("serial port") : path_) + ": not open");
  }
  int fd_ = -1;
  std::string path_;
};

}  // namespace

unsigned baud_to_speed(int baud) {
  switch (baud) {
    case 9600:
      return B9600;
    case 19200:
      return B19200;
    case 38400:
      return B38400;
    case 57600:
      return B57600;
    case 115200:
      return B115200;
    case 230400:
      return B230400;
    case 460800:
      return B460800;
    case 500000:
      return B500000;
    case 921600:
      return B921600;
    case 1000000:
      return B1000000;
    case 2000000:
      return B2000000;
    case 4000000:
      return B4000000;
    default:
      throw InvalidInput("baud rate " + std::to_string(baud) +
                         " not supported (use 9600, 19200, 38400, 57600, 115200, 230400, ...)");
  }
}

std::unique_ptr<SerialPort> make_posix_serial_port() { return std::make_unique<PosixSerialPort>(); }

bool LineReader::read_line(std::string& line, int timeout_ms) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  for (;;) {
    const auto nl = pending_.find('\n');
    if (nl != std::string::npos) {
      line = pending_.substr(0, nl);
      pending_.erase(0, nl + 1);
      line.erase(std::remove(line.begin(), line.end(), '\r'), line.end());
      return true;
    }
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                          deadline - std::chrono::steady_clock::now())
                          .count();
    if (left <= 0) return false;
    const std::string got = port_.read_some(256, static_cast<int>(left));
    if (got.empty()) return false;  // read_some waited the whole remaining time
    pending_ += got;
  }
}

void LineReader::drain(int quiet_ms, int max_ms) {
  pending_.clear();
  port_.discard_input();
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(max_ms);
  while (std::chrono::steady_clock::now() < deadline)
    if (port_.read_some(256, quiet_ms).empty()) break;
}

int LineReader::read_byte(int timeout_ms) {
  if (pending_.empty()) {
    pending_ = port_.read_some(256, timeout_ms);
    if (pending_.empty()) return -1;
  }
  const int b = static_cast<unsigned char>(pending_[0]);
  pending_.erase(0, 1);
  return b;
}

Sleeper real_sleeper() {
  return [](double seconds) {
    if (seconds > 0) std::this_thread::sleep_for(std::chrono::duration<double>(seconds));
  };
}

}  // namespace station
