#include "drivers/syscalls.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <cerrno>

namespace station {
namespace {

class RealSysCalls final : public SysCalls {
 public:
  int open(const char* path, int flags) override { return keep(::open(path, flags)); }
  int close(int fd) override { return keep(::close(fd)); }
  int ioctl(int fd, unsigned long request, void* arg) override {
    int r;
    do r = ::ioctl(fd, request, arg);  // retry on signals, as V4L2 recommends
    while (r < 0 && errno == EINTR);
    return keep(r);
  }
  ssize_t read(int fd, void* buf, size_t n) override { return keep(::read(fd, buf, n)); }
  ssize_t write(int fd, const void* buf, size_t n) override { return keep(::write(fd, buf, n)); }
  int poll_in(int fd, int timeout_ms) override {
    pollfd p{fd, POLLIN, 0};
    return keep(::poll(&p, 1, timeout_ms));
  }
  int last_error() const override { return error_; }
  void* mmap(void* addr, size_t length, int prot, int flags, int fd, off_t offset) override {
    void* p = ::mmap(addr, length, prot, flags, fd, offset);
    if (p == MAP_FAILED) error_ = errno;
    return p;
  }
  int munmap(void* addr, size_t length) override { return keep(::munmap(addr, length)); }

 private:
  template <typename T>
  T keep(T r) {
    if (r < 0) error_ = errno;
    return r;
  }
  static thread_local int error_;
};

thread_local int RealSysCalls::error_ = 0;

}  // namespace

std::shared_ptr<SysCalls> real_syscalls() {
  static auto instance = std::make_shared<RealSysCalls>();
  return instance;
}

}  // namespace station
