#pragma once
// The simulated bench: a scanner and a turntable behind the same interfaces as
// real devices (drivers/scanner.h).
//
// Synthetic mode ("sim:synthetic"): a mesh (vertex colours, or an OBJ texture
// decoded with OpenCV) stands on a virtual turntable disk and is seen by a
// pinhole range camera; views are ray cast through a BVH. The turntable disk
// hides the object's underside as a real one does. Depth noise is Gaussian
// along the ray with sigma(z) = noise + noise_quadratic * z^2, plus dropouts and
// colour noise; all seeded, and keyed by the frame's number in the scan (a
// resumed scan continues at its view, Scanner::resume_at: it records the views
// an uninterrupted scan would have).
//
// Replay mode ("sim:replay?session=DIR"): a recorded session played back frame
// by frame (points in the scanner frame, colour image when recorded).
//
// The sim turntable ("sim:turntable") shares the virtual bench with the
// synthetic scanner of the same registry (DeviceContext), so rotating it turns
// the object in the next grab.
#include <memory>
#include <string>

#include "core/geometry.h"
#include "drivers/registry.h"

namespace station {

/// Synthetic scanner parameters (URI query keys in brackets). Lengths in metres.
struct SyntheticParams {
  std::string mesh;             ///< [mesh] PLY/OBJ/OFF path; OBJ textures are sampled
  double scale = 1.0;           ///< [scale] multiplies mesh coordinates (e.g. 0.001 for mm files)
  /// [center] 1: put the mesh's xy bbox centre on the axis and its lowest point on the
  /// table; 0 (default): place the mesh frame as is (origin on the axis, z=0 on the
  /// table, +z up), so the object frame of merged views is the mesh file's frame.
  bool center = false;
  int width = 640;              ///< [width] pixels
  int height = 480;             ///< [height]
  double fov_deg = 50.0;        ///< [fov_deg] horizontal field of view
  double distance = 0.45;       ///< [distance] camera centre to the turntable axis
  double elevation_deg = 20.0;  ///< [elevation_deg] camera above the table plane, looking down
  double target_height = -1;    ///< [target_height] point on the axis the camera looks at; <0: mesh mid-height
  double noise = 0.0005;        ///< [noise] depth sigma constant term
  double noise_quadratic = 0;   ///< [noise_quadratic] depth sigma growth, sigma += k z^2
  double dropout = 0.0;         ///< [dropout] probability a pixel returns nothing
  double colour_noise = 0.0;     ///< [color_noise] sigma of per-channel colour noise (0-255 units)
  double table_radius = 0.15;   ///< [table_radius] turntable disk radius (rendered grey)
  double max_range = 3.0;       ///< [max_range] beyond it: no return
  unsigned seed = 1;            ///< [seed]
  bool colour = true;            ///< [color] render a colour image
};

/// Parses the options map; DeviceError naming the key on an unknown key or bad value.
SyntheticParams synthetic_params_from_options(const DeviceOptions& options,
                                              const std::string& uri);

/// Registers "sim:synthetic", "sim:replay" (scanners) and "sim:turntable".
void register_sim_devices(DeviceRegistry& registry);

}  // namespace station
