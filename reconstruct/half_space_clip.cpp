#include "reconstruct/half_space_clip.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "core/error.h"

namespace station {

HalfSpaceClip::HalfSpaceClip(const ImplicitFunction& f, const Vec3d& up, double height)
    : f_(f), up_(up), height_(height) {
  const double n = up.norm();
  if (!(n > 0) || !std::isfinite(n) || !std::isfinite(height))
    throw InvalidInput("half-space clip: the plane needs a finite non-zero normal and a finite height");
  up_ /= n;
}

namespace {
double clip(double f, double p) {
  if (std::isnan(f)) return p > 0 ? p : f;  // below the plane is outside whatever f says
  return std::max(f, p);
}
}  // namespace

double HalfSpaceClip::value(const Vec3d& x) const { return clip(f_.value(x), plane_value(x)); }

void HalfSpaceClip::values_near(const Vec3d* xs, int n, double* out) const {
  f_.values_near(xs, n, out);
  for (int i = 0; i < n; ++i) out[i] = clip(out[i], plane_value(xs[i]));
}

Vec3d HalfSpaceClip::gradient(const Vec3d& x) const {
  const double f = f_.value(x);
  return plane_value(x) >= f || std::isnan(f) ? Vec3d(-up_) : f_.gradient(x);
}

void HalfSpaceClip::gradients_near(const Vec3d* xs, int n, Vec3d* out) const {
  std::vector<double> fv(std::size_t(std::max(n, 0)));  // local: f may call back into *_near
  f_.values_gradients_near(xs, n, fv.data(), out);
  for (int i = 0; i < n; ++i) {
    const double f = fv[std::size_t(i)];
    if (plane_value(xs[i]) >= f || std::isnan(f)) out[i] = -up_;
  }
}

void HalfSpaceClip::values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const {
  f_.values_gradients_near(xs, n, values, grads);
  for (int i = 0; i < n; ++i) {
    const double f = values[i], p = plane_value(xs[i]);
    if (p >= f || std::isnan(f)) grads[i] = -up_;
    values[i] = clip(f, p);
  }
}

bool HalfSpaceClip::trusted(const Vec3d& x) const {
  const double f = f_.value(x);
  return plane_value(x) >= f || f_.trusted(x);
}

}  // namespace station
