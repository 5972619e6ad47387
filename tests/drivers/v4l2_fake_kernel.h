#pragma once
// An in-process fake of the kernel's V4L2 side for driver tests: capture nodes
// with capabilities and formats, S_FMT, mmap buffers, QBUF/DQBUF queues,
// controls, and scripted faults (busy, EAGAIN, a device that goes silent,
// unplug mid-stream).
#include <linux/videodev2.h>
#include <sys/mman.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <deque>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include "drivers/syscalls.h"

namespace station::testing {

class FakeV4l2Kernel : public SysCalls {
 public:
  struct Node {
    std::string card = "Fake Cam", driver = "fakecam";
    std::uint32_t caps = V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_STREAMING;
    std::vector<std::uint32_t> formats;
    int width = 8, height = 6;  ///< the only size: S_FMT adjusts to it
    int pad = 0;                ///< extra bytes per row (bytesperline > minimum)
    int open_errno = 0;
    int eagain_before_each_frame = 0;
    int frames_before_silence = -1;
    int frames_before_unplug = -1;
    /// Frame bytes for (fourcc, width, bytesperline, height, sequence).
    std::function<std::vector<std::uint8_t>(std::uint32_t, int, int, int, int)> make_frame;
    std::map<std::uint32_t, int> controls;
    // State.
    std::uint32_t fourcc = 0;
    std::vector<std::vector<std::uint8_t>> mem;
    std::deque<int> queued;
    bool streaming = false;
    int delivered = 0, eagain_left = 0;
    int streamoffs = 0, qbufs = 0;
    int bytesperline() const { return (fourcc == V4L2_PIX_FMT_MJPEG ? 0 : 2 * width + pad); }
  };
  std::map<std::string, Node> nodes;
  std::map<int, std::string> fds;
  int mapped = 0;
  int next_fd = 10;

  int open(const char* path, int) override {
    auto it = nodes.find(path);
    if (it == nodes.end()) return fail(ENOENT);
    if (it->second.open_errno) return fail(it->second.open_errno);
    fds[next_fd] = path;
    return next_fd++;
  }
  int close(int fd) override {
    if (!fds.erase(fd)) return fail(EBADF);
    return 0;
  }
  ssize_t read(int, void*, size_t) override { return fail(EINVAL); }
  ssize_t write(int, const void*, size_t) override { return fail(EINVAL); }
  int poll_in(int fd, int) override {
    Node* n = node(fd);
    if (!n) return fail(EBADF);
    if (n->frames_before_silence >= 0 && n->delivered >= n->frames_before_silence) return 0;
    return 1;  // always "ready", as under umockdev: DQBUF decides
  }
  int last_error() const override { return err; }
  void* mmap(void*, size_t length, int, int, int fd, off_t offset) override {
    Node* n = node(fd);
    const std::size_t i = static_cast<std::size_t>(offset) / kStride;
    if (!n || i >= n->mem.size() || length != n->mem[i].size()) {
      err = EINVAL;
      return MAP_FAILED;
    }
    ++mapped;
    return n->mem[i].data();
  }
  int munmap(void*, size_t) override {
    --mapped;
    return 0;
  }

  int ioctl(int fd, unsigned long req, void* arg) override {
    Node* n = node(fd);
    if (!n) return fail(EBADF);
    switch (req) {
      case VIDIOC_QUERYCAP: {
        auto* c = static_cast<v4l2_capability*>(arg);
        std::memset(c, 0, sizeof *c);
        std::memcpy(c->card, n->card.data(), std::min(n->card.size(), sizeof c->card - 1));
        std::memcpy(c->driver, n->driver.data(), std::min(n->driver.size(), sizeof c->driver - 1));
        c->capabilities = n->caps | V4L2_CAP_DEVICE_CAPS;
        c->device_caps = n->caps;
        return 0;
      }
      case VIDIOC_ENUM_FMT: {
        auto* d = static_cast<v4l2_fmtdesc*>(arg);
        if (d->type != V4L2_BUF_TYPE_VIDEO_CAPTURE || d->index >= n->formats.size())
          return fail(EINVAL);
        d->pixelformat = n->formats[d->index];
        return 0;
      }
      case VIDIOC_G_FMT:
      case VIDIOC_S_FMT: {
        auto* f = static_cast<v4l2_format*>(arg);
        if (f->type != V4L2_BUF_TYPE_VIDEO_CAPTURE) return fail(EINVAL);
        if (req == VIDIOC_S_FMT) {
          if (n->streaming) return fail(EBUSY);
          bool known = false;
          for (auto x : n->formats) known |= x == f->fmt.pix.pixelformat;
          n->fourcc = known ? f->fmt.pix.pixelformat : n->formats.at(0);
        } else if (!n->fourcc) {
          n->fourcc = n->formats.at(0);
        }
        f->fmt.pix.pixelformat = n->fourcc;
        f->fmt.pix.width = static_cast<std::uint32_t>(n->width);
        f->fmt.pix.height = static_cast<std::uint32_t>(n->height);
        f->fmt.pix.bytesperline = static_cast<std::uint32_t>(n->bytesperline());
        f->fmt.pix.sizeimage = static_cast<std::uint32_t>(frame_size(*n));
        return 0;
      }
      case VIDIOC_S_CTRL: {
        auto* c = static_cast<v4l2_control*>(arg);
        n->controls[c->id] = c->value;
        return 0;
      }
      case VIDIOC_REQBUFS: {
        auto* r = static_cast<v4l2_requestbuffers*>(arg);
        if (r->memory != V4L2_MEMORY_MMAP) return fail(EINVAL);
        n->mem.assign(std::min<std::uint32_t>(r->count, 3),
                      std::vector<std::uint8_t>(frame_size(*n)));
        r->count = static_cast<std::uint32_t>(n->mem.size());
        return 0;
      }
      case VIDIOC_QUERYBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        if (b->index >= n->mem.size()) return fail(EINVAL);
        b->length = static_cast<std::uint32_t>(n->mem[b->index].size());
        b->m.offset = b->index * kStride;
        return 0;
      }
      case VIDIOC_QBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        if (b->index >= n->mem.size()) return fail(EINVAL);
        if (n->frames_before_unplug >= 0 && n->delivered >= n->frames_before_unplug)
          return fail(ENODEV);
        n->queued.push_back(static_cast<int>(b->index));
        ++n->qbufs;
        return 0;
      }
      case VIDIOC_DQBUF: {
        auto* b = static_cast<v4l2_buffer*>(arg);
        if (!n->streaming) return fail(EINVAL);
        if (n->frames_before_unplug >= 0 && n->delivered >= n->frames_before_unplug)
          return fail(ENODEV);
        if (n->eagain_left > 0) {
          --n->eagain_left;
          return fail(EAGAIN);
        }
        if (n->queued.empty()) return fail(EAGAIN);
        const int i = n->queued.front();
        n->queued.pop_front();
        std::vector<std::uint8_t> data =
            n->make_frame(n->fourcc, n->width, n->bytesperline(), n->height, n->delivered);
        auto& m = n->mem[static_cast<std::size_t>(i)];
        std::copy(data.begin(), data.begin() + std::min(data.size(), m.size()), m.begin());
        b->index = static_cast<std::uint32_t>(i);
        b->bytesused = static_cast<std::uint32_t>(std::min(data.size(), m.size()));
        b->sequence = static_cast<std::uint32_t>(n->delivered);
        b->flags = 0;
        ++n->delivered;
        n->eagain_left = n->eagain_before_each_frame;
        return 0;
      }
      case VIDIOC_STREAMON:
        n->streaming = true;
        n->eagain_left = n->eagain_before_each_frame;
        return 0;
      case VIDIOC_STREAMOFF:
        n->streaming = false;
        n->queued.clear();
        ++n->streamoffs;
        return 0;
      default:
        return fail(ENOTTY);
    }
  }

 private:
  static constexpr std::size_t kStride = 1 << 24;
  static std::size_t frame_size(const Node& n) {
    return n.fourcc == V4L2_PIX_FMT_MJPEG ? 1 << 16
                                          : static_cast<std::size_t>(n.bytesperline()) * n.height;
  }
  Node* node(int fd) {
    auto it = fds.find(fd);
    return it == fds.end() ? nullptr : &nodes[it->second];
  }
  int fail(int e) {
    err = e;
    return -1;
  }
  int err = 0;
};

}  // namespace station::testing
