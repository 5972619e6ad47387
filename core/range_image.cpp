#include "core/range_image.h"

#include "core/io.h"
#include "core/normals.h"

#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>

namespace station {

std::optional<Vec3f> range_image_sensor(const std::filesystem::path& path) {
  std::string ext = path.extension().string();
  for (char& c : ext) c = char(std::tolower(static_cast<unsigned char>(c)));
  if (ext != ".pcd") return std::nullopt;
  std::ifstream in(path, std::ios::binary);
  if (!in) return std::nullopt;
  long long height = 1;
  Vec3f sensor = Vec3f::Zero();
  std::string line;
  // The header is text up to its DATA line (a few hundred bytes); 64 lines at most.
  for (int k = 0; k < 64 && std::getline(in, line); ++k) {
    std::istringstream words(line);
    std::string key;
    words >> key;
    if (key == "HEIGHT") {
      if (!(words >> height)) return std::nullopt;
    } else if (key == "VIEWPOINT") {
      float x = 0, y = 0, z = 0;
      if (!(words >> x >> y >> z) || !std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z)) return std::nullopt;
      sensor = Vec3f(x, y, z);
    } else if (key == "DATA") {
      break;
    }
  }
  if (height <= 1) return std::nullopt;
  return sensor;
}

Cloud read_cloud_oriented(const std::filesystem::path& path, int threads, std::string& note) {
  note.clear();
  Cloud cloud = read_cloud(path);
  if (cloud.size() < 3 || (cloud.has_normals() && any_usable_normal(cloud.normals))) return cloud;
  const std::optional<Vec3f> sensor = range_image_sensor(path);
  if (!sensor) return cloud;
  cloud.normals = estimate_normals(cloud.points, 12, threads);
  orient_normals_towards(cloud.points, cloud.normals, *sensor);
  char buf[160];
  std::snprintf(buf, sizeof buf, "no normals; estimated (PCA) facing the sensor at (%.4g, %.4g, %.4g): one range image",
                double(sensor->x()), double(sensor->y()), double(sensor->z()));
  note = path.string() + ": " + buf;
  return cloud;
}

}  // namespace station
