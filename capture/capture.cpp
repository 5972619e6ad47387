#include "capture/capture.h"

#include <Eigen/Geometry>
#include <chrono>
#include <cmath>
#include <thread>

#include "core/error.h"
#include "core/threads.h"

namespace station {
namespace {

double wrap_degrees(double a) {
  double w = std::fmod(a, 360.0);
  if (w < 0) w += 360.0;
  return w;
}

double plan_step(const CaptureParams& p) { return p.step_deg != 0 ? p.step_deg : 360.0 / p.views; }

}  // namespace

Cloud frame_to_cloud(const Frame& frame, double max_jump) {
  Cloud out;
  if (!frame.has_depth()) {
    out.points.reserve(frame.points.size());
    const bool n = frame.points.has_normals(), c = frame.points.has_colours();
    for (std::size_t i = 0; i < frame.points.size(); ++i) {
      const Vec3f& p = frame.points.points[i];
      if (!p.allFinite()) continue;
      out.points.push_back(p);
      if (n) out.normals.push_back(frame.points.normals[i]);
      if (c) out.colours.push_back(frame.points.colours[i]);
    }
    return out;
  }
  const Intrinsics& K = frame.intrinsics;
  if (!K.valid()) throw InvalidInput("frame: depth image without valid intrinsics");
  if (frame.depth.size() != std::size_t(K.width) * K.height)
    throw InvalidInput("frame: depth image size does not match its intrinsics");
  const int w = K.width, h = K.height;
  auto depth_at = [&](int u, int v) -> float {
    if (u < 0 || v < 0 || u >= w || v >= h) return 0.f;
    float d = frame.depth[std::size_t(v) * w + u];
    return std::isfinite(d) && d > 0 ? d : 0.f;
  };
  // Rays of the pixels, undistorted once per frame when the lens has distortion
  // (the depth is along the optical axis: point = (x d, y d, d)).
  std::vector<Eigen::Vector2f> rays;
  if (K.distorted()) {
    rays.resize(std::size_t(w) * h);
    for (int v = 0; v < h; ++v)
      for (int u = 0; u < w; ++u) rays[std::size_t(v) * w + u] = pixel_to_ray(K, u, v).cast<float>();
  }
  auto point_at = [&](int u, int v, float d) {
    if (!rays.empty()) {
      const Eigen::Vector2f& r = rays[std::size_t(v) * w + u];
      return Vec3f(r.x() * d, r.y() * d, d);
    }
    return Vec3f(float((u - K.cx) * d / K.fx), float((v - K.cy) * d / K.fy), d);
  };
  // Colour is used when the image is registered pixel for pixel with the depth.
  const Intrinsics& C = frame.colour_intrinsics;
  const bool colour = frame.has_colour() && C.width == w && C.height == h &&
                      frame.colour.size() == std::size_t(w) * h * 3;
  for (int v = 0; v < h; ++v) {
    for (int u = 0; u < w; ++u) {
      const float d = depth_at(u, v);
      if (d <= 0) continue;
      const Vec3f p = point_at(u, v, d);
      // Central differences where both neighbours are on the same surface,
      // one-sided otherwise; none across a silhouette.
      auto neighbour = [&](int du, int dv, Vec3f& q) {
        const float dn = depth_at(u + du, v + dv);
        if (dn <= 0 || std::abs(dn - d) > max_jump * d) return false;
        q = point_at(u + du, v + dv, dn);
        return true;
      };
      Vec3f l = Vec3f::Zero(), r = l, t = l, b = l;
      const bool hl = neighbour(-1, 0, l), hr = neighbour(1, 0, r);
      const bool ht = neighbour(0, -1, t), hb = neighbour(0, 1, b);
      Vec3f du = hl && hr ? Vec3f(r - l) : hr ? Vec3f(r - p) : hl ? Vec3f(p - l) : Vec3f::Zero();
      Vec3f dv = ht && hb ? Vec3f(b - t) : hb ? Vec3f(b - p) : ht ? Vec3f(p - t) : Vec3f::Zero();
      Vec3f n = du.cross(dv);
      if (n.squaredNorm() > 0) {
        n.normalize();
        if (n.dot(p) > 0) n = -n;  // towards the sensor at the origin
      } else {
        n = -p.normalized();
      }
      out.points.push_back(p);
      out.normals.push_back(n);
      if (colour) {
        const std::size_t k = (std::size_t(v) * w + u) * 3;
        out.colours.push_back({frame.colour[k], frame.colour[k + 1], frame.colour[k + 2]});
      }
    }
  }
  return out;
}


Cloud crop_to_volume(const Cloud& cloud, const TurntableAxis& axis, const WorkingVolume& vol) {
  const Eigen::Matrix4f T = table_from_scanner(axis).cast<float>();
  const Eigen::Matrix3f R = T.block<3, 3>(0, 0);
  const Vec3f t = T.block<3, 1>(0, 3);
  const float r2 = float(vol.radius * vol.radius);
  Cloud out;
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    const Vec3f q = R * cloud.points[i] + t;
    if (q.z() < vol.table_clearance || q.z() > vol.max_height) continue;
    if (q.head<2>().squaredNorm() > r2) continue;
    out.points.push_back(cloud.points[i]);
    if (cloud.has_normals()) out.normals.push_back(cloud.normals[i]);
    if (cloud.has_colours()) out.colours.push_back(cloud.colours[i]);
  }
  return out;
}

CaptureResult run_capture(Scanner& scanner, Turntable& turntable, Session& session,
                          const CaptureParams& params,
                          const std::function<void(const CaptureProgress&)>& progress,
                          const std::atomic<bool>* stop) {
  if (params.views < 1) throw InvalidInput("capture: views must be at least 1");
  const auto t0 = std::chrono::steady_clock::now();
  const double step = plan_step(params);
  SessionManifest& m = session.mutable_manifest();
  CaptureResult result;
  result.resumed_from = int(m.views.size());
  if (result.resumed_from > 0) {
    // A resumed scan continues its own recorded plan.
    if (m.planned_views != params.views || std::abs(m.start_deg - params.start_deg) > 1e-9 ||
        std::abs(m.step_deg - step) > 1e-9)
      throw InvalidInput(session.dir().string() + ": the session was recorded with " +
                         std::to_string(m.planned_views) + " views from " +
                         std::to_string(m.start_deg) + " deg in steps of " +
                         std::to_string(m.step_deg) + " deg; resume with the same plan");
  } else {
    m.planned_views = params.views;
    m.start_deg = params.start_deg;
    m.step_deg = step;
  }
  const ScannerCapabilities caps = scanner.capabilities();
  std::optional<TurntableAxis> axis = params.axis ? params.axis : caps.axis;
  if (axis) m.axis = axis;
  if (caps.intrinsics.valid()) m.intrinsics = caps.intrinsics;
  if (m.scanner.empty()) m.scanner = scanner.uri();
  if (m.turntable.empty()) m.turntable = turntable.uri();
  session.save();

  if (result.resumed_from == 0) turntable.home();
  else scanner.resume_at(std::uint64_t(result.resumed_from));
  for (int k = result.resumed_from; k < params.views; ++k) {
    if (stop && stop->load()) {
      result.interrupted = true;
      break;
    }
    const double angle = wrap_degrees(params.start_deg + k * step);
    turntable.rotate_to(angle);
    if (params.settle_s > 0)
      std::this_thread::sleep_for(std::chrono::duration<double>(params.settle_s));
    const Frame frame = scanner.grab();
    Cloud cloud = frame_to_cloud(frame, params.normal_max_depth_jump);
    if (params.crop && axis) cloud = crop_to_volume(cloud, *axis, params.volume);
    ViewRecord rec;
    rec.angle_deg = turntable.angle();  // what the table reports, not what was asked
    rec.reference_pose = frame.reference_pose;
    rec.timestamp = frame.timestamp > 0 ? std::optional<double>(frame.timestamp) : std::nullopt;
    // Recorded whenever its size is known, with or without a calibration for it (a
    // replayed view's image that is not the size of the session's intrinsics was dropped
    // without a word).
    const int cw = frame.colour_intrinsics.width, ch = frame.colour_intrinsics.height;
    const bool colour_image = frame.has_colour() && cw > 0 && ch > 0;
    session.add_view(cloud, rec, colour_image ? frame.colour : std::vector<std::uint8_t>{},
                     frame.colour_intrinsics.width, frame.colour_intrinsics.height);
    ++result.recorded;
    result.points += cloud.size();
    if (progress) progress({k, params.views, angle, cloud.size()});
  }
  result.seconds =
      seconds_since(t0);
  return result;
}

std::string resume_hint(const Session& session, const Turntable& turntable) {
  std::string hint = "continue with: station scan --resume -o " + session.dir().string();
  if (turntable.uri().rfind("sim:", 0) != 0)
    hint += " (first turn the table back to where it stood when the scan started: its zero is "
            "wherever it stands when reopened)";
  return hint;
}

MergeResult merge_by_turntable(const Session& session) {
  const SessionManifest& m = session.manifest();
  if (!m.axis)
    throw InvalidInput(session.dir().string() +
                       ": the session has no turntable_axis; views cannot be merged by angle");
  MergeResult out;
  for (std::size_t i = 0; i < m.views.size(); ++i) {
    if (!m.views[i].angle_deg) {
      ++out.skipped_views;
      continue;
    }
    Cloud view = session.load_view(i);
    if (view.empty()) {
      ++out.skipped_views;
      continue;
    }
    transform_cloud(view, turntable_pose(*m.axis, *m.views[i].angle_deg));
    const bool n = view.has_normals() && (out.cloud.empty() || out.cloud.has_normals());
    const bool c = view.has_colours() && (out.cloud.empty() || out.cloud.has_colours());
    // Attributes survive only when every merged view carries them.
    if (!n) out.cloud.normals.clear();
    if (!c) out.cloud.colours.clear();
    out.cloud.points.insert(out.cloud.points.end(), view.points.begin(), view.points.end());
    if (n) out.cloud.normals.insert(out.cloud.normals.end(), view.normals.begin(), view.normals.end());
    if (c) out.cloud.colours.insert(out.cloud.colours.end(), view.colours.begin(), view.colours.end());
    ++out.merged_views;
  }
  return out;
}

}  // namespace station
