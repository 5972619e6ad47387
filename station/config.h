#pragma once
// Station profiles (config/*.yaml). Every key is documented in config/default.yaml.
#include <filesystem>
#include <string>

#include "capture/capture.h"
#include "drivers/scanner.h"

namespace station {

struct StationConfig {
  std::string scanner_uri = "sim:synthetic";
  DeviceOptions scanner_options;  ///< merged into the scanner URI's query
  std::string turntable_uri = "sim:turntable";
  DeviceOptions turntable_options;
  CaptureParams capture;
  int threads = 0;  ///< 0 = all cores
  std::filesystem::path source;  ///< the profile file, empty for built-in defaults
};

/// Reads a profile. Relative paths in the `mesh` and `session` device options
/// resolve against the profile's folder. FormatError("FILE: key: problem").
StationConfig load_config(const std::filesystem::path& path);

/// The profile used when --config is not given: config/default.yaml of the
/// source tree the binary was built from, if it is there; else built-in defaults.
std::filesystem::path default_config_path();

/// "scheme:path?a=1" + {b: 2} -> "scheme:path?a=1&b=2" (options override the URI's).
std::string compose_uri(const std::string& uri, const DeviceOptions& options);

}  // namespace station
