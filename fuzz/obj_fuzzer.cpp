// libFuzzer target: station::parse_obj (OBJ) on arbitrary bytes. No base folder
// is given, so mtllib is never followed and the fuzzer never touches files.
#include "core/error.h"
#include "core/io.h"
#include "fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  station::TexturedMesh out;
  try {
    out = station::parse_obj(station::fuzz::as_text(data, size), "fuzz");
  } catch (const station::Error&) {
    return 0;
  }
  station::fuzz::check_mesh(out.mesh);
  if (!out.corner_uv.empty() && out.corner_uv.size() != 3 * out.mesh.faces.size()) std::abort();
  if (!out.texture.empty()) std::abort();
  return 0;
}
