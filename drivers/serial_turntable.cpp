#include "drivers/serial_turntable.h"

#include <cmath>
#include <cstdlib>

#include "core/error.h"

namespace station {

double StepperConfig::quantize_degrees(double degrees) const {
  const double per_rev = static_cast<double>(microsteps_per_revolution());
  return std::round(degrees * per_rev / 360.0) * 360.0 / per_rev;
}

double wrap_degrees(double degrees) {
  double a = std::fmod(degrees, 360.0);
  if (a < 0) a += 360.0;
  if (a >= 360.0) a -= 360.0;
  return a;
}


StepperConfig stepper_config_from_options(const DeviceOptions& options, const std::string& uri) {
  StepperConfig c;
  if (!options.count("steps"))
    throw DeviceError(uri +
                      ": option 'steps' (full motor steps per table revolution) is required; "
                      "set it in the profile or the URI, e.g. ?steps=200&microsteps=16");
  c.steps = option_integer(options, "steps", 0, 1, 10000000, uri);
  c.microsteps = option_integer(options, "microsteps", 1, 1, 256, uri);
  const auto d = options.find("direction");
  if (d != options.end()) {
    if (d->second == "ccw" || d->second == "1" || d->second == "+1")
      c.direction = 1;
    else if (d->second == "cw" || d->second == "-1")
      c.direction = -1;
    else
      throw DeviceError(uri + ": option direction=" + d->second + ": expected ccw or cw (1 or -1)");
  }
  return c;
}

}  // namespace station
