#pragma once
// sRGB <-> CIE L*a*b* (D65), the conversion the colour function works in
// (reconstruct/colour_function.h). Matches OpenCV's cv::cvtColor COLOR_RGB2Lab /
// COLOR_Lab2RGB on float images (sRGB companding, D65 white Xn = 0.950456,
// Zn = 1.088754, L in [0, 100]); tests/reconstruct/lab_test.cpp checks it against
// OpenCV. Own implementation so that the reconstruct library does not link OpenCV.
#include <array>

#include "core/geometry.h"

namespace station {

/// L*, a*, b*.
using Lab = std::array<double, 3>;

/// sRGB channels in [0, 1] (not clamped: values outside are extrapolated) -> L*a*b*.
Lab srgb_to_lab(double r, double g, double b);
/// An 8-bit sRGB colour -> L*a*b*.
Lab rgb_to_lab(const Rgb& c);
/// L*a*b* -> sRGB channels, clamped to [0, 1]. Non-finite input gives black.
std::array<double, 3> lab_to_srgb(const Lab& lab);
/// L*a*b* -> 8-bit sRGB (rounded, clamped).
Rgb lab_to_rgb(const Lab& lab);

/// Euclidean colour difference (CIE76 Delta E).
double delta_e(const Lab& a, const Lab& b);

}  // namespace station
