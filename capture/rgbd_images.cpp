// read_rgbd_frame (capture/capture.h): a depth camera's frame from image files.
#include <opencv2/imgcodecs.hpp>

#include "capture/capture.h"
#include "core/error.h"

namespace station {

namespace {

// cv::imread, with what OpenCV throws (an image bomb's header) said as the file's fault.
cv::Mat read_image(const std::string& file, int flags) {
  try {
    return cv::imread(file, flags);
  } catch (const cv::Exception& e) {
    throw InvalidInput(file + ": not a readable image (the decoder refused it: " + e.err + ")");
  }
}

}  // namespace

Frame read_rgbd_frame(const std::string& depth_file, const std::string& colour_file, Intrinsics intrinsics,
                      double depth_unit) {
  const cv::Mat depth = read_image(depth_file, cv::IMREAD_UNCHANGED);
  if (depth.empty()) throw InvalidInput(depth_file + ": cannot read the depth image");
  if (depth.type() != CV_16UC1) throw InvalidInput(depth_file + ": the depth image is not 16-bit, one channel");
  if (!(depth_unit > 0)) throw InvalidInput(depth_file + ": the depth unit must be positive");
  cv::Mat bgr;
  if (!colour_file.empty()) {
    bgr = read_image(colour_file, cv::IMREAD_COLOR);
    if (bgr.empty()) throw InvalidInput(colour_file + ": cannot read the colour image");
    if (bgr.size() != depth.size()) throw InvalidInput(colour_file + ": not the depth image's size");
  }
  Frame f;
  intrinsics.width = depth.cols;
  intrinsics.height = depth.rows;
  f.intrinsics = intrinsics;
  if (!bgr.empty()) f.colour_intrinsics = intrinsics;
  f.depth.reserve(std::size_t(depth.total()));
  for (int v = 0; v < depth.rows; ++v)
    for (int u = 0; u < depth.cols; ++u) {
      f.depth.push_back(float(depth_unit * depth.at<std::uint16_t>(v, u)));
      if (bgr.empty()) continue;
      const cv::Vec3b c = bgr.at<cv::Vec3b>(v, u);
      f.colour.insert(f.colour.end(), {c[2], c[1], c[0]});
    }
  return f;
}

}  // namespace station
