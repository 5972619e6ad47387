// PLY reader (ascii, binary little/big endian).
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <functional>
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

enum class Scalar { kI8, kU8, kI16, kU16, kI32, kU32, kF32, kF64 };

int scalar_size(Scalar t) {
  switch (t) {
    case Scalar::kI8:
    case Scalar::kU8: return 1;
    case Scalar::kI16:
    case Scalar::kU16: return 2;
    case Scalar::kI32:
    case Scalar::kU32:
    case Scalar::kF32: return 4;
    case Scalar::kF64: return 8;
  }
  return 1;
}

bool is_float(Scalar t) { return t == Scalar::kF32 || t == Scalar::kF64; }

bool scalar_from_name(std::string_view s, Scalar& t) {
  struct Entry {
    const char* name;
    Scalar type;
  };
  static const Entry kNames[] = {
      {"char", Scalar::kI8},     {"int8", Scalar::kI8},      {"uchar", Scalar::kU8},
      {"uint8", Scalar::kU8},    {"short", Scalar::kI16},    {"int16", Scalar::kI16},
      {"ushort", Scalar::kU16},  {"uint16", Scalar::kU16},   {"int", Scalar::kI32},
      {"int32", Scalar::kI32},   {"uint", Scalar::kU32},     {"uint32", Scalar::kU32},
      {"float", Scalar::kF32},   {"float32", Scalar::kF32},  {"double", Scalar::kF64},
      {"float64", Scalar::kF64},
  };
  for (const Entry& e : kNames)
    if (s == e.name) {
      t = e.type;
      return true;
    }
  return false;
}

struct Property {
  std::string name;
  bool is_list = false;
  Scalar type = Scalar::kF32;        // item type for lists
  Scalar count_type = Scalar::kU8;   // lists only
};

struct Element {
  std::string name;
  std::uint64_t count = 0;
  std::vector<Property> props;
  long long header_line = 0;

  int find(std::string_view n) const {
    for (std::size_t i = 0; i < props.size(); ++i)
      if (props[i].name == n) return static_cast<int>(i);
    return -1;
  }
  int find_scalar(std::initializer_list<const char*> names) const {
    for (const char* n : names) {
      const int i = find(n);
      if (i >= 0 && !props[i].is_list) return i;
    }
    return -1;
  }
};

enum class Encoding { kAscii, kBinaryLe, kBinaryBe };

struct Header {
  Encoding encoding = Encoding::kAscii;
  std::vector<Element> elements;
  std::size_t data_offset = 0;
  long long data_line = 1;  // line number of the first data line (ascii)
};

Header parse_header(std::string_view bytes, const std::string& name) {
  io_detail::LineReader lines(bytes);
  std::string_view line;
  if (!lines.next(line)) format_error(name, "empty file");
  if (io_detail::trim(line) != "ply") format_error(name, "line 1: not a PLY file (no 'ply' magic)");
  Header h;
  bool have_format = false, ended = false;
  std::string_view tok[6];
  while (lines.next(line)) {
    const long long ln = lines.line();
    auto bad = [&](const std::string& what) {
      format_error(name, "line " + std::to_string(ln) + ": " + what);
    };
    const std::size_t n = io_detail::split(line, tok, 6);
    if (n == 0) continue;
    const std::string_view kw = tok[0];
    if (kw == "end_header") {
      ended = true;
      break;
    }
    if (kw == "comment" || kw == "obj_info") continue;
    if (kw == "format") {
      if (n < 2) bad("format line without a format");
      if (have_format) bad("second format line");
      if (tok[1] == "ascii") h.encoding = Encoding::kAscii;
      else if (tok[1] == "binary_little_endian") h.encoding = Encoding::kBinaryLe;
      else if (tok[1] == "binary_big_endian") h.encoding = Encoding::kBinaryBe;
      else bad("unknown format " + quote(tok[1]));
      have_format = true;
    } else if (kw == "element") {
      if (n != 3) bad("expected 'element NAME COUNT'");
      long long count = 0;
      if (!io_detail::parse_int(tok[2], count) || count < 0)
        bad("bad element count " + quote(tok[2]));
      for (const Element& earlier : h.elements)
        if (earlier.name == tok[1] && (tok[1] == "vertex" || tok[1] == "face"))
          bad("a second 'element " + std::string(tok[1]) + "' (the first is on line " +
              std::to_string(earlier.header_line) + ")");
      Element e;
      e.name = std::string(tok[1]);
      e.count = static_cast<std::uint64_t>(count);
      e.header_line = ln;
      h.elements.push_back(std::move(e));
    } else if (kw == "property") {
      if (h.elements.empty()) bad("property before any element");
      Property p;
      if (n >= 2 && tok[1] == "list") {
        if (n != 5) bad("expected 'property list COUNT_TYPE ITEM_TYPE NAME'");
        if (!scalar_from_name(tok[2], p.count_type)) bad("unknown type " + quote(tok[2]));
        if (!scalar_from_name(tok[3], p.type)) bad("unknown type " + quote(tok[3]));
        if (is_float(p.count_type)) bad("list count type must be an integer type");
        p.is_list = true;
        p.name = std::string(tok[4]);
      } else {
        if (n != 3) bad("expected 'property TYPE NAME'");
        if (!scalar_from_name(tok[1], p.type)) bad("unknown type " + quote(tok[1]));
        p.name = std::string(tok[2]);
      }
      // (Only where the reader looks: an element it skips may repeat a name.)
      const std::string& element = h.elements.back().name;
      for (const Property& earlier : h.elements.back().props)
        if ((element == "vertex" || element == "face") && earlier.name == p.name)
          bad("property " + quote(p.name) + " declared twice in element '" + h.elements.back().name + "'");
      h.elements.back().props.push_back(std::move(p));
    } else {
      bad("unknown header keyword " + quote(kw));
    }
  }
  if (!ended) format_error(name, "header has no end_header line");
  if (!have_format) format_error(name, "header has no format line");
  h.data_offset = lines.offset();
  h.data_line = lines.line() + 1;
  return h;
}

// ---- value sources -----------------------------------------------------------
// The element loop is written once as a template over these two readers.

template <typename T>
T load_le(const unsigned char* p) {
  T v;
  std::memcpy(&v, p, sizeof(T));
  return v;
}

class BinarySource {
 public:
  BinarySource(std::string_view data, bool big_endian, const std::string& name)
      : p_(reinterpret_cast<const unsigned char*>(data.data())),
        end_(p_ + data.size()),
        big_(big_endian),
        name_(name) {}

  void begin(const char* element, std::uint64_t index) {
    element_ = element;
    index_ = index;
  }
  [[noreturn]] void fail(const std::string& what) const {
    format_error(name_, std::string(element_) + " " + std::to_string(index_) + ": " + what);
  }
  /// The next byte to read.
  const unsigned char* position() const { return p_; }

  double scalar(Scalar t) {
    const unsigned char* p = take(scalar_size(t));
    switch (t) {
      case Scalar::kI8: return static_cast<std::int8_t>(p[0]);
      case Scalar::kU8: return p[0];
      case Scalar::kI16: return load_le<std::int16_t>(p);
      case Scalar::kU16: return load_le<std::uint16_t>(p);
      case Scalar::kI32: return load_le<std::int32_t>(p);
      case Scalar::kU32: return load_le<std::uint32_t>(p);
      case Scalar::kF32: return load_le<float>(p);
      case Scalar::kF64: return load_le<double>(p);
    }
    return 0;
  }

  /// An integer-typed value (list counts and vertex indices).
  long long integer(Scalar t) {
    if (is_float(t)) fail("vertex indices must have an integer type");
    return static_cast<long long>(scalar(t));  // exact: at most 32-bit integers
  }

  /// Skips `n` items of type t; the caller has checked n against remaining().
  void skip(Scalar t, std::uint64_t n) {
    const std::uint64_t bytes = n * static_cast<std::uint64_t>(scalar_size(t));
    if (bytes > remaining()) fail("truncated");
    p_ += bytes;
  }

  /// Upper bound on how many more items of `size` bytes can follow.
  std::uint64_t max_items(int size) const { return remaining() / static_cast<std::uint64_t>(size); }

  /// After the last element: no data may follow (a header whose counts fall short of
  /// the data would drop the rest silently). Trailing whitespace or NUL bytes (a
  /// writer's final newline, padding to a block) are not data: other readers (rply,
  /// plyfile, Open3D) accept them, and no real file we have ends in anything else.
  void check_end() const {
    for (const unsigned char* q = p_; q != end_; ++q)
      if (!(*q == 0 || *q == '\n' || *q == '\r' || *q == ' ' || *q == '\t'))
        format_error(name_, std::to_string(remaining()) + (remaining() == 1 ? " byte" : " bytes") +
                                " after the last element the header declares (its counts are short of the data)");
  }

 private:
  std::uint64_t remaining() const { return static_cast<std::uint64_t>(end_ - p_); }

  const unsigned char* take(int n) {
    if (remaining() < static_cast<std::uint64_t>(n)) fail("truncated");
    const unsigned char* p = p_;
    p_ += n;
    if (!big_) return p;
    for (int i = 0; i < n; ++i) swapped_[i] = p[n - 1 - i];
    return swapped_;
  }

  const unsigned char* p_;
  const unsigned char* end_;
  bool big_;
  const std::string& name_;
  const char* element_ = "";
  std::uint64_t index_ = 0;
  unsigned char swapped_[8];
};

class AsciiSource {
 public:
  AsciiSource(std::string_view data, long long first_line, const std::string& name)
      : tok_(data, first_line), name_(name) {}

  void begin(const char* element, std::uint64_t index) {
    element_ = element;
    index_ = index;
    row_line_ = -1;
  }
  [[noreturn]] void fail(const std::string& what) const {
    // A value read from a later line than its row began on: the row was short (a
    // colour missing on some rows read the next row's x as red).
    const std::string hint = row_line_ >= 0 && tok_.line() != row_line_
                                 ? " (its row, line " + std::to_string(row_line_) +
                                       ", holds fewer values than the header's properties?)"
                                 : std::string();
    format_error(name_, "line " + std::to_string(tok_.line()) + ": " + element_ + " " +
                            std::to_string(index_) + ": " + what + hint);
  }

  double scalar(Scalar type) {
    const std::string_view t = next();
    double v;
    if (!io_detail::parse_double(t, v)) fail("bad number " + quote(t));
    // A binary value always fits its type; a written one must too (a uchar colour of
    // 300 or -5 was clamped silently). A signed type takes its unsigned twin's range as
    // well: writers that declare `char red` and write 0..255 are common, and such files
    // loaded before.
    double lo = 0, hi = 0;
    const char* type_name = nullptr;
    switch (type) {
      case Scalar::kI8: lo = -128, hi = 255, type_name = "char"; break;
      case Scalar::kU8: lo = 0, hi = 255, type_name = "uchar"; break;
      case Scalar::kI16: lo = -32768, hi = 65535, type_name = "short"; break;
      case Scalar::kU16: lo = 0, hi = 65535, type_name = "ushort"; break;
      case Scalar::kI32: lo = -2147483648.0, hi = 4294967295.0, type_name = "int"; break;
      case Scalar::kU32: lo = 0, hi = 4294967295.0, type_name = "uint"; break;
      case Scalar::kF32:
      case Scalar::kF64: break;
    }
    if (type_name && !(v >= lo && v <= hi))
      fail("value " + std::string(t) + " out of range for " + type_name + " (" + number(lo) + ".." + number(hi) + ")");
    return v;
  }

  static std::string number(double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.0f", v);
    return buf;
  }

  long long integer(Scalar) {
    const std::string_view t = next();
    long long v;
    if (!io_detail::parse_int(t, v)) fail("bad integer " + quote(t));
    return v;
  }

  void skip(Scalar, std::uint64_t n) {
    for (std::uint64_t i = 0; i < n; ++i) next();
  }

  /// Upper bound on how many more tokens can follow (each takes a byte and a separator).
  std::uint64_t max_items(int) const { return (tok_.remaining() + 1) / 2; }

  /// After the last element: only whitespace may follow (blank lines, a final CRLF,
  /// as the Stanford scans end); a value means the header's counts fall short of the data.
  void check_end() {
    std::string_view t;
    if (tok_.next(t))
      format_error(name_, "line " + std::to_string(tok_.line()) +
                              ": data after the last element the header declares (its counts are short of the data)");
  }

 private:
  std::string_view next() {
    std::string_view t;
    if (!tok_.next(t)) fail("unexpected end of file");
    if (row_line_ < 0) row_line_ = tok_.line();
    return t;
  }

  io_detail::Tokenizer tok_;
  const std::string& name_;
  const char* element_ = "";
  std::uint64_t index_ = 0;
  long long row_line_ = -1;  ///< the line the current row's first value is on
};

/// Smallest encoded size of one instance: bytes (binary) or tokens (ascii).
std::uint64_t min_instance_size(const Element& e, bool binary) {
  std::uint64_t s = 0;
  for (const Property& p : e.props)
    s += binary ? static_cast<std::uint64_t>(scalar_size(p.is_list ? p.count_type : p.type)) : 1;
  return s;
}

bool has_list(const Element& e) {
  for (const Property& p : e.props)
    if (p.is_list) return true;
  return false;
}

template <class Source>
long long list_length(Source& src, const Property& p) {
  const long long n = src.integer(p.count_type);
  if (n < 0) src.fail("negative list length " + std::to_string(n));
  if (static_cast<std::uint64_t>(n) > src.max_items(scalar_size(p.type)))
    src.fail("list length " + std::to_string(n) + " exceeds the remaining data");
  return n;
}

template <class Source>
void skip_instance(Source& src, const Element& e) {
  for (const Property& p : e.props) {
    if (p.is_list) src.skip(p.type, static_cast<std::uint64_t>(list_length(src, p)));
    else src.skip(p.type, 1);
  }
}

struct VertexLayout {
  int x = -1, y = -1, z = -1;
  int nx = -1, ny = -1, nz = -1;
  int r = -1, g = -1, b = -1;
  bool unit_colour = false;  // floating-point colours in [0, 1]
};

// Float colours a little outside 0..1 (a writer's rounding) are clamped, not refused.
constexpr double kUnitColourSlack = 1e-3;
std::string fmt_colour(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.6g", v);
  return buf;
}

// The vertices into `mesh`; with `chunk` > 0 and `emit`, `emit` is called after every
// `chunk` vertices (and after the last) and the vertices are cleared in between.
template <class Source>
void read_vertices(Source& src, const Element& e, const VertexLayout& L, Mesh& mesh, std::size_t chunk = 0,
                   const std::function<void(Mesh&)>& emit = {}) {
  const bool normals = L.nx >= 0, colours = L.r >= 0;
  const std::size_t reserve = chunk > 0 ? std::min<std::uint64_t>(chunk, e.count) : e.count;
  mesh.vertices.reserve(reserve);
  if (normals) mesh.normals.reserve(reserve);
  if (colours) mesh.colours.reserve(reserve);
  std::vector<double> v(e.props.size(), 0.0);
  for (std::uint64_t i = 0; i < e.count; ++i) {
    if (chunk > 0 && mesh.vertices.size() == chunk) {
      emit(mesh);
      mesh.vertices.clear();
      mesh.normals.clear();
      mesh.colours.clear();
    }
    src.begin("vertex", i);
    for (std::size_t k = 0; k < e.props.size(); ++k) {
      const Property& p = e.props[k];
      if (p.is_list) src.skip(p.type, static_cast<std::uint64_t>(list_length(src, p)));
      else v[k] = src.scalar(p.type);
    }
    const Vec3f pt(static_cast<float>(v[L.x]), static_cast<float>(v[L.y]), static_cast<float>(v[L.z]));
    if (const std::string why = io_detail::coordinate_problem(pt.x(), pt.y(), pt.z()); !why.empty())
      src.fail(why);
    mesh.vertices.push_back(pt);
    if (normals) {
      const Vec3f n(static_cast<float>(v[L.nx]), static_cast<float>(v[L.ny]), static_cast<float>(v[L.nz]));
      // A NaN normal went through every stage into the merged cloud and the mesh.
      if (!n.allFinite()) src.fail("non-finite normal");
      mesh.normals.push_back(n);
    }
    if (colours && L.unit_colour)
      for (const int c : {L.r, L.g, L.b})
        // Float colours are 0..1; a writer that stored 0..255 as floats came out white
        // (every channel clamped), NaN black. A rounding's overshoot is clamped.
        if (!(v[std::size_t(c)] >= -kUnitColourSlack && v[std::size_t(c)] <= 1 + kUnitColourSlack))
          src.fail("colour '" + e.props[std::size_t(c)].name + "' is " + fmt_colour(v[std::size_t(c)]) +
                   ", outside 0..1 (float colours are read as 0..1: 0..255 stored as floats?)");
    if (colours)
      mesh.colours.push_back(Rgb{io_detail::to_channel(v[L.r], L.unit_colour),
                                io_detail::to_channel(v[L.g], L.unit_colour),
                                io_detail::to_channel(v[L.b], L.unit_colour)});
  }
  if (chunk > 0 && !mesh.vertices.empty()) emit(mesh);
}

template <class Source>
void read_faces(Source& src, const Element& e, int list_prop, std::uint64_t vertex_count, Mesh& mesh) {
  mesh.faces.reserve(mesh.faces.size() + e.count);
  std::vector<int> poly;
  for (std::uint64_t i = 0; i < e.count; ++i) {
    src.begin("face", i);
    for (std::size_t k = 0; k < e.props.size(); ++k) {
      const Property& p = e.props[k];
      if (static_cast<int>(k) != list_prop) {
        if (p.is_list) src.skip(p.type, static_cast<std::uint64_t>(list_length(src, p)));
        else src.skip(p.type, 1);
        continue;
      }
      const long long n = list_length(src, p);
      poly.clear();
      for (long long c = 0; c < n; ++c) {
        const long long idx = src.integer(p.type);
        if (idx < 0 || static_cast<std::uint64_t>(idx) >= vertex_count)
          src.fail("vertex index " + std::to_string(idx) + " out of range (" +
                   std::to_string(vertex_count) + " vertices)");
        poly.push_back(static_cast<int>(idx));
      }
      // Fan triangulation; lines and points (fewer than 3 corners) carry no surface.
      for (std::size_t c = 2; c < poly.size(); ++c) mesh.faces.emplace_back(poly[0], poly[c - 1], poly[c]);
    }
  }
}

template <class Source>
Mesh read_body(Source& src, const Header& h, const std::string& name, std::uint64_t budget,
               bool binary, std::size_t chunk = 0, const std::function<void(Mesh&)>& emit = {}) {
  // Every declared count must fit in the data that follows before anything is
  // allocated: a hostile header can claim billions of vertices.
  const Element* vertex = nullptr;
  for (const Element& e : h.elements) {
    const std::uint64_t m = min_instance_size(e, binary);
    if (m > 0 && e.count > budget / m)
      format_error(name, "line " + std::to_string(e.header_line) + ": element '" + e.name +
                             "' declares " + std::to_string(e.count) +
                             " entries, more than the file holds");
    budget -= e.count * m;
    if (e.name == "vertex" && !vertex) vertex = &e;
  }
  if (!vertex) format_error(name, "no vertex element");
  if (vertex->count > static_cast<std::uint64_t>(std::numeric_limits<int>::max()))
    format_error(name, "too many vertices");

  VertexLayout L;
  L.x = vertex->find_scalar({"x"});
  L.y = vertex->find_scalar({"y"});
  L.z = vertex->find_scalar({"z"});
  if (L.x < 0 || L.y < 0 || L.z < 0)
    format_error(name, "line " + std::to_string(vertex->header_line) +
                           ": vertex element lacks x, y or z properties");
  L.nx = vertex->find_scalar({"nx", "normal_x"});
  L.ny = vertex->find_scalar({"ny", "normal_y"});
  L.nz = vertex->find_scalar({"nz", "normal_z"});
  if (L.nx < 0 || L.ny < 0 || L.nz < 0) L.nx = L.ny = L.nz = -1;
  L.r = vertex->find_scalar({"red", "r", "diffuse_red"});
  L.g = vertex->find_scalar({"green", "g", "diffuse_green"});
  L.b = vertex->find_scalar({"blue", "b", "diffuse_blue"});
  if (L.r < 0 || L.g < 0 || L.b < 0) L.r = L.g = L.b = -1;
  else L.unit_colour = is_float(vertex->props[L.r].type);

  Mesh mesh;
  for (const Element& e : h.elements) {
    if (e.props.empty() || e.count == 0) continue;
    if (&e == vertex) {
      read_vertices(src, e, L, mesh, chunk, emit);
      if (chunk > 0) {
        // Streamed: the points only; when nothing is declared after them, nothing may follow.
        bool last = true;
        for (const Element* f = &e + 1; f != h.elements.data() + h.elements.size(); ++f) last = last && f->count == 0;
        if (last) src.check_end();
        return mesh;
      }
      continue;
    }
    int list_prop = -1;
    if (e.name == "face") {
      list_prop = e.find("vertex_indices");
      if (list_prop < 0 || !e.props[list_prop].is_list) list_prop = e.find("vertex_index");
      if (list_prop >= 0 && !e.props[list_prop].is_list) list_prop = -1;
    }
    if (list_prop >= 0) {
      read_faces(src, e, list_prop, vertex->count, mesh);
    } else if (binary && !has_list(e)) {
      // Fixed-size unknown element: skip it in one step (already checked to fit).
      src.begin(e.name.c_str(), 0);
      src.skip(Scalar::kU8, e.count * min_instance_size(e, true));
    } else {
      for (std::uint64_t i = 0; i < e.count; ++i) {
        src.begin(e.name.c_str(), i);
        skip_instance(src, e);
      }
    }
  }
  src.check_end();
  return mesh;
}

}  // namespace

Mesh parse_ply(std::string_view bytes, const std::string& name) {
  const Header h = parse_header(bytes, name);
  const std::string_view data = bytes.substr(h.data_offset);
  if (h.encoding == Encoding::kAscii) {
    AsciiSource src(data, h.data_line, name);
    return read_body(src, h, name, (data.size() + 1) / 2, false);
  }
  BinarySource src(data, h.encoding == Encoding::kBinaryBe, name);
  return read_body(src, h, name, data.size(), true);
}

}  // namespace station

namespace station {

void stream_ply_points(const fs::path& path, std::size_t chunk, const std::function<void(const Cloud&)>& fn) {
  if (chunk == 0) chunk = 1;
  const std::string name = path.string();
  io_detail::refuse_special_file(name);
  const int fd = ::open(name.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) throw IoError(name + ": cannot open: " + std::strerror(errno));
  struct stat st {};
  if (::fstat(fd, &st) == 0 && S_ISDIR(st.st_mode)) {
    ::close(fd);
    throw IoError(name + ": cannot read: " + std::strerror(EISDIR));
  }
  if (::fstat(fd, &st) != 0 || st.st_size <= 0) {
    ::close(fd);
    throw IoError(name + ": cannot read (empty or unreadable)");
  }
  const std::size_t size = std::size_t(st.st_size);
  // Mapped, not read: the pages come and go with the walk, so a cloud larger than
  // memory streams through (only `chunk` points are held at a time).
  void* map = ::mmap(nullptr, size, PROT_READ, MAP_PRIVATE, fd, 0);
  ::close(fd);
  if (map == MAP_FAILED) throw IoError(name + ": cannot map: " + std::strerror(errno));
  ::madvise(map, size, MADV_SEQUENTIAL);
  struct Unmap {
    void* p;
    std::size_t n;
    ~Unmap() { ::munmap(p, n); }
  } unmap{map, size};
  const std::string_view bytes(static_cast<const char*>(map), size);
  const Header h = parse_header(bytes, name);
  const std::string_view data = bytes.substr(h.data_offset);
  Cloud c;
  // The pages read are handed back after each chunk (a mapped file's pages count as
  // the process's memory while they stay mapped).
  const long sys_page = ::sysconf(_SC_PAGESIZE);
  const std::size_t page = sys_page > 0 ? std::size_t(sys_page) : 4096;
  const char* const base = static_cast<const char*>(map);
  std::size_t released = 0;  // bytes from the start already handed back
  const auto release_to = [&](const char* upto) {
    const std::size_t end = std::size_t(upto - base) / page * page;
    if (end > released) {
      ::madvise(const_cast<char*>(base) + released, end - released, MADV_DONTNEED);
      released = end;
    }
  };
  std::function<const char*()> at;
  const std::function<void(Mesh&)> emit = [&](Mesh& m) {
    c.points.swap(m.vertices);
    c.normals.swap(m.normals);
    c.colours.swap(m.colours);
    fn(c);
    c.points.swap(m.vertices);
    c.normals.swap(m.normals);
    c.colours.swap(m.colours);
    if (at) release_to(at());
  };
  if (h.encoding == Encoding::kAscii) {
    AsciiSource src(data, h.data_line, name);
    read_body(src, h, name, (data.size() + 1) / 2, false, chunk, emit);
  } else {
    BinarySource src(data, h.encoding == Encoding::kBinaryBe, name);
    at = [&src] { return reinterpret_cast<const char*>(src.position()); };
    read_body(src, h, name, data.size(), true, chunk, emit);
  }
}

}  // namespace station
