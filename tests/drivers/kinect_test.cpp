// KinectScanner against a scripted in-process FreenectApi (no libfreenect needed).
#include <gtest/gtest.h>

#include <cmath>
#include <deque>
#include <memory>

#include "core/error.h"
#include "drivers/kinect_scanner.h"

namespace station {
namespace {

constexpr int kPixels = kKinectWidth * kKinectHeight;

/// What the fake delivers on one process_events call.
struct Event {
  enum Kind { kDepth, kVideo, kNothing, kError } kind = kNothing;
  std::uint16_t depth_value = 0;  ///< every pixel (pixel 0 gets 0 = no data)
  std::uint8_t rgb_value = 0;
  int code = 0;
  std::string log;
};

struct FakeState {
  FreenectApi::Result init_result;
  int count = 1;
  std::vector<KinectDepthFormat> formats = {KinectDepthFormat::kRegistered,
                                            KinectDepthFormat::kMillimetres,
                                            KinectDepthFormat::kRaw11Bit};
  FreenectApi::Result open_result;
  std::deque<Event> events;
  // tilt
  std::vector<double> tilts_set;
  int moving_polls = 0;  ///< tilt_state reports moving this many times
  bool limit = false;
  double tilt_reported = 0;
  // bookkeeping
  int opens = 0, starts = 0, closes = 0, process_calls = 0;
  int opened_index = -1;
  KinectDepthFormat started_format = KinectDepthFormat::kRegistered;
  bool is_open = false;
};

class FakeFreenect final : public FreenectApi {
 public:
  explicit FakeFreenect(std::shared_ptr<FakeState> s) : s_(std::move(s)) {}
  Result init() override { return s_->init_result; }
  int device_count() override { return s_->count; }
  std::vector<KinectDepthFormat> depth_formats() override { return s_->formats; }
  Result open(int index) override {
    ++s_->opens;
    s_->opened_index = index;
    if (s_->open_result.ok()) s_->is_open = true;
    return s_->open_result;
  }
  Result start(KinectDepthFormat f, DepthSink d, VideoSink v) override {
    ++s_->starts;
    s_->started_format = f;
    depth_ = std::move(d);
    video_ = std::move(v);
    return {};
  }
  Result process_events(int) override {
    ++s_->process_calls;
    if (s_->events.empty()) return {};  // nothing arrived (a real time-out)
    Event e = s_->events.front();
    s_->events.pop_front();
    if (e.kind == Event::kError) return {e.code, e.log};
    if (e.kind == Event::kDepth) {
      std::vector<std::uint16_t> d(kPixels, e.depth_value);
      d[0] = e.depth_value == kKinectNoDisparity ? kKinectNoDisparity : 0;
      depth_(d.data(), 1);
    } else if (e.kind == Event::kVideo) {
      std::vector<std::uint8_t> rgb(kPixels * 3, e.rgb_value);
      rgb[0] = 1;
      rgb[1] = 2;
      rgb[2] = 3;
      video_(rgb.data(), 1);
    }
    return {0, e.log};
  }
  Result set_tilt(double deg) override {
    s_->tilts_set.push_back(deg);
    return {};
  }
  Result tilt_state(TiltState& t) override {
    t.moving = s_->moving_polls > 0;
    if (s_->moving_polls > 0) --s_->moving_polls;
    t.limit = s_->limit;
    t.degrees = s_->tilt_reported;
    return {};
  }
  void close() override {
    ++s_->closes;
    s_->is_open = false;
  }

 private:
  std::shared_ptr<FakeState> s_;
  DepthSink depth_;
  VideoSink video_;
};

Event depth_event(std::uint16_t v) {
  Event e;
  e.kind = Event::kDepth;
  e.depth_value = v;
  return e;
}
Event video_event(std::uint8_t v) {
  Event e;
  e.kind = Event::kVideo;
  e.rgb_value = v;
  return e;
}

std::unique_ptr<KinectScanner> make(const std::shared_ptr<FakeState>& s,
                                    const std::string& query = "", const std::string& path = "0") {
  DeviceUri uri = parse_device_uri("kinect:" + path + (query.empty() ? "" : "?" + query));
  return std::make_unique<KinectScanner>(uri.text, uri.path, uri.options,
                                         std::make_unique<FakeFreenect>(s));
}

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const DeviceError& e) {
    return e.what();
  }
  return "(no error)";
}

TEST(KinectOptions, DefaultsAreTheRegisteredColourCamera) {
  const KinectOptions o = kinect_options("", {}, "kinect:");
  EXPECT_EQ(o.index, 0);
  EXPECT_EQ(o.depth_format, KinectDepthFormat::kRegistered);
  EXPECT_FALSE(o.tilt_deg);
  EXPECT_EQ(o.discard, 2);
  EXPECT_EQ(o.timeout_ms, 2000);
  EXPECT_EQ(o.depth_intrinsics.width, 640);
  EXPECT_EQ(o.depth_intrinsics.height, 480);
  EXPECT_DOUBLE_EQ(o.depth_intrinsics.fx, 525);
  EXPECT_DOUBLE_EQ(o.depth_intrinsics.fy, 525);
  EXPECT_DOUBLE_EQ(o.depth_intrinsics.cx, 319.5);
  EXPECT_DOUBLE_EQ(o.depth_intrinsics.cy, 239.5);
  EXPECT_DOUBLE_EQ(o.colour_intrinsics.fx, 525);
  EXPECT_FALSE(o.depth_intrinsics.distorted());
}

TEST(KinectOptions, UnregisteredDepthUsesTheIrCameraAndOwnColourIntrinsics) {
  const KinectOptions o = kinect_options(
      "1", {{"depth_format", "mm"}, {"color_fx", "530"}, {"distortion", "0.1,-0.2,0,0,0.05"}},
      "kinect:1");
  EXPECT_EQ(o.index, 1);
  EXPECT_EQ(o.depth_format, KinectDepthFormat::kMillimetres);
  EXPECT_DOUBLE_EQ(o.depth_intrinsics.fx, 580);
  EXPECT_DOUBLE_EQ(o.colour_intrinsics.fx, 530);
  EXPECT_DOUBLE_EQ(o.colour_intrinsics.fy, 525);
  EXPECT_DOUBLE_EQ(o.depth_intrinsics.distortion[0], 0.1);
  EXPECT_DOUBLE_EQ(o.depth_intrinsics.distortion[4], 0.05);
}

TEST(KinectOptions, BadValuesNameTheDeviceAndOption) {
  auto err = [](const std::string& path, const DeviceOptions& o) {
    return error_of([&] { kinect_options(path, o, "kinect:" + path); });
  };
  EXPECT_NE(err("0", {{"depth_format", "16bit"}}).find("kinect:0: option depth_format=16bit"),
            std::string::npos);
  EXPECT_NE(err("0", {{"tilt_deg", "40"}}).find("kinect:0: option tilt_deg"), std::string::npos);
  EXPECT_NE(err("0", {{"exposure", "3"}}).find("exposure"), std::string::npos);
  EXPECT_NE(err("abc", {}).find("kinect:abc: device index 'abc'"), std::string::npos);
  EXPECT_NE(err("0", {{"color_fx", "500"}}).find("not used with depth_format=registered"),
            std::string::npos);
  EXPECT_NE(err("0", {{"distortion", "1,2,3"}}).find("5 comma-separated"), std::string::npos);
  EXPECT_NE(err("0", {{"fx", "-3"}}).find("fx"), std::string::npos);
}

TEST(KinectDisparity, NoDataAndTheFitsInverse) {
  EXPECT_EQ(kinect_disparity_to_metres(kKinectNoDisparity), 0.0f);
  EXPECT_EQ(kinect_disparity_to_metres(2046), 0.0f);  // beyond the fit's pole
  EXPECT_NEAR(kinect_disparity_to_metres(0), 1.0 / 3.3309495161, 1e-6);
  // The recording generator's inverse: raw = round((1/z - b)/a). One raw step
  // is |a| z^2 metres, so the round trip is within half of that.
  const double a = -0.0030711016, b = 3.3309495161;
  for (double z = 0.5; z <= 4.0; z += 0.137) {
    const auto raw = static_cast<std::uint16_t>(std::lround((1.0 / z - b) / a));
    EXPECT_NEAR(kinect_disparity_to_metres(raw), z, 0.5 * std::abs(a) * z * z * 1.05 + 1e-6)
        << "z " << z;
  }
  // Monotonic up to the 10 m cut-off, 0 (no return) after it.
  float prev = 0;
  int raw = 0;
  for (; raw < 2047; ++raw) {
    const float z = kinect_disparity_to_metres(static_cast<std::uint16_t>(raw));
    if (z == 0) break;
    ASSERT_GT(z, prev) << raw;
    ASSERT_LE(z, 10.0f) << raw;
    prev = z;
  }
  EXPECT_GT(prev, 9.5f);
  for (; raw < 2048; ++raw)
    ASSERT_EQ(kinect_disparity_to_metres(static_cast<std::uint16_t>(raw)), 0.0f) << raw;
}

TEST(KinectScanner, GrabsRegisteredMillimetresAndRgb) {
  auto s = std::make_shared<FakeState>();
  s->events = {depth_event(1234), video_event(200)};
  auto k = make(s, "discard=0");
  k->open();
  EXPECT_EQ(s->opened_index, 0);
  EXPECT_EQ(s->started_format, KinectDepthFormat::kRegistered);
  const Frame f = k->grab();
  ASSERT_EQ(f.depth.size(), static_cast<std::size_t>(kPixels));
  EXPECT_FLOAT_EQ(f.depth[1], 1.234f);
  EXPECT_FLOAT_EQ(f.depth[kPixels - 1], 1.234f);
  EXPECT_EQ(f.depth[0], 0.0f);  // 0 mm = no data
  ASSERT_EQ(f.colour.size(), static_cast<std::size_t>(kPixels) * 3);
  EXPECT_EQ(f.colour[0], 1);
  EXPECT_EQ(f.colour[2], 3);
  EXPECT_EQ(f.colour[3], 200);
  EXPECT_EQ(f.intrinsics.width, 640);
  EXPECT_DOUBLE_EQ(f.intrinsics.fx, 525);
  EXPECT_DOUBLE_EQ(f.colour_intrinsics.fx, f.intrinsics.fx);
  EXPECT_DOUBLE_EQ(f.colour_intrinsics.cx, f.intrinsics.cx);
  EXPECT_GT(f.timestamp, 1.5e9);
  const ScannerCapabilities c = k->capabilities();
  EXPECT_TRUE(c.depth);
  EXPECT_TRUE(c.colour);
  EXPECT_FALSE(c.points);
  k->close();
  EXPECT_FALSE(s->is_open);
}

TEST(KinectScanner, DiscardsTheFirstFramesOfEachStreamEveryGrab) {
  auto s = std::make_shared<FakeState>();
  // Video arrives before depth; the first two of each are dropped.
  s->events = {video_event(1), depth_event(100), video_event(2), depth_event(200), video_event(3),
               depth_event(300),
               // second grab
               depth_event(500), depth_event(600), video_event(5), video_event(6), depth_event(700),
               video_event(7)};
  auto k = make(s);  // discard=2 by default
  k->open();
  Frame f = k->grab();
  EXPECT_FLOAT_EQ(f.depth[5], 0.3f);
  EXPECT_EQ(f.colour[5], 3);
  f = k->grab();
  EXPECT_FLOAT_EQ(f.depth[5], 0.7f);
  EXPECT_EQ(f.colour[5], 7);
}

TEST(KinectScanner, Raw11BitBecomesMetres) {
  auto s = std::make_shared<FakeState>();
  s->events = {depth_event(800), video_event(9)};
  auto k = make(s, "depth_format=11bit&discard=0&fx=600");
  k->open();
  EXPECT_EQ(s->started_format, KinectDepthFormat::kRaw11Bit);
  const Frame f = k->grab();
  EXPECT_FLOAT_EQ(f.depth[3], kinect_disparity_to_metres(800));
  EXPECT_NEAR(f.depth[3], 1.0 / (3.3309495161 - 0.0030711016 * 800), 1e-6);
  EXPECT_DOUBLE_EQ(f.intrinsics.fx, 600);
  EXPECT_DOUBLE_EQ(f.colour_intrinsics.fx, 525);  // colour keeps its own camera
}

TEST(KinectScanner, OpenErrorsNameTheDevice) {
  {
    auto s = std::make_shared<FakeState>();
    s->count = 0;
    auto k = make(s);
    EXPECT_EQ(error_of([&] { k->open(); }), "kinect:0: no Kinect found");
    EXPECT_GE(s->closes, 1);
  }
  {
    auto s = std::make_shared<FakeState>();
    s->count = 1;
    auto k = make(s, "", "2");
    EXPECT_EQ(error_of([&] { k->open(); }), "kinect:2: no Kinect with index 2 (1 found)");
  }
  {
    auto s = std::make_shared<FakeState>();
    s->open_result = {-1, "Failed to claim camera interface: LIBUSB_ERROR_BUSY\n"};
    auto k = make(s);
    EXPECT_EQ(error_of([&] { k->open(); }), "kinect:0: busy (another program has it open)");
  }
  {
    auto s = std::make_shared<FakeState>();
    s->open_result = {-1, "Could not open camera: -3\n"};
    auto k = make(s);
    EXPECT_NE(error_of([&] { k->open(); }).find("kinect:0: no permission"), std::string::npos);
  }
  {
    auto s = std::make_shared<FakeState>();
    s->open_result = {-1, "something odd\n"};
    auto k = make(s);
    EXPECT_EQ(error_of([&] { k->open(); }),
              "kinect:0: could not open the device (libfreenect: something odd)");
  }
  {
    auto s = std::make_shared<FakeState>();
    s->formats = {KinectDepthFormat::kRaw11Bit};
    auto k = make(s);
    EXPECT_EQ(error_of([&] { k->open(); }),
              "kinect:0: depth format 'registered' not offered by this libfreenect (offers: "
              "11bit)");
  }
  {
    auto s = std::make_shared<FakeState>();
    s->init_result = {-1, ""};
    auto k = make(s);
    EXPECT_NE(error_of([&] { k->open(); }).find("kinect:0: libfreenect could not start"),
              std::string::npos);
  }
  {
    auto k = make(std::make_shared<FakeState>());
    EXPECT_EQ(error_of([&] { k->grab(); }), "kinect:0: not open");
  }
}

TEST(KinectScanner, SilenceTimesOutAndUnplugEndsTheStream) {
  auto s = std::make_shared<FakeState>();
  s->events = {depth_event(500)};  // depth but never colour
  auto k = make(s, "discard=0&timeout_ms=150");
  k->open();
  EXPECT_EQ(error_of([&] { k->grab(); }),
            "kinect:0: no colour frame within 150 ms (the device stopped sending)");

  auto s2 = std::make_shared<FakeState>();
  Event gone;
  gone.kind = Event::kError;
  gone.code = -4;
  gone.log = "USB device disappeared, cancelling stream 80 :(\n";
  s2->events = {depth_event(500), video_event(1), gone};
  auto k2 = make(s2, "discard=0");
  k2->open();
  EXPECT_NO_THROW(k2->grab());
  const std::string e = error_of([&] { k2->grab(); });
  EXPECT_NE(e.find("kinect:0: device gone while streaming (unplugged?)"), std::string::npos) << e;
  EXPECT_FALSE(s2->is_open);
  EXPECT_EQ(error_of([&] { k2->grab(); }), "kinect:0: not open");
}

TEST(KinectScanner, TiltIsSetAtOpenAndWaitedFor) {
  auto s = std::make_shared<FakeState>();
  s->moving_polls = 3;
  s->tilt_reported = 9.5;
  auto k = make(s, "tilt_deg=10");
  k->open();
  ASSERT_EQ(s->tilts_set.size(), 1u);
  EXPECT_DOUBLE_EQ(s->tilts_set[0], 10);
  EXPECT_EQ(s->moving_polls, 0);  // polled until the motor stopped
  EXPECT_EQ(s->starts, 1);
  ASSERT_TRUE(k->tilt_degrees());
  EXPECT_DOUBLE_EQ(*k->tilt_degrees(), 9.5);

  auto s2 = std::make_shared<FakeState>();
  s2->limit = true;
  s2->tilt_reported = 15;
  auto k2 = make(s2, "tilt_deg=-20");
  EXPECT_EQ(error_of([&] { k2->open(); }),
            "kinect:0: tilt motor stopped at its limit (asked -20 deg, reports 15)");

  auto s3 = std::make_shared<FakeState>();
  s3->moving_polls = 1000000;
  auto k3 = make(s3, "tilt_deg=5&tilt_timeout_ms=120");
  EXPECT_EQ(error_of([&] { k3->open(); }), "kinect:0: tilt motor still moving after 120 ms");
  EXPECT_FALSE(s3->is_open);
}

TEST(KinectScanner, ConfigureValidatesBeforeReopening) {
  auto s = std::make_shared<FakeState>();
  auto k = make(s, "discard=0");
  k->open();
  EXPECT_NE(error_of([&] {
              k->configure({{"depth_format", "bogus"}});
            }).find("depth_format"),
            std::string::npos);
  EXPECT_EQ(s->opens, 1);  // nothing changed
  EXPECT_EQ(k->options().depth_format, KinectDepthFormat::kRegistered);
  k->configure({{"depth_format", "mm"}, {"tilt_deg", "-5"}});
  EXPECT_EQ(s->opens, 2);
  EXPECT_EQ(s->started_format, KinectDepthFormat::kMillimetres);
  ASSERT_EQ(s->tilts_set.size(), 1u);
  EXPECT_DOUBLE_EQ(s->tilts_set[0], -5);
  EXPECT_EQ(k->options().discard, 0);  // earlier options kept
  EXPECT_DOUBLE_EQ(k->capabilities().intrinsics.fx, 580);
}

TEST(KinectRegistry, ListsEveryKinectAndMakesScanners) {
  auto s = std::make_shared<FakeState>();
  s->count = 2;
  DeviceRegistry reg;
  register_kinect(reg, [s] { return std::make_unique<FakeFreenect>(s); });
  int kinects = 0;
  for (const auto& d : reg.list())
    if (d.uri.rfind("kinect:", 0) == 0) {
      EXPECT_EQ(d.kind, DeviceKind::kScanner);
      EXPECT_EQ(d.uri, "kinect:" + std::to_string(kinects));
      ++kinects;
    }
  EXPECT_EQ(kinects, 2);
  auto scanner = reg.make_scanner("kinect:1?tilt_deg=3&discard=0");
  s->events = {depth_event(700), video_event(5)};
  scanner->open();
  EXPECT_EQ(s->opened_index, 1);
  EXPECT_EQ(scanner->uri(), "kinect:1?tilt_deg=3&discard=0");
  EXPECT_FLOAT_EQ(scanner->grab().depth[7], 0.7f);
  EXPECT_THROW(reg.make_scanner("kinect:0?bogus=1"), DeviceError);

  DeviceRegistry none;
  register_kinect(none, [] { return std::unique_ptr<FreenectApi>(); });
  EXPECT_TRUE(none.list().empty());
  EXPECT_EQ(error_of([&] { none.make_scanner("kinect:0"); }),
            "kinect:0: this station was built without libfreenect");
}

TEST(KinectRegistry, BuildReportsLibfreenect) {
#ifdef STATION_HAVE_FREENECT
  EXPECT_TRUE(have_libfreenect());
  EXPECT_NE(make_libfreenect_api(), nullptr);
#else
  EXPECT_FALSE(have_libfreenect());
  EXPECT_EQ(make_libfreenect_api(), nullptr);
#endif
}

}  // namespace
}  // namespace station
