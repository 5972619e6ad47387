#include "drivers/options.h"

#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <sstream>

#include "core/error.h"

namespace station {

bool parse_number(const std::string& text, double& out) {
  const char* s = text.c_str();
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(s, &end);
  if (text.empty() || end != s + text.size() || errno == ERANGE || !std::isfinite(v)) return false;
  out = v;
  return true;
}

std::vector<double> option_numbers(const DeviceOptions& options, const std::string& key, int count,
                                   const std::string& what, const std::string& uri) {
  const auto it = options.find(key);
  if (it == options.end()) return {};
  std::vector<double> values;
  std::stringstream ss(it->second);
  std::string item;
  double v = 0;
  bool ok = true;
  while (ok && std::getline(ss, item, ',')) {
    ok = parse_number(item, v);
    values.push_back(v);
  }
  if (!ok || int(values.size()) != count || it->second.back() == ',')
    throw DeviceError(uri + ": option " + key + ": expected " + std::to_string(count) +
                      " comma-separated numbers (" + what + "), got '" + it->second + "'");
  return values;
}

void option_distortion(const DeviceOptions& options, const std::string& key, Intrinsics& k,
                       const std::string& uri) {
  const std::vector<double> d = option_numbers(options, key, 5, "k1,k2,p1,p2,k3", uri);
  for (std::size_t i = 0; i < d.size(); ++i) k.distortion[i] = d[i];
}

double option_number(const DeviceOptions& options, const std::string& key, double fallback,
                     double min, double max, const std::string& uri) {
  const auto it = options.find(key);
  if (it == options.end()) return fallback;
  double v = 0;
  if (!parse_number(it->second, v))
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
