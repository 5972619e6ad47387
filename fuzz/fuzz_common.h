#pragma once
// Shared by the fuzz targets: the input as a string_view, and the checks every
// successful parse must pass (a violated check aborts, which libFuzzer records).
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string_view>

#include "core/geometry.h"

namespace station::fuzz {

inline std::string_view as_text(const std::uint8_t* data, std::size_t size) {
  return std::string_view(reinterpret_cast<const char*>(data), size);
}

/// A reader must return consistent, finite data or throw.
inline void check_mesh(const Mesh& m) {
  m.check_consistent("fuzz");  // InvalidInput escapes the harness: a crash
  if (!all_finite(m.vertices)) std::abort();
}

inline void check_cloud(const Cloud& c) {
  c.check_consistent("fuzz");
  if (!all_finite(c.points)) std::abort();
}

}  // namespace station::fuzz
