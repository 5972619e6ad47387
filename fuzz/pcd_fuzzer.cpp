// libFuzzer target: station::parse_pcd (PCD) on arbitrary bytes.
#include "core/error.h"
#include "core/io.h"
#include "fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  station::Cloud out;
  try {
    out = station::parse_pcd(station::fuzz::as_text(data, size), "fuzz");
  } catch (const station::Error&) {
    return 0;  // rejecting bad input with a typed error is the expected outcome
  }
  station::fuzz::check_cloud(out);
  return 0;
}
