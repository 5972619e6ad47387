// OFF reader (ascii; [ST][C][N]OFF variants, colours from COFF).
//
// Lines are the unit: one vertex or face per line, '#' starts a comment. Vertex
// lines hold x y z [nx ny nz] [r g b [a]] [u v]; colours written as integers
// are 0-255, with a decimal point they are [0,1]. Face colours are ignored.
#include <cstdint>
#include <string>
#include <vector>

#include "core/io.h"
#include "core/io_detail.h"

namespace station {

namespace {

using io_detail::format_error;
using io_detail::quote;

/// Next non-empty line with its comment removed; false at the end.
bool content_line(io_detail::LineReader& lines, std::string_view& line) {
  while (lines.next(line)) {
    const std::size_t hash = line.find('#');
    if (hash != std::string_view::npos) line = line.substr(0, hash);
    line = io_detail::trim(line);
    if (!line.empty()) return true;
  }
  return false;
}

}  // namespace

Mesh parse_off(std::string_view bytes, const std::string& name) {
  if (bytes.empty()) format_error(name, "empty file");
  io_detail::LineReader lines(bytes);
  std::string_view line;
  if (!content_line(lines, line)) format_error(name, "no OFF header");
  auto bad = [&](const std::string& what) {
    format_error(name, "line " + std::to_string(lines.line()) + ": " + what);
  };

  // Magic: [ST][C][N][4][n]OFF, possibly followed by the counts on the same line.
  io_detail::Tokenizer head(line);
  std::string_view magic;
  head.next(magic);
  if (magic.size() < 3 || magic.substr(magic.size() - 3) != "OFF") bad("not an OFF file (no OFF magic)");
  std::string_view prefix = magic.substr(0, magic.size() - 3);
  bool has_uv = false, has_colour = false, has_normal = false;
  if (prefix.substr(0, 2) == "ST") {
    has_uv = true;
    prefix.remove_prefix(2);
  }
  if (!prefix.empty() && prefix[0] == 'C') {
    has_colour = true;
    prefix.remove_prefix(1);
  }
  if (!prefix.empty() && prefix[0] == 'N') {
    has_normal = true;
    prefix.remove_prefix(1);
  }
  if (!prefix.empty()) bad("unsupported OFF variant " + quote(magic));

  std::string_view counts[3];
  std::size_t nc = 0;
  for (std::string_view t; nc < 3 && head.next(t);) counts[nc++] = t;
  if (nc == 0) {
    if (!content_line(lines, line)) bad("missing vertex and face counts");
    nc = io_detail::split(line, counts, 3);
  }
  if (nc < 2) bad("expected 'VERTICES FACES [EDGES]'");
  long long nv = 0, nf = 0;
  if (!io_detail::parse_int(counts[0], nv) || nv < 0) bad("bad vertex count " + quote(counts[0]));
  if (!io_detail::parse_int(counts[1], nf) || nf < 0) bad("bad face count " + quote(counts[1]));
  // Each vertex line takes at least 6 bytes ("0 0 0\n"), each face 8: check
  // before reserving anything.
  const std::uint64_t rest = lines.remaining() + 1;
  if (static_cast<std::uint64_t>(nv) > rest / 6 || static_cast<std::uint64_t>(nf) > rest / 8 ||
      static_cast<std::uint64_t>(nv) * 6 + static_cast<std::uint64_t>(nf) * 8 > rest)
    bad("counts " + std::to_string(nv) + " vertices / " + std::to_string(nf) +
        " faces exceed the file size");

  Mesh mesh;
  mesh.vertices.reserve(static_cast<std::size_t>(nv));
  if (has_normal) mesh.normals.reserve(static_cast<std::size_t>(nv));
  std::vector<Rgb> colours;
  bool all_coloured = has_colour;
  const std::size_t base = has_normal ? 6 : 3;
  std::string_view tok[16];
  for (long long i = 0; i < nv; ++i) {
    if (!content_line(lines, line))
      bad("truncated: " + std::to_string(nv) + " vertices declared, " + std::to_string(i) + " found");
    const std::size_t n = io_detail::split(line, tok, 16);
    if (n < base) bad("vertex " + std::to_string(i) + ": expected " + std::to_string(base) + " values");
    double v[6];
    for (std::size_t k = 0; k < base; ++k)
      if (!io_detail::parse_double(tok[k], v[k])) bad("bad number " + quote(tok[k]));
    const Vec3f p(static_cast<float>(v[0]), static_cast<float>(v[1]), static_cast<float>(v[2]));
    if (const std::string why = io_detail::coordinate_problem(p.x(), p.y(), p.z()); !why.empty())
      bad("vertex " + std::to_string(i) + ": " + why);
    mesh.vertices.push_back(p);
    if (has_normal)
      mesh.normals.emplace_back(static_cast<float>(v[3]), static_cast<float>(v[4]), static_cast<float>(v[5]));
    if (has_colour) {
      const std::size_t ncol = std::min<std::size_t>(n, 16) - base - (has_uv ? 2 : 0);
      if (n < base + (has_uv ? 2 : 0) + 3 || ncol < 3) {
        all_coloured = false;
        continue;
      }
      bool integral = true;
      double c[3];
      for (int k = 0; k < 3; ++k) {
        const std::string_view t = tok[base + k];
        if (!io_detail::parse_double(t, c[k])) bad("bad colour value " + quote(t));
        long long dummy;
        integral = integral && io_detail::parse_int(t, dummy);
      }
      colours.push_back(Rgb{io_detail::to_channel(c[0], !integral), io_detail::to_channel(c[1], !integral),
                            io_detail::to_channel(c[2], !integral)});
    }
  }
  if (all_coloured && nv > 0) mesh.colours = std::move(colours);

  mesh.faces.reserve(static_cast<std::size_t>(nf));
  std::vector<int> poly;
  for (long long f = 0; f < nf; ++f) {
    if (!content_line(lines, line))
      bad("truncated: " + std::to_string(nf) + " faces declared, " + std::to_string(f) + " found");
    io_detail::Tokenizer t(line);
    std::string_view s;
    t.next(s);
    long long k = 0;
    if (!io_detail::parse_int(s, k) || k < 0) bad("face " + std::to_string(f) + ": bad corner count " + quote(s));
    poly.clear();
    for (long long c = 0; c < k; ++c) {
      long long idx;
      if (!t.next(s)) bad("face " + std::to_string(f) + ": expected " + std::to_string(k) + " indices");
      if (!io_detail::parse_int(s, idx)) bad("face " + std::to_string(f) + ": bad index " + quote(s));
      if (idx < 0 || idx >= nv)
        bad("face " + std::to_string(f) + ": vertex index " + std::to_string(idx) + " out of range (" +
            std::to_string(nv) + " vertices)");
      poly.push_back(static_cast<int>(idx));
    }
    // Fan triangulation; anything after the indices is a face colour.
    for (std::size_t c = 2; c < poly.size(); ++c) mesh.faces.emplace_back(poly[0], poly[c - 1], poly[c]);
  }
  return mesh;
}

}  // namespace station
