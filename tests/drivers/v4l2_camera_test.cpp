#include "drivers/v4l2_camera.h"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "core/error.h"
#include "v4l2_fake_kernel.h"

namespace station {
namespace {

using testing::FakeV4l2Kernel;

std::string message(const std::function<void()>& f) {
  try {
    f();
  } catch (const DeviceError& e) {
    return e.what();
  }
  return "(no DeviceError)";
}

// Depth frames: pixel (x, y) of frame s holds 1000 + 100 s + 10 y + x units.
std::vector<std::uint8_t> depth_frame(std::uint32_t, int w, int bpl, int h, int s) {
  std::vector<std::uint8_t> out(static_cast<std::size_t>(bpl) * h, 0xee);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const unsigned v = (x == 0 && y == 0) ? 0 : 1000 + 100 * s + 10 * y + x;
      out[y * bpl + 2 * x] = v & 0xff;
      out[y * bpl + 2 * x + 1] = v >> 8;
    }
  return out;
}

// YUYV frames: grey level Y = 16 + 20 s everywhere, no chroma.
std::vector<std::uint8_t> grey_frame(std::uint32_t, int w, int bpl, int h, int s) {
  std::vector<std::uint8_t> out(static_cast<std::size_t>(bpl) * h, 0);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      out[y * bpl + 2 * x] = static_cast<std::uint8_t>(16 + 20 * s);
      out[y * bpl + 2 * x + 1] = 128;
    }
  return out;
}

struct Rig {
  std::shared_ptr<FakeV4l2Kernel> k = std::make_shared<FakeV4l2Kernel>();
  Rig() {
    auto& d = k->nodes["/dev/video2"];
    d.card = "Depth Cam";
    d.formats = {V4L2_PIX_FMT_Z16};
    d.width = 4;
    d.height = 3;
    d.pad = 6;
    d.make_frame = depth_frame;
    auto& c = k->nodes["/dev/video4"];
    c.card = "Depth Cam";
    c.formats = {V4L2_PIX_FMT_MJPEG, V4L2_PIX_FMT_YUYV};
    c.width = 4;
    c.height = 3;
    c.make_frame = grey_frame;
    auto& m = k->nodes["/dev/video3"];
    m.card = "Depth Cam";
    m.caps = V4L2_CAP_META_CAPTURE | V4L2_CAP_STREAMING;
    m.formats = {};
  }
  std::unique_ptr<V4l2Camera> camera(const std::string& uri) {
    return std::make_unique<V4l2Camera>(
        k, parse_device_uri(uri),
        std::vector<std::string>{"/dev/video2", "/dev/video3", "/dev/video4"});
  }
};

const char* kK = "fx=100&fy=101&cx=1.5&cy=1";

TEST(V4l2Conversions, YuyvBt601) {
  // Two pixel pairs: white/black luma with neutral chroma, then BT.601 red.
  const std::uint8_t yuyv[] = {235, 128, 16, 128, 81, 90, 81, 240, /*padding*/ 0, 0};
  std::vector<std::uint8_t> rgb;
  yuyv_to_rgb(yuyv, 4, 1, 10, rgb);
  ASSERT_EQ(rgb.size(), 12u);
  EXPECT_EQ(rgb[0], 255);
  EXPECT_EQ(rgb[1], 255);
  EXPECT_EQ(rgb[2], 255);
  EXPECT_EQ(rgb[3], 0);
  EXPECT_EQ(rgb[4], 0);
  EXPECT_EQ(rgb[5], 0);
  for (int p = 2; p < 4; ++p) {
    EXPECT_NEAR(rgb[3 * p + 0], 255, 2);
    EXPECT_NEAR(rgb[3 * p + 1], 0, 2);
    EXPECT_NEAR(rgb[3 * p + 2], 0, 2);
  }
  // Mid grey: 1.164 * (126 - 16) = 128.
  const std::uint8_t grey[] = {126, 128, 126, 128};
  yuyv_to_rgb(grey, 2, 1, 4, rgb);
  for (auto v : rgb) EXPECT_EQ(v, 128);
}

TEST(V4l2Conversions, MjpegDecodesToRgbOrder) {
  cv::Mat bgr(8, 16, CV_8UC3, cv::Scalar(0, 0, 255));      // red (BGR order)
  bgr(cv::Rect(8, 0, 8, 8)).setTo(cv::Scalar(255, 0, 0));  // right half blue
  std::vector<std::uint8_t> jpeg;
  cv::imencode(".jpg", bgr, jpeg, {cv::IMWRITE_JPEG_QUALITY, 95});
  std::vector<std::uint8_t> rgb;
  mjpeg_to_rgb(jpeg.data(), jpeg.size(), 16, 8, "v4l2:/dev/video0", rgb);
  ASSERT_EQ(rgb.size(), 16u * 8 * 3);
  const std::size_t left = (4 * 16 + 2) * 3, right = (4 * 16 + 13) * 3;
  EXPECT_GT(rgb[left + 0], 200);
  EXPECT_LT(rgb[left + 2], 60);
  EXPECT_LT(rgb[right + 0], 60);
  EXPECT_GT(rgb[right + 2], 200);
  EXPECT_NE(message([&] {
              mjpeg_to_rgb(jpeg.data(), jpeg.size(), 32, 8, "cam", rgb);
            }).find("cam: MJPEG frame is 16x8, expected 32x8"),
            std::string::npos);
  const std::uint8_t junk[] = {1, 2, 3, 4, 5};
  EXPECT_NE(message([&] { mjpeg_to_rgb(junk, 5, 16, 8, "cam", rgb); }).find("does not decode"),
            std::string::npos);
}

TEST(V4l2Conversions, Depth16WithScale) {
  const std::uint8_t z[] = {0, 0, 0xe8, 0x03, 0xff, 0xff, 9, 9};
  std::vector<float> m;
  depth16_to_metres(z, 3, 1, 8, 0.001, m);
  EXPECT_EQ(m[0], 0.0f);
  EXPECT_FLOAT_EQ(m[1], 1.0f);
  EXPECT_FLOAT_EQ(m[2], 65.535f);
  depth16_to_metres(z, 3, 1, 8, 0.000125, m);  // a 1/8 mm sensor
  EXPECT_FLOAT_EQ(m[1], 0.125f);
}

TEST(V4l2Conversions, RegistrationShiftsByTheBaseline) {
  // Flat wall 1 m away; colour camera 0.1 m to the right: x_c = x_d - 0.1, so
  // depth pixel u sees colour pixel u - fx * 0.1 = u - 10.
  const Intrinsics k{40, 2, 100, 100, 20, 1};
  std::vector<float> depth(80, 1.0f);
  depth[5] = 0;  // no return stays black
  std::vector<std::uint8_t> rgb(80 * 3);
  for (int v = 0; v < 2; ++v)
    for (int u = 0; u < 40; ++u) rgb[(v * 40 + u) * 3] = static_cast<std::uint8_t>(u * 5);
  const std::array<double, 12> m{1, 0, 0, -0.1, 0, 1, 0, 0, 0, 0, 1, 0};
  const auto out = register_colour_to_depth(depth, k, rgb, k, m);
  EXPECT_EQ(out[(40 + 25) * 3], (25 - 10) * 5);
  EXPECT_EQ(out[(40 + 10) * 3], 0);  // u - 10 = 0: colour column 0 has value 0
  EXPECT_EQ(out[5 * 3], 0);          // no depth
  EXPECT_EQ(out[(40 + 3) * 3], 0);   // falls left of the colour image
  EXPECT_EQ(out[(40 + 39) * 3], 29 * 5);
}

TEST(V4l2Camera, StreamsDepthInMetresThroughRequeuedBuffers) {
  Rig r;
  auto cam = r.camera(std::string("v4l2:/dev/video2?depth_scale=0.001&") + kK);
  cam->open();
  const auto caps = cam->capabilities();
  EXPECT_TRUE(caps.depth);
  EXPECT_FALSE(caps.colour);
  for (int s = 0; s < 7; ++s) {  // more grabs than the 3 buffers: each goes back to the queue
    const Frame f = cam->grab();
    ASSERT_EQ(f.depth.size(), 12u);
    EXPECT_EQ(f.intrinsics.width, 4);
    EXPECT_DOUBLE_EQ(f.intrinsics.fy, 101);
    EXPECT_EQ(f.depth[0], 0.0f);
    EXPECT_NEAR(f.depth[2 * 4 + 3], (1000 + 100 * s + 20 + 3) * 0.001, 1e-6);
    EXPECT_FALSE(f.has_colour());
    EXPECT_GT(f.timestamp, 1.6e9);
  }
  const auto& node = r.k->nodes["/dev/video2"];
  EXPECT_EQ(node.qbufs, 3 + 6);
  cam->close();
  EXPECT_EQ(node.streamoffs, 1);
  EXPECT_TRUE(r.k->fds.empty());
  EXPECT_EQ(r.k->mapped, 0);
}

TEST(V4l2Camera, ColourNodePrefersYuyvAndSetsFixedExposureAndWhiteBalance) {
  Rig r;
  auto cam = r.camera("v4l2:/dev/video4?exposure=150&white_balance=4600");
  cam->open();
  const Frame f0 = cam->grab();
  const Frame f1 = cam->grab();
  EXPECT_FALSE(f0.has_depth());
  ASSERT_EQ(f0.colour.size(), 4u * 3 * 3);
  EXPECT_EQ(f0.colour_intrinsics.width, 4);
  EXPECT_EQ(f0.colour[0], 0);   // Y = 16: black
  EXPECT_EQ(f1.colour[7], 23);  // Y = 36: 1.164 * 20 = 23
  const auto& n = r.k->nodes["/dev/video4"];
  EXPECT_EQ(n.fourcc, V4L2_PIX_FMT_YUYV);
  EXPECT_EQ(n.controls.at(V4L2_CID_EXPOSURE_AUTO), V4L2_EXPOSURE_MANUAL);
  EXPECT_EQ(n.controls.at(V4L2_CID_EXPOSURE_ABSOLUTE), 150);
  EXPECT_EQ(n.controls.at(V4L2_CID_AUTO_WHITE_BALANCE), 0);
  EXPECT_EQ(n.controls.at(V4L2_CID_WHITE_BALANCE_TEMPERATURE), 4600);
}

TEST(V4l2Camera, ConfigureFromTheProfileReopensWithTheNewSettings) {
  Rig r;
  auto cam = r.camera("v4l2:/dev/video4");
  cam->open();
  cam->configure({{"exposure", "80"}});
  EXPECT_EQ(r.k->nodes["/dev/video4"].controls.at(V4L2_CID_EXPOSURE_ABSOLUTE), 80);
  EXPECT_TRUE(cam->grab().has_colour());
  EXPECT_NE(message([&] {
              cam->configure({{"exposur", "80"}});
            }).find("unknown option 'exposur'"),
            std::string::npos);
  EXPECT_TRUE(cam->grab().has_colour());  // a rejected option changes nothing
  cam->configure({{"white_balance", "5000"}});
  EXPECT_EQ(r.k->nodes["/dev/video4"].controls.at(V4L2_CID_WHITE_BALANCE_TEMPERATURE), 5000);
}

TEST(V4l2Camera, MjpegNode) {
  Rig r;
  auto& n = r.k->nodes["/dev/video4"];
  n.make_frame = [](std::uint32_t fourcc, int w, int, int h, int) {
    EXPECT_EQ(fourcc, V4L2_PIX_FMT_MJPEG);
    cv::Mat bgr(h, w, CV_8UC3, cv::Scalar(40, 120, 200));
    std::vector<std::uint8_t> jpeg;
    cv::imencode(".jpg", bgr, jpeg, {cv::IMWRITE_JPEG_QUALITY, 100});
    return jpeg;
  };
  auto cam = r.camera("v4l2:/dev/video4?format=MJPG");
  cam->open();
  const Frame f = cam->grab();
  ASSERT_EQ(f.colour.size(), 36u);
  EXPECT_NEAR(f.colour[0], 200, 4);
  EXPECT_NEAR(f.colour[1], 120, 4);
  EXPECT_NEAR(f.colour[2], 40, 4);
}

TEST(V4l2Camera, DepthAndColourPairRegisteredWithExtrinsics) {
  Rig r;
  auto cam = r.camera(std::string("v4l2:/dev/video2?color=/dev/video4&color_format=YUYV&") + kK +
                      "&color_fx=100&color_fy=101&color_cx=1.5&color_cy=1"
                      "&extrinsics=1,0,0,0,0,1,0,0,0,0,1,0");
  cam->open();
  EXPECT_TRUE(cam->capabilities().colour);
  cam->grab();
  const Frame f = cam->grab();
  ASSERT_EQ(f.depth.size(), 12u);
  ASSERT_EQ(f.colour.size(), 36u);
  EXPECT_EQ(f.colour_intrinsics.fx, f.intrinsics.fx);  // registered to depth
  EXPECT_EQ(f.colour[0], 0);                           // pixel without depth: black
  EXPECT_EQ(f.colour[3 * 5], 23);                      // identity: same pixel, Y = 36
}

TEST(V4l2Camera, AutoPicksNodesByFormatNotNumber) {
  Rig r;
  auto cam = r.camera(std::string("v4l2:auto?card=Depth&") + kK);
  cam->open();
  const Frame f = cam->grab();
  EXPECT_TRUE(f.has_depth());
  EXPECT_TRUE(f.has_colour());  // /dev/video4 paired, the metadata node skipped
  EXPECT_EQ(f.colour_intrinsics.width, 4);
  EXPECT_NE(
      message([&] { r.camera("v4l2:auto?card=Kinect")->open(); }).find("card matching 'Kinect'"),
      std::string::npos);
}

TEST(V4l2Camera, BusyDeviceIsNamed) {
  Rig r;
  r.k->nodes["/dev/video2"].open_errno = EBUSY;
  EXPECT_EQ(
      message([&] { r.camera(std::string("v4l2:/dev/video2?") + kK)->open(); }),
      std::string("v4l2:/dev/video2?") + kK + ": /dev/video2: busy (another program has it open)");
}

TEST(V4l2Camera, SecondStationOnAStreamingNodeIsBusy) {
  // V4L2 lets a second process open the node; the format change is what fails.
  Rig r;
  auto first = r.camera(std::string("v4l2:/dev/video2?") + kK);
  first->open();
  auto second = r.camera(std::string("v4l2:/dev/video2?") + kK);
  const std::string m = message([&] { second->open(); });
  EXPECT_NE(m.find("/dev/video2: busy (another program has it open)"), std::string::npos) << m;
  EXPECT_EQ(r.k->fds.size(), 1u);  // the second one closed its descriptor
  first->grab();
}

TEST(V4l2Camera, EagainIsRetriedUntilAFrameArrives) {
  Rig r;
  r.k->nodes["/dev/video2"].eagain_before_each_frame = 5;
  auto cam = r.camera(std::string("v4l2:/dev/video2?") + kK);
  cam->open();
  EXPECT_NEAR(cam->grab().depth[1], 1.001, 1e-6);
  EXPECT_NEAR(cam->grab().depth[1], 1.101, 1e-6);
}

TEST(V4l2Camera, SilentDeviceTimesOut) {
  Rig r;
  r.k->nodes["/dev/video2"].frames_before_silence = 1;
  auto cam = r.camera(std::string("v4l2:/dev/video2?timeout_ms=50&") + kK);
  cam->open();
  cam->grab();
  EXPECT_NE(message([&] { cam->grab(); }).find("/dev/video2: no frame within 50 ms"),
            std::string::npos);
}

TEST(V4l2Camera, UnplugMidStreamIsADeviceError) {
  Rig r;
  r.k->nodes["/dev/video2"].frames_before_unplug = 2;
  auto cam = r.camera(std::string("v4l2:/dev/video2?") + kK);
  cam->open();
  cam->grab();
  cam->grab();
  const std::string m = message([&] { cam->grab(); });
  EXPECT_NE(m.find("/dev/video2"), std::string::npos) << m;
  EXPECT_NE(m.find("unplugged"), std::string::npos) << m;
  cam->close();
  EXPECT_TRUE(r.k->fds.empty());
}

TEST(V4l2Camera, LensDistortionFromTheProfileReachesTheFrame) {
  Rig r;
  auto cam = r.camera(std::string("v4l2:/dev/video2?distortion=-0.2,0.05,0.001,-0.002,0&") + kK);
  cam->open();
  const Frame f = cam->grab();
  EXPECT_TRUE(f.intrinsics.distorted());
  EXPECT_DOUBLE_EQ(f.intrinsics.distortion[0], -0.2);
  EXPECT_DOUBLE_EQ(f.intrinsics.distortion[3], -0.002);
  EXPECT_NE(message([&] { r.camera(std::string("v4l2:/dev/video2?distortion=1,2&") + kK); })
                .find("distortion: expected 5 comma-separated numbers"),
            std::string::npos);
  EXPECT_NE(message([&] { r.camera(std::string("v4l2:/dev/video2?distortion=1,2,x,4,5&") + kK); })
                .find("distortion: expected 5"),
            std::string::npos);
}

TEST(V4l2Camera, ClearErrorsForBadSetups) {
  Rig r;
  EXPECT_NE(message([&] {
              r.camera("v4l2:/dev/video2")->open();
            }).find("needs intrinsics fx, fy, cx, cy"),
            std::string::npos);
  EXPECT_NE(message([&] {
              r.camera("v4l2:/dev/video4?format=Z16")->open();
            }).find("format Z16 not offered (offers MJPG, YUYV)"),
            std::string::npos);
  EXPECT_NE(message([&] { r.camera("v4l2:/dev/video3")->open(); }).find("not a video capture node"),
            std::string::npos);
  EXPECT_NE(message([&] { r.camera("v4l2:/dev/video9")->open(); }).find("no such device"),
            std::string::npos);
  EXPECT_NE(message([&] { r.camera("v4l2:/dev/video2?fx=1")->open(); }).find("give all of fx"),
            std::string::npos);
  EXPECT_NE(message([&] {
              r.camera(std::string("v4l2:/dev/video2?width=640&") + kK)->open();
            }).find("intrinsics are for 640x3 but the node delivers 4x3"),
            std::string::npos);
  EXPECT_NE(
      message([&] { r.camera("v4l2:/dev/video2?extrinsics=1,2,3"); }).find("12 comma-separated"),
      std::string::npos);
  EXPECT_NE(
      message([&] { r.camera("v4l2:/dev/video2?exposre=3"); }).find("unknown option 'exposre'"),
      std::string::npos);
  EXPECT_NE(message([&] { r.camera("v4l2:/dev/video2")->grab(); }).find("grab before open"),
            std::string::npos);
  EXPECT_TRUE(r.k->fds.empty());
  EXPECT_EQ(r.k->mapped, 0);
}

TEST(V4l2Camera, RegistryMakesAndListsCameras) {
  Rig r;
  DeviceRegistry reg;
  register_v4l2_camera(reg, r.k);
  auto cam = reg.make_scanner(std::string("v4l2:/dev/video4"));
  cam->open();
  EXPECT_TRUE(cam->grab().has_colour());
}

}  // namespace
}  // namespace station
