#include "drivers/options.h"

#include <cmath>
#include <cstdlib>

#include "core/error.h"

namespace station {

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

}  // namespace station
