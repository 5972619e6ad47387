#pragma once
// The system-call seam for real device back-ends: drivers call these instead
// of ::open/::ioctl/..., so tests inject a fake kernel (scripted ioctl replies,
// unplug mid-stream) and CI exercises drivers without hardware.
#include <sys/mman.h>
#include <sys/types.h>

#include <memory>

namespace station {

class SysCalls {
 public:
  virtual ~SysCalls() = default;
  virtual int open(const char* path, int flags) = 0;
  virtual int close(int fd) = 0;
  virtual int ioctl(int fd, unsigned long request, void* arg) = 0;
  virtual ssize_t read(int fd, void* buf, size_t n) = 0;
  virtual ssize_t write(int fd, const void* buf, size_t n) = 0;
  /// poll(2) on one descriptor; returns >0 ready, 0 time-out, <0 error.
  virtual int poll_in(int fd, int timeout_ms) = 0;
  /// errno of the last failing call on this thread.
  virtual int last_error() const = 0;
  /// mmap(2)/munmap(2) for streaming buffers. Not pure so older fakes that do
  /// not stream still compile: the defaults fail (MAP_FAILED / -1).
  virtual void* mmap(void* addr, size_t length, int prot, int flags, int fd, off_t offset) {
    (void)addr, (void)length, (void)prot, (void)flags, (void)fd, (void)offset;
    return MAP_FAILED;
  }
  virtual int munmap(void* addr, size_t length) {
    (void)addr, (void)length;
    return -1;
  }
};

/// The real kernel.
std::shared_ptr<SysCalls> real_syscalls();

}  // namespace station
