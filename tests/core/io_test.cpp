#include "core/io.h"

#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <functional>
#include <limits>
#include <random>
#include <sstream>
#include <unordered_map>

#include <sys/stat.h>
#include <unistd.h>

#include "core/error.h"
#include "core/texture.h"
#include "test_util.h"

namespace station {
namespace {

// ---- helpers --------------------------------------------------------------------

fs::path fixture(const std::string& name) { return test::source_dir() / "tests" / "data" / "io" / name; }

void write_bytes(const fs::path& p, const std::string& bytes) {
  std::ofstream out(p, std::ios::binary);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

std::string slurp(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

/// Runs f, expects error type E, returns its message (empty + test failure otherwise).
template <class E>
std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const E& e) {
    return e.what();
  } catch (const std::exception& e) {
    ADD_FAILURE() << "wrong exception type: " << e.what();
    return {};
  }
  ADD_FAILURE() << "no exception thrown";
  return {};
}

/// Expects parse(bytes) to throw FormatError whose message starts with NAME and contains `part`.
template <class Parse>
void expect_format_error(Parse parse, const std::string& bytes, const std::string& part) {
  const std::string msg = error_of<FormatError>([&] { parse(bytes, "input.x"); });
  EXPECT_EQ(msg.rfind("input.x: ", 0), 0u) << msg;
  EXPECT_NE(msg.find(part), std::string::npos) << "message: " << msg << "\nexpected part: " << part;
  EXPECT_EQ(msg.find('\n'), std::string::npos) << "multi-line message: " << msg;
}

auto ply = [](const std::string& b, const std::string& n) { return parse_ply(b, n); };
auto pcd = [](const std::string& b, const std::string& n) { return parse_pcd(b, n); };
auto obj = [](const std::string& b, const std::string& n) { return parse_obj(b, n); };
auto off = [](const std::string& b, const std::string& n) { return parse_off(b, n); };

template <class T>
void put(std::string& s, T v, bool big_endian = false) {
  char b[sizeof(T)];
  std::memcpy(b, &v, sizeof(T));
  if (big_endian) std::reverse(b, b + sizeof(T));
  s.append(b, sizeof(T));
}

Mesh coloured_sphere() {
  Mesh m = test::icosphere(2, 0.3, Vec3f(0.1f, -0.2f, 1.5f));
  m.normals = vertex_normals(m);
  std::mt19937 rng(7);
  for (std::size_t i = 0; i < m.vertices.size(); ++i)
    m.colours.push_back(Rgb{std::uint8_t(rng()), std::uint8_t(rng()), std::uint8_t(rng())});
  return m;
}

void expect_same_mesh(const Mesh& a, const Mesh& b) {
  EXPECT_EQ(a.vertices, b.vertices);
  EXPECT_EQ(a.normals, b.normals);
  EXPECT_EQ(a.colours, b.colours);
  EXPECT_EQ(a.faces, b.faces);
}

/// Greedy LZF compressor (hash of 3 bytes, 8 KiB window), written for the tests.
std::string lzf_compress(const std::string& in) {
  std::string out, lit;
  auto flush = [&] {
    for (std::size_t s = 0; s < lit.size(); s += 32) {
      const std::size_t n = std::min<std::size_t>(32, lit.size() - s);
      out += char(n - 1);
      out.append(lit, s, n);
    }
    lit.clear();
  };
  std::unordered_map<std::string, std::size_t> last;
  std::size_t i = 0;
  while (i < in.size()) {
    if (i + 3 <= in.size()) {
      const std::string key = in.substr(i, 3);
      auto it = last.find(key);
      const bool found = it != last.end() && i - it->second <= 8192;
      const std::size_t ref = found ? it->second : 0;
      last[key] = i;
      if (found) {
        std::size_t len = 0;
        while (i + len < in.size() && len < 264 && in[ref + len] == in[i + len]) ++len;
        flush();
        const std::size_t off = i - ref - 1, l = len - 2;
        if (l < 7) {
          out += char((l << 5) | (off >> 8));
        } else {
          out += char((7 << 5) | (off >> 8));
          out += char(l - 7);
        }
        out += char(off & 0xff);
        i += len;
        continue;
      }
    }
    lit += in[i++];
  }
  flush();
  return out;
}

std::string pcd_header(const std::string& fields, const std::string& size, const std::string& type,
                       const std::string& count, std::size_t w, std::size_t h, const std::string& data) {
  return "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS " + fields + "\nSIZE " + size +
         "\nTYPE " + type + "\nCOUNT " + count + "\nWIDTH " + std::to_string(w) + "\nHEIGHT " +
         std::to_string(h) + "\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS " + std::to_string(w * h) + "\nDATA " +
         data + "\n";
}

const float kNan = std::numeric_limits<float>::quiet_NaN();

// ---- PLY --------------------------------------------------------------------------

TEST(IoPly, BinaryRoundTripIsExact) {
  test::TempDir dir;
  const Mesh m = coloured_sphere();
  write_ply(dir / "m.ply", m);
  expect_same_mesh(read_mesh(dir / "m.ply"), m);
  EXPECT_EQ(slurp(dir / "m.ply").find("format binary_little_endian 1.0"), 4u);
}

TEST(IoPly, AsciiRoundTripIsExact) {
  test::TempDir dir;
  const Mesh m = coloured_sphere();
  write_ply(dir / "m.ply", m, PlyFormat::kAscii);
  EXPECT_NE(slurp(dir / "m.ply").find("format ascii 1.0"), std::string::npos);
  expect_same_mesh(read_mesh(dir / "m.ply"), m);
}

TEST(IoPly, CloudRoundTripHasNoFaces) {
  test::TempDir dir;
  Cloud c;
  c.points = {Vec3f(1e-7f, -3.25f, 1e6f), Vec3f(0, 0, 0)};
  c.colours = {Rgb{0, 128, 255}, Rgb{1, 2, 3}};
  for (PlyFormat f : {PlyFormat::kBinaryLittleEndian, PlyFormat::kAscii}) {
    write_ply(dir / "c.ply", c, f);
    EXPECT_EQ(slurp(dir / "c.ply").find("element face"), std::string::npos);
    const Cloud r = read_cloud(dir / "c.ply");
    EXPECT_EQ(r.points, c.points);
    EXPECT_TRUE(r.normals.empty());
    EXPECT_EQ(r.colours, c.colours);
  }
}

TEST(IoPly, WriterRejectsInconsistentMesh) {
  test::TempDir dir;
  Mesh m = test::box(Vec3f::Zero(), Vec3f::Ones());
  m.normals.resize(3);
  EXPECT_THROW(write_ply(dir / "bad.ply", m), InvalidInput);
  EXPECT_FALSE(fs::exists(dir / "bad.ply"));
}

TEST(IoPly, BigEndianWithMixedTypes) {
  std::string b =
      "ply\nformat binary_big_endian 1.0\ncomment hand-built\n"
      "element vertex 3\nproperty double x\nproperty int16 y\nproperty float z\n"
      "property uchar red\nproperty uchar green\nproperty uchar blue\n"
      "element face 1\nproperty list uint16 uint32 vertex_indices\nend_header\n";
  const double xs[3] = {0.5, -1.25, 3.0};
  const std::int16_t ys[3] = {-7, 300, 0};
  const float zs[3] = {1.5f, 2.5f, -0.125f};
  for (int i = 0; i < 3; ++i) {
    put(b, xs[i], true);
    put(b, ys[i], true);
    put(b, zs[i], true);
    b += char(10 * i);
    b += char(200);
    b += char(255);
  }
  put<std::uint16_t>(b, 3, true);
  for (std::uint32_t i : {2u, 0u, 1u}) put(b, i, true);
  const Mesh m = parse_ply(b, "be.ply");
  ASSERT_EQ(m.vertices.size(), 3u);
  EXPECT_EQ(m.vertices[0], Vec3f(0.5f, -7, 1.5f));
  EXPECT_EQ(m.vertices[1], Vec3f(-1.25f, 300, 2.5f));
  EXPECT_EQ(m.vertices[2], Vec3f(3, 0, -0.125f));
  ASSERT_EQ(m.colours.size(), 3u);
  EXPECT_EQ(m.colours[2], (Rgb{20, 200, 255}));
  ASSERT_EQ(m.faces.size(), 1u);
  EXPECT_EQ(m.faces[0], Face(2, 0, 1));
}

TEST(IoPly, PropertyOrderTypesAndPolygons) {
  const Mesh m = read_mesh(fixture("polygons.ply"));
  ASSERT_EQ(m.vertices.size(), 6u);
  EXPECT_EQ(m.vertices[1], Vec3f(1, 0, 0.5f));
  EXPECT_EQ(m.vertices[3], Vec3f(0, 1, 0.5f));
  EXPECT_EQ(m.vertices[4], Vec3f(0, 2, -1.5f));
  ASSERT_EQ(m.normals.size(), 6u);
  EXPECT_EQ(m.normals[0], Vec3f(0, 0, 1));  // nx ny nz listed as nz nx ny
  EXPECT_EQ(m.normals[4], Vec3f(1, 0, 0));
  ASSERT_EQ(m.colours.size(), 6u);  // float colours in [0,1] scaled to 0..255
  EXPECT_EQ(m.colours[0], (Rgb{0, 128, 255}));
  EXPECT_EQ(m.colours[3], (Rgb{255, 51, 255}));
  // A quad (2 triangles) and a pentagon (3), fan-triangulated.
  ASSERT_EQ(m.faces.size(), 5u);
  EXPECT_EQ(m.faces[0], Face(0, 1, 2));
  EXPECT_EQ(m.faces[1], Face(0, 2, 3));
  EXPECT_EQ(m.faces[2], Face(0, 1, 5));
  EXPECT_EQ(m.faces[4], Face(0, 4, 3));
}

TEST(IoPly, UnknownElementWithListsIsSkipped) {
  // Like the Stanford range scans: element range_grid with a list property.
  const Mesh m = read_mesh(fixture("range_grid.ply"));
  ASSERT_EQ(m.vertices.size(), 4u);
  EXPECT_EQ(m.vertices[3], Vec3f(1, 1, 0.5f));
  EXPECT_TRUE(m.faces.empty());
  EXPECT_TRUE(m.colours.empty());
}

TEST(IoPly, BinaryUnknownElementsBeforeAndAfterVertices) {
  std::string b =
      "ply\nformat binary_little_endian 1.0\n"
      "element camera 2\nproperty float view_px\nproperty list int int ids\nproperty double k\n"
      "element vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty float confidence\n"
      "element face 1\nproperty list uchar int vertex_indices\nproperty list uchar float texcoord\n"
      "element blob 3\nproperty uchar a\nproperty short b\n"
      "end_header\n";
  for (int i = 0; i < 2; ++i) {
    put(b, 1.f);
    put<std::int32_t>(b, i + 1);
    for (int k = 0; k <= i; ++k) put<std::int32_t>(b, 99);
    put(b, 2.0);
  }
  for (float v : {1.f, 2.f, 3.f, 0.5f, 4.f, 5.f, 6.f, 0.7f}) put(b, v);
  b += char(3);
  for (int i : {0, 1, 1}) put<std::int32_t>(b, i);
  b += char(6);
  for (int i = 0; i < 6; ++i) put(b, 0.25f);
  b += std::string(9, '\x01');
  const Mesh m = parse_ply(b, "skip.ply");
  ASSERT_EQ(m.vertices.size(), 2u);
  EXPECT_EQ(m.vertices[1], Vec3f(4, 5, 6));
  ASSERT_EQ(m.faces.size(), 1u);
  EXPECT_EQ(m.faces[0], Face(0, 1, 1));
  // One byte short in the trailing unknown element: truncated.
  expect_format_error(ply, b.substr(0, b.size() - 1), "truncated");
}

TEST(IoPly, ReadsCrlfAsciiAndAliases) {
  const std::string b =
      "ply\r\nformat ascii 1.0\r\nelement vertex 2\r\nproperty float32 x\r\nproperty float64 y\r\n"
      "property int8 z\r\nproperty uint8 r\r\nproperty uint8 g\r\nproperty uint8 b\r\nend_header\r\n"
      "1 2 3 4 5 6\r\n+7 -8e0 -9 255 0 0\r\n";
  const Mesh m = parse_ply(b, "crlf.ply");
  ASSERT_EQ(m.vertices.size(), 2u);
  EXPECT_EQ(m.vertices[1], Vec3f(7, -8, -9));
  ASSERT_EQ(m.colours.size(), 2u);
  EXPECT_EQ(m.colours[0], (Rgb{4, 5, 6}));
  EXPECT_EQ(m.colours[1], (Rgb{255, 0, 0}));  // (out of range is refused: AsciiValuesMustFitTheirType)
}

const std::string kAsciiHead =
    "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    "element face 1\nproperty list uchar int vertex_indices\nend_header\n";

TEST(IoPly, MalformedInputsAreFormatErrors) {
  expect_format_error(ply, "", "empty");
  expect_format_error(ply, "plx\nformat ascii 1.0\nend_header\n", "not a PLY");
  expect_format_error(ply, "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "end_header");
  expect_format_error(ply, "ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n",
                      "line 4: unknown type 'quad'");
  expect_format_error(ply, "ply\nformat xml 1.0\nend_header\n", "line 2");
  expect_format_error(ply, "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n0 0\n",
                      "lacks x, y or z");
  expect_format_error(ply, "ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no vertex element");
  expect_format_error(ply, kAsciiHead + "0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n", "index 3 out of range");
  expect_format_error(ply, kAsciiHead + "0 0 0\n1 0 0\n0 1 0\n3 0 1 -1\n", "out of range");
  expect_format_error(ply, kAsciiHead + "0 0 0\n1 0 0\n0 1 0\n", "element 'face' declares 1 entries");
  expect_format_error(ply, kAsciiHead + "0 0 0\n1 0 0\n0 1 0\n3 0 1\n", "line 13: face 0: unexpected end of file");
  expect_format_error(ply, kAsciiHead + "0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n", "line 11: vertex 1: non-finite");
  expect_format_error(ply, kAsciiHead + "0 0 0\n1 0 inf\n0 1 0\n3 0 1 2\n", "non-finite");
  // Finite but absurd: a corrupt file or wrong units, refused before it overflows a later stage.
  expect_format_error(ply, kAsciiHead + "0 0 0\n1 0 -1e38\n0 1 0\n3 0 1 2\n",
                      "line 11: vertex 1: coordinate 1e+38 is beyond +-1e9");
  EXPECT_EQ(parse_ply(kAsciiHead + "0 0 0\n1 0 -9e8\n0 1 0\n3 0 1 2\n", "big.ply").vertices[1].z(), -9e8f);
  // A NaN normal went through registration into the merged cloud: refused by name.
  const std::string with_normals =
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
      "property float nx\nproperty float ny\nproperty float nz\nend_header\n";
  expect_format_error(ply, with_normals + "0 0 0 0 0 1\n1 0 0 0 nan 1\n", "vertex 1: non-finite normal");
  EXPECT_EQ(parse_ply(with_normals + "0 0 0 0 0 1\n1 0 0 0 1 0\n", "n.ply").normals.size(), 2u);
  expect_format_error(ply, kAsciiHead + "0 0 0\n1 zero 0\n0 1 0\n3 0 1 2\n", "bad number 'zero'");
  // A row short of a colour reads the next row's x as red: said so.
  const std::string with_colours =
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
      "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n";
  expect_format_error(ply, with_colours + "0 0 0\n-0.5 1 0 10 20 30\n",
                      "line 12: vertex 0: value -0.5 out of range for uchar (0..255) (its row, line 11, holds fewer "
                      "values than the header's properties?)");
  expect_format_error(ply, kAsciiHead + "0 0 0\n1 0 0\n0 1 0\n200 0 1 2\n", "exceeds");
  // Float colours are 0..1: 0..255 stored as floats came out white, NaN black, exit 0.
  const std::string float_colours =
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
      "property float red\nproperty float green\nproperty float blue\nend_header\n";
  expect_format_error(ply, float_colours + "0 0 0 0.5 0.5 0.5\n1 0 0 0.5 128 0.5\n",
                      "line 12: vertex 1: colour 'green' is 128, outside 0..1 (float colours are read as 0..1: "
                      "0..255 stored as floats?)");
  expect_format_error(ply, float_colours + "0 0 0 nan 0.5 0.5\n1 0 0 0.5 0.5 0.5\n", "vertex 0: colour 'red' is nan");
  const Mesh rounded = parse_ply(float_colours + "0 0 0 1.0000001 -1e-7 0.5\n1 0 0 0 1 0.25\n", "f.ply");
  EXPECT_EQ(rounded.colours[0], (Rgb{255, 0, 128}));
  // A second vertex or face element, or a property twice: which one holds the data?
  // (The first was read and the rest skipped.)
  expect_format_error(ply,
                      "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty "
                      "float z\nelement vertex 1\nproperty float x\nend_header\n0 0 0\n1\n",
                      "line 7: a second 'element vertex' (the first is on line 3)");
  expect_format_error(ply,
                      "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty "
                      "float z\nproperty float x\nend_header\n0 0 0 1\n",
                      "line 7: property 'x' declared twice in element 'vertex'");
}

TEST(IoPly, BinaryTruncationAndHostileCounts) {
  const std::string head =
      "ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
      "property float z\nend_header\n";
  std::string b = head;
  for (float v : {1.f, 2.f, 3.f, 4.f, 5.f, 6.f}) put(b, v);
  EXPECT_EQ(parse_ply(b, "ok.ply").vertices.size(), 2u);
  expect_format_error(ply, b.substr(0, b.size() - 2), "more than the file holds");

  // Inf and NaN coordinates.
  std::string bad = b;
  const float inf = std::numeric_limits<float>::infinity();
  std::memcpy(&bad[head.size() + 16], &inf, 4);
  expect_format_error(ply, bad, "vertex 1: non-finite");
  std::memcpy(&bad[head.size() + 16], &kNan, 4);
  expect_format_error(ply, bad, "vertex 1: non-finite");
  const float far = 3e38f;
  std::memcpy(&bad[head.size() + 16], &far, 4);
  expect_format_error(ply, bad, "vertex 1: coordinate 3e+38 is beyond");

  // 2^31 vertices in a tiny file: refused before allocating.
  std::string huge = "ply\nformat binary_little_endian 1.0\nelement vertex 2147483648\nproperty float x\n"
                     "property float y\nproperty float z\nend_header\n" + std::string(24, '\0');
  expect_format_error(ply, huge, "line 3: element 'vertex' declares 2147483648 entries");

  // A face list whose length runs past the end of the data, binary.
  std::string f = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                  "property float z\nelement face 1\nproperty list int int vertex_indices\nend_header\n";
  for (int i = 0; i < 3; ++i) put(f, 0.f);
  put<std::int32_t>(f, 1 << 30);
  put<std::int32_t>(f, 0);
  expect_format_error(ply, f, "face 0: list length 1073741824 exceeds");
}

// A body with more data than the header declares used to load with the rest dropped
// silently; now it is an error naming the file. Trailing whitespace (blank lines, a
// final CRLF, as the Stanford scans end) is not data.
TEST(IoPly, DataBeyondTheDeclaredCountsIsAnError) {
  const std::string ascii = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                            "property float z\nend_header\n0 0 0\n1 0 0\n";
  EXPECT_EQ(parse_ply(ascii, "ok.ply").vertices.size(), 2u);
  EXPECT_EQ(parse_ply(ascii + "\r\n\n  \n", "ok.ply").vertices.size(), 2u);
  expect_format_error(ply, ascii + "0 1 0\n", "line 10: data after the last element the header declares");
  const std::string head = "ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n"
                           "property float y\nproperty float z\nend_header\n";
  std::string b = head;
  for (int i = 0; i < 9; ++i) put(b, float(i));  // 3 vertices' bytes, 2 declared
  expect_format_error(ply, b, "12 bytes after the last element the header declares");
  // A final newline or NUL padding after binary data is not data (other readers accept it).
  std::string b2 = head;
  for (int i = 0; i < 6; ++i) put(b2, float(i));
  EXPECT_EQ(parse_ply(b2 + "\n", "nl.ply").vertices.size(), 2u);
  EXPECT_EQ(parse_ply(b2 + std::string(3, '\0') + "\r\n", "pad.ply").vertices.size(), 2u);
  expect_format_error(ply, b2 + "\nx", "2 bytes after the last element");
  // Streamed (consolidate's and the blocks' reader) alike.
  const auto dir = std::filesystem::temp_directory_path() / ("station-ply-trailing-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  { std::ofstream(dir / "more.ply", std::ios::binary) << b; }
  const std::string msg = error_of<FormatError>([&] { stream_ply_points(dir / "more.ply", 1, [](const Cloud&) {}); });
  EXPECT_NE(msg.find("more.ply: 12 bytes after"), std::string::npos) << msg;
  std::filesystem::remove_all(dir);
}

// An ASCII value must fit its declared type: a uchar colour of 300 or -5 used to be
// clamped silently; now the error names the file, the line and the value.
TEST(IoPly, AsciiValuesMustFitTheirType) {
  const std::string head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                           "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
                           "end_header\n";
  EXPECT_EQ(parse_ply(head + "0.01 0.02 0.03 0 128 255\n1 2 3 4 5 6\n", "ok.ply").colours.size(), 2u);
  expect_format_error(ply, head + "0 0 0 1 2 3\n0.01 0.02 0.03 300 -5 50\n",
                      "line 12: vertex 1: value 300 out of range for uchar (0..255)");
  expect_format_error(ply, head + "0.01 0.02 0.03 30 -5 50\n0 0 0 1 2 3\n", "line 11: vertex 0: value -5 out of range");
  // A signed colour type written 0..255 (a common writer's mix-up) loads, as it did.
  std::string signed_head = head;
  for (const char* c : {"red", "green", "blue"})
    signed_head.replace(signed_head.find(std::string("uchar ") + c), 5, "char");
  const Mesh m = parse_ply(signed_head + "0 0 0 200 0 255\n1 1 1 1 2 3\n", "char.ply");
  ASSERT_EQ(m.colours.size(), 2u);
  EXPECT_EQ(m.colours[0], (Rgb{200, 0, 255}));
  expect_format_error(ply, signed_head + "0 0 0 256 0 0\n1 1 1 1 2 3\n", "value 256 out of range for char (-128..255)");
}

TEST(IoPly, AsciiReadIsFast) {
  test::TempDir dir;
  Cloud c;
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(-0.2f, 0.2f);
  for (int i = 0; i < 40000; ++i) c.points.emplace_back(u(rng), u(rng), u(rng));
  write_ply(dir / "big.ply", c, PlyFormat::kAscii);
  const auto t0 = std::chrono::steady_clock::now();
  const Cloud r = read_cloud(dir / "big.ply");
  const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  EXPECT_EQ(r.points, c.points);
#ifdef NDEBUG
  EXPECT_LT(ms, 100.0);
#endif
  std::cout << "[ info ] 40k-point ascii PLY read in " << ms << " ms\n";
}

// ---- PCD --------------------------------------------------------------------------

TEST(IoPcd, AsciiDropsNanPointsAndDecodesRgb) {
  const Cloud c = read_cloud(fixture("organised_ascii.pcd"));
  ASSERT_EQ(c.size(), 4u);
  EXPECT_EQ(c.points[0], Vec3f(0, 0, 1));
  EXPECT_EQ(c.points[3], Vec3f(1.5f, -1, 2.5f));
  ASSERT_EQ(c.colours.size(), 4u);
  EXPECT_EQ(c.colours[0], (Rgb{255, 0, 0}));
  EXPECT_EQ(c.colours[1], (Rgb{0, 255, 0}));
  EXPECT_EQ(c.colours[2], (Rgb{0, 0, 255}));
  EXPECT_EQ(c.colours[3], (Rgb{0x12, 0x34, 0x56}));
  EXPECT_TRUE(c.normals.empty());
}

TEST(IoPcd, AsciiFloatEncodedRgb) {
  // Older PCL writes rgb as the float that has the packed bits.
  std::uint32_t packed = 0x00ff8000;
  float as_float;
  std::memcpy(&as_float, &packed, 4);
  std::ostringstream s;
  s.precision(9);
  s << pcd_header("x y z rgb", "4 4 4 4", "F F F F", "1 1 1 1", 1, 1, "ascii") << "1 2 3 " << as_float << "\n";
  const Cloud c = parse_pcd(s.str(), "f.pcd");
  ASSERT_EQ(c.colours.size(), 1u);
  EXPECT_EQ(c.colours[0], (Rgb{255, 128, 0}));
}

/// Builds one binary point: x y z (F4), a 3-byte padding field, rgb (F4 with packed bits), normal (F4 x3).
struct BinPoint {
  float x, y, z;
  std::uint32_t rgb;
  float n[3];
};
const std::vector<BinPoint> kBinPoints = {
    {1, 2, 3, 0x00102030, {0, 0, 1}},
    {kNan, kNan, kNan, 0x00ffffff, {kNan, kNan, kNan}},
    {-1, 0.5f, 2, 0x00abcdef, {1, 0, 0}},
    {4, kNan, 4, 0, {0, 1, 0}},  // any NaN coordinate drops the point
};
const std::string kBinFields = "x y z _ rgb normal_x normal_y normal_z";
const std::string kBinSize = "4 4 4 1 4 4 4 4";
const std::string kBinType = "F F F U F F F F";
const std::string kBinCount = "1 1 1 3 1 1 1 1";

void expect_bin_points(const Cloud& c) {
  ASSERT_EQ(c.size(), 2u);
  EXPECT_EQ(c.points[0], Vec3f(1, 2, 3));
  EXPECT_EQ(c.points[1], Vec3f(-1, 0.5f, 2));
  ASSERT_EQ(c.colours.size(), 2u);
  EXPECT_EQ(c.colours[0], (Rgb{0x10, 0x20, 0x30}));
  EXPECT_EQ(c.colours[1], (Rgb{0xab, 0xcd, 0xef}));
  ASSERT_EQ(c.normals.size(), 2u);
  EXPECT_EQ(c.normals[1], Vec3f(1, 0, 0));
}

TEST(IoPcd, Binary) {
  std::string b = pcd_header(kBinFields, kBinSize, kBinType, kBinCount, 2, 2, "binary");
  for (const BinPoint& p : kBinPoints) {
    put(b, p.x), put(b, p.y), put(b, p.z);
    b += "pad";
    put(b, p.rgb);
    for (float v : p.n) put(b, v);
  }
  expect_bin_points(parse_pcd(b, "b.pcd"));
  expect_format_error(pcd, b.substr(0, b.size() - 1), "header declares 4");
}

std::string soa_bytes() {
  std::string raw;
  for (const BinPoint& p : kBinPoints) put(raw, p.x);
  for (const BinPoint& p : kBinPoints) put(raw, p.y);
  for (const BinPoint& p : kBinPoints) put(raw, p.z);
  for (std::size_t i = 0; i < kBinPoints.size(); ++i) raw += "pad";
  for (const BinPoint& p : kBinPoints) put(raw, p.rgb);
  for (int k = 0; k < 3; ++k)
    for (const BinPoint& p : kBinPoints) put(raw, p.n[k]);
  return raw;
}

std::string compressed_pcd(const std::string& raw, const std::string& packed) {
  std::string b = pcd_header(kBinFields, kBinSize, kBinType, kBinCount, 2, 2, "binary_compressed");
  put<std::uint32_t>(b, std::uint32_t(packed.size()));
  put<std::uint32_t>(b, std::uint32_t(raw.size()));
  return b + packed;
}

TEST(IoPcd, BinaryCompressed) {
  const std::string raw = soa_bytes();
  const std::string packed = lzf_compress(raw);
  EXPECT_LT(packed.size(), raw.size());  // the compressor really used back references
  expect_bin_points(parse_pcd(compressed_pcd(raw, packed), "c.pcd"));

  // A literal-only stream is valid LZF too.
  std::string literal;
  for (std::size_t s = 0; s < raw.size(); s += 32) {
    const std::size_t n = std::min<std::size_t>(32, raw.size() - s);
    literal += char(n - 1);
    literal += raw.substr(s, n);
  }
  expect_bin_points(parse_pcd(compressed_pcd(raw, literal), "lit.pcd"));
}

TEST(IoPcd, CompressedFixtureFromIndependentEncoder) {
  const Cloud c = read_cloud(fixture("organised_compressed.pcd"));
  ASSERT_EQ(c.size(), 10u);  // 12 pixels, 2 missing
  EXPECT_EQ(c.points[0], Vec3f(0, 0, 1));
  EXPECT_EQ(c.points[1], Vec3f(1, -0.5f, 3));  // pixel 2
  EXPECT_EQ(c.points[9], Vec3f(5.5f, -2.75f, 12));
  ASSERT_EQ(c.colours.size(), 10u);
  EXPECT_EQ(c.colours[1], (Rgb{20, 40, 253}));
  EXPECT_EQ(c.colours[9], (Rgb{110, 220, 244}));
  ASSERT_EQ(c.normals.size(), 10u);
  EXPECT_EQ(c.normals[4], Vec3f(0, 0, 1));
}

TEST(IoPcd, CorruptCompressedData) {
  const std::string raw = soa_bytes();
  const std::string packed = lzf_compress(raw);
  // Back reference before the start of the output.
  expect_format_error(pcd, compressed_pcd(raw, std::string("\x20\x05", 2) + packed), "corrupt LZF");
  // Stream shorter than declared.
  expect_format_error(pcd, compressed_pcd(raw, packed.substr(0, packed.size() - 4)), "corrupt LZF");
  // Declared compressed size beyond the file.
  std::string b = compressed_pcd(raw, packed);
  expect_format_error(pcd, b.substr(0, b.size() - 1), "bytes declared");
  // Uncompressed size disagreeing with the header.
  std::string hdr = pcd_header(kBinFields, kBinSize, kBinType, kBinCount, 2, 2, "binary_compressed");
  put<std::uint32_t>(hdr, 2);
  put<std::uint32_t>(hdr, 4000000000u);
  expect_format_error(pcd, hdr + "ab", "does not match");
  // Impossible expansion ratio with a hostile point count.
  std::string big = pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 100000000, 1, "binary_compressed");
  put<std::uint32_t>(big, 2);
  put<std::uint32_t>(big, 1200000000u);
  expect_format_error(pcd, big + "ab", "impossible");
}

TEST(IoPcd, MalformedInputsAreFormatErrors) {
  expect_format_error(pcd, "", "empty");
  expect_format_error(pcd, "VERSION 0.7\nFIELDS x y z\n", "no DATA");
  expect_format_error(pcd, "VERSION 9\nFIELDS x y z\nDATA ascii\n", "line 1: unsupported PCD version");
  expect_format_error(pcd, pcd_header("x y", "4 4", "F F", "1 1", 1, 1, "ascii") + "1 2\n", "x, y and z");
  expect_format_error(pcd, pcd_header("x y z", "4 4", "F F F", "1 1 1", 1, 1, "ascii"), "SIZE has 2");
  expect_format_error(pcd, pcd_header("x y z", "4 4 3", "F F F", "1 1 1", 1, 1, "ascii"), "size 3");
  expect_format_error(pcd, pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 2, 1, "ascii") + "1 2 3\n1 2 inf\n",
                      "point 1: non-finite");
  {
    // PCL's "not estimated" normals (NaN): the file's normals are dropped whole.
    const std::string head = pcd_header("x y z normal_x normal_y normal_z", "4 4 4 4 4 4", "F F F F F F",
                                        "1 1 1 1 1 1", 2, 1, "ascii");
    const Cloud some = parse_pcd(head + "1 2 3 0 0 1\n1 2 4 nan nan nan\n", "n.pcd");
    EXPECT_EQ(some.size(), 2u);
    EXPECT_TRUE(some.normals.empty());
    EXPECT_EQ(parse_pcd(head + "1 2 3 0 0 1\n1 2 4 0 1 0\n", "n.pcd").normals.size(), 2u);
  }
  expect_format_error(pcd, pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 2, 1, "ascii") + "1 2 3\n1 2 1e38\n",
                      "point 1: coordinate 1e+38 is beyond");
  expect_format_error(pcd, pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 1, 1, "ascii") + "1 2        \n",
                      "line 12: expected 3 values");
  expect_format_error(pcd, pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 1, 1, "ascii") + "1 2 q\n",
                      "bad number 'q'");
  expect_format_error(pcd, pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 2000000000, 1, "ascii") + "1 2 3\n",
                      "more than the file holds");
  expect_format_error(pcd, pcd_header("x y z", "4 4 4", "F F F", "1 1 1", 3000000000ull, 1, "binary") + "abc",
                      "header declares 3000000000");
  // Huge COUNTs (found by the fuzzer: once sized a 2.6 GB token buffer).
  const std::string counts = "FIELDS x y z a b\nCOUNT 1 1 1 16777216 16777216\n";
  EXPECT_TRUE(parse_pcd(counts + "POINTS 0\nDATA ascii\n", "c.pcd").empty());
  expect_format_error(pcd, counts + "POINTS 1\nDATA ascii\n1 2 3\n", "more than the file holds");
  expect_format_error(pcd, counts + "POINTS 1\nDATA binary\n1 2 3\n", "header declares 1");
  expect_format_error(pcd, "FIELDS x y z\nCOUNT 1 1 16777217\nPOINTS 0\nDATA ascii\n", "COUNT 16777217");
  // POINTS against WIDTH x HEIGHT (the campaign: a header saying 12 x 1 and POINTS 10
  // was read as 10 points, the two extra rows ignored).
  expect_format_error(pcd, "FIELDS x y z\nWIDTH 3\nHEIGHT 1\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 6\n7 8 9\n",
                      "header: POINTS 2 disagrees with WIDTH x HEIGHT = 3 x 1");
  expect_format_error(pcd, "FIELDS x y z\nWIDTH 3\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 6\n",
                      "(HEIGHT not given: 1)");
  EXPECT_EQ(parse_pcd("FIELDS x y z\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA ascii\n1 2 3\n4 5 6\n7 8 9\n1 1 1\n", "o.pcd").size(),
            4u);
  EXPECT_EQ(parse_pcd("FIELDS x y z\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 6\n", "p.pcd").size(), 2u);
}

// ---- OBJ --------------------------------------------------------------------------

TEST(IoObj, RoundTripWithColoursAndNormals) {
  test::TempDir dir;
  Mesh m = coloured_sphere();
  write_obj(dir / "m.obj", m);
  const Mesh r = read_mesh(dir / "m.obj");
  EXPECT_EQ(r.vertices, m.vertices);
  EXPECT_EQ(r.colours, m.colours);
  EXPECT_EQ(r.faces, m.faces);
  ASSERT_EQ(r.normals.size(), m.normals.size());
  for (std::size_t i = 0; i < m.normals.size(); ++i) EXPECT_TRUE(r.normals[i].isApprox(m.normals[i], 1e-6f));

  m.colours.clear();
  m.normals.clear();
  write_mesh(dir / "plain.OBJ", m);
  const std::string text = slurp(dir / "plain.OBJ");
  EXPECT_EQ(text.find("//"), std::string::npos);
  EXPECT_EQ(text.find("vn"), std::string::npos);
  expect_same_mesh(read_mesh(dir / "plain.OBJ"), m);
}

TEST(IoObj, RoundTripWithTextureCoordinates) {
  test::TempDir dir;
  Mesh m = coloured_sphere();
  std::vector<Vec2f> uv;
  for (std::size_t i = 0; i < 3 * m.faces.size(); ++i) uv.emplace_back(0.001f * float(i), 1.f - 0.0005f * float(i));
  write_obj(dir / "uv.obj", m, uv);
  const TexturedMesh t = read_textured_mesh(dir / "uv.obj");
  EXPECT_EQ(t.mesh.faces, m.faces);
  EXPECT_EQ(t.mesh.vertices, m.vertices);
  ASSERT_EQ(t.corner_uv.size(), uv.size());
  for (std::size_t i = 0; i < uv.size(); ++i) EXPECT_TRUE(t.corner_uv[i].isApprox(uv[i], 1e-6f)) << i;
  ASSERT_EQ(t.mesh.normals.size(), m.normals.size());  // f v/vt/vn
  uv.pop_back();
  EXPECT_THROW(write_obj(dir / "bad.obj", m, uv), InvalidInput);
  uv.push_back(Vec2f(std::nanf(""), 0));
  EXPECT_THROW(write_obj(dir / "bad.obj", m, uv), InvalidInput);
  EXPECT_FALSE(std::filesystem::exists(dir / "bad.obj"));
}

TEST(IoObj, TexturedFixture) {
  const TexturedMesh t = read_textured_mesh(fixture("textured_quad.obj"));
  ASSERT_EQ(t.mesh.vertices.size(), 5u);
  ASSERT_EQ(t.mesh.faces.size(), 3u);
  EXPECT_EQ(t.mesh.faces[0], Face(0, 1, 2));
  EXPECT_EQ(t.mesh.faces[1], Face(0, 2, 3));
  EXPECT_EQ(t.mesh.faces[2], Face(0, 2, 4));  // negative indices
  ASSERT_EQ(t.corner_uv.size(), 9u);
  EXPECT_EQ(t.corner_uv[4], Vec2f(1, 1));
  EXPECT_EQ(t.corner_uv[5], Vec2f(0, 1));
  EXPECT_EQ(t.corner_uv[8], Vec2f(0.5f, 0.5f));
  // vn 1 is (0,0,1) and vn 2 (0,0,2): normalised averages.
  ASSERT_EQ(t.mesh.normals.size(), 5u);
  for (const Vec3f& n : t.mesh.normals) EXPECT_TRUE(n.isApprox(Vec3f(0, 0, 1)));
  // usemtl picks "skin"; its map_Kd has options before the name and a trailing space.
  EXPECT_TRUE(t.texture.is_absolute());
  EXPECT_EQ(t.texture, fixture("skin_texture.jpg").lexically_normal());
}

TEST(IoObj, FaceCornerForms) {
  const std::string text =
      "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 1\nvn 0 0 1\n"
      "f 1 2 3\nf 2/1 4/2 3/1\nf 1//1 2//1 3//1\nf -4/-2/-1 -3/-1/-1 -2/-2/-1\n";
  const TexturedMesh t = parse_obj(text, "forms.obj");
  ASSERT_EQ(t.mesh.faces.size(), 4u);
  EXPECT_EQ(t.mesh.faces[1], Face(1, 3, 2));
  EXPECT_EQ(t.mesh.faces[3], Face(0, 1, 2));
  EXPECT_TRUE(t.corner_uv.empty());    // not every corner has a vt
  EXPECT_TRUE(t.mesh.normals.empty());  // nor a vn
  EXPECT_TRUE(t.texture.empty());
}

TEST(IoObj, MissingMaterialLibraryIsNotAnError) {
  test::TempDir dir;
  write_bytes(dir / "a.obj", "mtllib nowhere.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  const TexturedMesh t = read_textured_mesh(dir / "a.obj");
  EXPECT_EQ(t.mesh.faces.size(), 1u);
  EXPECT_TRUE(t.texture.empty());
  // ... but it is said (the texture was dropped without a word).
  EXPECT_EQ(t.material_problem, "its material library 'nowhere.mtl' could not be read in " + dir.path().string() +
                                    " (missing?): the mesh is read without its texture");
  // A library that is read and names no texture (colours only) is no problem.
  write_bytes(dir / "plain.mtl", "newmtl grey\nKd 0.5 0.5 0.5\n");
  write_bytes(dir / "b.obj", "mtllib plain.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  EXPECT_TRUE(read_textured_mesh(dir / "b.obj").material_problem.empty());
  write_bytes(dir / "c.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  EXPECT_TRUE(read_textured_mesh(dir / "c.obj").material_problem.empty());
}

TEST(IoObj, MalformedInputsAreFormatErrors) {
  const std::string tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
  expect_format_error(obj, tri + "f 1 2 4\n", "line 4: vertex index 4 out of range");
  expect_format_error(obj, tri + "f 0 1 2\n", "line 4: vertex index 0");
  expect_format_error(obj, tri + "f -4 1 2\n", "out of range");
  expect_format_error(obj, tri + "f 1/2 2/1 3/1\n", "texture index 2 out of range");
  expect_format_error(obj, tri + "f 1/1/1/1 2 3\n", "bad face corner");
  expect_format_error(obj, tri + "f 1 2 x\n", "bad vertex index 'x'");
  expect_format_error(obj, "v 0 0\n", "line 1: vertex needs x y z");
  expect_format_error(obj, "v 0 nan 0\n", "non-finite");
  expect_format_error(obj, "v 0 1e999 0\n", "non-finite");
  expect_format_error(obj, "v 0 2e10 0\n", "line 1: coordinate 2e+10 is beyond +-1e9");
  expect_format_error(obj, "v 0 0 0\nvn 1 2 y\n", "line 2: bad number 'y'");
  // Empty input is an empty mesh, not an error (OBJ has no magic).
  EXPECT_TRUE(parse_obj("", "e.obj").mesh.vertices.empty());
}

// ---- OFF --------------------------------------------------------------------------

TEST(IoOff, ColouredFixture) {
  const Mesh m = read_mesh(fixture("coloured.off"));
  ASSERT_EQ(m.vertices.size(), 4u);
  ASSERT_EQ(m.faces.size(), 3u);
  EXPECT_EQ(m.faces[1], Face(0, 2, 3));
  EXPECT_EQ(m.faces[2], Face(0, 2, 3));
  ASSERT_EQ(m.colours.size(), 4u);
  EXPECT_EQ(m.colours[1], (Rgb{0, 255, 0}));
  EXPECT_EQ(m.colours[3], (Rgb{10, 20, 30}));
}

TEST(IoOff, VariantsAndErrors) {
  const Mesh m = parse_off("OFF 3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "inline.off");
  EXPECT_EQ(m.faces.size(), 1u);
  const Mesh c = parse_off("COFF\n1 0 0\n0 0 0 1.0 0.5 0 1\n", "f.off");
  ASSERT_EQ(c.colours.size(), 1u);
  EXPECT_EQ(c.colours[0], (Rgb{255, 128, 0}));
  const Mesh n = parse_off("NOFF\n1 0 0\n0 0 0 0 1 0\n", "n.off");
  ASSERT_EQ(n.normals.size(), 1u);
  EXPECT_EQ(n.normals[0], Vec3f(0, 1, 0));

  expect_format_error(off, "", "empty");
  expect_format_error(off, "PLY\n", "not an OFF");
  expect_format_error(off, "4OFF\n1 0 0\n0 0 0 0\n", "unsupported");
  expect_format_error(off, "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n", "line 6: face 0: vertex index 3 out of range");
  expect_format_error(off, "OFF\n3 1 0\n0 0 0\n1 0 0\n", "exceed");
  expect_format_error(off, "OFF\n2 0 0\n0 0 0\n1 0\n\n\n\n\n\n\n", "line 4: vertex 1: expected 3");
  expect_format_error(off, "OFF\n1 0 0\n0 nan 0\n", "non-finite");
  expect_format_error(off, "OFF\n1 0 0\n0 3e20 0\n", "vertex 0: coordinate 3e+20 is beyond");
  expect_format_error(off, "OFF\n99999999 0 0\n0 0 0\n", "exceed the file size");
}

// ---- files and dispatch -----------------------------------------------------------

TEST(IoFiles, MissingFileIsAnIoError) {
  test::TempDir dir;
  const fs::path p = dir / "absent.ply";
  EXPECT_EQ(error_of<IoError>([&] { read_file_bytes(p); }),
            p.string() + ": cannot open: No such file or directory");
  EXPECT_THROW(read_cloud(p), IoError);
  EXPECT_THROW(read_mesh(p), IoError);
  EXPECT_THROW(read_textured_mesh(p), IoError);
  EXPECT_THROW(read_file_bytes(dir.path()), IoError);
}

// A device or a FIFO given as an input: refused by name (/dev/zero was read until
// memory ran out, a FIFO blocked the open for ever).
TEST(IoFiles, DevicesAndFifosAreRefused) {
  test::TempDir dir;
  const fs::path fifo = dir / "pipe.ply";
  ASSERT_EQ(::mkfifo(fifo.c_str(), 0666), 0);
  for (const fs::path& p : {fs::path("/dev/zero"), fifo}) {
    EXPECT_EQ(error_of<IoError>([&] { read_file_bytes(p); }),
              p.string() + ": cannot read: not a regular file (a device, FIFO or socket)");
    EXPECT_THROW(read_cloud(p), IoError);
    EXPECT_THROW(stream_ply_points(p, 1024, [](const Cloud&) {}), IoError);
  }
}

TEST(IoFiles, FormatErrorsNameTheFile) {
  test::TempDir dir;
  write_bytes(dir / "empty.ply", "");
  std::string msg = error_of<FormatError>([&] { read_mesh(dir / "empty.ply"); });
  EXPECT_EQ(msg.rfind((dir / "empty.ply").string() + ": ", 0), 0u) << msg;
  write_bytes(dir / "junk.xyz", "hello world\n");
  msg = error_of<FormatError>([&] { read_cloud(dir / "junk.xyz"); });
  EXPECT_EQ(msg.rfind((dir / "junk.xyz").string() + ": unknown file format", 0), 0u) << msg;
}

TEST(IoFiles, DispatchByExtensionAndMagic) {
  test::TempDir dir;
  const Mesh m = test::box(Vec3f::Zero(), Vec3f::Ones());
  write_ply(dir / "box.ply", m);
  fs::copy_file(dir / "box.ply", dir / "BOX.PLY");
  fs::copy_file(dir / "box.ply", dir / "box.bin");
  for (const char* n : {"box.ply", "BOX.PLY", "box.bin"}) expect_same_mesh(read_mesh(dir / n), m);

  write_obj(dir / "box.obj", m);
  fs::copy_file(dir / "box.obj", dir / "box_obj.txt");
  expect_same_mesh(read_mesh(dir / "box_obj.txt"), m);
  fs::copy_file(fixture("coloured.off"), dir / "c.model");
  EXPECT_EQ(read_mesh(dir / "c.model").faces.size(), 3u);
  fs::copy_file(fixture("organised_ascii.pcd"), dir / "cloud.dat");
  EXPECT_EQ(read_cloud(dir / "cloud.dat").size(), 4u);

  // Mesh files as clouds, PCD as a face-less mesh, PLY as an untextured mesh.
  EXPECT_EQ(read_cloud(dir / "box.obj").points, m.vertices);
  EXPECT_EQ(read_cloud(fixture("coloured.off")).colours.size(), 4u);
  const Mesh pm = read_mesh(fixture("organised_compressed.pcd"));
  EXPECT_EQ(pm.vertices.size(), 10u);
  EXPECT_TRUE(pm.faces.empty());
  const TexturedMesh tm = read_textured_mesh(dir / "box.ply");
  EXPECT_EQ(tm.mesh.faces.size(), 12u);
  EXPECT_TRUE(tm.corner_uv.empty());
  EXPECT_TRUE(tm.texture.empty());
}

TEST(IoFiles, WriteMeshChecksExtension) {
  test::TempDir dir;
  const Mesh m = test::box(Vec3f::Zero(), Vec3f::Ones());
  write_mesh(dir / "a.ply", m);
  EXPECT_EQ(slurp(dir / "a.ply").rfind("ply\nformat binary_little_endian", 0), 0u);
  write_mesh(dir / "a.obj", m);
  EXPECT_EQ(read_mesh(dir / "a.obj").faces.size(), 12u);
  const std::string msg = error_of<InvalidInput>([&] { write_mesh(dir / "a.stl", m); });
  EXPECT_NE(msg.find("a.stl"), std::string::npos);
  EXPECT_FALSE(fs::exists(dir / "a.stl"));
  EXPECT_THROW(write_mesh(dir / "missing" / "a.ply", m), IoError);
}

// Decoders fill a cut JPEG or PNG with grey and report nothing: a texture or a camera
// image cut short must be an error naming the file, not wrong colours.
TEST(Texture, TruncatedImagesAreRefusedNamingTheFile) {
  test::TempDir dir;
  for (const char* rel : {"data/mustard_bottle/texture_map.jpg", "tests/data/kinect_frames/frame0_depth.png"}) {
    const std::string whole = read_file_bytes(test::source_dir() / rel);
    const fs::path cut = dir / (std::string("cut") + fs::path(rel).extension().string());
    { std::ofstream(cut, std::ios::binary) << whole.substr(0, whole.size() / 2); }
    EXPECT_EQ(read_image_file(test::source_dir() / rel).size(), whole.size());
    try {
      load_texture(cut);
      ADD_FAILURE() << rel << ": a cut image loaded";
    } catch (const FormatError& e) {
      EXPECT_NE(std::string(e.what()).find(cut.string() + ": truncated"), std::string::npos) << e.what();
    }
  }
  const Texture t = load_texture(test::source_dir() / "data/mustard_bottle/texture_map.jpg");
  EXPECT_FALSE(t.empty());
  EXPECT_THROW(load_texture(dir / "missing.jpg"), IoError);
  { std::ofstream(dir / "junk.png", std::ios::binary) << "not an image at all"; }
  EXPECT_THROW(load_texture(dir / "junk.png"), FormatError);
  // 67 bytes whose header claims 100,000 x 100,000 pixels: OpenCV refuses it with an
  // exception, which came out as "internal error" naming no file.
  const unsigned char bomb[] = {
      0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44, 0x52, 0x00,
      0x01, 0x86, 0xa0, 0x00, 0x01, 0x86, 0xa0, 0x08, 0x00, 0x00, 0x00, 0x00, 0x8d, 0x39, 0x54, 0x14, 0x00,
      0x00, 0x00, 0x0a, 0x49, 0x44, 0x41, 0x54, 0x78, 0x9c, 0x63, 0x68, 0x00, 0x00, 0x00, 0x82, 0x00, 0x81,
      0x77, 0xcd, 0x72, 0xb6, 0x00, 0x00, 0x00, 0x00, 0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82};
  { std::ofstream(dir / "bomb.png", std::ios::binary).write(reinterpret_cast<const char*>(bomb), sizeof bomb); }
  const std::string msg = error_of<FormatError>([&] { load_texture(dir / "bomb.png"); });
  EXPECT_EQ(msg.rfind((dir / "bomb.png").string() + ": not a readable image (the decoder refused it: ", 0), 0u) << msg;
  // A byte flipped inside the image data: one error naming the file and the chunk
  // (libpng also printed "libpng error: IDAT: invalid literal/lengths set").
  std::string flipped = read_file_bytes(test::source_dir() / "tests/data/kinect_frames/frame0_rgb.png");
  const std::size_t idat = flipped.find("IDAT");
  ASSERT_NE(idat, std::string::npos);
  ASSERT_GT((std::uint32_t(std::uint8_t(flipped[idat - 2])) << 8) | std::uint8_t(flipped[idat - 1]), 64u)
      << "the first IDAT chunk is too short for the flipped byte";
  flipped[idat + 40] = char(flipped[idat + 40] ^ 0xFF);
  { std::ofstream(dir / "flipped.png", std::ios::binary) << flipped; }
  EXPECT_EQ(error_of<FormatError>([&] { load_texture(dir / "flipped.png"); }),
            (dir / "flipped.png").string() + ": corrupt PNG (its IDAT chunk at byte " + std::to_string(idat - 4) +
                " fails its CRC check)");
  // Padding after IEND is fine.
  { std::ofstream(dir / "padded.png", std::ios::binary) << read_file_bytes(test::source_dir() / "tests/data/kinect_frames/frame0_rgb.png") << std::string(100, '\0'); }
  EXPECT_FALSE(load_texture(dir / "padded.png").empty());
}

}  // namespace
}  // namespace station
