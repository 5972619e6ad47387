#include "capture/camera_calibration.h"

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <Eigen/Core>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>

#include "core/error.h"
#include "core/texture.h"

namespace station {

namespace fs = std::filesystem;

namespace {
// A calibration whose corners miss their model by more than this is no calibration
// (a good one is well under 1 px; blurred or badly printed boards 1-2 px).
constexpr double kMaxCalibrationRmsPx = 5;
// The boards' planes must differ by at least this much somewhere among the views (the
// rendered test set of boards at several tilts: up to 50 deg).
constexpr double kMinBoardTiltSpreadDeg = 10;
}  // namespace

CameraCalibration calibrate_camera(const std::vector<fs::path>& images, const ChessboardSpec& board) {
  // OpenCV's chessboard detector needs 3x3 inner corners at least (2x2 failed inside it).
  if (board.inner_cols < 3 || board.inner_rows < 3 || board.inner_cols > 1000 || board.inner_rows > 1000)
    throw InvalidInput("chessboard: needs 3x3 to 1000x1000 inner corners, got " + std::to_string(board.inner_cols) + "x" +
                       std::to_string(board.inner_rows));
  if (!(board.square >= 1e-6 && board.square <= 100))
    throw InvalidInput("chessboard: the square size must be between 1e-6 and 100 (metres)");
  CameraCalibration out;
  std::vector<std::vector<cv::Point3f>> object_points;
  std::vector<std::vector<cv::Point2f>> image_points;
  std::vector<int> index_of;  // calibration entry -> out.images index
  cv::Size size;
  std::vector<cv::Point3f> grid;
  for (int r = 0; r < board.inner_rows; ++r)
    for (int c = 0; c < board.inner_cols; ++c)
      grid.emplace_back(float(c * board.square), float(r * board.square), 0.f);
  for (const fs::path& file : images) {
    CameraImageResult res;
    res.file = file.string();
    const std::string bytes = read_image_file(file);
    cv::Mat img;
    try {
      if (!bytes.empty())
        img = cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())), cv::IMREAD_GRAYSCALE);
    } catch (const cv::Exception& e) {
      throw FormatError(file.string() + ": not a readable image (the decoder refused it: " + e.err + ")");
    }
    if (img.empty()) throw FormatError(file.string() + ": not a readable image");
    if (size.width == 0) size = img.size();
    if (img.size() != size)
      throw InvalidInput(file.string() + ": image size " + std::to_string(img.cols) + "x" +
                         std::to_string(img.rows) + " differs from the first image's");
    std::vector<cv::Point2f> corners;
    bool found = false;
    if (img.cols < 16 || img.rows < 16) {
      res.message = "too small for a chessboard (" + std::to_string(img.cols) + "x" + std::to_string(img.rows) + ")";
    } else {
      try {
        found = cv::findChessboardCorners(img, cv::Size(board.inner_cols, board.inner_rows), corners,
                                          cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE);
        if (found)
          cv::cornerSubPix(img, corners, cv::Size(5, 5), cv::Size(-1, -1),
                           cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 50, 1e-4));
      } catch (const cv::Exception& e) {
        throw InvalidInput(file.string() + ": the chessboard search failed (" + e.err + ")");
      }
      if (!found) res.message = "chessboard not found";
    }
    // The same view twice (a copy of an image, or a board that did not move) adds
    // nothing: the intrinsics need the board at different tilts.
    if (found)
      for (std::size_t k = 0; k < image_points.size(); ++k) {
        double sum = 0;
        for (std::size_t j = 0; j < corners.size(); ++j) {
          const cv::Point2f d = corners[j] - image_points[k][j];
          sum += std::sqrt(double(d.dot(d)));
        }
        if (sum / double(corners.size()) < 0.5) {
          found = false;
          res.message = "the same view as " + out.images[std::size_t(index_of[k])].file + " (the board did not move)";
          break;
        }
      }
    if (found) {
      res.used = true;
      object_points.push_back(grid);
      image_points.push_back(corners);
      index_of.push_back(int(out.images.size()));
    }
    out.images.push_back(res);
  }
  out.used_images = int(image_points.size());
  int repeated = 0;
  for (const CameraImageResult& r : out.images) repeated += r.message.rfind("the same view as ", 0) == 0 ? 1 : 0;
  if (out.used_images < 3)
    throw InvalidInput("calibrate camera: the chessboard (" + std::to_string(board.inner_cols) + "x" +
                       std::to_string(board.inner_rows) + " inner corners) was found in " +
                       std::to_string(out.used_images + repeated) + " of " + std::to_string(images.size()) +
                       " images" +
                       (repeated ? " (" + std::to_string(repeated) + " of them the same view as another)" : "") +
                       "; at least 3 different views are needed");
  cv::Mat K, dist;
  std::vector<cv::Mat> rvecs, tvecs;
  try {
    out.rms_px = cv::calibrateCamera(object_points, image_points, size, K, dist, rvecs, tvecs);
  } catch (const cv::Exception& e) {
    throw InvalidInput("calibrate camera: the calibration failed (" + e.err + ")");
  }
  if (!std::isfinite(out.rms_px)) throw InvalidInput("calibrate camera: the calibration did not converge");
  Intrinsics& in = out.intrinsics;
  in.width = size.width;
  in.height = size.height;
  in.fx = K.at<double>(0, 0);
  in.fy = K.at<double>(1, 1);
  in.cx = K.at<double>(0, 2);
  in.cy = K.at<double>(1, 2);
  for (int i = 0; i < 5 && i < int(dist.total()); ++i) in.distortion[i] = dist.at<double>(i);
  // Views that do not determine the camera (all nearly the same, the board never
  // tilted) give a solution far from any lens: refused, not written.
  const double side = std::max(size.width, size.height);
  char why[200];
  std::snprintf(why, sizeof why, "reprojection RMS %.3g px, fx %.4g, fy %.4g for a %dx%d image", out.rms_px, in.fx,
                in.fy, size.width, size.height);
  // Boards whose planes are all nearly parallel (turned only in the image plane, never
  // tilted) leave the focal length undetermined (Zhang's method needs planes at
  // different tilts): the rendered boards turned and moved about in their plane fitted
  // fx 456 px for a 420 px lens, the campaign's 13,796 px for 500, with OpenCV's
  // standard deviation of fx under 0.1 %. The largest angle between two boards' normals.
  double spread = 0;
  std::vector<Eigen::Vector3d> normals;
  for (const cv::Mat& r : rvecs) {
    cv::Mat R;
    cv::Rodrigues(r, R);
    normals.emplace_back(R.at<double>(0, 2), R.at<double>(1, 2), R.at<double>(2, 2));
  }
  for (std::size_t a = 0; a < normals.size(); ++a)
    for (std::size_t b = a + 1; b < normals.size(); ++b)
      spread = std::max(spread, std::acos(std::clamp(std::abs(normals[a].dot(normals[b])), 0.0, 1.0)) * 180 / M_PI);
  if (!(out.rms_px <= kMaxCalibrationRmsPx) || !(in.fx >= 0.05 * side && in.fx <= 100 * side) ||
      !(in.fy >= 0.05 * side && in.fy <= 100 * side) || !std::isfinite(in.cx) || !std::isfinite(in.cy) ||
      !(spread >= kMinBoardTiltSpreadDeg)) {
    if (!(spread >= kMinBoardTiltSpreadDeg)) {
      char tilt[96];
      std::snprintf(tilt, sizeof tilt, "; the boards' planes differ by at most %.1f deg", spread);
      std::strncat(why, tilt, sizeof why - std::strlen(why) - 1);
    }
    throw InvalidInput("calibrate camera: the " + std::to_string(out.used_images) +
                       " views do not determine the camera (" + why +
                       "): take the board at several tilts and places in the image");
  }
  for (std::size_t k = 0; k < image_points.size(); ++k) {
    std::vector<cv::Point2f> projected;
    cv::projectPoints(object_points[k], rvecs[k], tvecs[k], K, dist, projected);
    double sum = 0;
    for (std::size_t j = 0; j < projected.size(); ++j) {
      const cv::Point2f d = projected[j] - image_points[k][j];
      sum += d.dot(d);
    }
    out.images[index_of[k]].rms_px = std::sqrt(sum / projected.size());
  }
  return out;
}

std::string camera_profile_fragment(const CameraCalibration& c, const std::string& source) {
  const Intrinsics& k = c.intrinsics;
  char buf[1024];
  std::snprintf(buf, sizeof buf,
                "# Camera calibrated from %s: %d of %zu images, reprojection RMS %.4f px\n"
                "scanner:\n  options:\n"
                "    width: \"%d\"\n    height: \"%d\"\n"
                "    fx: \"%.10g\"\n    fy: \"%.10g\"\n    cx: \"%.10g\"\n    cy: \"%.10g\"\n"
                "    distortion: \"%.10g,%.10g,%.10g,%.10g,%.10g\"   # k1,k2,p1,p2,k3 (OpenCV order)\n",
                source.c_str(), c.used_images, c.images.size(), c.rms_px, k.width, k.height, k.fx, k.fy,
                k.cx, k.cy, k.distortion[0], k.distortion[1], k.distortion[2], k.distortion[3],
                k.distortion[4]);
  return buf;
}

}  // namespace station
