#pragma once
// The turntable plane as a bound of the reconstructed solid. A turntable never
// sees the underside of the object, and MPU's extrapolation there can flare
// far below the table (docs/mpu.md, "Known limits"). The object rests on the
// table, so nothing of it lies below the table plane: intersecting the implicit
// solid with the half-space above the plane closes the underside flat, where
// the real object is flat against the table.
#include <cmath>

#include "core/geometry.h"
#include "reconstruct/implicit.h"

namespace station {

/// f intersected with the half-space {x : up . x >= height}:
/// g(x) = max(f(x), height - up . x) (f < 0 inside, as every ImplicitFunction).
/// `up` is normalised; f must outlive this object. Thread-safe when f is.
class HalfSpaceClip : public ImplicitFunction {
 public:
  HalfSpaceClip(const ImplicitFunction& f, const Vec3d& up, double height);
  double value(const Vec3d& x) const override;
  /// The gradient of whichever side is larger (of the plane on a tie).
  Vec3d gradient(const Vec3d& x) const override;
  /// On the cut face (the plane side wins) the surface is trusted: the plane is
  /// known, not extrapolated. Elsewhere as f.
  bool trusted(const Vec3d& x) const override;
  /// Where the plane cuts f the solid has a crease; elsewhere as f.
  bool may_be_sharp(const Vec3d& x, double radius) const override {
    return std::abs(plane_value(x)) <= radius || f_.may_be_sharp(x, radius);
  }
  double plane_value(const Vec3d& x) const { return height_ - up_.dot(x); }
  /// value() at each point, f's values taken together (f.values_near).
  void values_near(const Vec3d* xs, int n, double* out) const override;
  /// gradient() at each point, f's values and gradients taken together.
  void gradients_near(const Vec3d* xs, int n, Vec3d* out) const override;
  /// Both from one values_gradients_near of f.
  void values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const override;

 private:
  const ImplicitFunction& f_;
  Vec3d up_;
  double height_;
};

}  // namespace station
