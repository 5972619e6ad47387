#include "registration/prior_check.h"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>

#include "core/geometry.h"
#include "registration/axis_calibration.h"
#include "registration/icp.h"

namespace station {

std::vector<double> angles_about_common_axis(const std::vector<Eigen::Matrix4d>& poses,
                                             const std::optional<Vec3d>& direction) {
  std::vector<Vec3d> w;
  Eigen::Matrix3d S = Eigen::Matrix3d::Zero();
  for (const Eigen::Matrix4d& X : poses) {
    const Eigen::AngleAxisd aa(Eigen::Matrix3d((rigid_inverse(poses.front()) * X).block<3, 3>(0, 0)));
    w.push_back(aa.axis() * aa.angle());
    S += w.back() * w.back().transpose();
  }
  const Vec3d d = direction ? direction->normalized()
                            : Vec3d(Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(S).eigenvectors().col(2));
  std::vector<double> angles;
  for (const Vec3d& v : w) angles.push_back(-v.dot(d) * 180.0 / M_PI);
  return angles;
}

AnglePriorFit fit_angle_prior(const std::vector<Eigen::Matrix4d>& poses, const std::vector<bool>& registered,
                              const SessionManifest& manifest, double tolerance_deg,
                              const std::optional<Vec3d>& known_direction) {
  AnglePriorFit best;
  best.residual_deg.assign(manifest.views.size(), std::nullopt);
  std::vector<int> idx;
  std::vector<Eigen::Matrix4d> ps;
  std::vector<double> cmd;
  for (std::size_t i = 0; i < manifest.views.size() && i < poses.size(); ++i)
    if (registered[i] && manifest.views[i].angle_deg && std::isfinite(*manifest.views[i].angle_deg) &&
        poses[i].allFinite()) {
      idx.push_back(int(i));
      ps.push_back(poses[i]);
      cmd.push_back(*manifest.views[i].angle_deg);
    }
  const int n = int(idx.size());
  best.views = n;
  if (n < 3) return best;
  // Measured angles about the known axis or the shared direction (both signs
  // of the latter are tried: its sign is arbitrary).
  std::vector<std::vector<double>> measured;
  const bool known = known_direction && known_direction->allFinite() && known_direction->norm() > 0;
  if (known) {
    measured.push_back(angles_about_common_axis(ps, known_direction));
  } else {
    measured.push_back(angles_about_common_axis(ps));
    measured.push_back(measured.back());
    for (double& a : measured.back()) a = -a;
  }
  // Scales: degrees, or step indices (all of the session's angles integers below
  // 64: 360 / (largest + 1) for indices from 0, 360 / largest from 1).
  std::vector<double> scales = {1.0};
  std::vector<double> all;
  for (const ViewRecord& v : manifest.views)
    if (v.angle_deg && std::isfinite(*v.angle_deg)) all.push_back(*v.angle_deg);
  const double top = all.empty() ? 0 : *std::max_element(all.begin(), all.end());
  if (std::all_of(all.begin(), all.end(), [](double c) { return c >= 0 && c == std::floor(c); }) && top >= 2 &&
      top < 64) {
    scales.push_back(360.0 / (top + 1));
    scales.push_back(360.0 / top);
  }
  const std::vector<double> signs = known ? std::vector<double>{1.0, -1.0} : std::vector<double>{1.0};
  double best_cost = 1e300;
  for (std::size_t mi = 0; mi < measured.size(); ++mi)
    for (double scale : scales)
      for (double sign : signs) {
        const std::vector<double>& meas = measured[mi];
        // One-point consensus: each view's offset tried; the most agreeing wins
        // (ties: the smaller sum of residuals). The degree-exact hypotheses
        // (sign +1, scale 1) are listed first and win ties.
        for (int k = 0; k < n; ++k) {
          const double b = wrap_angle_deg(meas[k] - sign * scale * cmd[k]);
          int agree = 0;
          double sum = 0, mean = 0;
          for (int j = 0; j < n; ++j) {
            const double r = wrap_angle_deg(meas[j] - sign * scale * cmd[j] - b);
            if (std::abs(r) <= tolerance_deg) {
              ++agree;
              mean += r;
            }
            sum += std::min(std::abs(r), 3 * tolerance_deg);
          }
          const double cost = -1e6 * agree + sum;
          if (cost < best_cost - 1e-9) {
            best_cost = cost;
            best.sign = sign;
            best.scale = scale;
            best.offset_deg = wrap_angle_deg(b + mean / std::max(agree, 1));
            best.agreeing = agree;
            for (int j = 0; j < n; ++j)
              best.residual_deg[idx[j]] = wrap_angle_deg(meas[j] - sign * scale * cmd[j] - best.offset_deg);
          }
        }
      }
  // Agreement and wrong views from the final residuals (the offset refined above).
  best.agreeing = 0;
  best.wrong.clear();
  for (int j = 0; j < n; ++j) {
    const std::optional<double>& r = best.residual_deg[idx[j]];
    if (r && std::abs(*r) <= tolerance_deg) ++best.agreeing;
    else best.wrong.push_back(idx[j]);
  }
  best.ok = 2 * best.agreeing >= n && best.agreeing >= 3;
  if (best.sign < 0 && best.scale != 1) best.convention = "the opposite sign, and steps of " + std::to_string(int(std::lround(best.scale))) + " degrees";
  else if (best.sign < 0) best.convention = "the opposite sign";
  else if (best.scale != 1) best.convention = "steps of " + std::to_string(best.scale).substr(0, 5) + " degrees, not degrees";
  return best;
}

TurntableSplit find_turntable_split(const std::vector<Eigen::Matrix4d>& poses, const std::vector<int>& order,
                                    const std::vector<double>& angles_deg, double min_misfit) {
  TurntableSplit best;
  const int n = int(order.size());
  if (n < 6 || int(angles_deg.size()) != n) return best;
  // Motions between consecutive views (a motion of about 180 degrees, e.g. from
  // the first view, has an ambiguous sense and is left out of the fit).
  const auto misfit = [&](int from, int to) {  // views order[from..to)
    std::vector<AxisMotion> ms;
    for (int k = from; k + 1 < to; ++k) {
      AxisMotion m;
      m.transform = rigid_inverse(poses[order[k]]) * poses[order[k + 1]];
      m.angle_deg = angles_deg[k + 1] - angles_deg[k];
      ms.push_back(m);
    }
    const AxisFitResult f = fit_turntable_axis(ms);
    return f.ok ? f.rms_translation : std::numeric_limits<double>::infinity();
  };
  const double whole = misfit(0, n);
  if (!std::isfinite(whole) || whole < min_misfit) return best;
  double parts = std::numeric_limits<double>::infinity();
  int split = -1;
  for (int k = 3; k + 3 <= n; ++k) {
    const double m = std::max(misfit(0, k), misfit(k, n));
    if (m < parts) parts = m, split = k;
  }
  if (split < 0 || !(whole >= 3 * parts)) return best;
  best.found = true;
  best.last_before = order[split - 1];
  best.first_after = order[split];
  best.whole_misfit = whole;
  best.parts_misfit = parts;
  return best;
}

}  // namespace station
