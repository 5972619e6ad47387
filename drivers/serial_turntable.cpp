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

double option_number(const DeviceOptions& options, const std::string& key, double fallback,
                     double min, double max, const std::string& uri) {
  const auto it = options.find(key);
  if (it == options.end()) return fallback;
  const char* s = it->second.c_str();
  char* end = nullptr;
  const double v = std::strtod(s, &end);
  if (it->second.empty() || *end != '\0' || !std::isfinite(v))
    throw DeviceError(uri + ": option " + key + "=" + it->second + ": not a number");
  if (v < min || v > max)
    throw DeviceError(uri + ": option " + key + "=" + it->second + ": out of range [" +
                      std::to_string(min) + ", " + std::to_string(max) + "]");
  return v;
}

int option_integer(const DeviceOptions& options, const std::string& key, int fallback, int min,
                   int max, const std::string& uri) {
  const double v = option_number(options, key, fallback, min, max, uri);
  if (v != std::floor(v))
    throw DeviceError(uri + ": option " + key + "=" + options.at(key) + ": not an integer");
  return static_cast<int>(v);
}

void reject_unknown_options(const DeviceOptions& options, const std::set<std::string>& known,
                            const std::string& uri) {
  for (const auto& [key, value] : options) {
    if (known.count(key)) continue;
    std::string list;
    for (const auto& k : known) list += (list.empty() ? "" : ", ") + k;
    throw DeviceError(uri + ": unknown option '" + key + "' (known: " + list + ")");
  }
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
