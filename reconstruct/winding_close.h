#pragma once
// Closing what the scanner never saw, by the winding number of the oriented cloud.
//
// Far from the data an implicit fit only extrapolates: on a turntable scan with an
// open bottom (the Stanford dragon on its stand) MPU's local quadrics flare outwards
// until the extraction box caps them (docs/mpu.md, "Known limits"). Telling the
// exterior from the interior there needs global information. The generalized
// winding number of the oriented points (Barill et al. 2018, "Fast winding numbers
// for soups and clouds") gives it: w(x) = sum_i a_i n_i . (p_i - x) / (4 pi |p_i - x|^3)
// is about 1 inside, 0 outside, and passes smoothly through 1/2 across holes, so its
// 1/2 level set spans a hole the way a membrane would.
//
// WindingClose blends: near the data (within the trust distance t1 of a point) the
// function is f; beyond t2 it is s(x) = (1/2 - w(x)) * scale; in between it moves
// linearly from one to the other with the distance. The blend is continuous, so the
// extracted mesh has no seams.
#include <memory>
#include <vector>

#include "core/geometry.h"
#include "reconstruct/implicit.h"

namespace station {

/// Barnes-Hut evaluation of the winding number of an oriented cloud. Each point
/// stands for the area pi r_8^2 / 8 (r_8: distance to its 8th neighbour); the cloud
/// is then reduced to one point per voxel (area-weighted centroid, summed area x
/// normal, so normals that cancel, as on both sides of a thin part, weigh less).
/// Far clusters (distance > 2 x their radius) count as one dipole. Thread-safe
/// after construction.
class WindingNumber {
 public:
  /// points and unit normals (outwards), same size; voxel > 0. `areas`: each point's
  /// area as point_areas gives it for these points (taken instead of computing it
  /// again; the same values), or null.
  WindingNumber(const std::vector<Vec3f>& points, const std::vector<Vec3f>& normals, double voxel,
                const std::vector<double>* areas = nullptr);
  ~WindingNumber();
  WindingNumber(WindingNumber&&) noexcept;
  WindingNumber& operator=(WindingNumber&&) noexcept;
  double operator()(const Vec3d& x) const;
  /// w(x) and, when grad is given, its gradient (analytic, from the same sum).
  double evaluate(const Vec3d& x, Vec3d* grad) const;
  /// evaluate() at n points close together, the same bits, from one walk of the tree
  /// where the points agree on a node (all far: its dipole; all near: its children)
  /// and one point at a time below a node where they do not. grads may be null.
  void evaluate_near(const Vec3d* xs, int n, double* w, Vec3d* grads) const;
  /// Points after the voxel reduction.
  std::size_t size() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// The area each point stands for in the winding number: pi r_8^2 / 8 over the points
/// whose coordinates and normal are finite (r_8: the distance to the 8th nearest of
/// them), 0 for the others. One k-d tree and one 9-nearest query per point: the
/// surface stage computes it once for the enclosure and the closing. InvalidInput when
/// the sizes differ.
std::vector<double> point_areas(const std::vector<Vec3f>& points, const std::vector<Vec3f>& normals);

/// How much an oriented cloud encloses: the median, over up to 2,000 of its points
/// p with normals n, of w(p - d n) + w(p + d n), with d the winding number's voxel
/// (half WindingClose's default trust distance, at least diagonal / 200). Just
/// inside and just outside a closed surface w is 1 and 0 (sum 1); on either side
/// of a one-sided patch (a single view, a wall fragment) it is +-1/2 plus what the
/// rest of the cloud adds (a plane 0, a hemisphere 0.65: its rim sees most of it). The
/// surface stage's HoleMode::kAuto closes at kEnclosedAbove and above. 0 for an
/// empty cloud or one without normals.
double cloud_enclosure(const Cloud& cloud, const std::vector<double>* areas = nullptr);
/// Measured: whole turntable sessions 1.00 (the bundled bottle) and 0.92 (the
/// Stanford dragon, open under its stand); single views 0.47 (a simulated bottle
/// view, half its side), 0.21 (a dragon scan), 0.17 (a Kinect scene); a sphere
/// 0.97, a hemisphere 0.65 (tests/reconstruct/surface_test.cpp), which stays open:
/// half an object is as likely a bowl as a ball. Thin objects read low: a plate
/// 1.5 mm thick seen from both sides 0.40 (inside it the Barnes-Hut far field, one
/// dipole for both sides whose normals cancel, loses the inside value; taking it
/// from the outside one instead, 1 + 2 w(p + d n), reads a plane as 0.31 from the
/// near field's discretisation), so such a plate is kept open: its two sides
/// still mesh as one thin shape (tests/reconstruct/surface_test.cpp).
inline constexpr double kEnclosedAbove = 0.75;

struct WindingCloseParams {
  /// Trust distance t1 (world units): within it the function is f alone. 0 = 4 x the
  /// cloud's mean nearest-neighbour spacing (MPU's trust_factor default).
  double trust_distance = 0;
  /// t2 = ramp x t1: beyond it the function is the winding-number term alone. 1.5
  /// measured best of 1.5, 2 and 3 on the Stanford dragon (mesh -> scans 3.5, 4.0
  /// and 4.9 mm).
  double ramp = 1.5;
  /// Voxel of the winding-number reduction; 0 = max(t1 / 2, diagonal / 200).
  double voxel = 0;
  /// point_areas of the cloud's points, when the caller has them (read during
  /// construction only), or null.
  const std::vector<double>* areas = nullptr;
};

/// g(x) = (1 - beta) f(x) + beta s(x), beta = clamp((d(x) - t1) / (t2 - t1), 0, 1),
/// d the distance to the nearest input point, s = (1/2 - w(x)) * 2 t2. f must
/// outlive this object; thread-safe when f is.
class WindingClose : public ImplicitFunction {
 public:
  /// InvalidInput when the cloud is empty or has no normals.
  WindingClose(const ImplicitFunction& f, const Cloud& cloud, const WindingCloseParams& params = {});
  ~WindingClose() override;
  double value(const Vec3d& x) const override;
  /// grad f where beta = 0; elsewhere the blend's gradient (grad w analytic).
  Vec3d gradient(const Vec3d& x) const override;
  /// value() at each point; f's values (where the blend needs them) taken together.
  void values_near(const Vec3d* xs, int n, double* out) const override;
  /// gradient() at each point; f's values and gradients (where needed) taken together
  /// (through the blend where the cluster is not surely trusted).
  void gradients_near(const Vec3d* xs, int n, Vec3d* out) const override;
  /// Both; f's in one values_gradients_near where the cluster is surely trusted.
  void values_gradients_near(const Vec3d* xs, int n, double* values, Vec3d* grads) const override;
  bool trusted(const Vec3d& x) const override { return f_.trusted(x); }
  bool may_be_trusted_near(const Vec3d& x, double radius) const override { return f_.may_be_trusted_near(x, radius); }
  /// The blend with the smooth winding field adds no crease: as f.
  bool may_be_sharp(const Vec3d& x, double radius) const override { return f_.may_be_sharp(x, radius); }
  double winding(const Vec3d& x) const { return (*w_)(x); }
  double trust_distance() const { return t1_; }
  std::size_t winding_points() const { return w_->size(); }

 private:
  double blend(const Vec3d& x, Vec3d* grad) const;
  // Whether every one of the n points is surely within the trust distance t1 of an
  // input point (each in a cell of the NearGrid, else one nearest-point query for the
  // cluster): blend() is 0 for all.
  bool all_trusted(const Vec3d* xs, int n) const;
  // values_gradients_near through the blend for every point (no trusted shortcut).
  void blended_values_gradients(const Vec3d* xs, int n, double* values, Vec3d* grads) const;
  // w (and its gradient, with grads) at the points whose blend weight beta is above 0,
  // taken together (WindingNumber::evaluate_near); 0 elsewhere.
  void winding_where_blended(const Vec3d* xs, int n, const std::vector<double>& beta, std::vector<double>& w,
                             std::vector<Vec3d>* grads) const;
  const ImplicitFunction& f_;
  const class MpuSurface* mpu_;  // f_ when it is an MPU surface (value and gradient in one walk)
  struct Index;
  std::unique_ptr<Index> index_;
  std::unique_ptr<WindingNumber> w_;
  double t1_ = 0, t2_ = 0;
};

}  // namespace station
