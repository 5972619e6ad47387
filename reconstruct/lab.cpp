#include "reconstruct/lab.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

namespace station {
namespace {

// OpenCV's constants (imgproc color_lab.cpp documents the same sRGB/D65 matrices).
constexpr double kXn = 0.950456, kZn = 1.088754;
constexpr double kThresh = 0.008856;  // (6/29)^3 as OpenCV rounds it
constexpr double kSlope = 7.787;      // (29/6)^2 / 3 rounded
constexpr double kOffset = 16.0 / 116.0;

double srgb_to_linear(double c) {
  return c <= 0.04045 ? c / 12.92 : std::pow((c + 0.055) / 1.055, 2.4);
}
double linear_to_srgb(double c) {
  return c <= 0.0031308 ? 12.92 * c : 1.055 * std::pow(c, 1 / 2.4) - 0.055;
}
double f_lab(double t) { return t > kThresh ? std::cbrt(t) : kSlope * t + kOffset; }
double f_lab_inv(double f) {
  const double t = f * f * f;
  return t > kThresh ? t : (f - kOffset) / kSlope;
}

}  // namespace

Lab srgb_to_lab(double r, double g, double b) {
  const double R = srgb_to_linear(r), G = srgb_to_linear(g), B = srgb_to_linear(b);
  const double X = (0.412453 * R + 0.357580 * G + 0.180423 * B) / kXn;
  const double Y = 0.212671 * R + 0.715160 * G + 0.072169 * B;
  const double Z = (0.019334 * R + 0.119193 * G + 0.950227 * B) / kZn;
  const double fx = f_lab(X), fy = f_lab(Y), fz = f_lab(Z);
  const double L = Y > kThresh ? 116 * fy - 16 : 903.3 * Y;
  return {L, 500 * (fx - fy), 200 * (fy - fz)};
}

Lab rgb_to_lab(const Rgb& c) { return srgb_to_lab(c.r / 255.0, c.g / 255.0, c.b / 255.0); }

std::array<double, 3> lab_to_srgb(const Lab& lab) {
  if (!std::isfinite(lab[0]) || !std::isfinite(lab[1]) || !std::isfinite(lab[2])) return {0, 0, 0};
  // Y from L (both branches of the forward map), then X, Z through f.
  const double L = lab[0];
  const double Y = L > 903.3 * kThresh ? std::pow((L + 16) / 116, 3) : L / 903.3;
  const double fy = Y > kThresh ? (L + 16) / 116 : kSlope * Y + kOffset;
  const double X = f_lab_inv(fy + lab[1] / 500) * kXn;
  const double Z = f_lab_inv(fy - lab[2] / 200) * kZn;
  // The exact inverse of the forward matrix (OpenCV's printed inverse agrees to
  // 6 digits), so that RGB -> Lab -> RGB is the identity to rounding.
  static const Eigen::Matrix3d inv = (Eigen::Matrix3d() << 0.412453, 0.357580, 0.180423, 0.212671, 0.715160,
                                      0.072169, 0.019334, 0.119193, 0.950227).finished().inverse();
  const Vec3d rgb = inv * Vec3d(X, Y, Z);
  const double R = rgb[0], G = rgb[1], B = rgb[2];
  auto out = [](double c) { return std::clamp(linear_to_srgb(std::clamp(c, 0.0, 1.0)), 0.0, 1.0); };
  return {out(R), out(G), out(B)};
}

Rgb lab_to_rgb(const Lab& lab) {
  const auto c = lab_to_srgb(lab);
  auto q = [](double v) { return std::uint8_t(std::lround(v * 255)); };
  return {q(c[0]), q(c[1]), q(c[2])};
}

double delta_e(const Lab& a, const Lab& b) {
  return std::sqrt((a[0] - b[0]) * (a[0] - b[0]) + (a[1] - b[1]) * (a[1] - b[1]) + (a[2] - b[2]) * (a[2] - b[2]));
}

}  // namespace station
