#include "sim/bench.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>

#include "core/error.h"

namespace station::sim {

// ---- bench -------------------------------------------------------------------

double Bench::angle_deg() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return angle_deg_;
}

void Bench::set_angle_deg(double degrees) {
  std::lock_guard<std::mutex> lock(mutex_);
  angle_deg_ = degrees;
  ++moves_;
}

std::uint64_t Bench::moves() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return moves_;
}

std::shared_ptr<Bench> bench_of(DeviceContext& context) {
  std::shared_ptr<void>& slot = context.shared[kBenchKey];
  if (!slot) slot = std::make_shared<Bench>();
  return std::static_pointer_cast<Bench>(slot);
}

// ---- random numbers ------------------------------------------------------------

namespace {

// SplitMix64 finaliser: a bijective avalanche mix, enough for noise.
inline std::uint64_t mix64(std::uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

inline std::uint64_t counter_hash(std::uint64_t seed, std::uint64_t frame, std::uint64_t pixel,
                                  std::uint32_t stream) {
  return mix64(mix64(mix64(mix64(seed) ^ frame) ^ pixel) ^ stream);
}

}  // namespace

double uniform01(std::uint64_t seed, std::uint64_t frame, std::uint64_t pixel, std::uint32_t stream) {
  return double(counter_hash(seed, frame, pixel, stream) >> 11) * 0x1.0p-53;
}

double gaussian(std::uint64_t seed, std::uint64_t frame, std::uint64_t pixel, std::uint32_t stream) {
  const double u1 = 1.0 - uniform01(seed, frame, pixel, stream);  // (0, 1]: log is finite
  const double u2 = uniform01(seed, frame, pixel, stream + 1);
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * M_PI * u2);
}

Eigen::Matrix4d rotate_z_deg(double degrees) {
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.topLeftCorner<3, 3>() = Eigen::AngleAxisd(degrees * M_PI / 180.0, Vec3d::UnitZ()).matrix();
  return T;
}

// ---- scene ---------------------------------------------------------------------

namespace {

constexpr Rgb kDiskColour{128, 128, 128};
constexpr Rgb kDefaultColour{200, 200, 200};  // light grey for meshes without colour

// Scales the mesh into the object frame and moves it into the placed frame.
TexturedMesh place(TexturedMesh m, const SyntheticParams& params, Vec3d& offset) {
  Aabb box;
  for (Vec3f& v : m.mesh.vertices) {
    v = (v.cast<double>() * params.scale).cast<float>();
    box.extend(v);
  }
  offset.setZero();
  if (params.center && box.valid()) {
    const Vec3f c = box.center();
    offset = Vec3d(-double(c.x()), -double(c.y()), -double(box.min.z()));
    for (Vec3f& v : m.mesh.vertices) v = (v.cast<double>() + offset).cast<float>();
  }
  return m;
}

}  // namespace

Scene::Scene(TexturedMesh mesh, Texture texture, const SyntheticParams& params)
    : mesh_(place(std::move(mesh), params, offset_)),
      texture_(std::move(texture)),
      bvh_(mesh_.mesh),
      params_(params) {
  // UVs only count when there is one per face corner.
  if (mesh_.corner_uv.size() != 3 * mesh_.mesh.faces.size()) mesh_.corner_uv.clear();
  if (mesh_.mesh.colours.size() != mesh_.mesh.vertices.size()) mesh_.mesh.colours.clear();
  float zmin = std::numeric_limits<float>::max(), zmax = -zmin;
  for (const Face& f : mesh_.mesh.faces)
    for (int k = 0; k < 3; ++k) {
      zmin = std::min(zmin, mesh_.mesh.vertices[f[k]].z());
      zmax = std::max(zmax, mesh_.mesh.vertices[f[k]].z());
    }
  mid_height_ = 0.5 * (double(zmin) + double(zmax));
  set_params(params);
}

void Scene::set_params(const SyntheticParams& params) {
  params_ = params;
  table_from_camera_ =
      camera_in_table(params, params.target_height >= 0 ? params.target_height : mid_height_);
}

Eigen::Matrix4d camera_in_table(const SyntheticParams& params, double target_height) {
  const double elevation = params.elevation_deg * M_PI / 180.0;
  const Vec3d centre(params.distance, 0, target_height + params.distance * std::tan(elevation));
  const Vec3d z = (Vec3d(0, 0, target_height) - centre).normalized();
  Vec3d x = z.cross(Vec3d::UnitZ());
  if (x.norm() < 1e-12) x = Vec3d::UnitY();  // looking straight down or up
  x.normalize();
  const Vec3d y = z.cross(x);  // completes x right, y down, z forward
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  T.block<3, 1>(0, 0) = x;
  T.block<3, 1>(0, 1) = y;
  T.block<3, 1>(0, 2) = z;
  T.block<3, 1>(0, 3) = centre;
  return T;
}

TurntableAxis axis_in_camera(const Eigen::Matrix4d& table_from_camera) {
  const Eigen::Matrix3d r = table_from_camera.topLeftCorner<3, 3>();
  const Vec3d c = table_from_camera.topRightCorner<3, 1>();
  TurntableAxis a;
  a.point = r.transpose() * (Vec3d::Zero() - c);
  a.direction = r.transpose() * Vec3d::UnitZ();
  return a;
}

Intrinsics synthetic_intrinsics(const SyntheticParams& params) {
  Intrinsics k;
  k.width = params.width;
  k.height = params.height;
  k.fx = k.fy = params.width / 2.0 / std::tan(params.fov_deg * M_PI / 360.0);
  k.cx = (params.width - 1) / 2.0;
  k.cy = (params.height - 1) / 2.0;
  return k;
}

TurntableAxis Scene::axis() const { return axis_in_camera(table_from_camera_); }

Eigen::Matrix4d Scene::object_from_camera(double angle_deg) const {
  Eigen::Matrix4d object_from_placed = Eigen::Matrix4d::Identity();
  object_from_placed.topRightCorner<3, 1>() = -offset_;
  return object_from_placed * rotate_z_deg(-angle_deg) * table_from_camera_;
}

Frame Scene::render(double angle_deg, std::uint64_t frame_index) const {
  const SyntheticParams& p = params_;
  const Intrinsics k = intrinsics();
  const int w = p.width, h = p.height;
  Frame frame;
  frame.intrinsics = k;
  frame.colour_intrinsics = k;
  frame.depth.assign(std::size_t(w) * h, 0.f);
  if (p.colour) frame.colour.assign(std::size_t(w) * h * 3, 0);
  frame.reference_pose = object_from_camera(angle_deg);

  // Cast in the placed frame: the object stays put and the camera turns the
  // other way, so the BVH is built once. The transform is rigid and the camera
  // ray has unit z, so the ray parameter t is the depth along the optical axis.
  const Eigen::Matrix4d placed_from_camera = rotate_z_deg(-angle_deg) * table_from_camera_;
  const Eigen::Matrix3d rot = placed_from_camera.topLeftCorner<3, 3>();
  const Vec3d origin = placed_from_camera.topRightCorner<3, 1>();
  const double disk_r2 = p.table_radius * p.table_radius;
  const std::uint64_t seed = p.seed;
  const bool use_texture = !texture_.empty() && !mesh_.corner_uv.empty();
  const bool use_vertex_colours = mesh_.mesh.has_colours();

  tbb::parallel_for(tbb::blocked_range<int>(0, h), [&](const tbb::blocked_range<int>& rows) {
    for (int row = rows.begin(); row != rows.end(); ++row) {
      for (int col = 0; col < w; ++col) {
        const std::size_t pixel = std::size_t(row) * w + col;
        const Vec3d dir = rot * Vec3d((col - k.cx) / k.fx, (row - k.cy) / k.fy, 1.0);
        // The disk is the plane z = 0 of the placed (and table) frame.
        double t_disk = std::numeric_limits<double>::infinity();
        if (dir.z() != 0 && p.table_radius > 0) {
          const double t = -origin.z() / dir.z();
          if (t > 0) {
            const Vec3d q = origin + t * dir;
            if (q.x() * q.x() + q.y() * q.y() <= disk_r2) t_disk = t;
          }
        }
        // The disk bounds the search: whatever lies behind it stays hidden.
        const std::optional<RayHit> hit = bvh_.intersect({origin, dir, 0.0, t_disk});
        const double t = hit ? hit->t : t_disk;
        if (!std::isfinite(t)) continue;  // background: no return, black

        if (t <= p.max_range) {
          const bool dropped = p.dropout > 0 && uniform01(seed, frame_index, pixel, 0) < p.dropout;
          if (!dropped) {
            const double sigma = p.noise + p.noise_quadratic * t * t;
            const double z = sigma > 0 ? t + sigma * gaussian(seed, frame_index, pixel, 1) : t;
            frame.depth[pixel] = z > 0 ? float(z) : 0.f;
          }
        }
        if (!p.colour) continue;
        Rgb c = kDiskColour;
        if (hit) {
          c = use_texture || use_vertex_colours
                  ? surface_colour(mesh_, texture_, hit->face, hit->u, hit->v)
                  : kDefaultColour;
        }
        std::uint8_t* out = &frame.colour[pixel * 3];
        const std::uint8_t channels[3] = {c.r, c.g, c.b};
        for (int ch = 0; ch < 3; ++ch) {
          double value = channels[ch];
          if (p.colour_noise > 0)
            value += p.colour_noise * gaussian(seed, frame_index, pixel, 3 + 2 * ch);
          out[ch] = std::uint8_t(std::clamp(std::lround(value), 0L, 255L));
        }
      }
    }
  });
  return frame;
}

}  // namespace station::sim
