// PCD reader (v0.5-0.7; DATA ascii, binary, binary_compressed).
#include <algorithm>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include "core/io.h"
#include "core/io_detail.h"

#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "the binary readers assume a little-endian host"
#endif

namespace station {

namespace {

using io_detail::format_error;
using io_detail::quote;

struct Field {
  std::string name;
  int size = 4;
  char type = 'F';
  std::uint64_t count = 1;
  std::uint64_t offset = 0;  // within one point of the interleaved (binary) layout
};

enum class DataKind { kAscii, kBinary, kCompressed };

struct PcdHeader {
  std::vector<Field> fields;
  std::uint64_t points = 0;
  DataKind kind = DataKind::kAscii;
  std::uint64_t stride = 0;  // bytes per point
  std::size_t data_offset = 0;
  long long data_line = 1;
};

std::uint64_t parse_count(std::string_view tok, const std::string& name, long long line,
                          const char* what) {
  long long v = 0;
  if (!io_detail::parse_int(tok, v) || v < 0)
    format_error(name, "line " + std::to_string(line) + ": bad " + what + " " + quote(tok));
  return static_cast<std::uint64_t>(v);
}

PcdHeader parse_header(std::string_view bytes, const std::string& name) {
  if (bytes.empty()) format_error(name, "empty file");
  io_detail::LineReader lines(bytes);
  std::string_view line;
  PcdHeader h;
  std::vector<std::string_view> tok;
  std::vector<std::string_view> sizes, types, counts;
  bool have_fields = false, have_points = false, have_width = false, have_height = false;
  bool have_data = false;
  std::uint64_t width = 0, height = 1;
  while (lines.next(line)) {
    const long long ln = lines.line();
    auto bad = [&](const std::string& what) {
      format_error(name, "line " + std::to_string(ln) + ": " + what);
    };
    line = io_detail::trim(line);
    if (line.empty() || line[0] == '#') continue;
    tok.clear();
    io_detail::Tokenizer t(line);
    for (std::string_view s; t.next(s);) tok.push_back(s);
    const std::string_view kw = tok[0];
    const std::size_t nargs = tok.size() - 1;
    if (kw == "VERSION") {
      if (nargs != 1) bad("expected 'VERSION x'");
      const std::string_view v = tok[1];
      if (v != ".5" && v != "0.5" && v != ".6" && v != "0.6" && v != ".7" && v != "0.7")
        bad("unsupported PCD version " + quote(v));
    } else if (kw == "FIELDS" || kw == "COLUMNS") {
      if (nargs == 0) bad("no fields");
      h.fields.clear();
      for (std::size_t i = 1; i < tok.size(); ++i) h.fields.push_back(Field{std::string(tok[i])});
      have_fields = true;
    } else if (kw == "SIZE") {
      sizes.assign(tok.begin() + 1, tok.end());
    } else if (kw == "TYPE") {
      types.assign(tok.begin() + 1, tok.end());
    } else if (kw == "COUNT") {
      counts.assign(tok.begin() + 1, tok.end());
    } else if (kw == "WIDTH") {
      if (nargs != 1) bad("expected 'WIDTH n'");
      width = parse_count(tok[1], name, ln, "width");
      have_width = true;
    } else if (kw == "HEIGHT") {
      if (nargs != 1) bad("expected 'HEIGHT n'");
      height = parse_count(tok[1], name, ln, "height");
      have_height = true;
    } else if (kw == "POINTS") {
      if (nargs != 1) bad("expected 'POINTS n'");
      h.points = parse_count(tok[1], name, ln, "point count");
      have_points = true;
    } else if (kw == "VIEWPOINT") {
      // The sensor pose is metadata: points are stored in the cloud's own frame.
      if (nargs != 7) bad("expected 7 VIEWPOINT values");
      for (std::size_t i = 1; i < tok.size(); ++i) {
        double v;
        if (!io_detail::parse_double(tok[i], v)) bad("bad VIEWPOINT value " + quote(tok[i]));
      }
    } else if (kw == "DATA") {
      if (nargs != 1) bad("expected 'DATA ascii|binary|binary_compressed'");
      if (tok[1] == "ascii") h.kind = DataKind::kAscii;
      else if (tok[1] == "binary") h.kind = DataKind::kBinary;
      else if (tok[1] == "binary_compressed") h.kind = DataKind::kCompressed;
      else bad("unknown DATA kind " + quote(tok[1]));
      have_data = true;
      break;
    } else {
      bad("unknown header keyword " + quote(kw));
    }
  }
  if (!have_data) format_error(name, "header has no DATA line (not a PCD file?)");
  if (!have_fields) format_error(name, "header has no FIELDS line");
  h.data_offset = lines.offset();
  h.data_line = lines.line() + 1;
  const long long dl = lines.line();
  auto bad = [&](const std::string& what) { format_error(name, "header: " + what); };

  const std::size_t nf = h.fields.size();
  if (!sizes.empty() && sizes.size() != nf) bad("SIZE has " + std::to_string(sizes.size()) + " entries for " + std::to_string(nf) + " fields");
  if (!types.empty() && types.size() != nf) bad("TYPE has " + std::to_string(types.size()) + " entries for " + std::to_string(nf) + " fields");
  if (!counts.empty() && counts.size() != nf) bad("COUNT has " + std::to_string(counts.size()) + " entries for " + std::to_string(nf) + " fields");
  std::uint64_t stride = 0;
  for (std::size_t i = 0; i < nf; ++i) {
    Field& f = h.fields[i];
    if (!sizes.empty()) {
      const std::uint64_t s = parse_count(sizes[i], name, dl, "SIZE");
      if (s != 1 && s != 2 && s != 4 && s != 8) bad("field '" + f.name + "' has size " + std::to_string(s));
      f.size = static_cast<int>(s);
    }
    if (!types.empty()) {
      if (types[i].size() != 1 || (types[i][0] != 'F' && types[i][0] != 'I' && types[i][0] != 'U'))
        bad("field '" + f.name + "' has unknown TYPE " + quote(types[i]));
      f.type = types[i][0];
    }
    if (f.type == 'F' && f.size != 4 && f.size != 8)
      bad("field '" + f.name + "' is a float of size " + std::to_string(f.size));
    if (!counts.empty()) {
      f.count = parse_count(counts[i], name, dl, "COUNT");
      if (f.count == 0 || f.count > (1u << 24)) bad("field '" + f.name + "' has COUNT " + std::to_string(f.count));
    }
    f.offset = stride;
    stride += f.count * static_cast<std::uint64_t>(f.size);  // < 2^24 * 8 * fields: no overflow
  }
  h.stride = stride;
  if (!have_points) {
    if (!have_width) bad("neither POINTS nor WIDTH given");
    if (height != 0 && width > std::numeric_limits<std::uint64_t>::max() / height) bad("WIDTH * HEIGHT overflows");
    h.points = width * height;
  }
  if (have_points && have_width) {
    // PCL writes both; a count that disagrees with the organised size is a corrupt or
    // hand-edited header (PCL's own reader refuses it too), whichever is right.
    const bool overflows = height != 0 && width > std::numeric_limits<std::uint64_t>::max() / height;
    if (overflows || width * height != h.points)
      bad("POINTS " + std::to_string(h.points) + " disagrees with WIDTH x HEIGHT = " + std::to_string(width) + " x " +
          std::to_string(height) + (have_height ? "" : " (HEIGHT not given: 1)"));
  }
  return h;
}

/// LZF decompression (the liblzf format PCL uses) with every read and write
/// bounds-checked. Returns the number of bytes produced, or -1 on corrupt input.
long long lzf_decompress(const unsigned char* in, std::size_t in_len, unsigned char* out,
                         std::size_t out_len) {
  std::size_t ip = 0, op = 0;
  while (ip < in_len) {
    const unsigned ctrl = in[ip++];
    if (ctrl < 32) {  // literal run of ctrl + 1 bytes
      const std::size_t len = ctrl + 1;
      if (len > in_len - ip || len > out_len - op) return -1;
      std::memcpy(out + op, in + ip, len);
      ip += len;
      op += len;
    } else {  // back reference: length (3 bits, extended by a byte) and 13-bit distance
      std::size_t len = ctrl >> 5;
      if (len == 7) {
        if (ip >= in_len) return -1;
        len += in[ip++];
      }
      if (ip >= in_len) return -1;
      const std::size_t back = ((static_cast<std::size_t>(ctrl & 0x1f) << 8) | in[ip++]) + 1;
      len += 2;
      if (back > op || len > out_len - op) return -1;
      // Byte by byte: the source may overlap the bytes being written (run-length use).
      for (std::size_t k = 0; k < len; ++k, ++op) out[op] = out[op - back];
    }
  }
  return static_cast<long long>(op);
}

double load_value(const unsigned char* p, const Field& f) {
  switch (f.type) {
    case 'F':
      if (f.size == 4) {
        float v;
        std::memcpy(&v, p, 4);
        return v;
      } else {
        double v;
        std::memcpy(&v, p, 8);
        return v;
      }
    case 'I':
      switch (f.size) {
        case 1: return static_cast<std::int8_t>(p[0]);
        case 2: { std::int16_t v; std::memcpy(&v, p, 2); return v; }
        case 4: { std::int32_t v; std::memcpy(&v, p, 4); return v; }
        default: { std::int64_t v; std::memcpy(&v, p, 8); return static_cast<double>(v); }
      }
    default:
      switch (f.size) {
        case 1: return p[0];
        case 2: { std::uint16_t v; std::memcpy(&v, p, 2); return v; }
        case 4: { std::uint32_t v; std::memcpy(&v, p, 4); return v; }
        default: { std::uint64_t v; std::memcpy(&v, p, 8); return static_cast<double>(v); }
      }
  }
}

Rgb unpack_rgb(std::uint32_t v) {
  return Rgb{static_cast<std::uint8_t>((v >> 16) & 0xff), static_cast<std::uint8_t>((v >> 8) & 0xff),
             static_cast<std::uint8_t>(v & 0xff)};
}

/// Indices of the fields we use (-1 when absent).
struct Layout {
  int x = -1, y = -1, z = -1, nx = -1, ny = -1, nz = -1, rgb = -1;
};

Layout find_layout(const PcdHeader& h, const std::string& name) {
  Layout L;
  for (std::size_t i = 0; i < h.fields.size(); ++i) {
    const std::string& n = h.fields[i].name;
    const int k = static_cast<int>(i);
    if (n == "x") L.x = k;
    else if (n == "y") L.y = k;
    else if (n == "z") L.z = k;
    else if (n == "normal_x") L.nx = k;
    else if (n == "normal_y") L.ny = k;
    else if (n == "normal_z") L.nz = k;
    else if ((n == "rgb" || n == "rgba") && h.fields[i].size == 4) L.rgb = k;
  }
  if (L.x < 0 || L.y < 0 || L.z < 0) format_error(name, "header: fields x, y and z are required");
  if (L.nx < 0 || L.ny < 0 || L.nz < 0) L.nx = L.ny = L.nz = -1;
  return L;
}

/// Appends one point unless a coordinate is NaN (organised clouds' missing pixels).
void add_point(Cloud& c, const Layout& L, double x, double y, double z, const Vec3f& n,
               std::uint32_t rgb, std::uint64_t index, const std::string& name) {
  const Vec3f p(static_cast<float>(x), static_cast<float>(y), static_cast<float>(z));
  if (std::isnan(p.x()) || std::isnan(p.y()) || std::isnan(p.z())) return;
  if (const std::string why = io_detail::coordinate_problem(p.x(), p.y(), p.z()); !why.empty())
    format_error(name, "point " + std::to_string(index) + ": " + why);
  c.points.push_back(p);
  if (L.nx >= 0) c.normals.push_back(n);
  if (L.rgb >= 0) c.colours.push_back(unpack_rgb(rgb));
}

/// Points in a binary buffer; `at(i, f)` gives the bytes of field f of point i.
template <class At>
Cloud read_binary_points(const PcdHeader& h, const Layout& L, const At& at, const std::string& name) {
  Cloud c;
  c.points.reserve(h.points);
  if (L.nx >= 0) c.normals.reserve(h.points);
  if (L.rgb >= 0) c.colours.reserve(h.points);
  const auto& F = h.fields;
  for (std::uint64_t i = 0; i < h.points; ++i) {
    Vec3f n = Vec3f::Zero();
    if (L.nx >= 0)
      n = Vec3f(static_cast<float>(load_value(at(i, L.nx), F[L.nx])),
                static_cast<float>(load_value(at(i, L.ny), F[L.ny])),
                static_cast<float>(load_value(at(i, L.nz), F[L.nz])));
    std::uint32_t rgb = 0;
    if (L.rgb >= 0) std::memcpy(&rgb, at(i, L.rgb), 4);  // packed bytes, whatever TYPE says
    add_point(c, L, load_value(at(i, L.x), F[L.x]), load_value(at(i, L.y), F[L.y]),
              load_value(at(i, L.z), F[L.z]), n, rgb, i, name);
  }
  return c;
}

Cloud read_ascii(std::string_view data, const PcdHeader& h, const Layout& L, const std::string& name) {
  // Token position of the first value of each field on a line.
  std::vector<std::uint64_t> first;
  std::uint64_t ntok = 0;
  for (const Field& f : h.fields) {
    first.push_back(ntok);
    ntok += f.count;
  }
  if (h.points == 0) return Cloud{};
  // Each value takes at least one character and a separator (this also bounds
  // ntok, which sizes the token buffer below).
  if (ntok == 0 || h.points > (data.size() + 1) / 2 / ntok)
    format_error(name, "header declares " + std::to_string(h.points) + " points, more than the file holds");
  Cloud c;
  c.points.reserve(h.points);
  if (L.nx >= 0) c.normals.reserve(h.points);
  if (L.rgb >= 0) c.colours.reserve(h.points);

  io_detail::LineReader lines(data);
  std::vector<std::string_view> tok(static_cast<std::size_t>(ntok));
  std::string_view line;
  std::uint64_t i = 0;
  while (i < h.points) {
    if (!lines.next(line))
      format_error(name, "truncated: " + std::to_string(h.points) + " points declared, " +
                             std::to_string(i) + " found");
    const long long ln = h.data_line + lines.line() - 1;
    auto bad = [&](const std::string& what) {
      format_error(name, "line " + std::to_string(ln) + ": " + what);
    };
    const std::size_t n = io_detail::split(line, tok.data(), tok.size());
    if (n == 0) continue;
    if (n < ntok) bad("expected " + std::to_string(ntok) + " values, found " + std::to_string(n));
    auto number = [&](int field) {
      const std::string_view t = tok[first[field]];
      double v;
      if (!io_detail::parse_double(t, v)) bad("bad number " + quote(t));
      return v;
    };
    Vec3f nrm = Vec3f::Zero();
    if (L.nx >= 0)
      nrm = Vec3f(static_cast<float>(number(L.nx)), static_cast<float>(number(L.ny)),
                  static_cast<float>(number(L.nz)));
    std::uint32_t rgb = 0;
    if (L.rgb >= 0) {
      // Newer PCL writes the packed value as an integer, older as the float with
      // those bits: take integers as they are, reinterpret anything else.
      const std::string_view t = tok[first[L.rgb]];
      long long iv;
      if (io_detail::parse_int(t, iv) && iv >= std::numeric_limits<std::int32_t>::min() &&
          iv <= std::numeric_limits<std::uint32_t>::max()) {
        rgb = static_cast<std::uint32_t>(iv);
      } else {
        const float fv = static_cast<float>(number(L.rgb));
        std::memcpy(&rgb, &fv, 4);
      }
    }
    add_point(c, L, number(L.x), number(L.y), number(L.z), nrm, rgb, i, name);
    ++i;
  }
  return c;
}

}  // namespace

namespace {
Cloud parse_pcd_fields(std::string_view bytes, const std::string& name);
}  // namespace

Cloud parse_pcd(std::string_view bytes, const std::string& name) {
  Cloud c = parse_pcd_fields(bytes, name);
  // PCL writes NaN normals where it could not estimate one: such a file's normals are
  // dropped whole (the stages estimate their own), never passed on as NaN.
  if (std::any_of(c.normals.begin(), c.normals.end(), [](const Vec3f& n) { return !n.allFinite(); }))
    c.normals.clear();
  return c;
}

namespace {
Cloud parse_pcd_fields(std::string_view bytes, const std::string& name) {
  const PcdHeader h = parse_header(bytes, name);
  const Layout L = find_layout(h, name);
  const std::string_view data = bytes.substr(h.data_offset);
  const auto* base = reinterpret_cast<const unsigned char*>(data.data());

  if (h.kind == DataKind::kAscii) return read_ascii(data, h, L, name);

  if (h.kind == DataKind::kBinary) {
    if (h.stride == 0 || h.points > data.size() / h.stride)
      format_error(name, "binary data holds " + std::to_string(h.stride ? data.size() / h.stride : 0) +
                             " points, header declares " + std::to_string(h.points));
    const std::uint64_t stride = h.stride;
    const auto& F = h.fields;
    return read_binary_points(
        h, L, [&](std::uint64_t i, int f) { return base + i * stride + F[f].offset; }, name);
  }

  // binary_compressed: uint32 compressed size, uint32 raw size, LZF stream of the
  // fields one after another (all values of field 1, then field 2, ...).
  if (data.size() < 8) format_error(name, "compressed data: truncated size header");
  std::uint32_t packed = 0, raw = 0;
  std::memcpy(&packed, base, 4);
  std::memcpy(&raw, base + 4, 4);
  if (packed > data.size() - 8)
    format_error(name, "compressed data: " + std::to_string(packed) + " bytes declared, " +
                           std::to_string(data.size() - 8) + " present");
  if (h.stride == 0 || h.points > std::numeric_limits<std::uint32_t>::max() / h.stride ||
      h.points * h.stride != raw)
    format_error(name, "compressed data: uncompressed size " + std::to_string(raw) +
                           " does not match " + std::to_string(h.points) + " points of " +
                           std::to_string(h.stride) + " bytes");
  // A 3-byte LZF back reference expands to at most 264 bytes: reject impossible
  // ratios before allocating the output.
  if (static_cast<std::uint64_t>(raw) > static_cast<std::uint64_t>(packed) * 88)
    format_error(name, "compressed data: uncompressed size " + std::to_string(raw) +
                           " impossible for " + std::to_string(packed) + " compressed bytes");
  std::vector<unsigned char> buf(raw);
  const long long got = lzf_decompress(base + 8, packed, buf.data(), buf.size());
  if (got != static_cast<long long>(raw))
    format_error(name, "compressed data: corrupt LZF stream");
  std::vector<std::uint64_t> column;  // start of each field's block
  std::uint64_t off = 0;
  for (const Field& f : h.fields) {
    column.push_back(off);
    off += h.points * f.count * static_cast<std::uint64_t>(f.size);
  }
  const auto& F = h.fields;
  const unsigned char* b = buf.data();
  return read_binary_points(
      h, L,
      [&](std::uint64_t i, int f) {
        return b + column[f] + i * F[f].count * static_cast<std::uint64_t>(F[f].size);
      },
      name);
}
}  // namespace

}  // namespace station
