#pragma once
// Reading and writing clouds and meshes.
//
// Readers: PLY (ascii, binary_little_endian, binary_big_endian; any scalar
// property type and order; unknown properties and elements skipped), PCD
// (ascii, binary, binary_compressed), OBJ (with UVs and an MTL texture name),
// OFF. Writers: binary PLY, ASCII PLY, OBJ. Every writer goes through a
// temporary file that is renamed into place, so a failure never leaves a
// half-written output.
//
// Every reader is total: malformed, truncated or hostile input raises
// FormatError("NAME: problem"), never crashes (each has a libFuzzer target in
// fuzz/). Non-finite coordinates are rejected with FormatError.
#include <filesystem>
#include <functional>
#include <string>
#include <string_view>

#include "core/geometry.h"

namespace station {

namespace fs = std::filesystem;

/// A mesh with per-corner texture coordinates, as read from OBJ.
struct TexturedMesh {
  Mesh mesh;
  /// 3*F entries (corner order of mesh.faces), or empty when the file has none.
  std::vector<Vec2f> corner_uv;
  /// Absolute path of the diffuse texture (MTL map_Kd), empty when none.
  fs::path texture;
  /// Set when the file names material libraries (mtllib) of which none could be read
  /// (missing, unreadable, too large): the mesh is read without their texture. A library
  /// that is read but names no texture (colours only) is no problem.
  std::string material_problem;
};

// ---- parsers over in-memory bytes (used by the file readers and fuzzers) ----
// `name` only labels error messages.

/// PLY: vertices (x y z, optional nx ny nz, red green blue as uchar or float in [0,1];
/// a non-finite coordinate or normal is an error naming the vertex),
/// faces (vertex_indices / vertex_index lists; polygons are fan-triangulated).
Mesh parse_ply(std::string_view bytes, const std::string& name);
/// PCD v0.5-0.7; fields x y z, optional normal_x/y/z and rgb/rgba (packed uint32).
/// Points with a NaN coordinate (organised clouds' missing pixels) are dropped;
/// infinite coordinates are an error. A file with any non-finite normal (PCL's mark
/// for "not estimated") loses its normals whole: the stages estimate their own.
Cloud parse_pcd(std::string_view bytes, const std::string& name);
/// OBJ: v (optionally with r g b after x y z), vt, vn, f (polygons, negative indices).
/// `base_dir` resolves mtllib; the texture is only named, never loaded here.
TexturedMesh parse_obj(std::string_view bytes, const std::string& name,
                       const fs::path& base_dir = {});
/// OFF (ascii; COFF colours honoured).
Mesh parse_off(std::string_view bytes, const std::string& name);

// ---- files -------------------------------------------------------------------

/// Whether two paths name the same file: std::filesystem::equivalent when both
/// exist, else the same weakly canonical path (an output not written yet).
bool same_file(const fs::path& a, const fs::path& b);

/// Reads the whole file; IoError naming it when that fails.
std::string read_file_bytes(const fs::path& path);

/// Reads a point cloud (.ply, .pcd, .obj, .off: mesh vertices are taken as points).
Cloud read_cloud(const fs::path& path);
/// Streams a PLY file's vertices as points (with normals and colours when it has
/// them), `chunk` at a time, in file order: `fn` gets each chunk; the file is mapped,
/// not loaded, so memory stays at one chunk whatever the file's size. The same
/// errors as read_cloud (FormatError naming the file and the vertex; IoError).
void stream_ply_points(const fs::path& path, std::size_t chunk, const std::function<void(const Cloud&)>& fn);
/// Reads a mesh (.ply, .obj, .off). A file without faces gives a mesh with no faces.
Mesh read_mesh(const fs::path& path);
/// Reads OBJ with its texture reference; other formats give no UVs.
TexturedMesh read_textured_mesh(const fs::path& path);

enum class PlyFormat { kBinaryLittleEndian, kAscii };

/// The pieces of write_ply's format, for a mesh written in one streamed pass (the
/// counts known first): the header (`with_faces`: a face element of `faces`), then
/// each vertex, then each face, binary little-endian.
std::string ply_header(std::size_t vertices, bool normals, bool colours, std::size_t faces, bool with_faces,
                       PlyFormat format = PlyFormat::kBinaryLittleEndian);
void put_ply_vertex(std::string& out, const Vec3f& p, const Vec3f* normal, const Rgb* colour);
void put_ply_face(std::string& out, const Face& f);

/// Writes vertices (+normals, +colours as uchar) and faces. Atomic.
void write_ply(const fs::path& path, const Mesh& mesh,
               PlyFormat format = PlyFormat::kBinaryLittleEndian);
void write_ply(const fs::path& path, const Cloud& cloud,
               PlyFormat format = PlyFormat::kBinaryLittleEndian);
/// Writes v (with r g b in [0,1] when coloured), vn, f. Atomic.
void write_obj(const fs::path& path, const Mesh& mesh);
/// The same with texture coordinates: `corner_uv` has 3 entries per face (corner
/// order of mesh.faces, as TexturedMesh::corner_uv), written as vt and f v/vt[/vn].
/// InvalidInput when the count is wrong or a coordinate is not finite.
void write_obj(const fs::path& path, const Mesh& mesh, const std::vector<Vec2f>& corner_uv);
/// Writes by extension: .ply (binary) or .obj.
void write_mesh(const fs::path& path, const Mesh& mesh);

}  // namespace station
