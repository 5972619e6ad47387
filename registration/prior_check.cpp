#include "registration/prior_check.h"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cstdio>
#include <cmath>
#include <limits>

#include "core/geometry.h"
#include "registration/axis_calibration.h"
#include "registration/icp.h"

namespace station {

namespace {
// How many more views a convention (the opposite sign, step indices) must fit than
// the angles as given (fit_angle_prior).
constexpr int kConventionMargin = 2;
}  // namespace

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
  const std::vector<double> scales = angle_scales(manifest);
  const std::vector<double> signs = known ? std::vector<double>{1.0, -1.0} : std::vector<double>{1.0};
  // The best hypothesis, and the best with the angles as given (sign +1, degrees).
  AnglePriorFit given = best;
  double best_cost = 1e300, given_cost = 1e300;
  for (std::size_t mi = 0; mi < measured.size(); ++mi)
    for (double scale : scales)
      for (double sign : signs) {
        const std::vector<double>& meas = measured[mi];
        const bool as_given = sign == 1 && scale == 1;
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
          const auto take = [&](AnglePriorFit& f, double& f_cost) {
            if (!(cost < f_cost - 1e-9)) return;
            f_cost = cost;
            f.sign = sign;
            f.scale = scale;
            f.offset_deg = wrap_angle_deg(b + mean / std::max(agree, 1));
            for (int j = 0; j < n; ++j)
              f.residual_deg[idx[j]] = wrap_angle_deg(meas[j] - sign * scale * cmd[j] - f.offset_deg);
          };
          take(best, best_cost);
          if (as_given) take(given, given_cost);
        }
      }
  // Agreement and wrong views from the final residuals (the offset refined above).
  const auto finish = [&](AnglePriorFit& f) {
    f.agreeing = 0;
    f.wrong.clear();
    for (int j = 0; j < n; ++j) {
      const std::optional<double>& r = f.residual_deg[idx[j]];
      if (r && std::abs(*r) <= tolerance_deg) ++f.agreeing;
      else f.wrong.push_back(idx[j]);
    }
    f.ok = 2 * f.agreeing >= n && f.agreeing >= 3;
    f.convention = convention_name(f.sign, f.scale);
  };
  finish(best);
  finish(given);
  // A convention (every angle as given wrong) must fit most views, and clearly more
  // than the angles as given: poses that are themselves wrong (a near-symmetric object
  // registered without angles, views on turned twins) fit some convention by chance
  // (the coloured Rubik's cube, the session: the opposite sign fitted 3 of 6
  // angles, and the run with it, kept, put four views 180 deg off).
  // (Every view fitting the convention is taken whatever the margin: with three views
  // at 0, 90 and 180 degrees of the opposite sign, two fit as given too.)
  if (!best.convention.empty() && !(2 * best.agreeing > n && (best.agreeing == n ||
                                                             best.agreeing >= given.agreeing + kConventionMargin)))
    return given;
  return best;
}

std::vector<double> angle_scales(const SessionManifest& manifest) {
  // Degrees, or step indices (all of the session's angles integers below 64:
  // 360 / (largest + 1) for indices from 0, 360 / largest from 1).
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
  return scales;
}

std::string convention_name(double sign, double scale) {
  // The step as a person writes it: 45, 51.43 (360 / 7), 22.5.
  char step[32];
  std::snprintf(step, sizeof step, "%.2f", scale);
  std::string text = step;
  while (text.find('.') != std::string::npos && (text.back() == '0' || text.back() == '.')) text.pop_back();
  if (sign < 0 && scale != 1) return "the opposite sign, and steps of " + text + " degrees";
  if (sign < 0) return "the opposite sign";
  if (scale != 1) return "steps of " + text + " degrees, not degrees";
  return "";
}

TurntableSplit find_turntable_split(const std::vector<Eigen::Matrix4d>& poses, const std::vector<int>& order,
                                    const std::vector<double>& angles_deg, double min_misfit, int max_runs) {
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
  // Two runs first; three (knocked twice) only where no two explain the motions.
  double parts = std::numeric_limits<double>::infinity();
  std::vector<int> splits;
  for (int k = 3; k + 3 <= n; ++k) {
    const double m = std::max(misfit(0, k), misfit(k, n));
    if (m < parts) parts = m, splits = {k};
  }
  if (!(whole >= 3 * parts)) {
    // The three-run search fits O(n^2) runs: only for sessions of a usual size (a
    // turntable session of 3600 views would take millions of fits).
    constexpr int kMaxViewsForThreeRuns = 72;
    if (max_runs < 3 || n > kMaxViewsForThreeRuns) return best;
    // Each run's misfit computed once per (from, to).
    std::vector<double> cache(std::size_t(n + 1) * std::size_t(n + 1), -1);
    const auto part = [&](int from, int to) {
      double& c = cache[std::size_t(from) * std::size_t(n + 1) + std::size_t(to)];
      if (c < 0) c = misfit(from, to);
      return c;
    };
    double parts3 = std::numeric_limits<double>::infinity();
    std::vector<int> splits3;
    for (int k = 3; k + 6 <= n; ++k)
      for (int l = k + 3; l + 3 <= n; ++l) {
        const double m = std::max({part(0, k), part(k, l), part(l, n)});
        if (m < parts3) parts3 = m, splits3 = {k, l};
      }
    if (!(whole >= 3 * parts3)) return best;
    parts = parts3;
    splits = splits3;
  }
  best.found = true;
  best.last_before = order[splits.front() - 1];
  best.first_after = order[splits.front()];
  for (int k : splits) {
    best.run_starts.push_back(order[k]);
    best.run_ends.push_back(order[k - 1]);
  }
  best.whole_misfit = whole;
  best.parts_misfit = parts;
  return best;
}

Eigen::Matrix4d screw_power(const Eigen::Matrix4d& T, double s) {
  const Eigen::AngleAxisd aa(Eigen::Matrix3d(T.block<3, 3>(0, 0)));
  const Vec3d d = aa.axis().normalized();
  const Vec3d t = T.block<3, 1>(0, 3);
  if (std::abs(aa.angle()) < 1e-9) {  // no turn: a slide
    Eigen::Matrix4d out = Eigen::Matrix4d::Identity();
    out.block<3, 1>(0, 3) = s * t;
    return out;
  }
  const Vec3d along = t.dot(d) * d, across = t - along;
  // A point of the axis line: t_across = (I - R) p, p across the axis.
  const double half = 0.5 * aa.angle();
  const Vec3d p = 0.5 * (across + std::cos(half) / std::sin(half) * d.cross(across));
  Eigen::Matrix4d out = Eigen::Matrix4d::Identity();
  const Eigen::Matrix3d Rs = Eigen::AngleAxisd(s * aa.angle(), d).toRotationMatrix();
  out.block<3, 3>(0, 0) = Rs;
  out.block<3, 1>(0, 3) = (Eigen::Matrix3d::Identity() - Rs) * p + s * along;
  return out;
}

std::optional<Eigen::Matrix4d> pose_from_neighbours_angles(const std::vector<Eigen::Matrix4d>& poses,
                                                            const std::vector<bool>& registered,
                                                            const SessionManifest& m, int j, double scale,
                                                            double tol_deg, double diagonal) {
  const std::size_t n = m.views.size();
  if (poses.size() != n || registered.size() != n || j < 0 || std::size_t(j) >= n || !m.views[std::size_t(j)].angle_deg)
    return std::nullopt;
  const auto usable = [&](int i) { return registered[std::size_t(i)] && m.views[std::size_t(i)].angle_deg.has_value(); };
  const double min_turn = std::max(15.0, 2 * tol_deg), max_turn = 180.0 - 2 * tol_deg;
  // The turn from a to b as its angles say (scaled, wrapped), when it is one that
  // tells its sense; and the axis the poses turn about, signed so that it is the
  // table's direction for a motion that turns as the angles say (P_a^-1 P_b turns
  // by minus the angle about it), when they turn by that much with no slide.
  struct Turn {
    double commanded = 0;
    Eigen::Matrix4d T;
    Vec3d sense;
  };
  const auto turn = [&](int a, int b) -> std::optional<Turn> {
    const double d = wrap_angle_deg(scale * (*m.views[std::size_t(b)].angle_deg - *m.views[std::size_t(a)].angle_deg));
    if (std::abs(d) < min_turn || std::abs(d) > max_turn) return std::nullopt;
    const Eigen::Matrix4d T = rigid_inverse(poses[std::size_t(a)]) * poses[std::size_t(b)];
    if (std::abs(rotation_angle_deg(T) - std::abs(d)) > tol_deg) return std::nullopt;
    const Eigen::AngleAxisd aa(Eigen::Matrix3d(T.block<3, 3>(0, 0)));
    if (std::abs(T.block<3, 1>(0, 3).dot(aa.axis())) > 0.02 * diagonal) return std::nullopt;
    return Turn{d, T, (d > 0 ? -1.0 : 1.0) * aa.axis().normalized()};
  };
  std::vector<int> below, above;
  for (int i = j - 1; i >= 0 && below.size() < 2; --i)
    if (usable(i)) below.push_back(i);
  for (int i = j + 1; i < int(n) && above.size() < 2; ++i)
    if (usable(i)) above.push_back(i);
  for (int k : below)
    for (int l : above) {
      const std::optional<Turn> kl = turn(k, l);
      if (!kl) continue;
      const double dj = wrap_angle_deg(scale * (*m.views[std::size_t(j)].angle_deg - *m.views[std::size_t(k)].angle_deg));
      const double f = dj / kl->commanded;
      if (!(f > 0 && f < 1)) continue;
      // The sense, from the pair beside this one: the nearest usable view before k
      // with k, else l with the nearest after it, when it turns as its angles say.
      // Within one pass every pair turns about the same line, so its direction must
      // agree within the tolerance (a move that tipped the object fails too).
      std::optional<Turn> beside;
      for (int i = k - 1; i >= 0; --i)
        if (usable(i)) {
          beside = turn(i, k);
          break;
        }
      if (!beside)
        for (int i = l + 1; i < int(n); ++i)
          if (usable(i)) {
            beside = turn(l, i);
            break;
          }
      if (beside && kl->sense.dot(beside->sense) < std::cos(tol_deg * M_PI / 180)) continue;
      return Eigen::Matrix4d(poses[std::size_t(k)] * screw_power(kl->T, f));
    }
  return std::nullopt;
}

std::vector<std::vector<int>> agreeing_runs(const AnglePriorFit& fit, const SessionManifest& manifest,
                                            double tolerance_deg, double min_turn_deg) {
  std::vector<std::vector<int>> runs;
  std::vector<int> run;
  std::size_t with_residual = 0, in_runs = 0;
  const auto close_run = [&] {
    if (run.size() >= 3) {
      double lo = 0, hi = 0;  // the angles' span, from the first, unwrapped along the run
      const double a0 = *manifest.views[std::size_t(run.front())].angle_deg;
      for (int i : run) {
        const double a = wrap_angle_deg(*manifest.views[std::size_t(i)].angle_deg - a0);
        lo = std::min(lo, a), hi = std::max(hi, a);
      }
      if (hi - lo >= min_turn_deg) runs.push_back(run), in_runs += run.size();
    }
    run.clear();
  };
  for (std::size_t k = 0; k < manifest.views.size(); ++k) {
    if (!manifest.views[k].angle_deg || !fit.residual_deg[k]) continue;
    ++with_residual;
    if (!run.empty() && std::abs(wrap_angle_deg(*fit.residual_deg[k] - *fit.residual_deg[std::size_t(run.front())])) >
                            tolerance_deg)
      close_run();
    run.push_back(int(k));
  }
  close_run();
  if (2 * in_runs < with_residual) runs.clear();
  return runs;
}

}  // namespace station
