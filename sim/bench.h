#pragma once
// Private to sim/: the virtual bench shared by the simulated devices, and the
// ray-casting renderer behind "sim:synthetic". Tests include it to reach the
// pieces (texture sampling, the per-pixel random numbers, the scene) directly.
//
// Frames (all right-handed, metres):
//  - object frame: the mesh file's own frame, scaled by `scale` (so with
//    scale != 1 it is the *scaled* file frame). Reference poses map into it.
//  - placed frame: the object as it stands on the table at angle 0. Without
//    `center` it is the object frame; with it, p_placed = p_object + offset
//    (xy bbox centre on the axis, lowest point on the table top).
//  - table frame: origin on the axis at the table top, z up along the axis.
//    At table angle a (degrees, counter-clockwise seen from above)
//    p_table = Rz(a) p_placed. The camera stands on the table frame's +x side,
//    so the table frame at angle 0 is the capture loop's turntable frame
//    (capture/capture.h: x towards the scanner).
//  - camera frame: x right, y down, z forward (the optical axis).
#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "core/bvh.h"
#include "core/io.h"
#include "core/texture.h"
#include "drivers/registry.h"
#include "sim/sim.h"

namespace station::sim {

/// Key of the bench in DeviceContext::shared.
inline constexpr const char* kBenchKey = "sim.bench";

/// What the simulated devices of one registry share: the turntable angle. The
/// scanner owns its mesh; a turntable without a scanner just keeps its angle.
class Bench {
 public:
  /// Table angle in degrees, [0, 360).
  double angle_deg() const;
  /// Sets the angle (already wrapped and quantised) and counts a move.
  void set_angle_deg(double degrees);
  /// Number of home/rotate_to calls so far (the replay scanner follows the
  /// table once it has moved).
  std::uint64_t moves() const;

 private:
  mutable std::mutex mutex_;
  double angle_deg_ = 0;
  std::uint64_t moves_ = 0;
};

/// The bench of a context, created on first use (by whichever sim device comes first).
std::shared_ptr<Bench> bench_of(DeviceContext& context);

/// Counter-based random numbers: a pure function of (seed, frame, pixel,
/// stream), so frames do not depend on thread count or scheduling.
double uniform01(std::uint64_t seed, std::uint64_t frame, std::uint64_t pixel, std::uint32_t stream);
/// Standard normal sample (Box-Muller over streams `stream` and `stream + 1`).
double gaussian(std::uint64_t seed, std::uint64_t frame, std::uint64_t pixel, std::uint32_t stream);

/// Pinhole intrinsics of the synthetic camera: fx = fy = width / 2 / tan(fov / 2);
/// principal point at the image centre, cx = (width - 1) / 2, cy = (height - 1) / 2,
/// with pixel centres at integer coordinates (pixel (u, v) sees the camera-frame
/// ray ((u - cx) / fx, (v - cy) / fy, 1)).
Intrinsics synthetic_intrinsics(const SyntheticParams& params);

/// Camera pose in the table frame (p_table = T * p_camera): on the +x side,
/// `distance` from the axis horizontally, pitched down by `elevation_deg`, looking
/// at (0, 0, target_height) on the axis (so its centre is at height
/// target_height + distance * tan(elevation)).
Eigen::Matrix4d camera_in_table(const SyntheticParams& params, double target_height);
/// The turntable axis (table frame z through the origin) in the camera frame.
TurntableAxis axis_in_camera(const Eigen::Matrix4d& table_from_camera);

/// Rotation about z by `degrees` as a 4x4 transform.
Eigen::Matrix4d rotate_z_deg(double degrees);

/// The placed object, the turntable disk and the camera; renders frames. Built
/// once per mesh; render() is const and runs the pixels in parallel (TBB).
class Scene {
 public:
  /// Places `mesh` (scale, centring from `params`) and builds its BVH.
  /// InvalidInput when the mesh has no faces or bad indices.
  Scene(TexturedMesh mesh, Texture texture, const SyntheticParams& params);

  /// Re-derives the camera from params (mesh placement is fixed at construction:
  /// mesh, scale and center are ignored here).
  void set_params(const SyntheticParams& params);
  const SyntheticParams& params() const { return params_; }

  /// synthetic_intrinsics(params()).
  Intrinsics intrinsics() const { return synthetic_intrinsics(params_); }
  /// The turntable axis in the camera frame.
  TurntableAxis axis() const;
  /// Camera pose in the table frame: p_table = table_from_camera * p_camera.
  const Eigen::Matrix4d& table_from_camera() const { return table_from_camera_; }
  /// Translation taking object-frame points to the placed frame.
  const Vec3d& placement_offset() const { return offset_; }
  /// Ground truth: p_object = object_from_camera(a) * p_camera at table angle a.
  Eigen::Matrix4d object_from_camera(double angle_deg) const;
  /// The placed mesh (placed frame).
  const Mesh& placed_mesh() const { return mesh_.mesh; }

  /// Renders the view at table angle `angle_deg` (depth, colour when enabled,
  /// intrinsics, reference pose). `frame_index` feeds the noise; timestamp is left 0.
  /// Colour: the texture through the corner UVs when the mesh has both, else
  /// interpolated vertex colours, else light grey (200); the disk is grey (128),
  /// background black. Depth and colour see the same surfaces (max_range and
  /// dropouts only blank depth).
  Frame render(double angle_deg, std::uint64_t frame_index) const;

 private:
  Vec3d offset_ = Vec3d::Zero();  // before mesh_: placing the mesh sets it
  TexturedMesh mesh_;              // placed frame
  Texture texture_;
  TriangleBvh bvh_;
  SyntheticParams params_;
  double mid_height_ = 0;
  Eigen::Matrix4d table_from_camera_ = Eigen::Matrix4d::Identity();
};

// ---- option parsing shared by the sim devices --------------------------------
// Each throws DeviceError("URI: option 'KEY': ...") naming the URI and the key.

double parse_double_option(const std::string& uri, const std::string& key, const std::string& value);
long long parse_int_option(const std::string& uri, const std::string& key, const std::string& value);
/// 1/0, true/false, yes/no, on/off (case-insensitive).
bool parse_bool_option(const std::string& uri, const std::string& key, const std::string& value);
/// DeviceError("URI: option 'KEY': VALUE: WHY") unless `ok`.
void require_option(bool ok, const std::string& uri, const std::string& key,
                    const std::string& value, const std::string& why);
/// DeviceError("URI: unknown option 'KEY' (known: ...)").
[[noreturn]] void unknown_option(const std::string& uri, const std::string& key,
                                 const std::string& known);

// ---- device factories (registered by register_sim_devices) -------------------

std::unique_ptr<Scanner> make_synthetic_scanner(const DeviceUri& uri, DeviceContext& context);
std::unique_ptr<Scanner> make_replay_scanner(const DeviceUri& uri, DeviceContext& context);
std::unique_ptr<Turntable> make_sim_turntable(const DeviceUri& uri, DeviceContext& context);

}  // namespace station::sim
