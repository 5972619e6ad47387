// The Kinect driver through the real libfreenect API, replayed by Debian's
// fakenect (libfreenect's replay library) from tests/data/fakenect/: three real
// Kinect frames from PCL's grabber sequence (see the README there).
//
// Built only as its own executable, kinect_fakenect_tests (tests/CMakeLists.txt,
// when libfreenect and fakenect are found), because it also records a session
// with run_capture. In drivers_tests (the glob picks up every *_test.cpp) this
// file compiles to nothing. ctest runs each test in its own process with
//   LD_LIBRARY_PATH=/usr/lib/<arch>/fakenect FAKENECT_PATH=<build>/tests/fakenect/kinect_sequence
// because fakenect keeps its place in the recording in process-wide state.
// By hand:
//   fakenect build/tests/fakenect/kinect_sequence build/tests/kinect_fakenect_tests
//       --gtest_filter=Fakenect.GrabsTheRecordedFrames    (one line)
#ifdef STATION_KINECT_FAKENECT_TESTS

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <opencv2/imgcodecs.hpp>

#include "capture/capture.h"
#include "capture/session.h"
#include "core/error.h"
#include "drivers/kinect_scanner.h"
#include "drivers/real_devices.h"
#include "test_util.h"

namespace station {
namespace {

// The recording's frames as PCL named them (the TIFFs in ../shared).
const char* kStamps[] = {"20121214T142255.814212", "20121214T142256.068683",
                         "20121214T142256.332395"};
// Intrinsics of the PCL frames (their .xml files): depth and colour registered.
const std::string kUri =
    "kinect:0?depth_format=11bit&discard=0&fx=525&fy=525&cx=320&cy=240&color_fx=525&color_fy=525&"
    "color_cx=320&color_cy=240";

std::string fakenect_path() {
  const char* p = std::getenv("FAKENECT_PATH");
  return p ? p : "";
}

#define REQUIRE_FAKENECT()                                                          \
  do {                                                                              \
    if (fakenect_path().empty())                                                    \
      GTEST_SKIP() << "FAKENECT_PATH not set: run under fakenect (ctest does, see " \
                      "tests/CMakeLists.txt)";                                      \
  } while (0)

struct Recorded {
  std::vector<std::uint16_t> raw;  ///< 11-bit disparity as recorded
  std::vector<std::uint8_t> rgb;
};

/// The recording's frames, read straight from its files (INDEX.txt order).
std::vector<Recorded> read_recording(const std::string& dir) {
  std::vector<Recorded> out;
  std::ifstream index(dir + "/INDEX.txt");
  std::string name;
  while (std::getline(index, name)) {
    if (name.empty() || (name[0] != 'd' && name[0] != 'r')) continue;
    std::ifstream f(dir + "/" + name, std::ios::binary);
    std::string header;
    std::getline(f, header);  // one header line, as fakenect expects
    if (name[0] == 'd') {
      out.emplace_back();
      out.back().raw.resize(kKinectWidth * kKinectHeight);
      f.read(reinterpret_cast<char*>(out.back().raw.data()), out.back().raw.size() * 2);
    } else {
      out.back().rgb.resize(kKinectWidth * kKinectHeight * 3);
      f.read(reinterpret_cast<char*>(out.back().rgb.data()), out.back().rgb.size());
    }
  }
  return out;
}

class StillTurntable : public Turntable {
 public:
  void open() override {}
  void close() override {}
  void home() override { angle_ = 0; }
  void rotate_to(double d) override { angle_ = d; }
  double angle() const override { return angle_; }
  int steps_per_revolution() const override { return 3600; }
  std::string uri() const override { return "fake:table"; }

 private:
  double angle_ = 0;
};

TEST(Fakenect, GrabsTheRecordedFrames) {
  REQUIRE_FAKENECT();
  const std::vector<Recorded> rec = read_recording(fakenect_path());
  ASSERT_EQ(rec.size(), 3u);
  DeviceRegistry reg;
  register_real_devices(reg);

  // Debian's fakenect replays raw 11-bit depth only: the default (registered)
  // is refused with the formats it offers, before anything is consumed.
  auto registered = reg.make_scanner("kinect:0");
  try {
    registered->open();
    FAIL() << "registered depth opened under fakenect";
  } catch (const DeviceError& e) {
    EXPECT_EQ(
        std::string(e.what()),
        "kinect:0: depth format 'registered' not offered by this libfreenect (offers: 11bit)");
  }

  auto scanner = reg.make_scanner(kUri);
  scanner->open();
  auto* kinect = dynamic_cast<KinectScanner*>(scanner.get());
  ASSERT_NE(kinect, nullptr);
  const std::filesystem::path shared =
      test::source_dir().parent_path() / "shared/data/rgbd_frames/pcl_kinect_sequence";
  for (int i = 0; i < 3; ++i) {
    const Frame f = scanner->grab();
    ASSERT_EQ(f.intrinsics.width, 640);
    ASSERT_EQ(f.intrinsics.height, 480);
    EXPECT_DOUBLE_EQ(f.intrinsics.cx, 320);
    ASSERT_EQ(f.depth.size(), 640u * 480u);
    ASSERT_EQ(f.colour.size(), 640u * 480u * 3u);
    std::size_t valid = 0;
    for (std::size_t p = 0; p < f.depth.size(); ++p) {
      ASSERT_EQ(f.depth[p], kinect_disparity_to_metres(rec[i].raw[p]))
          << "frame " << i << " px " << p;
      valid += f.depth[p] > 0;
    }
    EXPECT_GT(valid, 200000u) << "frame " << i;
    EXPECT_EQ(f.colour, rec[i].rgb) << "frame " << i;
    if (i == 0) {
      // The accelerometer record before the first frame says -5 degrees.
      ASSERT_TRUE(kinect->tilt_degrees());
      EXPECT_DOUBLE_EQ(*kinect->tilt_degrees(), -5.0);
    }
    // Against PCL's original millimetres: within half a disparity step.
    const cv::Mat mm =
        cv::imread((shared / (std::string("frame_") + kStamps[i] + "_depth.tiff")).string(),
                   cv::IMREAD_UNCHANGED);
    if (mm.empty() || mm.type() != CV_16UC1) continue;  // ../shared not here
    double worst = 0;
    for (int v = 0; v < 480; ++v)
      for (int u = 0; u < 640; ++u) {
        const double z = mm.at<std::uint16_t>(v, u) * 0.001;
        const double got = f.depth[v * 640 + u];
        if (z == 0) {
          ASSERT_EQ(got, 0.0) << u << "," << v;
          continue;
        }
        const double step = 0.0030711016 * z * z;  // one raw unit at depth z
        worst = std::max(worst, std::abs(got - z) / step);
      }
    EXPECT_LE(worst, 0.51) << "frame " << i << ": worst error in disparity steps";
    std::printf(
        "[ KINECT   ] frame %d: %zu valid pixels, worst %.3f disparity steps from PCL's mm\n", i,
        valid, worst);
  }
  // The recording ends: fakenect's event loop fails, as an unplugged Kinect's does.
  try {
    scanner->grab();
    FAIL() << "grab after the end of the recording";
  } catch (const DeviceError& e) {
    EXPECT_NE(std::string(e.what()).find("kinect:0: device gone while streaming (unplugged?)"),
              std::string::npos)
        << e.what();
  }
}

TEST(Fakenect, RecordsASessionAndKeepsItWhenTheDeviceGoes) {
  REQUIRE_FAKENECT();
  DeviceRegistry reg;
  register_real_devices(reg);
  bool listed = false;
  for (const auto& d : reg.list()) listed = listed || d.uri == "kinect:0";
  EXPECT_TRUE(listed) << "station devices should list kinect:0 (fakenect has one device)";

  auto scanner = reg.make_scanner(kUri);
  scanner->open();
  StillTurntable table;
  test::TempDir dir("station-kinect");
  SessionManifest m;
  m.scanner = kUri;
  m.turntable = table.uri();
  m.planned_views = 4;
  Session session = Session::create(dir / "session", m);
  CaptureParams params;
  params.views = 4;  // the recording has 3 frames: the 4th grab fails
  params.crop = false;
  EXPECT_THROW(run_capture(*scanner, table, session, params), DeviceError);

  const Session again = Session::open(dir / "session");
  ASSERT_EQ(again.manifest().views.size(), 3u);  // every finished view kept
  for (std::size_t i = 0; i < 3; ++i) {
    const ViewRecord& v = again.manifest().views[i];
    ASSERT_TRUE(v.angle_deg);
    EXPECT_DOUBLE_EQ(*v.angle_deg, 90.0 * i);
    EXPECT_GT(v.points, 200000u);
    std::printf("[ KINECT   ] view %zu: %zu points\n", i, v.points);
    EXPECT_FALSE(v.colour_image.empty());
    EXPECT_TRUE(std::filesystem::exists(dir / "session" / v.file));
  }
}

}  // namespace
}  // namespace station

#endif  // STATION_KINECT_FAKENECT_TESTS
