#include "registration/axis_calibration.h"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <Eigen/QR>
#include <cmath>

namespace station {

double wrap_angle_deg(double a) {
  a = std::fmod(a, 360.0);
  if (a > 180.0) a -= 360.0;
  if (a <= -180.0) a += 360.0;
  return a;
}

namespace {

constexpr double kDeg = M_PI / 180.0;

Vec3d axis_angle(const Eigen::Matrix3d& R) {
  const Eigen::AngleAxisd aa(R);
  return aa.axis() * aa.angle();
}

}  // namespace

AxisFitResult fit_turntable_axis(const std::vector<AxisMotion>& motions,
                                 const AxisFitParams& params) {
  AxisFitResult res;
  res.residuals.resize(motions.size());
  std::vector<std::size_t> used;
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  for (std::size_t k = 0; k < motions.size(); ++k) {
    const AxisMotion& m = motions[k];
    const double a = wrap_angle_deg(m.angle_deg);
    if (!m.transform.allFinite() || m.weight <= 0) continue;
    if (std::abs(a) > 180.0 - params.ambiguous_margin_deg || std::abs(a) < 1e-6) continue;
    const Vec3d w = axis_angle(m.transform.block<3, 3>(0, 0));
    M += m.weight * w * w.transpose();
    used.push_back(k);
  }
  double max_angle = 0;
  for (std::size_t k : used) max_angle = std::max(max_angle, std::abs(wrap_angle_deg(motions[k].angle_deg)));
  if (used.empty() || max_angle < 5.0) {
    res.message = "no usable motion (need one of at least 5 degrees)";
    return res;
  }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(M);
  Vec3d d = es.eigenvectors().col(2);
  // Sense: omega_k ~ -angle_k * d (the table turns the object by +angle, the
  // motion between scanner frames turns it back).
  double sense = 0;
  for (std::size_t k : used) {
    const Vec3d w = axis_angle(motions[k].transform.block<3, 3>(0, 0));
    sense += motions[k].weight * wrap_angle_deg(motions[k].angle_deg) * w.dot(d);
  }
  if (sense > 0) d = -d;

  // Point: stacked (I - R_k) p = t_k, each rank 2, plus d . p = d . p_near.
  const Vec3d near = params.point_near.value_or(Vec3d::Zero());
  Eigen::MatrixXd A(3 * used.size() + 1, 3);
  Eigen::VectorXd b(3 * used.size() + 1);
  for (std::size_t r = 0; r < used.size(); ++r) {
    const AxisMotion& m = motions[used[r]];
    const double w = std::sqrt(m.weight);
    A.block<3, 3>(3 * r, 0) = w * (Eigen::Matrix3d::Identity() - m.transform.block<3, 3>(0, 0));
    b.segment<3>(3 * r) = w * m.transform.block<3, 1>(0, 3);
  }
  A.row(3 * used.size()) = d.transpose();
  b(3 * used.size()) = d.dot(near);
  const Vec3d p = A.colPivHouseholderQr().solve(b);
  res.axis.direction = d;
  res.axis.point = p;
  res.ok = p.allFinite();
  if (!res.ok) res.message = "axis point is not finite";

  double sa = 0, st = 0, sx = 0;
  for (std::size_t k = 0; k < motions.size(); ++k) {
    const AxisMotion& m = motions[k];
    if (!m.transform.allFinite()) continue;
    AxisResidual& r = res.residuals[k];
    const Eigen::Matrix3d R = m.transform.block<3, 3>(0, 0);
    const Vec3d w = axis_angle(R);
    const double about = -w.dot(d) / kDeg;
    r.angle_deg = wrap_angle_deg(about - m.angle_deg);
    r.tilt_deg = (w - w.dot(d) * d).norm() / kDeg;
    r.translation = ((Eigen::Matrix3d::Identity() - R) * p - m.transform.block<3, 1>(0, 3)).norm();
    r.used = std::find(used.begin(), used.end(), k) != used.end();
    if (r.used) {
      sa += r.angle_deg * r.angle_deg;
      st += r.tilt_deg * r.tilt_deg;
      sx += r.translation * r.translation;
    }
  }
  res.rms_angle_deg = std::sqrt(sa / double(used.size()));
  res.rms_tilt_deg = std::sqrt(st / double(used.size()));
  res.rms_translation = std::sqrt(sx / double(used.size()));
  return res;
}

AxisFitResult calibrate_axis(const std::vector<Eigen::Matrix4d>& poses,
                             const std::vector<double>& angles_deg, const AxisFitParams& params) {
  AxisFitResult res;
  if (poses.size() != angles_deg.size()) {
    res.message = "poses and angles differ in number";
    return res;
  }
  std::size_t ref = poses.size();
  for (std::size_t i = 0; i < poses.size(); ++i)
    if (poses[i].allFinite() && std::isfinite(angles_deg[i])) {
      ref = i;
      break;
    }
  if (ref == poses.size()) {
    res.message = "no usable view";
    return res;
  }
  const Eigen::Matrix4d ref_inv = poses[ref].inverse();
  std::vector<AxisMotion> motions(poses.size());
  for (std::size_t i = 0; i < poses.size(); ++i) {
    if (i == ref || !poses[i].allFinite() || !std::isfinite(angles_deg[i])) {
      motions[i].weight = 0;
      continue;
    }
    motions[i].transform = ref_inv * poses[i];
    motions[i].angle_deg = angles_deg[i] - angles_deg[ref];
  }
  return fit_turntable_axis(motions, params);
}

}  // namespace station
