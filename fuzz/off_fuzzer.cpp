// libFuzzer target: station::parse_off (OFF) on arbitrary bytes.
#include "core/error.h"
#include "core/io.h"
#include "fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  station::Mesh out;
  try {
    out = station::parse_off(station::fuzz::as_text(data, size), "fuzz");
  } catch (const station::Error&) {
    return 0;  // rejecting bad input with a typed error is the expected outcome
  }
  station::fuzz::check_mesh(out);
  return 0;
}
