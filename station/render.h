#pragma once
// A small software rasteriser for the run report (station/report.h): meshes and
// clouds drawn headless on the CPU, orthographic, with a z-buffer and a
// headlight. No display, no GPU, no library beyond Eigen; PNG encoding through
// OpenCV lives in the .cpp.
#include <cstdint>
#include <string>
#include <vector>

#include "core/geometry.h"

namespace station {

/// 8-bit RGB image, row-major, top row first.
struct Image {
  int width = 0, height = 0;
  std::vector<std::uint8_t> rgb;  ///< width * height * 3
  Image() = default;
  Image(int w, int h, Rgb fill = {255, 255, 255});
  Rgb at(int x, int y) const {
    const std::size_t i = (std::size_t(y) * width + x) * 3;
    return {rgb[i], rgb[i + 1], rgb[i + 2]};
  }
  void set(int x, int y, Rgb c) {
    const std::size_t i = (std::size_t(y) * width + x) * 3;
    rgb[i] = c.r;
    rgb[i + 1] = c.g;
    rgb[i + 2] = c.b;
  }
};

/// Orthographic camera looking at the centre of `box` along -`toward_eye`
/// (toward_eye points from the object to the viewer), `up` projected to the
/// image's up. The box's bounding sphere fills the image minus `margin` pixels.
struct RenderView {
  Vec3d toward_eye = Vec3d::UnitZ();
  Vec3d up = Vec3d::UnitY();
  Aabb box;  ///< invalid: the drawn geometry's own bounding box
  int width = 400, height = 400;
  int margin = 8;
};

struct RenderOptions {
  Rgb background{255, 255, 255};
  /// Used where the geometry has no colours, or when use_colors is false.
  Rgb base{200, 200, 205};
  bool use_colours = true;
  /// Lambert shading with a light at the eye: c * (ambient + (1 - ambient) |n . l|).
  bool shade = true;
  double ambient = 0.3;
  int point_size = 2;  ///< pixels per point (squares)
};

/// Standard views for the report: from the front (scanner side, +x of the
/// turntable frame), the left, the back, the right (a little from above), and
/// from above. `up` is the object's up (the turntable axis; +z in the turntable frame).
RenderView view_from_side(int quarter_turns, const Aabb& box, int size = 400,
                          const Vec3d& up = Vec3d::UnitZ());
RenderView view_from_above(const Aabb& box, int size = 400, const Vec3d& up = Vec3d::UnitZ());

/// Draws the mesh's faces (both sides; shading by face normal). Colours per vertex
/// are interpolated when present and options.use_colors. Non-finite vertices are skipped.
Image render_mesh(const Mesh& mesh, const RenderView& view, const RenderOptions& options = {});

/// Draws points as squares of options.point_size. `colors` (optional, one per point)
/// overrides the cloud's own colours; normals shade when present.
Image render_points(const Cloud& cloud, const RenderView& view, const RenderOptions& options = {},
                    const std::vector<Rgb>* colours = nullptr);

/// PNG bytes of the image (InvalidInput on an empty image).
std::string encode_png(const Image& image);

/// Base64 (RFC 4648, with padding) of bytes, for data: URIs.
std::string base64(const std::string& bytes);

}  // namespace station
