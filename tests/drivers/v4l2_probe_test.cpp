#include "drivers/v4l2_probe.h"

#include <gtest/gtest.h>
#include <linux/videodev2.h>

#include <cerrno>
#include <cstring>
#include <map>

#include "core/error.h"

namespace station {
namespace {

// A scripted kernel: each path answers QUERYCAP with a fixed capability set,
// or fails to open (unplugged / no permission).
class FakeKernel : public SysCalls {
 public:
  struct Dev {
    bool opens = true;
    std::uint32_t caps = 0;
    const char* card = "";
  };
  std::map<std::string, Dev> devs;
  std::map<int, std::string> open_fds;
  int next_fd = 3;

  int open(const char* path, int) override {
    auto it = devs.find(path);
    if (it == devs.end() || !it->second.opens) {
      err = ENOENT;
      return -1;
    }
    open_fds[next_fd] = path;
    return next_fd++;
  }
  int close(int fd) override { return open_fds.erase(fd) ? 0 : -1; }
  int ioctl(int fd, unsigned long req, void* arg) override {
    if (req != VIDIOC_QUERYCAP || !open_fds.count(fd)) return -1;
    auto* cap = static_cast<v4l2_capability*>(arg);
    const Dev& d = devs[open_fds[fd]];
    cap->capabilities = d.caps;
    std::memset(cap->card, 'X', sizeof cap->card);  // unterminated, as the kernel may give
    std::memcpy(cap->card, d.card, std::strlen(d.card));
    std::strcpy(reinterpret_cast<char*>(cap->driver), "uvcvideo");
    return 0;
  }
  ssize_t read(int, void*, size_t) override { return -1; }
  ssize_t write(int, const void*, size_t) override { return -1; }
  int poll_in(int, int) override { return 0; }
  int last_error() const override { return err; }
  int err = 0;
};

TEST(V4l2Probe, ListsCaptureDevicesAndClosesEverything) {
  FakeKernel k;
  k.devs["/dev/video0"] = {true, V4L2_CAP_VIDEO_CAPTURE, "Depth Cam"};
  k.devs["/dev/video1"] = {true, V4L2_CAP_META_CAPTURE, "metadata node"};
  k.devs["/dev/video2"] = {false, V4L2_CAP_VIDEO_CAPTURE, "unplugged"};
  const auto found = probe_v4l2(k, {"/dev/video0", "/dev/video1", "/dev/video2", "/dev/video9"});
  ASSERT_EQ(found.size(), 1u);
  EXPECT_EQ(found[0].uri, "v4l2:/dev/video0");
  EXPECT_EQ(found[0].kind, DeviceKind::kScanner);
  EXPECT_FALSE(found[0].available);
  EXPECT_EQ(found[0].description.rfind("Depth Cam", 0), 0u);
  EXPECT_NE(found[0].description.find("uvcvideo"), std::string::npos);
  EXPECT_TRUE(k.open_fds.empty());
}

TEST(V4l2Probe, RegistryListsButCannotOpenYet) {
  auto k = std::make_shared<FakeKernel>();
  DeviceRegistry reg;
  register_v4l2_probe(reg, k);
  EXPECT_THROW(reg.make_scanner("v4l2:/dev/video0"), DeviceError);
}

}  // namespace
}  // namespace station
