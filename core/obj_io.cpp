// Wavefront OBJ reader (with the MTL diffuse texture name).
//
// Choices the header leaves open:
// - Vertex normals: taken from `vn` only when every face corner references one;
//   a vertex referenced with several normals gets their normalised average
//   (vertices no face uses get a zero normal).
//   Otherwise Mesh::normals stays empty.
// - Vertex colours (`v x y z r g b`, floats in [0,1]) are kept only when every
//   vertex has them.
// - Faces with fewer than three corners (degenerate lines) are skipped.
// - mtllib is followed only when base_dir is given (so parsing bytes from an
//   untrusted source never touches the file system unasked); the texture is the
//   map_Kd of the first material named by usemtl that has one, else the first
//   map_Kd in the library. A missing or unreadable .mtl leaves texture empty.
#include <cstdint>
#include <string>
#include <system_error>
#include <vector>

#include "core/io.h"
#include "core/io_detail.h"

namespace station {

namespace {

using io_detail::format_error;
using io_detail::quote;

constexpr std::uintmax_t kMaxMtlBytes = 16u << 20;

struct Corner {
  int v, vt, vn;  // 0-based, -1 when absent
};

/// Texture of the material library at `mtl` (empty when unknown); `readable` says
/// whether the library itself could be read.
fs::path texture_from_mtl(const fs::path& mtl, const std::vector<std::string>& used, bool& readable) {
  readable = false;
  std::error_code ec;
  if (!fs::is_regular_file(mtl, ec)) return {};
  const auto size = fs::file_size(mtl, ec);
  if (ec || size > kMaxMtlBytes) return {};
  std::string text;
  try {
    text = read_file_bytes(mtl);
  } catch (const Error&) {
    return {};
  }
  readable = true;
  std::vector<std::pair<std::string, std::string>> maps;  // material -> map_Kd
  std::string current;
  io_detail::LineReader lines(text);
  std::string_view line;
  std::string_view tok[64];
  while (lines.next(line)) {
    const std::size_t n = io_detail::split(line, tok, 64);
    if (n < 2) continue;
    if (tok[0] == "newmtl") {
      current = std::string(io_detail::trim(line.substr(line.find("newmtl") + 6)));
    } else if (tok[0] == "map_Kd") {
      // Options (-s 1 1 1, -clamp on, ...) come before the file name; the
      // name is the last token (trailing blanks, as in some exporters, dropped).
      maps.emplace_back(current, std::string(tok[std::min<std::size_t>(n, 64) - 1]));
    }
  }
  if (maps.empty()) return {};
  std::string chosen = maps.front().second;
  bool found = false;
  for (const std::string& u : used) {
    for (const auto& m : maps)
      if (m.first == u) {
        chosen = m.second;
        found = true;
        break;
      }
    if (found) break;
  }
  fs::path tex = mtl.parent_path() / chosen;
  fs::path abs = fs::absolute(tex, ec);
  return (ec ? tex : abs).lexically_normal();
}

}  // namespace

TexturedMesh parse_obj(std::string_view bytes, const std::string& name, const fs::path& base_dir) {
  TexturedMesh out;
  Mesh& mesh = out.mesh;
  std::vector<Rgb> colours;
  bool all_coloured = true;
  std::vector<Vec2f> uvs;
  std::vector<Vec3f> normals;
  std::vector<Corner> corners;  // 3 per triangle
  bool every_vt = true, every_vn = true;
  std::vector<std::string> libraries, used;
  std::vector<Corner> poly;

  io_detail::LineReader lines(bytes);
  std::string_view line;
  std::string_view tok[8];
  while (lines.next(line)) {
    const long long ln = lines.line();
    auto bad = [&](const std::string& what) {
      format_error(name, "line " + std::to_string(ln) + ": " + what);
    };
    const std::size_t n = io_detail::split(line, tok, 8);
    if (n == 0 || tok[0][0] == '#') continue;
    const std::string_view kw = tok[0];
    auto number = [&](std::size_t i) {
      double v;
      if (!io_detail::parse_double(tok[i], v)) bad("bad number " + quote(tok[i]));
      if (!std::isfinite(v)) bad("non-finite value " + quote(tok[i]));
      return v;
    };
    if (kw == "v") {
      if (n < 4) bad("vertex needs x y z");
      const Vec3f p(static_cast<float>(number(1)), static_cast<float>(number(2)),
                    static_cast<float>(number(3)));
      if (const std::string why = io_detail::coordinate_problem(p.x(), p.y(), p.z()); !why.empty())
        bad(why);
      mesh.vertices.push_back(p);
      if (n >= 7) {
        colours.push_back(Rgb{io_detail::to_channel(number(4), true),
                              io_detail::to_channel(number(5), true),
                              io_detail::to_channel(number(6), true)});
      } else {
        colours.push_back(Rgb{});
        all_coloured = false;
      }
    } else if (kw == "vt") {
      if (n < 2) bad("texture coordinate needs u");
      uvs.emplace_back(static_cast<float>(number(1)), n >= 3 ? static_cast<float>(number(2)) : 0.f);
    } else if (kw == "vn") {
      if (n < 4) bad("normal needs x y z");
      normals.emplace_back(static_cast<float>(number(1)), static_cast<float>(number(2)),
                           static_cast<float>(number(3)));
    } else if (kw == "f") {
      poly.clear();
      io_detail::Tokenizer t(line);
      std::string_view c;
      t.next(c);  // "f"
      while (t.next(c)) {
        // v, v/vt, v//vn or v/vt/vn
        std::string_view part[3];
        std::size_t parts = 0, start = 0;
        for (std::size_t i = 0; i <= c.size(); ++i) {
          if (i == c.size() || c[i] == '/') {
            if (parts == 3) bad("bad face corner " + quote(c));
            part[parts++] = c.substr(start, i - start);
            start = i + 1;
          }
        }
        auto resolve = [&](std::string_view s, std::size_t count, const char* what) {
          long long i;
          if (!io_detail::parse_int(s, i)) bad(std::string("bad ") + what + " index " + quote(s));
          const long long cnt = static_cast<long long>(count);
          // Positive indices are 1-based; negative ones count back from the last.
          const long long r = i > 0 ? i - 1 : cnt + i;
          if (i == 0 || r < 0 || r >= cnt)
            bad(std::string(what) + " index " + std::to_string(i) + " out of range (" +
                std::to_string(cnt) + " defined so far)");
          return static_cast<int>(r);
        };
        Corner k{resolve(part[0], mesh.vertices.size(), "vertex"), -1, -1};
        if (parts >= 2 && !part[1].empty()) k.vt = resolve(part[1], uvs.size(), "texture");
        if (parts >= 3 && !part[2].empty()) k.vn = resolve(part[2], normals.size(), "normal");
        poly.push_back(k);
      }
      if (poly.size() < 3) continue;
      for (std::size_t i = 2; i < poly.size(); ++i) {
        for (const Corner& k : {poly[0], poly[i - 1], poly[i]}) {
          every_vt = every_vt && k.vt >= 0;
          every_vn = every_vn && k.vn >= 0;
          corners.push_back(k);
        }
        mesh.faces.emplace_back(poly[0].v, poly[i - 1].v, poly[i].v);
      }
    } else if (kw == "mtllib") {
      if (n >= 2) libraries.emplace_back(io_detail::trim(line.substr(line.find("mtllib") + 6)));
    } else if (kw == "usemtl") {
      if (n >= 2) used.emplace_back(io_detail::trim(line.substr(line.find("usemtl") + 6)));
    }
    // Everything else (o, g, s, l, p, vp, curves...) carries nothing we keep.
  }

  if (all_coloured && !mesh.vertices.empty()) mesh.colours = std::move(colours);
  if (!corners.empty() && every_vt) {
    out.corner_uv.reserve(corners.size());
    for (const Corner& k : corners) out.corner_uv.push_back(uvs[k.vt]);
  }
  if (!corners.empty() && every_vn) {
    std::vector<Vec3f> acc(mesh.vertices.size(), Vec3f::Zero());
    for (const Corner& k : corners) {
      acc[k.v] += normals[k.vn].normalized();
    }
    for (Vec3f& a : acc) {
      const float len = a.norm();
      if (len > 0 && std::isfinite(len)) a /= len;
    }
    mesh.normals = std::move(acc);
  }

  if (!base_dir.empty()) {
    bool any_library_read = false;
    for (const std::string& lib : libraries) {
      // A library name may hold spaces; if the whole name is not a file, try
      // each word (the statement can list several libraries).
      std::vector<std::string> candidates{lib};
      io_detail::Tokenizer t(lib);
      for (std::string_view w; t.next(w);)
        if (w.size() != lib.size()) candidates.emplace_back(w);
      for (const std::string& c : candidates) {
        bool readable = false;
        out.texture = texture_from_mtl(base_dir / c, used, readable);
        any_library_read = any_library_read || readable;
        if (!out.texture.empty()) break;
      }
      if (!out.texture.empty()) break;
    }
    if (!libraries.empty() && !any_library_read)
      out.material_problem = "its material library " + quote(libraries.front()) + " could not be read in " +
                             base_dir.string() + " (missing?): the mesh is read without its texture";
  }
  return out;
}

}  // namespace station
