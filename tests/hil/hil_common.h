#pragma once
// Bench (hardware-in-the-loop) smoke tests: each probes for its device and
// skips with a message when it is absent; HIL_REQUIRE=1 turns absence into a
// failure. See docs/devices.md for the environment variables.
#include <gtest/gtest.h>

#include <cstdlib>
#include <string>

namespace station::hil {

inline std::string env(const char* name, const std::string& fallback = "") {
  const char* v = std::getenv(name);
  return v && *v ? std::string(v) : fallback;
}

inline bool required() { return env("HIL_REQUIRE") == "1"; }

/// Serial ports are probed only when asked (HIL=1, HIL_REQUIRE=1 or an explicit
/// HIL_SERIAL_PORTS list): probing writes Ctrl-X and byte 210 to every
/// /dev/ttyUSB* and /dev/ttyACM*, which other devices (a 3D printer) may not like.
inline bool serial_probing_allowed() {
  return env("HIL") == "1" || required() || !env("HIL_SERIAL_PORTS").empty();
}

}  // namespace station::hil

/// Skips the test (or fails it under HIL_REQUIRE=1) with `why`.
#define HIL_ABSENT(why)                                                   \
  do {                                                                    \
    if (::station::hil::required()) FAIL() << "HIL_REQUIRE=1: " << (why); \
    GTEST_SKIP() << (why);                                                \
  } while (0)
