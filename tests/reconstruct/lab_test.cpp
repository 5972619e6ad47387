#include "reconstruct/lab.h"

#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/imgproc.hpp>
#include <random>

namespace station {
namespace {

// Our conversion against OpenCV's on float images (sRGB in [0, 1], L in [0, 100]).
TEST(Lab, MatchesOpenCvOnFloatImages) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(0, 1);
  const int n = 4096;
  cv::Mat rgb(1, n, CV_32FC3);
  for (int i = 0; i < n; ++i) {
    cv::Vec3f c(u(rng), u(rng), u(rng));
    if (i < 8) c = cv::Vec3f(float(i & 1), float((i >> 1) & 1), float((i >> 2) & 1));  // cube corners
    if (i >= 8 && i < 16) c = cv::Vec3f(0.002f * i, 0.001f * i, 0.003f * i);          // near black (linear branch)
    rgb.at<cv::Vec3f>(0, i) = c;
  }
  cv::Mat lab, back;
  cv::cvtColor(rgb, lab, cv::COLOR_RGB2Lab);
  cv::cvtColor(lab, back, cv::COLOR_Lab2RGB);
  double max_lab = 0, max_back = 0, sum_lab = 0;
  for (int i = 0; i < n; ++i) {
    const cv::Vec3f c = rgb.at<cv::Vec3f>(0, i), l = lab.at<cv::Vec3f>(0, i);
    const Lab ours = srgb_to_lab(c[0], c[1], c[2]);
    for (int k = 0; k < 3; ++k) {
      max_lab = std::max(max_lab, std::abs(ours[k] - l[k]));
      sum_lab += std::abs(ours[k] - l[k]) / (3 * n);
    }
    const auto rt = lab_to_srgb({l[0], l[1], l[2]});
    const cv::Vec3f b = back.at<cv::Vec3f>(0, i);
    for (int k = 0; k < 3; ++k) max_back = std::max(max_back, std::abs(rt[k] - b[k]));
  }
  // OpenCV's float path interpolates tables (its a* of (0.2, 0.7, 0.1) is exactly -60,
  // the formula gives -60.07), most visibly near black: measured max 0.49, mean 0.04
  // L*a*b* units (a just noticeable difference is about 1-2).
  RecordProperty("max_lab_difference", std::to_string(max_lab));
  EXPECT_LT(max_lab, 0.6);
  EXPECT_LT(sum_lab, 0.08);
  EXPECT_LT(max_back, 1e-3);
}

TEST(Lab, RoundTripAndKnownValues) {
  for (int r = 0; r < 256; r += 15)
    for (int g = 0; g < 256; g += 15)
      for (int b = 0; b < 256; b += 15) {
        const Rgb c{std::uint8_t(r), std::uint8_t(g), std::uint8_t(b)};
        const auto s = lab_to_srgb(rgb_to_lab(c));
        EXPECT_NEAR(s[0], r / 255.0, 1e-5);
        EXPECT_NEAR(s[1], g / 255.0, 1e-5);
        EXPECT_NEAR(s[2], b / 255.0, 1e-5);
        EXPECT_TRUE(lab_to_rgb(rgb_to_lab(c)) == c);
      }
  const Lab white = rgb_to_lab({255, 255, 255});
  EXPECT_NEAR(white[0], 100, 1e-3);
  EXPECT_NEAR(white[1], 0, 1e-2);
  EXPECT_NEAR(white[2], 0, 1e-2);
  const Lab red = rgb_to_lab({255, 0, 0});  // textbook D65 values
  EXPECT_NEAR(red[0], 53.24, 0.05);
  EXPECT_NEAR(red[1], 80.09, 0.1);
  EXPECT_NEAR(red[2], 67.20, 0.1);
  EXPECT_NEAR(delta_e(rgb_to_lab({255, 0, 0}), rgb_to_lab({0, 0, 255})), 176.3, 0.5);
}

TEST(Lab, OutOfGamutAndNonFiniteAreClamped) {
  const auto s = lab_to_srgb({150, 300, -300});
  for (double v : s) EXPECT_TRUE(v >= 0 && v <= 1);
  const auto z = lab_to_srgb({NAN, 0, 0});
  for (double v : z) EXPECT_EQ(v, 0);
}

}  // namespace
}  // namespace station
