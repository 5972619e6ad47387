#pragma once
// Camera calibration from images of a chessboard (OpenCV's corner detector and
// Zhang's method): intrinsics, Brown-Conrady distortion and the reprojection
// error of every image, so a bad calibration is visible. `station calibrate camera`.
#include <filesystem>
#include <string>
#include <vector>

#include "drivers/scanner.h"

namespace station {

struct ChessboardSpec {
  int inner_cols = 9;    ///< inner corners along a row
  int inner_rows = 6;    ///< inner corners along a column
  double square = 0.025; ///< square side, metres
};

struct CameraImageResult {
  std::string file;
  bool used = false;          ///< the board was found
  double rms_px = 0;          ///< reprojection RMS of this image's corners, pixels
  std::string message;        ///< why it was not used
};

struct CameraCalibration {
  Intrinsics intrinsics;      ///< with distortion
  double rms_px = 0;          ///< overall reprojection RMS, pixels
  std::vector<CameraImageResult> images;
  int used_images = 0;
};

/// Calibrates from image files (PNG/JPEG, any size, all the same size). Images
/// where the board is not found are listed with a message and left out.
/// InvalidInput when fewer than 3 images show the board, or they differ in size;
/// IoError/FormatError naming an unreadable file.
CameraCalibration calibrate_camera(const std::vector<std::filesystem::path>& images,
                                   const ChessboardSpec& board);

/// The profile fragment (YAML) for a calibration: the scanner's intrinsics options.
std::string camera_profile_fragment(const CameraCalibration& calib, const std::string& source);

}  // namespace station
