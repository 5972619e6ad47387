// libFuzzer target: station::manifest_from_yaml (session.yaml) on arbitrary text.
// Only station::Error may escape the parser; anything else (a YAML::Exception,
// std::bad_alloc, a crash) is a finding.
#include <string>

#include "capture/session.h"
#include "core/error.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  try {
    station::manifest_from_yaml(std::string(reinterpret_cast<const char*>(data), size), "fuzz");
  } catch (const station::Error&) {
  }
  return 0;
}
