#pragma once
// Abstract implicit function f: R^3 -> R, the interface mesh extraction
// (reconstruct/marching_cubes.h) works on. Sign convention of the station:
// f < 0 inside, f > 0 outside, f = 0 on the surface, like a signed distance;
// grad f then points outwards.
#include "core/geometry.h"

namespace station {

class ImplicitFunction {
 public:
  virtual ~ImplicitFunction() = default;
  /// f(x). Must be thread-safe (called concurrently during extraction).
  virtual double value(const Vec3d& x) const = 0;
  /// grad f(x) (not necessarily unit). Thread-safe.
  virtual Vec3d gradient(const Vec3d& x) const = 0;
  /// Whether f is backed by data near x (default: everywhere). Extraction can drop
  /// the surface where it is not (MarchingCubesOptions::untrusted).
  virtual bool trusted(const Vec3d& x) const { return true; }
  /// False only when no point within `radius` of x is trusted (an extraction that drops
  /// the untrusted surface need not walk there); true may mean either. Default: true.
  virtual bool may_be_trusted_near(const Vec3d& x, double radius) const { return true; }
  /// Whether f may have a sharp edge or corner within `radius` of x (default: it may,
  /// anywhere). A function that knows where it is smooth (the MPU surface: only its
  /// leaves with an edge or corner fit make creases) lets DMC's feature step skip the
  /// cells there, where a bend of the surface would otherwise pass for an edge.
  virtual bool may_be_sharp(const Vec3d& x, double radius) const { return true; }
  /// f at n points close together (a lattice point's box, a few cells at most): the
  /// same values as value() one by one, which is what the default does. A function
  /// that can share work between nearby points overrides it (the MPU surface: one walk
  /// of its octree for all of them).
  virtual void values_near(const Vec3d* xs, int n, double* out) const {
    for (int i = 0; i < n; ++i) out[i] = value(xs[i]);
  }
  /// gradient() at n points close together, the same vectors bit for bit (as
  /// values_near for value()).
  virtual void gradients_near(const Vec3d* xs, int n, Vec3d* out) const {
    for (int i = 0; i < n; ++i) out[i] = gradient(xs[i]);
  }
  /// values_near and gradients_near at the same n points, the same bits; a function
  /// that finds both in one pass overrides it (the MPU surface: one octree walk).
  virtual void values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const {
    values_near(xs, n, values);
    gradients_near(xs, n, grads);
  }
};

}  // namespace station
