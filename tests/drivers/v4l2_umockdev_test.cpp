// V4L2 through the real system calls (open/ioctl/mmap/poll/close of
// real_syscalls()) under umockdev: run as
//   umockdev-wrapper build/tests/drivers_tests --gtest_filter='Umockdev*'
// Without the wrapper (LD_PRELOAD lacks libumockdev-preload) or without the
// umockdev runtime library the tests skip with a message.
//
// libumockdev is loaded with dlopen so the default build needs neither its
// headers nor its library. The ioctl handler (UMockdevIoctlBase "handle-ioctl"
// signal, called on umockdev's worker thread) serves QUERYCAP, ENUM_FMT,
// G_FMT/S_FMT, REQBUFS, QUERYBUF, QBUF/DQBUF, STREAMON/OFF. umockdev does not
// intercept mmap, so the device node is a plain file (created with contents
// through add_from_string, "N: video0=00") and the handler writes each frame
// into that file at its buffer's offset; poll on a plain file is always ready,
// so DQBUF answers EAGAIN while nothing is queued or due.
#include <dlfcn.h>
#include <fcntl.h>
#include <gtest/gtest.h>
#include <linux/videodev2.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <string>
#include <vector>

#include "core/error.h"
#include "drivers/syscalls.h"
#include "drivers/v4l2_camera.h"

namespace station {
namespace {

// The few umockdev / GObject entry points used, as opaque C functions.
struct GErrorView {
  unsigned domain;
  int code;
  char* message;
};
struct Umockdev {
  void* lib = nullptr;
  void* (*testbed_new)();
  char* (*testbed_get_root_dir)(void*);
  int (*testbed_attach_ioctl)(void*, const char*, void*, GErrorView**);
  int (*testbed_add_from_string)(void*, const char*, GErrorView**);
  void* (*ioctl_base_new)();
  unsigned long (*client_get_request)(void*);
  void* (*client_get_arg)(void*);
  void (*client_complete)(void*, long, int);
  void* (*data_resolve)(void*, std::size_t, std::size_t, GErrorView**);
  void (*data_update)(void*, std::size_t, std::uint8_t*, int);
  void (*data_retrieve)(void*, std::uint8_t**, int*);
  unsigned long (*signal_connect_data)(void*, const char*, void*, void*, void*, int);
  void (*object_unref)(void*);
  void (*g_free)(void*);

  std::string load() {
    lib = dlopen("libumockdev.so.0", RTLD_NOW | RTLD_LOCAL);
    if (!lib) return std::string("cannot load libumockdev.so.0 (install umockdev): ") + dlerror();
    bool ok = true;
    auto get = [&](auto& fn, const char* name) {
      void* p = dlsym(lib, name);
      ok = ok && p;
      fn = reinterpret_cast<std::remove_reference_t<decltype(fn)>>(p);
    };
    get(testbed_new, "umockdev_testbed_new");
    get(testbed_get_root_dir, "umockdev_testbed_get_root_dir");
    get(testbed_attach_ioctl, "umockdev_testbed_attach_ioctl");
    get(testbed_add_from_string, "umockdev_testbed_add_from_string");
    get(ioctl_base_new, "umockdev_ioctl_base_new");
    get(client_get_request, "umockdev_ioctl_client_get_request");
    get(client_get_arg, "umockdev_ioctl_client_get_arg");
    get(client_complete, "umockdev_ioctl_client_complete");
    get(data_resolve, "umockdev_ioctl_data_resolve");
    get(data_update, "umockdev_ioctl_data_update");
    get(data_retrieve, "umockdev_ioctl_data_retrieve");
    get(signal_connect_data, "g_signal_connect_data");
    get(object_unref, "g_object_unref");
    get(g_free, "g_free");
    return ok ? "" : "libumockdev.so.0 lacks the ioctl emulation API (umockdev >= 0.16 needed)";
  }
};

bool under_wrapper() {
  const char* p = std::getenv("LD_PRELOAD");
  return p && std::strstr(p, "libumockdev-preload");
}

// A Z16 depth camera, 4x3: pixel (x, y) of frame s = 1000 + 100 s + 10 y + x.
struct Camera {
  Umockdev* um = nullptr;
  std::string node_file;
  int width = 4, height = 3;
  std::size_t buffer_size = 4096;  // page aligned offsets for mmap
  std::size_t buffers = 0;
  std::deque<std::uint32_t> queued;
  bool streaming = false;
  int delivered = 0, eagain_left = 0;
  int eagain_before_each_frame = 0;
  int frames_before_silence = -1;
  int streamoffs = 0;
  std::vector<unsigned long> requests;

  long handle(unsigned long req, std::uint8_t* a, int& err) {
    requests.push_back(req);
    switch (req) {
      case VIDIOC_QUERYCAP: {
        auto* c = reinterpret_cast<v4l2_capability*>(a);
        std::memset(c, 0, sizeof *c);
        std::strcpy(reinterpret_cast<char*>(c->card), "umockdev depth");
        std::strcpy(reinterpret_cast<char*>(c->driver), "fakeuvc");
        c->capabilities = V4L2_CAP_VIDEO_CAPTURE | V4L2_CAP_STREAMING;
        return 0;
      }
      case VIDIOC_ENUM_FMT: {
        auto* d = reinterpret_cast<v4l2_fmtdesc*>(a);
        if (d->index > 0) return err = EINVAL, -1;
        d->pixelformat = v4l2_fourcc('Z', '1', '6', ' ');
        return 0;
      }
      case VIDIOC_G_FMT:
      case VIDIOC_S_FMT: {
        auto* f = reinterpret_cast<v4l2_format*>(a);
        f->fmt.pix.pixelformat = v4l2_fourcc('Z', '1', '6', ' ');
        f->fmt.pix.width = width;
        f->fmt.pix.height = height;
        f->fmt.pix.bytesperline = 2 * width;
        f->fmt.pix.sizeimage = 2 * width * height;
        return 0;
      }
      case VIDIOC_REQBUFS: {
        auto* r = reinterpret_cast<v4l2_requestbuffers*>(a);
        buffers = std::min<std::uint32_t>(r->count, 2);
        r->count = static_cast<std::uint32_t>(buffers);
        // The mmap'ed memory is the node's backing file: make it long enough.
        const int fd = ::open(node_file.c_str(), O_RDWR);
        if (fd < 0 || ::ftruncate(fd, static_cast<off_t>(buffers * buffer_size)) < 0)
          return err = EIO, -1;
        ::close(fd);
        return 0;
      }
      case VIDIOC_QUERYBUF: {
        auto* b = reinterpret_cast<v4l2_buffer*>(a);
        if (b->index >= buffers) return err = EINVAL, -1;
        b->length = static_cast<std::uint32_t>(2 * width * height);
        b->m.offset = static_cast<std::uint32_t>(b->index * buffer_size);
        return 0;
      }
      case VIDIOC_QBUF: {
        auto* b = reinterpret_cast<v4l2_buffer*>(a);
        if (b->index >= buffers) return err = EINVAL, -1;
        queued.push_back(b->index);
        return 0;
      }
      case VIDIOC_DQBUF: {
        auto* b = reinterpret_cast<v4l2_buffer*>(a);
        if (!streaming) return err = EINVAL, -1;
        if (frames_before_silence >= 0 && delivered >= frames_before_silence)
          return err = EAGAIN, -1;
        if (eagain_left > 0) return --eagain_left, err = EAGAIN, -1;
        if (queued.empty()) return err = EAGAIN, -1;
        const std::uint32_t i = queued.front();
        queued.pop_front();
        std::vector<std::uint8_t> frame(2 * width * height);
        for (int y = 0; y < height; ++y)
          for (int x = 0; x < width; ++x) {
            const unsigned v = 1000 + 100 * delivered + 10 * y + x;
            frame[2 * (y * width + x)] = v & 0xff;
            frame[2 * (y * width + x) + 1] = v >> 8;
          }
        const int fd = ::open(node_file.c_str(), O_RDWR);
        const bool written = fd >= 0 && ::pwrite(fd, frame.data(), frame.size(),
                                                 static_cast<off_t>(i * buffer_size)) ==
                                            static_cast<ssize_t>(frame.size());
        if (fd >= 0) ::close(fd);
        if (!written) return err = EIO, -1;
        b->index = i;
        b->bytesused = static_cast<std::uint32_t>(frame.size());
        b->flags = 0;
        b->sequence = static_cast<std::uint32_t>(delivered++);
        eagain_left = eagain_before_each_frame;
        return 0;
      }
      case VIDIOC_STREAMON:
        streaming = true;
        eagain_left = eagain_before_each_frame;
        return 0;
      case VIDIOC_STREAMOFF:
        streaming = false;
        queued.clear();
        ++streamoffs;
        return 0;
      default:
        return err = ENOTTY, -1;
    }
  }
};

int on_ioctl(void* /*handler*/, void* client, void* user) {
  auto* cam = static_cast<Camera*>(user);
  Umockdev& um = *cam->um;
  const unsigned long req = um.client_get_request(client);
  const std::size_t size = _IOC_SIZE(req);
  GErrorView* error = nullptr;
  void* data = um.data_resolve(um.client_get_arg(client), 0, size, &error);
  if (!data) {
    um.client_complete(client, -1, EFAULT);
    return 1;
  }
  std::uint8_t* bytes = nullptr;
  int len = 0;
  um.data_retrieve(data, &bytes, &len);
  std::vector<std::uint8_t> local(bytes, bytes + len);
  um.g_free(bytes);
  local.resize(std::max<std::size_t>(local.size(), size));
  int err = 0;
  const long r = cam->handle(req, local.data(), err);
  um.data_update(data, 0, local.data(), static_cast<int>(size));
  um.client_complete(client, r, r < 0 ? err : 0);
  return 1;
}

class Umockdev4l2 : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!under_wrapper())
      GTEST_SKIP() << "not under umockdev-wrapper (LD_PRELOAD lacks libumockdev-preload); run "
                      "umockdev-wrapper drivers_tests --gtest_filter='Umockdev*'";
    const std::string why = um_.load();
    if (!why.empty()) GTEST_SKIP() << why;
    cam_.um = &um_;
    testbed_ = um_.testbed_new();
    char* root = um_.testbed_get_root_dir(testbed_);
    cam_.node_file = std::string(root) + "/dev/video0";
    um_.g_free(root);
    handler_ = um_.ioctl_base_new();
    um_.signal_connect_data(handler_, "handle-ioctl", reinterpret_cast<void*>(&on_ioctl), &cam_,
                            nullptr, 0);
    GErrorView* error = nullptr;
    ASSERT_TRUE(um_.testbed_attach_ioctl(testbed_, "/dev/video0", handler_, &error));
    // With contents ("=00") the node is a plain file, which mmap can map.
    ASSERT_TRUE(um_.testbed_add_from_string(testbed_,
                                            "P: /devices/virtual/video4linux/video0\n"
                                            "N: video0=00\n"
                                            "E: SUBSYSTEM=video4linux\n"
                                            "E: DEVNAME=/dev/video0\n"
                                            "A: name=umockdev depth\n"
                                            "A: dev=81:0\n",
                                            &error));
  }
  void TearDown() override {
    if (handler_) um_.object_unref(handler_);
    if (testbed_) um_.object_unref(testbed_);
  }
  std::unique_ptr<V4l2Camera> camera(const std::string& query) {
    return std::make_unique<V4l2Camera>(
        real_syscalls(), parse_device_uri("v4l2:/dev/video0?fx=3&fy=3&cx=1.5&cy=1" + query));
  }
  Umockdev um_;
  Camera cam_;
  void* testbed_ = nullptr;
  void* handler_ = nullptr;
};

TEST_F(Umockdev4l2, StreamsDepthThroughRealSyscallsAndMmap) {
  auto cam = camera("&buffers=2");
  cam->open();
  for (int s = 0; s < 5; ++s) {  // more frames than buffers: each is requeued
    const Frame f = cam->grab();
    ASSERT_EQ(f.depth.size(), 12u);
    EXPECT_NEAR(f.depth[0], (1000 + 100 * s) * 0.001, 1e-6);
    EXPECT_NEAR(f.depth[2 * 4 + 3], (1000 + 100 * s + 23) * 0.001, 1e-6);
  }
  cam->close();
  EXPECT_EQ(cam_.streamoffs, 1);
}

TEST_F(Umockdev4l2, EagainWhilePollIsAlwaysReady) {
  cam_.eagain_before_each_frame = 4;
  auto cam = camera("");
  cam->open();
  EXPECT_NEAR(cam->grab().depth[1], 1.001, 1e-6);
  EXPECT_NEAR(cam->grab().depth[1], 1.101, 1e-6);
}

TEST_F(Umockdev4l2, DeviceThatStopsSendingTimesOut) {
  cam_.frames_before_silence = 1;
  auto cam = camera("&timeout_ms=100");
  cam->open();
  cam->grab();
  try {
    cam->grab();
    FAIL() << "expected a time-out";
  } catch (const DeviceError& e) {
    EXPECT_NE(std::string(e.what()).find("/dev/video0: no frame within 100 ms"), std::string::npos)
        << e.what();
  }
}

}  // namespace
}  // namespace station
