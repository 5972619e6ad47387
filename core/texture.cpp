#include "core/texture.h"

#include <algorithm>
#include <array>
#include <cstdint>
#include <cmath>
#include <string_view>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.h"

namespace station {

namespace {

// CRC-32 as PNG computes it (ISO 3309, reflected polynomial 0xEDB88320).
std::uint32_t png_crc(const unsigned char* p, std::size_t n) {
  static const auto table = [] {
    std::array<std::uint32_t, 256> t{};
    for (std::uint32_t i = 0; i < 256; ++i) {
      std::uint32_t c = i;
      for (int k = 0; k < 8; ++k) c = (c & 1) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
      t[i] = c;
    }
    return t;
  }();
  std::uint32_t c = 0xFFFFFFFFu;
  for (std::size_t i = 0; i < n; ++i) c = table[(c ^ p[i]) & 0xFF] ^ (c >> 8);
  return c ^ 0xFFFFFFFFu;
}

std::uint32_t big_endian_u32(const unsigned char* p) {
  return (std::uint32_t(p[0]) << 24) | (std::uint32_t(p[1]) << 16) | (std::uint32_t(p[2]) << 8) | p[3];
}

// Walks a PNG's chunks up to IEND and checks each critical chunk's CRC (IHDR, PLTE,
// IDAT, IEND: an upper-case first letter), so that a corrupt file is one error naming
// it; libpng also printed its own line ("libpng error: IDAT: invalid literal/lengths
// set") before OpenCV gave up. Data after IEND is allowed (some writers pad).
void check_png_chunks(const std::string& bytes, const fs::path& path) {
  const auto* data = reinterpret_cast<const unsigned char*>(bytes.data());
  std::size_t at = 8;
  for (;;) {
    if (bytes.size() - at < 12) throw FormatError(path.string() + ": truncated PNG (no IEND chunk)");
    const std::uint32_t length = big_endian_u32(data + at);
    if (length > 0x7FFFFFFFu || bytes.size() - at - 12 < length)
      throw FormatError(path.string() + ": truncated PNG (no IEND chunk)");
    const std::string type(bytes, at + 4, 4);
    const bool critical = type[0] >= 'A' && type[0] <= 'Z';
    if (critical && png_crc(data + at + 4, 4 + std::size_t(length)) != big_endian_u32(data + at + 8 + length))
      throw FormatError(path.string() + ": corrupt PNG (its " + type + " chunk at byte " + std::to_string(at) +
                        " fails its CRC check)");
    if (type == "IEND") return;
    at += 12 + std::size_t(length);
  }
}

}  // namespace

std::string read_image_file(const fs::path& path) {
  std::string bytes = read_file_bytes(path);
  const auto starts = [&](std::string_view magic) { return bytes.compare(0, magic.size(), magic) == 0; };
  // Markers are looked for in the last KiB: some writers pad after them.
  const auto ends_with = [&](std::string_view marker) {
    return bytes.find(marker, bytes.size() > 1024 ? bytes.size() - 1024 : 0) != std::string::npos;
  };
  if (starts("\xFF\xD8") && !ends_with("\xFF\xD9"))
    throw FormatError(path.string() + ": truncated JPEG (no end-of-image marker)");
  if (starts("\x89PNG\r\n\x1A\n")) check_png_chunks(bytes, path);
  return bytes;
}

Texture load_texture(const fs::path& path) {
  const std::string bytes = read_image_file(path);
  const cv::Mat encoded(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data()));
  cv::Mat bgr;
  try {
    if (!bytes.empty()) bgr = cv::imdecode(encoded, cv::IMREAD_COLOR);
  } catch (const cv::Exception& e) {
    // OpenCV refuses e.g. a header that claims more than 2^30 pixels (an image bomb).
    throw FormatError(path.string() + ": not a readable image (the decoder refused it: " + e.err + ")");
  }
  if (bgr.empty()) throw FormatError(path.string() + ": not a readable image");
  cv::Mat rgb;
  cv::cvtColor(bgr, rgb, cv::COLOR_BGR2RGB);
  Texture t;
  t.width = rgb.cols;
  t.height = rgb.rows;
  t.rgb.resize(std::size_t(t.width) * t.height * 3);
  for (int r = 0; r < t.height; ++r)
    std::copy_n(rgb.ptr<std::uint8_t>(r), std::size_t(t.width) * 3,
                t.rgb.data() + std::size_t(r) * t.width * 3);
  return t;
}

Rgb sample_texture(const Texture& texture, double u, double v) {
  if (texture.empty()) return {};
  if (!std::isfinite(u)) u = 0;
  if (!std::isfinite(v)) v = 0;
  // Coordinates outside [0, 1] repeat (OBJ); inside, 0 and 1 are the image edges.
  if (u < 0 || u > 1) u -= std::floor(u);
  if (v < 0 || v > 1) v -= std::floor(v);
  const int w = texture.width, h = texture.height;
  const double x = u * w - 0.5, y = (1.0 - v) * h - 0.5;
  const int x0 = int(std::floor(x)), y0 = int(std::floor(y));
  const double ax = x - x0, ay = y - y0;
  // Neighbours past the edge clamp to it: atlases must not bleed across seams.
  auto cx = [w](int i) { return std::clamp(i, 0, w - 1); };
  auto cy = [h](int j) { return std::clamp(j, 0, h - 1); };
  const std::uint8_t* p00 = &texture.rgb[(std::size_t(cy(y0)) * w + cx(x0)) * 3];
  const std::uint8_t* p10 = &texture.rgb[(std::size_t(cy(y0)) * w + cx(x0 + 1)) * 3];
  const std::uint8_t* p01 = &texture.rgb[(std::size_t(cy(y0 + 1)) * w + cx(x0)) * 3];
  const std::uint8_t* p11 = &texture.rgb[(std::size_t(cy(y0 + 1)) * w + cx(x0 + 1)) * 3];
  std::uint8_t out[3];
  for (int c = 0; c < 3; ++c) {
    const double top = p00[c] + ax * (p10[c] - p00[c]);
    const double bottom = p01[c] + ax * (p11[c] - p01[c]);
    out[c] = std::uint8_t(std::clamp(std::lround(top + ay * (bottom - top)), 0L, 255L));
  }
  return {out[0], out[1], out[2]};
}

Rgb surface_colour(const TexturedMesh& mesh, const Texture& texture, int face, double u,
                  double v) {
  const double w0 = 1.0 - u - v;
  if (!texture.empty() && !mesh.corner_uv.empty()) {
    const Vec2f* uv = &mesh.corner_uv[std::size_t(face) * 3];
    return sample_texture(texture, w0 * uv[0].x() + u * uv[1].x() + v * uv[2].x(),
                          w0 * uv[0].y() + u * uv[1].y() + v * uv[2].y());
  }
  if (mesh.mesh.has_colours()) {
    const Face& f = mesh.mesh.faces[face];
    const Rgb &a = mesh.mesh.colours[f[0]], &b = mesh.mesh.colours[f[1]], &c = mesh.mesh.colours[f[2]];
    auto mix = [&](std::uint8_t x, std::uint8_t y, std::uint8_t z) {
      return std::uint8_t(std::clamp(std::lround(w0 * x + u * y + v * z), 0L, 255L));
    };
    return {mix(a.r, b.r, c.r), mix(a.g, b.g, c.g), mix(a.b, b.b, c.b)};
  }
  return {};
}

}  // namespace station
