#pragma once
// Shared pieces of the serial turntable drivers (Horus, FabScan): stepper
// geometry from the profile and option parsing with clear errors.
#include <set>
#include <string>

#include "drivers/options.h"
#include "drivers/scanner.h"

namespace station {

/// Stepper geometry of a turntable. Nothing here has a built-in default for
/// `steps`: boards differ (gearing, 200 vs 400 step motors) and a wrong guess
/// silently scales every angle.
struct StepperConfig {
  int steps = 0;  ///< [steps] full motor steps per table revolution (gearing included); required
  int microsteps = 1;  ///< [microsteps] driver microstepping (1, 2, 4, 8, 16, 32...)
  /// [direction] +1 ("ccw"): a positive motor move turns the table counter-clockwise
  /// seen from above (the station's positive angle); -1 ("cw"): the motor is
  /// wired the other way round.
  int direction = 1;
  long long microsteps_per_revolution() const { return static_cast<long long>(steps) * microsteps; }
  /// Nearest reachable angle, in degrees (not wrapped).
  double quantize_degrees(double degrees) const;
};

/// Reads steps/microsteps/direction; DeviceError "URI: ..." when `steps` is
/// missing or a value is malformed.
StepperConfig stepper_config_from_options(const DeviceOptions& options, const std::string& uri);


/// Angle wrapped to [0, 360).
double wrap_degrees(double degrees);

}  // namespace station
