#pragma once
// Colour textures of meshes (OBJ map_Kd images): loading and bilinear lookup.
// OpenCV decodes the image; it stays out of this header.
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "core/io.h"

namespace station {

/// An RGB image, rows top to bottom.
struct Texture {
  int width = 0, height = 0;
  std::vector<std::uint8_t> rgb;  ///< width * height * 3
  bool empty() const { return width <= 0 || height <= 0; }
};

/// Loads a texture image (PNG, JPEG, ...) as RGB; IoError naming the path when it
/// cannot be read, FormatError when it is truncated (read_image_file) or cannot be
/// decoded.
Texture load_texture(const std::filesystem::path& path);

/// The bytes of an image file, for a decoder: IoError naming the path when it cannot
/// be read, FormatError when a JPEG or PNG is cut short (no end-of-image marker or IEND
/// chunk near its end). Decoders fill a cut image with grey and say nothing, so the
/// check is made here, before them.
std::string read_image_file(const std::filesystem::path& path);

/// Bilinear texture lookup with wrap-around addressing. Texel (column i, row j)
/// has its centre at u = (i + 0.5) / width, v = 1 - (j + 0.5) / height, i.e.
/// row = (1 - v) * height, column = u * width (the OBJ convention).
/// An empty texture gives black; non-finite coordinates are taken as 0.
Rgb sample_texture(const Texture& texture, double u, double v);

/// Colour of a mesh surface point given by face and barycentrics (point =
/// (1-u-v) a + u b + v c): the texture through the corner UVs when both are
/// present, else interpolated vertex colours, else black.
Rgb surface_colour(const TexturedMesh& mesh, const Texture& texture, int face, double u, double v);

}  // namespace station
