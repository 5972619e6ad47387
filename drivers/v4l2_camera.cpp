#include "drivers/v4l2_camera.h"

#include <fcntl.h>
#include <linux/videodev2.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>
#include <thread>

#include "core/error.h"
#include "drivers/serial_turntable.h"  // option readers
#include "drivers/v4l2_probe.h"

namespace station {
namespace {

#ifndef V4L2_PIX_FMT_Z16
#define V4L2_PIX_FMT_Z16 v4l2_fourcc('Z', '1', '6', ' ')
#endif

constexpr std::uint32_t kPreference[] = {V4L2_PIX_FMT_Z16, V4L2_PIX_FMT_Y16, V4L2_PIX_FMT_YUYV,
                                         V4L2_PIX_FMT_MJPEG};

bool is_depth(std::uint32_t f) { return f == V4L2_PIX_FMT_Z16 || f == V4L2_PIX_FMT_Y16; }
bool is_colour(std::uint32_t f) {
  return f == V4L2_PIX_FMT_YUYV || f == V4L2_PIX_FMT_MJPEG || f == V4L2_PIX_FMT_JPEG;
}

std::uint32_t parse_fourcc(const std::string& s, const std::string& who) {
  std::string f = s;
  if (f == "MJPEG") f = "MJPG";
  if (f.size() < 2 || f.size() > 4)
    throw DeviceError(who + ": format '" + s + "': expected YUYV, MJPG, Z16, Y16 or auto");
  while (f.size() < 4) f.push_back(' ');
  return v4l2_fourcc(f[0], f[1], f[2], f[3]);
}

std::string errno_text(int e) { return std::strerror(e); }

std::uint8_t clamp8(int v) { return static_cast<std::uint8_t>(std::clamp(v, 0, 255)); }

std::string fixed_string(const std::uint8_t* s, std::size_t n) {
  const char* c = reinterpret_cast<const char*>(s);
  return std::string(c, strnlen(c, n));
}

}  // namespace

std::string fourcc_text(std::uint32_t f) {
  std::string s;
  for (int i = 0; i < 4; ++i) s.push_back(static_cast<char>((f >> (8 * i)) & 0xff));
  while (!s.empty() && s.back() == ' ') s.pop_back();
  return s;
}

// ---- conversions ---------------------------------------------------------------

void yuyv_to_rgb(const std::uint8_t* src, int width, int height, int stride,
                 std::vector<std::uint8_t>& rgb) {
  rgb.resize(static_cast<std::size_t>(width) * height * 3);
  // Fixed point (x256) BT.601 limited range:
  // R = 1.164 (Y-16) + 1.596 (V-128)
  // G = 1.164 (Y-16) - 0.392 (U-128) - 0.813 (V-128)
  // B = 1.164 (Y-16) + 2.017 (U-128)
  for (int y = 0; y < height; ++y) {
    const std::uint8_t* row = src + static_cast<std::size_t>(y) * stride;
    std::uint8_t* out = rgb.data() + static_cast<std::size_t>(y) * width * 3;
    for (int x = 0; x < width; ++x) {
      const int pair = x / 2;
      const int luma = row[4 * pair + (x % 2 ? 2 : 0)];
      const int u = row[4 * pair + 1] - 128, v = row[4 * pair + 3] - 128;
      const int c = 298 * (luma - 16) + 128;
      out[3 * x + 0] = clamp8((c + 409 * v) >> 8);
      out[3 * x + 1] = clamp8((c - 100 * u - 208 * v) >> 8);
      out[3 * x + 2] = clamp8((c + 516 * u) >> 8);
    }
  }
}

void mjpeg_to_rgb(const std::uint8_t* data, std::size_t size, int width, int height,
                  const std::string& who, std::vector<std::uint8_t>& rgb) {
  if (size == 0) throw DeviceError(who + ": empty MJPEG frame");
  const cv::Mat encoded(1, static_cast<int>(size), CV_8UC1, const_cast<std::uint8_t*>(data));
  cv::Mat bgr;
  try {
    bgr = cv::imdecode(encoded, cv::IMREAD_COLOR);
  } catch (const cv::Exception&) {
    bgr.release();
  }
  if (bgr.empty())
    throw DeviceError(who + ": MJPEG frame does not decode (" + std::to_string(size) + " bytes)");
  if (bgr.cols != width || bgr.rows != height)
    throw DeviceError(who + ": MJPEG frame is " + std::to_string(bgr.cols) + "x" +
                      std::to_string(bgr.rows) + ", expected " + std::to_string(width) + "x" +
                      std::to_string(height));
  cv::Mat out(height, width, CV_8UC3);
  cv::cvtColor(bgr, out, cv::COLOR_BGR2RGB);
  rgb.assign(out.data, out.data + static_cast<std::size_t>(width) * height * 3);
}

void depth16_to_metres(const std::uint8_t* src, int width, int height, int stride, double scale,
                       std::vector<float>& metres) {
  metres.resize(static_cast<std::size_t>(width) * height);
  for (int y = 0; y < height; ++y) {
    const std::uint8_t* row = src + static_cast<std::size_t>(y) * stride;
    for (int x = 0; x < width; ++x) {
      const unsigned d = row[2 * x] | (static_cast<unsigned>(row[2 * x + 1]) << 8);
      metres[static_cast<std::size_t>(y) * width + x] = static_cast<float>(d * scale);
    }
  }
}

std::vector<std::uint8_t> register_colour_to_depth(const std::vector<float>& depth,
                                                  const Intrinsics& dk,
                                                  const std::vector<std::uint8_t>& rgb,
                                                  const Intrinsics& ck,
                                                  const std::array<double, 12>& m) {
  std::vector<std::uint8_t> out(static_cast<std::size_t>(dk.width) * dk.height * 3, 0);
  for (int v = 0; v < dk.height; ++v)
    for (int u = 0; u < dk.width; ++u) {
      const std::size_t i = static_cast<std::size_t>(v) * dk.width + u;
      const double z = depth[i];
      if (!(z > 0)) continue;
      // Through the lenses' distortion when the profile gives it (station calibrate camera).
      const Eigen::Vector2d ray = pixel_to_ray(dk, u, v);
      const double x = ray.x() * z, y = ray.y() * z;
      const double X = m[0] * x + m[1] * y + m[2] * z + m[3];
      const double Y = m[4] * x + m[5] * y + m[6] * z + m[7];
      const double Z = m[8] * x + m[9] * y + m[10] * z + m[11];
      if (!(Z > 0)) continue;
      const Eigen::Vector2d px = ray_to_pixel(ck, X / Z, Y / Z);
      const long cu = std::lround(px.x()), cv = std::lround(px.y());
      if (cu < 0 || cv < 0 || cu >= ck.width || cv >= ck.height) continue;
      const std::size_t j = (static_cast<std::size_t>(cv) * ck.width + cu) * 3;
      std::copy(rgb.begin() + j, rgb.begin() + j + 3, out.begin() + i * 3);
    }
  return out;
}

// ---- one node ------------------------------------------------------------------

V4l2Stream::V4l2Stream(std::shared_ptr<SysCalls> sys, std::string path, std::string who)
    : sys_(std::move(sys)), path_(std::move(path)), who_(std::move(who)) {}

V4l2Stream::~V4l2Stream() {
  try {
    stop();
  } catch (...) {
  }
}

namespace {
std::vector<std::uint32_t> enum_formats(SysCalls& sys, int fd) {
  std::vector<std::uint32_t> formats;
  for (std::uint32_t i = 0; i < 64; ++i) {
    v4l2_fmtdesc d;
    std::memset(&d, 0, sizeof d);
    d.index = i;
    d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (sys.ioctl(fd, VIDIOC_ENUM_FMT, &d) < 0) break;
    formats.push_back(d.pixelformat);
  }
  return formats;
}

std::string format_list(const std::vector<std::uint32_t>& f) {
  std::string s;
  for (auto x : f) s += (s.empty() ? "" : ", ") + fourcc_text(x);
  return s.empty() ? "none" : s;
}
}  // namespace

void V4l2Stream::start(const Settings& s) {
  stop();
  timeout_ms_ = s.timeout_ms;
  const int fd = sys_->open(path_.c_str(), O_RDWR | O_NONBLOCK);
  if (fd < 0) {
    const int e = sys_->last_error();
    if (e == EBUSY) throw DeviceError(who_ + ": " + path_ + ": busy (another program has it open)");
    if (e == ENOENT || e == ENODEV || e == ENXIO)
      throw DeviceError(who_ + ": " + path_ + ": no such device (unplugged?)");
    if (e == EACCES || e == EPERM)
      throw DeviceError(who_ + ": " + path_ +
                        ": permission denied (is the user in the video group?)");
    throw DeviceError(who_ + ": " + path_ + ": cannot open: " + errno_text(e));
  }
  fd_ = fd;
  try {
    auto fail = [&](const std::string& what) -> DeviceError {
      const int e = sys_->last_error();
      if (e == EBUSY)
        return DeviceError(who_ + ": " + path_ + ": busy (another program has it open)");
      if (e == ENODEV || e == EIO)
        return DeviceError(who_ + ": " + path_ + ": " + what + " failed (unplugged?)");
      return DeviceError(who_ + ": " + path_ + ": " + what + " failed: " + errno_text(e));
    };
    v4l2_capability cap;
    std::memset(&cap, 0, sizeof cap);
    if (sys_->ioctl(fd, VIDIOC_QUERYCAP, &cap) < 0)
      throw fail("VIDIOC_QUERYCAP (not a V4L2 device?)");
    const std::uint32_t caps =
        (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
    if (!(caps & V4L2_CAP_VIDEO_CAPTURE))
      throw DeviceError(who_ + ": " + path_ +
                        ": not a video capture node (a metadata or output node?)");
    if (!(caps & V4L2_CAP_STREAMING))
      throw DeviceError(who_ + ": " + path_ + ": does not support streaming I/O");

    const auto formats = enum_formats(*sys_, fd);
    std::uint32_t want = 0;
    if (s.format.empty() || s.format == "auto") {
      for (auto f : kPreference)
        if (std::find(formats.begin(), formats.end(), f) != formats.end()) {
          want = f;
          break;
        }
      if (!want)
        throw DeviceError(who_ + ": " + path_ + ": offers no supported format (offers " +
                          format_list(formats) + "; supported: Z16, Y16, YUYV, MJPG)");
    } else {
      want = parse_fourcc(s.format, who_);
      if (std::find(formats.begin(), formats.end(), want) == formats.end())
        throw DeviceError(who_ + ": " + path_ + ": format " + fourcc_text(want) +
                          " not offered (offers " + format_list(formats) + ")");
      if (!is_depth(want) && !is_colour(want))
        throw DeviceError(who_ + ": format " + fourcc_text(want) +
                          " not supported (supported: Z16, Y16, YUYV, MJPG)");
    }

    v4l2_format fmt;
    std::memset(&fmt, 0, sizeof fmt);
    fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (sys_->ioctl(fd, VIDIOC_G_FMT, &fmt) < 0) throw fail("VIDIOC_G_FMT");
    fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (s.width > 0) fmt.fmt.pix.width = static_cast<std::uint32_t>(s.width);
    if (s.height > 0) fmt.fmt.pix.height = static_cast<std::uint32_t>(s.height);
    fmt.fmt.pix.pixelformat = want;
    fmt.fmt.pix.field = V4L2_FIELD_NONE;
    fmt.fmt.pix.bytesperline = 0;
    if (sys_->ioctl(fd, VIDIOC_S_FMT, &fmt) < 0) throw fail("VIDIOC_S_FMT " + fourcc_text(want));
    if (fmt.fmt.pix.pixelformat != want)
      throw DeviceError(who_ + ": " + path_ + ": driver switched format " + fourcc_text(want) +
                        " to " + fourcc_text(fmt.fmt.pix.pixelformat));
    fourcc_ = want;
    width_ = static_cast<int>(fmt.fmt.pix.width);
    height_ = static_cast<int>(fmt.fmt.pix.height);
    if (width_ <= 0 || height_ <= 0 || width_ > 16384 || height_ > 16384)
      throw DeviceError(who_ + ": " + path_ + ": driver reports a bad size " +
                        std::to_string(width_) + "x" + std::to_string(height_));
    const int min_stride =
        fourcc_ == V4L2_PIX_FMT_MJPEG || fourcc_ == V4L2_PIX_FMT_JPEG ? 0 : 2 * width_;
    stride_ = std::max<int>(static_cast<int>(fmt.fmt.pix.bytesperline), min_stride);

    if (s.exposure) {
      set_control(V4L2_CID_EXPOSURE_AUTO, V4L2_EXPOSURE_MANUAL, "auto exposure off");
      set_control(V4L2_CID_EXPOSURE_ABSOLUTE, *s.exposure, "exposure");
    }
    if (s.white_balance) {
      set_control(V4L2_CID_AUTO_WHITE_BALANCE, 0, "auto white balance off");
      set_control(V4L2_CID_WHITE_BALANCE_TEMPERATURE, *s.white_balance, "white balance");
    }

    v4l2_requestbuffers req;
    std::memset(&req, 0, sizeof req);
    req.count = static_cast<std::uint32_t>(s.buffers);
    req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    req.memory = V4L2_MEMORY_MMAP;
    if (sys_->ioctl(fd, VIDIOC_REQBUFS, &req) < 0) throw fail("VIDIOC_REQBUFS");
    if (req.count < 1) throw DeviceError(who_ + ": " + path_ + ": driver granted no buffers");
    for (std::uint32_t i = 0; i < req.count; ++i) {
      v4l2_buffer b;
      std::memset(&b, 0, sizeof b);
      b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
      b.memory = V4L2_MEMORY_MMAP;
      b.index = i;
      if (sys_->ioctl(fd, VIDIOC_QUERYBUF, &b) < 0) throw fail("VIDIOC_QUERYBUF");
      void* p = sys_->mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd, b.m.offset);
      if (p == MAP_FAILED) throw fail("mmap of buffer " + std::to_string(i));
      buffers_.push_back({p, b.length});
      if (sys_->ioctl(fd, VIDIOC_QBUF, &b) < 0) throw fail("VIDIOC_QBUF");
    }
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (sys_->ioctl(fd, VIDIOC_STREAMON, &type) < 0) throw fail("VIDIOC_STREAMON");
    streaming_ = true;
  } catch (...) {
    stop();
    throw;
  }
}

void V4l2Stream::set_control(std::uint32_t id, int value, const char* name) {
  v4l2_control c;
  c.id = id;
  c.value = value;
  if (sys_->ioctl(fd_, VIDIOC_S_CTRL, &c) < 0)
    throw DeviceError(who_ + ": " + path_ + ": cannot set " + name + " to " +
                      std::to_string(value) + ": " + errno_text(sys_->last_error()));
}

void V4l2Stream::stop() {
  if (fd_ < 0) return;
  if (streaming_) {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    sys_->ioctl(fd_, VIDIOC_STREAMOFF, &type);
  }
  for (const Buffer& b : buffers_) sys_->munmap(b.start, b.length);
  buffers_.clear();
  sys_->close(fd_);
  fd_ = -1;
  held_ = -1;
  streaming_ = false;
}

void V4l2Stream::requeue() {
  if (held_ < 0) return;
  v4l2_buffer b;
  std::memset(&b, 0, sizeof b);
  b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  b.memory = V4L2_MEMORY_MMAP;
  b.index = static_cast<std::uint32_t>(held_);
  held_ = -1;
  if (sys_->ioctl(fd_, VIDIOC_QBUF, &b) < 0) {
    const int e = sys_->last_error();
    throw DeviceError(
        who_ + ": " + path_ + ": VIDIOC_QBUF failed" +
        (e == ENODEV || e == EIO ? std::string(" (unplugged?)") : ": " + errno_text(e)));
  }
}

V4l2Stream::Raw V4l2Stream::next_frame() {
  if (!streaming_) throw DeviceError(who_ + ": " + path_ + ": grab before open()");
  requeue();
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms_);
  auto timed_out = [&] {
    return DeviceError(who_ + ": " + path_ + ": no frame within " + std::to_string(timeout_ms_) +
                       " ms (the device stopped sending)");
  };
  for (;;) {
    const long long left = std::chrono::duration_cast<std::chrono::milliseconds>(
                               deadline - std::chrono::steady_clock::now())
                               .count();
    if (left <= 0) throw timed_out();
    const int r = sys_->poll_in(fd_, static_cast<int>(left));
    if (r == 0) throw timed_out();
    if (r < 0) {
      if (sys_->last_error() == EINTR) continue;
      throw DeviceError(who_ + ": " + path_ + ": poll failed: " + errno_text(sys_->last_error()));
    }
    v4l2_buffer b;
    std::memset(&b, 0, sizeof b);
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (sys_->ioctl(fd_, VIDIOC_DQBUF, &b) < 0) {
      const int e = sys_->last_error();
      if (e == EAGAIN || e == EINTR) {
        // Nothing done yet although poll said ready (umockdev's poll always is).
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
        continue;
      }
      if (e == ENODEV || e == EIO || e == ENXIO)
        throw DeviceError(who_ + ": " + path_ + ": device gone while streaming (unplugged?)");
      throw DeviceError(who_ + ": " + path_ + ": VIDIOC_DQBUF failed: " + errno_text(e));
    }
    if (b.index >= buffers_.size())
      throw DeviceError(who_ + ": " + path_ + ": driver returned unknown buffer " +
                        std::to_string(b.index));
    held_ = static_cast<int>(b.index);
    const std::size_t used = b.bytesused ? b.bytesused : buffers_[b.index].length;
    const bool compressed = fourcc_ == V4L2_PIX_FMT_MJPEG || fourcc_ == V4L2_PIX_FMT_JPEG;
    if ((b.flags & V4L2_BUF_FLAG_ERROR) || used > buffers_[b.index].length ||
        (!compressed && used < static_cast<std::size_t>(stride_) * (height_ - 1) + 2u * width_)) {
      requeue();  // a damaged or short frame: wait for the next one
      continue;
    }
    Raw raw;
    raw.data = static_cast<const std::uint8_t*>(buffers_[b.index].start);
    raw.bytes = used;
    raw.fourcc = fourcc_;
    raw.width = width_;
    raw.height = height_;
    raw.stride = stride_;
    return raw;
  }
}

// ---- discovery -----------------------------------------------------------------

bool V4l2NodeInfo::has_depth() const {
  return std::any_of(formats.begin(), formats.end(), is_depth);
}
bool V4l2NodeInfo::has_colour() const {
  return std::any_of(formats.begin(), formats.end(), is_colour);
}

std::vector<V4l2NodeInfo> describe_v4l2_nodes(SysCalls& sys,
                                              const std::vector<std::string>& paths) {
  std::vector<V4l2NodeInfo> out;
  for (const auto& path : paths) {
    const int fd = sys.open(path.c_str(), O_RDWR | O_NONBLOCK);
    if (fd < 0) continue;
    v4l2_capability cap;
    std::memset(&cap, 0, sizeof cap);
    if (sys.ioctl(fd, VIDIOC_QUERYCAP, &cap) < 0) {
      sys.close(fd);
      continue;
    }
    const std::uint32_t caps =
        (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
    if (caps & V4L2_CAP_VIDEO_CAPTURE) {
      V4l2NodeInfo info;
      info.path = path;
      info.card = fixed_string(cap.card, sizeof cap.card);
      info.driver = fixed_string(cap.driver, sizeof cap.driver);
      info.formats = enum_formats(sys, fd);
      out.push_back(info);
    }
    sys.close(fd);
  }
  return out;
}

// ---- the scanner ---------------------------------------------------------------

struct V4l2Camera::Parsed {
  std::string path, colour_path, card;
  V4l2Stream::Settings main, colour;
  double depth_scale = 0.001;
  Intrinsics k, colour_k;
  bool has_k = false, has_colour_k = false;
  std::optional<std::array<double, 12>> extrinsics;
};

V4l2Camera::V4l2Camera(std::shared_ptr<SysCalls> sys, const DeviceUri& uri,
                       std::vector<std::string> paths)
    : sys_(std::move(sys)), uri_(uri), paths_(std::move(paths)), p_(parse(uri_)) {}

V4l2Camera::~V4l2Camera() { close(); }

std::unique_ptr<V4l2Camera::Parsed> V4l2Camera::parse(const DeviceUri& uri) {
  const std::string& who = uri.text;
  const DeviceOptions& o = uri.options;
  reject_unknown_options(
      o, {"format",        "width",        "height",      "buffers",      "timeout_ms", "exposure",
          "white_balance", "depth_scale",  "fx",          "fy",           "cx",         "cy",
          "color",         "color_format", "color_width", "color_height", "color_fx",   "color_fy",
          "color_cx",      "color_cy",     "extrinsics",  "card",         "distortion", "color_distortion"},
      who);
  auto p = std::make_unique<Parsed>();
  p->path = uri.path;
  if (p->path.empty())
    throw DeviceError(who + ": no device path (e.g. v4l2:/dev/video0 or v4l2:auto)");
  auto fill = [&](V4l2Stream::Settings& s, const std::string& prefix) {
    if (o.count(prefix + "format")) s.format = o.at(prefix + "format");
    if (s.format != "auto") parse_fourcc(s.format, who);
    s.width = option_integer(o, prefix + "width", 0, 0, 16384, who);
    s.height = option_integer(o, prefix + "height", 0, 0, 16384, who);
    s.buffers = option_integer(o, "buffers", 4, 1, 32, who);
    s.timeout_ms = option_integer(o, "timeout_ms", 2000, 1, 600000, who);
    if (o.count("exposure")) s.exposure = option_integer(o, "exposure", 0, 1, 1000000, who);
    if (o.count("white_balance"))
      s.white_balance = option_integer(o, "white_balance", 0, 1000, 20000, who);
  };
  fill(p->main, "");
  fill(p->colour, "color_");
  p->depth_scale = option_number(o, "depth_scale", 0.001, 1e-9, 1e3, who);
  auto intr = [&](Intrinsics& k, const std::string& prefix) {
    const char* keys[] = {"fx", "fy", "cx", "cy"};
    int n = 0;
    for (auto key : keys) n += o.count(prefix + key) ? 1 : 0;
    if (n == 0) return false;
    if (n != 4)
      throw DeviceError(who + ": give all of " + prefix + "fx, " + prefix + "fy, " + prefix +
                        "cx, " + prefix + "cy or none");
    k.fx = option_number(o, prefix + "fx", 0, 1e-6, 1e7, who);
    k.fy = option_number(o, prefix + "fy", 0, 1e-6, 1e7, who);
    k.cx = option_number(o, prefix + "cx", 0, -1e7, 1e7, who);
    k.cy = option_number(o, prefix + "cy", 0, -1e7, 1e7, who);
    option_distortion(o, prefix + "distortion", k, who);
    return true;
  };
  p->has_k = intr(p->k, "");
  p->has_colour_k = intr(p->colour_k, "color_");
  if (o.count("color")) p->colour_path = o.at("color");
  if (o.count("card")) p->card = o.at("card");
  if (o.count("extrinsics")) {
    const std::vector<double> e = option_numbers(o, "extrinsics", 12, "3x4 [R|t]", who);
    std::array<double, 12> m{};
    std::copy(e.begin(), e.end(), m.begin());
    p->extrinsics = m;
  }
  return p;
}

void V4l2Camera::configure(const DeviceOptions& options) {
  DeviceUri next = uri_;
  for (const auto& [k, v] : options) next.options[k] = v;
  auto parsed = parse(next);  // a bad option changes nothing
  const bool was_open = main_ != nullptr;
  close();
  uri_ = std::move(next);
  p_ = std::move(parsed);
  if (was_open) open();
}

void V4l2Camera::open() {
  if (main_) return;
  const std::string& who = uri_.text;
  std::string main_path = p_->path, colour_path = p_->colour_path;
  if (main_path == "auto") {
    const auto nodes = describe_v4l2_nodes(*sys_, paths_.empty() ? v4l2_device_paths() : paths_);
    const V4l2NodeInfo* depth = nullptr;
    const V4l2NodeInfo* colour = nullptr;
    for (const auto& n : nodes) {
      if (!p_->card.empty() && n.card.find(p_->card) == std::string::npos) continue;
      if (!depth && n.has_depth()) depth = &n;
    }
    for (const auto& n : nodes) {
      if (!p_->card.empty() && n.card.find(p_->card) == std::string::npos) continue;
      if (depth && n.card != depth->card) continue;
      if (!colour && n.has_colour() && (!depth || n.path != depth->path)) colour = &n;
    }
    if (!depth && !colour)
      throw DeviceError(
          who + ": no V4L2 node with a Z16, Y16, YUYV or MJPG capture format" +
          (p_->card.empty() ? std::string() : " on a card matching '" + p_->card + "'") +
          " (found " + std::to_string(nodes.size()) + " capture nodes)");
    main_path = depth ? depth->path : colour->path;
    if (depth && colour && colour_path.empty()) colour_path = colour->path;
  }
  main_ = std::make_unique<V4l2Stream>(sys_, main_path, who);
  try {
    main_->start(p_->main);
    main_is_depth_ = is_depth(main_->fourcc());
    auto check_k = [&](const Intrinsics& k, const V4l2Stream& s, const char* prefix) {
      if (k.width != s.width() || k.height != s.height())
        throw DeviceError(who + ": " + prefix + "intrinsics are for " + std::to_string(k.width) +
                          "x" + std::to_string(k.height) + " but the node delivers " +
                          std::to_string(s.width()) + "x" + std::to_string(s.height()));
    };
    if (p_->has_k) {
      // The intrinsics belong to the requested size; unset sizes take the node's.
      p_->k.width = p_->main.width > 0 ? p_->main.width : main_->width();
      p_->k.height = p_->main.height > 0 ? p_->main.height : main_->height();
      check_k(p_->k, *main_, "");
    }
    if (main_is_depth_ && !p_->has_k)
      throw DeviceError(who +
                        ": depth node needs intrinsics fx, fy, cx, cy in the profile or URI "
                        "(plain V4L2 does not report them)");
    if (!colour_path.empty()) {
      if (!main_is_depth_)
        throw DeviceError(who + ": option color pairs a colour node with a depth node, but " +
                          main_path + " delivers " + fourcc_text(main_->fourcc()));
      colour_ = std::make_unique<V4l2Stream>(sys_, colour_path, who);
      colour_->start(p_->colour);
      if (!is_colour(colour_->fourcc()))
        throw DeviceError(who + ": colour node " + colour_path + " delivers " +
                          fourcc_text(colour_->fourcc()) + ", not a colour format");
      if (p_->has_colour_k) {
        p_->colour_k.width = p_->colour.width > 0 ? p_->colour.width : colour_->width();
        p_->colour_k.height = p_->colour.height > 0 ? p_->colour.height : colour_->height();
        check_k(p_->colour_k, *colour_, "color_");
      }
      if (p_->extrinsics && !p_->has_colour_k)
        throw DeviceError(
            who + ": extrinsics need the colour intrinsics color_fx, color_fy, color_cx, color_cy");
    } else if (p_->extrinsics) {
      throw DeviceError(who + ": option extrinsics needs a colour node (option color)");
    }
  } catch (...) {
    close();
    throw;
  }
}

void V4l2Camera::close() {
  colour_.reset();
  main_.reset();
}

ScannerCapabilities V4l2Camera::capabilities() const {
  ScannerCapabilities c;
  const bool depth =
      main_ ? main_is_depth_
            : (p_->main.format == "Z16" || p_->main.format == "Y16" || !p_->colour_path.empty());
  c.depth = depth;
  c.colour = main_ ? (!main_is_depth_ || colour_ != nullptr) : (!depth || !p_->colour_path.empty());
  if (depth && p_->has_k) c.intrinsics = p_->k;
  return c;
}

namespace {
void to_rgb(const V4l2Stream::Raw& raw, const std::string& who, std::vector<std::uint8_t>& rgb) {
  if (raw.fourcc == V4L2_PIX_FMT_YUYV)
    yuyv_to_rgb(raw.data, raw.width, raw.height, raw.stride, rgb);
  else
    mjpeg_to_rgb(raw.data, raw.bytes, raw.width, raw.height, who, rgb);
}
}  // namespace

Frame V4l2Camera::grab() {
  if (!main_) throw DeviceError(uri_.text + ": grab before open()");
  Frame f;
  const V4l2Stream::Raw raw = main_->next_frame();
  if (main_is_depth_) {
    depth16_to_metres(raw.data, raw.width, raw.height, raw.stride, p_->depth_scale, f.depth);
    f.intrinsics = p_->k;
  } else {
    to_rgb(raw, uri_.text, f.colour);
    f.colour_intrinsics = p_->has_k ? p_->k : Intrinsics{raw.width, raw.height, 0, 0, 0, 0};
  }
  if (colour_) {
    const V4l2Stream::Raw c = colour_->next_frame();
    std::vector<std::uint8_t> rgb;
    to_rgb(c, uri_.text, rgb);
    if (p_->extrinsics) {
      f.colour = register_colour_to_depth(f.depth, p_->k, rgb, p_->colour_k, *p_->extrinsics);
      f.colour_intrinsics = p_->k;
    } else {
      f.colour = std::move(rgb);
      f.colour_intrinsics =
          p_->has_colour_k ? p_->colour_k : Intrinsics{c.width, c.height, 0, 0, 0, 0};
    }
  }
  f.timestamp =
      std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  return f;
}

// ---- registry ------------------------------------------------------------------

void register_v4l2_camera(DeviceRegistry& registry, std::shared_ptr<SysCalls> sys) {
  registry.add_scanner(
      "v4l2:",
      [sys](const DeviceUri& uri, DeviceContext&) -> std::unique_ptr<Scanner> {
        return std::make_unique<V4l2Camera>(sys, uri);
      },
      [sys] {
        std::vector<DeviceInfo> out;
        for (const auto& n : describe_v4l2_nodes(*sys, v4l2_device_paths())) {
          const bool usable = n.has_depth() || n.has_colour();
          out.push_back({"v4l2:" + n.path, DeviceKind::kScanner,
                         n.card + " (" + n.driver + "): " + format_list(n.formats) +
                             (n.has_depth() ? "; depth: give fx, fy, cx, cy" : ""),
                         usable});
        }
        return out;
      });
}

}  // namespace station
