// File-level I/O: reading whole files, format dispatch, and the writers. The
// format parsers live in ply_io.cpp, pcd_io.cpp, obj_io.cpp and off_io.cpp.
#include "core/io.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cstring>
#include <string>
#include <system_error>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/io_detail.h"

namespace station {

namespace {

[[noreturn]] void io_fail(const fs::path& path, const char* what, int err) {
  throw IoError(path.string() + ": " + what + ": " + std::strerror(err));
}

enum class Format { kUnknown, kPly, kPcd, kObj, kOff };

std::string lower_extension(const fs::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return ext;
}

/// Guesses the format from the first bytes when the extension says nothing.
Format sniff(std::string_view bytes) {
  io_detail::LineReader lines(bytes.substr(0, 4096));
  std::string_view line;
  for (int i = 0; i < 64 && lines.next(line); ++i) {
    line = io_detail::trim(line);
    if (line.empty()) continue;
    if (i == 0 && line == "ply") return Format::kPly;
    if (line[0] == '#') continue;  // PCD, OBJ and OFF comments
    const std::string_view word = line.substr(0, line.find_first_of(" \t"));
    if (word == "VERSION" || word == "FIELDS" || word == "COLUMNS") return Format::kPcd;
    if (word.size() >= 3 && word.substr(word.size() - 3) == "OFF" && word.size() <= 7) return Format::kOff;
    if (word == "v" || word == "vn" || word == "vt" || word == "f" || word == "o" || word == "g" ||
        word == "mtllib" || word == "usemtl" || word == "s")
      return Format::kObj;
    return Format::kUnknown;
  }
  return Format::kUnknown;
}

Format detect(const fs::path& path, std::string_view bytes) {
  const std::string ext = lower_extension(path);
  if (ext == ".ply") return Format::kPly;
  if (ext == ".pcd") return Format::kPcd;
  if (ext == ".obj") return Format::kObj;
  if (ext == ".off") return Format::kOff;
  return sniff(bytes);
}

[[noreturn]] void unknown_format(const fs::path& path) {
  throw FormatError(path.string() + ": unknown file format (expected PLY, PCD, OBJ or OFF)");
}

fs::path folder_of(const fs::path& path) {
  std::error_code ec;
  fs::path abs = fs::absolute(path, ec);
  return (ec ? path : abs).parent_path();
}

// ---- writing helpers ----------------------------------------------------------

void put_le(std::string& out, const void* p, std::size_t n) {
  out.append(static_cast<const char*>(p), n);  // little-endian host (checked in the readers)
}

/// Shortest text that reads back as the same float.
void put_float(std::string& out, float v) {
  char buf[32];
  const auto r = std::to_chars(buf, buf + sizeof(buf), v);
  out.append(buf, static_cast<std::size_t>(r.ptr - buf));
}

void put_int(std::string& out, long long v) {
  char buf[24];
  const auto r = std::to_chars(buf, buf + sizeof(buf), v);
  out.append(buf, static_cast<std::size_t>(r.ptr - buf));
}

std::string ply_bytes(const std::vector<Vec3f>& pts, const std::vector<Vec3f>& normals,
                      const std::vector<Rgb>& colours, const std::vector<Face>* faces,
                      PlyFormat format) {
  const bool binary = format == PlyFormat::kBinaryLittleEndian;
  std::string out = ply_header(pts.size(), !normals.empty(), !colours.empty(), faces ? faces->size() : 0,
                               faces != nullptr, format);
  const std::size_t per_vertex = 12 + (normals.empty() ? 0 : 12) + (colours.empty() ? 0 : 3);
  out.reserve(out.size() + pts.size() * (binary ? per_vertex : 3 * per_vertex) +
              (faces ? faces->size() * (binary ? 13 : 30) : 0));
  for (std::size_t i = 0; i < pts.size(); ++i) {
    if (binary) {
      put_ply_vertex(out, pts[i], normals.empty() ? nullptr : &normals[i], colours.empty() ? nullptr : &colours[i]);
    } else {
      for (int k = 0; k < 3; ++k) {
        if (k) out += ' ';
        put_float(out, pts[i][k]);
      }
      if (!normals.empty())
        for (int k = 0; k < 3; ++k) {
          out += ' ';
          put_float(out, normals[i][k]);
        }
      if (!colours.empty()) {
        for (int c : {int(colours[i].r), int(colours[i].g), int(colours[i].b)}) {
          out += ' ';
          put_int(out, c);
        }
      }
      out += '\n';
    }
  }
  if (faces) {
    for (const Face& f : *faces) {
      if (binary) {
        put_ply_face(out, f);
      } else {
        out += '3';
        for (int k = 0; k < 3; ++k) {
          out += ' ';
          put_int(out, f[k]);
        }
        out += '\n';
      }
    }
  }
  return out;
}

}  // namespace

bool same_file(const fs::path& a, const fs::path& b) {
  if (a.empty() || b.empty()) return false;
  std::error_code ea, eb, ec;
  if (fs::exists(a, ea) && fs::exists(b, eb)) {
    const bool same = fs::equivalent(a, b, ec);
    if (!ec) return same;
  }
  const fs::path ca = fs::weakly_canonical(fs::absolute(a, ea), ea), cb = fs::weakly_canonical(fs::absolute(b, eb), eb);
  if (ea || eb) return fs::absolute(a, ea).lexically_normal() == fs::absolute(b, eb).lexically_normal();
  return ca == cb;
}

std::string ply_header(std::size_t vertices, bool normals, bool colours, std::size_t faces, bool with_faces,
                       PlyFormat format) {
  std::string out = "ply\nformat ";
  out += format == PlyFormat::kBinaryLittleEndian ? "binary_little_endian" : "ascii";
  out += " 1.0\ncomment turntable station\nelement vertex " + std::to_string(vertices) +
         "\nproperty float x\nproperty float y\nproperty float z\n";
  if (normals) out += "property float nx\nproperty float ny\nproperty float nz\n";
  if (colours) out += "property uchar red\nproperty uchar green\nproperty uchar blue\n";
  if (with_faces) out += "element face " + std::to_string(faces) + "\nproperty list uchar int vertex_indices\n";
  out += "end_header\n";
  return out;
}

void put_ply_vertex(std::string& out, const Vec3f& p, const Vec3f* normal, const Rgb* colour) {
  put_le(out, p.data(), 12);
  if (normal) put_le(out, normal->data(), 12);
  if (colour) {
    const unsigned char c[3] = {colour->r, colour->g, colour->b};
    put_le(out, c, 3);
  }
}

void put_ply_face(std::string& out, const Face& f) {
  out += static_cast<char>(3);
  const std::int32_t idx[3] = {f[0], f[1], f[2]};
  put_le(out, idx, 12);
}

namespace io_detail {

void refuse_special_file(const std::string& name) {
  struct stat st {};
  if (::stat(name.c_str(), &st) == 0 && !S_ISREG(st.st_mode) && !S_ISDIR(st.st_mode))
    throw IoError(name + ": cannot read: not a regular file (a device, FIFO or socket)");
}

}  // namespace io_detail

std::string read_file_bytes(const fs::path& path) {
  io_detail::refuse_special_file(path.string());
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) io_fail(path, "cannot open", errno);
  struct Closer {
    int fd;
    ~Closer() { ::close(fd); }
  } closer{fd};
  struct stat st {};
  if (::fstat(fd, &st) != 0) io_fail(path, "cannot stat", errno);
  if (S_ISDIR(st.st_mode)) io_fail(path, "cannot read", EISDIR);
  std::string out;
  if (S_ISREG(st.st_mode) && st.st_size > 0) out.reserve(static_cast<std::size_t>(st.st_size));
  char buf[1 << 16];
  while (true) {
    const ssize_t n = ::read(fd, buf, sizeof(buf));
    if (n < 0) {
      if (errno == EINTR) continue;
      io_fail(path, "cannot read", errno);
    }
    if (n == 0) break;
    out.append(buf, static_cast<std::size_t>(n));
  }
  return out;
}

Cloud read_cloud(const fs::path& path) {
  const std::string bytes = read_file_bytes(path);
  const std::string name = path.string();
  switch (detect(path, bytes)) {
    case Format::kPly: return parse_ply(bytes, name).as_cloud();
    case Format::kPcd: return parse_pcd(bytes, name);
    case Format::kObj: return parse_obj(bytes, name).mesh.as_cloud();
    case Format::kOff: return parse_off(bytes, name).as_cloud();
    case Format::kUnknown: break;
  }
  unknown_format(path);
}

namespace {

// Any supported file as a textured mesh (clouds: no faces); the one dispatcher
// behind read_mesh and read_textured_mesh.
TexturedMesh parse_any_mesh(const fs::path& path, const std::string& bytes) {
  const std::string name = path.string();
  TexturedMesh t;
  switch (detect(path, bytes)) {
    case Format::kPly: t.mesh = parse_ply(bytes, name); return t;
    case Format::kObj: return parse_obj(bytes, name, folder_of(path));
    case Format::kOff: t.mesh = parse_off(bytes, name); return t;
    case Format::kPcd: {
      // A point cloud is a mesh without faces.
      Cloud c = parse_pcd(bytes, name);
      t.mesh.vertices = std::move(c.points);
      t.mesh.normals = std::move(c.normals);
      t.mesh.colours = std::move(c.colours);
      return t;
    }
    case Format::kUnknown: break;
  }
  unknown_format(path);
}

}  // namespace

Mesh read_mesh(const fs::path& path) {
  return parse_any_mesh(path, read_file_bytes(path)).mesh;
}

TexturedMesh read_textured_mesh(const fs::path& path) {
  return parse_any_mesh(path, read_file_bytes(path));
}

void write_ply(const fs::path& path, const Mesh& mesh, PlyFormat format) {
  const std::string what = path.string();
  mesh.check_consistent(what.c_str());
  write_file_atomic(path, ply_bytes(mesh.vertices, mesh.normals, mesh.colours, &mesh.faces, format));
}

void write_ply(const fs::path& path, const Cloud& cloud, PlyFormat format) {
  const std::string what = path.string();
  cloud.check_consistent(what.c_str());
  write_file_atomic(path, ply_bytes(cloud.points, cloud.normals, cloud.colours, nullptr, format));
}

void write_obj(const fs::path& path, const Mesh& mesh) { write_obj(path, mesh, {}); }

void write_obj(const fs::path& path, const Mesh& mesh, const std::vector<Vec2f>& corner_uv) {
  const std::string what = path.string();
  mesh.check_consistent(what.c_str());
  const bool uv = !corner_uv.empty();
  if (uv && corner_uv.size() != 3 * mesh.faces.size())
    throw InvalidInput(what + ": " + std::to_string(corner_uv.size()) + " texture coordinates for " +
                       std::to_string(mesh.faces.size()) + " faces (3 per face expected)");
  for (const Vec2f& t : corner_uv)
    if (!t.allFinite()) throw InvalidInput(what + ": non-finite texture coordinate");
  std::string out = "# turntable station\n";
  out.reserve(mesh.vertices.size() * 60 + mesh.faces.size() * 40);
  for (std::size_t i = 0; i < mesh.vertices.size(); ++i) {
    out += 'v';
    for (int k = 0; k < 3; ++k) {
      out += ' ';
      put_float(out, mesh.vertices[i][k]);
    }
    if (mesh.has_colours()) {
      const Rgb& c = mesh.colours[i];
      for (int ch : {int(c.r), int(c.g), int(c.b)}) {
        out += ' ';
        put_float(out, static_cast<float>(ch) / 255.f);
      }
    }
    out += '\n';
  }
  for (const Vec3f& n : mesh.normals) {
    out += "vn";
    for (int k = 0; k < 3; ++k) {
      out += ' ';
      put_float(out, n[k]);
    }
    out += '\n';
  }
  for (const Vec2f& t : corner_uv) {
    out += "vt ";
    put_float(out, t.x());
    out += ' ';
    put_float(out, t.y());
    out += '\n';
  }
  for (std::size_t fi = 0; fi < mesh.faces.size(); ++fi) {
    const Face& f = mesh.faces[fi];
    out += 'f';
    for (int k = 0; k < 3; ++k) {
      out += ' ';
      put_int(out, f[k] + 1LL);
      if (uv) {
        out += '/';
        put_int(out, static_cast<long long>(3 * fi + k) + 1LL);
      }
      if (mesh.has_normals()) {
        out += uv ? "/" : "//";
        put_int(out, f[k] + 1LL);
      }
    }
    out += '\n';
  }
  write_file_atomic(path, out);
}

void write_mesh(const fs::path& path, const Mesh& mesh) {
  const std::string ext = lower_extension(path);
  if (ext == ".ply") return write_ply(path, mesh);
  if (ext == ".obj") return write_obj(path, mesh);
  throw InvalidInput(path.string() + ": cannot write meshes as '" + ext + "' (use .ply or .obj)");
}

}  // namespace station
