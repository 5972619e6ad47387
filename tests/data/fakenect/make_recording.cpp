// Builds the fakenect recording in this folder from PCL's Kinect frames
// (../shared/data/rgbd_frames/pcl_kinect_sequence/, see README.md). Not part of
// the build; run by hand:
//
//   g++ -std=c++17 -O2 tests/data/fakenect/make_recording.cpp -o /tmp/make_recording \
//       $(pkg-config --cflags --libs opencv4)
//   /tmp/make_recording ../shared/data/rgbd_frames/pcl_kinect_sequence /tmp/kinect_sequence
//   tar -C /tmp -cJf tests/data/fakenect/kinect_sequence.tar.xz kinect_sequence
//
// What it writes (fakenect's format, as libfreenect's fakenect-record writes it):
//   INDEX.txt                      one file name a line, replayed in order
//   a-<time>-<ts>.dump             freenect_raw_tilt_state, 12 bytes (tilt -5 deg)
//   d-<time>-<ts>.pgm              "P5 640 480 65535\n" + 640*480 uint16, host
//                                  (little-endian) order: raw 11-bit disparity,
//                                  2047 = no data
//   r-<time>-<ts>.ppm              "P6 640 480 255\n" + 640*480*3 RGB bytes
// <time> is the frame's capture time in seconds since the epoch (from the PCL
// file name, UTC); fakenect sleeps the differences between lines.
//
// The depth TIFFs hold millimetres; they become disparity through the inverse of
// the driver's conversion (drivers/kinect_scanner.h kinect_disparity_to_metres):
//   z = 1 / (a*raw + b),  a = -0.0030711016, b = 3.3309495161
//   raw = round((1/z - b) / a), clamped to [0, 2046]
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>
#include <vector>

int main(int argc, char** argv) {
  if (argc != 3) {
    std::cerr << "usage: make_recording SRC_DIR OUT_DIR\n";
    return 2;
  }
  const std::string src = argv[1], out = argv[2];
  // Capture times of the three PCL frames (file names, UTC): 2012-12-14T14:22:55.814212 etc.
  const char* stamps[] = {"20121214T142255.814212", "20121214T142256.068683",
                          "20121214T142256.332395"};
  const double times[] = {1355494975.814212, 1355494976.068683, 1355494976.332395};
  const double a = -0.0030711016, b = 3.3309495161;
  std::ofstream index(out + "/INDEX.txt");
  if (!index) {
    std::cerr << out << ": cannot write (create the folder first)\n";
    return 1;
  }
  {
    // Accelerometer/tilt record: x, y, z counts (819 per g: level, gravity on y),
    // tilt_angle in half degrees (-10 = -5 deg), status 0 = stopped.
    std::uint8_t state[12] = {0};
    const std::int16_t acc[3] = {0, 819, 0};
    std::memcpy(state, acc, 6);
    state[6] = static_cast<std::uint8_t>(static_cast<std::int8_t>(-10));
    char name[128];
    std::snprintf(name, sizeof name, "a-%.6f-%010u.dump", times[0] - 0.01, 0u);
    std::ofstream(out + "/" + name, std::ios::binary).write(reinterpret_cast<char*>(state), 12);
    index << name << "\n";
  }
  for (int i = 0; i < 3; ++i) {
    const std::string base = src + "/frame_" + stamps[i];
    cv::Mat depth = cv::imread(base + "_depth.tiff", cv::IMREAD_UNCHANGED);
    cv::Mat bgr = cv::imread(base + "_rgb.tiff", cv::IMREAD_COLOR);
    if (depth.empty() || bgr.empty() || depth.type() != CV_16UC1 || depth.cols != 640 ||
        depth.rows != 480 || bgr.cols != 640 || bgr.rows != 480) {
      std::cerr << base << ": not a 640x480 16-bit depth + RGB pair\n";
      return 1;
    }
    std::vector<std::uint16_t> raw(640 * 480);
    for (int v = 0; v < 480; ++v)
      for (int u = 0; u < 640; ++u) {
        const std::uint16_t mm = depth.at<std::uint16_t>(v, u);
        std::uint16_t d = 2047;
        if (mm > 0) {
          const double r = std::round((1000.0 / mm - b) / a);
          d = static_cast<std::uint16_t>(std::min(2046.0, std::max(0.0, r)));
        }
        raw[v * 640 + u] = d;
      }
    const unsigned ts = 1000000u * static_cast<unsigned>(i + 1);  // device timestamp (any)
    char dname[128], rname[128];
    std::snprintf(dname, sizeof dname, "d-%.6f-%010u.pgm", times[i], ts);
    std::snprintf(rname, sizeof rname, "r-%.6f-%010u.ppm", times[i], ts);
    {
      std::ofstream f(out + "/" + dname, std::ios::binary);
      f << "P5 640 480 65535\n";
      f.write(reinterpret_cast<const char*>(raw.data()), raw.size() * 2);
    }
    cv::Mat rgb;
    cv::cvtColor(bgr, rgb, cv::COLOR_BGR2RGB);
    {
      std::ofstream f(out + "/" + rname, std::ios::binary);
      f << "P6 640 480 255\n";
      for (int v = 0; v < 480; ++v) f.write(reinterpret_cast<const char*>(rgb.ptr(v)), 640 * 3);
    }
    index << dname << "\n" << rname << "\n";
  }
  return 0;
}
