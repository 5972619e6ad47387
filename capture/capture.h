#pragma once
// The capture loop: drive the turntable through N views, grab a frame at each,
// turn it into points, crop to the bench's working volume, drop the turntable
// surface, and record the view into a session. Also the turntable prior: the
// pose of each view from its angle and the calibrated axis, and the views
// merged with it (what `station scan` writes until registration refines it).
#include <atomic>
#include <functional>
#include <optional>
#include <string>

#include "capture/session.h"
#include "drivers/scanner.h"

namespace station {

/// The bench's working volume, in the turntable frame (metres): a cylinder about
/// the axis standing on the table top. Points outside are background.
struct WorkingVolume {
  double radius = 0.15;         ///< cylinder radius about the axis
  double max_height = 0.40;     ///< above the table top
  double table_clearance = 0.002;  ///< points lower than this are the turntable surface
};

struct CaptureParams {
  int views = 12;               ///< views over 360 degrees
  double start_deg = 0;         ///< angle of the first view
  double step_deg = 0;          ///< 0: 360 / views
  double settle_s = 0;          ///< wait after each rotation before grabbing
  bool crop = true;             ///< crop to the working volume (needs the axis)
  WorkingVolume volume;
  /// Bench calibration; when empty the scanner's own (the simulator's) is used.
  std::optional<TurntableAxis> axis;
  /// Depth-image normals: neighbours further apart than this ratio of the depth
  /// are a discontinuity (no normal across silhouettes).
  double normal_max_depth_jump = 0.05;
};

struct CaptureProgress {
  int view = 0;         ///< 0-based index of the view just recorded
  int total = 0;
  double angle_deg = 0;
  std::size_t points = 0;
};

struct CaptureResult {
  int recorded = 0;     ///< views grabbed in this run
  int resumed_from = 0; ///< views already in the session before this run
  std::size_t points = 0;
  double seconds = 0;
  bool interrupted = false;  ///< stopped by the stop flag; the session is resumable
};

/// Points of a frame in the scanner frame: back-projected depth pixels (with
/// normals from neighbouring pixels, oriented towards the sensor, and colours
/// when the colour image is registered), or the frame's points as they are.
/// Non-finite values are dropped.
Cloud frame_to_cloud(const Frame& frame, double normal_max_depth_jump = 0.05);

/// A depth camera's frame from two image files: 16-bit depth (PNG or TIFF; value x
/// `depth_unit` metres, 0 = no data) and 8-bit colour registered with it pixel for
/// pixel (`colour_file` empty: none). `intrinsics` hold fx, fy, cx, cy at the images'
/// size (width and height are taken from the depth image). InvalidInput naming the
/// file when one cannot be read, is not 16-bit, or differs in size.
Frame read_rgbd_frame(const std::string& depth_file, const std::string& colour_file, Intrinsics intrinsics,
                      double depth_unit = 0.001);


/// Keeps the points inside the working volume (scanner frame in and out).
Cloud crop_to_volume(const Cloud& cloud, const TurntableAxis& axis, const WorkingVolume& volume);

/// Runs (or resumes) the capture into `session`. A session already holding k
/// views continues with view k of its recorded plan (the plan in `params` must
/// match it, else InvalidInput). Every finished view is on disk before the next
/// rotation. `stop` (may be null) is polled between views: when set, returns
/// with interrupted = true. Scanner failures propagate as DeviceError after the
/// views already grabbed are safely recorded.
CaptureResult run_capture(Scanner& scanner, Turntable& turntable, Session& session,
                          const CaptureParams& params,
                          const std::function<void(const CaptureProgress&)>& progress = {},
                          const std::atomic<bool>* stop = nullptr);

/// How to go on after an interrupted capture into `session`: "continue with:
/// station scan --resume -o DIR", and for a real turntable (no end stop: reopened,
/// its zero is wherever it stands) the advice to turn it back to where it stood
/// when the scan started. The simulated turntable needs no such advice.
std::string resume_hint(const Session& session, const Turntable& turntable);

struct MergeResult {
  Cloud cloud;
  int merged_views = 0;
  int skipped_views = 0;  ///< views without a turntable angle (or with no points)
};

/// All views with a turntable angle, moved into the object frame by the
/// turntable prior. InvalidInput when the session has no turntable axis.
MergeResult merge_by_turntable(const Session& session);

}  // namespace station
